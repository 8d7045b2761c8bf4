//! Loop subdivision weights (C. Loop, *Smooth Subdivision Surfaces Based on Triangles*, MS
//! thesis, University of Utah, 1987; Zhang, Payandeh & Dill section 3.1 and Figure 3).
//!
//! Subdividing a triangle once makes two kinds of new nodes: **type-1** nodes, one per original
//! node, and **type-2** nodes, one per original edge. Every new position is a weighted sum of
//! nearby original positions; the weights sum to 1 (so the rules reproduce translations and,
//! on a flat regular mesh, every affine function):
//!
//! - type-1, interior node P of valence K: `(1 - K beta) P + beta sum(neighbours)` with
//!   `beta(K) = (1/K) (5/8 - (3/8 + 1/4 cos(2 pi / K))^2)` (Loop's weight; `beta(3) = 3/16`,
//!   `beta(6) = 1/16`);
//! - type-2, interior edge (a, b) with opposite vertices c, d: `3/8 (a + b) + 1/8 (c + d)`;
//! - on the rim (boundary) the cubic B-spline rules: type-1 `3/4 P + 1/8 (P- + P+)` over the
//!   two rim neighbours, type-2 the edge midpoint `1/2 (a + b)`.
//!
//! The body uses the type-2 rule for the rest position of every new edge node and, with
//! [`super::VertexRule::Loop`], the type-1 rule for the rest position of the original nodes of
//! a subdivided area ([`super::VertexRule`] says why that is not the default).
//!
//! Neighbours: reads [`super::surface::SpringSurface`]; used by [`super::refine`] and the body.

use std::f64::consts::TAU;

use glam::DVec3;

use super::surface::{NONE, SpringSurface};

/// Loop's weight `beta` of each neighbour of an interior type-1 node of valence `k`:
/// `(1/K) (5/8 - (3/8 + 1/4 cos(2 pi / K))^2)`.
///
/// # Panics
/// If `k < 3` (no interior vertex of a manifold triangle mesh has fewer neighbours).
pub fn loop_beta(k: u32) -> f64 {
    assert!(
        k >= 3,
        "an interior vertex has at least 3 neighbours, got {k}"
    );
    let kf = f64::from(k);
    let c = 3.0 / 8.0 + 0.25 * (TAU / kf).cos();
    (5.0 / 8.0 - c * c) / kf
}

/// One weighted original node of a stencil.
pub type Weighted = (u32, f64);

/// The type-1 (vertex) stencil of node `i`: `(node, weight)` pairs into `out` (cleared first),
/// weights summing to 1. Interior nodes use Loop's `beta(K)`; rim nodes the boundary rule.
pub fn vertex_stencil(surface: &SpringSurface, i: u32, out: &mut Vec<Weighted>) {
    out.clear();
    if surface.is_boundary(i) {
        out.push((i, 0.75));
        for (&j, &e) in surface.neighbours(i).iter().zip(surface.incident_edges(i)) {
            if surface.is_boundary_edge(e) {
                out.push((j, 0.125));
            }
        }
        return;
    }
    let k = surface.valence(i);
    let beta = loop_beta(k);
    out.push((i, 1.0 - f64::from(k) * beta));
    for &j in surface.neighbours(i) {
        out.push((j, beta));
    }
}

/// The type-2 (edge) stencil of edge `e`: `3/8, 3/8, 1/8, 1/8` over its end points and
/// opposite vertices for an interior edge, `1/2, 1/2` (and two zero-weight entries repeating
/// the end points) for a rim edge. The weights sum to 1.
pub fn edge_stencil(surface: &SpringSurface, e: u32) -> [Weighted; 4] {
    let [a, b] = surface.edges()[e as usize];
    let [c, d] = surface.edge_opposite(e);
    if d == NONE {
        [(a, 0.5), (b, 0.5), (a, 0.0), (b, 0.0)]
    } else {
        [(a, 0.375), (b, 0.375), (c, 0.125), (d, 0.125)]
    }
}

/// Applies a stencil to positions `x`.
pub fn apply(stencil: &[Weighted], x: &[DVec3]) -> DVec3 {
    stencil.iter().map(|&(i, w)| x[i as usize] * w).sum()
}

/// Rest positions of every type-2 node (one per edge, by [`edge_stencil`]) and of every type-1
/// node (one per node, by [`vertex_stencil`]) of a whole-surface Loop step, m. Fixed nodes keep
/// their position (a clamped rim stays where it is clamped).
pub fn loop_rest_positions(surface: &SpringSurface) -> (Vec<DVec3>, Vec<DVec3>) {
    let rest = surface.rest();
    let edges = (0..surface.edge_count() as u32)
        .map(|e| apply(&edge_stencil(surface, e), rest))
        .collect();
    let mut stencil = Vec::new();
    let vertices = (0..surface.node_count() as u32)
        .map(|i| {
            if surface.is_fixed(i) {
                rest[i as usize]
            } else {
                vertex_stencil(surface, i, &mut stencil);
                apply(&stencil, rest)
            }
        })
        .collect();
    (edges, vertices)
}
