//! Micro-benchmarks (issue 3, section 4) with divan: one internal-force evaluation
//! (`FemModel::add_internal_forces`, elastic + viscous, and elastic alone) and one full `FemBody::tick` (all
//! sub-steps, probe pressing 3 mm into the epicardium) on the structured LV at about 1k, 2k,
//! 10k tets, on `lv_h1.msh` (17 924 tets), and with quadratic (10-node) tetrahedra on the
//! structured LV at about 500 and 1k elements (`q` suffix); and the condensed tick of
//! `deploy/scenes/lv_h1_condensed.toml` at three active-region radii (`tick_condensed`).
//!
//! Run: `cargo bench -p haptic-model --bench micro` (single thread; divan prints median and
//! spread per size).

mod common;

use common::{lv_h1_scene, lv_scene};
use haptic_model::DVec3;
use haptic_model::fem::{FemBody, TickInput};
use haptic_model::scene::Scene;

fn main() {
    divan::main();
}

/// Meshes: structured LV at about N tets (`lvN`), `lv_h1` (`deploy/scenes/lv_h1.toml`:
/// `lv_h1.msh` with single-precision forces, or the structured `lv_shell(18000)` when the
/// shared data is absent; `lv_h1d` the same in double precision), and quadratic elements
/// (`lvNq`).
const SIZES: [&str; 9] = [
    "lv1000", "lv2000", "lv10000", "lv_h1", "lv_h1d", "lv_h1es", "lv300q", "lv500q", "lv1000q",
];

fn scene(name: &str) -> Scene {
    if name == "lv_h1" {
        return lv_h1_scene().unwrap_or_else(|| lv_scene(18000));
    }
    if name == "lv_h1d" || name == "lv_h1es" {
        let mut sc = scene("lv_h1");
        sc.integrator.single_precision_forces = false;
        if name == "lv_h1es" {
            // The same mesh with edge-based strain smoothing (ES-FEM-T4).
            sc.strain_smoothing = haptic_model::element::StrainSmoothing::Edge;
        }
        return sc;
    }
    let spec = name.trim_start_matches("lv");
    let quadratic = spec.ends_with('q');
    let tets: usize = spec.trim_end_matches('q').parse().expect("mesh size");
    if quadratic {
        common::lv_scene_on(haptic_model::mesh::generate::lv_shell_quadratic(tets))
    } else {
        lv_scene(tets)
    }
}

/// A simulation pressed 3 mm into the epicardium at the equator (200 ticks to get there), so
/// that forces and ticks are measured on a deformed body in contact.
fn pressed(size: &str) -> (FemBody, TickInput) {
    pressed_scene(&scene(size))
}

fn pressed_scene(scene: &Scene) -> (FemBody, TickInput) {
    let mut sim = FemBody::new(scene).expect("simulation");
    let mut input = TickInput::default();
    for k in 0..200 {
        let depth = 0.003 * common::smoothstep(k as f64 / 150.0);
        input = TickInput {
            device_position_m: Some(DVec3::new(0.011_682 - depth, 0.0, -0.005)),
            device_velocity_m_per_s: DVec3::ZERO,
        };
        sim.tick(&input).expect("tick");
    }
    (sim, input)
}

/// One force evaluation on the pressed body, with the viscous stress when `viscous`, in the
/// scene's precision (`FemModel::add_internal_forces_with`).
fn bench_forces(bencher: divan::Bencher, size: &str, viscous: bool) {
    bench_forces_of(bencher, pressed(size).0, viscous);
}

fn bench_forces_of(bencher: divan::Bencher, sim: FemBody, viscous: bool) {
    bench_model_forces(bencher, sim.fem(), &sim, viscous);
}

/// One force evaluation of `fem` (the model of `sim`, or a copy of it) in `sim`'s state.
fn bench_model_forces(
    bencher: divan::Bencher,
    fem: &haptic_model::element::FemModel,
    sim: &FemBody,
    viscous: bool,
) {
    let n = fem.node_count();
    let mut f = vec![DVec3::ZERO; n];
    let mut scratch = haptic_model::element::ForceScratch::new(n);
    let velocities = viscous.then_some(sim.state().v.as_slice());
    bencher.counter(fem.tets().len()).bench_local(|| {
        f.iter_mut().for_each(|v| *v = DVec3::ZERO);
        fem.add_internal_forces_with(&sim.state().x, velocities, &mut f, &mut scratch);
        divan::black_box(&f);
    });
}

#[divan::bench(args = SIZES, sample_count = 30)]
fn add_internal_forces(bencher: divan::Bencher, size: &str) {
    bench_forces(bencher, size, true);
}

/// The elastic force alone (no viscous stress), the quantity the peer comparison and the
/// issue's 0.3 ms target on `lv_h1` name.
#[divan::bench(args = SIZES, sample_count = 30)]
fn add_elastic_forces(bencher: divan::Bencher, size: &str) {
    bench_forces(bencher, size, false);
}

/// The single-precision force evaluation of `lv_h1` (pressed as in [`pressed`]) in each
/// instruction set the kernel is built for, `isa kind` (`avx2` or `avx512`; `viscous` or
/// `elastic`): the two builds compared in one run. An instruction set this CPU lacks is
/// reported and skipped.
const SINGLE_ISA_RUNS: [&str; 4] = [
    "avx2 viscous",
    "avx512 viscous",
    "avx2 elastic",
    "avx512 elastic",
];

#[divan::bench(args = SINGLE_ISA_RUNS, sample_count = 30)]
fn add_forces_single_isa(bencher: divan::Bencher, run: &str) {
    use haptic_model::element::SingleIsa;
    let (isa, kind) = run.split_once(' ').expect("isa kind");
    let isa = if isa == "avx2" {
        SingleIsa::Avx2
    } else {
        SingleIsa::Avx512
    };
    if !isa.is_available() {
        eprintln!("{isa:?} is not available on this CPU: {run} skipped");
        return;
    }
    let sim = pressed("lv_h1").0;
    let mut fem = sim.fem().clone();
    fem.pin_single_precision_isa(isa)
        .expect("lv_h1 runs single precision");
    bench_model_forces(bencher, &fem, &sim, kind == "viscous");
}

/// Force evaluation (elastic + viscous) per material model: `mesh material`.
const MATERIAL_RUNS: [&str; 6] = [
    "lv500q stvk",
    "lv500q stable-neo-hookean",
    "lv500q corotational",
    "lv_h1 stvk",
    "lv_h1 stable-neo-hookean",
    "lv_h1 corotational",
];

#[divan::bench(args = MATERIAL_RUNS, sample_count = 20)]
fn add_internal_forces_material(bencher: divan::Bencher, run: &str) {
    let (mesh, model) = run.split_once(' ').expect("mesh material");
    let mut sc = scene(mesh);
    sc.material.model =
        haptic_model::material::MaterialModel::from_scene_name(model).expect("material");
    // The single-precision kernel is StVK's only: the other laws run in double precision.
    sc.integrator.single_precision_forces &= model == "stvk";
    bench_forces_of(bencher, pressed_scene(&sc).0, true);
}

#[divan::bench(args = SIZES, sample_count = 20)]
fn tick(bencher: divan::Bencher, size: &str) {
    let (mut sim, input) = pressed(size);
    bencher.bench_local(|| sim.tick(divan::black_box(&input)).expect("tick"));
}

/// `lv_h1.msh` with edge smoothing and backward Euler on the tetrahedra within R mm of the
/// probe, the rest condensed (`deploy/scenes/lv_h1_condensed.toml`, radius overridden).
const CONDENSED_RADII_MM: [f64; 3] = [6.0, 7.0, 8.0];

#[divan::bench(args = CONDENSED_RADII_MM, sample_count = 20)]
fn tick_condensed(bencher: divan::Bencher, radius_mm: f64) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../deploy/scenes/lv_h1_condensed.toml");
    let Ok(mut sc) = haptic_model::scene::load_scene_file(&path) else {
        eprintln!("lv_h1.msh not found: tick_condensed skipped");
        return;
    };
    if let Some(r) = &mut sc.active_region {
        r.radius_m = radius_mm * 1e-3;
    }
    let (mut sim, input) = pressed_scene(&sc);
    bencher.bench_local(|| sim.tick(divan::black_box(&input)).expect("tick"));
}

/// Integrators on the curved quadratic LV meshes: `mesh integrator safety-factor-or-CG-cap`.
/// (`backward-euler rest`: the rest factor, the built-in `lv`'s default.)
const QUADRATIC_RUNS: [&str; 7] = [
    "lv300q symplectic-euler 0.9",
    "lv500q symplectic-euler 0.9",
    "lv500q symplectic-euler 0.5",
    "lv500q backward-euler 5",
    "lv500q backward-euler 8",
    "lv500q backward-euler rest",
    "lv500q semi-implicit 0.5",
];

#[divan::bench(args = QUADRATIC_RUNS, sample_count = 20)]
fn tick_quadratic(bencher: divan::Bencher, run: &str) {
    use haptic_model::integrate::IntegratorKind;
    let f: Vec<&str> = run.split(' ').collect();
    let mut sc = scene(f[0]);
    sc.integrator.kind = IntegratorKind::from_name(f[1]).expect("integrator");
    if sc.integrator.kind == IntegratorKind::BackwardEuler {
        use haptic_model::integrate::LinearSolver;
        if f[2] == "rest" {
            sc.integrator.linear_solver = LinearSolver::RestCholesky;
        } else {
            sc.integrator.linear_solver = LinearSolver::Cg;
            sc.integrator.cg_max_iterations = f[2].parse().expect("CG cap");
        }
    } else {
        sc.integrator.safety_factor = f[2].parse().expect("safety factor");
    }
    let (mut sim, input) = pressed_scene(&sc);
    bencher.bench_local(|| sim.tick(divan::black_box(&input)).expect("tick"));
}
