//! Haptic probe contact: a sphere at the device position (the haptic interaction point, HIP)
//! touches the touchable surface through a god-object (proxy) joined to the device point by a
//! virtual coupling. Four contact models ([`ContactModel`], scene key `probe.contact`):
//!
//! - **Sphere**: the probe is a
//!   rigid sphere of radius `r`. Each update casts it out of the deformed triangles near the
//!   device along the contact normal `n` ([`sphere::sphere_exit`], exact): the proxy
//!   `device + t n` is the nearest centre on that line where the sphere penetrates no
//!   triangle. The faces within a band `delta = max(t, r/100)` of the proxy sphere are in
//!   contact, weighted `A_T (1 - gap/delta)^2`; their weighted face normal is the next `n`, and
//!   their weights, spread to their nodes by the barycentric coordinates of each face's point
//!   closest to the proxy, carry the reaction. The contact area grows with the depth as a
//!   Hertz contact's does, and the weights vanish at the band's edge so the contact set changes
//!   continuously while sliding. On the default LV the servo's force equals an independent
//!   static solve with exact sphere contact (`crate::indent`) to 0.5 % (`tests/sim_lv.rs`);
//!   but the real-time meshes' facets (2-4 mm) are coarser than the contact (about 1 mm), so
//!   that equilibrium is 60-90 % stiffer than the mesh-converged one. Under backward Euler
//!   (whole body or condensed) the same sphere is implicit in the step
//!   ([`Probe::use_implicit_sphere`], module `probe::implicit`): the faces it touches are
//!   penalty springs with a smooth onset, in series with the coupling through the massless
//!   proxy, so the load distribution is solved with the body instead of taken from the
//!   previous configuration (which oscillated from tick to tick under 1 ms steps).
//! - **Patch**: a smoothed local surface around the device, the touchable nodes within `2 r`
//!   with kernel weights `w_i ∝ (1 - d_i^2 / (2r)^2)^2` (sum 1) define the plane through
//!   `c = sum w_i x_i` with normal `n` the weighted vertex normals; with
//!   `s = (device - c) . n`, the probe touches when `s < r` and the proxy is
//!   `device + (r - s) n`. It spreads the load over 4 mm whatever the depth (35-40 % stiffer
//!   than the sphere on the LV), but its distribution depends on the device position only, so
//!   every integrator carries it; the mass-spring surface's calibration and the seed's point
//!   contact are built on it too.
//! - **PatchHertz** (the default on FEM bodies until 2026-11-26): the patch, with the
//!   sphere's local Hertz indentation `delta` in series between the patch's surface and the
//!   proxy, a sub-grid
//!   model of what coarse facets cannot resolve: the mesh carries the body's structural
//!   response to the patch's smooth load, the Hertz spring `F = 4/3 E* r^(1/2) delta^(3/2)`
//!   ([`probe::hertz_stiffness`], `E* = E / (1 - nu^2)` of the material) the local one, and the
//!   coupling stretches by `(r - s) - delta` ([`probe::hertz_series_indentation`]). On the
//!   default LV it reads within the converged sphere reference's uncertainty for St.
//!   Venant-Kirchhoff (`docs/accuracy.md`, "Sub-grid Hertz contact").
//! - **PatchLocal** (the default on FEM bodies since 2026-11-26): PatchHertz with the
//!   material's own law of a rigid sphere on a half-space in place of Hertz's
//!   ([`local_law`]: the exact finite-strain axisymmetric solve of [`half_space`], tabulated
//!   once per material model and scaled by the scene's Young's modulus and probe radius), the
//!   patch's plane raised by its rest curvature's sag under the device
//!   ([`probe::patch_sag`]: the chord plane through the patch's nodes lies below a convex
//!   surface, so contact started late) and a fixed footprint, the nodes within
//!   [`LOCAL_PATCH_RADIUS_FACTOR`] `r` of the device's foot on that plane. On the default LV
//!   it reads within 3 % of the rigid-sphere reference from 0.25 to 1 mm (St.
//!   Venant-Kirchhoff) and within 5 % to 4 mm (stable neo-Hookean) (`docs/accuracy.md`, "The
//!   sphere's local law in the patch").
//!
//! All give the device force `F_dev = k (proxy - device) + b ((v_c - v_dev) . n) n`, clamped
//! to `[0, max_force_n]` along `n`, with the proxy and the surface velocity `v_c` taken at the
//! end of the step (implicit: [`Probe::finish_implicit`]). Its reaction `-F_dev` acts on the
//! body over the contact nodes with their weights (sum 1), so linear momentum is conserved;
//! the coupling's implicit term is the rank-one `gamma U U^T`, `U = (w_i n)` (with `k` in
//! series with the local law's tangent under PatchHertz and PatchLocal), which every
//! integrator solves (the explicit ones per node by Sherman-Morrison; backward Euler and the
//! condensed model take it, or the implicit sphere's one row per face, as the low-rank term
//! [`ContactCoupling`] `h^2 A^T C A`, inverted by Woodbury in the CG's preconditioner and on
//! the condensed factor). Frictionless by default: the proxy slides freely along the surface;
//! `friction_coefficient > 0` gives every model a god-object friction cone.
//!
//! Owns: [`surface`] (closest points, kernel patches, triangle neighbourhoods), [`sphere`]
//! (sphere casts against triangles), [`probe`] (the proxy and the coupling force; its
//! `implicit` module, the sphere under backward Euler), [`coupling`] (the probe's low-rank
//! term for implicit solves), [`local_law`] and [`half_space`] (the sphere's local law and its
//! calibration). May use: [`crate::material`] (the laws' stresses) and [`crate::linalg::ordering`]
//! (the calibration's sparse Cholesky), nothing else of the crate (positions come as slices);
//! in particular nothing of
//! [`crate::integrate`]: the integrators use this module, not the other way round. The FEM
//! body ([`crate::fem`]) calls [`Probe::update`] every sub-step, adds the reaction, and lets its
//! stepper complete the coupling.

pub mod coupling;
pub mod half_space;
pub mod local_law;
pub mod probe;
mod sample;
pub mod sphere;
pub mod surface;

pub use coupling::{ContactCoupling, CouplingMerge};
pub use local_law::LocalLaw;
pub use probe::{ContactModel, ContactState, Probe, ProbeParams};
pub use sample::SurfaceSampler;
pub use surface::{ContactSurface, SurfacePoint, closest_point_on_triangle};

/// Largest number of nodes in a contact patch.
pub const MAX_PATCH_NODES: usize = 256;

/// Largest number of surface triangles the sphere contact examines around the device.
pub const MAX_CONTACT_TRIANGLES: usize = 1024;

/// Radius of the contact patch around the device point, in probe radii.
pub const PATCH_RADIUS_FACTOR: f64 = 2.0;

/// Radius of the [`ContactModel::PatchLocal`] patch around the device's foot on the patch's
/// plane, in probe radii: `sqrt(3)`, the footprint of the two-radius patch around the device
/// when the sphere first touches (the nodes within `2 r` of a centre `r` above the surface lie
/// within `sqrt(3) r` of its foot), kept at every depth. (Around the device, the patch widens
/// to `2 r` as the device sinks towards the surface, which stiffened deep presses: +9.6 %
/// against the neo-Hookean reference at 4 mm on the default LV, +4.8 % with this footprint.)
pub const LOCAL_PATCH_RADIUS_FACTOR: f64 = 1.732_050_807_568_877_2;
