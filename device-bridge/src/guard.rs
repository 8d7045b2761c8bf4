//! The force guard: the bridge's last line of defence between the server's force command and the
//! device (devices.md section 4, layer L2). Pure functions plus one state machine
//! ([`ForceGuard`]) that takes `now_us` as an argument, so every rule is tested at its exact
//! threshold with a manual clock.
//!
//! Per device tick, in this order:
//! 1. **Accept** a new command only if its `seq` is newer than the held one and its numbers are
//!    finite (S11); older ones are dropped and counted (the link drops commands for unknown
//!    `seq` before they get here).
//! 2. **Age** = now minus the time the pose it answers was read (the bridge knows it by `seq`),
//!    not its arrival: a burst of commands answering old poses after a stall is old, so it
//!    never makes the watchdog fresh again.
//! 3. **Watchdog gain** `w(age)`: 1 up to **10 ms** (S3), linear to **0 at 60 ms** (S4).
//! 4. **Latch** (S5): at **100 ms** the output is disabled (once the guard has seen a fresh
//!    command: old answers at start-up are only ignored). It comes back only when the link has
//!    been healthy for **500 ms** *and* the operator re-arms ([`ForceGuard::request_rearm`]; a
//!    request before then is discarded); then the gain ramps from 0 to 1 over **200 ms** (S9).
//!    Healthy means an open stream whose newest command is younger than the 60 ms ramp (the
//!    watchdog would render it): stricter (every command under 10 ms for 500 ms) never
//!    re-armed on a loaded 2-core machine whose round trips reach 10 ms at p99.
//! 5. **Arm gain** `a = min(w, a + dt / 200 ms)`: after *any* ramp-down (a stall of 20 ms, a
//!    re-arm, the start) the force comes back along a 200 ms ramp, never as a step.
//! 6. **Local contact model** ([`extrapolate`]): `f = f0 + K (x - x0)` from the held command's
//!    force `f0`, its 3x3 contact stiffness `K` and the position `x0` of the pose it answers, at
//!    the device rate, so the force follows the hand between server updates.
//! 7. **Passivity** ([`crate::passivity`], S12): damping that dissipates injected energy.
//! 8. **Clamp** (S6) to the lower of the device's and the scene's `max_force_n` and the thermal
//!    limit's clamp (S8, [`crate::thermal`]: lowered toward the continuous rating while the
//!    motors run hot), keeping the direction, then **slew** (S7) to the lower of the two
//!    force-rate limits.
//!
//! A position outside the workspace grown by 10 % (S11) or a failed device read zero the force
//! at once: dropping to zero is always safe, so those bypass the slew limit.
//!
//! Not here: S10 dead-man (drivers that have a switch report it as a device
//! error or keep their output disabled).
//!
//! Neighbours: [`crate::link`] calls [`ForceGuard::filter`] once per device tick;
//! [`crate::device::DeviceSpec`] supplies the device limits, the server the scene's
//! ([`Limits`]).

use crate::device::{DeviceSpec, DeviceState, vec3};
use crate::passivity::{PassivityController, PassivityMode, PassivityParams, PassivityStats};
use crate::thermal::ThermalLimit;

/// A force limit and a force-rate limit. The lower of two wins ([`Limits::lower`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    /// Largest force magnitude, N.
    pub max_force_n: f64,
    /// Largest change of the force vector per second, N/s.
    pub max_rate_n_per_s: f64,
}

impl Limits {
    /// Component-wise minimum: the stricter of `self` and `other`. A NaN in `other` is
    /// ignored (the limit it would replace stays).
    pub fn lower(self, other: Limits) -> Limits {
        Limits {
            max_force_n: self.max_force_n.min(other.max_force_n),
            max_rate_n_per_s: self.max_rate_n_per_s.min(other.max_rate_n_per_s),
        }
    }

    /// True when both limits are finite... or infinite, but positive and not NaN.
    pub fn is_valid(&self) -> bool {
        self.max_force_n >= 0.0 && self.max_rate_n_per_s > 0.0
    }
}

/// Guard limits and timings. Times are microseconds of the injected clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuardParams {
    /// Largest force magnitude sent to the device, in N (S6).
    pub max_force_n: f64,
    /// Continuous rating, in N: the thermal limit (S8, [`crate::thermal`]) lowers the clamp
    /// toward it while the motors run hot. At or above `max_force_n`: never limited.
    pub max_continuous_force_n: f64,
    /// Largest change of the force vector per second, in N/s (S7).
    pub max_rate_n_per_s: f64,
    /// Nominal device tick, in s; the slew step is `max_rate_n_per_s * period_s`.
    pub period_s: f64,
    /// Commands at most this old are applied unchanged, in us (S3, default 10 000).
    pub fresh_us: u64,
    /// Age at which the ramp reaches zero, in us (S4, default 60 000).
    pub zero_us: u64,
    /// Age at which the output is disabled until re-armed, in us (S5, default 100 000).
    pub latch_us: u64,
    /// Healthy link time needed before a re-arm is accepted, in us (S9, default 500 000).
    pub healthy_us: u64,
    /// Duration of the gain ramp from 0 to 1 after a re-arm or any ramp-down, in us (S9,
    /// default 200 000).
    pub rearm_ramp_us: u64,
    /// Workspace margin as a fraction of the box extent (S11, default 0.1).
    pub workspace_margin: f64,
    /// Largest displacement the local contact model extrapolates over, in m (default 2 mm;
    /// beyond it the displacement is held at this length).
    pub max_extrapolation_m: f64,
    /// Passivity observer and controller.
    pub passivity: PassivityParams,
}

impl GuardParams {
    /// Defaults from a device spec: clamp at the spec's peak force, slew at
    /// `max_stiffness_n_per_m * 1 m/s`, period `1 / rate_hz`, watchdog 10 / 60 / 100 ms,
    /// re-arm after 500 ms healthy with a 200 ms ramp, passivity control with the spec's
    /// damping limit.
    pub fn from_spec(spec: &DeviceSpec) -> Self {
        Self {
            max_force_n: spec.max_force_n,
            max_continuous_force_n: spec.max_continuous_force_n,
            max_rate_n_per_s: spec.max_stiffness_n_per_m * 1.0,
            period_s: 1.0 / spec.rate_hz,
            fresh_us: 10_000,
            zero_us: 60_000,
            latch_us: 100_000,
            healthy_us: 500_000,
            rearm_ramp_us: 200_000,
            workspace_margin: 0.1,
            max_extrapolation_m: 0.002,
            passivity: PassivityParams {
                mode: PassivityMode::Control,
                max_damping_n_s_per_m: spec.max_damping_n_s_per_m,
            },
        }
    }

    /// The device limits of these parameters.
    pub fn device_limits(&self) -> Limits {
        Limits {
            max_force_n: self.max_force_n,
            max_rate_n_per_s: self.max_rate_n_per_s,
        }
    }

    /// Largest change of the force vector in one tick under the device limits, in N.
    pub fn max_step_n(&self) -> f64 {
        self.max_rate_n_per_s * self.period_s
    }
}

/// Clamps the magnitude of `force_n` to `max_n` (N), keeping its direction (S6).
///
/// Returns the clamped force and whether clamping happened. A force exactly at the limit is not
/// clamped.
pub fn clamp_magnitude(force_n: [f64; 3], max_n: f64) -> ([f64; 3], bool) {
    let m = vec3::norm(force_n);
    if m > max_n {
        (vec3::scale(force_n, max_n / m), true)
    } else {
        (force_n, false)
    }
}

/// Moves from `previous_n` toward `target_n` by at most `max_step_n` (N) in vector norm, along the
/// straight line between them (S7). Returns the new force and whether the step was limited.
pub fn rate_limit(previous_n: [f64; 3], target_n: [f64; 3], max_step_n: f64) -> ([f64; 3], bool) {
    let delta = vec3::sub(target_n, previous_n);
    let d = vec3::norm(delta);
    if d > max_step_n {
        (vec3::axpy(previous_n, max_step_n / d, delta), true)
    } else {
        (target_n, false)
    }
}

/// Watchdog gain for a command of age `age_us` (S3, S4): 1 while `age_us <= fresh_us`, falling
/// linearly to exactly 0 at `zero_us`, 0 beyond.
pub fn watchdog_gain(age_us: u64, fresh_us: u64, zero_us: u64) -> f64 {
    if age_us <= fresh_us {
        1.0
    } else if age_us >= zero_us {
        0.0
    } else {
        (zero_us - age_us) as f64 / (zero_us - fresh_us) as f64
    }
}

/// The bridge-side local contact model: `f = f0 + K (x - x0)` (N), with `K` the 3x3 row-major
/// contact stiffness `d f / d x` (N/m) the server computed at the device position `x0` (m) for
/// which it computed `f0` (N), evaluated at the current device position `x` (m).
///
/// Two guards keep the linearisation honest: the displacement `x - x0` is shortened to at most
/// `max_dx_m` (m), and a contact force only pushes: when the extrapolated force points against
/// `f0` (the hand left the surface) the result is zero. With `f0 = 0` (no contact) the result
/// is zero whatever `K` says, since the normal is unknown.
pub fn extrapolate(
    f0_n: [f64; 3],
    k_n_per_m: &[f64; 9],
    x0_m: [f64; 3],
    x_m: [f64; 3],
    max_dx_m: f64,
) -> [f64; 3] {
    let Some(n) = vec3::normalized(f0_n) else {
        return [0.0; 3];
    };
    let mut dx = vec3::sub(x_m, x0_m);
    let d = vec3::norm(dx);
    if !d.is_finite() {
        return f0_n;
    }
    if d > max_dx_m {
        dx = vec3::scale(dx, max_dx_m / d);
    }
    let k = k_n_per_m;
    let f = [
        f0_n[0] + k[0] * dx[0] + k[1] * dx[1] + k[2] * dx[2],
        f0_n[1] + k[3] * dx[0] + k[4] * dx[1] + k[5] * dx[2],
        f0_n[2] + k[6] * dx[0] + k[7] * dx[1] + k[8] * dx[2],
    ];
    if vec3::dot(f, n) <= 0.0 { [0.0; 3] } else { f }
}

/// Where the guard's output came from on the last tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GuardState {
    /// No valid command received yet: zero.
    #[default]
    NoCommand,
    /// The command is fresh (S3) and the arm gain is 1: applied.
    Fresh,
    /// The command is fresh and the gain is coming back up (start, re-arm, after a stall).
    Rising,
    /// The command is stale (S4): ramping to zero.
    Ramp,
    /// The command is older than the ramp (S4): zero.
    Expired,
    /// Disabled after 100 ms without a fresh command (S5); waiting for a healthy link.
    Disabled,
    /// Disabled; the link has been healthy for 500 ms: waiting for the operator's re-arm.
    ReadyToRearm,
    /// The position is outside the workspace (S11): zero.
    OutsideWorkspace,
}

impl GuardState {
    /// A short code for logs and atomics (stable: 0..=7 in declaration order).
    pub fn code(self) -> u8 {
        self as u8
    }

    /// The state with code `c` ([`GuardState::code`]); `NoCommand` for unknown codes.
    pub fn from_code(c: u8) -> Self {
        use GuardState::*;
        [
            NoCommand,
            Fresh,
            Rising,
            Ramp,
            Expired,
            Disabled,
            ReadyToRearm,
            OutsideWorkspace,
        ]
        .get(usize::from(c))
        .copied()
        .unwrap_or(NoCommand)
    }

    /// A short lower-case name for logs and recordings.
    pub fn name(self) -> &'static str {
        match self {
            GuardState::NoCommand => "no-command",
            GuardState::Fresh => "fresh",
            GuardState::Rising => "rising",
            GuardState::Ramp => "ramp",
            GuardState::Expired => "expired",
            GuardState::Disabled => "disabled",
            GuardState::ReadyToRearm => "ready-to-rearm",
            GuardState::OutsideWorkspace => "outside-workspace",
        }
    }

    /// True while the output is latched off (S5).
    pub fn is_disabled(self) -> bool {
        matches!(self, GuardState::Disabled | GuardState::ReadyToRearm)
    }
}

/// A force command as the guard sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuardCommand {
    /// Changes whenever a new command arrives (the link's receive counter).
    pub generation: u64,
    /// Sequence number of the pose this command answers.
    pub seq: u64,
    /// Commanded force at `position_m`, in N (may be non-finite: the guard rejects it).
    pub force_n: [f64; 3],
    /// Contact stiffness `d f / d x`, 3x3 row-major, in N/m (zero out of contact).
    pub stiffness_n_per_m: [f64; 9],
    /// Device position of the pose this command answers, in m.
    pub position_m: [f64; 3],
    /// Clock time that pose was read, in us: the command's age runs from here.
    pub sample_time_us: u64,
}

/// Counters of guard interventions (S14: every intervention is counted).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GuardStats {
    /// Commands whose magnitude exceeded the clamp (counted once per command).
    pub clamped: u64,
    /// Ticks on which the slew limit cut the step.
    pub rate_limited: u64,
    /// Non-finite commands rejected.
    pub rejected_nan: u64,
    /// Commands dropped because their `seq` was not newer than the held one.
    pub stale_dropped: u64,
    /// Entries into the stale ramp (one per episode, not per tick).
    pub watchdog_ramps: u64,
    /// Entries into the expired state (one per episode).
    pub watchdog_expired: u64,
    /// Times the output was disabled (S5).
    pub latches: u64,
    /// Re-arms accepted (S9).
    pub rearms: u64,
    /// Re-arm requests discarded because the link was not yet healthy for long enough.
    pub rearm_refused: u64,
    /// Ticks zeroed because the position was outside the workspace.
    pub workspace_violations: u64,
    /// Ticks on which the thermal limit (S8) held the clamp below the peak force.
    pub thermal_limited: u64,
    /// The passivity observer and controller.
    pub passivity: PassivityStats,
}

/// Arming mode of the guard (S5, S9).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Arm {
    /// Forces allowed, scaled by the arm gain.
    Armed,
    /// Latched off; `healthy_since_us` is when the current healthy stretch started.
    Latched { healthy_since_us: Option<u64> },
}

/// The guard's state: held command, gains, last output, counters. Allocation-free; one per
/// device.
#[derive(Debug, Clone)]
pub struct ForceGuard {
    params: GuardParams,
    app_limits: Option<Limits>,
    last_generation: Option<u64>,
    /// Last valid (finite) command.
    held: Option<GuardCommand>,
    arm: Arm,
    arm_gain: f64,
    /// A fresh command was seen since the last arming: only then can the output latch.
    engaged: bool,
    rearm_requested: bool,
    last_now_us: Option<u64>,
    output_n: [f64; 3],
    /// Magnitude of the last tick's command at the device position (step 6, before the gain),
    /// N: recorded so that tests can check the output against the ramp.
    command_n: f64,
    state: GuardState,
    stats: GuardStats,
    passivity: PassivityController,
    thermal: ThermalLimit,
}

impl ForceGuard {
    /// A guard with zero output, no command, armed with gain 0 (the first commands ramp in
    /// over [`GuardParams::rearm_ramp_us`]).
    pub fn new(params: GuardParams) -> Self {
        Self {
            params,
            app_limits: None,
            last_generation: None,
            held: None,
            arm: Arm::Armed,
            arm_gain: 0.0,
            engaged: false,
            rearm_requested: false,
            last_now_us: None,
            output_n: [0.0; 3],
            command_n: 0.0,
            state: GuardState::NoCommand,
            stats: GuardStats::default(),
            passivity: PassivityController::new(params.passivity),
            thermal: ThermalLimit::new(params.max_force_n, params.max_continuous_force_n),
        }
    }

    /// The parameters in use.
    pub fn params(&self) -> &GuardParams {
        &self.params
    }

    /// Sets the application limits the server sent for this session (`None`: device limits
    /// only). The lower of these and the device limits wins.
    pub fn set_app_limits(&mut self, limits: Option<Limits>) {
        self.app_limits = limits.filter(Limits::is_valid);
    }

    /// The limits in force: the device's, lowered by the application's.
    pub fn limits(&self) -> Limits {
        let d = self.params.device_limits();
        self.app_limits.map_or(d, |a| d.lower(a))
    }

    /// The force returned by the last [`filter`](Self::filter), in N.
    pub fn output_n(&self) -> [f64; 3] {
        self.output_n
    }

    /// Magnitude of the held command's force at the last tick's device position (the local
    /// contact model, step 6), before the gain, passivity, clamp and slew, in N; 0 on ticks
    /// that did not evaluate a command (none held, latched, outside the workspace).
    pub fn command_n(&self) -> f64 {
        self.command_n
    }

    /// The state of the last tick.
    pub fn state(&self) -> GuardState {
        self.state
    }

    /// Age of the held command at the last tick, in us (`None` without one).
    pub fn held_age_us(&self) -> Option<u64> {
        Some(self.last_now_us?.saturating_sub(self.held?.sample_time_us))
    }

    /// The thermal limit's clamp of the last tick, in N (S8; the peak while cool).
    pub fn thermal_clamp_n(&self) -> f64 {
        self.thermal.clamp_n()
    }

    /// The arm gain of the last tick (0..=1).
    pub fn arm_gain(&self) -> f64 {
        self.arm_gain
    }

    /// Intervention counters.
    pub fn stats(&self) -> GuardStats {
        let mut s = self.stats;
        s.passivity = self.passivity.stats();
        s
    }

    /// The operator asks to re-arm. Accepted on the next tick if the output is disabled and
    /// the link has been healthy for [`GuardParams::healthy_us`]; otherwise discarded and
    /// counted (`rearm_refused`), so an early key press never arms later by surprise.
    pub fn request_rearm(&mut self) {
        self.rearm_requested = true;
    }

    /// Forgets the held command and outputs zero from now on until a new command arrives (use
    /// when the device read fails: its pose is not to be trusted).
    pub fn reset(&mut self) {
        self.held = None;
        self.arm_gain = 0.0;
        self.output_n = [0.0; 3];
    }

    /// One guard tick at clock time `now_us`: returns the force to write to the device, in N.
    ///
    /// `link_up` is false while no stream is open (the held command keeps ageing, so the force
    /// ramps down as for a stall). `command` is the latest command received (the same one may
    /// be passed on many ticks; a new `generation` marks a new one). `device` is this tick's
    /// reading (position for the workspace check and the local model, velocity for passivity).
    pub fn filter(
        &mut self,
        now_us: u64,
        link_up: bool,
        command: Option<&GuardCommand>,
        device: &DeviceState,
        spec: &DeviceSpec,
    ) -> [f64; 3] {
        let p = self.params;
        let dt_us = self
            .last_now_us
            .map_or((p.period_s * 1e6) as u64, |t| now_us.saturating_sub(t));
        self.last_now_us = Some(now_us);
        // The thermal limit (S8) sees what was rendered since the last tick.
        let thermal_clamp_n = self.thermal.update(
            vec3::norm(self.output_n),
            dt_us as f64 * 1e-6,
            device.motor_temperature,
        );
        self.stats.thermal_limited += u64::from(self.thermal.limiting());
        // 1. Accept.
        self.accept(command);
        // 2-3. Age and watchdog gain.
        let age = self.held.map(|h| now_us.saturating_sub(h.sample_time_us));
        let w = age.map_or(0.0, |a| watchdog_gain(a, p.fresh_us, p.zero_us));
        let fresh = link_up && age.is_some_and(|a| a <= p.fresh_us);
        let healthy = link_up && age.is_some_and(|a| a < p.zero_us);
        // 4. Latch and re-arm.
        self.latch_or_rearm(now_us, age, fresh, healthy);
        // 5. Arm gain: follows the watchdog down at once, comes back up along the ramp.
        if self.arm == Arm::Armed {
            let up = dt_us as f64 / p.rearm_ramp_us.max(1) as f64;
            self.arm_gain = (self.arm_gain + up).min(w).clamp(0.0, 1.0);
        }
        let previous_state = self.state;
        let limits = self.limits();
        self.command_n = 0.0;
        let (state, target) = self.target(now_us, age, w, device, spec);
        if state != previous_state {
            match state {
                GuardState::Ramp => self.stats.watchdog_ramps += 1,
                GuardState::Expired => self.stats.watchdog_expired += 1,
                _ => {}
            }
        }
        self.state = state;
        self.output_n = match target {
            // Zero is always safe: no slew limit on the way down to it.
            None => [0.0; 3],
            Some(t) => {
                // 7. Passivity, 8. clamp and slew.
                let t = self
                    .passivity
                    .apply(t, device.velocity_m_per_s, dt_us as f64 * 1e-6);
                let (t, _) = clamp_magnitude(t, limits.max_force_n.min(thermal_clamp_n));
                let (f, limited) =
                    rate_limit(self.output_n, t, limits.max_rate_n_per_s * p.period_s);
                self.stats.rate_limited += u64::from(limited);
                f
            }
        };
        self.output_n
    }

    /// Step 1: holds a new finite command that is newer than the held one; counts the
    /// non-finite (rejected), the old (stale) and the too strong (clamped later).
    fn accept(&mut self, command: Option<&GuardCommand>) {
        if let Some(c) = command
            && self.last_generation != Some(c.generation)
        {
            self.last_generation = Some(c.generation);
            let finite = vec3::is_finite(c.force_n)
                && vec3::is_finite(c.position_m)
                && c.stiffness_n_per_m.iter().all(|v| v.is_finite());
            if !finite {
                self.stats.rejected_nan += 1;
            } else if self.held.is_some_and(|h| c.seq <= h.seq) {
                self.stats.stale_dropped += 1;
            } else {
                let limit = self.limits().max_force_n;
                self.stats.clamped += u64::from(vec3::norm(c.force_n) > limit);
                self.held = Some(*c);
            }
        }
    }

    /// Step 4 (S5, S9): latches the output off once an engaged command is `latch_us` old;
    /// while latched, tracks the healthy stretch and takes a pending re-arm request (accepted
    /// after `healthy_us`, refused and counted before).
    fn latch_or_rearm(&mut self, now_us: u64, age: Option<u64>, fresh: bool, healthy: bool) {
        let p = self.params;
        let requested = std::mem::take(&mut self.rearm_requested);
        match self.arm {
            Arm::Armed => {
                self.engaged |= fresh;
                if self.engaged && age.is_some_and(|a| a >= p.latch_us) {
                    self.engaged = false;
                    self.arm = Arm::Latched {
                        healthy_since_us: None,
                    };
                    self.stats.latches += 1;
                    self.arm_gain = 0.0;
                    self.passivity.reset();
                }
            }
            Arm::Latched { healthy_since_us } => {
                let since = if healthy {
                    Some(healthy_since_us.unwrap_or(now_us))
                } else {
                    None
                };
                self.arm = Arm::Latched {
                    healthy_since_us: since,
                };
                let ready = since.is_some_and(|s| now_us.saturating_sub(s) >= p.healthy_us);
                if requested {
                    if ready {
                        self.arm = Arm::Armed;
                        self.arm_gain = 0.0;
                        self.stats.rearms += 1;
                    } else {
                        self.stats.rearm_refused += 1;
                    }
                }
            }
        }
    }

    /// This tick's state and the force to aim at before passivity, clamp and slew (`None`:
    /// zero): nothing outside the workspace or while latched, else step 6, the held command's
    /// local contact model at the device position scaled by the arm gain (`w` is the
    /// watchdog gain of the command's `age`, us).
    fn target(
        &mut self,
        now_us: u64,
        age: Option<u64>,
        w: f64,
        device: &DeviceState,
        spec: &DeviceSpec,
    ) -> (GuardState, Option<[f64; 3]>) {
        let p = self.params;
        if !spec.contains(device.position_m, p.workspace_margin) {
            self.stats.workspace_violations += 1;
            return (GuardState::OutsideWorkspace, None);
        }
        if let Arm::Latched { healthy_since_us } = self.arm {
            let ready = healthy_since_us.is_some_and(|s| now_us.saturating_sub(s) >= p.healthy_us);
            let state = if ready {
                GuardState::ReadyToRearm
            } else {
                GuardState::Disabled
            };
            return (state, None);
        }
        let (Some(h), Some(a)) = (self.held, age) else {
            return (GuardState::NoCommand, None);
        };
        let state = if a <= p.fresh_us {
            if self.arm_gain >= 1.0 {
                GuardState::Fresh
            } else {
                GuardState::Rising
            }
        } else if w > 0.0 {
            GuardState::Ramp
        } else {
            GuardState::Expired
        };
        // 6. Local contact model, scaled by the gain.
        let f = extrapolate(
            h.force_n,
            &h.stiffness_n_per_m,
            h.position_m,
            device.position_m,
            p.max_extrapolation_m,
        );
        self.command_n = vec3::norm(f);
        // A zero gain is a zero force: no passivity damping either (the watchdog
        // promises exactly zero from 60 ms on).
        (
            state,
            (self.arm_gain > 0.0).then(|| vec3::scale(f, self.arm_gain)),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::{Clock, ManualClock};

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        vec3::norm(vec3::sub(a, b)) < 1e-12
    }

    fn at(x: [f64; 3]) -> DeviceState {
        DeviceState {
            position_m: x,
            ..DeviceState::default()
        }
    }

    const ORIGIN: DeviceState = DeviceState {
        time_us: 0,
        position_m: [0.0; 3],
        velocity_m_per_s: [0.0; 3],
        motor_temperature: None,
    };

    fn cmd(generation: u64, force_n: [f64; 3], sample_time_us: u64) -> GuardCommand {
        GuardCommand {
            generation,
            seq: generation,
            force_n,
            stiffness_n_per_m: [0.0; 9],
            position_m: [0.0; 3],
            sample_time_us,
        }
    }

    /// A guard without slew limit and without the start-up ramp, so watchdog numbers are seen
    /// exactly.
    fn unlimited() -> (ForceGuard, DeviceSpec) {
        let spec = DeviceSpec::sim_default();
        let mut p = GuardParams::from_spec(&spec);
        p.max_rate_n_per_s = f64::INFINITY;
        p.rearm_ramp_us = 1;
        (ForceGuard::new(p), spec)
    }

    #[test]
    fn defaults_follow_the_spec() {
        let p = GuardParams::from_spec(&DeviceSpec::sim_default());
        assert_eq!(p.max_force_n, 10.0);
        assert_eq!(p.max_rate_n_per_s, 1000.0); // 1000 N/m * 1 m/s
        assert!((p.max_step_n() - 1.0).abs() < 1e-12); // 1 N per 1 ms tick
        assert_eq!(
            (
                p.fresh_us,
                p.zero_us,
                p.latch_us,
                p.healthy_us,
                p.rearm_ramp_us
            ),
            (10_000, 60_000, 100_000, 500_000, 200_000)
        );
    }

    #[test]
    fn a_held_force_above_the_continuous_rating_is_brought_down_to_it_s8() {
        // Sim spec: 10 N peak, 3 N continuous. The server asks for 5 N, fresh, for 10 s.
        let (mut g, spec) = unlimited();
        g.params.passivity.mode = crate::passivity::PassivityMode::Off;
        g.passivity = PassivityController::new(g.params.passivity);
        let mut out = [0.0; 3];
        for i in 1..=10_000u64 {
            let t = i * 1000;
            out = g.filter(t, true, Some(&cmd(i, [5.0, 0.0, 0.0], t)), &ORIGIN, &spec);
            if i == 300 {
                // RMS over 1 s passes 3 N after -ln(1 - 9/25) s = 446 ms: not limited yet.
                assert!(close(out, [5.0, 0.0, 0.0]), "{out:?}");
            }
        }
        assert!(close(out, [3.0, 0.0, 0.0]), "held at the rating: {out:?}");
        assert!(g.stats().thermal_limited > 5_000);
        // A device that reports a hot motor is limited whatever the force.
        let (mut g, spec) = unlimited();
        let hot = DeviceState {
            motor_temperature: Some(0.9),
            ..ORIGIN
        };
        for i in 1..=1_000u64 {
            let t = i * 1000;
            g.filter(t, true, Some(&cmd(i, [0.1, 0.0, 0.0], t)), &hot, &spec);
        }
        assert!((g.thermal_clamp_n() - 10.0 * 0.999f64.powi(1_000)).abs() < 1e-9);
    }

    #[test]
    fn watchdog_gain_at_exact_thresholds() {
        // (age in us, expected gain)
        let table = [
            (0, 1.0),
            (9_999, 1.0),
            (10_000, 1.0),
            (10_001, 49_999.0 / 50_000.0),
            (35_000, 0.5),
            (59_999, 1.0 / 50_000.0),
            (60_000, 0.0),
            (60_001, 0.0),
            (1_000_000, 0.0),
        ];
        for (age, want) in table {
            assert_eq!(watchdog_gain(age, 10_000, 60_000), want, "age {age} us");
        }
    }

    #[test]
    fn guard_watchdog_follows_the_pose_age_on_the_manual_clock() {
        let f = [2.0, -1.0, 0.5];
        // (age in us, expected state, expected fraction of f)
        let table = [
            (9_999, GuardState::Fresh, 1.0),
            (10_000, GuardState::Fresh, 1.0),
            (10_001, GuardState::Ramp, 49_999.0 / 50_000.0),
            (35_000, GuardState::Ramp, 0.5),
            (60_000, GuardState::Expired, 0.0),
            (60_001, GuardState::Expired, 0.0),
            (99_999, GuardState::Expired, 0.0),
            (100_000, GuardState::Disabled, 0.0),
        ];
        for (age, state, frac) in table {
            let (mut g, spec) = unlimited();
            let clock = ManualClock::new(1_000_000);
            let c = cmd(1, f, clock.now_us());
            let out = g.filter(clock.now_us(), true, Some(&c), &ORIGIN, &spec);
            assert!(close(out, f), "{out:?}");
            clock.advance_us(age);
            let out = g.filter(clock.now_us(), true, Some(&c), &ORIGIN, &spec);
            assert_eq!(g.state(), state, "age {age} us");
            assert!(close(out, vec3::scale(f, frac)), "age {age} us: {out:?}");
        }
    }

    #[test]
    fn a_command_is_aged_from_its_pose_not_from_its_arrival() {
        let (mut g, spec) = unlimited();
        // Arrives now, but answers a pose read 35 ms ago: half force at once.
        let c = cmd(1, [1.0, 0.0, 0.0], 0);
        let out = g.filter(35_000, true, Some(&c), &ORIGIN, &spec);
        assert_eq!(g.state(), GuardState::Ramp);
        assert!(close(out, [0.5, 0.0, 0.0]), "{out:?}");
    }

    #[test]
    fn a_burst_of_old_commands_after_a_stall_never_revives_the_force() {
        let (mut g, spec) = unlimited();
        let mut t = 0;
        let mut generation = 0;
        // Fresh commands every ms up to t = 100 ms.
        while t <= 100_000 {
            generation += 1;
            g.filter(
                t,
                true,
                Some(&cmd(generation, [1.0, 0.0, 0.0], t)),
                &ORIGIN,
                &spec,
            );
            t += 1_000;
        }
        // A 300 ms stall: no command.
        while t <= 400_000 {
            g.filter(t, true, None, &ORIGIN, &spec);
            t += 1_000;
        }
        assert_eq!(g.state(), GuardState::Disabled);
        // The burst: 300 commands answering the poses of the stall, all in one ms.
        for k in 0..300 {
            generation += 1;
            let c = cmd(generation, [1.0, 0.0, 0.0], 101_000 + 1_000 * k);
            assert_eq!(g.filter(t, true, Some(&c), &ORIGIN, &spec), [0.0; 3]);
            assert!(g.state().is_disabled());
        }
        // An older seq than the held one is dropped and counted.
        let old = GuardCommand {
            seq: 5,
            ..cmd(generation + 1, [1.0, 0.0, 0.0], t)
        };
        g.filter(t, true, Some(&old), &ORIGIN, &spec);
        assert_eq!(g.stats().stale_dropped, 1);
        assert_eq!(g.stats().latches, 1);
    }

    #[test]
    fn rearm_needs_500_ms_of_health_and_the_operator_then_ramps_over_200_ms() {
        let spec = DeviceSpec::sim_default();
        let mut p = GuardParams::from_spec(&spec);
        p.max_rate_n_per_s = f64::INFINITY;
        let mut g = ForceGuard::new(p);
        let f = [0.05, 0.0, 0.0];
        let mut generation = 0;
        let mut tick = |g: &mut ForceGuard, t: u64, fresh: bool| {
            generation += 1;
            let c = cmd(generation, f, if fresh { t } else { 0 });
            g.filter(t, true, Some(&c), &ORIGIN, &spec)
        };
        // Start: ramps in over 200 ms (a tick counts one period: gain 0.5 at 99 ms), full at
        // 200 ms.
        tick(&mut g, 0, true);
        let out = tick(&mut g, 99_000, true);
        assert!(close(out, vec3::scale(f, 0.5)), "{out:?}");
        assert_eq!(g.state(), GuardState::Rising);
        assert!(close(tick(&mut g, 200_000, true), f));
        assert_eq!(g.state(), GuardState::Fresh);
        // Stall: no new command; disabled at 100 ms of age.
        g.filter(299_999, true, None, &ORIGIN, &spec);
        assert_eq!(g.state(), GuardState::Expired);
        g.filter(300_000, true, None, &ORIGIN, &spec);
        assert_eq!(g.state(), GuardState::Disabled);
        // Healthy again from t = 400 ms; a request at 899.999 ms is refused ...
        let mut t = 400_000;
        while t < 899_999 {
            assert_eq!(tick(&mut g, t, true), [0.0; 3]);
            t += 1_000;
        }
        g.request_rearm();
        assert_eq!(tick(&mut g, 899_999, true), [0.0; 3]);
        assert_eq!(g.state(), GuardState::Disabled);
        assert_eq!(g.stats().rearm_refused, 1);
        // ... and not remembered: at 900 ms the link is healthy, still no force without a request.
        assert_eq!(tick(&mut g, 900_000, true), [0.0; 3]);
        assert_eq!(g.state(), GuardState::ReadyToRearm);
        assert_eq!(tick(&mut g, 950_000, true), [0.0; 3]);
        // The operator re-arms: the gain ramps 0 -> 1 over 200 ms, never a step.
        g.request_rearm();
        let mut last = 0.0;
        let mut t = 951_000;
        tick(&mut g, 950_500, true);
        assert_eq!(g.stats().rearms, 1);
        while t <= 1_151_000 {
            let out = tick(&mut g, t, true)[0];
            assert!(out >= last && out - last <= f[0] * 1_000.0 / 200_000.0 + 1e-12);
            last = out;
            t += 1_000;
        }
        assert!((last - f[0]).abs() < 1e-12);
    }

    #[test]
    fn after_a_short_stall_the_force_comes_back_along_the_ramp_not_as_a_step() {
        let (mut g, spec) = {
            let spec = DeviceSpec::sim_default();
            let mut p = GuardParams::from_spec(&spec);
            p.max_rate_n_per_s = f64::INFINITY;
            (ForceGuard::new(p), spec)
        };
        let f = [0.05, 0.0, 0.0];
        let mut t = 0;
        let mut generation = 0;
        while t <= 300_000 {
            generation += 1;
            g.filter(t, true, Some(&cmd(generation, f, t)), &ORIGIN, &spec);
            t += 1_000;
        }
        assert!(close(g.output_n(), f));
        // 50 ms stall: the gain falls to 0.2 (age 50 ms).
        let stall_end = t + 49_000;
        while t <= stall_end {
            g.filter(t, true, None, &ORIGIN, &spec);
            t += 1_000;
        }
        assert!((g.output_n()[0] - 0.2 * f[0]).abs() < 1e-3 * f[0]);
        // Fresh commands again: the force rises at most 1/200 of f per ms.
        let mut last = g.output_n()[0];
        let mut max_step: f64 = 0.0;
        for _ in 0..300 {
            generation += 1;
            let out = g.filter(t, true, Some(&cmd(generation, f, t)), &ORIGIN, &spec)[0];
            max_step = max_step.max(out - last);
            last = out;
            t += 1_000;
        }
        assert!(max_step <= f[0] / 200.0 + 1e-12, "step {max_step}");
        assert!((last - f[0]).abs() < 1e-12);
        assert_eq!(g.stats().latches, 0);
    }

    #[test]
    fn command_n_is_the_command_before_the_gain_and_zero_once_latched() {
        let (mut g, spec) = unlimited();
        let f = [0.0, 0.03, 0.04];
        let mut t = 0;
        for generation in 1..=10 {
            g.filter(t, true, Some(&cmd(generation, f, t)), &ORIGIN, &spec);
            t += 1_000;
        }
        assert!((g.command_n() - 0.05).abs() < 1e-12);
        // A 35 ms old command: rendered at gain 0.5, recorded unscaled.
        let last = t - 1_000;
        g.filter(last + 35_000, true, None, &ORIGIN, &spec);
        assert!(
            close(g.output_n(), vec3::scale(f, 0.5)),
            "{:?}",
            g.output_n()
        );
        assert!((g.command_n() - 0.05).abs() < 1e-12);
        // Latched at 100 ms: nothing evaluated.
        g.filter(last + 100_000, true, None, &ORIGIN, &spec);
        assert_eq!(g.state(), GuardState::Disabled);
        assert_eq!(g.command_n(), 0.0);
    }

    #[test]
    fn an_expired_command_renders_exactly_zero_even_while_the_hand_moves() {
        let (mut g, spec) = unlimited();
        let moving = DeviceState {
            velocity_m_per_s: [0.1, 0.0, 0.0],
            ..ORIGIN
        };
        // Pushing along the motion: the passivity controller is active while ramping ...
        let c = cmd(1, [1.0, 0.0, 0.0], 0);
        g.filter(0, true, Some(&c), &moving, &spec);
        g.filter(30_000, true, Some(&c), &moving, &spec);
        // ... but from 60 ms on the output is exactly zero.
        for t in [60_000, 61_000, 80_000] {
            assert_eq!(g.filter(t, true, Some(&c), &moving, &spec), [0.0; 3]);
        }
    }

    #[test]
    fn old_answers_at_start_up_are_ignored_without_latching() {
        let (mut g, spec) = unlimited();
        // The first command answers a pose read 150 ms earlier (a slow stream set-up).
        g.filter(
            150_000,
            true,
            Some(&cmd(1, [1.0, 0.0, 0.0], 0)),
            &ORIGIN,
            &spec,
        );
        assert_eq!(g.state(), GuardState::Expired);
        // Fresh ones follow: the force comes in without an operator.
        let c = cmd(2, [1.0, 0.0, 0.0], 150_500);
        assert_eq!(
            g.filter(151_000, true, Some(&c), &ORIGIN, &spec),
            [1.0, 0.0, 0.0]
        );
        assert_eq!(g.stats().latches, 0);
    }

    #[test]
    fn link_loss_ramps_down_like_a_stall() {
        let (mut g, spec) = unlimited();
        let c = cmd(1, [3.0, 0.0, 0.0], 0);
        assert_eq!(g.filter(0, true, Some(&c), &ORIGIN, &spec), [3.0, 0.0, 0.0]);
        // Stream closed at 1 ms: the held command keeps ageing.
        let out = g.filter(35_000, false, Some(&c), &ORIGIN, &spec);
        assert!(close(out, [1.5, 0.0, 0.0]));
        assert_eq!(g.filter(60_000, false, Some(&c), &ORIGIN, &spec), [0.0; 3]);
        g.filter(100_000, false, Some(&c), &ORIGIN, &spec);
        assert_eq!(g.state(), GuardState::Disabled);
    }

    #[test]
    fn clamp_keeps_direction() {
        // (force, max, expected, clamped?)
        let table = [
            ([3.0, 4.0, 0.0], 10.0, [3.0, 4.0, 0.0], false),
            ([6.0, 8.0, 0.0], 10.0, [6.0, 8.0, 0.0], false), // exactly at the limit
            ([30.0, 40.0, 0.0], 10.0, [6.0, 8.0, 0.0], true),
            ([0.0, 0.0, -20.0], 3.3, [0.0, 0.0, -3.3], true),
            ([0.0; 3], 1.0, [0.0; 3], false),
        ];
        for (f, max, want, clamped) in table {
            let (out, c) = clamp_magnitude(f, max);
            assert_eq!(c, clamped, "{f:?}");
            assert!(close(out, want), "{f:?} -> {out:?}");
        }
    }

    #[test]
    fn the_lower_of_device_and_scene_limits_wins() {
        let (mut g, spec) = unlimited();
        g.set_app_limits(Some(Limits {
            max_force_n: 0.5,
            max_rate_n_per_s: f64::INFINITY,
        }));
        let out = g.filter(0, true, Some(&cmd(1, [0.0, 60.0, 80.0], 0)), &ORIGIN, &spec);
        assert!(close(out, [0.0, 0.3, 0.4]), "{out:?}");
        assert_eq!(g.stats().clamped, 1);
        // A scene that allows more than the device: the device wins.
        g.set_app_limits(Some(Limits {
            max_force_n: 100.0,
            max_rate_n_per_s: 1e9,
        }));
        assert_eq!(g.limits().max_force_n, 10.0);
        assert_eq!(g.limits().max_rate_n_per_s, f64::INFINITY.min(1e9));
        // The scene's rate limit slews a 5 N fault: 0.3 N per 1 ms tick at 300 N/s.
        let spec = DeviceSpec::sim_default();
        let mut p = GuardParams::from_spec(&spec);
        p.rearm_ramp_us = 1;
        let mut g = ForceGuard::new(p);
        g.set_app_limits(Some(Limits {
            max_force_n: 10.0,
            max_rate_n_per_s: 300.0,
        }));
        let mut seen = Vec::new();
        for k in 0..3 {
            let t = 1_000 * k;
            seen.push(
                g.filter(
                    t,
                    true,
                    Some(&cmd(1 + k, [5.0, 0.0, 0.0], t)),
                    &ORIGIN,
                    &spec,
                )[0],
            );
        }
        assert!(
            close([seen[0], seen[1], seen[2]], [0.3, 0.6, 0.9]),
            "{seen:?}"
        );
    }

    #[test]
    fn rate_limit_steps_at_most_max_step() {
        // (previous, target, max step, expected, limited?)
        let table = [
            ([0.0; 3], [0.5, 0.0, 0.0], 1.0, [0.5, 0.0, 0.0], false),
            ([0.0; 3], [1.0, 0.0, 0.0], 1.0, [1.0, 0.0, 0.0], false), // exactly at the limit
            ([0.0; 3], [3.0, 4.0, 0.0], 1.0, [0.6, 0.8, 0.0], true),
            (
                [1.0, 1.0, 1.0],
                [1.0, 1.0, -4.0],
                0.5,
                [1.0, 1.0, 0.5],
                true,
            ),
        ];
        for (prev, target, step, want, limited) in table {
            let (out, l) = rate_limit(prev, target, step);
            assert_eq!(l, limited);
            assert!(close(out, want), "{out:?}");
        }
    }

    #[test]
    fn nan_command_keeps_last_safe_force_and_its_age() {
        let (mut g, spec) = unlimited();
        let good = cmd(1, [1.0, 2.0, 0.0], 0);
        assert_eq!(
            g.filter(0, true, Some(&good), &ORIGIN, &spec),
            [1.0, 2.0, 0.0]
        );
        for (i, bad) in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY]
            .into_iter()
            .enumerate()
        {
            let t = 1_000 * (i as u64 + 1);
            let c = cmd(2 + i as u64, [bad, 0.0, 0.0], t);
            assert_eq!(g.filter(t, true, Some(&c), &ORIGIN, &spec), [1.0, 2.0, 0.0]);
        }
        let mut k = cmd(5, [1.0, 0.0, 0.0], 4_000);
        k.stiffness_n_per_m[4] = f64::NAN;
        g.filter(4_000, true, Some(&k), &ORIGIN, &spec);
        assert_eq!(g.stats().rejected_nan, 4);
        // The held force ages from its own pose time: half at 35 ms.
        let out = g.filter(35_000, true, None, &ORIGIN, &spec);
        assert!(close(out, [0.5, 1.0, 0.0]));
    }

    #[test]
    fn outside_workspace_commands_zero() {
        let (mut g, spec) = unlimited();
        let c = cmd(1, [1.0, 0.0, 0.0], 0);
        assert_eq!(
            g.filter(0, true, Some(&c), &at([0.5, 0.0, 0.0]), &spec),
            [0.0; 3]
        );
        assert_eq!(g.state(), GuardState::OutsideWorkspace);
        assert_eq!(
            g.filter(1_000, true, Some(&c), &ORIGIN, &spec),
            [1.0, 0.0, 0.0]
        );
        assert_eq!(g.stats().workspace_violations, 1);
    }

    #[test]
    fn the_local_model_follows_the_hand_between_updates() {
        // Contact along +x: f0 = 0.05 N at x0 = 0, K = 300 N/m along x (pressing in is -x).
        let mut k = [0.0; 9];
        k[0] = -300.0;
        let f0 = [0.05, 0.0, 0.0];
        // 0.1 mm deeper: 0.08 N; 0.1 mm out: 0.02 N; 0.2 mm out: left contact, 0; NaN-free.
        let table = [
            ([-1e-4, 0.0, 0.0], [0.08, 0.0, 0.0]),
            ([1e-4, 0.0, 0.0], [0.02, 0.0, 0.0]),
            ([2e-4, 0.0, 0.0], [0.0, 0.0, 0.0]),
            ([5e-4, 0.0, 0.0], [0.0, 0.0, 0.0]),
            // 5 mm deeper is held at the 2 mm bound: 0.05 + 0.6 N.
            ([-5e-3, 0.0, 0.0], [0.65, 0.0, 0.0]),
        ];
        for (x, want) in table {
            let f = extrapolate(f0, &k, [0.0; 3], x, 0.002);
            assert!(close(f, want), "{x:?}: {f:?}");
        }
        // No contact force: nothing to extrapolate.
        assert_eq!(
            extrapolate([0.0; 3], &k, [0.0; 3], [-1e-3, 0.0, 0.0], 0.002),
            [0.0; 3]
        );
        // Through the guard: the rendered force follows the device between two commands.
        let (mut g, spec) = unlimited();
        let c = GuardCommand {
            stiffness_n_per_m: k,
            ..cmd(1, f0, 0)
        };
        let out = g.filter(1_000, true, Some(&c), &at([-1e-4, 0.0, 0.0]), &spec);
        assert!(close(out, [0.08, 0.0, 0.0]), "{out:?}");
    }

    #[test]
    fn state_codes_round_trip() {
        for c in 0..8 {
            assert_eq!(GuardState::from_code(c).code(), c);
        }
        assert_eq!(GuardState::from_code(200), GuardState::NoCommand);
    }
}
