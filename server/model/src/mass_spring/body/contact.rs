//! The organ table at each tool's contact: the sphere depth, the probe's foot on the coarse
//! rest surface and the contact factor ([`crate::mass_spring::organ`]).

use super::MassSpringBody;
use crate::mass_spring::organ::OrganTable;
use crate::mass_spring::organ::foot::RestFoot;
use crate::mass_spring::organ::foot::foot_depth_m;
use crate::mass_spring::organ::foot::rest_foot;
use crate::mass_spring::refine::NO_OWNER;
use glam::DVec3;

impl MassSpringBody {
    /// Tool slot `k`'s sphere depth ([`MassSpringBody::contact_depth_m`]: below the organ at
    /// the foot, the kernel plane's travel without a foot) and the
    /// contact factor at its current contact: the organ table at that depth, interpolated at
    /// the foot of the kernel patch's centroid ([`MassSpringBody::patch_foot`]) on the coarse
    /// surface, at the probe's foot ([`crate::mass_spring::organ::foot`]) when its triangle
    /// touches a subdivided area (session 16; session 15 the patch's centroid there too), over
    /// its coarse triangle's Loop children ([`MassSpringBody::organ_factor_at`]). Off the rest
    /// surface (no foot), at the contact point of the deformed surface (the probe's triangle).
    /// Unchanged out of contact; the factor unchanged without a table. Allocation-free.
    pub(super) fn update_contact_factor(&mut self, k: usize) {
        let st = self.state.tools[k].probe.state;
        if !st.in_contact {
            return;
        }
        self.update_foot(k);
        // Wherever the probe has a foot, the sphere's depth below the organ there: below the
        // flat rest triangle plus the organ's height over it (the arcs over its edges; session
        // 12 in subdivided areas: without it a press between nodes near the LV's apex, 0.09 mm
        // of sag, read the table 0.09 mm shallow, -45 % at 0.25 mm; session 13 on the coarse
        // surface too: the kernel plane's travel ran 0.02 mm ahead of the sphere's depth at
        // the lv-probe point, between nodes, +10 % at 0.25 mm). Without a foot, the kernel
        // plane's travel.
        let depth = match &self.state.tools[k].foot {
            Some(foot) => {
                foot_depth_m(foot, self.state.tools[k].probe.params.radius_m)
                    + self.organ_height_m(foot)
            }
            None => {
                let (nodes, weights) = self.state.tools[k].probe.patch();
                nodes
                    .iter()
                    .zip(weights)
                    .map(|(&i, &w)| {
                        w * (self.state.rest[i as usize] - self.state.x[i as usize]).dot(st.normal)
                    })
                    .sum()
            }
        };
        self.state.tools[k].contact_depth_m = depth;
        let Some(table) = &self.model.organ else {
            return;
        };
        // On the coarse surface at the patch's centroid ([`MassSpringBody::patch_foot`], session
        // 6); in a subdivided area at the proxy's foot (session 16, with the corner children's
        // sites: a press along a child site's normal has its foot there, where the patch's
        // centroid lies nearer the node; session 15 read the patch's centroid there too, with
        // no child sites: on the 4 mm hemisphere the proxy's foot at h4 read the two edge
        // midpoints' subdivided rows for 77 %, whose presses bear on one type-2 node).
        let proxy = self.state.tools[k].foot;
        let subdivided = |f: &RestFoot| {
            let tri = self.model.surface.triangles()[f.triangle as usize];
            tri.iter()
                .any(|&s| self.state.owner[s as usize] != NO_OWNER)
        };
        let at = if proxy.as_ref().is_some_and(subdivided) {
            proxy
        } else {
            self.patch_foot(k).or(proxy)
        };
        let beta = match at {
            Some(foot) => {
                let tri = self.model.surface.triangles()[foot.triangle as usize];
                self.organ_factor_at(table, (tri, foot.bary), Some(foot.triangle), depth)
            }
            None => {
                let tri = self.state.tools[k]
                    .probe
                    .surface
                    .triangles
                    .get(st.triangle as usize);
                let Some(&tri) = tri else {
                    return;
                };
                let nc = self.model.surface.node_count() as u32;
                if tri.iter().all(|&s| s < nc) {
                    // A coarse triangle: over its Loop children, without the child sites.
                    self.organ_factor_at(table, (tri, st.bary), None, depth)
                } else {
                    // A site of a subdivided area takes the subdivided configuration's factor.
                    tri.iter()
                        .zip(&st.bary)
                        .map(|(&s, &w)| {
                            w * table.factor(s, depth, self.state.owner[s as usize] != NO_OWNER)
                        })
                        .sum()
                }
            }
        };
        if beta.is_finite() && beta > 0.0 {
            self.state.tools[k].contact_factor = beta;
        }
    }

    /// The organ table's factor at barycentric weights `b` on coarse triangle `tri` (nodes; its
    /// index `t` when known) and sphere depth `depth` (m) ([`crate::mass_spring::organ`]): over
    /// the triangle's four Loop children (corner i's child where `b_i >= 1/2`, else the middle
    /// one), whose corners are nodes and edge midpoints: linear over the middle child; in a
    /// corner child over the three triangles its centroid's site makes with its sides (linear
    /// without `t` or when the table has no child sites). Each
    /// site's coarse factor, or its subdivided one when it lies in a subdivided area (a child
    /// site when its corner does). Allocation-free.
    fn organ_factor_at(
        &self,
        table: &OrganTable,
        (tri, b): ([u32; 3], [f64; 3]),
        t: Option<u32>,
        depth: f64,
    ) -> f64 {
        let nc = self.model.surface.node_count() as u32;
        let owned = |s: u32| self.state.owner[s as usize] != NO_OWNER;
        let site = |s: u32| table.factor(s, depth, owned(s));
        let edge = |i: usize| {
            self.model
                .surface
                .edge_between(tri[i], tri[(i + 1) % 3])
                .map_or(0.5 * (site(tri[i]) + site(tri[(i + 1) % 3])), |e| {
                    site(nc + e)
                })
        };
        // m[i]: the factor at the midpoint of side (i, i + 1).
        let m = [edge(0), edge(1), edge(2)];
        let Some(i) = (0..3).find(|&i| b[i] >= 0.5) else {
            return (1.0 - 2.0 * b[2]) * m[0]
                + (1.0 - 2.0 * b[0]) * m[1]
                + (1.0 - 2.0 * b[1]) * m[2];
        };
        let (j, k) = ((i + 1) % 3, (i + 2) % 3);
        // The child's own weights on its corners: the node, side (i, j)'s and side (k, i)'s
        // midpoints.
        let w = [2.0 * b[i] - 1.0, 2.0 * b[j], 2.0 * b[k]];
        let v = [site(tri[i]), m[i], m[k]];
        let linear = w[0] * v[0] + w[1] * v[1] + w[2] * v[2];
        let Some(c) = t.and_then(|t| table.child_site(t, i)) else {
            return linear;
        };
        // The sub-triangle (centroid, two of the child's corners) holding the foot: the
        // centroid's weight three times the smallest child weight.
        let low = w[0].min(w[1]).min(w[2]);
        let centre = table.factor(c, depth, owned(tri[i]));
        3.0 * low * centre + linear - low * (v[0] + v[1] + v[2])
    }

    /// Where the organ table is read for tool slot `k` ([`crate::mass_spring::organ::foot`], session 6): the foot on the coarse
    /// rest surface of the probe's patch centroid at rest, `sum w_j rest_j` over the patch's
    /// slots, along the contact normal. The patch carries the force: on `hemisphere-springs`
    /// (8 mm edges under a 4 mm sphere) a press between nodes bears on the nearest node almost
    /// alone (3 mm from node 13 at the point `h1`: its weight 0.987), as a press on that node
    /// does, and reads that node's row, not the mean of its edges' (about half a node's) that
    /// the proxy's foot gave; on a node, an edge's midpoint (equal weights on its ends) and a
    /// symmetric patch it is the proxy's foot, as the calibration pressed. Continuous as the
    /// weights are. `None` without a foot (then the proxy's foot or the contact triangle).
    /// Allocation-free.
    fn patch_foot(&self, k: usize) -> Option<RestFoot> {
        let tool = &self.state.tools[k];
        let hint = tool.foot?.triangle;
        let (nodes, weights) = tool.probe.patch();
        if nodes.is_empty() {
            return None;
        }
        let centre: DVec3 = nodes
            .iter()
            .zip(weights)
            .map(|(&i, &w)| self.state.rest[i as usize] * w)
            .sum();
        let m = tool.probe.state.normal;
        let r = tool.probe.params.radius_m;
        rest_foot(&self.model.surface, centre + m * r, m, r, r, Some(hint))
            .filter(|h| h.miss_m <= r)
            .map(|h| h.foot)
    }

    /// The organ's height over the flat rest triangle at `foot`, m: zero at its corners (the
    /// nodes lie on the organ), the arc's height over each edge's midpoint
    /// ([`crate::mass_spring::contact_rest::arc_midpoint`]), quadratic between, `4 sum b_i b_j h_ij`.
    /// Allocation-free.
    fn organ_height_m(&self, foot: &RestFoot) -> f64 {
        let e = self.model.surface.triangle_edges(foot.triangle);
        let b = foot.bary;
        4.0 * (b[0] * b[1] * self.model.edge_arc_m[e[0] as usize]
            + b[1] * b[2] * self.model.edge_arc_m[e[1] as usize]
            + b[2] * b[0] * self.model.edge_arc_m[e[2] as usize])
    }

    /// Tool slot `k`'s foot on the coarse rest surface ([`crate::mass_spring::organ::foot`]) from its state now:
    /// searched around the last foot's triangles, over the whole surface at a first contact (at
    /// most once a tick while none is found); `None` when the line through the proxy along the
    /// normal meets no rest triangle within a probe radius of where the centre should be.
    /// Allocation-free.
    fn update_foot(&mut self, k: usize) {
        let tool = &mut self.state.tools[k];
        let hint = tool.foot.map(|f| f.triangle);
        if hint.is_none() {
            if tool.foot_searched {
                return;
            }
            tool.foot_searched = true;
        }
        let st = tool.probe.state;
        let r = tool.probe.params.radius_m;
        let expected = if hint.is_some() {
            r - tool.contact_depth_m
        } else {
            r
        };
        tool.foot = rest_foot(
            &self.model.surface,
            st.proxy_m,
            st.normal,
            expected,
            r,
            hint,
        )
        .filter(|f| f.miss_m <= r)
        .map(|f| f.foot);
    }
}
