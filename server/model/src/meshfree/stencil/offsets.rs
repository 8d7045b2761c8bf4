//! [`Stencil`]: what the stencil loops need of a particle cloud's lattice, fixed for the cloud
//! (offsets, their rest weights and hourglass constants, the classes of pairs `(k, -k)`).

use glam::DVec3;

use crate::meshfree::MeshfreeVariant;
use crate::meshfree::cloud::ParticleCloud;

/// The stencil of a cloud (module documentation of [`super`]): fixed once the cloud is.
#[derive(Debug, Clone)]
pub(super) struct Stencil {
    pub(super) seed: bool,
    pub(super) volume_m3: f64,
    /// Stencil offsets (lattice cells) and, per offset, `w_k` (1/m), `X_k` (m), `c_k` (N/m)
    /// and `u_k = c_k X_k` (N).
    pub(super) dirs: Vec<[i32; 3]>,
    pub(super) w: Vec<[f64; 3]>,
    pub(super) x: Vec<DVec3>,
    pub(super) c: Vec<f64>,
    pub(super) u: Vec<[f64; 3]>,
    /// Largest component of a stencil offset (the stencil loop needs 1: the 26-cell cube or
    /// part of it).
    pub(super) reach: i64,
    /// Half the stencil, one entry `k` of each pair `(k, -k)`, ordered by class (the pairs of
    /// [`super::StencilLayout`] in this order).
    pub(super) half: Vec<usize>,
    /// Classes of stencil entries of equal length: `beta = c_k / phi_k` (`c_k X_k = beta
    /// w_k`), `c_k`, and their range in `half`.
    pub(super) classes: Vec<(f64, f64, std::ops::Range<usize>)>,
    /// Class of each stencil entry.
    pub(super) class_of: Vec<usize>,
    /// Per stencil entry `k`, its pair in `half` and whether `k` is the pair's negative
    /// (`w_k = -w_pair`): pass 2 computes `(N - beta F) w` once per pair.
    pub(super) half_of: Vec<(usize, bool)>,
    /// The stencil is the whole 26-cell cube: the loops run [`super::CUBE`]'s pairs with
    /// their weights' zeros and signs known at compile time.
    pub(super) cube: bool,
    /// The nonzero components' magnitude `|w_k|_max` of each class (faces, edges, corners),
    /// 1/m: `w_k = scale * (the lattice offset)` exactly (cube only).
    pub(super) cube_scale: [f64; 3],
}

/// The pairs and classes of a stencil: `half`, `classes`, `class_of`, `half_of` of
/// [`Stencil`].
type Classes = (
    Vec<usize>,
    Vec<(f64, f64, std::ops::Range<usize>)>,
    Vec<usize>,
    Vec<(usize, bool)>,
);

impl Stencil {
    /// The stencil of `cloud`'s lattice.
    pub(super) fn new(cloud: &ParticleCloud) -> Self {
        let s = cloud.lattice().spacing_m();
        // By x offset first, so that the second pass's partially overlapping read-modify-writes
        // of one row (offsets -1, 0, +1 along x) are a third of the stencil apart.
        let mut dirs: Vec<[i32; 3]> = cloud.lattice().stencil().to_vec();
        dirs.sort_by_key(|d| (d[0], d[2], d[1]));
        let x: Vec<DVec3> = dirs
            .iter()
            .map(|d| DVec3::new(d[0] as f64, d[1] as f64, d[2] as f64) * s)
            .collect();
        let w: Vec<[f64; 3]> = x.iter().map(|&o| cloud.pair_weight(o).to_array()).collect();
        let c: Vec<f64> = x.iter().map(|&o| cloud.hourglass_stiffness(o)).collect();
        let u = x
            .iter()
            .zip(&c)
            .map(|(o, c)| (*o * *c).to_array())
            .collect();
        let reach = dirs
            .iter()
            .flat_map(|d| d.iter().map(|v| v.unsigned_abs() as i64))
            .max()
            .unwrap_or(0);
        let (half, classes, class_of, half_of) = pair_classes(&dirs, &w, &x, &c);
        // The 26-cell cube: three classes (faces, edges, corners, by length).
        let cube = dirs.len() == 26 && reach == 1 && classes.len() == 3;
        let mut cube_scale = [0.0; 3];
        for (sc, cl) in cube_scale.iter_mut().zip(&classes) {
            *sc = w[half[cl.2.start]]
                .iter()
                .fold(0.0f64, |a, v| a.max(v.abs()));
        }
        Self {
            seed: cloud.params().variant == MeshfreeVariant::Seed,
            volume_m3: cloud.volume_m3(),
            dirs,
            w,
            x,
            c,
            u,
            reach,
            half,
            classes,
            class_of,
            half_of,
            cube,
            cube_scale,
        }
    }
}

/// The pairs `(k, -k)` of stencil offsets `dirs` (weights `w`, rest offsets `x`, hourglass
/// constants `c`) by class of length; `w_-k = -w_k` exactly (the weight is odd).
fn pair_classes(dirs: &[[i32; 3]], w: &[[f64; 3]], x: &[DVec3], c: &[f64]) -> Classes {
    let mut half: Vec<usize> = (0..dirs.len())
        .filter(|&k| {
            let d = dirs[k];
            let first = d.iter().copied().find(|&v| v != 0).unwrap_or(0);
            first > 0 && dirs.contains(&[-d[0], -d[1], -d[2]])
        })
        .collect();
    let len2 = |k: usize| dirs[k].iter().map(|v| v * v).sum::<i32>();
    half.sort_by_key(|&k| len2(k));
    let mut classes: Vec<(f64, f64, std::ops::Range<usize>)> = Vec::new();
    for (j, &k) in half.iter().enumerate() {
        if classes
            .last()
            .is_some_and(|cl| len2(half[cl.2.start]) == len2(k))
        {
            classes.last_mut().expect("a class").2.end = j + 1;
        } else {
            let phi = DVec3::from_array(w[k]).length() / x[k].length();
            classes.push((c[k] / phi, c[k], j..j + 1));
        }
    }
    let mut class_of = vec![0usize; dirs.len()];
    for (ci, cl) in classes.iter().enumerate() {
        for &k in &half[cl.2.clone()] {
            let d = dirs[k];
            class_of[k] = ci;
            if let Some(m) = dirs.iter().position(|e| *e == [-d[0], -d[1], -d[2]]) {
                class_of[m] = ci;
            }
        }
    }
    let mut half_of = vec![(usize::MAX, false); dirs.len()];
    for (j, &k) in half.iter().enumerate() {
        let d = dirs[k];
        half_of[k] = (j, false);
        if let Some(m) = dirs.iter().position(|e| *e == [-d[0], -d[1], -d[2]]) {
            half_of[m] = (j, true);
        }
    }
    (half, classes, class_of, half_of)
}
