//! The `hapticmaster` driver: the Moog/FCS HapticMaster's TCP text protocol, spoken natively
//! (devices.md section 1.1; \[S2\] pyHapticMaster, \[S3\] lab code using HapticAPI), and an
//! [`Emulator`] of the device side for tests.
//!
//! Wire format (both ways): a 4-byte big-endian length, 4 zero bytes, then that many bytes of
//! ASCII text. One request, one reply. Commands used: `get position_calibrated`, `set state
//! init|force|stop|off`, `get state`, `remove all`, `create biasforce NAME`, `set NAME force
//! [x,y,z]`, `set NAME enable|disable`, `get modelpos; get modelvel` (batched with `;`, replies
//! `;`-separated). Vectors are `[x,y,z]`; errors contain `--- ERROR`. SI units, z vertical.
//!
//! The HapticMaster is an admittance device with its own 2.5 kHz controller: the host does not
//! close a force loop, it updates a **bias force** effect that stays in force until the next
//! update (what the lab code does with `set ballForce force [..]`, \[S3\]).
//!
//! State machine ([`HapticMaster::connect`]): connect (TCP_NODELAY) -> if `get
//! position_calibrated` is not `true`: `set state init`, then poll `get state` until `stop`
//! (calibration done) -> `remove all` (never keep an effect with a stale target, devices.md
//! S13) -> `create biasforce NAME`, force zero, enable -> `set state force`. Every exit path
//! ([`HapticDevice::safe_stop`], also from `Drop`, so an error or a panic that unwinds still
//! gets it) sends: bias force `[0,0,0]`, `set NAME disable`, `remove all`, then `set state
//! stop` (the lab code's sequence, \[S3\]; `set state off` with [`ExitState::Off`]); the
//! `haptic-bridge` binary takes this path on SIGINT, SIGTERM and SIGHUP too. A bridge killed
//! outright (SIGKILL, power loss) cannot do this: the device then keeps the last bias force,
//! which the guard's scene limits keep small (the HapticMaster has no host watchdog in its
//! public protocol).
//!
//! Per device tick: one `get modelpos; get modelvel` round trip ([`HapticDevice::read`]) and one
//! `set NAME force [..]` ([`HapticDevice::write_force`]). Each waits at most
//! [`HapticMasterParams::io_timeout`]; a timeout is a [`DeviceError::Comm`] (the bridge zeroes
//! the force, then gives up after 20 ms of failures). A reply that came too late would answer
//! the next command, so after any I/O error the connection is dropped and the next command
//! reconnects first (the device keeps its state and effects across connections).
//!
//! Neighbours: implements [`crate::device::HapticDevice`]; its poses are in the device frame,
//! [`crate::transform`] maps them to the scene (`--axes y,z,x` as HAPI does).

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use crate::device::{DeviceError, DeviceSpec, DeviceState, HapticDevice, vec3};
use crate::sim::Script;

/// The HapticMaster's TCP port in public code (\[S2\]).
pub const DEFAULT_PORT: u16 = 7654;
/// Largest reply accepted, bytes (replies are short text lines).
pub const MAX_MESSAGE_BYTES: usize = 64 * 1024;
/// Commands the emulator keeps in [`EmulatorLog::recent_commands`].
pub const EMULATOR_RECENT_COMMANDS: usize = 64;

/// Encodes one message: 4-byte big-endian length, 4 zero bytes, the text.
pub fn encode(text: &str) -> Vec<u8> {
    let mut out = Vec::with_capacity(8 + text.len());
    out.extend_from_slice(&(text.len() as u32).to_be_bytes());
    out.extend_from_slice(&[0; 4]);
    out.extend_from_slice(text.as_bytes());
    out
}

/// Reads one message from `r` (blocking, within the stream's timeouts).
///
/// # Errors
/// I/O errors; `InvalidData` for a length above [`MAX_MESSAGE_BYTES`] or non-UTF-8 text.
pub fn read_message(r: &mut impl Read) -> std::io::Result<String> {
    let mut header = [0u8; 8];
    r.read_exact(&mut header)?;
    let len = u32::from_be_bytes([header[0], header[1], header[2], header[3]]) as usize;
    if len > MAX_MESSAGE_BYTES {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("message of {len} bytes"),
        ));
    }
    let mut body = vec![0u8; len];
    r.read_exact(&mut body)?;
    String::from_utf8(body)
        .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e.to_string()))
}

/// Parses a reply vector `[x,y,z]` (whitespace allowed).
///
/// # Errors
/// [`DeviceError::Comm`] quoting the text.
pub fn parse_vector(text: &str) -> Result<[f64; 3], DeviceError> {
    let bad = || DeviceError::Comm(format!("HapticMaster: expected [x,y,z], got {text:?}"));
    let inner = text
        .trim()
        .strip_prefix('[')
        .and_then(|t| t.strip_suffix(']'))
        .ok_or_else(bad)?;
    let mut v = [0.0; 3];
    let mut n = 0;
    for (i, part) in inner.split(',').enumerate() {
        if i >= 3 {
            return Err(bad());
        }
        v[i] = part.trim().parse().map_err(|_| bad())?;
        n += 1;
    }
    if n != 3 || !vec3::is_finite(v) {
        return Err(bad());
    }
    Ok(v)
}

fn format_vector(v: [f64; 3]) -> String {
    format!("[{:.6},{:.6},{:.6}]", v[0], v[1], v[2])
}

/// The state the device is left in on exit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ExitState {
    /// `set state stop`: the arm holds its position (the lab code's choice, \[S3\]).
    #[default]
    Stop,
    /// `set state off`.
    Off,
}

/// Connection parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct HapticMasterParams {
    /// Device address (`192.168.0.25:7654` in lab code).
    pub addr: SocketAddr,
    /// Name of the bias force effect the driver creates.
    pub effect_name: String,
    /// State on exit.
    pub exit_state: ExitState,
    /// Longest wait for one reply during the servo loop.
    pub io_timeout: Duration,
    /// Longest wait for connecting and for calibration (`set state init` until `stop`).
    pub setup_timeout: Duration,
    /// Force clamp of the device spec, N (research code clamps the bias force at 100 N, \[S3\]).
    pub max_force_n: f64,
}

impl HapticMasterParams {
    /// Defaults for `addr`: effect `bridgeForce`, exit in `stop`, 20 ms I/O timeout (the
    /// bridge's device-fault limit), 30 s set-up timeout, 100 N clamp.
    pub fn new(addr: SocketAddr) -> Self {
        Self {
            addr,
            effect_name: "bridgeForce".to_owned(),
            exit_state: ExitState::Stop,
            io_timeout: Duration::from_millis(20),
            setup_timeout: Duration::from_secs(30),
            max_force_n: 100.0,
        }
    }
}

/// The HapticMaster spec: 100 N clamp, 5 kN/m stiffness for the slew limit (unverified: the
/// datasheet is not public, devices.md section 6), the bounding box of the vendor example's
/// cylindrical workspace (r 0.28-0.64 m, phi +-0.5 rad, z +-0.2 m), a 1 kHz host loop, 50 N s/m
/// damping.
pub fn spec(max_force_n: f64) -> DeviceSpec {
    DeviceSpec {
        name: "hapticmaster".to_owned(),
        // Position in, force out (an admittance-controlled 3-DOF arm; the gimbal is passive).
        sensed_degrees_of_freedom: 3,
        actuated_degrees_of_freedom: 3,
        max_force_n,
        // No rating is public (devices.md section 6): the clamp is not lowered by S8.
        max_continuous_force_n: max_force_n,
        max_stiffness_n_per_m: 5_000.0,
        workspace_min_m: [0.28 * 0.5f64.cos(), -0.64 * 0.5f64.sin(), -0.2],
        workspace_max_m: [0.64, 0.64 * 0.5f64.sin(), 0.2],
        rate_hz: 1000.0,
        max_damping_n_s_per_m: 50.0,
    }
}

/// A connected, calibrated HapticMaster in force state (module documentation).
pub struct HapticMaster {
    stream: TcpStream,
    /// An I/O error left the request/reply stream out of step: reconnect before the next command.
    broken: bool,
    params: HapticMasterParams,
    spec: DeviceSpec,
    stopped: bool,
    /// Commands sent (for rate measurements).
    commands: u64,
}

impl HapticMaster {
    /// Connects, calibrates if needed, creates the bias force effect and enters force state.
    ///
    /// # Errors
    /// [`DeviceError::Comm`] naming the step that failed (connect, calibration timeout, an
    /// `--- ERROR` reply).
    pub fn connect(params: HapticMasterParams) -> Result<Self, DeviceError> {
        let stream = TcpStream::connect_timeout(&params.addr, params.setup_timeout)
            .map_err(|e| DeviceError::Comm(format!("HapticMaster at {}: {e}", params.addr)))?;
        stream
            .set_nodelay(true)
            .and_then(|()| stream.set_read_timeout(Some(params.setup_timeout)))
            .and_then(|()| stream.set_write_timeout(Some(params.setup_timeout)))
            .map_err(|e| DeviceError::Comm(format!("HapticMaster socket options: {e}")))?;
        let spec = spec(params.max_force_n);
        let mut hm = Self {
            stream,
            broken: false,
            params,
            spec,
            stopped: false,
            commands: 0,
        };
        if hm.command("get position_calibrated")?.trim() != "true" {
            hm.command("set state init")?;
            let deadline = Instant::now() + hm.params.setup_timeout;
            loop {
                let state = hm.command("get state")?;
                if state.trim() == "stop" {
                    break;
                }
                if Instant::now() >= deadline {
                    return Err(DeviceError::Comm(format!(
                        "HapticMaster calibration did not finish within {:?} (state {state:?})",
                        hm.params.setup_timeout
                    )));
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        }
        let name = hm.params.effect_name.clone();
        hm.command("remove all")?;
        hm.command(&format!("create biasforce {name}"))?;
        hm.command(&format!("set {name} force [0,0,0]"))?;
        hm.command(&format!("set {name} enable"))?;
        hm.command("set state force")?;
        let t = Some(hm.params.io_timeout);
        hm.stream
            .set_read_timeout(t)
            .and_then(|()| hm.stream.set_write_timeout(t))
            .map_err(|e| DeviceError::Comm(format!("HapticMaster socket options: {e}")))?;
        Ok(hm)
    }

    /// Commands sent so far.
    pub fn commands(&self) -> u64 {
        self.commands
    }

    /// Sends one command and returns the reply.
    ///
    /// # Errors
    /// [`DeviceError::Comm`] on I/O failure or an `--- ERROR` reply.
    pub fn command(&mut self, text: &str) -> Result<String, DeviceError> {
        if self.broken {
            let t = self.params.io_timeout;
            let s = TcpStream::connect_timeout(&self.params.addr, t)
                .and_then(|s| {
                    s.set_nodelay(true)?;
                    s.set_read_timeout(Some(t))?;
                    s.set_write_timeout(Some(t))?;
                    Ok(s)
                })
                .map_err(|e| {
                    DeviceError::Comm(format!(
                        "HapticMaster reconnect to {}: {e}",
                        self.params.addr
                    ))
                })?;
            self.stream = s;
            self.broken = false;
        }
        self.commands += 1;
        let io = self
            .stream
            .write_all(&encode(text))
            .and_then(|()| read_message(&mut self.stream));
        if io.is_err() {
            self.broken = true;
            let _ = self.stream.shutdown(std::net::Shutdown::Both);
        }
        io.map_err(|e| DeviceError::Comm(format!("HapticMaster `{text}`: {e}")))
            .and_then(|reply| {
                if reply.contains("--- ERROR") {
                    Err(DeviceError::Comm(format!(
                        "HapticMaster `{text}` answered {reply:?}"
                    )))
                } else {
                    Ok(reply)
                }
            })
    }
}

impl HapticDevice for HapticMaster {
    fn spec(&self) -> &DeviceSpec {
        &self.spec
    }

    fn read(&mut self, now_us: u64) -> Result<DeviceState, DeviceError> {
        let reply = self.command("get modelpos; get modelvel")?;
        let mut parts = reply.split(';');
        let p = parse_vector(parts.next().unwrap_or(""))?;
        let v = parse_vector(parts.next().unwrap_or(""))?;
        Ok(DeviceState {
            time_us: now_us,
            position_m: p,
            velocity_m_per_s: v,
            motor_temperature: None,
        })
    }

    fn write_force(&mut self, force_n: [f64; 3]) -> Result<(), DeviceError> {
        if !vec3::is_finite(force_n) {
            return Err(DeviceError::NonFiniteForce(force_n));
        }
        let name = &self.params.effect_name;
        let cmd = format!("set {name} force {}", format_vector(force_n));
        self.command(&cmd).map(|_| ())
    }

    fn finished(&self, _now_us: u64) -> bool {
        false
    }

    fn set_output_enabled(&mut self, on: bool) -> Result<(), DeviceError> {
        let name = self.params.effect_name.clone();
        if !on {
            self.command(&format!("set {name} force [0,0,0]"))?;
        }
        let word = if on { "enable" } else { "disable" };
        self.command(&format!("set {name} {word}")).map(|_| ())
    }

    fn safe_stop(&mut self) {
        if self.stopped {
            return;
        }
        self.stopped = true;
        // The exit sequence matters more than the loop's latency: wait longer for each reply.
        self.params.io_timeout = self.params.io_timeout.max(Duration::from_millis(500));
        let _ = self.stream.set_read_timeout(Some(self.params.io_timeout));
        let name = self.params.effect_name.clone();
        let exit = match self.params.exit_state {
            ExitState::Stop => "set state stop",
            ExitState::Off => "set state off",
        };
        // Best effort, each step on its own: one failing must not skip the others.
        for cmd in [
            format!("set {name} force [0,0,0]"),
            format!("set {name} disable"),
            "remove all".to_owned(),
            exit.to_owned(),
        ] {
            let _ = self.command(&cmd);
        }
    }
}

impl Drop for HapticMaster {
    fn drop(&mut self) {
        self.safe_stop();
    }
}

/// What the emulator saw, for tests.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EmulatorLog {
    /// Every `set state` value, in order.
    pub states: Vec<String>,
    /// Bias force the device renders after each command that changed it: (seconds since the
    /// emulator started, force in N). Zero while the effect is disabled or the state is not
    /// `force`.
    pub rendered: Vec<(f64, [f64; 3])>,
    /// Effects alive after the last command.
    pub effects: Vec<String>,
    /// Connections accepted.
    pub connections: u64,
    /// The last [`EMULATOR_RECENT_COMMANDS`] commands received, oldest first (a batch such as
    /// `get modelpos; get modelvel` counts as its commands).
    pub recent_commands: std::collections::VecDeque<String>,
    /// For each connection that ended (the host closed it or it broke), the number of commands
    /// answered by then: a host's exit sequence came before its connection closed when the
    /// last entry equals the total.
    pub closed_after_commands: Vec<u64>,
}

/// A HapticMaster device side on `127.0.0.1` (module documentation): calibration takes
/// `calibration` after `set state init`; the model position follows a [`Script`] (a hand
/// holding the end effector) from the moment the state becomes `force`.
pub struct Emulator {
    addr: SocketAddr,
    slow_reply_ms: Arc<AtomicU64>,
    log: Arc<Mutex<EmulatorLog>>,
    stop: Arc<AtomicBool>,
    commands: Arc<AtomicU64>,
    thread: Option<std::thread::JoinHandle<()>>,
}

#[derive(Debug)]
struct EmState {
    calibrated: bool,
    init_since: Option<Instant>,
    state: String,
    effects: Vec<(String, [f64; 3], bool)>,
    force_since: Option<Instant>,
    calibration: Duration,
}

impl Emulator {
    /// Starts the emulator on `127.0.0.1:0`.
    ///
    /// # Errors
    /// The listener cannot be bound.
    pub fn spawn(script: Script, calibration: Duration) -> std::io::Result<Self> {
        let listener = TcpListener::bind("127.0.0.1:0")?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        let log = Arc::new(Mutex::new(EmulatorLog::default()));
        let stop = Arc::new(AtomicBool::new(false));
        let commands = Arc::new(AtomicU64::new(0));
        let slow_reply_ms = Arc::new(AtomicU64::new(0));
        let (l2, s2, c2, d2) = (
            log.clone(),
            stop.clone(),
            commands.clone(),
            slow_reply_ms.clone(),
        );
        let thread = std::thread::Builder::new()
            .name("hm-emulator".into())
            .spawn(move || emulate(listener, script, calibration, l2, s2, c2, d2))?;
        Ok(Self {
            addr,
            slow_reply_ms,
            log,
            stop,
            commands,
            thread: Some(thread),
        })
    }

    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// A copy of the log.
    pub fn log(&self) -> EmulatorLog {
        self.log
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Delays the reply to the next request by `ms` milliseconds (a stalled device or network).
    pub fn delay_next_reply(&self, ms: u64) {
        self.slow_reply_ms.store(ms, Ordering::Release);
    }

    /// Commands answered so far.
    pub fn commands(&self) -> u64 {
        self.commands.load(Ordering::Acquire)
    }
}

impl Drop for Emulator {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn emulate(
    listener: TcpListener,
    script: Script,
    calibration: Duration,
    log: Arc<Mutex<EmulatorLog>>,
    stop: Arc<AtomicBool>,
    commands: Arc<AtomicU64>,
    slow_reply_ms: Arc<AtomicU64>,
) {
    let started = Instant::now();
    let mut st = EmState {
        calibrated: false,
        init_since: None,
        state: "off".to_owned(),
        effects: Vec::new(),
        force_since: None,
        calibration,
    };
    while !stop.load(Ordering::Acquire) {
        let Ok((mut conn, _)) = listener.accept() else {
            std::thread::sleep(Duration::from_millis(2));
            continue;
        };
        log.lock()
            .unwrap_or_else(PoisonError::into_inner)
            .connections += 1;
        let _ = conn.set_nonblocking(false);
        let _ = conn.set_nodelay(true);
        let _ = conn.set_read_timeout(Some(Duration::from_millis(50)));
        loop {
            if stop.load(Ordering::Acquire) {
                return;
            }
            let text = match read_message(&mut conn) {
                Ok(t) => t,
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    continue;
                }
                Err(_) => break, // the host went away: keep the state, accept the next one
            };
            let reply = text
                .split(';')
                .map(|c| {
                    commands.fetch_add(1, Ordering::AcqRel);
                    answer(c.trim(), &mut st, &script, started, &log)
                })
                .collect::<Vec<_>>()
                .join(";");
            let delay = slow_reply_ms.swap(0, Ordering::AcqRel);
            if delay > 0 {
                std::thread::sleep(Duration::from_millis(delay));
            }
            if conn.write_all(&encode(&reply)).is_err() {
                break;
            }
        }
        log.lock()
            .unwrap_or_else(PoisonError::into_inner)
            .closed_after_commands
            .push(commands.load(Ordering::Acquire));
    }
}

fn rendered_force(st: &EmState) -> [f64; 3] {
    if st.state != "force" {
        return [0.0; 3];
    }
    st.effects
        .iter()
        .filter(|(_, _, on)| *on)
        .fold([0.0; 3], |acc, (_, f, _)| vec3::axpy(acc, 1.0, *f))
}

fn answer(
    cmd: &str,
    st: &mut EmState,
    script: &Script,
    started: Instant,
    log: &Mutex<EmulatorLog>,
) -> String {
    let before = rendered_force(st);
    let words: Vec<&str> = cmd.split_whitespace().collect();
    let reply = match words.as_slice() {
        ["get", "position_calibrated"] => st.calibrated.to_string(),
        ["get", "state"] => st.state.clone(),
        ["set", "state", s] => {
            let s = s.to_string();
            log.lock()
                .unwrap_or_else(PoisonError::into_inner)
                .states
                .push(s.clone());
            match s.as_str() {
                "init" => {
                    st.init_since = Some(Instant::now());
                    st.state = "init".into();
                    "\"State set\"".into()
                }
                "force" if !st.calibrated => "--- ERROR: not calibrated".into(),
                "force" => {
                    st.force_since = Some(Instant::now());
                    st.state = s;
                    "\"State set\"".into()
                }
                "stop" | "off" | "home" | "position" => {
                    st.state = s;
                    st.force_since = None;
                    "\"State set\"".into()
                }
                _ => format!("--- ERROR: unknown state {s}"),
            }
        }
        ["get", "modelpos"] | ["get", "modelvel"] => {
            let t = st.force_since.map_or(0.0, |t| t.elapsed().as_secs_f64());
            let (p, v) = script.kinematics(t);
            format_vector(if words[1] == "modelpos" { p } else { v })
        }
        ["get", "measforce"] => format_vector(rendered_force(st)),
        ["remove", "all"] => {
            st.effects.clear();
            "\"Effects removed\"".into()
        }
        ["create", "biasforce", name] => {
            st.effects.push((name.to_string(), [0.0; 3], false));
            format!("\"Effect {name} created\"")
        }
        ["set", name, "force", rest @ ..] => match parse_vector(&rest.join("")) {
            Ok(f) => match st.effects.iter_mut().find(|(n, _, _)| n == name) {
                Some(e) => {
                    e.1 = f;
                    "\"Effect's force set\"".into()
                }
                None => format!("--- ERROR: no effect {name}"),
            },
            Err(_) => "--- ERROR: bad vector".into(),
        },
        ["set", name, w @ ("enable" | "disable")] => {
            match st.effects.iter_mut().find(|(n, _, _)| n == name) {
                Some(e) => {
                    e.2 = *w == "enable";
                    "\"Effect enabled\"".into()
                }
                None => format!("--- ERROR: no effect {name}"),
            }
        }
        _ => format!("--- ERROR: unknown command {cmd:?}"),
    };
    // Calibration completes `calibration` after `set state init` (checked on every command).
    if st.state == "init"
        && let Some(t) = st.init_since
        && t.elapsed() >= st.calibration
    {
        st.calibrated = true;
        st.state = "stop".into();
        st.init_since = None;
    }
    let after = rendered_force(st);
    let mut l = log.lock().unwrap_or_else(PoisonError::into_inner);
    if l.recent_commands.len() == EMULATOR_RECENT_COMMANDS {
        l.recent_commands.pop_front();
    }
    l.recent_commands.push_back(cmd.to_owned());
    if after != before {
        l.rendered.push((started.elapsed().as_secs_f64(), after));
    }
    l.effects = st.effects.iter().map(|(n, _, _)| n.clone()).collect();
    reply
}
