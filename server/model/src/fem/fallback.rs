//! The coarse companion of a following active region ([`super`] module documentation, "The
//! coarse companion"): a coarse whole-body [`FemBody`] ticked with the same device inputs, whose
//! answer for a tool is blended into the region's where that tool's contact patch leaves the
//! region.
//!
//! Owns: the companion's blend state and statistics. May use: its parent [`super`] (the FEM
//! body) and [`crate::body`] (tick input and output).

use glam::DVec3;

use super::{FALLBACK_BLEND_TICKS, FALLBACK_SETTLE_TICKS, FemBody};
use crate::ModelError;
use crate::body::{MAX_TOOLS, TickInput, TickOutput};

/// The coarse whole-body companion of a following region and its blending state.
#[derive(Debug, Clone)]
pub(super) struct Fallback {
    sim: FemBody,
    /// Per tool slot: weight of the companion's answer in the output, in `[0, 1]`.
    weight: [f64; MAX_TOOLS],
    /// Per tool slot: ticks until the region may take the tool back (counts down while it
    /// holds the tool's patch).
    settle_ticks: [u32; MAX_TOOLS],
    /// Ticks with a nonzero weight.
    ticks_answered: u64,
    /// Of those, the ticks whose output is in contact.
    contact_ticks_answered: u64,
    /// The region's own force in the last tick per slot, N.
    region_force_n: [DVec3; MAX_TOOLS],
    /// The companion's own force in the last tick per slot, N.
    companion_force_n: [DVec3; MAX_TOOLS],
}

/// What the coarse companion of a following region did ([`FemBody::fallback_stats`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FallbackStats {
    /// The companion's weight in the last output of tool slot 0, in `[0, 1]`.
    pub weight: f64,
    /// Its weight per tool slot.
    pub weights: [f64; MAX_TOOLS],
    /// Ticks in which it contributed to an output.
    pub ticks_answered: u64,
    /// Of those, the ticks in contact.
    pub contact_ticks_answered: u64,
    /// Its tetrahedra.
    pub elements: usize,
    /// The force the region alone gave tool slot 0 in the last tick (before the blend), N.
    pub region_force_n: DVec3,
    /// The force the companion alone gave tool slot 0 in the last tick (before the blend), N.
    pub companion_force_n: DVec3,
    /// [`Self::region_force_n`] per tool slot, N.
    pub region_forces_n: [DVec3; MAX_TOOLS],
    /// [`Self::companion_force_n`] per tool slot, N.
    pub companion_forces_n: [DVec3; MAX_TOOLS],
}

impl Fallback {
    /// The companion `sim`, not yet answering (weight 0).
    pub(super) fn new(sim: FemBody) -> Self {
        Self {
            sim,
            weight: [0.0; MAX_TOOLS],
            settle_ticks: [0; MAX_TOOLS],
            ticks_answered: 0,
            contact_ticks_answered: 0,
            region_force_n: [DVec3::ZERO; MAX_TOOLS],
            companion_force_n: [DVec3::ZERO; MAX_TOOLS],
        }
    }

    /// What it did so far ([`FemBody::fallback_stats`]).
    pub(super) fn stats(&self) -> FallbackStats {
        FallbackStats {
            weight: self.weight[0],
            weights: self.weight,
            ticks_answered: self.ticks_answered,
            contact_ticks_answered: self.contact_ticks_answered,
            elements: self.sim.fem.element_count(),
            region_force_n: self.region_force_n[0],
            companion_force_n: self.companion_force_n[0],
            region_forces_n: self.region_force_n,
            companion_forces_n: self.companion_force_n,
        }
    }

    /// Ticks the companion with every slot's `inputs` into `outputs` (on a pool worker beside
    /// the region: it shares no state with it).
    ///
    /// # Errors
    /// The companion's tick errors (a diverged companion quarantines the session as the
    /// region would).
    pub(super) fn tick_companion(
        &mut self,
        inputs: &[TickInput],
        outputs: &mut [TickOutput],
    ) -> Result<(), ModelError> {
        self.sim.tick_tools(inputs, outputs)
    }

    /// Blends the companion's answers `coarse` of this tick into the region's `fine` ones, slot
    /// by slot into `out`: `outside[k]` when slot `k`'s contact patch reaches a node the region
    /// does not simulate, `swapped` when a new region came in this tick (module documentation,
    /// "The coarse companion"). A tick counts as answered when some slot's weight is nonzero.
    pub(super) fn blend(
        &mut self,
        fine: &[TickOutput],
        coarse: &[TickOutput],
        outside: &[bool],
        swapped: bool,
        out: &mut [TickOutput],
    ) {
        let (mut answered, mut in_contact) = (false, false);
        for (k, ((o, (&f, &c)), &away)) in out
            .iter_mut()
            .zip(fine.iter().zip(coarse))
            .zip(outside)
            .enumerate()
            .take(MAX_TOOLS)
        {
            *o = self.blend_slot(k, f, c, away, swapped);
            answered |= self.weight[k] > 0.0;
            in_contact |= self.weight[k] > 0.0 && o.in_contact;
        }
        self.ticks_answered += u64::from(answered);
        self.contact_ticks_answered += u64::from(in_contact);
    }

    /// [`Self::blend`] of slot `k`.
    fn blend_slot(
        &mut self,
        k: usize,
        fine: TickOutput,
        coarse: TickOutput,
        outside: bool,
        swapped: bool,
    ) -> TickOutput {
        self.region_force_n[k] = fine.force_on_device_n;
        self.companion_force_n[k] = coarse.force_on_device_n;
        if outside || (swapped && self.weight[k] > 0.0) {
            self.settle_ticks[k] = FALLBACK_SETTLE_TICKS;
        } else {
            self.settle_ticks[k] = self.settle_ticks[k].saturating_sub(1);
        }
        let target = if self.settle_ticks[k] > 0 { 1.0 } else { 0.0 };
        let rate = 1.0 / f64::from(FALLBACK_BLEND_TICKS);
        self.weight[k] += (target - self.weight[k]).clamp(-rate, rate);
        let w = self.weight[k];
        if w <= 0.0 {
            return fine;
        }
        let main = if w >= 0.5 { coarse } else { fine };
        let mut stiffness = fine.contact_stiffness_n_per_m;
        for (s, c) in stiffness.iter_mut().zip(coarse.contact_stiffness_n_per_m) {
            *s += w * (c - *s);
        }
        TickOutput {
            force_on_device_n: fine.force_on_device_n.lerp(coarse.force_on_device_n, w),
            contact_stiffness_n_per_m: stiffness,
            in_contact: fine.in_contact || coarse.in_contact,
            proxy_position_m: main.proxy_position_m,
            sim_time_s: fine.sim_time_s,
        }
    }
}
