//! Probe presses as a user feels them: scripted device paths driven through
//! [`SoftBody::tick`] exactly as the servo drives a body, with what a hand would notice
//! measured per hold (the force, its tick-to-tick change, the probe sphere's depth).
//!
//! Three protocols (DESIGN.md section 5: "every family's probe force against depth follows the
//! same reference within the force JND (7 %), and every hold is steady"):
//!
//! - [`staircase`]: the device ramps along a [`PressLine`] to each depth in turn (a C1 ramp of
//!   `ramp_s`) and holds it `hold_s`; per hold a [`HoldReport`].
//! - [`constant_speed_press`]: the demo's press, at a constant speed to one depth, then a hold.
//! - [`stroke`]: pressed to a depth, then slid at a constant speed along a circle around an axis
//!   (on the left ventricle: half way round at the probe's height).
//!
//! Depths are measured along the line from where the probe sphere (radius `r`) first touches
//! the surface: the analytic surface when one is known ([`PressLine::lv_probe`]), otherwise the
//! body's rest surface ([`PressLine::from_rest_surface`], an exact sphere cast against its
//! triangles). Two conventions, as in the references: the **device depth** (the device's
//! travel past first contact, which includes the virtual coupling's stretch) and the **sphere
//! depth** (the proxy's travel past first contact, read from [`TickOutput::proxy_position_m`]).
//!
//! Steadiness is `max |F_k - F_(k-1)|` over the ticks of a hold (vector difference of the
//! device force, N), reported against the hold's mean force magnitude.
//!
//! Owns: the protocols and their reports. Uses: [`crate::body`] (the seam), [`crate::contact`]
//! (sphere casts). Not on the real-time path: the protocols allocate their reports.

use std::time::Instant;

use glam::DVec3;

use crate::ModelError;
use crate::body::{SoftBody, TickInput, TickOutput};
use crate::contact::sphere::sphere_exit;

/// The lv-probe point's epicardium: the analytic surface's `x` at `y = 0`, `z = -5 mm` of the
/// idealized left ventricle (epicardium semi-axes 10, 10, 20 mm: `10 sqrt(1 - 5^2 / 20^2)` mm).
pub const LV_PROBE_SURFACE_X_M: f64 = 9.682_458_365_518_542e-3;

/// Height of the lv-probe line, m (`z = -5 mm`).
pub const LV_PROBE_Z_M: f64 = -5e-3;

/// Device travel before depth zero of [`PressLine::at_surface_point`], m.
pub const SURFACE_LINE_CLEARANCE_M: f64 = 1e-3;

/// Semi-axes of the idealized left ventricle's epicardium (the built-in `lv` geometry), m:
/// `x^2 / a^2 + y^2 / a^2 + z^2 / c^2 = 1` with `a = 10 mm`, `c = 20 mm`, cut at `z = 5 mm`.
pub const LV_EPICARDIUM_SEMI_AXES_M: (f64, f64) = (10e-3, 20e-3);

/// The point of the analytic LV epicardium at height `z_m` (m, between the apex at -20 mm and
/// the base at 5 mm) and azimuth `azimuth_rad` (from +x towards +y), and the inward unit normal
/// there: a press line for [`PressLine::at_surface_point`].
pub fn lv_epicardium_point(z_m: f64, azimuth_rad: f64) -> (DVec3, DVec3) {
    let (a, c) = LV_EPICARDIUM_SEMI_AXES_M;
    let rho = a * (1.0 - (z_m / c).powi(2)).max(0.0).sqrt();
    let p = DVec3::new(rho * azimuth_rad.cos(), rho * azimuth_rad.sin(), z_m);
    let n = DVec3::new(p.x / (a * a), p.y / (a * a), p.z / (c * c)).normalize();
    (p, -n)
}

/// A straight device path: the device moves from `start_m` along `direction`; the probe sphere
/// first touches the surface after `contact_travel_m` of travel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PressLine {
    /// Start of the path, clear of the body, m.
    pub start_m: DVec3,
    /// Unit direction of the press.
    pub direction: DVec3,
    /// Travel from `start_m` at which the sphere first touches the surface, m.
    pub contact_travel_m: f64,
}

impl PressLine {
    /// The `lv-probe` line of the left-ventricle scenes: along -x at `y = 0`, `z = -5 mm`,
    /// starting at `x = 15 mm`, with depth zero where a sphere of `radius_m` touches the
    /// analytic epicardium ([`LV_PROBE_SURFACE_X_M`]).
    pub fn lv_probe(radius_m: f64) -> Self {
        let start_x = 15e-3;
        Self {
            start_m: DVec3::new(start_x, 0.0, LV_PROBE_Z_M),
            direction: DVec3::NEG_X,
            contact_travel_m: start_x - (LV_PROBE_SURFACE_X_M + radius_m),
        }
    }

    /// A line along `direction` (unit after normalising) through the surface point `point_m`,
    /// whose depth zero is the sphere of `radius_m` centred `radius_m` before the point on the
    /// line: the sphere touching the point (on a convex analytic surface pressed along its
    /// inward normal, as [`lv_epicardium_point`] gives, exactly its first contact). The device
    /// starts [`SURFACE_LINE_CLEARANCE_M`] before that.
    pub fn at_surface_point(point_m: DVec3, direction: DVec3, radius_m: f64) -> Self {
        let n = direction.normalize_or_zero();
        Self {
            start_m: point_m - n * (radius_m + SURFACE_LINE_CLEARANCE_M),
            direction: n,
            contact_travel_m: SURFACE_LINE_CLEARANCE_M,
        }
    }

    /// A line from `start_m` along `direction` whose depth zero is where a sphere of
    /// `radius_m` first touches the body's rest surface (exact sphere cast against the
    /// surface triangles, [`sphere_exit`]).
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] for a zero or non-finite direction, a start inside the
    /// surface's reach, or a line that misses the surface.
    pub fn from_rest_surface(
        body: &dyn SoftBody,
        start_m: DVec3,
        direction: DVec3,
        radius_m: f64,
    ) -> Result<Self, ModelError> {
        let n = direction.normalize_or_zero();
        if n == DVec3::ZERO || !start_m.is_finite() || !(radius_m > 0.0) {
            return Err(ModelError::InvalidInput(format!(
                "press line from {start_m} along {direction} with radius {radius_m} m: needs a \
                 finite start, a non-zero direction and a positive radius"
            )));
        }
        let topo = body.surface_topology();
        let mut rest = vec![0f32; 3 * topo.vertex_count];
        body.write_surface_rest_positions(&mut rest);
        let p = |i: u32| {
            let i = 3 * i as usize;
            DVec3::new(rest[i] as f64, rest[i + 1] as f64, rest[i + 2] as f64)
        };
        // Entry along +n is the exit along -n seen from far beyond the body.
        let far = 1.0;
        let beyond = start_m + n * far;
        let mut first: Option<f64> = None;
        for t in topo.triangles {
            if let Some(s) = sphere_exit(beyond, -n, radius_m, p(t[0]), p(t[1]), p(t[2])) {
                let entry = far - s;
                first = Some(first.map_or(entry, |f: f64| f.min(entry)));
            }
        }
        match first {
            Some(t) if t > 0.0 => Ok(Self {
                start_m,
                direction: n,
                contact_travel_m: t,
            }),
            Some(t) => Err(ModelError::InvalidInput(format!(
                "the probe sphere at {start_m} m already touches the surface ({:.3} mm past \
                 first contact): start farther out",
                -t * 1e3
            ))),
            None => Err(ModelError::InvalidInput(format!(
                "the press line from {start_m} m along {n} misses the body's surface"
            ))),
        }
    }

    /// Device position at `depth_m` past first contact (negative: before it), m.
    pub fn device_at(&self, depth_m: f64) -> DVec3 {
        self.start_m + self.direction * (self.contact_travel_m + depth_m)
    }

    /// Depth past first contact of a point (the proxy's centre) projected on the line, m.
    pub fn depth_of(&self, point_m: DVec3) -> f64 {
        (point_m - self.start_m).dot(self.direction) - self.contact_travel_m
    }
}

/// Timing of a [`staircase`]: each depth is reached by a C1 ramp of `ramp_s` and held
/// `hold_s`; the force is averaged over the last `average_s` of each hold.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HoldParams {
    /// Ramp time from one depth to the next, s.
    pub ramp_s: f64,
    /// Hold time at each depth, s.
    pub hold_s: f64,
    /// Averaging window at the end of each hold, s (at most `hold_s`).
    pub average_s: f64,
}

impl Default for HoldParams {
    /// The feel protocol of issue 46: ramps of 0.5 s, holds of 1.5 s, the last 1 s averaged.
    fn default() -> Self {
        Self {
            ramp_s: 0.5,
            hold_s: 1.5,
            average_s: 1.0,
        }
    }
}

/// What one hold of a press felt like.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct HoldReport {
    /// The device's depth past first contact, m.
    pub device_depth_m: f64,
    /// The proxy sphere's depth past first contact, averaged like the force, m.
    pub sphere_depth_m: f64,
    /// Mean device force magnitude over the averaging window, N.
    pub force_n: f64,
    /// Mean device force over the averaging window, N.
    pub force_vector_n: DVec3,
    /// Smallest and largest force magnitude over the whole hold, N.
    pub force_min_n: f64,
    /// See `force_min_n`.
    pub force_max_n: f64,
    /// Largest tick-to-tick change of the device force over the whole hold, N.
    pub max_tick_change_n: f64,
    /// Ticks in contact over the whole hold, of `hold_ticks`.
    pub contact_ticks: usize,
    /// Ticks of the hold.
    pub hold_ticks: usize,
}

impl HoldReport {
    /// `max_tick_change_n / force_n` (infinite for a zero mean force with changes; 0 for a
    /// quiet zero force).
    pub fn steadiness(&self) -> f64 {
        if self.max_tick_change_n == 0.0 {
            0.0
        } else {
            self.max_tick_change_n / self.force_n
        }
    }
}

/// Wall time of each tick of a protocol, s, and the device forces tick by tick.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PressTrace {
    /// Wall time of each [`SoftBody::tick`], s.
    pub tick_wall_s: Vec<f64>,
    /// Device force of each tick, N.
    pub force_n: Vec<DVec3>,
    /// Device position of each tick, m.
    pub device_m: Vec<DVec3>,
    /// Proxy position of each tick, m.
    pub proxy_m: Vec<DVec3>,
}

impl PressTrace {
    fn with_capacity(n: usize) -> Self {
        Self {
            tick_wall_s: Vec::with_capacity(n),
            force_n: Vec::with_capacity(n),
            device_m: Vec::with_capacity(n),
            proxy_m: Vec::with_capacity(n),
        }
    }

    fn tick(
        &mut self,
        body: &mut dyn SoftBody,
        device_m: DVec3,
        velocity: DVec3,
    ) -> Result<TickOutput, ModelError> {
        let input = TickInput {
            device_position_m: Some(device_m),
            device_velocity_m_per_s: velocity,
        };
        let t0 = Instant::now();
        let out = body.tick(&input)?;
        self.tick_wall_s.push(t0.elapsed().as_secs_f64());
        self.force_n.push(out.force_on_device_n);
        self.device_m.push(device_m);
        self.proxy_m.push(out.proxy_position_m);
        Ok(out)
    }

    /// The `q`-quantile (0..=1) of the tick wall times, s (0 when there are none).
    pub fn tick_quantile_s(&self, q: f64) -> f64 {
        quantile(&self.tick_wall_s, q)
    }

    /// Largest tick-to-tick change of the device force over ticks `range`, N.
    pub fn max_tick_change_n(&self, range: std::ops::Range<usize>) -> f64 {
        let lo = range.start.max(1);
        (lo..range.end)
            .map(|k| (self.force_n[k] - self.force_n[k - 1]).length())
            .fold(0.0, f64::max)
    }

    /// A hold's report over ticks `hold` (the last `average` of them averaged) of a line.
    fn hold_report(
        &self,
        line: &PressLine,
        device_depth_m: f64,
        hold: std::ops::Range<usize>,
        average: usize,
    ) -> HoldReport {
        let avg = hold.end.saturating_sub(average.max(1))..hold.end;
        let n = avg.len().max(1) as f64;
        let force_vector_n = self.force_n[avg.clone()].iter().sum::<DVec3>() / n;
        let force_n = self.force_n[avg.clone()]
            .iter()
            .map(|f| f.length())
            .sum::<f64>()
            / n;
        let sphere_depth_m = self.proxy_m[avg]
            .iter()
            .map(|p| line.depth_of(*p))
            .sum::<f64>()
            / n;
        let mags = self.force_n[hold.clone()].iter().map(|f| f.length());
        HoldReport {
            device_depth_m,
            sphere_depth_m,
            force_n,
            force_vector_n,
            force_min_n: mags.clone().fold(f64::INFINITY, f64::min),
            force_max_n: mags.fold(0.0, f64::max),
            // The first tick of a hold is compared with the ramp's last.
            max_tick_change_n: self.max_tick_change_n(hold.start..hold.end),
            contact_ticks: self.force_n[hold.clone()]
                .iter()
                .filter(|f| **f != DVec3::ZERO)
                .count(),
            hold_ticks: hold.len(),
        }
    }
}

/// The `q`-quantile (0..=1, nearest rank) of `values` (0 when empty).
pub fn quantile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let k = ((q.clamp(0.0, 1.0) * (v.len() - 1) as f64).round()) as usize;
    v[k]
}

/// `3 s^2 - 2 s^3` on `[0, 1]` and its derivative, clamped outside.
fn smoothstep(s: f64) -> (f64, f64) {
    let s = s.clamp(0.0, 1.0);
    (s * s * (3.0 - 2.0 * s), 6.0 * s * (1.0 - s))
}

fn ticks_of(seconds: f64, tick_s: f64) -> usize {
    (seconds / tick_s).round().max(0.0) as usize
}

fn check_timing(tick_s: f64, what: &str, seconds: &[f64]) -> Result<(), ModelError> {
    if !(tick_s > 0.0) || seconds.iter().any(|s| !(s.is_finite() && *s >= 0.0)) {
        return Err(ModelError::InvalidInput(format!(
            "{what}: the tick ({tick_s} s) must be positive and every duration finite and \
             non-negative ({seconds:?} s)"
        )));
    }
    Ok(())
}

/// Presses along `line` to each of `depths_m` (device depths past first contact, m) in turn:
/// from the start (the device at depth `-1 mm`, one tick out of contact), a C1 ramp of
/// `params.ramp_s` to each depth and a hold of `params.hold_s`, ticked at `tick_s` (the
/// body's servo period). Returns one [`HoldReport`] per depth and the whole trace.
///
/// # Errors
/// [`ModelError::InvalidInput`] for a non-positive tick or negative durations; the body's
/// tick errors (a fault ends the press with that error).
pub fn staircase(
    body: &mut dyn SoftBody,
    line: &PressLine,
    depths_m: &[f64],
    params: &HoldParams,
    tick_s: f64,
) -> Result<(Vec<HoldReport>, PressTrace), ModelError> {
    check_timing(
        tick_s,
        "staircase",
        &[params.ramp_s, params.hold_s, params.average_s],
    )?;
    let (ramp, hold) = (
        ticks_of(params.ramp_s, tick_s),
        ticks_of(params.hold_s, tick_s),
    );
    let average = ticks_of(params.average_s.min(params.hold_s), tick_s);
    let mut trace = PressTrace::with_capacity(1 + depths_m.len() * (ramp + hold));
    let mut prev = -1e-3;
    trace.tick(body, line.device_at(prev), DVec3::ZERO)?;
    let mut holds = Vec::with_capacity(depths_m.len());
    for &d in depths_m {
        for k in 1..=ramp {
            let (s, rate) = smoothstep(k as f64 / ramp as f64);
            let v = line.direction * ((d - prev) * rate / params.ramp_s);
            trace.tick(body, line.device_at(prev + (d - prev) * s), v)?;
        }
        let start = trace.force_n.len();
        for _ in 0..hold {
            trace.tick(body, line.device_at(d), DVec3::ZERO)?;
        }
        holds.push(trace.hold_report(line, d, start..trace.force_n.len(), average));
        prev = d;
    }
    Ok((holds, trace))
}

/// The demo's press: from the device at `-1 mm` along `line` at a constant `speed_m_per_s` to
/// `depth_m`, then a hold of `hold_s` (the force averaged over the hold's last half). Returns
/// the hold's report and the trace.
///
/// # Errors
/// As [`staircase`]; also a non-positive speed.
pub fn constant_speed_press(
    body: &mut dyn SoftBody,
    line: &PressLine,
    depth_m: f64,
    speed_m_per_s: f64,
    hold_s: f64,
    tick_s: f64,
) -> Result<(HoldReport, PressTrace), ModelError> {
    check_timing(tick_s, "press", &[hold_s])?;
    if !(speed_m_per_s > 0.0) || !depth_m.is_finite() {
        return Err(ModelError::InvalidInput(format!(
            "press: speed {speed_m_per_s} m/s must be positive and depth {depth_m} m finite"
        )));
    }
    let start = -1e-3;
    let travel = ticks_of((depth_m - start) / speed_m_per_s, tick_s).max(1);
    let hold = ticks_of(hold_s, tick_s);
    let mut trace = PressTrace::with_capacity(travel + hold + 1);
    let v = line.direction * speed_m_per_s;
    for k in 0..=travel {
        let d = start + (depth_m - start) * k as f64 / travel as f64;
        trace.tick(
            body,
            line.device_at(d),
            if k == travel { DVec3::ZERO } else { v },
        )?;
    }
    let s = trace.force_n.len();
    for _ in 0..hold {
        trace.tick(body, line.device_at(depth_m), DVec3::ZERO)?;
    }
    let report = trace.hold_report(line, depth_m, s..trace.force_n.len(), hold / 2);
    Ok((report, trace))
}

/// A slide along a circle: the device at `radius_m` from the axis through `centre_m` along
/// `axis` (unit), in the plane through `centre_m` normal to the axis, starting in the direction
/// `start_dir` (unit, normal to the axis) from the axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Circle {
    /// A point of the axis in the circle's plane, m.
    pub centre_m: DVec3,
    /// The axis.
    pub axis: DVec3,
    /// Where the circle starts, seen from the axis.
    pub start_dir: DVec3,
    /// Radius of the device's circle, m.
    pub radius_m: f64,
}

impl Circle {
    /// Device position at angle `theta` (rad) from the start, turning right-handed about the
    /// axis.
    pub fn at(&self, theta: f64) -> DVec3 {
        let b = self.axis.cross(self.start_dir);
        self.centre_m + (self.start_dir * theta.cos() + b * theta.sin()) * self.radius_m
    }

    /// Unit tangent at angle `theta`.
    pub fn tangent(&self, theta: f64) -> DVec3 {
        let b = self.axis.cross(self.start_dir);
        -self.start_dir * theta.sin() + b * theta.cos()
    }
}

/// What a stroke felt like.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StrokeReport {
    /// The hold before the slide (its force is the reference for the slide's changes).
    pub hold: HoldReport,
    /// Largest tick-to-tick change of the device force during the slide, N.
    pub max_tick_change_n: f64,
    /// Smallest and largest device force magnitude during the slide, N.
    pub force_min_n: f64,
    /// See `force_min_n`.
    pub force_max_n: f64,
    /// Ticks of the slide, and those in contact.
    pub slide_ticks: usize,
    /// See `slide_ticks`.
    pub contact_ticks: usize,
}

/// A stroke: pressed along `line` to `depth_m` (ramp 0.5 s, hold 0.5 s), then slid along
/// `circle` (which must start at that device position) at `speed_m_per_s` through `angle_rad`,
/// ticked at `tick_s`.
///
/// # Errors
/// As [`staircase`]; also a non-positive speed or angle.
pub fn stroke(
    body: &mut dyn SoftBody,
    line: &PressLine,
    depth_m: f64,
    circle: &Circle,
    speed_m_per_s: f64,
    angle_rad: f64,
    tick_s: f64,
) -> Result<(StrokeReport, PressTrace), ModelError> {
    if !(speed_m_per_s > 0.0 && angle_rad > 0.0 && circle.radius_m > 0.0) {
        return Err(ModelError::InvalidInput(format!(
            "stroke: speed {speed_m_per_s} m/s, angle {angle_rad} rad and radius {} m must be \
             positive",
            circle.radius_m
        )));
    }
    let params = HoldParams {
        ramp_s: 0.5,
        hold_s: 0.5,
        average_s: 0.25,
    };
    let (holds, mut trace) = staircase(body, line, &[depth_m], &params, tick_s)?;
    let ticks = ticks_of(angle_rad * circle.radius_m / speed_m_per_s, tick_s).max(1);
    let start = trace.force_n.len();
    for k in 1..=ticks {
        let theta = angle_rad * k as f64 / ticks as f64;
        let v = circle.tangent(theta) * speed_m_per_s;
        trace.tick(body, circle.at(theta), v)?;
    }
    let slide = start..trace.force_n.len();
    let mags = trace.force_n[slide.clone()].iter().map(|f| f.length());
    let report = StrokeReport {
        hold: holds[0],
        max_tick_change_n: trace.max_tick_change_n(slide.clone()),
        force_min_n: mags.clone().fold(f64::INFINITY, f64::min),
        force_max_n: mags.fold(0.0, f64::max),
        slide_ticks: slide.len(),
        contact_ticks: trace.force_n[slide]
            .iter()
            .filter(|f| **f != DVec3::ZERO)
            .count(),
    };
    Ok((report, trace))
}

/// The left ventricle's stroke of issue 46: the lv-probe press to `depth_m`, then half way
/// round the ventricle at the probe's height (`z = -5 mm`, the device circle through the
/// pressed device position, around the long axis).
///
/// # Errors
/// As [`stroke`].
pub fn lv_half_turn(
    body: &mut dyn SoftBody,
    radius_m: f64,
    depth_m: f64,
    speed_m_per_s: f64,
    tick_s: f64,
) -> Result<(StrokeReport, PressTrace), ModelError> {
    let line = PressLine::lv_probe(radius_m);
    let pressed = line.device_at(depth_m);
    let circle = Circle {
        centre_m: DVec3::new(0.0, 0.0, LV_PROBE_Z_M),
        axis: DVec3::Z,
        start_dir: DVec3::X,
        radius_m: pressed.x,
    };
    stroke(
        body,
        &line,
        depth_m,
        &circle,
        speed_m_per_s,
        std::f64::consts::PI,
        tick_s,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lv_probe_depth_zero_touches_the_analytic_epicardium() {
        let r = 2e-3;
        let line = PressLine::lv_probe(r);
        let c = line.device_at(0.0);
        // The epicardium's point on the line lies exactly one radius beyond the centre.
        let on = c + line.direction * r;
        let (a, b) = (10e-3, 20e-3);
        let level = (on.x * on.x + on.y * on.y) / (a * a) + on.z * on.z / (b * b);
        assert!((level - 1.0).abs() < 1e-12, "{level}");
        assert!((line.depth_of(line.device_at(1.5e-3)) - 1.5e-3).abs() < 1e-15);
    }

    #[test]
    fn an_epicardium_line_touches_the_analytic_surface_at_depth_zero() {
        let r = 2e-3;
        let (p, n) = lv_epicardium_point(-12e-3, 1.0);
        let (a, c) = LV_EPICARDIUM_SEMI_AXES_M;
        let level = |q: DVec3| (q.x * q.x + q.y * q.y) / (a * a) + q.z * q.z / (c * c);
        assert!((level(p) - 1.0).abs() < 1e-12);
        let line = PressLine::at_surface_point(p, n, r);
        let centre = line.device_at(0.0);
        assert!((centre + n * r - p).length() < 1e-15);
        // The sphere there touches the ellipsoid only at p: points of the sphere around the
        // contact lie outside (level > 1), the contact point on it.
        for k in 0..64 {
            let t = k as f64 * 0.1;
            let u = n.any_orthonormal_pair();
            let dir = (n + (u.0 * t.cos() + u.1 * t.sin()) * 0.3).normalize();
            assert!(level(centre + dir * r) >= 1.0 - 1e-12, "{k}");
        }
        // Along the lv-probe line the same constructor gives the lv-probe line's depth zero.
        let lv = PressLine::lv_probe(r);
        let q = PressLine::at_surface_point(
            DVec3::new(LV_PROBE_SURFACE_X_M, 0.0, LV_PROBE_Z_M),
            DVec3::NEG_X,
            r,
        );
        assert!((lv.device_at(0.7e-3) - q.device_at(0.7e-3)).length() < 1e-15);
    }

    #[test]
    fn quantiles_take_the_nearest_rank() {
        let v = [5.0, 1.0, 3.0, 2.0, 4.0];
        assert_eq!(quantile(&v, 0.0), 1.0);
        assert_eq!(quantile(&v, 0.5), 3.0);
        assert_eq!(quantile(&v, 1.0), 5.0);
        assert_eq!(quantile(&[], 0.5), 0.0);
    }

    #[test]
    fn the_circle_starts_on_its_radius_and_turns_about_the_axis() {
        let c = Circle {
            centre_m: DVec3::new(0.0, 0.0, -5e-3),
            axis: DVec3::Z,
            start_dir: DVec3::X,
            radius_m: 0.01,
        };
        assert!((c.at(0.0) - DVec3::new(0.01, 0.0, -5e-3)).length() < 1e-15);
        assert!(
            (c.at(std::f64::consts::FRAC_PI_2) - DVec3::new(0.0, 0.01, -5e-3)).length() < 1e-15
        );
        // The tangent is the derivative of the position over the radius.
        let h = 1e-6;
        let fd = (c.at(0.3 + h) - c.at(0.3 - h)) / (2.0 * h * c.radius_m);
        assert!((fd - c.tangent(0.3)).length() < 1e-8);
    }
}
