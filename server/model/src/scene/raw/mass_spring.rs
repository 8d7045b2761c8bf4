//! The `[mass_spring]` section and its organ part.

use super::*;

// ----- mass-spring section -----

/// The mesh of a spring surface cut from `mesh`: its nodes (in the surface's order), no
/// tetrahedra, its triangles as the surface `name`, and `mesh`'s node groups restricted to it.
pub(super) fn surface_mesh(mesh: &TetMesh, surface: &SpringSurface, name: &str) -> TetMesh {
    let mut local = vec![u32::MAX; mesh.node_count()];
    for i in 0..surface.node_count() as u32 {
        local[surface.source_node(i) as usize] = i;
    }
    TetMesh {
        nodes: surface.rest().to_vec(),
        tets: Vec::new(),
        tet_edge_nodes: Vec::new(),
        surfaces: vec![crate::mesh::SurfaceGroup {
            name: name.to_string(),
            triangles: surface.triangles().to_vec(),
        }],
        node_groups: mesh
            .node_groups
            .iter()
            .map(|g| crate::mesh::NodeGroup {
                name: g.name.clone(),
                nodes: g
                    .nodes
                    .iter()
                    .filter_map(|&i| local.get(i as usize).copied().filter(|&l| l != u32::MAX))
                    .collect(),
            })
            .filter(|g| !g.nodes.is_empty())
            .collect(),
    }
}

#[allow(clippy::too_many_arguments)]
pub(super) fn build_mass_spring(
    m: &RawMassSpring,
    mesh: &TetMesh,
    touchable: &[[u32; 3]],
    clamped: &[u32],
    probe: ProbeParams,
    scene_name: &str,
    base_dir: &Path,
    origin: Origin,
) -> Result<MassSpringScene, ModelError> {
    let req = |field: &str, v: Option<f64>| required(&format!("mass_spring.{field}"), v);
    let km = req("mesh_spring_n_per_m", m.mesh_spring_n_per_m)?;
    let kh = req("home_spring_n_per_m", m.home_spring_n_per_m)?;
    let rings = match m.rings {
        None => 1,
        Some(r) => int_in("mass_spring.rings", r, 0, i64::from(MAX_RINGS))? as u32,
    };
    let springs = match m.springs.as_deref() {
        None => SpringRule::Calibrated,
        Some(n) => SpringRule::from_name(n).ok_or_else(|| {
            ModelError::field(
                "mass_spring.springs",
                format!("unknown rule `{n}` (expected \"calibrated\", \"unchanged\" or \"area\")"),
            )
        })?,
    };
    let vertex_rule = match m.vertex_rule.as_deref() {
        None => VertexRule::Keep,
        Some(n) => VertexRule::from_name(n).ok_or_else(|| {
            ModelError::field(
                "mass_spring.vertex_rule",
                format!("unknown rule `{n}` (expected \"keep\" or \"loop\")"),
            )
        })?,
    };
    let params = MassSpringParams {
        mesh_spring_n_per_m: km,
        home_spring_n_per_m: kh,
        damping_n_s_per_m: m.damping_n_s_per_m.unwrap_or(0.0),
        node_mass_kg: req("node_mass_kg", m.node_mass_kg)?,
        subdivision: SubdivisionParams {
            rings,
            springs,
            km_over_kh_after: m.km_over_kh_after.unwrap_or(km / kh),
            vertex_rule,
            coarsen_delay_s: m.coarsen_delay_s.unwrap_or(0.2),
        },
    };
    params.validate()?;
    let surface = SpringSurface::from_mesh(&mesh.nodes, touchable, clamped).map_err(|e| {
        ModelError::field(
            "boundary.touchable",
            format!("the touchable triangles are not a valid spring surface: {e}"),
        )
    })?;
    let file = m
        .calibration_file
        .clone()
        .unwrap_or_else(|| format!("{scene_name}.calibration.csv"));
    let needed = rings > 0 && springs == SpringRule::Calibrated;
    let shape = ContactShape::Probe(probe);
    let key = calibration_key(&surface, &params, shape);
    let path = match origin {
        Origin::Builtin => None,
        Origin::File => Some(base_dir.join(&file)),
    };
    let table = if !needed {
        TableState::NotNeeded
    } else {
        let text = match &path {
            None => builtin_calibration(&file)
                .map(str::to_string)
                .ok_or_else(|| format!("no built-in calibration table `{file}`")),
            Some(p) => std::fs::read_to_string(p).map_err(|e| format!("cannot be read ({e})")),
        };
        let shown = file.clone();
        match text.and_then(|t| CalibrationTable::parse(&t, &shown).map_err(|e| e.to_string())) {
            Err(why) => TableState::Unusable(why),
            Ok(t) if t.key() != key => TableState::Unusable(format!(
                "is stale: computed for key {:016x}, this scene needs {key:016x} (the surface, springs, rings, vertex rule or probe radius changed)",
                t.key()
            )),
            Ok(t) if t.node_count() != surface.node_count() => TableState::Unusable(format!(
                "covers {} nodes, the surface has {}",
                t.node_count(),
                surface.node_count()
            )),
            Ok(t) => TableState::Ready(t),
        }
    };
    let organ = match &m.reference_file {
        None => {
            for (field, given) in [
                ("mass_spring.organ_file", m.organ_file.is_some()),
                ("mass_spring.reference_axis", m.reference_axis.is_some()),
            ] {
                if given {
                    return Err(ModelError::field(
                        field,
                        "needs mass_spring.reference_file (the organ's reference)",
                    ));
                }
            }
            None
        }
        Some(reference) => Some(build_organ(
            m, reference, &surface, &params, &probe, scene_name, base_dir, origin,
        )?),
    };
    Ok(MassSpringScene {
        params,
        surface,
        contact: shape,
        key,
        calibration_file: file,
        calibration_path: path,
        table,
        organ,
    })
}

/// The organ part of a mass-spring scene: the reference (read now: a scene whose reference
/// cannot be read or parsed is refused), its axis, and the organ table (missing, malformed or
/// stale: recorded, refused when a body is started).
#[allow(clippy::too_many_arguments)]
pub(super) fn build_organ(
    m: &RawMassSpring,
    reference_file: &str,
    surface: &SpringSurface,
    params: &MassSpringParams,
    probe: &ProbeParams,
    scene_name: &str,
    base_dir: &Path,
    origin: Origin,
) -> Result<OrganScene, ModelError> {
    let field = "mass_spring.reference_file";
    let read = |file: &str| -> Result<(String, Option<PathBuf>), String> {
        match origin {
            Origin::Builtin => builtin_calibration(file)
                .map(|t| (t.to_string(), None))
                .ok_or_else(|| format!("no built-in file `{file}`")),
            Origin::File => {
                let p = base_dir.join(file);
                // Named as the scene names it, not where it resolved (issue 47).
                std::fs::read_to_string(&p)
                    .map(|t| (t, Some(p.clone())))
                    .map_err(|e| format!("`{file}` cannot be read ({e})"))
            }
        }
    };
    let (text, _) = read(reference_file).map_err(|e| ModelError::field(field, e))?;
    let reference = OrganReference::parse(&text, reference_file)
        .map_err(|e| ModelError::field(field, e.to_string()))?;
    let axis = DVec3::from_array(m.reference_axis.unwrap_or([0.0, 0.0, 1.0]));
    if !(axis.is_finite() && axis.length() > 0.0) {
        return Err(ModelError::field(
            "mass_spring.reference_axis",
            "must be a finite non-zero vector",
        ));
    }
    let axis = axis.normalize();
    let file = m
        .organ_file
        .clone()
        .unwrap_or_else(|| format!("{scene_name}.organ.csv"));
    let key = organ_key(surface, params, probe, &reference, axis);
    let path = match origin {
        Origin::Builtin => None,
        Origin::File => Some(base_dir.join(&file)),
    };
    let table = read(&file)
        // As the scene names it, not where it resolved (issue 47).
        .and_then(|(t, _)| OrganTable::parse(&t, &file).map_err(|e| e.to_string()))
        .and_then(|t| {
            if t.key() != key {
                Err(format!(
                    "is stale: computed for key {:016x}, this scene needs {key:016x} (the surface, springs, probe, reference or axis changed)",
                    t.key()
                ))
            } else if (t.node_count(), t.edge_count())
                != (surface.node_count(), surface.edge_count())
            {
                Err(format!(
                    "covers {} nodes and {} edges, the surface has {} and {}",
                    t.node_count(),
                    t.edge_count(),
                    surface.node_count(),
                    surface.edge_count()
                ))
            } else {
                Ok(t)
            }
        });
    Ok(OrganScene {
        reference,
        axis,
        key,
        file,
        path,
        table,
    })
}

/// A mass-spring scene's `(mesh, touchable triangles, clamped nodes)`.
pub(super) type SurfaceScene = (TetMesh, Vec<[u32; 3]>, Vec<u32>);

/// The scene's mesh becomes the surface the body simulates (listings and outputs then count its
/// nodes): `(mesh, touchable, clamped nodes)` of the spring surface's nodes, no tetrahedra, the
/// touchable triangles as one surface named after the touchable surfaces (`touchable_names`,
/// else every surface of `mesh`), node groups restricted to it; `ms.surface` is renumbered as
/// the new mesh (its key is unchanged).
pub(super) fn into_spring_mesh(
    ms: &mut MassSpringScene,
    touchable_names: Option<&[String]>,
    mesh: &TetMesh,
) -> Result<SurfaceScene, ModelError> {
    let names = touchable_names
        .map(<[String]>::to_vec)
        .unwrap_or_else(|| mesh.surfaces.iter().map(|s| s.name.clone()).collect());
    let mesh = surface_mesh(mesh, &ms.surface, &names.join("+"));
    let touchable = ms.surface.triangles().to_vec();
    let clamped_nodes = (0..ms.surface.node_count() as u32)
        .filter(|&i| ms.surface.is_fixed(i))
        .collect();
    let fixed = (0..ms.surface.node_count() as u32)
        .map(|i| ms.surface.is_fixed(i))
        .collect();
    ms.surface = SpringSurface::new(mesh.nodes.clone(), touchable.clone(), fixed)?;
    Ok((mesh, touchable, clamped_nodes))
}
