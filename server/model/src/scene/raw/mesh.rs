//! The `[mesh]` section.

use super::*;
use crate::hybrid::section::HybridMesh;

/// Length unit name to metres.
pub(super) fn unit_m(field: &str, name: &str) -> Result<f64, ModelError> {
    match name {
        "m" => Ok(1.0),
        "cm" => Ok(1e-2),
        "mm" => Ok(1e-3),
        "um" => Ok(1e-6),
        _ => Err(ModelError::field(
            field,
            format!("unknown unit `{name}` (expected m, cm, mm or um)"),
        )),
    }
}

/// Refuses the `[mesh]` parameters that only other built-ins accept (the per-builtin table).
fn check_builtin_params(m: &RawMesh) -> Result<(), ModelError> {
    let params: [(&str, bool, &[&str]); 8] = [
        (
            "mesh.target_tets",
            m.target_tets.is_some(),
            &["lv", "ellipsoids", "sphere"],
        ),
        ("mesh.inner_radius", m.inner_radius.is_some(), &["sphere"]),
        (
            "mesh.outer_radius",
            m.outer_radius.is_some(),
            &["sphere", "hemisphere"],
        ),
        ("mesh.edge_length", m.edge_length.is_some(), &["hemisphere"]),
        (
            "mesh.inner_semi_axes",
            m.inner_semi_axes.is_some(),
            &["ellipsoids"],
        ),
        (
            "mesh.outer_semi_axes",
            m.outer_semi_axes.is_some(),
            &["ellipsoids"],
        ),
        ("mesh.size", m.size.is_some(), &["box"]),
        ("mesh.cells", m.cells.is_some(), &["box"]),
    ];
    let builtin = m.builtin.as_deref().unwrap_or("");
    for (field, given, allowed) in params {
        if given && !allowed.contains(&builtin) {
            return Err(ModelError::field(
                field,
                format!(
                    "only applies to mesh.builtin = {}",
                    allowed
                        .iter()
                        .map(|b| format!("\"{b}\""))
                        .collect::<Vec<_>>()
                        .join(" or ")
                ),
            ));
        }
    }
    Ok(())
}

/// `mesh.order`: quadratic (2) or linear (1, the default).
fn quadratic_order(m: &RawMesh) -> Result<bool, ModelError> {
    match m.order.unwrap_or(1) {
        1 => Ok(false),
        2 => Ok(true),
        other => Err(ModelError::field(
            "mesh.order",
            format!("must be 1 (linear) or 2 (quadratic), got {other}"),
        )),
    }
}

/// `mesh.target_tets`, or `default`.
fn target_tets(m: &RawMesh, default: usize) -> Result<usize, ModelError> {
    m.target_tets
        .map_or(Ok(default), |t| int_in("mesh.target_tets", t, 100, 500_000))
}

/// The built-in "ellipsoids" shell (`unit`: metres per length unit).
fn ellipsoids_mesh(m: &RawMesh, unit: f64, quadratic: bool) -> Result<TetMesh, ModelError> {
    let inner = m
        .inner_semi_axes
        .map_or(Ok(DVec3::new(6e-3, 6e-3, 12e-3)), |v| {
            positive_vec("mesh.inner_semi_axes", v, unit)
        })?;
    let outer = m
        .outer_semi_axes
        .map_or(Ok(DVec3::new(10e-3, 10e-3, 16e-3)), |v| {
            positive_vec("mesh.outer_semi_axes", v, unit)
        })?;
    if !inner.cmplt(outer).all() {
        return Err(ModelError::field(
            "mesh.outer_semi_axes",
            "every outer semi-axis must exceed the inner one",
        ));
    }
    Ok(if quadratic {
        crate::mesh::generate::ellipsoid_shell_quadratic(inner, outer, target_tets(m, 188)?)
    } else {
        crate::mesh::generate::ellipsoid_shell(inner, outer, target_tets(m, 188)?)
    })
}

/// The built-in "sphere" shell.
fn sphere_mesh(m: &RawMesh, unit: f64, quadratic: bool) -> Result<TetMesh, ModelError> {
    let ri = positive(
        "mesh.inner_radius",
        required("mesh.inner_radius", m.inner_radius)?,
    )? * unit;
    let ro = positive(
        "mesh.outer_radius",
        required("mesh.outer_radius", m.outer_radius)?,
    )? * unit;
    if ro <= ri {
        return Err(ModelError::field(
            "mesh.outer_radius",
            "must exceed mesh.inner_radius",
        ));
    }
    Ok(if quadratic {
        crate::mesh::generate::sphere_shell_quadratic(ri, ro, target_tets(m, 5000)?)
    } else {
        crate::mesh::generate::sphere_shell(ri, ro, target_tets(m, 5000)?)
    })
}

/// The built-in "hemisphere" surface (linear only).
fn hemisphere_mesh(m: &RawMesh, unit: f64, quadratic: bool) -> Result<TetMesh, ModelError> {
    let radius = positive(
        "mesh.outer_radius",
        required("mesh.outer_radius", m.outer_radius)?,
    )? * unit;
    let edge = positive(
        "mesh.edge_length",
        required("mesh.edge_length", m.edge_length)?,
    )? * unit;
    if edge > radius || edge < radius / 200.0 {
        return Err(ModelError::field(
            "mesh.edge_length",
            "must be between outer_radius / 200 and outer_radius",
        ));
    }
    if quadratic {
        return Err(ModelError::field(
            "mesh.order",
            "the hemisphere is a triangle surface: order = 1 only",
        ));
    }
    Ok(crate::mesh::generate::hemisphere_surface(radius, edge))
}

/// The built-in "box".
fn box_mesh(m: &RawMesh, unit: f64) -> Result<TetMesh, ModelError> {
    let size = positive_vec("mesh.size", required("mesh.size", m.size)?, unit)?;
    let c = required("mesh.cells", m.cells)?;
    let mut cells = [0usize; 3];
    for k in 0..3 {
        cells[k] = int_in("mesh.cells", c[k], 1, 200)?;
    }
    if cells.iter().product::<usize>() > 100_000 {
        return Err(ModelError::field("mesh.cells", "more than 100000 cells"));
    }
    Ok(crate::mesh::generate::box_mesh(size, cells))
}

/// The built-in mesh `builtin` (one of [`BUILTIN_MESHES`]).
fn builtin_mesh(
    m: &RawMesh,
    builtin: &str,
    unit: f64,
    quadratic: bool,
) -> Result<TetMesh, ModelError> {
    match builtin {
        // Built-in shells get curved quadratic elements (mid-edge nodes on the surfaces).
        "lv" if quadratic => Ok(crate::mesh::generate::lv_shell_quadratic(target_tets(
            m, 2000,
        )?)),
        "lv" => Ok(crate::mesh::generate::lv_shell(target_tets(m, 2000)?)),
        "ellipsoids" => ellipsoids_mesh(m, unit, quadratic),
        "sphere" => sphere_mesh(m, unit, quadratic),
        "hemisphere" => hemisphere_mesh(m, unit, quadratic),
        "box" => box_mesh(m, unit),
        other => {
            let (rest, last) = BUILTIN_MESHES.split_at(BUILTIN_MESHES.len() - 1);
            Err(ModelError::field(
                "mesh.builtin",
                format!(
                    "unknown builtin mesh `{other}` (expected {} or {})",
                    rest.join(", "),
                    last.join("")
                ),
            ))
        }
    }
}

/// The scene's mesh (a Gmsh file relative to `base_dir`, or a built-in) in metres, and the
/// length unit in metres.
pub(super) fn build_mesh(m: &RawMesh, base_dir: &Path) -> Result<(TetMesh, f64), ModelError> {
    let unit = unit_m("mesh.length_unit", m.length_unit.as_deref().unwrap_or("m"))?;
    check_builtin_params(m)?;
    let quadratic = quadratic_order(m)?;
    let mesh = match (&m.file, &m.builtin) {
        (Some(_), Some(_)) => {
            return Err(ModelError::field(
                "mesh.builtin",
                "give either mesh.file or mesh.builtin, not both",
            ));
        }
        (None, None) => {
            return Err(ModelError::field(
                "mesh.file",
                "is required (or mesh.builtin)",
            ));
        }
        (Some(file), None) => {
            // Errors name the file as the scene wrote it (issue 47).
            let mut mesh = crate::mesh::gmsh::load_msh_named(&base_dir.join(file), file)?;
            mesh.scale(unit);
            mesh
        }
        (None, Some(b)) => builtin_mesh(m, b, unit, quadratic)?,
    };
    let mesh = if quadratic && !mesh.is_quadratic() {
        mesh.to_quadratic()
    } else {
        mesh
    };
    Ok((mesh, unit))
}

/// The `[mesh]` keys the hybrid section reads (`unit_m`: metres per length unit).
pub(super) fn hybrid_mesh(m: &RawMesh, unit_m: f64) -> HybridMesh<'_> {
    HybridMesh {
        builtin: m.builtin.as_deref(),
        inner_semi_axes: m.inner_semi_axes,
        outer_semi_axes: m.outer_semi_axes,
        order: m.order,
        target_tets: m.target_tets,
        unit_m,
    }
}

/// The mesh rules: a volume family needs tetrahedra (`springs`: the mass-spring family takes a
/// surface mesh); `mesh.strain_smoothing` (none when absent) is for linear tetrahedra.
pub(super) fn mesh_rules(
    mesh_raw: &RawMesh,
    mesh: &TetMesh,
    springs: bool,
) -> Result<StrainSmoothing, ModelError> {
    if !springs && mesh.tets.is_empty() {
        let field = if mesh_raw.builtin.is_some() {
            "mesh.builtin"
        } else {
            "mesh.file"
        };
        return Err(ModelError::field(
            field,
            "the mesh has no tetrahedra: a surface mesh is for model.family = \"mass-spring\"",
        ));
    }
    let strain_smoothing = match mesh_raw.strain_smoothing.as_deref() {
        None => StrainSmoothing::None,
        Some(name) => StrainSmoothing::from_name(name).ok_or_else(|| {
            ModelError::field(
                "mesh.strain_smoothing",
                format!("unknown strain smoothing `{name}` (expected none or edge)"),
            )
        })?,
    };
    if strain_smoothing != StrainSmoothing::None && mesh.is_quadratic() {
        return Err(ModelError::field(
            "mesh.strain_smoothing",
            "strain smoothing is for linear tetrahedra (order = 1)",
        ));
    }
    Ok(strain_smoothing)
}
