//! The LV probe press, shared by the `precision` benchmark (`lv-probe`, `lv-h1`) and the
//! `lv_study` example: the probe centre moves along -x at z = -5 mm into the epicardium of an
//! LV scene ([`super::lv_scene_on`]) to the depths of [`DEPTHS_MM`], statically
//! ([`probe_static_at`]: equilibrium with the probe coupling per depth) or dynamically
//! ([`probe_dynamic`]: `FemBody::tick` through a staircase of ramps and holds).

use std::time::Instant;

use haptic_model::DVec3;
use haptic_model::body::SoftBody;
use haptic_model::contact::{ContactModel, Probe};
use haptic_model::element::FemModel;
use haptic_model::fem::{FemBody, TickInput};
use haptic_model::scene::Scene;
use haptic_model::statics::{StaticParams, solve_static};

use super::{TickTimes, device_at, smoothstep, smoothstep_rate};

/// Probe depths of the press, mm below first contact.
pub const DEPTHS_MM: [f64; 6] = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0];

/// Quasi-static probe solution on one mesh: device force per depth and the positions at the
/// last depth.
#[derive(Debug, Clone)]
pub struct ProbeCurve {
    /// Device force per depth, N.
    pub forces_n: Vec<f64>,
    /// Positions at the last depth, m.
    pub x_last: Vec<DVec3>,
    /// The body's surface at the end of each depth's hold (dynamic runs; empty otherwise).
    pub surfaces: Vec<SurfaceSnapshot>,
}

/// A body's surface at one instant: rest and current vertex positions (m) and its triangles
/// (read together: a subdividing surface changes its topology).
#[derive(Debug, Clone, Default)]
pub struct SurfaceSnapshot {
    pub rest: Vec<DVec3>,
    pub x: Vec<DVec3>,
    pub triangles: Vec<[u32; 3]>,
}

impl SurfaceSnapshot {
    /// The surface of `body` now.
    pub fn of(body: &dyn SoftBody) -> Self {
        let topology = body.surface_topology();
        let n = topology.vertex_count;
        let triangles = topology.triangles.to_vec();
        let mut buf = vec![0f32; 3 * n];
        let to_vec = |b: &[f32]| -> Vec<DVec3> {
            b.chunks_exact(3)
                .map(|c| DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64))
                .collect()
        };
        body.write_surface_rest_positions(&mut buf);
        let rest = to_vec(&buf);
        body.write_surface_positions(&mut buf);
        Self {
            rest,
            x: to_vec(&buf),
            triangles,
        }
    }
}

/// Largest number of patch passes of [`probe_static_at`] per depth; more is an error.
const MAX_PATCH_ITERATIONS: usize = 30;

/// Relative force change between patch passes at which [`probe_static_at`] has converged.
const PATCH_ITERATION_TOLERANCE: f64 = 3e-4;

/// Static equilibrium with the kernel patch's probe coupling at each depth of `depths_mm`
/// (mm, increasing; `lv_study static`): for a trial coupling force `F`, the patch load `-F w_i n` (patch, weights, normal of the probe at the
/// current positions) is applied and the body solved statically; the probe then reports the
/// coupling force `k (r - s)` at the new positions. A bracketed regula falsi (Illinois) on `F`
/// makes the two agree; the patch is then refreshed until the force changes by less than
/// [`PATCH_ITERATION_TOLERANCE`]. With `debug`, prints the force of every patch iteration.
/// Returns `Err` if the bracket or the patch iteration fails (at most
/// [`MAX_PATCH_ITERATIONS`] passes: no silent cap). A trial force under which Newton finds no
/// equilibrium counts as too large (a dead load past the wall's limit point).
pub fn probe_static_at(
    scene: &Scene,
    depths_mm: &[f64],
    debug: bool,
) -> Result<ProbeCurve, String> {
    let mut fem = FemModel::with_smoothing(&scene.mesh, scene.material, scene.strain_smoothing)
        .map_err(|e| e.to_string())?;
    fem.clamp_nodes(&scene.clamped_nodes);
    // The patch model's equilibrium (the surface-displacement reference), whatever the scene
    // says.
    let params = haptic_model::contact::ProbeParams {
        contact: ContactModel::Patch,
        ..scene.probe
    };
    let mut probe = Probe::new(params, scene.touchable.clone(), fem.rest());
    let n = fem.node_count();
    let mut x = fem.rest().to_vec();
    let params = StaticParams {
        rel_tol: 1e-8,
        ..StaticParams::default()
    };
    let mut forces = Vec::new();
    let mut f_prev = 0.0;
    // The last in-contact patch (nodes, weights) and normal: a trial force that pushes the
    // surface beyond the probe still needs a patch to act on.
    let mut patch: Vec<(u32, f64)> = Vec::new();
    let mut normal = DVec3::ZERO;
    let (kc, r) = (scene.probe.coupling_stiffness_n_per_m, scene.probe.radius_m);
    for (k, d) in depths_mm.iter().enumerate() {
        let device = device_at(d * 1e-3);
        let mut f = if k == 0 {
            0.005 * d / DEPTHS_MM[0]
        } else {
            f_prev * (d / depths_mm[k - 1])
        };
        // Outer: freeze the probe patch (nodes, weights, normal) at the current positions; inner:
        // find the force F whose patch load puts the body where the frozen patch plane gives
        // k (r - s) = F. Repeat until the patch stops changing the force.
        for outer in 0..=MAX_PATCH_ITERATIONS {
            let st = probe.update(&x, device, DVec3::ZERO);
            if st.in_contact {
                let (nodes, w) = probe.patch();
                patch.clear();
                patch.extend(nodes.iter().copied().zip(w.iter().copied()));
                normal = st.normal;
            }
            if patch.is_empty() {
                return Err(format!("no contact at depth {d} mm"));
            }
            let mut f_ext = vec![DVec3::ZERO; n];
            let mut g = |f: f64, x: &mut Vec<DVec3>| -> Result<f64, String> {
                f_ext.iter_mut().for_each(|v| *v = DVec3::ZERO);
                let mut centre = DVec3::ZERO;
                for &(i, w) in &patch {
                    f_ext[i as usize] = -normal * (f * w);
                }
                let backup = x.clone();
                if solve_static(&fem, &f_ext, x, &params).is_err() {
                    // No equilibrium under this patch load (the wall gives way under a dead
                    // load): the trial force is too large.
                    x.copy_from_slice(&backup);
                    return Ok(f);
                }
                for &(i, w) in &patch {
                    centre += x[i as usize] * w;
                }
                let phi = (kc * (r - (device - centre).dot(normal))).max(0.0);
                Ok(f - phi)
            };
            let fi = bracketed_root(f, *d, |t| g(t, &mut x))?;
            let change = (fi - f).abs() / fi;
            f = fi;
            if debug {
                eprintln!("depth {d} mm outer {outer}: F = {f:.6e} N, change {change:.2e}");
            }
            if outer > 0 && change < PATCH_ITERATION_TOLERANCE {
                break;
            }
            if outer == MAX_PATCH_ITERATIONS {
                return Err(format!(
                    "lv-probe static: the patch iteration at depth {d} mm did not converge in {MAX_PATCH_ITERATIONS} passes (last change {change:.2e}, tolerance {PATCH_ITERATION_TOLERANCE:.0e})"
                ));
            }
        }
        f_prev = f;
        forces.push(f);
    }
    Ok(ProbeCurve {
        forces_n: forces,
        x_last: x,
        surfaces: Vec::new(),
    })
}

/// The root of `g(F) = F - k (r - s(F))`, which increases with `F`, from the guess `f` (N) at
/// depth `d` (mm): a bracket grown by 1.25, then Illinois (at most 80 iterations, to 1e-8
/// relative or a 1e-10 relative bracket).
fn bracketed_root(
    f: f64,
    d: f64,
    mut g: impl FnMut(f64) -> Result<f64, String>,
) -> Result<f64, String> {
    let (mut lo, mut hi) = (f / 1.1, f * 1.1);
    let mut glo = g(lo)?;
    while glo > 0.0 {
        hi = lo;
        lo /= 1.25;
        glo = g(lo)?;
    }
    let mut ghi = g(hi)?;
    while ghi < 0.0 {
        (lo, glo) = (hi, ghi);
        hi *= 1.25;
        ghi = g(hi)?;
        if hi > 100.0 {
            return Err(format!("no bracket at depth {d} mm"));
        }
    }
    let mut side = 0i8;
    let mut fi = hi;
    for it in 0..=80 {
        if it == 80 {
            return Err(format!("no convergence at depth {d} mm: F in [{lo}, {hi}]"));
        }
        fi = (lo * ghi - hi * glo) / (ghi - glo);
        let gf = g(fi)?;
        if gf.abs() <= 1e-8 * fi.max(1e-3) || (hi - lo) <= 1e-10 * hi {
            break;
        }
        if gf < 0.0 {
            (lo, glo) = (fi, gf);
            if side == -1 {
                ghi *= 0.5;
            }
            side = -1;
        } else {
            (hi, ghi) = (fi, gf);
            if side == 1 {
                glo *= 0.5;
            }
            side = 1;
        }
    }
    Ok(fi)
}

/// Half-width of the bracket of sphere depths [`probe_sphere_at`] solves at below each device
/// depth, m: the device sits `F / k` beyond the sphere, at most 0.2 mm for forces to 60 mN
/// with the lv coupling (300 N/m).
pub const SPHERE_BRACKET_M: f64 = 2e-4;

/// The probe press with a rigid sphere in place of the kernel patch: static indentation
/// ([`haptic_model::indent`], augmented Lagrangian, converged at every depth or an error) of
/// the scene's touchable surface by its probe sphere moving along -x at z = -5 mm, reported at
/// each device depth `D` of `depths_mm` (mm below [`super::CONTACT_X_M`], the same frame as
/// [`probe_dynamic`]). The device pulls the sphere through the virtual coupling, so the sphere
/// centre sits at the depth `s` with `s + F(s) / k = D`: the sphere is solved at `D -`
/// [`SPHERE_BRACKET_M`] and at `D`, and `s` and the force found by linear interpolation in that
/// bracket (the curve's curvature over 0.2 mm changes the force by well under 0.1 %); the
/// positions at the last depth are interpolated the same way. Returns `Err` when a depth does
/// not converge or the coupling puts the sphere outside its bracket.
pub fn probe_sphere_at(scene: &Scene, depths_mm: &[f64]) -> Result<ProbeCurve, String> {
    use haptic_model::indent::{IndentParams, Indenter, contact_distance, indent};
    let fem = scene.fem_model().map_err(|e| e.to_string())?;
    let params = IndentParams::default();
    let indenter = Indenter {
        radius_m: scene.probe.radius_m,
        from_m: device_at(-1e-3),
        direction: DVec3::new(-1.0, 0.0, 0.0),
    };
    let t0 =
        contact_distance(&fem, &scene.touchable, &indenter, &params).map_err(|e| e.to_string())?;
    // Sphere depth s (below CONTACT_X_M) = indent depth - offset.
    let offset = 1e-3 - t0;
    let mut sphere_depths = Vec::new();
    for &d in depths_mm {
        let d = d * 1e-3;
        for s in [d - SPHERE_BRACKET_M, d] {
            sphere_depths.push((s + offset).max(0.0));
        }
    }
    let started = std::time::Instant::now();
    let points = indent(
        &fem,
        &scene.touchable,
        &indenter,
        &sphere_depths,
        &params,
        // Progress: a refined mesh takes minutes per depth.
        &mut |p| {
            eprintln!(
                "    sphere depth {:.3} mm: |F| {:.4e} N, {} multiplier updates, {} Newton iterations, {:.1} s",
                (p.depth_m - offset) * 1e3,
                p.force_on_sphere_n.length(),
                p.augmentations,
                p.newton_iterations,
                started.elapsed().as_secs_f64()
            )
        },
    )
    .map_err(|e| e.to_string())?;
    let kc = scene.probe.coupling_stiffness_n_per_m;
    let mut forces = Vec::new();
    let mut x_last = Vec::new();
    for (k, &d) in depths_mm.iter().enumerate() {
        let d = d * 1e-3;
        let (lo, hi) = (&points[2 * k], &points[2 * k + 1]);
        // The force along the press (+x on the sphere) and the device depth at each end.
        let (f_lo, f_hi) = (lo.force_on_sphere_n.x, hi.force_on_sphere_n.x);
        let (s_lo, s_hi) = (lo.depth_m - offset, hi.depth_m - offset);
        let (dev_lo, dev_hi) = (s_lo + f_lo / kc, s_hi + f_hi / kc);
        if !(dev_lo <= d && d <= dev_hi) {
            return Err(format!(
                "device depth {:.3} mm: the coupled sphere is outside the bracket [{:.3}, {:.3}] \
                 mm of sphere depths (device depths {:.3} to {:.3} mm)",
                d * 1e3,
                s_lo * 1e3,
                s_hi * 1e3,
                dev_lo * 1e3,
                dev_hi * 1e3
            ));
        }
        let t = (d - dev_lo) / (dev_hi - dev_lo);
        // Reported like the dynamic runs: the magnitude of the device force.
        let (m_lo, m_hi) = (lo.force_on_sphere_n.length(), hi.force_on_sphere_n.length());
        forces.push(m_lo + t * (m_hi - m_lo));
        if k + 1 == depths_mm.len() {
            x_last = lo
                .x_m
                .iter()
                .zip(&hi.x_m)
                .map(|(a, b)| *a + (*b - *a) * t)
                .collect();
        }
    }
    Ok(ProbeCurve {
        forces_n: forces,
        x_last,
        surfaces: Vec::new(),
    })
}

/// A value extrapolated from three meshes by Richardson.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Extrapolated {
    /// The extrapolated value (the finest mesh's when the convergence is not monotone).
    pub value: f64,
    /// Error estimate of `value`: Roache's grid convergence index, 1.25 `|value - finest|`,
    /// with monotone convergence; otherwise the largest distance of a mesh's value from the
    /// finest one's.
    pub uncertainty: f64,
    /// Observed order of convergence in the mesh size, if monotone.
    pub order: Option<f64>,
}

/// Richardson extrapolation of `f = f* + C h^p` through three meshes of sizes `h` (decreasing:
/// coarse to fine, any ratios) with values `f`: the order `p` solves `(f3 - f2) / (f2 - f1) =
/// (h3^p - h2^p) / (h2^p - h1^p)` by bisection on [0.3, 8]. Convergence that is not monotone
/// (the differences change sign or grow) or an order outside that range gives the finest
/// value with the spread of the three as its uncertainty.
pub fn richardson(h: [f64; 3], f: [f64; 3]) -> Extrapolated {
    let spread = f.iter().map(|v| (v - f[2]).abs()).fold(0.0, f64::max);
    let fallback = Extrapolated {
        value: f[2],
        uncertainty: spread,
        order: None,
    };
    let (e21, e32) = (f[1] - f[0], f[2] - f[1]);
    if e21 == 0.0 || e32 / e21 <= 0.0 || e32.abs() >= e21.abs() {
        return fallback;
    }
    let target = e32 / e21;
    let g = |p: f64| (h[2].powf(p) - h[1].powf(p)) / (h[1].powf(p) - h[0].powf(p)) - target;
    let (mut lo, mut hi) = (0.3, 8.0);
    if g(lo).signum() == g(hi).signum() {
        return fallback;
    }
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if g(mid).signum() == g(lo).signum() {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let p = 0.5 * (lo + hi);
    let c = e32 / (h[2].powf(p) - h[1].powf(p));
    let value = f[2] - c * h[2].powf(p);
    Extrapolated {
        value,
        uncertainty: 1.25 * (value - f[2]).abs(),
        order: Some(p),
    }
}

/// The dynamic press protocol with `FemBody::tick`: the probe centre moves along -x from
/// 0.3 mm clear of contact to each depth of [`DEPTHS_MM`], a smoothstep ramp then a hold
/// (100 ms each, 80 ms with `quick`); the force per depth is the mean device force over the
/// second half of the hold. Returns the curve, the tick times and the sub-steps per tick, or
/// the error that stopped it (refused plan or divergence).
///
/// The probe uses the scene's contact model (`auto`: the patch with the sphere's Hertz
/// compliance); the forces are compared with the converged sphere reference
/// (`lv_probe::sphere_reference`).
pub fn probe_dynamic(scene: &Scene, quick: bool) -> Result<(ProbeCurve, TickTimes, u32), String> {
    let mut sim = FemBody::new(scene).map_err(|e| e.to_string())?;
    let tick = sim.tick_s();
    let (mut curve, ticks) = probe_dynamic_body(&mut sim, tick, quick)?;
    let substeps = sim.plan().substeps;
    sim.recover_far_field();
    curve.x_last = sim.state().x.clone();
    Ok((curve, ticks, substeps))
}

/// The dynamic press protocol of [`probe_dynamic`] on any body (ticked at `tick_s`): the
/// forces per depth, the surface at the end of each hold, and the tick times (`x_last` is left
/// empty: the positions are the body's to read afterwards).
pub fn probe_dynamic_body(
    body: &mut dyn SoftBody,
    tick_s: f64,
    quick: bool,
) -> Result<(ProbeCurve, TickTimes), String> {
    let (ramp, hold) = if quick { (0.08, 0.08) } else { (0.1, 0.1) };
    let seg_ticks = ((ramp + hold) / tick_s).round() as usize;
    let mut ticks = TickTimes::new();
    let mut forces = Vec::new();
    let mut surfaces = Vec::new();
    let mut prev = -0.3e-3;
    for d in DEPTHS_MM {
        let d = d * 1e-3;
        let mut sum = 0.0;
        let mut count = 0;
        for k in 0..seg_ticks {
            let t = (k + 1) as f64 * tick_s;
            let s = t / ramp;
            let depth = prev + (d - prev) * smoothstep(s);
            let rate = (d - prev) / ramp * smoothstep_rate(s);
            let input = TickInput {
                device_position_m: Some(device_at(depth)),
                device_velocity_m_per_s: DVec3::new(-rate, 0.0, 0.0),
            };
            let t0 = Instant::now();
            let out = body.tick(&input).map_err(|e| e.to_string())?;
            ticks.record(t0.elapsed());
            if t > ramp + hold / 2.0 {
                sum += out.force_on_device_n.length();
                count += 1;
            }
        }
        forces.push(sum / count as f64);
        surfaces.push(SurfaceSnapshot::of(body));
        prev = d;
    }
    Ok((
        ProbeCurve {
            forces_n: forces,
            x_last: Vec::new(),
            surfaces,
        },
        ticks,
    ))
}
