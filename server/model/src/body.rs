//! The soft-body seam: [`SoftBody`], the one interface through which the servo, the sessions
//! and the services drive a deformable model, whatever its family (DESIGN.md section 5: the FEM,
//! the seeds' hybrid FEM + particle model, the mass-spring surface with run-time subdivision).
//!
//! A body is ticked once per servo period with the device input and returns the device force
//! with its local contact stiffness ([`SoftBody::tick`]); it writes its surface for viewers
//! ([`SoftBody::write_surface_positions`]) and describes the surface's connectivity with a
//! version number that changes whenever the connectivity does ([`SoftBody::surface_topology`]),
//! so that viewers get a new keyframe then; it reports its size and cost drivers
//! ([`SoftBody::stats`]). Everything a servo tick calls is allocation-free and lock-free.
//!
//! [`crate::build_body`] picks the family a scene asks for: [`crate::fem::FemBody`] (FEM),
//! [`crate::mass_spring::MassSpringBody`], [`crate::hybrid::HybridBody`].
//!
//! Owns: the interface and its plain data types. May use: [`crate::contact`] and
//! [`crate::loads`] (input limits). Implemented by the model families; used by the server
//! (never the other way round: the model knows nothing of sockets or logging, and of threads
//! only its own: the tick pool and the region follower).

use std::sync::Arc;

use glam::DVec3;

use crate::ModelError;
use crate::pool::TickPool;

pub use crate::contact::probe::MAX_DEVICE_DISTANCE_M;
pub use crate::loads::{MAX_POINT_FORCE_N, MAX_POINT_LOAD_DURATION_S, validate_point_load};

/// What the device reports for one servo tick.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TickInput {
    /// Haptic interaction point, m, scene frame; `None` when no device is connected.
    pub device_position_m: Option<DVec3>,
    /// Device velocity, m/s.
    pub device_velocity_m_per_s: DVec3,
}

impl TickInput {
    /// Rejects a non-finite or absurd device input; every body's tick calls it first, so the
    /// state is not touched. Allocation-free.
    ///
    /// # Errors
    /// [`ModelError::InvalidDevice`] when a connected device's position or velocity is not
    /// finite, or its position lies farther than [`MAX_DEVICE_DISTANCE_M`] (10 m) from the
    /// origin along an axis.
    pub fn validate(&self) -> Result<(), ModelError> {
        if let Some(p) = self.device_position_m {
            if !p.is_finite() || !self.device_velocity_m_per_s.is_finite() {
                return Err(ModelError::InvalidDevice(
                    "device position or velocity is not finite",
                ));
            }
            if p.abs().max_element() > MAX_DEVICE_DISTANCE_M {
                return Err(ModelError::InvalidDevice(
                    "device position is farther than 10 m from the origin",
                ));
            }
        }
        Ok(())
    }
}

/// What one servo tick returns to the device.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TickOutput {
    /// Force the device must render, N (the virtual coupling force at the end of the tick).
    pub force_on_device_n: DVec3,
    /// Whether the probe touches the surface.
    pub in_contact: bool,
    /// Proxy (god-object) position, m; the device point out of contact.
    pub proxy_position_m: DVec3,
    /// Local contact stiffness `d F_device / d x_device`, 3x3 row-major, N/m (zero out of
    /// contact), for force extrapolation between ticks on the device side.
    pub contact_stiffness_n_per_m: [f64; 9],
    /// Simulated time after the tick, s.
    pub sim_time_s: f64,
}

/// The connectivity of the surface shown to viewers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceTopology<'a> {
    /// Changes whenever `triangles` or the vertex count change (never otherwise).
    pub version: u64,
    /// Number of surface vertices: [`SoftBody::write_surface_positions`] writes `3 *` this many
    /// values.
    pub vertex_count: usize,
    /// Triangles as indices into the surface vertices, outward oriented
    /// (counter-clockwise seen from outside).
    pub triangles: &'a [[u32; 3]],
}

/// Upper bounds on the surface over the body's lifetime, so that callers can size buffers once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SurfaceCapacity {
    /// Largest vertex count.
    pub vertices: usize,
    /// Largest triangle count.
    pub triangles: usize,
}

/// Fixed facts about a body, for session set-up and reports.
#[derive(Debug, Clone, PartialEq)]
pub struct BodyInfo {
    /// Model family, e.g. `"fem"`.
    pub family: &'static str,
    /// Scene name.
    pub scene: String,
    /// Servo period the body is ticked at, s.
    pub tick_s: f64,
    /// Model sub-steps per tick.
    pub substeps: u32,
    /// Stability limit of the time step, s (`f64::INFINITY` when there is none).
    pub critical_dt_s: f64,
    /// Probe sphere radius, m.
    pub probe_radius_m: f64,
    /// Where [`SoftBody::add_point_load`] may act.
    pub point_loads: PointLoadZone,
}

/// Where a body takes point loads ([`SoftBody::add_point_load`]); fixed over its life, so a
/// server can refuse a load with a clear error before queueing it for the servo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PointLoadZone {
    /// Anywhere on the surface.
    Anywhere,
    /// Within `radius_m` (m) of `centre_m` (m): a fixed contact-local active region, whose
    /// condensed elements take no load (a load elsewhere would otherwise be moved to the
    /// nearest simulated surface).
    Ball {
        /// Centre, m.
        centre_m: DVec3,
        /// Radius, m.
        radius_m: f64,
    },
    /// Nowhere, for the reason given.
    Refused(&'static str),
}

impl PointLoadZone {
    /// Whether a point load at `point_m` (m) may act.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] naming the zone when it may not.
    pub fn check(&self, point_m: DVec3) -> Result<(), ModelError> {
        match *self {
            Self::Anywhere => Ok(()),
            Self::Ball { centre_m, radius_m } if point_m.distance(centre_m) <= radius_m => Ok(()),
            Self::Ball { centre_m, radius_m } => Err(ModelError::InvalidInput(format!(
                "point_m {point_m} is {:.1} mm from the active region's centre {centre_m}, outside its {:.1} mm radius: condensed elements take no load (move the load, or enlarge or move active_region)",
                point_m.distance(centre_m) * 1e3,
                radius_m * 1e3
            ))),
            Self::Refused(why) => Err(ModelError::InvalidInput(why.to_string())),
        }
    }
}

/// Size and state of a body, cheap to read (allocation-free, O(nodes) at most).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BodyStats {
    /// Simulation nodes.
    pub nodes: usize,
    /// Elements of the model (tetrahedra for the FEM).
    pub elements: usize,
    /// Elements simulated with full dynamics (all of them, or those of a contact-local active
    /// region).
    pub active_elements: usize,
    /// Meshfree particles (0 for families without them).
    pub particles: usize,
    /// Particles currently simulated.
    pub active_particles: usize,
    /// Point loads still acting ([`SoftBody::add_point_load`]).
    pub active_point_loads: usize,
    /// Surface vertices shown to viewers now.
    pub surface_vertices: usize,
    /// Current surface topology version ([`SurfaceTopology::version`]).
    pub topology_version: u64,
    /// Simulated time, s.
    pub sim_time_s: f64,
    /// Largest nodal displacement from rest, m.
    pub max_displacement_m: f64,
    /// Regions swapped in so far by a following active region (0 otherwise).
    pub region_swaps: u64,
    /// Preparation time of the last region a following active region prepared, s (0 if none).
    pub region_preparation_s: f64,
    /// Regions of a following region's cache (`active_region.tiles = "background"`): how many
    /// centres it covers the touchable surface with (0 without a cache), and how many of them
    /// are prepared (built, or failed and not tried again). A stroke faster than a region's
    /// preparation meets its own regions only once the two are equal.
    pub region_tiles: u64,
    /// See [`BodyStats::region_tiles`].
    pub region_tiles_ready: u64,
    /// Of `region_tiles_ready`, the regions read from the host's region cache on disk
    /// ([`crate::BodyOptions::region_cache`]) instead of prepared.
    pub region_tiles_loaded: u64,
    /// Files of the region cache on disk refused (damaged, truncated, of another format, key or
    /// centre: prepared again and replaced), so far; the host's
    /// [`crate::BodyOptions::region_cache_report`] receives each reason.
    pub region_tiles_refused: u64,
    /// Bytes the region cache's regions hold in memory now
    /// ([`crate::integrate::follow::FollowStats::tile_cache_bytes`]).
    pub region_tile_memory_bytes: u64,
    /// Regions dropped from memory to stay under the host's memory limit for them (their
    /// files stay), and regions read back from those files, so far.
    pub region_tiles_dropped: u64,
    /// See [`BodyStats::region_tiles_dropped`].
    pub region_tiles_reloaded: u64,
    /// Requests whose region was not in memory (read or prepared meanwhile), so far.
    pub region_tile_misses: u64,
    /// Swaps to a region beyond the far nodes the previous one mapped (those start at rest).
    pub region_unmapped_swaps: u64,
    /// Ticks in contact in which a following region's coarse companion contributed to the
    /// force (its blend weight was positive), so far; 0 without a companion. Against the
    /// servo's count of contact ticks it says how much of a press the coarse organ answered.
    pub companion_ticks: u64,
}

/// A deformable body the servo can drive (module documentation). Implementations must keep
/// [`SoftBody::tick`], [`SoftBody::add_point_load`], [`SoftBody::write_surface_positions`],
/// [`SoftBody::surface_topology`] and [`SoftBody::stats`] free of allocation, locks and I/O.
pub trait SoftBody: Send {
    /// Advances one servo tick with the device input and returns the force for the device.
    ///
    /// # Errors
    /// [`ModelError::InvalidDevice`] for a non-finite or absurd device input (the state is not
    /// touched); [`ModelError::Diverged`] when the state became non-finite or diverged (the
    /// caller must quarantine the body: its state is no longer meaningful).
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError>;

    /// Applies `force_n` (N) at the surface point closest to `point_m` (m) for `duration_s` of
    /// simulated time, spread as a probe touching there would spread it.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] for values [`validate_point_load`] rejects or a point
    /// outside [`BodyInfo::point_loads`] (nothing changed); [`ModelError::LoadTableFull`] when
    /// the preallocated load table is full.
    fn add_point_load(
        &mut self,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
    ) -> Result<(), ModelError>;

    /// The surface's current connectivity and its version.
    fn surface_topology(&self) -> SurfaceTopology<'_>;

    /// Upper bounds on the surface's vertex and triangle counts over the body's lifetime.
    fn surface_capacity(&self) -> SurfaceCapacity;

    /// Writes the current surface vertex positions (xyz interleaved, f32, m) into `out` and
    /// returns the largest displacement from rest among them, m.
    ///
    /// # Panics
    /// If `out.len()` is not `3 * surface_topology().vertex_count`.
    fn write_surface_positions(&self, out: &mut [f32]) -> f64;

    /// Writes the rest positions of the current surface vertices (as
    /// [`SoftBody::write_surface_positions`]), for viewers that colour by displacement.
    ///
    /// # Panics
    /// As [`SoftBody::write_surface_positions`].
    fn write_surface_rest_positions(&self, out: &mut [f32]);

    /// Size and state.
    fn stats(&self) -> BodyStats;

    /// Fixed facts (family, timing, probe).
    fn info(&self) -> BodyInfo;

    /// Threads this body's tick can use to advantage (issue 48): the session gives it at most
    /// this many, counting the servo thread. Provided: 1 (the one-core tick).
    fn wants_threads(&self) -> usize {
        1
    }

    /// Threads the body keeps busy beside its tick now (issue 48): a region worker building a
    /// region cache. While they are busy a session with an automatic thread count lends them the
    /// tick-pool workers that the cores no other session holds cannot hold beside them (the
    /// pool's `set_active_workers`); it asks again every statistics window, between ticks, so
    /// this must not allocate, lock or block. Provided: 0.
    fn background_threads(&self) -> usize {
        0
    }

    /// Hands the body the worker pool of its session, before the first tick (the session's
    /// set-up, not a tick: may allocate). A body cuts its jobs into `pool.threads()` parts, so
    /// its results depend on the thread count only. Provided: the pool is not used.
    fn set_tick_pool(&mut self, pool: Arc<TickPool>) {
        let _ = pool;
    }

    /// Tools (device streams) this body takes at once (issue 50): the session accepts at most
    /// this many, each in its own slot `0..max_tools()`. At most [`MAX_TOOLS`]. Provided: 1.
    fn max_tools(&self) -> usize {
        1
    }

    /// The slot a tool named `tool_id` must take, when the scene names its tools (with their
    /// own probe parameters); `None`: any free slot the scene does not reserve for a named
    /// tool. Provided: `None`.
    fn tool_slot(&self, tool_id: &str) -> Option<usize> {
        let _ = tool_id;
        None
    }

    /// Advances one servo tick with every tool slot's input: `inputs[k]` is slot `k`'s device
    /// (`device_position_m: None` for a slot without a stream: its contact is released) and
    /// `outputs[k]` receives its force. All tools' contacts act on the body in the same tick.
    /// Allocation-free, as [`SoftBody::tick`].
    ///
    /// Provided for one-tool bodies: one slot is [`SoftBody::tick`].
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] when `inputs` and `outputs` differ in length, are empty or
    /// longer than [`SoftBody::max_tools`] (nothing changed); otherwise as [`SoftBody::tick`]
    /// (any tool's invalid input refuses the whole tick).
    fn tick_tools(
        &mut self,
        inputs: &[TickInput],
        outputs: &mut [TickOutput],
    ) -> Result<(), ModelError> {
        check_tool_slots(inputs.len(), outputs.len(), self.max_tools())?;
        outputs[0] = self.tick(&inputs[0])?;
        Ok(())
    }
}

/// Most tools any body takes at once (issue 50); a scene's `probe.max_tools` is at most this.
pub const MAX_TOOLS: usize = 4;

/// The slot counts [`SoftBody::tick_tools`] accepts: `inputs` and `outputs` of one length in
/// `1..=max_tools`.
///
/// # Errors
/// [`ModelError::InvalidInput`] otherwise.
pub fn check_tool_slots(inputs: usize, outputs: usize, max_tools: usize) -> Result<(), ModelError> {
    if inputs != outputs {
        return Err(ModelError::InvalidInput(
            "tick_tools: inputs and outputs differ in length".into(),
        ));
    }
    if inputs == 0 || inputs > max_tools.min(MAX_TOOLS) {
        return Err(ModelError::InvalidInput(
            "tick_tools: the slot count is zero or above the body's max_tools".into(),
        ));
    }
    Ok(())
}

/// [`check_tool_slots`] and then every input's [`TickInput::validate`]: what each family's
/// [`SoftBody::tick_tools`] checks before it changes anything.
///
/// # Errors
/// [`ModelError::InvalidInput`] for the slot counts or the first invalid input.
pub fn check_tool_inputs(
    inputs: &[TickInput],
    outputs: usize,
    max_tools: usize,
) -> Result<(), ModelError> {
    check_tool_slots(inputs.len(), outputs, max_tools)?;
    inputs.iter().try_for_each(TickInput::validate)
}

#[cfg(test)]
mod tool_slot_tests {
    use super::{MAX_TOOLS, check_tool_slots};

    #[test]
    fn slot_counts_outside_one_to_max_tools_or_of_unequal_lengths_are_refused() {
        assert!(check_tool_slots(1, 1, 1).is_ok());
        assert!(check_tool_slots(2, 2, 2).is_ok());
        assert!(check_tool_slots(0, 0, 2).is_err());
        assert!(check_tool_slots(2, 1, 2).is_err());
        assert!(check_tool_slots(3, 3, 2).is_err());
        // A body claiming more than MAX_TOOLS is held to MAX_TOOLS.
        assert!(check_tool_slots(MAX_TOOLS + 1, MAX_TOOLS + 1, MAX_TOOLS + 1).is_err());
        assert!(check_tool_slots(MAX_TOOLS, MAX_TOOLS, MAX_TOOLS + 1).is_ok());
    }
}
