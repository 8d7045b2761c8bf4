//! The `[probe]` section.

use super::*;

/// The probe section (every integrator carries every contact model:
/// [`crate::integrate::resolve_contact_model`]).
pub(super) fn build_probe(p: &RawProbe) -> Result<ProbeParams, ModelError> {
    let d = ProbeParams::default();
    let contact = match p.contact.as_deref() {
        None => d.contact,
        Some(name) => ContactModel::from_name(name).ok_or_else(|| {
            ModelError::field(
                "probe.contact",
                format!(
                    "unknown contact model {:?}: expected \"auto\", \"sphere\", \"patch\", \"patch-hertz\" or \"patch-local\"",
                    name.chars().take(40).collect::<String>()
                ),
            )
        })?,
    };
    let params = ProbeParams {
        contact,
        radius_m: positive("probe.radius_m", p.radius_m.unwrap_or(d.radius_m))?,
        coupling_stiffness_n_per_m: positive(
            "probe.coupling_stiffness_n_per_m",
            p.coupling_stiffness_n_per_m
                .unwrap_or(d.coupling_stiffness_n_per_m),
        )?,
        coupling_damping_n_s_per_m: non_negative(
            "probe.coupling_damping_n_s_per_m",
            p.coupling_damping_n_s_per_m
                .unwrap_or(d.coupling_damping_n_s_per_m),
        )?,
        max_force_n: positive("probe.max_force_n", p.max_force_n.unwrap_or(d.max_force_n))?,
        friction_coefficient: checked(
            "probe.friction_coefficient",
            p.friction_coefficient.unwrap_or(d.friction_coefficient),
            |mu| (0.0..=10.0).contains(&mu),
            "in [0, 10]",
        )?,
        hertz_modulus_pa: d.hertz_modulus_pa,
    };
    Ok(params)
}
