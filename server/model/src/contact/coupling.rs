//! The virtual coupling's implicit term as a rank-one matrix `gamma U U^T` over the contact
//! patch, shared by the probe (which builds it) and the implicit integrators (which solve with
//! it): the type both sides use, so that neither module imports the other.

use glam::DVec3;

/// The probe's virtual coupling as a rank-one term `gamma U U^T` of the backward Euler matrix,
/// `U = (w_i n)` over the contact patch (see [`crate::contact::Probe::coupling_gamma`]).
#[derive(Debug, Clone, Copy)]
pub struct RankOneCoupling<'a> {
    /// `gamma = h (k h + b)`, kg.
    pub gamma_kg: f64,
    /// Unit contact normal.
    pub normal: DVec3,
    /// Patch nodes.
    pub nodes: &'a [u32],
    /// Patch weights (sum 1), same length as `nodes`.
    pub weights: &'a [f64],
}

impl RankOneCoupling<'_> {
    /// `U^T p` for a nodal field `p` (one vector per body node).
    pub fn ut(&self, p: &[DVec3]) -> f64 {
        self.nodes
            .iter()
            .zip(self.weights)
            .map(|(&i, &w)| w * self.normal.dot(p[i as usize]))
            .sum()
    }
}
