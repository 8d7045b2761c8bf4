//! Preprocessing of the hybrid model (seed 000 section 6): [`prepare`] builds a
//! [`HybridModel`] (immutable at run time) from a [`ShellGeometry`], the parameters and the
//! material.
//!
//! Steps, with progress reported through a callback:
//! 1. the FEM core: the inner `core_fraction` of the wall, meshed as a shell of revolution;
//! 2. the outer surface: the outer boundary of a shell mesh of the whole wall;
//! 3. the lattice: every lattice point of the wall outside the core is a *layer particle*;
//!    lattice points inside the core within two kernel supports of a layer particle are
//!    *anchors* (always tied to the core, so that layer particles next to the core have full
//!    neighbourhoods);
//! 4. ties: each particle and outer vertex to the core tetrahedron whose barycentric
//!    coordinates are "most inside" (largest minimum coordinate), found through a coarse grid
//!    of the core's tetrahedra;
//! 5. regions: each layer particle belongs to the outer vertex nearest to it in direction from
//!    the centre of mass (the seed's radial projection towards the mass centre); `RV(ps)` of a
//!    vertex is its set of particles;
//! 6. the critical time step of the particles (both variants, [`crate::meshfree`]); the core's
//!    depends on the masses the body gives it ([`super::HybridBody::new`]).
//!
//! Cost: O(lattice cells + particles x stencil); about 1 s per 100 000 particles (see
//! `docs/benchmarks.md`).

use glam::{DMat3, DVec3};

use super::{HybridParams, InactiveLayer, ShellGeometry};
use crate::ModelError;
use crate::material::{MaterialModel, MaterialParams};
use crate::mesh::generate::{truncated_ellipsoid_shell, truncated_ellipsoid_shell_quadratic};
use crate::mesh::{TET_EDGES, TetMesh};
use crate::meshfree::{Lattice, MeshfreeVariant, ParticleCloud, TermBlock, critical_time_step};

/// A particle's or vertex's tie to the core: tetrahedron and its barycentric (reference)
/// coordinates (sum 1). For a linear core they are the weights of the tetrahedron's four
/// nodes; for a quadratic one the ten quadratic shape functions are evaluated at them
/// ([`HybridModel::tie_nodes`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Tie {
    /// Core tetrahedron.
    pub tet: u32,
    /// Barycentric coordinates in it.
    pub w: [f64; 4],
}

/// Most core nodes of one tie (a quadratic tetrahedron's ten).
pub const MAX_TIE_NODES: usize = 10;

/// A tie expanded to its core nodes and their weights (`sum_k w_k x_k`; weights sum to 1);
/// entries past `len` are zero.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TieNodes {
    /// Core nodes.
    pub nodes: [u32; MAX_TIE_NODES],
    /// Their weights.
    pub w: [f64; MAX_TIE_NODES],
    /// Number of nodes: 4 or 10.
    pub len: usize,
}

impl TieNodes {
    /// `sum_k w_k x_k`. The ten-node tie of a quadratic core is unrolled and summed in two
    /// halves, `(sum_(k < 5) w_k x_k) + (sum_(k >= 5) w_k x_k)`, each in order from its
    /// first node: two chains of five dependent additions instead of one of ten (the sum's
    /// latency bounded the interpolation). Other ties: in order from `k = 0`.
    #[inline]
    pub fn interpolate(&self, x: &[DVec3]) -> DVec3 {
        let mut p = DVec3::ZERO;
        if self.len == MAX_TIE_NODES {
            let mut q = DVec3::ZERO;
            for k in 0..MAX_TIE_NODES / 2 {
                p += x[self.nodes[k] as usize] * self.w[k];
                q += x[self.nodes[k + 5] as usize] * self.w[k + 5];
            }
            return p + q;
        }
        for k in 0..self.len {
            p += x[self.nodes[k] as usize] * self.w[k];
        }
        p
    }

    /// `f[k] += w_k force` for every node `k` of the tie (N; the ten-node tie unrolled).
    #[inline]
    pub fn scatter(&self, force: DVec3, f: &mut [DVec3]) {
        if self.len == MAX_TIE_NODES {
            for k in 0..MAX_TIE_NODES {
                f[self.nodes[k] as usize] += force * self.w[k];
            }
            return;
        }
        for k in 0..self.len {
            f[self.nodes[k] as usize] += force * self.w[k];
        }
    }
}

/// The ten quadratic shape functions at barycentric coordinates `l` (corners, then the mid-edge
/// nodes in the order of [`TET_EDGES`]).
pub fn quadratic_shape(l: [f64; 4]) -> [f64; 10] {
    let mut n = [0.0; 10];
    for i in 0..4 {
        n[i] = l[i] * (2.0 * l[i] - 1.0);
    }
    for (k, [i, j]) in TET_EDGES.iter().enumerate() {
        n[4 + k] = 4.0 * l[*i] * l[*j];
    }
    n
}

/// The preprocessed hybrid model (module documentation). Particles `0..layer_count` are layer
/// particles (may be activated), the rest anchors.
#[derive(Debug, Clone)]
pub struct HybridModel {
    /// Parameters.
    pub params: HybridParams,
    /// Geometry of the wall.
    pub geometry: ShellGeometry,
    /// The FEM mesh (surfaces `INNER`, `OUTER`, `BASE` when truncated): the inner
    /// `core_fraction` of the wall, or with `inactive_layer = "elements"` the whole wall.
    pub core_mesh: TetMesh,
    /// The particles.
    pub cloud: ParticleCloud,
    /// Number of layer particles.
    pub layer_count: usize,
    /// Tie of each particle.
    pub particle_tie: Vec<Tie>,
    /// Particles whose neighbourhood is too degenerate for the corrected gradient: never
    /// activated (they follow the core).
    pub degenerate: Vec<bool>,
    /// Outer surface rest positions, m.
    pub outer_rest_m: Vec<DVec3>,
    /// Outer surface triangles (outward).
    pub outer_triangles: Vec<[u32; 3]>,
    /// Tie of each outer vertex.
    pub vertex_tie: Vec<Tie>,
    /// Nearest layer particle of each outer vertex (`u32::MAX` if none within two cells).
    pub vertex_particle: Vec<u32>,
    /// Region of vertex `v`: `region_particles[region_start[v]..region_start[v + 1]]`.
    pub region_start: Vec<u32>,
    /// Layer particles by region.
    pub region_particles: Vec<u32>,
    /// Centre of mass of the layer at rest, m.
    pub centre_m: DVec3,
    /// Particles' explicit stability limit (elastic, Gershgorin bound, unit mass scale), s.
    pub particle_dt_s: f64,
    /// Largest number of terms of one region (its particles and their tied neighbours).
    pub largest_region: usize,
}

impl HybridModel {
    /// The core nodes and weights of `tie` (module documentation of [`super`]).
    #[inline]
    pub fn tie_nodes(&self, tie: &Tie) -> TieNodes {
        let mesh = &self.core_mesh;
        let t = mesh.tets[tie.tet as usize];
        let mut out = TieNodes::default();
        if mesh.is_quadratic() {
            let e = mesh.tet_edge_nodes[tie.tet as usize];
            out.nodes[..4].copy_from_slice(&t);
            out.nodes[4..].copy_from_slice(&e);
            out.w = quadratic_shape(tie.w);
            out.len = 10;
        } else {
            out.nodes[..4].copy_from_slice(&t);
            out.w[..4].copy_from_slice(&tie.w);
            out.len = 4;
        }
        out
    }

    /// `sum_k w_k x_k` over `tie` for the core positions `x` (m).
    #[inline]
    pub fn interpolate(&self, tie: &Tie, x: &[DVec3]) -> DVec3 {
        self.tie_nodes(tie).interpolate(x)
    }

    /// Particles (layer and anchors) tied to each core tetrahedron.
    pub fn particles_per_element(&self) -> Vec<u32> {
        let mut n = vec![0u32; self.core_mesh.tets.len()];
        for t in &self.particle_tie {
            n[t.tet as usize] += 1;
        }
        n
    }

    /// The layer particles' mass carried by each core node, kg (length: core nodes; unit mass
    /// scale), for `inactive_layer = "tied"` (a core that covers the whole wall carries it as
    /// its own lumped mass): each layer particle's mass (`density spacing^3`) spread over its tie's four
    /// nodes in proportion to the tie weights (negative weights of a tie extrapolated past its
    /// tetrahedron count as zero, the rest renormalised, so every share is non-negative and
    /// the total is the layer's mass). Inactive particles follow the core, so this is where
    /// their inertia lives (seed 000 section 6: the surface follows the core where no particle
    /// is simulated).
    pub fn layer_mass_on_core_kg(&self) -> Vec<f64> {
        let mut kg = vec![0.0; self.core_mesh.nodes.len()];
        let m = self.cloud.mass_kg();
        for tie in &self.particle_tie[..self.layer_count] {
            // Barycentric weights sum to 1, so at least one is positive.
            let w = tie.w.map(|w| w.max(0.0));
            let sum: f64 = w.iter().sum();
            debug_assert!(sum > 0.0, "tie weights {:?}", tie.w);
            let t = self.core_mesh.tets[tie.tet as usize];
            for (node, w) in t.iter().zip(w) {
                kg[*node as usize] += m * w / sum;
            }
        }
        kg
    }

    /// The core nodes a scene clamps: those on the base plane of a truncated wall (the LV's
    /// base), or those below `-0.8` times the core's outer z semi-axis of a closed one (the
    /// bottom pole cap, as the `ellipsoids` scene clamps), sorted.
    pub fn clamped_core_nodes(&self) -> Vec<u32> {
        let nodes = &self.core_mesh.nodes;
        match self.geometry.z_cut_m {
            Some(z) => (0..nodes.len() as u32)
                .filter(|&i| nodes[i as usize].z >= z - 1e-9)
                .collect(),
            None => {
                let cap = -0.8 * self.geometry.axes(self.params.core_fraction).z;
                (0..nodes.len() as u32)
                    .filter(|&i| nodes[i as usize].z < cap)
                    .collect()
            }
        }
    }

    /// Each particle's contact skin `t_p` (m, [`super::proxy`]): a layer particle at most a
    /// lattice spacing `s` below the outer surface at rest stands for the material up to that
    /// surface (its depth, [`ShellGeometry::outer_depth_m`]); every other particle for half a
    /// spacing.
    pub fn contact_skin_m(&self) -> Vec<f64> {
        let s = self.cloud.lattice().spacing_m();
        self.cloud
            .rest_m()
            .iter()
            .enumerate()
            .map(|(p, &x)| {
                let d = self.geometry.outer_depth_m(x);
                // `<= s`: a lattice plane on the surface itself is outside the layer (its
                // points are not strictly inside), so the plane below it, `s` deep, is the
                // surface's (the ellipsoids' poles).
                if p < self.layer_count && (0.0..=s * (1.0 + 1e-9)).contains(&d) {
                    d
                } else {
                    0.5 * s
                }
            })
            .collect()
    }

    /// Heap memory of the preprocessed model, bytes (approximate: vectors' capacities).
    pub fn memory_bytes(&self) -> usize {
        self.cloud.memory_bytes()
            + self.particle_tie.capacity() * std::mem::size_of::<Tie>()
            + self.degenerate.capacity()
            + self.outer_rest_m.capacity() * 24
            + self.outer_triangles.capacity() * 12
            + self.vertex_tie.capacity() * std::mem::size_of::<Tie>()
            + self.vertex_particle.capacity() * 4
            + self.region_start.capacity() * 4
            + self.region_particles.capacity() * 4
            + self.core_mesh.nodes.capacity() * 24
            + self.core_mesh.tets.capacity() * 16
    }
}

/// Builds the hybrid model (module documentation). `core_target_tets`: wanted tetrahedra of
/// the core; `progress(stage, fraction)` is called at each step.
///
/// # Errors
/// [`ModelError::SceneField`] for bad parameters (the `hybrid.*` field; `hybrid.variant` for
/// the seed variant with another law than StVK), too few or too many
/// particles (`hybrid.spacing_m`), or a stencil the meshfree terms cannot hold
/// (`hybrid.smoothing_ratio`).
pub fn prepare(
    geometry: ShellGeometry,
    params: &HybridParams,
    material: &MaterialParams,
    core_target_tets: usize,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<HybridModel, ModelError> {
    params.validate()?;
    if params.meshfree.variant == MeshfreeVariant::Seed
        && material.model != MaterialModel::StVenantKirchhoff
    {
        return Err(ModelError::field(
            "hybrid.variant",
            "\"seed\" is the paper's St. Venant-Kirchhoff formulation: set material.model = \"stvk\" or use \"corrected\"",
        ));
    }
    // 1. Core: the inner part of the wall, or the whole wall when elements carry the
    // inactive layer.
    progress("core mesh", 0.0);
    let core_mesh = core_mesh(&geometry, params, core_target_tets)?;
    // 2. Outer surface.
    progress("outer surface", 0.05);
    let (outer_rest_m, outer_triangles) = outer_surface(&geometry, params);
    // 3. Lattice and particles.
    progress("lattice", 0.1);
    let (cloud, layer_count) = particle_cloud(&geometry, params, material)?;
    progress("particles", 0.3);
    // 4. Ties.
    let locator = TetLocator::new(
        &core_mesh,
        (geometry.outer_m - geometry.inner_m).max_element(),
    );
    let tie = |p: DVec3| {
        let t = locator.tie(&core_mesh.nodes, &core_mesh.tets, p);
        if core_mesh.is_quadratic() {
            curved_tie(&core_mesh, t, p)
        } else {
            t
        }
    };
    let particle_tie: Vec<Tie> = cloud.rest_m().iter().map(|&p| tie(p)).collect();
    let vertex_tie: Vec<Tie> = outer_rest_m.iter().map(|&p| tie(p)).collect();
    progress("ties", 0.55);
    // Degenerate neighbourhoods (corrected variant only).
    let mut degenerate = vec![false; cloud.len()];
    {
        let mut block = TermBlock::new(&cloud, 1);
        for (p, d) in degenerate.iter_mut().enumerate() {
            block.clear();
            *d = block.push(&cloud, p as u32).is_err();
        }
    }
    let vertex_particle = nearest_layer_particles(&cloud, layer_count, &outer_rest_m);
    // 5. Regions by direction from the centre of mass.
    progress("regions", 0.65);
    let regions = Regions::new(&cloud, layer_count, &outer_rest_m);
    // 6. Critical steps.
    progress("critical time steps", 0.75);
    // The core's step depends on the masses the body gives it (HybridBody::new).
    let particle_dt_s = critical_time_step(&cloud)?;
    progress("done", 1.0);
    Ok(HybridModel {
        params: *params,
        geometry,
        core_mesh,
        cloud,
        layer_count,
        particle_tie,
        degenerate,
        outer_rest_m,
        outer_triangles,
        vertex_tie,
        vertex_particle,
        region_start: regions.start,
        region_particles: regions.particles,
        centre_m: regions.centre_m,
        particle_dt_s,
        largest_region: regions.largest,
    })
}

/// The core's mesh (step 1 of [`prepare`]): the inner part of the wall up to the core
/// fraction, or the whole wall when elements carry the inactive layer; linear or quadratic.
fn core_mesh(
    geometry: &ShellGeometry,
    params: &HybridParams,
    core_target_tets: usize,
) -> Result<TetMesh, ModelError> {
    let core_outer = match params.inactive_layer {
        InactiveLayer::Tied => geometry.axes(params.core_fraction),
        InactiveLayer::Elements => geometry.outer_m,
    };
    let mut core_mesh = if params.core_order == 2 {
        truncated_ellipsoid_shell_quadratic(
            geometry.inner_m,
            core_outer,
            geometry.z_cut_m,
            core_target_tets,
        )
    } else {
        truncated_ellipsoid_shell(
            geometry.inner_m,
            core_outer,
            geometry.z_cut_m,
            core_target_tets,
        )
    };
    core_mesh.orient_and_check()?;
    Ok(core_mesh)
}

/// The outer surface (step 2 of [`prepare`]): its vertices' rest positions, m, and its
/// triangles over them, from a shell mesh of `surface_target_tets`.
fn outer_surface(geometry: &ShellGeometry, params: &HybridParams) -> (Vec<DVec3>, Vec<[u32; 3]>) {
    let shell = truncated_ellipsoid_shell(
        geometry.inner_m,
        geometry.outer_m,
        geometry.z_cut_m,
        params.surface_target_tets,
    );
    let outer = shell
        .surface("OUTER")
        .map(|g| g.triangles.clone())
        .unwrap_or_default();
    let mut map = vec![u32::MAX; shell.nodes.len()];
    let mut outer_rest_m = Vec::new();
    let outer_triangles: Vec<[u32; 3]> = outer
        .iter()
        .map(|t| {
            t.map(|i| {
                if map[i as usize] == u32::MAX {
                    map[i as usize] = outer_rest_m.len() as u32;
                    outer_rest_m.push(shell.nodes[i as usize]);
                }
                map[i as usize]
            })
        })
        .collect();
    (outer_rest_m, outer_triangles)
}

/// The lattice and the particle cloud (step 3 of [`prepare`]): the layer's particles first
/// (their count is returned), then the anchors in the core.
///
/// # Errors
/// [`ModelError::SceneField`] (`hybrid.spacing_m`) for a lattice above 2e9 cells or a layer of
/// fewer than 8 or more than 20 000 000 particles; the cloud's errors.
fn particle_cloud(
    geometry: &ShellGeometry,
    params: &HybridParams,
    material: &MaterialParams,
) -> Result<(ParticleCloud, usize), ModelError> {
    let f = params.core_fraction;
    let s = params.meshfree.spacing_m;
    let support = params.meshfree.support_m();
    let half = geometry.outer_m + DVec3::splat(2.0 * support);
    let lo = -half;
    let hi = DVec3::new(
        half.x,
        half.y,
        geometry.z_cut_m.map_or(half.z, |z| z + 2.0 * support),
    );
    let dims_f = ((hi - lo) / s).ceil() + DVec3::ONE;
    let dims = [dims_f.x as usize, dims_f.y as usize, dims_f.z as usize];
    let cells_total = dims[0] as f64 * dims[1] as f64 * dims[2] as f64;
    if cells_total > 2e9 {
        return Err(ModelError::field(
            "hybrid.spacing_m",
            format!("{s} m needs {cells_total:.3e} lattice cells; use a larger spacing"),
        ));
    }
    let lattice = Lattice::new(lo, s, dims, support);
    let count = dims[0] * dims[1] * dims[2];
    let mut layer_cells = Vec::new();
    for c in 0..count {
        let p = lattice.position(lattice.cell(c));
        if geometry.contains(p, f, 1.0) {
            layer_cells.push(c as u32);
        }
    }
    let layer_count = layer_cells.len();
    if layer_count < 8 {
        return Err(ModelError::field(
            "hybrid.spacing_m",
            format!("{s} m gives {layer_count} particles in the layer; use a smaller spacing"),
        ));
    }
    if layer_count > 20_000_000 {
        return Err(ModelError::field(
            "hybrid.spacing_m",
            format!("{s} m gives {layer_count} particles; at most 20 000 000"),
        ));
    }
    let anchors = anchor_cells(
        &lattice,
        geometry,
        f,
        &layer_cells,
        params.inactive_layer == InactiveLayer::Elements,
    );
    let mut cells = layer_cells;
    cells.extend_from_slice(&anchors);
    let cloud = ParticleCloud::new(lattice, cells, params.meshfree, *material)?;
    Ok((cloud, layer_count))
}

/// The anchors' lattice cells, sorted: two stencil rings into the core from the layer's
/// `layer_cells`, so that every anchor whose term reaches a layer particle has a full
/// neighbourhood; with `every_core_point` (elements carry the inactive layer) every lattice
/// point of the core: the lattice then covers every element, and an element's share replaced
/// by the block's terms is the share of its particles in the block ([`super::layer`]). Anchors
/// cost memory only: they are evaluated when next to an active particle.
fn anchor_cells(
    lattice: &Lattice,
    geometry: &ShellGeometry,
    core_fraction: f64,
    layer_cells: &[u32],
    every_core_point: bool,
) -> Vec<u32> {
    let dims = lattice.dims();
    let count = dims[0] * dims[1] * dims[2];
    let mut is_anchor = vec![false; count];
    let mut anchor_cells: Vec<u32> = Vec::new();
    for pass in 0..2 {
        let sources: Vec<u32> = if pass == 0 {
            layer_cells.to_vec()
        } else {
            anchor_cells.clone()
        };
        for &c in &sources {
            let ijk = lattice.cell(c as usize);
            for d in lattice.stencil() {
                let q = [
                    ijk[0] as i64 + d[0] as i64,
                    ijk[1] as i64 + d[1] as i64,
                    ijk[2] as i64 + d[2] as i64,
                ];
                if q.iter().zip(dims).any(|(&v, n)| v < 0 || v >= n as i64) {
                    continue;
                }
                let qi = lattice.index([q[0] as usize, q[1] as usize, q[2] as usize]);
                if is_anchor[qi] {
                    continue;
                }
                let p = lattice.position(lattice.cell(qi));
                if geometry.contains(p, 0.0, core_fraction) {
                    is_anchor[qi] = true;
                    anchor_cells.push(qi as u32);
                }
            }
        }
    }
    if every_core_point {
        for (c, anchor) in is_anchor.iter_mut().enumerate() {
            if !*anchor && geometry.contains(lattice.position(lattice.cell(c)), 0.0, core_fraction)
            {
                *anchor = true;
                anchor_cells.push(c as u32);
            }
        }
    }
    anchor_cells.sort_unstable();
    anchor_cells
}

/// Per outer vertex, the nearest layer particle (of the first `layer_count`) within two
/// lattice cells of it (`u32::MAX`: none).
fn nearest_layer_particles(
    cloud: &ParticleCloud,
    layer_count: usize,
    outer_rest_m: &[DVec3],
) -> Vec<u32> {
    outer_rest_m
        .iter()
        .map(|&v| {
            let ijk = cloud.lattice().nearest_cell(v);
            let mut best = (f64::INFINITY, u32::MAX);
            for k in -2i32..=2 {
                for j in -2i32..=2 {
                    for i in -2i32..=2 {
                        if let Some(q) = cloud.lattice().get_offset(ijk, [i, j, k])
                            && (q as usize) < layer_count
                        {
                            let d = (cloud.rest_m()[q as usize] - v).length_squared();
                            if d < best.0 {
                                best = (d, q);
                            }
                        }
                    }
                }
            }
            best.1
        })
        .collect()
}

/// The particle regions (step 5 of [`prepare`]): each layer particle belongs to the outer
/// vertex nearest in direction from the layer's centre of mass; CSR over the vertices.
struct Regions {
    centre_m: DVec3,
    start: Vec<u32>,
    particles: Vec<u32>,
    largest: usize,
}

impl Regions {
    fn new(cloud: &ParticleCloud, layer_count: usize, outer_rest_m: &[DVec3]) -> Self {
        let centre_m = cloud.rest_m()[..layer_count].iter().sum::<DVec3>() / layer_count as f64;
        let directions = DirectionGrid::new(
            &outer_rest_m
                .iter()
                .map(|&v| (v - centre_m).normalize_or_zero())
                .collect::<Vec<_>>(),
        );
        let owner: Vec<u32> = cloud.rest_m()[..layer_count]
            .iter()
            .map(|&p| directions.nearest((p - centre_m).normalize_or_zero()))
            .collect();
        let nv = outer_rest_m.len();
        let mut start = vec![0u32; nv + 1];
        for &o in &owner {
            start[o as usize + 1] += 1;
        }
        for v in 0..nv {
            start[v + 1] += start[v];
        }
        let mut fill = start.clone();
        let mut particles = vec![0u32; layer_count];
        for (p, &o) in owner.iter().enumerate() {
            particles[fill[o as usize] as usize] = p as u32;
            fill[o as usize] += 1;
        }
        let largest = (0..nv)
            .map(|v| (start[v + 1] - start[v]) as usize)
            .max()
            .unwrap_or(0);
        Self {
            centre_m,
            start,
            particles,
            largest,
        }
    }
}

/// The reference (barycentric) coordinates of `p` in the curved quadratic tetrahedron of `t`
/// (whose straight tetrahedron's coordinates `t.w` start the iteration): Newton on
/// `sum_k N_k(l) X_k = p`, a few iterations (the elements are nearly straight). Falls back to
/// `t` when it does not converge.
fn curved_tie(mesh: &TetMesh, t: Tie, p: DVec3) -> Tie {
    let corners = mesh.tets[t.tet as usize];
    let mids = mesh.tet_edge_nodes[t.tet as usize];
    let node = |k: usize| {
        if k < 4 {
            mesh.nodes[corners[k] as usize]
        } else {
            mesh.nodes[mids[k - 4] as usize]
        }
    };
    let map = |l: [f64; 4]| -> DVec3 {
        let n = quadratic_shape(l);
        (0..10).map(|k| node(k) * n[k]).sum()
    };
    // dx/d(l_1, l_2, l_3) with l_0 = 1 - l_1 - l_2 - l_3.
    let jacobian = |l: [f64; 4]| -> DMat3 {
        let mut cols = [DVec3::ZERO; 3];
        // dN/dl_i of each shape function, then the chain rule through l_0.
        let mut dn = [[0.0; 4]; 10];
        for i in 0..4 {
            dn[i][i] = 4.0 * l[i] - 1.0;
        }
        for (k, [i, j]) in TET_EDGES.iter().enumerate() {
            dn[4 + k][*i] = 4.0 * l[*j];
            dn[4 + k][*j] = 4.0 * l[*i];
        }
        for (c, col) in cols.iter_mut().enumerate() {
            for (k, d) in dn.iter().enumerate() {
                *col += node(k) * (d[c + 1] - d[0]);
            }
        }
        DMat3::from_cols(cols[0], cols[1], cols[2])
    };
    let mut l = t.w;
    let scale = (node(1) - node(0)).length();
    for _ in 0..20 {
        let r = p - map(l);
        if r.length() < 1e-12 * scale {
            return Tie { tet: t.tet, w: l };
        }
        let d = jacobian(l).inverse() * r;
        if !d.is_finite() {
            break;
        }
        l = [l[0] - d.x - d.y - d.z, l[1] + d.x, l[2] + d.y, l[3] + d.z];
    }
    if (p - map(l)).length() < 1e-9 * scale {
        Tie { tet: t.tet, w: l }
    } else {
        t
    }
}

/// Barycentric weights of `p` in the tetrahedron `t` (rest positions `x`).
pub fn barycentric(x: &[DVec3], t: [u32; 4], p: DVec3) -> [f64; 4] {
    let a = x[t[0] as usize];
    let m = DMat3::from_cols(
        x[t[1] as usize] - a,
        x[t[2] as usize] - a,
        x[t[3] as usize] - a,
    );
    let b = m.inverse() * (p - a);
    [1.0 - b.x - b.y - b.z, b.x, b.y, b.z]
}

/// A coarse uniform grid over the core's tetrahedra (each listed in the cells its bounding box,
/// grown by `reach`, overlaps), for ties.
struct TetLocator {
    origin: DVec3,
    cell: f64,
    dims: [usize; 3],
    start: Vec<u32>,
    tets: Vec<u32>,
}

impl TetLocator {
    fn new(mesh: &TetMesh, reach: f64) -> Self {
        let (lo, hi) = mesh.bounding_box();
        let lo = lo - DVec3::splat(reach);
        let hi = hi + DVec3::splat(reach);
        let mean_edge = (mesh.volume() / mesh.tets.len().max(1) as f64).cbrt() * 1.5;
        let cell = mean_edge.max((hi - lo).max_element() / 64.0);
        let d = ((hi - lo) / cell).ceil();
        let dims = [d.x as usize + 1, d.y as usize + 1, d.z as usize + 1];
        let n = dims[0] * dims[1] * dims[2];
        let range = |t: &[u32; 4]| {
            let mut a = DVec3::splat(f64::INFINITY);
            let mut b = DVec3::splat(f64::NEG_INFINITY);
            for &i in t {
                a = a.min(mesh.nodes[i as usize]);
                b = b.max(mesh.nodes[i as usize]);
            }
            let a = ((a - DVec3::splat(reach) - lo) / cell)
                .floor()
                .max(DVec3::ZERO);
            let b = ((b + DVec3::splat(reach) - lo) / cell).floor();
            (a, b)
        };
        let mut counts = vec![0u32; n + 1];
        let pass = |fill: &mut dyn FnMut(usize, u32)| {
            for (e, t) in mesh.tets.iter().enumerate() {
                let (a, b) = range(t);
                for k in a.z as usize..=(b.z as usize).min(dims[2] - 1) {
                    for j in a.y as usize..=(b.y as usize).min(dims[1] - 1) {
                        for i in a.x as usize..=(b.x as usize).min(dims[0] - 1) {
                            fill(i + dims[0] * (j + dims[1] * k), e as u32);
                        }
                    }
                }
            }
        };
        pass(&mut |c, _| counts[c + 1] += 1);
        for c in 0..n {
            counts[c + 1] += counts[c];
        }
        let mut tets = vec![0u32; counts[n] as usize];
        let mut next = counts.clone();
        pass(&mut |c, e| {
            tets[next[c] as usize] = e;
            next[c] += 1;
        });
        Self {
            origin: lo,
            cell,
            dims,
            start: counts,
            tets,
        }
    }

    /// The tie of `p`: the tetrahedron with the largest minimum barycentric coordinate among
    /// those listed in `p`'s cell (all tetrahedra if the cell is empty).
    fn tie(&self, x: &[DVec3], tets: &[[u32; 4]], p: DVec3) -> Tie {
        let q = ((p - self.origin) / self.cell).floor();
        let c = |v: f64, n: usize| (v.max(0.0) as usize).min(n - 1);
        let ci = c(q.x, self.dims[0])
            + self.dims[0] * (c(q.y, self.dims[1]) + self.dims[1] * c(q.z, self.dims[2]));
        let list = &self.tets[self.start[ci] as usize..self.start[ci + 1] as usize];
        let mut best = Tie::default();
        let mut best_min = f64::NEG_INFINITY;
        let mut consider = |e: u32| {
            let w = barycentric(x, tets[e as usize], p);
            let m = w.iter().fold(f64::INFINITY, |a, &b| a.min(b));
            if m > best_min {
                best_min = m;
                best = Tie { tet: e, w };
            }
        };
        if list.is_empty() {
            (0..tets.len() as u32).for_each(&mut consider);
        } else {
            list.iter().copied().for_each(&mut consider);
        }
        best
    }
}

/// Unit directions bucketed in a 3D grid over `[-1, 1]^3`, for nearest-direction queries.
struct DirectionGrid {
    dirs: Vec<DVec3>,
    n: usize,
    start: Vec<u32>,
    items: Vec<u32>,
}

impl DirectionGrid {
    fn new(dirs: &[DVec3]) -> Self {
        let n = 24;
        let cell_of = |d: DVec3| {
            let q = ((d + DVec3::ONE) * 0.5 * n as f64).floor();
            let c = |v: f64| (v.max(0.0) as usize).min(n - 1);
            c(q.x) + n * (c(q.y) + n * c(q.z))
        };
        let mut start = vec![0u32; n * n * n + 1];
        for &d in dirs {
            start[cell_of(d) + 1] += 1;
        }
        for c in 0..n * n * n {
            start[c + 1] += start[c];
        }
        let mut next = start.clone();
        let mut items = vec![0u32; dirs.len()];
        for (i, &d) in dirs.iter().enumerate() {
            let c = cell_of(d);
            items[next[c] as usize] = i as u32;
            next[c] += 1;
        }
        Self {
            dirs: dirs.to_vec(),
            n,
            start,
            items,
        }
    }

    /// Index of the direction nearest to `d` (shell search outwards from `d`'s cell).
    fn nearest(&self, d: DVec3) -> u32 {
        let n = self.n as i64;
        let q = ((d + DVec3::ONE) * 0.5 * self.n as f64).floor();
        let c0 = [q.x as i64, q.y as i64, q.z as i64].map(|v| v.clamp(0, n - 1));
        let width = 2.0 / self.n as f64;
        let mut best = (f64::INFINITY, 0u32);
        for r in 0..n {
            for k in (c0[2] - r).max(0)..=(c0[2] + r).min(n - 1) {
                for j in (c0[1] - r).max(0)..=(c0[1] + r).min(n - 1) {
                    for i in (c0[0] - r).max(0)..=(c0[0] + r).min(n - 1) {
                        let on_shell = (i - c0[0]).abs() == r
                            || (j - c0[1]).abs() == r
                            || (k - c0[2]).abs() == r;
                        if !on_shell {
                            continue;
                        }
                        let c = (i + n * (j + n * k)) as usize;
                        for &it in &self.items[self.start[c] as usize..self.start[c + 1] as usize] {
                            let e = (self.dirs[it as usize] - d).length_squared();
                            if e < best.0 {
                                best = (e, it);
                            }
                        }
                    }
                }
            }
            // Every point of a cell at shell distance r + 1 is farther than r cell widths.
            if best.0.is_finite() && best.0.sqrt() <= r as f64 * width {
                break;
            }
        }
        best.1
    }
}
