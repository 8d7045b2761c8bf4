//! Linear tetrahedral finite elements (seed 000 section 3.1) with St. Venant-Kirchhoff and
//! viscous stress (section 2).
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
//! by the HRZ rule (Hinton, Rock & Zienkiewicz 1976): `rho V / 36` per corner and `4 rho V /
//! 27` per mid-edge node (the row sums of the consistent T10 mass are negative at the
//! corners).
//!
//! **Strain smoothing.** Linear tetrahedra can instead carry the edge-based smoothed
//! deformation gradient of ES-FEM-T4 ([`StrainSmoothing::Edge`]): one integration point per mesh
//! edge whose gradients are the volume-weighted average of the surrounding elements'. Points
//! are grouped in *cells* (an element, or a smoothing domain with its own node list), so every
//! generic path and the static solver work on either.
//!
//! Neighbours: [`crate::material`] (stress laws), [`crate::integrator`] (uses forces, masses and
//! the per-node rest Jacobian), [`crate::statics`] (uses [`FemModel::stiffness_action`]).

use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::material::{self, MaterialModel, MaterialParams};
use crate::mesh::TetMesh;
use crate::simd::{Lane, Lanes8, Plain8};
#[cfg(target_arch = "x86_64")]
use crate::simd::{Ymm2, Zmm};

/// Bit mask of constrained displacement components of a node: bit 0 = x, 1 = y, 2 = z.
pub type ConstraintMask = u8;
/// All three components fixed (a clamped node).
pub const CLAMPED: ConstraintMask = 0b111;

/// Precomputed rest-state data of a tetrahedral FEM body. Immutable after construction.
#[derive(Debug, Clone)]
pub struct FemModel {
    /// Rest positions, m. Length N.
    pub rest: Vec<DVec3>,
    /// Element node indices, positively oriented. Length E.
    pub tets: Vec<[u32; 4]>,
    /// Inverse rest edge matrix per element, 1/m. Row `a` is `grad N_{a+1}`.
    pub dm_inv: Vec<DMat3>,
    /// Rest volume per element, m^3.
    pub volume_m3: Vec<f64>,
    /// Lumped nodal masses `m_i = sum_e rho V_e / 4`, kg. Length N.
    pub lumped_mass_kg: Vec<f64>,
    /// Constrained components per node ([`CLAMPED`] for a clamped node). Length N.
    pub constraint: Vec<ConstraintMask>,
    /// Material.
    pub material: MaterialParams,
    /// The element data of `tets`, `dm_inv` and `volume_m3` again, in batches of [`LANES`]
    /// elements laid out lane-innermost, for the vectorised StVK force kernel (linear elements
    /// only).
    batches: Vec<ElementBatch>,
    /// Integration points of every element, for the generic (quadratic) paths.
    points: IntegrationPoints,
    /// Quadratic elements in batches of [`LANES`], for the vectorised StVK kernel (empty for
    /// linear elements).
    quad_batches: Vec<QuadraticBatch>,
    /// The element order of the batches (lane `l` of batch `b` is element
    /// `quad_order[b * LANES + l]`).
    quad_order: Vec<u32>,
    /// The smoothing domains in batches of [`LANES`], for the vectorised kernel (empty without
    /// strain smoothing).
    domain_batches: DomainBatches,
    /// Whether the elements are 10-node tetrahedra.
    quadratic: bool,
    /// Strain smoothing of linear elements.
    smoothing: StrainSmoothing,
}

/// Integration-point data in flat arrays, grouped in *cells*: a cell is an element (linear or
/// quadratic) or, with strain smoothing, a smoothing domain. Cell `c` has the nodes
/// `nodes[node_start[c]..node_start[c + 1]]` and the integration points
/// `q = point_start[c]..point_start[c + 1]`; point `q` has the rest shape-function gradients
/// `grad[grad_start[q]..grad_start[q + 1]]` (1/m, one per node of its cell, in the cell's node
/// order) and the weight `weight_m3[q]` (m^3; the weights sum to the body's volume).
#[derive(Debug, Clone, Default)]
struct IntegrationPoints {
    node_start: Vec<usize>,
    nodes: Vec<u32>,
    point_start: Vec<usize>,
    /// The cell of each point.
    cell: Vec<u32>,
    grad_start: Vec<usize>,
    grad: Vec<DVec3>,
    weight_m3: Vec<f64>,
}

impl IntegrationPoints {
    fn new() -> Self {
        Self {
            node_start: vec![0],
            point_start: vec![0],
            grad_start: vec![0],
            ..Self::default()
        }
    }

    /// Appends a cell with `nodes` and its points `(gradients in node order, weight)`.
    fn push_cell<'a>(
        &mut self,
        nodes: &[u32],
        points: impl IntoIterator<Item = (&'a [DVec3], f64)>,
    ) {
        let c = self.node_start.len() as u32 - 1;
        self.nodes.extend_from_slice(nodes);
        self.node_start.push(self.nodes.len());
        for (g, w) in points {
            debug_assert_eq!(g.len(), nodes.len());
            self.grad.extend_from_slice(g);
            self.grad_start.push(self.grad.len());
            self.weight_m3.push(w);
            self.cell.push(c);
        }
        self.point_start.push(self.weight_m3.len());
    }
}

/// Strain smoothing of linear tetrahedra (element technology), chosen per scene with
/// `[mesh] strain_smoothing`.
///
/// - [`StrainSmoothing::None`]: standard FEM, one deformation gradient per tetrahedron.
/// - [`StrainSmoothing::Edge`]: the edge-based smoothed FEM, ES-FEM-T4 (G. R. Liu and
///   T. Nguyen-Thoi, *Smoothed Finite Element Methods*, CRC Press 2010; Zeng & Liu,
///   Arch. Comput. Methods Eng. 25 (2018) 397). Each mesh edge `k` owns the smoothing domain
///   made of one sixth of every tetrahedron around it, of volume `V_k = sum_e V_e / 6`, and
///   carries the volume-averaged deformation gradient
///   `F_k = (1 / V_k) sum_e (V_e / 6) F_e = sum_j x_j (G_kj)^T`,
///   `G_kj = (1 / V_k) sum_{e ∋ k, j} (V_e / 6) grad N_j^e`. The energy is
///   `sum_k V_k Psi(F_k)`; forces, stiffness and viscous stress follow from `F_k` exactly as from
///   an integration point with weight `V_k` and gradients `G_kj` (its nodes: those of the
///   tetrahedra around the edge, 4 to 11, 6.6 on average on `lv_h1`). Linear tetrahedra are
///   overly stiff in bending and shear; the smoothed strain softens them while keeping the
///   linear patch test exact (a linear field has the same `F` in every element, so its average
///   too), and unlike the node-based variant it has no spurious low-energy modes. On
///   `lv_h1.msh` the small-strain probe compliance moves from 15 % below the quadratic
///   solution on the same mesh to 3 % below (README, "Strain smoothing"). Linear meshes only;
///   masses stay lumped per element.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum StrainSmoothing {
    /// Standard FEM.
    #[default]
    None,
    /// Edge-based smoothed FEM (ES-FEM-T4).
    Edge,
}

impl StrainSmoothing {
    /// Parses the scene name: `"none"` or `"edge"`.
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "none" => Some(Self::None),
            "edge" => Some(Self::Edge),
            _ => None,
        }
    }

    /// The scene name.
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Edge => "edge",
        }
    }
}

/// The integration points of linear tetrahedra: one per element (`grad N_0 = -(g1 + g2 + g3)`,
/// weight the volume).
fn linear_points(tets: &[[u32; 4]], dm_inv: &[DMat3], volume_m3: &[f64]) -> IntegrationPoints {
    let mut p = IntegrationPoints::new();
    for ((t, m), &v) in tets.iter().zip(dm_inv).zip(volume_m3) {
        p.push_cell(t, [(linear_gradients(m).as_slice(), v)]);
    }
    p
}

/// The four shape-function gradients of a linear tetrahedron from its `Dm^-1` (rows 1..3).
fn linear_gradients(dm_inv: &DMat3) -> [DVec3; 4] {
    let (g1, g2, g3) = (dm_inv.row(0), dm_inv.row(1), dm_inv.row(2));
    [-(g1 + g2 + g3), g1, g2, g3]
}

/// The smoothing domains of the edge-based smoothed FEM ([`StrainSmoothing::Edge`]) of linear
/// tetrahedra: one cell with one point per mesh edge.
fn edge_smoothed_points(
    tets: &[[u32; 4]],
    dm_inv: &[DMat3],
    volume_m3: &[f64],
) -> IntegrationPoints {
    // Edge id of every (tet, local edge), in order of first appearance.
    let mut ids = std::collections::HashMap::with_capacity(tets.len() * 2);
    let mut edge_of = Vec::with_capacity(6 * tets.len());
    for t in tets {
        for [a, b] in crate::mesh::TET_EDGES {
            let key = (t[a].min(t[b]), t[a].max(t[b]));
            let next = ids.len();
            edge_of.push(*ids.entry(key).or_insert(next));
        }
    }
    let edges = ids.len();
    // Tetrahedra around each edge (CSR).
    let mut start = vec![0usize; edges + 1];
    for &k in &edge_of {
        start[k + 1] += 1;
    }
    for k in 0..edges {
        start[k + 1] += start[k];
    }
    let mut fill = start.clone();
    let mut around = vec![0u32; edge_of.len()];
    for (i, &k) in edge_of.iter().enumerate() {
        around[fill[k]] = (i / 6) as u32;
        fill[k] += 1;
    }
    let mut p = IntegrationPoints::new();
    let (mut nodes, mut grads) = (Vec::<u32>::new(), Vec::<DVec3>::new());
    for k in 0..edges {
        nodes.clear();
        grads.clear();
        let ring = &around[start[k]..start[k + 1]];
        let vk: f64 = ring.iter().map(|&e| volume_m3[e as usize] / 6.0).sum();
        for &e in ring {
            let e = e as usize;
            let w = volume_m3[e] / 6.0 / vk;
            for (&i, g) in tets[e].iter().zip(linear_gradients(&dm_inv[e])) {
                match nodes.iter().position(|&j| j == i) {
                    Some(a) => grads[a] += g * w,
                    None => {
                        nodes.push(i);
                        grads.push(g * w);
                    }
                }
            }
        }
        p.push_cell(&nodes, [(grads.as_slice(), vk)]);
    }
    p
}

/// Barycentric coordinates of the points of the 4-point degree-2 Gauss rule on a tetrahedron.
const GAUSS4_A: f64 = 0.585_410_196_624_968_5;
const GAUSS4_B: f64 = 0.138_196_601_125_010_5;

/// Derivatives of the 10 quadratic shape functions with respect to the reference coordinates
/// `(xi_1, xi_2, xi_3) = (L_1, L_2, L_3)` at barycentric point `l` (node order: corners, then
/// the mid-edge nodes of [`crate::mesh::TET_EDGES`]).
fn quadratic_reference_gradients(l: [f64; 4]) -> [DVec3; 10] {
    let dl = [DVec3::splat(-1.0), DVec3::X, DVec3::Y, DVec3::Z];
    let mut g = [DVec3::ZERO; 10];
    for i in 0..4 {
        g[i] = dl[i] * (4.0 * l[i] - 1.0);
    }
    for (k, [i, j]) in crate::mesh::TET_EDGES.iter().enumerate() {
        g[4 + k] = (dl[*j] * l[*i] + dl[*i] * l[*j]) * 4.0;
    }
    g
}

/// Elements per batch of the force kernel: 8 f64 lanes fill an AVX-512 register (two AVX2
/// registers).
const LANES: usize = 8;

/// `a . b` of two 3-vectors with [`Lane::madd`] (fused multiply-adds when `FMA`; Rust never
/// contracts `a * b + c` by itself, and fusing cut the kernels' instruction count by a third).
#[inline(always)]
fn dot3<const FMA: bool, T: Lane>(a: [T; 3], b: [T; 3]) -> T {
    T::madd::<FMA>(a[2], b[2], T::madd::<FMA>(a[1], b[1], a[0] * b[0]))
}

/// Column `j` of a row-major 3x3 matrix.
#[inline(always)]
fn column<T: Copy>(m: &[T; 9], j: usize) -> [T; 3] {
    [m[j], m[3 + j], m[6 + j]]
}

/// `a x b` with [`Lane::msub`].
#[inline(always)]
fn cross3<const FMA: bool, T: Lane>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [
        T::msub::<FMA>(a[1], b[2], a[2] * b[1]),
        T::msub::<FMA>(a[2], b[0], a[0] * b[2]),
        T::msub::<FMA>(a[0], b[1], a[1] * b[0]),
    ]
}

/// [`LANES`] elements, structure-of-arrays: `dm_inv[3 r + c][lane]` is entry (r, c) of
/// `Dm^-1`. Padding lanes (at the end of the mesh) repeat node 0 with zero `Dm^-1` and volume,
/// so they add exactly zero force.
#[derive(Debug, Clone)]
struct ElementBatch {
    nodes: [[u32; 4]; LANES],
    /// `3 * nodes[l][k]` at `node3[k][l]`: f64 offsets of the node coordinates, for gathers.
    node3: [[i32; LANES]; 4],
    dm_inv: [[f64; LANES]; 9],
    volume_m3: [f64; LANES],
}

/// Element order for the force kernel: by the Morton (Z-order) code of the centroid, so that
/// consecutive elements touch nearby, mostly cache-resident nodes. Ties keep the mesh order.
fn locality_order(nodes: &[DVec3], tets: &[[u32; 4]]) -> Vec<u32> {
    let centroid = |t: &[u32; 4]| t.iter().map(|&i| nodes[i as usize]).sum::<DVec3>() * 0.25;
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for t in tets {
        let c = centroid(t);
        lo = lo.min(c);
        hi = hi.max(c);
    }
    let scale = (hi - lo).max_element();
    let scale = if scale > 0.0 { 1023.0 / scale } else { 0.0 };
    // Spreads the 10 low bits of `v` to every third bit.
    let spread = |v: u64| {
        let mut x = v & 0x3ff;
        x = (x | (x << 16)) & 0x0300_00ff;
        x = (x | (x << 8)) & 0x0300_f00f;
        x = (x | (x << 4)) & 0x030c_30c3;
        (x | (x << 2)) & 0x0924_9249
    };
    let mut keyed: Vec<(u64, u32)> = tets
        .iter()
        .enumerate()
        .map(|(e, t)| {
            let q = ((centroid(t) - lo) * scale).round();
            let code = spread(q.x as u64) | (spread(q.y as u64) << 1) | (spread(q.z as u64) << 2);
            (code, e as u32)
        })
        .collect();
    keyed.sort_unstable();
    // Interleave LANES runs of the curve, so that the lanes of a batch lie far apart and
    // rarely share a node (a shared node serialises the scatter of the forces).
    let n = keyed.len();
    let run = n.div_ceil(LANES);
    (0..run)
        .flat_map(|k| (0..LANES).map(move |l| l * run + k))
        .filter(|&i| i < n)
        .map(|i| keyed[i].1)
        .collect()
}

impl ElementBatch {
    /// Batches of the elements in the given `order` (a permutation of the element indices).
    fn build(order: &[u32], tets: &[[u32; 4]], dm_inv: &[DMat3], volume_m3: &[f64]) -> Vec<Self> {
        order
            .chunks(LANES)
            .map(|chunk| {
                let mut b = Self {
                    nodes: [[0; 4]; LANES],
                    node3: [[0; LANES]; 4],
                    dm_inv: [[0.0; LANES]; 9],
                    volume_m3: [0.0; LANES],
                };
                for (l, &e) in chunk.iter().enumerate() {
                    let e = e as usize;
                    b.nodes[l] = tets[e];
                    for (row, &node) in b.node3.iter_mut().zip(&tets[e]) {
                        row[l] = 3 * node as i32;
                    }
                    let m = dm_inv[e];
                    for r in 0..3 {
                        for c in 0..3 {
                            b.dm_inv[3 * r + c][l] = m.col(c)[r];
                        }
                    }
                    b.volume_m3[l] = volume_m3[e];
                }
                b
            })
            .collect()
    }
}

/// Material models with a vectorised lane kernel, the `MODEL` parameter of the batch kernels.
const LANE_STVK: u8 = 0;
/// See [`LANE_STVK`].
const LANE_STABLE_NEO_HOOKEAN: u8 = 1;

/// The `MODEL` of the lane kernels for `model`, or `None` (corotational: scalar path).
fn lane_model(model: MaterialModel) -> Option<u8> {
    match model {
        MaterialModel::StVenantKirchhoff => Some(LANE_STVK),
        MaterialModel::StableNeoHookean => Some(LANE_STABLE_NEO_HOOKEAN),
        MaterialModel::Corotational => None,
    }
}

/// First Piola-Kirchhoff stress `P = P_elastic + F S_viscous` of one lane, row-major
/// (`fm[3 i + j] = F_ij`, `fd` = `dF/dt` likewise, or `None` without viscosity), Pa. Elastic
/// part by `MODEL`: StVK `F S` with `C = F^T F`, `S = mu (C - I) + lambda/2 (tr C - 3) I`
/// (seed 000 eq. 9); stable Neo-Hookean `mu F + lambda_s (J - alpha) cof F` (see
/// [`MaterialModel::StableNeoHookean`]). Viscous `S_v = 2 psi nu + phi tr(nu) I`,
/// `nu = F^T Fdot + Fdot^T F` (eq. 10-11). The same formulas as [`material::first_piola`] and
/// [`material::viscous_stress`], generic over the lane type `T` (one `f64` or a [`Lanes8`]).
#[inline(always)]
fn first_piola_lane<const FMA: bool, const MODEL: u8, T: Lane>(
    fm: &[T; 9],
    fd: Option<&[T; 9]>,
    mat: &MaterialParams,
) -> [T; 9] {
    let (lambda, mu) = (mat.lambda_pa, mat.mu_pa);
    let (phi, psi) = (mat.phi_pa_s, mat.psi_pa_s);
    // No closures here: they are not inlined into the `target_feature` kernels.
    let dot = dot3::<FMA, T>;
    let (c0, c1, c2) = (column(fm, 0), column(fm, 1), column(fm, 2));
    let zero = T::splat(0.0);
    let mu_v = T::splat(mu);
    // s: the symmetric stress multiplied by F from the left (StVK: S_elastic + S_v; stable
    // Neo-Hookean: S_v only).
    let mut s = [zero; 9];
    if MODEL == LANE_STVK {
        // C = F^T F (symmetric), S = mu (C - I) + lambda/2 (tr C - 3) I.
        let (c00, c11, c22) = (dot(c0, c0), dot(c1, c1), dot(c2, c2));
        let (c01, c02, c12) = (dot(c0, c1), dot(c0, c2), dot(c1, c2));
        let diag = T::splat(0.5 * lambda) * (c00 + c11 + c22 - T::splat(3.0)) - mu_v;
        s = [
            T::madd::<FMA>(mu_v, c00, diag),
            mu_v * c01,
            mu_v * c02,
            mu_v * c01,
            T::madd::<FMA>(mu_v, c11, diag),
            mu_v * c12,
            mu_v * c02,
            mu_v * c12,
            T::madd::<FMA>(mu_v, c22, diag),
        ];
    }
    if let Some(fd) = fd {
        // A = F^T Fdot, nu = A + A^T, S_v = 2 psi nu + phi tr(nu) I (eq. 10-11).
        let (d0, d1, d2) = (column(fd, 0), column(fd, 1), column(fd, 2));
        let two = T::splat(2.0);
        let n00 = two * dot(c0, d0);
        let n11 = two * dot(c1, d1);
        let n22 = two * dot(c2, d2);
        let n01 = dot(c0, d1) + dot(c1, d0);
        let n02 = dot(c0, d2) + dot(c2, d0);
        let n12 = dot(c1, d2) + dot(c2, d1);
        let vd = T::splat(phi) * (n00 + n11 + n22);
        let p2 = T::splat(2.0 * psi);
        s[0] = s[0] + (T::madd::<FMA>(p2, n00, vd));
        s[4] = s[4] + (T::madd::<FMA>(p2, n11, vd));
        s[8] = s[8] + (T::madd::<FMA>(p2, n22, vd));
        s[1] = s[1] + p2 * n01;
        s[3] = s[3] + p2 * n01;
        s[2] = s[2] + p2 * n02;
        s[6] = s[6] + p2 * n02;
        s[5] = s[5] + p2 * n12;
        s[7] = s[7] + p2 * n12;
    }
    let mut p = [zero; 9];
    if MODEL == LANE_STVK || fd.is_some() {
        for i in 0..3 {
            for j in 0..3 {
                p[3 * i + j] = dot(
                    [fm[3 * i], fm[3 * i + 1], fm[3 * i + 2]],
                    [s[j], s[3 + j], s[6 + j]],
                );
            }
        }
    }
    if MODEL == LANE_STABLE_NEO_HOOKEAN {
        // cof F: columns c1 x c2, c2 x c0, c0 x c1 (= J F^-T); J = c0 . (c1 x c2).
        let cross = cross3::<FMA, T>;
        let cof = [cross(c1, c2), cross(c2, c0), cross(c0, c1)];
        let j = dot(c0, cof[0]);
        let (ls, alpha) = material::neo_hookean_params(lambda, mu);
        let k = T::splat(ls) * (j - T::splat(alpha));
        for i in 0..3 {
            for jj in 0..3 {
                p[3 * i + jj] =
                    p[3 * i + jj] + T::madd::<FMA>(mu_v, fm[3 * i + jj], k * cof[jj][i]);
            }
        }
    }
    p
}

/// Whether this CPU runs the AVX-512 kernels (AVX-512F + VL, AVX2, FMA); cached by std.
#[cfg(target_arch = "x86_64")]
fn has_avx512() -> bool {
    std::is_x86_feature_detected!("avx512f")
        && std::is_x86_feature_detected!("avx512vl")
        && has_avx2_fma()
}

/// Whether this CPU runs the AVX2 + FMA kernels; cached by std.
#[cfg(target_arch = "x86_64")]
fn has_avx2_fma() -> bool {
    std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
}

/// StVK or stable Neo-Hookean (+ viscous) nodal forces of every batch of linear elements,
/// added to `f` (see [`FemModel::add_internal_forces`]), with every batch quantity held in
/// lane type `V` (one lane per element): gathers of the edge vectors, `F = Ds Dm^-1` (seed 000
/// eq. 21), the stress by [`first_piola_lane`] and `H = -V P Dm^-T` (eq. 22) without leaving
/// registers, then [`scatter_linear`].
///
/// # Safety
/// The CPU must support the instructions of `V` (enabled in the caller); every node index of
/// `batches` must be below `x.len()` and `v.len()`.
#[inline(always)]
unsafe fn forces_linear<const FMA: bool, const MODEL: u8, V: Lanes8>(
    batches: &[ElementBatch],
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    let zero = V::splat(0.0);
    for batch in batches {
        let mut bm = [zero; 9];
        for (b, row) in bm.iter_mut().zip(&batch.dm_inv) {
            *b = V::load(row);
        }
        // SAFETY: node indices are below x.len() (caller's contract).
        let fm =
            edge_gradient::<FMA, V>(&unsafe { gather_differences::<V, 9>(&batch.node3, x) }, &bm);
        // No closure (`v.map`): closures are not inlined into `target_feature` functions.
        #[allow(clippy::manual_map)]
        let fd = match v {
            // SAFETY: node indices are below v.len() (caller's contract).
            Some(v) => Some(edge_gradient::<FMA, V>(
                &unsafe { gather_differences::<V, 9>(&batch.node3, v) },
                &bm,
            )),
            None => None,
        };
        let p = first_piola_lane::<FMA, MODEL, V>(&fm, fd.as_ref(), mat);
        let w = zero - V::load(&batch.volume_m3);
        // h[3 k + i][l]: component i of the force on node k+1 of lane l.
        let mut h = [[0.0; LANES]; 9];
        for k in 0..3 {
            for i in 0..3 {
                let hk = w * dot3::<FMA, V>(
                    [p[3 * i], p[3 * i + 1], p[3 * i + 2]],
                    [bm[3 * k], bm[3 * k + 1], bm[3 * k + 2]],
                );
                hk.store(&mut h[3 * k + i]);
            }
        }
        scatter_linear(batch, &h, f);
    }
}

/// Adds the nodal forces of a batch to `f`: `h[3 k + i][l]` is component i of the force on
/// node k+1 of lane l; node 0 gets minus their sum. Scalar, since lanes may share nodes.
#[inline(always)]
fn scatter_linear(batch: &ElementBatch, h: &[[f64; LANES]; 9], f: &mut [DVec3]) {
    for (l, t) in batch.nodes.iter().enumerate() {
        let [a, b, c, d] = t.map(|i| i as usize);
        let hk = |k: usize| DVec3::new(h[3 * k][l], h[3 * k + 1][l], h[3 * k + 2][l]);
        let (h1, h2, h3) = (hk(0), hk(1), hk(2));
        f[b] += h1;
        f[c] += h2;
        f[d] += h3;
        f[a] -= h1 + h2 + h3;
    }
}

/// Differences `y_a - y_0` (a = 1..N/3) of the nodes of a batch whose gather offsets are
/// `node3` (row a: `3 *` node a of each lane), `y` positions or velocities: `out[3 (a - 1) + c]`
/// holds component c, one lane per element. For a linear batch (N = 9) these are the edge
/// vectors `Ds`; for a quadratic one (N = 27) the differences to the first corner.
///
/// # Safety
/// As [`forces_linear`]: `V`'s instructions enabled, node indices below `y.len()`.
#[inline(always)]
unsafe fn gather_differences<V: Lanes8, const N: usize>(
    node3: &[[i32; LANES]],
    y: &[DVec3],
) -> [V; N] {
    debug_assert_eq!(node3.len(), N / 3 + 1);
    // DVec3 is three packed f64 (repr(C)), so component c of node n is at 3 n + c.
    let base = y.as_ptr().cast::<f64>();
    let mut out = [V::splat(0.0); N];
    for c in 0..3 {
        // SAFETY: node3 holds 3 * (node index), so offset + c addresses a component of a node
        // below y.len() (caller's contract).
        unsafe {
            let p = base.add(c);
            let y0 = V::gather(p, &node3[0]);
            for a in 1..=N / 3 {
                out[3 * (a - 1) + c] = V::gather(p, &node3[a]) - y0;
            }
        }
    }
    out
}

/// `F = Ds Dm^-1`: `d` from [`gather_differences`], `bm[3 r + c]` entry (r, c) of `Dm^-1`;
/// `F_ij = sum_k d[3 k + i] bm[3 k + j]`, row-major (seed 000 eq. 21).
#[inline(always)]
fn edge_gradient<const FMA: bool, V: Lanes8>(d: &[V; 9], bm: &[V; 9]) -> [V; 9] {
    let mut out = [V::splat(0.0); 9];
    for i in 0..3 {
        for j in 0..3 {
            out[3 * i + j] =
                dot3::<FMA, V>([d[i], d[3 + i], d[6 + i]], [bm[j], bm[3 + j], bm[6 + j]]);
        }
    }
    out
}

/// [`LANES`] quadratic elements, structure-of-arrays, for the vectorised StVK kernel of
/// 10-node tetrahedra: `grad[q][3 (a - 1) + c][l]` is component c of `grad N_a` (a = 1..9;
/// `grad N_0` is minus their sum and is not needed, since forces use differences to node 0)
/// at integration point q of lane l, `weight_m3[q][l]` its weight. Padding lanes repeat node
/// 0 with zero gradients and weights.
#[derive(Debug, Clone)]
struct QuadraticBatch {
    nodes: [[u32; 10]; LANES],
    /// `3 * nodes[l][a]` at `node3[a][l]`: f64 offsets of the node coordinates, for gathers.
    node3: [[i32; LANES]; 10],
    grad: [[[f64; LANES]; 27]; 4],
    weight_m3: [[f64; LANES]; 4],
}

impl QuadraticBatch {
    fn build(order: &[u32], points: &IntegrationPoints) -> Vec<Self> {
        order
            .chunks(LANES)
            .map(|chunk| {
                let mut b = Self {
                    nodes: [[0; 10]; LANES],
                    node3: [[0; LANES]; 10],
                    grad: [[[0.0; LANES]; 27]; 4],
                    weight_m3: [[0.0; LANES]; 4],
                };
                for (l, &e) in chunk.iter().enumerate() {
                    let e = e as usize;
                    b.nodes[l].copy_from_slice(&points.nodes[10 * e..10 * e + 10]);
                    debug_assert_eq!(points.node_start[e], 10 * e);
                    for (row, &node) in b.node3.iter_mut().zip(&b.nodes[l]) {
                        row[l] = 3 * node as i32;
                    }
                    for q in 0..4 {
                        let ip = 4 * e + q;
                        b.weight_m3[q][l] = points.weight_m3[ip];
                        for a in 1..10 {
                            let g = points.grad[points.grad_start[ip] + a];
                            for c in 0..3 {
                                b.grad[q][3 * (a - 1) + c][l] = g[c];
                            }
                        }
                    }
                }
                b
            })
            .collect()
    }
}

/// StVK or stable Neo-Hookean (+ viscous) nodal forces of quadratic elements, added to `f`
/// (see [`FemModel::add_internal_forces`]), every batch quantity held in lane type `V` (one
/// lane per element): gathers of `x_a - x_0` (a = 1..9), then per integration point
/// `F = sum_a (x_a - x_0) (grad N_a)^T`, the stress by [`first_piola_lane`] and
/// `h_a -= w P grad N_a`, then [`scatter_quadratic`] (`f_0 -= sum_a h_a`).
///
/// # Safety
/// As [`forces_linear`].
#[inline(always)]
unsafe fn forces_quadratic<const FMA: bool, const MODEL: u8, V: Lanes8>(
    batches: &[QuadraticBatch],
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    let zero = V::splat(0.0);
    for batch in batches {
        // SAFETY: node indices are below x.len() and v.len() (caller's contract).
        let d = unsafe { gather_differences::<V, 27>(&batch.node3, x) };
        // No closure (`v.map`): closures are not inlined into `target_feature` functions.
        #[allow(clippy::manual_map)]
        let dv = match v {
            // SAFETY: as above.
            Some(v) => Some(unsafe { gather_differences::<V, 27>(&batch.node3, v) }),
            None => None,
        };
        let mut h = [zero; 27];
        for q in 0..4 {
            let g = &batch.grad[q];
            let fm = quadratic_gradient::<FMA, V>(&d, g);
            #[allow(clippy::manual_map)]
            let fd = match &dv {
                Some(dv) => Some(quadratic_gradient::<FMA, V>(dv, g)),
                None => None,
            };
            let p = first_piola_lane::<FMA, MODEL, V>(&fm, fd.as_ref(), mat);
            let w = zero - V::load(&batch.weight_m3[q]);
            let mut m = [zero; 9];
            for (mk, pk) in m.iter_mut().zip(p) {
                *mk = w * pk;
            }
            add_divergence::<FMA, V>(&m, g, &mut h);
        }
        store_scatter_quadratic(batch, &h, f);
    }
}

/// `h_a += M grad N_a` (a = 1..9), `M` row-major (already scaled by the integration weight),
/// `g` a batch's gradients at one integration point: the scatter-side counterpart of
/// [`quadratic_gradient`].
#[inline(always)]
fn add_divergence<const FMA: bool, V: Lanes8>(m: &[V; 9], g: &[[f64; LANES]; 27], h: &mut [V; 27]) {
    for a in 0..9 {
        let ga = [
            V::load(&g[3 * a]),
            V::load(&g[3 * a + 1]),
            V::load(&g[3 * a + 2]),
        ];
        for i in 0..3 {
            let acc = V::madd::<FMA>(m[3 * i], ga[0], h[3 * a + i]);
            let acc = V::madd::<FMA>(m[3 * i + 1], ga[1], acc);
            h[3 * a + i] = V::madd::<FMA>(m[3 * i + 2], ga[2], acc);
        }
    }
}

/// [`scatter_quadratic`] of per-node vectors held in lanes (`h[3 (a - 1) + c]`).
#[inline(always)]
fn store_scatter_quadratic<V: Lanes8>(batch: &QuadraticBatch, h: &[V; 27], out: &mut [DVec3]) {
    let mut hs = [[0.0; LANES]; 27];
    for (row, hk) in hs.iter_mut().zip(h) {
        hk.store(row);
    }
    scatter_quadratic(batch, &hs, out);
}

/// Adds the per-node vectors `h` of a quadratic batch (`h[3 (a - 1) + c][l]`: component c for lane l) to
/// `out`: `out[n_a] += h_a` for a = 1..9 and `out[n_0] -= sum_a h_a`. Padding lanes carry
/// zeros (zero gradients and weights), so adding them changes nothing.
#[inline(always)]
fn scatter_quadratic(batch: &QuadraticBatch, h: &[[f64; LANES]; 27], out: &mut [DVec3]) {
    for (l, t) in batch.nodes.iter().enumerate() {
        let mut sum = DVec3::ZERO;
        for a in 1..10 {
            let ha = DVec3::new(
                h[3 * (a - 1)][l],
                h[3 * (a - 1) + 1][l],
                h[3 * (a - 1) + 2][l],
            );
            out[t[a] as usize] += ha;
            sum += ha;
        }
        out[t[0] as usize] -= sum;
    }
}

/// `F = sum_a d_a (grad N_a)^T`, row-major: `d` from [`gather_differences`], `g` a batch's
/// gradients at one integration point.
#[inline(always)]
fn quadratic_gradient<const FMA: bool, V: Lanes8>(d: &[V; 27], g: &[[f64; LANES]; 27]) -> [V; 9] {
    let mut out = [V::splat(0.0); 9];
    for a in 0..9 {
        let ga = [
            V::load(&g[3 * a]),
            V::load(&g[3 * a + 1]),
            V::load(&g[3 * a + 2]),
        ];
        for i in 0..3 {
            for j in 0..3 {
                out[3 * i + j] = V::madd::<FMA>(d[3 * a + i], ga[j], out[3 * i + j]);
            }
        }
    }
    out
}

/// Single-point cells with a variable number of nodes (the smoothing domains of
/// [`StrainSmoothing::Edge`]) in batches of [`LANES`], for the vectorised force kernel. Batch
/// `b` has node slots `start[b]..start[b + 1]`; slot `s` holds, per lane, the node
/// (`nodes[s]`, and `3 *` it in `node3[s]`) and its smoothed gradient (`grad[s][c]`,
/// component c). Cells are sorted by node count so a batch pads few slots; a padding slot
/// repeats the lane's first node with a zero gradient, a padding lane has weight zero.
#[derive(Debug, Clone, Default)]
struct DomainBatches {
    start: Vec<usize>,
    nodes: Vec<[u32; LANES]>,
    node3: Vec<[i32; LANES]>,
    grad: Vec<[[f64; LANES]; 3]>,
    weight_m3: Vec<[f64; LANES]>,
}

impl DomainBatches {
    fn build(points: &IntegrationPoints) -> Self {
        let cells = points.node_start.len() - 1;
        debug_assert_eq!(points.weight_m3.len(), cells, "one point per cell");
        let count = |c: usize| points.node_start[c + 1] - points.node_start[c];
        let mut order: Vec<usize> = (0..cells).collect();
        order.sort_by_key(|&c| count(c));
        let mut out = Self {
            start: vec![0],
            ..Self::default()
        };
        for chunk in order.chunks(LANES) {
            let slots = chunk.iter().map(|&c| count(c)).max().unwrap_or(0);
            let first = out.nodes.len();
            out.nodes.resize(first + slots, [0; LANES]);
            out.node3.resize(first + slots, [0; LANES]);
            out.grad.resize(first + slots, [[0.0; LANES]; 3]);
            let mut w = [0.0; LANES];
            for (l, &c) in chunk.iter().enumerate() {
                let nodes = &points.nodes[points.node_start[c]..points.node_start[c + 1]];
                let grads = &points.grad[points.grad_start[c]..points.grad_start[c + 1]];
                w[l] = points.weight_m3[c];
                // Padding slots: the lane's first node with a zero gradient.
                let padded = nodes
                    .iter()
                    .copied()
                    .zip(grads.iter().copied())
                    .chain(std::iter::repeat((nodes[0], DVec3::ZERO)));
                for (s, (node, g)) in padded.take(slots).enumerate() {
                    out.nodes[first + s][l] = node;
                    out.node3[first + s][l] = 3 * node as i32;
                    for c in 0..3 {
                        out.grad[first + s][c][l] = g[c];
                    }
                }
            }
            out.weight_m3.push(w);
            out.start.push(out.nodes.len());
        }
        out
    }
}

/// Internal forces of single-point cells with variable node counts ([`DomainBatches`]):
/// `F = sum_s (y_s - y_0) G_s^T` (positions, and velocities for the viscous stress) streamed
/// slot by slot, the stress of material `MODEL`, then `f_s -= w P G_s` scattered per lane.
///
/// # Safety
/// As [`forces_linear`].
#[inline(always)]
unsafe fn forces_domains<const FMA: bool, const MODEL: u8, V: Lanes8>(
    d: &DomainBatches,
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    let zero = V::splat(0.0);
    for (b, w) in d.weight_m3.iter().enumerate() {
        let (node3, grad) = (
            &d.node3[d.start[b]..d.start[b + 1]],
            &d.grad[d.start[b]..d.start[b + 1]],
        );
        // SAFETY (both): node indices are below x.len() and v.len() (caller's contract).
        let fm = unsafe { domain_gradient::<FMA, V>(node3, grad, x) };
        #[allow(clippy::manual_map)]
        let fd = match v {
            Some(v) => Some(unsafe { domain_gradient::<FMA, V>(node3, grad, v) }),
            None => None,
        };
        let p = first_piola_lane::<FMA, MODEL, V>(&fm, fd.as_ref(), mat);
        let wn = zero - V::load(w);
        let mut m = [zero; 9];
        for (mk, pk) in m.iter_mut().zip(p) {
            *mk = wn * pk;
        }
        for (s, g) in grad.iter().enumerate() {
            let g = [V::load(&g[0]), V::load(&g[1]), V::load(&g[2])];
            let mut h = [[0.0; LANES]; 3];
            for (i, hi) in h.iter_mut().enumerate() {
                let acc = V::madd::<FMA>(m[3 * i + 1], g[1], m[3 * i] * g[0]);
                V::madd::<FMA>(m[3 * i + 2], g[2], acc).store(hi);
            }
            for (l, &node) in d.nodes[d.start[b] + s].iter().enumerate() {
                f[node as usize] += DVec3::new(h[0][l], h[1][l], h[2][l]);
            }
        }
    }
}

/// `sum_s (y_s - y_0) G_s^T` (row-major) of one batch of [`DomainBatches`].
///
/// # Safety
/// As [`gather_differences`].
#[inline(always)]
unsafe fn domain_gradient<const FMA: bool, V: Lanes8>(
    node3: &[[i32; LANES]],
    grad: &[[[f64; LANES]; 3]],
    y: &[DVec3],
) -> [V; 9] {
    let base = y.as_ptr().cast::<f64>();
    let mut out = [V::splat(0.0); 9];
    // SAFETY: as in `gather_differences`.
    let y0 = unsafe {
        [
            V::gather(base, &node3[0]),
            V::gather(base.add(1), &node3[0]),
            V::gather(base.add(2), &node3[0]),
        ]
    };
    for (n3, g) in node3.iter().zip(grad).skip(1) {
        let g = [V::load(&g[0]), V::load(&g[1]), V::load(&g[2])];
        for i in 0..3 {
            // SAFETY: as above.
            let di = unsafe { V::gather(base.add(i), n3) } - y0[i];
            for j in 0..3 {
                out[3 * i + j] = V::madd::<FMA>(di, g[j], out[3 * i + j]);
            }
        }
    }
    out
}

/// The force kernel of `fem`'s element order with lane type `V`.
///
/// # Safety
/// As [`forces_linear`].
#[inline(always)]
unsafe fn forces_with<const FMA: bool, const MODEL: u8, V: Lanes8>(
    fem: &FemModel,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    let mat = &fem.material;
    // SAFETY: the caller's contract.
    unsafe {
        if fem.is_quadratic() {
            forces_quadratic::<FMA, MODEL, V>(&fem.quad_batches, mat, x, v, f);
        } else if fem.smoothing != StrainSmoothing::None {
            forces_domains::<FMA, MODEL, V>(&fem.domain_batches, mat, x, v, f);
        } else {
            forces_linear::<FMA, MODEL, V>(&fem.batches, mat, x, v, f);
        }
    }
}

/// [`forces_with`] in AVX-512 registers ([`Zmm`]).
///
/// # Safety
/// The CPU must support AVX-512F, AVX-512VL, AVX2 and FMA; node indices as [`forces_linear`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
unsafe fn forces_avx512<const MODEL: u8>(
    fem: &FemModel,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    // SAFETY: the caller's contract; AVX-512 is enabled here.
    unsafe { forces_with::<true, MODEL, Zmm>(fem, x, v, f) }
}

/// [`forces_with`] in pairs of AVX2 registers ([`Ymm2`]).
///
/// # Safety
/// The CPU must support AVX2 and FMA; node indices as [`forces_linear`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn forces_avx2<const MODEL: u8>(
    fem: &FemModel,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    // SAFETY: the caller's contract; AVX2 and FMA are enabled here.
    unsafe { forces_with::<true, MODEL, Ymm2>(fem, x, v, f) }
}

/// [`forces_with`] in plain code ([`Plain8`], unfused multiply-adds).
///
/// # Safety
/// Node indices as [`forces_linear`].
unsafe fn forces_plain<const MODEL: u8>(
    fem: &FemModel,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    // SAFETY: the caller's contract; Plain8 needs no CPU feature.
    unsafe { forces_with::<false, MODEL, Plain8>(fem, x, v, f) }
}

/// Action of the backward Euler operator's element part on `p` for quadratic StVK elements,
/// added to `out` (see [`FemModel::quadratic_stvk_operator_action`]), every batch quantity in
/// lane type `V`: per integration point `dF = sum_a p_a (grad N_a)^T`,
/// `w (h2 dF S + F S_stvk(sym(F^T dF); lam, mu)) grad N_a` with the cached `F` and `S`.
///
/// # Safety
/// As [`forces_linear`] (node indices below `p.len()`).
#[inline(always)]
unsafe fn stvk_operator_quadratic<const FMA: bool, V: Lanes8>(
    batches: &[QuadraticBatch],
    order: &[u32],
    ip_f: &[DMat3],
    ip_s: &[DMat3],
    (h2, lam, mu): (f64, f64, f64),
    p: &[DVec3],
    out: &mut [DVec3],
) {
    let zero = V::splat(0.0);
    let (h2, lam, mu2, half) = (
        V::splat(h2),
        V::splat(lam),
        V::splat(2.0 * mu),
        V::splat(0.5),
    );
    for (b, batch) in batches.iter().enumerate() {
        // SAFETY: node indices are below p.len() (caller's contract).
        let dp = unsafe { gather_differences::<V, 27>(&batch.node3, p) };
        let elements = &order[b * LANES..((b + 1) * LANES).min(order.len())];
        let mut h = [zero; 27];
        for q in 0..4 {
            let g = &batch.grad[q];
            let df = quadratic_gradient::<FMA, V>(&dp, g);
            // Cached F and S of each lane's integration point, lane-innermost, row-major.
            let mut fl = [[0.0; LANES]; 9];
            let mut sl = [[0.0; LANES]; 9];
            for (l, &e) in elements.iter().enumerate() {
                let ip = 4 * e as usize + q;
                let (f, s) = (ip_f[ip], ip_s[ip]);
                for i in 0..3 {
                    for j in 0..3 {
                        fl[3 * i + j][l] = f.col(j)[i];
                        sl[3 * i + j][l] = s.col(j)[i];
                    }
                }
            }
            let (mut f, mut s) = ([zero; 9], [zero; 9]);
            for k in 0..9 {
                f[k] = V::load(&fl[k]);
                s[k] = V::load(&sl[k]);
            }
            // dE = sym(F^T dF), dS = 2 mu dE + lam tr(dE) I.
            let mut de = [zero; 9];
            for i in 0..3 {
                for j in 0..3 {
                    let a =
                        dot3::<FMA, V>([f[i], f[3 + i], f[6 + i]], [df[j], df[3 + j], df[6 + j]]);
                    let b =
                        dot3::<FMA, V>([f[j], f[3 + j], f[6 + j]], [df[i], df[3 + i], df[6 + i]]);
                    de[3 * i + j] = half * (a + b);
                }
            }
            let tr = de[0] + de[4] + de[8];
            let mut ds = [zero; 9];
            for (d, e) in ds.iter_mut().zip(de) {
                *d = mu2 * e;
            }
            for k in [0, 4, 8] {
                ds[k] = V::madd::<FMA>(lam, tr, ds[k]);
            }
            let w = V::load(&batch.weight_m3[q]);
            let mut pk = [zero; 9];
            for i in 0..3 {
                for j in 0..3 {
                    let geo = dot3::<FMA, V>(
                        [df[3 * i], df[3 * i + 1], df[3 * i + 2]],
                        [s[j], s[3 + j], s[6 + j]],
                    );
                    let mat = dot3::<FMA, V>(
                        [f[3 * i], f[3 * i + 1], f[3 * i + 2]],
                        [ds[j], ds[3 + j], ds[6 + j]],
                    );
                    pk[3 * i + j] = w * V::madd::<FMA>(h2, geo, mat);
                }
            }
            add_divergence::<FMA, V>(&pk, g, &mut h);
        }
        store_scatter_quadratic(batch, &h, out);
    }
}

/// [`stvk_operator_quadratic`] in AVX-512 registers.
///
/// # Safety
/// The CPU must support AVX-512F, AVX-512VL, AVX2 and FMA; node indices below `p.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
unsafe fn stvk_operator_quadratic_avx512(
    batches: &[QuadraticBatch],
    order: &[u32],
    ip_f: &[DMat3],
    ip_s: &[DMat3],
    c: (f64, f64, f64),
    p: &[DVec3],
    out: &mut [DVec3],
) {
    // SAFETY: the caller's contract; AVX-512 is enabled here.
    unsafe { stvk_operator_quadratic::<true, Zmm>(batches, order, ip_f, ip_s, c, p, out) }
}

/// [`stvk_operator_quadratic`] in pairs of AVX2 registers.
///
/// # Safety
/// The CPU must support AVX2 and FMA; node indices below `p.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn stvk_operator_quadratic_avx2(
    batches: &[QuadraticBatch],
    order: &[u32],
    ip_f: &[DMat3],
    ip_s: &[DMat3],
    c: (f64, f64, f64),
    p: &[DVec3],
    out: &mut [DVec3],
) {
    // SAFETY: the caller's contract; AVX2 and FMA are enabled here.
    unsafe { stvk_operator_quadratic::<true, Ymm2>(batches, order, ip_f, ip_s, c, p, out) }
}

/// Lumped nodal masses, kg, one per node of `mesh` (m) with density `density_kg_per_m3`:
/// `m_i = sum_e rho |V_e| / 4` for linear elements; for quadratic ones the HRZ lumping
/// `rho |V_e| / 36` per corner and `4 rho |V_e| / 27` per mid-edge node (module docs).
/// [`FemModel::new`] stores the same values in `lumped_mass_kg`.
pub fn lumped_masses(mesh: &TetMesh, density_kg_per_m3: f64) -> Vec<f64> {
    let mut m = vec![0.0; mesh.nodes.len()];
    let (corner, edge) = if mesh.is_quadratic() {
        (1.0 / 36.0, 4.0 / 27.0)
    } else {
        (0.25, 0.0)
    };
    for (e, t) in mesh.tets.iter().enumerate() {
        let [a, b, c, d] = t.map(|i| mesh.nodes[i as usize]);
        let mass = density_kg_per_m3 * crate::mesh::tet_signed_volume(a, b, c, d).abs();
        for &i in t {
            m[i as usize] += mass * corner;
        }
        if let Some(mid) = mesh.tet_edge_nodes.get(e) {
            for &i in mid {
                m[i as usize] += mass * edge;
            }
        }
    }
    m
}

/// Integration points of the quadratic elements of `mesh` (module docs), with the isoparametric
/// map of the rest positions (so curved elements are handled).
fn quadratic_points(mesh: &TetMesh) -> Result<IntegrationPoints, ModelError> {
    let n = mesh.nodes.len();
    let e_count = mesh.tets.len();
    if mesh.tet_edge_nodes.len() != e_count {
        return Err(ModelError::InvalidMesh(format!(
            "{} rows of mid-edge nodes for {e_count} tetrahedra",
            mesh.tet_edge_nodes.len()
        )));
    }
    let mut p = IntegrationPoints::new();
    let mut grads = [[DVec3::ZERO; 10]; 4];
    let mut weights = [0.0; 4];
    for (k, (t, mid)) in mesh.tets.iter().zip(&mesh.tet_edge_nodes).enumerate() {
        let en: Vec<u32> = t.iter().chain(mid).copied().collect();
        if let Some(bad) = en.iter().find(|&&i| i as usize >= n) {
            return Err(ModelError::InvalidMesh(format!(
                "quadratic tetrahedron {k} has an out-of-range node {bad}"
            )));
        }
        for q in 0..4 {
            let mut l = [GAUSS4_B; 4];
            l[q] = GAUSS4_A;
            let dn = quadratic_reference_gradients(l);
            // J = dX/dxi = sum_a X_a (dN_a/dxi)^T
            let jac = en.iter().zip(&dn).fold(DMat3::ZERO, |acc, (&i, g)| {
                let x = mesh.nodes[i as usize];
                acc + DMat3::from_cols(x * g.x, x * g.y, x * g.z)
            });
            let det = jac.determinant();
            if !(det > 0.0) || !det.is_finite() {
                return Err(ModelError::InvalidMesh(format!(
                    "quadratic tetrahedron {k} has a non-positive Jacobian {det:.3e} at \
                     integration point {q}"
                )));
            }
            let jit = jac.inverse().transpose();
            grads[q] = dn.map(|g| jit * g);
            weights[q] = det / 24.0;
        }
        p.push_cell(&en, grads.iter().map(|g| g.as_slice()).zip(weights));
    }
    Ok(p)
}

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
        let domain_batches = if smoothing == StrainSmoothing::None {
            DomainBatches::default()
        } else {
            DomainBatches::build(&points)
        };
        let order = locality_order(&mesh.nodes, &mesh.tets);
        let (batches, quad_batches) = if mesh.is_quadratic() {
            (Vec::new(), QuadraticBatch::build(&order, &points))
        } else if smoothing != StrainSmoothing::None {
            (Vec::new(), Vec::new())
        } else {
            (
                ElementBatch::build(&order, &mesh.tets, &dm_inv, &volume_m3),
                Vec::new(),
            )
        };
        Ok(Self {
            batches,
            quad_batches,
            quad_order: if mesh.is_quadratic() {
                order
            } else {
                Vec::new()
            },
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
            domain_batches,
        })
    }

    /// Number of nodes N.
    pub fn node_count(&self) -> usize {
        self.rest.len()
    }

    /// Clamps the given nodes (all components fixed at rest).
    pub fn clamp_nodes(&mut self, nodes: &[u32]) {
        for &i in nodes {
            self.constraint[i as usize] = CLAMPED;
        }
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
        // Also the safety precondition of the gathers of the vectorised kernels: every node
        // index is below n (checked in `new`).
        assert!(x.len() >= n && f.len() >= n && viscous.is_none_or(|v| v.len() >= n));
        match lane_model(mat.model) {
            Some(LANE_STVK) => self.lane_forces::<LANE_STVK>(x, viscous, f),
            Some(LANE_STABLE_NEO_HOOKEAN) => {
                self.lane_forces::<LANE_STABLE_NEO_HOOKEAN>(x, viscous, f);
            }
            _ => self.generic_forces(x, viscous, f),
        }
    }

    /// [`Self::add_internal_forces`] by the vectorised batch kernels of material `MODEL`
    /// (linear or quadratic elements), the instruction set chosen at run time.
    fn lane_forces<const MODEL: u8>(&self, x: &[DVec3], v: Option<&[DVec3]>, f: &mut [DVec3]) {
        // SAFETY (all three): node indices are below n (checked in `new`), and x, v are at
        // least n long (asserted by the caller); each instruction set was detected on this
        // CPU just before its kernel.
        #[cfg(target_arch = "x86_64")]
        if has_avx512() {
            unsafe { forces_avx512::<MODEL>(self, x, v, f) };
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            unsafe { forces_avx2::<MODEL>(self, x, v, f) };
            return;
        }
        unsafe { forces_plain::<MODEL>(self, x, v, f) };
    }

    /// [`Self::add_internal_forces`] element by element (integration point by integration point
    /// for quadratic elements) with [`material::first_piola`]: the corotational material.
    fn generic_forces(&self, x: &[DVec3], viscous: Option<&[DVec3]>, f: &mut [DVec3]) {
        let mat = &self.material;
        if !self.is_plain_linear() {
            for q in 0..self.integration_point_count() {
                let fm = self.ip_field_gradient(q, x);
                let mut p = material::first_piola(mat, &fm);
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
            let mut p = material::first_piola(mat, &fm);
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

    /// Total elastic strain energy `sum_e V_e Psi(F_e)` of the material model for positions
    /// `x`, J.
    pub fn elastic_energy(&self, x: &[DVec3]) -> f64 {
        let mat = &self.material;
        (0..self.integration_point_count())
            .map(|q| {
                self.points.weight_m3[q]
                    * material::energy_density(mat, &self.ip_field_gradient(q, x))
            })
            .sum()
    }

    /// Adds the action of the elastic tangent stiffness `K(x) = -d f_elastic / d x` on the
    /// displacement increment `dx` to `out` (N/m times m = N; all length N):
    /// `dF = dDs Dm^-1`, `dP` from [`material::first_piola_differential`] (for StVK
    /// `dE = sym(F^T dF)`, `dS = lambda tr(dE) I + 2 mu dE`, `dP = dF S + F dS`),
    /// `out_a += V dP grad N_a`. At rest this is the linear-elastic stiffness for every material.
    pub fn stiffness_action(&self, x: &[DVec3], dx: &[DVec3], out: &mut [DVec3]) {
        let mat = &self.material;
        if !self.is_plain_linear() {
            for q in 0..self.integration_point_count() {
                let fm = self.ip_field_gradient(q, x);
                let dfm = self.ip_field_gradient(q, dx);
                let dp = material::first_piola_differential(mat, &fm, &dfm);
                self.ip_scatter(q, &(dp * self.points.weight_m3[q]), out);
            }
            return;
        }
        for (e, t) in self.tets.iter().enumerate() {
            let [a, b, c, d] = t.map(|i| i as usize);
            let dm_inv = self.dm_inv[e];
            let x0 = x[a];
            let fm = DMat3::from_cols(x[b] - x0, x[c] - x0, x[d] - x0) * dm_inv;
            let d0 = dx[a];
            let dfm = DMat3::from_cols(dx[b] - d0, dx[c] - d0, dx[d] - d0) * dm_inv;
            let dp = material::first_piola_differential(mat, &fm, &dfm);
            let h = dp * dm_inv.transpose() * self.volume_m3[e];
            out[b] += h.x_axis;
            out[c] += h.y_axis;
            out[d] += h.z_axis;
            out[a] -= h.x_axis + h.y_axis + h.z_axis;
        }
    }

    /// The 3x3 diagonal blocks `K_ii` of the linear-elastic stiffness at rest, N/m (one per
    /// node): `K_ii = sum_e V_e ((lambda + mu) g g^T + mu |g|^2 I)` with `g = grad N_i` in `e`.
    /// The same for every [`material::MaterialModel`]: all linearise at rest to this.
    /// The seed's per-node Jacobian of eq. 34 is `J_i = -K_ii` ("precomputed at rest assuming
    /// that its neighbours are fixed").
    pub fn rest_diagonal_blocks(&self) -> Vec<DMat3> {
        let mat = &self.material;
        self.isotropic_diagonal_blocks(mat.lambda_pa, mat.mu_pa)
    }

    /// The 3x3 diagonal blocks of the isotropic operator with Lamé-like coefficients
    /// `(lambda, mu)` at rest: `sum_q w_q ((lambda + mu) g g^T + mu |g|^2 I)`, `g = grad N_i` at
    /// integration point `q` (units of `lambda` times m). [`Self::rest_diagonal_blocks`] is
    /// this with the material's Lamé parameters; with `(2 phi, 2 psi)` it is the viscous one.
    pub fn isotropic_diagonal_blocks(&self, lambda: f64, mu: f64) -> Vec<DMat3> {
        let mut k = vec![DMat3::ZERO; self.node_count()];
        for q in 0..self.integration_point_count() {
            let w = self.points.weight_m3[q];
            for (&i, &ga) in self.ip_nodes(q).iter().zip(self.ip_gradients(q)) {
                let outer = DMat3::from_cols(ga * ga.x, ga * ga.y, ga * ga.z);
                k[i as usize] += (outer * (lambda + mu)
                    + DMat3::from_diagonal(DVec3::splat(mu * ga.length_squared())))
                    * w;
            }
        }
        k
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
        if !self.is_quadratic() {
            return false;
        }
        let n = self.node_count();
        let nq = self.integration_point_count();
        assert!(p.len() >= n && out.len() >= n && ip_f.len() >= nq && ip_s.len() >= nq);
        let c = (h2, lambda, mu);
        let (b, o) = (&self.quad_batches, &self.quad_order);
        #[cfg(target_arch = "x86_64")]
        if has_avx512() {
            // SAFETY: all four features were detected on this CPU just above; node indices
            // are below n (checked in `new`) and p.len() >= n (asserted above).
            unsafe { stvk_operator_quadratic_avx512(b, o, ip_f, ip_s, c, p, out) };
            return true;
        }
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            // SAFETY: both features were detected on this CPU just above; node indices as
            // above.
            unsafe { stvk_operator_quadratic_avx2(b, o, ip_f, ip_s, c, p, out) };
            return true;
        }
        // SAFETY: node indices as above; Plain8 needs no CPU feature.
        unsafe { stvk_operator_quadratic::<false, Plain8>(b, o, ip_f, ip_s, c, p, out) };
        true
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
    /// the units of assembly ([`crate::statics::cell_tangent_blocks`]).
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

    /// Largest eigenvalue of the symmetric operator `M^-1/2 (K - c K_D) M^-1/2` on the free
    /// degrees of freedom at rest, by shifted power iteration with a Rayleigh-quotient estimate,
    /// 1/s^2. `K` is the linear-elastic stiffness, `K_D` its block diagonal, `c >= 0`.
    /// With `c = 0` this is `omega_max^2`, the square of the highest natural frequency.
    ///
    /// The estimate approaches the true value from below; `iterations` of 300 give about 0.1 %
    /// on the meshes we use.
    pub fn max_eigenvalue(&self, diag_weight: f64, iterations: usize) -> f64 {
        let n = self.node_count();
        let kd = self.rest_diagonal_blocks();
        let inv_sqrt_m: Vec<f64> = self.lumped_mass_kg.iter().map(|m| 1.0 / m.sqrt()).collect();
        // Shift so the operator is positive semi-definite: -c K_D >= -c max_i lambda_max(K_ii)/m_i.
        let shift = if diag_weight > 0.0 {
            diag_weight
                * kd.iter()
                    .zip(&self.lumped_mass_kg)
                    .map(|(k, m)| gershgorin_bound(k) / m)
                    .fold(0.0, f64::max)
        } else {
            0.0
        };
        let mut z: Vec<DVec3> = (0..n)
            .map(|i| {
                // Deterministic pseudo-random start vector.
                let h = |s: u64| {
                    ((i as u64).wrapping_mul(6364136223846793005).wrapping_add(s) >> 33) as f64
                };
                DVec3::new(h(1), h(2), h(3)) / (u32::MAX as f64) - 0.25
            })
            .collect();
        for (i, zi) in z.iter_mut().enumerate() {
            apply_constraint(self.constraint[i], zi);
        }
        let norm = |v: &[DVec3]| v.iter().map(|a| a.length_squared()).sum::<f64>().sqrt();
        let mut tmp = vec![DVec3::ZERO; n];
        let mut out = vec![DVec3::ZERO; n];
        let mut estimate = 0.0;
        for _ in 0..iterations {
            let nz = norm(&z);
            if nz == 0.0 {
                return 0.0;
            }
            for (i, zi) in z.iter_mut().enumerate() {
                *zi /= nz;
                tmp[i] = *zi * inv_sqrt_m[i];
            }
            out.iter_mut().for_each(|o| *o = DVec3::ZERO);
            self.stiffness_action(&self.rest, &tmp, &mut out);
            for i in 0..n {
                let mut y =
                    (out[i] - (kd[i] * tmp[i]) * diag_weight) * inv_sqrt_m[i] + z[i] * shift;
                apply_constraint(self.constraint[i], &mut y);
                out[i] = y;
            }
            estimate = z.iter().zip(&out).map(|(a, b)| a.dot(*b)).sum::<f64>();
            std::mem::swap(&mut z, &mut out);
        }
        estimate - shift
    }
}

/// Gershgorin bound on the largest eigenvalue of a 3x3 matrix.
fn gershgorin_bound(m: &DMat3) -> f64 {
    (0..3)
        .map(|r| m.row(r).abs().element_sum())
        .fold(0.0, f64::max)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesher::box_mesh;

    /// A large non-affine deformation of the rest shape and pseudo-random velocities.
    fn deformed_state(fem: &FemModel) -> (Vec<DVec3>, Vec<DVec3>) {
        let mut seed = 7_u64;
        let mut next = move || {
            seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            (seed >> 11) as f64 / (1_u64 << 53) as f64 - 0.5
        };
        let x = fem
            .rest
            .iter()
            .map(|p| {
                DVec3::new(
                    p.x + 0.2 * p.y + 30.0 * p.z * p.z + 3e-4 * next(),
                    0.9 * p.y - 0.1 * p.x + 3e-4 * next(),
                    1.1 * p.z + 20.0 * p.x * p.y + 3e-4 * next(),
                )
            })
            .collect();
        let v = (0..fem.node_count())
            .map(|_| DVec3::new(next(), next(), next()) * 0.2)
            .collect();
        (x, v)
    }

    /// Every instruction-set variant of the batch kernels that this CPU can run (AVX-512
    /// registers, AVX2 + FMA, plain code) against the scalar element loop `generic_forces`
    /// (`material::first_piola` per element or integration point), for StVK and stable
    /// Neo-Hookean, linear, quadratic and edge-smoothed linear elements, with and without
    /// viscosity. The public
    /// `add_internal_forces` runs only the best variant, so the others are checked here.
    #[test]
    fn every_kernel_variant_matches_the_scalar_element_loop() {
        type Kernel = fn(&FemModel, &[DVec3], Option<&[DVec3]>, &mut [DVec3]);
        // The inputs are the test's own (node indices checked by `FemModel::new`, x and v
        // n long); each instruction set is asserted before its kernel runs.
        fn plain<const MODEL: u8>(m: &FemModel, x: &[DVec3], v: Option<&[DVec3]>, f: &mut [DVec3]) {
            // SAFETY: see above.
            unsafe { forces_plain::<MODEL>(m, x, v, f) }
        }
        #[cfg(target_arch = "x86_64")]
        fn avx2<const MODEL: u8>(m: &FemModel, x: &[DVec3], v: Option<&[DVec3]>, f: &mut [DVec3]) {
            assert!(has_avx2_fma());
            // SAFETY: see above.
            unsafe { forces_avx2::<MODEL>(m, x, v, f) }
        }
        #[cfg(target_arch = "x86_64")]
        fn zmm<const MODEL: u8>(m: &FemModel, x: &[DVec3], v: Option<&[DVec3]>, f: &mut [DVec3]) {
            assert!(has_avx512());
            // SAFETY: see above.
            unsafe { forces_avx512::<MODEL>(m, x, v, f) }
        }
        let mut checked = 0;
        for (model, kernels) in [
            (MaterialModel::StVenantKirchhoff, {
                let mut k: Vec<(&str, Kernel)> = vec![("plain", plain::<LANE_STVK>)];
                #[cfg(target_arch = "x86_64")]
                {
                    if has_avx2_fma() {
                        k.push(("avx2", avx2::<LANE_STVK>));
                    }
                    if has_avx512() {
                        k.push(("avx512", zmm::<LANE_STVK>));
                    }
                }
                k
            }),
            (MaterialModel::StableNeoHookean, {
                let mut k: Vec<(&str, Kernel)> = vec![("plain", plain::<LANE_STABLE_NEO_HOOKEAN>)];
                #[cfg(target_arch = "x86_64")]
                {
                    if has_avx2_fma() {
                        k.push(("avx2", avx2::<LANE_STABLE_NEO_HOOKEAN>));
                    }
                    if has_avx512() {
                        k.push(("avx512", zmm::<LANE_STABLE_NEO_HOOKEAN>));
                    }
                }
                k
            }),
        ] {
            for (quadratic, smoothing) in [
                (false, StrainSmoothing::None),
                (true, StrainSmoothing::None),
                (false, StrainSmoothing::Edge),
            ] {
                // 3 x 2 x 3 cells: 90 tets (and 169 edge domains), so the last batch has
                // padding lanes.
                let mesh = box_mesh(DVec3::splat(0.01), [3, 2, 3]);
                let mesh = if quadratic { mesh.to_quadratic() } else { mesh };
                let mut mat = MaterialParams::from_youngs(1e4, 0.45, 1000.0);
                mat.model = model;
                mat.phi_pa_s = 0.3;
                mat.psi_pa_s = 0.2;
                let fem = FemModel::with_smoothing(&mesh, mat, smoothing).unwrap();
                assert_ne!(fem.element_count() % LANES, 0, "want padding lanes");
                assert_ne!(fem.cell_count() % LANES, 0, "want padding lanes");
                if smoothing == StrainSmoothing::Edge {
                    // Domains of several node counts: batches with padding slots.
                    let counts: std::collections::BTreeSet<usize> = (0..fem.cell_count())
                        .map(|c| fem.cell_nodes(c).len())
                        .collect();
                    assert!(counts.len() >= 3, "{counts:?}");
                }
                let (x, v) = deformed_state(&fem);
                for velocities in [None, Some(v.as_slice())] {
                    let mut expected = vec![DVec3::ZERO; fem.node_count()];
                    fem.generic_forces(&x, velocities, &mut expected);
                    let scale = expected.iter().map(|a| a.length()).fold(0.0, f64::max);
                    assert!(scale > 0.0);
                    for (name, kernel) in &kernels {
                        let mut f = vec![DVec3::ZERO; fem.node_count()];
                        kernel(&fem, &x, velocities, &mut f);
                        let err = f
                            .iter()
                            .zip(&expected)
                            .map(|(a, b)| (*a - *b).length())
                            .fold(0.0, f64::max);
                        assert!(
                            err < 1e-12 * scale,
                            "{name} {model:?} quadratic={quadratic} {smoothing:?} viscous={}: {err:e} of {scale:e}",
                            velocities.is_some()
                        );
                        checked += 1;
                    }
                }
            }
        }
        // At least the plain variant of each of the 12 combinations.
        assert!(checked >= 12);
    }

    /// Every instruction-set variant of the quadratic backward Euler operator kernel against
    /// the plain one (the integration test `vectorised_operator_matches_the_integration_point_formula`
    /// checks the variant this CPU runs against the formula).
    #[test]
    fn every_operator_variant_matches_the_plain_one() {
        let mesh = box_mesh(DVec3::splat(0.01), [3, 2, 3]).to_quadratic();
        let fem = FemModel::new(&mesh, MaterialParams::from_youngs(1e4, 0.45, 1000.0)).unwrap();
        let (x, p) = deformed_state(&fem);
        let nq = fem.integration_point_count();
        let ip_f: Vec<_> = (0..nq).map(|q| fem.ip_field_gradient(q, &x)).collect();
        let ip_s: Vec<_> = ip_f
            .iter()
            .map(|f| material::stvk_stress(&material::green_strain(f), 4e3, 1e3))
            .collect();
        let c = (1e-6, 3.0e3, 2.0e3);
        let (b, o) = (&fem.quad_batches, &fem.quad_order);
        let mut expected = vec![DVec3::ZERO; fem.node_count()];
        // SAFETY: node indices checked by `FemModel::new`; p is n long.
        unsafe {
            stvk_operator_quadratic::<false, Plain8>(b, o, &ip_f, &ip_s, c, &p, &mut expected)
        };
        let scale = expected.iter().map(|a| a.length()).fold(0.0, f64::max);
        assert!(scale > 0.0);
        let check = |name: &str, got: &[DVec3]| {
            let err = got
                .iter()
                .zip(&expected)
                .map(|(a, b)| (*a - *b).length())
                .fold(0.0, f64::max);
            assert!(err < 1e-12 * scale, "{name}: {err:e} of {scale:e}");
        };
        #[cfg(target_arch = "x86_64")]
        {
            if has_avx2_fma() {
                let mut out = vec![DVec3::ZERO; fem.node_count()];
                // SAFETY: AVX2 and FMA detected; indices as above.
                unsafe { stvk_operator_quadratic_avx2(b, o, &ip_f, &ip_s, c, &p, &mut out) };
                check("avx2", &out);
            }
            if has_avx512() {
                let mut out = vec![DVec3::ZERO; fem.node_count()];
                // SAFETY: AVX-512 detected; indices as above.
                unsafe { stvk_operator_quadratic_avx512(b, o, &ip_f, &ip_s, c, &p, &mut out) };
                check("avx512", &out);
            }
        }
        let mut out = vec![DVec3::ZERO; fem.node_count()];
        assert!(fem.quadratic_stvk_operator_action(&ip_f, &ip_s, c, &p, &mut out));
        check("public", &out);
    }
}
