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
//! exists. Everything is sized at construction for the whole surface subdivided. A
//! [`Refinement`] holds the labels only, and remembers which triangles, edges and nodes it
//! labelled: [`Refinement::begin`] forgets exactly those and [`Refinement::finish`] labels the
//! new ones, so an update costs O(refined region) (the areas before and after), not
//! O(surface), and is allocation-free. The triangles and springs of the mixed-level mesh are
//! listed by [`Refinement::mesh`] (O(surface), for tools and tests); the body keeps its own copy
//! up to date by local edits (`super::mixed`).
//!
//! Neighbours: reads [`super::surface::SpringSurface`]; driven by the body and the calibration.

use super::prefaulted;
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

/// What a coarse triangle is in the mixed-level mesh.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TriangleState {
    /// Kept whole (level 0, no split edge).
    Kept,
    /// Split into four (level 1; "red").
    Split,
    /// Cut in two by the crack-filling edge from the type-2 node of side `s` (0: `(t0, t1)`, 1:
    /// `(t1, t2)`, 2: `(t2, t0)`) to the opposite vertex (level 0; "green").
    Cut(u8),
}

impl TriangleState {
    /// Number of pieces: 1 kept, 4 split, 2 cut.
    pub fn piece_count(self) -> usize {
        match self {
            Self::Kept => 1,
            Self::Split => 4,
            Self::Cut(_) => 2,
        }
    }

    /// The pieces of coarse triangle `tri` in this state, over slots; `m` the type-2 slots of
    /// its sides `(t0, t1)`, `(t1, t2)`, `(t2, t0)`. Outward oriented as `tri`. The first piece
    /// keeps the coarse triangle's place in the body's lists.
    pub fn pieces(self, tri: [u32; 3], m: [u32; 3]) -> ([[u32; 3]; 4], usize) {
        let [a, b, c] = tri;
        let z = [0; 3];
        match self {
            Self::Kept => ([tri, z, z, z], 1),
            Self::Split => (crate::mesh::split_triangle(tri, m[0], m[1], m[2]), 4),
            Self::Cut(0) => ([[a, m[0], c], [m[0], b, c], z, z], 2),
            Self::Cut(1) => ([[a, b, m[1]], [a, m[1], c], z, z], 2),
            Self::Cut(_) => ([[a, b, m[2]], [m[2], b, c], z, z], 2),
        }
    }
}

/// The triangles and springs of a mixed-level mesh ([`Refinement::mesh`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RefinedMesh {
    /// Triangles over slots, outward oriented: the pieces of each coarse triangle in coarse
    /// triangle order.
    pub triangles: Vec<[u32; 3]>,
    /// Mesh springs: each coarse edge (or its two halves), then the inner edges of each split
    /// triangle and the crack-filling edge of each cut one, in coarse triangle order.
    pub springs: Vec<SpringLink>,
}

/// The labels of a coarse triangle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct TriangleLabel {
    /// Split into four.
    red: bool,
    /// Split edges counted from split neighbours.
    split_count: u8,
    /// The centre slot owning a split triangle.
    owner: u8,
}

impl Default for TriangleLabel {
    fn default() -> Self {
        Self {
            red: false,
            split_count: 0,
            owner: NO_OWNER,
        }
    }
}

/// The current refinement: which coarse triangles are split, and the labels (module
/// documentation).
#[derive(Debug, Clone)]
pub struct Refinement {
    nc: u32,
    /// Per coarse triangle (one array: an event reads the three together).
    tri: Vec<TriangleLabel>,
    split: Vec<bool>,
    node_owner: Vec<u8>,
    /// Coarse triangles labelled since [`Refinement::begin`] (split, or with a split edge),
    /// ascending after [`Refinement::finish`].
    region: Vec<u32>,
    /// Split coarse edges, ascending after [`Refinement::finish`].
    active_edges: Vec<u32>,
    /// Type-1 nodes (the coarse nodes of split triangles).
    type1: Vec<u32>,
    queue: Vec<u32>,
    ring: Vec<(u32, u32)>,
    dist: Vec<u32>,
}

impl Refinement {
    /// The unrefined state of `surface`, with every buffer sized for the whole surface
    /// subdivided.
    pub fn new(surface: &SpringSurface) -> Self {
        let (n, t, e) = (
            surface.node_count(),
            surface.triangle_count(),
            surface.edge_count(),
        );
        Self {
            nc: n as u32,
            tri: vec![TriangleLabel::default(); t],
            split: prefaulted(false, e),
            node_owner: vec![NO_OWNER; n + e],
            region: Vec::with_capacity(t),
            active_edges: Vec::with_capacity(e),
            type1: Vec::with_capacity(n),
            queue: Vec::with_capacity(t),
            ring: Vec::with_capacity(n),
            dist: vec![u32::MAX; n],
        }
    }

    /// Starts a new refinement: forgets every split and label (O(labelled region)).
    pub fn begin(&mut self) {
        for &t in &self.region {
            let t = t as usize;
            self.tri[t] = TriangleLabel::default();
        }
        self.region.clear();
        for &e in &self.active_edges {
            self.split[e as usize] = false;
            self.node_owner[(self.nc + e) as usize] = NO_OWNER;
        }
        self.active_edges.clear();
        for &i in &self.type1 {
            self.node_owner[i as usize] = NO_OWNER;
        }
        self.type1.clear();
        self.queue.clear();
    }

    /// Marks coarse triangle `t` split, owned by `owner`, unless it already is.
    fn mark_red(&mut self, t: u32, owner: u8) {
        let k = t as usize;
        if self.tri[k].red {
            return;
        }
        if self.tri[k].split_count == 0 {
            self.region.push(t);
        }
        self.tri[k].red = true;
        self.tri[k].owner = owner;
        self.queue.push(t);
    }

    /// Asks for the triangles of the `rings`-ring of coarse node `centre` (those whose three
    /// vertices are in it) to be split, owned by centre slot `owner` unless an earlier request
    /// owns them. Call between [`Refinement::begin`] and [`Refinement::finish`]. O(ring).
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
                if tri.iter().all(|&k| self.dist[k as usize] == 0) {
                    self.mark_red(t, owner);
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
        self.mark_red(t, owner);
    }

    /// Closes the requested split set (no triangle left with two or three split edges) and
    /// sets the labels: split edges (type-2 nodes), the cut triangles (one split edge), the
    /// owners of type-1 and type-2 nodes. O(region), allocation-free.
    pub fn finish(&mut self, surface: &SpringSurface) {
        // Closure: split every edge of a split triangle; a neighbour with two split edges is
        // split too (and owned by the same centre).
        let mut head = 0;
        while head < self.queue.len() {
            let t = self.queue[head];
            head += 1;
            for e in surface.triangle_edges(t) {
                if self.split[e as usize] {
                    continue;
                }
                self.split[e as usize] = true;
                self.active_edges.push(e);
                for u in surface.edge_triangles(e) {
                    if u == NONE || u == t {
                        continue;
                    }
                    let k = u as usize;
                    if self.tri[k].split_count == 0 && !self.tri[k].red {
                        self.region.push(u);
                    }
                    self.tri[k].split_count += 1;
                    if !self.tri[k].red && self.tri[k].split_count >= 2 {
                        self.tri[k].red = true;
                        self.tri[k].owner = self.tri[t as usize].owner;
                        self.queue.push(u);
                    }
                }
            }
        }
        self.queue.clear();
        self.region.sort_unstable();
        self.active_edges.sort_unstable();
        // Owners of type-1 and type-2 nodes: the first split triangle (in coarse order) that
        // has them.
        let nc = self.nc;
        for &t in &self.region {
            if !self.tri[t as usize].red {
                continue;
            }
            let owner = self.tri[t as usize].owner;
            for &i in &surface.triangles()[t as usize] {
                if self.node_owner[i as usize] == NO_OWNER {
                    self.node_owner[i as usize] = owner;
                    self.type1.push(i);
                }
            }
            for e in surface.triangle_edges(t) {
                let slot = (nc + e) as usize;
                if self.node_owner[slot] == NO_OWNER {
                    self.node_owner[slot] = owner;
                }
            }
        }
    }

    /// What coarse triangle `t` is now.
    pub fn triangle_state(&self, surface: &SpringSurface, t: u32) -> TriangleState {
        if self.tri[t as usize].red {
            return TriangleState::Split;
        }
        if self.tri[t as usize].split_count == 0 {
            return TriangleState::Kept;
        }
        let te = surface.triangle_edges(t);
        match (0..3).find(|&s| self.split[te[s] as usize]) {
            Some(s) => TriangleState::Cut(s as u8),
            None => TriangleState::Kept,
        }
    }

    /// The centre slot that owns split triangle `t` ([`NO_OWNER`] when it is not split).
    pub fn triangle_owner(&self, t: u32) -> u8 {
        self.tri[t as usize].owner
    }

    /// The triangles and springs of the current mixed-level mesh (allocates; O(surface)).
    pub fn mesh(&self, surface: &SpringSurface) -> RefinedMesh {
        let nc = self.nc;
        let mut triangles = Vec::with_capacity(surface.triangle_count() + 3 * self.region.len());
        for (t, &tri) in surface.triangles().iter().enumerate() {
            let m = surface.triangle_edges(t as u32).map(|e| nc + e);
            let (pieces, count) = self.triangle_state(surface, t as u32).pieces(tri, m);
            triangles.extend_from_slice(&pieces[..count]);
        }
        let mut springs = Vec::with_capacity(surface.edge_count() + 4 * self.region.len());
        for (e, &[a, b]) in surface.edges().iter().enumerate() {
            if self.split[e] {
                let m = nc + e as u32;
                let owner = self.node_owner[m as usize];
                springs.push(SpringLink { i: a, j: m, owner });
                springs.push(SpringLink { i: m, j: b, owner });
            } else {
                springs.push(SpringLink {
                    i: a,
                    j: b,
                    owner: NO_OWNER,
                });
            }
        }
        for (t, &tri) in surface.triangles().iter().enumerate() {
            let m = surface.triangle_edges(t as u32).map(|e| nc + e);
            match self.triangle_state(surface, t as u32) {
                TriangleState::Kept => {}
                TriangleState::Split => {
                    let owner = self.tri[t].owner;
                    for s in 0..3 {
                        springs.push(SpringLink {
                            i: m[s],
                            j: m[(s + 1) % 3],
                            owner,
                        });
                    }
                }
                TriangleState::Cut(s) => {
                    let s = s as usize;
                    springs.push(SpringLink {
                        i: m[s],
                        j: tri[(s + 2) % 3],
                        owner: self.node_owner[m[s] as usize],
                    });
                }
            }
        }
        RefinedMesh { triangles, springs }
    }

    /// Number of coarse nodes (slots below it are coarse nodes).
    pub fn coarse_nodes(&self) -> u32 {
        self.nc
    }

    /// Coarse triangles that are split or cut, ascending.
    pub fn region(&self) -> &[u32] {
        &self.region
    }

    /// Coarse edges whose type-2 node exists, ascending (its slot is `N + e`).
    pub fn active_edges(&self) -> &[u32] {
        &self.active_edges
    }

    /// Type-1 nodes: the coarse nodes of the split triangles (in the order they were labelled).
    pub fn type1_nodes(&self) -> &[u32] {
        &self.type1
    }

    /// Whether coarse triangle `t` is split into four (its subdivision level is 1).
    pub fn is_split(&self, t: u32) -> bool {
        self.tri[t as usize].red
    }

    /// Whether coarse edge `e` carries a type-2 node.
    pub fn is_edge_split(&self, e: u32) -> bool {
        self.split[e as usize]
    }

    /// The coarse triangle's level: 1 when split into four, 0 otherwise (also for the
    /// crack-filling halves).
    pub fn triangle_level(&self, t: u32) -> u8 {
        u8::from(self.tri[t as usize].red)
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
        self.type1.len()
    }

    /// Type-2 nodes (one per split edge): N' - N of eq. 3.
    pub fn type2_count(&self) -> usize {
        self.active_edges.len()
    }
}
