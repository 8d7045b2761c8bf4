//! Time-domain passivity at the bridge-device port: a passivity observer (energy bookkeeping)
//! and a passivity controller (adaptive damping that dissipates any energy the far side would
//! inject), after Ryu, Kwon and Hannaford, "Stability guaranteed control: time domain passivity
//! approach" (devices.md \[S24\], \[S25\]; section 4 rule S12).
//!
//! Sign convention: `f` is the force rendered on the hand (N), `v` the device velocity (m/s).
//! The observer sums the energy the environment (server, network and local model together)
//! has *absorbed* from the hand, `E(n) = E(n-1) - f(n) . v(n) T` (J). A passive environment
//! keeps `E >= 0`: it can give back at most what it was given. Delay makes it active (the force
//! lags the motion, so releasing returns more than pressing stored), and `E` goes negative.
//! The controller then adds a damping force `-alpha v` with
//! `alpha = -E / (|v|^2 T)`, capped at `max_damping_n_s_per_m`, which dissipates exactly the
//! excess (or as much of it as the cap allows) in the same tick. The deficit a delay leaves at
//! the end of a release is often still there when the hand leaves the surface: the controller
//! then dissipates it in free space, a brief drag of at most `max_damping_n_s_per_m` times the
//! speed (0.02 N at 10 mm/s on the sim device, a few ticks in the LV demo). Acting only in
//! contact was tried: it left 9 % of the injected energy with 20 ms of delay
//! (`tests/passivity.rs`), so the drag is the price of passivity.
//!
//! Neighbours: [`crate::guard::ForceGuard`] calls [`PassivityController::apply`] once per
//! device tick, after the watchdog gains and before the clamp and slew limit.

use crate::device::vec3;

/// What the passivity layer does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PassivityMode {
    /// Nothing (no bookkeeping).
    Off,
    /// Observe only: the energy is tracked and reported, the force is not changed.
    Observe,
    /// Observe and dissipate (the default).
    #[default]
    Control,
}

/// Passivity parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PassivityParams {
    /// Off, observe or control.
    pub mode: PassivityMode,
    /// Largest damping the controller adds, in N s/m (a device's `HD_NOMINAL_MAX_DAMPING`;
    /// more would itself destabilise the device).
    pub max_damping_n_s_per_m: f64,
}

/// Counters and state of the observer.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PassivityStats {
    /// Energy absorbed by the environment so far, J (the observer's `E`).
    pub energy_j: f64,
    /// Energy the controller dissipated in total, J.
    pub dissipated_j: f64,
    /// Ticks on which the controller added damping.
    pub active_ticks: u64,
    /// Smallest `E` the observer saw before control, J (how active the far side tried to be).
    pub min_energy_j: f64,
}

/// The observer and controller. Allocation-free; one per device.
#[derive(Debug, Clone)]
pub struct PassivityController {
    params: PassivityParams,
    stats: PassivityStats,
}

impl PassivityController {
    /// A controller with zero stored energy.
    pub fn new(params: PassivityParams) -> Self {
        Self {
            params,
            stats: PassivityStats::default(),
        }
    }

    /// Counters.
    pub fn stats(&self) -> PassivityStats {
        self.stats
    }

    /// Forgets the stored energy (call when the output was disabled: a new episode starts).
    pub fn reset(&mut self) {
        self.stats.energy_j = 0.0;
    }

    /// One tick: `force_n` (N) is about to be rendered while the device moves at
    /// `velocity_m_per_s` (m/s) for `dt_s` (s). Returns the force to render, with the
    /// dissipating damping added when the observer finds the port active.
    pub fn apply(&mut self, force_n: [f64; 3], velocity_m_per_s: [f64; 3], dt_s: f64) -> [f64; 3] {
        if self.params.mode == PassivityMode::Off
            || !vec3::is_finite(velocity_m_per_s)
            || !dt_s.is_finite()
            || dt_s <= 0.0
        {
            return force_n;
        }
        let v = velocity_m_per_s;
        let e = self.stats.energy_j - vec3::dot(force_n, v) * dt_s;
        self.stats.min_energy_j = self.stats.min_energy_j.min(e);
        let v2 = vec3::dot(v, v);
        if e >= 0.0 || self.params.mode == PassivityMode::Observe || v2 <= 0.0 {
            self.stats.energy_j = e;
            return force_n;
        }
        let alpha = (-e / (v2 * dt_s)).min(self.params.max_damping_n_s_per_m.max(0.0));
        let dissipated = alpha * v2 * dt_s;
        self.stats.energy_j = e + dissipated;
        self.stats.dissipated_j += dissipated;
        self.stats.active_ticks += 1;
        vec3::axpy(force_n, -alpha, v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pc(mode: PassivityMode, b: f64) -> PassivityController {
        PassivityController::new(PassivityParams {
            mode,
            max_damping_n_s_per_m: b,
        })
    }

    #[test]
    fn a_spring_without_delay_is_passive_and_untouched() {
        // Press 1 mm into a 300 N/m wall and back, 1 ms ticks at 10 mm/s.
        let mut c = pc(PassivityMode::Control, 10.0);
        let mut x = 0.0_f64;
        for i in 0..200 {
            let v = if i < 100 { 0.01 } else { -0.01 };
            x += v * 1e-3;
            let f = [-300.0 * x.max(0.0), 0.0, 0.0];
            let out = c.apply(f, [v, 0.0, 0.0], 1e-3);
            assert_eq!(out, f);
        }
        // The sampled spring returns a little less than it stored (2 % of the 0.15 mJ at the
        // deepest point): passive, never active.
        let e = c.stats().energy_j;
        assert!((0.0..5e-6).contains(&e), "{:?}", c.stats());
        assert_eq!(c.stats().active_ticks, 0);
    }

    #[test]
    fn an_active_force_is_damped_until_the_energy_is_back_to_zero() {
        // A force pushing along the motion injects energy; the controller removes it each tick.
        let mut c = pc(PassivityMode::Control, 1e9);
        let out = c.apply([1.0, 0.0, 0.0], [0.1, 0.0, 0.0], 1e-3);
        // E would be -1e-4 J; alpha = 1e-4 / (0.01 * 1e-3) = 10 N s/m; f = 1 - 10 * 0.1 = 0.
        assert!((out[0] - 0.0).abs() < 1e-12, "{out:?}");
        assert!(c.stats().energy_j.abs() < 1e-15);
        assert!((c.stats().dissipated_j - 1e-4).abs() < 1e-15);
        // The cap limits the damping: then the energy stays negative.
        let mut c = pc(PassivityMode::Control, 2.0);
        let out = c.apply([1.0, 0.0, 0.0], [0.1, 0.0, 0.0], 1e-3);
        assert!((out[0] - 0.8).abs() < 1e-12, "{out:?}");
        assert!(c.stats().energy_j < 0.0);
        // Observe mode reports without changing the force.
        let mut c = pc(PassivityMode::Observe, 2.0);
        assert_eq!(
            c.apply([1.0, 0.0, 0.0], [0.1, 0.0, 0.0], 1e-3),
            [1.0, 0.0, 0.0]
        );
        assert!(c.stats().energy_j < 0.0);
    }
}
