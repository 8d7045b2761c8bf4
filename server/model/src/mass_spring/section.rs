//! The `[mass_spring]` section of a scene and its organ part: the family parses and validates
//! its own parameters, builds its spring surface from the scene's mesh and reads its
//! calibration tables ([`TableSource`]: compiled in for a built-in scene, beside a scene file).

use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::Deserialize;

use super::calibration::{CalibrationTable, ContactShape, calibration_key};
use super::organ::{OrganReference, OrganTable, organ_key};
use super::{
    MAX_RINGS, MassSpringParams, SpringRule, SpringSurface, SubdivisionParams, VertexRule,
};
use crate::ModelError;
use crate::check::{int_in, required};
use crate::contact::ProbeParams;
use crate::mesh::TetMesh;

/// The `[mass_spring]` section as written.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawMassSpring {
    mesh_spring_n_per_m: Option<f64>,
    home_spring_n_per_m: Option<f64>,
    damping_n_s_per_m: Option<f64>,
    node_mass_kg: Option<f64>,
    rings: Option<i64>,
    springs: Option<String>,
    km_over_kh_after: Option<f64>,
    vertex_rule: Option<String>,
    coarsen_delay_s: Option<f64>,
    calibration_file: Option<String>,
    reference_file: Option<String>,
    reference_axis: Option<[f64; 3]>,
    organ_file: Option<String>,
}

/// Where a scene's calibration files come from.
#[derive(Debug, Clone, Copy)]
pub(crate) enum TableSource<'a> {
    /// A built-in scene: the files are compiled into the library, found by name with this
    /// function (`crate::scene::builtin_calibration`).
    Builtin(fn(&str) -> Option<&'static str>),
    /// A scene file: the files are in its directory.
    Dir(&'a Path),
}

impl TableSource<'_> {
    /// Where file `file` is read from and written to: `None` for a built-in scene.
    fn path(&self, file: &str) -> Option<PathBuf> {
        match self {
            TableSource::Builtin(_) => None,
            TableSource::Dir(dir) => Some(dir.join(file)),
        }
    }
}

/// The mass-spring part of a scene: the spring surface (the touchable triangles, with the
/// clamped nodes fixed), the parameters, and the calibrated table with its cache file.
#[derive(Debug, Clone)]
pub struct MassSpringScene {
    /// Parameters (eq. 1-3, subdivision).
    pub params: MassSpringParams,
    /// The coarse surface.
    pub surface: SpringSurface,
    /// The contact the table is calibrated for: the scene's probe.
    pub contact: ContactShape,
    /// The key a valid table must carry ([`crate::mass_spring::calibration::calibration_key`]).
    pub key: u64,
    /// The table's file name as the scene gives it (`calibration_file`, default
    /// `<scene name>.calibration.csv`).
    pub calibration_file: String,
    /// Where the table is read from and written to (relative to the scene's directory);
    /// `None` for a built-in scene, whose table is compiled into the library.
    pub calibration_path: Option<PathBuf>,
    /// The table, or why there is none.
    pub table: TableState,
    /// The organ calibration (`reference_file`, [`crate::mass_spring::organ`]), if the scene
    /// gives a reference.
    pub organ: Option<OrganScene>,
}

/// The organ calibration of a mass-spring scene: the organ's reference, the axis its target is
/// interpolated along, and the organ table.
#[derive(Debug, Clone)]
pub struct OrganScene {
    /// The reference (`mass_spring.reference_file`).
    pub reference: OrganReference,
    /// `mass_spring.reference_axis`, unit.
    pub axis: DVec3,
    /// The key a valid table must carry ([`crate::mass_spring::organ::organ_key`]).
    pub key: u64,
    /// The table's file name as the scene gives it (`organ_file`, default
    /// `<scene name>.organ.csv`).
    pub file: String,
    /// Where it is read from and written to; `None` for a built-in scene.
    pub path: Option<PathBuf>,
    /// The table, or why it is unusable (missing, malformed, stale).
    pub table: Result<OrganTable, String>,
}

impl OrganScene {
    /// The table.
    ///
    /// # Errors
    /// [`ModelError::Calibration`] naming the file, what is wrong and the command that
    /// computes it.
    pub fn table(&self) -> Result<OrganTable, ModelError> {
        self.table.clone().map_err(|why| ModelError::Calibration {
            // As the scene names it, not where it resolved (issue 47).
            path: self.file.clone(),
            message: format!(
                "{why}; compute it with `haptic-calibrate SCENE_FILE` (writes it beside the scene)"
            ),
        })
    }
}

/// The calibration table of a mass-spring scene.
#[derive(Debug, Clone)]
pub enum TableState {
    /// The scene does not subdivide with calibrated springs.
    NotNeeded,
    /// Read and valid for this scene.
    Ready(CalibrationTable),
    /// Missing, unreadable, malformed or stale: why.
    Unusable(String),
}

impl MassSpringScene {
    /// The table the body needs (`None` when it needs none).
    ///
    /// # Errors
    /// [`ModelError::Calibration`] naming the file, saying what is wrong and the command that
    /// computes it, when the table is needed but unusable.
    pub fn table(&self) -> Result<Option<CalibrationTable>, ModelError> {
        match &self.table {
            TableState::NotNeeded => Ok(None),
            TableState::Ready(t) => Ok(Some(t.clone())),
            TableState::Unusable(why) => Err(ModelError::Calibration {
                // As the scene names it, not where it resolved (issue 47).
                path: self.calibration_file.clone(),
                message: format!(
                    "{why}; compute it with `haptic-calibrate SCENE_FILE` (writes it beside the scene), or set mass_spring.springs = \"unchanged\" or rings = 0"
                ),
            }),
        }
    }
}

/// The mesh of a spring surface cut from `mesh`: its nodes (in the surface's order), no
/// tetrahedra, its triangles as the surface `name`, and `mesh`'s node groups restricted to it.
fn surface_mesh(mesh: &TetMesh, surface: &SpringSurface, name: &str) -> TetMesh {
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

/// The parameters of section `m` (validated).
fn mass_spring_params(m: &RawMassSpring) -> Result<MassSpringParams, ModelError> {
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
    Ok(params)
}

/// The calibration table `file` read from `source`, checked against the scene's `key` and
/// `surface`.
fn calibration_table(
    file: &str,
    source: TableSource,
    key: u64,
    surface: &SpringSurface,
) -> TableState {
    let text = match source {
        TableSource::Builtin(lookup) => lookup(file)
            .map(str::to_string)
            .ok_or_else(|| format!("no built-in calibration table `{file}`")),
        TableSource::Dir(dir) => {
            std::fs::read_to_string(dir.join(file)).map_err(|e| format!("cannot be read ({e})"))
        }
    };
    match text.and_then(|t| CalibrationTable::parse(&t, file).map_err(|e| e.to_string())) {
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
}

/// The mass-spring part of a scene: section `m` on the scene's `mesh` with its `touchable`
/// triangles and `clamped` nodes, calibrated for the scene's `probe`; the tables named after
/// `scene_name` unless the section names them, read from `source`.
pub(crate) fn build_mass_spring(
    m: &RawMassSpring,
    mesh: &TetMesh,
    touchable: &[[u32; 3]],
    clamped: &[u32],
    probe: ProbeParams,
    scene_name: &str,
    source: TableSource,
) -> Result<MassSpringScene, ModelError> {
    let params = mass_spring_params(m)?;
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
    let sub = &params.subdivision;
    let needed = sub.rings > 0 && sub.springs == SpringRule::Calibrated;
    let shape = ContactShape::Probe(probe);
    let key = calibration_key(&surface, &params, shape);
    let path = source.path(&file);
    let table = if !needed {
        TableState::NotNeeded
    } else {
        calibration_table(&file, source, key, &surface)
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
            m, reference, &surface, &params, &probe, scene_name, source,
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
fn build_organ(
    m: &RawMassSpring,
    reference_file: &str,
    surface: &SpringSurface,
    params: &MassSpringParams,
    probe: &ProbeParams,
    scene_name: &str,
    source: TableSource,
) -> Result<OrganScene, ModelError> {
    let field = "mass_spring.reference_file";
    let read = |file: &str| -> Result<(String, Option<PathBuf>), String> {
        match source {
            TableSource::Builtin(lookup) => lookup(file)
                .map(|t| (t.to_string(), None))
                .ok_or_else(|| format!("no built-in file `{file}`")),
            TableSource::Dir(base_dir) => {
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
    let path = source.path(&file);
    let table = read(&file)
        // As the scene names it, not where it resolved (issue 47).
        .and_then(|(t, _)| OrganTable::parse(&t, &file).map_err(|e| e.to_string()))
        .and_then(|t| {
            if t.key() != key {
                Err(format!(
                    "is stale: computed for key {:016x}, this scene needs {key:016x} (the surface, springs, probe, reference or axis changed)",
                    t.key()
                ))
            } else if let Some(why) = t.mismatch(surface) {
                Err(why)
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
pub(crate) type SurfaceScene = (TetMesh, Vec<[u32; 3]>, Vec<u32>);

/// The scene's mesh becomes the surface the body simulates (listings and outputs then count its
/// nodes): `(mesh, touchable, clamped nodes)` of the spring surface's nodes, no tetrahedra, the
/// touchable triangles as one surface named after the touchable surfaces (`touchable_names`,
/// else every surface of `mesh`), node groups restricted to it; `ms.surface` is renumbered as
/// the new mesh (its key is unchanged).
pub(crate) fn into_spring_mesh(
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
