//! The `haptic-bridge` command line: raw [`Args`] (clap) validated into a [`Setup`] (a device
//! and a checked [`BridgeConfig`]), so the binary stays glue.
//!
//! Neighbours: builds [`crate::sim::SimProbe`] or [`crate::replay::ReplayDevice`] and a
//! [`crate::link::BridgeConfig`]; `src/bin/haptic-bridge.rs` calls [`crate::link::run`].

use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, ValueEnum};
use haptics_proto::parse_vec3;
use thiserror::Error;

use crate::device::{DeviceError, DeviceSpec, HapticDevice};
use crate::link::{BridgeConfig, BridgeError};
use crate::replay::{ReplayDevice, Trajectory};
use crate::sim::{Script, SimProbe};

/// Which driver to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Driver {
    /// Scripted, position-controlled probe.
    Sim,
    /// Recorded trajectory from `--replay FILE`.
    Replay,
}

/// Which sim script to play.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ScriptKind {
    /// Press in, hold, release.
    Press,
    /// Press, slide along `--along`, release.
    Stroke,
    /// Sinusoidal pokes.
    Poke,
}

/// Streams a haptic device's poses to a hapticd session and renders the forces it answers.
#[derive(Debug, Clone, Parser)]
#[command(name = "haptic-bridge", version)]
pub struct Args {
    /// Server URL, e.g. http://127.0.0.1:50051.
    #[arg(long)]
    pub server: String,
    /// Session id (from SessionControl.StartSession).
    #[arg(long)]
    pub session: String,
    /// Device driver.
    #[arg(long, value_enum, default_value_t = Driver::Sim)]
    pub driver: Driver,
    /// Sim script.
    #[arg(long, value_enum, default_value_t = ScriptKind::Press)]
    pub script: ScriptKind,
    /// Script start point X,Y,Z in m.
    #[arg(long, default_value = "0.014,0,-0.005", value_parser = parse_vec3, allow_hyphen_values = true)]
    pub start_m: [f64; 3],
    /// Press direction X,Y,Z (normalised).
    #[arg(long, default_value = "-1,0,0", value_parser = parse_vec3, allow_hyphen_values = true)]
    pub direction: [f64; 3],
    /// Press depth in m (press, stroke): travel from the start point. The default takes the 2 mm
    /// probe from 14 mm to 8 mm off the LV axis, 3.7 mm into the epicardium (9.68 mm at z = -5 mm).
    #[arg(long, default_value_t = 0.006)]
    pub depth_m: f64,
    /// Probe speed in m/s (press, stroke).
    #[arg(long, default_value_t = 0.01)]
    pub speed_m_per_s: f64,
    /// Hold time at depth in s (press).
    #[arg(long, default_value_t = 1.0)]
    pub hold_s: f64,
    /// Slide length in m (stroke).
    #[arg(long, default_value_t = 0.01)]
    pub length_m: f64,
    /// Slide direction X,Y,Z (stroke; normalised).
    #[arg(long, default_value = "0,1,0", value_parser = parse_vec3, allow_hyphen_values = true)]
    pub along: [f64; 3],
    /// Poke amplitude in m (poke).
    #[arg(long, default_value_t = 0.003)]
    pub amplitude_m: f64,
    /// Poke frequency in Hz (poke).
    #[arg(long, default_value_t = 1.0)]
    pub frequency_hz: f64,
    /// Number of pokes (poke).
    #[arg(long, default_value_t = 3)]
    pub cycles: u32,
    /// Trajectory CSV (t_s,x_m,y_m,z_m) for --driver replay.
    #[arg(long)]
    pub replay: Option<PathBuf>,
    /// Write one CSV row per device tick to this file at the end.
    #[arg(long)]
    pub record: Option<PathBuf>,
    /// Force clamp in N.
    #[arg(long, default_value_t = 10.0)]
    pub max_force_n: f64,
    /// Device stiffness limit in N/m; the slew limit is this times 1 m/s.
    #[arg(long, default_value_t = 1000.0)]
    pub max_stiffness_n_per_m: f64,
    /// Device loop rate in Hz.
    #[arg(long, default_value_t = 1000.0)]
    pub rate_hz: f64,
    /// Hard stop after this many seconds.
    #[arg(long)]
    pub duration_s: Option<f64>,
    /// Print the summary as one JSON line instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Errors turning arguments into a runnable setup.
#[derive(Debug, Error)]
pub enum CliError {
    /// A flag value is out of range or missing.
    #[error("{0}")]
    Invalid(String),
    /// The device could not be built (bad script, unreadable replay file ...).
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The bridge configuration is invalid.
    #[error(transparent)]
    Bridge(#[from] BridgeError),
}

/// Everything the binary needs to call [`crate::link::run`].
pub struct Setup {
    /// The device to drive.
    pub device: Box<dyn HapticDevice>,
    /// Checked bridge configuration.
    pub config: BridgeConfig,
    /// Where to write the per-tick CSV, if anywhere.
    pub record_path: Option<PathBuf>,
    /// Print JSON instead of the table.
    pub json: bool,
}

impl Args {
    /// The device spec these flags describe (sim defaults with the clamp, stiffness and rate).
    pub fn spec(&self) -> DeviceSpec {
        DeviceSpec {
            name: format!("{:?}", self.driver).to_lowercase(),
            max_force_n: self.max_force_n,
            max_stiffness_n_per_m: self.max_stiffness_n_per_m,
            rate_hz: self.rate_hz,
            ..DeviceSpec::sim_default()
        }
    }

    /// The sim script these flags describe.
    pub fn sim_script(&self) -> Script {
        match self.script {
            ScriptKind::Press => Script::Press {
                start_m: self.start_m,
                direction: self.direction,
                depth_m: self.depth_m,
                speed_m_per_s: self.speed_m_per_s,
                hold_s: self.hold_s,
            },
            ScriptKind::Stroke => Script::Stroke {
                start_m: self.start_m,
                direction: self.direction,
                depth_m: self.depth_m,
                along: self.along,
                length_m: self.length_m,
                speed_m_per_s: self.speed_m_per_s,
            },
            ScriptKind::Poke => Script::Poke {
                start_m: self.start_m,
                direction: self.direction,
                amplitude_m: self.amplitude_m,
                frequency_hz: self.frequency_hz,
                cycles: self.cycles,
            },
        }
    }

    /// Validates the flags and builds the device and configuration.
    ///
    /// # Errors
    /// [`CliError`] saying which flag is wrong.
    pub fn setup(&self) -> Result<Setup, CliError> {
        let spec = self.spec();
        spec.validate()?;
        let device: Box<dyn HapticDevice> = match self.driver {
            Driver::Sim => Box::new(SimProbe::new(self.sim_script(), spec.clone())?),
            Driver::Replay => {
                let path = self.replay.as_ref().ok_or_else(|| {
                    CliError::Invalid("--driver replay needs --replay FILE".to_owned())
                })?;
                Box::new(ReplayDevice::new(
                    Trajectory::from_path(path)?,
                    spec.clone(),
                )?)
            }
        };
        let mut config = BridgeConfig::new(&self.server, &self.session, &spec);
        config.record = self.record.is_some();
        if let Some(d) = self.duration_s {
            if !(d.is_finite() && d > 0.0) {
                return Err(CliError::Invalid(format!(
                    "--duration-s must be > 0, got {d}"
                )));
            }
            config.max_duration = Some(Duration::from_secs_f64(d));
        }
        config.validate()?;
        Ok(Setup {
            device,
            config,
            record_path: self.record.clone(),
            json: self.json,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_build_a_press_setup() {
        let a = Args::try_parse_from([
            "haptic-bridge",
            "--server",
            "http://127.0.0.1:1",
            "--session",
            "s",
        ])
        .unwrap();
        assert_eq!(a.start_m, [0.014, 0.0, -0.005]);
        assert_eq!(a.direction, [-1.0, 0.0, 0.0]);
        assert_eq!((a.depth_m, a.speed_m_per_s, a.hold_s), (0.006, 0.01, 1.0));
        let s = a.setup().unwrap();
        assert_eq!(s.config.guard.max_force_n, 10.0);
        assert!(s.device.press_axis().is_some());
        assert!(s.config.max_duration.is_none() && !s.config.record && !s.json);
    }

    #[test]
    fn bad_flags_are_explained() {
        let a = Args::try_parse_from([
            "haptic-bridge",
            "--server",
            "http://x:1",
            "--session",
            "s",
            "--direction",
            "1,0",
        ]);
        assert!(a.unwrap_err().to_string().contains("expected X,Y,Z"));
        let a = Args::try_parse_from([
            "haptic-bridge",
            "--server",
            "http://x:1",
            "--session",
            "s",
            "--driver",
            "replay",
        ])
        .unwrap();
        assert!(
            a.setup()
                .err()
                .unwrap()
                .to_string()
                .contains("--replay FILE")
        );
        let a =
            Args::try_parse_from(["haptic-bridge", "--server", "localhost:1", "--session", "s"])
                .unwrap();
        assert!(a.setup().err().unwrap().to_string().contains("http://"));
        let a = Args::try_parse_from([
            "haptic-bridge",
            "--server",
            "http://x:1",
            "--session",
            "s",
            "--start-m",
            "1,nan,0",
        ]);
        let e = a.unwrap_err().to_string();
        assert!(e.contains("1,nan,0") && e.contains("not finite"), "{e}");
    }
}
