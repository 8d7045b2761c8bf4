//! Run-time refinement of the coarse surface around contact nodes (section 3.1 and Figure 4 of
//! Zhang, Payandeh & Dill): the triangles of the n-ring of each centre node are split into four
//! (one Loop step: a type-2 node on each edge), and the neighbouring triangles that got split
//! edges are closed so that no crack opens:
//!
//! - a triangle with two or three split edges is split into four too (repeated until none is
//!   left: the "red" set is closed);
//! - a triangle with exactly one split edge is cut in two by a new edge from that edge's
//!   type-2 node to the opposite vertex (the paper's grey crack-filling edges; "green").
//!
//! Every coarse triangle carries its subdivision level (0 or 1), every node its level (0, or 1
//! inside a subdivided area), and refinement is always recomputed from the coarse level: two
//! centres whose rings overlap split the shared triangles once, never twice (the paper's labels
//! "checked against the current subdivision level ... so that ... the area in between is not
//! over-subdivided"). Coarsening is the same computation with fewer centres.
//!
//! Node numbering is stable ("slots"): coarse node `i` is slot `i`, the type-2 node of coarse
//! edge `e` is slot `N + e`, so a node keeps its index (and state) across events while it
//! exists. Everything is sized at construction for the whole surface subdivided; an update is
//! allocation-free and costs O(triangles + edges).
//!
//! Neighbours: reads [`super::surface::SpringSurface`]; driven by the body and the calibration.

use super::surface::{NONE, SpringSurface};

/// Owner value of nodes, triangles and springs outside every subdivided area.
pub const NO_OWNER: u8 = u8::MAX;

/// A mesh spring of the current (mixed-level) mesh: nodes as slots, and the centre whose
/// subdivided area it belongs to ([`NO_OWNER`] for an original coarse edge, constant `K_m`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpringLink {
    /// First node (slot).
    pub i: u32,
    /// Second node (slot).
    pub j: u32,
    /// Owning centre, or [`NO_OWNER`].
    pub owner: u8,
}

/// The current refinement: which coarse triangles are split, the resulting triangles, springs
/// and labels (module documentation).
#[derive(Debug, Clone)]
pub struct Refinement {
    nc: u32,
    red: Vec<bool>,
    green_edge: Vec<u8>,
    split_count: Vec<u8>,
    tri_owner: Vec<u8>,
    split: Vec<bool>,
    node_owner: Vec<u8>,
    type1_count: usize,
    active_edges: Vec<u32>,
    triangles: Vec<[u32; 3]>,
    springs: Vec<SpringLink>,
    queue: Vec<u32>,
    ring: Vec<(u32, u32)>,
    dist: Vec<u32>,
}

impl Refinement {
    /// The unrefined state of `surface`, with every buffer sized for the whole surface
    /// subdivided (4 triangles per coarse triangle, a node per edge).
    pub fn new(surface: &SpringSurface) -> Self {
        let (n, t, e) = (
            surface.node_count(),
            surface.triangle_count(),
            surface.edge_count(),
        );
        let mut r = Self {
            nc: n as u32,
            red: vec![false; t],
            green_edge: vec![3; t],
            split_count: vec![0; t],
            tri_owner: vec![NO_OWNER; t],
            split: vec![false; e],
            node_owner: vec![NO_OWNER; n + e],
            type1_count: 0,
            active_edges: Vec::with_capacity(e),
            triangles: Vec::with_capacity(4 * t),
            springs: Vec::with_capacity(2 * e + 3 * t),
            queue: Vec::with_capacity(t),
            ring: Vec::with_capacity(n),
            dist: vec![u32::MAX; n],
        };
        r.begin();
        r.finish(surface);
        r
    }

    /// Starts a new refinement: forgets every split (O(triangles + edges)).
    pub fn begin(&mut self) {
        self.red.iter_mut().for_each(|r| *r = false);
        self.green_edge.iter_mut().for_each(|g| *g = 3);
        self.split_count.iter_mut().for_each(|c| *c = 0);
        self.tri_owner.iter_mut().for_each(|o| *o = NO_OWNER);
        self.split.iter_mut().for_each(|s| *s = false);
        self.queue.clear();
    }

    /// Asks for the triangles of the `rings`-ring of coarse node `centre` (those whose three
    /// vertices are in it) to be split, owned by centre slot `owner` unless an earlier request
    /// owns them. Call between [`Refinement::begin`] and [`Refinement::finish`].
    pub fn request_ring(&mut self, surface: &SpringSurface, centre: u32, rings: u32, owner: u8) {
        if rings == 0 {
            return;
        }
        let mut ring = std::mem::take(&mut self.ring);
        surface.ring(centre, rings, &mut self.dist, &mut ring);
        for &(i, _) in &ring {
            self.dist[i as usize] = 0;
        }
        for &(i, _) in &ring {
            for &t in surface.triangles_at(i) {
                let tri = surface.triangles()[t as usize];
                if !self.red[t as usize] && tri.iter().all(|&k| self.dist[k as usize] == 0) {
                    self.red[t as usize] = true;
                    self.tri_owner[t as usize] = owner;
                    self.queue.push(t);
                }
            }
        }
        for &(i, _) in &ring {
            self.dist[i as usize] = u32::MAX;
        }
        self.ring = ring;
    }

    /// Asks for coarse triangle `t` to be split, owned by `owner` (tests and tools).
    pub fn request_triangle(&mut self, t: u32, owner: u8) {
        if !self.red[t as usize] {
            self.red[t as usize] = true;
            self.tri_owner[t as usize] = owner;
            self.queue.push(t);
        }
    }

    /// Closes the requested red set (no triangle left with two or three split edges), marks
    /// the green (one split edge) triangles, and builds the triangles, springs, active type-2
    /// nodes and labels. Allocation-free.
    pub fn finish(&mut self, surface: &SpringSurface) {
        // Closure: split every edge of a red triangle; a neighbour with two split edges turns
        // red (and owned by the same centre).
        let mut head = 0;
        while head < self.queue.len() {
            let t = self.queue[head];
            head += 1;
            for e in surface.triangle_edges(t) {
                if self.split[e as usize] {
                    continue;
                }
                self.split[e as usize] = true;
                for u in surface.edge_triangles(e) {
                    if u == NONE || u == t {
                        continue;
                    }
                    self.split_count[u as usize] += 1;
                    if !self.red[u as usize] && self.split_count[u as usize] >= 2 {
                        self.red[u as usize] = true;
                        self.tri_owner[u as usize] = self.tri_owner[t as usize];
                        self.queue.push(u);
                    }
                }
            }
        }
        self.queue.clear();
        let nc = self.nc;
        // Labels: owners of type-1 and type-2 nodes.
        self.node_owner.iter_mut().for_each(|o| *o = NO_OWNER);
        self.type1_count = 0;
        for (t, tri) in surface.triangles().iter().enumerate() {
            if !self.red[t] {
                continue;
            }
            let owner = self.tri_owner[t];
            for &i in tri {
                if self.node_owner[i as usize] == NO_OWNER {
                    self.node_owner[i as usize] = owner;
                    self.type1_count += 1;
                }
            }
            for e in surface.triangle_edges(t as u32) {
                let slot = (nc + e) as usize;
                if self.node_owner[slot] == NO_OWNER {
                    self.node_owner[slot] = owner;
                }
            }
        }
        self.active_edges.clear();
        for (e, &s) in self.split.iter().enumerate() {
            if s {
                self.active_edges.push(e as u32);
            }
        }
        // Triangles, in coarse triangle order; greens.
        self.triangles.clear();
        for (t, tri) in surface.triangles().iter().enumerate() {
            let [a, b, c] = *tri;
            let te = surface.triangle_edges(t as u32);
            let m = te.map(|e| nc + e);
            if self.red[t] {
                self.triangles
                    .extend(crate::mesh::split_triangle(*tri, m[0], m[1], m[2]));
                continue;
            }
            let split_side = (0..3).find(|&s| self.split[te[s] as usize]);
            match split_side {
                None => self.triangles.push(*tri),
                Some(s) => {
                    self.green_edge[t] = s as u8;
                    match s {
                        0 => self.triangles.extend([[a, m[0], c], [m[0], b, c]]),
                        1 => self.triangles.extend([[a, b, m[1]], [a, m[1], c]]),
                        _ => self.triangles.extend([[a, b, m[2]], [m[2], b, c]]),
                    }
                }
            }
        }
        // Springs: coarse or halved edges, the three inner edges of red triangles, the
        // crack-filling edge of green ones.
        self.springs.clear();
        for (e, &[a, b]) in surface.edges().iter().enumerate() {
            if self.split[e] {
                let m = nc + e as u32;
                let owner = self.node_owner[m as usize];
                self.springs.push(SpringLink { i: a, j: m, owner });
                self.springs.push(SpringLink { i: m, j: b, owner });
            } else {
                self.springs.push(SpringLink {
                    i: a,
                    j: b,
                    owner: NO_OWNER,
                });
            }
        }
        for (t, tri) in surface.triangles().iter().enumerate() {
            let m = surface.triangle_edges(t as u32).map(|e| nc + e);
            if self.red[t] {
                let owner = self.tri_owner[t];
                for s in 0..3 {
                    self.springs.push(SpringLink {
                        i: m[s],
                        j: m[(s + 1) % 3],
                        owner,
                    });
                }
            } else if self.green_edge[t] < 3 {
                let s = self.green_edge[t] as usize;
                let opposite = tri[(s + 2) % 3];
                self.springs.push(SpringLink {
                    i: m[s],
                    j: opposite,
                    owner: self.node_owner[m[s] as usize],
                });
            }
        }
    }

    /// Number of coarse nodes (slots below it are coarse nodes).
    pub fn coarse_nodes(&self) -> u32 {
        self.nc
    }

    /// Triangles of the current mesh, over slots, outward oriented.
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.triangles
    }

    /// Mesh springs of the current mesh.
    pub fn springs(&self) -> &[SpringLink] {
        &self.springs
    }

    /// Coarse edges whose type-2 node exists, ascending (its slot is `N + e`).
    pub fn active_edges(&self) -> &[u32] {
        &self.active_edges
    }

    /// Whether coarse triangle `t` is split into four (its subdivision level is 1).
    pub fn is_split(&self, t: u32) -> bool {
        self.red[t as usize]
    }

    /// Whether coarse edge `e` carries a type-2 node.
    pub fn is_edge_split(&self, e: u32) -> bool {
        self.split[e as usize]
    }

    /// The coarse triangle's level: 1 when split into four, 0 otherwise (also for the
    /// crack-filling halves).
    pub fn triangle_level(&self, t: u32) -> u8 {
        u8::from(self.red[t as usize])
    }

    /// The centre slot whose subdivided area slot `s` belongs to, or [`NO_OWNER`].
    pub fn node_owner(&self, s: u32) -> u8 {
        self.node_owner[s as usize]
    }

    /// A node's subdivision level: 1 inside a subdivided area (type-1 and type-2 nodes), 0
    /// elsewhere.
    pub fn node_level(&self, s: u32) -> u8 {
        u8::from(self.node_owner[s as usize] != NO_OWNER)
    }

    /// Type-1 nodes (original nodes of split triangles): N of eq. 3.
    pub fn type1_count(&self) -> usize {
        self.type1_count
    }

    /// Type-2 nodes (one per split edge): N' - N of eq. 3.
    pub fn type2_count(&self) -> usize {
        self.active_edges.len()
    }
}
