//! The subdivided areas' centres: which coarse node the probe touches, when an area is
//! added or coarsened, and the areas' spring constants (section 3.2.4).

use super::Centre;
use super::MAX_CENTRES;
use super::MassSpringBody;
use super::QUIET_DISPLACEMENT_OVER_L;
use crate::mass_spring::SpringRule;
use crate::mass_spring::refine::TriangleState;

impl MassSpringBody {
    /// `K'_h` and `K'_m` of each centre's area at the current state (section 3.2.4: the table
    /// at the centre's displacement over L; the coarse constants with
    /// [`SpringRule::Unchanged`]; eq. 5 with [`SpringRule::Area`]).
    pub(super) fn update_area_constants(&mut self) {
        let kh = self.setup.params.home_spring_n_per_m;
        let ratio = match self.setup.params.subdivision.springs {
            SpringRule::Calibrated => self.setup.params.subdivision.km_over_kh_after,
            SpringRule::Unchanged => self.setup.params.mesh_spring_n_per_m / kh,
            SpringRule::Area => {
                // Eq. 5 over the areas (as the masses of eq. 3), the mesh springs unchanged.
                let (n1, n2) = (
                    self.state.refinement.type1_count(),
                    self.state.refinement.type2_count(),
                );
                let n_ratio = if n1 + n2 > 0 {
                    n1 as f64 / (n1 + n2) as f64
                } else {
                    1.0
                };
                for k in 0..self.state.centre_count {
                    self.state.kh_area[k] = kh * n_ratio;
                    self.state.km_area[k] = self.setup.params.mesh_spring_n_per_m;
                }
                return;
            }
        };
        for k in 0..self.state.centre_count {
            let c = self.state.centres[k].node;
            let a = match &self.model.table {
                Some(t) => {
                    let u = (self.state.x[c as usize] - self.state.rest[c as usize]).length();
                    t.scale(c, u / self.model.surface.element_size_m(c))
                }
                None => 1.0,
            };
            self.state.kh_area[k] = a * kh;
            self.state.km_area[k] = ratio * a * kh;
        }
    }

    /// The contact node C of the paper for tool slot `k`: while the probe's foot on the coarse
    /// rest surface ([`crate::mass_spring::organ::foot`]) or the triangle it touches lies in a
    /// subdivided area, that area's centre (the area the press made stays its area: session
    /// 12, a second one-ring area joining as the dent deepened made the LV 14 % stiffer at
    /// 4 mm; session 15, the foot too: past 3 mm on the 4 mm hemisphere the touched triangle of
    /// the dent left the area while the foot stayed in it, and the second area made h2 +20 %
    /// stiffer at 4 mm and the calibration's edge presses 10-20 % stiffer past 2-3 mm);
    /// elsewhere the coarse node nearest its contact point among the coarse vertices of the
    /// triangle it touches, if it is free.
    fn contact_node(&self, k: usize) -> Option<u32> {
        let probe = &self.state.tools[k].probe;
        let st = probe.state;
        if !st.in_contact {
            return None;
        }
        let tri = *probe.surface.triangles.get(st.triangle as usize)?;
        let touched = self.state.mesh.coarse_triangle_of(st.triangle);
        let foot = self.state.tools[k].foot.map(|f| f.triangle);
        for coarse in foot.into_iter().chain([touched]) {
            if self
                .state
                .refinement
                .triangle_state(&self.model.surface, coarse)
                == TriangleState::Split
            {
                let owner = self.state.refinement.triangle_owner(coarse) as usize;
                if owner < self.state.centre_count {
                    return Some(self.state.centres[owner].node);
                }
            }
        }
        let point = st.proxy_m - st.normal * probe.params.radius_m;
        let nc = self.model.surface.node_count() as u32;
        let mut best: Option<(f64, u32)> = None;
        for s in tri {
            let parents = if s < nc {
                [s, s]
            } else {
                self.model.surface.edges()[(s - nc) as usize]
            };
            for p in parents {
                if self.model.fixed[p as usize] {
                    continue;
                }
                let d = (self.scratch.cx[p as usize] - point).length_squared();
                if best.is_none_or(|(bd, _)| d < bd) {
                    best = Some((d, p));
                }
            }
        }
        best.map(|b| b.1)
    }

    /// Updates the centres from the tools' contacts (each tool's contact node touched now:
    /// refreshed or added; untouched for longer than the delay: removed) and runs an event
    /// when they changed.
    pub(super) fn update_centres(&mut self) {
        if self.setup.params.subdivision.rings == 0 {
            return;
        }
        let now = self.state.time_s;
        let mut added = false;
        for k in 0..self.state.tools.len() {
            if let Some(c) = self.contact_node(k) {
                added |= self.touch_centre(c, now);
            }
        }
        let delay = self.setup.params.subdivision.coarsen_delay_s;
        let before = self.state.centre_count;
        let mut k = 0;
        while k < self.state.centre_count {
            if now - self.state.centres[k].last_contact_s > delay && self.area_is_quiet(k) {
                self.state.centre_count -= 1;
                self.state.centres[k] = self.state.centres[self.state.centre_count];
            } else {
                k += 1;
            }
        }
        let removed = self.state.centre_count < before;
        if added || removed {
            self.event(added, removed);
        }
    }

    /// Marks coarse node `c` touched at `now` (s): refreshes its centre, or adds one (replacing
    /// the one touched longest ago when all [`MAX_CENTRES`] are in use, never one touched at
    /// `now`: there are more centres than tools). Returns whether it added one.
    fn touch_centre(&mut self, c: u32, now: f64) -> bool {
        let count = self.state.centre_count;
        if let Some(k) = self.state.centres[..count].iter_mut().find(|k| k.node == c) {
            k.last_contact_s = k.last_contact_s.max(now);
            return false;
        }
        let centre = Centre {
            node: c,
            last_contact_s: now,
        };
        if count == MAX_CENTRES {
            let oldest = (0..MAX_CENTRES)
                .min_by(|&a, &b| {
                    self.state.centres[a]
                        .last_contact_s
                        .total_cmp(&self.state.centres[b].last_contact_s)
                })
                .unwrap_or(0);
            self.state.centres[oldest] = centre;
        } else {
            self.state.centres[count] = centre;
            self.state.centre_count += 1;
        }
        true
    }

    /// Whether every node of centre `k`'s area (its rings' coarse nodes and their type-2
    /// nodes) is within [`QUIET_DISPLACEMENT_OVER_L`] of its rest position. O(area),
    /// allocation-free.
    fn area_is_quiet(&mut self, k: usize) -> bool {
        let c = self.state.centres[k].node;
        let limit = QUIET_DISPLACEMENT_OVER_L * self.model.surface.element_size_m(c);
        let limit2 = limit * limit;
        let rings = self.setup.params.subdivision.rings;
        let mut ring = std::mem::take(&mut self.event.ring);
        self.model
            .surface
            .ring(c, rings, &mut self.event.ring_dist, &mut ring);
        let nc = self.model.surface.node_count() as u32;
        let moved = |s: u32| {
            (self.state.x[s as usize] - self.state.rest[s as usize]).length_squared() > limit2
        };
        let quiet = ring.iter().all(|&(i, _)| {
            !moved(i)
                && self
                    .model
                    .surface
                    .incident_edges(i)
                    .iter()
                    .all(|&e| !self.state.refinement.is_edge_split(e) || !moved(nc + e))
        });
        self.event.ring = ring;
        quiet
    }

    /// Subdivides around the coarse nodes `nodes` (replacing every current area; they stay
    /// subdivided until [`MassSpringBody::coarsen`]): a subdivision event, for tests, tools and
    /// the calibration experiment. At most [`MAX_CENTRES`] nodes are taken; fixed ones and
    /// nodes out of range are skipped. Allocation-free.
    pub fn subdivide_around(&mut self, nodes: &[u32]) {
        self.state.centre_count = 0;
        for &c in nodes.iter().take(MAX_CENTRES) {
            if (c as usize) < self.model.surface.node_count() && !self.model.surface.is_fixed(c) {
                self.state.centres[self.state.centre_count] = Centre {
                    node: c,
                    last_contact_s: f64::INFINITY,
                };
                self.state.centre_count += 1;
            }
        }
        self.event(true, false);
    }

    /// Coarsens every subdivided area: back to the coarse mesh (an event). Allocation-free.
    pub fn coarsen(&mut self) {
        self.state.centre_count = 0;
        self.event(false, true);
    }
}
