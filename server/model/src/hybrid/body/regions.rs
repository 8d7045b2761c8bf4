//! Contact-local activation and release of the particle regions (seed 000 section 6; module
//! documentation of [`super`], a tick's step 1).

use super::HybridBody;
use crate::hybrid::HybridModel;
use glam::DVec3;

/// The activation scan's bound ([`HybridBody::activate_near`]).
#[derive(Debug)]
pub(super) struct VertexBounds {
    /// Each outer vertex's tie at the core's rest positions, m.
    rest_m: Vec<DVec3>,
    /// The largest `sum_k |w_k|` of an outer vertex's tie: a vertex is at most this times the
    /// core's largest nodal displacement from `rest_m`.
    reach: f64,
}

impl VertexBounds {
    /// The bounds of `model`'s outer vertices over the core's rest positions `core_rest_m` (m).
    pub(super) fn new(model: &HybridModel, core_rest_m: &[DVec3]) -> Self {
        let rest_m = (model.vertex_tie.iter())
            .map(|t| model.interpolate(t, core_rest_m))
            .collect();
        let reach = (model.vertex_tie.iter())
            .map(|t| model.tie_nodes(t).w.iter().map(|w| w.abs()).sum::<f64>())
            .fold(0.0, f64::max);
        Self { rest_m, reach }
    }
}

impl HybridBody {
    /// Activates the regions of the outer vertices within `radius_m` of `point_m` (m, at
    /// their current positions), nearest first. When a region does not fit under
    /// `max_active_particles`, active regions whose vertex is farther from `point_m` than the
    /// region's by half of `release_radius_m - radius_m` are released, farthest first, settled
    /// or not, to make room (not while
    /// [`Self::hold_regions`] holds them): the probe keeps simulated particles under it as it
    /// slides. Allocation-free; the terms are refilled at the next tick or
    /// [`Self::evaluate_forces`].
    pub fn activate_near(&mut self, point_m: DVec3, radius_m: f64) {
        let r2 = radius_m * radius_m;
        // A vertex moved at most `reach` times the core's largest displacement from its
        // rest tie (`x_v - X_v = sum_k w_k (x_k - X_k)`), so one whose rest tie is farther
        // than `radius_m` plus that (and 1 nm for round-off) is not a candidate: most of the
        // surface is skipped without its interpolation, and the list is the same.
        let moved_m = (self.state.xc.iter().zip(self.fem.rest()))
            .map(|(x, x0)| (*x - *x0).length_squared())
            .fold(0.0, f64::max)
            .sqrt();
        let reach_m = radius_m + self.regions.vertex_bounds.reach * moved_m + 1e-9;
        let reach2 = reach_m * reach_m;
        // Nearest first: when the cap binds, the regions under the probe get in.
        self.scratch.candidates.clear();
        for v in 0..self.model.outer_rest_m.len() {
            // (`f64::max` skips NaN displacements; a NaN position is never a candidate,
            // with or without the bound.)
            let far = (self.regions.vertex_bounds.rest_m[v] - point_m).length_squared() > reach2;
            if self.regions.region_active[v] || far {
                continue;
            }
            let x = self
                .model
                .interpolate(&self.model.vertex_tie[v], &self.state.xc);
            let d2 = (x - point_m).length_squared();
            if d2 < r2 {
                self.scratch.candidates.push((d2, v as u32));
            }
        }
        self.scratch
            .candidates
            .sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        for k in 0..self.scratch.candidates.len() {
            let (d2, v) = self.scratch.candidates[k];
            let v = v as usize;
            if !self.fits(v) && !self.regions.hold {
                // Regions farther than the candidate by half the release band give way: a
                // region near the activation radius's edge is not evicted and re-activated
                // tick after tick, and one coming under the probe gets in first.
                let p = &self.model.params;
                let band_m = 0.5 * (p.release_radius_m - radius_m).max(0.0);
                self.evict_far(point_m, d2.sqrt() + band_m, v);
            }
            if self.fits(v) {
                self.activate_region(v);
            } else {
                self.stats.refused_activations += 1;
            }
        }
    }

    /// Whether the region of vertex `v` fits under `max_active_particles`.
    pub(super) fn fits(&self, v: usize) -> bool {
        let m = &self.model;
        let len = (m.region_start[v + 1] - m.region_start[v]) as usize;
        self.regions.active_list.len() + len <= m.params.max_active_particles
    }

    /// Releases active regions whose vertex is farther than `radius_m` from `probe_m`,
    /// farthest first, until the region of vertex `v` fits or none is left; never a region
    /// within `release_radius_m` of another tool (`self.state.evict_guard`).
    pub(super) fn evict_far(&mut self, probe_m: DVec3, radius_m: f64, v: usize) {
        let r2 = radius_m * radius_m;
        while !self.fits(v) {
            let m = &self.model;
            let mut farthest = None;
            let mut d2_max = r2;
            let guard2 = m.params.release_radius_m * m.params.release_radius_m;
            for (k, &u) in self.regions.active_regions.iter().enumerate() {
                let x = m.interpolate(&m.vertex_tie[u as usize], &self.state.xc);
                let d2 = (x - probe_m).length_squared();
                // Regions under another tool (or where one left) are not this one's to evict.
                let guarded = self
                    .state
                    .evict_guard
                    .iter()
                    .flatten()
                    .any(|&g| (x - g).length_squared() < guard2);
                if d2 > d2_max && !guarded {
                    d2_max = d2;
                    farthest = Some(k);
                }
            }
            let Some(k) = farthest else {
                return;
            };
            self.deactivate_region(k);
            self.stats.released_for_room += 1;
            let active = &self.regions.active;
            self.regions.active_list.retain(|&p| active[p as usize]);
        }
    }

    /// Switches off the `k`-th active region (its particles follow the core again, and may be
    /// tied to it as neighbours of the next active set); the caller prunes `active_list`.
    pub(super) fn deactivate_region(&mut self, k: usize) {
        let m = &self.model;
        let v = self.regions.active_regions[k] as usize;
        for &p in &m.region_particles[m.region_start[v] as usize..m.region_start[v + 1] as usize] {
            self.regions.active[p as usize] = false;
            // `rebuild_terms` clears the marks of the pruned `active_list` only.
            self.regions.in_block[p as usize] = false;
        }
        self.regions.region_active[v] = false;
        self.regions.active_regions.swap_remove(k);
        self.regions.changed = true;
    }

    pub(super) fn activate_region(&mut self, v: usize) {
        let m = &self.model;
        let range = m.region_start[v] as usize..m.region_start[v + 1] as usize;
        for k in range {
            let p = m.region_particles[k] as usize;
            if m.degenerate[p] {
                continue;
            }
            let tie = &m.particle_tie[p];
            self.state.xp[p] = m.interpolate(tie, &self.state.xc);
            if self.setup.deviation {
                // On the core's interpolation, moving with it: no deviation.
                self.state.xd[p] = DVec3::ZERO;
                self.state.vp[p] = DVec3::ZERO;
            } else {
                self.state.vp[p] = m.interpolate(tie, &self.state.vc);
            }
            self.regions.active[p] = true;
            self.regions.active_list.push(p as u32);
        }
        self.regions.region_active[v] = true;
        self.regions.active_regions.push(v as u32);
        self.regions.changed = true;
    }

    /// Releases the settled regions whose vertex is farther than `release_radius_m` from every
    /// device (`None`: no device there). Regions near the last point of a tool that left while
    /// another stays (`self.state.departed`) stay active until no tool is connected: their
    /// release (185 particles) moved the other tool's force by 13 % in one tick on
    /// `lv-hybrid` (`tests/tools.rs`).
    pub(super) fn release_far(&mut self, devices: &[Option<DVec3>]) {
        let p = &self.model.params;
        let r2 = p.release_radius_m * p.release_radius_m;
        let tol2 = p.release_tolerance_m * p.release_tolerance_m;
        let mut released = false;
        let mut k = 0;
        while k < self.regions.active_regions.len() {
            let m = &self.model;
            let v = self.regions.active_regions[k] as usize;
            let vertex = m.interpolate(&m.vertex_tie[v], &self.state.xc);
            let near = devices
                .iter()
                .flatten()
                .any(|&c| (vertex - c).length_squared() < r2);
            let kept = self
                .state
                .departed
                .iter()
                .flatten()
                .any(|&c| (vertex - c).length_squared() < r2);
            let region =
                &m.region_particles[m.region_start[v] as usize..m.region_start[v + 1] as usize];
            // Settled: back on the core's interpolation, or at rest (speeds below the tolerance
            // per 0.1 s) in a state the layer cannot leave by itself (a fold pressed in by the
            // probe), which the release then removes.
            let settled = !near
                && !kept
                && (region.iter().all(|&p| {
                    let p = p as usize;
                    !self.regions.active[p]
                        || (self.state.xp[p] - m.interpolate(&m.particle_tie[p], &self.state.xc))
                            .length_squared()
                            < tol2
                }) || region.iter().all(|&p| {
                    !self.regions.active[p as usize]
                        || self.state.vp[p as usize].length_squared() * 0.01 < tol2
                }));
            if settled {
                self.deactivate_region(k);
                released = true;
            } else {
                k += 1;
            }
        }
        if released {
            let active = &self.regions.active;
            self.regions.active_list.retain(|&p| active[p as usize]);
        }
    }
}
