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
