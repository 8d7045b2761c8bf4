//! The force guard: the bridge's last line of defence between the server's force command and the
//! device (devices.md section 4, layer L2). Pure functions plus one small state machine
//! ([`ForceGuard`]) that takes `now_us` as an argument, so every rule is tested at its exact
//! threshold with a manual clock.
//!
//! Rules and their numbers (defaults; all are [`GuardParams`] fields):
//! - **S3 fresh**: age `a` of the last valid command `<= 10 ms` -> apply it (zero-order hold).
//!   Tactile-Internet budgets are 1-10 ms; task performance drops beyond 14 ms one-way delay.
//! - **S4 stale**: `10 ms < a < 60 ms` -> hold the command but scale it linearly to reach
//!   **0 exactly at a = 60 ms** (a 50 ms ramp). A sudden zero is itself a felt "kick"
//!   (OpenHaptics `HD_FORCE_RAMPING`); packet loss alone does not hurt task performance.
//! - `a >= 60 ms`, no command yet, or **link lost** (stream closed or never opened) -> zero at
//!   once. Dropping to zero is always safe, so these bypass the slew limit.
//! - **S6 clamp**: `|F| <= max_force_n`, scaling the vector so its direction is kept (as
//!   `UpdateBallForce` in HapticMaster lab code does).
//! - **S7 slew**: `|F_k - F_(k-1)| <= max_rate_n_per_s * period_s` per tick, default rate
//!   `max_stiffness_n_per_m * 1 m/s`: a wall at the device's stable stiffness hit at 1 m/s never
//!   needs a faster rise; faster steps come from lost packets or server bugs.
//! - **S11 sanity**: a non-finite command is rejected and counted; the last safe command stays
//!   in force and keeps ageing (its age, not the rejected one's, drives the watchdog). A position
//!   outside the workspace grown by 10 % commands zero and is counted.
//!
//! Not here yet: S5 latching after 100 ms and the S9 re-arm sequence, S8 thermal limit, S10
//! dead-man, S12 passivity observer.
//!
//! Neighbours: [`crate::link`] calls [`ForceGuard::filter`] once per device tick;
//! [`crate::device::DeviceSpec`] supplies the limits.

use crate::device::{DeviceSpec, vec3};

/// Guard limits. Times are microseconds of the injected clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuardParams {
    /// Largest force magnitude sent to the device, in N (S6).
    pub max_force_n: f64,
    /// Largest change of the force vector per second, in N/s (S7).
    pub max_rate_n_per_s: f64,
    /// Nominal device tick, in s; the slew step is `max_rate_n_per_s * period_s`.
    pub period_s: f64,
    /// Commands at most this old are applied unchanged, in us (S3, default 10 000).
    pub fresh_us: u64,
    /// Age at which the ramp reaches zero, in us (S4, default 60 000).
    pub zero_us: u64,
    /// Workspace margin as a fraction of the box extent (S11, default 0.1).
    pub workspace_margin: f64,
}

impl GuardParams {
    /// Defaults from a device spec: clamp at the spec's peak force, slew at
    /// `max_stiffness_n_per_m * 1 m/s`, period `1 / rate_hz`, 10 ms / 60 ms watchdog.
    pub fn from_spec(spec: &DeviceSpec) -> Self {
        Self {
            max_force_n: spec.max_force_n,
            max_rate_n_per_s: spec.max_stiffness_n_per_m * 1.0,
            period_s: 1.0 / spec.rate_hz,
            fresh_us: 10_000,
            zero_us: 60_000,
            workspace_margin: 0.1,
        }
    }

    /// Largest change of the force vector in one tick, in N.
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

/// Where the guard's output came from on the last tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GuardState {
    /// No valid command received on this link yet: zero.
    #[default]
    NoCommand,
    /// The command is fresh (S3): applied.
    Fresh,
    /// The command is stale (S4): ramping to zero.
    Ramp,
    /// The command is older than the ramp (S4): zero.
    Expired,
    /// The link is down: zero.
    LinkLost,
    /// The position is outside the workspace (S11): zero.
    OutsideWorkspace,
}

/// A force command as the guard sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuardCommand {
    /// Changes whenever a new command arrives (the link's receive counter).
    pub generation: u64,
    /// Commanded force, in N (may be non-finite: the guard rejects it).
    pub force_n: [f64; 3],
    /// Clock time the command was received, in us.
    pub received_us: u64,
}

/// Counters of guard interventions (S14: every intervention is counted).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct GuardStats {
    /// Commands whose magnitude exceeded the clamp (counted once per command).
    pub clamped: u64,
    /// Ticks on which the slew limit cut the step.
    pub rate_limited: u64,
    /// Non-finite commands rejected.
    pub rejected_nan: u64,
    /// Entries into the stale ramp (one per episode, not per tick).
    pub watchdog_ramps: u64,
    /// Entries into the expired state (one per episode).
    pub watchdog_expired: u64,
    /// Ticks zeroed because the position was outside the workspace.
    pub workspace_violations: u64,
}

/// The guard's state: last safe command, last output, counters. Allocation-free; one per device.
#[derive(Debug, Clone)]
pub struct ForceGuard {
    params: GuardParams,
    last_generation: Option<u64>,
    /// Last valid (finite, clamped) command and its receive time.
    held: Option<([f64; 3], u64)>,
    output_n: [f64; 3],
    state: GuardState,
    stats: GuardStats,
}

impl ForceGuard {
    /// A guard with zero output and no command.
    pub fn new(params: GuardParams) -> Self {
        Self {
            params,
            last_generation: None,
            held: None,
            output_n: [0.0; 3],
            state: GuardState::NoCommand,
            stats: GuardStats::default(),
        }
    }

    /// The parameters in use.
    pub fn params(&self) -> &GuardParams {
        &self.params
    }

    /// The force returned by the last [`filter`](Self::filter), in N.
    pub fn output_n(&self) -> [f64; 3] {
        self.output_n
    }

    /// The state of the last tick.
    pub fn state(&self) -> GuardState {
        self.state
    }

    /// Intervention counters.
    pub fn stats(&self) -> GuardStats {
        self.stats
    }

    /// Forgets the held command and outputs zero from now on until a new command arrives (use
    /// when the link drops, so a stale force never resumes after a reconnect).
    pub fn reset(&mut self) {
        self.held = None;
        self.output_n = [0.0; 3];
    }

    /// One guard tick at clock time `now_us`: returns the force to write to the device, in N.
    ///
    /// `link_up` is false while no stream is open. `command` is the latest command received (the
    /// same one may be passed on many ticks; a new `generation` marks a new one). `position_m` is
    /// the device position this tick, checked against `spec`'s workspace.
    pub fn filter(
        &mut self,
        now_us: u64,
        link_up: bool,
        command: Option<&GuardCommand>,
        position_m: [f64; 3],
        spec: &DeviceSpec,
    ) -> [f64; 3] {
        let p = self.params;
        if let Some(c) = command
            && self.last_generation != Some(c.generation)
        {
            self.last_generation = Some(c.generation);
            if vec3::is_finite(c.force_n) {
                let (f, clamped) = clamp_magnitude(c.force_n, p.max_force_n);
                self.stats.clamped += u64::from(clamped);
                self.held = Some((f, c.received_us));
            } else {
                self.stats.rejected_nan += 1;
            }
        }
        let previous_state = self.state;
        let (state, target) = if !link_up {
            self.held = None;
            (GuardState::LinkLost, None)
        } else if !spec.contains(position_m, p.workspace_margin) {
            self.stats.workspace_violations += 1;
            (GuardState::OutsideWorkspace, None)
        } else {
            match self.held {
                None => (GuardState::NoCommand, None),
                Some((f, received_us)) => {
                    let age = now_us.saturating_sub(received_us);
                    let gain = watchdog_gain(age, p.fresh_us, p.zero_us);
                    if age <= p.fresh_us {
                        (GuardState::Fresh, Some(f))
                    } else if gain > 0.0 {
                        (GuardState::Ramp, Some(vec3::scale(f, gain)))
                    } else {
                        (GuardState::Expired, None)
                    }
                }
            }
        };
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
                let (f, limited) = rate_limit(self.output_n, t, p.max_step_n());
                self.stats.rate_limited += u64::from(limited);
                f
            }
        };
        self.output_n
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::{Clock, ManualClock};

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        vec3::norm(vec3::sub(a, b)) < 1e-12
    }

    /// A guard without slew limit, so watchdog numbers are seen exactly.
    fn unlimited() -> (ForceGuard, DeviceSpec) {
        let spec = DeviceSpec::sim_default();
        let mut p = GuardParams::from_spec(&spec);
        p.max_rate_n_per_s = f64::INFINITY;
        (ForceGuard::new(p), spec)
    }

    #[test]
    fn defaults_follow_the_spec() {
        let p = GuardParams::from_spec(&DeviceSpec::sim_default());
        assert_eq!(p.max_force_n, 10.0);
        assert_eq!(p.max_rate_n_per_s, 1000.0); // 1000 N/m * 1 m/s
        assert!((p.max_step_n() - 1.0).abs() < 1e-12); // 1 N per 1 ms tick
        assert_eq!((p.fresh_us, p.zero_us), (10_000, 60_000));
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
    fn guard_watchdog_follows_the_manual_clock() {
        let f = [2.0, -1.0, 0.5];
        // (age in us, expected state, expected fraction of f)
        let table = [
            (9_999, GuardState::Fresh, 1.0),
            (10_000, GuardState::Fresh, 1.0),
            (10_001, GuardState::Ramp, 49_999.0 / 50_000.0),
            (35_000, GuardState::Ramp, 0.5),
            (60_000, GuardState::Expired, 0.0),
            (60_001, GuardState::Expired, 0.0),
        ];
        for (age, state, frac) in table {
            let (mut g, spec) = unlimited();
            let clock = ManualClock::new(1_000_000);
            let cmd = GuardCommand {
                generation: 1,
                force_n: f,
                received_us: clock.now_us(),
            };
            let out = g.filter(clock.now_us(), true, Some(&cmd), [0.0; 3], &spec);
            assert!(close(out, f));
            clock.advance_us(age);
            let out = g.filter(clock.now_us(), true, Some(&cmd), [0.0; 3], &spec);
            assert_eq!(g.state(), state, "age {age} us");
            assert!(close(out, vec3::scale(f, frac)), "age {age} us: {out:?}");
        }
    }

    #[test]
    fn ramp_is_counted_once_per_episode() {
        let (mut g, spec) = unlimited();
        let cmd = GuardCommand {
            generation: 7,
            force_n: [1.0, 0.0, 0.0],
            received_us: 0,
        };
        for t in (0..=70_000).step_by(1_000) {
            g.filter(t, true, Some(&cmd), [0.0; 3], &spec);
        }
        assert_eq!(g.stats().watchdog_ramps, 1);
        assert_eq!(g.stats().watchdog_expired, 1);
        assert_eq!(g.output_n(), [0.0; 3]);
        // A new command revives the output.
        let fresh = GuardCommand {
            generation: 8,
            force_n: [1.0, 0.0, 0.0],
            received_us: 70_000,
        };
        let out = g.filter(70_500, true, Some(&fresh), [0.0; 3], &spec);
        assert_eq!(out, [1.0, 0.0, 0.0]);
        assert_eq!(g.state(), GuardState::Fresh);
    }

    #[test]
    fn link_lost_zeroes_at_once_and_forgets_the_command() {
        let (mut g, spec) = unlimited();
        let cmd = GuardCommand {
            generation: 1,
            force_n: [3.0, 0.0, 0.0],
            received_us: 0,
        };
        assert_eq!(
            g.filter(0, true, Some(&cmd), [0.0; 3], &spec),
            [3.0, 0.0, 0.0]
        );
        assert_eq!(
            g.filter(1_000, false, Some(&cmd), [0.0; 3], &spec),
            [0.0; 3]
        );
        assert_eq!(g.state(), GuardState::LinkLost);
        // The same (old) command does not come back when the link returns.
        assert_eq!(g.filter(2_000, true, Some(&cmd), [0.0; 3], &spec), [0.0; 3]);
        assert_eq!(g.state(), GuardState::NoCommand);
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
    fn guard_clamps_commands_and_counts_once() {
        let spec = DeviceSpec::sim_default();
        let mut p = GuardParams::from_spec(&spec);
        p.max_rate_n_per_s = f64::INFINITY;
        let mut g = ForceGuard::new(p);
        let cmd = GuardCommand {
            generation: 1,
            force_n: [0.0, 60.0, 80.0],
            received_us: 0,
        };
        for t in 0..5 {
            let out = g.filter(t * 1_000, true, Some(&cmd), [0.0; 3], &spec);
            assert!(close(out, [0.0, 6.0, 8.0]));
        }
        assert_eq!(g.stats().clamped, 1);
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
    fn guard_slews_a_step_command_at_one_newton_per_tick() {
        let spec = DeviceSpec::sim_default(); // 1000 N/m -> 1 N per 1 ms tick
        let mut g = ForceGuard::new(GuardParams::from_spec(&spec));
        let clock = ManualClock::new(0);
        let cmd = GuardCommand {
            generation: 1,
            force_n: [0.0, 0.0, 3.5],
            received_us: 0,
        };
        let mut seen = Vec::new();
        for _ in 0..5 {
            seen.push(g.filter(clock.now_us(), true, Some(&cmd), [0.0; 3], &spec)[2]);
            clock.advance_us(1_000);
        }
        assert_eq!(seen, vec![1.0, 2.0, 3.0, 3.5, 3.5]);
        assert_eq!(g.stats().rate_limited, 3);
    }

    #[test]
    fn nan_command_keeps_last_safe_force_and_its_age() {
        let (mut g, spec) = unlimited();
        let good = GuardCommand {
            generation: 1,
            force_n: [1.0, 2.0, 0.0],
            received_us: 0,
        };
        assert_eq!(
            g.filter(0, true, Some(&good), [0.0; 3], &spec),
            [1.0, 2.0, 0.0]
        );
        for (i, bad) in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY]
            .into_iter()
            .enumerate()
        {
            let cmd = GuardCommand {
                generation: 2 + i as u64,
                force_n: [bad, 0.0, 0.0],
                received_us: 1_000 * (i as u64 + 1),
            };
            let out = g.filter(1_000 * (i as u64 + 1), true, Some(&cmd), [0.0; 3], &spec);
            assert_eq!(out, [1.0, 2.0, 0.0]);
        }
        assert_eq!(g.stats().rejected_nan, 3);
        // The held force ages from its own receive time: ramping at 35 ms is half.
        let last = GuardCommand {
            generation: 4,
            force_n: [f64::NAN; 3],
            received_us: 3_000,
        };
        let out = g.filter(35_000, true, Some(&last), [0.0; 3], &spec);
        assert!(close(out, [0.5, 1.0, 0.0]));
    }

    #[test]
    fn outside_workspace_commands_zero() {
        let (mut g, spec) = unlimited();
        let cmd = GuardCommand {
            generation: 1,
            force_n: [1.0, 0.0, 0.0],
            received_us: 0,
        };
        assert_eq!(
            g.filter(0, true, Some(&cmd), [0.5, 0.0, 0.0], &spec),
            [0.0; 3]
        );
        assert_eq!(g.state(), GuardState::OutsideWorkspace);
        assert_eq!(
            g.filter(1_000, true, Some(&cmd), [0.0; 3], &spec),
            [1.0, 0.0, 0.0]
        );
        assert_eq!(g.stats().workspace_violations, 1);
    }
}
