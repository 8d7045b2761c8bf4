//! Scratch (not committed): ripple between nodes, analytic depth zero (lv ellipsoid or sphere).
use haptic_model::DVec3;
use haptic_model::press::{self, HoldParams, PressLine};
use haptic_model::scene::load_scene_file;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let scene = load_scene_file(std::path::Path::new(&a[1])).unwrap();
    let p: Vec<f64> = a[2].split(',').map(|s| s.parse().unwrap()).collect();
    let depths: Vec<f64> = a[3].split(',').map(|s| s.parse::<f64>().unwrap() * 1e-3).collect();
    let semi = if a.len() > 4 { DVec3::splat(a[4].parse::<f64>().unwrap() * 1e-3) } else { DVec3::new(10e-3, 10e-3, 20e-3) };
    let p = DVec3::new(p[0], p[1], p[2]) * 1e-3;
    let ms = scene.mass_spring.as_ref().unwrap();
    let s = &ms.surface;
    let c = (0..s.node_count() as u32)
        .min_by(|&i, &j| (s.rest()[i as usize] - p).length().total_cmp(&(s.rest()[j as usize] - p).length()))
        .unwrap();
    let nb = s.neighbours(c)[0];
    let t = s.triangles_at(c)[0];
    let tri = s.triangles()[t as usize];
    let r = scene.probe.radius_m;
    let places = [
        ("node", s.rest()[c as usize]),
        ("edge", (s.rest()[c as usize] + s.rest()[nb as usize]) * 0.5),
        ("centroid", tri.iter().map(|&i| s.rest()[i as usize]).sum::<DVec3>() / 3.0),
    ];
    println!("node {c} at {:?} mm, L {:.3} mm", s.rest()[c as usize] * 1e3, s.element_size_m(c) * 1e3);
    let params = HoldParams { ramp_s: 0.3, hold_s: 0.5, average_s: 0.2 };
    let mut base: Vec<f64> = Vec::new();
    for (name, q) in places {
        let mut body = haptic_model::build_body(&scene).unwrap();
        let k = 1.0 / ((q / semi).length());
        let pe = q * k;
        let ne = (pe / (semi * semi)).normalize();
        let line = PressLine::at_surface_point(pe, -ne, r);
        let (holds, _) = press::staircase(body.as_mut(), &line, &depths, &params, 1e-3).unwrap();
        let f: Vec<f64> = holds.iter().map(|h| h.force_n).collect();
        if base.is_empty() { base = f.clone(); }
        println!("{name:>8}: {}", f.iter().zip(&base).zip(&holds).map(|((f, b), h)| format!("{:.3} mN s {:.3} ({:+.1} %)", f * 1e3, h.sphere_depth_m * 1e3, 100.0 * (f / b - 1.0))).collect::<Vec<_>>().join(" | "));
    }
}
