//! The coarse surface of the mass-spring model: a triangle mesh checked to be a manifold with
//! consistent orientation, with its edges (and the two vertices opposite each, for Loop's edge
//! rule), vertex neighbourhoods (valence K, rings), per-node element size L and rest normals.
//!
//! Neighbours: [`super::loop_rules`] computes the subdivided rest geometry from it,
//! [`super::refine`] the subdivided topology, [`super::calibration`] cuts local patches out of it.

use glam::DVec3;

use crate::ModelError;

/// Marks "no such index" in the adjacency tables (a boundary edge's missing second triangle).
pub const NONE: u32 = u32::MAX;

/// A coarse triangle surface (section 2 of Zhang, Payandeh & Dill: "the simulated surface is
/// divided into small triangles, where at each vertex a mass point (a node) is defined"), with
/// the adjacency run-time subdivision needs. Built once per scene; immutable.
#[derive(Debug, Clone)]
pub struct SpringSurface {
    rest: Vec<DVec3>,
    triangles: Vec<[u32; 3]>,
    fixed: Vec<bool>,
    /// Edges `[a, b]` with `a < b`.
    edges: Vec<[u32; 2]>,
    /// The (one or two) triangles of each edge; `NONE` for the second of a boundary edge.
    edge_tris: Vec<[u32; 2]>,
    /// The vertices opposite each edge in its triangles; `NONE` for a boundary edge's second.
    edge_opposite: Vec<[u32; 2]>,
    /// Edge index of sides `(t0, t1)`, `(t1, t2)`, `(t2, t0)` of each triangle.
    tri_edges: Vec<[u32; 3]>,
    /// CSR: neighbours of node `i` are `nbrs[nbr_offsets[i]..nbr_offsets[i + 1]]`, with the
    /// connecting edges in `nbr_edges` at the same positions.
    nbr_offsets: Vec<u32>,
    nbrs: Vec<u32>,
    nbr_edges: Vec<u32>,
    /// CSR: triangles around node `i`.
    tri_offsets: Vec<u32>,
    node_tris: Vec<u32>,
    /// Whether a node lies on a boundary edge (an open surface's rim).
    boundary: Vec<bool>,
    /// Mean length of the edges at each node, m (the paper's element size L, locally).
    element_size_m: Vec<f64>,
    /// Unit outward normal at each node (area weighted), at rest.
    rest_normal: Vec<DVec3>,
    /// Index of each node in the mesh the surface was cut from ([`SpringSurface::from_mesh`]).
    source_node: Vec<u32>,
}

impl SpringSurface {
    /// The surface of `triangles` (outward oriented, counter-clockwise seen from outside) over
    /// the nodes they use among `nodes` (m), with the nodes listed in `clamped` fixed at rest.
    /// Nodes no triangle uses are dropped; [`SpringSurface::source_node`] maps back.
    ///
    /// # Errors
    /// As [`SpringSurface::new`].
    pub fn from_mesh(
        nodes: &[DVec3],
        triangles: &[[u32; 3]],
        clamped: &[u32],
    ) -> Result<Self, ModelError> {
        let mut local = vec![NONE; nodes.len()];
        let mut source = Vec::new();
        let mut tris = Vec::with_capacity(triangles.len());
        for t in triangles {
            let mut lt = [0u32; 3];
            for (k, &i) in t.iter().enumerate() {
                let Some(slot) = local.get_mut(i as usize) else {
                    return Err(ModelError::InvalidMesh(format!(
                        "surface triangle {t:?} names node {i}, beyond the {} nodes",
                        nodes.len()
                    )));
                };
                if *slot == NONE {
                    *slot = source.len() as u32;
                    source.push(i);
                }
                lt[k] = *slot;
            }
            tris.push(lt);
        }
        let rest: Vec<DVec3> = source.iter().map(|&i| nodes[i as usize]).collect();
        let mut fixed = vec![false; rest.len()];
        for &c in clamped {
            if let Some(&l) = local.get(c as usize)
                && l != NONE
            {
                fixed[l as usize] = true;
            }
        }
        let mut s = Self::new(rest, tris, fixed)?;
        s.source_node = source;
        Ok(s)
    }

    /// The surface of `triangles` over `rest` (m; every node used by some triangle), with the
    /// nodes flagged in `fixed` held at rest.
    ///
    /// # Errors
    /// [`ModelError::InvalidMesh`] when a triangle names a node out of range or repeats one,
    /// has (nearly) zero area, an edge belongs to more than two triangles, two triangles
    /// sharing an edge are oriented inconsistently, a vertex's triangles do not form one fan
    /// (a non-manifold vertex), a node is used by no triangle, or `fixed` has the wrong length.
    pub fn new(
        rest: Vec<DVec3>,
        triangles: Vec<[u32; 3]>,
        fixed: Vec<bool>,
    ) -> Result<Self, ModelError> {
        Self::build(rest, triangles, fixed, true)
    }

    /// A patch cut out of a checked surface (the calibration's local problems): as
    /// [`SpringSurface::new`] but a vertex on the cut may have several fans (it is fixed there).
    pub(crate) fn patch(
        rest: Vec<DVec3>,
        triangles: Vec<[u32; 3]>,
        fixed: Vec<bool>,
    ) -> Result<Self, ModelError> {
        Self::build(rest, triangles, fixed, false)
    }

    fn build(
        rest: Vec<DVec3>,
        triangles: Vec<[u32; 3]>,
        fixed: Vec<bool>,
        check_fans: bool,
    ) -> Result<Self, ModelError> {
        let n = rest.len();
        check_input(&rest, &triangles, &fixed)?;
        let EdgeTable {
            edges,
            edge_tris,
            edge_opposite,
            tri_edges,
        } = EdgeTable::new(&triangles)?;
        let (nbr_offsets, nbrs, nbr_edges) = node_neighbours(n, &edges);
        let (tri_offsets, node_tris) = node_triangles(n, &triangles);
        let bad = |m: String| Err(ModelError::InvalidMesh(m));
        let mut boundary = vec![false; n];
        for (e, t) in edges.iter().zip(&edge_tris) {
            if t[1] == NONE {
                boundary[e[0] as usize] = true;
                boundary[e[1] as usize] = true;
            }
        }
        let mut s = Self {
            element_size_m: vec![0.0; n],
            rest_normal: vec![DVec3::ZERO; n],
            source_node: (0..n as u32).collect(),
            rest,
            triangles,
            fixed,
            edges,
            edge_tris,
            edge_opposite,
            tri_edges,
            nbr_offsets,
            nbrs,
            nbr_edges,
            tri_offsets,
            node_tris,
            boundary,
        };
        for i in 0..n {
            if s.valence(i as u32) == 0 {
                return bad(format!("surface node {i} belongs to no triangle"));
            }
            if check_fans {
                s.check_fan(i as u32)?;
            }
            let sum: f64 = s
                .neighbours(i as u32)
                .iter()
                .map(|&j| (s.rest[j as usize] - s.rest[i]).length())
                .sum();
            s.element_size_m[i] = sum / s.valence(i as u32) as f64;
            let nsum: DVec3 = s
                .triangles_at(i as u32)
                .iter()
                .map(|&t| {
                    let [a, b, c] = s.triangles[t as usize].map(|k| s.rest[k as usize]);
                    (b - a).cross(c - a)
                })
                .sum();
            s.rest_normal[i] = nsum.normalize_or_zero();
        }
        Ok(s)
    }

    /// The paper's experiment mesh (section 3.2.2): a regular equilateral triangular mesh of
    /// edge `edge_m` (m) in the plane z = 0, normal +z, as a hexagon of `rings` rings around
    /// node 0 (the contact node C) at the origin; the outermost ring is fixed. Nodes are
    /// ordered by ring. `3 rings (rings + 1) + 1` nodes.
    ///
    /// # Panics
    /// If `rings` is 0 or `edge_m` is not positive.
    pub fn regular_hexagon(edge_m: f64, rings: u32) -> Self {
        assert!(
            rings > 0 && edge_m > 0.0,
            "a hexagon needs rings and an edge"
        );
        let r = rings as i32;
        let hex = |q: i32, s: i32| q.abs().max(s.abs()).max((q + s).abs());
        let mut coords: Vec<(i32, i32)> = Vec::new();
        for q in -r..=r {
            for s in -r..=r {
                if hex(q, s) <= r {
                    coords.push((q, s));
                }
            }
        }
        coords.sort_by_key(|&(q, s)| (hex(q, s), q, s));
        let index = |q: i32, s: i32| coords.iter().position(|&c| c == (q, s));
        let h = 3f64.sqrt() / 2.0;
        let rest: Vec<DVec3> = coords
            .iter()
            .map(|&(q, s)| {
                DVec3::new(
                    edge_m * (q as f64 + 0.5 * s as f64),
                    edge_m * h * s as f64,
                    0.0,
                )
            })
            .collect();
        let mut triangles = Vec::new();
        for &(q, s) in &coords {
            let up = [(q, s), (q + 1, s), (q, s + 1)];
            let down = [(q + 1, s), (q + 1, s + 1), (q, s + 1)];
            for tri in [up, down] {
                let idx: Vec<Option<usize>> = tri.iter().map(|&(a, b)| index(a, b)).collect();
                if idx.iter().all(|i| i.is_some()) {
                    triangles.push([0, 1, 2].map(|k| idx[k].unwrap_or(0) as u32));
                }
            }
        }
        let fixed = coords.iter().map(|&(q, s)| hex(q, s) == r).collect();
        Self::new(rest, triangles, fixed).expect("the regular hexagon is a valid surface")
    }

    /// Checks that the triangles around node `i` form one fan (closed for an interior node,
    /// open with two boundary edges for a rim node).
    fn check_fan(&self, i: u32) -> Result<(), ModelError> {
        let tris = self.triangles_at(i);
        let boundary_edges = self
            .incident_edges(i)
            .iter()
            .filter(|&&e| self.edge_tris[e as usize][1] == NONE)
            .count();
        // A fan over K edges has K triangles (closed) or K - 1 (open, two boundary edges).
        let k = self.valence(i) as usize;
        let ok = match boundary_edges {
            0 => tris.len() == k,
            2 => tris.len() + 1 == k,
            _ => false,
        };
        // Connectivity of the fan: walk across shared edges from the first triangle.
        let mut reached = 1usize;
        if ok {
            let mut seen = vec![tris[0]];
            let mut head = 0;
            while head < seen.len() {
                let t = seen[head];
                head += 1;
                for &e in &self.tri_edges[t as usize] {
                    let [a, b] = self.edges[e as usize];
                    if a != i && b != i {
                        continue;
                    }
                    for &u in &self.edge_tris[e as usize] {
                        if u != NONE && !seen.contains(&u) {
                            seen.push(u);
                        }
                    }
                }
            }
            reached = seen.len();
        }
        if !ok || reached != tris.len() {
            return Err(ModelError::InvalidMesh(format!(
                "surface node {i} is not a manifold vertex (its triangles do not form one fan)"
            )));
        }
        Ok(())
    }

    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.rest.len()
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// Number of edges (mesh springs of the coarse model).
    pub fn edge_count(&self) -> usize {
        self.edges.len()
    }

    /// Rest positions, m.
    pub fn rest(&self) -> &[DVec3] {
        &self.rest
    }

    /// Triangles, outward oriented.
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.triangles
    }

    /// Whether node `i` is held at rest.
    pub fn is_fixed(&self, i: u32) -> bool {
        self.fixed[i as usize]
    }

    /// Whether node `i` is on the surface's rim (a boundary edge).
    pub fn is_boundary(&self, i: u32) -> bool {
        self.boundary[i as usize]
    }

    /// Edges as `[a, b]`, `a < b`.
    pub fn edges(&self) -> &[[u32; 2]] {
        &self.edges
    }

    /// The triangles of edge `e` (`NONE` as the second for a boundary edge).
    pub fn edge_triangles(&self, e: u32) -> [u32; 2] {
        self.edge_tris[e as usize]
    }

    /// The vertices opposite edge `e` in its triangles (`NONE` as the second for a boundary
    /// edge).
    pub fn edge_opposite(&self, e: u32) -> [u32; 2] {
        self.edge_opposite[e as usize]
    }

    /// Whether edge `e` is on the rim.
    pub fn is_boundary_edge(&self, e: u32) -> bool {
        self.edge_tris[e as usize][1] == NONE
    }

    /// Edge indices of the sides `(t0, t1)`, `(t1, t2)`, `(t2, t0)` of triangle `t`.
    pub fn triangle_edges(&self, t: u32) -> [u32; 3] {
        self.tri_edges[t as usize]
    }

    /// Nodes joined to `i` by an edge.
    pub fn neighbours(&self, i: u32) -> &[u32] {
        let (lo, hi) = (
            self.nbr_offsets[i as usize],
            self.nbr_offsets[i as usize + 1],
        );
        &self.nbrs[lo as usize..hi as usize]
    }

    /// Edges at node `i` (in the order of [`SpringSurface::neighbours`]).
    pub fn incident_edges(&self, i: u32) -> &[u32] {
        let (lo, hi) = (
            self.nbr_offsets[i as usize],
            self.nbr_offsets[i as usize + 1],
        );
        &self.nbr_edges[lo as usize..hi as usize]
    }

    /// Triangles at node `i`.
    pub fn triangles_at(&self, i: u32) -> &[u32] {
        let (lo, hi) = (
            self.tri_offsets[i as usize],
            self.tri_offsets[i as usize + 1],
        );
        &self.node_tris[lo as usize..hi as usize]
    }

    /// Valence K of node `i`: the number of nodes directly connected to it (section 3.1).
    pub fn valence(&self, i: u32) -> u32 {
        self.nbr_offsets[i as usize + 1] - self.nbr_offsets[i as usize]
    }

    /// The edge joining `a` and `b`, if any.
    pub fn edge_between(&self, a: u32, b: u32) -> Option<u32> {
        self.neighbours(a)
            .iter()
            .position(|&j| j == b)
            .map(|p| self.incident_edges(a)[p])
    }

    /// Mean rest length of the edges at node `i`, m: the element size L the paper normalizes
    /// contact displacements by (x / L, section 3.2.2).
    pub fn element_size_m(&self, i: u32) -> f64 {
        self.element_size_m[i as usize]
    }

    /// Unit outward normal at node `i` at rest (area-weighted over its triangles).
    pub fn rest_normal(&self, i: u32) -> DVec3 {
        self.rest_normal[i as usize]
    }

    /// Index of node `i` in the mesh the surface was cut from (itself for
    /// [`SpringSurface::new`]).
    pub fn source_node(&self, i: u32) -> u32 {
        self.source_node[i as usize]
    }

    /// The nodes of the `n`-ring of `centre` (section 3.2: the first ring is the node and every
    /// node directly connected to it; the second adds every node connected to the first, and so
    /// on), with their ring distance, into `out` (cleared first). `dist` is scratch of length
    /// [`SpringSurface::node_count`] filled with `u32::MAX`, and is left so. Allocation-free when
    /// `out` has room for the ring.
    pub fn ring(&self, centre: u32, n: u32, dist: &mut [u32], out: &mut Vec<(u32, u32)>) {
        out.clear();
        dist[centre as usize] = 0;
        out.push((centre, 0));
        let mut head = 0;
        while head < out.len() {
            let (i, d) = out[head];
            head += 1;
            if d == n {
                continue;
            }
            for &j in self.neighbours(i) {
                if dist[j as usize] == u32::MAX {
                    dist[j as usize] = d + 1;
                    out.push((j, d + 1));
                }
            }
        }
        for &(i, _) in out.iter() {
            dist[i as usize] = u32::MAX;
        }
    }
}

/// The checks of [`SpringSurface::new`] on its input alone: flags per node, finite positions,
/// triangles over existing distinct nodes with a non-zero area.
fn check_input(rest: &[DVec3], triangles: &[[u32; 3]], fixed: &[bool]) -> Result<(), ModelError> {
    let n = rest.len();
    let bad = |m: String| Err(ModelError::InvalidMesh(m));
    if fixed.len() != n {
        return bad(format!("{} fixed flags for {n} nodes", fixed.len()));
    }
    if triangles.is_empty() {
        return bad("the spring surface has no triangle".into());
    }
    for p in rest {
        if !p.is_finite() {
            return bad("a surface node position is not finite".into());
        }
    }
    for t in triangles {
        if t.iter().any(|&i| i as usize >= n) || t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
            return bad(format!("surface triangle {t:?} is invalid for {n} nodes"));
        }
        let [a, b, c] = t.map(|i| rest[i as usize]);
        let area2 = (b - a).cross(c - a).length();
        let scale = (b - a).length_squared().max((c - a).length_squared());
        if !(area2 > 1e-12 * scale) {
            return bad(format!("surface triangle {t:?} has zero area"));
        }
    }
    Ok(())
}

/// The edges of a triangle list, from its sorted directed half-edges: per edge its ends, its
/// one or two triangles and their opposite corners; per triangle its three edges.
struct EdgeTable {
    edges: Vec<[u32; 2]>,
    edge_tris: Vec<[u32; 2]>,
    edge_opposite: Vec<[u32; 2]>,
    tri_edges: Vec<[u32; 3]>,
}

impl EdgeTable {
    /// # Errors
    /// [`ModelError::InvalidMesh`] for an edge of more than two triangles or two triangles
    /// sharing an edge with the same orientation.
    fn new(triangles: &[[u32; 3]]) -> Result<Self, ModelError> {
        let bad = |m: String| Err(ModelError::InvalidMesh(m));
        let mut half: Vec<(u32, u32, u32, u32)> = Vec::with_capacity(3 * triangles.len());
        for (k, t) in triangles.iter().enumerate() {
            for s in 0..3 {
                let (a, b) = (t[s], t[(s + 1) % 3]);
                half.push((a.min(b), a.max(b), k as u32, s as u32));
            }
        }
        half.sort_unstable();
        let mut edges = Vec::new();
        let mut edge_tris = Vec::new();
        let mut edge_opposite = Vec::new();
        let mut tri_edges = vec![[NONE; 3]; triangles.len()];
        let mut k = 0;
        while k < half.len() {
            let (a, b) = (half[k].0, half[k].1);
            let mut m = k;
            while m < half.len() && half[m].0 == a && half[m].1 == b {
                m += 1;
            }
            if m - k > 2 {
                return bad(format!(
                    "edge ({a}, {b}) belongs to {} triangles: the surface is not a manifold",
                    m - k
                ));
            }
            let e = edges.len() as u32;
            let mut tris = [NONE; 2];
            let mut opp = [NONE; 2];
            for (slot, h) in half[k..m].iter().enumerate() {
                let t = triangles[h.2 as usize];
                tris[slot] = h.2;
                opp[slot] = t[(h.3 as usize + 2) % 3];
                tri_edges[h.2 as usize][h.3 as usize] = e;
            }
            if m - k == 2 {
                // Consistent orientation: the two triangles run along the edge in opposite
                // directions.
                let dir = |h: &(u32, u32, u32, u32)| triangles[h.2 as usize][h.3 as usize] == a;
                if dir(&half[k]) == dir(&half[k + 1]) {
                    return bad(format!(
                        "triangles {} and {} share edge ({a}, {b}) with the same orientation",
                        half[k].2,
                        half[k + 1].2
                    ));
                }
            }
            edges.push([a, b]);
            edge_tris.push(tris);
            edge_opposite.push(opp);
            k = m;
        }
        Ok(Self {
            edges,
            edge_tris,
            edge_opposite,
            tri_edges,
        })
    }
}

/// Node adjacency from the edges, CSR: `(offsets, neighbours, edges)`, node `i`'s neighbours
/// `neighbours[offsets[i]..offsets[i + 1]]` and the edges to them.
fn node_neighbours(n: usize, edges: &[[u32; 2]]) -> (Vec<u32>, Vec<u32>, Vec<u32>) {
    let mut nbr_offsets = vec![0u32; n + 1];
    for e in edges {
        nbr_offsets[e[0] as usize + 1] += 1;
        nbr_offsets[e[1] as usize + 1] += 1;
    }
    for i in 0..n {
        nbr_offsets[i + 1] += nbr_offsets[i];
    }
    let mut cursor = nbr_offsets.clone();
    let mut nbrs = vec![0u32; 2 * edges.len()];
    let mut nbr_edges = vec![0u32; 2 * edges.len()];
    for (e, &[a, b]) in edges.iter().enumerate() {
        for (p, q) in [(a, b), (b, a)] {
            let c = &mut cursor[p as usize];
            nbrs[*c as usize] = q;
            nbr_edges[*c as usize] = e as u32;
            *c += 1;
        }
    }
    (nbr_offsets, nbrs, nbr_edges)
}

/// The triangles at each node, CSR: `(offsets, triangles)`.
fn node_triangles(n: usize, triangles: &[[u32; 3]]) -> (Vec<u32>, Vec<u32>) {
    let mut tri_offsets = vec![0u32; n + 1];
    for t in triangles {
        for &i in t {
            tri_offsets[i as usize + 1] += 1;
        }
    }
    for i in 0..n {
        tri_offsets[i + 1] += tri_offsets[i];
    }
    let mut cursor = tri_offsets.clone();
    let mut node_tris = vec![0u32; 3 * triangles.len()];
    for (k, t) in triangles.iter().enumerate() {
        for &i in t {
            node_tris[cursor[i as usize] as usize] = k as u32;
            cursor[i as usize] += 1;
        }
    }
    (tri_offsets, node_tris)
}
