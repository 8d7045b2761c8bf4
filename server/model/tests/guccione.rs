//! Guccione's transversely isotropic law (issue 14, section 4): the stress and its differential
//! against finite differences of the energy, per material point and assembled (with the fibre
//! field and the element-mean dilatation), and its isotropic limit.

mod common;
use common::Rng;

use glam::{DMat3, DQuat};
use haptic_model::DVec3;
use haptic_model::element::tangent::cell_tangent_blocks;
use haptic_model::element::{FemModel, FibreField, FibreRule};
use haptic_model::material::{
    self, GuccioneParams, MaterialModel, MaterialParams, energy_density_oriented,
    first_piola_differential_oriented, first_piola_oriented,
};
use haptic_model::mesh::generate::{box_mesh, lv_shell_quadratic};

fn random_f(rng: &mut Rng, amplitude: f64) -> DMat3 {
    DMat3::IDENTITY
        + DMat3::from_cols_array(&std::array::from_fn(|_| amplitude * (2.0 * rng.next() - 1.0)))
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
    let mut rng = Rng::new(11);
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
        assert!(worst < 1e-6 * scale.max(1.0), "P vs dW/dF: {worst:e} of {scale:e}");
        let df = random_f(&mut rng, 1.0) - DMat3::IDENTITY;
        let dp = first_piola_differential_oriented(&mat, &f, &r, &df);
        let fd = (first_piola_oriented(&mat, &(f + df * h), &r)
            - first_piola_oriented(&mat, &(f - df * h), &r))
            * (0.5 / h);
        let err = (dp - fd).to_cols_array().iter().fold(0.0f64, |a, b| a.max(b.abs()));
        let s = dp.to_cols_array().iter().fold(0.0f64, |a, b| a.max(b.abs()));
        assert!(err < 1e-6 * s, "dP: {err:e} of {s:e}");
    }
}
