//! The built-in scenes: TOML texts compiled into the library (it reads no file outside
//! itself); identical copies live in `deploy/scenes/` for users to edit, and a test checks that
//! they agree.

/// Built-in scene `lv`: the idealized left ventricle built in code.
const LV_TOML: &str = r#"# Built-in scene "lv" (a copy of the constant in server/model/src/scene/builtin.rs).
name = "lv"
description = "Idealized left ventricle (geometry of the Land et al. 2015 cardiac mechanics benchmark, Proc. R. Soc. A 471:20150641: endocardium 7x7x17 mm, epicardium 10x10x20 mm, cut at z = 5 mm), meshed in code, base clamped, epicardium touchable. Material: stable neo-Hookean (the organ of every LV scene; StVK has no equilibrium under the probe past about 1.3 mm), mu = 5 kPa from the linearised Guccione law of benchmark problem 2 (C = 10 kPa, b_f = b_t = b_fs = 1, so mu = C/2), Poisson ratio 0.45 as a compressible stand-in for the benchmark's incompressibility, hence E = 14.5 kPa; rho = 1060 kg/m^3."

[mesh]
builtin = "lv"
target_tets = 500       # 474 tets (993 nodes with order 2); 1000..=30000 land within about 30 % of the target
order = 2               # quadratic 10-node tets, mid-edge nodes on the ellipsoids (1: linear)
length_unit = "mm"      # unit for reports; the built-in geometry is fixed

[material]
model = "stable-neo-hookean"    # an equilibrium under the probe to 4 mm and past (StVK: none past ~1.3 mm)
youngs_modulus_pa = 14500.0
poisson_ratio = 0.45
phi_pa_s = 0.05
psi_pa_s = 0.05
density_kg_per_m3 = 1060.0
mass_damping_per_s = 5.0

[boundary]
clamped = ["BASE"]
touchable = ["EPI"]

[integrator]
kind = "backward-euler"         # one implicit step per tick, solved with the factor below
linear_solver = "rest-cholesky" # the tick matrix frozen at rest and factorised once at set-up (0.3 s)
stiffness_margin = 2.0          # 2 K_0 in the frozen matrix: stiffening under large strain (1.0 diverged under a 50 mN point load, StVK)
tick_s = 0.001
substeps = "auto"               # the explicit kinds' sub-steps ("symplectic-euler": 12 here)
max_substeps = 64
safety_factor = 0.9             # explicit kinds: presses to 8 mm stay stable (StVK stiffens little: the wall bends)

[probe]
radius_m = 0.002
coupling_stiffness_n_per_m = 300.0
coupling_damping_n_s_per_m = 0.05
max_force_n = 10.0
"#;

/// Built-in scene `ellipsoids`: the seed's coarse Ellipsoids Model.
const ELLIPSOIDS_TOML: &str = r#"# Built-in scene "ellipsoids" (a copy of the constant in server/model/src/scene/builtin.rs).
name = "ellipsoids"
description = "The seed's Ellipsoids Model (Mero & Susin 2006, Table 1): a coarse closed ellipsoidal shell of about 188 tets; the paper gives no sizes, we use inner semi-axes 6x6x12 mm and outer 10x10x16 mm. Table 1 prints lambda = 5.5, mu = 2.5, phi = psi = 9e-5 without units; our reading is kPa and kPa s: lambda = 5.5 kPa, mu = 2.5 kPa, phi = psi = 0.09 Pa s. Density 1060 kg/m^3 and mass damping 5/s are ours. The bottom pole cap is clamped so that the body cannot drift."

[mesh]
builtin = "ellipsoids"
length_unit = "mm"
inner_semi_axes = [6.0, 6.0, 12.0]
outer_semi_axes = [10.0, 10.0, 16.0]
target_tets = 188

[material]
lambda_pa = 5500.0
mu_pa = 2500.0
phi_pa_s = 0.09
psi_pa_s = 0.09
density_kg_per_m3 = 1060.0
mass_damping_per_s = 5.0

[boundary]
clamped = ["POLE"]
touchable = ["OUTER"]

[integrator]
kind = "semi-implicit"
tick_s = 0.001
substeps = "auto"
max_substeps = 64
safety_factor = 0.5             # the critical step is computed at rest; StVK stiffens under large strain

[probe]
radius_m = 0.002
coupling_stiffness_n_per_m = 300.0
coupling_damping_n_s_per_m = 0.05
max_force_n = 10.0
"#;

/// Built-in scene `hemisphere-springs`: the paper's Figure 12 hemisphere as a mass-spring
/// surface with one-ring subdivision.
const HEMISPHERE_SPRINGS_TOML: &str = r#"# Built-in scene "hemisphere-springs" (a copy of the constant in server/model/src/scene/builtin.rs).
name = "hemisphere-springs"
description = "A triangulated hemisphere (Zhang, Payandeh & Dill, Haptic Subdivision, Figure 12) as a mass-spring surface with home springs (eq. 1-2) and run-time one-ring Loop subdivision around the contact node, spring constants from the calibrated table (section 3.2.4). K_h = K_m = 0.06 N/mm as in the paper's experiment (section 3.2.2); radius 50 mm and edges of about 4 mm (the paper's 8 mm until session 13: under the 4 mm probe a press between nodes then bore on one node), node mass 1 g and damping 0.2 N s/m are ours (the paper gives none); rim clamped. Every spring times the contact factor of the organ table (per node, edge midpoint and corner Loop child of a triangle, and sphere depth), calibrated to the FEM of the solid half ball it bounds (stable neo-Hookean, E = 14.5 kPa, nu = 0.45, base clamped, the exact 4 mm sphere) at six points from the pole towards the rim (reference_file; docs/accuracy.md)."

[model]
family = "mass-spring"

[mesh]
builtin = "hemisphere"
length_unit = "mm"
outer_radius = 50.0             # mm
edge_length = 4.0               # mm, about (the paper's L is 8 mm: half, so that several nodes carry a press)

[boundary]
clamped = ["RIM"]
touchable = ["SURFACE"]

[mass_spring]
mesh_spring_n_per_m = 60.0      # K_m, eq. 2
home_spring_n_per_m = 60.0      # K_h, eq. 2
damping_n_s_per_m = 0.2         # K_d, eq. 2
node_mass_kg = 0.001            # m, eq. 3
rings = 1                       # one-ring subdivision around the contact node
springs = "calibrated"          # K'_h, K'_m from the lookup table (section 3.2.4)
km_over_kh_after = 1.0          # the fixed ratio K'_m / K'_h, kept at K_m / K_h
vertex_rule = "keep"            # original nodes keep their rest position
coarsen_delay_s = 0.2           # an area is coarsened 0.2 s after the probe left it
calibration_file = "hemisphere-springs.calibration.csv"
reference_file = "hemisphere-springs.reference.csv"  # the solid half ball's FEM reference at six points (springs_reference/)
reference_axis = [0, 0, 1]      # a body of revolution about z: the target depends on the height (the polar angle)
organ_file = "hemisphere-springs.organ.csv"  # the contact factor per node, edge midpoint and corner Loop child of a triangle, and sphere depth (haptic-calibrate)

[integrator]
kind = "symplectic-euler"
tick_s = 0.001
substeps = "auto"
max_substeps = 64
safety_factor = 0.5

[probe]
radius_m = 0.004                # the patch (8 mm) holds a node and its ring on the 4 mm mesh
coupling_stiffness_n_per_m = 300.0
coupling_damping_n_s_per_m = 0.05
max_force_n = 10.0
"#;

/// Built-in scene `lv-surface-springs`: the LV epicardium as a mass-spring surface.
const LV_SURFACE_SPRINGS_TOML: &str = r#"# Built-in scene "lv-surface-springs" (a copy of the constant in server/model/src/scene/builtin.rs).
name = "lv-surface-springs"
description = "The epicardium of the idealized left ventricle (built-in lv geometry, the linear mesh of about 2000 tets: 350 surface nodes, edges of about 2.2 mm) as a mass-spring surface with home springs (Zhang, Payandeh & Dill eq. 1-2), base rim clamped, run-time two-ring Loop subdivision with calibrated springs (the area the press made kept while the probe stays in it). K_h = K_m = 2.013 N/m, every spring times the contact factor of the organ table, calibrated to the stable neo-Hookean reference at six epicardial points (reference_file: lv-probe, p1-p5; per node, edge midpoint and corner Loop child of a triangle; within 10 % at the six points from 0.25 to 4 mm, subdivided and not: docs/accuracy.md); node mass: the myocardium (3.43 g) over the epicardial nodes; damping about critical per node."

[model]
family = "mass-spring"

[mesh]
builtin = "lv"
target_tets = 2000
length_unit = "mm"

[boundary]
clamped = ["BASE"]
touchable = ["EPI"]

[mass_spring]
mesh_spring_n_per_m = 2.013     # K_m = K_h (the paper's ratio)
home_spring_n_per_m = 2.013     # the organ table's contact factor (0.03..1.6) scales it to the reference
damping_n_s_per_m = 0.01        # about critical for a node on its home spring
node_mass_kg = 0.00001          # the myocardium's 3.43 g over the 350 epicardial nodes
rings = 2                       # two rings: the dent of the 2 mm probe stays inside the area to 4 mm (docs/accuracy.md, session 12)
springs = "calibrated"
vertex_rule = "keep"
coarsen_delay_s = 0.2
calibration_file = "lv-surface-springs.calibration.csv"
reference_file = "lv-surface-springs.reference.csv"  # the organ's FEM reference at six points (springs_reference/)
reference_axis = [0, 0, 1]      # the LV is a body of revolution about z: the target depends on the height
organ_file = "lv-surface-springs.organ.csv"  # the contact factor per node, edge midpoint and corner Loop child of a triangle, and sphere depth (haptic-calibrate)

[integrator]
kind = "symplectic-euler"
tick_s = 0.001
substeps = "auto"
max_substeps = 64
safety_factor = 0.5

[probe]
radius_m = 0.002
coupling_stiffness_n_per_m = 300.0
coupling_damping_n_s_per_m = 0.05
max_force_n = 10.0
"#;

/// Built-in scene `lv-hybrid`: the seeds' hybrid model on the LV geometry.
const LV_HYBRID_TOML: &str = r#"# Built-in scene "lv-hybrid" (a copy of the constant in server/model/src/scene/builtin.rs).
name = "lv-hybrid"
description = "The seeds' hybrid model (Mero & Susin 2006, sections 4-6) on the idealized LV of the built-in lv scene: an FEM of the whole wall (about 700 curved quadratic tets, base clamped) and about 53 000 meshfree particles at 0.35 mm (corrected variant) in its outer 65 %, simulated only in the regions under the probe; there their terms take over the elements' energy, elsewhere the elements carry the layer's stiffness. The probe is a proxy sphere on the particles with the virtual coupling. Material of the lv scene: stable neo-Hookean, E = 14.5 kPa, nu = 0.45 (St. Venant-Kirchhoff has no equilibrium under the probe past about 1.3 mm). Ours, not in the seed: the elements under the layer, the proxy, the active particles' deviation from the FEM's interpolation weighing mass_scale = 20000 (one explicit sub-step per 1 ms tick), and the FEM, at its real inertia, stepping implicitly."

[model]
family = "hybrid"

[mesh]
builtin = "lv"
target_tets = 700       # the FEM of the whole wall: 702 tets (1000: 948, 0.7 points closer to the reference, 40 us more a tick)
order = 2               # curved 10-node tets (linear ones lock: +40 % at 1 500)
length_unit = "mm"      # unit for reports; the built-in geometry is fixed

[material]
model = "stable-neo-hookean"    # the lv scene's organ: an equilibrium under the probe to 4 mm and past (StVK: none past ~1.3 mm)
youngs_modulus_pa = 14500.0
poisson_ratio = 0.45
phi_pa_s = 0.05
psi_pa_s = 0.05
density_kg_per_m3 = 1060.0
mass_damping_per_s = 20.0

[boundary]
clamped = ["BASE"]      # the hybrid body clamps its core's base
touchable = ["EPI"]     # the hybrid body's outer surface is the epicardium

[integrator]
tick_s = 0.001          # sub-steps come from the hybrid body's own critical step

[hybrid]
variant = "corrected"           # or "seed" (the paper's kernel and gradient)
spacing_m = 0.00035             # lattice spacing of the particles: within 1.6 % of the 0.26 mm
                                # lattice's force at every depth, 40 % less tick (docs/decisions.md)
smoothing_ratio = 1.0           # h / spacing: 26 neighbours
hourglass_coefficient = 0.5
core_fraction = 0.35            # the particles fill the wall outside its inner 35 %
inactive_layer = "elements"     # the FEM's elements carry the layer where no particle is
                                # simulated ("tied": the seed, no stiffness there)
surface_target_tets = 12000     # resolution of the outer surface (per-vertex particle regions)
activation_radius_m = 0.004     # 2 mm beyond the probe: a 1 mm press activates about 1 450
release_radius_m = 0.006
release_tolerance_m = 0.00002
max_active_particles = 6000
contact_stiffness_pa_per_m = 2.367e8 # probe-particle penalty per area (29 N/m a particle at 0.35 mm; in series with the coupling)
mass_scale = 20000.0             # on the active particles' deviations: 1 sub-step per tick (10 000
                                 # gives it too, but the demo's first touch then dips 9 %)
scaled_motion = "deviation"      # only the deviation from the FEM's interpolation is heavier
core_step = "implicit"           # the FEM's linearly implicit step, matrix frozen at rest
core_stiffness_margin = 10.0     # 10 x the FEM's rest stiffness in that matrix: the particles'
                                 # penalty on its nodes stays explicit (4 chattered at 3 mm)
core_mass_scale = "auto"         # with the implicit core: 1, the body's real inertia
safety_factor = 0.9
max_substeps = 64

[probe]
radius_m = 0.002
coupling_stiffness_n_per_m = 300.0 # the proxy's virtual coupling, as the lv scene's
max_force_n = 10.0
"#;

/// Built-in scene `ellipsoids-hybrid`: the seeds' Hybrid Model setting (Table 1).
const ELLIPSOIDS_HYBRID_TOML: &str = r#"# Built-in scene "ellipsoids-hybrid" (a copy of the constant in server/model/src/scene/builtin.rs).
name = "ellipsoids-hybrid"
description = "The seeds' Hybrid Model setting (Mero & Susin 2006, Table 1): lambda = 5.0, mu = 2.0, phi = psi = 9e-5 (read as kPa and kPa s, as in the ellipsoids scene) on the ellipsoidal wall 6x6x12 to 10x10x16 mm (bottom pole clamped), stable neo-Hookean (the seed's material is St. Venant-Kirchhoff): about 27 000 particles at 0.5 mm in the outer 60 % of the wall, simulated in the regions under the probe, over an FEM of the whole wall (about 400 curved quadratic tets) that carries the layer's stiffness elsewhere. Ours, not in the seed: the corrected meshfree variant (the seed's softens and loses monotony past 3 mm), the elements under the layer, the proxy sphere with the virtual coupling, the deviation mass (mass_scale = 10000) and the implicit FEM step (the seed's variant, layer and material: variant = \"seed\", inactive_layer = \"tied\", model = \"stvk\", docs/scenes.md)."

[model]
family = "hybrid"

[mesh]
builtin = "ellipsoids"
length_unit = "mm"
inner_semi_axes = [6.0, 6.0, 12.0]
outer_semi_axes = [10.0, 10.0, 16.0]
target_tets = 400       # the FEM of the whole wall (the seed's core had 188 linear tets)
order = 2

[material]
model = "stable-neo-hookean"    # as the LV scenes (the seed's St. Venant-Kirchhoff: model = "stvk")
lambda_pa = 5000.0
mu_pa = 2000.0
phi_pa_s = 0.09
psi_pa_s = 0.09
density_kg_per_m3 = 1060.0
mass_damping_per_s = 20.0

[boundary]
clamped = ["POLE"]      # the hybrid body clamps its core's bottom pole cap
touchable = ["OUTER"]   # the hybrid body's outer surface is the outer ellipsoid

[integrator]
tick_s = 0.001

[hybrid]
variant = "corrected"
spacing_m = 0.0005
smoothing_ratio = 1.0
core_fraction = 0.4
inactive_layer = "elements"
surface_target_tets = 8000
activation_radius_m = 0.0035
release_radius_m = 0.005
release_tolerance_m = 0.00002
max_active_particles = 2000
contact_stiffness_pa_per_m = 8.0e6 # probe-particle penalty per area (2 N/m a particle at 0.5 mm)
mass_scale = 10000.0
scaled_motion = "deviation"
core_step = "implicit"
core_stiffness_margin = 10.0
core_mass_scale = "auto"
safety_factor = 0.9
max_substeps = 64

[probe]
radius_m = 0.002
max_force_n = 10.0
"#;

/// The calibration tables and organ references of the built-in scenes, by file name (identical
/// copies beside the scenes in `deploy/scenes/`).
const CALIBRATIONS: [(&str, &str); 6] = [
    (
        "hemisphere-springs.calibration.csv",
        include_str!("calibrations/hemisphere-springs.calibration.csv"),
    ),
    (
        "hemisphere-springs.reference.csv",
        include_str!("calibrations/hemisphere-springs.reference.csv"),
    ),
    (
        "hemisphere-springs.organ.csv",
        include_str!("calibrations/hemisphere-springs.organ.csv"),
    ),
    (
        "lv-surface-springs.calibration.csv",
        include_str!("calibrations/lv-surface-springs.calibration.csv"),
    ),
    (
        "lv-surface-springs.reference.csv",
        include_str!("calibrations/lv-surface-springs.reference.csv"),
    ),
    (
        "lv-surface-springs.organ.csv",
        include_str!("calibrations/lv-surface-springs.organ.csv"),
    ),
];

/// The calibration table text of a built-in scene, by the file name its scene gives
/// (`mass_spring.calibration_file`), or `None`.
pub fn builtin_calibration(file: &str) -> Option<&'static str> {
    CALIBRATIONS.iter().find(|c| c.0 == file).map(|c| c.1)
}

/// Built-in scenes: (name, TOML text, one-line description).
const BUILTINS: [(&str, &str, &str); 6] = [
    (
        "lv",
        LV_TOML,
        "idealized left ventricle (Land et al. 2015 benchmark geometry), 474 quadratic tets (993 nodes; linear and up to 30k selectable), base clamped",
    ),
    (
        "ellipsoids",
        ELLIPSOIDS_TOML,
        "the seed's coarse Ellipsoids Model (~188 tets, Mero & Susin 2006 Table 1)",
    ),
    (
        "hemisphere-springs",
        HEMISPHERE_SPRINGS_TOML,
        "mass-spring hemisphere (Zhang, Payandeh & Dill Figure 12), one-ring Loop subdivision at the contact, calibrated springs",
    ),
    (
        "lv-surface-springs",
        LV_SURFACE_SPRINGS_TOML,
        "the LV epicardium as a mass-spring surface, one-ring Loop subdivision at the contact, calibrated springs",
    ),
    (
        "lv-hybrid",
        LV_HYBRID_TOML,
        "the seeds' hybrid model on the LV (stable neo-Hookean): quadratic FEM of the wall + ~53k meshfree particles simulated only under the probe",
    ),
    (
        "ellipsoids-hybrid",
        ELLIPSOIDS_HYBRID_TOML,
        "the seeds' Hybrid Model setting (Table 1) on ellipsoids, stable neo-Hookean: quadratic FEM of the wall + meshfree particle layer (corrected variant)",
    ),
];

/// Names and one-line descriptions of the built-in scenes, e.g. `("lv", "idealized left ...")`.
pub fn builtin_scene_names() -> &'static [(&'static str, &'static str)] {
    const NAMES: [(&str, &str); 6] = [
        (BUILTINS[0].0, BUILTINS[0].2),
        (BUILTINS[1].0, BUILTINS[1].2),
        (BUILTINS[2].0, BUILTINS[2].2),
        (BUILTINS[3].0, BUILTINS[3].2),
        (BUILTINS[4].0, BUILTINS[4].2),
        (BUILTINS[5].0, BUILTINS[5].2),
    ];
    &NAMES
}

/// The TOML text of the built-in scene `name`, or `None` if there is no such built-in. The same
/// texts are in `deploy/scenes/<name>.toml`.
pub fn builtin_scene_toml(name: &str) -> Option<&'static str> {
    BUILTINS.iter().find(|b| b.0 == name).map(|b| b.1)
}
