//! The `[loads]` section.

use super::*;

/// `[[loads.pressure]]` number `k`: its surfaces' triangles (each once) and pressure.
fn pressure_load(k: usize, p: &RawPressure, mesh: &TetMesh) -> Result<PressureLoad, ModelError> {
    let field = |name: &str| format!("loads.pressure[{k}].{name}");
    let surfaces = required(&field("surfaces"), p.surfaces.clone())?;
    if surfaces.is_empty() {
        return Err(ModelError::field(field("surfaces"), "names no surface"));
    }
    let mut triangles: Vec<[u32; 3]> = Vec::new();
    for name in &surfaces {
        let Some(s) = mesh.surface(name) else {
            let known: Vec<&str> = mesh.surfaces.iter().map(|s| s.name.as_str()).collect();
            return Err(ModelError::field(
                field("surfaces"),
                format!(
                    "no surface named `{name}` (mesh surfaces: {})",
                    known.join(", ")
                ),
            ));
        };
        triangles.extend(s.triangles.iter().copied());
    }
    let mut seen = std::collections::HashSet::new();
    triangles.retain(|t| {
        let mut key = *t;
        key.sort_unstable();
        seen.insert(key)
    });
    let pressure_pa = checked(
        &field("pressure_pa"),
        required(&field("pressure_pa"), p.pressure_pa)?,
        |x| x.abs() <= MAX_PRESSURE_PA,
        "at most 1e9 Pa in magnitude",
    )?;
    let quadratic = mesh.is_quadratic() && crate::loads::is_quadratic_split(&triangles);
    Ok(PressureLoad {
        surfaces,
        triangles,
        pressure_pa,
        follower: p.follower.unwrap_or(false),
        quadratic,
    })
}

/// `[[loads.point]]`: each force on the closest free boundary triangle (`clamped`: sorted
/// clamped nodes), within the body's size of it.
fn point_loads(
    points: &[RawPoint],
    mesh: &TetMesh,
    clamped: &[u32],
) -> Result<Vec<PointForce>, ModelError> {
    let mut point = Vec::new();
    if points.is_empty() {
        return Ok(point);
    }
    let surface: Vec<[u32; 3]> = mesh
        .boundary_triangles()
        .into_iter()
        .filter(|t| !t.iter().all(|i| clamped.binary_search(i).is_ok()))
        .collect();
    let (lo, hi) = mesh.bounding_box();
    let size = (hi - lo).length();
    for (k, p) in points.iter().enumerate() {
        let field = |name: &str| format!("loads.point[{k}].{name}");
        let at = required(&field("point_m"), p.point_m)?;
        for x in at {
            checked(&field("point_m"), x, |_| true, "finite")?;
        }
        let point_m = DVec3::from_array(at);
        let force_n = bounded_vec(
            &field("force_n"),
            required(&field("force_n"), p.force_n)?,
            MAX_SCENE_POINT_FORCE_N,
        )?;
        let best = surface
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| mesh.nodes[i as usize]);
                let (q, bary) = crate::contact::closest_point_on_triangle(point_m, a, b, c);
                (*t, bary, (q - point_m).length())
            })
            .min_by(|a, b| a.2.total_cmp(&b.2));
        let Some((nodes, bary, dist)) = best else {
            return Err(ModelError::field(
                field("point_m"),
                "the body has no free boundary surface to load",
            ));
        };
        if dist > size {
            return Err(ModelError::field(
                field("point_m"),
                format!(
                    "is {dist:.3e} m from the body's surface, farther than the body's size {size:.3e} m"
                ),
            ));
        }
        point.push(PointForce {
            point_m,
            force_n,
            nodes,
            bary,
        });
    }
    Ok(point)
}

/// The `[loads]` section on `mesh` (`clamped`: sorted clamped nodes).
pub(super) fn build_loads(
    l: &RawLoads,
    mesh: &TetMesh,
    clamped: &[u32],
) -> Result<SceneLoads, ModelError> {
    let gravity_m_per_s2 = match l.gravity_m_per_s2 {
        Some(g) => bounded_vec("loads.gravity_m_per_s2", g, MAX_GRAVITY_M_PER_S2)?,
        None => DVec3::ZERO,
    };
    let pressure = l
        .pressure
        .iter()
        .flatten()
        .enumerate()
        .map(|(k, p)| pressure_load(k, p, mesh))
        .collect::<Result<Vec<_>, _>>()?;
    let point = point_loads(l.point.as_deref().unwrap_or_default(), mesh, clamped)?;
    Ok(SceneLoads {
        gravity_m_per_s2,
        pressure,
        point,
    })
}
