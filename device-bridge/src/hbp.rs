//! HBP/1, the Haptic Bridge Protocol: the project's framed serial protocol for custom arms and
//! adapters ([`docs/serial-protocol.md`](../../docs/serial-protocol.md) is the specification a
//! firmware author implements from; devices.md section 3.4 proposed it).
//!
//! A frame is a body `ver u8 | type u8 | seq u16 | t_us u32 | payload | crc u16` (little-endian;
//! CRC-16/IBM-3740 over everything before it), COBS-encoded (the `cobs` crate) and terminated
//! by one `0x00`. Decoded bodies longer than [`MAX_BODY`] bytes are discarded. The
//! [`FrameDecoder`] resynchronises at the next zero after noise and counts what it drops.
//!
//! This module also holds the device side's logic, [`DeviceCore`] (handshake, force rules,
//! device watchdog), pure and driven by explicit times, shared by the emulator in
//! [`crate::serial`] and by any firmware port that wants a reference.
//!
//! Neighbours: [`crate::serial`] (the host driver and the PTY emulator thread).

use crc::{CRC_16_IBM_3740, Crc};

use crate::device::vec3;
use crate::sim::Script;

/// Protocol version in every frame.
pub const VERSION: u8 = 1;
/// Largest decoded body, bytes (longer frames are dropped).
pub const MAX_BODY: usize = 128;
/// Largest encoded frame without its terminator: COBS adds one byte per 254, plus one.
pub const MAX_ENCODED: usize = MAX_BODY + MAX_BODY / 254 + 1;
/// Bytes before the payload.
pub const HEADER_LEN: usize = 8;
/// CRC-16/IBM-3740 (CCITT-FALSE): poly 0x1021, init 0xFFFF, no reflection, check 0x29B1.
pub const CRC16: Crc<u16> = Crc::<u16>::new(&CRC_16_IBM_3740);

/// Message type codes.
pub mod kind {
    /// Host -> device: start a session.
    pub const HELLO: u8 = 0x01;
    /// Device -> host: capabilities (answers HELLO).
    pub const CAPS: u8 = 0x02;
    /// Device -> host, every device tick: pose and status.
    pub const STATE: u8 = 0x10;
    /// Host -> device, every host tick: the force to render.
    pub const FORCE: u8 = 0x20;
    /// Either way: keeps the link alive, no payload.
    pub const HEARTBEAT: u8 = 0x30;
    /// Device -> host: a fault.
    pub const FAULT: u8 = 0x7F;
}

/// STATE status bits.
pub mod status {
    /// The device renders forces (outputs enabled).
    pub const FORCE_ENABLED: u16 = 1 << 0;
    /// The dead-man switch is held.
    pub const DEADMAN: u16 = 1 << 1;
    /// The emergency stop is pressed.
    pub const ESTOP: u16 = 1 << 2;
    /// The device watchdog tripped (no valid FORCE within `watchdog_ms`).
    pub const WD_TRIPPED: u16 = 1 << 3;
    /// Motors too warm.
    pub const OVERTEMP: u16 = 1 << 4;
    /// Position calibrated.
    pub const CALIBRATED: u16 = 1 << 5;
}

/// FORCE flag: render the force (clear: output zero, disabled).
pub const FORCE_FLAG_ENABLE: u16 = 1;
/// CAPS flag: the device has a dead-man switch.
pub const CAPS_FLAG_DEADMAN: u16 = 1;
/// CAPS flag: the device has a hardware watchdog.
pub const CAPS_FLAG_WATCHDOG: u16 = 2;

/// Device capabilities (CAPS payload; IEEE 1918.1.1 Part IV in spirit). SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Caps {
    /// Input degrees of freedom (3 for position only).
    pub dof_in: u8,
    /// Output degrees of freedom (3 for force only).
    pub dof_out: u8,
    /// Peak force, N.
    pub peak_force_n: f32,
    /// Continuous force, N.
    pub continuous_force_n: f32,
    /// Largest stable stiffness, N/m.
    pub max_stiffness_n_per_m: f32,
    /// Largest stable damping, N s/m.
    pub max_damping_n_s_per_m: f32,
    /// Workspace box lower corner, m (device frame).
    pub workspace_min_m: [f32; 3],
    /// Workspace box upper corner, m.
    pub workspace_max_m: [f32; 3],
    /// Device loop rate, Hz.
    pub native_rate_hz: u16,
    /// [`CAPS_FLAG_DEADMAN`], [`CAPS_FLAG_WATCHDOG`].
    pub flags: u16,
    /// Model name, ASCII, zero-padded.
    pub model: [u8; 16],
}

/// One device reading (STATE payload).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct State {
    /// Position, m (device frame).
    pub position_m: [f32; 3],
    /// Orientation quaternion w, x, y, z (1, 0, 0, 0 for a 3-DOF device).
    pub quat_wxyz: [f32; 4],
    /// Velocity, m/s.
    pub velocity_m_per_s: [f32; 3],
    /// Button bits.
    pub buttons: u16,
    /// [`status`] bits.
    pub status: u16,
    /// `seq` of the last FORCE frame the device applied.
    pub applied_force_seq: u16,
}

/// A force command (FORCE payload).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Force {
    /// Force, N (device frame).
    pub force_n: [f32; 3],
    /// Torque, N m (zero for 3-DOF devices).
    pub torque_n_m: [f32; 3],
    /// [`FORCE_FLAG_ENABLE`].
    pub flags: u16,
}

/// A message.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Message {
    /// Host -> device: protocol version, host rate (Hz), watchdog (ms, 2..=100).
    Hello {
        /// Protocol version the host speaks.
        proto: u8,
        /// Host loop rate, Hz.
        rate_hz: u16,
        /// Device watchdog, ms.
        watchdog_ms: u16,
    },
    /// Device -> host capabilities.
    Caps(Caps),
    /// Device -> host state.
    State(State),
    /// Host -> device force.
    Force(Force),
    /// Keep-alive.
    Heartbeat,
    /// Device -> host fault: code and detail.
    Fault {
        /// Fault code (device-specific; 1 = e-stop, 2 = over-temperature, 3 = watchdog).
        code: u16,
        /// Detail.
        detail: u16,
    },
}

impl Message {
    /// The type code.
    pub fn kind(&self) -> u8 {
        match self {
            Message::Hello { .. } => kind::HELLO,
            Message::Caps(_) => kind::CAPS,
            Message::State(_) => kind::STATE,
            Message::Force(_) => kind::FORCE,
            Message::Heartbeat => kind::HEARTBEAT,
            Message::Fault { .. } => kind::FAULT,
        }
    }

    /// Payload length of a type, bytes (`None` for an unknown type).
    pub fn payload_len(kind: u8) -> Option<usize> {
        Some(match kind {
            kind::HELLO => 5,
            kind::CAPS => 62,
            kind::STATE => 46,
            kind::FORCE => 26,
            kind::HEARTBEAT => 0,
            kind::FAULT => 4,
            _ => return None,
        })
    }
}

/// A frame: the sender's sequence number and clock, and a message.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Frame {
    /// Per-sender sequence number (wraps).
    pub seq: u16,
    /// Sender's monotonic clock, us (wraps after about 71 minutes).
    pub t_us: u32,
    /// The message.
    pub msg: Message,
}

fn put_f32s(out: &mut Vec<u8>, v: &[f32]) {
    for x in v {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

/// The frame body (header, payload, CRC), before COBS.
pub fn body(frame: &Frame) -> Vec<u8> {
    let mut b = Vec::with_capacity(MAX_BODY);
    b.push(VERSION);
    b.push(frame.msg.kind());
    b.extend_from_slice(&frame.seq.to_le_bytes());
    b.extend_from_slice(&frame.t_us.to_le_bytes());
    match frame.msg {
        Message::Hello {
            proto,
            rate_hz,
            watchdog_ms,
        } => {
            b.push(proto);
            b.extend_from_slice(&rate_hz.to_le_bytes());
            b.extend_from_slice(&watchdog_ms.to_le_bytes());
        }
        Message::Caps(c) => {
            b.push(c.dof_in);
            b.push(c.dof_out);
            put_f32s(
                &mut b,
                &[
                    c.peak_force_n,
                    c.continuous_force_n,
                    c.max_stiffness_n_per_m,
                    c.max_damping_n_s_per_m,
                ],
            );
            put_f32s(&mut b, &c.workspace_min_m);
            put_f32s(&mut b, &c.workspace_max_m);
            b.extend_from_slice(&c.native_rate_hz.to_le_bytes());
            b.extend_from_slice(&c.flags.to_le_bytes());
            b.extend_from_slice(&c.model);
        }
        Message::State(s) => {
            put_f32s(&mut b, &s.position_m);
            put_f32s(&mut b, &s.quat_wxyz);
            put_f32s(&mut b, &s.velocity_m_per_s);
            b.extend_from_slice(&s.buttons.to_le_bytes());
            b.extend_from_slice(&s.status.to_le_bytes());
            b.extend_from_slice(&s.applied_force_seq.to_le_bytes());
        }
        Message::Force(f) => {
            put_f32s(&mut b, &f.force_n);
            put_f32s(&mut b, &f.torque_n_m);
            b.extend_from_slice(&f.flags.to_le_bytes());
        }
        Message::Heartbeat => {}
        Message::Fault { code, detail } => {
            b.extend_from_slice(&code.to_le_bytes());
            b.extend_from_slice(&detail.to_le_bytes());
        }
    }
    let crc = CRC16.checksum(&b);
    b.extend_from_slice(&crc.to_le_bytes());
    b
}

/// Appends the encoded frame (COBS, then `0x00`) to `out`.
pub fn encode(frame: &Frame, out: &mut Vec<u8>) {
    let b = body(frame);
    let start = out.len();
    out.resize(start + cobs::max_encoding_length(b.len()), 0);
    let n = cobs::encode(&b, &mut out[start..]);
    out.truncate(start + n);
    out.push(0);
}

/// Why a frame body was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DecodeError {
    /// Not valid COBS.
    Cobs,
    /// Shorter than a header and CRC.
    Short,
    /// CRC mismatch.
    Crc,
    /// Another protocol version.
    Version(u8),
    /// Unknown message type.
    UnknownType(u8),
    /// The payload length does not match the type.
    Length {
        /// Type code.
        kind: u8,
        /// Payload bytes found.
        found: usize,
    },
}

struct Cursor<'a>(&'a [u8]);

impl Cursor<'_> {
    fn u8(&mut self) -> u8 {
        let v = self.0[0];
        self.0 = &self.0[1..];
        v
    }
    fn u16(&mut self) -> u16 {
        let v = u16::from_le_bytes([self.0[0], self.0[1]]);
        self.0 = &self.0[2..];
        v
    }
    fn u32(&mut self) -> u32 {
        let v = u32::from_le_bytes([self.0[0], self.0[1], self.0[2], self.0[3]]);
        self.0 = &self.0[4..];
        v
    }
    fn f32(&mut self) -> f32 {
        f32::from_bits(self.u32())
    }
    fn f32s<const N: usize>(&mut self) -> [f32; N] {
        std::array::from_fn(|_| self.f32())
    }
}

/// Decodes a frame body (after COBS): checks length, CRC, version, type and payload length.
///
/// # Errors
/// [`DecodeError`] saying which check failed.
pub fn decode_body(b: &[u8]) -> Result<Frame, DecodeError> {
    if b.len() < HEADER_LEN + 2 {
        return Err(DecodeError::Short);
    }
    let (data, crc) = b.split_at(b.len() - 2);
    if CRC16.checksum(data) != u16::from_le_bytes([crc[0], crc[1]]) {
        return Err(DecodeError::Crc);
    }
    if data[0] != VERSION {
        return Err(DecodeError::Version(data[0]));
    }
    let k = data[1];
    let want = Message::payload_len(k).ok_or(DecodeError::UnknownType(k))?;
    let found = data.len() - HEADER_LEN;
    if found != want {
        return Err(DecodeError::Length { kind: k, found });
    }
    let mut c = Cursor(&data[2..]);
    let seq = c.u16();
    let t_us = c.u32();
    let msg = match k {
        kind::HELLO => Message::Hello {
            proto: c.u8(),
            rate_hz: c.u16(),
            watchdog_ms: c.u16(),
        },
        kind::CAPS => {
            let dof_in = c.u8();
            let dof_out = c.u8();
            let [peak, cont, k_max, b_max] = c.f32s::<4>();
            let workspace_min_m = c.f32s::<3>();
            let workspace_max_m = c.f32s::<3>();
            let native_rate_hz = c.u16();
            let flags = c.u16();
            let mut model = [0u8; 16];
            model.copy_from_slice(&c.0[..16]);
            Message::Caps(Caps {
                dof_in,
                dof_out,
                peak_force_n: peak,
                continuous_force_n: cont,
                max_stiffness_n_per_m: k_max,
                max_damping_n_s_per_m: b_max,
                workspace_min_m,
                workspace_max_m,
                native_rate_hz,
                flags,
                model,
            })
        }
        kind::STATE => Message::State(State {
            position_m: c.f32s(),
            quat_wxyz: c.f32s(),
            velocity_m_per_s: c.f32s(),
            buttons: c.u16(),
            status: c.u16(),
            applied_force_seq: c.u16(),
        }),
        kind::FORCE => Message::Force(Force {
            force_n: c.f32s(),
            torque_n_m: c.f32s(),
            flags: c.u16(),
        }),
        kind::HEARTBEAT => Message::Heartbeat,
        _ => Message::Fault {
            code: c.u16(),
            detail: c.u16(),
        },
    };
    Ok(Frame { seq, t_us, msg })
}

/// What a [`FrameDecoder`] dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DecodeStats {
    /// Frames decoded.
    pub frames: u64,
    /// Frames with a CRC mismatch.
    pub crc_errors: u64,
    /// Frames that were not valid COBS, too short, of another version or type, or of the
    /// wrong length.
    pub malformed: u64,
    /// Frames longer than [`MAX_ENCODED`] (discarded up to the next zero).
    pub oversize: u64,
}

/// A streaming decoder: feed it bytes as they come; it yields every valid frame and
/// resynchronises at each `0x00`. Its buffer is allocated once ([`MAX_ENCODED`] bytes).
#[derive(Debug, Clone)]
pub struct FrameDecoder {
    buf: Vec<u8>,
    overflow: bool,
    stats: DecodeStats,
}

impl Default for FrameDecoder {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameDecoder {
    /// An empty decoder.
    pub fn new() -> Self {
        Self {
            buf: Vec::with_capacity(MAX_ENCODED),
            overflow: false,
            stats: DecodeStats::default(),
        }
    }

    /// Counters so far.
    pub fn stats(&self) -> DecodeStats {
        self.stats
    }

    /// Feeds `bytes`; calls `on_frame` for each valid frame, in order. Never panics, whatever
    /// the bytes.
    pub fn push(&mut self, bytes: &[u8], mut on_frame: impl FnMut(Frame)) {
        for &byte in bytes {
            if byte != 0 {
                if self.buf.len() >= MAX_ENCODED {
                    self.overflow = true;
                } else {
                    self.buf.push(byte);
                }
                continue;
            }
            if self.overflow {
                self.stats.oversize += 1;
            } else if !self.buf.is_empty() {
                match cobs::decode_in_place(&mut self.buf) {
                    Ok(n) => match decode_body(&self.buf[..n]) {
                        Ok(f) => {
                            self.stats.frames += 1;
                            on_frame(f);
                        }
                        Err(DecodeError::Crc) => self.stats.crc_errors += 1,
                        Err(_) => self.stats.malformed += 1,
                    },
                    Err(_) => self.stats.malformed += 1,
                }
            }
            self.buf.clear();
            self.overflow = false;
        }
    }
}

/// `true` when sequence number `a` is newer than `b` in a 16-bit window (RFC 1982 style).
pub fn seq_newer(a: u16, b: u16) -> bool {
    let d = a.wrapping_sub(b);
    d != 0 && d < 0x8000
}

/// The device side of HBP/1 (the rules of the specification, section "Device rules"), pure:
/// times are arguments. Outputs start disabled; a HELLO whose `proto` is not [`VERSION`] is
/// not answered and leaves the outputs disabled and no session open; a FORCE is applied only
/// if a HELLO was accepted, it is newer than the last applied one, finite, has the enable flag
/// and the dead-man is held; the force is clamped to the peak force keeping its direction; no
/// valid FORCE within the watchdog zeroes the output and sets [`status::WD_TRIPPED`] until the
/// next valid FORCE. HEARTBEAT (and any frame the device does not expect) changes nothing: in
/// particular it does not feed the watchdog.
#[derive(Debug, Clone)]
pub struct DeviceCore {
    caps: Caps,
    script: Script,
    started_us: u64,
    /// Watchdog, us (from HELLO, 2..=100 ms; 20 ms before any HELLO).
    watchdog_us: u64,
    hello_seen: bool,
    last_valid_force_us: Option<u64>,
    last_applied_seq: Option<u16>,
    output_n: [f64; 3],
    enabled: bool,
    wd_tripped: bool,
    /// Dead-man switch held (tests clear it).
    pub deadman: bool,
    seq: u16,
    /// (us, force) each time the rendered force changed.
    pub rendered: Vec<(u64, [f64; 3])>,
    /// FORCE frames refused (old seq, non-finite, no enable or no dead-man).
    pub refused: u64,
}

impl DeviceCore {
    /// A device at `started_us` whose hand follows `script`.
    pub fn new(caps: Caps, script: Script, started_us: u64) -> Self {
        Self {
            caps,
            script,
            started_us,
            watchdog_us: 20_000,
            hello_seen: false,
            last_valid_force_us: None,
            last_applied_seq: None,
            output_n: [0.0; 3],
            enabled: false,
            wd_tripped: false,
            deadman: true,
            seq: 0,
            rendered: Vec::new(),
            refused: 0,
        }
    }

    /// The force the motors render now, N.
    pub fn output_n(&self) -> [f64; 3] {
        self.output_n
    }

    /// True after a watchdog trip until the next valid FORCE.
    pub fn wd_tripped(&self) -> bool {
        self.wd_tripped
    }

    fn set_output(&mut self, now_us: u64, f: [f64; 3]) {
        if f != self.output_n {
            self.output_n = f;
            self.rendered.push((now_us, f));
        }
    }

    fn next(&mut self, now_us: u64, msg: Message) -> Frame {
        self.seq = self.seq.wrapping_add(1);
        Frame {
            seq: self.seq,
            t_us: now_us as u32,
            msg,
        }
    }

    /// Handles a frame from the host at `now_us`; returns the reply, if any (CAPS for a HELLO
    /// of protocol [`VERSION`]).
    pub fn on_frame(&mut self, now_us: u64, frame: &Frame) -> Option<Frame> {
        match frame.msg {
            Message::Hello {
                proto, watchdog_ms, ..
            } => {
                // Any HELLO ends the current session with the outputs off; only one of our
                // version opens a new one (the host then times out waiting for CAPS).
                self.hello_seen = proto == VERSION;
                self.watchdog_us = u64::from(watchdog_ms.clamp(2, 100)) * 1_000;
                self.enabled = false;
                self.last_applied_seq = None;
                self.last_valid_force_us = None;
                self.set_output(now_us, [0.0; 3]);
                self.hello_seen
                    .then(|| self.next(now_us, Message::Caps(self.caps)))
            }
            Message::Force(f) => {
                let force = f.force_n.map(f64::from);
                let newer = self
                    .last_applied_seq
                    .is_none_or(|s| seq_newer(frame.seq, s));
                if !self.hello_seen || !newer || !vec3::is_finite(force) {
                    self.refused += 1;
                    return None;
                }
                self.last_applied_seq = Some(frame.seq);
                self.last_valid_force_us = Some(now_us);
                self.wd_tripped = false;
                self.enabled = f.flags & FORCE_FLAG_ENABLE != 0;
                if !self.enabled || !self.deadman {
                    if self.enabled {
                        self.refused += 1;
                    }
                    self.set_output(now_us, [0.0; 3]);
                    return None;
                }
                let peak = f64::from(self.caps.peak_force_n);
                let m = vec3::norm(force);
                let out = if m > peak {
                    vec3::scale(force, peak / m)
                } else {
                    force
                };
                self.set_output(now_us, out);
                None
            }
            _ => None,
        }
    }

    /// One device tick at `now_us`: runs the watchdog and returns the STATE frame to send.
    pub fn tick(&mut self, now_us: u64) -> Frame {
        if let Some(t) = self.last_valid_force_us
            && now_us.saturating_sub(t) > self.watchdog_us
            && !self.wd_tripped
        {
            self.wd_tripped = true;
            self.set_output(now_us, [0.0; 3]);
        }
        let t_s = now_us.saturating_sub(self.started_us) as f64 * 1e-6;
        let (p, v) = self.script.kinematics(t_s);
        let mut st = status::CALIBRATED;
        if self.enabled && !self.wd_tripped {
            st |= status::FORCE_ENABLED;
        }
        if self.deadman {
            st |= status::DEADMAN;
        }
        if self.wd_tripped {
            st |= status::WD_TRIPPED;
        }
        let state = State {
            position_m: p.map(|x| x as f32),
            quat_wxyz: [1.0, 0.0, 0.0, 0.0],
            velocity_m_per_s: v.map(|x| x as f32),
            buttons: 0,
            status: st,
            applied_force_seq: self.last_applied_seq.unwrap_or(0),
        };
        self.next(now_us, Message::State(state))
    }
}

/// Capabilities of the emulated arm: 3 DOF in and out, 5 N peak, 1.5 N continuous,
/// 1 kN/m, 2 N s/m, a +-0.15 m box, 1 kHz, watchdog and dead-man, model `hbp-emulator`.
pub fn emulator_caps() -> Caps {
    let mut model = [0u8; 16];
    model[..12].copy_from_slice(b"hbp-emulator");
    Caps {
        dof_in: 3,
        dof_out: 3,
        peak_force_n: 5.0,
        continuous_force_n: 1.5,
        max_stiffness_n_per_m: 1000.0,
        max_damping_n_s_per_m: 2.0,
        workspace_min_m: [-0.15; 3],
        workspace_max_m: [0.15; 3],
        native_rate_hz: 1000,
        flags: CAPS_FLAG_DEADMAN | CAPS_FLAG_WATCHDOG,
        model,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn still() -> Script {
        Script::Poke {
            start_m: [0.0, 0.0, 0.0],
            direction: [0.0, 0.0, -1.0],
            amplitude_m: 0.001,
            frequency_hz: 1.0,
            cycles: 1,
        }
    }

    fn all_messages() -> Vec<Message> {
        vec![
            Message::Hello {
                proto: 1,
                rate_hz: 1000,
                watchdog_ms: 20,
            },
            Message::Caps(emulator_caps()),
            Message::State(State {
                position_m: [0.01, -0.02, 0.03],
                quat_wxyz: [1.0, 0.0, 0.0, 0.0],
                velocity_m_per_s: [0.1, 0.0, -0.1],
                buttons: 3,
                status: status::FORCE_ENABLED | status::DEADMAN,
                applied_force_seq: 65_535,
            }),
            Message::Force(Force {
                force_n: [0.5, -0.25, 1.0],
                torque_n_m: [0.0; 3],
                flags: FORCE_FLAG_ENABLE,
            }),
            Message::Heartbeat,
            Message::Fault { code: 3, detail: 9 },
        ]
    }

    #[test]
    fn crc_check_value_and_golden_force_frame() {
        assert_eq!(CRC16.checksum(b"123456789"), 0x29B1);
        // Golden bytes of a FORCE frame (docs/serial-protocol.md, "Example").
        let f = Frame {
            seq: 1,
            t_us: 1000,
            msg: Message::Force(Force {
                force_n: [0.0, 0.0, 1.0],
                torque_n_m: [0.0; 3],
                flags: FORCE_FLAG_ENABLE,
            }),
        };
        let b = body(&f);
        assert_eq!(b.len(), HEADER_LEN + 26 + 2);
        assert_eq!(&b[..8], &[1, 0x20, 1, 0, 0xE8, 0x03, 0, 0]);
        assert_eq!(&b[16..20], &1.0f32.to_le_bytes());
        let mut wire = Vec::new();
        encode(&f, &mut wire);
        assert_eq!(*wire.last().unwrap(), 0);
        assert!(wire[..wire.len() - 1].iter().all(|&x| x != 0));
        println!("golden FORCE frame: {wire:02X?}");
    }

    #[test]
    fn every_message_round_trips_and_a_corrupted_byte_is_rejected() {
        for (i, msg) in all_messages().into_iter().enumerate() {
            let f = Frame {
                seq: i as u16 * 7,
                t_us: 123_456,
                msg,
            };
            let mut wire = Vec::new();
            encode(&f, &mut wire);
            let mut got = Vec::new();
            let mut d = FrameDecoder::new();
            d.push(&wire, |f| got.push(f));
            assert_eq!(got, vec![f]);
            // Flip one byte of the body: never accepted.
            for k in 0..wire.len() - 1 {
                let mut bad = wire.clone();
                bad[k] ^= 0x5A;
                if bad[k] == 0 {
                    continue; // a new terminator: two short frames, both rejected below
                }
                let mut d = FrameDecoder::new();
                let mut n = 0;
                d.push(&bad, |_| n += 1);
                assert_eq!(n, 0, "message {i}, byte {k}");
            }
        }
    }

    #[test]
    fn garbage_truncation_and_oversize_resync_at_the_next_zero() {
        let f = Frame {
            seq: 9,
            t_us: 1,
            msg: Message::Heartbeat,
        };
        let mut wire = vec![0x11, 0x22, 0x33, 0x00]; // garbage then a terminator
        let mut half = Vec::new();
        encode(&f, &mut half);
        wire.extend_from_slice(&half[..half.len() / 2]); // truncated frame ...
        wire.push(0); // ... cut by a zero
        wire.extend(std::iter::repeat_n(0x7F, 300)); // oversize
        wire.push(0);
        encode(&f, &mut wire); // then a good one
        let mut d = FrameDecoder::new();
        let mut got = Vec::new();
        d.push(&wire, |f| got.push(f));
        assert_eq!(got, vec![f]);
        let s = d.stats();
        assert_eq!((s.frames, s.oversize), (1, 1));
        assert!(s.malformed + s.crc_errors >= 2, "{s:?}");
    }

    #[test]
    fn sequence_numbers_compare_modulo_2_16() {
        assert!(seq_newer(1, 0));
        assert!(seq_newer(0, 65_535));
        assert!(!seq_newer(5, 5));
        assert!(!seq_newer(65_535, 0));
    }

    fn force(seq: u16, f: [f32; 3], flags: u16) -> Frame {
        Frame {
            seq,
            t_us: 0,
            msg: Message::Force(Force {
                force_n: f,
                torque_n_m: [0.0; 3],
                flags,
            }),
        }
    }

    #[test]
    fn device_rules_and_watchdog_at_exact_thresholds() {
        let mut d = DeviceCore::new(emulator_caps(), still(), 0);
        // Before HELLO: refused.
        d.on_frame(0, &force(1, [1.0, 0.0, 0.0], FORCE_FLAG_ENABLE));
        assert_eq!(d.output_n(), [0.0; 3]);
        let hello = Frame {
            seq: 1,
            t_us: 0,
            msg: Message::Hello {
                proto: 1,
                rate_hz: 1000,
                watchdog_ms: 10,
            },
        };
        let caps = d.on_frame(0, &hello).unwrap();
        assert!(matches!(caps.msg, Message::Caps(_)));
        d.on_frame(1_000, &force(2, [1.0, 0.0, 0.0], FORCE_FLAG_ENABLE));
        assert_eq!(d.output_n(), [1.0, 0.0, 0.0]);
        // Old seq, NaN, no enable flag.
        d.on_frame(1_500, &force(1, [2.0, 0.0, 0.0], FORCE_FLAG_ENABLE));
        d.on_frame(1_600, &force(3, [f32::NAN, 0.0, 0.0], FORCE_FLAG_ENABLE));
        assert_eq!(d.output_n(), [1.0, 0.0, 0.0]);
        // Clamped to the 5 N peak, direction kept.
        d.on_frame(2_000, &force(4, [0.0, 30.0, 40.0], FORCE_FLAG_ENABLE));
        assert_eq!(d.output_n(), [0.0, 3.0, 4.0]);
        // Watchdog 10 ms: still on at 12 ms (10 ms after the last FORCE), off just after.
        let s = d.tick(12_000);
        assert_eq!(d.output_n(), [0.0, 3.0, 4.0]);
        assert!(matches!(s.msg, Message::State(st) if st.status & status::FORCE_ENABLED != 0));
        let s = d.tick(12_001);
        assert_eq!(d.output_n(), [0.0; 3]);
        assert!(matches!(s.msg, Message::State(st) if st.status & status::WD_TRIPPED != 0));
        // The next valid FORCE clears the trip; without the dead-man the output stays zero.
        d.deadman = false;
        d.on_frame(13_000, &force(5, [1.0, 0.0, 0.0], FORCE_FLAG_ENABLE));
        assert_eq!(d.output_n(), [0.0; 3]);
        assert!(!d.wd_tripped());
        d.deadman = true;
        d.on_frame(14_000, &force(6, [1.0, 0.0, 0.0], 0));
        assert_eq!(d.output_n(), [0.0; 3]);
        d.on_frame(15_000, &force(7, [1.0, 0.0, 0.0], FORCE_FLAG_ENABLE));
        assert_eq!(d.output_n(), [1.0, 0.0, 0.0]);
    }

    fn hello(proto: u8) -> Frame {
        Frame {
            seq: 1,
            t_us: 0,
            msg: Message::Hello {
                proto,
                rate_hz: 1000,
                watchdog_ms: 10,
            },
        }
    }

    #[test]
    fn a_hello_of_another_version_is_not_answered_and_ends_the_session() {
        let mut d = DeviceCore::new(emulator_caps(), still(), 0);
        assert!(d.on_frame(0, &hello(2)).is_none(), "no CAPS for HBP/2");
        d.on_frame(1_000, &force(2, [1.0, 0.0, 0.0], FORCE_FLAG_ENABLE));
        assert_eq!(d.output_n(), [0.0; 3], "no session: FORCE refused");
        assert!(d.on_frame(2_000, &hello(VERSION)).is_some());
        d.on_frame(3_000, &force(3, [1.0, 0.0, 0.0], FORCE_FLAG_ENABLE));
        assert_eq!(d.output_n(), [1.0, 0.0, 0.0]);
        // A HELLO of another version in a session: outputs off, FORCE refused until a HELLO
        // of ours.
        assert!(d.on_frame(4_000, &hello(0)).is_none());
        assert_eq!(d.output_n(), [0.0; 3]);
        d.on_frame(5_000, &force(4, [1.0, 0.0, 0.0], FORCE_FLAG_ENABLE));
        assert_eq!(d.output_n(), [0.0; 3]);
    }

    #[test]
    fn a_heartbeat_does_not_feed_the_device_watchdog() {
        let mut d = DeviceCore::new(emulator_caps(), still(), 0);
        d.on_frame(0, &hello(VERSION));
        d.on_frame(1_000, &force(2, [1.0, 0.0, 0.0], FORCE_FLAG_ENABLE));
        let beat = |seq| Frame {
            seq,
            t_us: 0,
            msg: Message::Heartbeat,
        };
        for (i, t) in [5_000, 10_000].into_iter().enumerate() {
            assert!(d.on_frame(t, &beat(3 + i as u16)).is_none());
            d.tick(t);
        }
        assert_eq!(d.output_n(), [1.0, 0.0, 0.0]);
        // 10 ms watchdog from the FORCE at 1 ms: tripped at 11.001 ms despite the heartbeats.
        d.on_frame(11_000, &beat(5));
        d.tick(11_001);
        assert!(d.wd_tripped());
        assert_eq!(d.output_n(), [0.0; 3]);
    }

    #[test]
    fn wire_sizes_are_the_specified_ones() {
        // docs/serial-protocol.md, section 4: COBS adds exactly one byte to a body under 254
        // bytes, the terminator one more.
        let sizes: Vec<(u8, usize)> = all_messages()
            .into_iter()
            .map(|msg| {
                let mut wire = Vec::new();
                encode(
                    &Frame {
                        seq: 0,
                        t_us: 0,
                        msg,
                    },
                    &mut wire,
                );
                (msg.kind(), wire.len())
            })
            .collect();
        assert_eq!(
            sizes,
            [
                (kind::HELLO, 17),
                (kind::CAPS, 74),
                (kind::STATE, 58),
                (kind::FORCE, 38),
                (kind::HEARTBEAT, 12),
                (kind::FAULT, 16),
            ]
        );
    }

    fn arb_message() -> impl Strategy<Value = Message> {
        let f3 = || prop::array::uniform3(-1e3f32..1e3);
        prop_oneof![
            (any::<u8>(), any::<u16>(), any::<u16>()).prop_map(|(proto, rate_hz, watchdog_ms)| {
                Message::Hello {
                    proto,
                    rate_hz,
                    watchdog_ms,
                }
            }),
            (f3(), f3(), any::<u16>(), any::<u16>(), any::<u16>()).prop_map(
                |(p, v, buttons, status, applied_force_seq)| Message::State(State {
                    position_m: p,
                    quat_wxyz: [1.0, 0.0, 0.0, 0.0],
                    velocity_m_per_s: v,
                    buttons,
                    status,
                    applied_force_seq,
                })
            ),
            (f3(), any::<u16>()).prop_map(|(f, flags)| Message::Force(Force {
                force_n: f,
                torque_n_m: [0.0; 3],
                flags,
            })),
            Just(Message::Heartbeat),
            (any::<u16>(), any::<u16>()).prop_map(|(code, detail)| Message::Fault { code, detail }),
            Just(Message::Caps(emulator_caps())),
        ]
    }

    fn arb_frame() -> impl Strategy<Value = Frame> {
        (any::<u16>(), any::<u32>(), arb_message()).prop_map(|(seq, t_us, msg)| Frame {
            seq,
            t_us,
            msg,
        })
    }

    /// Bodies with a valid CRC and random version, type and payload length (mostly the
    /// right ones, so that every check is reached), the CRC appended last.
    fn arb_crc_valid_body() -> impl Strategy<Value = Vec<u8>> {
        let known = vec![
            kind::HELLO,
            kind::CAPS,
            kind::STATE,
            kind::FORCE,
            kind::HEARTBEAT,
            kind::FAULT,
        ];
        let ver = prop_oneof![3 => Just(VERSION), 1 => any::<u8>()];
        let k = prop_oneof![3 => prop::sample::select(known), 1 => any::<u8>()];
        (ver, k)
            .prop_flat_map(|(ver, k)| {
                let want = Message::payload_len(k).unwrap_or(0);
                let len = prop_oneof![
                    3 => Just(want),
                    1 => Just(want + 1),
                    1 => Just(want.saturating_sub(1)),
                    1 => 0..=MAX_BODY - HEADER_LEN - 2,
                ];
                (
                    Just(ver),
                    Just(k),
                    any::<[u8; 6]>(),
                    len.prop_flat_map(|n| prop::collection::vec(any::<u8>(), n)),
                )
            })
            .prop_map(|(ver, k, seq_and_time, payload)| {
                let mut b = vec![ver, k];
                b.extend_from_slice(&seq_and_time);
                b.extend_from_slice(&payload);
                let crc = CRC16.checksum(&b);
                b.extend_from_slice(&crc.to_le_bytes());
                b
            })
    }

    /// 256 cases per property in CI. `PROPTEST_CASES=N` raises it for a local soak: read here
    /// because `with_cases` alone would override the variable.
    fn proptest_config() -> ProptestConfig {
        let cases = std::env::var("PROPTEST_CASES")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(256);
        ProptestConfig::with_cases(cases)
    }

    proptest! {
        #![proptest_config(proptest_config())]

        #[test]
        fn crc_valid_bodies_pass_only_with_our_version_a_known_type_and_its_length(
            b in arb_crc_valid_body(),
        ) {
            let (ver, k, found) = (b[0], b[1], b.len() - HEADER_LEN - 2);
            let expected = if ver != VERSION {
                Err(DecodeError::Version(ver))
            } else {
                match Message::payload_len(k) {
                    None => Err(DecodeError::UnknownType(k)),
                    Some(n) if n != found => Err(DecodeError::Length { kind: k, found }),
                    Some(_) => Ok(()),
                }
            };
            let decoded = decode_body(&b);
            match expected {
                Err(e) => prop_assert_eq!(decoded, Err(e)),
                Ok(()) => {
                    let f = decoded.expect("a valid body decodes");
                    prop_assert_eq!(f.msg.kind(), k);
                    // Every field read back where it was: re-encoding gives the same bytes.
                    prop_assert_eq!(body(&f), b.clone());
                }
            }
            // The streaming decoder gives the same verdict and counts a rejection as
            // malformed, never as a CRC error.
            let mut wire = vec![0; cobs::max_encoding_length(b.len())];
            let n = cobs::encode(&b, &mut wire);
            wire.truncate(n);
            wire.push(0);
            let mut d = FrameDecoder::new();
            let mut got = 0u64;
            d.push(&wire, |_| got += 1);
            let s = d.stats();
            prop_assert_eq!(got, u64::from(expected.is_ok()));
            prop_assert_eq!(s.malformed, u64::from(expected.is_err()));
            prop_assert_eq!(s.crc_errors, 0);
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
            let mut d = FrameDecoder::new();
            let mut n = 0u64;
            d.push(&bytes, |_| n += 1);
            let s = d.stats();
            prop_assert_eq!(n, s.frames);
        }

        #[test]
        fn valid_frames_round_trip(frames in prop::collection::vec(arb_frame(), 1..8)) {
            let mut wire = Vec::new();
            for f in &frames {
                encode(f, &mut wire);
            }
            let mut got = Vec::new();
            FrameDecoder::new().push(&wire, |f| got.push(f));
            prop_assert_eq!(got, frames);
        }

        #[test]
        fn noise_between_frames_never_yields_a_frame_that_was_not_sent(
            frames in prop::collection::vec(arb_frame(), 1..6),
            noise in prop::collection::vec(prop::collection::vec(any::<u8>(), 0..40), 6),
        ) {
            let mut wire = Vec::new();
            for (f, n) in frames.iter().zip(&noise) {
                wire.extend_from_slice(n);
                wire.push(0);
                encode(f, &mut wire);
            }
            let mut got = Vec::new();
            FrameDecoder::new().push(&wire, |f| got.push(f));
            // Every sent frame arrives (the zero before it resynchronises) and nothing else
            // passes the CRC, except by a 2^-16 chance that the noise itself is a valid frame.
            for f in &frames {
                prop_assert!(got.contains(f));
            }
            prop_assert!(got.len() <= frames.len() + 1);
        }
    }
}
