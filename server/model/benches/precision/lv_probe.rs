//! `lv-probe`: the built-in `lv` scene (material, probe, coupling) on the structured LV mesh;
//! the probe centre moves along -x at z = -5 mm from 11.98 mm (0.3 mm clear of contact) in
//! steps to depths 0.5, 1, ..., 3 mm (contact at 11.68 mm: the epicardium at 9.68 mm plus the
//! 2 mm probe radius), each step a smoothstep ramp of 100 ms then a 100 ms hold; the force
//! reported per depth is the mean device force over the last 50 ms of the hold
//! ([`crate::common::lv_press`]). Reference: static equilibrium with the probe coupling at
//! each depth on [`LV_REFERENCE`] (cached in `target/bench/`). Errors: probe-force error = the
//! largest relative force error over the depths; surface displacement error at 3 mm on the
//! epicardial nodes, the reference interpolated barycentrically at the closest point of its
//! rest epicardium. Linear, quadratic and edge-smoothed linear elements (method suffix " ES"
//! on the 2 000 and 5 000 target meshes), and the mass-spring surface of the epicardium
//! (`lv-surface-springs`, seed 003) with and without run-time subdivision.

use std::time::Instant;

use haptic_model::DVec3;
use haptic_model::contact::ContactSurface;
use haptic_model::element::StrainSmoothing;
use haptic_model::material::MaterialModel;
use haptic_model::mesh::TetMesh;
use serde::{Deserialize, Serialize};

use crate::common::lv_press::{
    DEPTHS_MM, ProbeCurve, probe_dynamic, probe_dynamic_body, probe_static,
};
use crate::common::{MATERIALS, lv_scene, lv_scene_order};
use crate::method::{material_label, methods};
use crate::report::Model;
use crate::report::{Row, Scenario};
use crate::{Config, LvProbeRows};
use haptic_model::body::SoftBody;
use haptic_model::build_body;
use haptic_model::mass_spring::{MassSpringBody, SpringRule};
use haptic_model::meshfree::{KernelKind, MeshfreeVariant};
use haptic_model::scene::load_builtin;

/// The nodes of the epicardium (`EPI`), sorted.
fn epi_nodes(mesh: &TetMesh) -> Vec<u32> {
    let mut v: Vec<u32> = mesh
        .surface("EPI")
        .expect("EPI")
        .triangles
        .iter()
        .flatten()
        .copied()
        .collect();
    v.sort_unstable();
    v.dedup();
    v
}

/// The converged reference: curve and the reference epicardium for interpolation.
pub struct LvReference {
    /// Elements of the reference mesh.
    pub tets: usize,
    /// Forces per depth and positions at the last depth.
    pub curve: ProbeCurve,
    rest: Vec<DVec3>,
    epi: ContactSurface,
}

impl LvReference {
    /// Relative L2 and max error (m) of the epicardial displacement at the last depth.
    fn surface_errors(&self, mesh: &TetMesh, x: &[DVec3]) -> (f64, f64) {
        self.surface_errors_at(
            epi_nodes(mesh)
                .into_iter()
                .map(|i| (mesh.nodes[i as usize], x[i as usize])),
        )
    }

    /// Relative L2 and max error (m) of the displacement of surface points given as
    /// (rest, current) pairs against the reference's at their rest position.
    fn surface_errors_at(&self, points: impl Iterator<Item = (DVec3, DVec3)>) -> (f64, f64) {
        let (mut n2, mut d2, mut max_e) = (0.0, 0.0, 0.0f64);
        for (p, x) in points {
            let sp = self
                .epi
                .closest_global(&self.rest, p)
                .expect("reference surface");
            let tri = self.epi.triangles[sp.triangle as usize];
            let u_ref: DVec3 = (0..3)
                .map(|k| {
                    (self.curve.x_last[tri[k] as usize] - self.rest[tri[k] as usize]) * sp.bary[k]
                })
                .sum();
            let e = (x - p - u_ref).length();
            n2 += e * e;
            d2 += u_ref.length_squared();
            max_e = max_e.max(e);
        }
        ((n2 / d2).sqrt(), max_e)
    }

    fn force_error(&self, forces: &[f64]) -> f64 {
        forces
            .iter()
            .zip(&self.curve.forces_n)
            .map(|(f, r)| (f - r).abs() / r)
            .fold(0.0, f64::max)
    }
}

/// A reference curve cached in `target/bench/lv_probe_reference_*.json`, valid while `key`
/// (mesh, material, probe, depths) matches.
#[derive(Serialize, Deserialize)]
struct CachedReference {
    key: String,
    forces_n: Vec<f64>,
    x_last: Vec<[f64; 3]>,
}

/// The static reference of the press on `lv_shell(tets)` (quadratic elements if `quadratic`)
/// with material `model`, from the cache in `cfg.cache_dir` when its key matches (and
/// `--fresh-reference` was not given), else solved ([`probe_static`]) and cached.
pub fn lv_reference(
    (tets, quadratic): (usize, bool),
    model: MaterialModel,
    cfg: &Config,
) -> LvReference {
    let (fresh, cache_dir) = (cfg.fresh_reference, cfg.cache_dir.as_path());
    let mut scene = lv_scene_order(tets, quadratic);
    scene.material.model = model;
    // St. Venant-Kirchhoff keeps the key and file name it had before the other materials.
    let mut suffix = if model == MaterialModel::StVenantKirchhoff {
        String::new()
    } else {
        format!("_{}", model.scene_name())
    };
    if quadratic {
        suffix.push_str("_t10");
    }
    let key = format!(
        "lv_shell({tets}) E={} nu={} k={} r={} depths={DEPTHS_MM:?} nodes={}{suffix}",
        scene.material.youngs_modulus_pa(),
        scene.material.poisson_ratio(),
        scene.probe.coupling_stiffness_n_per_m,
        scene.probe.radius_m,
        scene.mesh.node_count()
    );
    let path = cache_dir.join(format!("lv_probe_reference_{tets}{suffix}.json"));
    let cached = (!fresh)
        .then(|| std::fs::read_to_string(&path).ok())
        .flatten()
        .and_then(|t| serde_json::from_str::<CachedReference>(&t).ok())
        .filter(|c| c.key == key)
        .map(|c| ProbeCurve {
            forces_n: c.forces_n,
            x_last: c.x_last.into_iter().map(DVec3::from_array).collect(),
        });
    let curve = match cached {
        Some(c) => {
            println!("lv-probe reference: cached {}", path.display());
            c
        }
        None => {
            let t = Instant::now();
            let c = probe_static(&scene, cfg.debug).expect("lv-probe reference static solve");
            println!(
                "lv-probe reference ({}): static solve on {} tets took {:.1} s",
                model.scene_name(),
                scene.mesh.tet_count(),
                t.elapsed().as_secs_f64()
            );
            let entry = CachedReference {
                key,
                forces_n: c.forces_n.clone(),
                x_last: c.x_last.iter().map(|p| p.to_array()).collect(),
            };
            std::fs::create_dir_all(cache_dir).expect("cache dir");
            std::fs::write(&path, serde_json::to_string(&entry).expect("json"))
                .expect("writing reference cache");
            c
        }
    };
    println!(
        "lv-probe reference ({}) forces (N) at {DEPTHS_MM:?} mm: {:?}",
        model.scene_name(),
        curve
            .forces_n
            .iter()
            .map(|f| (f * 1e4).round() / 1e4)
            .collect::<Vec<_>>()
    );
    LvReference {
        tets: scene.mesh.tet_count(),
        epi: ContactSurface::new(
            scene.mesh.surface("EPI").expect("EPI").triangles.clone(),
            scene.mesh.node_count(),
        ),
        rest: scene.mesh.nodes,
        curve,
    }
}

/// The LV reference mesh: `lv_shell(2000)` (2 010 elements) with quadratic elements. The
/// former reference, linear elements on `lv_shell(10000)` (10 017 tets), is 20-30 % stiffer
/// than the quadratic solutions, which agree among themselves: linear tetrahedra lock in
/// the bending of the 3 mm wall (see the `static` rows and the README).
pub const LV_REFERENCE: (usize, bool) = (2000, true);

/// Runs the scenario: per mesh and material the static curve and every dynamic method, then
/// the mass-spring rows ([`mass_spring_rows`]); with `--lv-probe-rows mass-spring` those only.
pub fn run(cfg: &Config, rows: &mut Vec<Row>) {
    if cfg.lv_probe_rows != LvProbeRows::All {
        let reference = lv_reference(LV_REFERENCE, MaterialModel::StVenantKirchhoff, cfg);
        match cfg.lv_probe_rows {
            LvProbeRows::MassSpring => mass_spring_rows(&reference, cfg.quick, rows),
            _ => hybrid_rows(&reference, cfg.quick, rows),
        }
        return;
    }
    run_fem(cfg, rows);
    let reference = lv_reference(LV_REFERENCE, MaterialModel::StVenantKirchhoff, cfg);
    mass_spring_rows(&reference, cfg.quick, rows);
    hybrid_rows(&reference, cfg.quick, rows);
}

/// The seeds' hybrid model `lv-hybrid` (a coarse LV core and about 130 000 meshfree particles
/// up to the epicardium, activated under the probe) pressed like the FEM
/// ([`probe_dynamic_body`]), both meshfree variants. Errors against the same FEM reference; the
/// displacement error on the outer surface's vertices (the epicardium).
pub fn hybrid_rows(reference: &LvReference, quick: bool, rows: &mut Vec<Row>) {
    let base = load_builtin("lv-hybrid").expect("built-in lv-hybrid");
    let ref_text = format!(
        "static with probe coupling on lv_shell ({} quadratic tets, stvk): F(3 mm) = {:.4} N",
        reference.tets,
        reference.curve.forces_n[DEPTHS_MM.len() - 1]
    );
    for variant in [MeshfreeVariant::Seed, MeshfreeVariant::Corrected] {
        let mut scene = base.clone();
        let h = scene.hybrid.as_mut().expect("a hybrid scene");
        h.params.meshfree.variant = variant;
        h.params.meshfree.kernel = KernelKind::default_for(variant);
        let label = format!("hybrid {}", variant.name());
        let mut row = Row::blank(Scenario::LvProbe, label.clone(), "symplectic-euler");
        row.model = Model::Hybrid;
        row.material = scene.material.model.scene_name().into();
        row.reference = ref_text.clone();
        let mut body = match build_body(&scene) {
            Ok(b) => b,
            Err(e) => {
                row.settings = format!("{label}: {e}");
                row.print();
                rows.push(row);
                continue;
            }
        };
        let stats0 = body.stats();
        row.nodes = stats0.nodes;
        row.tets = stats0.elements;
        match probe_dynamic_body(body.as_mut(), scene.integrator.tick_s, quick) {
            Ok((forces, ticks)) => {
                let info = body.info();
                let stats = body.stats();
                row.settings = format!(
                    "tick 1 ms, {} sub-steps; {} particles, {} active at 3 mm; mass_scale {}; staircase 0.5..3 mm",
                    info.substeps,
                    stats.particles,
                    stats.active_particles,
                    scene.hybrid.as_ref().map_or(1.0, |h| h.params.mass_scale)
                );
                row.set_times(&ticks, scene.integrator.tick_s);
                let n = body.surface_topology().vertex_count;
                let (mut rest, mut now) = (vec![0f32; 3 * n], vec![0f32; 3 * n]);
                body.write_surface_rest_positions(&mut rest);
                body.write_surface_positions(&mut now);
                let v = |a: &[f32]| DVec3::new(a[0] as f64, a[1] as f64, a[2] as f64);
                let (l2, max_e) = reference.surface_errors_at(
                    rest.chunks_exact(3)
                        .zip(now.chunks_exact(3))
                        .map(|(r, x)| (v(r), v(x))),
                );
                let curve = ProbeCurve {
                    forces_n: forces,
                    x_last: Vec::new(),
                };
                fill_lv_force_errors(&mut row, reference, &curve, DEPTHS_MM.len() - 1);
                row.rel_l2_error = l2;
                row.max_nodal_error_m = max_e;
            }
            Err(e) => row.settings = format!("{label}: {e}"),
        }
        row.print();
        rows.push(row);
    }
}

/// The mass-spring surface `lv-surface-springs` (the epicardium of `lv_shell(2000)` on home
/// springs, seed 003) pressed like the FEM ([`probe_dynamic_body`]): coarse, one-ring subdivided
/// with the calibrated springs (the scene's table) and with the springs unchanged. Errors
/// against the same FEM reference; the displacement error on the epicardial nodes, which are
/// the surface's nodes.
pub fn mass_spring_rows(reference: &LvReference, quick: bool, rows: &mut Vec<Row>) {
    let scene = load_builtin("lv-surface-springs").expect("built-in lv-surface-springs");
    let ms = scene.mass_spring.clone().expect("a mass-spring scene");
    let variants: [(&str, u32, SpringRule); 3] = [
        ("mass-spring", 0, SpringRule::Calibrated),
        ("mass-spring 1-ring", 1, SpringRule::Calibrated),
        ("mass-spring 1-ring unchanged", 1, SpringRule::Unchanged),
    ];
    let ref_text = format!(
        "static with probe coupling on lv_shell ({} quadratic tets, stvk): F(3 mm) = {:.4} N",
        reference.tets,
        reference.curve.forces_n[DEPTHS_MM.len() - 1]
    );
    for (label, rings, springs) in variants {
        let mut params = ms.params;
        params.subdivision.rings = rings;
        params.subdivision.springs = springs;
        let table = if rings > 0 && springs == SpringRule::Calibrated {
            ms.table().expect("the built-in table")
        } else {
            None
        };
        let mut row = Row::blank(Scenario::LvProbe, label.into(), "symplectic-euler");
        row.model = Model::MassSpring;
        row.material = "mass-spring".into();
        row.nodes = ms.surface.node_count();
        row.reference = ref_text.clone();
        let mut body = match MassSpringBody::new(
            ms.surface.clone(),
            &params,
            table,
            scene.probe,
            &scene.integrator,
            label,
        ) {
            Ok(b) => b,
            Err(e) => {
                row.settings = format!("{label}: {e}");
                row.print();
                rows.push(row);
                continue;
            }
        };
        match probe_dynamic_body(&mut body, scene.integrator.tick_s, quick) {
            Ok((forces, ticks)) => {
                row.settings = format!(
                    "tick 1 ms, {} sub-steps (worst-case Gershgorin bound); K_h = K_m = {} N/m; {} subdivision event(s), up to {} nodes; staircase 0.5..3 mm",
                    body.plan().substeps,
                    params.home_spring_n_per_m,
                    body.event_stats().events,
                    body.stats().nodes
                );
                row.set_times(&ticks, scene.integrator.tick_s);
                // Displacements on the reference's epicardium: the scene's mesh is the surface
                // (named `EPI`), its nodes the body's first slots.
                let curve = ProbeCurve {
                    forces_n: forces,
                    x_last: body.positions()[..ms.surface.node_count()].to_vec(),
                };
                fill_lv_errors(
                    &mut row,
                    reference,
                    &scene.mesh,
                    &curve,
                    DEPTHS_MM.len() - 1,
                );
            }
            Err(e) => row.settings = format!("{label}: {e}"),
        }
        row.print();
        rows.push(row);
    }
}

/// The FEM rows of the scenario.
fn run_fem(cfg: &Config, rows: &mut Vec<Row>) {
    let quick = cfg.quick;
    let lv_materials: &[MaterialModel] = if quick { &MATERIALS[..1] } else { LV_MATERIALS };
    let references: Vec<(MaterialModel, LvReference, String)> = lv_materials
        .iter()
        .map(|&m| {
            let r = lv_reference(LV_REFERENCE, m, cfg);
            let text = format!(
                "static with probe coupling on lv_shell ({} {} tets, {}): F(3 mm) = {:.4} N",
                r.tets,
                if LV_REFERENCE.1 {
                    "quadratic"
                } else {
                    "linear"
                },
                m.scene_name(),
                r.curve.forces_n[DEPTHS_MM.len() - 1]
            );
            (m, r, text)
        })
        .collect();
    // The former reference (linear elements on lv_shell(10000)) against the new one.
    if !quick {
        let old = lv_reference((10000, false), MaterialModel::StVenantKirchhoff, cfg);
        let (_, reference, ref_text) = &references[0];
        let mesh = lv_scene(10000).mesh;
        let mut row = Row::new(Scenario::LvProbe, "static".into(), "static", &mesh);
        row.reference = ref_text.clone();
        row.settings = "static with probe coupling per depth (the former reference; cached)".into();
        fill_lv_errors(&mut row, reference, &mesh, &old.curve, DEPTHS_MM.len() - 1);
        row.print();
        rows.push(row);
    }
    // (target tets, quadratic elements, strain smoothing)
    let (none, edge) = (StrainSmoothing::None, StrainSmoothing::Edge);
    let targets: &[(usize, bool, StrainSmoothing)] = if quick {
        &[(1000, false, none), (300, true, none)]
    } else {
        &[
            (1000, false, none),
            (2000, false, none),
            (5000, false, none),
            (2000, false, edge),
            (5000, false, edge),
            (300, true, none),
            (500, true, none),
            (1000, true, none),
        ]
    };
    // (safety factor, largest target it is run at: small steps on big meshes cost minutes).
    let safeties: &[f64] = if quick { &[0.5] } else { &[0.9, 0.5, 0.25] };
    let all_methods = methods(safeties);
    let last = DEPTHS_MM.len() - 1;
    for &(target, quadratic, smoothing) in targets {
        let mut base_scene = lv_scene_order(target, quadratic);
        base_scene.strain_smoothing = smoothing;
        for (model, reference, ref_text) in &references {
            let mut scene = base_scene.clone();
            scene.material.model = *model;
            // Static on this mesh: the discretisation error alone.
            let mut row = Row::new(
                Scenario::LvProbe,
                material_label("static".into(), *model),
                "static",
                &scene.mesh,
            )
            .smoothed(smoothing)
            .material(*model);
            row.reference = ref_text.clone();
            row.settings = "static with probe coupling per depth; time = whole curve".into();
            let t = Instant::now();
            match probe_static(&scene, cfg.debug) {
                Ok(c) => {
                    row.set_solve_time(t.elapsed().as_secs_f64() * 1e6);
                    fill_lv_errors(&mut row, reference, &scene.mesh, &c, last);
                }
                Err(e) => row.settings = format!("failed: {e}"),
            }
            row.print();
            rows.push(row);
            for m in all_methods.iter().filter(|m| m.material == *model) {
                let mut sc = scene.clone();
                sc.integrator.kind = m.kind;
                sc.integrator.safety_factor = m.sf;
                sc.integrator.cg_max_iterations = m.cg;
                sc.integrator.max_substeps = 1000;
                let mut row = Row::new(Scenario::LvProbe, m.label(), m.kind.name(), &scene.mesh)
                    .smoothed(smoothing)
                    .material(*model);
                row.reference = ref_text.clone();
                match probe_dynamic(&sc, quick) {
                    Ok((c, ticks, sub)) => {
                        row.settings =
                            format!("tick 1 ms, {}; staircase 0.5..3 mm", m.step_text(sub));
                        row.set_times(&ticks, sc.integrator.tick_s);
                        fill_lv_errors(&mut row, reference, &scene.mesh, &c, last);
                    }
                    Err(e) => row.settings = format!("{}: {e}", m.label()),
                }
                row.print();
                rows.push(row);
            }
        }
    }
}

/// Materials of the full `lv-probe` run. Each needs its own reference solve on the 10k-tet
/// mesh, which for the corotational material took longer than the whole run's budget, so
/// the other materials are compared on the Lamé and cantilever scenarios only (whose
/// references are analytic and small-strain, valid for all three).
pub const LV_MATERIALS: &[MaterialModel] = &[MaterialModel::StVenantKirchhoff];

/// Fills the error columns of `row` from the curve `c` on `mesh` against `reference`, `last`
/// being the index of the deepest depth.
pub fn fill_lv_errors(
    row: &mut Row,
    reference: &LvReference,
    mesh: &TetMesh,
    c: &ProbeCurve,
    last: usize,
) {
    let (l2, max_e) = reference.surface_errors(mesh, &c.x_last);
    row.rel_l2_error = l2;
    row.max_nodal_error_m = max_e;
    fill_lv_force_errors(row, reference, c, last);
    row.stable = row.stable && c.x_last.iter().all(|p| p.is_finite());
}

/// The force columns of [`fill_lv_errors`] (any body: no nodal positions needed).
pub fn fill_lv_force_errors(row: &mut Row, reference: &LvReference, c: &ProbeCurve, last: usize) {
    row.probe_force_error = reference.force_error(&c.forces_n);
    let r = reference.curve.forces_n[last];
    row.observable_error = (c.forces_n[last] - r).abs() / r;
    row.observable = format!(
        "F(mm) = [{}] N",
        c.forces_n
            .iter()
            .map(|f| format!("{f:.4}"))
            .collect::<Vec<_>>()
            .join(" ")
    );
    row.stable = c.forces_n.iter().all(|f| f.is_finite());
}
