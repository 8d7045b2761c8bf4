//! Corotational linear elasticity: `Psi = mu |F - R|^2 + lambda/2 tr(R^T F - I)^2` with R the
//! rotation of the polar decomposition `F = R S` (for inverted elements the proper-rotation
//! variant of Irving, Teran & Fedkiw 2004), with the decompositions it needs: a Jacobi symmetric
//! eigen-solver, the rotation-variant SVD and the differential of the rotation.
//!
//! Neighbours: dispatched from [`super`]; [`crate::integrate`] uses [`polar_decomposition`] for
//! the warped stiffness of backward Euler.

use glam::{DMat3, DVec3};

use super::{ddot, trace};

/// Symmetric eigen-decomposition by cyclic Jacobi rotations: returns `(V, d)` with
/// `A = V diag(d) V^T`, V orthonormal, `d` sorted in decreasing order. `a` must be symmetric.
#[allow(
    clippy::needless_range_loop,
    reason = "Jacobi rotations index rows and columns p, q together"
)]
pub fn symmetric_eigen(a: &DMat3) -> (DMat3, DVec3) {
    let mut m = a.to_cols_array_2d(); // m[col][row], symmetric so also m[row][col]
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]; // v[col][row]
    let scale = m.iter().flatten().fold(0.0_f64, |s, x| s.max(x.abs()));
    if scale == 0.0 || !scale.is_finite() {
        return (DMat3::IDENTITY, DVec3::new(m[0][0], m[1][1], m[2][2]));
    }
    for _sweep in 0..32 {
        let off = m[0][1] * m[0][1] + m[0][2] * m[0][2] + m[1][2] * m[1][2];
        if off <= (1e-18 * scale) * (1e-18 * scale) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            let apq = m[p][q];
            if apq == 0.0 {
                continue;
            }
            // Rotation annihilating (p, q) (Golub & Van Loan, Algorithm 8.4.2).
            let tau = (m[q][q] - m[p][p]) / (2.0 * apq);
            let t = tau.signum() / (tau.abs() + (1.0 + tau * tau).sqrt());
            let t = if tau == 0.0 { 1.0 } else { t };
            let c = 1.0 / (1.0 + t * t).sqrt();
            let s = t * c;
            // m <- J^T m J with J = rotation in the (p, q) plane.
            for k in 0..3 {
                let (mkp, mkq) = (m[k][p], m[k][q]);
                m[k][p] = c * mkp - s * mkq;
                m[k][q] = s * mkp + c * mkq;
            }
            for k in 0..3 {
                let (mpk, mqk) = (m[p][k], m[q][k]);
                m[p][k] = c * mpk - s * mqk;
                m[q][k] = s * mpk + c * mqk;
            }
            for row in 0..3 {
                let (vp, vq) = (v[p][row], v[q][row]);
                v[p][row] = c * vp - s * vq;
                v[q][row] = s * vp + c * vq;
            }
        }
    }
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| m[j][j].total_cmp(&m[i][i]));
    let cols = order.map(|i| DVec3::from_array(v[i]));
    (
        DMat3::from_cols(cols[0], cols[1], cols[2]),
        DVec3::new(
            m[order[0]][order[0]],
            m[order[1]][order[1]],
            m[order[2]][order[2]],
        ),
    )
}

/// A unit vector orthogonal to the unit vector `u`.
fn any_orthogonal(u: DVec3) -> DVec3 {
    let a = if u.x.abs() < 0.6 { DVec3::X } else { DVec3::Y };
    (a - u * u.dot(a)).normalize()
}

/// Rotation-variant singular value decomposition `F = U diag(sigma) V^T` with U and V proper
/// rotations (det = +1), `sigma_1 >= sigma_2 >= |sigma_3|`, and `sigma_3 < 0` exactly when
/// `det F < 0` (Irving, Teran, Fedkiw 2004, "Invertible finite elements for robust simulation of
/// large deformation", section 5: the reflection is moved onto the smallest singular value).
///
/// V from a Jacobi eigen-decomposition of `F^T F`, then U from a Gram-Schmidt QR of `F V`
/// with `u_3 = u_1 x u_2` (as in McAdams et al. 2011), which stays defined for rank-deficient F.
pub fn rotation_variant_svd(f: &DMat3) -> (DMat3, DVec3, DMat3) {
    let (mut v, _) = symmetric_eigen(&(f.transpose() * *f));
    if v.determinant() < 0.0 {
        v.z_axis = -v.z_axis;
    }
    let b = *f * v;
    let s1 = b.x_axis.length();
    let u1 = if s1 > 0.0 {
        b.x_axis / s1
    } else {
        // F = 0: any rotation.
        v.x_axis
    };
    let b2 = b.y_axis - u1 * u1.dot(b.y_axis);
    let n2 = b2.length();
    let u2 = if n2 > 1e-300 && n2 > 1e-15 * s1 {
        b2 / n2
    } else {
        any_orthogonal(u1)
    };
    let u3 = u1.cross(u2);
    let sigma = DVec3::new(s1, u2.dot(b.y_axis), u3.dot(b.z_axis));
    (DMat3::from_cols(u1, u2, u3), sigma, v)
}

/// Polar decomposition `F = R S` with R a proper rotation and S symmetric, returned as
/// `(R, S)`. For `det F < 0` (an inverted element) S is indefinite: R is the rotation of
/// [`rotation_variant_svd`] (`R = U V^T`, `S = V diag(sigma) V^T` with `sigma_3 < 0`), not the
/// reflection of the classical polar decomposition, so the corotational force pushes the element
/// back through the inversion (Irving et al. 2004).
pub fn polar_decomposition(f: &DMat3) -> (DMat3, DMat3) {
    let (u, sigma, v) = rotation_variant_svd(f);
    let r = u * v.transpose();
    let s = v * DMat3::from_diagonal(sigma) * v.transpose();
    (r, (s + s.transpose()) * 0.5)
}

/// Differential of the rotation of [`polar_decomposition`]: with `F = R S`, `R^T dR = [w]x`
/// and `((tr S) I - S) w = axial(R^T dF - dF^T R)` (from the skew part of
/// `R^T dF = [w]x S + dS`, using `[w]x S + S [w]x = [((tr S) I - S) w]x`). Solved in the
/// eigenbasis V of S, where the matrix is `diag(sigma_2 + sigma_3, sigma_1 + sigma_3,
/// sigma_1 + sigma_2)`; a pair sum below `1e-12 * sigma_1` in magnitude (an element crushed to
/// a line, or half way through an inversion) is clamped there, which bounds dR.
fn rotation_differential(u: &DMat3, sigma: DVec3, v: &DMat3, df: &DMat3) -> DMat3 {
    let r = *u * v.transpose();
    let m = r.transpose() * *df;
    let k = m - m.transpose();
    let a = DVec3::new(k.y_axis.z, k.z_axis.x, k.x_axis.y);
    let floor = 1e-12 * sigma.x.abs().max(1e-300);
    let clamp = |d: f64| {
        if d.abs() >= floor {
            d
        } else if d >= 0.0 {
            floor
        } else {
            -floor
        }
    };
    let den = DVec3::new(
        clamp(sigma.y + sigma.z),
        clamp(sigma.x + sigma.z),
        clamp(sigma.x + sigma.y),
    );
    let w = *v * ((v.transpose() * a) / den);
    r * skew(w)
}

/// `[w]x`, the cross-product matrix: `[w]x y = w x y`.
#[inline]
fn skew(w: DVec3) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(0.0, w.z, -w.y),
        DVec3::new(-w.z, 0.0, w.x),
        DVec3::new(w.y, -w.x, 0.0),
    )
}

/// `P = 2 mu (F - R) + lambda tr(R^T F - I) R`, Pa.
#[inline]
pub(super) fn first_piola(f: &DMat3, lambda_pa: f64, mu_pa: f64) -> DMat3 {
    let (r, s) = polar_decomposition(f);
    (*f - r) * (2.0 * mu_pa) + r * (lambda_pa * (trace(&s) - 3.0))
}

/// `dP = 2 mu (dF - dR) + lambda ((R : dF) R + tr(S - I) dR)`, dR from the polar-decomposition
/// differential (`d tr(S) = R : dF`), Pa.
#[inline]
pub(super) fn first_piola_differential(f: &DMat3, df: &DMat3, lambda_pa: f64, mu_pa: f64) -> DMat3 {
    let (u, sigma, v) = rotation_variant_svd(f);
    let r = u * v.transpose();
    let dr = rotation_differential(&u, sigma, &v, df);
    let tr_s = sigma.x + sigma.y + sigma.z;
    (*df - dr) * (2.0 * mu_pa) + (r * ddot(&r, df) + dr * (tr_s - 3.0)) * lambda_pa
}

/// `Psi(F)`, J/m^3 (zero at `F = I`).
#[inline]
pub(super) fn energy_density(f: &DMat3, lambda_pa: f64, mu_pa: f64) -> f64 {
    let (r, s) = polar_decomposition(f);
    let d = *f - r;
    let t = trace(&s) - 3.0;
    mu_pa * ddot(&d, &d) + 0.5 * lambda_pa * t * t
}
