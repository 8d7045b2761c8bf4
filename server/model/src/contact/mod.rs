//! Haptic probe contact: a sphere at the device position (the haptic interaction point, HIP)
//! touches the touchable surface through a god-object (proxy) joined to the device point by a
//! virtual coupling.
//!
//! Each update finds the closest triangle of the deformed touchable surface to the device point
//! (a local walk over neighbouring triangles while in contact, a full search otherwise), then
//! a smoothed local surface around the device: the touchable nodes within `2 r` of it with
//! kernel weights `w_i ∝ (1 - d_i^2 / (2r)^2)^2` (sum 1) define the plane through
//! `c = sum w_i x_i` with normal `n` the weighted vertex normals. Because the weights vanish at
//! the rim, `c` and `n` move continuously as the surface dimples under the probe (a plain
//! closest point jumps between the walls of the dimple and makes the force chatter). With the
//! signed distance `s = (device - c) . n`, the probe touches when `s < r`. The proxy is then
//! held outside the surface at `device + (r - s) n` (it cannot penetrate), and
//! the virtual coupling gives the device force
//! `F_dev = k (proxy - device) + b ((v_c - v_dev) . n) n`, clamped to `[0, max_force_n]` along
//! `n`, with the proxy and the surface velocity `v_c` taken at the end of the step (implicit:
//! [`Probe::finish_implicit`]). Its reaction
//! `-F_dev` acts on the body over the same patch with the same weights, so linear momentum is
//! conserved. Spreading over the patch
//! (a 2 mm sphere does not push on one triangle) also raises the effective mass the coupling
//! acts on, `m_eff = 1 / sum(w_i^2 / m_i)`, which keeps the explicit coupling stable: it needs
//! `dt^2 k / m_eff + 2 dt b / m_eff < 4` (a damped spring under symplectic Euler).
//! Frictionless: the proxy slides freely along the surface.
//!
//! Owns: [`surface`] (closest points, kernel patches), [`probe`] (the proxy and the coupling
//! force), [`coupling`] (the coupling's rank-one term for implicit solves). May use:
//! nothing else of the crate (positions come as slices); in particular nothing of
//! [`crate::integrate`]: the integrators use this module, not the other way round. The FEM
//! body ([`crate::sim`]) calls [`Probe::update`] every sub-step, adds the reaction, and lets its
//! stepper complete the coupling.

pub mod coupling;
pub mod probe;
pub mod sphere;
pub mod surface;

pub use coupling::RankOneCoupling;
pub use probe::{ContactModel, ContactState, Probe, ProbeParams};
pub use surface::{ContactSurface, SurfacePoint, closest_point_on_triangle};

/// Largest number of nodes in a contact patch.
pub const MAX_PATCH_NODES: usize = 256;

/// Largest number of surface triangles the sphere contact examines around the device.
pub const MAX_CONTACT_TRIANGLES: usize = 1024;

/// Radius of the contact patch around the device point, in probe radii.
pub const PATCH_RADIUS_FACTOR: f64 = 2.0;
