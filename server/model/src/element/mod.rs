//! Tetrahedral finite elements: linear 4-node tetrahedra (seed 000 section 3.1), 10-node
//! quadratic tetrahedra (the default of the built-in `lv` scene), and linear tetrahedra with
//! edge-based strain smoothing; St. Venant-Kirchhoff and the other laws of [`crate::material`],
//! plus the seed's viscous stress (section 2).
//!
//! Per element the rest data is precomputed once: the inverse rest edge matrix
//! `Dm^-1 = [X1-X0, X2-X0, X3-X0]^-1`, whose rows are the shape-function gradients `grad N_a`
//! of eq. 13-21 (`grad N_0 = -(grad N_1 + grad N_2 + grad N_3)`), and the rest volume (eq. 17).
//! Per step the deformation gradient is `F = Ds Dm^-1 = sum_a x_a (grad N_a)^T` (eq. 21), the Green
//! strain `E` (eq. 4), the stress `S` (eq. 9 + eq. 11), and the nodal forces
//! `f_a = -V F S grad N_a` (eq. 22).
//!
//! **Note on eq. 22.** The seed writes `F^i = vol/2 sum_j x^j sum_kl Gamma_jl Gamma_ik sigma_kl`,
//! taken from O'Brien & Hodgins 1999, whose Green strain has no factor 1/2. With the strain of
//! eq. 4 (with the 1/2), the force that is minus the gradient of the StVK energy has no factor
//! 1/2; we implement the energy-consistent force, and a test checks it against finite
//! differences of the energy.
//!
//! **Quadratic tetrahedra.** A mesh with mid-edge nodes ([`TetMesh::tet_edge_nodes`]) gets
//! isoparametric 10-node elements (Zienkiewicz & Taylor, *The Finite Element Method*, vol. 1,
//! section 6.8; the C3D10 of Abaqus): shape functions `N_i = L_i (2 L_i - 1)` at the corners and
//! `N_ij = 4 L_i L_j` at the mid-edge nodes in the barycentric coordinates `L`, integrated with
//! the 4-point Gauss rule of degree 2 (barycentric `(a, b, b, b)` and permutations, `a =
//! 0.5854101966249685`, `b = 0.1381966011250105`, weights `V/4`). Each integration point is
//! treated like a linear element: `F = sum_a x_a (grad N_a)^T` over its 10 nodes, `f_a -= w P
//! grad N_a`. The strain varies linearly inside the element, so bending is represented and
//! the shear locking of linear tetrahedra in thin walls and beams goes away. Masses are lumped
//! by the HRZ rule ([`mass`]).
//!
//! **Strain smoothing.** Linear tetrahedra can instead carry the edge-based smoothed
//! deformation gradient of ES-FEM-T4 ([`StrainSmoothing::Edge`]): one integration point per mesh
//! edge whose gradients are the volume-weighted average of the surrounding elements'. Points
//! are grouped in *cells* (an element, or a smoothing domain with its own node list), so every
//! generic path and the static solver work on either.
//!
//! Owns: [`FemModel`] and its parts: `quadrature` (integration points), [`smoothing`],
//! [`mass`], [`tangent`] (stiffness action, tangent blocks, eigenvalue bound) and `kernels`
//! (the vectorised force kernels, the crate's only `unsafe` besides the condensed solver's
//! dot products). May use: [`crate::mesh`], [`crate::material`]. Used by
//! [`crate::integrate`], [`crate::contact`] (positions only), [`crate::statics`] and the
//! bodies.

use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::material::{self, MaterialParams};
use crate::mesh::TetMesh;
use crate::pool::TickPool;

pub mod fibres;
mod kernels;
pub mod mass;
mod quadrature;
pub mod smoothing;
pub mod tangent;

pub use fibres::{FibreField, FibreRule};
pub(crate) use kernels::SingleElastic;
pub use kernels::{ForcePart, ForceScratch, MAX_FORCE_PARTS, SingleIsa};
use kernels::{Kernels, RunParts, SingleLinear};
pub use mass::lumped_masses;
use quadrature::{IntegrationPoints, linear_gradients, linear_points, quadratic_points};
pub use smoothing::StrainSmoothing;
use smoothing::edge_smoothed_points;

/// Largest number of integration points of a cell (the 4-point rule of quadratic elements).
pub const MAX_CELL_POINTS: usize = 4;

/// What runs the parts of one force evaluation ([`FemModel::add_internal_forces_in`]): a
/// [`TickPool`], or in tests and benchmarks any other runner with the same contract.
pub trait PartRunner {
    /// Threads that run a job, and so the number of parts an evaluation is cut into (at most
    /// [`MAX_FORCE_PARTS`] and the scratch's parts are used).
    fn threads(&self) -> usize;

    /// Calls `f(p, &mut parts[p])` once for every `p`, each on one thread, and returns when all
    /// are done. Must not allocate (it runs in the tick).
    fn run_parts(&self, parts: &mut [ForcePart], f: &(dyn Fn(usize, &mut ForcePart) + Sync));
}

impl PartRunner for TickPool {
    fn threads(&self) -> usize {
        TickPool::threads(self)
    }

    fn run_parts(&self, parts: &mut [ForcePart], f: &(dyn Fn(usize, &mut ForcePart) + Sync)) {
        self.for_each_mut(parts, f);
    }
}

/// Bit mask of constrained displacement components of a node: bit 0 = x, 1 = y, 2 = z.
pub type ConstraintMask = u8;

/// All three components fixed (a clamped node).
pub const CLAMPED: ConstraintMask = 0b111;

/// Zeroes the constrained components of `v` (a per-node vector field) in place.
#[inline]
pub fn apply_constraint(mask: ConstraintMask, v: &mut DVec3) {
    if mask & 1 != 0 {
        v.x = 0.0;
    }
    if mask & 2 != 0 {
        v.y = 0.0;
    }
    if mask & 4 != 0 {
        v.z = 0.0;
    }
}

/// Precomputed rest-state data of a tetrahedral FEM body: element geometry, integration
/// points, lumped masses, material and constraints. The element data is fixed at
/// construction (the vectorised kernels rely on it); the constraints can be changed
/// ([`FemModel::clamp_nodes`], [`FemModel::set_constraint`]). Fields are private: read them
/// through the accessors.
#[derive(Debug, Clone)]
pub struct FemModel {
    /// Rest positions, m. Length N.
    rest: Vec<DVec3>,
    /// Element corner indices, positively oriented. Length E.
    tets: Vec<[u32; 4]>,
    /// Inverse rest edge matrix per element, 1/m. Row `a` is `grad N_{a+1}`.
    dm_inv: Vec<DMat3>,
    /// Rest volume per element, m^3.
    volume_m3: Vec<f64>,
    /// Lumped nodal masses ([`lumped_masses`]), kg. Length N.
    lumped_mass_kg: Vec<f64>,
    /// Constrained components per node ([`CLAMPED`] for a clamped node). Length N.
    constraint: Vec<ConstraintMask>,
    material: MaterialParams,
    /// Integration points of every cell, for the generic paths.
    points: IntegrationPoints,
    /// The same cells in batches for the vectorised force kernels.
    kernels: Kernels,
    /// The single-precision kernel, when enabled ([`FemModel::set_single_precision`]).
    single: Option<SingleLinear>,
    /// Whether the elements are 10-node tetrahedra.
    quadratic: bool,
    /// Strain smoothing of linear elements.
    smoothing: StrainSmoothing,
    /// The material frame (fibre, sheet, sheet-normal columns) of every integration point for
    /// an anisotropic material; empty: the identity everywhere.
    frames: Vec<DMat3>,
    /// The fibre field the frames come from (kept for models built from part of this one).
    fibres: Option<FibreField>,
    /// Augmented-Lagrangian pressure of every cell, Pa, added to `U'(J_c)` of the
    /// mean-dilatation penalty (empty: zero). See [`FemModel::set_cell_pressures`].
    cell_pressure_pa: Vec<f64>,
}

impl FemModel {
    /// Precomputes element data and lumped masses for `mesh` (positively oriented tets, m).
    ///
    /// # Errors
    /// [`ModelError::InvalidMesh`] for an empty mesh or a degenerate/inverted tetrahedron;
    /// [`ModelError::SceneField`] for inadmissible material parameters.
    pub fn new(mesh: &TetMesh, material: MaterialParams) -> Result<Self, ModelError> {
        Self::with_smoothing(mesh, material, StrainSmoothing::None)
    }

    /// [`Self::new`] with the strain smoothing `smoothing` (see [`StrainSmoothing`]).
    ///
    /// # Errors
    /// As [`Self::new`], and [`ModelError::SceneField`] for strain smoothing on a quadratic mesh.
    pub fn with_smoothing(
        mesh: &TetMesh,
        material: MaterialParams,
        smoothing: StrainSmoothing,
    ) -> Result<Self, ModelError> {
        material.validate()?;
        if smoothing != StrainSmoothing::None && mesh.is_quadratic() {
            return Err(ModelError::field(
                "mesh.strain_smoothing",
                "strain smoothing is for linear tetrahedra (order = 1); quadratic ones need none",
            ));
        }
        if mesh.tets.is_empty() {
            return Err(ModelError::InvalidMesh("the mesh has no tetrahedra".into()));
        }
        let n = mesh.nodes.len();
        if n > i32::MAX as usize / 3 {
            return Err(ModelError::InvalidMesh(format!("{n} nodes are too many")));
        }
        let mut dm_inv = Vec::with_capacity(mesh.tets.len());
        let mut volume_m3 = Vec::with_capacity(mesh.tets.len());
        for (k, t) in mesh.tets.iter().enumerate() {
            if t.iter().any(|&i| i as usize >= n) {
                return Err(ModelError::InvalidMesh(format!(
                    "tetrahedron {k} has an out-of-range node"
                )));
            }
            let [x0, x1, x2, x3] = t.map(|i| mesh.nodes[i as usize]);
            let dm = DMat3::from_cols(x1 - x0, x2 - x0, x3 - x0);
            let vol = dm.determinant() / 6.0;
            if !(vol > 0.0) || !vol.is_finite() {
                return Err(ModelError::InvalidMesh(format!(
                    "tetrahedron {k} {t:?} has non-positive volume {vol:.3e} m^3"
                )));
            }
            dm_inv.push(dm.inverse());
            volume_m3.push(vol);
        }
        let points = match (mesh.is_quadratic(), smoothing) {
            (true, _) => quadratic_points(mesh)?,
            (false, StrainSmoothing::None) => linear_points(&mesh.tets, &dm_inv, &volume_m3),
            (false, StrainSmoothing::Edge) => edge_smoothed_points(&mesh.tets, &dm_inv, &volume_m3),
        };
        let kernels = if mesh.is_quadratic() {
            Kernels::quadratic(&mesh.nodes, &mesh.tets, &points)
        } else if smoothing != StrainSmoothing::None {
            Kernels::domains(&mesh.nodes, &points)
        } else {
            Kernels::linear(&mesh.nodes, &mesh.tets, &dm_inv, &volume_m3)
        };
        Ok(Self {
            kernels,
            single: None,
            points,
            rest: mesh.nodes.clone(),
            tets: mesh.tets.clone(),
            dm_inv,
            volume_m3,
            lumped_mass_kg: lumped_masses(mesh, material.density_kg_per_m3),
            constraint: vec![0; n],
            material,
            quadratic: mesh.is_quadratic(),
            smoothing,
            frames: Vec::new(),
            fibres: None,
            cell_pressure_pa: Vec::new(),
        })
    }

    /// Sets the fibre field: the material frame of every integration point from `field`
    /// ([`FibreField::frame`] at the point's transmural coordinate and its gradient).
    ///
    /// # Panics
    /// If `field.transmural` does not have one value per node.
    pub fn set_fibres(&mut self, field: FibreField) {
        assert_eq!(
            field.transmural.len(),
            self.node_count(),
            "one value per node"
        );
        let mut frames = vec![DMat3::IDENTITY; self.integration_point_count()];
        let mut shape = Vec::new();
        for c in 0..self.cell_count() {
            let nodes = self.cell_nodes(c);
            let points = self.cell_points(c);
            let np = points.len();
            for (k, q) in points.enumerate() {
                fibres::point_shape_values(nodes.len(), np, k, &mut shape);
                let t: f64 = nodes
                    .iter()
                    .zip(&shape)
                    .map(|(&i, n)| field.transmural[i as usize] * n)
                    .sum();
                let grad: DVec3 = nodes
                    .iter()
                    .zip(self.ip_gradients(q))
                    .map(|(&i, g)| *g * field.transmural[i as usize])
                    .sum();
                frames[q] = field.frame(t, grad);
            }
        }
        self.frames = frames;
        self.fibres = Some(field);
    }

    /// Copies the fibre field of `other` (a model over the same nodes), recomputing the frames
    /// of this model's integration points. No-op when `other` has none.
    pub fn copy_fibres_from(&mut self, other: &FemModel) {
        if let Some(f) = &other.fibres {
            self.set_fibres(f.clone());
        }
    }

    /// The fibre field, if any.
    pub fn fibres(&self) -> Option<&FibreField> {
        self.fibres.as_ref()
    }

    /// The material frame of integration point `q` (identity without a fibre field).
    #[inline]
    pub fn ip_frame(&self, q: usize) -> DMat3 {
        self.frames.get(q).copied().unwrap_or(DMat3::IDENTITY)
    }

    /// Bytes of the model's arrays: element data, lumped masses, constraints, integration
    /// points, the force kernels' batches and cuts (both precisions), material frames and
    /// pressures (capacities; the struct itself not counted).
    pub fn heap_bytes(&self) -> usize {
        use crate::linalg::vec_bytes as b;
        b(&self.rest)
            + b(&self.tets)
            + b(&self.dm_inv)
            + b(&self.volume_m3)
            + b(&self.lumped_mass_kg)
            + b(&self.constraint)
            + self.points.heap_bytes()
            + self.kernels.heap_bytes()
            + self.single.as_ref().map_or(0, SingleLinear::heap_bytes)
            + b(&self.frames)
            + self.fibres.as_ref().map_or(0, |f| b(&f.transmural))
            + b(&self.cell_pressure_pa)
    }

    /// Number of nodes N.
    pub fn node_count(&self) -> usize {
        self.rest.len()
    }

    /// Rest positions, m. Length N.
    pub fn rest(&self) -> &[DVec3] {
        &self.rest
    }

    /// Element corner indices, positively oriented. Length E (for quadratic elements the
    /// corners only; [`Self::cell_nodes`] lists all ten nodes).
    pub fn tets(&self) -> &[[u32; 4]] {
        &self.tets
    }

    /// Inverse rest edge matrix `Dm^-1` per element (straight-sided geometry of the corners),
    /// 1/m. Row `a` is `grad N_{a+1}` of the linear element.
    pub fn dm_inv(&self) -> &[DMat3] {
        &self.dm_inv
    }

    /// Rest volume per element, m^3.
    pub fn volume_m3(&self) -> &[f64] {
        &self.volume_m3
    }

    /// Lumped nodal masses, kg (see [`lumped_masses`]). Length N.
    pub fn lumped_mass_kg(&self) -> &[f64] {
        &self.lumped_mass_kg
    }

    /// Adds `kg` to the lumped mass of every node (`kg[i]` to node `i`), for bodies whose
    /// inertia is carried by the mesh but whose mass lies partly outside it (the hybrid model's
    /// particle layer).
    ///
    /// # Panics
    /// If `kg` does not have one value per node, or a resulting mass is not finite and
    /// positive.
    pub fn add_lumped_mass(&mut self, kg: &[f64]) {
        assert_eq!(kg.len(), self.lumped_mass_kg.len(), "one mass per node");
        for (m, a) in self.lumped_mass_kg.iter_mut().zip(kg) {
            *m += a;
            assert!(m.is_finite() && *m > 0.0, "lumped mass {m} kg");
        }
    }

    /// Constrained components per node ([`CLAMPED`] for a clamped node). Length N.
    pub fn constraints(&self) -> &[ConstraintMask] {
        &self.constraint
    }

    /// The material.
    pub fn material(&self) -> &MaterialParams {
        &self.material
    }

    /// Clamps the given nodes (all components fixed at rest).
    ///
    /// # Panics
    /// If a node index is out of range.
    pub fn clamp_nodes(&mut self, nodes: &[u32]) {
        for &i in nodes {
            self.constraint[i as usize] = CLAMPED;
        }
    }

    /// Sets the constrained components of node `i` (a roller: some components fixed).
    ///
    /// # Panics
    /// If `i` is out of range.
    pub fn set_constraint(&mut self, i: usize, mask: ConstraintMask) {
        self.constraint[i] = mask & CLAMPED;
    }

    /// Copies every node's constraints from `other` (a model over the same nodes).
    ///
    /// # Panics
    /// If the node counts differ.
    pub fn copy_constraints_from(&mut self, other: &FemModel) {
        assert_eq!(self.node_count(), other.node_count(), "node counts differ");
        self.constraint.copy_from_slice(&other.constraint);
    }

    /// Total rest volume, m^3.
    pub fn total_volume_m3(&self) -> f64 {
        self.volume_m3.iter().sum()
    }

    /// Shape-function gradients `[grad N_0, .., grad N_3]` of element `e` at rest, 1/m
    /// (seed 000 eq. 13-14).
    #[inline]
    pub fn shape_gradients(&self, e: usize) -> [DVec3; 4] {
        linear_gradients(&self.dm_inv[e])
    }

    /// Deformation gradient `F = Ds Dm^-1` of element `e` for positions `x` (eq. 21).
    #[inline]
    pub fn deformation_gradient(&self, e: usize, x: &[DVec3]) -> DMat3 {
        let [a, b, c, d] = self.tets[e];
        let x0 = x[a as usize];
        DMat3::from_cols(x[b as usize] - x0, x[c as usize] - x0, x[d as usize] - x0)
            * self.dm_inv[e]
    }

    /// Adds the internal (elastic + viscous) nodal forces to `f` (N, length N): for each element
    /// `f_a += -V F (S_elastic + S_viscous) grad N_a` (seed 000 eq. 9, 11, 22; see the module note
    /// on the factor 1/2). `v` (m/s) enables the viscous stress; pass `None` for elastic only.
    ///
    /// # Panics
    /// If `x`, `v` or `f` is shorter than the node count.
    pub fn add_internal_forces(&self, x: &[DVec3], v: Option<&[DVec3]>, f: &mut [DVec3]) {
        let mat = &self.material;
        let viscous = v.filter(|_| mat.phi_pa_s > 0.0 || mat.psi_pa_s > 0.0);
        let n = self.node_count();
        assert!(x.len() >= n && f.len() >= n && viscous.is_none_or(|v| v.len() >= n));
        // The vectorised kernels cover StVK and stable Neo-Hookean.
        if !self.kernels.add_forces(mat, x, viscous, f) {
            self.generic_forces(x, viscous, f);
        }
    }

    /// Switches the internal forces of [`FemModel::add_internal_forces_with`] to the
    /// single-precision kernel (`true`) or back to double precision (`false`). The kernel
    /// covers linear St Venant-Kirchhoff tetrahedra, standard or edge-smoothed, on CPUs with
    /// AVX2 and FMA (elsewhere the double-precision kernel runs); its set-up holds 56 bytes
    /// per element (standard) or 16 bytes per node slot of a smoothing domain. See `docs/decisions.md` ("Single-precision forces") for its error.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] (`integrator.force_precision`) for another element or material.
    pub fn set_single_precision(&mut self, on: bool) -> Result<(), ModelError> {
        if !on {
            self.single = None;
            return Ok(());
        }
        if self.quadratic || SingleElastic::of(&self.material).is_none() {
            return Err(ModelError::field(
                "integrator.force_precision",
                "single precision is for linear St Venant-Kirchhoff or stable Neo-Hookean \
                 tetrahedra",
            ));
        }
        if self.single.is_none() {
            self.single = match self.smoothing {
                StrainSmoothing::None => {
                    let order =
                        kernels::locality_order(&self.rest, &self.tets, SingleLinear::LANES);
                    Some(SingleLinear::build(
                        &order,
                        &self.rest,
                        &self.tets,
                        &self.dm_inv,
                        &self.volume_m3,
                    ))
                }
                StrainSmoothing::Edge => self.kernels.single_domains(&self.rest),
            };
        }
        Ok(())
    }

    /// Pins the single-precision kernel (enabled by [`Self::set_single_precision`]) to the
    /// instruction set `isa` instead of the widest this CPU runs, for benchmarks that compare
    /// the builds on one machine.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] (`integrator.force_precision`) when single precision is
    /// off or this CPU does not run `isa` ([`SingleIsa::available`]).
    pub fn pin_single_precision_isa(&mut self, isa: SingleIsa) -> Result<(), ModelError> {
        let single = self.single.as_mut().ok_or_else(|| {
            ModelError::field("integrator.force_precision", "single precision is off")
        })?;
        single
            .pin_isa(isa)
            .map_err(|e| ModelError::field("integrator.force_precision", e))
    }

    /// Whether [`FemModel::add_internal_forces_with`] uses the single-precision kernel.
    pub fn single_precision(&self) -> bool {
        self.single.is_some()
    }

    /// [`Self::add_internal_forces`] through the single-precision kernel when it is enabled
    /// ([`Self::set_single_precision`]) and `scratch` serves this model's node count; otherwise
    /// exactly [`Self::add_internal_forces`]. Allocation-free.
    ///
    /// # Panics
    /// As [`Self::add_internal_forces`].
    pub fn add_internal_forces_with(
        &self,
        x: &[DVec3],
        v: Option<&[DVec3]>,
        f: &mut [DVec3],
        scratch: &mut ForceScratch,
    ) {
        let mat = &self.material;
        if let Some(single) = &self.single
            && scratch.node_count() >= self.node_count()
        {
            let viscous = v.filter(|_| mat.phi_pa_s > 0.0 || mat.psi_pa_s > 0.0);
            let elastic = SingleElastic::of(mat);
            if let Some(elastic) = elastic
                && single.add_forces(
                    elastic,
                    (mat.phi_pa_s, mat.psi_pa_s),
                    x,
                    viscous,
                    f,
                    scratch,
                )
            {
                return;
            }
        }
        self.add_internal_forces(x, v, f);
    }

    /// [`Self::add_internal_forces_with`] cut into parts that `pool` runs on its threads, in
    /// `k = min(pool.threads(), scratch.parts(), MAX_FORCE_PARTS)` parts, each part summing
    /// into its own arrays over the nodes it touches, the nodes several parts touch summed on
    /// the caller in part order (`docs/decisions.md`, "Element forces in parts"). With single
    /// precision enabled and `scratch` for this model's node count: the single-precision
    /// kernel's batches in `k` ranges or lane halves; `k = 1` is
    /// [`Self::add_internal_forces_with`] bit for bit. In double precision with `k = 2`, linear
    /// tetrahedra (lane halves) or smoothing domains (halves of the Morton curve) of a material
    /// with a vectorised kernel on a CPU with AVX2 and FMA: the double-precision kernel in two
    /// parts, within rounding of [`Self::add_internal_forces`] (the sums at the cut in another
    /// order). The arithmetic depends only on `k`, not on which thread ran which part.
    /// Otherwise exactly [`Self::add_internal_forces_with`] on the caller. Allocation-free.
    ///
    /// # Panics
    /// As [`Self::add_internal_forces`].
    pub fn add_internal_forces_in<R: PartRunner + ?Sized>(
        &self,
        pool: &R,
        x: &[DVec3],
        v: Option<&[DVec3]>,
        f: &mut [DVec3],
        scratch: &mut ForceScratch,
    ) {
        let run: RunParts<'_> = &|parts, g| pool.run_parts(parts, g);
        let mat = &self.material;
        let viscous = v.filter(|_| mat.phi_pa_s > 0.0 || mat.psi_pa_s > 0.0);
        if let Some(single) = &self.single
            && scratch.node_count() >= self.node_count()
            && let Some(elastic) = SingleElastic::of(mat)
        {
            let law = (mat.phi_pa_s, mat.psi_pa_s);
            let parts = (pool.threads(), run);
            if single.add_forces_parts(elastic, law, (x, viscous), f, scratch, parts) {
                return;
            }
        }
        let n = self.node_count();
        assert!(x.len() >= n && f.len() >= n && viscous.is_none_or(|v| v.len() >= n));
        if self.single.is_none()
            && self
                .kernels
                .add_forces_parts(mat, (x, viscous), f, scratch, (pool.threads(), run))
        {
            return;
        }
        self.add_internal_forces(x, v, f);
    }

    /// For an evaluation in `parts` parts ([`Self::add_internal_forces_in`], 1 to
    /// [`MAX_FORCE_PARTS`]): the nodes its elements touch and, of them, the nodes more than one
    /// part touches (summed after the parts). `None` where the evaluation is not cut
    /// (quadratic elements in double precision).
    pub fn force_part_nodes(&self, parts: usize) -> Option<(usize, usize)> {
        match &self.single {
            Some(single) => single.cut_nodes(parts),
            None => self.kernels.cut_nodes(parts),
        }
    }

    /// [`Self::add_internal_forces`] element by element (integration point by integration point
    /// for quadratic elements) with [`material::first_piola_oriented`]: the corotational and
    /// Guccione materials, and the reference the kernels are tested against.
    pub(crate) fn generic_forces(&self, x: &[DVec3], viscous: Option<&[DVec3]>, f: &mut [DVec3]) {
        let mat = &self.material;
        if mat.mean_dilatation() {
            self.mean_dilatation_forces(x, viscous, f);
            return;
        }
        if !self.is_plain_linear() {
            for q in 0..self.integration_point_count() {
                let fm = self.ip_field_gradient(q, x);
                let mut p = material::first_piola_oriented(mat, &fm, &self.ip_frame(q));
                if let Some(v) = viscous {
                    let f_dot = self.ip_field_gradient(q, v);
                    p += fm * material::viscous_stress(&fm, &f_dot, mat.phi_pa_s, mat.psi_pa_s);
                }
                self.ip_scatter(q, &(p * -self.points.weight_m3[q]), f);
            }
            return;
        }
        for (e, t) in self.tets.iter().enumerate() {
            let [a, b, c, d] = t.map(|i| i as usize);
            let dm_inv = self.dm_inv[e];
            let x0 = x[a];
            let fm = DMat3::from_cols(x[b] - x0, x[c] - x0, x[d] - x0) * dm_inv;
            let mut p = material::first_piola_oriented(mat, &fm, &self.ip_frame(e));
            if let Some(v) = viscous {
                let v0 = v[a];
                let f_dot = DMat3::from_cols(v[b] - v0, v[c] - v0, v[d] - v0) * dm_inv;
                p += fm * material::viscous_stress(&fm, &f_dot, mat.phi_pa_s, mat.psi_pa_s);
            }
            // H = -V P Dm^-T: column k is the force on node k+1.
            let h = p * dm_inv.transpose() * (-self.volume_m3[e]);
            f[b] += h.x_axis;
            f[c] += h.y_axis;
            f[d] += h.z_axis;
            f[a] -= h.x_axis + h.y_axis + h.z_axis;
        }
    }

    /// The mean dilatation of cell `c`: its deformation gradients at the integration points
    /// (at most [`MAX_CELL_POINTS`]) and `J_c = sum_q w_q det F_q / sum_q w_q`, the ratio of its
    /// deformed to its rest volume (exact for straight-sided elements).
    #[inline]
    fn cell_dilatation(&self, c: usize, x: &[DVec3]) -> ([DMat3; MAX_CELL_POINTS], f64, f64) {
        let mut fms = [DMat3::IDENTITY; MAX_CELL_POINTS];
        let (mut vol, mut def) = (0.0, 0.0);
        for (k, q) in self.cell_points(c).enumerate() {
            let fm = self.ip_field_gradient(q, x);
            let w = self.points.weight_m3[q];
            vol += w;
            def += w * fm.determinant();
            fms[k] = fm;
        }
        (fms, def / vol, vol)
    }

    /// Internal forces with the volumetric term on the element-mean dilatation
    /// ([`material::GuccioneParams::mean_dilatation`]): with `p_c = U'(J_c)`, each point adds
    /// `-w_q (P_dev(F_q) + p_c cof F_q) grad N_a`, the gradient of
    /// `sum_q w_q Psi_dev(F_q) + V_c U(J_c)`.
    fn mean_dilatation_forces(&self, x: &[DVec3], viscous: Option<&[DVec3]>, f: &mut [DVec3]) {
        let mat = &self.material;
        let g = &mat.guccione;
        for c in 0..self.cell_count() {
            let (fms, jc, _) = self.cell_dilatation(c, x);
            let pc = material::guccione::volumetric(g, jc).1 + self.cell_pressure(c);
            for (k, q) in self.cell_points(c).enumerate() {
                let fm = fms[k];
                let mut p = material::guccione::first_piola_deviatoric(g, &fm, &self.ip_frame(q))
                    + material::cofactor(&fm) * pc;
                if let Some(v) = viscous {
                    let f_dot = self.ip_field_gradient(q, v);
                    p += fm * material::viscous_stress(&fm, &f_dot, mat.phi_pa_s, mat.psi_pa_s);
                }
                self.ip_scatter(q, &(p * -self.points.weight_m3[q]), f);
            }
        }
    }

    /// Sets an augmented-Lagrangian pressure `lambda_c` (Pa) per cell for the mean-dilatation
    /// penalty ([`material::GuccioneParams::mean_dilatation`]): the cell's volumetric energy
    /// becomes `V_c (lambda_c (J_c - 1) + U(J_c))` and its pressure `lambda_c + U'(J_c)`. Updating
    /// `lambda_c += U'(J_c)` after each converged solve (Uzawa) drives every `J_c` to 1 with a
    /// moderate penalty, where a large penalty alone stalls Newton (the static solves,
    /// [`crate::statics::solve_scene_loads`]). Zero (the default) for the dynamic bodies.
    ///
    /// # Panics
    /// If `pressures_pa` is not empty and its length is not the cell count.
    pub fn set_cell_pressures(&mut self, pressures_pa: Vec<f64>) {
        assert!(pressures_pa.is_empty() || pressures_pa.len() == self.cell_count());
        self.cell_pressure_pa = pressures_pa;
    }

    /// The augmented-Lagrangian pressure of cell `c`, Pa (see [`Self::set_cell_pressures`]).
    #[inline]
    pub fn cell_pressure(&self, c: usize) -> f64 {
        self.cell_pressure_pa.get(c).copied().unwrap_or(0.0)
    }

    /// Total elastic strain energy `sum_e V_e Psi(F_e)` of the material model for positions
    /// `x`, J.
    pub fn elastic_energy(&self, x: &[DVec3]) -> f64 {
        let mat = &self.material;
        if mat.mean_dilatation() {
            let g = &mat.guccione;
            return (0..self.cell_count())
                .map(|c| {
                    let (fms, jc, vol) = self.cell_dilatation(c, x);
                    let dev: f64 = self
                        .cell_points(c)
                        .enumerate()
                        .map(|(k, q)| {
                            self.points.weight_m3[q]
                                * material::guccione::energy_density_deviatoric(
                                    g,
                                    &fms[k],
                                    &self.ip_frame(q),
                                )
                        })
                        .sum();
                    dev + vol
                        * (material::guccione::volumetric(g, jc).0
                            + self.cell_pressure(c) * (jc - 1.0))
                })
                .sum();
        }
        (0..self.integration_point_count())
            .map(|q| {
                self.points.weight_m3[q]
                    * material::energy_density_oriented(
                        mat,
                        &self.ip_field_gradient(q, x),
                        &self.ip_frame(q),
                    )
            })
            .sum()
    }

    /// Volume ratio `J_c` (deformed / rest volume) of every cell for positions `x`, appended to
    /// `out` (cleared first): the element-mean dilatation of
    /// [`material::GuccioneParams::mean_dilatation`].
    pub fn cell_volume_ratios(&self, x: &[DVec3], out: &mut Vec<f64>) {
        out.clear();
        out.extend((0..self.cell_count()).map(|c| self.cell_dilatation(c, x).1));
    }

    /// Deformed volume, m^3, for positions `x`: `sum_e V_e det F_e` over linear tetrahedra
    /// (exact; with or without strain smoothing), `sum_q w_q det F_q` over the integration points
    /// of quadratic ones (exact for straight-sided elements up to the quadrature error).
    pub fn deformed_volume_m3(&self, x: &[DVec3]) -> f64 {
        if self.quadratic {
            (0..self.integration_point_count())
                .map(|q| self.points.weight_m3[q] * self.ip_field_gradient(q, x).determinant())
                .sum()
        } else {
            (0..self.element_count())
                .map(|e| self.volume_m3[e] * self.deformation_gradient(e, x).determinant())
                .sum()
        }
    }

    /// Number of elements with `det F <= 0` (inverted or flat) at some integration point, for
    /// positions `x` (with strain smoothing: of the tetrahedra themselves, not of the smoothed
    /// gradients). Allocation-free.
    pub fn inverted_elements(&self, x: &[DVec3]) -> usize {
        if self.quadratic {
            (0..self.cell_count())
                .filter(|&c| {
                    self.cell_points(c)
                        .any(|q| !(self.ip_field_gradient(q, x).determinant() > 0.0))
                })
                .count()
        } else {
            (0..self.element_count())
                .filter(|&e| !(self.deformation_gradient(e, x).determinant() > 0.0))
                .count()
        }
    }

    /// For quadratic St. Venant-Kirchhoff elements: adds to `out` (N, length N) the element part
    /// of the backward Euler operator applied to `p`,
    /// `sum_q w_q (h2 dF S_q + F_q S_stvk(dE; lambda, mu)) grad N_a` with `dF` the gradient of
    /// `p`, `dE = sym(F_q^T dF)`, and `F_q`, `S_q` the deformation gradient and StVK stress
    /// cached per integration point (`ip_f`, `ip_s`, length [`Self::integration_point_count`]).
    /// Vectorised like the force kernel. Returns `false` (and does nothing) for linear
    /// elements, where the caller's own loop is used.
    ///
    /// # Panics
    /// If the slices are shorter than the node or integration-point count.
    pub fn quadratic_stvk_operator_action(
        &self,
        ip_f: &[DMat3],
        ip_s: &[DMat3],
        (h2, lambda, mu): (f64, f64, f64),
        p: &[DVec3],
        out: &mut [DVec3],
    ) -> bool {
        self.kernels
            .quadratic_stvk_operator_action(ip_f, ip_s, (h2, lambda, mu), p, out)
    }

    /// Whether the elements are quadratic (10-node) tetrahedra.
    #[inline]
    pub fn is_quadratic(&self) -> bool {
        self.quadratic
    }

    /// The strain smoothing of the model.
    #[inline]
    pub fn strain_smoothing(&self) -> StrainSmoothing {
        self.smoothing
    }

    /// Whether the model is plain linear tetrahedra (no smoothing): then element `e` is cell
    /// `e` with the one integration point `e`, and the per-tetrahedron arrays (`tets`,
    /// `dm_inv`, `volume_m3`) describe it completely.
    #[inline]
    pub fn is_plain_linear(&self) -> bool {
        !self.quadratic && self.smoothing == StrainSmoothing::None
    }

    /// Number of elements (tetrahedra).
    #[inline]
    pub fn element_count(&self) -> usize {
        self.tets.len()
    }

    /// Number of cells: the elements, or with strain smoothing the smoothing domains. Cells are
    /// the units of assembly ([`crate::element::tangent::cell_tangent_blocks`]).
    #[inline]
    pub fn cell_count(&self) -> usize {
        self.points.node_start.len() - 1
    }

    /// Nodes of cell `c`: for an element its 4 corners, then for a quadratic element the 6
    /// mid-edge nodes in the order of [`crate::mesh::TET_EDGES`]; for a smoothing domain the
    /// nodes of the tetrahedra around it.
    #[inline]
    pub fn cell_nodes(&self, c: usize) -> &[u32] {
        &self.points.nodes[self.points.node_start[c]..self.points.node_start[c + 1]]
    }

    /// The integration points of cell `c` (1 per linear element or smoothing domain, 4 per
    /// quadratic element).
    #[inline]
    pub fn cell_points(&self, c: usize) -> std::ops::Range<usize> {
        self.points.point_start[c]..self.points.point_start[c + 1]
    }

    /// Total number of integration points.
    #[inline]
    pub fn integration_point_count(&self) -> usize {
        self.points.weight_m3.len()
    }

    /// Nodes whose shape functions are non-zero at integration point `q` (those of its cell).
    #[inline]
    pub fn ip_nodes(&self, q: usize) -> &[u32] {
        self.cell_nodes(self.points.cell[q] as usize)
    }

    /// Rest shape-function gradients `grad N_a` at integration point `q`, 1/m, in the order
    /// of [`Self::ip_nodes`] (for a smoothing domain the smoothed gradients `G_kj`).
    #[inline]
    pub fn ip_gradients(&self, q: usize) -> &[DVec3] {
        &self.points.grad[self.points.grad_start[q]..self.points.grad_start[q + 1]]
    }

    /// Integration weight of point `q` (its share of the rest volume), m^3.
    #[inline]
    pub fn ip_weight_m3(&self, q: usize) -> f64 {
        self.points.weight_m3[q]
    }

    /// Material gradient `sum_a u_a (grad N_a)^T` of the nodal field `u` at integration point
    /// `q`: the deformation gradient `F` for positions, `dF` for increments, `dF/dt` for
    /// velocities.
    #[inline]
    pub fn ip_field_gradient(&self, q: usize, u: &[DVec3]) -> DMat3 {
        let mut m = DMat3::ZERO;
        let nodes = self.ip_nodes(q);
        // The gradients sum to zero: subtracting the first node's value changes nothing but
        // the round-off (positions far from the origin would otherwise cancel).
        let u0 = u[nodes[0] as usize];
        for (&i, g) in nodes.iter().zip(self.ip_gradients(q)).skip(1) {
            let ui = u[i as usize] - u0;
            m.x_axis += ui * g.x;
            m.y_axis += ui * g.y;
            m.z_axis += ui * g.z;
        }
        m
    }

    /// Adds `m grad N_a` to `out[a]` for every node `a` of integration point `q` (with `m =
    /// -w P` this adds the point's internal forces).
    #[inline]
    pub fn ip_scatter(&self, q: usize, m: &DMat3, out: &mut [DVec3]) {
        for (&i, g) in self.ip_nodes(q).iter().zip(self.ip_gradients(q)) {
            out[i as usize] += *m * *g;
        }
    }
}
