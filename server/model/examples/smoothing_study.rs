//! Element-technology study on `lv_h1.msh` (17 924 linear tets): which strain smoothing brings
//! linear tetrahedra close to the converged solution, and could a prefactored sparse system
//! make backward Euler fast there. Prints only (README, "Strain smoothing").
//!
//! 1. Small-strain probe compliance (patch displacement per newton of the built-in `lv` probe
//!    patch at 0.5 mm, all at rest, base clamped) of standard FEM and of node-, face- and
//!    edge-based strain smoothing (NS-, FS-, ES-FEM-T4; G. R. Liu and T. Nguyen-Thoi,
//!    *Smoothed Finite Element Methods*, CRC Press 2010), and of alpha-FEM mixes
//!    `alpha K_FEM + (1 - alpha) K_NS` (Liu, Nguyen-Thoi & Lam 2008), each by Jacobi-PCG on a
//!    matrix-free operator written here independently of the library; against quadratic
//!    10-node tets on the same mesh (the library's static Newton solve, sparse Cholesky). The
//!    library's own ES-FEM (`StrainSmoothing::Edge`) is solved statically as a cross-check of
//!    the independent operator.
//! 2. Factorisation and solve time of the backward Euler matrix `M / h^2 + K_rest`
//!    (h = 1 ms) with faer's sparse Cholesky: the per-tick cost of a prefactored system.
//!
//! Run: `cargo run --release -p haptic-model --example smoothing_study` (about 1 minute;
//! `-- --alpha 0.3,0.5` sets the alpha values, default 0.3, 0.5 and 0.7).

#[path = "../benches/common/mod.rs"]
mod common;

use std::collections::HashMap;
use std::time::Instant;

use clap::Parser;
use common::TickTimes;
use faer::linalg::solvers::Solve;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Mat, Side};
use glam::DMat3;
use haptic_model::DVec3;
use haptic_model::contact::Probe;
use haptic_model::element::tangent::cell_tangent_blocks;
use haptic_model::element::{FemModel, StrainSmoothing, apply_constraint};
use haptic_model::mesh::TET_EDGES;
use haptic_model::scene::Scene;
use haptic_model::statics::{StaticParams, free_dofs, solve_static};

/// Smoothing domains of the study's operator.
#[derive(Clone, Copy, Debug)]
enum Domains {
    /// One per tetrahedron (standard FEM).
    Element,
    /// One per node, a quarter of each tetrahedron around it.
    Node,
    /// One per face, a quarter of each of its (one or two) tetrahedra.
    Face,
    /// One per edge, a sixth of each tetrahedron around it.
    Edge,
}

/// The small-strain stiffness `sum_d V_d B_d^T C B_d` of smoothed gradients, matrix-free:
/// element gradients are averaged into the domains (`V_e * share`), the domain stresses
/// averaged back into the elements.
struct SmoothedOperator {
    /// (domain, share of the element's volume) per element.
    domains: Vec<Vec<(usize, f64)>>,
    volume: Vec<f64>,
    grad: Vec<DMat3>,
    stress: Vec<DMat3>,
}

impl SmoothedOperator {
    fn new(fem: &FemModel, kind: Domains) -> Self {
        let mut ids: HashMap<Vec<u32>, usize> = HashMap::new();
        let mut domains = Vec::with_capacity(fem.tets().len());
        for (e, t) in fem.tets().iter().enumerate() {
            let keys: Vec<Vec<u32>> = match kind {
                Domains::Element => vec![vec![e as u32]],
                Domains::Node => t.iter().map(|&i| vec![i]).collect(),
                Domains::Face => (0..4)
                    .map(|skip| {
                        let mut f: Vec<u32> = (0..4).filter(|&k| k != skip).map(|k| t[k]).collect();
                        f.sort_unstable();
                        f
                    })
                    .collect(),
                Domains::Edge => TET_EDGES
                    .iter()
                    .map(|[a, b]| vec![t[*a].min(t[*b]), t[*a].max(t[*b])])
                    .collect(),
            };
            let share = 1.0 / keys.len() as f64;
            domains.push(
                keys.into_iter()
                    .map(|k| {
                        let next = ids.len();
                        (*ids.entry(k).or_insert(next), share)
                    })
                    .collect(),
            );
        }
        let mut volume = vec![0.0; ids.len()];
        for (e, row) in domains.iter().enumerate() {
            for &(d, share) in row {
                volume[d] += fem.volume_m3()[e] * share;
            }
        }
        Self {
            domains,
            grad: vec![DMat3::ZERO; volume.len()],
            stress: vec![DMat3::ZERO; volume.len()],
            volume,
        }
    }

    /// `out += K u`.
    fn apply(&mut self, fem: &FemModel, u: &[DVec3], out: &mut [DVec3]) {
        let (lambda, mu) = (fem.material().lambda_pa, fem.material().mu_pa);
        self.grad.iter_mut().for_each(|m| *m = DMat3::ZERO);
        for (e, t) in fem.tets().iter().enumerate() {
            let [a, b, c, d] = t.map(|i| i as usize);
            let g = DMat3::from_cols(u[b] - u[a], u[c] - u[a], u[d] - u[a]) * fem.dm_inv()[e];
            for &(k, share) in &self.domains[e] {
                self.grad[k] += g * (fem.volume_m3()[e] * share);
            }
        }
        for ((s, g), v) in self.stress.iter_mut().zip(&self.grad).zip(&self.volume) {
            let h = *g * (1.0 / v);
            let tr = h.x_axis.x + h.y_axis.y + h.z_axis.z;
            *s = DMat3::from_diagonal(DVec3::splat(lambda * tr)) + (h + h.transpose()) * mu;
        }
        for (e, t) in fem.tets().iter().enumerate() {
            let [a, b, c, d] = t.map(|i| i as usize);
            let s = self.domains[e]
                .iter()
                .fold(DMat3::ZERO, |acc, &(k, share)| acc + self.stress[k] * share);
            let h = s * fem.dm_inv()[e].transpose() * fem.volume_m3()[e];
            out[b] += h.x_axis;
            out[c] += h.y_axis;
            out[d] += h.z_axis;
            out[a] -= h.x_axis + h.y_axis + h.z_axis;
        }
    }
}

fn dot(a: &[DVec3], b: &[DVec3]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x.dot(*y)).sum()
}

/// Solves `sum_i w_i K_i u = f` on the free degrees of freedom by Jacobi-PCG to 1e-9 relative;
/// returns u and the iteration count.
fn pcg(fem: &FemModel, ops: &mut [(f64, SmoothedOperator)], f: &[DVec3]) -> (Vec<DVec3>, usize) {
    let n = fem.node_count();
    let diag_inv: Vec<DMat3> = fem
        .rest_diagonal_blocks()
        .iter()
        .map(|m| m.inverse())
        .collect();
    let constrain = |v: &mut [DVec3]| {
        for (vi, &c) in v.iter_mut().zip(fem.constraints()) {
            apply_constraint(c, vi);
        }
    };
    let mut tmp = vec![DVec3::ZERO; n];
    let mut apply = |ops: &mut [(f64, SmoothedOperator)], x: &[DVec3], y: &mut [DVec3]| {
        y.iter_mut().for_each(|v| *v = DVec3::ZERO);
        for (w, op) in ops.iter_mut() {
            tmp.iter_mut().for_each(|v| *v = DVec3::ZERO);
            op.apply(fem, x, &mut tmp);
            for (yi, ti) in y.iter_mut().zip(&tmp) {
                *yi += *ti * *w;
            }
        }
        constrain(y);
    };
    let precondition = |r: &[DVec3], z: &mut Vec<DVec3>| {
        z.clear();
        z.extend(r.iter().zip(&diag_inv).map(|(r, d)| *d * *r));
        constrain(z);
    };
    let mut x = vec![DVec3::ZERO; n];
    let mut r = f.to_vec();
    constrain(&mut r);
    let mut z = Vec::with_capacity(n);
    precondition(&r, &mut z);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    let r0 = dot(&r, &r).sqrt();
    let mut ap = vec![DVec3::ZERO; n];
    for it in 1..=50_000 {
        apply(ops, &p, &mut ap);
        let a = rz / dot(&p, &ap);
        for ((xi, ri), (pi, api)) in x.iter_mut().zip(r.iter_mut()).zip(p.iter().zip(&ap)) {
            *xi += *pi * a;
            *ri -= *api * a;
        }
        if dot(&r, &r).sqrt() < 1e-9 * r0 {
            return (x, it);
        }
        precondition(&r, &mut z);
        let rz_new = dot(&r, &z);
        let b = rz_new / rz;
        rz = rz_new;
        for (pi, zi) in p.iter_mut().zip(&z) {
            *pi = *zi + *pi * b;
        }
    }
    panic!("PCG did not converge");
}

/// The probe patch of `scene` at 0.5 mm on the rest shape: (node, weight) and the inward load
/// direction.
fn probe_patch(scene: &Scene, fem: &FemModel) -> (Vec<(u32, f64)>, DVec3) {
    let mut probe = Probe::new(scene.probe, scene.touchable.clone(), fem.rest());
    let st = probe.update(fem.rest(), common::device_at(0.5e-3), DVec3::ZERO);
    assert!(st.in_contact);
    let (nodes, w) = probe.patch();
    (
        nodes.iter().copied().zip(w.iter().copied()).collect(),
        -st.normal,
    )
}

/// A patch load of `total_n` along `dir`.
fn patch_load(n: usize, patch: &[(u32, f64)], dir: DVec3, total_n: f64) -> Vec<DVec3> {
    let mut f = vec![DVec3::ZERO; n];
    for &(i, w) in patch {
        f[i as usize] = dir * (w * total_n);
    }
    f
}

/// Mean patch displacement along `dir` per newton, m/N.
fn compliance(patch: &[(u32, f64)], dir: DVec3, u: &[DVec3], total_n: f64) -> f64 {
    patch
        .iter()
        .map(|&(i, w)| u[i as usize].dot(dir) * w)
        .sum::<f64>()
        / total_n
}

fn static_compliance(scene: &Scene, smoothing: StrainSmoothing) -> (f64, usize, f64) {
    let mut fem = FemModel::with_smoothing(&scene.mesh, scene.material, smoothing).expect("FEM");
    fem.clamp_nodes(&scene.clamped_nodes);
    let (patch, dir) = probe_patch(scene, &fem);
    // A load small enough for the geometric nonlinearity to stay below 1e-6.
    let load = 1e-4;
    let f = patch_load(fem.node_count(), &patch, dir, load);
    let mut x = fem.rest().to_vec();
    let t = Instant::now();
    let params = StaticParams {
        rel_tol: 1e-10,
        ..StaticParams::default()
    };
    solve_static(&fem, &f, &mut x, &params).expect("static solve");
    let u: Vec<DVec3> = x.iter().zip(fem.rest()).map(|(a, b)| *a - *b).collect();
    (
        compliance(&patch, dir, &u, load),
        fem.node_count(),
        t.elapsed().as_secs_f64(),
    )
}

/// Element-technology study on lv_h1.msh: strain smoothing against quadratic elements, and
/// the cost of a prefactored backward Euler matrix. Prints only.
#[derive(Debug, Parser)]
#[command(name = "smoothing_study")]
struct Args {
    /// Weights alpha of the alpha-FEM mixes alpha K_FEM + (1 - alpha) K_NS, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [0.3, 0.5, 0.7])]
    alpha: Vec<f64>,
}

fn main() {
    let args = Args::parse();
    let Some(h1) = common::lv_h1_scene() else {
        eprintln!("lv_h1.msh not found (../shared/data/lv): nothing to study");
        return;
    };
    let scene = common::lv_scene_on(h1.mesh);
    let quad = common::lv_scene_on(scene.mesh.to_quadratic());
    let fem = compliance_study(&args.alpha, &scene, &quad);
    prefactored_study(&fem);
}

/// Part 1: the small-strain probe compliance with each smoothing domain, the alpha-FEM mixes
/// `alphas` and the library's smoothings against quadratic elements; the linear model.
fn compliance_study(alphas: &[f64], scene: &Scene, quad: &Scene) -> FemModel {
    println!("1. small-strain probe compliance on lv_h1.msh (17 924 tets), patch load at 0.5 mm");
    let (c_ref, n_ref, t_ref) = static_compliance(quad, StrainSmoothing::None);
    println!(
        "quadratic T10 on the same mesh ({n_ref} nodes, static, {t_ref:.1} s): {c_ref:.5e} m/N (reference)"
    );
    let mut fem = FemModel::new(&scene.mesh, scene.material).expect("FEM");
    fem.clamp_nodes(&scene.clamped_nodes);
    let (patch, dir) = probe_patch(scene, &fem);
    let f = patch_load(fem.node_count(), &patch, dir, 1.0);
    let report = |name: &str, c: f64, extra: String| {
        println!(
            "{name:<28} {c:.5e} m/N  {:+6.1} % vs T10  {extra}",
            (c / c_ref - 1.0) * 100.0
        );
    };
    for kind in [
        Domains::Element,
        Domains::Node,
        Domains::Face,
        Domains::Edge,
    ] {
        let t = Instant::now();
        let mut ops = vec![(1.0, SmoothedOperator::new(&fem, kind))];
        let domains = ops[0].1.volume.len();
        let (u, it) = pcg(&fem, &mut ops, &f);
        report(
            &format!("{kind:?} (PCG)"),
            compliance(&patch, dir, &u, 1.0),
            format!(
                "{domains} domains, {it} PCG it, {:.1} s",
                t.elapsed().as_secs_f64()
            ),
        );
    }
    for &a in alphas {
        let mut ops = vec![
            (a, SmoothedOperator::new(&fem, Domains::Element)),
            (1.0 - a, SmoothedOperator::new(&fem, Domains::Node)),
        ];
        let (u, it) = pcg(&fem, &mut ops, &f);
        report(
            &format!("alpha-FEM {a} (PCG)"),
            compliance(&patch, dir, &u, 1.0),
            format!("{it} PCG it"),
        );
    }
    for smoothing in [StrainSmoothing::None, StrainSmoothing::Edge] {
        let (c, _, t) = static_compliance(scene, smoothing);
        report(
            &format!("library, smoothing {}", smoothing.name()),
            c,
            format!("static Newton, {t:.1} s"),
        );
    }
    fem
}

/// Part 2: the prefactored backward Euler matrix M/h^2 + K_rest of `fem`: factorisation and
/// solve times.
fn prefactored_study(fem: &FemModel) {
    println!("2. prefactored backward Euler matrix M/h^2 + K_rest on lv_h1.msh, h = 1 ms");
    let (dof, free) = free_dofs(fem);
    let h = 1e-3;
    let mut triplets = Vec::new();
    let mut blocks = Vec::new();
    for c in 0..fem.cell_count() {
        cell_tangent_blocks(fem, c, fem.rest(), &mut blocks);
        let t = fem.cell_nodes(c);
        for (a, &na) in t.iter().enumerate() {
            for (b, &nb) in t.iter().enumerate() {
                for ca in 0..3 {
                    for cb in 0..3 {
                        let (ra, rb) = (dof[3 * na as usize + ca], dof[3 * nb as usize + cb]);
                        if ra != usize::MAX && rb != usize::MAX && rb <= ra {
                            triplets.push(Triplet::new(
                                ra,
                                rb,
                                blocks[a * t.len() + b].col(cb)[ca],
                            ));
                        }
                    }
                }
            }
        }
    }
    for (i, m) in fem.lumped_mass_kg().iter().enumerate() {
        for c in 0..3 {
            if dof[3 * i + c] != usize::MAX {
                triplets.push(Triplet::new(dof[3 * i + c], dof[3 * i + c], m / (h * h)));
            }
        }
    }
    let k =
        SparseColMat::<usize, f64>::try_new_from_triplets(free, free, &triplets).expect("assembly");
    let t = Instant::now();
    let llt = k.sp_cholesky(Side::Lower).expect("Cholesky");
    let factor_s = t.elapsed().as_secs_f64();
    let mut rhs = Mat::<f64>::from_fn(free, 1, |i, _| (i as f64).sin());
    let mut times = TickTimes::new();
    for _ in 0..200 {
        let t = Instant::now();
        llt.solve_in_place(rhs.as_mut());
        times.record(t.elapsed());
    }
    let p50 = times.percentiles().p50_us;
    println!(
        "{free} free dofs, {} stored entries of the lower triangle: factorisation {:.2} s, one solve (forward + back substitution) p50 {p50:.0} us over 200",
        k.compute_nnz(),
        factor_s
    );
}
