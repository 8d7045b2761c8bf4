//! [`ImplicitCore`]: the hybrid core's linearly implicit step (`hybrid.core_step =
//! "implicit"`, not in the seed), with the matrix frozen at rest and factorised once.
//!
//! **The step.** With `h` the sub-step, `M` the core's lumped mass (its own and the particle
//! layer's), `alpha` the mass damping, `D` the viscous stress's rest operator and `K~` the
//! frozen stiffness,
//!
//! `((1 + alpha h) M + h D + h^2 K~) v+ = M v + h (f_el(x) + f_coup)`, `x+ = x + h v+`,
//!
//! where `f_el` is the core's elastic force at the start of the step and `f_coup` every force
//! the particles and point loads put on the core nodes (explicit). `K~ = margin (K_core +
//! K_layer)`: the core's small-strain stiffness at rest and the particle layer's, condensed on
//! the core through the ties ([`layer_stiffness_blocks`]). The layer's part is there because
//! the particles' terms stiffen the core nodes they are tied to (with `scaled_motion =
//! "deviation"` every active particle's force drives the core): a frozen matrix that
//! dominates the true tangent keeps the step stable, as the whole-body FEM's rest factor does
//! with its `stiffness_margin` (`integrate::LinearSolver::RestCholesky`). The surplus
//! `K~ - K` damps: a mode of stiffness `k` gets the damping `h (k~ - k)`.
//!
//! Neighbours: the core's [`FemModel`], the ties and the cloud of [`mod@super::prepare`], the
//! sparse factor of [`crate::ordering`].

use faer::dyn_stack::MemBuffer;
use faer::sparse::{SparseColMat, Triplet};
use faer::{MatMut, Side};
use glam::{DMat3, DVec3};

use super::prepare::HybridModel;
use crate::ModelError;
use crate::element::FemModel;
use crate::meshfree::cloud::{MAX_STENCIL, TermRest};
use crate::ordering::SparseCholesky;

/// The small-strain stiffness block `K_kl` (3x3, N/m) of an energy `V W(eps)` of isotropic
/// linear elasticity (`lambda`, `mu`, Pa) whose strain is `eps = sym(sum_k u_k (x) b_k)`:
/// `V (lambda b_k (x) b_l + mu b_l (x) b_k + mu (b_k . b_l) I)`, with `(a (x) b)_ij = a_i b_j`.
/// For a linear tetrahedron `b_k` are the shape-function gradients (1/m) and `V` its volume
/// (m^3).
pub fn isotropic_block(lambda_pa: f64, mu_pa: f64, volume_m3: f64, bk: DVec3, bl: DVec3) -> DMat3 {
    let outer = |a: DVec3, b: DVec3| DMat3::from_cols(a * b.x, a * b.y, a * b.z);
    (outer(bk, bl) * lambda_pa
        + outer(bl, bk) * mu_pa
        + DMat3::from_diagonal(DVec3::splat(mu_pa * bk.dot(bl))))
        * volume_m3
}

/// Symmetric 3x3 blocks between node pairs, accumulated per row node (the few neighbours of a
/// core node: a linear search).
#[derive(Debug, Clone)]
pub struct BlockRows {
    rows: Vec<Vec<(u32, DMat3)>>,
}

impl BlockRows {
    /// No blocks, `n` nodes.
    pub fn new(n: usize) -> Self {
        Self {
            rows: vec![Vec::new(); n],
        }
    }

    /// `K_kl += b`.
    pub fn add(&mut self, k: u32, l: u32, b: DMat3) {
        let row = &mut self.rows[k as usize];
        match row.iter_mut().find(|(c, _)| *c == l) {
            Some((_, m)) => *m += b,
            None => row.push((l, b)),
        }
    }

    /// The blocks of row `k`.
    pub fn row(&self, k: usize) -> &[(u32, DMat3)] {
        &self.rows[k]
    }

    /// `out = K u` (N; `u` in m).
    pub fn apply(&self, u: &[DVec3], out: &mut [DVec3]) {
        for (k, row) in self.rows.iter().enumerate() {
            out[k] = row.iter().map(|(l, b)| *b * u[*l as usize]).sum();
        }
    }
}

/// The core's small-strain stiffness at rest (`lambda`, `mu`) or, with the viscous
/// coefficients `(2 phi, 2 psi)` in their place, the viscous operator `D`: linear
/// tetrahedra only.
pub fn core_blocks(fem: &FemModel, lambda_pa: f64, mu_pa: f64) -> BlockRows {
    let mut rows = BlockRows::new(fem.node_count());
    for (e, tet) in fem.tets().iter().enumerate() {
        let g = fem.shape_gradients(e);
        let v = fem.volume_m3()[e];
        for a in 0..4 {
            for b in 0..4 {
                rows.add(
                    tet[a],
                    tet[b],
                    isotropic_block(lambda_pa, mu_pa, v, g[a], g[b]),
                );
            }
        }
    }
    rows
}

/// The particle layer's small-strain stiffness at rest condensed on the core nodes through the
/// ties, `T^T K_layer T` (N/m blocks, core node pairs): every non-degenerate particle's term
/// (seed 000 eq. 26-29 in the corrected form of [`crate::meshfree::block`]) with all its
/// neighbours on their ties `x_j = sum_k w_jk x_k`. Term `i` then has
/// `dF_i = sum_k du_k (x) b_ik`, `b_ik = sum_j (w_jk - w_ik) g_ij`, an element with the
/// gradients `b_ik` and the volume `V_i`, plus its hourglass energy
/// `sum_j c_ij |dF_i X_ij - (du_j - du_i)|^2 / 2`. For neighbours tied to one tetrahedron
/// `b_ik` are that tetrahedron's gradients (the corrected gradients reproduce affine fields)
/// and the hourglass part vanishes. The seed variant's rest strain is ignored (its tangent
/// at rest differs by the kernel estimate's `A_i`).
///
/// # Errors
/// The cloud's [`crate::meshfree::ParticleCloud::term_rest`] errors.
pub fn layer_stiffness_blocks(model: &HybridModel) -> Result<BlockRows, ModelError> {
    let cloud = &model.cloud;
    let tets = &model.core_mesh.tets;
    let mat = cloud.material();
    let (lambda, mu) = (mat.lambda_pa, mat.mu_pa);
    let v = cloud.volume_m3();
    let n = model.core_mesh.nodes.len();
    let mut rows = BlockRows::new(n);
    let mut nbr = [0u32; MAX_STENCIL];
    let mut rest = Box::<TermRest>::default();
    // Per term: the core nodes its particles are tied to, each particle's weights on them
    // (`wt[j * len + s]`, the owner last), `b_ik`, and the hourglass part `sum_j c_j a_j a_j^T`.
    let mut nodes: Vec<u32> = Vec::with_capacity(4 * (MAX_STENCIL + 1));
    let mut wt: Vec<f64> = Vec::new();
    let mut b: Vec<DVec3> = Vec::new();
    let mut a: Vec<f64> = Vec::new();
    let mut hg: Vec<f64> = Vec::new();
    let mut slot_of = vec![u32::MAX; n];
    let mut row_pos = vec![u32::MAX; n];
    for p in 0..cloud.len() as u32 {
        if model.degenerate[p as usize] {
            continue;
        }
        let count = cloud.neighbours(p, &mut nbr);
        cloud.term_rest(p, &nbr[..count], &mut rest)?;
        nodes.clear();
        let particles = nbr[..count].iter().chain(std::iter::once(&p));
        for &q in particles.clone() {
            for &k in &tets[model.particle_tie[q as usize].tet as usize] {
                if slot_of[k as usize] == u32::MAX {
                    slot_of[k as usize] = nodes.len() as u32;
                    nodes.push(k);
                }
            }
        }
        let len = nodes.len();
        wt.clear();
        wt.resize((count + 1) * len, 0.0);
        for (j, &q) in particles.enumerate() {
            let t = &model.particle_tie[q as usize];
            for (k, w) in tets[t.tet as usize].iter().zip(t.w) {
                wt[j * len + slot_of[*k as usize] as usize] += w;
            }
        }
        let own = count * len;
        b.clear();
        b.resize(len, DVec3::ZERO);
        for j in 0..count {
            for s in 0..len {
                b[s] += rest.g[j] * (wt[j * len + s] - wt[own + s]);
            }
        }
        hg.clear();
        hg.resize(len * len, 0.0);
        for j in 0..count {
            let c = rest.hourglass_n_per_m[j];
            if c == 0.0 {
                continue;
            }
            a.clear();
            a.extend(
                (0..len).map(|s| b[s].dot(rest.offset_m[j]) - (wt[j * len + s] - wt[own + s])),
            );
            for s in 0..len {
                let ca = c * a[s];
                for t in 0..len {
                    hg[s * len + t] += ca * a[t];
                }
            }
        }
        for s in 0..len {
            let row = &mut rows.rows[nodes[s] as usize];
            for (i, (l, _)) in row.iter().enumerate() {
                row_pos[*l as usize] = i as u32;
            }
            for t in 0..len {
                let blk = isotropic_block(lambda, mu, v, b[s], b[t])
                    + DMat3::from_diagonal(DVec3::splat(hg[s * len + t]));
                let l = nodes[t];
                match row_pos[l as usize] {
                    u32::MAX => {
                        row_pos[l as usize] = row.len() as u32;
                        row.push((l, blk));
                    }
                    i => row[i as usize].1 += blk,
                }
            }
            for (l, _) in row.iter() {
                row_pos[*l as usize] = u32::MAX;
            }
        }
        for &k in &nodes {
            slot_of[k as usize] = u32::MAX;
        }
    }
    Ok(rows)
}

/// The frozen, factorised matrix of the core's linearly implicit step and its workspace
/// (module documentation). Allocation-free in [`ImplicitCore::step`].
pub struct ImplicitCore {
    h_s: f64,
    factor: SparseCholesky,
    mem: MemBuffer,
    rhs: Vec<f64>,
    /// Constrained components (clamped core nodes), by equation `3 i + c`.
    fixed: Vec<bool>,
}

impl std::fmt::Debug for ImplicitCore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ImplicitCore")
            .field("h_s", &self.h_s)
            .field("factor_entries", &self.factor.factor_entries())
            .finish_non_exhaustive()
    }
}

impl ImplicitCore {
    /// Assembles and factorises `(1 + alpha h) M + h D + h^2 margin (K_core + K_layer)` for the
    /// core `fem` (its lumped mass, constraints and material) and the condensed layer
    /// stiffness `layer` (N/m blocks, or `None`), step `h_s` (s).
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] when the matrix is not positive definite or its analysis
    /// fails.
    pub fn new(
        fem: &FemModel,
        layer: Option<&BlockRows>,
        h_s: f64,
        margin: f64,
    ) -> Result<Self, ModelError> {
        let n = fem.node_count();
        let mat = fem.material();
        let k_core = core_blocks(fem, mat.lambda_pa, mat.mu_pa);
        let d_core = core_blocks(fem, 2.0 * mat.phi_pa_s, 2.0 * mat.psi_pa_s);
        let fixed: Vec<bool> = (0..3 * n)
            .map(|q| fem.constraints()[q / 3] & (1 << (q % 3)) != 0)
            .collect();
        let mut triplets = Vec::new();
        let hh = h_s * h_s * margin;
        let mut push_blocks = |rows: &BlockRows, scale: f64| {
            for k in 0..n {
                for &(l, blk) in rows.row(k) {
                    for r in 0..3 {
                        for c in 0..3 {
                            let (qr, qc) = (3 * k + r, 3 * l as usize + c);
                            if qr >= qc && !fixed[qr] && !fixed[qc] {
                                triplets.push(Triplet::new(qr, qc, blk.col(c)[r] * scale));
                            }
                        }
                    }
                }
            }
        };
        push_blocks(&k_core, hh);
        push_blocks(&d_core, h_s);
        if let Some(layer) = layer {
            push_blocks(layer, hh);
        }
        let damp = 1.0 + mat.mass_damping_per_s * h_s;
        for (q, fixed) in fixed.iter().enumerate() {
            let diag = if *fixed {
                1.0
            } else {
                damp * fem.lumped_mass_kg()[q / 3]
            };
            triplets.push(Triplet::new(q, q, diag));
        }
        let a = SparseColMat::<usize, f64>::try_new_from_triplets(3 * n, 3 * n, &triplets)
            .map_err(|e| ModelError::InvalidInput(format!("implicit core matrix: {e:?}")))?;
        let group: Vec<usize> = (0..3 * n).map(|q| q / 3).collect();
        let factor = SparseCholesky::factor(a.as_ref(), Side::Lower, &group)?;
        let mem = factor.solve_workspace(1);
        Ok(Self {
            h_s,
            factor,
            mem,
            rhs: vec![0.0; 3 * n],
            fixed,
        })
    }

    /// The step the matrix was built for, s.
    pub fn h_s(&self) -> f64 {
        self.h_s
    }

    /// One step: `f` holds the elastic and coupling forces on the core nodes at `x` (N, no
    /// viscous force: the viscous operator is in the matrix); `mass_kg` the lumped masses the
    /// matrix was built with. Updates `v` and `x`; returns the largest squared speed (NaN if
    /// not finite).
    pub fn step(&mut self, mass_kg: &[f64], f: &[DVec3], x: &mut [DVec3], v: &mut [DVec3]) -> f64 {
        let h = self.h_s;
        for (i, ((m, f), v)) in mass_kg.iter().zip(f).zip(v.iter()).enumerate() {
            let r = *v * *m + *f * h;
            for c in 0..3 {
                let q = 3 * i + c;
                self.rhs[q] = if self.fixed[q] { 0.0 } else { r[c] };
            }
        }
        let n = self.rhs.len();
        self.factor.solve_in_place_with(
            MatMut::from_column_major_slice_mut(&mut self.rhs, n, 1),
            &mut self.mem,
        );
        let mut max_v2: f64 = 0.0;
        let mut finite = true;
        for (i, (x, v)) in x.iter_mut().zip(v.iter_mut()).enumerate() {
            *v = DVec3::new(self.rhs[3 * i], self.rhs[3 * i + 1], self.rhs[3 * i + 2]);
            *x += *v * h;
            let s = v.length_squared();
            finite &= s.is_finite();
            max_v2 = max_v2.max(s);
        }
        if finite { max_v2 } else { f64::NAN }
    }
}
