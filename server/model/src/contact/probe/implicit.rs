//! The sphere contact for backward Euler: the faces the sphere touches are penalty springs
//! in series with the virtual coupling through the massless proxy, all implicit in the step.
//!
//! The explicit sphere contact ([`Probe`]'s `update_sphere`) fixes the load distribution from
//! the previous configuration's gaps; a backward Euler step of 1 ms nearly reaches the
//! quasi-static response to that distribution, and past about 2.5 mm indentation on the LV the
//! distribution then swung from tick to tick (a period-2 oscillation, `docs/accuracy.md`).
//! Under-relaxing it did not help. Here the distribution is part of the step's unknowns.
//!
//! **Model.** The proxy `p` (the sphere's centre) is massless. Each face `f` near it has the
//! point `c_f` closest to `p` (barycentric `beta_f`), the unit direction `nu_f = (c_f - p) /
//! |c_f - p|` from the centre to it (faces need not be consistently oriented) and the gap
//! `g_f = |c_f - p| - r`; a penetrating face pushes the body along `nu_f` with the smoothed
//! penalty `lambda_f(g_f)` ([`contact_law`]: quadratic over the first [`PENALTY_BAND`] `r` of
//! penetration, then linear with the stiffness `k_p`, [`PENALTY_FACTOR`] times the coupling's)
//! spread to its corners by `beta_f`, and the sphere back. The coupling pulls the proxy
//! towards the device with `phi - Q_c dp`: `phi = k (d - p0) + b n (n . v_d)`,
//! `Q_c = k I + (b / h) n n^T` (the damping acts along the contact normal `n` only, so the
//! proxy slides freely). Linearising each face's law at its gap (stiffness `k_f`), the gaps in
//! the step (`dx = h v'` of the corners, `dp` of the proxy, `beta_f` and `nu_f` frozen) and
//! eliminating `dp` from the proxy's balance `phi - Q_c dp = N lambda` (`N = [nu_f]`) gives
//!
//! `lambda = -C (g_hat + A dx)`, `C^-1 = K_f^-1 + N^T Q_c^-1 N`,
//! `g_hat = -lambda_f(g) / k_f - N^T Q_c^-1 phi`,
//!
//! with `A` the rows `a_f = (beta_fj nu_f)`: the body's contact force `A^T lambda` has the
//! explicit part `A^T lambda0`, `lambda0 = -C g_hat` ([`Probe::add_reaction`]), and the implicit
//! term `h^2 A^T C A` that the integrators solve with ([`ContactCoupling`]). With one face,
//! `C = k_f k_eff / (k_f + k_eff)`: the coupling in series with the penalty; as `k_p` grows,
//! relative motions of the faces that a rigid sphere forbids become stiff, which is what holds
//! the distribution still. After the solve, `lambda` follows from the end-of-step velocities,
//! the device force is `F = -N lambda` (minus the body's total contact force, so linear
//! momentum is conserved) and the proxy moves by `dp = Q_c^-1 (phi + F)`.
//!
//! **Which faces.** Every face the proxy penetrates at the start of the step (`g_f < 0`);
//! at first touch the cast proxy is moved a tenth of the onset band inwards so that the face
//! it touches has a stiffness. A face's stiffness vanishes with its force at `g_f = 0`, so
//! faces enter and leave the set without a jump. There is no active-set iteration: dropping
//! the faces whose `lambda0_f` came out negative made the load jump between two faces from
//! tick to tick while sliding (33 % of the force); kept, such a face pulls a little for a step
//! (at most 1.5 mN of 11 in the LV stroke) and leaves as it separates. No face left ends the
//! contact (the proxy returns to the device). The smooth onset costs accuracy: the sphere
//! sinks in by up to half the band plus `lambda / k_p` (10 + 2 um at 50 mN for the 2 mm
//! probe), 0.1 % of the default LV's force against its static sphere solve.

use glam::{DMat3, DVec3};

use super::super::coupling::{
    ContactCoupling, MAX_COUPLING_ROWS, cholesky_in_place, cholesky_solve,
};
use super::super::{MAX_CONTACT_TRIANGLES, SurfacePoint};
use super::Probe;

/// Penalty stiffness of a face in contact, in coupling stiffnesses (300 N/m coupling: 30 kN/m
/// per face, so a 50 mN press sinks the sphere about 2 um into the faces).
pub const PENALTY_FACTOR: f64 = 100.0;

/// Width of the penalty's smooth onset, in probe radii (20 um for the 2 mm probe): a face's
/// force grows quadratically over the first `PENALTY_BAND r` of penetration
/// ([`contact_law`]), so faces enter and leave the contact without a jump while the probe
/// slides over the facets.
pub const PENALTY_BAND: f64 = 0.01;

/// The smoothed penalty law: the push `lambda` (N) of a face at gap `g_m` (negative:
/// penetration) and its stiffness `-d lambda / d g` (N/m): zero for `g >= 0`,
/// `k_p g^2 / (2 w)` over `-w < g < 0`, `k_p (-g - w / 2)` deeper (continuous with its slope).
pub fn contact_law(g_m: f64, k_p: f64, band_m: f64) -> (f64, f64) {
    if g_m >= 0.0 {
        (0.0, 0.0)
    } else if g_m > -band_m {
        (k_p * g_m * g_m / (2.0 * band_m), -k_p * g_m / band_m)
    } else {
        (k_p * (-g_m - 0.5 * band_m), k_p)
    }
}

/// A face near the proxy.
#[derive(Debug, Clone, Copy)]
pub(super) struct Candidate {
    triangle: u32,
    bary: [f64; 3],
    nu: DVec3,
    g_hat: f64,
    /// The face's penalty stiffness in the step, N/m.
    k_f: f64,
}

/// The probe's implicit term: rows, compliance and its factor, the explicit multipliers; also
/// the kernel patch's single row ([`Probe::coupling`]).
#[derive(Debug, Clone, Default)]
pub(super) struct CouplingRows {
    pub(super) row_ptr: Vec<u32>,
    pub(super) nodes: Vec<u32>,
    pub(super) vectors: Vec<DVec3>,
    pub(super) compliance: Vec<f64>,
    pub(super) factor: Vec<f64>,
    /// Explicit multipliers `lambda0` (N), one per row (implicit sphere only).
    lambda0: Vec<f64>,
    /// `nu_f` per row (implicit sphere only).
    normals: Vec<DVec3>,
    /// Per candidate face, in `candidates` (capacity [`MAX_CONTACT_TRIANGLES`]).
    candidates: Vec<Candidate>,
    /// `phi` (N), `Q_c^-1` (m/N) and the proxy at the start of the step (m).
    phi_n: DVec3,
    qc_inv: DMat3,
    proxy0_m: DVec3,
    /// The frictionless proxy at the end of the last step, m (`state.proxy_m` adds the
    /// friction's tangential offset to it).
    proxy_free_m: DVec3,
}

impl CouplingRows {
    /// The explicit multipliers `lambda0` of the candidate rows: the compliance `A Q_c^-1 A^T
    /// + K_f^-1` (`qc_inv`: the coupling's inverse stiffness), its Cholesky factor, and the
    /// solve for `-g_hat`. `false` when the factor fails (a non-finite state).
    fn solve_multipliers(&mut self, qc_inv: &DMat3) -> bool {
        let rows = self;
        let nf = rows.candidates.len();
        for f in 0..nf {
            let qf = *qc_inv * rows.candidates[f].nu;
            for g in 0..=f {
                let mut v = rows.candidates[g].nu.dot(qf);
                if f == g {
                    v += 1.0 / rows.candidates[f].k_f;
                }
                rows.compliance[f * nf + g] = v;
                rows.compliance[g * nf + f] = v;
            }
        }
        rows.factor[..nf * nf].copy_from_slice(&rows.compliance[..nf * nf]);
        if !cholesky_in_place(&mut rows.factor[..nf * nf], nf) {
            return false;
        }
        rows.lambda0.clear();
        rows.lambda0
            .extend(rows.candidates.iter().map(|c| -c.g_hat));
        cholesky_solve(&rows.factor[..nf * nf], nf, &mut rows.lambda0);
        true
    }

    pub(super) fn with_capacity() -> Self {
        Self {
            row_ptr: Vec::with_capacity(MAX_COUPLING_ROWS + 1),
            nodes: Vec::with_capacity((3 * MAX_COUPLING_ROWS).max(super::MAX_PATCH_NODES)),
            vectors: Vec::with_capacity((3 * MAX_COUPLING_ROWS).max(super::MAX_PATCH_NODES)),
            compliance: vec![0.0; MAX_COUPLING_ROWS * MAX_COUPLING_ROWS],
            factor: vec![0.0; MAX_COUPLING_ROWS * MAX_COUPLING_ROWS],
            lambda0: Vec::with_capacity(MAX_COUPLING_ROWS),
            normals: Vec::with_capacity(MAX_COUPLING_ROWS),
            candidates: Vec::with_capacity(MAX_CONTACT_TRIANGLES),
            phi_n: DVec3::ZERO,
            qc_inv: DMat3::ZERO,
            proxy0_m: DVec3::ZERO,
            proxy_free_m: DVec3::ZERO,
        }
    }

    pub(super) fn rows(&self) -> usize {
        self.row_ptr.len().saturating_sub(1)
    }

    pub(super) fn view(&self) -> ContactCoupling<'_> {
        let nf = self.rows();
        ContactCoupling {
            row_ptr: &self.row_ptr,
            nodes: &self.nodes,
            vectors: &self.vectors,
            compliance: &self.compliance[..nf * nf],
            compliance_factor: &self.factor[..nf * nf],
        }
    }

    /// One row `(nodes[i], vectors[i])` with the scalar compliance `1 / c_n_per_m`.
    pub(super) fn set_single_row(
        &mut self,
        nodes: &[u32],
        vector: impl Fn(usize) -> DVec3,
        c_n_per_m: f64,
    ) {
        self.row_ptr.clear();
        self.nodes.clear();
        self.vectors.clear();
        self.lambda0.clear();
        self.row_ptr.extend([0, nodes.len() as u32]);
        self.nodes.extend_from_slice(nodes);
        self.vectors.extend((0..nodes.len()).map(vector));
        self.compliance[0] = 1.0 / c_n_per_m;
        self.factor[0] = self.compliance[0].sqrt();
    }
}

impl Probe {
    /// The implicit sphere contact's update (module documentation): the proxy of the last
    /// step (or, at first touch, the sphere cast out of the surface), the faces in contact, and
    /// the explicit multipliers. `sp` is the surface point closest to the device.
    pub(super) fn update_sphere_implicit(
        &mut self,
        x: &[DVec3],
        device_m: DVec3,
        device_vel: DVec3,
        sp: SurfacePoint,
    ) -> super::ContactState {
        let (r, h) = (self.params.radius_m, self.implicit_dt_s);
        let first_touch = !self.state.in_contact;
        if first_touch {
            // First touch: the exact non-penetrating proxy.
            let st = self.update_sphere(x, device_m, device_vel, sp);
            if !st.in_contact {
                return st;
            }
        }
        let n = self.state.normal;
        let mut p0 = if first_touch {
            self.state.proxy_m
        } else {
            self.rows.proxy_free_m
        };
        if first_touch {
            // The cast proxy touches with zero gap, where the penalty has no stiffness yet:
            // start it a tenth of the penalty's onset band inside.
            p0 -= n * (0.1 * PENALTY_BAND * r);
        }
        let (k, b) = (
            self.params.coupling_stiffness_n_per_m,
            self.params.coupling_damping_n_s_per_m,
        );
        let k_n = k + b / h;
        let phi = (device_m - p0) * k + n * (b * n.dot(device_vel));
        // Q_c = k I + (b/h) n n^T  =>  Q_c^-1 = (I - n n^T) / k + n n^T / (k + b/h).
        let nn = DMat3::from_cols(n * n.x, n * n.y, n * n.z);
        let qc_inv = (DMat3::IDENTITY - nn) * (1.0 / k) + nn * (1.0 / k_n);
        let free = qc_inv * phi;
        self.gather_candidates(x, p0, n, free);

        // Every penetrated face is in the step (no active-set iteration: dropping the faces
        // whose multiplier comes out negative made the load jump between two faces from tick
        // to tick while sliding; kept, such a face pulls a little for a step and leaves as it
        // separates, its stiffness vanishing with its force).
        let rows = &mut self.rows;
        let nf = rows.candidates.len();
        if nf == 0 {
            rows.row_ptr.clear();
            return self.disengage(device_m);
        }
        if !rows.solve_multipliers(&qc_inv) {
            rows.row_ptr.clear();
            return self.disengage(device_m);
        }
        // Rows a_f = (beta_fj nu_f) over the face's corners.
        rows.row_ptr.clear();
        rows.nodes.clear();
        rows.vectors.clear();
        rows.normals.clear();
        rows.row_ptr.push(0);
        let (mut best, mut best_lambda) = (0, f64::NEG_INFINITY);
        let mut total = DVec3::ZERO;
        for (f, c) in rows.candidates.iter().enumerate() {
            let tri = self.surface.triangles[c.triangle as usize];
            for (&i, &beta) in tri.iter().zip(&c.bary) {
                rows.nodes.push(i);
                rows.vectors.push(c.nu * beta);
            }
            rows.row_ptr.push(rows.nodes.len() as u32);
            rows.normals.push(c.nu);
            total += c.nu * rows.lambda0[f];
            if rows.lambda0[f] > best_lambda {
                best_lambda = rows.lambda0[f];
                best = f;
            }
        }
        rows.phi_n = phi;
        rows.qc_inv = qc_inv;
        rows.proxy0_m = p0;
        self.share_patch();
        let c = self.rows.candidates[best];
        let normal = (-total).try_normalize().unwrap_or(n);
        self.state.in_contact = true;
        self.state.normal = normal;
        self.state.triangle = c.triangle;
        self.state.bary = c.bary;
        self.state.force_on_device_n = -total;
        self.apply_friction(p0 + (free - normal * free.dot(normal)), total, first_touch);
        self.state.force_on_device_n += self.friction_n;
        self.state
    }

    /// The faces within reach of the proxy `p0` moving freely (by `free`) towards the device,
    /// penetrated by it, as candidate rows (at most [`MAX_COUPLING_ROWS`], the deepest), with
    /// the smoothed penalty linearised at their gaps; `n` is the last contact normal.
    fn gather_candidates(&mut self, x: &[DVec3], p0: DVec3, n: DVec3, free: DVec3) {
        let r = self.params.radius_m;
        let k = self.params.coupling_stiffness_n_per_m;
        // Faces within reach of the proxy moving freely towards the device.
        self.stamp = self.stamp.wrapping_add(1);
        if self.stamp == 0 {
            self.tri_stamps.fill(0);
            self.stamp = 1;
        }
        let seed = self.state.triangle;
        self.surface.gather_triangles(
            x,
            p0,
            seed,
            1.5 * r + free.length(),
            (&mut self.tri_stamps, self.stamp),
            &mut self.tris,
        );
        let k_p = PENALTY_FACTOR * k;
        let band = PENALTY_BAND * r;
        let rows = &mut self.rows;
        rows.candidates.clear();
        for &t in &self.tris {
            let c = self.surface.closest_on(t, x, p0);
            let dist = c.dist2.sqrt();
            // Faces are not assumed consistently oriented (Gmsh surfaces are not): the
            // direction is the centre's to the face's closest point; a centre on the face
            // pushes along the contact normal. (The face's own normal instead made deep
            // presses oscillate: at 3.7 mm on the default LV the force swung by 56 %.)
            let (nu, g) = if dist > 1e-9 * r {
                ((c.point - p0) / dist, dist - r)
            } else {
                (-n, -r)
            };
            if nu == DVec3::ZERO {
                continue;
            }
            // The smoothed penalty (`contact_law`), linearised at the current gap: a face's
            // stiffness in the step vanishes with its force, so it enters and leaves smoothly.
            if g >= 0.0 {
                continue;
            }
            let (lambda_now, k_f) = contact_law(g, k_p, band);
            if !(k_f > 1e-9 * k_p) {
                continue;
            }
            // The linear law through (g, lambda_now) with slope -k_f, in the form
            // `lambda = -k_f (g_eff + ...)`, then minus the proxy's free motion.
            let g_hat = -lambda_now / k_f - nu.dot(free);
            rows.candidates.push(Candidate {
                triangle: t,
                bary: c.bary,
                nu,
                g_hat,
                k_f,
            });
        }
        if rows.candidates.len() > MAX_COUPLING_ROWS {
            rows.candidates
                .select_nth_unstable_by(MAX_COUPLING_ROWS, |a, b| a.g_hat.total_cmp(&b.g_hat));
            rows.candidates.truncate(MAX_COUPLING_ROWS);
        }
    }

    /// The coupling force's tangential part under Coulomb friction, `friction_n`, and its
    /// anchor, for the frictionless proxy's position along the surface `frictionless` and
    /// the contact force `total` (N; `first_touch`: no offset yet).
    fn apply_friction(&mut self, frictionless: DVec3, total: DVec3, first_touch: bool) {
        let normal = self.state.normal;
        let k = self.params.coupling_stiffness_n_per_m;
        // Coulomb friction: the god-object cone of the other contact models
        // ([`Probe::engage`]), explicit in the step: the felt proxy sticks where it was while
        // the tangential coupling force `k o_t` stays within `mu` times the normal force,
        // and is dragged along the cone's edge beyond.
        self.friction_n = DVec3::ZERO;
        let mu = self.params.friction_coefficient;
        if mu > 0.0 {
            let offset = if first_touch {
                DVec3::ZERO
            } else {
                let o = self.anchor_m - frictionless;
                o - normal * o.dot(normal)
            };
            let limit = mu * total.length().min(self.params.max_force_n) / k;
            let len = offset.length();
            let offset = if len > limit {
                offset * (limit / len)
            } else {
                offset
            };
            self.friction_n = offset * k;
            self.anchor_m = frictionless + offset;
        }
    }

    /// The contact nodes and their share of the explicit load (what `patch` reports).
    fn share_patch(&mut self) {
        let rows = &self.rows;
        self.patch_nodes.clear();
        self.patch_weights.clear();
        let sum: f64 = rows.lambda0.iter().sum();
        for (f, c) in rows.candidates.iter().enumerate() {
            let tri = self.surface.triangles[c.triangle as usize];
            for (&i, &beta) in tri.iter().zip(&c.bary) {
                let w = if sum > 0.0 {
                    beta * rows.lambda0[f] / sum
                } else {
                    beta / rows.candidates.len() as f64
                };
                let slot = self.node_slot[i as usize];
                if slot != u32::MAX {
                    self.patch_weights[slot as usize] += w;
                } else if self.patch_nodes.len() < super::MAX_PATCH_NODES {
                    self.node_slot[i as usize] = self.patch_nodes.len() as u32;
                    self.patch_nodes.push(i);
                    self.patch_weights.push(w);
                }
            }
        }
        for &i in &self.patch_nodes {
            self.node_slot[i as usize] = u32::MAX;
        }
    }

    /// Adds the implicit sphere's explicit contact force `A^T lambda0` and minus the friction
    /// force (over the contact nodes' shares) to `f` (N).
    pub(super) fn add_implicit_sphere_reaction(&self, f: &mut [DVec3]) {
        let rows = &self.rows;
        let view = rows.view();
        view.add_at(&rows.lambda0, 1.0, f);
        if self.friction_n != DVec3::ZERO {
            for (&i, &w) in self.patch_nodes.iter().zip(&self.patch_weights) {
                f[i as usize] -= self.friction_n * w;
            }
        }
    }

    /// Completes an implicit sphere step from the end-of-step velocities `v`: the faces'
    /// multipliers `lambda = lambda0 - h C A v'`, the device force `F = -N lambda` (clamped in
    /// magnitude to [`super::ProbeParams::max_force_n`]; the body received the unclamped
    /// `A^T lambda`, so linear momentum is conserved) plus the friction force, and the proxy
    /// `p0 + Q_c^-1 (phi + F)` (reported with the friction's offset). Allocation-free.
    pub(super) fn finish_implicit_sphere(&mut self, dt_s: f64, v: &[DVec3]) {
        let nf = self.rows.rows();
        if nf == 0 {
            return;
        }
        let view = self.rows.view();
        let mut lambda = [0.0; MAX_COUPLING_ROWS];
        view.a_times(v, &mut lambda);
        view.apply_c(&mut lambda[..nf]);
        for (l, l0) in lambda.iter_mut().zip(&self.rows.lambda0) {
            *l = l0 - dt_s * *l;
        }
        let rows = &self.rows;
        let mut force = DVec3::ZERO;
        for (nu, l) in rows.normals.iter().zip(&lambda[..nf]) {
            force -= *nu * *l;
        }
        let proxy = rows.proxy0_m + rows.qc_inv * (rows.phi_n + force);
        let magnitude = force.length();
        let clamped = if magnitude > self.params.max_force_n {
            force * (self.params.max_force_n / magnitude)
        } else {
            force
        };
        let n = force.try_normalize().unwrap_or(self.state.normal);
        self.rows.proxy_free_m = proxy;
        let offset = self.friction_n / self.params.coupling_stiffness_n_per_m;
        self.state.proxy_m = proxy + offset;
        self.state.normal = n;
        self.state.force_on_device_n = clamped + self.friction_n;
        self.stiffness.observe(
            dt_s,
            self.device_m.dot(n),
            clamped.dot(n).max(0.0),
            self.params.coupling_stiffness_n_per_m,
        );
    }
}
