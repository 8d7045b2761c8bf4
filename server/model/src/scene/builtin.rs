//! The built-in scenes: TOML texts compiled into the library (it reads no file outside
//! itself); identical copies live in `deploy/scenes/` for users to edit, and a test checks that
//! they agree.

/// Built-in scene `lv`: the idealized left ventricle built in code.
const LV_TOML: &str = r#"# Built-in scene "lv" (a copy of the constant in server/model/src/scene/builtin.rs).
name = "lv"
description = "Idealized left ventricle (geometry of the Land et al. 2015 cardiac mechanics benchmark, Proc. R. Soc. A 471:20150641: endocardium 7x7x17 mm, epicardium 10x10x20 mm, cut at z = 5 mm), meshed in code, base clamped, epicardium touchable. Material: mu = 5 kPa from the linearised Guccione law of benchmark problem 2 (C = 10 kPa, b_f = b_t = b_fs = 1, so mu = C/2), Poisson ratio 0.45 as a compressible stand-in for the benchmark's incompressibility, hence E = 14.5 kPa; rho = 1060 kg/m^3."

[mesh]
builtin = "lv"
target_tets = 500       # 474 tets (993 nodes with order 2); 1000..=30000 land within about 30 % of the target
order = 2               # quadratic 10-node tets, mid-edge nodes on the ellipsoids (1: linear)
length_unit = "mm"      # unit for reports; the built-in geometry is fixed

[material]
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
kind = "symplectic-euler"       # on this mesh the seed's semi-implicit scheme (eq. 34) reads forces up to 27 % high
tick_s = 0.001
substeps = "auto"
max_substeps = 64
safety_factor = 0.9             # 12 sub-steps; presses to 8 mm stay stable (StVK stiffens little: the wall bends)

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

/// Built-in scenes: (name, TOML text, one-line description).
const BUILTINS: [(&str, &str, &str); 2] = [
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
];

/// Names and one-line descriptions of the built-in scenes, e.g. `("lv", "idealized left ...")`.
pub fn builtin_scene_names() -> &'static [(&'static str, &'static str)] {
    const NAMES: [(&str, &str); 2] = [
        (BUILTINS[0].0, BUILTINS[0].2),
        (BUILTINS[1].0, BUILTINS[1].2),
    ];
    &NAMES
}

/// The TOML text of the built-in scene `name`, or `None` if there is no such built-in. The same
/// texts are in `deploy/scenes/<name>.toml`.
pub fn builtin_scene_toml(name: &str) -> Option<&'static str> {
    BUILTINS.iter().find(|b| b.0 == name).map(|b| b.1)
}
