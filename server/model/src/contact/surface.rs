//! The touchable surface as a triangle mesh over the body's nodes: closest-point queries on the
//! deformed configuration (a global search, or a local walk while in contact), vertex normals,
//! and the kernel-weighted patch of nodes around a point that spreads a contact or a point load.
//! A surface whose triangles change at run time (the subdivided mass-spring surface) is edited
//! one triangle at a time within room reserved per node ([`ContactSurface::with_node_room`]), so
//! that a local change costs O(1) instead of a rebuild.
//!
//! Neighbours: used by [`super::probe`] and by [`crate::loads`] (point loads).

use glam::{DMat3, DVec3};

use super::MAX_PATCH_NODES;

/// A triangle surface over the body's nodes with vertex-to-triangle adjacency, for closest-point
/// queries on the deformed configuration.
#[derive(Debug, Clone)]
pub struct ContactSurface {
    /// Triangles (node indices), outward oriented.
    pub triangles: Vec<[u32; 3]>,
    /// CSR: the triangles around node `i` are `node_tris[start..end]` with `[start, end] =
    /// node_lists[i]` (one entry per node and a last one, `start` of the next node bounding
    /// the room of this one); `end` is the next `start` unless the surface has room per node.
    node_lists: Vec<[u32; 2]>,
    node_tris: Vec<u32>,
    /// Whether the lists have room reserved per node ([`ContactSurface::with_node_room`]), kept
    /// by every edit, rather than packed by [`ContactSurface::set_triangles`].
    has_room: bool,
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
        let mut node_lists: Vec<[u32; 2]> = counts.windows(2).map(|w| [w[0], w[1]]).collect();
        node_lists.push([counts[node_count]; 2]);
        Self {
            triangles,
            node_lists,
            node_tris,
            has_room: false,
        }
    }

    /// An empty surface over `node_count` nodes whose buffers hold up to `max_triangles`
    /// triangles, for a body whose surface changes at run time (the subdivided mass-spring
    /// surface): [`ContactSurface::set_triangles`] then replaces the triangles without
    /// allocating.
    pub fn with_capacity(max_triangles: usize, node_count: usize) -> Self {
        Self {
            triangles: Vec::with_capacity(max_triangles),
            node_lists: vec![[0; 2]; node_count + 1],
            node_tris: Vec::with_capacity(3 * max_triangles),
            has_room: false,
        }
    }

    /// An empty surface over `room.len()` nodes for triangles edited one at a time
    /// ([`ContactSurface::push_triangle`], [`ContactSurface::set_triangle`],
    /// [`ContactSurface::swap_remove_triangle`]; each O(1) and allocation-free): up to
    /// `max_triangles` triangles, node `i` in at most `room[i]` of them at a time. Its memory
    /// is written at once, so that no edit takes a page fault on a page never used before.
    pub fn with_node_room(max_triangles: usize, room: &[u32]) -> Self {
        let mut node_lists = Vec::with_capacity(room.len() + 1);
        let mut start = 0u32;
        for &r in room {
            node_lists.push([start; 2]);
            start += r;
        }
        node_lists.push([start; 2]);
        let mut triangles = vec![[u32::MAX; 3]; max_triangles];
        triangles.clear();
        Self {
            triangles,
            node_lists,
            node_tris: vec![u32::MAX; start as usize],
            has_room: true,
        }
    }

    /// Appends triangle `t` (index [`ContactSurface::triangles`]`.len()`).
    ///
    /// # Panics
    /// If the surface was not built by [`ContactSurface::with_node_room`], a node index is out
    /// of range or a node of `t` has no room left.
    pub fn push_triangle(&mut self, t: [u32; 3]) {
        let k = self.triangles.len() as u32;
        self.triangles.push(t);
        self.link(k, t);
    }

    /// Replaces triangle `k` by `t`.
    ///
    /// # Panics
    /// As [`ContactSurface::push_triangle`], or if `k` is out of range.
    pub fn set_triangle(&mut self, k: u32, t: [u32; 3]) {
        let old = self.triangles[k as usize];
        self.unlink(k, old);
        self.triangles[k as usize] = t;
        self.link(k, t);
    }

    /// Removes triangle `k`; the last triangle takes its index (as [`Vec::swap_remove`]).
    ///
    /// # Panics
    /// If `k` is out of range.
    pub fn swap_remove_triangle(&mut self, k: u32) {
        let last = self.triangles.len() as u32 - 1;
        let old = self.triangles[k as usize];
        self.unlink(k, old);
        if k != last {
            let moved = self.triangles[last as usize];
            for &i in &moved {
                let (lo, hi) = self.node_range(i);
                for entry in &mut self.node_tris[lo..hi] {
                    if *entry == last {
                        *entry = k;
                    }
                }
            }
        }
        self.triangles.swap_remove(k as usize);
    }

    #[inline]
    fn node_range(&self, i: u32) -> (usize, usize) {
        let [lo, hi] = self.node_lists[i as usize];
        (lo as usize, hi as usize)
    }

    /// Adds triangle index `k` to the lists of the nodes of `t`.
    fn link(&mut self, k: u32, t: [u32; 3]) {
        for i in t {
            let end = self.node_lists[i as usize][1];
            assert!(
                self.has_room && end < self.node_lists[i as usize + 1][0],
                "node {i} has no room for another triangle"
            );
            self.node_tris[end as usize] = k;
            self.node_lists[i as usize][1] = end + 1;
        }
    }

    /// Removes triangle index `k` from the lists of the nodes of `t`.
    fn unlink(&mut self, k: u32, t: [u32; 3]) {
        for i in t {
            let (lo, hi) = self.node_range(i);
            if let Some(p) = self.node_tris[lo..hi].iter().position(|&e| e == k) {
                self.node_tris[lo + p] = self.node_tris[hi - 1];
                self.node_lists[i as usize][1] -= 1;
            }
        }
    }

    /// Triangles around node `i`.
    #[inline]
    fn triangles_at(&self, i: u32) -> &[u32] {
        let (lo, hi) = self.node_range(i);
        &self.node_tris[lo..hi]
    }

    /// Makes this surface a copy of `other` (triangles and adjacency) in place, for a body
    /// that keeps several probes on one changing surface (the mass-spring surface's tools).
    /// O(triangles + nodes); allocation-free when this surface's capacities hold `other`'s
    /// lengths (both built alike, e.g. by the same [`ContactSurface::with_node_room`]).
    pub fn copy_from(&mut self, other: &ContactSurface) {
        self.triangles.clear();
        self.triangles.extend_from_slice(&other.triangles);
        self.node_lists.clear();
        self.node_lists.extend_from_slice(&other.node_lists);
        self.node_tris.clear();
        self.node_tris.extend_from_slice(&other.node_tris);
        self.has_room = other.has_room;
    }

    /// Replaces the triangles (node indices below the node count given at construction) and
    /// rebuilds the vertex-to-triangle adjacency in place: O(triangles + nodes), and
    /// allocation-free when `triangles.len()` is within the capacity of
    /// [`ContactSurface::with_capacity`] (or [`ContactSurface::with_node_room`], whose room per
    /// node it keeps).
    ///
    /// # Panics
    /// If a node index is not below the node count, or a node has no room left.
    pub fn set_triangles(&mut self, triangles: &[[u32; 3]]) {
        let node_count = self.node_lists.len() - 1;
        self.triangles.clear();
        self.triangles.extend_from_slice(triangles);
        if self.has_room {
            for list in &mut self.node_lists {
                list[1] = list[0];
            }
            for (k, &t) in triangles.iter().enumerate() {
                self.link(k as u32, t);
            }
            return;
        }
        self.node_lists.iter_mut().for_each(|l| *l = [0; 2]);
        for t in triangles {
            for &i in t {
                assert!((i as usize) < node_count, "triangle node {i} out of range");
                self.node_lists[i as usize + 1][0] += 1;
            }
        }
        for i in 0..node_count {
            self.node_lists[i + 1][0] += self.node_lists[i][0];
        }
        self.node_tris.clear();
        self.node_tris.resize(3 * triangles.len(), 0);
        // Fill with the ends as cursors.
        for list in &mut self.node_lists {
            list[1] = list[0];
        }
        for (k, t) in triangles.iter().enumerate() {
            for &i in t {
                let end = &mut self.node_lists[i as usize][1];
                self.node_tris[*end as usize] = k as u32;
                *end += 1;
            }
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
            for &t in self.triangles_at(node as u32) {
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

    /// The rest surface's curvature tensor at every node, from the positions `rest` (m): at a
    /// surface node `i`, with the unit vertex normal `N` and a tangent frame `(e1, e2)`, the
    /// weighted least-squares quadric `z = b u + c v + (A u^2 + 2 B u v + C v^2) / 2` through
    /// the nodes within `reach_m` (kernel weights, [`ContactSurface::gather_kernel_patch`]),
    /// `z` along `N`, gives `H = A e1 e1^T + B (e1 e2^T + e2 e1^T) + C e2 e2^T` (1/m; negative
    /// definite on a convex surface: a sphere of radius `R` gives `-P / R`, `P` the tangential
    /// projector). Zero off the surface and where the fit is singular (fewer than five
    /// neighbours, or neighbours on a line). For set-up only (allocates).
    pub fn curvature_tensors(&self, rest: &[DVec3], reach_m: f64) -> Vec<DMat3> {
        let mut out = vec![DMat3::ZERO; rest.len()];
        let (mut nodes, mut weights) = (
            Vec::with_capacity(MAX_PATCH_NODES),
            Vec::with_capacity(MAX_PATCH_NODES),
        );
        for (i, h) in out.iter_mut().enumerate().take(self.node_count()) {
            let Some(&seed) = self.triangles_at(i as u32).first() else {
                continue;
            };
            let Some(n) = self.vertex_normal(i as u32, rest).try_normalize() else {
                continue;
            };
            self.gather_kernel_patch(rest, rest[i], seed, reach_m, &mut nodes, &mut weights);
            let (e1, e2) = n.any_orthonormal_pair();
            let scale = 1.0 / reach_m;
            let mut m = [[0.0; 5]; 5];
            let mut b = [0.0; 5];
            for (&j, &w) in nodes.iter().zip(&weights) {
                let d = (rest[j as usize] - rest[i]) * scale;
                let (u, v, z) = (d.dot(e1), d.dot(e2), d.dot(n));
                let phi = [u, v, 0.5 * u * u, u * v, 0.5 * v * v];
                for r in 0..5 {
                    b[r] += w * phi[r] * z;
                    for c in 0..5 {
                        m[r][c] += w * phi[r] * phi[c];
                    }
                }
            }
            let Some(beta) = solve_spd5(m, b) else {
                continue;
            };
            // Back to 1/m: z and (u, v) were scaled alike, so curvatures scale by `scale`.
            let (a, bb, c) = (beta[2] * scale, beta[3] * scale, beta[4] * scale);
            let outer = |p: DVec3, q: DVec3| DMat3::from_cols(p * q.x, p * q.y, p * q.z);
            *h = outer(e1, e1) * a + (outer(e1, e2) + outer(e2, e1)) * bb + outer(e2, e2) * c;
        }
        out
    }

    /// Number of nodes the surface indexes into.
    pub fn node_count(&self) -> usize {
        self.node_lists.len() - 1
    }

    /// Collects into `tris` (cleared first) the triangles closer than `reach_m` to `q` (m) that
    /// are reachable from triangle `seed` over the vertex-to-triangle adjacency through such
    /// triangles, at most `tris.capacity()` of them (allocation-free). `stamps` (one entry per
    /// triangle) and `stamp` mark visited triangles: the caller bumps `stamp` per call and
    /// resets `stamps` when it wraps.
    pub fn gather_triangles(
        &self,
        x: &[DVec3],
        q: DVec3,
        seed: u32,
        reach_m: f64,
        (stamps, stamp): (&mut [u32], u32),
        tris: &mut Vec<u32>,
    ) {
        tris.clear();
        let r2 = reach_m * reach_m;
        if self.closest_on(seed, x, q).dist2 >= r2 {
            return;
        }
        stamps[seed as usize] = stamp;
        tris.push(seed);
        let mut head = 0;
        while head < tris.len() {
            let k = tris[head] as usize;
            head += 1;
            for &node in &self.triangles[k] {
                for &j in self.triangles_at(node) {
                    if stamps[j as usize] == stamp || tris.len() == tris.capacity() {
                        continue;
                    }
                    stamps[j as usize] = stamp;
                    if self.closest_on(j, x, q).dist2 < r2 {
                        tris.push(j);
                    }
                }
            }
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
                for &k in self.triangles_at(node) {
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
        self.triangles_at(i).iter().fold(DVec3::ZERO, |acc, &t| {
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

/// Solves the symmetric positive definite 5 x 5 system `m x = b` by Cholesky; `None` when a
/// pivot is not clearly positive (relative to the diagonal's largest entry).
fn solve_spd5(m: [[f64; 5]; 5], b: [f64; 5]) -> Option<[f64; 5]> {
    let scale = (0..5).map(|k| m[k][k]).fold(0.0f64, f64::max);
    let mut l = [[0.0; 5]; 5];
    for r in 0..5 {
        for c in 0..=r {
            let v = m[r][c] - (0..c).map(|k| l[r][k] * l[c][k]).sum::<f64>();
            if r == c {
                if !(v > 1e-10 * scale) {
                    return None;
                }
                l[r][r] = v.sqrt();
            } else {
                l[r][c] = v / l[c][c];
            }
        }
    }
    let mut z = [0.0; 5];
    for r in 0..5 {
        z[r] = (b[r] - (0..r).map(|k| l[r][k] * z[k]).sum::<f64>()) / l[r][r];
    }
    let mut x = [0.0; 5];
    for r in (0..5).rev() {
        x[r] = (z[r] - (r + 1..5).map(|k| l[k][r] * x[k]).sum::<f64>()) / l[r][r];
    }
    Some(x)
}
