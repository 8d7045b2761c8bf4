//! The static indentation solver on a quadratic Hertz block: how fast `haptic_model::indent`
//! is and how close its force and contact radius are to Hertz's (docs/decisions.md, "The
//! indentation solver: exact node contact by a semismooth Newton"). Prints only.
//!
//! The block is the quarter of `server/model/tests/hertz.rs` (7R x 7R x 7R, symmetry rollers on
//! x = 0 and y = 0, base clamped; R = 2 mm, E = 10 kPa, nu = 0.3, StVK) on a coarser tensor
//! grid (cells of R/30 under the sphere growing by 1.6: 19 x 19 x 13 vertices) with 10-node
//! tetrahedra: 34 225 nodes, 96 792 free equations. Hertz: `F = 4/3 E/(1 - nu^2) R^1/2
//! d^3/2`, `a = (R d)^1/2` (K. L. Johnson, *Contact Mechanics*, 1985, eq. 4.22-4.23).
//!
//! Run: `cargo run --release -p haptic-model --example hertz_block` (six depths 0.04 to 0.2
//! mm); `-- --depths 0.04,0.1` for others; `-- --write-msh FILE` also writes the linear block
//! as a Gmsh 2.2 file (mm; physical groups XMIN, YMIN, ZMIN, ZMAX, BLOCK) for other codes.

use std::io::Write as _;
use std::time::Instant;

use clap::Parser;
use haptic_model::DVec3;
use haptic_model::element::FemModel;
use haptic_model::indent::{IndentParams, Indentation, Indenter};
use haptic_model::material::MaterialParams;
use haptic_model::mesh::TetMesh;
use haptic_model::mesh::generate::{box_mesh_graded, graded_coordinates};

const R: f64 = 2e-3;
const E: f64 = 10e3;
const NU: f64 = 0.3;

/// The quadratic Hertz block against Hertz's solution.
#[derive(Debug, Parser)]
struct Args {
    /// Depths, mm, increasing.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0.04,0.072,0.104,0.136,0.168,0.2"
    )]
    depths: Vec<f64>,
    /// Fine cell size as a fraction of R.
    #[arg(long, default_value_t = 1.0 / 30.0)]
    fine: f64,
    /// Growth of the cells away from the contact.
    #[arg(long, default_value_t = 1.6)]
    ratio: f64,
    /// Linear (4-node) elements instead of quadratic ones.
    #[arg(long)]
    linear: bool,
    /// Split every cell of the graded grid into this many along each axis (a nested
    /// family for self-convergence: the sizes scale by 1/k everywhere).
    #[arg(long, default_value_t = 1)]
    subdivide: usize,
    /// Material model by scene name (stvk, corotational, stable-neo-hookean).
    #[arg(long, default_value = "stvk")]
    material: String,
    /// Write the linear block as a Gmsh 2.2 file (mm) and exit.
    #[arg(long)]
    write_msh: Option<std::path::PathBuf>,
}

/// The linear quarter block (m), every cell split `k` times along each axis.
fn block(fine: f64, ratio: f64, k: usize) -> TetMesh {
    let size = 7.0 * R;
    let split = |xs: Vec<f64>| -> Vec<f64> {
        let mut out = vec![xs[0]];
        for w in xs.windows(2) {
            for j in 1..=k {
                out.push(w[0] + (w[1] - w[0]) * j as f64 / k as f64);
            }
        }
        out
    };
    let lateral = split(graded_coordinates(fine * R, 0.3 * R, ratio, size));
    let depth: Vec<f64> = split(graded_coordinates(fine * R, 0.1 * R, ratio, size))
        .iter()
        .rev()
        .map(|z| -z)
        .collect();
    box_mesh_graded(&lateral, &lateral, &depth)
}

fn write_msh(mesh: &TetMesh, path: &std::path::Path) -> std::io::Result<()> {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    let groups = ["XMIN", "YMIN", "ZMIN", "ZMAX"];
    writeln!(f, "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$PhysicalNames")?;
    writeln!(f, "{}", groups.len() + 1)?;
    for (k, g) in groups.iter().enumerate() {
        writeln!(f, "2 {} \"{g}\"", k + 1)?;
    }
    writeln!(
        f,
        "3 10 \"BLOCK\"\n$EndPhysicalNames\n$Nodes\n{}",
        mesh.nodes.len()
    )?;
    for (i, p) in mesh.nodes.iter().enumerate() {
        writeln!(f, "{} {} {} {}", i + 1, p.x * 1e3, p.y * 1e3, p.z * 1e3)?;
    }
    let tris: Vec<(usize, [u32; 3])> = groups
        .iter()
        .enumerate()
        .flat_map(|(k, g)| {
            let s = mesh.surface(g).expect("a box face");
            s.triangles.iter().map(move |t| (k + 1, *t))
        })
        .collect();
    writeln!(f, "$EndNodes\n$Elements\n{}", tris.len() + mesh.tets.len())?;
    let mut id = 1;
    for (tag, t) in &tris {
        writeln!(
            f,
            "{id} 2 2 {tag} {tag} {} {} {}",
            t[0] + 1,
            t[1] + 1,
            t[2] + 1
        )?;
        id += 1;
    }
    for t in &mesh.tets {
        writeln!(
            f,
            "{id} 4 2 10 10 {} {} {} {}",
            t[0] + 1,
            t[1] + 1,
            t[2] + 1,
            t[3] + 1
        )?;
        id += 1;
    }
    writeln!(f, "$EndElements")
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let linear = block(args.fine, args.ratio, args.subdivide.max(1));
    if let Some(path) = &args.write_msh {
        write_msh(&linear, path)?;
        println!(
            "wrote {} ({} vertices, {} tets)",
            path.display(),
            linear.nodes.len(),
            linear.tets.len()
        );
        return Ok(());
    }
    let vertices = linear.nodes.len();
    let mesh = if args.linear {
        linear
    } else {
        linear.to_quadratic()
    };
    let size = 7.0 * R;
    let mut material = MaterialParams::from_youngs(E, NU, 1000.0);
    material.model = haptic_model::material::MaterialModel::from_scene_name(&args.material)
        .ok_or_else(|| anyhow::anyhow!("unknown material {:?}", args.material))?;
    let mut fem = FemModel::new(&mesh, material)?;
    for (i, p) in mesh.nodes.iter().enumerate() {
        let mut mask = 0u8;
        if p.x == 0.0 {
            mask |= 1;
        }
        if p.y == 0.0 {
            mask |= 2;
        }
        if p.z == -size {
            mask = 7;
        }
        if mask != 0 {
            fem.set_constraint(i, mask);
        }
    }
    let free = 3 * mesh.nodes.len()
        - fem
            .constraints()
            .iter()
            .map(|m| m.count_ones() as usize)
            .sum::<usize>();
    println!(
        "Hertz block: {vertices} vertices, {} nodes, {} tets ({}), {free} free equations",
        mesh.nodes.len(),
        mesh.tets.len(),
        if args.linear { "linear" } else { "quadratic" }
    );
    let top = mesh
        .surface("ZMAX")
        .expect("the top face")
        .triangles
        .clone();
    let indenter = Indenter {
        radius_m: R,
        from_m: DVec3::new(0.0, 0.0, 1.5 * R),
        direction: DVec3::new(0.0, 0.0, -1.0),
    };
    let t = Instant::now();
    let mut run = Indentation::new(&fem, &top, &indenter, &IndentParams::default())?;
    println!("set-up {:.2} s", t.elapsed().as_secs_f64());
    let e_star = E / (1.0 - NU * NU);
    println!(
        "| d/R | F, N | F / Hertz - 1 | a / Hertz - 1 | nodes in contact | Newton | factorisations | CG iterations | s |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut last = t.elapsed().as_secs_f64();
    for &d_mm in &args.depths {
        let d = d_mm * 1e-3;
        let p = run.solve(d)?;
        let now = t.elapsed().as_secs_f64();
        let f = 4.0 * p.force_on_sphere_n.z;
        let f_hertz = 4.0 / 3.0 * e_star * R.sqrt() * d.powf(1.5);
        let a = (4.0 * p.contact_area_m2 / std::f64::consts::PI).sqrt();
        let a_hertz = (R * d).sqrt();
        println!(
            "| {:.3} | {f:.5e} | {:+.2} % | {:+.1} % | {} | {} | {} | {} | {:.1} |",
            d / R,
            100.0 * (f / f_hertz - 1.0),
            100.0 * (a / a_hertz - 1.0),
            p.nodes_in_contact,
            p.newton_iterations,
            p.linear.factorizations,
            p.linear.iterations,
            now - last
        );
        last = now;
    }
    println!("total {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}
