//! Per-tick recording (`--record FILE.csv`): one [`TickRecord`] per device tick with the pose,
//! the force actually written, the contact flag, the round trip and age of the force in use,
//! the guard's state and the command's magnitude before the guard scaled it.
//!
//! Choice: the device thread appends to a `Vec` reserved up front (120 s at the device rate when
//! recording is on, so a normal session never reallocates on the servo thread) and the rows are
//! written to disk after the run, from the calling thread. No file I/O ever happens in a tick.
//!
//! With a `.mcap` path the rows go to MCAP instead ([`write_mcap_file`]): `/device/sample`
//! (`DeviceSample`: position, velocity by finite difference) and `/device/force` (`ForceCommand`:
//! the force written after the guard, contact flag), log time = time since the bridge started,
//! so Foxglove plots them and `--driver replay` reads the samples back.
//!
//! Neighbours: filled by [`crate::link`]; the first four columns (`t_s,x_m,y_m,z_m`) are what
//! [`crate::replay`] reads, so a recording can be replayed.

use std::io::Write;
use std::path::Path;

/// One device tick.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TickRecord {
    /// Time since the bridge started, in s.
    pub t_s: f64,
    /// Device position, in m.
    pub position_m: [f64; 3],
    /// Force written to the device after the guard, in N.
    pub force_n: [f64; 3],
    /// Contact flag of the force command in use (false when none).
    pub in_contact: bool,
    /// Pose-to-force round trip of the command in use, in us (`None` when none).
    pub rtt_us: Option<u64>,
    /// Age of the held command (now minus the read time of the pose it answers), in us
    /// (`None` when no command is held).
    pub age_us: Option<u64>,
    /// The guard's state this tick ([`crate::guard::GuardState`] as a short name).
    pub state: &'static str,
    /// Magnitude of the held command's force at this position before the guard's gain, clamp
    /// and slew, in N ([`crate::guard::ForceGuard::command_n`]; 0 when none was evaluated).
    pub command_n: f64,
}

/// True when `path` names an MCAP recording (extension `.mcap`, any case).
pub fn is_mcap(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("mcap"))
}

/// Writes `rows` to `path` as MCAP (see the module docs): one `DeviceSample` (seq = row
/// number from 1) and one `ForceCommand` answering it per row.
///
/// # Errors
/// Any I/O or MCAP error, as `std::io::Error`.
pub fn write_mcap_file(path: &Path, rows: &[TickRecord]) -> std::io::Result<()> {
    use haptic_cli::recording::{Recorder, topic};
    use haptics_proto::v1::{DeviceSample, ForceCommand, Vec3};
    let other = |e: haptic_cli::recording::RecordingError| std::io::Error::other(e.to_string());
    let f = std::fs::File::create(path)?;
    let mut rec = Recorder::new(std::io::BufWriter::new(f)).map_err(other)?;
    for (i, r) in rows.iter().enumerate() {
        let t_ns = (r.t_s.max(0.0) * 1e9) as u64;
        let velocity = match (i.checked_sub(1).map(|j| &rows[j]), rows.get(i + 1)) {
            (Some(a), Some(b)) if b.t_s > a.t_s => {
                let dt = b.t_s - a.t_s;
                [0, 1, 2].map(|k| (b.position_m[k] - a.position_m[k]) / dt)
            }
            _ => [0.0; 3],
        };
        let seq = i as u64 + 1;
        let sample = DeviceSample {
            session_id: String::new(),
            seq,
            device_time_us: t_ns / 1000,
            position_m: Some(Vec3::from(r.position_m)),
            velocity_m_per_s: Some(Vec3::from(velocity)),
            capabilities: None,
            tool_id: String::new(),
        };
        rec.write(topic::DEVICE_SAMPLE, t_ns, &sample)
            .map_err(other)?;
        let force = ForceCommand {
            seq,
            force_n: Some(Vec3::from(r.force_n)),
            in_contact: r.in_contact,
            ..ForceCommand::default()
        };
        rec.write(topic::DEVICE_FORCE, t_ns, &force)
            .map_err(other)?;
    }
    rec.finish().map_err(other)
}

/// CSV header written by [`write_csv`].
pub const CSV_HEADER: &str =
    "t_s,x_m,y_m,z_m,fx_n,fy_n,fz_n,in_contact,rtt_us,age_us,state,command_n";

/// Writes `rows` as CSV with [`CSV_HEADER`] through the `csv` crate (the reader of
/// [`crate::replay`]); `rtt_us` and `age_us` are empty when absent. Fields are formatted as
/// `{:.6}` (time, force, command) and `{:.9}` (position); no field needs quoting, so the
/// bytes are those of the plain format.
///
/// # Errors
/// Any I/O error of the writer.
pub fn write_csv<W: Write>(out: W, rows: &[TickRecord]) -> std::io::Result<()> {
    let mut w = csv::Writer::from_writer(out);
    w.write_record(CSV_HEADER.split(','))?;
    let optional = |v: Option<u64>| v.map_or_else(String::new, |v| v.to_string());
    for r in rows {
        let [x, y, z] = r.position_m;
        let [fx, fy, fz] = r.force_n;
        w.write_record([
            format!("{:.6}", r.t_s),
            format!("{x:.9}"),
            format!("{y:.9}"),
            format!("{z:.9}"),
            format!("{fx:.6}"),
            format!("{fy:.6}"),
            format!("{fz:.6}"),
            r.in_contact.to_string(),
            optional(r.rtt_us),
            optional(r.age_us),
            r.state.to_owned(),
            format!("{:.6}", r.command_n),
        ])?;
    }
    w.flush()
}

/// Writes `rows` to the file at `path` (created or truncated).
///
/// # Errors
/// Any I/O error creating or writing the file.
pub fn write_csv_file(path: &Path, rows: &[TickRecord]) -> std::io::Result<()> {
    let f = std::fs::File::create(path)?;
    write_csv(std::io::BufWriter::new(f), rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::replay::Trajectory;

    #[test]
    fn rows_have_twelve_columns_and_empty_rtt_when_absent() {
        let rows = [
            TickRecord {
                t_s: 0.0,
                ..Default::default()
            },
            TickRecord {
                t_s: 0.001,
                position_m: [0.01, 0.0, -0.005],
                force_n: [1.5, 0.0, 0.0],
                in_contact: true,
                rtt_us: Some(87),
                age_us: Some(120),
                state: "fresh",
                command_n: 1.75,
            },
        ];
        let mut buf = Vec::new();
        write_csv(&mut buf, &rows).unwrap();
        let text = String::from_utf8(buf).unwrap();
        let lines: Vec<_> = text.lines().collect();
        assert_eq!(lines[0], CSV_HEADER);
        assert!(lines[1].ends_with(",false,,,,0.000000"), "{}", lines[1]);
        assert!(
            lines[2].ends_with(",true,87,120,fresh,1.750000"),
            "{}",
            lines[2]
        );
        assert!(lines.iter().all(|l| l.split(',').count() == 12));
    }

    /// The exact bytes of two rows, written by hand (the format of the recordings already on
    /// disk: `{:.6}` time, force and command, `{:.9}` position, empty rtt/age when absent,
    /// `\n` line ends, no quoting).
    #[test]
    fn two_rows_are_these_bytes() {
        let rows = [
            TickRecord {
                t_s: 0.0,
                ..Default::default()
            },
            TickRecord {
                t_s: 12.3456789,
                position_m: [0.01, -0.0123456789, 1.5],
                force_n: [-1.5, 0.25, 3.3],
                in_contact: true,
                rtt_us: Some(87),
                age_us: None,
                state: "scaled",
                command_n: 4.0000004,
            },
        ];
        let mut buf = Vec::new();
        write_csv(&mut buf, &rows).unwrap();
        let expected = "t_s,x_m,y_m,z_m,fx_n,fy_n,fz_n,in_contact,rtt_us,age_us,state,command_n\n\
            0.000000,0.000000000,0.000000000,0.000000000,0.000000,0.000000,0.000000,false,,,,0.000000\n\
            12.345679,0.010000000,-0.012345679,1.500000000,-1.500000,0.250000,3.300000,true,87,,scaled,4.000000\n";
        assert_eq!(String::from_utf8(buf).unwrap(), expected);
    }

    #[test]
    fn a_recording_replays() {
        let rows: Vec<_> = (0..5)
            .map(|i| TickRecord {
                t_s: i as f64 * 1e-3,
                position_m: [i as f64 * 1e-4, 0.0, 0.0],
                ..Default::default()
            })
            .collect();
        let mut buf = Vec::new();
        write_csv(&mut buf, &rows).unwrap();
        let tr = Trajectory::from_csv(buf.as_slice()).unwrap();
        assert!((tr.end_s() - 0.004).abs() < 1e-12);
    }
}

#[cfg(test)]
mod mcap_tests {
    use super::*;

    #[test]
    fn an_mcap_recording_replays_the_same_trajectory() {
        let rows: Vec<TickRecord> = (0..50)
            .map(|i| TickRecord {
                t_s: 0.001 * f64::from(i),
                position_m: [0.014 - 1e-5 * f64::from(i), 0.0, -0.005],
                force_n: [0.001 * f64::from(i), 0.0, 0.0],
                in_contact: i > 10,
                state: "fresh",
                ..TickRecord::default()
            })
            .collect();
        let dir = std::env::temp_dir().join(format!("bridge-mcap-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("r.MCAP");
        assert!(is_mcap(&path) && !is_mcap(&dir.join("r.csv")));
        write_mcap_file(&path, &rows).unwrap();
        let t = crate::replay::Trajectory::from_path(&path).unwrap();
        assert!((t.start_s() - 0.0).abs() < 1e-9 && (t.end_s() - 0.049).abs() < 1e-9);
        let (p, v, _) = t.sample(0.0205, 0);
        assert!((p[0] - (0.014 - 1e-5 * 20.5)).abs() < 1e-12, "{p:?}");
        assert!((v[0] + 1e-2).abs() < 1e-9, "{v:?}");
        let bytes = std::fs::read(&path).unwrap();
        let forces = haptic_cli::recording::read_topic::<haptics_proto::v1::ForceCommand>(
            &bytes,
            haptic_cli::recording::topic::DEVICE_FORCE,
        )
        .unwrap();
        assert_eq!(forces.len(), 50);
        assert_eq!(forces[30].1.force_n.as_ref().unwrap().x, 0.03);
        assert!(forces[30].1.in_contact && !forces[5].1.in_contact);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
