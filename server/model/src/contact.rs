//! Haptic probe contact. Placeholder; filled in by the FEM core change.

/// Haptic probe and virtual coupling parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeParams {
    /// Probe sphere radius, m.
    pub radius_m: f64,
    /// Virtual coupling stiffness between proxy and device point, N/m.
    pub coupling_stiffness_n_per_m: f64,
    /// Virtual coupling damping, N s/m.
    pub coupling_damping_n_s_per_m: f64,
    /// Largest coupling force magnitude the model applies and returns, N.
    pub max_force_n: f64,
}

impl Default for ProbeParams {
    fn default() -> Self {
        Self {
            radius_m: 2e-3,
            coupling_stiffness_n_per_m: 300.0,
            coupling_damping_n_s_per_m: 0.5,
            max_force_n: 10.0,
        }
    }
}
