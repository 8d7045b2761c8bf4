//! Guccione's transversely isotropic law (issue 14, section 4): the stress and its differential
//! against finite differences of the energy, per material point and assembled (with the fibre
//! field and the element-mean dilatation), and its isotropic limit.

use crate::common;
use common::Rng;

use glam::{DMat3, DQuat};
use haptic_model::material::{
    GuccioneParams, MaterialParams, energy_density_oriented, first_piola_differential_oriented,
    first_piola_oriented,
};

fn random_f(rng: &mut Rng, amplitude: f64) -> DMat3 {
    DMat3::IDENTITY + DMat3::from_cols_array(&std::array::from_fn(|_| amplitude * rng.next()))
}

fn random_frame(rng: &mut Rng) -> DMat3 {
    let q = DQuat::from_xyzw(
        rng.next() - 0.5,
        rng.next() - 0.5,
        rng.next() - 0.5,
        rng.next() - 0.5,
    )
    .normalize();
    DMat3::from_quat(q)
}

fn anisotropic(mean_dilatation: bool) -> MaterialParams {
    // Land et al. 2015 problem 3 coefficients, a moderate penalty.
    let g = GuccioneParams {
        c_pa: 2e3,
        b_f: 8.0,
        b_t: 2.0,
        b_fs: 4.0,
        bulk_modulus_pa: 5e4,
        mean_dilatation,
    };
    MaterialParams::with_guccione(g, 1060.0)
}

#[test]
fn stress_is_the_energy_gradient_and_its_differential_matches_differences() {
    let mut rng = Rng(11);
    let mat = anisotropic(false);
    for _ in 0..20 {
        let f = random_f(&mut rng, 0.3);
        let r = random_frame(&mut rng);
        let p = first_piola_oriented(&mat, &f, &r);
        let h = 1e-6;
        let mut worst: f64 = 0.0;
        for i in 0..3 {
            for j in 0..3 {
                let mut fp = f;
                fp.col_mut(j)[i] += h;
                let mut fm = f;
                fm.col_mut(j)[i] -= h;
                let d = (energy_density_oriented(&mat, &fp, &r)
                    - energy_density_oriented(&mat, &fm, &r))
                    / (2.0 * h);
                worst = worst.max((d - p.col(j)[i]).abs());
            }
        }
        let scale = p.to_cols_array().iter().fold(0.0f64, |a, b| a.max(b.abs()));
        assert!(
            worst < 1e-6 * scale.max(1.0),
            "P vs dW/dF: {worst:e} of {scale:e}"
        );
        let df = random_f(&mut rng, 1.0) - DMat3::IDENTITY;
        let dp = first_piola_differential_oriented(&mat, &f, &r, &df);
        let fd = (first_piola_oriented(&mat, &(f + df * h), &r)
            - first_piola_oriented(&mat, &(f - df * h), &r))
            * (0.5 / h);
        let err = (dp - fd)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |a, b| a.max(b.abs()));
        let s = dp
            .to_cols_array()
            .iter()
            .fold(0.0f64, |a, b| a.max(b.abs()));
        assert!(err < 1e-6 * s, "dP: {err:e} of {s:e}");
    }
}

#[test]
fn the_isotropic_limit_does_not_depend_on_the_fibre_frame() {
    // b_f = b_t = b_fs: Q = b E:E, so the stress may not depend on the fibre directions; with
    // distinct coefficients it must.
    let iso = MaterialParams::with_guccione(GuccioneParams::isotropic(10e3, 1.0, 5e5), 1060.0);
    let aniso = anisotropic(false);
    let mut rng = Rng(5);
    let mut aniso_spread: f64 = 0.0;
    for _ in 0..20 {
        let f = random_f(&mut rng, 0.2);
        let (r1, r2) = (random_frame(&mut rng), random_frame(&mut rng));
        let (p1, p2) = (
            first_piola_oriented(&iso, &f, &r1),
            first_piola_oriented(&iso, &f, &r2),
        );
        let scale = p1
            .to_cols_array()
            .iter()
            .fold(0.0f64, |a, b| a.max(b.abs()));
        let diff = (p1 - p2)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |a, b| a.max(b.abs()));
        assert!(
            diff < 1e-9 * scale.max(1.0),
            "isotropic: {diff:e} of {scale:e}"
        );
        let (a1, a2) = (
            first_piola_oriented(&aniso, &f, &r1),
            first_piola_oriented(&aniso, &f, &r2),
        );
        let s = a1
            .to_cols_array()
            .iter()
            .fold(0.0f64, |a, b| a.max(b.abs()));
        aniso_spread = aniso_spread.max(
            (a1 - a2)
                .to_cols_array()
                .iter()
                .fold(0.0f64, |a, b| a.max(b.abs()))
                / s,
        );
    }
    assert!(
        aniso_spread > 1e-2,
        "the anisotropic law ignores the fibres: {aniso_spread:e}"
    );
    // At rest: no stress.
    let p0 = first_piola_oriented(&iso, &DMat3::IDENTITY, &DMat3::IDENTITY);
    assert!(p0.to_cols_array().iter().all(|v| v.abs() < 1e-9), "{p0:?}");
}
