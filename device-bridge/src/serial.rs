//! The `serial` driver: an arm speaking HBP/1 ([`crate::hbp`], specified in
//! `docs/serial-protocol.md`) over a serial port (`serialport`, no default features), and the
//! [`SerialEmulator`], a device-side thread for pseudo-terminal tests and demos.
//!
//! Host side ([`SerialDevice`]): `HELLO` (rate, device watchdog) then wait for `CAPS`, whose
//! limits and workspace make the device spec; then per tick: read every byte available (the
//! port's timeout is zero, so a read never blocks), keep the newest `STATE`, and send one
//! `FORCE` with the next sequence number and the enable flag. Host rules (the spec's "Host
//! rules"): no valid `STATE` for 20 ms, more than 1 % corrupted frames (CRC or COBS) over a
//! second (with at least 100 frames), a `FAULT` frame, or end of file are device errors (the bridge zeroes the force
//! and gives up after 20 ms). A `CAPS` after the handshake means the device rebooted: its
//! outputs are disabled, so the driver reports an error rather than pretend.
//!
//! Neighbours: [`crate::hbp`] (codec, device rules), [`crate::device::HapticDevice`].

use std::io::{ErrorKind, Read, Write};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use crate::clock::{Clock, MonotonicClock};
use crate::device::{DeviceError, DeviceSpec, DeviceState, HapticDevice, vec3};
use crate::hbp::{self, Caps, DeviceCore, Force, Frame, FrameDecoder, Message};
use crate::sim::Script;

/// No valid STATE for this long is a device error, us (devices.md section 3.4, host rules).
pub const STATE_TIMEOUT_US: u64 = 20_000;

/// Serial driver parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SerialParams {
    /// Host loop rate announced in HELLO, Hz.
    pub rate_hz: u16,
    /// Device watchdog asked for in HELLO, ms (2..=100; default 20, devices.md S1).
    pub watchdog_ms: u16,
    /// Longest wait for CAPS after HELLO.
    pub handshake_timeout: Duration,
}

impl Default for SerialParams {
    fn default() -> Self {
        Self {
            rate_hz: 1000,
            watchdog_ms: 20,
            handshake_timeout: Duration::from_millis(500),
        }
    }
}

/// The device spec from a CAPS message (device frame, SI).
pub fn spec_from_caps(caps: &Caps) -> DeviceSpec {
    let name = String::from_utf8_lossy(&caps.model)
        .trim_end_matches('\0')
        .to_owned();
    DeviceSpec {
        name: if name.is_empty() {
            "serial".into()
        } else {
            name
        },
        sensed_degrees_of_freedom: u32::from(caps.dof_in),
        actuated_degrees_of_freedom: u32::from(caps.dof_out),
        max_force_n: f64::from(caps.peak_force_n),
        max_continuous_force_n: f64::from(caps.continuous_force_n),
        max_stiffness_n_per_m: f64::from(caps.max_stiffness_n_per_m),
        workspace_min_m: caps.workspace_min_m.map(f64::from),
        workspace_max_m: caps.workspace_max_m.map(f64::from),
        rate_hz: f64::from(caps.native_rate_hz.max(1)),
        max_damping_n_s_per_m: f64::from(caps.max_damping_n_s_per_m),
    }
}

/// An HBP/1 device on a byte stream (module documentation).
pub struct SerialDevice<P: Read + Write + Send> {
    port: P,
    clock: Arc<dyn Clock>,
    decoder: FrameDecoder,
    spec: DeviceSpec,
    caps: Caps,
    seq: u16,
    latest: Option<(u64, hbp::State)>,
    fault: Option<String>,
    enabled: bool,
    stopped: bool,
    window_start_us: u64,
    window_frames: u64,
    window_crc: u64,
    buf: Vec<u8>,
    out: Vec<u8>,
}

impl SerialDevice<Box<dyn serialport::SerialPort>> {
    /// Opens the serial port at `path` (`baud` 0 for a pseudo-terminal; >= 1 Mbaud for a UART,
    /// USB CDC-ACM ignores it) and runs the handshake.
    ///
    /// # Errors
    /// [`DeviceError::Comm`] when the port cannot be opened or the device does not answer.
    pub fn open_path(path: &str, baud: u32, params: SerialParams) -> Result<Self, DeviceError> {
        let port = serialport::new(path, baud)
            .timeout(Duration::ZERO)
            .open()
            .map_err(|e| DeviceError::Comm(format!("serial port {path}: {e}")))?;
        Self::open(port, Arc::new(MonotonicClock::new()), params)
    }
}

impl<P: Read + Write + Send> SerialDevice<P> {
    /// Runs the handshake on `port` (whose reads must not block: a zero or short timeout).
    ///
    /// # Errors
    /// [`DeviceError::Comm`] when no CAPS arrives within the handshake timeout.
    pub fn open(port: P, clock: Arc<dyn Clock>, params: SerialParams) -> Result<Self, DeviceError> {
        let mut d = Self {
            port,
            clock,
            decoder: FrameDecoder::new(),
            spec: DeviceSpec::sim_default(),
            caps: hbp::emulator_caps(),
            seq: 0,
            latest: None,
            fault: None,
            enabled: true,
            stopped: false,
            window_start_us: 0,
            window_frames: 0,
            window_crc: 0,
            buf: vec![0; 4096],
            out: Vec::with_capacity(2 * hbp::MAX_ENCODED),
        };
        let hello = Message::Hello {
            proto: hbp::VERSION,
            rate_hz: params.rate_hz,
            watchdog_ms: params.watchdog_ms.clamp(2, 100),
        };
        d.send(hello)?;
        let deadline = Instant::now() + params.handshake_timeout;
        loop {
            let mut caps = None;
            d.pump(|f| {
                if let Message::Caps(c) = f.msg {
                    caps = Some(c);
                }
            })?;
            if let Some(c) = caps {
                d.caps = c;
                d.spec = spec_from_caps(&c);
                d.spec.validate()?;
                return Ok(d);
            }
            if Instant::now() >= deadline {
                return Err(DeviceError::Comm(format!(
                    "serial device: no CAPS within {:?} of HELLO (not an HBP/1 device, or off?)",
                    params.handshake_timeout
                )));
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// The device's capabilities.
    pub fn caps(&self) -> &Caps {
        &self.caps
    }

    /// Decoder counters (frames, CRC errors, malformed, oversize).
    pub fn decode_stats(&self) -> hbp::DecodeStats {
        self.decoder.stats()
    }

    /// The newest STATE's status bits ([`hbp::status`]), if any.
    pub fn status(&self) -> Option<u16> {
        self.latest.map(|(_, s)| s.status)
    }

    fn send(&mut self, msg: Message) -> Result<(), DeviceError> {
        self.seq = self.seq.wrapping_add(1);
        let frame = Frame {
            seq: self.seq,
            t_us: self.clock.now_us() as u32,
            msg,
        };
        self.out.clear();
        hbp::encode(&frame, &mut self.out);
        self.port
            .write_all(&self.out)
            .and_then(|()| self.port.flush())
            .map_err(|e| DeviceError::Comm(format!("serial write: {e}")))
    }

    /// Reads every byte available and hands each valid frame to `on_frame`.
    fn pump(&mut self, mut on_frame: impl FnMut(Frame)) -> Result<(), DeviceError> {
        loop {
            match self.port.read(&mut self.buf) {
                Ok(0) => return Err(DeviceError::Comm("serial device: end of file".into())),
                Ok(n) => {
                    let bytes = &self.buf[..n];
                    self.decoder.push(bytes, &mut on_frame);
                    if n < self.buf.len() {
                        return Ok(());
                    }
                }
                Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => {
                    return Ok(());
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => return Err(DeviceError::Comm(format!("serial read: {e}"))),
            }
        }
    }
}

impl<P: Read + Write + Send> HapticDevice for SerialDevice<P> {
    fn spec(&self) -> &DeviceSpec {
        &self.spec
    }

    fn read(&mut self, now_us: u64) -> Result<DeviceState, DeviceError> {
        if let Some(f) = &self.fault {
            return Err(DeviceError::Comm(f.clone()));
        }
        let before = self.decoder.stats();
        let mut latest = self.latest;
        let mut fault = None;
        let mut rebooted = false;
        self.pump(|f| match f.msg {
            Message::State(s) => latest = Some((now_us, s)),
            Message::Fault { code, detail } => {
                fault = Some(format!("serial device FAULT code {code} detail {detail}"));
            }
            Message::Caps(_) => rebooted = true,
            _ => {}
        })?;
        self.latest = latest;
        if rebooted {
            fault = Some("serial device sent CAPS again: it rebooted (outputs disabled)".into());
        }
        // Host rule: > 1 % CRC errors over one second (at least 100 frames) is a fault.
        let after = self.decoder.stats();
        self.window_frames += after.frames - before.frames;
        // A corrupted frame fails COBS or the CRC: both count against the 1 % rule.
        self.window_crc +=
            (after.crc_errors + after.malformed) - (before.crc_errors + before.malformed);
        if now_us.saturating_sub(self.window_start_us) >= 1_000_000 {
            let total = self.window_frames + self.window_crc;
            if total >= 100 && self.window_crc * 100 > total {
                fault = Some(format!(
                    "serial link: {} CRC errors in {} frames over 1 s (> 1 %)",
                    self.window_crc, total
                ));
            }
            self.window_start_us = now_us;
            self.window_frames = 0;
            self.window_crc = 0;
        }
        if let Some(f) = fault {
            self.fault = Some(f.clone());
            return Err(DeviceError::Comm(f));
        }
        match self.latest {
            Some((t, s)) if now_us.saturating_sub(t) <= STATE_TIMEOUT_US => Ok(DeviceState {
                time_us: now_us,
                position_m: s.position_m.map(f64::from),
                velocity_m_per_s: s.velocity_m_per_s.map(f64::from),
                motor_temperature: None,
            }),
            _ => Err(DeviceError::Comm(
                "serial device: no valid STATE for 20 ms".into(),
            )),
        }
    }

    fn write_force(&mut self, force_n: [f64; 3]) -> Result<(), DeviceError> {
        if !vec3::is_finite(force_n) {
            return Err(DeviceError::NonFiniteForce(force_n));
        }
        let flags = if self.enabled && !self.stopped {
            hbp::FORCE_FLAG_ENABLE
        } else {
            0
        };
        self.send(Message::Force(Force {
            force_n: force_n.map(|x| x as f32),
            torque_n_m: [0.0; 3],
            flags,
        }))
    }

    fn finished(&self, _now_us: u64) -> bool {
        false
    }

    fn set_output_enabled(&mut self, on: bool) -> Result<(), DeviceError> {
        self.enabled = on;
        Ok(())
    }

    fn safe_stop(&mut self) {
        if self.stopped {
            return;
        }
        self.stopped = true;
        // Zero with the enable flag cleared; the device watchdog covers a lost frame.
        let _ = self.send(Message::Force(Force::default()));
    }
}

impl<P: Read + Write + Send> Drop for SerialDevice<P> {
    fn drop(&mut self) {
        self.safe_stop();
    }
}

/// Emulator faults for tests.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct EmulatorFaults {
    /// Corrupt one byte of every `n`-th STATE frame (0: never).
    pub corrupt_every: u32,
}

/// What the emulator thread reports.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SerialEmulatorLog {
    /// (us since start, force) each time the rendered force changed.
    pub rendered: Vec<(u64, [f64; 3])>,
    /// Watchdog trips.
    pub watchdog_trips: u64,
    /// FORCE frames refused.
    pub refused: u64,
    /// Frames decoded from the host.
    pub frames_in: u64,
    /// CRC errors seen from the host.
    pub crc_errors_in: u64,
}

/// An HBP/1 device on the master end of a pseudo-terminal: a thread running [`DeviceCore`] at
/// 1 kHz on the real clock (module documentation).
pub struct SerialEmulator {
    stop: Arc<AtomicBool>,
    log: Arc<Mutex<SerialEmulatorLog>>,
    ticks: Arc<AtomicU64>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl SerialEmulator {
    /// Starts the device on `port` (reads must not block: give it a zero timeout).
    ///
    /// # Errors
    /// The thread cannot be spawned.
    pub fn spawn<P: Read + Write + Send + 'static>(
        mut port: P,
        script: Script,
        faults: EmulatorFaults,
    ) -> std::io::Result<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let log = Arc::new(Mutex::new(SerialEmulatorLog::default()));
        let ticks = Arc::new(AtomicU64::new(0));
        let (s2, l2, t2) = (stop.clone(), log.clone(), ticks.clone());
        let thread = std::thread::Builder::new()
            .name("hbp-emulator".into())
            .spawn(move || {
                let clock = MonotonicClock::new();
                let mut core = DeviceCore::new(hbp::emulator_caps(), script, 0);
                let mut dec = FrameDecoder::new();
                let mut buf = vec![0u8; 4096];
                let mut out = Vec::new();
                let mut next = 0u64;
                let mut n_state = 0u32;
                let mut was_tripped = false;
                while !s2.load(Ordering::Acquire) {
                    let now = clock.now_us();
                    let mut frames = Vec::new();
                    loop {
                        match port.read(&mut buf) {
                            Ok(0) => break,
                            Ok(n) => dec.push(&buf[..n], |f| frames.push(f)),
                            Err(_) => break,
                        }
                    }
                    out.clear();
                    for f in &frames {
                        if let Some(reply) = core.on_frame(now, f) {
                            hbp::encode(&reply, &mut out);
                        }
                    }
                    let state = core.tick(now);
                    n_state += 1;
                    let start = out.len();
                    hbp::encode(&state, &mut out);
                    if faults.corrupt_every > 0 && n_state.is_multiple_of(faults.corrupt_every) {
                        // Flip a payload byte (never the terminator).
                        let k = start + (out.len() - start) / 2;
                        out[k] ^= 0x20;
                        if out[k] == 0 {
                            out[k] = 0x01;
                        }
                    }
                    if port.write_all(&out).is_err() {
                        break;
                    }
                    let _ = port.flush();
                    if core.wd_tripped() && !was_tripped {
                        l2.lock()
                            .unwrap_or_else(PoisonError::into_inner)
                            .watchdog_trips += 1;
                    }
                    was_tripped = core.wd_tripped();
                    {
                        let mut l = l2.lock().unwrap_or_else(PoisonError::into_inner);
                        l.rendered.clone_from(&core.rendered);
                        l.refused = core.refused;
                        l.frames_in = dec.stats().frames;
                        l.crc_errors_in = dec.stats().crc_errors;
                    }
                    t2.fetch_add(1, Ordering::AcqRel);
                    next += 1_000;
                    if clock.now_us() > next {
                        next = clock.now_us();
                    }
                    clock.sleep_until_us(next);
                }
            })?;
        Ok(Self {
            stop,
            log,
            ticks,
            thread: Some(thread),
        })
    }

    /// A copy of the log.
    pub fn log(&self) -> SerialEmulatorLog {
        self.log
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Device ticks run.
    pub fn ticks(&self) -> u64 {
        self.ticks.load(Ordering::Acquire)
    }

    /// Stops the thread and closes the port (the host then sees end of file or no STATE).
    pub fn stop(mut self) -> SerialEmulatorLog {
        self.halt();
        self.log()
    }

    fn halt(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for SerialEmulator {
    fn drop(&mut self) {
        self.halt();
    }
}
