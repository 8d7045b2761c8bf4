//! The `[material]` section and its fibres.

use super::*;

/// The Guccione keys of `[material]` (`model = "guccione"`); refused with other models.
pub(super) fn build_guccione(m: &RawMaterial, density: f64) -> Result<MaterialParams, ModelError> {
    let guccione = m.model.as_deref() == Some("guccione");
    let given: [(&str, bool); 6] = [
        ("material.guccione_c_pa", m.guccione_c_pa.is_some()),
        ("material.b_f", m.b_f.is_some()),
        ("material.b_t", m.b_t.is_some()),
        ("material.b_fs", m.b_fs.is_some()),
        ("material.bulk_modulus_pa", m.bulk_modulus_pa.is_some()),
        ("material.volumetric", m.volumetric.is_some()),
    ];
    if !guccione {
        if let Some((field, _)) = given.iter().find(|g| g.1) {
            return Err(ModelError::field(
                *field,
                "only applies to material.model = \"guccione\"",
            ));
        }
        return Err(ModelError::field(
            "material.model",
            "internal: not guccione",
        ));
    }
    for (field, present) in [
        ("material.youngs_modulus_pa", m.youngs_modulus_pa.is_some()),
        ("material.poisson_ratio", m.poisson_ratio.is_some()),
        ("material.lambda_pa", m.lambda_pa.is_some()),
        ("material.mu_pa", m.mu_pa.is_some()),
    ] {
        if present {
            return Err(ModelError::field(
                field,
                "does not apply to material.model = \"guccione\" (give guccione_c_pa, b_f, b_t, b_fs, bulk_modulus_pa)",
            ));
        }
    }
    let c = positive(
        "material.guccione_c_pa",
        required("material.guccione_c_pa", m.guccione_c_pa)?,
    )?;
    let b = |field: &str, v: Option<f64>| positive(field, required(field, v)?);
    let mean_dilatation = match m.volumetric.as_deref() {
        None | Some("mean-dilatation") => true,
        Some("point") => false,
        Some(other) => {
            return Err(ModelError::field(
                "material.volumetric",
                format!(
                    "unknown volumetric treatment `{other}` (expected \"mean-dilatation\" or \"point\")"
                ),
            ));
        }
    };
    let g = crate::material::GuccioneParams {
        c_pa: c,
        b_f: b("material.b_f", m.b_f)?,
        b_t: b("material.b_t", m.b_t)?,
        b_fs: b("material.b_fs", m.b_fs)?,
        bulk_modulus_pa: positive(
            "material.bulk_modulus_pa",
            required("material.bulk_modulus_pa", m.bulk_modulus_pa)?,
        )?,
        mean_dilatation,
    };
    Ok(MaterialParams::with_guccione(g, density))
}

/// The fibre rule of `[material.fibres]`: `(endo surface, epi surface, rule)`; `None` when the
/// material needs no frame (not an anisotropic Guccione law) and the section is absent.
pub(super) fn build_fibres(
    m: &RawMaterial,
    mat: &MaterialParams,
    mesh: &TetMesh,
) -> Result<Option<crate::scene::FibreSpec>, ModelError> {
    if m.fibres.is_some() && mat.model != MaterialModel::Guccione {
        return Err(ModelError::field(
            "material.fibres",
            "only applies to material.model = \"guccione\"",
        ));
    }
    if m.fibres.is_none() && !mat.is_anisotropic() {
        return Ok(None);
    }
    let f = m.fibres.as_ref();
    let endo = f
        .and_then(|f| f.endo.clone())
        .unwrap_or_else(|| "ENDO".into());
    let epi = f
        .and_then(|f| f.epi.clone())
        .unwrap_or_else(|| "EPI".into());
    for (field, name) in [
        ("material.fibres.endo", &endo),
        ("material.fibres.epi", &epi),
    ] {
        if mesh.surface(name).is_none() {
            let known: Vec<&str> = mesh.surfaces.iter().map(|s| s.name.as_str()).collect();
            return Err(ModelError::field(
                field,
                format!(
                    "no surface named `{name}` for the fibre rule (mesh surfaces: {})",
                    known.join(", ")
                ),
            ));
        }
    }
    let d = crate::element::FibreRule::default();
    let angle = |field: &str, v: Option<f64>, default: f64| {
        checked(
            field,
            v.unwrap_or(default),
            |x| x.abs() <= 180.0,
            "in [-180, 180] degrees",
        )
    };
    let axis = match f.and_then(|f| f.long_axis) {
        Some(a) => {
            let v = bounded_vec("material.fibres.long_axis", a, 1e9)?;
            if v.length() == 0.0 {
                return Err(ModelError::field(
                    "material.fibres.long_axis",
                    "must not be zero",
                ));
            }
            v.normalize()
        }
        None => d.long_axis,
    };
    Ok(Some(crate::scene::FibreSpec {
        endo_surface: endo,
        epi_surface: epi,
        rule: crate::element::FibreRule {
            helix_endo_deg: angle(
                "material.fibres.helix_endo_deg",
                f.and_then(|f| f.helix_endo_deg),
                d.helix_endo_deg,
            )?,
            helix_epi_deg: angle(
                "material.fibres.helix_epi_deg",
                f.and_then(|f| f.helix_epi_deg),
                d.helix_epi_deg,
            )?,
            long_axis: axis,
        },
    }))
}

pub(super) fn build_material(m: &RawMaterial) -> Result<MaterialParams, ModelError> {
    const E: &str = "material.youngs_modulus_pa";
    const NU: &str = "material.poisson_ratio";
    const LAMBDA: &str = "material.lambda_pa";
    const MU: &str = "material.mu_pa";
    let density = required("material.density_kg_per_m3", m.density_kg_per_m3)?;
    let density = positive("material.density_kg_per_m3", density)?;
    if m.model.as_deref() == Some("guccione")
        || m.guccione_c_pa.is_some()
        || m.b_f.is_some()
        || m.b_t.is_some()
        || m.b_fs.is_some()
        || m.bulk_modulus_pa.is_some()
        || m.volumetric.is_some()
    {
        let mut mat = build_guccione(m, density)?;
        mat.phi_pa_s = non_negative("material.phi_pa_s", m.phi_pa_s.unwrap_or(0.0))?;
        mat.psi_pa_s = non_negative("material.psi_pa_s", m.psi_pa_s.unwrap_or(0.0))?;
        mat.mass_damping_per_s = non_negative(
            "material.mass_damping_per_s",
            m.mass_damping_per_s.unwrap_or(0.0),
        )?;
        mat.validate()?;
        return Ok(mat);
    }
    let engineering = m.youngs_modulus_pa.is_some() || m.poisson_ratio.is_some();
    let lame = m.lambda_pa.is_some() || m.mu_pa.is_some();
    let mut mat = match (engineering, lame) {
        (true, true) => {
            let field = if m.lambda_pa.is_some() { LAMBDA } else { MU };
            return Err(ModelError::field(
                field,
                "give exactly one pair: youngs_modulus_pa + poisson_ratio, or lambda_pa + mu_pa",
            ));
        }
        (false, false) => {
            return Err(ModelError::field(
                E,
                "is required (with poisson_ratio), or give lambda_pa + mu_pa",
            ));
        }
        (true, false) => {
            let e = positive(E, required(E, m.youngs_modulus_pa)?)?;
            let nu = checked(
                NU,
                required(NU, m.poisson_ratio)?,
                |x| x > -1.0 && x < 0.5,
                "in (-1, 0.5)",
            )?;
            let mat = MaterialParams::from_youngs(e, nu, density);
            if mat.lambda_pa < 0.0 {
                return Err(ModelError::field(
                    NU,
                    format!("{nu} gives lambda < 0, which the model does not support"),
                ));
            }
            mat
        }
        (false, true) => {
            let lambda = non_negative(LAMBDA, required(LAMBDA, m.lambda_pa)?)?;
            let mu = positive(MU, required(MU, m.mu_pa)?)?;
            MaterialParams {
                model: Default::default(),
                lambda_pa: lambda,
                mu_pa: mu,
                density_kg_per_m3: density,
                ..MaterialParams::from_youngs(1.0, 0.0, 1.0)
            }
        }
    };
    if let Some(name) = &m.model {
        mat.model = MaterialModel::from_scene_name(name).ok_or_else(|| {
            ModelError::field(
                "material.model",
                format!(
                    "unknown material model `{name}` (expected \"stvk\", \"corotational\", \"stable-neo-hookean\" or \"guccione\")"
                ),
            )
        })?;
    }
    mat.phi_pa_s = non_negative("material.phi_pa_s", m.phi_pa_s.unwrap_or(0.0))?;
    mat.psi_pa_s = non_negative("material.psi_pa_s", m.psi_pa_s.unwrap_or(0.0))?;
    mat.mass_damping_per_s = non_negative(
        "material.mass_damping_per_s",
        m.mass_damping_per_s.unwrap_or(0.0),
    )?;
    mat.validate()?;
    Ok(mat)
}

/// The material and its fibre frame: required for the volume families, refused for the
/// mass-spring family (`springs`), which takes its constants from `[mass_spring]`.
pub(super) fn material_section(
    raw_material: Option<RawMaterial>,
    mesh: &TetMesh,
    springs: bool,
) -> Result<(MaterialParams, Option<crate::scene::FibreSpec>), ModelError> {
    if springs {
        if raw_material.is_some() {
            return Err(ModelError::field(
                "material",
                "the mass-spring family takes its constants from [mass_spring]: remove [material]",
            ));
        }
        return Ok((MaterialParams::default(), None));
    }
    let raw_material = required("material", raw_material)?;
    let material = build_material(&raw_material)?;
    let fibres = build_fibres(&raw_material, &material, mesh)?;
    Ok((material, fibres))
}
