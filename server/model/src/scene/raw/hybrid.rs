//! The `[hybrid]` section.

use super::*;

// ----- hybrid section -----

pub(super) fn build_hybrid(
    h: &RawHybrid,
    mesh: &RawMesh,
    unit_m: f64,
) -> Result<HybridScene, ModelError> {
    let mm = 1e-3;
    let geometry = match mesh.builtin.as_deref() {
        Some("lv") => ShellGeometry {
            inner_m: DVec3::new(7.0, 7.0, 17.0) * mm,
            outer_m: DVec3::new(10.0, 10.0, 20.0) * mm,
            z_cut_m: Some(5.0 * mm),
        },
        Some("ellipsoids") => ShellGeometry {
            inner_m: mesh
                .inner_semi_axes
                .map_or(Ok(DVec3::new(6e-3, 6e-3, 12e-3)), |v| {
                    positive_vec("mesh.inner_semi_axes", v, unit_m)
                })?,
            outer_m: mesh
                .outer_semi_axes
                .map_or(Ok(DVec3::new(10e-3, 10e-3, 16e-3)), |v| {
                    positive_vec("mesh.outer_semi_axes", v, unit_m)
                })?,
            z_cut_m: None,
        },
        _ => {
            return Err(ModelError::field(
                "mesh.builtin",
                "model.family = \"hybrid\" needs mesh.builtin = \"lv\" or \"ellipsoids\" (a wall between two ellipsoids)",
            ));
        }
    };
    let d = HybridParams::default();
    let inactive_layer = h
        .inactive_layer
        .as_deref()
        .map_or(Ok(d.inactive_layer), InactiveLayer::parse)?;
    let core_order = match mesh.order.unwrap_or(1) {
        o @ (1 | 2) => o as u8,
        o => {
            return Err(ModelError::field(
                "mesh.order",
                format!("must be 1 or 2, got {o}"),
            ));
        }
    };
    let variant = match h.variant.as_deref() {
        None => MeshfreeVariant::default(),
        Some(v) => MeshfreeVariant::from_name(v).ok_or_else(|| {
            ModelError::field(
                "hybrid.variant",
                format!("unknown variant `{v}` (expected seed or corrected)"),
            )
        })?,
    };
    let kernel = match h.kernel.as_deref() {
        None => KernelKind::default_for(variant),
        Some(k) => KernelKind::from_name(k).ok_or_else(|| {
            ModelError::field(
                "hybrid.kernel",
                format!("unknown kernel `{k}` (expected seed-linear or wendland-c2)"),
            )
        })?,
    };
    let spacing_m = positive(
        "hybrid.spacing_m",
        required("hybrid.spacing_m", h.spacing_m)?,
    )?;
    let opt_int = |field: &str, v: Option<i64>, default: usize, lo: i64, hi: i64| {
        v.map_or(Ok(default), |v| int_in(field, v, lo, hi))
    };
    let params = HybridParams {
        meshfree: MeshfreeParams {
            variant,
            kernel,
            spacing_m,
            smoothing_ratio: h.smoothing_ratio.unwrap_or(d.meshfree.smoothing_ratio),
            hourglass_coefficient: h
                .hourglass_coefficient
                .unwrap_or(d.meshfree.hourglass_coefficient),
        },
        core_fraction: h.core_fraction.unwrap_or(d.core_fraction),
        surface_target_tets: opt_int(
            "hybrid.surface_target_tets",
            h.surface_target_tets,
            d.surface_target_tets,
            100,
            200_000,
        )?,
        activation_radius_m: h.activation_radius_m.unwrap_or(d.activation_radius_m),
        release_radius_m: h.release_radius_m.unwrap_or(d.release_radius_m),
        release_tolerance_m: h.release_tolerance_m.unwrap_or(d.release_tolerance_m),
        max_active_particles: opt_int(
            "hybrid.max_active_particles",
            h.max_active_particles,
            d.max_active_particles,
            1,
            1_000_000,
        )?,
        contact_stiffness_n_per_m: h
            .contact_stiffness_n_per_m
            .unwrap_or(d.contact_stiffness_n_per_m),
        mass_scale: h.mass_scale.unwrap_or(d.mass_scale),
        core_mass_scale: match &h.core_mass_scale {
            None => CoreMassScale::Uniform,
            Some(RawCoreMassScale::Number(v)) => CoreMassScale::Fixed(*v),
            Some(RawCoreMassScale::Name(t)) => CoreMassScale::parse(t)?,
        },
        scaled_motion: h
            .scaled_motion
            .as_deref()
            .map_or(Ok(d.scaled_motion), ScaledMotion::parse)?,
        core_step: CoreStep::parse(
            h.core_step.as_deref().unwrap_or("explicit"),
            h.core_stiffness_margin,
        )?,
        inactive_layer,
        core_order,
        safety_factor: h.safety_factor.unwrap_or(d.safety_factor),
        max_substeps: opt_int(
            "hybrid.max_substeps",
            h.max_substeps,
            d.max_substeps as usize,
            1,
            10_000,
        )? as u32,
    };
    params.validate()?;
    let core_target_tets = mesh
        .target_tets
        .map_or(Ok(200), |t| int_in("mesh.target_tets", t, 100, 500_000))?;
    Ok(HybridScene {
        geometry,
        params,
        core_target_tets,
    })
}

/// The `[hybrid]` section: required for the hybrid family, refused for the others.
pub(super) fn hybrid_section(
    family: ModelFamily,
    section: Option<&RawHybrid>,
    mesh_raw: &RawMesh,
    length_unit_m: f64,
) -> Result<Option<HybridScene>, ModelError> {
    if family == ModelFamily::Hybrid {
        let section = required("hybrid", section)?;
        Ok(Some(build_hybrid(section, mesh_raw, length_unit_m)?))
    } else if section.is_some() {
        Err(ModelError::field(
            "hybrid",
            "is only for model.family = \"hybrid\"",
        ))
    } else {
        Ok(None)
    }
}
