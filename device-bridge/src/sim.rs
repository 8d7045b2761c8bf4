//! The `sim` driver: a scripted, position-controlled probe, i.e. a simulated hand holding the
//! stylus firmly. The [`Script`] alone decides where the probe is; commanded forces do not move
//! it, they are recorded (last force, peak, count) and visible through a [`ForceMonitor`].
//!
//! Every script starts and ends with a [`SETTLE_S`] rest at its start point. Positions and
//! velocities are analytic functions of the time since the first `read` (velocity is the exact
//! derivative of position inside each phase).
//!
//! Neighbours: implements [`crate::device::HapticDevice`]; [`crate::replay`] is the recorded
//! counterpart; tests and the `haptic-bridge --driver sim` binary use it (devices.md section 3.3).

use std::f64::consts::PI;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use crate::device::{DeviceError, DeviceSpec, DeviceState, HapticDevice, PressAxis, vec3};

/// Rest at the start point before and after every script, in s.
pub const SETTLE_S: f64 = 0.3;

/// A scripted motion of the probe. Directions are normalised by [`Script::validate`].
#[derive(Debug, Clone, PartialEq)]
pub enum Script {
    /// Move from `start_m` along `direction` at `speed_m_per_s` until `depth_m` travelled, hold
    /// for `hold_s`, move back at the same speed, then finish.
    Press {
        /// Start point, in m.
        start_m: [f64; 3],
        /// Press direction (normalised on validation).
        direction: [f64; 3],
        /// Distance travelled along `direction`, in m.
        depth_m: f64,
        /// Speed in and out, in m/s.
        speed_m_per_s: f64,
        /// Hold time at full depth, in s.
        hold_s: f64,
    },
    /// Press to `depth_m` along `direction`, slide `length_m` along `along`, release back along
    /// `-direction`, all at `speed_m_per_s`.
    Stroke {
        /// Start point, in m.
        start_m: [f64; 3],
        /// Press direction (normalised on validation).
        direction: [f64; 3],
        /// Press depth, in m.
        depth_m: f64,
        /// Slide direction, tangent to the surface (normalised on validation).
        along: [f64; 3],
        /// Slide length, in m.
        length_m: f64,
        /// Speed of every phase, in m/s.
        speed_m_per_s: f64,
    },
    /// Sinusoidal pokes along `direction`: `d(t) = amplitude_m (1 - cos(2 pi f t)) / 2` for
    /// `cycles` periods.
    Poke {
        /// Start point, in m.
        start_m: [f64; 3],
        /// Poke direction (normalised on validation).
        direction: [f64; 3],
        /// Peak displacement, in m.
        amplitude_m: f64,
        /// Poke frequency, in Hz.
        frequency_hz: f64,
        /// Number of full pokes.
        cycles: u32,
    },
}

fn check_positive(name: &str, v: f64) -> Result<(), DeviceError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(DeviceError::InvalidScript(format!(
            "{name} must be positive and finite, got {v}"
        )))
    }
}

fn unit(name: &str, v: [f64; 3]) -> Result<[f64; 3], DeviceError> {
    vec3::normalized(v).ok_or_else(|| {
        DeviceError::InvalidScript(format!(
            "{name} must be a non-zero finite vector, got {v:?}"
        ))
    })
}

impl Script {
    /// Checks ranges and returns the script with unit directions.
    ///
    /// # Errors
    /// [`DeviceError::InvalidScript`] naming the parameter.
    pub fn validate(self) -> Result<Self, DeviceError> {
        let start_ok = |s: [f64; 3]| {
            if vec3::is_finite(s) {
                Ok(())
            } else {
                Err(DeviceError::InvalidScript(format!(
                    "start_m must be finite, got {s:?}"
                )))
            }
        };
        match self {
            Script::Press {
                start_m,
                direction,
                depth_m,
                speed_m_per_s,
                hold_s,
            } => {
                start_ok(start_m)?;
                check_positive("depth_m", depth_m)?;
                check_positive("speed_m_per_s", speed_m_per_s)?;
                if !(hold_s.is_finite() && hold_s >= 0.0) {
                    return Err(DeviceError::InvalidScript(format!(
                        "hold_s must be finite and >= 0, got {hold_s}"
                    )));
                }
                Ok(Script::Press {
                    start_m,
                    direction: unit("direction", direction)?,
                    depth_m,
                    speed_m_per_s,
                    hold_s,
                })
            }
            Script::Stroke {
                start_m,
                direction,
                depth_m,
                along,
                length_m,
                speed_m_per_s,
            } => {
                start_ok(start_m)?;
                check_positive("depth_m", depth_m)?;
                check_positive("length_m", length_m)?;
                check_positive("speed_m_per_s", speed_m_per_s)?;
                Ok(Script::Stroke {
                    start_m,
                    direction: unit("direction", direction)?,
                    depth_m,
                    along: unit("along", along)?,
                    length_m,
                    speed_m_per_s,
                })
            }
            Script::Poke {
                start_m,
                direction,
                amplitude_m,
                frequency_hz,
                cycles,
            } => {
                start_ok(start_m)?;
                check_positive("amplitude_m", amplitude_m)?;
                check_positive("frequency_hz", frequency_hz)?;
                if cycles == 0 {
                    return Err(DeviceError::InvalidScript("cycles must be >= 1".to_owned()));
                }
                Ok(Script::Poke {
                    start_m,
                    direction: unit("direction", direction)?,
                    amplitude_m,
                    frequency_hz,
                    cycles,
                })
            }
        }
    }

    /// Start point, in m.
    pub fn start_m(&self) -> [f64; 3] {
        match self {
            Script::Press { start_m, .. }
            | Script::Stroke { start_m, .. }
            | Script::Poke { start_m, .. } => *start_m,
        }
    }

    /// Press direction (unit after validation).
    pub fn direction(&self) -> [f64; 3] {
        match self {
            Script::Press { direction, .. }
            | Script::Stroke { direction, .. }
            | Script::Poke { direction, .. } => *direction,
        }
    }

    /// Total duration including both settles, in s.
    pub fn duration_s(&self) -> f64 {
        2.0 * SETTLE_S
            + match *self {
                Script::Press {
                    depth_m,
                    speed_m_per_s,
                    hold_s,
                    ..
                } => 2.0 * depth_m / speed_m_per_s + hold_s,
                Script::Stroke {
                    depth_m,
                    length_m,
                    speed_m_per_s,
                    ..
                } => (2.0 * depth_m + length_m) / speed_m_per_s,
                Script::Poke {
                    frequency_hz,
                    cycles,
                    ..
                } => f64::from(cycles) / frequency_hz,
            }
    }

    /// Position (m) and velocity (m/s) at `t_s` seconds after the script started. Before 0 and
    /// after [`duration_s`](Self::duration_s) the probe rests at its start (or, for a stroke,
    /// its end point).
    pub fn kinematics(&self, t_s: f64) -> ([f64; 3], [f64; 3]) {
        let t = t_s - SETTLE_S;
        match *self {
            Script::Press {
                start_m,
                direction,
                depth_m,
                speed_m_per_s: v,
                hold_s,
            } => {
                let t_in = depth_m / v;
                let (d, dd) = if t <= 0.0 {
                    (0.0, 0.0)
                } else if t < t_in {
                    (v * t, v)
                } else if t < t_in + hold_s {
                    (depth_m, 0.0)
                } else if t < 2.0 * t_in + hold_s {
                    (depth_m - v * (t - t_in - hold_s), -v)
                } else {
                    (0.0, 0.0)
                };
                (
                    vec3::axpy(start_m, d, direction),
                    vec3::scale(direction, dd),
                )
            }
            Script::Stroke {
                start_m,
                direction,
                depth_m,
                along,
                length_m,
                speed_m_per_s: v,
            } => {
                let (t_in, t_slide) = (depth_m / v, length_m / v);
                let (d, dd, s, ds) = if t <= 0.0 {
                    (0.0, 0.0, 0.0, 0.0)
                } else if t < t_in {
                    (v * t, v, 0.0, 0.0)
                } else if t < t_in + t_slide {
                    (depth_m, 0.0, v * (t - t_in), v)
                } else if t < 2.0 * t_in + t_slide {
                    (depth_m - v * (t - t_in - t_slide), -v, length_m, 0.0)
                } else {
                    (0.0, 0.0, length_m, 0.0)
                };
                let p = vec3::axpy(vec3::axpy(start_m, d, direction), s, along);
                let vel = vec3::axpy(vec3::scale(direction, dd), ds, along);
                (p, vel)
            }
            Script::Poke {
                start_m,
                direction,
                amplitude_m: a,
                frequency_hz: f,
                cycles,
            } => {
                let end = f64::from(cycles) / f;
                let (d, dd) = if t <= 0.0 || t >= end {
                    (0.0, 0.0)
                } else {
                    let w = 2.0 * PI * f;
                    (a * (1.0 - (w * t).cos()) / 2.0, a * w * (w * t).sin() / 2.0)
                };
                (
                    vec3::axpy(start_m, d, direction),
                    vec3::scale(direction, dd),
                )
            }
        }
    }
}

/// Shared view of the forces a [`SimProbe`] was told to render. Lock-free (atomics holding f64
/// bits), so the device thread never waits on a reader.
#[derive(Debug, Clone, Default)]
pub struct ForceMonitor {
    inner: Arc<MonitorInner>,
}

#[derive(Debug, Default)]
struct MonitorInner {
    last_n: [AtomicU64; 3],
    peak_n: AtomicU64,
    writes: AtomicU64,
    safe_stopped: AtomicU64,
}

impl ForceMonitor {
    pub(crate) fn record_force(&self, force_n: [f64; 3]) {
        for (slot, v) in self.inner.last_n.iter().zip(force_n) {
            slot.store(v.to_bits(), Ordering::Relaxed);
        }
        let m = vec3::norm(force_n);
        if m > self.peak_force_n() {
            self.inner.peak_n.store(m.to_bits(), Ordering::Relaxed);
        }
        self.inner.writes.fetch_add(1, Ordering::Release);
    }

    pub(crate) fn mark_safe_stopped(&self) {
        self.inner.safe_stopped.store(1, Ordering::Release);
    }

    /// The last force written, in N (zero before any write).
    pub fn last_force_n(&self) -> [f64; 3] {
        let l = &self.inner.last_n;
        [0, 1, 2].map(|i| f64::from_bits(l[i].load(Ordering::Relaxed)))
    }

    /// Largest force magnitude written so far, in N.
    pub fn peak_force_n(&self) -> f64 {
        f64::from_bits(self.inner.peak_n.load(Ordering::Relaxed))
    }

    /// Number of `write_force` calls (including the zero written by `safe_stop`).
    pub fn writes(&self) -> u64 {
        self.inner.writes.load(Ordering::Acquire)
    }

    /// True once `safe_stop` was called.
    pub fn safe_stopped(&self) -> bool {
        self.inner.safe_stopped.load(Ordering::Acquire) != 0
    }
}

/// The scripted, position-controlled probe.
#[derive(Debug)]
pub struct SimProbe {
    spec: DeviceSpec,
    script: Script,
    /// Clock time of the first `read`: the script's zero.
    t0_us: Option<u64>,
    monitor: ForceMonitor,
}

impl SimProbe {
    /// A probe playing `script` (validated and normalised here) under `spec`.
    ///
    /// # Errors
    /// [`DeviceError::InvalidScript`] or [`DeviceError::InvalidSpec`].
    pub fn new(script: Script, spec: DeviceSpec) -> Result<Self, DeviceError> {
        spec.validate()?;
        Ok(Self {
            spec,
            script: script.validate()?,
            t0_us: None,
            monitor: ForceMonitor::default(),
        })
    }

    /// A handle on the forces this probe renders (clone it before moving the probe away).
    pub fn monitor(&self) -> ForceMonitor {
        self.monitor.clone()
    }

    /// The (validated) script.
    pub fn script(&self) -> &Script {
        &self.script
    }
}

impl HapticDevice for SimProbe {
    fn spec(&self) -> &DeviceSpec {
        &self.spec
    }

    fn read(&mut self, now_us: u64) -> Result<DeviceState, DeviceError> {
        let t0 = *self.t0_us.get_or_insert(now_us);
        let t_s = now_us.saturating_sub(t0) as f64 * 1e-6;
        let (position_m, velocity_m_per_s) = self.script.kinematics(t_s);
        Ok(DeviceState {
            time_us: now_us,
            position_m,
            velocity_m_per_s,
            motor_temperature: None,
        })
    }

    fn write_force(&mut self, force_n: [f64; 3]) -> Result<(), DeviceError> {
        if !vec3::is_finite(force_n) {
            return Err(DeviceError::NonFiniteForce(force_n));
        }
        self.monitor.record_force(force_n);
        Ok(())
    }

    fn finished(&self, now_us: u64) -> bool {
        self.t0_us
            .is_some_and(|t0| now_us.saturating_sub(t0) as f64 * 1e-6 >= self.script.duration_s())
    }

    fn safe_stop(&mut self) {
        self.monitor.record_force([0.0; 3]);
        self.monitor.mark_safe_stopped();
    }

    fn press_axis(&self) -> Option<PressAxis> {
        Some(PressAxis {
            start_m: self.script.start_m(),
            direction: self.script.direction(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn press() -> Script {
        Script::Press {
            start_m: [0.014, 0.0, -0.005],
            direction: [-2.0, 0.0, 0.0],
            depth_m: 0.004,
            speed_m_per_s: 0.01,
            hold_s: 1.0,
        }
        .validate()
        .unwrap()
    }

    fn stroke() -> Script {
        Script::Stroke {
            start_m: [0.0; 3],
            direction: [0.0, 0.0, -1.0],
            depth_m: 0.002,
            along: [0.0, 3.0, 0.0],
            length_m: 0.01,
            speed_m_per_s: 0.02,
        }
        .validate()
        .unwrap()
    }

    fn poke() -> Script {
        Script::Poke {
            start_m: [0.0, 0.01, 0.0],
            direction: [0.0, -1.0, 0.0],
            amplitude_m: 0.003,
            frequency_hz: 2.0,
            cycles: 3,
        }
        .validate()
        .unwrap()
    }

    fn depth(s: &Script, t: f64) -> f64 {
        vec3::dot(vec3::sub(s.kinematics(t).0, s.start_m()), s.direction())
    }

    #[test]
    fn press_reaches_depth_at_depth_over_speed_and_returns() {
        let s = press();
        assert_eq!(s.direction(), [-1.0, 0.0, 0.0]);
        // 0.3 s settle + 0.4 s in + 1 s hold + 0.4 s out + 0.3 s settle
        assert!((s.duration_s() - 2.4).abs() < 1e-12);
        let t_reach = SETTLE_S + 0.004 / 0.01;
        assert!(depth(&s, SETTLE_S).abs() < 1e-12);
        assert!((depth(&s, t_reach) - 0.004).abs() < 1e-12);
        assert!((depth(&s, t_reach - 0.1) - 0.003).abs() < 1e-12);
        assert!((depth(&s, t_reach + 0.5) - 0.004).abs() < 1e-12);
        assert!((depth(&s, SETTLE_S + 1.4 + 0.2) - 0.002).abs() < 1e-12);
        let (end, v_end) = s.kinematics(s.duration_s());
        assert!(vec3::norm(vec3::sub(end, s.start_m())) < 1e-12);
        assert_eq!(v_end, [0.0; 3]);
        let max = (0..=2400)
            .map(|i| depth(&s, i as f64 * 1e-3))
            .fold(0.0, f64::max);
        assert!((max - 0.004).abs() < 1e-12);
    }

    /// Central differences of the position match the analytic velocity away from phase
    /// boundaries (where the velocity of a press or stroke jumps).
    fn check_velocity(s: &Script, skip_near: &[f64]) {
        let h = 1e-6;
        let mut t = 0.001;
        while t < s.duration_s() {
            if skip_near.iter().all(|b| (t - b).abs() > 2.0 * h) {
                let (p1, _) = s.kinematics(t + h);
                let (p0, _) = s.kinematics(t - h);
                let fd = vec3::scale(vec3::sub(p1, p0), 0.5 / h);
                let (_, v) = s.kinematics(t);
                assert!(
                    vec3::norm(vec3::sub(fd, v)) < 1e-6,
                    "t = {t}: fd {fd:?} vs {v:?}"
                );
            }
            t += 0.0123;
        }
    }

    #[test]
    fn velocities_match_finite_differences() {
        let p = press();
        let b = SETTLE_S;
        check_velocity(&p, &[b, b + 0.4, b + 1.4, b + 1.8]);
        let s = stroke();
        check_velocity(&s, &[b, b + 0.1, b + 0.6, b + 0.7]);
        check_velocity(&poke(), &[]);
    }

    #[test]
    fn stroke_presses_slides_and_releases() {
        let s = stroke(); // 0.1 s in, 0.5 s slide, 0.1 s out
        assert!((s.duration_s() - (0.6 + 0.7)).abs() < 1e-12);
        let (p, v) = s.kinematics(SETTLE_S + 0.35);
        assert!(vec3::norm(vec3::sub(p, [0.0, 0.005, -0.002])) < 1e-12);
        assert!(vec3::norm(vec3::sub(v, [0.0, 0.02, 0.0])) < 1e-12);
        let (end, _) = s.kinematics(s.duration_s());
        assert!(vec3::norm(vec3::sub(end, [0.0, 0.01, 0.0])) < 1e-12);
    }

    #[test]
    fn poke_follows_the_raised_cosine() {
        let s = poke(); // 2 Hz, 3 cycles, 3 mm
        assert!((s.duration_s() - (0.6 + 1.5)).abs() < 1e-12);
        assert!((depth(&s, SETTLE_S + 0.25) - 0.003).abs() < 1e-12); // half period: peak
        assert!(depth(&s, SETTLE_S + 0.5).abs() < 1e-12); // full period: back at start
        assert!((depth(&s, SETTLE_S + 0.125) - 0.0015).abs() < 1e-12);
    }

    #[test]
    fn invalid_scripts_are_rejected_by_name() {
        let bad = Script::Press {
            start_m: [0.0; 3],
            direction: [0.0; 3],
            depth_m: 0.01,
            speed_m_per_s: 0.01,
            hold_s: 0.0,
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("direction")
        );
        let bad = Script::Poke {
            start_m: [0.0; 3],
            direction: [1.0, 0.0, 0.0],
            amplitude_m: 0.01,
            frequency_hz: 0.0,
            cycles: 1,
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("frequency_hz")
        );
    }

    #[test]
    fn probe_time_starts_at_first_read_and_records_forces() {
        let mut p = SimProbe::new(press(), DeviceSpec::sim_default()).unwrap();
        let m = p.monitor();
        assert!(!p.finished(10_000_000));
        let s = p.read(5_000_000).unwrap();
        assert_eq!(s.position_m, [0.014, 0.0, -0.005]);
        assert!(!p.finished(5_000_000 + 2_399_999));
        assert!(p.finished(5_000_000 + 2_400_000));
        p.write_force([1.0, -2.0, 2.0]).unwrap();
        assert_eq!(m.last_force_n(), [1.0, -2.0, 2.0]);
        assert!((m.peak_force_n() - 3.0).abs() < 1e-12);
        assert!(p.write_force([f64::NAN, 0.0, 0.0]).is_err());
        p.safe_stop();
        assert_eq!(m.last_force_n(), [0.0; 3]);
        assert!(m.safe_stopped());
        assert_eq!(m.writes(), 2);
    }
}
