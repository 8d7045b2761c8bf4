//! The organ table's calibration: every free node pressed by the probe through the body itself
//! (the same [`MassSpringBody::tick`] the servo runs, its constants unscaled), held at each of
//! the reference's sphere depths until the force settles; the factor is the reference's force
//! over the body's.
//!
//! A static solve of the calibration's local patch ([`super::super::calibration::LocalPatch`])
//! gives the same forces (checked in `tests/mass_spring_organ.rs`), but with a three-ring area
//! on the 1.4 mm left-ventricle surface one node took 55 s there (a nine-ring patch, and the
//! probe's patch found by a fixed point around every Newton solve) against about 0.1 s here:
//! the body's damped dynamics settle a hold in 20-60 ticks.

use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use glam::DVec3;

use super::{FACTOR_RANGE, OrganReference, OrganRow, OrganTable, organ_key};
use crate::ModelError;
use crate::body::TickInput;
use crate::contact::ProbeParams;
use crate::integrate::IntegratorParams;
use crate::mass_spring::calibration::CalibrationTable;
use crate::mass_spring::surface::SpringSurface;
use crate::mass_spring::{MassSpringBody, MassSpringParams};

/// Ticks of the ramp from one device depth to the next (a smoothstep).
pub const RAMP_TICKS: usize = 20;

/// A hold has settled when the force changed by less than this fraction over
/// [`SETTLE_WINDOW_TICKS`] ticks.
pub const SETTLE_TOLERANCE: f64 = 1e-5;

/// See [`SETTLE_TOLERANCE`].
pub const SETTLE_WINDOW_TICKS: usize = 10;

/// Most ticks of a hold; a hold that has not settled by then is an error.
pub const MAX_HOLD_TICKS: usize = 5_000;

/// The sphere depth must land within this fraction of the wanted depth (a few corrections
/// of the device's depth at most), and the force is then corrected to it along the local
/// slope.
pub const DEPTH_TOLERANCE: f64 = 2e-3;

/// Holds tried to reach a sphere depth within [`DEPTH_TOLERANCE`]; if none did, the closest
/// is used when it lies within [`DEPTH_FALLBACK_TOLERANCE`] (its force corrected along the
/// local slope), else the force is interpolated between the holds on either side of the depth
/// (the depth can jump past it when a subdivision event moves the contact), else the
/// calibration fails.
pub const DEPTH_ATTEMPTS: usize = 12;

/// See [`DEPTH_ATTEMPTS`].
pub const DEPTH_FALLBACK_TOLERANCE: f64 = 2e-2;

/// A site's subdivided factor is clamped to within this ratio of its coarse one (either way)
/// at each depth. Every factor multiplies the whole body's springs, so the sub-step plan grows
/// with the largest: at 0.1 mm, where the subdivided surface is touched later, the factors
/// reach 3-4 times the coarse ones (on `lv-surface-springs` every site is clamped there, and
/// 21-48 sites at 0.25-1 mm; until session 4, 23 nodes with a broken eq. 4 row needed 20-124).
pub const SUBDIVIDED_FACTOR_SPREAD: f64 = 2.0;

/// What the calibration needs of a scene besides the surface: its constants, the probe, the
/// servo tick settings and, with [`crate::mass_spring::SpringRule::Calibrated`], the eq. 4 table.
#[derive(Debug, Clone, Copy)]
pub struct OrganSetup<'a> {
    /// The scene's constants (`[mass_spring]`).
    pub params: &'a MassSpringParams,
    /// The scene's probe.
    pub probe: ProbeParams,
    /// The scene's servo tick settings.
    pub integrator: &'a IntegratorParams,
    /// The eq. 4 table (needed only with [`crate::mass_spring::SpringRule::Calibrated`] and
    /// rings > 0: the subdivided surface the calibration presses uses it).
    pub subdivision_table: Option<&'a CalibrationTable>,
}

/// The contact factor of a calibration press follows the one it measures, `F_target / F_1`
/// ([`press_sphere_depths`]), to within this fraction; else the hold is repeated with the new
/// factor.
pub const FACTOR_TOLERANCE: f64 = 1e-2;

/// Presses `body` with the probe at `point_m` along `direction` (unit, inward) to the sphere
/// depths `depths_m` in turn (device depth corrected until the body's sphere depth,
/// [`MassSpringBody::contact_depth_m`], is within [`DEPTH_TOLERANCE`]), each held until the
/// force settles: the force of the body's constant springs at each depth, `F_1`, N.
///
/// With `targets_n` (the force wanted at each depth, N) the body is pressed at the run time's
/// state: its springs scaled by the factor `beta = F_target / F_1` that the press measures
/// ([`MassSpringBody::set_contact_factor`], iterated with the depth to within
/// [`FACTOR_TOLERANCE`]), so that the coupling stretches by `F_target / k` as at run time and
/// the device, around which the kernel patch is gathered and weighted, sits where the run
/// time's sits; `F_1` is the force over `beta` (session 14: with the constant springs the 4 mm
/// hemisphere's coupling stretched 4.3 mm against 0.9 mm at run time, and the table read
/// +20-25 % at 4 mm; a coupling stiffened by `1 / beta` instead did not settle near the rim).
/// The body's factor is left at the last depth's.
///
/// # Errors
/// [`ModelError::NoConvergence`] when a hold does not settle in [`MAX_HOLD_TICKS`] or the
/// depth cannot be reached; the body's tick errors; [`ModelError::Unstable`] for a factor
/// the sub-steps cannot carry.
pub fn press_sphere_depths(
    body: &mut MassSpringBody,
    point_m: DVec3,
    direction: DVec3,
    depths_m: &[f64],
    targets_n: Option<&[f64]>,
) -> Result<Vec<f64>, ModelError> {
    let r = body.probe().params.radius_m;
    // Device at depth `d` below first contact: the sphere's centre `r - d` before the point.
    let device = |d: f64| point_m - direction * (r - d);
    let mut press = DepthPress {
        at: -0.2 * r.min(1e-3),
        measured: vec![(0.0, 0.0)],
        k: body.probe().params.coupling_stiffness_n_per_m,
        beta: body.contact_factor(),
    };
    let mut out = Vec::with_capacity(depths_m.len());
    for (j, &s) in depths_m.iter().enumerate() {
        let target = targets_n.and_then(|t| t.get(j).copied());
        out.push(press.depth(body, &device, s, target)?);
    }
    Ok(out)
}

/// The state of [`press_sphere_depths`] between its depths.
struct DepthPress {
    /// The device's depth now, m.
    at: f64,
    /// The holds so far, `(sphere depth m, force of the constant springs N)`, the origin first.
    measured: Vec<(f64, f64)>,
    /// The coupling's stiffness, N/m, and the body's contact factor now.
    k: f64,
    beta: f64,
}

impl DepthPress {
    /// Local slope dF_1/ds from the last two holds.
    fn slope(&self) -> f64 {
        let m = &self.measured;
        let n = m.len();
        if n >= 2 && m[n - 1].0 > m[n - 2].0 {
            (m[n - 1].1 - m[n - 2].1) / (m[n - 1].0 - m[n - 2].0)
        } else {
            0.0
        }
    }

    /// `F_1` at sphere depth `s` (m), N ([`press_sphere_depths`]), the factor following
    /// `target_n` when given.
    fn depth(
        &mut self,
        body: &mut MassSpringBody,
        device: &dyn Fn(f64) -> DVec3,
        s: f64,
        target_n: Option<f64>,
    ) -> Result<f64, ModelError> {
        let (s_last, f_last) = *self.measured.last().expect("starts with the origin");
        let mut target = s + self.beta * (f_last + self.slope() * (s - s_last)) / self.k;
        let mut result = None;
        // The closest hold so far: (|depth - s|, depth, F_1).
        let mut closest = (f64::INFINITY, 0.0, 0.0);
        for attempt in 0..DEPTH_ATTEMPTS {
            let (depth, force) = ramp_and_hold(body, device, self.at, target)?;
            let f1 = force / self.beta;
            self.at = target;
            self.measured.push((depth, f1));
            let sl = self.slope().max(0.0);
            if (depth - s).abs() < closest.0 {
                closest = ((depth - s).abs(), depth, f1);
            }
            let f_s = f1 + sl * (s - depth);
            // The run time's factor at this depth (the body's without a target).
            let beta = match target_n {
                Some(t) if t > 0.0 && f_s > 0.0 => t / f_s,
                _ => self.beta,
            };
            let settled = (beta / self.beta - 1.0).abs() <= FACTOR_TOLERANCE;
            if (depth - s).abs() <= DEPTH_TOLERANCE * s && settled {
                result = Some(f_s);
                break;
            }
            // The device moves by the sphere's shortfall plus the coupling's extra stretch
            // (halved after the first corrections: nodes entering the probe's patch can make
            // the full step overshoot back and forth), and by the coupling's change of stretch
            // with the factor.
            let gain = if attempt < 3 { 1.0 } else { 0.5 };
            target +=
                gain * (s - depth) * (1.0 + beta * sl / self.k) + f1 * (beta - self.beta) / self.k;
            if !settled {
                self.beta = beta;
                body.set_contact_factor(beta)?;
            }
        }
        if result.is_none() && closest.0 <= DEPTH_FALLBACK_TOLERANCE * s {
            // Close enough to correct along the local slope of the last holds.
            result = Some(closest.2 + self.slope().max(0.0) * (s - closest.1));
        }
        if result.is_none() {
            // The depth jumps past `s` (a subdivision event, nodes entering the patch): linear
            // between the closest holds on either side of it (the origin among them).
            result = bracketed(&self.measured, s);
        }
        result.ok_or_else(|| {
            ModelError::NoConvergence(format!(
                "the probe's sphere depth did not reach {:.3} mm within {:.1} % in {DEPTH_ATTEMPTS} holds, none beyond it (closest {:.4} mm)",
                s * 1e3,
                100.0 * DEPTH_FALLBACK_TOLERANCE,
                closest.1 * 1e3
            ))
        })
    }
}

/// The force at sphere depth `s` linear between the measured `(depth, force)` holds closest to
/// it below and above; `None` when no hold lies above.
fn bracketed(measured: &[(f64, f64)], s: f64) -> Option<f64> {
    let below = measured
        .iter()
        .filter(|m| m.0 <= s)
        .max_by(|a, b| a.0.total_cmp(&b.0))?;
    let above = measured
        .iter()
        .filter(|m| m.0 > s)
        .min_by(|a, b| a.0.total_cmp(&b.0))?;
    let t = (s - below.0) / (above.0 - below.0);
    Some(below.1 + t * (above.1 - below.1))
}

/// Ramps the device from depth `from` to `to` (m) and holds it until the force settles:
/// `(sphere depth m, force N)` at the end of the hold.
fn ramp_and_hold(
    body: &mut MassSpringBody,
    device: &dyn Fn(f64) -> DVec3,
    from: f64,
    to: f64,
) -> Result<(f64, f64), ModelError> {
    let tick = |body: &mut MassSpringBody, d: f64| {
        body.tick(&TickInput {
            device_position_m: Some(device(d)),
            device_velocity_m_per_s: DVec3::ZERO,
        })
    };
    for j in 1..=RAMP_TICKS {
        let t = j as f64 / RAMP_TICKS as f64;
        tick(body, from + (to - from) * t * t * (3.0 - 2.0 * t))?;
    }
    let mut history = [0.0; SETTLE_WINDOW_TICKS];
    for j in 0..MAX_HOLD_TICKS {
        let out = tick(body, to)?;
        let f = out.force_on_device_n.length();
        let old = history[j % SETTLE_WINDOW_TICKS];
        history[j % SETTLE_WINDOW_TICKS] = f;
        if j >= SETTLE_WINDOW_TICKS && (f - old).abs() <= SETTLE_TOLERANCE * f.max(1e-12) {
            if !out.in_contact {
                return Ok((0.0, 0.0));
            }
            return Ok((body.contact_depth_m(), f));
        }
    }
    Err(ModelError::NoConvergence(format!(
        "a hold at {:.3} mm did not settle in {MAX_HOLD_TICKS} ticks",
        to * 1e3
    )))
}

/// Where and along which direction (unit, inward) the calibration presses site `site` of
/// `surface` (module documentation of [`super`]): a coarse node at its rest position along its
/// inward rest normal; an edge's site (`node_count + e`) at the midpoint of the edge's ends
/// along the inward mean of their normals; a corner child's site ([`child_of_site`]) at its
/// centroid on the flat rest triangle (weights 2/3 on the corner, 1/6 on the others) along the
/// inward normals' mean with the same weights.
pub fn site_press(surface: &SpringSurface, site: u32) -> (DVec3, DVec3) {
    let nc = surface.node_count() as u32;
    let rest = surface.rest();
    if let Some((t, i)) = child_of_site(surface, site) {
        let tri = surface.triangles()[t as usize];
        let w = |k: usize| if k == i { 2.0 / 3.0 } else { 1.0 / 6.0 };
        let point = (0..3).map(|k| rest[tri[k] as usize] * w(k)).sum();
        let normal: DVec3 = (0..3).map(|k| surface.rest_normal(tri[k]) * w(k)).sum();
        return (point, -normal.normalize_or_zero());
    }
    if site < nc {
        return (rest[site as usize], -surface.rest_normal(site));
    }
    let [a, b] = surface.edges()[(site - nc) as usize];
    let normal = (surface.rest_normal(a) + surface.rest_normal(b)).normalize_or_zero();
    (0.5 * (rest[a as usize] + rest[b as usize]), -normal)
}

/// The coarse triangle and corner (0..3) of corner-child site `site` (`N + E + 3 t + i`,
/// [`OrganTable::child_site`]); `None` for a node's or an edge's site or beyond.
pub fn child_of_site(surface: &SpringSurface, site: u32) -> Option<(u32, usize)> {
    let k = (site as usize).checked_sub(surface.node_count() + surface.edge_count())?;
    (k < 3 * surface.triangle_count()).then_some(((k / 3) as u32, k % 3))
}

/// The subdivided row of corner-child site `site` ([`child_of_site`]): the body `subdivided`
/// (the scene's run-time subdivision) pressed at the site ([`site_press`]) in its corner's area
/// at the run time's factor ([`press_sphere_depths`]); its coarse `factor` left empty (the
/// corners' mean, [`calibrate_organ`]) and its subdivided factor not yet clamped. `None` when
/// the press fails or a factor falls outside [`FACTOR_RANGE`] (the site then takes its
/// corners' mean).
pub fn calibrate_child_site(
    surface: &SpringSurface,
    mut subdivided: MassSpringBody,
    reference: &OrganReference,
    axis: DVec3,
    site: u32,
) -> Option<OrganRow> {
    let (t, i) = child_of_site(surface, site)?;
    let corner = surface.triangles()[t as usize][i];
    if !surface.is_fixed(corner) {
        subdivided.subdivide_around(&[corner]);
    }
    let (point, inward) = site_press(surface, site);
    let target = reference.target_at(axis, point);
    let depths = reference.depths_m();
    let f = press_sphere_depths(&mut subdivided, point, inward, depths, Some(&target)).ok()?;
    let beta: Vec<f64> = target.iter().zip(&f).map(|(t, f)| t / f).collect();
    if !beta
        .iter()
        .all(|b| (FACTOR_RANGE.0..=FACTOR_RANGE.1).contains(b))
    {
        return None;
    }
    Some(OrganRow {
        factor: Vec::new(),
        factor_subdivided: beta,
        target_force_n: target,
        spring_force_n: vec![0.0; depths.len()],
        subdivided_force_n: f,
    })
}

/// The organ row of site `site` (a free node, or an edge with a free end; module documentation
/// of [`super`]): the body with constant springs pressed at the site ([`site_press`]) never
/// subdivided, and with the scene's run-time subdivision (its rings and spring rule, the eq. 4
/// table with [`crate::mass_spring::SpringRule::Calibrated`]) when `subdivided` is given; `coarse` and `subdivided`
/// are fresh bodies of the two kinds. Without subdivision, or when the subdivided press fails
/// (the depth not reached, a factor out of range), the subdivided factor is the coarse one
/// and the row's `subdivided_force_n` is 0; it is clamped to [`SUBDIVIDED_FACTOR_SPREAD`] of
/// the coarse one.
///
/// # Errors
/// As [`press_sphere_depths`]; [`ModelError::Calibration`] when a factor falls outside
/// [`FACTOR_RANGE`].
pub fn calibrate_organ_node(
    surface: &SpringSurface,
    (coarse, subdivided): (MassSpringBody, Option<MassSpringBody>),
    reference: &OrganReference,
    axis: DVec3,
    site: u32,
) -> Result<OrganRow, ModelError> {
    let (point, inward) = site_press(surface, site);
    let depths = reference.depths_m();
    let target = reference.target_at(axis, point);
    let factor = |f: &[f64], what: &str| -> Result<Vec<f64>, ModelError> {
        f.iter()
            .zip(&target)
            .zip(depths)
            .map(|((&f, &t), &d)| {
                let beta = t / f;
                if f > 0.0 && (FACTOR_RANGE.0..=FACTOR_RANGE.1).contains(&beta) {
                    Ok(beta)
                } else {
                    Err(ModelError::Calibration {
                        path: String::new(),
                        message: format!(
                            "at {:.3} mm the {what} surface gives {f:.3e} N for a target of {t:.3e} N (factor outside {FACTOR_RANGE:?}): the scene's constants are far from the reference",
                            d * 1e3
                        ),
                    })
                }
            })
            .collect()
    };
    let mut body = coarse.clone();
    let f_coarse = match press_sphere_depths(&mut body, point, inward, depths, Some(&target)) {
        Ok(f) => f,
        // By the clamped rim a hold at the run time's factor can oscillate without settling
        // (node 945 of the 4 mm hemisphere at 3.5 mm): the constant springs' press there.
        Err(ModelError::NoConvergence(_)) => {
            let mut body = coarse;
            press_sphere_depths(&mut body, point, inward, depths, None)?
        }
        Err(e) => return Err(e),
    };
    let beta = factor(&f_coarse, "coarse")?;
    // A subdivided press that fails (near the left ventricle's apex the subdivided surface
    // lets the sphere through past 2-3 mm) keeps the coarse factor, its force row 0; the
    // subdivided factor stays within SUBDIVIDED_FACTOR_SPREAD of the coarse one.
    let subdivided_row = subdivided.and_then(|mut body| {
        if let Some(end) = edge_area_end(surface, site) {
            body.subdivide_around(&[end]);
        }
        let f = press_sphere_depths(&mut body, point, inward, depths, Some(&target)).ok()?;
        let b = factor(&f, "subdivided").ok()?;
        let spread = SUBDIVIDED_FACTOR_SPREAD;
        let b = b
            .iter()
            .zip(&beta)
            .map(|(s, c)| s.clamp(c / spread, c * spread));
        Some((b.collect(), f))
    });
    let (beta_sub, f_sub) =
        subdivided_row.unwrap_or_else(|| (beta.clone(), vec![0.0; depths.len()]));
    Ok(OrganRow {
        factor: beta,
        factor_subdivided: beta_sub,
        target_force_n: target,
        spring_force_n: f_coarse,
        subdivided_force_n: f_sub,
    })
}

/// The node whose one-ring area the subdivided press at edge site `site` is made in, when the
/// run-time rule (the coarse node nearest the contact point among the touched triangle's,
/// `MassSpringBody::contact_node`) would not give one of the edge's ends: a long edge, whose
/// midpoint lies nearer a triangle's third node than its ends. There the press at the midpoint
/// makes two areas, about the third nodes on either side (the contact flickers between the
/// two triangles), which a press beside the midpoint never does: on the 4 mm hemisphere,
/// edge 28-51 next to the point h1 (its midpoint 2.58 mm from node 29, 3.05 from its ends)
/// was calibrated 25-35 % stiffer than a press in node 28's area, so h1 subdivided read -25 to
/// -30 % (session 14). So the press is made in the area of its nearer free end (the first on a
/// tie), as a user's press on either side of the midpoint makes it. `None` for a node's site
/// and an ordinary edge (the run time's rule then picks an end itself).
pub fn edge_area_end(surface: &SpringSurface, site: u32) -> Option<u32> {
    let nc = surface.node_count() as u32;
    let [a, b] = *surface.edges().get(site.checked_sub(nc)? as usize)?;
    let rest = surface.rest();
    let mid = 0.5 * (rest[a as usize] + rest[b as usize]);
    let dist = |i: u32| (rest[i as usize] - mid).length();
    let ends = dist(a).min(dist(b));
    let third_nearer = surface
        .neighbours(a)
        .iter()
        .filter(|&&o| o != b && surface.neighbours(b).contains(&o))
        .any(|&o| !surface.is_fixed(o) && dist(o) < ends);
    if !third_nearer {
        return None;
    }
    [a, b]
        .into_iter()
        .filter(|&i| !surface.is_fixed(i))
        .min_by(|&i, &j| dist(i).total_cmp(&dist(j)))
}

/// The organ table of `surface` for the scene `setup`, the reference and its axis, computed on
/// `threads` threads with `progress(done, total)` after each site (module documentation of
/// [`super`]): every free node, every edge with a free end and (subdividing) every corner
/// child's site with a free corner is pressed; a fixed node takes the mean factors of its free
/// neighbours, an edge between two fixed nodes (or one whose press fails) the mean of its ends,
/// a child's site not pressed its corners' ([`calibrate_child_site`]).
///
/// # Errors
/// The errors of building the bodies ([`MassSpringBody::new`]); the first error of
/// [`calibrate_organ_node`] at a node, naming it.
pub fn calibrate_organ(
    surface: &SpringSurface,
    setup: OrganSetup<'_>,
    (reference, axis): (&OrganReference, DVec3),
    threads: usize,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<OrganTable, ModelError> {
    let params = setup.params;
    let (coarse, subdivided) = organ_bodies(surface, &setup)?;
    let nc = surface.node_count();
    let ns = nc + surface.edge_count();
    let free = pressed_sites(surface, subdivided.is_some());
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(0);
    let rows: Mutex<Vec<Option<OrganRow>>> =
        Mutex::new(vec![None; ns + 3 * surface.triangle_count()]);
    let failure: Mutex<Option<ModelError>> = Mutex::new(None);
    std::thread::scope(|scope| {
        for _ in 0..threads.max(1) {
            scope.spawn(|| {
                loop {
                    let k = next.fetch_add(1, Ordering::Relaxed);
                    if k >= free.len() || failure.lock().map(|f| f.is_some()).unwrap_or(true) {
                        break;
                    }
                    let site = free[k];
                    let bodies = (coarse.clone(), subdivided.clone());
                    let result = match (site as usize >= ns, bodies.1) {
                        (true, Some(body)) => {
                            calibrate_child_site(surface, body, reference, axis, site)
                                .ok_or_else(|| ModelError::NoConvergence(String::new()))
                        }
                        (_, sub) => {
                            calibrate_organ_node(surface, (bodies.0, sub), reference, axis, site)
                        }
                    };
                    match result {
                        // An edge's or child's site the probe cannot press takes its ends' or
                        // corners' mean.
                        Err(_) if site as usize >= nc => {
                            progress(done.fetch_add(1, Ordering::Relaxed) + 1, free.len());
                        }
                        Ok(row) => {
                            if let Ok(mut rows) = rows.lock() {
                                rows[site as usize] = Some(row);
                            }
                            progress(done.fetch_add(1, Ordering::Relaxed) + 1, free.len());
                        }
                        Err(e) => {
                            if let Ok(mut f) = failure.lock() {
                                let what = if (site as usize) < nc {
                                    "node"
                                } else {
                                    "edge site"
                                };
                                f.get_or_insert(ModelError::Calibration {
                                    path: String::new(),
                                    message: format!("{what} {site}: {e}"),
                                });
                            }
                            break;
                        }
                    }
                }
            });
        }
    });
    if let Some(e) = failure.into_inner().ok().flatten() {
        return Err(e);
    }
    let mut rows = rows.into_inner().unwrap_or_default();
    fill_fixed_sites(&mut rows, surface, reference.depths_m().len());
    Ok(OrganTable {
        key: organ_key(surface, params, &setup.probe, reference, axis),
        depths_m: reference.depths_m().to_vec(),
        nodes: nc,
        children: 3 * surface.triangle_count(),
        rows: rows.into_iter().map(Option::unwrap_or_default).collect(),
    })
}

/// The sites [`calibrate_organ`] presses: every free node, every edge with a free end and, on
/// a subdividing scene (`subdivides`), every corner child's site with a free corner.
fn pressed_sites(surface: &SpringSurface, subdivides: bool) -> Vec<u32> {
    let nc = surface.node_count();
    let ns = nc + surface.edge_count();
    let children = if subdivides {
        3 * surface.triangle_count()
    } else {
        0
    };
    (0..(ns + children) as u32)
        .filter(|&s| {
            if let Some((t, i)) = child_of_site(surface, s) {
                !surface.is_fixed(surface.triangles()[t as usize][i])
            } else if (s as usize) < nc {
                !surface.is_fixed(s)
            } else {
                let [a, b] = surface.edges()[s as usize - nc];
                !(surface.is_fixed(a) && surface.is_fixed(b))
            }
        })
        .collect()
}

/// The bodies a site is pressed on: the coarse surface (no subdivision) and, when the scene
/// subdivides, the subdivided one.
///
/// # Errors
/// The errors of [`MassSpringBody::new`].
fn organ_bodies(
    surface: &SpringSurface,
    setup: &OrganSetup<'_>,
) -> Result<(MassSpringBody, Option<MassSpringBody>), ModelError> {
    let params = setup.params;
    let mut coarse_params = *params;
    coarse_params.subdivision.rings = 0;
    let coarse = MassSpringBody::new(
        surface.clone(),
        &coarse_params,
        None,
        setup.probe,
        setup.integrator,
        "organ calibration",
    )?;
    let subdivided = if params.subdivision.rings > 0 {
        Some(MassSpringBody::new(
            surface.clone(),
            params,
            setup.subdivision_table.cloned(),
            setup.probe,
            setup.integrator,
            "organ calibration",
        )?)
    } else {
        None
    };
    Ok((coarse, subdivided))
}

/// Gives every site without a row (a fixed node, an edge whose press failed or whose ends are
/// fixed) the mean row of its neighbours (a node) or its ends (an edge site), `m` samples;
/// then every corner child's site ([`child_of_site`]) its corners' (the node and its two
/// edges' sites) mean coarse factor and, unless pressed ([`calibrate_child_site`]), their
/// mean subdivided factor and target; a pressed one clamped to [`SUBDIVIDED_FACTOR_SPREAD`]
/// of its coarse factor.
fn fill_fixed_sites(rows: &mut [Option<OrganRow>], surface: &SpringSurface, m: usize) {
    let nc = surface.node_count();
    let ns = nc + surface.edge_count();
    let fixed: Vec<(usize, OrganRow)> = (0..nc)
        .filter(|&i| rows[i].is_none())
        .map(|i| (i, mean_row(rows, surface.neighbours(i as u32), m)))
        .collect();
    for (i, row) in fixed {
        rows[i] = Some(row);
    }
    for s in nc..ns {
        if rows[s].is_none() {
            let ends = surface.edges()[s - nc];
            rows[s] = Some(mean_row(rows, &ends, m));
        }
    }
    for s in ns..rows.len() {
        let Some((t, i)) = child_of_site(surface, s as u32) else {
            continue;
        };
        let tri = surface.triangles()[t as usize];
        // The child's corners: the node and the sites of its two sides.
        let side = |j: usize| surface.edge_between(tri[j], tri[(j + 1) % 3]);
        let corners: Vec<u32> = std::iter::once(tri[i])
            .chain(
                [side(i), side((i + 2) % 3)]
                    .into_iter()
                    .flatten()
                    .map(|e| nc as u32 + e),
            )
            .collect();
        let mean = mean_row(rows, &corners, m);
        rows[s] = Some(match rows[s].take() {
            Some(pressed) => {
                let spread = SUBDIVIDED_FACTOR_SPREAD;
                let sub = pressed.factor_subdivided.iter().zip(&mean.factor);
                OrganRow {
                    factor_subdivided: sub.map(|(s, c)| s.clamp(c / spread, c * spread)).collect(),
                    factor: mean.factor,
                    ..pressed
                }
            }
            None => mean,
        });
    }
}

/// The mean factors and target of the calibrated sites `of` (factor 1 without any): the row
/// of a site the probe cannot press (a fixed node, an edge between two).
fn mean_row(rows: &[Option<OrganRow>], of: &[u32], samples: usize) -> OrganRow {
    let mut row = OrganRow {
        factor: vec![0.0; samples],
        factor_subdivided: vec![0.0; samples],
        target_force_n: vec![0.0; samples],
        spring_force_n: vec![0.0; samples],
        subdivided_force_n: vec![0.0; samples],
    };
    let mut n = 0.0;
    for &j in of {
        if let Some(r) = &rows[j as usize] {
            for k in 0..samples {
                row.factor[k] += r.factor[k];
                row.factor_subdivided[k] += r.factor_subdivided[k];
                row.target_force_n[k] += r.target_force_n[k];
            }
            n += 1.0;
        }
    }
    for k in 0..samples {
        if n > 0.0 {
            row.factor[k] /= n;
            row.factor_subdivided[k] /= n;
            row.target_force_n[k] /= n;
        } else {
            row.factor[k] = 1.0;
            row.factor_subdivided[k] = 1.0;
        }
    }
    row
}
