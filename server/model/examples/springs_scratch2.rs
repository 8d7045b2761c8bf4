//! Scratch (not committed): coarse against subdivided (eq. 5 area rule) at sphere depths.
use haptic_model::mass_spring::calibration::{ContactShape, LocalPatch, default_margin, surface_contact_rest};
use haptic_model::mass_spring::VertexRule;
use haptic_model::scene::load_scene_file;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let scene = load_scene_file(std::path::Path::new(&a[1])).unwrap();
    let ms = scene.mass_spring.as_ref().unwrap();
    let s = &ms.surface;
    let shape = ContactShape::Probe(scene.probe);
    let cr = surface_contact_rest(s, shape);
    let rings: u32 = a[3].parse().unwrap();
    let (kh, km) = (ms.params.home_spring_n_per_m, ms.params.mesh_spring_n_per_m);
    for node in a[2].split(',').map(|s| s.parse::<u32>().unwrap()) {
        let t = std::time::Instant::now();
        let mut p = LocalPatch::with_contact(s, node, rings, default_margin(s, node, shape), VertexRule::Keep, shape, (kh, km), cr.as_ref()).unwrap();
        let (n, n2) = p.area_node_counts();
        let mut xc = p.coarse_rest();
        let mut xf = p.fine_rest();
        let mut out = Vec::new();
        for d in [0.1, 0.25, 0.5, 1.0, 2.0, 3.0, 4.0] {
            let fc = p.coarse_press_sphere_depth(d * 1e-3, &mut xc).unwrap();
            let (ff, _) = p.fine_press_sphere_depth((kh * n as f64 / n2 as f64, km), d * 1e-3, &mut xf).unwrap();
            let (fu, _) = { let mut xu = p.fine_rest(); p.fine_press_sphere_depth((kh, km), d * 1e-3, &mut xu).unwrap() };
            out.push(format!("{d}: {:.3} mN area {:+.1} % unchanged {:+.1} %", fc * 1e3, 100.0 * (ff / fc - 1.0), 100.0 * (fu / fc - 1.0)));
        }
        println!("node {node} (N {n}, N' {n2}, {:.1} s): {}", t.elapsed().as_secs_f64(), out.join(" | "));
    }
}
