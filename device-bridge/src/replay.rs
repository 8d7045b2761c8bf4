//! The `replay` driver: plays a recorded trajectory from CSV (header starting with
//! `t_s,x_m,y_m,z_m`, further columns ignored, SI units, strictly increasing times). Positions are linearly interpolated; the velocity is the
//! finite difference of the enclosing segment (the exact derivative of the interpolant). The
//! driver finishes at the last recorded time. Forces it is told to render are kept like the
//! [`crate::sim`] probe's.
//!
//! Neighbours: implements [`crate::device::HapticDevice`]; the bridge's `--record` output
//! ([`crate::record`]) starts with the same four columns, so a recorded session can be replayed.
//! Format background: devices.md section 5.4.

use std::io::Read;
use std::path::Path;

use crate::device::{DeviceError, DeviceSpec, DeviceState, HapticDevice, vec3};
use crate::sim::ForceMonitor;

/// A recorded trajectory: sample times (s) and positions (m), at least one sample.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    times_s: Vec<f64>,
    positions_m: Vec<[f64; 3]>,
}

const HEADER: [&str; 4] = ["t_s", "x_m", "y_m", "z_m"];

fn err(line: u64, message: impl Into<String>) -> DeviceError {
    DeviceError::Replay {
        line,
        message: message.into(),
    }
}

impl Trajectory {
    /// Builds a trajectory from samples.
    ///
    /// # Errors
    /// [`DeviceError::Replay`] (line 0) when empty, lengths differ, a value is not finite, or
    /// times are not strictly increasing.
    pub fn new(times_s: Vec<f64>, positions_m: Vec<[f64; 3]>) -> Result<Self, DeviceError> {
        if times_s.is_empty() || times_s.len() != positions_m.len() {
            return Err(err(
                0,
                "need at least one sample and as many times as positions",
            ));
        }
        for (i, (t, p)) in times_s.iter().zip(&positions_m).enumerate() {
            if !t.is_finite() || !vec3::is_finite(*p) {
                return Err(err(0, format!("sample {i} is not finite")));
            }
            if i > 0 && *t <= times_s[i - 1] {
                return Err(err(
                    0,
                    format!("sample {i}: time {t} s is not after the previous"),
                ));
            }
        }
        Ok(Self {
            times_s,
            positions_m,
        })
    }

    /// Parses CSV whose header starts with `t_s,x_m,y_m,z_m` (later columns, such as the
    /// bridge's own `--record` output, are ignored).
    ///
    /// # Errors
    /// [`DeviceError::Replay`] with the 1-based line number of the first malformed line: wrong
    /// header, a row with a different field count than the header, a non-number or non-finite value, or a time not after the
    /// previous one; line 0 when the file has no data rows.
    pub fn from_csv<R: Read>(reader: R) -> Result<Self, DeviceError> {
        let mut rdr = csv::ReaderBuilder::new()
            .has_headers(false)
            .flexible(true)
            .trim(csv::Trim::All)
            .from_reader(reader);
        let mut times_s = Vec::new();
        let mut positions_m = Vec::new();
        let mut record = csv::StringRecord::new();
        let mut columns = 0;
        loop {
            let more = rdr.read_record(&mut record).map_err(|e| {
                let line = e.position().map_or(0, |p| p.line());
                err(line, format!("unreadable CSV: {e}"))
            })?;
            if !more {
                break;
            }
            let line = record.position().map_or(0, |p| p.line());
            if columns == 0 {
                columns = record.len();
                if columns < 4 || record.iter().take(4).ne(HEADER) {
                    return Err(err(
                        line,
                        format!(
                            "expected header `t_s,x_m,y_m,z_m`, got `{}`",
                            record.iter().collect::<Vec<_>>().join(",")
                        ),
                    ));
                }
                continue;
            }
            if record.len() != columns {
                return Err(err(
                    line,
                    format!("expected {columns} fields, got {}", record.len()),
                ));
            }
            let mut v = [0.0; 4];
            for (i, field) in record.iter().take(4).enumerate() {
                v[i] = field
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| {
                        err(
                            line,
                            format!("{} = `{field}` is not a finite number", HEADER[i]),
                        )
                    })?;
            }
            if let Some(&prev) = times_s.last()
                && v[0] <= prev
            {
                return Err(err(
                    line,
                    format!("t_s = {} is not after the previous time {prev}", v[0]),
                ));
            }
            times_s.push(v[0]);
            positions_m.push([v[1], v[2], v[3]]);
        }
        if times_s.is_empty() {
            return Err(err(
                0,
                "no samples (need the header and at least one data row)",
            ));
        }
        Self::new(times_s, positions_m)
    }

    /// Reads [`from_csv`](Self::from_csv) from a file.
    ///
    /// # Errors
    /// As `from_csv`, plus line 0 when the file cannot be opened.
    pub fn from_path(path: &Path) -> Result<Self, DeviceError> {
        if crate::record::is_mcap(path) {
            let bytes = std::fs::read(path)
                .map_err(|e| err(0, format!("cannot open {}: {e}", path.display())))?;
            return Self::from_mcap(&bytes);
        }
        let f = std::fs::File::open(path)
            .map_err(|e| err(0, format!("cannot open {}: {e}", path.display())))?;
        Self::from_csv(std::io::BufReader::new(f))
    }

    /// Reads the `/device/sample` topic of an MCAP recording (`haptic-bridge --record
    /// FILE.mcap`): times from the log times (s), positions from `position_m`.
    ///
    /// # Errors
    /// [`DeviceError::Replay`] (line 0) for a malformed file, a sample without a position, or
    /// the checks of [`Trajectory::new`].
    pub fn from_mcap(bytes: &[u8]) -> Result<Self, DeviceError> {
        use haptic_cli::recording::{read_topic, topic};
        let samples = read_topic::<haptics_proto::v1::DeviceSample>(bytes, topic::DEVICE_SAMPLE)
            .map_err(|e| err(0, e.to_string()))?;
        let mut times_s = Vec::with_capacity(samples.len());
        let mut positions_m = Vec::with_capacity(samples.len());
        for (i, (t_ns, s)) in samples.iter().enumerate() {
            let p = s
                .position_m
                .as_ref()
                .ok_or_else(|| err(0, format!("sample {i} has no position")))?;
            times_s.push(*t_ns as f64 * 1e-9);
            positions_m.push(p.to_array());
        }
        Self::new(times_s, positions_m)
    }

    /// First recorded time, in s.
    pub fn start_s(&self) -> f64 {
        self.times_s[0]
    }

    /// Last recorded time, in s.
    pub fn end_s(&self) -> f64 {
        self.times_s[self.times_s.len() - 1]
    }

    /// Position (m) and velocity (m/s) at recorded time `t_s`, searching from segment `hint`
    /// (returned updated, so playing forward costs O(1) per call). Clamped to the first and last
    /// sample outside the recorded range, with zero velocity there.
    pub fn sample(&self, t_s: f64, hint: usize) -> ([f64; 3], [f64; 3], usize) {
        let n = self.times_s.len();
        if n == 1 || t_s <= self.times_s[0] {
            return (self.positions_m[0], [0.0; 3], 0);
        }
        if t_s >= self.times_s[n - 1] {
            return (self.positions_m[n - 1], [0.0; 3], n - 2);
        }
        let mut i = hint.min(n - 2);
        while i > 0 && self.times_s[i] > t_s {
            i -= 1;
        }
        while self.times_s[i + 1] <= t_s {
            i += 1;
        }
        let (t0, t1) = (self.times_s[i], self.times_s[i + 1]);
        let (p0, p1) = (self.positions_m[i], self.positions_m[i + 1]);
        let slope = vec3::scale(vec3::sub(p1, p0), 1.0 / (t1 - t0));
        (vec3::axpy(p0, t_s - t0, slope), slope, i)
    }
}

/// A device that plays a [`Trajectory`] in real time from its first `read`.
#[derive(Debug)]
pub struct ReplayDevice {
    spec: DeviceSpec,
    trajectory: Trajectory,
    t0_us: Option<u64>,
    cursor: usize,
    monitor: ForceMonitor,
}

impl ReplayDevice {
    /// A replay of `trajectory` under `spec`.
    ///
    /// # Errors
    /// [`DeviceError::InvalidSpec`].
    pub fn new(trajectory: Trajectory, spec: DeviceSpec) -> Result<Self, DeviceError> {
        spec.validate()?;
        Ok(Self {
            spec,
            trajectory,
            t0_us: None,
            cursor: 0,
            monitor: ForceMonitor::default(),
        })
    }

    /// A handle on the forces this device renders.
    pub fn monitor(&self) -> ForceMonitor {
        self.monitor.clone()
    }

    fn recorded_time_s(&self, now_us: u64, t0_us: u64) -> f64 {
        self.trajectory.start_s() + now_us.saturating_sub(t0_us) as f64 * 1e-6
    }
}

impl HapticDevice for ReplayDevice {
    fn spec(&self) -> &DeviceSpec {
        &self.spec
    }

    fn read(&mut self, now_us: u64) -> Result<DeviceState, DeviceError> {
        let t0 = *self.t0_us.get_or_insert(now_us);
        let t = self.recorded_time_s(now_us, t0);
        let (position_m, velocity_m_per_s, cursor) = self.trajectory.sample(t, self.cursor);
        self.cursor = cursor;
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
            .is_some_and(|t0| self.recorded_time_s(now_us, t0) >= self.trajectory.end_s())
    }

    fn safe_stop(&mut self) {
        self.monitor.record_force([0.0; 3]);
        self.monitor.mark_safe_stopped();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = "t_s,x_m,y_m,z_m\n0.0,0,0,0\n0.5,0.01,0,-0.02\n1.5,0.01,0.01,-0.02\n";

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        vec3::norm(vec3::sub(a, b)) < 1e-12
    }

    #[test]
    fn interpolates_linearly_with_segment_velocity() {
        let tr = Trajectory::from_csv(GOOD.as_bytes()).unwrap();
        assert_eq!((tr.start_s(), tr.end_s()), (0.0, 1.5));
        let (p, v, _) = tr.sample(0.25, 0);
        assert!(close(p, [0.005, 0.0, -0.01]));
        assert!(close(v, [0.02, 0.0, -0.04]));
        let (p, v, _) = tr.sample(1.0, 0);
        assert!(close(p, [0.01, 0.005, -0.02]));
        assert!(close(v, [0.0, 0.01, 0.0]));
        // Searching backwards from a later hint gives the same answer.
        let (p2, _, _) = tr.sample(0.25, 1);
        assert!(close(p2, [0.005, 0.0, -0.01]));
        // Clamped outside the range.
        assert_eq!(tr.sample(9.0, 0).0, [0.01, 0.01, -0.02]);
        assert_eq!(tr.sample(9.0, 0).1, [0.0; 3]);
    }

    #[test]
    fn device_plays_from_first_read_and_finishes_at_last_time() {
        let tr = Trajectory::from_csv(GOOD.as_bytes()).unwrap();
        let mut d = ReplayDevice::new(tr, DeviceSpec::sim_default()).unwrap();
        assert!(!d.finished(0));
        let s = d.read(1_000_000).unwrap();
        assert_eq!(s.position_m, [0.0; 3]);
        let s = d.read(1_250_000).unwrap();
        assert!(close(s.position_m, [0.005, 0.0, -0.01]));
        // Finite differences of successive reads match the reported velocity.
        let a = d.read(1_600_000).unwrap();
        let b = d.read(1_601_000).unwrap();
        let fd = vec3::scale(vec3::sub(b.position_m, a.position_m), 1e3);
        assert!(close(fd, a.velocity_m_per_s));
        assert!(!d.finished(2_499_999));
        assert!(d.finished(2_500_000));
    }

    #[test]
    fn malformed_csv_names_the_line() {
        // (input, expected line, expected words)
        let table = [
            ("t,x,y,z\n0,0,0,0\n", 1, "header"),
            (
                "t_s,x_m,y_m,z_m\n0,0,0,0\n0.1,0,zero,0\n",
                3,
                "y_m = `zero`",
            ),
            (
                "t_s,x_m,y_m,z_m\n0,0,0,0\n0.1,0,0\n",
                3,
                "expected 4 fields",
            ),
            (
                "t_s,x_m,y_m,z_m\n0,0,0,0\n0.1,0,0,0\n0.1,1,0,0\n",
                4,
                "not after",
            ),
            ("t_s,x_m,y_m,z_m\n0,0,0,NaN\n", 2, "finite"),
            ("t_s,x_m,y_m,z_m\n", 0, "no samples"),
            ("", 0, "no samples"),
        ];
        for (text, line, words) in table {
            match Trajectory::from_csv(text.as_bytes()) {
                Err(DeviceError::Replay { line: l, message }) => {
                    assert_eq!(l, line, "{text:?}: {message}");
                    assert!(message.contains(words), "{text:?}: {message}");
                }
                other => panic!("{text:?}: expected a replay error, got {other:?}"),
            }
        }
        let e = Trajectory::from_csv("t_s,x_m,y_m,z_m\n0,0,0,0\n0,1,1,1\n".as_bytes())
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("replay file, line 3:"), "{e}");
    }
}
