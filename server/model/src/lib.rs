//! # haptic-model: soft-body physics for a 1 kHz haptic loop
//!
//! A pure, synchronous library (no async runtime, network or logging dependency) so that it can
//! be tested and benchmarked alone. Module map, lowest layer first (a module uses only those
//! above it; `tests/module_layers.rs` checks that no import goes the other way):
//!
//! - `check` (crate-private): the field validators of scene sections (scene and the families'
//!   own sections).
//! - [`pool`]: the real-time worker pool a body may cut its tick into (issue 48): no allocation or
//!   lock in a job, results fixed by the thread count, one thread the one-core path.
//! - `simd` (crate-private): what the CPU can run and the lane types of the vectorised kernels.
//! - [`linalg`]: [`linalg::ordering`], fill-reducing orderings (METIS nested dissection) and a
//!   sparse Cholesky factor for the static solver and contact-local condensation;
//!   [`linalg::supernodal`], one right-hand side through a single-precision supernodal Cholesky
//!   factor, allocation-free (the condensed tick's solve).
//! - [`mesh`]: tetrahedral meshes, linear (4-node) or quadratic (10-node), with tagged boundary
//!   surfaces; [`mesh::gmsh`] reads Gmsh `.msh` 2.2 / 4.1 ASCII; [`mesh::generate`] builds
//!   structured shells (ellipsoids, the idealized left ventricle, the Lamé sphere) and boxes;
//!   [`mesh::export`] writes CSV node tables and ParaView `.vtu` files.
//! - [`material`]: Lamé parameters and constitutive laws: St. Venant-Kirchhoff (seed 000 eq. 4,
//!   9), corotational, stable Neo-Hookean, and the seed's viscous stress (eq. 10-11).
//! - [`meshfree`]: the seeds' meshfree (SPH) elasticity (seed 000 eq. 23-29) in
//!   total-Lagrangian form, `seed` and `corrected` (Bonet-Lok + hourglass control) variants.
//! - [`element`]: [`element::FemModel`], precomputed element data: shape-function gradients
//!   (eq. 13-21), nodal forces (eq. 22) by vectorised kernels, lumped masses, strain smoothing,
//!   tangent stiffness, the largest eigenvalue for critical time steps.
//! - [`contact`]: the haptic probe: god-object proxy on the touchable surface joined to the
//!   device point by a virtual coupling; the coupling's rank-one term.
//! - [`integrate`]: the seed's semi-implicit scheme (eq. 34), symplectic Euler, backward Euler,
//!   contact-local condensation, the Courant step and sub-stepping, behind one
//!   [`integrate::Stepper`].
//! - [`loads`]: scene loads, point loads, the probe load, pressure forces.
//! - [`scene`]: scene files (TOML) and built-in scenes, validated into a [`scene::Scene`].
//! - [`fem`]: [`fem::FemBody`], the FEM body: state + scratch + parameters, one `tick` per
//!   servo period.
//! - [`body`]: [`body::SoftBody`], the interface the server drives every model family through;
//!   [`build_body`] builds the family a scene names.
//! - [`mass_spring`]: the mass-spring surface with run-time Loop subdivision (seed 003, Zhang,
//!   Payandeh & Dill, *Haptic Subdivision*): eq. 1-3, the calibrated spring table (section
//!   3.2.4), [`mass_spring::MassSpringBody`].
//! - [`hybrid`]: the seeds' hybrid model (seed 000 sections 4-6): FEM core + meshfree particle
//!   layer simulated only where the probe touches, [`hybrid::HybridBody`].
//! - [`statics`]: static equilibrium (Newton on the tangent, sparse Cholesky) for references.
//! - [`indent`]: static indentation by a rigid frictionless sphere (augmented Lagrangian over
//!   [`statics`]): the probe-force reference and `haptic-solve --indent`.
//! - [`press`]: scripted probe presses through [`body::SoftBody`] as a user feels them
//!   (staircase holds, the demo's press, strokes): force, steadiness, depth, tick times.
//!
//! Units are SI throughout (m, kg, s, N, Pa). Seeds are cited as "seed 000 eq. N":
//! Mero & Susin, *Deformable Hybrid Approach*, Eurographics 2006.

// `!(x > 0.0)` is how this crate rejects NaN together with out-of-range values; the lint's
// `partial_cmp` rewrite would hide exactly that intent.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod body;
pub(crate) mod check;
pub mod contact;
pub mod element;
pub mod error;
pub mod fem;
pub mod hybrid;
pub mod indent;
pub mod integrate;
pub mod linalg;
pub mod loads;
pub mod mass_spring;
pub mod material;
pub mod mesh;
pub mod meshfree;
pub mod pool;
pub mod press;
pub mod scene;
pub(crate) mod simd;
pub mod statics;

pub use error::ModelError;
pub use glam::DVec3;

/// Builds the body a scene describes: the model family it names (`[model] family`,
/// [`scene::ModelFamily`]), behind the [`body::SoftBody`] interface.
///
/// # Errors
/// The errors of the family's constructor ([`fem::FemBody::new`] for the FEM,
/// [`mass_spring::MassSpringBody::new`] for the mass-spring surface, after
/// [`scene::MassSpringScene::table`]: a missing or stale calibration table;
/// [`fn@hybrid::prepare`] and [`hybrid::HybridBody::new`] for the hybrid model).
pub fn build_body(scene: &scene::Scene) -> Result<Box<dyn body::SoftBody>, ModelError> {
    build_body_with_progress(scene, &mut |_, _| {})
}

/// Preprocesses the hybrid model of a `family = "hybrid"` scene ([`fn@hybrid::prepare`] with the
/// scene's geometry, `[hybrid]` parameters, material and core size), reporting its stages to
/// `progress`.
///
/// # Errors
/// [`ModelError::SceneField`] naming `hybrid` when the scene has no `[hybrid]` section; the
/// errors of [`fn@hybrid::prepare`].
pub fn prepare_hybrid(
    scene: &scene::Scene,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<hybrid::HybridModel, ModelError> {
    let h = scene
        .hybrid
        .as_ref()
        .ok_or_else(|| ModelError::field("hybrid", "is required for model.family = \"hybrid\""))?;
    hybrid::prepare(
        h.geometry,
        &h.params,
        &scene.material,
        h.core_target_tets,
        progress,
    )
}

/// The hybrid body of a `family = "hybrid"` scene: [`prepare_hybrid`], then
/// [`hybrid::HybridBody::new`] with the core's clamped nodes, the scene's probe and tick (what
/// [`build_body`] boxes, for callers that read the hybrid body's own accessors).
///
/// # Errors
/// Those of [`prepare_hybrid`] and [`hybrid::HybridBody::new`].
pub fn build_hybrid_body(
    scene: &scene::Scene,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<hybrid::HybridBody, ModelError> {
    let model = prepare_hybrid(scene, progress)?;
    let clamped = model.clamped_core_nodes();
    // About 0.2 s, and 0.8 s more with an implicit core (lv-hybrid), after the preprocessing.
    progress(
        "body set-up: the sub-step check, and the implicit core's condensed layer",
        1.0,
    );
    let mut body = hybrid::HybridBody::new(
        model,
        &clamped,
        scene.tool_probe(0),
        scene.integrator.tick_s,
        &scene.name,
    )?;
    let more: Vec<contact::ProbeParams> = (1..scene.tools.max_tools)
        .map(|k| scene.tool_probe(k))
        .collect();
    let ids: Vec<String> = scene.tools.named.iter().map(|t| t.id.clone()).collect();
    body.set_tools(&more, &ids);
    Ok(body)
}

/// The mass-spring body of a `family = "mass-spring"` scene: [`mass_spring::MassSpringBody::new`]
/// with the scene's surface, parameters, calibration table and probe, one tool slot per
/// `probe.max_tools` ([`mass_spring::MassSpringBody::with_tools`], the named tools' probes in
/// their slots) and the organ table when the scene has one (what [`build_body`] boxes, for
/// callers that read the mass-spring body's own accessors).
///
/// # Errors
/// [`ModelError::SceneField`] naming `mass_spring` when the scene has no `[mass_spring]`
/// section; [`scene::MassSpringScene::table`]'s (a missing or stale calibration table); those of
/// [`mass_spring::MassSpringBody::new`], [`mass_spring::MassSpringBody::with_tools`] and
/// [`mass_spring::MassSpringBody::with_organ_table`].
pub fn build_mass_spring_body(
    scene: &scene::Scene,
) -> Result<mass_spring::MassSpringBody, ModelError> {
    let ms = scene.mass_spring.as_ref().ok_or_else(|| {
        ModelError::field(
            "mass_spring",
            "is required for model.family = \"mass-spring\"",
        )
    })?;
    let body = mass_spring::MassSpringBody::new(
        ms.surface.clone(),
        &ms.params,
        ms.table()?,
        scene.probe,
        &scene.integrator,
        &scene.name,
    )?;
    let probes: Vec<_> = (0..scene.tools.max_tools.max(1))
        .map(|slot| scene.tool_probe(slot))
        .collect();
    let ids: Vec<String> = scene.tools.named.iter().map(|t| t.id.clone()).collect();
    let body = body.with_tools(&probes, &ids)?;
    match &ms.organ {
        Some(o) => body.with_organ_table(o.table()?),
        None => Ok(body),
    }
}

/// What the host (the daemon) gives a body beside its scene: settings of the machine, which a
/// scene (a client's file) cannot set.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BodyOptions {
    /// Where a following region with tiles keeps them between sessions
    /// ([`integrate::follow::RegionCacheDir`]); `None`: in the session's memory only.
    pub region_cache: Option<integrate::follow::RegionCacheDir>,
    /// Where the region cache's complaints go as they happen (a file refused, a write failed;
    /// [`integrate::follow::RegionCacheReport`]); `None`: only counted in the body's stats.
    pub region_cache_report: Option<integrate::follow::RegionCacheReport>,
    /// Fill the region cache only: a following region's worker writes the tiles missing
    /// from `region_cache`, leaves the files there unread and keeps no tile in memory
    /// ([`integrate::follow::RegionFollower::spawn_with_cache`]); for a host preparing the
    /// cache ahead of sessions (`hapticd --prepare-regions`, `prepare_regions`), not for a
    /// session.
    pub region_cache_fill_only: bool,
}

/// [`build_body`] reporting the preprocessing's progress (`stage`, fraction in `[0, 1]`) for
/// families that preprocess (the hybrid model, [`fn@hybrid::prepare`]; the FEM with a
/// contact-local active region, [`fem::FemBody::new_with_progress`]).
///
/// # Errors
/// As [`build_body`]; for the hybrid family the errors of [`fn@hybrid::prepare`] and
/// [`hybrid::HybridBody::new`]; [`ModelError::SceneField`] naming `model.realtime` for a scene
/// that declares itself a static benchmark (`[model] realtime = false`).
pub fn build_body_with_progress(
    scene: &scene::Scene,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Box<dyn body::SoftBody>, ModelError> {
    build_body_with_options(scene, &BodyOptions::default(), progress)
}

/// [`build_body_with_progress`] with the host's `options` ([`BodyOptions`]).
///
/// # Errors
/// As [`build_body_with_progress`].
pub fn build_body_with_options(
    scene: &scene::Scene,
    options: &BodyOptions,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Box<dyn body::SoftBody>, ModelError> {
    if !scene.realtime {
        return Err(ModelError::field(
            "model.realtime",
            format!(
                "is false: scene `{}` is a static benchmark for haptic-solve, not a scene for \
                 the haptic loop",
                scene.name
            ),
        ));
    }
    match scene.family {
        scene::ModelFamily::Hybrid => Ok(Box::new(build_hybrid_body(scene, progress)?)),
        scene::ModelFamily::Fem => Ok(Box::new(fem::FemBody::new_with_options(
            scene, options, progress,
        )?)),
        scene::ModelFamily::MassSpring => Ok(Box::new(build_mass_spring_body(scene)?)),
    }
}
