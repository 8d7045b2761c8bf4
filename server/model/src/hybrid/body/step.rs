//! The energy terms of the active set and the particle steps: forces on the particles and the
//! core, the update (module documentation of [`super`], a tick's step 2).

use super::{ExtraTool, HybridBody, HybridPipeline, PointLoad};
use crate::ModelError;
use crate::body::{SoftBody, TickInput};
use crate::hybrid::prepare::{HybridModel, TieNodes};
use crate::hybrid::proxy::{ParticleProxy, ProxyContact};
use crate::integrate::IntegratorKind;
use crate::integrate::explicit::integrate_nodes;
use crate::pool::{TickPool, cut_at_middle};
use glam::DVec3;
use std::ops::Range;

/// A slot without a device: no contact.
pub(super) const NO_CONTACT: ProxyContact = ProxyContact {
    force_on_device_n: DVec3::ZERO,
    stiffness_n_per_m: [0.0; 9],
    proxy_m: DVec3::ZERO,
    in_contact: false,
};

impl HybridBody {
    /// Refills the energy terms for the current active set (allocation-free): terms of the
    /// active particles and of their inactive neighbours (ring 1); the tied list holds ring 1
    /// and the inactive neighbours of ring 1 (ring 2), whose positions those terms read and
    /// whose forces go to the core. Then the ties copied in the lists' order and the implicit
    /// core's matrix where the active regions left it.
    pub(super) fn rebuild_terms(&mut self) {
        self.refill_block();
        let m = &self.model;
        self.pipeline.tied_ties.clear();
        for &q in &self.regions.tied_list {
            self.pipeline
                .tied_ties
                .push(m.tie_nodes(&m.particle_tie[q as usize]));
        }
        self.refresh_implicit_matrix();
        let m = &self.model;
        self.state.xp_fresh = false;
        self.pipeline.active_ties.clear();
        self.pipeline.active_order.clear();
        if self.setup.deviation {
            for &p in &self.regions.active_list {
                self.pipeline
                    .active_ties
                    .push(m.tie_nodes(&m.particle_tie[p as usize]));
            }
            let list = &self.regions.active_list;
            self.pipeline.active_order.extend(0..list.len() as u32);
            self.pipeline
                .active_order
                .sort_unstable_by_key(|&k| list[k as usize]);
        }
        self.regions.changed = false;
    }

    /// The term block and the tied list (rings 1 and 2) for the active list, sorted in memory
    /// order; the layer's term counts.
    fn refill_block(&mut self) {
        for &q in &self.regions.tied_list {
            self.regions.in_block[q as usize] = false;
        }
        for &q in &self.regions.active_list {
            self.regions.in_block[q as usize] = false;
        }
        self.regions.tied_list.clear();
        self.pipeline.block.clear();
        if let Some(layer) = &mut self.pipeline.layer {
            layer.clear();
        }
        let cloud = &self.model.cloud;
        let ties = &self.model.particle_tie;
        let mut nbr = [0u32; crate::meshfree::cloud::MAX_STENCIL];
        for &p in &self.regions.active_list {
            self.regions.in_block[p as usize] = true;
            if matches!(self.pipeline.block.push(cloud, p), Ok(true)) {
                if let Some(layer) = &mut self.pipeline.layer {
                    layer.count_term(ties[p as usize].tet);
                }
            } else {
                self.stats.refused_activations += 1;
            }
        }
        for ring in 0..2 {
            let to = if ring == 0 {
                self.regions.active_list.len()
            } else {
                self.regions.tied_list.len()
            };
            for a in 0..to {
                let p = if ring == 0 {
                    self.regions.active_list[a]
                } else {
                    self.regions.tied_list[a]
                };
                let k = cloud.neighbours(p, &mut nbr);
                for &q in &nbr[..k] {
                    if self.regions.in_block[q as usize]
                        || self.regions.tied_list.len() == self.regions.tied_list.capacity()
                    {
                        continue;
                    }
                    self.regions.in_block[q as usize] = true;
                    self.regions.tied_list.push(q);
                    if ring == 0 && !self.model.degenerate[q as usize] {
                        if matches!(self.pipeline.block.push(cloud, q), Ok(true)) {
                            if let Some(layer) = &mut self.pipeline.layer {
                                layer.count_term(ties[q as usize].tet);
                            }
                        } else {
                            self.stats.refused_activations += 1;
                        }
                    }
                }
            }
        }
        // In memory order: the tie gathers and scatters of every sub-step walk the particle
        // arrays forwards.
        self.regions.tied_list.sort_unstable();
        if let Some(layer) = &mut self.pipeline.layer {
            layer.finish();
        }
    }

    /// Refactors the implicit core's matrix when an active region is not in it (a non-finite
    /// factor marks the body diverged).
    fn refresh_implicit_matrix(&mut self) {
        // The implicit core's matrix holds the active regions and their neighbours (which stand
        // for the terms of inactive particles next to the active ones, which the block also
        // holds). It is refactored only when an active region is not in it: a region released,
        // or activated next to the active ones (already a neighbour), leaves a matrix that
        // still dominates the tangent, with a little more damping where it has too much.
        let refactor = self.pipeline.implicit.is_some()
            && self.pipeline.layer.is_none()
            && !self
                .regions
                .active_regions
                .iter()
                .all(|&v| self.scratch.region_mark[v as usize]);
        if refactor {
            for &v in &self.scratch.matrix_regions {
                self.scratch.region_mark[v as usize] = false;
            }
            self.scratch.matrix_regions.clear();
            for &v in &self.regions.active_regions {
                let (a, b) = (
                    self.regions.vertex_adj_start[v as usize] as usize,
                    self.regions.vertex_adj_start[v as usize + 1] as usize,
                );
                for &w in std::iter::once(&v).chain(&self.regions.vertex_adj[a..b]) {
                    if !self.scratch.region_mark[w as usize] {
                        self.scratch.region_mark[w as usize] = true;
                        self.scratch.matrix_regions.push(w);
                    }
                }
            }
        }
        if let Some((core, _)) = &mut self.pipeline.implicit
            && refactor
        {
            self.stats.implicit_refactors += 1;
            if core.refactor(&self.scratch.matrix_regions).is_err() {
                // Positive definite by construction; a failure is a non-finite state.
                self.state.diverged_at_s = Some(self.state.time_s);
            }
        }
    }

    /// Particle forces of the current state (no update): tied positions from the core, terms,
    /// the probe at `probe_m` (returns the force on the device, N, and its stiffness
    /// `sum k n n^T`, N/m); the tied particles' forces and the point loads go to the core
    /// nodes' coupling buffer with the tie weights.
    pub(super) fn particle_forces(&mut self, probe_m: Option<DVec3>) -> ProxyContact {
        let mut contact = [NO_CONTACT];
        self.particle_forces_tools(&[probe_m], &mut contact);
        contact[0]
    }

    /// [`Self::particle_forces`] with a probe per tool slot: `devices[k]` drives slot `k`'s
    /// proxy (slot 0 the body's first, slot `k > 0` its `tools[k - 1]`), whose contact goes to
    /// `contacts[k]`; every proxy adds its penalty forces to the same particles' forces.
    pub(super) fn particle_forces_tools(
        &mut self,
        devices: &[Option<DVec3>],
        contacts: &mut [ProxyContact],
    ) {
        if self.regions.changed {
            self.rebuild_terms();
        }
        let m = &self.model;
        let xc = &self.state.xc;
        interpolate_sorted(
            self.pipeline.pool.as_deref(),
            (&self.regions.tied_list, &self.pipeline.tied_ties),
            xc,
            &mut self.state.xp,
        );
        // The particle step leaves the active particles where this would put them (bit for
        // bit: the same sum of the same values).
        if self.setup.deviation && !std::mem::replace(&mut self.state.xp_fresh, true) {
            for (&p, t) in self
                .regions
                .active_list
                .iter()
                .zip(&self.pipeline.active_ties)
            {
                self.state.xp[p as usize] = t.interpolate(xc) + self.state.xd[p as usize];
            }
        }
        let HybridPipeline { block, pool, .. } = &mut self.pipeline;
        block.write_forces_in(
            pool.as_deref(),
            &m.cloud,
            &self.state.xp,
            &mut self.scratch.fp,
        );
        let scatter = TieScatter {
            proxy: &mut self.state.proxy,
            tools: &mut self.state.tools,
            xp: &self.state.xp,
            active: &self.regions.active_list,
            tied: &self.regions.tied_list,
            tied_ties: &self.pipeline.tied_ties,
            active_ties: &self.pipeline.active_ties,
            loads: &self.state.loads[..self.state.load_count],
            model: &self.model,
            fp: &mut self.scratch.fp,
            fcoup: &mut self.scratch.fcoup,
            deviation: self.setup.deviation,
        };
        let beside = self
            .pipeline
            .pool
            .as_deref()
            .filter(|p| p.threads() > 1 && self.pipeline.implicit.is_some());
        let Some(pool) = beside else {
            return scatter.run(devices, contacts);
        };
        // Two threads: the FEM's forces for the implicit step (they read the core's positions
        // only) on the worker; beside them the proxies and the ties, the shorter side, and then
        // the layer's replaced shares into their own array (docs/benchmarks.md, "the hybrid's
        // join, rebalanced").
        let (fem, layer, xc) = (&self.fem, &self.pipeline.layer, &self.state.xc);
        let (ffem, flayer) = (&mut self.scratch.ffem, &mut self.scratch.flayer);
        pool.join(
            || {
                scatter.run(devices, contacts);
                if let Some(layer) = layer {
                    flayer.iter_mut().for_each(|f| *f = DVec3::ZERO);
                    layer.subtract_forces(fem, xc, None, flayer);
                }
            },
            || {
                ffem.iter_mut().for_each(|f| *f = DVec3::ZERO);
                fem.add_internal_forces(xc, None, ffem);
            },
        );
        self.scratch.ffem_ready = true;
    }

    /// Core forces: the coupling buffer plus the FEM's internal (elastic and viscous) forces.
    pub(super) fn core_forces(&mut self) {
        self.scratch.ffem_ready = false;
        self.scratch.fc.copy_from_slice(&self.scratch.fcoup);
        self.add_fem_forces(true);
    }

    /// Adds the FEM's internal forces at the core's positions to `fc` (with the viscous stress
    /// at its velocities when `viscous`), less the shares the particles' terms replace
    /// (`inactive_layer = "elements"`, [`LayerElements`]).
    pub(super) fn add_fem_forces(&mut self, viscous: bool) {
        let v = viscous.then_some(self.state.vc.as_slice());
        self.fem
            .add_internal_forces(&self.state.xc, v, &mut self.scratch.fc);
        if let Some(layer) = &self.pipeline.layer {
            layer.subtract_forces(&self.fem, &self.state.xc, v, &mut self.scratch.fc);
        }
    }

    /// Computes the forces of the current state without advancing it and returns the core
    /// nodes' forces and the particles' forces (N; particle entries are meaningful for active
    /// and tied particles). For tests: constant strain, momentum.
    pub fn evaluate_forces(&mut self) -> (&[DVec3], &[DVec3]) {
        self.particle_forces(None);
        self.core_forces();
        (&self.scratch.fc, &self.scratch.fp)
    }

    /// One particle step of length `dt` from the forces in the buffers, during which the core
    /// takes `core_substeps` steps with the coupling forces held (multi-rate: the impulses
    /// exchanged through the ties are equal and opposite, so momentum stays exact); returns the
    /// largest squared speed (NaN when non-finite).
    pub(super) fn update(&mut self, dt: f64) -> f64 {
        let dt_c = dt / self.setup.core_substeps as f64;
        let mut max_v2: f64 = 0.0;
        let mut non_finite = false;
        if self.pipeline.implicit.is_some() {
            // Elastic and coupling forces; the viscous operator is in the frozen matrix.
            if std::mem::take(&mut self.scratch.ffem_ready) {
                let sc = &mut self.scratch;
                let fem = sc.ffem.iter().zip(&sc.flayer);
                for ((fc, &coupling), (&elastic, &layer)) in
                    sc.fc.iter_mut().zip(&sc.fcoup).zip(fem)
                {
                    *fc = coupling + (elastic + layer);
                }
            } else {
                self.scratch.fc.copy_from_slice(&self.scratch.fcoup);
                self.add_fem_forces(false);
            }
            let HybridPipeline { implicit, pool, .. } = &mut self.pipeline;
            let Some((core, _)) = implicit else {
                unreachable!("checked above")
            };
            let v2 = core.step_in(
                pool.as_deref(),
                self.fem.lumped_mass_kg(),
                &self.scratch.fc,
                &mut self.state.xc,
                &mut self.state.vc,
            );
            non_finite |= !v2.is_finite();
            max_v2 = max_v2.max(v2);
        }
        let explicit_core_steps = if self.pipeline.implicit.is_some() {
            0
        } else {
            self.setup.core_substeps
        };
        for _ in 0..explicit_core_steps {
            self.core_forces();
            let v2 = integrate_nodes(
                IntegratorKind::SymplecticEuler,
                &self.fem,
                &[],
                dt_c,
                &self.scratch.fc,
                &mut self.state.xc,
                &mut self.state.vc,
            );
            non_finite |= !v2.is_finite();
            max_v2 = max_v2.max(v2);
        }
        let damp = 1.0 / (1.0 + self.fem.material().mass_damping_per_s * dt);
        let inv_m = dt / self.setup.particle_mass_kg;
        if self.setup.deviation {
            let step = ActiveStep {
                order: &self.pipeline.active_order,
                list: &self.regions.active_list,
                ties: &self.pipeline.active_ties,
                xc: &self.state.xc,
                fp: &self.scratch.fp,
                inv_m,
                damp,
                dt,
            };
            let (v2, bad) = step.run_in(
                self.pipeline.pool.as_deref(),
                (&mut self.state.vp, &mut self.state.xd, &mut self.state.xp),
            );
            non_finite |= bad;
            max_v2 = max_v2.max(v2);
            self.state.xp_fresh = true;
        } else {
            for &p in &self.regions.active_list {
                let p = p as usize;
                let v = (self.state.vp[p] + self.scratch.fp[p] * inv_m) * damp;
                self.state.vp[p] = v;
                self.state.xp[p] += v * dt;
                let s = v.length_squared();
                non_finite |= !s.is_finite();
                max_v2 = max_v2.max(s);
            }
        }
        if non_finite { f64::NAN } else { max_v2 }
    }

    /// Advances `ticks` servo periods without a device (for tests and studies).
    ///
    /// # Errors
    /// As [`SoftBody::tick`].
    pub fn run_free(&mut self, ticks: usize) -> Result<(), ModelError> {
        for _ in 0..ticks {
            self.tick(&TickInput::default())?;
        }
        Ok(())
    }
}

/// What the proxy and the ties' scatter read and write, borrowed apart from the rest of the
/// body so that the FEM's forces can be computed beside them ([`HybridBody::particle_forces`]).
struct TieScatter<'a> {
    /// Slot 0's proxy and the other slots' tools.
    proxy: &'a mut ParticleProxy,
    tools: &'a mut [ExtraTool],
    xp: &'a [DVec3],
    active: &'a [u32],
    tied: &'a [u32],
    tied_ties: &'a [TieNodes],
    active_ties: &'a [TieNodes],
    loads: &'a [PointLoad],
    model: &'a HybridModel,
    fp: &'a mut [DVec3],
    fcoup: &'a mut [DVec3],
    deviation: bool,
}

impl TieScatter<'_> {
    /// Every slot's probe (`devices[k]`, slot 0 the body's first proxy, slot `k > 0` its
    /// `tools[k - 1]`) on the particles, its contact into `contacts[k]` and its reaction into
    /// `fp`, then the tied (and, in deviation mode, the active) particles' forces and the
    /// point loads onto the core nodes' coupling buffer with the tie weights.
    fn run(self, devices: &[Option<DVec3>], contacts: &mut [ProxyContact]) {
        for (k, (device, contact)) in devices.iter().zip(contacts.iter_mut()).enumerate() {
            let proxy = match k {
                0 => &mut *self.proxy,
                _ => &mut self.tools[k - 1].proxy,
            };
            *contact = match device {
                Some(device) => proxy.update(*device, self.xp, self.active, Some(&mut *self.fp)),
                None => NO_CONTACT,
            };
        }
        self.fcoup.iter_mut().for_each(|f| *f = DVec3::ZERO);
        for (&q, t) in self.tied.iter().zip(self.tied_ties) {
            t.scatter(self.fp[q as usize], self.fcoup);
        }
        if self.deviation {
            // `d x_p / d x_k = w_pk`: the active particles' forces drive the core too.
            for (&p, t) in self.active.iter().zip(self.active_ties) {
                t.scatter(self.fp[p as usize], self.fcoup);
            }
        }
        for l in self.loads {
            self.model.tie_nodes(&l.tie).scatter(l.force_n, self.fcoup);
        }
    }
}

/// `xp[q] = ties[i].interpolate(xc)` for every `q = list[i]` (`list` ascending, no repeats):
/// on a pool with a worker the list is cut at its middle and each half writes its own side of
/// `xp` (split at the middle's particle), else serially; the same values either way (each
/// particle's interpolation is its own). Allocation-free.
fn interpolate_sorted(
    pool: Option<&TickPool>,
    (list, ties): (&[u32], &[TieNodes]),
    xc: &[DVec3],
    xp: &mut [DVec3],
) {
    let run = |xs: &mut [DVec3], range: Range<usize>, offset: usize| {
        for (&q, t) in list[range.clone()].iter().zip(&ties[range]) {
            xs[q as usize - offset] = t.interpolate(xc);
        }
    };
    let cut = cut_at_middle(list.len(), |i| list[i]);
    match (pool.filter(|p| p.threads() > 1), cut) {
        (Some(pool), Some((h, mid))) => {
            let (lo, hi) = xp.split_at_mut(mid);
            let mut halves = [(lo, 0..h, 0), (hi, h..list.len(), mid)];
            pool.for_each_mut(&mut halves, &|_, (xs, range, offset)| {
                run(xs, range.clone(), *offset);
            });
        }
        _ => run(xp, 0..list.len(), 0),
    }
}

/// The active particles' step in deviation mode ([`HybridBody::update`]): what every
/// particle's step reads.
struct ActiveStep<'a> {
    /// Indices into `list` in memory order (ascending particle).
    order: &'a [u32],
    list: &'a [u32],
    ties: &'a [TieNodes],
    xc: &'a [DVec3],
    fp: &'a [DVec3],
    inv_m: f64,
    damp: f64,
    dt: f64,
}

/// The particle arrays (velocity, deviation, position) from particle `offset` on, the part of
/// `order` whose particles they hold, and the part's largest squared speed.
struct ActiveSide<'a> {
    vp: &'a mut [DVec3],
    xd: &'a mut [DVec3],
    xp: &'a mut [DVec3],
    offset: usize,
    order: Range<usize>,
    max_v2: f64,
    non_finite: bool,
}

impl ActiveStep<'_> {
    /// The step of the particles of `side`: velocity, deviation, and the absolute position
    /// (for the surface and the release test between ticks).
    fn run(&self, side: &mut ActiveSide<'_>) {
        for &k in &self.order[side.order.clone()] {
            let k = k as usize;
            let p = self.list[k] as usize;
            let i = p - side.offset;
            let v = (side.vp[i] + self.fp[p] * self.inv_m) * self.damp;
            side.vp[i] = v;
            side.xd[i] += v * self.dt;
            side.xp[i] = self.ties[k].interpolate(self.xc) + side.xd[i];
            let s = v.length_squared();
            side.non_finite |= !s.is_finite();
            side.max_v2 = side.max_v2.max(s);
        }
    }

    /// Every active particle's step, cut at the middle of `order` on a pool with a worker
    /// (each half on its side of the arrays), else serially; the same values either way.
    /// Returns the largest squared speed and whether any was not finite. Allocation-free.
    fn run_in(
        &self,
        pool: Option<&TickPool>,
        (vp, xd, xp): (&mut [DVec3], &mut [DVec3], &mut [DVec3]),
    ) -> (f64, bool) {
        let n = self.order.len();
        let side = |(vp, xd, xp), offset, order| ActiveSide {
            vp,
            xd,
            xp,
            offset,
            order,
            max_v2: 0.0,
            non_finite: false,
        };
        let cut = cut_at_middle(n, |i| self.list[self.order[i] as usize]);
        let (Some(pool), Some((h, mid))) = (pool.filter(|p| p.threads() > 1), cut) else {
            let mut all = side((vp, xd, xp), 0, 0..n);
            self.run(&mut all);
            return (all.max_v2, all.non_finite);
        };
        let (vp0, vp1) = vp.split_at_mut(mid);
        let (xd0, xd1) = xd.split_at_mut(mid);
        let (xp0, xp1) = xp.split_at_mut(mid);
        let mut halves = [
            side((vp0, xd0, xp0), 0, 0..h),
            side((vp1, xd1, xp1), mid, h..n),
        ];
        pool.for_each_mut(&mut halves, &|_, s| self.run(s));
        let [a, b] = &halves;
        (a.max_v2.max(b.max_v2), a.non_finite | b.non_finite)
    }
}
