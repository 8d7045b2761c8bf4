//! The dynamic methods the scenarios compare ([`methods`]): integrator, step setting and
//! material, with the labels that name their curves.

use haptic_model::integrate::{IntegratorKind, IntegratorParams, LinearSolver};
use haptic_model::material::MaterialModel;

use crate::common::{CG_ITERATIONS, INTEGRATORS, MATERIALS};

/// One dynamic method: integrator with its step setting, and the material.
#[derive(Debug, Clone, Copy)]
pub struct Method {
    pub kind: IntegratorKind,
    /// Safety factor on the critical step (explicit schemes; backward Euler: one sub-step).
    pub sf: f64,
    /// CG iteration cap (backward Euler with CG).
    pub cg: u32,
    /// Backward Euler's linear solver: CG on the current tangent, or the rest factor (the
    /// built-in `lv`'s default).
    pub solver: LinearSolver,
    pub material: MaterialModel,
}

impl Method {
    /// The curve label: "backward-euler cg=10", "semi-implicit sf=0.5 [corotational]".
    pub fn label(&self) -> String {
        let base = match (self.kind, self.solver) {
            (IntegratorKind::BackwardEuler, LinearSolver::RestCholesky) => {
                format!("{} rest-cholesky", self.kind.name())
            }
            (IntegratorKind::BackwardEuler, LinearSolver::Cg) => {
                format!("{} cg={}", self.kind.name(), self.cg)
            }
            (k, _) => format!("{} sf={}", k.name(), self.sf),
        };
        material_label(base, self.material)
    }

    /// "auto sub-steps at 0.5 dt_crit (3)" or "1 sub-step(s), CG <= 10 it."
    pub fn step_text(&self, substeps: u32) -> String {
        match (self.kind, self.solver) {
            (IntegratorKind::BackwardEuler, LinearSolver::RestCholesky) => {
                format!("{substeps} sub-step(s), rest factor")
            }
            (IntegratorKind::BackwardEuler, LinearSolver::Cg) => {
                format!("{substeps} sub-step(s), CG <= {} it.", self.cg)
            }
            (_, _) => format!("auto sub-steps at {} dt_crit ({substeps})", self.sf),
        }
    }

    /// Integrator settings of the loaded runs (`lame`, `cantilever`).
    pub fn params(&self) -> IntegratorParams {
        IntegratorParams {
            kind: self.kind,
            safety_factor: self.sf,
            cg_max_iterations: self.cg,
            linear_solver: self.solver,
            max_substeps: 2000,
            ..IntegratorParams::default()
        }
    }
}

/// `base`, with the material appended unless it is St. Venant-Kirchhoff.
pub fn material_label(base: String, m: MaterialModel) -> String {
    if m == MaterialModel::StVenantKirchhoff {
        base
    } else {
        format!("{base} [{}]", m.scene_name())
    }
}

/// The dynamic methods of a scenario: every integrator on St. Venant-Kirchhoff (explicit ones
/// at each safety factor of `safeties`, backward Euler at each CG cap of [`CG_ITERATIONS`] and
/// with the rest factor), and the other materials with the semi-implicit scheme at `sf` 0.5
/// and backward Euler at the largest CG cap and with the rest factor.
pub fn methods(safeties: &[f64]) -> Vec<Method> {
    let mut out = Vec::new();
    for &material in MATERIALS {
        let stvk = material == MaterialModel::StVenantKirchhoff;
        for &kind in INTEGRATORS {
            match kind {
                IntegratorKind::BackwardEuler => {
                    let caps: &[u32] = if stvk {
                        CG_ITERATIONS
                    } else {
                        &CG_ITERATIONS[CG_ITERATIONS.len() - 1..]
                    };
                    for &cg in caps {
                        out.push(Method {
                            kind,
                            sf: 1.0,
                            cg,
                            solver: LinearSolver::Cg,
                            material,
                        });
                    }
                    out.push(Method {
                        kind,
                        sf: 1.0,
                        cg: 0,
                        solver: LinearSolver::RestCholesky,
                        material,
                    });
                }
                IntegratorKind::SemiImplicit | IntegratorKind::SymplecticEuler => {
                    if !stvk && kind != IntegratorKind::SemiImplicit {
                        continue;
                    }
                    for &sf in safeties {
                        if !stvk && sf != 0.5 {
                            continue;
                        }
                        out.push(Method {
                            kind,
                            sf,
                            cg: 20,
                            solver: LinearSolver::Cg,
                            material,
                        });
                    }
                }
            }
        }
    }
    out
}

/// "steady after T ms", or "not steady at the T ms cap".
pub fn steady_text(time_s: f64, cap_s: f64) -> String {
    if time_s >= cap_s - 1e-9 {
        format!("not steady at the {:.0} ms cap", cap_s * 1e3)
    } else {
        format!("steady after {:.0} ms", time_s * 1e3)
    }
}
