//! The coarse companion of a following active region ([`super`] module documentation, "The
//! coarse companion"): a coarse whole-body [`FemBody`] ticked with the same device input, whose
//! answer is blended into the region's where the contact patch leaves the region.
//!
//! Owns: the companion's blend state and statistics. May use: its parent [`super`] (the FEM
//! body) and [`crate::body`] (tick input and output).

use glam::DVec3;

use super::{FALLBACK_BLEND_TICKS, FALLBACK_SETTLE_TICKS, FemBody};
use crate::ModelError;
use crate::body::{TickInput, TickOutput};

/// The coarse whole-body companion of a following region and its blending state.
#[derive(Debug, Clone)]
pub(super) struct Fallback {
    sim: FemBody,
    /// Weight of the companion's answer in the output, in `[0, 1]`.
    weight: f64,
    /// Ticks until the region may take the probe back (counts down while it holds the patch).
    settle_ticks: u32,
    /// Ticks with a nonzero weight.
    ticks_answered: u64,
    /// Of those, the ticks whose output is in contact.
    contact_ticks_answered: u64,
    /// The region's own force in the last tick, N.
    region_force_n: DVec3,
    /// The companion's own force in the last tick, N.
    companion_force_n: DVec3,
}

/// What the coarse companion of a following region did ([`FemBody::fallback_stats`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FallbackStats {
    /// The companion's weight in the last output, in `[0, 1]`.
    pub weight: f64,
    /// Ticks in which it contributed to the output.
    pub ticks_answered: u64,
    /// Of those, the ticks in contact.
    pub contact_ticks_answered: u64,
    /// Its tetrahedra.
    pub elements: usize,
    /// The force the region alone gave in the last tick (before the blend), N.
    pub region_force_n: DVec3,
    /// The force the companion alone gave in the last tick (before the blend), N.
    pub companion_force_n: DVec3,
}

impl Fallback {
    /// The companion `sim`, not yet answering (weight 0).
    pub(super) fn new(sim: FemBody) -> Self {
        Self {
            sim,
            weight: 0.0,
            settle_ticks: 0,
            ticks_answered: 0,
            contact_ticks_answered: 0,
            region_force_n: DVec3::ZERO,
            companion_force_n: DVec3::ZERO,
        }
    }

    /// What it did so far ([`FemBody::fallback_stats`]).
    pub(super) fn stats(&self) -> FallbackStats {
        FallbackStats {
            weight: self.weight,
            ticks_answered: self.ticks_answered,
            contact_ticks_answered: self.contact_ticks_answered,
            elements: self.sim.fem.element_count(),
            region_force_n: self.region_force_n,
            companion_force_n: self.companion_force_n,
        }
    }

    /// Ticks the companion with `input` (on a pool worker beside the region: it shares no
    /// state with it).
    ///
    /// # Errors
    /// The companion's tick errors (a diverged companion quarantines the session as the
    /// region would).
    pub(super) fn tick_companion(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        self.sim.tick(input)
    }

    /// Blends the companion's answer `coarse` of this tick into the region's `fine` one:
    /// `outside` when the region's contact patch reaches a node it does not simulate, `swapped`
    /// when a new region came in this tick (module documentation, "The coarse companion").
    pub(super) fn blend(
        &mut self,
        fine: TickOutput,
        coarse: TickOutput,
        outside: bool,
        swapped: bool,
    ) -> TickOutput {
        self.region_force_n = fine.force_on_device_n;
        self.companion_force_n = coarse.force_on_device_n;
        if outside || (swapped && self.weight > 0.0) {
            self.settle_ticks = FALLBACK_SETTLE_TICKS;
        } else {
            self.settle_ticks = self.settle_ticks.saturating_sub(1);
        }
        let target = if self.settle_ticks > 0 { 1.0 } else { 0.0 };
        let rate = 1.0 / f64::from(FALLBACK_BLEND_TICKS);
        self.weight += (target - self.weight).clamp(-rate, rate);
        let w = self.weight;
        if w <= 0.0 {
            return fine;
        }
        self.ticks_answered += 1;
        let main = if w >= 0.5 { coarse } else { fine };
        let mut stiffness = fine.contact_stiffness_n_per_m;
        for (k, c) in stiffness.iter_mut().zip(coarse.contact_stiffness_n_per_m) {
            *k += w * (c - *k);
        }
        let in_contact = fine.in_contact || coarse.in_contact;
        self.contact_ticks_answered += u64::from(in_contact);
        TickOutput {
            force_on_device_n: fine.force_on_device_n.lerp(coarse.force_on_device_n, w),
            contact_stiffness_n_per_m: stiffness,
            in_contact,
            proxy_position_m: main.proxy_position_m,
            sim_time_s: fine.sim_time_s,
        }
    }
}
