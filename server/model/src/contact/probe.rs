//! The haptic probe: a sphere at the device point touching the touchable surface through a
//! god-object (proxy) and a virtual coupling (see the module documentation of [`super`]).
//!
//! Neighbours: [`super::surface`] for the geometry, [`super::coupling`] for the low-rank term
//! the implicit integrators solve with; driven every sub-step by the FEM body's tick.

use glam::{DMat3, DVec3};

use super::coupling::ContactCoupling;
use super::local_law::LocalLaw;
use super::sphere::sphere_exit;
use super::surface::{ContactSurface, SurfacePoint};
use super::{
    LOCAL_PATCH_RADIUS_FACTOR, MAX_CONTACT_TRIANGLES, MAX_PATCH_NODES, PATCH_RADIUS_FACTOR,
};

mod implicit;

pub use implicit::{PENALTY_BAND, PENALTY_FACTOR, contact_law};

/// Largest accepted distance between a device point (or any point a client names) and the
/// scene origin, m: farther points are absurd (a unit error or a broken sensor).
pub const MAX_DEVICE_DISTANCE_M: f64 = 10.0;

/// How the probe meets the surface (scene key `probe.contact`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ContactModel {
    /// The most accurate model on the body: [`ContactModel::PatchLocal`] on FEM bodies under
    /// every integrator ([`crate::integrate::resolve_contact_model`]), the patch on
    /// mass-spring surfaces. A [`Probe`] given `Auto` uses the patch.
    #[default]
    Auto,
    /// The rigid sphere: the proxy is the sphere's non-penetrating position and the reaction
    /// acts on the faces the sphere actually touches (module documentation of [`super`]);
    /// under backward Euler those faces are stiff penalty springs solved inside the step and
    /// the sphere sinks in by about 12 um ([`Probe::use_implicit_sphere`]).
    Sphere,
    /// The kernel patch: a smoothed plane through the touchable nodes within `2 r` of the
    /// device, the reaction spread over them with kernel weights, whatever the depth.
    Patch,
    /// The kernel patch with the sphere's local Hertz compliance in series (a sub-grid contact
    /// model): the mesh carries the body's response to the patch's smooth load, and the local
    /// indentation of the tissue around a sphere of radius `r`, which facets coarser than the
    /// contact cannot resolve, is added as the Hertz spring `F = 4/3 E* r^(1/2) delta^(3/2)`
    /// between the patch's surface and the proxy ([`ProbeParams::hertz_modulus_pa`]). Its
    /// load distribution is the patch's, so every integrator carries it.
    PatchHertz,
    /// The kernel patch with the sphere's local indentation in series, as
    /// [`ContactModel::PatchHertz`] but with the material's own law of a sphere on a
    /// half-space ([`super::local_law`], set by the FEM body: [`Probe::set_local_law`]) in place
    /// of Hertz's, and the patch's plane raised to the rest surface under the device (its
    /// curvature's sag, [`patch_sag`]), so that contact starts where the sphere touches the
    /// surface rather than the chord plane through the patch's nodes.
    PatchLocal,
}

impl ContactModel {
    /// Every model a scene may name, in the order of [`ContactModel::name`] (for parsing and
    /// listings; the README test checks each is documented).
    pub const ALL: [ContactModel; 5] = [
        Self::Auto,
        Self::Sphere,
        Self::Patch,
        Self::PatchHertz,
        Self::PatchLocal,
    ];

    /// The scene-file name (`"auto"`, `"sphere"`, `"patch"`, `"patch-hertz"`,
    /// `"patch-local"`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Sphere => "sphere",
            Self::Patch => "patch",
            Self::PatchHertz => "patch-hertz",
            Self::PatchLocal => "patch-local",
        }
    }

    /// The model of a scene-file name.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.name() == name)
    }
}

/// Haptic probe and virtual coupling parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeParams {
    /// Contact model.
    pub contact: ContactModel,
    /// Probe sphere radius, m.
    pub radius_m: f64,
    /// Virtual coupling stiffness between proxy and device point, N/m.
    pub coupling_stiffness_n_per_m: f64,
    /// Virtual coupling damping along the contact normal, N s/m.
    pub coupling_damping_n_s_per_m: f64,
    /// Largest coupling force magnitude the model applies and returns, N.
    pub max_force_n: f64,
    /// Coulomb friction coefficient between the probe and the surface (0: frictionless).
    pub friction_coefficient: f64,
    /// Effective (plane-strain) modulus `E* = E / (1 - nu^2)` of the touched tissue at small
    /// strain, Pa, for [`ContactModel::PatchHertz`] (and [`ContactModel::PatchLocal`] until
    /// its law is set): set by the FEM body from its material (scene files do not set it); zero
    /// when unknown.
    pub hertz_modulus_pa: f64,
}

impl Default for ProbeParams {
    fn default() -> Self {
        Self {
            contact: ContactModel::default(),
            radius_m: 2e-3,
            coupling_stiffness_n_per_m: 300.0,
            coupling_damping_n_s_per_m: 0.05,
            max_force_n: 10.0,
            friction_coefficient: 0.0,
            hertz_modulus_pa: 0.0,
        }
    }
}

/// Result of a probe update.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ContactState {
    /// Whether the probe touches the surface.
    pub in_contact: bool,
    /// Force the device must render (virtual coupling on the device), N.
    pub force_on_device_n: DVec3,
    /// Proxy (god-object) centre, m. Equals the device point out of contact.
    pub proxy_m: DVec3,
    /// Outward contact normal (zero out of contact).
    pub normal: DVec3,
    /// Contact triangle and barycentric weights (valid in contact).
    pub triangle: u32,
    /// Barycentric weights on `triangle`.
    pub bary: [f64; 3],
}

/// The haptic probe: parameters, the touchable surface and the contact state.
#[derive(Debug, Clone)]
pub struct Probe {
    /// Parameters.
    pub params: ProbeParams,
    /// Touchable surface.
    pub surface: ContactSurface,
    /// Rest-configuration bounding box of the surface, expanded by a margin, for a cheap
    /// "far away" test that skips the search.
    reach_min: DVec3,
    reach_max: DVec3,
    /// Last contact state.
    pub state: ContactState,
    /// Contact patch nodes and weights (capacity [`MAX_PATCH_NODES`], never reallocated).
    patch_nodes: Vec<u32>,
    patch_weights: Vec<f64>,
    /// Explicit part of the normal coupling force of the current step, N.
    phi0_n: f64,
    /// Stiffness of the normal coupling against the surface's motion along `n` in the current
    /// step, N/m: the coupling `k`, or with the local law in series
    /// ([`ContactModel::PatchHertz`], [`ContactModel::PatchLocal`]) `k K' / (k + K')` with `K'`
    /// the law's tangent.
    coupling_k_n_per_m: f64,
    /// Sphere contact scratch: candidate triangles (capacity [`MAX_CONTACT_TRIANGLES`]), their
    /// visit stamps (one per surface triangle) and each node's slot in the patch (one per
    /// node, `u32::MAX` when not in it).
    tris: Vec<u32>,
    tri_stamps: Vec<u32>,
    /// Device point of the last update, m.
    device_m: DVec3,
    /// Friction: where the proxy sticks (valid in contact), m, and the tangential coupling
    /// force on the device of the current step, N.
    anchor_m: DVec3,
    friction_n: DVec3,
    /// Running estimate of the contact stiffness at the device ([`Probe::contact_stiffness`]).
    stiffness: StiffnessEstimate,
    /// Footprint of an injected probe load ([`Probe::load_patch`]), capacity
    /// [`MAX_PATCH_NODES`].
    load_nodes: Vec<u32>,
    load_weights: Vec<f64>,
    stamp: u32,
    node_slot: Vec<u32>,
    /// The implicit term handed to backward Euler ([`Probe::coupling`]).
    rows: implicit::CouplingRows,
    /// Sub-step of the backward Euler body the sphere contact is implicit for, s; zero for
    /// the explicit sphere contact ([`Probe::use_implicit_sphere`]).
    implicit_dt_s: f64,
    /// The local law of [`ContactModel::PatchLocal`] ([`Probe::set_local_law`]).
    local_law: LocalLaw,
    /// Rest positions and rest curvature tensors of the body's nodes (for the patch's sag
    /// under [`ContactModel::PatchLocal`]; empty otherwise).
    rest: Vec<DVec3>,
    rest_curvature: Vec<DMat3>,
}

/// Reach of the rest curvature fit at each node ([`ContactSurface::curvature_tensors`]), in
/// radii of the local patch: twice the patch, so that coarse meshes (nodes 3-4 mm apart on
/// `lv_h3`) still have enough neighbours.
const CURVATURE_REACH_FACTOR: f64 = 2.0;

/// Smallest contact band of the sphere contact, in probe radii: at first touch (proxy offset
/// `t` near zero) the faces within `r / 100` of the sphere carry the load.
const SPHERE_BAND_MIN: f64 = 0.01;

impl Probe {
    /// Builds a probe over `touchable` triangles of a body whose rest positions are `rest`.
    pub fn new(params: ProbeParams, touchable: Vec<[u32; 3]>, rest: &[DVec3]) -> Self {
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for t in &touchable {
            for &i in t {
                lo = lo.min(rest[i as usize]);
                hi = hi.max(rest[i as usize]);
            }
        }
        // Deformations larger than half the body size are far outside haptic use.
        let margin = (hi - lo).max_element() * 0.5 + params.radius_m;
        let mut probe = Self {
            params,
            surface: ContactSurface::new(touchable, rest.len()),
            reach_min: lo - DVec3::splat(margin),
            reach_max: hi + DVec3::splat(margin),
            state: ContactState::default(),
            patch_nodes: Vec::with_capacity(MAX_PATCH_NODES),
            patch_weights: Vec::with_capacity(MAX_PATCH_NODES),
            phi0_n: 0.0,
            coupling_k_n_per_m: params.coupling_stiffness_n_per_m,
            tris: Vec::with_capacity(MAX_CONTACT_TRIANGLES),
            tri_stamps: Vec::new(),
            device_m: DVec3::ZERO,
            anchor_m: DVec3::ZERO,
            friction_n: DVec3::ZERO,
            stiffness: StiffnessEstimate::default(),
            load_nodes: Vec::with_capacity(MAX_PATCH_NODES),
            load_weights: Vec::with_capacity(MAX_PATCH_NODES),
            stamp: 0,
            node_slot: Vec::new(),
            rows: implicit::CouplingRows::with_capacity(),
            implicit_dt_s: 0.0,
            local_law: LocalLaw::hertz(params.hertz_modulus_pa, params.radius_m),
            rest: Vec::new(),
            rest_curvature: Vec::new(),
        };
        probe.size_scratch();
        if params.contact == ContactModel::PatchLocal {
            probe.rest = rest.to_vec();
            probe.rest_curvature = probe.surface.curvature_tensors(
                rest,
                CURVATURE_REACH_FACTOR * LOCAL_PATCH_RADIUS_FACTOR * params.radius_m,
            );
        }
        probe
    }

    /// A copy of this probe for another tool slot: the same surface, law and curvature, the
    /// contact scratch at full capacity (a derived clone keeps only the lengths, so the copy
    /// would grow its patch and rows in its first contacts: allocations in the servo tick).
    /// Not for the servo tick.
    pub fn clone_for_slot(&self) -> Self {
        Self {
            patch_nodes: Vec::with_capacity(MAX_PATCH_NODES),
            patch_weights: Vec::with_capacity(MAX_PATCH_NODES),
            tris: Vec::with_capacity(MAX_CONTACT_TRIANGLES),
            load_nodes: Vec::with_capacity(MAX_PATCH_NODES),
            load_weights: Vec::with_capacity(MAX_PATCH_NODES),
            rows: implicit::CouplingRows::with_capacity(),
            ..self.clone()
        }
    }

    /// Sets the local law of [`ContactModel::PatchLocal`] (by default Hertz's with
    /// [`ProbeParams::hertz_modulus_pa`]). Not for the servo tick (the law is moved in).
    pub fn set_local_law(&mut self, law: LocalLaw) {
        self.local_law = law;
    }

    /// The local law of [`ContactModel::PatchLocal`].
    pub fn local_law(&self) -> &LocalLaw {
        &self.local_law
    }

    /// Replaces the touchable surface (a body whose surface changes at run time builds it with
    /// [`ContactSurface::with_capacity`]) and sizes the contact scratch for its triangle
    /// capacity and node count. Not for the servo tick (allocates).
    pub fn replace_surface(&mut self, surface: ContactSurface) {
        self.surface = surface;
        self.state = ContactState::default();
        self.size_scratch();
    }

    fn size_scratch(&mut self) {
        let capacity = self
            .surface
            .triangles
            .capacity()
            .max(self.surface.triangles.len());
        self.tri_stamps = vec![0; capacity];
        self.stamp = 0;
        self.node_slot = vec![u32::MAX; self.surface.node_count()];
    }

    /// Updates the contact for device point `device_m` (m) moving at `device_vel` (m/s) against
    /// the body at positions `x`. The surface-velocity part of the coupling is implicit
    /// ([`Probe::finish_implicit`]). Allocation-free.
    pub fn update(&mut self, x: &[DVec3], device_m: DVec3, device_vel: DVec3) -> ContactState {
        self.device_m = device_m;
        if self.surface.triangles.is_empty()
            || device_m.cmplt(self.reach_min).any()
            || device_m.cmpgt(self.reach_max).any()
        {
            return self.disengage(device_m);
        }
        let sp = if self.state.in_contact {
            self.surface
                .closest_local(x, device_m, self.state.triangle, 16)
        } else {
            match self.surface.closest_global(x, device_m) {
                Some(sp) => sp,
                None => return self.disengage(device_m),
            }
        };
        match self.params.contact {
            ContactModel::Sphere if self.implicit_dt_s > 0.0 => {
                self.update_sphere_implicit(x, device_m, device_vel, sp)
            }
            ContactModel::Sphere => self.update_sphere(x, device_m, device_vel, sp),
            ContactModel::Patch
            | ContactModel::PatchHertz
            | ContactModel::PatchLocal
            | ContactModel::Auto => self.update_patch(x, device_m, device_vel, sp),
        }
    }

    /// The kernel patch (module documentation of [`super`]); `sp` is the closest surface point
    /// to the device.
    fn update_patch(
        &mut self,
        x: &[DVec3],
        device_m: DVec3,
        device_vel: DVec3,
        sp: SurfacePoint,
    ) -> ContactState {
        let r = self.params.radius_m;
        let reach = PATCH_RADIUS_FACTOR * r;
        if sp.dist2 >= reach * reach {
            return self.disengage(device_m);
        }
        // Smoothed local surface: kernel-weighted plane through the patch around the device.
        // (Also with the Hertz spring in series: a patch centred where the plain patch's probe
        // would be, `delta` further out along the last normal, made backward Euler diverge
        // under a ten-fold injected load, the patch then following the deformation a step
        // late.)
        self.gather_patch(x, device_m, sp.triangle);
        let Some((mut centre, mut n)) = self.patch_plane(x) else {
            return self.disengage(device_m);
        };
        let mut signed = (device_m - centre).dot(n);
        if self.params.contact == ContactModel::PatchLocal {
            // The footprint of the first touch, kept: the nodes within `sqrt(3) r` of the
            // device's foot on the plane (module documentation of [`super`]).
            let foot = device_m - n * signed;
            self.surface.gather_kernel_patch(
                x,
                foot,
                sp.triangle,
                LOCAL_PATCH_RADIUS_FACTOR * r,
                &mut self.patch_nodes,
                &mut self.patch_weights,
            );
            let Some(plane) = self.patch_plane(x) else {
                return self.disengage(device_m);
            };
            (centre, n) = plane;
            signed = (device_m - centre).dot(n);
            // The plane through the nodes lies below a convex surface by its sag.
            signed -= patch_sag(
                &self.patch_nodes,
                &self.patch_weights,
                &self.rest,
                &self.rest_curvature,
                r,
            );
        }
        if signed >= r {
            return self.disengage(device_m);
        }
        let sp = SurfacePoint {
            point: centre,
            ..sp
        };
        self.engage(device_m, device_vel, n, r - signed, sp)
    }

    /// The rigid sphere. Starting from the last contact normal `n0` (on first touch, the
    /// direction from the closest surface point `sp` to the device), the sphere is cast along
    /// `n0` out of the deformed triangles near the device ([`sphere_exit`]): the proxy
    /// `device + t n0` is the nearest centre on that line at which the sphere penetrates no
    /// triangle. The faces within a band of the proxy sphere, gap
    /// `g_T = dist(proxy, T) - r < delta` with `delta = max(t, r / 100)`, are in contact;
    /// each carries the weight `A_T (1 - g_T / delta)^2` (area times a kernel that vanishes at
    /// the band's edge, so the contact set changes continuously), and the normal becomes their
    /// weighted face normal `n`; the sphere is cast again along `n` for the final proxy. The
    /// face weights go to the nodes by the barycentric coordinates of each face's closest point
    /// to the proxy (normalised to sum 1): the reaction acts on the faces the sphere touches,
    /// on an area that grows with the depth, as a Hertz contact's does.
    fn update_sphere(
        &mut self,
        x: &[DVec3],
        device_m: DVec3,
        device_vel: DVec3,
        sp: SurfacePoint,
    ) -> ContactState {
        let r = self.params.radius_m;
        let (n0, t_guess) = if self.state.in_contact {
            let n = self.state.normal;
            (n, (self.state.proxy_m - device_m).dot(n).max(0.0))
        } else {
            if sp.dist2 >= r * r {
                return self.disengage(device_m);
            }
            let face_n = self.surface.normal(sp.triangle, x);
            let out = device_m - sp.point;
            let n = if out.dot(face_n) > 1e-6 * r {
                out.normalize()
            } else {
                face_n
            };
            (n, 0.0)
        };
        if n0 == DVec3::ZERO {
            return self.disengage(device_m);
        }
        // Faces that can stop the cast or lie in the band: within r + 2 t of the device, with
        // room for the device's motion since the last update.
        self.stamp = self.stamp.wrapping_add(1);
        if self.stamp == 0 {
            self.tri_stamps.fill(0);
            self.stamp = 1;
        }
        self.surface.gather_triangles(
            x,
            device_m,
            sp.triangle,
            3.0 * r + 2.0 * t_guess,
            (&mut self.tri_stamps, self.stamp),
            &mut self.tris,
        );
        let Some((t0, _)) = self.cast(x, device_m, n0) else {
            return self.disengage(device_m);
        };
        let band = t0.max(SPHERE_BAND_MIN * r);
        let proxy0 = device_m + n0 * t0;
        let mut normal_sum = DVec3::ZERO;
        for &k in &self.tris {
            if let Some((w, _, normal)) = self.band_face(k, x, proxy0, band) {
                normal_sum += normal * w;
            }
        }
        let n = normal_sum.try_normalize().unwrap_or(n0);
        let Some((t, exit_face)) = self.cast(x, device_m, n) else {
            return self.disengage(device_m);
        };
        let proxy = device_m + n * t;
        // Node weights of the faces in contact at the final proxy.
        self.patch_nodes.clear();
        self.patch_weights.clear();
        let band = t.max(SPHERE_BAND_MIN * r);
        let mut sum = 0.0;
        for &k in &self.tris {
            let Some((w, c, _)) = self.band_face(k, x, proxy, band) else {
                continue;
            };
            let tri = self.surface.triangles[k as usize];
            for (&node, &bary) in tri.iter().zip(&c.bary) {
                let wn = w * bary;
                if wn <= 0.0 {
                    continue;
                }
                let slot = self.node_slot[node as usize];
                if slot != u32::MAX {
                    self.patch_weights[slot as usize] += wn;
                } else if self.patch_nodes.len() < MAX_PATCH_NODES {
                    self.node_slot[node as usize] = self.patch_nodes.len() as u32;
                    self.patch_nodes.push(node);
                    self.patch_weights.push(wn);
                } else {
                    continue;
                }
                sum += wn;
            }
        }
        for &i in &self.patch_nodes {
            self.node_slot[i as usize] = u32::MAX;
        }
        if !(sum > 0.0) {
            return self.disengage(device_m);
        }
        self.patch_weights.iter_mut().for_each(|w| *w /= sum);
        let contact = self.surface.closest_on(exit_face, x, proxy);
        self.engage(device_m, device_vel, n, t, contact)
    }

    /// Triangle `k` in the contact band of the sphere centred at `proxy_m`: its weight
    /// `A_T (1 - g / band)^2` for the gap `g = dist - r` below `band` (a penetrating face
    /// counts as touching), its point closest to the centre and its unit normal; `None` beyond
    /// the band or for a degenerate face.
    fn band_face(
        &self,
        k: u32,
        x: &[DVec3],
        proxy_m: DVec3,
        band_m: f64,
    ) -> Option<(f64, SurfacePoint, DVec3)> {
        let c = self.surface.closest_on(k, x, proxy_m);
        let gap = (c.dist2.sqrt() - self.params.radius_m).max(0.0);
        if gap >= band_m {
            return None;
        }
        let [a, b, cc] = self.surface.triangles[k as usize].map(|i| x[i as usize]);
        let cross = (b - a).cross(cc - a);
        let u = 1.0 - gap / band_m;
        let w = 0.5 * cross.length() * u * u;
        (w > 0.0).then(|| (w, c, cross.normalize()))
    }

    /// The largest exit distance ([`sphere_exit`]) of the probe sphere cast from `device_m`
    /// along `n` over the gathered triangles, with the triangle that sets it; `None` when the
    /// sphere at the device touches none of them (exit at or behind the device).
    fn cast(&self, x: &[DVec3], device_m: DVec3, n: DVec3) -> Option<(f64, u32)> {
        let r = self.params.radius_m;
        let mut best: Option<(f64, u32)> = None;
        for &k in &self.tris {
            let [a, b, c] = self.surface.triangles[k as usize].map(|i| x[i as usize]);
            if let Some(t) = sphere_exit(device_m, n, r, a, b, c)
                && best.is_none_or(|(bt, _)| t > bt)
            {
                best = Some((t, k));
            }
        }
        best.filter(|&(t, _)| t > 0.0)
    }

    /// Out of contact.
    fn disengage(&mut self, device_m: DVec3) -> ContactState {
        self.stiffness = StiffnessEstimate::default();
        self.state = ContactState {
            proxy_m: device_m,
            ..ContactState::default()
        };
        self.state
    }

    /// In contact along the unit normal `n` with the proxy `depth_m` beyond the device
    /// (the coupling's stretch), touching at `sp`: sets the explicit coupling force.
    ///
    /// With Coulomb friction `mu > 0` the proxy sticks where it touched (a god-object with a
    /// friction cone): its tangential offset `o_t` from the frictionless position
    /// `device + depth n` gives the device the tangential force `k o_t`, as long as
    /// `|k o_t| <= mu phi0`; beyond it the proxy slides, dragged to the cone's edge. The
    /// anchor is a point in space (not on the surface) and the tangential reaction is applied
    /// explicitly over the contact weights: it does not depend on the body's positions, so it
    /// adds no stiffness to the step.
    fn engage(
        &mut self,
        device_m: DVec3,
        device_vel: DVec3,
        n: DVec3,
        depth_m: f64,
        sp: SurfacePoint,
    ) -> ContactState {
        let p = &self.params;
        // With the Hertz compliance in series the proxy sinks `delta` into the patch's surface
        // and the coupling stretches by the rest of the depth.
        let (depth_m, k_series) = if p.contact == ContactModel::PatchHertz {
            let (k, hertz_k) = (
                p.coupling_stiffness_n_per_m,
                hertz_stiffness(p.hertz_modulus_pa, p.radius_m),
            );
            let delta = hertz_series_indentation(depth_m, k, hertz_k);
            // The Hertz spring's tangent dF/d(delta) in series with the coupling.
            let k_hertz = 1.5 * hertz_k * delta.sqrt();
            (depth_m - delta, k * k_hertz / (k + k_hertz))
        } else if p.contact == ContactModel::PatchLocal {
            let k = p.coupling_stiffness_n_per_m;
            let delta = self.local_law.series_indentation(depth_m, k);
            // The law's tangent dF/d(delta) in series with the coupling.
            let k_local = self.local_law.force(delta).1;
            (depth_m - delta, k * k_local / (k + k_local))
        } else {
            (depth_m, p.coupling_stiffness_n_per_m)
        };
        self.coupling_k_n_per_m = k_series;
        // Explicit part of the normal coupling force (the surface-velocity term is implicit).
        let phi0 = p.coupling_stiffness_n_per_m * depth_m
            - p.coupling_damping_n_s_per_m * device_vel.dot(n);
        self.phi0_n = phi0;
        let frictionless = device_m + n * depth_m;
        let mut proxy = frictionless;
        self.friction_n = DVec3::ZERO;
        if p.friction_coefficient > 0.0 {
            let offset = if self.state.in_contact {
                let o = self.anchor_m - frictionless;
                o - n * o.dot(n)
            } else {
                DVec3::ZERO
            };
            let k = p.coupling_stiffness_n_per_m;
            let limit = p.friction_coefficient * phi0.clamp(0.0, p.max_force_n) / k;
            let len = offset.length();
            let offset = if len > limit {
                offset * (limit / len)
            } else {
                offset
            };
            proxy = frictionless + offset;
            self.friction_n = offset * k;
        }
        self.anchor_m = proxy;
        self.state = ContactState {
            in_contact: true,
            force_on_device_n: n * phi0.clamp(0.0, p.max_force_n) + self.friction_n,
            proxy_m: proxy,
            normal: n,
            triangle: sp.triangle,
            bary: sp.bary,
        };
        self.state
    }

    /// The device left the scene: no contact (the proxy state is cleared).
    pub fn release(&mut self) {
        self.stiffness = StiffnessEstimate::default();
        self.state = ContactState::default();
    }

    /// Completes a step with the coupling treated implicitly. After the integrator advanced
    /// every node with the explicit coupling part (see [`Probe::add_reaction`]), giving
    /// velocities `y`, the coupling term `gamma U U^T v'` with `U = (w_i n)` over the patch and
    /// `gamma = dt (k dt + b)` is solved exactly by Sherman-Morrison:
    /// `v' = y - z (gamma U^T y) / (1 + gamma U^T z)`, `z_i = w_i B_i^-1 n` where
    /// `B_i^-1 v = inv(i, v)` is the integrator's per-node inverse divided by the mass.
    /// Positions are corrected by `dt (v' - y)`. The device force becomes
    /// `phi n`, `phi = phi0 + (k dt + b) U^T v'`, clamped to `[0, max_force_n]`.
    /// This makes the virtual coupling unconditionally stable for any `k`, `b`. Allocation-free.
    pub fn finish_implicit(
        &mut self,
        dt_s: f64,
        x: &mut [DVec3],
        v: &mut [DVec3],
        inv: impl Fn(usize, DVec3) -> DVec3,
    ) {
        if !self.state.in_contact {
            return;
        }
        let n = self.state.normal;
        let gamma = self.coupling_gamma(dt_s);
        let (mut uty, mut utz) = (0.0, 0.0);
        for (&i, &w) in self.patch_nodes.iter().zip(&self.patch_weights) {
            uty += w * n.dot(v[i as usize]);
            utz += w * n.dot(inv(i as usize, n * w));
        }
        let delta = gamma * uty / (1.0 + gamma * utz);
        let mut utv = 0.0;
        for (&i, &w) in self.patch_nodes.iter().zip(&self.patch_weights) {
            let dv = inv(i as usize, n * w) * delta;
            v[i as usize] -= dv;
            x[i as usize] -= dv * dt_s;
            utv += w * n.dot(v[i as usize]);
        }
        self.set_device_force(dt_s, utv);
    }

    /// `gamma = dt (k dt + b)` (kg): the weight of the coupling's implicit rank-one term
    /// `gamma U U^T` over the patch (see [`Probe::finish_implicit`]); `k` is the coupling's
    /// stiffness against the surface's motion, in series with the local law under
    /// [`ContactModel::PatchHertz`] and [`ContactModel::PatchLocal`].
    pub fn coupling_gamma(&self, dt_s: f64) -> f64 {
        dt_s * (self.coupling_k_n_per_m * dt_s + self.params.coupling_damping_n_s_per_m)
    }

    /// Makes the sphere contact implicit for a backward Euler body with sub-step `dt_s` (s):
    /// the faces in contact become penalty springs in series with the coupling, solved inside
    /// the step ([`Probe::coupling`]; module `implicit` of this file's folder). Without it the
    /// sphere contact's load distribution is explicit, which only the explicit integrators carry.
    /// No effect on the patch models.
    pub fn use_implicit_sphere(&mut self, dt_s: f64) {
        self.implicit_dt_s = dt_s;
    }

    /// The probe's implicit term `h^2 A^T C A` for a global implicit solve with sub-step
    /// `dt_s` ([`crate::integrate::implicit::ImplicitSolver`], the condensed solver); `None`
    /// out of contact. For the patch models one row, `U = (w_i n)` with `C = k + b / h` (the
    /// rank-one coupling); for the implicit sphere one row per face in contact. Pair with
    /// [`Probe::finish_solved`]. Allocation-free.
    pub fn coupling(&mut self, dt_s: f64) -> Option<ContactCoupling<'_>> {
        if !self.state.in_contact {
            return None;
        }
        if !self.implicit_sphere() {
            let n = self.state.normal;
            let weights = &self.patch_weights;
            let c = self.coupling_gamma(dt_s) / (dt_s * dt_s);
            self.rows
                .set_single_row(&self.patch_nodes, |i| n * weights[i], c);
        }
        Some(self.rows.view())
    }

    fn implicit_sphere(&self) -> bool {
        self.implicit_dt_s > 0.0 && self.params.contact == ContactModel::Sphere
    }

    /// The device force from the coupling's end-of-step normal velocity `utv = U^T v'` (m/s):
    /// `phi n + friction`, `phi = phi0 + (k dt + b) utv` clamped to `[0, max_force_n]`; feeds
    /// the contact stiffness estimate.
    fn set_device_force(&mut self, dt_s: f64, utv: f64) {
        let (n, p) = (self.state.normal, self.params);
        let phi = (self.phi0_n
            + (self.coupling_k_n_per_m * dt_s + p.coupling_damping_n_s_per_m) * utv)
            .clamp(0.0, p.max_force_n);
        self.state.force_on_device_n = n * phi + self.friction_n;
        self.stiffness.observe(
            dt_s,
            self.device_m.dot(n),
            phi,
            p.coupling_stiffness_n_per_m,
        );
    }

    /// Completes a step whose solve already contained the probe's term ([`Probe::coupling`]):
    /// the end-of-step velocities `v` (m/s) give the device force `phi n`,
    /// `phi = phi0 + (k dt + b) U^T v'`, clamped to `[0, max_force_n]`, the same force whose
    /// unclamped reaction the body received (the implicit sphere: the faces' multipliers
    /// `lambda = lambda0 - h C A v'` and the device force `-N lambda`). Allocation-free.
    pub fn finish_solved(&mut self, dt_s: f64, v: &[DVec3]) {
        if !self.state.in_contact {
            return;
        }
        if self.implicit_sphere() {
            self.finish_implicit_sphere(dt_s, v);
            return;
        }
        let n = self.state.normal;
        let utv: f64 = self
            .patch_nodes
            .iter()
            .zip(&self.patch_weights)
            .map(|(&i, &w)| w * n.dot(v[i as usize]))
            .sum();
        self.set_device_force(dt_s, utv);
    }

    /// The kernel-weighted plane of the current patch: its centre `sum w_i x_i` (m) and unit
    /// normal (the weighted vertex normals); `None` for an empty patch or a vanishing normal.
    fn patch_plane(&self, x: &[DVec3]) -> Option<(DVec3, DVec3)> {
        if self.patch_nodes.is_empty() {
            return None;
        }
        let mut centre = DVec3::ZERO;
        let mut normal_sum = DVec3::ZERO;
        for (&i, &w) in self.patch_nodes.iter().zip(&self.patch_weights) {
            centre += x[i as usize] * w;
            normal_sum += self.surface.vertex_normal(i, x) * w;
        }
        normal_sum.try_normalize().map(|n| (centre, n))
    }

    /// Collects the contact patch around the device point `q` (see
    /// [`ContactSurface::gather_kernel_patch`], radius `PATCH_RADIUS_FACTOR * r`).
    fn gather_patch(&mut self, x: &[DVec3], q: DVec3, seed: u32) {
        self.surface.gather_kernel_patch(
            x,
            q,
            seed,
            PATCH_RADIUS_FACTOR * self.params.radius_m,
            &mut self.patch_nodes,
            &mut self.patch_weights,
        );
    }

    /// Nodes and weights (sum 1) over which a force injected at the probe acts (empty out of
    /// contact): the kernel patch of radius `2 r` around the contact point `proxy - r n`
    /// (for the patch model, the contact patch itself), a footprint that does not
    /// shrink with the depth. An injected force may be ten times the contact force, and on the
    /// few faces a shallow sphere contact touches a load of that size inverts StVK elements
    /// (the condensed LV's 10-fold impulse diverged there). Allocation-free.
    pub fn load_patch(&mut self, x: &[DVec3]) -> (&[u32], &[f64]) {
        if !self.state.in_contact {
            return (&[], &[]);
        }
        if self.params.contact == ContactModel::Sphere {
            let r = self.params.radius_m;
            let point = self.state.proxy_m - self.state.normal * r;
            self.surface.gather_kernel_patch(
                x,
                point,
                self.state.triangle,
                PATCH_RADIUS_FACTOR * r,
                &mut self.load_nodes,
                &mut self.load_weights,
            );
            return (&self.load_nodes, &self.load_weights);
        }
        (&self.patch_nodes, &self.patch_weights)
    }

    /// Nodes and weights (sum 1) of the current contact patch (empty out of contact).
    pub fn patch(&self) -> (&[u32], &[f64]) {
        if self.state.in_contact {
            (&self.patch_nodes, &self.patch_weights)
        } else {
            (&[], &[])
        }
    }

    /// Adds the explicit part of the coupling reaction, `-phi0 n` and minus the friction force,
    /// to the nodal forces `f` (N) over the contact nodes with their weights (the implicit part
    /// follows in [`Probe::finish_implicit`]).
    /// Does nothing out of contact.
    pub fn add_reaction(&self, f: &mut [DVec3]) {
        if !self.state.in_contact {
            return;
        }
        if self.implicit_sphere() {
            self.add_implicit_sphere_reaction(f);
            return;
        }
        let fr = self.state.normal * self.phi0_n + self.friction_n;
        for (&i, &w) in self.patch_nodes.iter().zip(&self.patch_weights) {
            f[i as usize] -= fr * w;
        }
    }

    /// Local contact stiffness felt at the device, 3x3 row-major N/m: `k_c n n^T` in contact,
    /// zero out of contact. `k_c` is the slope of the contact force against the device's
    /// travel along `n` over the last [`STIFFNESS_WINDOW_S`] of contact (least squares with
    /// exponential forgetting, `StiffnessEstimate`): the virtual coupling `k` in series with
    /// the tissue under the probe, `k_c = k K / (k + K)`, as the model responds. Until the device
    /// has travelled enough to measure it (just after first touch, or held still since), `k_c`
    /// is the last measured value, or unknown and then `k`, the stiffest the device can feel.
    pub fn contact_stiffness(&self) -> [f64; 9] {
        if !self.state.in_contact {
            return [0.0; 9];
        }
        let n = self.state.normal;
        let k_c = self
            .stiffness
            .slope_n_per_m
            .unwrap_or(self.params.coupling_stiffness_n_per_m);
        let a = n.to_array();
        let mut out = [0.0; 9];
        for r in 0..3 {
            for c in 0..3 {
                out[r * 3 + c] = k_c * a[r] * a[c];
            }
        }
        out
    }
}

/// The height (m) of the rest surface above the rest plane of a kernel patch at its centre:
/// the plane through the weighted centroid `c0 = sum w_i X_i` of the patch's nodes lies below a
/// convex surface by the curvature's sag, about 0.07 mm on the default LV, so a patch contact
/// measured from it starts that much late. With the patch's mean rest curvature tensor
/// `H = sum w_i H_i` ([`ContactSurface::curvature_tensors`]), the surface `z = d^T H d / 2`
/// around the centre puts the plane at `sum w_i z_i`, so the sag is
/// `-1/2 sum w_i (X_i - c0)^T H (X_i - c0)` (positive on a convex surface), bounded by `r / 2`
/// in magnitude. `rest` and `curvature` are per node (m, 1/m); zero without them.
/// Allocation-free.
pub fn patch_sag(
    nodes: &[u32],
    weights: &[f64],
    rest: &[DVec3],
    curvature: &[DMat3],
    radius_m: f64,
) -> f64 {
    if rest.is_empty() || curvature.is_empty() {
        return 0.0;
    }
    let (mut c0, mut h) = (DVec3::ZERO, DMat3::ZERO);
    for (&i, &w) in nodes.iter().zip(weights) {
        c0 += rest[i as usize] * w;
        h += curvature[i as usize] * w;
    }
    let mut plane = 0.0;
    for (&i, &w) in nodes.iter().zip(weights) {
        let d = rest[i as usize] - c0;
        plane += w * 0.5 * d.dot(h * d);
    }
    (-plane).clamp(-0.5 * radius_m, 0.5 * radius_m)
}

/// `K = 4/3 E* R^(1/2)` (N/m^(3/2)) of the Hertz contact of a sphere of radius `radius_m` on a
/// half-space of effective modulus `modulus_pa`: `F = K delta^(3/2)` (Johnson, Contact
/// Mechanics, 1985, eq. 4.23).
pub fn hertz_stiffness(modulus_pa: f64, radius_m: f64) -> f64 {
    4.0 / 3.0 * modulus_pa * radius_m.sqrt()
}

/// The Hertz indentation `delta` (m) of a spring `F = K delta^(3/2)` in series with a linear
/// spring `k` (N/m) stretched together by `depth_m`: the root of `k (depth - delta) =
/// K delta^(3/2)` in `[0, depth]`, by Newton on `s = delta^(1/2)` (`K s^3 + k s^2 - k depth`
/// is convex and increasing for `s > 0`, so Newton from an upper bound decreases monotonically
/// onto the root). `K <= 0` (an unknown modulus) gives `depth`: no force. Allocation-free.
pub fn hertz_series_indentation(depth_m: f64, k_n_per_m: f64, hertz_k: f64) -> f64 {
    if !(depth_m > 0.0) {
        return 0.0;
    }
    if !(hertz_k > 0.0) {
        return depth_m;
    }
    let target = k_n_per_m * depth_m;
    let mut s = depth_m.sqrt().min((target / hertz_k).cbrt());
    for _ in 0..60 {
        let g = hertz_k * s * s * s + k_n_per_m * s * s - target;
        let dg = 3.0 * hertz_k * s * s + 2.0 * k_n_per_m * s;
        if !(dg > 0.0) {
            break;
        }
        let step = g / dg;
        s -= step;
        if step.abs() <= 1e-14 * s.abs() {
            break;
        }
    }
    (s * s).clamp(0.0, depth_m)
}

/// Time over which [`Probe::contact_stiffness`] fits the force against the device's travel, s.
pub const STIFFNESS_WINDOW_S: f64 = 0.05;

/// Least spread of the device's positions in the window (standard deviation) for a new
/// stiffness measurement, m.
const STIFFNESS_MIN_TRAVEL_M: f64 = 1e-6;

/// Least-squares slope of the device force along the normal `phi` against the device's
/// position along the normal `s` over the last [`STIFFNESS_WINDOW_S`] (samples weighted by
/// their duration with exponential forgetting): `k_c = -cov(s, phi) / var(s)` (the force grows
/// as the device moves into the tissue), clamped to `[0, k]`. Positions are taken relative to
/// the first contact's, so the sums keep their precision. A fit of levels over tens of
/// milliseconds sees the quasi-static response; increments from one tick to the next would
/// see the coupling spring alone (the tissue has not moved yet).
#[derive(Debug, Clone, Copy, Default)]
struct StiffnessEstimate {
    origin_m: Option<f64>,
    /// Forgetting-weighted sums: weight (s), `s`, `phi`, `s^2`, `s phi`.
    w: f64,
    s: f64,
    phi: f64,
    ss: f64,
    sphi: f64,
    slope_n_per_m: Option<f64>,
}

impl StiffnessEstimate {
    fn observe(&mut self, dt_s: f64, s_m: f64, phi_n: f64, k_max: f64) {
        let origin = *self.origin_m.get_or_insert(s_m);
        let s = s_m - origin;
        let forget = (-dt_s / STIFFNESS_WINDOW_S).exp();
        self.w = forget * self.w + dt_s;
        self.s = forget * self.s + dt_s * s;
        self.phi = forget * self.phi + dt_s * phi_n;
        self.ss = forget * self.ss + dt_s * s * s;
        self.sphi = forget * self.sphi + dt_s * s * phi_n;
        let (mean_s, mean_phi) = (self.s / self.w, self.phi / self.w);
        let var = self.ss / self.w - mean_s * mean_s;
        if var > STIFFNESS_MIN_TRAVEL_M * STIFFNESS_MIN_TRAVEL_M {
            let cov = self.sphi / self.w - mean_s * mean_phi;
            self.slope_n_per_m = Some((-cov / var).clamp(0.0, k_max));
        }
    }
}
