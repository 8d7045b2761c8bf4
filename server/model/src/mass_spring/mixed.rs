//! The mixed-level mesh the body's tick runs on: the mesh springs, the triangles (the probe's
//! contact surface, and the viewer's copy over compact vertex indices) and the active nodes.
//! They always list what [`super::refine::Refinement::mesh`] would list for the current
//! labels, but are kept so by **local edits**: an event rebuilds only the coarse triangles and
//! edges whose state changed, in time proportional to the subdivided areas, not to the
//! surface.
//!
//! Layout: spring `e < E` is coarse edge `e` (its first half while it is split); triangle
//! `t < T` is coarse triangle `t` (its first piece while it is split or cut). The other springs
//! (second halves, the inner edges of split triangles, crack-filling edges) and pieces are
//! appended, and removed by swap-remove; each appended entry carries a back reference (its
//! *key*) so that the entry moved into the hole is re-pointed in O(1). Once every area is
//! coarsened the lists are the coarse ones in coarse order again. The viewer's vertices are
//! the coarse nodes, then the active type-2 nodes in the order they appeared (swap-removed
//! too); the viewer triangles whose vertices moved are re-indexed.
//!
//! Neighbours: reads [`super::surface`] and [`super::refine`]; edits the probe's
//! [`ContactSurface`] (built with room per node); owned by [`super::body`].

use glam::DVec3;

use super::refine::{NO_OWNER, Refinement, TriangleState};
use super::surface::{NONE, SpringSurface};
use super::{prefaulted, prefaulted_capacity};
use crate::contact::ContactSurface;

/// A mesh spring of the current mesh with its rest length and owning centre ([`NO_OWNER`]:
/// the coarse constant `K_m`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct RtSpring {
    pub i: u32,
    pub j: u32,
    pub rest_length_m: f64,
    pub owner: u8,
}

/// The extra springs of a coarse triangle in `state`: the inner edges of a split one, the
/// crack-filling edge of a cut one.
fn spring_count(state: TriangleState) -> usize {
    match state {
        TriangleState::Kept => 0,
        TriangleState::Split => 3,
        TriangleState::Cut(_) => 1,
    }
}

/// A coarse triangle as built (one struct: an event reads these together).
#[derive(Debug, Clone, Copy)]
struct BuiltTriangle {
    state: TriangleState,
    /// The triangle indices of its pieces after the first (`NONE` beyond).
    extra_tris: [u32; 3],
    /// The spring indices of its inner or crack-filling springs.
    extra_springs: [u32; 3],
}

/// The mixed-level mesh (module documentation).
#[derive(Debug, Clone)]
pub(crate) struct MixedMesh {
    nc: u32,
    nt: u32,
    ne: u32,
    /// Per coarse triangle, as built.
    tris: Vec<BuiltTriangle>,
    /// Per coarse edge: the spring index of its second half (`NONE` when whole).
    half: Vec<u32>,
    /// Per triangle index: the key of an appended piece, `3 t + k` for piece `k + 1` of `t`.
    tri_key: Vec<u32>,
    /// Per spring index: the key of an appended spring, `e` for the second half of edge `e`,
    /// `E + 3 t + k` for the `k`-th extra spring of triangle `t`.
    spring_key: Vec<u32>,
    springs: Vec<RtSpring>,
    /// Active slots (the coarse nodes, then the active type-2 nodes): the viewer's vertices.
    active: Vec<u32>,
    slot_to_view: Vec<u32>,
    /// The triangles over viewer vertex indices, index for index as the contact surface's.
    view: Vec<[u32; 3]>,
    /// Triangle indices whose viewer copy must be re-indexed, with stamps against repeats.
    dirty: Vec<u32>,
    dirty_stamp: Vec<u32>,
    stamp: u32,
    /// Type-2 slots whose viewer index changed in the current edit.
    moved: Vec<u32>,
}

impl MixedMesh {
    /// The coarse mesh of `surface` over rest positions `rest` (per slot, m), and the contact
    /// surface holding its triangles (over slots, with room for every mixed-level mesh).
    pub fn new(surface: &SpringSurface, rest: &[DVec3]) -> (Self, ContactSurface) {
        let (nc, nt, ne) = (
            surface.node_count(),
            surface.triangle_count(),
            surface.edge_count(),
        );
        // A coarse node is in at most two pieces of each of its triangles (the opposite vertex
        // of a cut side), a type-2 node in three of each triangle of its edge.
        let mut room: Vec<u32> = (0..nc as u32)
            .map(|i| 2 * surface.triangles_at(i).len() as u32)
            .collect();
        room.extend((0..ne as u32).map(|e| {
            3 * surface
                .edge_triangles(e)
                .iter()
                .filter(|&&t| t != NONE)
                .count() as u32
        }));
        let mut contact = ContactSurface::with_node_room(4 * nt, &room);
        let max_springs = 2 * ne + 3 * nt;
        let mut mesh = Self {
            nc: nc as u32,
            nt: nt as u32,
            ne: ne as u32,
            tris: vec![
                BuiltTriangle {
                    state: TriangleState::Kept,
                    extra_tris: [NONE; 3],
                    extra_springs: [NONE; 3],
                };
                nt
            ],
            half: vec![NONE; ne],
            tri_key: prefaulted_capacity(NONE, 4 * nt),
            spring_key: prefaulted_capacity(NONE, max_springs),
            springs: prefaulted_capacity(
                RtSpring {
                    i: 0,
                    j: 0,
                    rest_length_m: 0.0,
                    owner: NO_OWNER,
                },
                max_springs,
            ),
            active: prefaulted_capacity(NONE, nc + ne),
            slot_to_view: vec![NONE; nc + ne],
            view: prefaulted_capacity([NONE; 3], 4 * nt),
            dirty: prefaulted_capacity(NONE, 4 * nt),
            dirty_stamp: prefaulted(0, 4 * nt),
            stamp: 0,
            moved: Vec::with_capacity(ne),
        };
        for (e, &[a, b]) in surface.edges().iter().enumerate() {
            mesh.springs.push(RtSpring {
                i: a,
                j: b,
                rest_length_m: (rest[b as usize] - rest[a as usize]).length(),
                owner: NO_OWNER,
            });
            mesh.spring_key.push(e as u32);
        }
        for &t in surface.triangles() {
            contact.push_triangle(t);
            mesh.view.push(t);
            mesh.tri_key.push(NONE);
        }
        mesh.active.extend(0..nc as u32);
        for i in 0..nc {
            mesh.slot_to_view[i] = i as u32;
        }
        (mesh, contact)
    }

    /// The mesh springs.
    pub fn springs(&self) -> &[RtSpring] {
        &self.springs
    }

    /// Active slots: the viewer's vertices in order.
    pub fn active(&self) -> &[u32] {
        &self.active
    }

    /// Whether slot `s` is active.
    pub fn is_active(&self, s: u32) -> bool {
        self.slot_to_view[s as usize] != NONE
    }

    /// The triangles over viewer vertex indices.
    pub fn view_triangles(&self) -> &[[u32; 3]] {
        &self.view
    }

    /// Whether coarse edge `e` is split as built.
    pub fn is_edge_split(&self, e: u32) -> bool {
        self.half[e as usize] != NONE
    }

    /// The coarse triangle whose piece triangle index `k` is.
    pub fn coarse_triangle_of(&self, k: u32) -> u32 {
        if k < self.nt {
            k
        } else {
            self.tri_key[k as usize] / 3
        }
    }

    /// Calls `f` with the index of every spring of coarse edge `e` (one, or its two halves).
    pub fn edge_springs(&self, e: u32, mut f: impl FnMut(usize)) {
        f(e as usize);
        let h = self.half[e as usize];
        if h != NONE {
            f(h as usize);
        }
    }

    /// Calls `f` with the index of every inner or crack-filling spring of coarse triangle `t`.
    pub fn triangle_springs(&self, t: u32, mut f: impl FnMut(usize)) {
        let t = t as usize;
        for &k in &self.tris[t].extra_springs[..spring_count(self.tris[t].state)] {
            f(k as usize);
        }
    }

    fn spring_ref(&mut self, key: u32) -> &mut u32 {
        if key < self.ne {
            &mut self.half[key as usize]
        } else {
            let k = key - self.ne;
            &mut self.tris[(k / 3) as usize].extra_springs[(k % 3) as usize]
        }
    }

    fn push_spring(&mut self, i: u32, j: u32, key: u32) -> u32 {
        self.springs.push(RtSpring {
            i,
            j,
            rest_length_m: 0.0,
            owner: NO_OWNER,
        });
        self.spring_key.push(key);
        self.springs.len() as u32 - 1
    }

    fn remove_spring(&mut self, k: u32) {
        self.springs.swap_remove(k as usize);
        self.spring_key.swap_remove(k as usize);
        if (k as usize) < self.springs.len() {
            let key = self.spring_key[k as usize];
            *self.spring_ref(key) = k;
        }
    }

    fn mark_dirty(&mut self, k: u32) {
        if self.dirty_stamp[k as usize] != self.stamp {
            self.dirty_stamp[k as usize] = self.stamp;
            self.dirty.push(k);
        }
    }

    fn push_triangle(&mut self, contact: &mut ContactSurface, tri: [u32; 3], key: u32) -> u32 {
        contact.push_triangle(tri);
        self.view.push([0; 3]);
        self.tri_key.push(key);
        let k = self.view.len() as u32 - 1;
        self.mark_dirty(k);
        k
    }

    fn remove_triangle(&mut self, contact: &mut ContactSurface, k: u32) {
        contact.swap_remove_triangle(k);
        self.view.swap_remove(k as usize);
        self.tri_key.swap_remove(k as usize);
        if (k as usize) < self.view.len() {
            let key = self.tri_key[k as usize];
            self.tris[(key / 3) as usize].extra_tris[(key % 3) as usize] = k;
            self.mark_dirty(k);
        }
    }

    /// Starts an edit.
    pub fn begin(&mut self) {
        self.stamp = self.stamp.wrapping_add(1);
        if self.stamp == 0 {
            self.dirty_stamp.fill(0);
            self.stamp = 1;
        }
        self.dirty.clear();
        self.moved.clear();
    }

    /// Rebuilds coarse triangle `t` as `refinement` labels it, if its state changed: its
    /// pieces and extra springs (their rest lengths and owners are set by
    /// [`MixedMesh::refresh_triangle`]). O(1).
    pub fn update_triangle(
        &mut self,
        surface: &SpringSurface,
        refinement: &Refinement,
        contact: &mut ContactSurface,
        t: u32,
    ) {
        let new = refinement.triangle_state(surface, t);
        let old = self.tris[t as usize].state;
        if new == old {
            return;
        }
        let tu = t as usize;
        let old_count = old.piece_count();
        for k in (0..old_count - 1).rev() {
            let idx = self.tris[tu].extra_tris[k];
            self.remove_triangle(contact, idx);
            self.tris[tu].extra_tris[k] = NONE;
        }
        for k in (0..spring_count(old)).rev() {
            let idx = self.tris[tu].extra_springs[k];
            self.remove_spring(idx);
            self.tris[tu].extra_springs[k] = NONE;
        }
        let tri = surface.triangles()[tu];
        let m = surface.triangle_edges(t).map(|e| self.nc + e);
        let (pieces, count) = new.pieces(tri, m);
        contact.set_triangle(t, pieces[0]);
        self.mark_dirty(t);
        for (k, &piece) in pieces[1..count].iter().enumerate() {
            self.tris[tu].extra_tris[k] = self.push_triangle(contact, piece, 3 * t + k as u32);
        }
        let key = self.ne + 3 * t;
        match new {
            TriangleState::Kept => {}
            TriangleState::Split => {
                for s in 0..3 {
                    self.tris[tu].extra_springs[s] =
                        self.push_spring(m[s], m[(s + 1) % 3], key + s as u32);
                }
            }
            TriangleState::Cut(s) => {
                let s = s as usize;
                self.tris[tu].extra_springs[0] = self.push_spring(m[s], tri[(s + 2) % 3], key);
            }
        }
        self.tris[tu].state = new;
    }

    /// Splits or joins coarse edge `e` as `refinement` labels it, and (de)activates its
    /// type-2 node. O(1).
    pub fn update_edge(&mut self, surface: &SpringSurface, refinement: &Refinement, e: u32) {
        let split = refinement.is_edge_split(e);
        if split == self.is_edge_split(e) {
            return;
        }
        let [a, b] = surface.edges()[e as usize];
        let m = self.nc + e;
        if split {
            self.springs[e as usize].j = m;
            self.half[e as usize] = self.push_spring(m, b, e);
            self.slot_to_view[m as usize] = self.active.len() as u32;
            self.active.push(m);
        } else {
            self.remove_spring(self.half[e as usize]);
            self.half[e as usize] = NONE;
            self.springs[e as usize].j = b;
            let v = self.slot_to_view[m as usize];
            self.slot_to_view[m as usize] = NONE;
            self.active.swap_remove(v as usize);
            if let Some(&moved) = self.active.get(v as usize) {
                self.slot_to_view[moved as usize] = v;
                self.moved.push(moved);
            }
        }
        debug_assert_eq!(self.springs[e as usize].i, a);
    }

    /// Sets the rest lengths (from `rest`, m per slot) and owners (`owner` per slot) of the
    /// springs of coarse edge `e`: whole, `K_m`; halves, their type-2 node's owner.
    pub fn refresh_edge(&mut self, e: u32, rest: &[DVec3], owner: &[u8]) {
        let h = self.half[e as usize];
        let o = if h == NONE {
            NO_OWNER
        } else {
            owner[(self.nc + e) as usize]
        };
        for k in [e, h] {
            if k == NONE {
                continue;
            }
            let sp = &mut self.springs[k as usize];
            sp.rest_length_m = (rest[sp.j as usize] - rest[sp.i as usize]).length();
            sp.owner = o;
        }
    }

    /// Sets the rest lengths and owners of the inner springs of coarse triangle `t` (the
    /// triangle's owner in `refinement`) or of its crack-filling spring (its type-2 node's
    /// owner).
    pub fn refresh_triangle(
        &mut self,
        refinement: &Refinement,
        t: u32,
        rest: &[DVec3],
        owner: &[u8],
    ) {
        let tu = t as usize;
        let state = self.tris[tu].state;
        for k in 0..spring_count(state) {
            let sp = &mut self.springs[self.tris[tu].extra_springs[k] as usize];
            sp.rest_length_m = (rest[sp.j as usize] - rest[sp.i as usize]).length();
            sp.owner = match state {
                TriangleState::Split => refinement.triangle_owner(t),
                _ => owner[sp.i as usize],
            };
        }
    }

    /// Ends an edit: re-indexes the viewer triangles that changed or whose vertices moved.
    pub fn finish(&mut self, surface: &SpringSurface, contact: &ContactSurface) {
        for k in 0..self.moved.len() {
            let e = self.moved[k] - self.nc;
            for t in surface.edge_triangles(e) {
                if t == NONE {
                    continue;
                }
                self.mark_dirty(t);
                let count = self.tris[t as usize].state.piece_count();
                for j in 0..count - 1 {
                    self.mark_dirty(self.tris[t as usize].extra_tris[j]);
                }
            }
        }
        for &k in &self.dirty {
            if let Some(v) = self.view.get_mut(k as usize) {
                *v = contact.triangles[k as usize].map(|s| self.slot_to_view[s as usize]);
            }
        }
    }
}
