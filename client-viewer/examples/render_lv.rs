//! Renders a synthetic left ventricle (a truncated prolate ellipsoid, long axis z, apex at -z)
//! with a probe pressing a dent into its side, using only the `raster` module.
//!
//! `cargo run -p haptic-client --example render_lv -- /tmp/lv_sample.png`

use glam::DVec3;
use haptic_client::raster::{
    Camera, ProbeView, RenderParams, SurfaceView, bounding_box, render_surface,
};

fn main() -> anyhow::Result<()> {
    let out = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "lv_sample.png".into());
    // Ellipsoid radii 25 mm (x, y) and 45 mm (z), cut at z = +20 mm (the base).
    let (nu, nv) = (48usize, 24usize);
    let (a, c) = (0.025f32, 0.045f32);
    let sweep = std::f32::consts::PI - (0.020f32 / c).acos(); // apex (-z) to base (z = +20 mm)
    let mut rest = Vec::new();
    for j in 0..=nv {
        let th = std::f32::consts::PI - sweep * j as f32 / nv as f32;
        for i in 0..nu {
            let ph = std::f32::consts::TAU * i as f32 / nu as f32;
            rest.extend([
                a * th.sin() * ph.cos(),
                a * th.sin() * ph.sin(),
                c * th.cos(),
            ]);
        }
    }
    let mut tris = Vec::new();
    for j in 0..nv as u32 {
        for i in 0..nu as u32 {
            let (i1, n) = ((i + 1) % nu as u32, nu as u32);
            let (p, q, r, s) = (j * n + i, j * n + i1, (j + 1) * n + i, (j + 1) * n + i1);
            tris.extend([p, q, s, p, s, r]);
        }
    }
    // A dent of up to 4 mm around the point facing +x+y at mid height.
    let centre = [0.0177f32, 0.0177, -0.005];
    let mut pos = rest.clone();
    for v in pos.chunks_exact_mut(3) {
        let d2 =
            (v[0] - centre[0]).powi(2) + (v[1] - centre[1]).powi(2) + (v[2] - centre[2]).powi(2);
        let w = 0.004 * (-d2 / (2.0 * 0.008f32.powi(2))).exp();
        let r = (v[0] * v[0] + v[1] * v[1]).sqrt().max(1e-9);
        v[0] -= w * v[0] / r;
        v[1] -= w * v[1] / r;
    }
    let params = RenderParams::default();
    let (min, max) = bounding_box(&rest).expect("points");
    let cam = Camera::auto_frame(min, max, &params);
    let probe = ProbeView {
        position_m: DVec3::new(0.0177 - 0.0028 + 0.0035, 0.0177 - 0.0028 + 0.0035, -0.005),
        radius_m: 0.004,
        force_n: DVec3::new(0.9, 0.9, 0.0),
        in_contact: true,
    };
    let view = SurfaceView {
        rest_m: &rest,
        positions_m: &pos,
        triangles: &tris,
        probe: Some(probe),
    };
    render_surface(&view, &cam, &params).write_png(std::path::Path::new(&out))?;
    eprintln!("wrote {out}");
    Ok(())
}
