use super::*;

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// One assembly entry: row, column (32-bit: the triplets of an edge-smoothed far part run to
/// tens of millions, and a third less memory matters there) and value.
#[derive(Clone, Copy)]
struct Entry<T> {
    row: u32,
    col: u32,
    val: T,
}

impl<T> Entry<T> {
    fn new(row: usize, col: usize, val: T) -> Self {
        // Indices are equation numbers, below 3 n (checked in `CondensedSolver::new`).
        Self {
            row: row as u32,
            col: col as u32,
            val,
        }
    }
}

/// Square `n x n` sparse matrix from triplets, duplicates summed. A counting sort by column
/// and a dense row marker per column: linear in the triplets, where a general sort of the
/// millions of triplets of an edge-smoothed far part took a fifth of a region's preparation.
///
/// # Errors
/// [`ModelError::InvalidMesh`] for an index out of range.
fn sparse<T: Copy + Default + std::ops::AddAssign + faer::traits::ComplexField>(
    n: usize,
    t: &[Entry<T>],
) -> Result<SparseColMat<usize, T>, ModelError> {
    if t.iter().any(|e| e.row as usize >= n || e.col as usize >= n) {
        return Err(ModelError::InvalidMesh(
            "sparse assembly: an index is out of range".into(),
        ));
    }
    // Bucket the triplets by column.
    let mut start = vec![0usize; n + 1];
    for e in t {
        start[e.col as usize + 1] += 1;
    }
    for j in 0..n {
        start[j + 1] += start[j];
    }
    let mut fill = start.clone();
    let mut order = vec![0u32; t.len()];
    for (k, e) in t.iter().enumerate() {
        order[fill[e.col as usize]] = k as u32;
        fill[e.col as usize] += 1;
    }
    // Per column: merge duplicate rows through a marker, then sort the distinct rows.
    let mut slot = vec![usize::MAX; n];
    let mut col_ptr = Vec::with_capacity(n + 1);
    let mut rows: Vec<usize> = Vec::new();
    let mut vals: Vec<T> = Vec::new();
    let mut column: Vec<(usize, T)> = Vec::new();
    col_ptr.push(0);
    for j in 0..n {
        column.clear();
        for &k in &order[start[j]..start[j + 1]] {
            let e = &t[k as usize];
            match slot[e.row as usize] {
                usize::MAX => {
                    slot[e.row as usize] = column.len();
                    column.push((e.row as usize, e.val));
                }
                s => column[s].1 += e.val,
            }
        }
        for &(r, _) in &column {
            slot[r] = usize::MAX;
        }
        column.sort_unstable_by_key(|&(r, _)| r);
        rows.extend(column.iter().map(|&(r, _)| r));
        vals.extend(column.iter().map(|&(_, v)| v));
        col_ptr.push(rows.len());
    }
    let symbolic = faer::sparse::SymbolicSparseColMat::new_checked(n, n, col_ptr, None, rows);
    Ok(SparseColMat::new(symbolic, vals))
}

/// The model of the tetrahedra `keep` of `body` (mesh `mesh`): every node kept, so numbering
/// is shared; the body's material, strain smoothing and constraints.
pub(super) fn part_model(
    body: &FemModel,
    mesh: &TetMesh,
    keep: &[bool],
) -> Result<FemModel, ModelError> {
    let mut m = FemModel::with_smoothing(
        &sub_mesh(mesh, keep),
        *body.material(),
        body.strain_smoothing(),
    )?;
    m.copy_constraints_from(body);
    m.copy_fibres_from(body);
    m.set_single_precision(body.single_precision())?;
    Ok(m)
}

/// The sub-mesh with the tetrahedra `keep` (every node kept, so numbering is shared).
fn sub_mesh(mesh: &TetMesh, keep: &[bool]) -> TetMesh {
    fn kept<T: Copy>(rows: &[T], keep: &[bool]) -> Vec<T> {
        rows.iter()
            .zip(keep)
            .filter(|(_, k)| **k)
            .map(|(r, _)| *r)
            .collect()
    }
    TetMesh {
        nodes: mesh.nodes.clone(),
        tets: kept(&mesh.tets, keep),
        tet_edge_nodes: kept(&mesh.tet_edge_nodes, keep),
        surfaces: Vec::new(),
        node_groups: Vec::new(),
    }
}

/// Calls `push(row, col, value)` for every entry of the rest tangent stiffness of material
/// `mat` on every cell of `fem` (N/m), rows and columns as global components `3 i + c`,
/// constrained components skipped (duplicates are summed by the caller's assembly).
/// What the tick matrix `A = M (1 + alpha h) + h D0 + h^2 (c K0 + S)` is made of, for any
/// stiffness margin `c` (the lumped masses are the whole body's: an interface node keeps the
/// share of its far elements).
pub(super) struct TickMatrixParts<'a> {
    pub(super) active: &'a FemModel,
    pub(super) material: MaterialParams,
    pub(super) eq: &'a [usize],
    pub(super) gamma_dof: &'a [usize],
    /// `S`, row-major `g x g`.
    pub(super) schur: &'a [f64],
    /// Per interface component, the group of balls of a union region it is nearest
    /// ([`ball_of`]; empty: one group). `S`'s entries between two groups stay out of the
    /// matrix.
    pub(super) ball: Vec<u8>,
    /// Lumped mass per equation, kg.
    pub(super) mass: &'a [f64],
    pub(super) h: f64,
}

impl TickMatrixParts<'_> {
    /// The lower triangle of `A` with margin `c`, in single precision: the solve only sets
    /// the step, while the residual (forces) stays in double precision, so equilibria are
    /// unaffected (module documentation); it halves the memory the solve streams. For the
    /// same reason the far field's coupling between two balls of a union region
    /// [`SEPARATE_BALLS_RADII`] apart (`S`'s entries between their interfaces) is left out: it acts through the residual, and the
    /// balls' parts of the factor stay separate instead of filling a dense block over every
    /// interface.
    pub(super) fn lower(&self, c: f64) -> Result<SparseColMat<usize, f32>, ModelError> {
        let (h, mat, eq) = (self.h, self.material, self.eq);
        let combined = MaterialParams {
            model: MaterialModel::StVenantKirchhoff,
            lambda_pa: c * h * h * mat.lambda_pa + 2.0 * h * mat.phi_pa_s,
            mu_pa: c * h * h * mat.mu_pa + 2.0 * h * mat.psi_pa_s,
            ..mat
        };
        let mut lower = Vec::new();
        let mut push = |r: usize, c: usize, v: f64| {
            if c <= r {
                lower.push(Entry::new(r, c, v as f32));
            }
        };
        rest_tangent(self.active, &combined, |r, c, v| push(eq[r], eq[c], v));
        let g = self.gamma_dof.len();
        let apart = |a: usize, b: usize| !self.ball.is_empty() && self.ball[a] != self.ball[b];
        for a in 0..g {
            for b in 0..g {
                let v = h * h * self.schur[a * g + b];
                if v != 0.0 && !apart(a, b) {
                    push(eq[self.gamma_dof[a]], eq[self.gamma_dof[b]], v);
                }
            }
        }
        for (k, m) in self.mass.iter().enumerate() {
            push(k, k, m * (1.0 + mat.mass_damping_per_s * h));
        }
        sparse(self.mass.len(), &lower)
    }
}

/// The single-precision Cholesky factor of `a_lower` on its analysis `symbolic`.
///
/// # Errors
/// [`ModelError::InvalidMesh`] when the matrix is not positive definite.
pub(super) fn factorize(
    symbolic: &SymbolicCholesky<usize>,
    a_lower: &SparseColMat<usize, f32>,
) -> Result<Vec<f32>, ModelError> {
    let mut factor = vec![0.0f32; symbolic.len_val()];
    let mut mem =
        MemBuffer::new(symbolic.factorize_numeric_llt_scratch::<f32>(Par::Seq, Default::default()));
    symbolic
        .factorize_numeric_llt::<f32>(
            &mut factor,
            a_lower.as_ref(),
            Side::Lower,
            Default::default(),
            Par::Seq,
            MemStack::new(&mut mem),
            Default::default(),
        )
        .map_err(|e| {
            ModelError::InvalidMesh(format!("the tick matrix is not positive definite: {e:?}"))
        })?;
    Ok(factor)
}

fn rest_tangent(fem: &FemModel, mat: &MaterialParams, mut push: impl FnMut(usize, usize, f64)) {
    let mut blocks = Vec::new();
    let constraint = fem.constraints();
    for c in 0..fem.cell_count() {
        cell_tangent_blocks_of(fem, mat, c, fem.rest(), &mut blocks);
        let t = fem.cell_nodes(c);
        for (a, &na) in t.iter().enumerate() {
            for (b, &nb) in t.iter().enumerate() {
                let k = blocks[a * t.len() + b];
                for ca in 0..3 {
                    if constraint[na as usize] & (1 << ca) != 0 {
                        continue;
                    }
                    for cb in 0..3 {
                        if constraint[nb as usize] & (1 << cb) != 0 {
                            continue;
                        }
                        push(3 * na as usize + ca, 3 * nb as usize + cb, k.col(cb)[ca]);
                    }
                }
            }
        }
    }
}

fn rest_tangent_opt(fem: Option<&FemModel>, push: impl FnMut(usize, usize, f64)) {
    if let Some(f) = fem {
        rest_tangent(f, f.material(), push);
    }
}

impl CondensedSolver {
    /// Splits `body` (the whole body's model, with its constraints; `mesh` its mesh) by
    /// `region`, condenses the far part and factorises the tick matrix for the step `dt_s` (s).
    /// Costs one sparse factorisation of the far stiffness and `3|G|` solves with it. A region holding every element condenses nothing: then this is
    /// backward Euler with a prefactored rest matrix on the whole body.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] (`active_region`) for a non-positive radius, a stiffness
    /// margin outside `[1, 100]`, or a region with no element;
    /// [`ModelError::InvalidMesh`] when a factorisation fails (a far part that is not held by
    /// clamps, or an indefinite matrix).
    pub fn new(
        body: &FemModel,
        mesh: &TetMesh,
        region: ActiveRegion,
        dt_s: f64,
    ) -> Result<Self, ModelError> {
        Self::new_with_progress(body, mesh, region, dt_s, &mut |_, _| {})
    }

    /// [`CondensedSolver::new`] reporting its stages: `progress(stage, fraction)` with the
    /// fraction of the work done in `[0, 1]` (the far factorisation, the column solves in
    /// blocks of 64, the tick factorisation); for set-up output on large meshes.
    ///
    /// # Errors
    /// As [`CondensedSolver::new`].
    pub fn new_with_progress(
        body: &FemModel,
        mesh: &TetMesh,
        region: ActiveRegion,
        dt_s: f64,
        progress: &mut dyn FnMut(&str, f64),
    ) -> Result<Self, ModelError> {
        let balls = RegionBalls::one(region.centre_m);
        Self::with_balls(body, mesh, region, balls, dt_s, 1, progress)
    }

    /// [`CondensedSolver::new_union`] (one ball: [`CondensedSolver::new`]) with the
    /// interface column solves, most of a preparation, on `threads` threads (the calling one
    /// and `threads - 1` scoped ones; 0 counts as 1), each taking the next block of 64
    /// columns. The solver is the same bit for bit whatever `threads` is: each column's solve
    /// and each entry's sums are the one-thread ones. `progress` is called on the calling
    /// thread only.
    ///
    /// # Errors
    /// As [`CondensedSolver::new_union`]; a thread that cannot be started is
    /// [`ModelError::InvalidInput`].
    pub fn new_in_threads(
        body: &FemModel,
        mesh: &TetMesh,
        region: ActiveRegion,
        balls: RegionBalls,
        dt_s: f64,
        threads: usize,
        progress: &mut dyn FnMut(&str, f64),
    ) -> Result<Self, ModelError> {
        let Some(&first) = balls.centres().first() else {
            return Err(ModelError::field("active_region", "a union of no ball"));
        };
        let region = ActiveRegion {
            centre_m: first,
            ..region
        };
        Self::with_balls(body, mesh, region, balls, dt_s, threads.max(1), progress)
    }

    /// [`CondensedSolver::new`] on the union of balls of `region`'s radius at `balls`
    /// ([`RegionBalls`]; issue 50: a following region around several tools). The region's
    /// centre becomes the first ball's; one ball is [`CondensedSolver::new`].
    ///
    /// # Errors
    /// As [`CondensedSolver::new`]; a non-finite centre or no ball is
    /// [`ModelError::SceneField`] (`active_region`).
    pub fn new_union(
        body: &FemModel,
        mesh: &TetMesh,
        region: ActiveRegion,
        balls: RegionBalls,
        dt_s: f64,
    ) -> Result<Self, ModelError> {
        Self::new_in_threads(body, mesh, region, balls, dt_s, 1, &mut |_, _| {})
    }

    fn with_balls(
        body: &FemModel,
        mesh: &TetMesh,
        region: ActiveRegion,
        balls: RegionBalls,
        dt_s: f64,
        threads: usize,
        progress: &mut dyn FnMut(&str, f64),
    ) -> Result<Self, ModelError> {
        check_region(body, &region)?;
        if !balls.centres().iter().all(|c| c.is_finite()) {
            return Err(ModelError::field("active_region", "needs finite centres"));
        }
        let system = CondensedSystem::build(body, mesh, &region, &balls, dt_s, threads, progress)?;
        progress("condensation: done", 1.0);
        Ok(Self::assemble(
            system,
            region,
            balls,
            dt_s,
            body.node_count(),
        ))
    }

    /// The solver of a built `system` for `region` (`balls`) and step `dt_s` over a body of
    /// `nodes` nodes: no contact column prepared, the state at rest, zeroed work arrays.
    pub(super) fn assemble(
        system: CondensedSystem,
        region: ActiveRegion,
        balls: RegionBalls,
        dt_s: f64,
        nodes: usize,
    ) -> Self {
        let (m, g) = (system.eq_dof.len(), system.gamma_dof.len());
        let stack = Workspace::new(system.symbolic.solve_in_place_scratch::<f32>(2, Par::Seq));
        Self {
            params: CondensedParams {
                h: dt_s,
                region,
                balls,
            },
            system,
            contact: ContactColumns {
                col: vec![u32::MAX; nodes],
                z: Vec::new().into(),
            },
            state: CondensedState {
                relaxation: 1.0,
                last_contact: Vec::with_capacity(ENTRY_TRACKED_NODES),
                surface_cursor: 0,
            },
            scratch: CondensedScratch::new(m, g, stack),
            stats: CondensedStats::default(),
        }
    }
}

impl CondensedSystem {
    /// Splits `body` (mesh `mesh`) by `region`, condenses the far part and factorises the
    /// tick matrix for the step `h` (s); `progress` as [`CondensedSolver::new_with_progress`]
    /// (all but the last stage), the column solves on `threads` threads.
    ///
    /// # Errors
    /// As [`CondensedSolver::new`], the region's parameters already checked.
    fn build(
        body: &FemModel,
        mesh: &TetMesh,
        region: &ActiveRegion,
        balls: &RegionBalls,
        h: f64,
        threads: usize,
        progress: &mut dyn FnMut(&str, f64),
    ) -> Result<Self, ModelError> {
        let Selection {
            active_tets,
            active,
            far_model,
            node_active,
            node_far,
        } = select_elements(body, mesh, region, balls, true)?;
        let num = number_equations(body, &node_active, &node_far);
        let Condensation {
            schur,
            map_far,
            map,
            surface_rows,
            map_row,
            llt,
            kfg,
        } = condense_far(
            mesh,
            region,
            balls,
            far_model.as_ref(),
            &num,
            threads,
            progress,
        )?;
        let g = num.gamma_dof.len();
        progress("condensation: tick matrix factorisation", 0.85);
        let split = Split::new(body, active_tets, active, node_active, num);
        let parts = split.tick_matrix_parts(body, region, balls, &schur, h);
        let tick = factor_tick_matrix(&parts, &split.num.eq_dof, region.stiffness_margin)?;
        let schur: Vec<f32> = (0..g)
            .flat_map(|a| schur[a * g + a..(a + 1) * g].iter().map(|&v| v as f32))
            .collect();
        let rows = MapRows {
            map_far,
            surface_rows,
            map_row,
        };
        Ok(split.into_system(schur, tick, rows, map, llt, kfg))
    }
}

/// A region's split and what it gives without the far solves: the active elements, the
/// numbering and the lumped mass per equation ([`CondensedSystem::build`], and a region read
/// back from its image).
pub(super) struct Split {
    pub(super) active_tets: usize,
    pub(super) active: FemModel,
    pub(super) node_active: Vec<bool>,
    pub(super) num: Numbering,
    /// Lumped mass per equation, kg.
    pub(super) mass: Vec<f64>,
}

impl Split {
    /// The split of `body` into `active` (`active_tets` elements on `node_active`) and the
    /// numbering `num`.
    pub(super) fn new(
        body: &FemModel,
        active_tets: usize,
        active: FemModel,
        node_active: Vec<bool>,
        num: Numbering,
    ) -> Self {
        let mass = num
            .eq_dof
            .iter()
            .map(|d| body.lumped_mass_kg()[d / 3])
            .collect();
        Self {
            active_tets,
            active,
            node_active,
            num,
            mass,
        }
    }

    /// The tick matrix's parts with `S` row-major (`schur`) and step `h`, s.
    pub(super) fn tick_matrix_parts<'a>(
        &'a self,
        body: &FemModel,
        region: &ActiveRegion,
        balls: &RegionBalls,
        schur: &'a [f64],
        h: f64,
    ) -> TickMatrixParts<'a> {
        TickMatrixParts {
            active: &self.active,
            material: *body.material(),
            eq: &self.num.eq,
            gamma_dof: &self.num.gamma_dof,
            schur,
            ball: ball_of(balls, region.radius_m, body.rest(), &self.num.gamma_dof),
            mass: &self.mass,
            h,
        }
    }

    /// The system of this split with `S` packed in single precision, the tick factor, the far
    /// map's rows and values, and (a region that keeps it) the far factor and `K_FG`.
    pub(super) fn into_system(
        self,
        schur: Vec<f32>,
        (symbolic, factor, sweep, half): TickFactor,
        rows: MapRows,
        map: Vec<u16>,
        llt: Option<SparseCholesky>,
        kfg: Vec<(usize, usize, f64)>,
    ) -> CondensedSystem {
        let Numbering {
            eq,
            eq_dof,
            gamma_dof,
            far_dofs,
            interface_nodes,
            ..
        } = self.num;
        let sizes = CondensedSizes {
            active_tets: self.active_tets,
            active_nodes: self.node_active.iter().filter(|a| **a).count(),
            interface_nodes,
            equations: eq_dof.len(),
            factor_entries: symbolic.len_val(),
        };
        CondensedSystem {
            active: self.active,
            eq,
            eq_dof,
            mass: self.mass,
            gamma_dof,
            schur: schur.into(),
            avx2: Avx2Fma::detect(),
            f16c: Avx2FmaF16c::detect(),
            symbolic: Arc::new(symbolic),
            factor,
            sweep,
            half: half.map(Arc::new),
            map_dofs: rows.map_far.iter().map(|&k| far_dofs[k]).collect(),
            map: map.into(),
            surface_rows: rows.surface_rows,
            map_row: rows.map_row,
            far: FarField {
                dofs: far_dofs,
                llt,
                kfg,
            },
            sizes,
            node_active: self.node_active,
            entry: None,
        }
    }
}

/// Per interface component `gamma_dof` (global components of nodes at `rest`, m): the group
/// of the nearest of `balls` (ties: the first), balls whose centres are within
/// [`SEPARATE_BALLS_RADII`] radii `radius_m` of each other (transitively) forming one group;
/// empty when there is one group.
pub(super) fn ball_of(
    balls: &RegionBalls,
    radius_m: f64,
    rest: &[DVec3],
    gamma_dof: &[usize],
) -> Vec<u8> {
    let centres = balls.centres();
    let mut group: [u8; MAX_REGION_BALLS] = std::array::from_fn(|k| k as u8);
    // Merge until stable (at most MAX_REGION_BALLS passes): the smaller label wins.
    for _ in 0..centres.len() {
        for i in 0..centres.len() {
            for j in 0..centres.len() {
                if centres[i].distance(centres[j]) < SEPARATE_BALLS_RADII * radius_m {
                    let g = group[i].min(group[j]);
                    (group[i], group[j]) = (g, g);
                }
            }
        }
    }
    if group[..centres.len()].iter().all(|&g| g == group[0]) {
        return Vec::new();
    }
    let nearest = |p: DVec3| {
        let k = (0..centres.len())
            .min_by(|&i, &j| p.distance(centres[i]).total_cmp(&p.distance(centres[j])))
            .unwrap_or(0);
        group[k]
    };
    gamma_dof.iter().map(|&d| nearest(rest[d / 3])).collect()
}

/// The region's parameters and the mesh's size checked ([`CondensedSolver::new`]'s errors).
pub(super) fn check_region(body: &FemModel, region: &ActiveRegion) -> Result<(), ModelError> {
    let field = |m: &str| ModelError::field("active_region", m);
    if !(region.radius_m > 0.0) || !region.radius_m.is_finite() || !region.centre_m.is_finite() {
        return Err(field("needs a finite centre and a positive radius"));
    }
    if !(region.stiffness_margin >= 1.0) || region.stiffness_margin > 100.0 {
        return Err(field("stiffness_margin must be in [1, 100]"));
    }
    if 3 * body.node_count() > u32::MAX as usize {
        return Err(field(
            "the mesh has more nodes than 32-bit equation numbers allow",
        ));
    }
    Ok(())
}

/// The active and far elements of a region ([`select_elements`]).
pub(super) struct Selection {
    pub(super) active_tets: usize,
    pub(super) active: FemModel,
    /// `None` when the region holds every element: then this is backward Euler with a
    /// prefactored rest matrix on the whole body.
    pub(super) far_model: Option<FemModel>,
    /// Nodes of an active element.
    pub(super) node_active: Vec<bool>,
    /// Nodes of a far element.
    pub(super) node_far: Vec<bool>,
}

/// Every tetrahedron with a corner node within the region (within its radius of one of
/// `balls`) is active, the others far; the far part's model is built only `with_far`.
///
/// # Errors
/// [`ModelError::SceneField`] for a region with no element; the parts' model errors.
pub(super) fn select_elements(
    body: &FemModel,
    mesh: &TetMesh,
    region: &ActiveRegion,
    balls: &RegionBalls,
    with_far: bool,
) -> Result<Selection, ModelError> {
    let n = body.node_count();
    let r2 = region.radius_m * region.radius_m;
    let inside: Vec<bool> = body
        .rest()
        .iter()
        .map(|p| balls.centres().iter().any(|c| p.distance_squared(*c) <= r2))
        .collect();
    let keep: Vec<bool> = mesh
        .tets
        .iter()
        .map(|t| t.iter().any(|&i| inside[i as usize]))
        .collect();
    let active_tets = keep.iter().filter(|k| **k).count();
    if active_tets == 0 {
        return Err(ModelError::field("active_region", "contains no element"));
    }
    let active = part_model(body, mesh, &keep)?;
    let far_keep: Vec<bool> = keep.iter().map(|k| !k).collect();
    let far_model = if with_far && far_keep.contains(&true) {
        Some(part_model(body, mesh, &far_keep)?)
    } else {
        None
    };
    let mut node_active = vec![false; n];
    let mut node_far = vec![false; n];
    for (e, (t, k)) in mesh.tets.iter().zip(&keep).enumerate() {
        let mid = mesh.tet_edge_nodes.get(e).map_or(&[][..], |m| &m[..]);
        for &i in t.iter().chain(mid) {
            if *k {
                node_active[i as usize] = true;
            } else {
                node_far[i as usize] = true;
            }
        }
    }
    Ok(Selection {
        active_tets,
        active,
        far_model,
        node_active,
        node_far,
    })
}

/// The components of a split: equations (free components of active nodes), interface
/// components (free, of nodes both active and far) and far-only components; each index
/// array maps a global component `3 i + c` to its number, or `usize::MAX`.
pub(super) struct Numbering {
    pub(super) eq: Vec<usize>,
    pub(super) eq_dof: Vec<usize>,
    pub(super) gamma_index: Vec<usize>,
    pub(super) gamma_dof: Vec<usize>,
    pub(super) far_index: Vec<usize>,
    pub(super) far_dofs: Vec<usize>,
    pub(super) interface_nodes: usize,
}

/// Numbers the components of the split `node_active` / `node_far` of `body`.
pub(super) fn number_equations(
    body: &FemModel,
    node_active: &[bool],
    node_far: &[bool],
) -> Numbering {
    let n = body.node_count();
    let free = |i: usize, c: usize| body.constraints()[i] & (1 << c) == 0;
    // Equations: free components of active nodes.
    let mut eq = vec![usize::MAX; 3 * n];
    let mut eq_dof = Vec::new();
    for i in (0..n).filter(|&i| node_active[i]) {
        for c in (0..3).filter(|&c| free(i, c)) {
            eq[3 * i + c] = eq_dof.len();
            eq_dof.push(3 * i + c);
        }
    }
    // Interface components and far-only components.
    let mut gamma_index = vec![usize::MAX; 3 * n];
    let mut gamma_dof = Vec::new();
    let mut far_index = vec![usize::MAX; 3 * n];
    let mut far_dofs = Vec::new();
    let mut interface_nodes = 0;
    for i in 0..n {
        if node_active[i] && node_far[i] {
            interface_nodes += 1;
        }
        for c in (0..3).filter(|&c| free(i, c)) {
            if node_active[i] && node_far[i] {
                gamma_index[3 * i + c] = gamma_dof.len();
                gamma_dof.push(3 * i + c);
            } else if node_far[i] && !node_active[i] {
                far_index[3 * i + c] = far_dofs.len();
                far_dofs.push(3 * i + c);
            }
        }
    }
    Numbering {
        eq,
        eq_dof,
        gamma_index,
        gamma_dof,
        far_index,
        far_dofs,
        interface_nodes,
    }
}

/// The far part condensed on the interface ([`condense_far`]).
struct Condensation {
    /// `S`, row-major `g x g`, symmetrised.
    schur: Vec<f64>,
    /// The far component of each row of the map.
    map_far: Vec<usize>,
    /// The far map `-(K_FF^-1 K_FG)`, rows `map_far`, half-precision bits.
    map: Vec<u16>,
    surface_rows: Vec<u32>,
    map_row: Vec<u32>,
    llt: Option<SparseCholesky>,
    kfg: Vec<(usize, usize, f64)>,
}

/// The Schur complement `S = K_GG - K_GF K_FF^-1 K_FG` of the far part `far_model` on the
/// interface, the far map's rows and the far factor (module documentation); the column
/// solves on `threads` threads.
///
/// # Errors
/// [`ModelError::InvalidMesh`] when the far part is not held.
fn condense_far(
    mesh: &TetMesh,
    region: &ActiveRegion,
    balls: &RegionBalls,
    far_model: Option<&FemModel>,
    num: &Numbering,
    threads: usize,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Condensation, ModelError> {
    let (g, f) = (num.gamma_dof.len(), num.far_dofs.len());
    let (gamma_index, far_index, far_dofs) = (&num.gamma_index, &num.far_index, &num.far_dofs);
    progress("condensation: far stiffness", 0.0);
    // Far stiffness blocks.
    let mut kgg = vec![0.0; g * g];
    let mut kff = Vec::new();
    let mut kfg = Vec::new();
    rest_tangent_opt(far_model, |r, c, v| {
        match (gamma_index[r], gamma_index[c], far_index[r], far_index[c]) {
            (gr, gc, _, _) if gr != usize::MAX && gc != usize::MAX => kgg[gr * g + gc] += v,
            (_, gc, fr, _) if fr != usize::MAX && gc != usize::MAX => kfg.push((fr, gc, v)),
            (_, _, fr, fc) if fr != usize::MAX && fc != usize::MAX && fc <= fr => {
                kff.push(Entry::new(fr, fc, v));
            }
            _ => {}
        }
    });
    let mut schur = kgg;
    let MapRows {
        map_far,
        surface_rows,
        map_row,
    } = map_rows(mesh, region, balls, num);
    let mut map = vec![0u16; map_far.len() * g];
    let llt = if f > 0 {
        progress("condensation: far factorisation", 0.15);
        let far = FarSolve {
            g,
            far_dofs,
            map_far: &map_far,
            kfg: &kfg,
        };
        let llt = far.solve(kff, &mut schur, &mut map, threads, progress)?;
        // A following region recovers its far field from its maps only (the factor is
        // most of its memory: 42 of 80 MB on `lv_h1` at r = 7 mm).
        (!region.follow).then_some(llt)
    } else {
        None
    };
    // Symmetrise (round-off).
    for a in 0..g {
        for b in 0..a {
            let s = 0.5 * (schur[a * g + b] + schur[b * g + a]);
            schur[a * g + b] = s;
            schur[b * g + a] = s;
        }
    }
    Ok(Condensation {
        schur,
        map_far,
        map,
        surface_rows,
        map_row,
        llt,
        kfg,
    })
}

/// Which far components the far map keeps ([`map_rows`]).
pub(super) struct MapRows {
    /// The far component (index into the numbering's far components) of each row.
    pub(super) map_far: Vec<usize>,
    /// Rows on the far boundary.
    pub(super) surface_rows: Vec<u32>,
    /// Following regions: per global component its row or `u32::MAX`; empty otherwise.
    pub(super) map_row: Vec<u32>,
}

/// The rows of `-X` kept: the far boundary components (the surface viewers see, refreshed a
/// slice per tick), or for a following region every far component (a successor may activate
/// any far node: `hand_over`), or for a tile ([`tile_ring`]) the far components within its
/// ring.
pub(super) fn map_rows(
    mesh: &TetMesh,
    region: &ActiveRegion,
    balls: &RegionBalls,
    num: &Numbering,
) -> MapRows {
    let n = num.eq.len() / 3;
    let far_dofs = &num.far_dofs;
    let mut on_boundary = vec![false; n];
    for t in mesh.boundary_triangles() {
        for i in t {
            on_boundary[i as usize] = true;
        }
    }
    let ring = tile_ring(mesh, region, balls);
    let in_ring = |d: usize| ring.is_none_or(|(c, r)| mesh.nodes[d / 3].distance(c) <= r);
    let map_far: Vec<usize> = (0..far_dofs.len())
        .filter(|&k| {
            let d = far_dofs[k];
            if region.follow {
                in_ring(d)
            } else {
                on_boundary[d / 3]
            }
        })
        .collect();
    let surface_rows: Vec<u32> = (0..map_far.len())
        .filter(|&r| on_boundary[far_dofs[map_far[r]] / 3])
        .map(|r| r as u32)
        .collect();
    MapRows::of(num, region.follow, map_far, surface_rows)
}

impl MapRows {
    /// The rows `map_far` (far components of `num`, increasing) with the boundary rows
    /// `surface_rows`, and for a following region (`follow`) the row of every global
    /// component.
    fn of(
        num: &Numbering,
        follow: bool,
        mut map_far: Vec<usize>,
        mut surface_rows: Vec<u32>,
    ) -> Self {
        // Held as long as the region: no spare capacity (a tile read back holds the same heap
        // as the one built, CondensedSolver::heap_bytes).
        map_far.shrink_to_fit();
        surface_rows.shrink_to_fit();
        let mut map_row = vec![u32::MAX; if follow { num.eq.len() } else { 0 }];
        if follow {
            for (r, &k) in map_far.iter().enumerate() {
                map_row[num.far_dofs[k]] = r as u32;
            }
        }
        MapRows {
            map_far,
            surface_rows,
            map_row,
        }
    }

    /// A following region's rows as an image stores them ([`CondensedSolver::to_image`]):
    /// the global components of the rows `map_dofs` (far components of `num`, increasing) and
    /// the boundary rows `surface_rows` (increasing, below the row count), or `None` when they
    /// are not such rows.
    pub(super) fn read_back(
        num: &Numbering,
        map_dofs: &[u32],
        surface_rows: Vec<u32>,
    ) -> Option<Self> {
        let increasing = |v: &[u32]| v.windows(2).all(|w| w[0] < w[1]);
        let rows = map_dofs.len();
        if !increasing(map_dofs)
            || !increasing(&surface_rows)
            || surface_rows.last().is_some_and(|&r| r as usize >= rows)
        {
            return None;
        }
        let map_far = map_dofs
            .iter()
            .map(|&d| {
                num.far_index
                    .get(d as usize)
                    .copied()
                    .filter(|&k| k != usize::MAX)
            })
            .collect::<Option<Vec<usize>>>()?;
        Some(Self::of(num, true, map_far, surface_rows))
    }
}

/// The ball whose far components a tile's map keeps (centre, radius m), or `None` to keep
/// every far component: a following region with tiles ([`TileMode::Background`]) and one
/// ball keeps only what a neighbouring tile can take over, the nodes within
/// `radius + 2 cover` of its centre (a request moves to another tile when the device leaves
/// the cover, and that tile's centre lies within the cover of the device) plus
/// [`TILE_RING_SLACK_M`] and the mesh's longest edge (a successor activates every node of an
/// element that reaches into its ball). A successor beyond the ring (the probe lifted and
/// put down elsewhere) gets the far field's rest state for the components this region does
/// not map ([`CondensedSolver::hand_over`]). On the 100 000-tet LV at r = 4.5 mm and a
/// 2.5 mm cover this keeps about a third of the far map: 42-45 MB tile files instead of
/// 115 MB (docs/benchmarks.md, "Tiles for the 100 000-tet LV").
pub(super) fn tile_ring(
    mesh: &TetMesh,
    region: &ActiveRegion,
    balls: &RegionBalls,
) -> Option<(DVec3, f64)> {
    let TileMode::Background { cover_m } = region.tiles else {
        return None;
    };
    let [centre] = balls.centres() else {
        return None;
    };
    region.follow.then(|| {
        (
            *centre,
            region.radius_m + 2.0 * cover_m + TILE_RING_SLACK_M + mesh.longest_edge_m(),
        )
    })
}

/// What a tile's ring (`build::tile_ring`) adds for a request that moved a little past the cover
/// before the next tile arrived, m: the tile choice's hysteresis (0.5 mm) and as much again.
pub const TILE_RING_SLACK_M: f64 = 1e-3;

/// What the far solves of [`condense_far`] read.
struct FarSolve<'a> {
    /// Interface components.
    g: usize,
    far_dofs: &'a [usize],
    map_far: &'a [usize],
    kfg: &'a [(usize, usize, f64)],
}

impl FarSolve<'_> {
    /// Factorises `K_FF` (lower triplets `kff`) on `threads` threads (faer's parallel dense
    /// kernels, [`SparseCholesky::with_threads`]: the same factor bit for bit), then
    /// `X = K_FF^-1 K_FG` in blocks of columns on as many (each takes the next block;
    /// [`FarSolve::block`]): the map's rows `-X` into `map`, `S -= K_GF X` into `schur`. A
    /// block writes only its own columns of both, so the result does not depend on the thread
    /// count.
    ///
    /// # Errors
    /// [`ModelError::InvalidMesh`] when the far part is not held;
    /// [`ModelError::InvalidInput`] when a thread cannot be started.
    fn solve(
        &self,
        kff: Vec<Entry<f64>>,
        schur: &mut [f64],
        map: &mut [u16],
        threads: usize,
        progress: &mut dyn FnMut(&str, f64),
    ) -> Result<SparseCholesky, ModelError> {
        let (g, f, kfg) = (self.g, self.far_dofs.len(), self.kfg);
        let far_nodes: Vec<usize> = self.far_dofs.iter().map(|&d| d / 3).collect();
        // The triplets go before the factorisation (on a 100 000-tet mesh they are about
        // 0.4 GB, as much as the factor).
        let kff_csc = sparse(f, &kff)?;
        drop(kff);
        let llt = SparseCholesky::factor(kff_csc.as_ref(), Side::Lower, &far_nodes, threads)
            .map_err(|e| {
                ModelError::InvalidMesh(format!(
                    "the far part is not held (add clamps or enlarge the active region): {e}"
                ))
            })?;
        drop(kff_csc);
        let mut by_col: Vec<Vec<(usize, f64)>> = vec![Vec::new(); g];
        for &(fr, gc, v) in kfg {
            by_col[gc].push((fr, v));
        }
        let blocks = g.div_ceil(FAR_SOLVE_BLOCK);
        let next = AtomicUsize::new(0);
        let done = AtomicUsize::new(0);
        let failed = AtomicBool::new(false);
        let out = Mutex::new((schur, map));
        // Takes blocks until none is left (or one failed), calling `before` with the blocks
        // done before each; the first error.
        let work = |before: &mut dyn FnMut(usize)| -> Result<(), ModelError> {
            loop {
                before(done.load(Ordering::Relaxed));
                let b = next.fetch_add(1, Ordering::Relaxed);
                if b >= blocks || failed.load(Ordering::Relaxed) {
                    return Ok(());
                }
                let result = self.block(&llt, &by_col, b * FAR_SOLVE_BLOCK, &out);
                done.fetch_add(1, Ordering::Relaxed);
                if result.is_err() {
                    failed.store(true, Ordering::Relaxed);
                    return result;
                }
            }
        };
        std::thread::scope(|scope| -> Result<(), ModelError> {
            let mut helpers = Vec::with_capacity(threads.saturating_sub(1));
            for _ in 1..threads.min(blocks) {
                let helper = std::thread::Builder::new()
                    .name("region-prep-solve".into())
                    .spawn_scoped(scope, move || work(&mut |_| {}))
                    .map_err(|e| {
                        failed.store(true, Ordering::Relaxed);
                        ModelError::InvalidInput(format!("cannot start a column-solve thread: {e}"))
                    });
                match helper {
                    Ok(h) => helpers.push(h),
                    Err(e) => {
                        for h in helpers {
                            let _ = h.join();
                        }
                        return Err(e);
                    }
                }
            }
            // The calling thread works too, reporting progress between its blocks.
            let mine = work(&mut |d| {
                progress(
                    "condensation: interface column solves",
                    0.25 + 0.6 * d as f64 / blocks.max(1) as f64,
                );
            });
            let mut first = mine;
            for h in helpers {
                let r = h.join().unwrap_or_else(|_| {
                    Err(ModelError::InvalidInput(
                        "a column-solve thread panicked".into(),
                    ))
                });
                if first.is_ok() {
                    first = r;
                }
            }
            first
        })?;
        Ok(llt)
    }

    /// The block of columns from `j0` (at most [`FAR_SOLVE_BLOCK`]): `X = K_FF^-1 K_FG` there,
    /// then, under `out`'s lock, its columns of the map (`-X`, half precision) and of `S`
    /// (`-= K_GF X`).
    ///
    /// # Errors
    /// [`ModelError::InvalidMesh`] when a far displacement leaves half precision's range.
    fn block(
        &self,
        llt: &SparseCholesky,
        by_col: &[Vec<(usize, f64)>],
        j0: usize,
        out: &Mutex<(&mut [f64], &mut [u16])>,
    ) -> Result<(), ModelError> {
        let (g, f, kfg) = (self.g, self.far_dofs.len(), self.kfg);
        let w = FAR_SOLVE_BLOCK.min(g - j0);
        let mut x = Mat::<f64>::zeros(f, w);
        for j in 0..w {
            for &(fr, v) in &by_col[j0 + j] {
                x[(fr, j)] += v;
            }
        }
        llt.solve_in_place(x.as_mut());
        let mut rows = Vec::with_capacity(self.map_far.len() * w);
        for &k in self.map_far {
            for j in 0..w {
                let q = ::half::f16::from_f64(-x[(k, j)]);
                // Entries are displacements per interface displacement, of order one;
                // beyond half precision's range the far part is barely held.
                if !q.is_finite() {
                    return Err(ModelError::InvalidMesh(format!(
                        "the far part is barely held: a far displacement is {:.3e} times \
                         an interface displacement (add clamps or enlarge the active \
                         region)",
                        x[(k, j)].abs()
                    )));
                }
                rows.push(q.to_bits());
            }
        }
        let mut guard = out
            .lock()
            .map_err(|_| ModelError::InvalidInput("a column-solve thread panicked".into()))?;
        let (schur, map) = &mut *guard;
        for (r, row) in rows.chunks_exact(w).enumerate() {
            map[r * g + j0..r * g + j0 + w].copy_from_slice(row);
        }
        // S[gi, j0 + j] -= sum_fr K_FG[fr, gi] X[fr, j]
        for &(fr, gi, v) in kfg {
            let row = &mut schur[gi * g + j0..gi * g + j0 + w];
            for (j, s) in row.iter_mut().enumerate() {
                *s -= v * x[(fr, j)];
            }
        }
        Ok(())
    }
}

/// Columns of `K_FG` per far solve ([`FarSolve::solve`]; 256 gave nothing more,
/// docs/benchmarks.md).
const FAR_SOLVE_BLOCK: usize = 64;

/// The tick matrix's factor: its analysis, the single-precision factor and, when the
/// rounding allows ([`half_of`]), the half-precision sweep.
pub(super) type TickFactor = (
    SymbolicCholesky<usize>,
    Vec<f32>,
    Option<SupernodalSolve>,
    Option<HalfFactor>,
);

/// Factorises the tick matrix of `parts` with stiffness margin `c` (equations `eq_dof`).
///
/// # Errors
/// [`ModelError::InvalidMesh`] when the matrix is not positive definite.
pub(super) fn factor_tick_matrix(
    parts: &TickMatrixParts<'_>,
    eq_dof: &[usize],
    c: f64,
) -> Result<TickFactor, ModelError> {
    let a_lower = parts.lower(c)?;
    let eq_nodes: Vec<usize> = eq_dof.iter().map(|&d| d / 3).collect();
    let symbolic = symbolic_cholesky(a_lower.symbolic(), Side::Lower, &eq_nodes)?;
    let mut factor = factorize(&symbolic, &a_lower)?;
    let mut sweep = SupernodalSolve::new(&symbolic);
    let half = half_of(sweep.as_mut(), &mut factor, &a_lower);
    Ok((symbolic, factor, sweep, half))
}
