//! Haptic probe contact: a sphere at the device position (the haptic interaction point, HIP)
//! touches the touchable surface through a god-object (proxy) joined to the device point by a
//! virtual coupling.
//!
//! Each update finds the closest triangle of the deformed touchable surface to the device point
//! (a local walk over neighbouring triangles while in contact, a full search otherwise), then
//! a smoothed local surface around the device: the touchable nodes within `2 r` of it with
//! kernel weights `w_i ∝ (1 - d_i^2 / (2r)^2)^2` (sum 1) define the plane through
//! `c = sum w_i x_i` with normal `n` the weighted vertex normals. Because the weights vanish at
//! the rim, `c` and `n` move continuously as the surface dimples under the probe (a plain
//! closest point jumps between the walls of the dimple and makes the force chatter). With the
//! signed distance `s = (device - c) . n`, the probe touches when `s < r`. The proxy is then
//! held outside the surface at `device + (r - s) n` (it cannot penetrate), and
//! the virtual coupling gives the device force
//! `F_dev = k (proxy - device) + b ((v_c - v_dev) . n) n`, clamped to `[0, max_force_n]` along
//! `n`, with the proxy and the surface velocity `v_c` taken at the end of the step (implicit:
//! [`Probe::finish_implicit`]). Its reaction
//! `-F_dev` acts on the body over the same patch with the same weights, so linear momentum is
//! conserved. Spreading over the patch
//! (a 2 mm sphere does not push on one triangle) also raises the effective mass the coupling
//! acts on, `m_eff = 1 / sum(w_i^2 / m_i)`, which keeps the explicit coupling stable: it needs
//! `dt^2 k / m_eff + 2 dt b / m_eff < 4` (a damped spring under symplectic Euler).
//! Frictionless: the proxy slides freely along the surface.
//!
//! Neighbours: [`crate::sim`] calls [`Probe::update`] every sub-step and adds the reaction.

use glam::DVec3;

/// Haptic probe and virtual coupling parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeParams {
    /// Probe sphere radius, m.
    pub radius_m: f64,
    /// Virtual coupling stiffness between proxy and device point, N/m.
    pub coupling_stiffness_n_per_m: f64,
    /// Virtual coupling damping along the contact normal, N s/m.
    pub coupling_damping_n_s_per_m: f64,
    /// Largest coupling force magnitude the model applies and returns, N.
    pub max_force_n: f64,
}

impl Default for ProbeParams {
    fn default() -> Self {
        Self {
            radius_m: 2e-3,
            coupling_stiffness_n_per_m: 300.0,
            coupling_damping_n_s_per_m: 0.05,
            max_force_n: 10.0,
        }
    }
}

/// A triangle surface over the body's nodes with vertex-to-triangle adjacency, for closest-point
/// queries on the deformed configuration.
#[derive(Debug, Clone)]
pub struct ContactSurface {
    /// Triangles (node indices), outward oriented.
    pub triangles: Vec<[u32; 3]>,
    /// CSR offsets: triangles around node `i` are `node_tris[node_offsets[i]..node_offsets[i+1]]`.
    node_offsets: Vec<u32>,
    node_tris: Vec<u32>,
}

/// The closest point of a surface to a query point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfacePoint {
    /// Triangle index into [`ContactSurface::triangles`].
    pub triangle: u32,
    /// Barycentric weights of the point on the triangle (sum 1, each >= 0).
    pub bary: [f64; 3],
    /// The point, m.
    pub point: DVec3,
    /// Squared distance to the query, m^2.
    pub dist2: f64,
}

impl ContactSurface {
    /// Builds the adjacency for `triangles` over `node_count` nodes.
    pub fn new(triangles: Vec<[u32; 3]>, node_count: usize) -> Self {
        let mut counts = vec![0u32; node_count + 1];
        for t in &triangles {
            for &i in t {
                counts[i as usize + 1] += 1;
            }
        }
        for i in 0..node_count {
            counts[i + 1] += counts[i];
        }
        let mut fill = counts.clone();
        let mut node_tris = vec![0u32; counts[node_count] as usize];
        for (k, t) in triangles.iter().enumerate() {
            for &i in t {
                node_tris[fill[i as usize] as usize] = k as u32;
                fill[i as usize] += 1;
            }
        }
        Self {
            triangles,
            node_offsets: counts,
            node_tris,
        }
    }

    /// Collects the surface nodes within `reach_m` of `q` (m) reachable from triangle `seed`
    /// over the vertex-to-triangle adjacency, with the kernel weights `(1 - d^2 / reach^2)^2`
    /// normalised to sum 1, into `nodes` and `weights` (cleared first; empty when all weights
    /// vanish). The weights go to zero at the rim, so a patch centre that moves makes the patch
    /// change continuously. At most [`MAX_PATCH_NODES`] nodes; allocation-free when both
    /// vectors have that capacity. Used for the probe's contact patch and for point loads.
    pub fn gather_kernel_patch(
        &self,
        x: &[DVec3],
        q: DVec3,
        seed: u32,
        reach_m: f64,
        nodes: &mut Vec<u32>,
        weights: &mut Vec<f64>,
    ) {
        let r2 = reach_m * reach_m;
        nodes.clear();
        weights.clear();
        for &i in &self.triangles[seed as usize] {
            if (x[i as usize] - q).length_squared() < r2 && !nodes.contains(&i) {
                nodes.push(i);
            }
        }
        let mut head = 0;
        while head < nodes.len() {
            let node = nodes[head] as usize;
            head += 1;
            let (lo, hi) = (self.node_offsets[node], self.node_offsets[node + 1]);
            for &t in &self.node_tris[lo as usize..hi as usize] {
                for &j in &self.triangles[t as usize] {
                    if nodes.len() < MAX_PATCH_NODES
                        && !nodes.contains(&j)
                        && (x[j as usize] - q).length_squared() < r2
                    {
                        nodes.push(j);
                    }
                }
            }
        }
        let mut sum = 0.0;
        for &i in nodes.iter() {
            let u = 1.0 - (x[i as usize] - q).length_squared() / r2;
            let w = u * u;
            weights.push(w);
            sum += w;
        }
        if !(sum > 0.0) {
            nodes.clear();
            weights.clear();
            return;
        }
        for w in weights.iter_mut() {
            *w /= sum;
        }
    }

    /// Closest point of triangle `k` to `q` on positions `x`.
    #[inline]
    pub fn closest_on(&self, k: u32, x: &[DVec3], q: DVec3) -> SurfacePoint {
        let [a, b, c] = self.triangles[k as usize].map(|i| x[i as usize]);
        let (point, bary) = closest_point_on_triangle(q, a, b, c);
        SurfacePoint {
            triangle: k,
            bary,
            point,
            dist2: (q - point).length_squared(),
        }
    }

    /// Closest point over all triangles (O(T)). `None` for an empty surface.
    pub fn closest_global(&self, x: &[DVec3], q: DVec3) -> Option<SurfacePoint> {
        let mut best: Option<SurfacePoint> = None;
        for k in 0..self.triangles.len() as u32 {
            let c = self.closest_on(k, x, q);
            if best.is_none_or(|b| c.dist2 < b.dist2) {
                best = Some(c);
            }
        }
        best
    }

    /// Closest point by a local walk from triangle `start` over vertex-adjacent triangles, until
    /// no neighbour is closer (at most `max_hops` moves). Allocation-free.
    pub fn closest_local(
        &self,
        x: &[DVec3],
        q: DVec3,
        start: u32,
        max_hops: usize,
    ) -> SurfacePoint {
        let mut best = self.closest_on(start, x, q);
        for _ in 0..max_hops {
            let current = best.triangle;
            for &node in &self.triangles[current as usize] {
                let (lo, hi) = (
                    self.node_offsets[node as usize],
                    self.node_offsets[node as usize + 1],
                );
                for &k in &self.node_tris[lo as usize..hi as usize] {
                    let c = self.closest_on(k, x, q);
                    if c.dist2 < best.dist2 {
                        best = c;
                    }
                }
            }
            if best.triangle == current {
                break;
            }
        }
        best
    }

    /// Area-weighted outward normal at node `i` (sum of the cross products of its triangles;
    /// not normalised; zero for a node not on this surface).
    pub fn vertex_normal(&self, i: u32, x: &[DVec3]) -> DVec3 {
        let (lo, hi) = (
            self.node_offsets[i as usize],
            self.node_offsets[i as usize + 1],
        );
        self.node_tris[lo as usize..hi as usize]
            .iter()
            .fold(DVec3::ZERO, |acc, &t| {
                let [a, b, c] = self.triangles[t as usize].map(|k| x[k as usize]);
                acc + (b - a).cross(c - a)
            })
    }

    /// Unit outward normal of triangle `k` on positions `x` (zero for a degenerate triangle).
    #[inline]
    pub fn normal(&self, k: u32, x: &[DVec3]) -> DVec3 {
        let [a, b, c] = self.triangles[k as usize].map(|i| x[i as usize]);
        (b - a).cross(c - a).normalize_or_zero()
    }
}

/// Closest point to `p` on triangle `(a, b, c)` and its barycentric weights (Ericson,
/// *Real-Time Collision Detection*, 5.1.5).
pub fn closest_point_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> (DVec3, [f64; 3]) {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(ap);
    let d2 = ac.dot(ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (a, [1.0, 0.0, 0.0]);
    }
    let bp = p - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (b, [0.0, 1.0, 0.0]);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (a + ab * v, [1.0 - v, v, 0.0]);
    }
    let cp = p - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (c, [0.0, 0.0, 1.0]);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (a + ac * w, [1.0 - w, 0.0, w]);
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (b + (c - b) * w, [0.0, 1.0 - w, w]);
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    (a + ab * v + ac * w, [1.0 - v - w, v, w])
}

/// Result of a probe update.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ContactState {
    /// Whether the probe touches the surface.
    pub in_contact: bool,
    /// Force the device must render (virtual coupling on the device), N.
    pub force_on_device_n: DVec3,
    /// Proxy (god-object) centre, m. Equals the device point out of contact.
    pub proxy_m: DVec3,
    /// Outward contact normal (zero out of contact).
    pub normal: DVec3,
    /// Contact triangle and barycentric weights (valid in contact).
    pub triangle: u32,
    /// Barycentric weights on `triangle`.
    pub bary: [f64; 3],
}

/// The haptic probe: parameters, the touchable surface and the contact state.
#[derive(Debug, Clone)]
pub struct Probe {
    /// Parameters.
    pub params: ProbeParams,
    /// Touchable surface.
    pub surface: ContactSurface,
    /// Rest-configuration bounding box of the surface, expanded by a margin, for a cheap
    /// "far away" test that skips the search.
    reach_min: DVec3,
    reach_max: DVec3,
    /// Last contact state.
    pub state: ContactState,
    /// Contact patch nodes and weights (capacity [`MAX_PATCH_NODES`], never reallocated).
    patch_nodes: Vec<u32>,
    patch_weights: Vec<f64>,
    /// Explicit part of the normal coupling force of the current step, N.
    phi0_n: f64,
}

/// Largest number of nodes in a contact patch.
pub const MAX_PATCH_NODES: usize = 256;
/// Radius of the contact patch around the device point, in probe radii.
pub const PATCH_RADIUS_FACTOR: f64 = 2.0;

impl Probe {
    /// Builds a probe over `touchable` triangles of a body whose rest positions are `rest`.
    pub fn new(params: ProbeParams, touchable: Vec<[u32; 3]>, rest: &[DVec3]) -> Self {
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for t in &touchable {
            for &i in t {
                lo = lo.min(rest[i as usize]);
                hi = hi.max(rest[i as usize]);
            }
        }
        // Deformations larger than half the body size are far outside haptic use.
        let margin = (hi - lo).max_element() * 0.5 + params.radius_m;
        Self {
            params,
            surface: ContactSurface::new(touchable, rest.len()),
            reach_min: lo - DVec3::splat(margin),
            reach_max: hi + DVec3::splat(margin),
            state: ContactState::default(),
            patch_nodes: Vec::with_capacity(MAX_PATCH_NODES),
            patch_weights: Vec::with_capacity(MAX_PATCH_NODES),
            phi0_n: 0.0,
        }
    }

    /// Updates the contact for device point `device_m` (m) moving at `device_vel` (m/s) against
    /// the body at positions `x`. The surface-velocity part of the coupling is implicit
    /// ([`Probe::finish_implicit`]). Allocation-free.
    pub fn update(&mut self, x: &[DVec3], device_m: DVec3, device_vel: DVec3) -> ContactState {
        let none = ContactState {
            proxy_m: device_m,
            ..ContactState::default()
        };
        if self.surface.triangles.is_empty()
            || device_m.cmplt(self.reach_min).any()
            || device_m.cmpgt(self.reach_max).any()
        {
            self.state = none;
            return none;
        }
        let sp = if self.state.in_contact {
            self.surface
                .closest_local(x, device_m, self.state.triangle, 16)
        } else {
            match self.surface.closest_global(x, device_m) {
                Some(sp) => sp,
                None => return none,
            }
        };
        let r = self.params.radius_m;
        let reach = PATCH_RADIUS_FACTOR * r;
        if sp.dist2 >= reach * reach {
            self.state = none;
            return none;
        }
        // Smoothed local surface: kernel-weighted plane through the patch around the device.
        self.gather_patch(x, device_m, sp.triangle);
        if self.patch_nodes.is_empty() {
            self.state = none;
            return none;
        }
        let mut centre = DVec3::ZERO;
        let mut normal_sum = DVec3::ZERO;
        for (&i, &w) in self.patch_nodes.iter().zip(&self.patch_weights) {
            centre += x[i as usize] * w;
            normal_sum += self.surface.vertex_normal(i, x) * w;
        }
        let n = normal_sum.normalize_or_zero();
        let signed = (device_m - centre).dot(n);
        if signed >= r || n == DVec3::ZERO {
            self.state = none;
            return none;
        }
        let proxy = device_m + n * (r - signed);
        let sp = SurfacePoint {
            point: centre,
            ..sp
        };
        let p = &self.params;
        // Explicit part of the normal coupling force (the surface-velocity term is implicit).
        let phi0 = p.coupling_stiffness_n_per_m * (r - signed)
            - p.coupling_damping_n_s_per_m * device_vel.dot(n);
        self.phi0_n = phi0;
        self.state = ContactState {
            in_contact: true,
            force_on_device_n: n * phi0.clamp(0.0, p.max_force_n),
            proxy_m: proxy,
            normal: n,
            triangle: sp.triangle,
            bary: sp.bary,
        };
        self.state
    }

    /// Completes a step with the coupling treated implicitly. After the integrator advanced
    /// every node with the explicit coupling part (see [`Probe::add_reaction`]), giving
    /// velocities `y`, the coupling term `gamma U U^T v'` with `U = (w_i n)` over the patch and
    /// `gamma = dt (k dt + b)` is solved exactly by Sherman-Morrison:
    /// `v' = y - z (gamma U^T y) / (1 + gamma U^T z)`, `z_i = w_i B_i^-1 n` where
    /// `B_i^-1 v = inv(i, v)` is the integrator's per-node inverse divided by the mass.
    /// Positions are corrected by `dt (v' - y)`. The device force becomes
    /// `phi n`, `phi = phi0 + (k dt + b) U^T v'`, clamped to `[0, max_force_n]`.
    /// This makes the virtual coupling unconditionally stable for any `k`, `b`. Allocation-free.
    pub fn finish_implicit(
        &mut self,
        dt_s: f64,
        x: &mut [DVec3],
        v: &mut [DVec3],
        inv: impl Fn(usize, DVec3) -> DVec3,
    ) {
        if !self.state.in_contact {
            return;
        }
        let n = self.state.normal;
        let p = self.params;
        let gamma = dt_s * (p.coupling_stiffness_n_per_m * dt_s + p.coupling_damping_n_s_per_m);
        let (mut uty, mut utz) = (0.0, 0.0);
        for (&i, &w) in self.patch_nodes.iter().zip(&self.patch_weights) {
            uty += w * n.dot(v[i as usize]);
            utz += w * n.dot(inv(i as usize, n * w));
        }
        let delta = gamma * uty / (1.0 + gamma * utz);
        let mut utv = 0.0;
        for (&i, &w) in self.patch_nodes.iter().zip(&self.patch_weights) {
            let dv = inv(i as usize, n * w) * delta;
            v[i as usize] -= dv;
            x[i as usize] -= dv * dt_s;
            utv += w * n.dot(v[i as usize]);
        }
        let phi = self.phi0_n
            + (p.coupling_stiffness_n_per_m * dt_s + p.coupling_damping_n_s_per_m) * utv;
        self.state.force_on_device_n = n * phi.clamp(0.0, p.max_force_n);
    }

    /// `gamma = dt (k dt + b)` (kg): the weight of the coupling's implicit rank-one term
    /// `gamma U U^T` over the patch (see [`Probe::finish_implicit`]).
    pub fn coupling_gamma(&self, dt_s: f64) -> f64 {
        let p = &self.params;
        dt_s * (p.coupling_stiffness_n_per_m * dt_s + p.coupling_damping_n_s_per_m)
    }

    /// The coupling's implicit term as a rank-one matrix for a global implicit solve
    /// ([`crate::integrator::ImplicitSolver`]); `None` out of contact. Pair with
    /// [`Probe::finish_solved`].
    pub fn rank_one(&self, dt_s: f64) -> Option<crate::integrator::RankOneCoupling<'_>> {
        if !self.state.in_contact {
            return None;
        }
        Some(crate::integrator::RankOneCoupling {
            gamma_kg: self.coupling_gamma(dt_s),
            normal: self.state.normal,
            nodes: &self.patch_nodes,
            weights: &self.patch_weights,
        })
    }

    /// Completes a step whose solve already contained the coupling's rank-one term
    /// ([`Probe::rank_one`]): the end-of-step velocities `v` (m/s) give the device force
    /// `phi n`, `phi = phi0 + (k dt + b) U^T v'`, clamped to `[0, max_force_n]`, the same force
    /// whose unclamped reaction the body received. Allocation-free.
    pub fn finish_solved(&mut self, dt_s: f64, v: &[DVec3]) {
        if !self.state.in_contact {
            return;
        }
        let n = self.state.normal;
        let p = self.params;
        let utv: f64 = self
            .patch_nodes
            .iter()
            .zip(&self.patch_weights)
            .map(|(&i, &w)| w * n.dot(v[i as usize]))
            .sum();
        let phi = self.phi0_n
            + (p.coupling_stiffness_n_per_m * dt_s + p.coupling_damping_n_s_per_m) * utv;
        self.state.force_on_device_n = n * phi.clamp(0.0, p.max_force_n);
    }

    /// Collects the contact patch around the device point `q` (see
    /// [`ContactSurface::gather_kernel_patch`], radius `PATCH_RADIUS_FACTOR * r`).
    fn gather_patch(&mut self, x: &[DVec3], q: DVec3, seed: u32) {
        self.surface.gather_kernel_patch(
            x,
            q,
            seed,
            PATCH_RADIUS_FACTOR * self.params.radius_m,
            &mut self.patch_nodes,
            &mut self.patch_weights,
        );
    }

    /// Nodes and weights (sum 1) of the current contact patch (empty out of contact).
    pub fn patch(&self) -> (&[u32], &[f64]) {
        if self.state.in_contact {
            (&self.patch_nodes, &self.patch_weights)
        } else {
            (&[], &[])
        }
    }

    /// Adds the explicit part of the coupling reaction, `-phi0 n`, to the nodal forces `f` (N)
    /// over the contact patch (the implicit part follows in [`Probe::finish_implicit`]).
    /// Does nothing out of contact.
    pub fn add_reaction(&self, f: &mut [DVec3]) {
        if !self.state.in_contact {
            return;
        }
        let fr = self.state.normal * self.phi0_n;
        for (&i, &w) in self.patch_nodes.iter().zip(&self.patch_weights) {
            f[i as usize] -= fr * w;
        }
    }

    /// Local contact stiffness felt at the device, 3x3 row-major N/m: `k n n^T` in contact
    /// (the coupling stiffness along the normal; the tissue in series makes the true value
    /// smaller), zero out of contact.
    pub fn contact_stiffness(&self) -> [f64; 9] {
        if !self.state.in_contact {
            return [0.0; 9];
        }
        let n = self.state.normal;
        let k = self.params.coupling_stiffness_n_per_m;
        let a = n.to_array();
        let mut out = [0.0; 9];
        for r in 0..3 {
            for c in 0..3 {
                out[r * 3 + c] = k * a[r] * a[c];
            }
        }
        out
    }
}
