//! From device coordinates to scene coordinates: a rotation, a motion scale and an offset
//! ([`DeviceTransform`]), applied by the [`Transformed`] wrapper around any driver, so every
//! driver hands the bridge poses in the scene frame (right-handed, SI) and receives forces in
//! it (devices.md section 3.1).
//!
//! `p_scene = offset_m + scale * R p_device`, `v_scene = scale * R v_device`,
//! `f_device = force_scale * R^T f_scene`. With `force_scale = scale` the mapping conserves
//! power (`f_scene . v_scene = f_device . v_device`), which keeps the passivity observer's
//! bookkeeping valid across it; the default `force_scale = 1` renders scene forces unscaled.
//!
//! Examples (`docs/decisions.md`, "Drivers (issue 15)", gives each with a full command line and
//! a worked point):
//! - HapticMaster (z vertical, x fore-aft, y lateral; SI): `--axes y,z,x` is HAPI's mapping
//!   `(pos[1], pos[2], pos[0])` (devices.md \[S4\]); add `--offset-m 0,0,-0.45` to bring the
//!   middle of its cylindrical workspace (radius 0.28-0.64 m) near the scene origin.
//! - Phantom/Touch through OpenHaptics (x right, y up, z toward the user; the driver converts
//!   mm to m): identity axes; `--scale 0.2` maps its 0.16 m workspace onto a 32 mm organ.
//! - A serial (HBP) arm reports in its own frame; e.g. `--axes x,-z,y` for one mounted with z
//!   down.
//!
//! Neighbours: [`crate::device`] (the trait wrapped), [`crate::cli`] (`--axes`, `--rotation`,
//! `--scale`, `--offset-m`, `--force-scale`).

use crate::device::{DeviceError, DeviceSpec, DeviceState, HapticDevice, PressAxis, vec3};

/// A device-to-scene transform (module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeviceTransform {
    /// Rotation, row-major: row `i` says which device axes make scene axis `i`. Orthonormal
    /// with determinant +1 (checked by [`DeviceTransform::validate`]).
    pub rotation: [[f64; 3]; 3],
    /// Motion scale (scene metres per device metre), > 0.
    pub scale: f64,
    /// Scene position of the device origin, m.
    pub offset_m: [f64; 3],
    /// Factor from scene force to device force, > 0 (1 by default).
    pub force_scale: f64,
}

impl Default for DeviceTransform {
    fn default() -> Self {
        Self::IDENTITY
    }
}

fn mat_vec(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [vec3::dot(m[0], v), vec3::dot(m[1], v), vec3::dot(m[2], v)]
}

fn mat_t_vec(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    let mut out = [0.0; 3];
    for (i, row) in m.iter().enumerate() {
        for j in 0..3 {
            out[j] += row[j] * v[i];
        }
    }
    out
}

impl DeviceTransform {
    /// No rotation, scale 1, no offset.
    pub const IDENTITY: Self = Self {
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        scale: 1.0,
        offset_m: [0.0; 3],
        force_scale: 1.0,
    };

    /// A signed axis permutation from text `A,B,C`: scene x, y, z are the device axes named
    /// (`x`, `y`, `z`, each optionally prefixed by `-`), e.g. `y,z,x` or `x,-z,y`.
    ///
    /// # Errors
    /// [`DeviceError::InvalidSpec`] for another form, a repeated axis or a left-handed result.
    pub fn parse_axes(text: &str) -> Result<[[f64; 3]; 3], DeviceError> {
        let bad = |m: String| DeviceError::InvalidSpec(format!("--axes {text:?}: {m}"));
        let parts: Vec<&str> = text.split(',').map(str::trim).collect();
        if parts.len() != 3 {
            return Err(bad("expected three axes such as y,z,x".into()));
        }
        let mut r = [[0.0; 3]; 3];
        for (i, p) in parts.iter().enumerate() {
            let (sign, name) = match p.strip_prefix('-') {
                Some(n) => (-1.0, n),
                None => (1.0, p.strip_prefix('+').unwrap_or(p)),
            };
            let j = match name {
                "x" | "X" => 0,
                "y" | "Y" => 1,
                "z" | "Z" => 2,
                other => return Err(bad(format!("unknown axis {other:?}"))),
            };
            r[i][j] = sign;
        }
        let t = DeviceTransform {
            rotation: r,
            ..Self::IDENTITY
        };
        t.validate()
            .map_err(|_| bad("axes repeat or the frame is left-handed".into()))?;
        Ok(r)
    }

    /// Checks that the rotation is orthonormal with determinant +1 (to 1e-6) and the scales
    /// and offset are finite, scales positive.
    ///
    /// # Errors
    /// [`DeviceError::InvalidSpec`] saying what is wrong.
    pub fn validate(&self) -> Result<(), DeviceError> {
        let r = &self.rotation;
        for i in 0..3 {
            for j in 0..3 {
                let d = vec3::dot(r[i], r[j]);
                let want = if i == j { 1.0 } else { 0.0 };
                if (d - want).abs() >= 1e-6 || !d.is_finite() {
                    return Err(DeviceError::InvalidSpec(format!(
                        "rotation is not orthonormal (rows {i}, {j}: {d})"
                    )));
                }
            }
        }
        let c = [
            r[0][1] * r[1][2] - r[0][2] * r[1][1],
            r[0][2] * r[1][0] - r[0][0] * r[1][2],
            r[0][0] * r[1][1] - r[0][1] * r[1][0],
        ];
        if vec3::dot(c, r[2]) < 0.0 {
            return Err(DeviceError::InvalidSpec(
                "rotation is a reflection (determinant -1): the scene frame must stay right-handed"
                    .into(),
            ));
        }
        let pos = |v: f64| v.is_finite() && v > 0.0;
        if !pos(self.scale) || !pos(self.force_scale) || !vec3::is_finite(self.offset_m) {
            return Err(DeviceError::InvalidSpec(format!(
                "scale ({}) and force scale ({}) must be > 0, offset finite ({:?})",
                self.scale, self.force_scale, self.offset_m
            )));
        }
        Ok(())
    }

    /// A device position (m) in the scene frame.
    pub fn position_to_scene(&self, p_device_m: [f64; 3]) -> [f64; 3] {
        vec3::axpy(
            self.offset_m,
            self.scale,
            mat_vec(&self.rotation, p_device_m),
        )
    }

    /// A device velocity (m/s) in the scene frame.
    pub fn velocity_to_scene(&self, v_device: [f64; 3]) -> [f64; 3] {
        vec3::scale(mat_vec(&self.rotation, v_device), self.scale)
    }

    /// A scene force (N) as the device must render it.
    pub fn force_to_device(&self, f_scene_n: [f64; 3]) -> [f64; 3] {
        vec3::scale(mat_t_vec(&self.rotation, f_scene_n), self.force_scale)
    }

    /// The device spec seen from the scene: the workspace box is the bounding box of the
    /// transformed corners; forces scale by `1 / force_scale`, stiffness by
    /// `1 / (force_scale * scale)`, damping likewise.
    pub fn spec_to_scene(&self, spec: &DeviceSpec) -> DeviceSpec {
        let (lo, hi) = (spec.workspace_min_m, spec.workspace_max_m);
        let mut min = [f64::INFINITY; 3];
        let mut max = [f64::NEG_INFINITY; 3];
        for k in 0..8 {
            let c = [
                if k & 1 == 0 { lo[0] } else { hi[0] },
                if k & 2 == 0 { lo[1] } else { hi[1] },
                if k & 4 == 0 { lo[2] } else { hi[2] },
            ];
            let p = self.position_to_scene(c);
            for i in 0..3 {
                min[i] = min[i].min(p[i]);
                max[i] = max[i].max(p[i]);
            }
        }
        DeviceSpec {
            name: spec.name.clone(),
            sensed_degrees_of_freedom: spec.sensed_degrees_of_freedom,
            actuated_degrees_of_freedom: spec.actuated_degrees_of_freedom,
            max_force_n: spec.max_force_n / self.force_scale,
            max_continuous_force_n: spec.max_continuous_force_n / self.force_scale,
            max_stiffness_n_per_m: spec.max_stiffness_n_per_m / (self.force_scale * self.scale),
            workspace_min_m: min,
            workspace_max_m: max,
            rate_hz: spec.rate_hz,
            max_damping_n_s_per_m: spec.max_damping_n_s_per_m / (self.force_scale * self.scale),
        }
    }
}

/// A driver seen through a [`DeviceTransform`]: poses come out in the scene frame, forces go
/// in from it.
pub struct Transformed<D> {
    inner: D,
    transform: DeviceTransform,
    spec: DeviceSpec,
}

impl<D: HapticDevice> Transformed<D> {
    /// Wraps `inner`.
    ///
    /// # Errors
    /// [`DeviceError::InvalidSpec`] when the transform is invalid.
    pub fn new(inner: D, transform: DeviceTransform) -> Result<Self, DeviceError> {
        transform.validate()?;
        let spec = transform.spec_to_scene(inner.spec());
        Ok(Self {
            inner,
            transform,
            spec,
        })
    }

    /// The wrapped driver.
    pub fn inner(&self) -> &D {
        &self.inner
    }
}

impl<D: HapticDevice> HapticDevice for Transformed<D> {
    fn spec(&self) -> &DeviceSpec {
        &self.spec
    }
    fn read(&mut self, now_us: u64) -> Result<DeviceState, DeviceError> {
        let s = self.inner.read(now_us)?;
        Ok(DeviceState {
            time_us: s.time_us,
            position_m: self.transform.position_to_scene(s.position_m),
            velocity_m_per_s: self.transform.velocity_to_scene(s.velocity_m_per_s),
            motor_temperature: s.motor_temperature,
        })
    }
    fn write_force(&mut self, force_n: [f64; 3]) -> Result<(), DeviceError> {
        self.inner
            .write_force(self.transform.force_to_device(force_n))
    }
    fn finished(&self, now_us: u64) -> bool {
        self.inner.finished(now_us)
    }
    fn safe_stop(&mut self) {
        self.inner.safe_stop();
    }
    fn set_output_enabled(&mut self, on: bool) -> Result<(), DeviceError> {
        self.inner.set_output_enabled(on)
    }
    fn press_axis(&self) -> Option<PressAxis> {
        let a = self.inner.press_axis()?;
        Some(PressAxis {
            start_m: self.transform.position_to_scene(a.start_m),
            direction: mat_vec(&self.transform.rotation, a.direction),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        vec3::norm(vec3::sub(a, b)) < 1e-12
    }

    #[test]
    fn hapticmaster_axes_follow_hapi() {
        // HAPI: pos_HAPI = (pos[1], pos[2], pos[0]).
        let t = DeviceTransform {
            rotation: DeviceTransform::parse_axes("y,z,x").unwrap(),
            ..DeviceTransform::IDENTITY
        };
        assert!(close(t.position_to_scene([1.0, 2.0, 3.0]), [2.0, 3.0, 1.0]));
        // A scene force along +y (up) is a device force along +z (vertical).
        assert!(close(t.force_to_device([0.0, 1.0, 0.0]), [0.0, 0.0, 1.0]));
    }

    #[test]
    fn power_is_conserved_when_the_force_scale_equals_the_motion_scale() {
        let t = DeviceTransform {
            rotation: DeviceTransform::parse_axes("x,-z,y").unwrap(),
            scale: 0.2,
            offset_m: [0.01, -0.02, 0.03],
            force_scale: 0.2,
        };
        let (v_dev, f_scene) = ([0.1, -0.3, 0.2], [0.5, 0.25, -1.0]);
        let p_scene = vec3::dot(f_scene, t.velocity_to_scene(v_dev));
        let p_dev = vec3::dot(t.force_to_device(f_scene), v_dev);
        assert!((p_scene - p_dev).abs() < 1e-12);
        assert!(close(t.position_to_scene([0.0; 3]), [0.01, -0.02, 0.03]));
    }

    #[test]
    fn bad_axes_and_reflections_are_refused() {
        for bad in ["x,y", "x,x,z", "x,y,-z", "x,y,w", "y,x,z"] {
            assert!(DeviceTransform::parse_axes(bad).is_err(), "{bad}");
        }
        let mut t = DeviceTransform::IDENTITY;
        t.scale = 0.0;
        assert!(t.validate().is_err());
    }

    #[test]
    fn the_workspace_box_follows_the_transform() {
        let t = DeviceTransform {
            rotation: DeviceTransform::parse_axes("y,z,x").unwrap(),
            scale: 0.5,
            offset_m: [1.0, 0.0, 0.0],
            force_scale: 1.0,
        };
        let mut spec = DeviceSpec::sim_default();
        spec.workspace_min_m = [-0.1, -0.2, -0.3];
        spec.workspace_max_m = [0.1, 0.2, 0.3];
        let s = t.spec_to_scene(&spec);
        assert!(close(s.workspace_min_m, [0.9, -0.15, -0.05]));
        assert!(close(s.workspace_max_m, [1.1, 0.15, 0.05]));
    }
}
