//! # haptic-model: soft-body physics for a 1 kHz haptic loop
//!
//! A pure, synchronous library (no async runtime, network or logging dependency) so that it can
//! be tested and benchmarked alone. Module map:
//!
//! - [`mesh`]: linear tetrahedral meshes with tagged boundary surfaces; [`gmsh`] reads Gmsh
//!   `.msh` 2.2 / 4.1 ASCII; [`mesher`] builds structured shells (ellipsoids, the idealized left
//!   ventricle, the Lamé sphere) and boxes in code.
//! - [`material`]: Lamé parameters, St. Venant-Kirchhoff and viscous stress (seed 000, eq. 4, 9-11).
//! - [`fem`]: precomputed shape-function gradients (eq. 13-21), nodal forces (eq. 22), lumped
//!   masses, tangent stiffness action, critical (Courant) time step.
//! - [`integrator`]: the seed's semi-implicit scheme (eq. 34), symplectic Euler and backward
//!   Euler; [`condensed`]: backward Euler on a contact-local active region with the rest of the
//!   body condensed statically.
//! - [`contact`]: the haptic probe: god-object proxy on the touchable surface joined to the device
//!   point by a virtual coupling.
//! - [`sim`]: [`sim::Simulation`], state + scratch + parameters, one `tick` per servo period.
//! - [`scene`]: scene files (TOML) and built-in scenes, validated into a [`scene::Scene`].
//! - [`statics`]: static equilibrium (Newton on the StVK tangent, sparse Cholesky) for references.
//! - [`export`]: node tables (CSV) and ParaView `.vtu` files of a configuration.
//!
//! Units are SI throughout (m, kg, s, N, Pa). Seeds are cited as "seed 000 eq. N":
//! Mero & Susin, *Deformable Hybrid Approach*, Eurographics 2006.

// `!(x > 0.0)` is how this crate rejects NaN together with out-of-range values; the lint's
// `partial_cmp` rewrite would hide exactly that intent.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod condensed;
pub mod contact;
pub mod error;
pub mod export;
pub mod fem;
pub mod gmsh;
pub mod integrator;
pub mod material;
pub mod mesh;
pub mod mesher;
pub mod scene;
pub mod sim;
mod simd;
pub mod statics;

pub use error::ModelError;
pub use glam::DVec3;
