//! Loads: what pushes a body besides the probe's reaction. Scene loads (gravity, dead and
//! follower surface pressure, permanent point forces; section `[loads]`), point loads added at
//! run time (`ApplyForce`), and the probe load (a disturbance at the probe's contact patch).
//!
//! [`BodyLoads`] holds them for a dynamic body, sized at construction so that adding them to
//! the nodal forces each sub-step allocates nothing: the state-independent part (gravity, dead
//! pressure, point forces) is summed once into a constant nodal force; follower pressure is
//! recomputed from the current positions each sub-step. [`static_external_forces`] gives the
//! same forces for static solves.
//!
//! Owns: load data and their nodal forces. May use: [`crate::contact`] (kernel patches place
//! point loads as a probe touching there would spread its reaction), [`crate::element`]
//! (masses), [`crate::mesh`]. Used by the bodies, [`crate::scene`] (builds [`SceneLoads`]) and
//! static solves.

use glam::DVec3;

use crate::ModelError;
use crate::contact::probe::MAX_DEVICE_DISTANCE_M;
use crate::contact::{ContactSurface, MAX_PATCH_NODES, PATCH_RADIUS_FACTOR};
use crate::element::lumped_masses;
use crate::mesh::TetMesh;

/// Largest number of point loads active at once (the table is preallocated).
pub const MAX_POINT_LOADS: usize = 32;
/// Largest accepted point-load magnitude, N. Anything larger is rejected as absurd for a
/// haptic scene (the strongest device we drive renders 100 N).
pub const MAX_POINT_FORCE_N: f64 = 100.0;
/// Largest accepted point-load duration, s.
pub const MAX_POINT_LOAD_DURATION_S: f64 = 3600.0;

/// External loads of a scene (section `[loads]`), SI units; the default is no load. Applied by
/// every integrator in every sub-step ([`BodyLoads`]) and, for static solves, by
/// [`static_external_forces`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SceneLoads {
    /// Gravitational acceleration, m/s^2 (nodal forces `m_i g`).
    pub gravity_m_per_s2: DVec3,
    /// Uniform pressures on tagged surfaces.
    pub pressure: Vec<PressureLoad>,
    /// Permanent point forces.
    pub point: Vec<PointForce>,
}

impl SceneLoads {
    /// Whether the scene has no load at all.
    pub fn is_empty(&self) -> bool {
        self.gravity_m_per_s2 == DVec3::ZERO && self.pressure.is_empty() && self.point.is_empty()
    }
}

/// A uniform pressure on tagged surfaces: each triangle carries `-p A n` (n its outward
/// normal), a third per vertex, so a positive pressure pushes the surface into the body.
#[derive(Debug, Clone, PartialEq)]
pub struct PressureLoad {
    /// Surface names the load acts on.
    pub surfaces: Vec<String>,
    /// Their triangles, outward oriented, distinct.
    pub triangles: Vec<[u32; 3]>,
    /// Pressure, Pa.
    pub pressure_pa: f64,
    /// Follower load (`true`: area and normal from the current geometry, recomputed every
    /// sub-step) or dead load (`false`: from the rest geometry).
    pub follower: bool,
    /// Whether `triangles` are the four-way splits of the 6-node faces of a quadratic mesh, in
    /// groups of four ([`crate::mesh::split_triangle`] order): the forces are then the
    /// consistent nodal forces of the curved quadratic faces ([`add_pressure_load`]).
    pub quadratic: bool,
}

/// A permanent (dead) point force on the surface point closest, at rest, to `point_m`, spread
/// over that boundary triangle by barycentric weights.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointForce {
    /// Requested point, m.
    pub point_m: DVec3,
    /// Force, N.
    pub force_n: DVec3,
    /// The boundary triangle (node indices) holding the closest point.
    pub nodes: [u32; 3],
    /// Barycentric weights of the closest point on it (sum 1).
    pub bary: [f64; 3],
}

/// Nodal forces (N) of a uniform pressure `pressure_pa` (Pa) on `triangles` at positions `x`:
/// each triangle carries `-p A n` (n its outward unit normal, A its area), one third per vertex.
/// A positive pressure pushes the surface inwards along its outward normal (for the inner
/// surface of a hollow body, whose outward normal faces the cavity, it inflates the body).
/// Evaluated at rest positions this is a dead load; re-evaluated each step, a follower load.
pub fn add_pressure_forces(triangles: &[[u32; 3]], x: &[DVec3], pressure_pa: f64, f: &mut [DVec3]) {
    for t in triangles {
        let [a, b, c] = t.map(|i| x[i as usize]);
        // (b-a) x (c-a) = 2 A n
        let fa = (b - a).cross(c - a) * (-pressure_pa / 6.0);
        for &i in t {
            f[i as usize] += fa;
        }
    }
}

/// The 6-node face `[a, b, c, m_ab, m_bc, m_ca]` of a group of four triangles made by
/// [`crate::mesh::split_triangle`], or `None` when `group` is not such a split.
pub fn quadratic_face(group: &[[u32; 3]]) -> Option<[u32; 6]> {
    let [t0, t1, t2, t3] = group else {
        return None;
    };
    let face = [t0[0], t1[1], t2[2], t0[1], t1[2], t0[2]];
    let [a, b, c, ab, bc, ca] = face;
    (crate::mesh::split_triangle([a, b, c], ab, bc, ca) == [*t0, *t1, *t2, *t3]).then_some(face)
}

/// Whether `triangles` are four-way splits of 6-node faces throughout (see
/// [`quadratic_face`]).
pub fn is_quadratic_split(triangles: &[[u32; 3]]) -> bool {
    triangles.len().is_multiple_of(4) && triangles.chunks(4).all(|g| quadratic_face(g).is_some())
}

/// One point of Dunavant's degree-4 rule on the reference triangle `{xi, eta >= 0, xi + eta
/// <= 1}` with the values and derivatives of the 6-node shape functions there (node order
/// `a, b, c, m_ab, m_bc, m_ca`; `xi`, `eta` the barycentrics of `b`, `c`).
#[derive(Clone, Copy)]
pub(crate) struct FacePoint {
    /// Weight (the six sum to 1/2, the reference area).
    pub w: f64,
    pub n: [f64; 6],
    pub dxi: [f64; 6],
    pub deta: [f64; 6],
}

/// The six points of Dunavant's degree-4 rule (D. A. Dunavant, Int. J. Numer. Meth. Eng. 21,
/// 1985, table of degree 4): exact for the integrand `N_k (x_xi x x_eta)` (degree 4) of a
/// 6-node face.
pub(crate) fn face_points() -> [FacePoint; 6] {
    const A1: f64 = 0.445_948_490_915_965;
    const B1: f64 = 0.108_103_018_168_070;
    const W1: f64 = 0.223_381_589_678_011;
    const A2: f64 = 0.091_576_213_509_771;
    const B2: f64 = 0.816_847_572_980_459;
    const W2: f64 = 0.109_951_743_655_322;
    let bary = [
        (B1, A1, A1, W1),
        (A1, B1, A1, W1),
        (A1, A1, B1, W1),
        (B2, A2, A2, W2),
        (A2, B2, A2, W2),
        (A2, A2, B2, W2),
    ];
    bary.map(|(l1, l2, l3, w)| FacePoint {
        w: 0.5 * w,
        n: [
            l1 * (2.0 * l1 - 1.0),
            l2 * (2.0 * l2 - 1.0),
            l3 * (2.0 * l3 - 1.0),
            4.0 * l1 * l2,
            4.0 * l2 * l3,
            4.0 * l3 * l1,
        ],
        dxi: [
            1.0 - 4.0 * l1,
            4.0 * l2 - 1.0,
            0.0,
            4.0 * (l1 - l2),
            4.0 * l3,
            -4.0 * l3,
        ],
        deta: [
            1.0 - 4.0 * l1,
            0.0,
            4.0 * l3 - 1.0,
            -4.0 * l2,
            4.0 * l2,
            4.0 * (l1 - l3),
        ],
    })
}

/// The tangents `x_xi`, `x_eta` of face `face` at point `q` for positions `x`.
#[inline]
pub(crate) fn face_tangents(q: &FacePoint, face: &[u32; 6], x: &[DVec3]) -> (DVec3, DVec3) {
    let (mut t_xi, mut t_eta) = (DVec3::ZERO, DVec3::ZERO);
    for (k, &i) in face.iter().enumerate() {
        t_xi += x[i as usize] * q.dxi[k];
        t_eta += x[i as usize] * q.deta[k];
    }
    (t_xi, t_eta)
}

/// Nodal forces (N) of a uniform pressure `pressure_pa` (Pa) on the curved 6-node faces whose
/// four-way splits are `triangles` ([`quadratic_face`]), at positions `x`: the consistent
/// forces `f_k = -p int N_k n dA` (`n dA = x_xi x x_eta dxi deta`), integrated exactly by
/// Dunavant's degree-4 rule. On a flat face they are zero at the corners and `-p A n / 3` at
/// each mid-edge node (lumping over the four flat sub-triangles would give the corners 1/12
/// and the mid-edge nodes 1/4 of the load, which biases the surface displacement of
/// quadratic elements by about 2 %; measured in `tests/incompressible.rs`).
///
/// # Panics
/// If `triangles` is not a four-way split ([`is_quadratic_split`]).
pub fn add_quadratic_pressure_forces(
    triangles: &[[u32; 3]],
    x: &[DVec3],
    pressure_pa: f64,
    f: &mut [DVec3],
) {
    let points = face_points();
    for group in triangles.chunks(4) {
        let face = quadratic_face(group).expect("four-way split of a 6-node face");
        add_face_forces(&points, &face, x, pressure_pa, f);
    }
}

/// [`add_quadratic_pressure_forces`] on 6-node faces already gathered (`[a, b, c, m_ab, m_bc,
/// m_ca]`, see [`quadratic_face`]): what a dynamic body calls every sub-step.
pub fn add_face_pressure_forces(
    faces: &[[u32; 6]],
    x: &[DVec3],
    pressure_pa: f64,
    f: &mut [DVec3],
) {
    let points = face_points();
    for face in faces {
        add_face_forces(&points, face, x, pressure_pa, f);
    }
}

/// The consistent pressure forces of one 6-node face.
#[inline]
fn add_face_forces(
    points: &[FacePoint; 6],
    face: &[u32; 6],
    x: &[DVec3],
    pressure_pa: f64,
    f: &mut [DVec3],
) {
    for q in points {
        let (t_xi, t_eta) = face_tangents(q, face, x);
        let load = t_xi.cross(t_eta) * (-pressure_pa * q.w);
        for (k, &i) in face.iter().enumerate() {
            f[i as usize] += load * q.n[k];
        }
    }
}

/// Adds the nodal forces of pressure `pressure_pa` (Pa) on `triangles` at positions `x` to
/// `f`: over the 6-node faces when `quadratic` ([`add_quadratic_pressure_forces`]), else
/// per flat triangle ([`add_pressure_forces`]).
pub fn add_pressure_load(
    triangles: &[[u32; 3]],
    quadratic: bool,
    x: &[DVec3],
    pressure_pa: f64,
    f: &mut [DVec3],
) {
    if quadratic {
        add_quadratic_pressure_forces(triangles, x, pressure_pa, f);
    } else {
        add_pressure_forces(triangles, x, pressure_pa, f);
    }
}

/// Checks a point load's numbers (see [`BodyLoads::add_point_load`]).
///
/// # Errors
/// [`ModelError::InvalidInput`] saying which value is wrong.
pub fn validate_point_load(
    point_m: DVec3,
    force_n: DVec3,
    duration_s: f64,
) -> Result<(), ModelError> {
    if !point_m.is_finite() {
        return Err(ModelError::InvalidInput("point_m is not finite".into()));
    }
    if !force_n.is_finite() {
        return Err(ModelError::InvalidInput("force_n is not finite".into()));
    }
    if !duration_s.is_finite() || duration_s <= 0.0 || duration_s > MAX_POINT_LOAD_DURATION_S {
        return Err(ModelError::InvalidInput(format!(
            "duration_s = {duration_s} must be in (0, {MAX_POINT_LOAD_DURATION_S}] s"
        )));
    }
    if force_n.length() > MAX_POINT_FORCE_N {
        return Err(ModelError::InvalidInput(format!(
            "|force_n| = {:.3} N exceeds the {MAX_POINT_FORCE_N} N limit",
            force_n.length()
        )));
    }
    if point_m.abs().max_element() > MAX_DEVICE_DISTANCE_M {
        return Err(ModelError::InvalidInput(format!(
            "point_m {point_m} is absurdly far from the scene"
        )));
    }
    Ok(())
}

/// The state-independent part of `loads` on nodes with rest positions `rest` and lumped masses
/// `mass_kg`: gravity, dead pressure (rest geometry) and point forces. Empty when there is none
/// of them.
fn constant_external_forces(loads: &SceneLoads, rest: &[DVec3], mass_kg: &[f64]) -> Vec<DVec3> {
    let l = loads;
    if l.gravity_m_per_s2 == DVec3::ZERO
        && l.point.is_empty()
        && l.pressure.iter().all(|p| p.follower)
    {
        return Vec::new();
    }
    let mut f: Vec<DVec3> = mass_kg.iter().map(|m| l.gravity_m_per_s2 * *m).collect();
    for p in l.pressure.iter().filter(|p| !p.follower) {
        add_pressure_load(&p.triangles, p.quadratic, rest, p.pressure_pa, &mut f);
    }
    for p in &l.point {
        for k in 0..3 {
            f[p.nodes[k] as usize] += p.force_n * p.bary[k];
        }
    }
    f
}

/// External nodal forces (N, one per node of `mesh`) of `loads` at positions `x` (m), for
/// static solves: gravity on the lumped masses (density `density_kg_per_m3`), dead pressure on
/// the rest geometry, follower pressure on `x`, point forces. The same forces [`BodyLoads`]
/// applies in every sub-step.
///
/// # Panics
/// If `x` is shorter than the mesh's node count.
pub fn static_external_forces(
    loads: &SceneLoads,
    mesh: &TetMesh,
    density_kg_per_m3: f64,
    x: &[DVec3],
) -> Vec<DVec3> {
    let mut f = static_dead_forces(loads, mesh, density_kg_per_m3);
    for p in loads.pressure.iter().filter(|p| p.follower) {
        add_pressure_load(&p.triangles, p.quadratic, x, p.pressure_pa, &mut f);
    }
    f
}

/// The part of [`static_external_forces`] that does not move with the body (N, one per node of
/// `mesh`): gravity, dead pressure, point forces; no follower pressure (a static solve adds
/// that as a term with its load stiffness, `statics::FollowerPressure`).
pub fn static_dead_forces(
    loads: &SceneLoads,
    mesh: &TetMesh,
    density_kg_per_m3: f64,
) -> Vec<DVec3> {
    let mass = lumped_masses(mesh, density_kg_per_m3);
    let f = constant_external_forces(loads, &mesh.nodes, &mass);
    if f.is_empty() {
        vec![DVec3::ZERO; mesh.nodes.len()]
    } else {
        f
    }
}

/// A point load: a force on a surface point, spread over the surface nodes around it
/// (`nodes[..len]`, `weights[..len]`, sum 1), see [`BodyLoads::add_point_load`].
#[derive(Debug, Clone, Copy, PartialEq)]
struct PointLoad {
    nodes: [u32; MAX_PATCH_NODES],
    weights: [f64; MAX_PATCH_NODES],
    len: usize,
    force_n: DVec3,
    remaining_s: f64,
}

/// A follower pressure of a dynamic body.
#[derive(Debug, Clone)]
struct FollowerLoad {
    triangles: Vec<[u32; 3]>,
    /// The 6-node faces of `triangles` on a quadratic mesh (empty on a linear one), gathered
    /// once here rather than every sub-step.
    faces: Vec<[u32; 6]>,
    pressure_pa: f64,
}

/// The loads of a dynamic body (module documentation), sized at construction.
#[derive(Debug, Clone)]
pub struct BodyLoads {
    /// Scene loads that do not depend on the state (gravity, dead pressure, point forces), N
    /// per node; empty when there are none.
    constant: Vec<DVec3>,
    /// Follower pressures.
    follower: Vec<FollowerLoad>,
    /// Surface on which point loads are placed.
    surface: ContactSurface,
    /// Active point loads (capacity [`MAX_POINT_LOADS`]).
    points: Vec<PointLoad>,
    /// Scratch for the patch of a new point load (capacity [`MAX_PATCH_NODES`]).
    patch_nodes: Vec<u32>,
    patch_weights: Vec<f64>,
    /// Extra force on the probe's contact patch (N) and its remaining time (s).
    probe_n: DVec3,
    probe_remaining_s: f64,
}

impl BodyLoads {
    /// The loads of a body with rest positions `rest` (m) and lumped masses `mass_kg`: the
    /// scene's `loads`, and point loads placed on `load_surface` (triangles over the body's
    /// nodes; for example the free boundary).
    pub fn new(
        loads: &SceneLoads,
        rest: &[DVec3],
        mass_kg: &[f64],
        load_surface: Vec<[u32; 3]>,
    ) -> Self {
        Self {
            constant: constant_external_forces(loads, rest, mass_kg),
            follower: loads
                .pressure
                .iter()
                .filter(|l| l.follower)
                .map(|l| {
                    let faces = if l.quadratic {
                        l.triangles
                            .chunks(4)
                            .map(|g| quadratic_face(g).expect("four-way split of a 6-node face"))
                            .collect()
                    } else {
                        Vec::new()
                    };
                    FollowerLoad {
                        triangles: l.triangles.clone(),
                        faces,
                        pressure_pa: l.pressure_pa,
                    }
                })
                .collect(),
            surface: ContactSurface::new(load_surface, rest.len()),
            points: Vec::with_capacity(MAX_POINT_LOADS),
            patch_nodes: Vec::with_capacity(MAX_PATCH_NODES),
            patch_weights: Vec::with_capacity(MAX_PATCH_NODES),
            probe_n: DVec3::ZERO,
            probe_remaining_s: 0.0,
        }
    }

    /// Whether a scene load acts on a node for which `inside` is false (the condensed model
    /// refuses loads on its condensed elements).
    pub fn acts_outside(&self, inside: impl Fn(u32) -> bool) -> bool {
        let constant = self
            .constant
            .iter()
            .enumerate()
            .any(|(i, f)| *f != DVec3::ZERO && !inside(i as u32));
        let follower = self
            .follower
            .iter()
            .any(|l| !l.triangles.iter().flatten().all(|&i| inside(i)));
        constant || follower
    }

    /// Adds the scene loads (follower pressure at positions `x`, m) and the active point loads
    /// to the nodal forces `f` (N). Allocation-free.
    pub fn add_to(&self, x: &[DVec3], f: &mut [DVec3]) {
        if !self.constant.is_empty() {
            for (fi, l) in f.iter_mut().zip(&self.constant) {
                *fi += *l;
            }
        }
        for l in &self.follower {
            if l.faces.is_empty() {
                add_pressure_forces(&l.triangles, x, l.pressure_pa, f);
            } else {
                add_face_pressure_forces(&l.faces, x, l.pressure_pa, f);
            }
        }
        for l in &self.points {
            for (&i, &w) in l.nodes[..l.len].iter().zip(&l.weights[..l.len]) {
                f[i as usize] += l.force_n * w;
            }
        }
    }

    /// Adds the active probe load ([`BodyLoads::set_probe_load`]) over the probe's contact
    /// patch (`nodes`, `weights`, sum 1) to `f` (N). Allocation-free.
    pub fn add_probe_load_to(&self, (nodes, weights): (&[u32], &[f64]), f: &mut [DVec3]) {
        if self.probe_remaining_s > 0.0 {
            for (&i, &w) in nodes.iter().zip(weights) {
                f[i as usize] += self.probe_n * w;
            }
        }
    }

    /// Applies `force_n` (N) at the surface point closest to `point_m` (m) on positions `x` for
    /// `duration_s` of simulated time, spread as a probe of radius `r = probe_radius_m`
    /// touching there spreads its reaction: over the surface nodes within `2 r` of the point
    /// `r` outside the surface (the probe's centre) with the contact kernel weights
    /// `(1 - d^2 / (2r)^2)^2` (sum 1, see [`ContactSurface::gather_kernel_patch`]; a disc of
    /// radius `sqrt(3) r` on the surface), fixed to those nodes when the load is added. When
    /// no node lies that close (a triangle much larger than the probe) it falls back to the
    /// closest triangle's barycentric weights.
    ///
    /// A force on the three nodes of one triangle is a point load in the continuum sense: its
    /// local displacement grows without bound as the mesh is refined; spread over the probe's
    /// footprint it converges with the mesh. It moves the surface more than a probe held
    /// against it with the same force, because the probe's patch widens as the surface wraps
    /// around the sphere, while this one stays on the nodes it was given.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] (nothing changed) for the values [`validate_point_load`]
    /// rejects; [`ModelError::LoadTableFull`] when [`MAX_POINT_LOADS`] loads are already
    /// active; [`ModelError::InvalidDevice`] when the body has no free surface. Allocation-free,
    /// so the servo tick may call it.
    pub fn add_point_load(
        &mut self,
        x: &[DVec3],
        probe_radius_m: f64,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
    ) -> Result<(), ModelError> {
        validate_point_load(point_m, force_n, duration_s)?;
        if self.points.len() >= MAX_POINT_LOADS {
            return Err(ModelError::LoadTableFull(MAX_POINT_LOADS));
        }
        let sp = self
            .surface
            .closest_global(x, point_m)
            .ok_or(ModelError::InvalidDevice(
                "the body has no free surface to load",
            ))?;
        let mut load = PointLoad {
            nodes: [0; MAX_PATCH_NODES],
            weights: [0.0; MAX_PATCH_NODES],
            len: 0,
            force_n,
            remaining_s: duration_s,
        };
        // The kernel centre sits one probe radius outside the surface, where a probe touching
        // there has its centre, so the weights are the probe's.
        let r = probe_radius_m;
        let centre = sp.point + self.surface.normal(sp.triangle, x) * r;
        self.surface.gather_kernel_patch(
            x,
            centre,
            sp.triangle,
            PATCH_RADIUS_FACTOR * r,
            &mut self.patch_nodes,
            &mut self.patch_weights,
        );
        if self.patch_nodes.is_empty() {
            let tri = self.surface.triangles[sp.triangle as usize];
            load.nodes[..3].copy_from_slice(&tri);
            load.weights[..3].copy_from_slice(&sp.bary);
            load.len = 3;
        } else {
            load.len = self.patch_nodes.len();
            load.nodes[..load.len].copy_from_slice(&self.patch_nodes);
            load.weights[..load.len].copy_from_slice(&self.patch_weights);
        }
        self.points.push(load);
        Ok(())
    }

    /// Sets the probe load: `force_n` (N) on the probe's contact patch for `duration_s` of
    /// simulated time (replacing an active one); see [`BodyLoads::add_probe_load_to`].
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] (nothing changed) for the values [`validate_point_load`]
    /// rejects.
    pub fn set_probe_load(&mut self, force_n: DVec3, duration_s: f64) -> Result<(), ModelError> {
        validate_point_load(DVec3::ZERO, force_n, duration_s)?;
        self.probe_n = force_n;
        self.probe_remaining_s = duration_s;
        Ok(())
    }

    /// Advances the loads' clocks by `dt_s` (s): expired point loads are dropped, the probe
    /// load's time runs (in contact or not). Allocation-free.
    pub fn advance(&mut self, dt_s: f64) {
        self.points.retain_mut(|l| {
            l.remaining_s -= dt_s;
            l.remaining_s > 1e-12
        });
        if self.probe_remaining_s > 0.0 {
            self.probe_remaining_s -= dt_s;
            if self.probe_remaining_s <= 1e-12 {
                self.probe_remaining_s = 0.0;
            }
        }
    }

    /// Number of point loads still active.
    pub fn active_point_loads(&self) -> usize {
        self.points.len()
    }

    /// Remaining time of the probe load, s (0 when none).
    pub fn probe_load_remaining_s(&self) -> f64 {
        self.probe_remaining_s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat 6-node face of area 2 m^2 (corners (0,0,0), (2,0,0), (0,2,0)) in the split order of
    /// the meshes, its mid-edge nodes off their midpoints in the plane (a curved-sided face).
    fn flat_face(shift: f64) -> (Vec<[u32; 3]>, Vec<DVec3>) {
        let x = vec![
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(2.0, 0.0, 0.0),
            DVec3::new(0.0, 2.0, 0.0),
            DVec3::new(1.0 + shift, shift, 0.0),
            DVec3::new(1.0, 1.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        ];
        (crate::mesh::split_triangle([0, 1, 2], 3, 4, 5).to_vec(), x)
    }

    #[test]
    fn a_flat_quadratic_face_loads_its_mid_edge_nodes() {
        let (tris, x) = flat_face(0.0);
        assert!(is_quadratic_split(&tris) && !is_quadratic_split(&tris[..3]));
        assert_eq!(quadratic_face(&tris), Some([0, 1, 2, 3, 4, 5]));
        let p = 10.0;
        let mut f = vec![DVec3::ZERO; 6];
        add_quadratic_pressure_forces(&tris, &x, p, &mut f);
        // Consistent loads of a straight 6-node triangle: 0 at the corners, p A / 3 at each
        // mid-edge node, against the outward normal +z.
        for (k, fk) in f.iter().enumerate() {
            let expected = if k < 3 { 0.0 } else { -p * 2.0 / 3.0 };
            assert!(
                (fk.z - expected).abs() < 1e-12 && fk.x.abs() + fk.y.abs() < 1e-12,
                "{k}: {fk}"
            );
        }
        // The sub-triangle lumping puts 1/12 of the load on each corner.
        let mut lumped = vec![DVec3::ZERO; 6];
        add_pressure_forces(&tris, &x, p, &mut lumped);
        assert!((lumped[0].z + p * 2.0 / 12.0).abs() < 1e-12);
        // Moving a mid-edge node within the plane keeps the total force p A.
        let (tris, x) = flat_face(0.2);
        let mut f = vec![DVec3::ZERO; 6];
        add_pressure_load(&tris, true, &x, p, &mut f);
        let total: DVec3 = f.iter().sum();
        // Area of the curved-sided triangle: the straight one less the parabolic segment of
        // edge a-b, whose midpoint moved 0.2 into the face (a parabola over a chord c with
        // sagitta s encloses 2/3 c s with it: 2/3 * 2 * 0.2); the shift along the edge changes
        // no area.
        let area = 2.0 - 2.0 / 3.0 * 2.0 * 0.2;
        assert!((total.z + p * area).abs() < 1e-12, "{total}");
    }

    #[test]
    fn a_body_applies_the_static_forces_of_a_quadratic_follower_pressure() {
        let mesh = crate::mesh::generate::sphere_shell_quadratic(7e-3, 10e-3, 150);
        let triangles = mesh.surface("INNER").unwrap().triangles.clone();
        let loads = SceneLoads {
            pressure: vec![PressureLoad {
                surfaces: vec!["INNER".into()],
                quadratic: is_quadratic_split(&triangles),
                triangles,
                pressure_pa: 500.0,
                follower: true,
            }],
            ..SceneLoads::default()
        };
        assert!(loads.pressure[0].quadratic);
        let x: Vec<DVec3> = mesh
            .nodes
            .iter()
            .enumerate()
            .map(|(i, p)| *p * (1.0 + 0.01 * (i as f64).sin()))
            .collect();
        let mass = lumped_masses(&mesh, 1000.0);
        let body = BodyLoads::new(&loads, &mesh.nodes, &mass, mesh.boundary_triangles());
        let mut f = vec![DVec3::ZERO; x.len()];
        body.add_to(&x, &mut f);
        let expected = static_external_forces(&loads, &mesh, 1000.0, &x);
        let worst = f
            .iter()
            .zip(&expected)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        let largest = expected.iter().map(|v| v.length()).fold(0.0, f64::max);
        assert!(
            largest > 0.0 && worst <= 1e-12 * largest,
            "{worst:e} of {largest:e}"
        );
    }
}
