//! The `hybrid.*` (and material) overrides shared by the hybrid study tools (`hybrid_press`,
//! `hybrid_bench`): each option replaces one scene value; `apply` checks the result.

use haptic_model::hybrid::{CoreMassScale, CoreStep, InactiveLayer, ScaledMotion};
use haptic_model::material::MaterialModel;
use haptic_model::meshfree::{KernelKind, MeshfreeVariant};
use haptic_model::scene::Scene;

#[derive(clap::Args, Debug, Default)]
pub struct HybridOverrides {
    /// Meshfree variant: seed or corrected (default: the scene's).
    #[arg(long)]
    pub variant: Option<String>,
    /// `hybrid.spacing_m` override: the particle lattice spacing, m.
    #[arg(long)]
    pub spacing_m: Option<f64>,
    /// `hybrid.mass_scale` override.
    #[arg(long)]
    pub mass_scale: Option<f64>,
    /// `hybrid.core_mass_scale` override: a number (1: the body's real inertia), `auto` or
    /// `uniform`.
    #[arg(long)]
    pub core_mass_scale: Option<String>,
    /// `hybrid.scaled_motion` override: `absolute` or `deviation`.
    #[arg(long)]
    pub scaled_motion: Option<String>,
    /// `hybrid.core_step` override: `explicit` or `implicit`.
    #[arg(long)]
    pub core_step: Option<String>,
    /// `hybrid.core_stiffness_margin` override (with an implicit core).
    #[arg(long)]
    pub core_stiffness_margin: Option<f64>,
    /// `mesh.target_tets` override: wanted tetrahedra of the FEM core.
    #[arg(long)]
    pub core_tets: Option<usize>,
    /// `hybrid.core_fraction` override: share of the wall thickness in the FEM core.
    #[arg(long)]
    pub core_fraction: Option<f64>,
    /// `hybrid.safety_factor` override: the sub-step's share of the critical step bound.
    #[arg(long)]
    pub safety_factor: Option<f64>,
    /// `hybrid.contact_stiffness_n_per_m` override (probe penalty per particle, whatever the
    /// spacing; clears a per-area penalty).
    #[arg(long, conflicts_with = "contact_stiffness_pa_per_m")]
    pub contact_stiffness_n_per_m: Option<f64>,
    /// `hybrid.contact_stiffness_pa_per_m` override (probe penalty per area, Pa/m: one
    /// particle's is this times the spacing squared).
    #[arg(long)]
    pub contact_stiffness_pa_per_m: Option<f64>,
    /// `hybrid.max_active_particles` override.
    #[arg(long)]
    pub max_active: Option<usize>,
    /// `hybrid.activation_radius_m` override, m.
    #[arg(long)]
    pub activation_radius_m: Option<f64>,
    /// `hybrid.release_radius_m` override, m.
    #[arg(long)]
    pub release_radius_m: Option<f64>,
    /// `hybrid.hourglass_coefficient` override.
    #[arg(long)]
    pub hourglass_coefficient: Option<f64>,
    /// `hybrid.inactive_layer` override: `tied` or `elements`.
    #[arg(long)]
    pub inactive_layer: Option<String>,
    /// `mesh.order` override: element order of the core (1 or 2).
    #[arg(long)]
    pub core_order: Option<u8>,
    /// `material.model` override (e.g. `stvk`, `stable-neo-hookean`).
    #[arg(long)]
    pub material_model: Option<String>,
    /// `material.mass_damping_per_s` override (1/s).
    #[arg(long)]
    pub mass_damping_per_s: Option<f64>,
}

impl HybridOverrides {
    /// Applies the overrides to the hybrid scene `scene` and checks its parameters.
    pub fn apply(&self, scene: &mut Scene) -> anyhow::Result<()> {
        if let Some(a) = self.mass_damping_per_s {
            scene.material.mass_damping_per_s = a;
        }
        if let Some(m) = &self.material_model {
            scene.material.model = MaterialModel::from_scene_name(m)
                .ok_or_else(|| anyhow::anyhow!("material model {m}: unknown"))?;
        }
        let h = scene
            .hybrid
            .as_mut()
            .ok_or_else(|| anyhow::anyhow!("{} is not a hybrid scene", scene.name))?;
        let p = &mut h.params;
        if let Some(v) = &self.variant {
            p.meshfree.variant = MeshfreeVariant::from_name(v)
                .ok_or_else(|| anyhow::anyhow!("variant {v}: seed or corrected"))?;
            p.meshfree.kernel = KernelKind::default_for(p.meshfree.variant);
        }
        if let Some(s) = self.spacing_m {
            p.meshfree.spacing_m = s;
        }
        if let Some(m) = self.mass_scale {
            p.mass_scale = m;
        }
        if let Some(c) = &self.core_mass_scale {
            p.core_mass_scale = CoreMassScale::parse(c)?;
        }
        if let Some(m) = &self.scaled_motion {
            p.scaled_motion = ScaledMotion::parse(m)?;
        }
        if let Some(step) = &self.core_step {
            p.core_step = CoreStep::parse(step, self.core_stiffness_margin)?;
        } else if let (CoreStep::Implicit { margin }, Some(m)) =
            (&mut p.core_step, self.core_stiffness_margin)
        {
            *margin = m;
        }
        if let Some(n) = self.core_tets {
            h.core_target_tets = n;
        }
        if let Some(c) = self.core_fraction {
            p.core_fraction = c;
        }
        if let Some(f) = self.safety_factor {
            p.safety_factor = f;
        }
        if let Some(k) = self.contact_stiffness_n_per_m {
            p.contact_stiffness_n_per_m = k;
            p.contact_stiffness_pa_per_m = None;
        }
        if let Some(k) = self.contact_stiffness_pa_per_m {
            p.contact_stiffness_pa_per_m = Some(k);
        }
        if let Some(n) = self.max_active {
            p.max_active_particles = n;
        }
        if let Some(r) = self.activation_radius_m {
            p.activation_radius_m = r;
        }
        if let Some(r) = self.release_radius_m {
            p.release_radius_m = r;
        }
        if let Some(c) = self.hourglass_coefficient {
            p.meshfree.hourglass_coefficient = c;
        }
        if let Some(l) = &self.inactive_layer {
            p.inactive_layer = InactiveLayer::parse(l)?;
        }
        if let Some(o) = self.core_order {
            p.core_order = o;
        }
        p.validate()?;
        Ok(())
    }
}
