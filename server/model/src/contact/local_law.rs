//! The probe's local contact law: the force `F(d)` with which the touched tissue resists a rigid
//! sphere of the probe's radius pressed `d` into it, the sub-grid part of the patch contact
//! models ([`super::ContactModel::PatchLocal`], [`super::ContactModel::PatchHertz`]) that
//! meshes coarser than the contact cannot resolve.
//!
//! Two laws:
//! - **Hertz** (Johnson, *Contact Mechanics*, 1985, eq. 4.23): `F = 4/3 E* a^(1/2) d^(3/2)`,
//!   `E* = E / (1 - nu^2)`: linear elasticity, small depth.
//! - **The material's own half-space law**: the exact finite-strain solve of a rigid sphere on a
//!   half-space of the scene's material ([`super::half_space::indent_half_space`]), tabulated
//!   once for each material model and Poisson ratio as `F / (E a^2)` against `d / a`
//!   (`half_space_law.csv`, written by the example `half_space_law`), scaled by the scene's
//!   Young's modulus and the probe's radius, and interpolated linearly in the Poisson ratio. It
//!   equals Hertz's at small depth and departs from it as the tissue does: St.
//!   Venant-Kirchhoff at nu = 0.45 is 4 % softer at `d / a = 0.01` and 27 % at 0.25 (its volume
//!   term softens in compression), stable neo-Hookean 2 % at 0.1 and 14 % at 1 (the sphere is
//!   not Hertz's paraboloid).
//!
//! Between the tabulated depths the law is a monotone cubic in `(ln d, ln F)`; below the first
//! depth it is Hertz's power `d^(3/2)` through the first point, beyond the last the power of the
//! last interval (at least 1); its slope is continuous everywhere (the cubic's end slopes are
//! those powers).
//!
//! Owns: the laws and the series solve with the virtual coupling. Uses: [`crate::material`].
//! Not for the servo tick: building a law parses the table (allocates); evaluating it does not.

use crate::ModelError;
use crate::material::{MaterialModel, MaterialParams};

/// The compiled-in half-space table (see the module documentation): rows
/// `model,poisson_ratio,depth_ratio,force_ratio,contact_radius_ratio`, grouped by model and
/// Poisson ratio with increasing depths.
const HALF_SPACE_TABLE: &str = include_str!("half_space_law.csv");

/// A sphere's local force-indentation law (module documentation).
#[derive(Debug, Clone, PartialEq)]
pub enum LocalLaw {
    /// `F = K d^(3/2)` with `K` in N/m^(3/2) ([`super::probe::hertz_stiffness`]).
    Hertz {
        /// `K = 4/3 E* a^(1/2)`, N/m^(3/2).
        stiffness: f64,
    },
    /// A tabulated law ([`LocalLaw::from_points`]).
    Table(LawTable),
}

/// Knots of a tabulated law: `x = ln d`, `y = ln F` (d in m, F in N), the slopes `dy/dx` at
/// the knots, and the power beyond the last knot.
#[derive(Debug, Clone, PartialEq)]
pub struct LawTable {
    x: Vec<f64>,
    y: Vec<f64>,
    slope: Vec<f64>,
    tail_power: f64,
}

/// Power of the law below the first knot (Hertz's).
const HEAD_POWER: f64 = 1.5;

impl LocalLaw {
    /// Hertz's law of a sphere of radius `radius_m` on a half-space of effective modulus
    /// `modulus_pa` (`E / (1 - nu^2)`); zero force when the modulus is unknown (zero).
    pub fn hertz(modulus_pa: f64, radius_m: f64) -> Self {
        Self::Hertz {
            stiffness: super::probe::hertz_stiffness(modulus_pa, radius_m),
        }
    }

    /// A law through the points `(depth_m[i], force_n[i])` (m, N; depths and forces positive
    /// and increasing, at least two).
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] when the points are fewer than two, not positive or not
    /// increasing.
    pub fn from_points(depth_m: &[f64], force_n: &[f64]) -> Result<Self, ModelError> {
        let ok = depth_m.len() >= 2
            && depth_m.len() == force_n.len()
            && depth_m
                .iter()
                .chain(force_n)
                .all(|v| *v > 0.0 && v.is_finite())
            && depth_m.windows(2).all(|w| w[1] > w[0])
            && force_n.windows(2).all(|w| w[1] > w[0]);
        if !ok {
            return Err(ModelError::InvalidInput(
                "local contact law: needs two or more positive, increasing depths and forces"
                    .into(),
            ));
        }
        let x: Vec<f64> = depth_m.iter().map(|d| d.ln()).collect();
        let y: Vec<f64> = force_n.iter().map(|f| f.ln()).collect();
        let secant: Vec<f64> = (0..x.len() - 1)
            .map(|i| (y[i + 1] - y[i]) / (x[i + 1] - x[i]))
            .collect();
        // Fritsch-Butland: the harmonic mean of the neighbouring secants keeps the cubic
        // monotone; the ends take the powers of the head (Hertz's) and of the tail, so that
        // the law's slope is continuous at the first and last knots.
        let tail_power = secant[secant.len() - 1].max(1.0);
        let mut slope = vec![0.0; x.len()];
        // (At most three times the secant, which keeps the end intervals monotone.)
        slope[0] = HEAD_POWER.min(3.0 * secant[0]);
        slope[x.len() - 1] = tail_power.min(3.0 * secant[secant.len() - 1]);
        for i in 1..x.len() - 1 {
            let (a, b) = (secant[i - 1], secant[i]);
            slope[i] = if a * b > 0.0 {
                let (ha, hb) = (x[i] - x[i - 1], x[i + 1] - x[i]);
                3.0 * (ha + hb) / ((2.0 * hb + ha) / a + (hb + 2.0 * ha) / b)
            } else {
                0.0
            };
        }
        Ok(Self::Table(LawTable {
            x,
            y,
            slope,
            tail_power,
        }))
    }

    /// The law of `mat` for a sphere of radius `radius_m`: its material model's half-space
    /// table (`half_space_law.csv`, module documentation) at its Poisson ratio (interpolated
    /// linearly between the tabulated ratios; the nearest one outside them, with Hertz's
    /// `1 / (1 - nu^2)`), scaled by its Young's modulus; Hertz's law for a model without a
    /// table (corotational, Guccione, anisotropic).
    pub fn for_material(mat: &MaterialParams, radius_m: f64) -> Self {
        let (e, nu) = (mat.youngs_modulus_pa(), mat.poisson_ratio());
        let hertz = || Self::hertz(e / (1.0 - nu * nu), radius_m);
        if mat.is_anisotropic() || mat.model == MaterialModel::Guccione {
            return hertz();
        }
        match half_space_points(mat.model, nu) {
            Some((d, f)) => {
                let scale_f = e * radius_m * radius_m;
                let depth: Vec<f64> = d.iter().map(|r| r * radius_m).collect();
                let force: Vec<f64> = f.iter().map(|r| r * scale_f).collect();
                Self::from_points(&depth, &force).unwrap_or_else(|_| hertz())
            }
            None => hertz(),
        }
    }

    /// The force `F(d)` (N) and its slope `dF/dd` (N/m) at the indentation `delta_m` (m);
    /// zero at and below zero depth. Allocation-free.
    pub fn force(&self, delta_m: f64) -> (f64, f64) {
        if !(delta_m > 0.0) {
            return (0.0, 0.0);
        }
        match self {
            Self::Hertz { stiffness } => {
                let s = delta_m.sqrt();
                (stiffness * delta_m * s, 1.5 * stiffness * s)
            }
            Self::Table(t) => {
                let (y, dy) = t.eval(delta_m.ln());
                let f = y.exp();
                (f, f * dy / delta_m)
            }
        }
    }

    /// The indentation `d` (m) of this law in series with a linear spring `k_n_per_m` (N/m),
    /// the two stretched together by `depth_m` (m): the root of `F(d) = k (depth - d)` in
    /// `[0, depth]` (unique: the left side increases, the right decreases), by Newton
    /// safeguarded by bisection. `depth` when the law gives no force. Allocation-free.
    pub fn series_indentation(&self, depth_m: f64, k_n_per_m: f64) -> f64 {
        if let Self::Hertz { stiffness } = self {
            return super::probe::hertz_series_indentation(depth_m, k_n_per_m, *stiffness);
        }
        if !(depth_m > 0.0) {
            return 0.0;
        }
        let (mut lo, mut hi) = (0.0, depth_m);
        // Start where the spring alone would hold the law's force at the full depth.
        let mut d = 0.5 * depth_m;
        for _ in 0..100 {
            let (f, df) = self.force(d);
            let g = f - k_n_per_m * (depth_m - d);
            if g > 0.0 {
                hi = d;
            } else {
                lo = d;
            }
            let step = g / (df + k_n_per_m);
            let mut next = d - step;
            if !(next > lo && next < hi) {
                next = 0.5 * (lo + hi);
            }
            if (next - d).abs() <= 1e-13 * depth_m || hi - lo <= 1e-13 * depth_m {
                return next;
            }
            d = next;
        }
        d
    }
}

impl LawTable {
    /// `y(x)` and `dy/dx` (module documentation). Allocation-free.
    fn eval(&self, x: f64) -> (f64, f64) {
        let n = self.x.len();
        if x <= self.x[0] {
            return (self.y[0] + HEAD_POWER * (x - self.x[0]), HEAD_POWER);
        }
        if x >= self.x[n - 1] {
            return (
                self.y[n - 1] + self.tail_power * (x - self.x[n - 1]),
                self.tail_power,
            );
        }
        // The interval [x_i, x_(i+1)] holding x.
        let i = self.x.partition_point(|&k| k <= x) - 1;
        let h = self.x[i + 1] - self.x[i];
        let t = (x - self.x[i]) / h;
        let (y0, y1) = (self.y[i], self.y[i + 1]);
        let (m0, m1) = (self.slope[i] * h, self.slope[i + 1] * h);
        let (t2, t3) = (t * t, t * t * t);
        let y = (2.0 * t3 - 3.0 * t2 + 1.0) * y0
            + (t3 - 2.0 * t2 + t) * m0
            + (-2.0 * t3 + 3.0 * t2) * y1
            + (t3 - t2) * m1;
        let dy = ((6.0 * t2 - 6.0 * t) * y0
            + (3.0 * t2 - 4.0 * t + 1.0) * m0
            + (-6.0 * t2 + 6.0 * t) * y1
            + (3.0 * t2 - 2.0 * t) * m1)
            / h;
        (y, dy)
    }
}

/// The rows of [`HALF_SPACE_TABLE`] for `model`: per tabulated Poisson ratio, the depth and
/// force ratios.
fn table_rows(model: MaterialModel) -> Vec<(f64, Vec<f64>, Vec<f64>)> {
    let mut out: Vec<(f64, Vec<f64>, Vec<f64>)> = Vec::new();
    for line in HALF_SPACE_TABLE.lines() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') || line.starts_with("model") {
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        if f.len() < 4 || MaterialModel::from_scene_name(f[0]) != Some(model) {
            continue;
        }
        let num = |s: &str| s.trim().parse::<f64>().ok();
        let (Some(nu), Some(d), Some(force)) = (num(f[1]), num(f[2]), num(f[3])) else {
            continue;
        };
        match out.last_mut() {
            Some(last) if last.0 == nu => {
                last.1.push(d);
                last.2.push(force);
            }
            _ => out.push((nu, vec![d], vec![force])),
        }
    }
    out
}

/// The dimensionless law of `model` at Poisson ratio `nu`: depth ratios `d / a` and force
/// ratios `F / (E a^2)`, interpolated linearly in `nu` between the two nearest tabulated ratios
/// (the force's logarithm at the depth ratios both have); outside them the nearest ratio's,
/// scaled by Hertz's `(1 - nu_t^2) / (1 - nu^2)`. `None` without a table for `model`.
fn half_space_points(model: MaterialModel, nu: f64) -> Option<(Vec<f64>, Vec<f64>)> {
    let rows = table_rows(model);
    let first = rows.first()?;
    let last = rows.last()?;
    // Outside the tabulated ratios: the nearest one's law with Hertz's dependence on the
    // ratio, `F ~ E / (1 - nu^2)`.
    let nearest = |row: &(f64, Vec<f64>, Vec<f64>)| {
        let scale = (1.0 - row.0 * row.0) / (1.0 - nu * nu);
        (row.1.clone(), row.2.iter().map(|f| f * scale).collect())
    };
    if nu <= first.0 {
        return Some(nearest(first));
    }
    if nu >= last.0 {
        return Some(nearest(last));
    }
    let j = rows.iter().position(|r| r.0 >= nu)?;
    let (lo, hi) = (&rows[j - 1], &rows[j]);
    let w = (nu - lo.0) / (hi.0 - lo.0);
    let (mut d, mut f) = (Vec::new(), Vec::new());
    for (k, &dr) in lo.1.iter().enumerate() {
        if let Some(m) = hi.1.iter().position(|&x| (x - dr).abs() < 1e-9) {
            d.push(dr);
            f.push(((1.0 - w) * lo.2[k].ln() + w * hi.2[m].ln()).exp());
        }
    }
    (d.len() >= 2).then_some((d, f))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The series solve balances the law against the spring, for Hertz and for a table.
    #[test]
    fn series_indentation_balances_the_spring() {
        let hertz = LocalLaw::hertz(18e3, 2e-3);
        let table =
            LocalLaw::from_points(&[1e-5, 1e-4, 5e-4, 1e-3], &[3.4e-5, 1.1e-3, 1.1e-2, 2.8e-2])
                .unwrap();
        for law in [hertz, table] {
            for depth in [1e-6, 1e-4, 1e-3, 4e-3, 2e-2] {
                let d = law.series_indentation(depth, 300.0);
                let (f, _) = law.force(d);
                assert!(d > 0.0 && d < depth, "{law:?} {depth}: {d}");
                assert!(
                    (f - 300.0 * (depth - d)).abs() <= 1e-9 * f.max(1e-12),
                    "{law:?} {depth}: F {f} against {}",
                    300.0 * (depth - d)
                );
            }
        }
    }

    /// The compiled-in laws start as Hertz's, `F = 4/3 E/(1 - nu^2) a^(1/2) d^(3/2)` (Johnson
    /// 1985, eq. 4.23): at and below the first tabulated depth (`d / a = 0.005`) within the
    /// finite-strain departure (St. Venant-Kirchhoff softens by 2.9 % there, stable
    /// neo-Hookean by 0.3 %), with Hertz's power; `F / (E a^2)` does not depend on the modulus
    /// or the radius; models without a table get Hertz's law itself.
    #[test]
    fn material_laws_start_as_hertz_and_scale_with_modulus_and_radius() {
        let nu = 0.45;
        for (model, tol) in [
            (MaterialModel::StVenantKirchhoff, 0.035),
            (MaterialModel::StableNeoHookean, 0.01),
        ] {
            let mut scaled = Vec::new();
            for (e, a) in [(14.5e3, 2e-3), (3.0e3, 0.5e-3)] {
                let mut mat = MaterialParams::from_youngs(e, nu, 1000.0);
                mat.model = model;
                let law = LocalLaw::for_material(&mat, a);
                assert!(matches!(law, LocalLaw::Table(_)), "{model:?}: no table");
                for ratio in [0.001, 0.005] {
                    let d = ratio * a;
                    let hertz = 4.0 / 3.0 * e / (1.0 - nu * nu) * a.sqrt() * d.powf(1.5);
                    let (f, df) = law.force(d);
                    assert!(
                        (f / hertz - 1.0).abs() < tol,
                        "{model:?} at d/a {ratio}: {f} against Hertz's {hertz}"
                    );
                    assert!(
                        (df * d / f - 1.5).abs() < 1e-9,
                        "{model:?}: power {}",
                        df * d / f
                    );
                }
                scaled.push(law.force(0.1 * a).0 / (e * a * a));
            }
            assert!(
                (scaled[0] / scaled[1] - 1.0).abs() < 1e-12,
                "{model:?}: {scaled:?}"
            );
        }
        // Away from the tabulated ratio, Hertz's dependence on it.
        let mut mat = MaterialParams::from_youngs(14.5e3, 0.3, 1000.0);
        mat.model = MaterialModel::StableNeoHookean;
        let d: f64 = 0.005 * 2e-3;
        let hertz = 4.0 / 3.0 * 14.5e3 / (1.0 - 0.09) * 2e-3f64.sqrt() * d.powf(1.5);
        let f = LocalLaw::for_material(&mat, 2e-3).force(d).0;
        assert!(
            (f / hertz - 1.0).abs() < 0.01,
            "nu 0.3: {f} against {hertz}"
        );
        let mut mat = MaterialParams::from_youngs(14.5e3, nu, 1000.0);
        mat.model = MaterialModel::Corotational;
        let hertz = super::super::probe::hertz_stiffness(14.5e3 / (1.0 - nu * nu), 2e-3);
        match LocalLaw::for_material(&mat, 2e-3) {
            LocalLaw::Hertz { stiffness } => {
                assert!(
                    (stiffness / hertz - 1.0).abs() < 1e-12,
                    "{stiffness} against {hertz}"
                )
            }
            law => panic!("corotational: expected Hertz's law, got {law:?}"),
        }
    }

    /// The table law's slope is the derivative of its force (central differences), inside,
    /// below and beyond the knots, and its force is continuous at the knots.
    #[test]
    fn table_slope_is_the_derivative() {
        let law =
            LocalLaw::from_points(&[1e-5, 1e-4, 5e-4, 1e-3], &[3.4e-5, 1.1e-3, 1.1e-2, 2.8e-2])
                .unwrap();
        for d in [3e-6, 1e-5, 4e-5, 1e-4, 3e-4, 7e-4, 1e-3, 2e-3] {
            let h = 1e-7 * d;
            let (f, df) = law.force(d);
            let fd = (law.force(d + h).0 - law.force(d - h).0) / (2.0 * h);
            assert!((fd - df).abs() <= 1e-5 * df, "{d}: {df} against {fd}");
            assert!(f > 0.0);
        }
        let (f, _) = law.force(1e-4);
        assert!((f - 1.1e-3).abs() < 1e-12);
    }
}
