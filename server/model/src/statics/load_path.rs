//! The load path of a scene's static solve ([`solve_scene_loads`]): load increments, penalty
//! continuation and augmented-Lagrangian volume passes around the Newton solver of
//! [`super`].

use glam::DVec3;

use super::{FollowerPressure, StaticParams, StaticTerm, free_residual_norm, solve_static_with};
use crate::ModelError;
use crate::element::FemModel;
use crate::material::{MaterialModel, MaterialParams};

/// Bulk moduli of the volumetric penalty a static solve passes through for `material`
/// (penalty continuation), Pa, ending with the material's own; a single entry when no
/// continuation is needed.
///
/// Newton on a displacement-only penalty formulation converges only within a radius that
/// shrinks as the bulk modulus `kappa` grows: a step that is right to first order leaves a
/// second-order volume error which `kappa` turns into a stress far above the load. On the LV
/// inflation (`deploy/scenes/lv_guccione_inflation.toml`, 474 quadratic elements) Newton
/// converges with `kappa` = 20 times the shear modulus in 45 iterations, needs 115 at 200
/// times, and diverges from the first step at 2 000 times. So the load is applied with
/// `kappa_0 = 20 mu`, and [`solve_scene_loads`] then either raises `kappa` tenfold per stage at
/// full load (each stage starts within `p / kappa` of its solution; this still stalls at
/// 2 000 times on finer LV meshes) or, with the element-mean dilatation, keeps `kappa_0` and
/// adds augmented-Lagrangian element pressures. The equilibrium of a hyperelastic body under
/// the final load does not depend on the path.
///
/// Only the Guccione material has a separate bulk modulus; for the others this returns its
/// `lambda` alone.
pub fn penalty_continuation(material: &MaterialParams) -> Vec<f64> {
    let kappa = material.lambda_pa;
    if material.model != MaterialModel::Guccione {
        return vec![kappa];
    }
    let start = 20.0 * material.mu_pa;
    let mut stages = Vec::new();
    let mut k = start;
    while k < kappa {
        stages.push(k);
        k *= 10.0;
    }
    stages.push(kappa);
    stages
}

/// `material` with the volumetric penalty `bulk_modulus_pa` (Pa): see
/// [`penalty_continuation`].
pub fn with_bulk_modulus(material: &MaterialParams, bulk_modulus_pa: f64) -> MaterialParams {
    let mut m = *material;
    m.lambda_pa = bulk_modulus_pa;
    m.guccione.bulk_modulus_pa = bulk_modulus_pa;
    m
}

/// What [`solve_scene_loads`] did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadPathReport {
    /// Newton iterations over all increments and passes.
    pub newton_iterations: usize,
    /// Solves at full load after the increments: penalty stages ([`penalty_continuation`]) or
    /// augmented-Lagrangian updates of the element pressures (0 when none).
    pub constraint_passes: usize,
    /// Largest `|J_c - 1|` over the cells at the end, for the mean-dilatation Guccione material
    /// (0 otherwise).
    pub worst_volume_change: f64,
    /// Final free residual of the model of the last solve (with its element pressures), every
    /// load evaluated at the final shape, N.
    pub residual_n: f64,
}

/// Largest `|J_c - 1|` the augmented-Lagrangian passes of [`solve_scene_loads`] leave.
pub const VOLUME_TOLERANCE: f64 = 1e-6;
/// Largest number of those passes.
pub const MAX_VOLUME_PASSES: usize = 60;

/// Static equilibrium of `scene` under its `[loads]` from the rest shape: the load in
/// `load_steps` equal increments (dead loads scaled, follower pressures as
/// [`FollowerPressure`] with their load stiffness), Newton at each with `params`. `progress`
/// sees each increment or pass as `(label, Newton iterations)`. Returns the node positions, m.
///
/// A Guccione material whose bulk modulus exceeds 20 times its shear modulus stands for an
/// incompressible one, and a large penalty stalls Newton ([`penalty_continuation`]): the
/// increments run with the penalty `kappa_0 = 20 mu`; then, with the element-mean dilatation
/// (`volumetric = "mean-dilatation"`) on quadratic elements, augmented-Lagrangian passes at full load (method of
/// multipliers: `lambda_c += kappa (J_c - 1)`, [`FemModel::set_cell_pressures`], the penalty
/// raised fourfold towards the scene's after each pass Newton finishes in at most three
/// iterations) drive every element's volume ratio to 1 within [`VOLUME_TOLERANCE`]: the
/// incompressible solution, whatever the scene's bulk modulus; otherwise (per-point penalty, or
/// linear elements, which lock under one constraint each) the penalty is raised tenfold per
/// pass to the scene's.
///
/// # Errors
/// The scene's model errors ([`crate::scene::Scene::fem_model`]);
/// [`ModelError::NoConvergence`] naming the increment or pass that failed and why, or when
/// the volume constraint is not met after [`MAX_VOLUME_PASSES`] passes.
pub fn solve_scene_loads(
    scene: &crate::scene::Scene,
    load_steps: usize,
    params: &StaticParams,
    progress: &mut dyn FnMut(&str, usize),
) -> Result<(Vec<DVec3>, LoadPathReport), ModelError> {
    let stages = penalty_continuation(&scene.material);
    let fem = if stages.len() > 1 {
        scene_model(scene, stages[0])?
    } else {
        scene.fem_model()?
    };
    let mut path = LoadPath {
        scene,
        dead: scene.dead_forces(),
        params,
        progress,
        fem,
        x: scene.mesh.nodes.clone(),
        report: LoadPathReport {
            newton_iterations: 0,
            constraint_passes: 0,
            worst_volume_change: 0.0,
            residual_n: 0.0,
        },
    };
    let steps = load_steps.max(1);
    for k in 1..=steps {
        let label = if stages.len() > 1 {
            format!("load increment {k}/{steps} (penalty {:.1e} Pa)", stages[0])
        } else {
            format!("load increment {k}/{steps}")
        };
        let hint = " (more load steps may help)";
        path.report.newton_iterations += path.solve(k as f64 / steps as f64, label, hint)?;
    }
    // The multipliers need an element that can keep its volume: on linear tetrahedra one
    // constraint per element locks (and the passes diverge), so they take the penalty stages.
    if scene.material.mean_dilatation() && scene.mesh.is_quadratic() && stages.len() > 1 {
        path.volume_passes(&stages)?;
    } else {
        path.penalty_stages(&stages)?;
    }
    path.report.residual_n = path.true_residual();
    Ok((path.x, path.report))
}

/// The model of `scene` with the volumetric penalty `kappa` (Pa, [`with_bulk_modulus`]).
fn scene_model(scene: &crate::scene::Scene, kappa: f64) -> Result<FemModel, ModelError> {
    let mut s = scene.clone();
    s.material = with_bulk_modulus(&scene.material, kappa);
    s.fem_model()
}

/// Largest `|J_c - 1|` over the cells of `fem` at `x` (`ratios` receives every `J_c`).
fn worst_volume_change(fem: &FemModel, x: &[DVec3], ratios: &mut Vec<f64>) -> f64 {
    fem.cell_volume_ratios(x, ratios);
    ratios.iter().map(|j| (j - 1.0).abs()).fold(0.0, f64::max)
}

/// The solves of [`solve_scene_loads`]: the scene, its dead loads at full scale, Newton's
/// parameters, the progress callback, and the path's state (the model with its penalty and
/// element pressures, the positions and the report so far).
struct LoadPath<'a> {
    scene: &'a crate::scene::Scene,
    /// Dead nodal forces at full load, N.
    dead: Vec<DVec3>,
    params: &'a StaticParams,
    progress: &'a mut dyn FnMut(&str, usize),
    /// The model of the current penalty stage.
    fem: FemModel,
    /// Node positions, m.
    x: Vec<DVec3>,
    report: LoadPathReport,
}

impl LoadPath<'_> {
    /// Static equilibrium of the model from `x` under the scene's loads scaled by `scale`;
    /// returns Newton's iterations. `hint` is added to the message of a failure only (a
    /// converged increment prints its label alone).
    ///
    /// # Errors
    /// [`ModelError::NoConvergence`] naming `label`.
    fn solve(&mut self, scale: f64, label: String, hint: &str) -> Result<usize, ModelError> {
        let f: Vec<DVec3> = self.dead.iter().map(|v| *v * scale).collect();
        let follower = FollowerPressure::new(&self.scene.loads, scale);
        let term = (!follower.is_empty()).then_some(&follower as &dyn StaticTerm);
        let r = solve_static_with(&self.fem, &f, term, &mut self.x, self.params)
            .map_err(|e| ModelError::NoConvergence(format!("{label}{hint}: {e}")))?;
        (self.progress)(&label, r.iterations);
        Ok(r.iterations)
    }

    /// The free residual at `x` with every load evaluated at `x`, N.
    fn true_residual(&self) -> f64 {
        let scene = self.scene;
        free_residual_norm(
            &self.fem,
            &crate::loads::static_external_forces(
                &scene.loads,
                &scene.mesh,
                scene.material.density_kg_per_m3,
                &self.x,
            ),
            &self.x,
        )
    }

    /// Method of multipliers at full load: `lambda_c += kappa (J_c - 1)` after each solve;
    /// the penalty grows fourfold (up to the scene's, the last of `stages`) after a pass
    /// Newton finished in a few iterations, which keeps it where Newton converges while the
    /// constraint error shrinks ([`solve_scene_loads`]).
    ///
    /// # Errors
    /// As [`Self::solve`]; [`ModelError::NoConvergence`] after [`MAX_VOLUME_PASSES`] passes.
    fn volume_passes(&mut self, stages: &[f64]) -> Result<(), ModelError> {
        let kappa_max = stages[stages.len() - 1];
        let mut kappa = stages[0];
        let mut lambda = vec![0.0; self.fem.cell_count()];
        let mut ratios = Vec::new();
        for pass in 1.. {
            let w = worst_volume_change(&self.fem, &self.x, &mut ratios);
            self.report.worst_volume_change = w;
            if w <= VOLUME_TOLERANCE {
                break;
            }
            if pass > MAX_VOLUME_PASSES {
                return Err(ModelError::NoConvergence(format!(
                    "the volume constraint: an element still changes its volume by {w:.2e} \
                     after {MAX_VOLUME_PASSES} augmented-Lagrangian passes (tolerance \
                     {VOLUME_TOLERANCE:.0e})"
                )));
            }
            for (l, j) in lambda.iter_mut().zip(&ratios) {
                *l += kappa * (j - 1.0);
            }
            self.fem.set_cell_pressures(lambda.clone());
            let label = format!(
                "volume pass {pass} (worst element volume change {w:.2e}, penalty {kappa:.1e} Pa)"
            );
            let its = self.solve(1.0, label, "")?;
            self.report.newton_iterations += its;
            self.report.constraint_passes += 1;
            if its <= 3 && kappa < kappa_max {
                kappa = (kappa * 4.0).min(kappa_max);
                self.fem = scene_model(self.scene, kappa)?;
                self.fem.set_cell_pressures(lambda.clone());
            }
        }
        Ok(())
    }

    /// The penalty stages after the first (tenfold each, to the scene's bulk modulus) at full
    /// load; the worst volume change at the end for a mean-dilatation material.
    ///
    /// # Errors
    /// As [`Self::solve`].
    fn penalty_stages(&mut self, stages: &[f64]) -> Result<(), ModelError> {
        for (j, &kappa) in stages.iter().enumerate().skip(1) {
            self.fem = scene_model(self.scene, kappa)?;
            let label = format!(
                "penalty stage {j}/{} (bulk modulus {kappa:.1e} Pa)",
                stages.len() - 1
            );
            self.report.newton_iterations += self.solve(1.0, label, "")?;
            self.report.constraint_passes += 1;
        }
        if self.scene.material.mean_dilatation() {
            let mut ratios = Vec::new();
            self.report.worst_volume_change = worst_volume_change(&self.fem, &self.x, &mut ratios);
        }
        Ok(())
    }
}
