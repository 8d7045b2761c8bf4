//! Computes the probe's local contact law ([`haptic_model::contact::local_law`]): a rigid sphere
//! pressed into a half-space of each material at each Poisson ratio
//! ([`haptic_model::contact::half_space::indent_half_space`], axisymmetric, exact contact),
//! written as the dimensionless table the crate compiles in
//! (`server/model/src/contact/half_space_law.csv`: `F / (E a^2)` against `d / a`; the law
//! scales with Young's modulus `E` and the sphere radius `a`). A depth that does not converge
//! ends that material's rows (St. Venant-Kirchhoff has no equilibrium past about `d / a = 0.25`
//! at nu = 0.45), and the log says so.
//!
//! Run (about 2 minutes per material and Poisson ratio here; rows go to stdout):
//! `cargo run --release -p haptic-model --example half_space_law -- --nu 0.45 > rows.csv`

use clap::Parser;
use haptic_model::contact::half_space::{HalfSpaceParams, indent_half_space};
use haptic_model::material::{MaterialModel, MaterialParams};

/// Tabulates the sphere-on-half-space law (prints CSV rows).
#[derive(Debug, Parser)]
#[command(name = "half_space_law")]
struct Args {
    /// Material models (scene names).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "stvk,corotational,stable-neo-hookean"
    )]
    models: Vec<String>,
    /// Poisson ratios.
    #[arg(long, value_delimiter = ',', default_value = "0.45")]
    nu: Vec<f64>,
    /// Fine cell size, in sphere radii.
    #[arg(long, default_value_t = HalfSpaceParams::default().fine_cell)]
    fine_cell: f64,
    /// Deepest depth, in sphere radii.
    #[arg(long, default_value_t = 1.0)]
    max_depth: f64,
    /// Print the header line.
    #[arg(long)]
    header: bool,
}

/// Depths of the table, in sphere radii: dense where the law bends away from Hertz's.
fn depths(max: f64) -> Vec<f64> {
    let mut d = vec![0.005, 0.01, 0.02, 0.03, 0.05, 0.075];
    let mut x = 0.1;
    while x <= max + 1e-9 {
        d.push(x);
        x += 0.025;
    }
    d
}

fn main() {
    let args = Args::parse();
    // The law is dimensionless: any modulus and radius give the same table.
    let (e, a) = (1.0e4, 1.0e-3);
    let params = HalfSpaceParams {
        fine_cell: args.fine_cell,
        ..HalfSpaceParams::default()
    };
    if args.header {
        println!("model,poisson_ratio,depth_ratio,force_ratio,contact_radius_ratio");
    }
    for name in &args.models {
        let Some(model) = MaterialModel::from_scene_name(name) else {
            eprintln!("unknown material model {name}");
            std::process::exit(2);
        };
        for &nu in &args.nu {
            let mut mat = MaterialParams::from_youngs(e, nu, 1000.0);
            mat.model = model;
            let ds: Vec<f64> = depths(args.max_depth).iter().map(|r| r * a).collect();
            let t = std::time::Instant::now();
            let result = indent_half_space(&mat, a, &ds, &params, &mut |p| {
                println!(
                    "{},{},{:.6},{:.8e},{:.6}",
                    model.scene_name(),
                    nu,
                    p.depth_m / a,
                    p.force_n / (e * a * a),
                    p.contact_radius_m / a
                );
            });
            match result {
                Ok(_) => eprintln!(
                    "{} nu {nu}: to d/a {} in {:.0} s",
                    model.scene_name(),
                    args.max_depth,
                    t.elapsed().as_secs_f64()
                ),
                Err(err) => eprintln!(
                    "{} nu {nu}: stopped after {:.0} s: {err}",
                    model.scene_name(),
                    t.elapsed().as_secs_f64()
                ),
            }
        }
    }
}
