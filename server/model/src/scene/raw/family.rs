//! Each model family's rules about the common sections (`[model]`, `[integrator]`, `[loads]`,
//! `[active_region]`, the families' own sections).

use super::*;

/// `model.family`: FEM when absent; an unknown name lists the known ones.
pub(super) fn model_family(name: Option<&str>) -> Result<ModelFamily, ModelError> {
    match name {
        None => Ok(ModelFamily::Fem),
        Some(name) => ModelFamily::from_name(name).ok_or_else(|| {
            let known: Vec<&str> = ModelFamily::ALL.iter().map(|f| f.name()).collect();
            ModelError::field(
                "model.family",
                format!(
                    "unknown model family `{name}` (known: {})",
                    known.join(", ")
                ),
            )
        }),
    }
}

/// Which optional sections a scene has (the families refuse some of them).
pub(super) struct Present {
    /// `[loads]`.
    pub(super) loads: bool,
    /// `[active_region]`.
    pub(super) active_region: bool,
    /// `[mass_spring]`.
    pub(super) mass_spring: bool,
}

/// The mass-spring family (`springs`) integrates with symplectic Euler (the default it sets when
/// `integrator.kind` is absent) and refuses `[loads]` and `[active_region]`; the other families
/// refuse `[mass_spring]`.
pub(super) fn family_rules(
    springs: bool,
    kind: Option<&str>,
    integrator: &mut IntegratorParams,
    present: &Present,
) -> Result<(), ModelError> {
    if !springs {
        if present.mass_spring {
            return Err(ModelError::field(
                "mass_spring",
                "is only for model.family = \"mass-spring\"",
            ));
        }
        return Ok(());
    }
    match kind {
        None => integrator.kind = IntegratorKind::SymplecticEuler,
        Some(_) if integrator.kind == IntegratorKind::SymplecticEuler => {}
        Some(k) => {
            return Err(ModelError::field(
                "integrator.kind",
                format!(
                    "the mass-spring family integrates with \"symplectic-euler\" only, got `{k}`"
                ),
            ));
        }
    }
    if present.loads {
        return Err(ModelError::field(
            "loads",
            "scene loads are not supported by the mass-spring family (clients can still apply point forces)",
        ));
    }
    if present.active_region {
        return Err(ModelError::field(
            "active_region",
            "is for the FEM family with backward Euler",
        ));
    }
    Ok(())
}

/// Single-precision forces (`integrator.force_precision = "single"`) are for linear St
/// Venant-Kirchhoff or stable Neo-Hookean tetrahedra of the FEM family.
pub(super) fn single_precision_rule(
    integrator: &IntegratorParams,
    mesh: &TetMesh,
    material: &MaterialParams,
    family: ModelFamily,
) -> Result<(), ModelError> {
    if integrator.single_precision_forces
        && (mesh.is_quadratic()
            || crate::element::SingleElastic::of(material).is_none()
            || family != ModelFamily::Fem)
    {
        return Err(ModelError::field(
            "integrator.force_precision",
            "\"single\" is for linear St Venant-Kirchhoff or stable Neo-Hookean tetrahedra \
             (FEM family)",
        ));
    }
    Ok(())
}
