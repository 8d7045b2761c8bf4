//! Element forces in parts (issue 48 section 1): the single-precision kernel's batches cut into
//! contiguous ranges, one per thread, each summing into its own arrays. On `lv_h1.msh` (4 398
//! nodes, 17 924 tets, as shipped in `deploy/scenes/lv_h1.toml`) dented 3 mm: two parts agree
//! with one part within the kernel's own bound (2e-6 of the largest nodal force,
//! `docs/decisions.md`, "Single-precision forces"), whole body (edge-smoothed and plain) and an
//! r = 7 mm region's model (every body node, a tenth of them touched); two parts on two threads
//! equal the two parts run one after the other bit for bit; no allocation. The double-precision
//! kernel in two parts (issue 48 section 3: lane halves of the tetrahedra, halves of the
//! Morton curve of the smoothing domains) likewise, within 1e-13 of the largest nodal force of
//! one part (the kernel's own unit tests hold one and two parts to 1e-12 of the scalar loop).

use crate::counting_alloc;

use std::path::Path;
use std::sync::Arc;

use haptic_model::DVec3;
use haptic_model::element::{FemModel, ForceScratch, PartRunner, StrainSmoothing};
use haptic_model::mesh::TetMesh;
use haptic_model::pool::{StartHook, TickPool};

#[path = "../examples/common/part_runners.rs"]
mod part_runners;
use part_runners::{Scoped, Serial};

/// The probe's point on the epicardium of `lv_h1` (m) and the outward normal there.
const CENTRE_M: DVec3 = DVec3::new(0.009682, 0.0, -0.005);

/// `lv_h1.msh` as shipped, with its material (stable neo-Hookean, viscous).
fn lv_h1() -> (TetMesh, haptic_model::material::MaterialParams) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../deploy/scenes/lv_h1.toml");
    let scene = haptic_model::scene::load_scene_file(&path).unwrap_or_else(|e| {
        panic!(
            "{}: {e} (lv_h1.msh is read from ../shared/data/lv beside the repository)",
            path.display()
        )
    });
    (scene.mesh, scene.material)
}

/// A model of `mesh`'s tetrahedra `keep` (every node kept) in single precision.
fn model(
    mesh: &TetMesh,
    mat: haptic_model::material::MaterialParams,
    keep: &dyn Fn(&[u32; 4]) -> bool,
    smoothing: StrainSmoothing,
) -> FemModel {
    let mut m = model_double(mesh, mat, keep, smoothing);
    m.set_single_precision(true).expect("single precision");
    m
}

/// [`model`] in double precision.
fn model_double(
    mesh: &TetMesh,
    mat: haptic_model::material::MaterialParams,
    keep: &dyn Fn(&[u32; 4]) -> bool,
    smoothing: StrainSmoothing,
) -> FemModel {
    let part = TetMesh {
        nodes: mesh.nodes.clone(),
        tets: mesh.tets.iter().copied().filter(|t| keep(t)).collect(),
        tet_edge_nodes: Vec::new(),
        surfaces: Vec::new(),
        node_groups: Vec::new(),
    };
    FemModel::with_smoothing(&part, mat, smoothing).expect("the lv_h1 model")
}

/// A 3 mm dent along `-n` around [`CENTRE_M`] (Gaussian, 3 mm wide) and a velocity of ten
/// times the displacement per second: positions and velocities.
fn dented(rest: &[DVec3]) -> (Vec<DVec3>, Vec<DVec3>) {
    let n = DVec3::new(CENTRE_M.x, CENTRE_M.y, 0.0).normalize();
    let u: Vec<DVec3> = rest
        .iter()
        .map(|p| -0.003 * n * (-(*p - CENTRE_M).length_squared() / (2.0 * 0.003f64.powi(2))).exp())
        .collect();
    let x = rest.iter().zip(&u).map(|(p, u)| *p + *u).collect();
    (x, u.iter().map(|u| 10.0 * *u).collect())
}

/// A non-zero start for the forces (the kernel adds to them).
fn start(n: usize) -> Vec<DVec3> {
    (0..n)
        .map(|i| DVec3::new(1e-3, -2e-3, 3e-3) * (i % 7) as f64)
        .collect()
}

/// The forces added by `model` for the dented state through `runner`.
fn forces(model: &FemModel, runner: &dyn PartRunner, scratch: &mut ForceScratch) -> Vec<DVec3> {
    let (x, v) = dented(model.rest());
    let mut f = start(model.node_count());
    model.add_internal_forces_in(runner, &x, Some(&v), &mut f, scratch);
    f
}

/// A tetrahedron with a corner within 7 mm of [`CENTRE_M`] (the region of [`models`]).
fn near_centre(mesh: &TetMesh, t: &[u32; 4]) -> bool {
    t.iter()
        .any(|&i| (mesh.nodes[i as usize] - CENTRE_M).length() < 0.007)
}

/// The three models: whole body edge-smoothed (as shipped) and plain, and the r = 7 mm region
/// (tetrahedra with a corner within 7 mm of the centre) edge-smoothed.
fn models() -> Vec<(&'static str, FemModel)> {
    let (mesh, mat) = lv_h1();
    let near = |t: &[u32; 4]| near_centre(&mesh, t);
    vec![
        (
            "whole, edge-smoothed",
            model(&mesh, mat, &|_| true, StrainSmoothing::Edge),
        ),
        (
            "whole, plain",
            model(&mesh, mat, &|_| true, StrainSmoothing::None),
        ),
        (
            "r = 7 mm region",
            model(&mesh, mat, &near, StrainSmoothing::Edge),
        ),
    ]
}

#[test]
fn two_parts_agree_with_one_part_and_one_part_is_the_serial_path() {
    for (name, m) in models() {
        let n = m.node_count();
        let mut scratch = ForceScratch::with_parts(n, 2);
        let one = forces(&m, &Serial(1), &mut scratch);
        // One part is add_internal_forces_with, bit for bit.
        let (x, v) = dented(m.rest());
        let mut with = start(n);
        m.add_internal_forces_with(&x, Some(&v), &mut with, &mut ForceScratch::new(n));
        assert!(
            one.iter()
                .zip(&with)
                .all(|(a, b)| a.to_array() == b.to_array()),
            "{name}"
        );
        let two = forces(&m, &Serial(2), &mut scratch);
        let base = start(n);
        let scale = one
            .iter()
            .zip(&base)
            .map(|(f, s)| (*f - *s).length())
            .fold(0.0, f64::max);
        let err = one
            .iter()
            .zip(&two)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        eprintln!(
            "{name}: largest nodal force {scale:.3e} N, 2 parts vs 1: {:.2e} of it",
            err / scale
        );
        let (touched_nodes, shared) = m.force_part_nodes(2).expect("single precision");
        eprintln!("{name}: 2 parts touch {touched_nodes} of {n} nodes, {shared} shared");
        assert!(shared > 0 && shared <= touched_nodes, "{name}");
        if name.contains("plain") {
            // Tetrahedra in Morton runs: the halves are compact, the cut is thin.
            assert!(shared < touched_nodes / 4, "{name}");
        }
        assert!(
            scale > 1e-3,
            "{name}: the dent loads the body ({scale:e} N)"
        );
        // The sums of the cut differ by rounding only; at least one differs at all (the cut
        // exists), none by more than the kernel's bound.
        assert!(
            err < 2e-6 * scale && err > 0.0,
            "{name}: {err:e} of {scale:e} N"
        );
        // Nodes no element of the model touches keep their forces exactly (the region).
        let touched: std::collections::HashSet<usize> =
            m.tets().iter().flatten().map(|&i| i as usize).collect();
        for i in (0..n).filter(|i| !touched.contains(i)) {
            assert_eq!(two[i].to_array(), base[i].to_array(), "{name}: node {i}");
        }
        if name.starts_with("r = 7") {
            assert!(
                touched.len() < n / 4,
                "{name}: {} of {n} nodes",
                touched.len()
            );
        }
        // The scratch is clean after a call: the same call again gives the same forces.
        assert_eq!(forces(&m, &Serial(2), &mut scratch), two, "{name}");
    }
}

#[test]
fn two_parts_on_two_threads_equal_two_parts_on_one() {
    for (name, m) in models() {
        let mut scratch = ForceScratch::with_parts(m.node_count(), 2);
        let serial = forces(&m, &Serial(2), &mut scratch);
        for _ in 0..3 {
            let threaded = forces(&m, &Scoped, &mut scratch);
            assert!(
                serial
                    .iter()
                    .zip(&threaded)
                    .all(|(a, b)| a.to_array() == b.to_array()),
                "{name}"
            );
        }
        // A scratch of one part runs one part whatever the pool.
        let mut one = ForceScratch::new(m.node_count());
        assert_eq!(
            forces(&m, &Scoped, &mut one),
            forces(&m, &Serial(1), &mut one),
            "{name}"
        );
    }
}

#[test]
fn force_parts_allocate_nothing() {
    // Registers pool workers: one such test at a time in this binary (`counting_alloc`).
    let _one = counting_alloc::one_at_a_time();
    let (mesh, mat) = lv_h1();
    let m = model(&mesh, mat, &|_| true, StrainSmoothing::Edge);
    let n = m.node_count();
    let (x, v) = dented(m.rest());
    let mut f = vec![DVec3::ZERO; n];
    let mut scratch = ForceScratch::with_parts(n, 2);
    // A pool's workers register themselves (with the serial skeleton there are none).
    let hook: StartHook = Arc::new(|_| counting_alloc::count_this_thread());
    let pool = TickPool::new(1, hook).expect("a pool of one worker");
    let ((), allocations) = counting_alloc::counted_registered(|| {
        for _ in 0..3 {
            m.add_internal_forces_in(&Serial(2), &x, Some(&v), &mut f, &mut scratch);
            m.add_internal_forces_in(&*pool, &x, Some(&v), &mut f, &mut scratch);
            m.add_internal_forces_in(&*pool, &x, None, &mut f, &mut scratch);
        }
    });
    assert_eq!(allocations, 0);
    assert!(f.iter().any(|f| f.length() > 0.0));
}

/// The models of [`models`] in double precision, and the whole body plain in St
/// Venant-Kirchhoff (the peer comparison's law).
fn models_double() -> Vec<(&'static str, FemModel)> {
    let (mesh, mat) = lv_h1();
    let near = |t: &[u32; 4]| near_centre(&mesh, t);
    let mut stvk = mat;
    stvk.model = haptic_model::material::MaterialModel::StVenantKirchhoff;
    vec![
        (
            "double, whole, edge-smoothed",
            model_double(&mesh, mat, &|_| true, StrainSmoothing::Edge),
        ),
        (
            "double, whole, plain",
            model_double(&mesh, mat, &|_| true, StrainSmoothing::None),
        ),
        (
            "double, whole, plain, StVK",
            model_double(&mesh, stvk, &|_| true, StrainSmoothing::None),
        ),
        (
            "double, r = 7 mm region",
            model_double(&mesh, mat, &near, StrainSmoothing::Edge),
        ),
    ]
}

/// Whether the double-precision parts run here (AVX2 and FMA; elsewhere they decline and the
/// one-part kernel runs).
fn double_parts_run() -> bool {
    haptic_model::element::SingleIsa::detect().is_some()
}

#[test]
fn double_precision_in_two_parts_agrees_with_one_part() {
    for (name, m) in models_double() {
        let n = m.node_count();
        let mut scratch = ForceScratch::with_parts(n, 2);
        let one = forces(&m, &Serial(1), &mut scratch);
        // One part is add_internal_forces, bit for bit.
        let (x, v) = dented(m.rest());
        let mut plain = start(n);
        m.add_internal_forces(&x, Some(&v), &mut plain);
        assert_eq!(one, plain, "{name}");
        let two = forces(&m, &Serial(2), &mut scratch);
        let base = start(n);
        let scale = one
            .iter()
            .zip(&base)
            .map(|(f, s)| (*f - *s).length())
            .fold(0.0, f64::max);
        assert!(
            scale > 1e-3,
            "{name}: the dent loads the body ({scale:e} N)"
        );
        let err = one
            .iter()
            .zip(&two)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        let (touched_nodes, shared) = m.force_part_nodes(2).expect("a cut");
        eprintln!(
            "{name}: 2 parts vs 1: {:.2e} of {scale:.3e} N; {touched_nodes} of {n} nodes \
             touched, {shared} shared",
            err / scale
        );
        // Both halves are compact: the cut is thin.
        assert!(shared > 0 && shared < touched_nodes / 4, "{name}");
        if double_parts_run() {
            assert!(
                err < 1e-13 * scale && err > 0.0,
                "{name}: {err:e} of {scale:e} N"
            );
        } else {
            assert_eq!(one, two, "{name}");
        }
        // Nodes no element of the model touches keep their forces exactly (the region).
        let touched: std::collections::HashSet<usize> =
            m.tets().iter().flatten().map(|&i| i as usize).collect();
        // (The double-precision domain batches' padding lanes name node 0, adding zero.)
        let padding = usize::from(!touched.contains(&0));
        assert_eq!(touched.len() + padding, touched_nodes, "{name}");
        for i in (0..n).filter(|i| !touched.contains(i)) {
            assert_eq!(two[i].to_array(), base[i].to_array(), "{name}: node {i}");
        }
        // The scratch is clean after a call: the same call again gives the same forces; two
        // threads give the two parts' forces bit for bit.
        assert_eq!(forces(&m, &Serial(2), &mut scratch), two, "{name}");
        for _ in 0..3 {
            assert_eq!(forces(&m, &Scoped, &mut scratch), two, "{name}");
        }
        // A scratch of one part runs one part whatever the pool.
        let mut single_part = ForceScratch::new(n);
        assert_eq!(forces(&m, &Scoped, &mut single_part), one, "{name}");
    }
}

#[test]
fn double_precision_parts_allocate_nothing() {
    // Registers pool workers: one such test at a time in this binary (`counting_alloc`).
    let _one = counting_alloc::one_at_a_time();
    let (mesh, mat) = lv_h1();
    let hook: StartHook = Arc::new(|_| counting_alloc::count_this_thread());
    let pool = TickPool::new(1, hook).expect("a pool of one worker");
    for smoothing in [StrainSmoothing::Edge, StrainSmoothing::None] {
        let m = model_double(&mesh, mat, &|_| true, smoothing);
        let n = m.node_count();
        let (x, v) = dented(m.rest());
        let mut f = vec![DVec3::ZERO; n];
        let mut scratch = ForceScratch::with_parts(n, 2);
        let ((), allocations) = counting_alloc::counted_registered(|| {
            for _ in 0..3 {
                m.add_internal_forces_in(&Serial(2), &x, Some(&v), &mut f, &mut scratch);
                m.add_internal_forces_in(&*pool, &x, Some(&v), &mut f, &mut scratch);
                m.add_internal_forces_in(&*pool, &x, None, &mut f, &mut scratch);
            }
        });
        assert_eq!(allocations, 0, "{smoothing:?}");
        assert!(f.iter().any(|f| f.length() > 0.0));
    }
}
