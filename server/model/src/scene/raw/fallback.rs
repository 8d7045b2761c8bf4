//! The coarse whole-body companion of a following region.

use super::*;

/// The coarse whole-body companion of a following region (`active_region.fallback_target_tets`,
/// [`Scene::fallback`]): the scene `text` again, on the built-in mesh `builtin` at about `tets`
/// quadratic tetrahedra (in place of the scene's mesh) without strain smoothing, backward Euler
/// on the whole-body rest factor with the region's stiffness margin, double-precision forces,
/// no active region. Parsed by [`parse_scene`], so every check applies; an error names the
/// fallback's field.
pub(super) fn fallback_scene(
    text: &str,
    base_dir: &Path,
    name: &str,
    origin: Origin,
    (builtin, tets): (&str, usize),
    stiffness_margin: f64,
) -> Result<Scene, ModelError> {
    let field = "active_region.fallback_target_tets";
    let bad = |e: String| ModelError::field(field, format!("the coarse companion: {e}"));
    let mut doc: toml::Table = text
        .parse()
        .map_err(|e: toml::de::Error| bad(e.to_string()))?;
    doc.remove("active_region");
    fn table<'a>(doc: &'a mut toml::Table, key: &str) -> Option<&'a mut toml::Table> {
        doc.entry(key)
            .or_insert_with(|| toml::Value::Table(toml::Table::new()))
            .as_table_mut()
    }
    let mesh = table(&mut doc, "mesh").ok_or_else(|| bad("[mesh] is not a table".into()))?;
    if mesh.remove("file").is_some() {
        // The file's parameters are not the built-in's (its length unit names the outputs').
        mesh.retain(|k, _| k == "length_unit");
    }
    mesh.insert("builtin".into(), builtin.into());
    mesh.insert("target_tets".into(), toml::Value::Integer(tets as i64));
    mesh.insert("order".into(), toml::Value::Integer(2));
    mesh.remove("strain_smoothing");
    let integrator =
        table(&mut doc, "integrator").ok_or_else(|| bad("[integrator] is not a table".into()))?;
    integrator.insert("linear_solver".into(), "rest-cholesky".into());
    integrator.insert("stiffness_margin".into(), stiffness_margin.into());
    integrator.remove("force_precision");
    let text = toml::to_string(&doc).map_err(|e| bad(e.to_string()))?;
    parse_scene(&text, base_dir, name, origin).map_err(|e| bad(e.to_string()))
}

/// Refuses a companion whose mesh is not the scene mesh's shape: their bounding boxes (m) must
/// agree to 2 % of the scene mesh's diagonal (a mesh file of another geometry, or in another
/// unit, would be answered by a body the probe is not touching).
pub(super) fn check_same_shape(mesh: &TetMesh, coarse: &TetMesh) -> Result<(), ModelError> {
    let ((lo, hi), (clo, chi)) = (mesh.bounding_box(), coarse.bounding_box());
    let off = (lo - clo).abs().max((hi - chi).abs()).max_element();
    let size = (hi - lo).length();
    if off > 0.02 * size {
        return Err(ModelError::field(
            "active_region.fallback_builtin",
            format!(
                "the companion's geometry does not match the mesh: bounding boxes differ by {:.3} mm (the mesh spans {:.1} mm)",
                off * 1e3,
                size * 1e3
            ),
        ));
    }
    Ok(())
}

/// Where the scene text being parsed comes from (for its companion's re-parse).
pub(super) struct Source<'a> {
    /// The scene's TOML text.
    pub(super) text: &'a str,
    /// The directory relative paths resolve against.
    pub(super) base_dir: &'a Path,
    /// The scene's name.
    pub(super) name: &'a str,
    /// Built-in or file.
    pub(super) origin: Origin,
}

/// The companion of `region` (section `a`) when `active_region.fallback_target_tets` is set:
/// needs `follow = true`, a built-in "lv", "ellipsoids" or "sphere" geometry (the scene's own or
/// `fallback_builtin`), and the scene mesh's shape.
pub(super) fn companion(
    a: &RawActiveRegion,
    region: &ActiveRegion,
    mesh_raw: &RawMesh,
    mesh: &TetMesh,
    source: Source,
) -> Result<Option<Box<Scene>>, ModelError> {
    let Some(tets) = a.fallback_target_tets else {
        if a.fallback_builtin.is_some() {
            return Err(ModelError::field(
                "active_region.fallback_builtin",
                "needs active_region.fallback_target_tets",
            ));
        }
        return Ok(None);
    };
    let field = "active_region.fallback_target_tets";
    if !region.follow {
        return Err(ModelError::field(
            field,
            "needs active_region.follow = true",
        ));
    }
    let tets = int_in(field, tets, 100, 20_000)?;
    // The companion's geometry: the scene's own built-in, or the one named for a
    // mesh file of the same shape.
    let builtin = match (&a.fallback_builtin, &mesh_raw.builtin) {
        (Some(b), _) | (None, Some(b)) => b.as_str(),
        (None, None) => {
            return Err(ModelError::field(
                "active_region.fallback_builtin",
                "is required with a mesh file: the built-in geometry the file meshes (\"lv\", \"ellipsoids\" or \"sphere\")",
            ));
        }
    };
    if !matches!(builtin, "lv" | "ellipsoids" | "sphere") {
        let field = if a.fallback_builtin.is_some() {
            "active_region.fallback_builtin"
        } else {
            field
        };
        return Err(ModelError::field(
            field,
            format!(
                "the companion is a built-in \"lv\", \"ellipsoids\" or \"sphere\", not \"{builtin}\""
            ),
        ));
    }
    let margin = region.stiffness_margin;
    let Source {
        text,
        base_dir,
        name,
        origin,
    } = source;
    let coarse = fallback_scene(text, base_dir, name, origin, (builtin, tets), margin)?;
    check_same_shape(mesh, &coarse.mesh)?;
    Ok(Some(Box::new(coarse)))
}
