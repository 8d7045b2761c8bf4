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
//! K_anchors + sum K_region)`: the core's small-strain stiffness at rest and the particle
//! terms' condensed on the core through the ties ([`condensed_blocks`]), for the anchors
//! (always tied) and for each active region and its neighbouring regions (which stand for the
//! inactive particles next to the active ones, whose terms the body also evaluates): the
//! particles' terms stiffen the core nodes they are tied to (with `scaled_motion =
//! "deviation"` every active particle's force drives the core), and a matrix that dominates
//! the true tangent keeps the step stable, as the whole-body FEM's rest factor does with its
//! `stiffness_margin` (`integrate::LinearSolver::RestCholesky`). The matrix's values are
//! rebuilt and refactored when an active region is not in it ([`ImplicitCore::refactor`]); its
//! pattern holds every region's entries. With the explicit elastic force the matrix's
//! stiffness acts as a damping `h K~`: the whole layer in it (tried) overdamps the wall's
//! bending modes (`docs/accuracy.md`, "Deviation mass and an implicit core").
//!
//! Neighbours: the core's [`FemModel`], the ties and the cloud of [`mod@super::prepare`], the
//! sparse factor of [`crate::linalg::ordering`].

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::SparseColMat;
use faer::{MatMut, Par, Side};
use glam::{DMat3, DVec3};

use super::prepare::HybridModel;
use crate::ModelError;
use crate::element::FemModel;
use crate::linalg::ordering::{SparseCholesky, symbolic_cholesky};
use crate::linalg::supernodal::{HalfFactor, SupernodalSolve};
use crate::meshfree::cloud::{MAX_STENCIL, TermRest};
use crate::pool::TickPool;

/// The largest relative difference allowed between the half-precision sweep's solve and the
/// double-precision factor's on a test right-hand side; above it the step keeps faer's solve.
const HALF_MAX_DEVIATION: f64 = 1e-2;

/// The one-column solve of a matrix that never changes ([`crate::linalg::supernodal`]: faer's
/// supernodal factor swept in panels from half precision, as the FEM family's tick does),
/// with its single-precision right-hand side.
struct FrozenSweep {
    sweep: SupernodalSolve,
    half: HalfFactor,
    rhs: Vec<f32>,
}

impl FrozenSweep {
    /// The sweep of `matrix` (lower triangle, positive definite) under the ordering of
    /// `group`, checked against `reference` (its double-precision factor) on a fixed
    /// pseudo-random right-hand side; `None` for a simplicial factor or a deviation above
    /// [`HALF_MAX_DEVIATION`].
    fn new(
        matrix: &SparseColMat<usize, f64>,
        group: &[usize],
        reference: &SparseCholesky,
    ) -> Result<Option<Self>, ModelError> {
        let symbolic = symbolic_cholesky(matrix.symbolic(), Side::Lower, group)?;
        let Some(mut sweep) = SupernodalSolve::new(&symbolic) else {
            return Ok(None);
        };
        let mut values = vec![0.0f64; symbolic.len_val()];
        let mut mem = MemBuffer::new(
            symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()),
        );
        symbolic
            .factorize_numeric_llt::<f64>(
                &mut values,
                matrix.as_ref(),
                Side::Lower,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .map_err(|e| {
                ModelError::InvalidInput(format!("the matrix is not positive definite: {e:?}"))
            })?;
        let mut rounded: Vec<f32> = values.iter().map(|&v| v as f32).collect();
        let Some(half) = sweep.half_factor(&mut rounded) else {
            return Ok(None);
        };
        let n = matrix.nrows();
        let b: Vec<f64> = (0..n as u64)
            .map(|i| ((i.wrapping_mul(2_654_435_761) % 1_000) as f64) / 500.0 - 1.0)
            .collect();
        let mut exact = b.clone();
        reference.solve_in_place(MatMut::from_column_major_slice_mut(&mut exact, n, 1));
        let mut swept: Vec<f32> = b.iter().map(|&v| v as f32).collect();
        sweep.solve_in_place(&half, &mut swept);
        let (mut diff, mut norm) = (0.0f64, 0.0f64);
        for (e, s) in exact.iter().zip(&swept) {
            diff += (e - f64::from(*s)).powi(2);
            norm += e * e;
        }
        if !(diff.sqrt() <= HALF_MAX_DEVIATION * norm.sqrt()) {
            return Ok(None);
        }
        Ok(Some(Self {
            sweep,
            half,
            rhs: vec![0.0; n],
        }))
    }
}

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
/// coefficients `(2 phi, 2 psi)` in their place, the viscous operator `D`, assembled over the
/// FEM's integration points (linear or quadratic tetrahedra):
/// `K_ab = sum_q w_q B(g_a(q), g_b(q))` with [`isotropic_block`].
pub fn core_blocks(fem: &FemModel, lambda_pa: f64, mu_pa: f64) -> BlockRows {
    let mut rows = BlockRows::new(fem.node_count());
    for q in 0..fem.integration_point_count() {
        let nodes = fem.ip_nodes(q);
        let g = fem.ip_gradients(q);
        let w = fem.ip_weight_m3(q);
        for a in 0..nodes.len() {
            for b in 0..nodes.len() {
                rows.add(
                    nodes[a],
                    nodes[b],
                    isotropic_block(lambda_pa, mu_pa, w, g[a], g[b]),
                );
            }
        }
    }
    rows
}

/// Per-term scratch of the condensation ([`Condenser::add_term`]).
#[derive(Debug)]
struct Condenser {
    nbr: [u32; MAX_STENCIL],
    rest: Box<TermRest>,
    /// The core nodes a term's particles are tied to.
    nodes: Vec<u32>,
    /// Each particle's weights on `nodes` (`wt[j * len + s]`, the owner last).
    wt: Vec<f64>,
    /// `b_ik` per node of `nodes`.
    b: Vec<DVec3>,
    /// One hourglass row `a_ij` over `nodes`.
    a: Vec<f64>,
    /// `sum_j c_ij a_ij a_ij^T`.
    hg: Vec<f64>,
    /// Slot of a core node in `nodes` (`u32::MAX`: none).
    slot_of: Vec<u32>,
    /// Position of a column node in the row being filled (`u32::MAX`: none).
    row_pos: Vec<u32>,
}

impl Condenser {
    fn new(core_nodes: usize) -> Self {
        Self {
            nbr: [0; MAX_STENCIL],
            rest: Box::default(),
            nodes: Vec::with_capacity(4 * (MAX_STENCIL + 1)),
            wt: Vec::new(),
            b: Vec::new(),
            a: Vec::new(),
            hg: Vec::new(),
            slot_of: vec![u32::MAX; core_nodes],
            row_pos: vec![u32::MAX; core_nodes],
        }
    }

    /// Adds term `p`'s condensed small-strain stiffness at rest to `rows`
    /// ([`layer_stiffness_blocks`]).
    fn add_term(
        &mut self,
        model: &HybridModel,
        p: u32,
        rows: &mut BlockRows,
    ) -> Result<(), ModelError> {
        let cloud = &model.cloud;
        let tets = &model.core_mesh.tets;
        let mat = cloud.material();
        let (lambda, mu, v) = (mat.lambda_pa, mat.mu_pa, cloud.volume_m3());
        let count = cloud.neighbours(p, &mut self.nbr);
        cloud.term_rest(p, &self.nbr[..count], &mut self.rest)?;
        let rest = &self.rest;
        let nodes = &mut self.nodes;
        nodes.clear();
        let particles = self.nbr[..count].iter().chain(std::iter::once(&p));
        for &q in particles.clone() {
            for &k in &tets[model.particle_tie[q as usize].tet as usize] {
                if self.slot_of[k as usize] == u32::MAX {
                    self.slot_of[k as usize] = nodes.len() as u32;
                    nodes.push(k);
                }
            }
        }
        let len = nodes.len();
        let wt = &mut self.wt;
        wt.clear();
        wt.resize((count + 1) * len, 0.0);
        for (j, &q) in particles.enumerate() {
            let t = &model.particle_tie[q as usize];
            for (k, w) in tets[t.tet as usize].iter().zip(t.w) {
                wt[j * len + self.slot_of[*k as usize] as usize] += w;
            }
        }
        let own = count * len;
        let b = &mut self.b;
        b.clear();
        b.resize(len, DVec3::ZERO);
        for j in 0..count {
            for s in 0..len {
                b[s] += rest.g[j] * (wt[j * len + s] - wt[own + s]);
            }
        }
        let hg = &mut self.hg;
        hg.clear();
        hg.resize(len * len, 0.0);
        for j in 0..count {
            let c = rest.hourglass_n_per_m[j];
            if c == 0.0 {
                continue;
            }
            self.a.clear();
            self.a.extend(
                (0..len).map(|s| b[s].dot(rest.offset_m[j]) - (wt[j * len + s] - wt[own + s])),
            );
            for s in 0..len {
                let ca = c * self.a[s];
                for t in 0..len {
                    hg[s * len + t] += ca * self.a[t];
                }
            }
        }
        for s in 0..len {
            let row = &mut rows.rows[nodes[s] as usize];
            for (i, (l, _)) in row.iter().enumerate() {
                self.row_pos[*l as usize] = i as u32;
            }
            for t in 0..len {
                let blk = isotropic_block(lambda, mu, v, b[s], b[t])
                    + DMat3::from_diagonal(DVec3::splat(hg[s * len + t]));
                let l = nodes[t];
                match self.row_pos[l as usize] {
                    u32::MAX => {
                        self.row_pos[l as usize] = row.len() as u32;
                        row.push((l, blk));
                    }
                    i => row[i as usize].1 += blk,
                }
            }
            for (l, _) in row.iter() {
                self.row_pos[*l as usize] = u32::MAX;
            }
        }
        for &k in nodes.iter() {
            self.slot_of[k as usize] = u32::MAX;
        }
        Ok(())
    }
}

/// The particle layer's small-strain stiffness at rest condensed on the core nodes through the
/// ties, `T^T K_layer T` (N/m blocks, core node pairs), of the terms of `owners` (skipping
/// degenerate particles): each with all its neighbours on their ties `x_j = sum_k w_jk x_k`.
/// Term `i` (seed 000 eq. 26-29 in the corrected form of [`crate::meshfree::block`]) then has
/// `dF_i = sum_k du_k (x) b_ik`, `b_ik = sum_j (w_jk - w_ik) g_ij`: an element with the
/// gradients `b_ik` and the volume `V_i`, plus its hourglass energy
/// `sum_j c_ij |dF_i X_ij - (du_j - du_i)|^2 / 2`. For neighbours tied to one tetrahedron
/// `b_ik` are that tetrahedron's gradients (the corrected gradients reproduce affine fields)
/// and the hourglass part vanishes. The seed variant's rest strain is ignored (its tangent
/// at rest differs by the kernel estimate's `A_i`).
///
/// # Errors
/// The cloud's [`crate::meshfree::ParticleCloud::term_rest`] errors.
pub fn condensed_blocks(
    model: &HybridModel,
    owners: impl IntoIterator<Item = u32>,
) -> Result<BlockRows, ModelError> {
    let n = model.core_mesh.nodes.len();
    let mut rows = BlockRows::new(n);
    let mut c = Condenser::new(n);
    for p in owners {
        if !model.degenerate[p as usize] {
            c.add_term(model, p, &mut rows)?;
        }
    }
    Ok(rows)
}

/// [`condensed_blocks`] of every particle: the whole layer (and the anchors inside the core)
/// held on its ties.
///
/// # Errors
/// As [`condensed_blocks`].
pub fn layer_stiffness_blocks(model: &HybridModel) -> Result<BlockRows, ModelError> {
    condensed_blocks(model, 0..model.cloud.len() as u32)
}

/// The condensed rest stiffness the implicit core's matrix is built from, computed once per
/// model: the anchors' terms (always tied) and each outer vertex's particle region's terms
/// (added to the matrix while the region is active), as lower-triangle block lists
/// `(k, l, K_kl)` with `k >= l`.
#[derive(Debug, Clone)]
pub struct CondensedLayer {
    anchors: BlockRows,
    regions: Vec<Vec<(u32, u32, DMat3)>>,
}

impl CondensedLayer {
    /// Condenses the anchors' and every region's terms (about 0.8 s for `lv-hybrid`'s
    /// 171 000 particles on one core).
    ///
    /// # Errors
    /// As [`condensed_blocks`].
    pub fn new(model: &HybridModel) -> Result<Self, ModelError> {
        let n = model.core_mesh.nodes.len();
        let anchors = condensed_blocks(model, model.layer_count as u32..model.cloud.len() as u32)?;
        let mut c = Condenser::new(n);
        let mut rows = BlockRows::new(n);
        let mut touched: Vec<u32> = Vec::new();
        let mut regions = Vec::with_capacity(model.region_start.len().saturating_sub(1));
        for v in 0..model.region_start.len().saturating_sub(1) {
            let range = model.region_start[v] as usize..model.region_start[v + 1] as usize;
            for &p in &model.region_particles[range] {
                if !model.degenerate[p as usize] {
                    c.add_term(model, p, &mut rows)?;
                }
            }
            touched.clear();
            touched.extend((0..n as u32).filter(|&k| !rows.rows[k as usize].is_empty()));
            let mut list = Vec::new();
            for &k in &touched {
                for (l, blk) in rows.rows[k as usize].drain(..) {
                    if k >= l {
                        list.push((k, l, blk));
                    }
                }
            }
            regions.push(list);
        }
        Ok(Self { anchors, regions })
    }
}

/// The factorised matrix of the core's linearly implicit step and its workspace (module
/// documentation): allocation-free in [`ImplicitCore::step`] and [`ImplicitCore::refactor`].
pub struct ImplicitCore {
    h_s: f64,
    margin: f64,
    /// The matrix's lower triangle: pattern of every region's entries, values of the current
    /// active set.
    matrix: SparseColMat<usize, f64>,
    /// Values without any region: mass, viscous operator, core and anchors.
    base: Vec<f64>,
    /// Per region: the value indices and values to add while it is active (double
    /// precision: every row of a region's stiffness sums to zero, so the step conserves
    /// momentum to round-off).
    region_start: Vec<usize>,
    region_index: Vec<u32>,
    region_value: Vec<f64>,
    factor: SparseCholesky,
    /// The half-precision sweep when the matrix never changes (no layer condensed in it).
    frozen: Option<FrozenSweep>,
    factor_mem: MemBuffer,
    mem: MemBuffer,
    rhs: Vec<f64>,
    /// Constrained components (clamped core nodes), by equation `3 i + c`.
    fixed: Vec<bool>,
}

impl std::fmt::Debug for ImplicitCore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ImplicitCore")
            .field("h_s", &self.h_s)
            .field("margin", &self.margin)
            .field("factor_entries", &self.factor.factor_entries())
            .finish_non_exhaustive()
    }
}

impl ImplicitCore {
    /// Assembles `(1 + alpha h) M + h D + h^2 margin (K_core + K_anchors)` for the core `fem`
    /// (its lumped mass, constraints and material) with the pattern of every region's
    /// condensed stiffness in `layer`, step `h_s` (s), and factorises it with no region
    /// active. Without a layer (`inactive_layer = "elements"`: the FEM covers the whole wall
    /// and stands for the particles' terms) the matrix is `(1 + alpha h) M + h D + h^2 margin
    /// K_core` and never changes.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] when the matrix is not positive definite or its analysis
    /// fails.
    pub fn new(
        fem: &FemModel,
        layer: Option<&CondensedLayer>,
        h_s: f64,
        margin: f64,
    ) -> Result<Self, ModelError> {
        let no_regions = CondensedLayer {
            anchors: BlockRows::new(fem.node_count()),
            regions: Vec::new(),
        };
        let layer = layer.unwrap_or(&no_regions);
        let n = fem.node_count();
        let fixed: Vec<bool> = (0..3 * n)
            .map(|q| fem.constraints()[q / 3] & (1 << (q % 3)) != 0)
            .collect();
        let hh = h_s * h_s * margin;
        let base_entries = base_entries(fem, layer, &fixed, h_s, hh);
        let (col_ptr, row_idx) = pattern(3 * n, &base_entries, layer, &fixed, hh);
        let index = |r: usize, c: usize| {
            let rows = &row_idx[col_ptr[c]..col_ptr[c + 1]];
            col_ptr[c] + rows.binary_search(&r).expect("entry in the pattern")
        };
        let mut base = vec![0.0; row_idx.len()];
        for &(r, c, v) in &base_entries {
            base[index(r, c)] += v;
        }
        let mut region_start = vec![0usize];
        let (mut region_index, mut region_value) = (Vec::new(), Vec::new());
        let mut region_scalars: Vec<(usize, usize, f64)> = Vec::new();
        for list in &layer.regions {
            region_scalars.clear();
            for (k, l, blk) in list {
                lower_scalars(&fixed, *k, *l, blk, hh, &mut region_scalars);
            }
            for &(r, c, v) in &region_scalars {
                region_index.push(index(r, c) as u32);
                region_value.push(v);
            }
            region_start.push(region_index.len());
        }
        let symbolic =
            faer::sparse::SymbolicSparseColMat::new_checked(3 * n, 3 * n, col_ptr, None, row_idx);
        let matrix = SparseColMat::new(symbolic, base.clone());
        let group: Vec<usize> = (0..3 * n).map(|q| q / 3).collect();
        let mut factor = SparseCholesky::analyse(matrix.symbolic(), Side::Lower, &group)?;
        let mut factor_mem = factor.factor_workspace();
        factor.factor_llt_in(matrix.as_ref(), Side::Lower, &mut factor_mem)?;
        let mem = factor.solve_workspace(1);
        // A matrix without regions is never refactored: its one-column solve per tick is the
        // tick's largest cost (faer's general solve, a dense call per supernode), so it goes
        // through the panel sweep the FEM family uses.
        let frozen = if layer.regions.is_empty() {
            FrozenSweep::new(&matrix, &group, &factor)?
        } else {
            None
        };
        Ok(Self {
            h_s,
            margin,
            matrix,
            base,
            region_start,
            region_index,
            region_value,
            factor,
            frozen,
            factor_mem,
            mem,
            rhs: vec![0.0; 3 * n],
            fixed,
        })
    }

    /// The step the matrix was built for, s.
    pub fn h_s(&self) -> f64 {
        self.h_s
    }

    /// Heap bytes held: the matrix (pattern and two sets of values), the regions' entries and
    /// the factor.
    pub fn memory_bytes(&self) -> usize {
        let values = self.base.len();
        values * (2 * 8 + 8)
            + self.region_index.len() * (4 + 8)
            + self.region_start.len() * 8
            + self.factor.factor_entries() * 8
            + self.rhs.len() * 9
    }

    /// Rebuilds the matrix's values with the regions `active` (indices of outer vertices) and
    /// refactors it (numeric only, allocation-free).
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] when the matrix is not positive definite (it is, by
    /// construction: a sum of positive semi-definite terms and a positive mass).
    pub fn refactor(&mut self, active: &[u32]) -> Result<(), ModelError> {
        let values = self.matrix.val_mut();
        values.copy_from_slice(&self.base);
        for &v in active {
            let v = v as usize;
            let range = self.region_start[v]..self.region_start[v + 1];
            for (&i, &x) in self.region_index[range.clone()]
                .iter()
                .zip(&self.region_value[range])
            {
                values[i as usize] += x;
            }
        }
        self.factor
            .factor_llt_in(self.matrix.as_ref(), Side::Lower, &mut self.factor_mem)
    }

    /// One step: `f` holds the elastic and coupling forces on the core nodes at `x` (N, no
    /// viscous force: the viscous operator is in the matrix); `mass_kg` the lumped masses the
    /// matrix was built with. Updates `v` and `x`; returns the largest squared speed (NaN if
    /// not finite).
    pub fn step(&mut self, mass_kg: &[f64], f: &[DVec3], x: &mut [DVec3], v: &mut [DVec3]) -> f64 {
        self.step_in(None, mass_kg, f, x, v)
    }

    /// Cuts the frozen matrix's half-precision sweep in two for a tick pool of `parts` threads
    /// when its elimination tree forks in balanced halves
    /// ([`SupernodalSolve::set_parts`]); returns whether it did. Set-up, not a tick.
    pub fn set_parts(&mut self, parts: usize) -> bool {
        self.frozen
            .as_mut()
            .is_some_and(|f| f.sweep.set_parts(parts))
    }

    /// [`Self::step`] with the frozen sweep's halves on `pool` ([`Self::set_parts`];
    /// [`SupernodalSolve::solve_in_place_in`]). Allocation-free.
    pub fn step_in(
        &mut self,
        pool: Option<&TickPool>,
        mass_kg: &[f64],
        f: &[DVec3],
        x: &mut [DVec3],
        v: &mut [DVec3],
    ) -> f64 {
        let h = self.h_s;
        let momenta = mass_kg
            .iter()
            .zip(f)
            .zip(v.iter())
            .map(|((m, f), v)| *v * *m + *f * h);
        if let Some(frozen) = &mut self.frozen {
            // The right-hand side straight into the sweep's single precision, and the velocities
            // straight out of it (no double-precision copy on the way).
            let rows = frozen
                .rhs
                .chunks_exact_mut(3)
                .zip(self.fixed.chunks_exact(3));
            for ((s, fixed), r) in rows.zip(momenta) {
                for c in 0..3 {
                    s[c] = if fixed[c] { 0.0 } else { r[c] as f32 };
                }
            }
            frozen
                .sweep
                .solve_in_place_in(pool, &frozen.half, &mut frozen.rhs);
            let velocities = frozen
                .rhs
                .chunks_exact(3)
                .map(|s| DVec3::new(f64::from(s[0]), f64::from(s[1]), f64::from(s[2])));
            return advance(h, velocities, x, v);
        }
        let rows = self.rhs.chunks_exact_mut(3).zip(self.fixed.chunks_exact(3));
        for ((s, fixed), r) in rows.zip(momenta) {
            for c in 0..3 {
                s[c] = if fixed[c] { 0.0 } else { r[c] };
            }
        }
        let n = self.rhs.len();
        self.factor.solve_in_place_with(
            MatMut::from_column_major_slice_mut(&mut self.rhs, n, 1),
            &mut self.mem,
        );
        let velocities = self
            .rhs
            .chunks_exact(3)
            .map(|s| DVec3::new(s[0], s[1], s[2]));
        advance(h, velocities, x, v)
    }
}

/// `v = velocities`, `x += h v` node by node; returns the largest squared speed (NaN when one
/// is not finite).
fn advance(
    h: f64,
    velocities: impl Iterator<Item = DVec3>,
    x: &mut [DVec3],
    v: &mut [DVec3],
) -> f64 {
    let mut max_v2: f64 = 0.0;
    let mut finite = true;
    for ((x, v), new) in x.iter_mut().zip(v.iter_mut()).zip(velocities) {
        *v = new;
        *x += new * h;
        let s = new.length_squared();
        finite &= s.is_finite();
        max_v2 = max_v2.max(s);
    }
    if finite { max_v2 } else { f64::NAN }
}

/// The lower-triangle scalar entries `(row, column, value)` of block `blk` at block row `k`,
/// column `l`, times `scale`, into `out`, leaving out the `fixed` degrees of freedom.
fn lower_scalars(
    fixed: &[bool],
    k: u32,
    l: u32,
    blk: &DMat3,
    scale: f64,
    out: &mut Vec<(usize, usize, f64)>,
) {
    for r in 0..3 {
        for c in 0..3 {
            let (qr, qc) = (3 * k as usize + r, 3 * l as usize + c);
            if qr >= qc && !fixed[qr] && !fixed[qc] {
                out.push((qr, qc, blk.col(c)[r] * scale));
            }
        }
    }
}

/// The lower-triangle entries of the matrix with no region active ([`ImplicitCore::new`]):
/// `hh K_core`, `h D`, `hh` times the anchors of `layer` (`hh = h^2 margin`), then the
/// diagonal `(1 + alpha h) M` (1 on `fixed` degrees of freedom).
fn base_entries(
    fem: &FemModel,
    layer: &CondensedLayer,
    fixed: &[bool],
    h_s: f64,
    hh: f64,
) -> Vec<(usize, usize, f64)> {
    let n = fem.node_count();
    let mat = fem.material();
    let mut base_entries: Vec<(usize, usize, f64)> = Vec::new();
    let k_core = core_blocks(fem, mat.lambda_pa, mat.mu_pa);
    let d_core = core_blocks(fem, 2.0 * mat.phi_pa_s, 2.0 * mat.psi_pa_s);
    for (rows, scale) in [(&k_core, hh), (&d_core, h_s), (&layer.anchors, hh)] {
        for k in 0..n {
            for (l, blk) in rows.row(k) {
                if k as u32 >= *l {
                    lower_scalars(fixed, k as u32, *l, blk, scale, &mut base_entries);
                }
            }
        }
    }
    let damp = 1.0 + mat.mass_damping_per_s * h_s;
    for (q, fixed) in fixed.iter().enumerate() {
        let diag = if *fixed {
            1.0
        } else {
            damp * fem.lumped_mass_kg()[q / 3]
        };
        base_entries.push((q, q, diag));
    }
    base_entries
}

/// The pattern (column pointers, row indices of the lower triangle, `dofs` columns) of every
/// entry any active set can have: `base_entries` and every region's of `layer` (`hh` their
/// scale), marked in a bitmap of the lower triangle (no list of every region's scalars).
fn pattern(
    dofs: usize,
    base_entries: &[(usize, usize, f64)],
    layer: &CondensedLayer,
    fixed: &[bool],
    hh: f64,
) -> (Vec<usize>, Vec<usize>) {
    let mut seen = vec![0u64; (dofs * dofs).div_ceil(64)];
    let mark = |r: usize, c: usize, seen: &mut [u64]| {
        let bit = c * dofs + r;
        seen[bit / 64] |= 1 << (bit % 64);
    };
    let mut region_scalars: Vec<(usize, usize, f64)> = Vec::new();
    for &(r, c, _) in base_entries {
        mark(r, c, &mut seen);
    }
    for list in &layer.regions {
        region_scalars.clear();
        for (k, l, blk) in list {
            lower_scalars(fixed, *k, *l, blk, hh, &mut region_scalars);
        }
        for &(r, c, _) in &region_scalars {
            mark(r, c, &mut seen);
        }
    }
    let mut col_ptr = vec![0usize];
    let mut row_idx = Vec::new();
    for c in 0..dofs {
        row_idx.extend((c..dofs).filter(|&r| {
            let bit = c * dofs + r;
            seen[bit / 64] & (1 << (bit % 64)) != 0
        }));
        col_ptr.push(row_idx.len());
    }
    (col_ptr, row_idx)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::element::tangent::cell_tangent_blocks;
    use crate::material::MaterialParams;
    use crate::mesh::generate::box_mesh;

    /// The core's assembled small-strain stiffness equals the FEM's own tangent at rest
    /// (`cell_tangent_blocks`, the directional derivative of the first Piola-Kirchhoff stress
    /// at each integration point), block by block, over a 2 x 2 x 2 box of linear and of
    /// quadratic tetrahedra.
    #[test]
    fn core_blocks_are_the_fem_tangent_at_rest() {
        let linear = box_mesh(DVec3::new(0.02, 0.01, 0.015), [2, 2, 2]);
        for mesh in [linear.clone(), linear.to_quadratic()] {
            let material = MaterialParams::from_youngs(14_500.0, 0.45, 1060.0);
            let fem = FemModel::new(&mesh, material).expect("model");
            let rows = core_blocks(&fem, material.lambda_pa, material.mu_pa);
            let mut reference = BlockRows::new(fem.node_count());
            let mut blocks = Vec::new();
            for c in 0..fem.cell_count() {
                cell_tangent_blocks(&fem, c, fem.rest(), &mut blocks);
                let nodes = fem.cell_nodes(c);
                for (a, &na) in nodes.iter().enumerate() {
                    for (b, &nb) in nodes.iter().enumerate() {
                        reference.add(na, nb, blocks[a * nodes.len() + b]);
                    }
                }
            }
            let scale = rows
                .row(0)
                .iter()
                .map(|(_, m)| m.abs().to_cols_array().into_iter().fold(0.0, f64::max))
                .fold(0.0, f64::max);
            assert!(scale > 0.0);
            for k in 0..fem.node_count() {
                assert_eq!(rows.row(k).len(), reference.row(k).len(), "row {k}");
                for (l, m) in rows.row(k) {
                    let (_, r) = reference
                        .row(k)
                        .iter()
                        .find(|(c, _)| c == l)
                        .expect("same pattern");
                    let diff = (*m - *r)
                        .abs()
                        .to_cols_array()
                        .into_iter()
                        .fold(0.0, f64::max);
                    assert!(diff < 1e-10 * scale, "block ({k}, {l}): {m} against {r}");
                }
            }
        }
    }
}
