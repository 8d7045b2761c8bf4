//! `lv-probe`: the built-in `lv` scene (material, probe, coupling) on the structured LV mesh;
//! the probe centre moves along -x at z = -5 mm from 11.98 mm (0.3 mm clear of contact) in
//! steps to depths 0.5, 1, ..., 3 mm (contact at 11.68 mm: the epicardium at 9.68 mm plus the
//! 2 mm probe radius), each step a smoothstep ramp of 100 ms then a 100 ms hold; the force
//! reported per depth is the mean device force over the last 50 ms of the hold
//! ([`crate::common::lv_press`]), with the scene's contact model (`auto`: the patch with the
//! sphere's local law of the material in series).
//!
//! Reference: the stored rigid-sphere reference ([`sphere_reference`],
//! `lv_sphere_reference.csv`: the exact 2 mm sphere on meshes refined under the probe, with
//! its uncertainty), at the depths of this press it has (St. Venant-Kirchhoff 0.5 and 1 mm,
//! stable neo-Hookean 0.5 to 3 mm; corotational 0.5 to 3 mm from the 2026-11-23 reference).
//! Probe-force error = the largest relative error over those depths, or "below uncertainty"
//! when every depth is within the reference's uncertainty. Surface-displacement error (StVK
//! rows, the `rel_l2_error` and `max_nodal_error_m` columns): the body's surface at the end of
//! the 0.5 and 1 mm holds read at 21 epicardium points around the contact
//! ([`crate::common::surface_sample_points_m`]) against the same solves' extrapolated
//! displacement there ([`fill_lv_surface_errors`]). Linear, quadratic and
//! edge-smoothed linear elements (method suffix " ES" on the 2 000 and 5 000 target meshes),
//! the mass-spring surface of the epicardium (`lv-surface-springs`, seed 003) with and without
//! run-time subdivision, and the hybrid model.

use haptic_model::element::StrainSmoothing;
use haptic_model::material::MaterialModel;

use crate::common::lv_press::{DEPTHS_MM, ProbeCurve, probe_dynamic, probe_dynamic_body};
use crate::common::{MATERIALS, lv_scene_order};
use crate::method::methods;
use crate::report::Model;
use crate::report::{Row, Scenario};
use crate::{Config, LvProbeRows};
use haptic_model::DVec3;
use haptic_model::body::SoftBody;
use haptic_model::contact::ContactModel;
use haptic_model::contact::SurfaceSampler;
use haptic_model::hybrid::{CoreMassScale, CoreStep, ScaledMotion};
use haptic_model::mass_spring::{MassSpringBody, SpringRule};
use haptic_model::meshfree::{KernelKind, MeshfreeVariant};
use haptic_model::scene::load_builtin;

/// One depth of the converged sphere reference: device depth below first contact (mm), the
/// extrapolated force magnitude (N) and its uncertainty (N).
#[derive(Debug, Clone, Copy)]
pub struct SpherePoint {
    pub depth_mm: f64,
    pub force_n: f64,
    pub uncertainty_n: f64,
}

const fn point(depth_mm: f64, force_mn: f64, uncertainty_mn: f64) -> SpherePoint {
    SpherePoint {
        depth_mm,
        force_n: force_mn * 1e-3,
        uncertainty_n: uncertainty_mn * 1e-3,
    }
}

/// The stored rigid-sphere reference of the `lv-probe` press (the exact 2 mm sphere,
/// frictionless, static, on meshes refined under the probe; issue 46): rows `material,
/// depth_convention, depth_mm, force_n, uncertainty_n, ...` (only those five columns are read;
/// the file's header says where each value comes from). Its device-convention rows are the
/// reference of this scenario.
const SPHERE_REFERENCE_CSV: &str = include_str!("lv_sphere_reference.csv");

/// The rigid-sphere reference of the `lv-probe` press for `model` (`None`: not computed): the
/// device-convention rows of [`SPHERE_REFERENCE_CSV`] (St. Venant-Kirchhoff 0.25-1 mm, stable
/// neo-Hookean 0.5-4 mm in the preliminary file of 2026-11-26). The corotational material has
/// no rows there; it keeps the 2026-11-23 three-mesh reference (`lv_sphere_reference.sh`:
/// `haptic-solve --indent` on Gmsh meshes with `hmin` 0.6 / 0.42 / 0.3 mm under the probe,
/// Richardson, Roache's grid convergence index; docs/accuracy.md "A converged sphere
/// reference"), a self-convergence study of our static solver.
pub fn sphere_reference(model: MaterialModel) -> Option<Vec<SpherePoint>> {
    const COROTATIONAL: [SpherePoint; 6] = [
        point(0.5, 4.5224, 0.1346),
        point(1.0, 9.6137, 0.4167),
        point(1.5, 15.5060, 0.4369),
        point(2.0, 18.7675, 2.8059),
        point(2.5, 24.1831, 2.6765),
        point(3.0, 31.4036, 1.0755),
    ];
    let mut points: Vec<SpherePoint> = SPHERE_REFERENCE_CSV
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#') && !l.starts_with("material"))
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').map(str::trim).collect();
            if f.len() < 5 || f[0] != model.scene_name() || f[1] != "device" {
                return None;
            }
            let num = |s: &str| s.parse::<f64>().expect("a number in the sphere reference");
            Some(SpherePoint {
                depth_mm: num(f[2]),
                force_n: num(f[3]),
                uncertainty_n: num(f[4]),
            })
        })
        .collect();
    points.sort_by(|a, b| a.depth_mm.total_cmp(&b.depth_mm));
    if points.is_empty() && model == MaterialModel::Corotational {
        points = COROTATIONAL.to_vec();
    }
    (!points.is_empty()).then_some(points)
}

/// The reference text of a row of `model`.
pub fn sphere_reference_text(model: MaterialModel) -> String {
    match sphere_reference(model) {
        Some(points) => format!(
            "rigid-sphere reference ({}): {}",
            model.scene_name(),
            points
                .iter()
                .map(|p| format!(
                    "{:.2} +- {:.2} mN at {} mm",
                    p.force_n * 1e3,
                    p.uncertainty_n * 1e3,
                    p.depth_mm
                ))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        None => format!("no rigid-sphere reference for {}", model.scene_name()),
    }
}

/// Runs the scenario: per mesh and material every dynamic method, then the mass-spring rows
/// ([`mass_spring_rows`]) and the hybrid rows ([`hybrid_rows`]); with `--lv-probe-rows` those
/// only.
pub fn run(cfg: &Config, rows: &mut Vec<Row>) {
    match cfg.lv_probe_rows {
        LvProbeRows::MassSpring => mass_spring_rows(cfg.quick, rows),
        LvProbeRows::Hybrid => hybrid_rows(cfg.quick, rows),
        LvProbeRows::Contact => contact_rows(cfg.quick, rows),
        LvProbeRows::All => {
            run_fem(cfg, rows);
            contact_rows(cfg.quick, rows);
            mass_spring_rows(cfg.quick, rows);
            hybrid_rows(cfg.quick, rows);
        }
    }
}

/// The built-in `lv` scene (474 quadratic tets on the rest factor) with each explicit probe
/// contact model: the exact sphere, the kernel patch, the patch with the sphere's Hertz
/// compliance, and the patch with the material's own local law (`auto`, as every FEM row).
/// The local indentation of the last two is sub-grid, so their surface shows the dent without
/// it.
pub fn contact_rows(quick: bool, rows: &mut Vec<Row>) {
    let base = load_builtin("lv").expect("built-in lv");
    let ref_text = sphere_reference_text(base.material.model);
    for contact in [
        ContactModel::Sphere,
        ContactModel::Patch,
        ContactModel::PatchHertz,
        ContactModel::PatchLocal,
    ] {
        let mut scene = base.clone();
        scene.probe.contact = contact;
        let label = format!("lv default, contact {}", contact.name());
        let mut row = Row::new(
            Scenario::LvProbe,
            label.clone(),
            scene.integrator.kind.name(),
            &scene.mesh,
        )
        .material(scene.material.model);
        row.reference = ref_text.clone();
        match probe_dynamic(&scene, quick) {
            Ok((c, ticks, sub)) => {
                row.settings = format!(
                    "tick 1 ms, {sub} sub-steps, the lv scene's integrator; staircase 0.5..3 mm"
                );
                row.set_times(&ticks, scene.integrator.tick_s);
                fill_lv_errors(&mut row, scene.material.model, &c);
            }
            Err(e) => row.settings = format!("{label}: {e}"),
        }
        row.print();
        rows.push(row);
    }
}

/// The seeds' hybrid model `lv-hybrid` (a coarse LV core and about 53 000 meshfree particles
/// up to the epicardium, activated under the probe) pressed like the FEM
/// ([`probe_dynamic_body`]): both meshfree variants as the scene steps them (deviation mass
/// `mass_scale` of the scene, the implicit core at its real inertia) and stepped explicitly at the
/// scene's former scales (`mass_scale = 1000`, `core_mass_scale = "auto"`); the corrected
/// one explicitly with the core as heavy as the particles (`"uniform"`) at 1000 and at 100,
/// and both explicitly with the body's real inertia (`core_mass_scale = 1`, particles at
/// `mass_scale = 300`); forces against the sphere reference of its material: the scene's
/// stable neo-Hookean for the corrected variant ("hybrid corrected" is the scene as it
/// ships), St. Venant-Kirchhoff for the seed variant, the paper's formulation, which the
/// scene refuses on another material.
pub fn hybrid_rows(quick: bool, rows: &mut Vec<Row>) {
    let base = load_builtin("lv-hybrid").expect("built-in lv-hybrid");
    let (seed, corrected) = (MeshfreeVariant::Seed, MeshfreeVariant::Corrected);
    let (auto, uniform, real) = (
        CoreMassScale::Auto,
        CoreMassScale::Uniform,
        CoreMassScale::Fixed(1.0),
    );
    // `None`: as the scene says; else stepped explicitly at (mass_scale, core_mass_scale).
    for (variant, explicit) in [
        (seed, None),
        (corrected, None),
        (seed, Some((1000.0, auto))),
        (corrected, Some((1000.0, auto))),
        (corrected, Some((1000.0, uniform))),
        (corrected, Some((100.0, uniform))),
        (seed, Some((300.0, real))),
        (corrected, Some((300.0, real))),
    ] {
        let mut scene = base.clone();
        let h = scene.hybrid.as_mut().expect("a hybrid scene");
        h.params.meshfree.variant = variant;
        h.params.meshfree.kernel = KernelKind::default_for(variant);
        // The seed variant is the paper's St. Venant-Kirchhoff formulation (the scene refuses
        // it on another material): its rows run StVK, against the StVK reference.
        if variant == MeshfreeVariant::Seed {
            scene.material.model = MaterialModel::StVenantKirchhoff;
        }
        let material = scene.material.model;
        let ref_text = sphere_reference_text(material);
        let label = match explicit {
            None => format!("hybrid {}", variant.name()),
            Some((mass_scale, core)) => {
                h.params.scaled_motion = ScaledMotion::Absolute;
                h.params.core_step = CoreStep::Explicit;
                h.params.mass_scale = mass_scale;
                h.params.core_mass_scale = core;
                match core {
                    CoreMassScale::Fixed(_) => {
                        format!(
                            "hybrid {}, explicit, real inertia ({mass_scale})",
                            variant.name()
                        )
                    }
                    _ => format!("hybrid {}, explicit, {core} {mass_scale}", variant.name()),
                }
            }
        };
        let mass_scale = h.params.mass_scale;
        let stepping = match h.params.core_step {
            CoreStep::Explicit => format!("{} mass, explicit core", h.params.scaled_motion),
            CoreStep::Implicit { margin } => format!(
                "{} mass, implicit core (margin {margin})",
                h.params.scaled_motion
            ),
        };
        let mut row = Row::blank(Scenario::LvProbe, label.clone(), "symplectic-euler");
        row.model = Model::Hybrid;
        row.material = material.scene_name().into();
        row.reference = ref_text;
        let mut body = match haptic_model::build_hybrid_body(&scene, &mut |_, _| {}) {
            Ok(b) => b,
            Err(e) => {
                row.settings = format!("{label}: {e}");
                row.print();
                rows.push(row);
                continue;
            }
        };
        let core_scale = body.core_mass_scale();
        let stats0 = body.stats();
        row.nodes = stats0.nodes;
        row.tets = stats0.elements;
        match probe_dynamic_body(&mut body, scene.integrator.tick_s, quick) {
            Ok((curve, ticks)) => {
                let info = body.info();
                let stats = body.stats();
                row.settings = format!(
                    "tick 1 ms, {} sub-steps; {} particles, {} active at 3 mm; mass_scale {}, core_mass_scale {}, {stepping}; staircase 0.5..3 mm",
                    info.substeps, stats.particles, stats.active_particles, mass_scale, core_scale
                );
                row.set_times(&ticks, scene.integrator.tick_s);
                fill_lv_errors(&mut row, material, &curve);
            }
            Err(e) => row.settings = format!("{label}: {e}"),
        }
        row.print();
        rows.push(row);
    }
}

/// The mass-spring surface `lv-surface-springs` (the epicardium of `lv_shell(2000)` on home
/// springs, seed 003) pressed like the FEM ([`probe_dynamic_body`]): the scene as it ships
/// (one-ring subdivision, calibrated springs and its organ table of contact factors, built as
/// `build_body` builds it; label "lv-surface-springs (scene)"), then without the organ table:
/// coarse, one-ring subdivided with the calibrated springs (the scene's table) and with the
/// springs unchanged. Forces against the stable neo-Hookean sphere reference, the organ the
/// scene's organ table is calibrated to (before 2026-11-26 session 3: StVK, which the springs
/// alone were once fitted to).
pub fn mass_spring_rows(quick: bool, rows: &mut Vec<Row>) {
    let scene = load_builtin("lv-surface-springs").expect("built-in lv-surface-springs");
    let ms = scene.mass_spring.clone().expect("a mass-spring scene");
    // (label, rings, spring rule, with the scene's organ table)
    let variants: [(&str, u32, SpringRule, bool); 4] = [
        (
            "lv-surface-springs (scene)",
            ms.params.subdivision.rings,
            ms.params.subdivision.springs,
            true,
        ),
        ("mass-spring", 0, SpringRule::Calibrated, false),
        ("mass-spring 1-ring", 1, SpringRule::Calibrated, false),
        (
            "mass-spring 1-ring unchanged",
            1,
            SpringRule::Unchanged,
            false,
        ),
    ];
    // The spring surface has no material law: its forces are held against the sphere
    // reference of the organ its organ table is calibrated to, stable neo-Hookean.
    let organ = MaterialModel::StableNeoHookean;
    let ref_text = sphere_reference_text(organ);
    for (label, rings, springs, with_organ) in variants {
        let mut params = ms.params;
        params.subdivision.rings = rings;
        params.subdivision.springs = springs;
        let table = if rings > 0 && springs == SpringRule::Calibrated {
            ms.table().expect("the built-in table")
        } else {
            None
        };
        let organ_table = match (&ms.organ, with_organ) {
            (Some(o), true) => Some(o.table().expect("the built-in organ table")),
            _ => None,
        };
        let mut row = Row::blank(Scenario::LvProbe, label.into(), "symplectic-euler");
        row.model = Model::MassSpring;
        row.material = "mass-spring".into();
        row.nodes = ms.surface.node_count();
        row.reference = ref_text.clone();
        let built = MassSpringBody::new(
            ms.surface.clone(),
            &params,
            table,
            scene.probe,
            &scene.integrator,
            label,
        )
        .and_then(|b| match organ_table {
            Some(t) => b.with_organ_table(t),
            None => Ok(b),
        });
        let mut body = match built {
            Ok(b) => b,
            Err(e) => {
                row.settings = format!("{label}: {e}");
                row.print();
                rows.push(row);
                continue;
            }
        };
        match probe_dynamic_body(&mut body, scene.integrator.tick_s, quick) {
            Ok((curve, ticks)) => {
                row.settings = format!(
                    "tick 1 ms, {} sub-steps (worst-case Gershgorin bound); K_h = K_m = {} N/m{}; {} subdivision event(s), up to {} nodes; staircase 0.5..3 mm",
                    body.plan().substeps,
                    params.home_spring_n_per_m,
                    if body.organ_table().is_some() {
                        ", times the organ table's contact factor"
                    } else {
                        ""
                    },
                    body.event_stats().events,
                    body.stats().nodes
                );
                row.set_times(&ticks, scene.integrator.tick_s);
                fill_lv_errors(&mut row, organ, &curve);
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
    let references: Vec<(MaterialModel, String)> = lv_materials
        .iter()
        .map(|&m| (m, sphere_reference_text(m)))
        .collect();
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
    for &(target, quadratic, smoothing) in targets {
        let mut base_scene = lv_scene_order(target, quadratic);
        base_scene.strain_smoothing = smoothing;
        for (model, ref_text) in &references {
            let mut scene = base_scene.clone();
            scene.material.model = *model;
            for m in all_methods.iter().filter(|m| m.material == *model) {
                let mut sc = scene.clone();
                sc.integrator.kind = m.kind;
                sc.integrator.safety_factor = m.sf;
                sc.integrator.cg_max_iterations = m.cg;
                sc.integrator.linear_solver = m.solver;
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
                        fill_lv_errors(&mut row, *model, &c);
                    }
                    Err(e) => row.settings = format!("{}: {e}", m.label()),
                }
                row.print();
                rows.push(row);
            }
        }
    }
}

/// Materials of the full `lv-probe` run: those with a converged sphere reference
/// ([`sphere_reference`]), all three.
pub const LV_MATERIALS: &[MaterialModel] = &[
    MaterialModel::StVenantKirchhoff,
    MaterialModel::Corotational,
    MaterialModel::StableNeoHookean,
];

/// The force columns of a row from the curve `c` (any body): the largest relative error against
/// [`sphere_reference`] of `model` over its depths, the reference's largest
/// relative uncertainty, whether every depth is within it, and the observable error at the
/// reference's deepest depth. Without a reference for `model` the errors stay unmeasured.
/// The converged surface-displacement reference of the `lv-probe` press (St. Venant-Kirchhoff,
/// device depths 0.5 and 1 mm): the epicardium's displacement at
/// [`crate::common::surface_sample_points_m`] from the same three refined-mesh `haptic-solve
/// --indent` runs as [`sphere_reference`] (`lv_sphere_reference.sh`, then `lv_study reference
/// --surface`), Richardson's extrapolation per point and component, the uncertainty the norm
/// of the components' grid convergence indices. CSV, mm.
const SURFACE_REFERENCE_CSV: &str = include_str!("lv_probe_surface_reference.csv");

/// One row of [`SURFACE_REFERENCE_CSV`] (m).
struct SurfacePoint {
    depth_mm: f64,
    point: usize,
    u_m: DVec3,
    uncertainty_m: f64,
}

fn surface_reference() -> Vec<SurfacePoint> {
    SURFACE_REFERENCE_CSV
        .lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l
                .split(',')
                .map(|x| x.trim().parse().expect("a number in the surface reference"))
                .collect();
            SurfacePoint {
                depth_mm: v[0],
                point: v[1] as usize,
                u_m: DVec3::new(v[5], v[6], v[7]) * 1e-3,
                uncertainty_m: v[8] * 1e-3,
            }
        })
        .collect()
}

/// The surface-displacement error of a dynamic `lv-probe` run against [`surface_reference`]
/// (St. Venant-Kirchhoff only): at each reference depth, the body's surface at the end of the
/// hold read at the sample points ([`SurfaceSampler`]); `rel_l2_error` = the largest over the
/// depths of `sqrt(sum |u - u_ref|^2 / sum |u_ref|^2)`, `max_nodal_error_m` = the largest
/// point error (m). The reference's own relative uncertainty is printed with it.
pub fn fill_lv_surface_errors(row: &mut Row, model: MaterialModel, c: &ProbeCurve) {
    if model != MaterialModel::StVenantKirchhoff || c.surfaces.is_empty() {
        return;
    }
    let reference = surface_reference();
    let points = crate::common::surface_sample_points_m();
    let (mut rel, mut max_m, mut unc) = (0.0f64, 0.0f64, 0.0f64);
    for (j, d) in DEPTHS_MM.iter().enumerate() {
        let here: Vec<&SurfacePoint> = reference
            .iter()
            .filter(|p| (p.depth_mm - d).abs() < 1e-9)
            .collect();
        if here.is_empty() || j >= c.surfaces.len() {
            continue;
        }
        let snap = &c.surfaces[j];
        let sampler = SurfaceSampler::new(&snap.rest, &snap.triangles, &points);
        let u = sampler.displacements(&snap.rest, &snap.x);
        let (mut num, mut den, mut unc2) = (0.0, 0.0, 0.0);
        for p in &here {
            let e = (u[p.point] - p.u_m).length();
            num += e * e;
            den += p.u_m.length_squared();
            unc2 += p.uncertainty_m * p.uncertainty_m;
            max_m = max_m.max(e);
        }
        rel = rel.max((num / den).sqrt());
        unc = unc.max((unc2 / den).sqrt());
    }
    row.rel_l2_error = rel;
    row.max_nodal_error_m = max_m;
    row.settings.push_str(&format!(
        "; surface reference uncertainty {:.1} %",
        100.0 * unc
    ));
}

/// [`fill_lv_force_errors`] and [`fill_lv_surface_errors`].
pub fn fill_lv_errors(row: &mut Row, model: MaterialModel, c: &ProbeCurve) {
    fill_lv_force_errors(row, model, c);
    fill_lv_surface_errors(row, model, c);
}

pub fn fill_lv_force_errors(row: &mut Row, model: MaterialModel, c: &ProbeCurve) {
    row.observable = format!(
        "F(mm) = [{}] N",
        c.forces_n
            .iter()
            .map(|f| format!("{f:.4}"))
            .collect::<Vec<_>>()
            .join(" ")
    );
    row.stable = c.forces_n.iter().all(|f| f.is_finite());
    let Some(points) = sphere_reference(model) else {
        return;
    };
    let (mut error, mut uncertainty, mut below) = (0.0f64, 0.0f64, true);
    for p in points {
        let Some(j) = DEPTHS_MM.iter().position(|d| (d - p.depth_mm).abs() < 1e-9) else {
            continue;
        };
        let f = c.forces_n[j];
        error = error.max((f - p.force_n).abs() / p.force_n);
        uncertainty = uncertainty.max(p.uncertainty_n / p.force_n);
        below &= (f - p.force_n).abs() <= p.uncertainty_n;
        row.observable_error = (f - p.force_n).abs() / p.force_n;
    }
    row.probe_force_error = error;
    row.force_reference_uncertainty = uncertainty;
    row.force_below_uncertainty = below;
}
