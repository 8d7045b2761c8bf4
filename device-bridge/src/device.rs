//! The device abstraction: a [`HapticDevice`] trait with a declared [`DeviceSpec`] (limits the
//! guard enforces) and the [`DeviceState`] it reports each tick.
//!
//! Neighbours: drivers live in [`crate::sim`] (scripted probe) and [`crate::replay`] (recorded
//! trajectory); [`crate::link`] owns one device on its device thread; [`crate::guard`] reads the
//! spec's force and stiffness limits (devices.md section 3.2 sketches this trait; section 4 S6/S7
//! gives the per-model numbers).
//!
//! Frame and units: every driver converts to one right-handed frame in SI units (metres, m/s,
//! newtons) at its boundary (devices.md section 3.1).

use thiserror::Error;

/// Static description of a device: its limits and nominal rate.
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceSpec {
    /// Model name, for logs and the capabilities the bridge sends (`DeviceCapabilities`).
    pub name: String,
    /// Pose inputs: 3 (position) or 6 (position and orientation).
    pub sensed_degrees_of_freedom: u32,
    /// Force outputs: 3 for a force-feedback arm.
    pub actuated_degrees_of_freedom: u32,
    /// Peak force the device may render, in N (devices.md S6; Touch 3.3 N, Premium 3.0 22 N).
    pub max_force_n: f64,
    /// Force the motors can hold, in N (devices.md S8, `HD_NOMINAL_MAX_CONTINUOUS_FORCE`; Touch
    /// 0.88 N). The guard's thermal limit lowers its clamp toward it when the motors run hot;
    /// equal to `max_force_n` when the device does not say (never limited).
    pub max_continuous_force_n: f64,
    /// Largest stable wall stiffness at the device rate, in N/m (devices.md table 1.2). The
    /// guard's default slew limit is this stiffness times 1 m/s (S7).
    pub max_stiffness_n_per_m: f64,
    /// Lower corner of the usable workspace box, in m.
    pub workspace_min_m: [f64; 3],
    /// Upper corner of the usable workspace box, in m.
    pub workspace_max_m: [f64; 3],
    /// Nominal servo rate, in Hz (1000 for Phantoms).
    pub rate_hz: f64,
    /// Largest damping the device renders stably, in N s/m (`HD_NOMINAL_MAX_DAMPING`); the cap
    /// of the passivity controller's added damping.
    pub max_damping_n_s_per_m: f64,
}

impl DeviceSpec {
    /// Spec of the simulated probe: 10 N peak, 3 N continuous, 1000 N/m (so a 1 N/ms slew
    /// limit), a +-0.2 m box, 1 kHz, 2 N s/m damping. The numbers sit between a Phantom Desktop
    /// and a Premium 3.0 (devices.md table 1.2; the continuous rating is an assumption).
    pub fn sim_default() -> Self {
        Self {
            name: "sim".to_owned(),
            sensed_degrees_of_freedom: 3,
            actuated_degrees_of_freedom: 3,
            max_force_n: 10.0,
            max_continuous_force_n: 3.0,
            max_stiffness_n_per_m: 1000.0,
            workspace_min_m: [-0.2; 3],
            workspace_max_m: [0.2; 3],
            rate_hz: 1000.0,
            max_damping_n_s_per_m: 2.0,
        }
    }

    /// Checks that limits are positive and finite and the workspace box is not inverted.
    ///
    /// # Errors
    /// [`DeviceError::InvalidSpec`] naming the offending field.
    pub fn validate(&self) -> Result<(), DeviceError> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.max_force_n) {
            return Err(DeviceError::InvalidSpec(format!(
                "max_force_n must be positive and finite, got {}",
                self.max_force_n
            )));
        }
        if !positive(self.max_continuous_force_n) {
            return Err(DeviceError::InvalidSpec(format!(
                "max_continuous_force_n must be positive and finite, got {}",
                self.max_continuous_force_n
            )));
        }
        if !positive(self.max_stiffness_n_per_m) {
            return Err(DeviceError::InvalidSpec(format!(
                "max_stiffness_n_per_m must be positive and finite, got {}",
                self.max_stiffness_n_per_m
            )));
        }
        if !(self.max_damping_n_s_per_m.is_finite() && self.max_damping_n_s_per_m >= 0.0) {
            return Err(DeviceError::InvalidSpec(format!(
                "max_damping_n_s_per_m must be finite and >= 0, got {}",
                self.max_damping_n_s_per_m
            )));
        }
        if !positive(self.rate_hz) {
            return Err(DeviceError::InvalidSpec(format!(
                "rate_hz must be positive and finite, got {}",
                self.rate_hz
            )));
        }
        for i in 0..3 {
            let (lo, hi) = (self.workspace_min_m[i], self.workspace_max_m[i]);
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return Err(DeviceError::InvalidSpec(format!(
                    "workspace axis {i}: need finite min < max, got {lo}..{hi}"
                )));
            }
        }
        Ok(())
    }

    /// True when `position_m` lies inside the workspace box grown by `margin` times its extent
    /// on every side (devices.md S11 uses a 10 % margin, `margin = 0.1`).
    pub fn contains(&self, position_m: [f64; 3], margin: f64) -> bool {
        (0..3).all(|i| {
            let (lo, hi) = (self.workspace_min_m[i], self.workspace_max_m[i]);
            let pad = (hi - lo) * margin;
            position_m[i] >= lo - pad && position_m[i] <= hi + pad
        })
    }
}

/// One reading of the device, in the bridge frame.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct DeviceState {
    /// Clock time of the reading, in microseconds (the [`crate::clock::Clock`] passed to `read`).
    pub time_us: u64,
    /// Haptic interaction point, in m.
    pub position_m: [f64; 3],
    /// Velocity of the interaction point, in m/s.
    pub velocity_m_per_s: [f64; 3],
    /// Normalised motor temperature of the hottest motor (0 cold .. 1 at the vendor's limit)
    /// when the driver reports one (OpenHaptics `HD_MOTOR_TEMPERATURE`); `None` otherwise, and
    /// the thermal limit estimates heat from the RMS force (devices.md S8).
    pub motor_temperature: Option<f64>,
}

/// A straight reference axis of a scripted device: where it started and the unit direction it
/// presses along. The bridge reports the largest distance travelled along it (`max_depth_m`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PressAxis {
    /// Start point, in m.
    pub start_m: [f64; 3],
    /// Unit press direction (dimensionless).
    pub direction: [f64; 3],
}

/// What can go wrong with a device or its driver.
#[derive(Debug, Error)]
pub enum DeviceError {
    /// The spec has a non-positive or non-finite limit.
    #[error("invalid device spec: {0}")]
    InvalidSpec(String),
    /// A script parameter is out of range (zero speed, zero-length direction ...).
    #[error("invalid script: {0}")]
    InvalidScript(String),
    /// A replay file could not be read or parsed; `line` is 1-based, 0 when not applicable.
    #[error("replay file, line {line}: {message}")]
    Replay {
        /// 1-based line number in the CSV file (0 when the error is not tied to a line).
        line: u64,
        /// What was wrong.
        message: String,
    },
    /// The device was asked to render a non-finite force.
    #[error("non-finite force {0:?} N")]
    NonFiniteForce([f64; 3]),
    /// Communication with the hardware failed.
    #[error("device communication failed: {0}")]
    Comm(String),
}

/// A haptic device behind the bridge: position in, force out, at the device rate.
///
/// Implementations are called only from the bridge's device thread. `read` and `write_force`
/// must not block longer than one period.
pub trait HapticDevice: Send {
    /// The device's declared limits.
    fn spec(&self) -> &DeviceSpec;

    /// Reads the current state at clock time `now_us` (microseconds).
    ///
    /// # Errors
    /// [`DeviceError::Comm`] when the device cannot be read; the bridge then commands zero force.
    fn read(&mut self, now_us: u64) -> Result<DeviceState, DeviceError>;

    /// Renders `force_n` (N, bridge frame) until the next call.
    ///
    /// # Errors
    /// [`DeviceError::NonFiniteForce`] or [`DeviceError::Comm`].
    fn write_force(&mut self, force_n: [f64; 3]) -> Result<(), DeviceError>;

    /// True once a scripted or recorded driver has played to its end at `now_us`. Hardware
    /// drivers return false.
    fn finished(&self, now_us: u64) -> bool;

    /// Best-effort zero force and output disable; must not panic. Called on every exit path
    /// of the bridge (end of script, shutdown, device fault, link given up).
    fn safe_stop(&mut self);

    /// Enables or disables the force output (HDAPI `hdEnable(HD_FORCE_OUTPUT)`, the HBP
    /// `FORCE` enable flag, the HapticMaster bias force effect). The bridge disables it while
    /// the guard is latched off (devices.md S5) and enables it again on re-arm. The default
    /// does nothing (drivers without such a switch get zero force instead).
    ///
    /// # Errors
    /// [`DeviceError::Comm`] when the device does not answer.
    fn set_output_enabled(&mut self, _on: bool) -> Result<(), DeviceError> {
        Ok(())
    }

    /// The straight press axis of a scripted driver, if it has one.
    fn press_axis(&self) -> Option<PressAxis> {
        None
    }
}

impl<D: HapticDevice + ?Sized> HapticDevice for Box<D> {
    fn spec(&self) -> &DeviceSpec {
        (**self).spec()
    }
    fn read(&mut self, now_us: u64) -> Result<DeviceState, DeviceError> {
        (**self).read(now_us)
    }
    fn write_force(&mut self, force_n: [f64; 3]) -> Result<(), DeviceError> {
        (**self).write_force(force_n)
    }
    fn finished(&self, now_us: u64) -> bool {
        (**self).finished(now_us)
    }
    fn safe_stop(&mut self) {
        (**self).safe_stop()
    }
    fn set_output_enabled(&mut self, on: bool) -> Result<(), DeviceError> {
        (**self).set_output_enabled(on)
    }
    fn press_axis(&self) -> Option<PressAxis> {
        (**self).press_axis()
    }
}

/// Small vector helpers on `[f64; 3]` shared by drivers and the guard.
pub mod vec3 {
    /// Dot product.
    pub fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }
    /// Euclidean norm.
    pub fn norm(a: [f64; 3]) -> f64 {
        dot(a, a).sqrt()
    }
    /// `a + s * b`.
    pub fn axpy(a: [f64; 3], s: f64, b: [f64; 3]) -> [f64; 3] {
        [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
    }
    /// `a - b`.
    pub fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
    }
    /// `s * a`.
    pub fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
        [s * a[0], s * a[1], s * a[2]]
    }
    /// True when all components are finite.
    pub fn is_finite(a: [f64; 3]) -> bool {
        a.iter().all(|v| v.is_finite())
    }
    /// `a / |a|`, or `None` when `|a|` is zero or not finite.
    pub fn normalized(a: [f64; 3]) -> Option<[f64; 3]> {
        let n = norm(a);
        (n.is_finite() && n > 0.0).then(|| scale(a, 1.0 / n))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_validation_names_the_bad_field() {
        assert!(DeviceSpec::sim_default().validate().is_ok());
        let mut s = DeviceSpec::sim_default();
        s.max_force_n = f64::NAN;
        assert!(
            s.validate()
                .unwrap_err()
                .to_string()
                .contains("max_force_n")
        );
        let mut s = DeviceSpec::sim_default();
        s.workspace_min_m[1] = 1.0;
        assert!(s.validate().unwrap_err().to_string().contains("axis 1"));
    }

    #[test]
    fn workspace_margin_is_ten_percent_of_extent() {
        let s = DeviceSpec::sim_default(); // extent 0.4 m, so 0.04 m margin
        assert!(s.contains([0.2399, 0.0, 0.0], 0.1));
        assert!(!s.contains([0.2401, 0.0, 0.0], 0.1));
    }
}
