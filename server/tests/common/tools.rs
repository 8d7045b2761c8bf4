//! A test body with several tool slots (issue 50), until the model families take them: a rigid
//! wall at x = 0 that every tool presses on its own. Slot `k`'s force is
//! `(k + 1) * WALL_STIFFNESS_N_PER_M * depth` along +x while its device is at x = -depth < 0, so
//! a force routed to the wrong stream shows. Its surface is one triangle. `#[path]`-included by
//! the tests that need it.

#![allow(dead_code)] // each includer uses its part

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use haptic_model::body::{
    BodyInfo, BodyStats, PointLoadZone, SoftBody, SurfaceCapacity, SurfaceTopology, TickInput,
    TickOutput, check_tool_slots,
};
use haptic_model::{DVec3, ModelError};

/// Stiffness of slot 0 against the wall, N/m (slot k: k + 1 times this).
pub const WALL_STIFFNESS_N_PER_M: f64 = 100.0;

/// The wall body: `tools` slots, tools named `names[k]` reserved slot `k`.
pub struct Wall {
    /// Slots ([`SoftBody::max_tools`]).
    pub tools: usize,
    /// Named tools, by slot.
    pub names: Vec<String>,
    /// Ticks in which two or more tools touched the wall at once (shared with the test).
    pub ticks_with_several_contacts: Arc<AtomicU64>,
    sim_time_s: f64,
}

impl Wall {
    /// A wall for `tools` slots, the first `names.len()` reserved for those names.
    pub fn new(tools: usize, names: &[&str]) -> Self {
        Self {
            tools,
            names: names.iter().map(|n| (*n).to_owned()).collect(),
            ticks_with_several_contacts: Arc::new(AtomicU64::new(0)),
            sim_time_s: 0.0,
        }
    }
}

/// Slot `k`'s force against the wall for a device at `p`, N (zero out of contact).
pub fn wall_force(k: usize, p: Option<DVec3>) -> DVec3 {
    match p {
        Some(p) if p.x < 0.0 => DVec3::X * ((k + 1) as f64 * WALL_STIFFNESS_N_PER_M * -p.x),
        _ => DVec3::ZERO,
    }
}

const TRIANGLE: [[u32; 3]; 1] = [[0, 1, 2]];

impl SoftBody for Wall {
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        let mut out = [TickOutput::default()];
        self.tick_tools(std::slice::from_ref(input), &mut out)?;
        Ok(out[0])
    }

    fn tick_tools(
        &mut self,
        inputs: &[TickInput],
        outputs: &mut [TickOutput],
    ) -> Result<(), ModelError> {
        check_tool_slots(inputs.len(), outputs.len(), self.max_tools())?;
        for i in inputs {
            i.validate()?;
        }
        self.sim_time_s += 1e-3;
        let mut contacts = 0;
        for (k, (i, o)) in inputs.iter().zip(outputs.iter_mut()).enumerate() {
            let f = wall_force(k, i.device_position_m);
            let in_contact = f.x > 0.0;
            contacts += usize::from(in_contact);
            *o = TickOutput {
                force_on_device_n: f,
                in_contact,
                proxy_position_m: i.device_position_m.unwrap_or_default().with_x(0.0),
                contact_stiffness_n_per_m: [0.0; 9],
                sim_time_s: self.sim_time_s,
            };
        }
        if contacts >= 2 {
            self.ticks_with_several_contacts
                .fetch_add(1, Ordering::Relaxed);
        }
        Ok(())
    }

    fn max_tools(&self) -> usize {
        self.tools
    }

    fn tool_slot(&self, tool_id: &str) -> Option<usize> {
        self.names.iter().position(|n| n == tool_id)
    }

    fn add_point_load(&mut self, _p: DVec3, _f: DVec3, _d: f64) -> Result<(), ModelError> {
        Ok(())
    }

    fn surface_topology(&self) -> SurfaceTopology<'_> {
        SurfaceTopology {
            version: 0,
            vertex_count: 3,
            triangles: &TRIANGLE,
        }
    }

    fn surface_capacity(&self) -> SurfaceCapacity {
        SurfaceCapacity {
            vertices: 3,
            triangles: 1,
        }
    }

    fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        self.write_surface_rest_positions(out);
        0.0
    }

    fn write_surface_rest_positions(&self, out: &mut [f32]) {
        out.copy_from_slice(&[0.0, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0, 0.0, 0.01]);
    }

    fn stats(&self) -> BodyStats {
        BodyStats {
            nodes: 3,
            elements: 1,
            active_elements: 1,
            surface_vertices: 3,
            sim_time_s: self.sim_time_s,
            ..BodyStats::default()
        }
    }

    fn info(&self) -> BodyInfo {
        BodyInfo {
            family: "wall",
            scene: "wall".into(),
            tick_s: 1e-3,
            substeps: 1,
            critical_dt_s: f64::INFINITY,
            probe_radius_m: 0.002,
            point_loads: PointLoadZone::Anywhere,
        }
    }
}
