//! The `haptic-bridge` command line: raw [`Args`] (clap) validated into a [`Setup`] (a device
//! and a checked [`BridgeConfig`]), so the binary stays glue.
//!
//! Neighbours: builds a driver ([`crate::sim::SimProbe`], [`crate::replay::ReplayDevice`],
//! [`crate::hapticmaster::HapticMaster`], [`crate::serial::SerialDevice`],
//! [`crate::openhaptics::OpenHapticsDevice`]) seen through its [`crate::transform`], and a
//! [`crate::link::BridgeConfig`]; `src/bin/haptic-bridge.rs` calls [`crate::link::run`].

use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, ValueEnum};
use haptic_cli::vec3::parse_vec3;
use thiserror::Error;

use crate::device::{DeviceError, DeviceSpec, HapticDevice};
use crate::hapticmaster::{ExitState, HapticMaster, HapticMasterParams};
use crate::link::{BridgeConfig, BridgeError, FaultInjection, RearmButton, RearmMode};
use crate::passivity::PassivityMode;
use crate::replay::{ReplayDevice, Trajectory};
use crate::serial::{SerialDevice, SerialParams};
use crate::sim::{Script, SimProbe};
use crate::transform::{DeviceTransform, Transformed};

/// Which driver to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Driver {
    /// Scripted, position-controlled probe.
    Sim,
    /// Recorded trajectory from `--replay FILE`.
    Replay,
    /// Moog/FCS HapticMaster over its TCP text protocol (`--hm-addr`).
    Hapticmaster,
    /// An HBP/1 arm on a serial port (`--serial-port`; docs/serial-protocol.md).
    Serial,
    /// Phantom / Touch through OpenHaptics (build with `--features openhaptics`).
    Openhaptics,
}

/// Who re-arms the forces after the guard disabled them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum RearmArg {
    /// The operator presses Enter (after the link has been healthy for 0.5 s).
    Key,
    /// Automatically once the link has been healthy for 0.5 s (consent given up front).
    Auto,
}

/// What the passivity layer does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum PassivityArg {
    /// Nothing.
    Off,
    /// Track the energy and report it.
    Observe,
    /// Track and dissipate (default).
    Control,
}

/// The HapticMaster's exit state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ExitStateArg {
    /// `set state stop` (holds position; the lab code's sequence).
    Stop,
    /// `set state off`.
    Off,
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
    #[arg(long, env = "HAPTICD_ADDR")]
    pub server: String,
    /// Token and TLS files (a `device` token is enough).
    #[command(flatten)]
    pub credentials: haptic_cli::credentials::ClientCredentials,
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
    /// Force clamp in N (sim and replay: the device's clamp, default 10; hardware drivers: a
    /// lower cap on the limit the device reports).
    #[arg(long)]
    pub max_force_n: Option<f64>,
    /// Device stiffness limit in N/m (sim and replay); the slew limit is this times 1 m/s.
    #[arg(long, default_value_t = 1000.0)]
    pub max_stiffness_n_per_m: f64,
    /// HapticMaster address (--driver hapticmaster).
    #[arg(long, default_value = "192.168.0.25:7654")]
    pub hm_addr: std::net::SocketAddr,
    /// HapticMaster state on exit.
    #[arg(long, value_enum, default_value_t = ExitStateArg::Stop)]
    pub hm_exit_state: ExitStateArg,
    /// Serial port of an HBP/1 device (--driver serial), e.g. /dev/ttyACM0.
    #[arg(long)]
    pub serial_port: Option<String>,
    /// Serial baud rate (0 for a pseudo-terminal; USB CDC-ACM ignores it).
    #[arg(long, default_value_t = 2_000_000)]
    pub baud: u32,
    /// Device-side watchdog asked of an HBP/1 device, ms (2..=100).
    #[arg(long, default_value_t = 20)]
    pub device_watchdog_ms: u16,
    /// The OpenHaptics HDAPI library to load (default: libHD.so on the library path).
    #[arg(long)]
    pub hd_library: Option<PathBuf>,
    /// Device to scene axes: scene x,y,z as signed device axes (default: y,z,x for the
    /// HapticMaster, as HAPI maps it; x,y,z otherwise).
    #[arg(long)]
    pub axes: Option<String>,
    /// Device to scene rotation as 9 numbers, row-major (instead of --axes).
    #[arg(long, allow_hyphen_values = true)]
    pub rotation: Option<String>,
    /// Motion scale, scene metres per device metre.
    #[arg(long, default_value_t = 1.0)]
    pub scale: f64,
    /// Scene position of the device origin X,Y,Z in m.
    #[arg(long, default_value = "0,0,0", value_parser = parse_vec3, allow_hyphen_values = true)]
    pub offset_m: [f64; 3],
    /// Scene force to device force factor (set it equal to --scale to conserve energy).
    #[arg(long, default_value_t = 1.0)]
    pub force_scale: f64,
    /// Who re-arms the forces after a link loss disabled them.
    #[arg(long, value_enum, default_value_t = RearmArg::Key)]
    pub rearm: RearmArg,
    /// Passivity observer/controller at the device port.
    #[arg(long, value_enum, default_value_t = PassivityArg::Control)]
    pub passivity: PassivityArg,
    /// Perceptual deadband on the pose stream, as a fraction (e.g. 0.07); off by default.
    #[arg(long)]
    pub deadband: Option<f64>,
    /// The tool this bridge drives in the session (several bridges, one tool each, press one
    /// session at once up to its scene's probe.max_tools); empty: the default tool. Repeated
    /// with `--driver sim` (at most [`MAX_SIM_TOOLS`]), one process drives a simulated arm per
    /// tool: tool k of n plays the script turned by k 360/n degrees about the scene's z axis
    /// (the LV's long axis: two tools press opposite sides).
    #[arg(long = "tool", default_value = "")]
    pub tool: Vec<String>,
    /// Fault injection (tests only): fraction of messages dropped each way.
    #[arg(long, default_value_t = 0.0)]
    pub fault_drop: f64,
    /// Fault injection (tests only): force commands delayed by MIN,MAX ms (uniform, in order).
    #[arg(long)]
    pub fault_delay_ms: Option<String>,
    /// Fault injection seed.
    #[arg(long, default_value_t = 1)]
    pub fault_seed: u64,
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

/// Most tools one `haptic-bridge --driver sim` process drives (`--tool` repeated); the daemon's
/// own limit is the scene's `probe.max_tools` (at most 4).
pub const MAX_SIM_TOOLS: usize = 4;

/// Everything the binary needs to call [`crate::link::run`] for one tool.
pub struct Setup {
    /// The device to drive.
    pub device: Box<dyn HapticDevice>,
    /// Checked bridge configuration.
    pub config: BridgeConfig,
    /// Where to write the per-tick CSV, if anywhere.
    pub record_path: Option<PathBuf>,
    /// Print JSON instead of the table.
    pub json: bool,
    /// The operator's re-arm button, when `--rearm key` (the binary presses it on Enter).
    pub rearm_button: Option<RearmButton>,
}

impl Args {
    /// The device spec these flags describe (sim defaults with the clamp, stiffness and rate).
    pub fn spec(&self) -> DeviceSpec {
        DeviceSpec {
            name: format!("{:?}", self.driver).to_lowercase(),
            max_force_n: self.max_force_n.unwrap_or(10.0),
            max_continuous_force_n: self
                .max_force_n
                .map_or(DeviceSpec::sim_default().max_continuous_force_n, |m| {
                    m.min(DeviceSpec::sim_default().max_continuous_force_n)
                }),
            max_stiffness_n_per_m: self.max_stiffness_n_per_m,
            rate_hz: self.rate_hz,
            ..DeviceSpec::sim_default()
        }
    }

    /// The sim script these flags describe (the first tool's).
    pub fn sim_script(&self) -> Script {
        self.sim_script_for(0, 1)
    }

    /// The sim script of tool `k` of `n` (`--tool` repeated): the flags' script with its start
    /// point, press direction and slide direction turned by `k 360 / n` degrees about the
    /// scene's z axis.
    pub fn sim_script_for(&self, k: usize, n: usize) -> Script {
        let angle = std::f64::consts::TAU * k as f64 / n.max(1) as f64;
        let (sin, cos) = angle.sin_cos();
        let turn = |v: [f64; 3]| [cos * v[0] - sin * v[1], sin * v[0] + cos * v[1], v[2]];
        let (start_m, direction, along) =
            (turn(self.start_m), turn(self.direction), turn(self.along));
        match self.script {
            ScriptKind::Press => Script::Press {
                start_m,
                direction,
                depth_m: self.depth_m,
                speed_m_per_s: self.speed_m_per_s,
                hold_s: self.hold_s,
            },
            ScriptKind::Stroke => Script::Stroke {
                start_m,
                direction,
                depth_m: self.depth_m,
                along,
                length_m: self.length_m,
                speed_m_per_s: self.speed_m_per_s,
            },
            ScriptKind::Poke => Script::Poke {
                start_m,
                direction,
                amplitude_m: self.amplitude_m,
                frequency_hz: self.frequency_hz,
                cycles: self.cycles,
            },
        }
    }

    /// The device-to-scene transform these flags describe.
    ///
    /// # Errors
    /// [`CliError::Device`] for bad axes, a bad rotation or non-positive scales.
    pub fn transform(&self) -> Result<DeviceTransform, CliError> {
        let rotation = match (&self.rotation, &self.axes) {
            (Some(_), Some(_)) => {
                return Err(CliError::Invalid(
                    "give --axes or --rotation, not both".to_owned(),
                ));
            }
            (Some(r), None) => {
                let v: Vec<f64> = r
                    .split(',')
                    .map(|x| x.trim().parse::<f64>())
                    .collect::<Result<_, _>>()
                    .map_err(|e| CliError::Invalid(format!("--rotation {r:?}: {e}")))?;
                if v.len() != 9 {
                    return Err(CliError::Invalid(format!(
                        "--rotation needs 9 numbers (row-major 3x3), got {}",
                        v.len()
                    )));
                }
                [[v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]]]
            }
            (None, Some(a)) => DeviceTransform::parse_axes(a)?,
            (None, None) if self.driver == Driver::Hapticmaster => {
                DeviceTransform::parse_axes("y,z,x")?
            }
            (None, None) => DeviceTransform::IDENTITY.rotation,
        };
        let t = DeviceTransform {
            rotation,
            scale: self.scale,
            offset_m: self.offset_m,
            force_scale: self.force_scale,
        };
        t.validate()?;
        Ok(t)
    }

    /// Builds the driver (connecting to hardware drivers), seen through the transform.
    ///
    /// # Errors
    /// [`CliError`] when a flag is missing or the device cannot be reached.
    pub fn device(&self) -> Result<Box<dyn HapticDevice>, CliError> {
        self.device_for(0, 1)
    }

    /// [`Self::device`] of tool `k` of `n` (the sim driver plays [`Self::sim_script_for`]).
    fn device_for(&self, k: usize, n: usize) -> Result<Box<dyn HapticDevice>, CliError> {
        let spec = self.spec();
        spec.validate()?;
        let t = self.transform()?;
        let cap = |mut d: DeviceSpec| {
            if let Some(m) = self.max_force_n {
                d.max_force_n = d.max_force_n.min(m);
            }
            d
        };
        Ok(match self.driver {
            Driver::Sim => Box::new(Transformed::new(
                SimProbe::new(self.sim_script_for(k, n), spec)?,
                t,
            )?),
            Driver::Replay => {
                let path = self.replay.as_ref().ok_or_else(|| {
                    CliError::Invalid("--driver replay needs --replay FILE".to_owned())
                })?;
                Box::new(Transformed::new(
                    ReplayDevice::new(Trajectory::from_path(path)?, spec)?,
                    t,
                )?)
            }
            Driver::Hapticmaster => {
                let mut p = HapticMasterParams::new(self.hm_addr);
                p.exit_state = match self.hm_exit_state {
                    ExitStateArg::Stop => ExitState::Stop,
                    ExitStateArg::Off => ExitState::Off,
                };
                p.max_force_n = cap(crate::hapticmaster::spec(p.max_force_n)).max_force_n;
                Box::new(Transformed::new(HapticMaster::connect(p)?, t)?)
            }
            Driver::Serial => {
                let path = self.serial_port.as_deref().ok_or_else(|| {
                    CliError::Invalid("--driver serial needs --serial-port PATH".to_owned())
                })?;
                let params = SerialParams {
                    watchdog_ms: self.device_watchdog_ms,
                    rate_hz: self.rate_hz.round().clamp(1.0, 65_535.0) as u16,
                    ..SerialParams::default()
                };
                Box::new(Transformed::new(
                    Capped::new(SerialDevice::open_path(path, self.baud, params)?, cap),
                    t,
                )?)
            }
            Driver::Openhaptics => self.openhaptics(t, cap)?,
        })
    }

    #[cfg(feature = "openhaptics")]
    fn openhaptics(
        &self,
        t: DeviceTransform,
        cap: impl Fn(DeviceSpec) -> DeviceSpec,
    ) -> Result<Box<dyn HapticDevice>, CliError> {
        use crate::openhaptics::{HdApi, OpenHapticsDevice};
        let dev = OpenHapticsDevice::open(HdApi::load(self.hd_library.as_deref())?)?;
        Ok(Box::new(Transformed::new(Capped::new(dev, cap), t)?))
    }

    #[cfg(not(feature = "openhaptics"))]
    fn openhaptics(
        &self,
        _t: DeviceTransform,
        _cap: impl Fn(DeviceSpec) -> DeviceSpec,
    ) -> Result<Box<dyn HapticDevice>, CliError> {
        Err(CliError::Invalid(
            "this haptic-bridge was built without OpenHaptics support: rebuild with \
             `cargo build --release -p haptic-bridge --features openhaptics`"
                .to_owned(),
        ))
    }

    /// Validates the flags and builds the device and configuration of a one-tool bridge.
    ///
    /// # Errors
    /// [`CliError`] saying which flag is wrong; [`CliError::Invalid`] when `--tool` is
    /// repeated (use [`Self::setups`]).
    pub fn setup(&self) -> Result<Setup, CliError> {
        match self.tool.as_slice() {
            [tool] => self.setup_for(0, 1, tool),
            _ => Err(CliError::Invalid(
                "several --tool flags: build them with Args::setups".to_owned(),
            )),
        }
    }

    /// One [`Setup`] per `--tool` (one without the flag), in the order given: each its own
    /// device (tool `k` of `n` plays [`Self::sim_script_for`]) and configuration; with several
    /// tools a `--record FILE` is written per tool as `FILE` with `-TOOL` before its extension.
    ///
    /// # Errors
    /// [`CliError`] as [`Self::setup`]; [`CliError::Invalid`] for more than one tool with a
    /// driver other than `sim`, more than [`MAX_SIM_TOOLS`] tools, an empty or repeated id.
    pub fn setups(&self) -> Result<Vec<Setup>, CliError> {
        let n = self.tool.len();
        if n > 1 {
            if self.driver != Driver::Sim {
                return Err(CliError::Invalid(format!(
                    "--tool given {n} times: one process drives several tools with --driver sim \
                     only; run one haptic-bridge per device"
                )));
            }
            if n > MAX_SIM_TOOLS {
                return Err(CliError::Invalid(format!(
                    "--tool given {n} times: at most {MAX_SIM_TOOLS}"
                )));
            }
            for (k, t) in self.tool.iter().enumerate() {
                if t.is_empty() || self.tool[..k].contains(t) {
                    return Err(CliError::Invalid(format!(
                        "--tool {t:?}: several tools need distinct, non-empty ids"
                    )));
                }
            }
        }
        (0..n.max(1))
            .map(|k| self.setup_for(k, n.max(1), self.tool.get(k).map_or("", String::as_str)))
            .collect()
    }

    /// The [`Setup`] of tool `k` of `n`, named `tool`.
    fn setup_for(&self, k: usize, n: usize, tool: &str) -> Result<Setup, CliError> {
        let device = self.device_for(k, n)?;
        let spec = device.spec().clone();
        let mut config = BridgeConfig::new(&self.server, &self.session, &spec);
        config.credentials = self.credentials.clone();
        config.rate_hz = self.rate_hz;
        config.guard.period_s = 1.0 / self.rate_hz;
        config.guard.passivity.mode = match self.passivity {
            PassivityArg::Off => PassivityMode::Off,
            PassivityArg::Observe => PassivityMode::Observe,
            PassivityArg::Control => PassivityMode::Control,
        };
        let rearm_button = (self.rearm == RearmArg::Key).then(RearmButton::new);
        config.rearm = match &rearm_button {
            Some(b) => RearmMode::Operator(b.clone()),
            None => RearmMode::Auto,
        };
        config.deadband = self.deadband;
        tool.clone_into(&mut config.tool_id);
        let delay = match &self.fault_delay_ms {
            None => None,
            Some(text) => {
                let v: Vec<u64> = text
                    .split(',')
                    .map(|x| x.trim().parse::<u64>())
                    .collect::<Result<_, _>>()
                    .map_err(|e| CliError::Invalid(format!("--fault-delay-ms {text:?}: {e}")))?;
                match v.as_slice() {
                    [a, b] => Some((a * 1_000, b * 1_000)),
                    [a] => Some((a * 1_000, a * 1_000)),
                    _ => {
                        return Err(CliError::Invalid(format!(
                            "--fault-delay-ms takes MIN,MAX, got {text:?}"
                        )));
                    }
                }
            }
        };
        if self.fault_drop > 0.0 || delay.is_some() {
            let (lo, hi) = delay.unwrap_or((0, 0));
            config.fault = Some(FaultInjection {
                drop_fraction: self.fault_drop,
                delay_min_us: lo,
                delay_max_us: hi,
                seed: self.fault_seed,
            });
        }
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
            record_path: self.record.as_deref().map(|p| {
                if n > 1 {
                    tool_file(p, tool)
                } else {
                    p.to_owned()
                }
            }),
            json: self.json,
            rearm_button,
        })
    }
}

/// `path` with `-TOOL` before its extension (`press.mcap` -> `press-left.mcap`).
fn tool_file(path: &std::path::Path, tool: &str) -> PathBuf {
    let stem = path.file_stem().unwrap_or_default().to_string_lossy();
    let name = match path.extension() {
        Some(ext) => format!("{stem}-{tool}.{}", ext.to_string_lossy()),
        None => format!("{stem}-{tool}"),
    };
    path.with_file_name(name)
}

/// A driver whose spec's force limit is lowered by the operator (`--max-force-n`).
struct Capped<D> {
    inner: D,
    spec: DeviceSpec,
}

impl<D: HapticDevice> Capped<D> {
    fn new(inner: D, cap: impl Fn(DeviceSpec) -> DeviceSpec) -> Self {
        let spec = cap(inner.spec().clone());
        Self { inner, spec }
    }
}

impl<D: HapticDevice> HapticDevice for Capped<D> {
    fn spec(&self) -> &DeviceSpec {
        &self.spec
    }
    fn read(&mut self, now_us: u64) -> Result<crate::device::DeviceState, DeviceError> {
        self.inner.read(now_us)
    }
    fn write_force(&mut self, force_n: [f64; 3]) -> Result<(), DeviceError> {
        self.inner.write_force(force_n)
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
        assert!(matches!(s.config.rearm, RearmMode::Operator(_)) && s.rearm_button.is_some());
        assert!(s.config.fault.is_none() && s.config.deadband.is_none());
        assert!(s.device.press_axis().is_some());
        assert!(s.config.max_duration.is_none() && !s.config.record && !s.json);
        assert_eq!(s.config.tool_id, "", "the default tool");
    }

    #[test]
    fn the_tool_flag_names_the_tool_and_bad_ids_are_refused() {
        let args = |tool: &str| {
            Args::try_parse_from([
                "haptic-bridge",
                "--server",
                "http://127.0.0.1:1",
                "--session",
                "s",
                "--tool",
                tool,
            ])
            .unwrap()
        };
        assert_eq!(args("left").setup().unwrap().config.tool_id, "left");
        let e = args("a b").setup().err().unwrap().to_string();
        assert!(e.contains("tool id"), "{e}");
        assert!(args(&"x".repeat(65)).setup().is_err());
    }

    #[test]
    fn a_repeated_tool_flag_drives_one_simulated_arm_per_tool_turned_about_z() {
        let args = |extra: &[&str]| {
            let mut v = vec![
                "haptic-bridge",
                "--server",
                "http://127.0.0.1:1",
                "--session",
                "s",
            ];
            v.extend_from_slice(extra);
            Args::try_parse_from(v).unwrap()
        };
        let a = args(&[
            "--tool",
            "left",
            "--tool",
            "right",
            "--record",
            "out/p.mcap",
        ]);
        let s = a.setups().unwrap();
        assert_eq!(s.len(), 2);
        assert_eq!(
            (s[0].config.tool_id.as_str(), s[1].config.tool_id.as_str()),
            ("left", "right")
        );
        let paths: Vec<_> = s.iter().map(|s| s.record_path.clone().unwrap()).collect();
        assert_eq!(
            paths,
            [
                PathBuf::from("out/p-left.mcap"),
                PathBuf::from("out/p-right.mcap")
            ]
        );
        // Tool 1 of 2 presses the mirror point (turned 180 degrees about z), towards the axis.
        let Script::Press {
            start_m, direction, ..
        } = a.sim_script_for(1, 2)
        else {
            panic!("a press")
        };
        let near = |u: [f64; 3], v: [f64; 3]| (0..3).all(|i| (u[i] - v[i]).abs() < 1e-15);
        assert!(near(start_m, [-0.014, 0.0, -0.005]) && near(direction, [1.0, 0.0, 0.0]));
        assert_eq!(a.sim_script_for(0, 2), a.sim_script());
        assert!(a.setup().is_err(), "setup() builds one tool only");
        // Refusals: duplicates, empty ids among several, a hardware driver, too many.
        for (extra, says) in [
            (&["--tool", "a", "--tool", "a"][..], "distinct"),
            (&["--tool", "a", "--tool", ""][..], "distinct"),
            (
                &["--tool", "a", "--tool", "b", "--driver", "serial"][..],
                "--driver sim",
            ),
            (
                &[
                    "--tool", "a", "--tool", "b", "--tool", "c", "--tool", "d", "--tool", "e",
                ][..],
                "at most 4",
            ),
        ] {
            let e = args(extra).setups().err().unwrap().to_string();
            assert!(e.contains(says), "{extra:?}: {e}");
        }
        assert_eq!(
            args(&[]).setups().unwrap().len(),
            1,
            "no flag: the default tool"
        );
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
