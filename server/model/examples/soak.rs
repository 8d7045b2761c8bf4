//! One-hour soak (issue 3, section 3, the long version of the stability suite): the daemon's
//! default interactive configuration (the built-in `lv` scene exactly as `load_builtin("lv")`
//! gives it) runs 3 600 000 servo ticks of 1 ms (one simulated hour) while a random but
//! reproducible probe path presses, slides over and leaves the epicardium. Claims checked:
//!
//! - **no NaN**: every tick returns `Ok`, its device force and the kinetic energy are finite,
//!   and the state is finite at every [`CADENCE_TICKS`] check;
//! - **rest shape recovered**: at every settle check (every [`SETTLE_EVERY_TICKS`] and at the
//!   end) the probe has withdrawn out of contact and the body has had [`SETTLE_TICKS`] to
//!   settle; the largest nodal distance from the rest shape must then be below
//!   [`REST_TOLERANCE_M`];
//! - **no energy growth**: at every settle check the total energy (kinetic + elastic) is below
//!   [`SETTLED_ENERGY_LIMIT_J`], it fell during the second half of the settle (the body without
//!   the probe is a passive, damped system), and the settled energies do not trend up over the
//!   run (a log-linear fit through the checks, energies below [`AT_REST_ENERGY_J`] counted as
//!   that value, grows by at most [`MAX_TREND_FACTOR`] from first to last check).
//!
//! Probe path ([`ProbePath`]): waypoints on the epicardium (the ellipsoid with semi-axes 10, 10,
//! 20 mm of the `lv` mesh, around the equator and the lower wall, z in [`Z_RANGE_M`]), each a
//! direction (azimuth, height) and a depth of the device point below the rest surface along
//! the outward normal (0 to 4 mm, or 0.5 to 3 mm clear of it), joined by smoothstep
//! interpolation over 0.2 to 2 s (longer when needed to keep the hand speed below
//! [`PLAN_SPEED_M_PER_S`]); the reported device velocity is the time derivative of the path.
//! Before each settle check the probe withdraws along the normal to 3 mm clear and is held
//! still.
//!
//! Measured per simulated minute: tick wall time p50 / p99 / max (an HDR histogram at 1 us
//! resolution, no per-tick allocation), peak kinetic energy, peak elastic energy and inverted
//! elements (at the [`CADENCE_TICKS`] cadence: the elastic energy costs a force evaluation),
//! peak displacement and device force, contact time.
//!
//! Run: `cargo run --release -p haptic-model --example soak` (6 to 10 min on one core: 3.6 M
//! ticks at the `lv` tick cost plus the checks). `-- --minutes N` for a shorter (or longer)
//! run, `-- --quick` for 2 minutes, `-- --seed S` for another path. Writes
//! `target/bench/soak-<N>min.json` (or into `--out DIR`); `-- --publish` writes the committed
//! `docs/bench/soak.json` instead, and only for a run of at least the full 60 minutes. Exits
//! with status 1 when a verdict fails.
//!
//! An example rather than an ignored test: it takes options (length, seed, output), prints a
//! line per simulated minute for up to an hour, and writes a result to publish; its verdicts are
//! its exit status. The short stability suite runs with `cargo test` (`tests/stability.rs`).

#[path = "../benches/common/mod.rs"]
mod common;

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use clap::Parser;
use common::{Percentiles, TickTimes, git_commit, smoothstep, smoothstep_rate};
use haptic_model::DVec3;
use haptic_model::fem::{FemBody, TickInput};
use haptic_model::scene::load_builtin;

/// Servo tick, s (the `lv` scene's `integrator.tick_s`; checked at start).
const TICK_S: f64 = 1e-3;
/// Ticks per simulated minute.
const TICKS_PER_MINUTE: u64 = 60_000;
/// Default run length, simulated minutes (one hour, 3.6 M ticks).
const DEFAULT_MINUTES: u64 = 60;
/// Length of `--quick`, simulated minutes.
const QUICK_MINUTES: u64 = 2;
/// Default seed of the probe path.
const DEFAULT_SEED: u64 = 0x50a4_2026;

/// Cadence of the state checks that cost a force evaluation (elastic energy, inverted elements,
/// finiteness of every position and velocity): once per simulated second.
const CADENCE_TICKS: u64 = 1000;
/// A settle check every five simulated minutes (and one at the end of the run).
const SETTLE_EVERY_TICKS: u64 = 300_000;
/// The probe is held out of contact this long before each settle check (2 s).
const SETTLE_TICKS: u64 = 2000;
/// Shortest withdrawal before a settle (the last random segment ends early enough).
const WITHDRAW_MIN_TICKS: u64 = 500;

/// Rest-shape tolerance after a settle: the 0.1 mm.
const REST_TOLERANCE_M: f64 = 1e-4;
/// Upper bound of the settled total energy, J. A residual dent at the 0.1 mm tolerance stores
/// about `k u^2 / 2` with the wall's probe stiffness `k` of 10 to 20 N/m (0.05 N at 3 mm), i.e.
/// 5e-8 to 1e-7 J; a body that has settled holds far less than that.
const SETTLED_ENERGY_LIMIT_J: f64 = 1e-8;
/// Settled energies below this count as at rest for the trend (J): the energy of a residual
/// dent of about 4 um (`k u^2 / 2` with `k` = 15 N/m), far below anything a hand or an eye
/// could notice. The exponential tail of the last press left after the settle varies over many
/// decades with how and when the probe left (1e-30 to 1e-11 J in trial runs); fitting a trend
/// to that tail would measure the random path, not the integrator.
const AT_REST_ENERGY_J: f64 = 1e-10;
/// Energies below this are round-off (J): the decay check does not judge them. Round-off of
/// 1e-18 m in the positions of the 338 nodes stores about 1e-33 J.
const ROUND_OFF_ENERGY_J: f64 = 1e-30;
/// Largest accepted growth of the settled energy over the run, from a log-linear fit through
/// all settle checks (first to last fitted value).
const MAX_TREND_FACTOR: f64 = 10.0;

/// Epicardium of the built-in `lv` mesh: ellipsoid semi-axes (x = y, z), m, cut at z = 5 mm.
const EPI_SEMI_AXES_M: (f64, f64) = (0.010, 0.020);
/// Height range of the probe waypoints on the epicardium, m: the lower wall up to the equator
/// (z = 0), clear of the clamped base at z = 5 mm and of the apex at z = -20 mm.
const Z_RANGE_M: (f64, f64) = (-0.015, 0.0);
/// Device depth below the rest surface at a pressing waypoint, m.
const PRESS_DEPTH_M: (f64, f64) = (0.0, 0.004);
/// Device clearance above the rest surface at a non-contact waypoint, m (as negative depth).
const CLEAR_DEPTH_M: (f64, f64) = (-0.003, -0.0005);
/// Depth of the device while the body settles, m: 3 mm clear of the rest surface.
const SETTLE_DEPTH_M: f64 = -0.003;
/// Probability that a waypoint is clear of the surface.
const P_CLEAR: f64 = 0.2;
/// Probability that a segment holds still at its start.
const P_HOLD: f64 = 0.1;
/// Largest azimuth change between waypoints, rad.
const MAX_DTHETA_RAD: f64 = 1.2;
/// Random segment duration range, ticks (0.2 to 2 s).
const SEGMENT_TICKS: (u64, u64) = (200, 2000);
/// Planning speed bound of the device point, m/s (the hand bound is 0.1 m/s; the margin covers
/// the approximations of [`path_length_bound_m`]). The measured maximum is reported.
const PLAN_SPEED_M_PER_S: f64 = 0.095;
/// Largest device speed accepted as a plausible hand motion, m/s (reported, not a verdict).
const HAND_SPEED_M_PER_S: f64 = 0.1;

/// One-hour soak of the default interactive configuration (built-in `lv`) under a random,
/// reproducible probe path; exits with status 1 when a verdict fails.
#[derive(Debug, Parser)]
#[command(name = "soak")]
struct Args {
    /// Simulated minutes.
    #[arg(long, default_value_t = DEFAULT_MINUTES, value_parser = clap::value_parser!(u64).range(1..))]
    minutes: u64,
    /// A 2-minute smoke test (--minutes 2).
    #[arg(long, conflicts_with = "minutes")]
    quick: bool,
    /// Seed of the probe path.
    #[arg(long, default_value_t = DEFAULT_SEED)]
    seed: u64,
    /// Folder of soak-<N>min.json [default: target/bench of the workspace].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write docs/bench/soak.json, the committed result, instead (runs of at least 60 minutes).
    #[arg(long, conflicts_with = "out")]
    publish: bool,
}

/// Checked run configuration from the command line.
#[derive(Debug, Clone)]
struct SoakConfig {
    /// Simulated minutes.
    minutes: u64,
    /// Probe path seed.
    seed: u64,
    /// The result file.
    output: PathBuf,
}

impl SoakConfig {
    /// Validates the arguments.
    fn new(args: Args) -> Result<Self, String> {
        let minutes = if args.quick {
            QUICK_MINUTES
        } else {
            args.minutes
        };
        let output = if args.publish {
            if minutes < DEFAULT_MINUTES {
                return Err(format!(
                    "--publish replaces the committed {DEFAULT_MINUTES}-minute result: run at least {DEFAULT_MINUTES} minutes"
                ));
            }
            common::workspace_root().join("docs/bench/soak.json")
        } else {
            args.out
                .unwrap_or_else(common::default_out_dir)
                .join(format!("soak-{minutes}min.json"))
        };
        Ok(Self {
            minutes,
            seed: args.seed,
            output,
        })
    }

    fn total_ticks(&self) -> u64 {
        self.minutes * TICKS_PER_MINUTE
    }

    /// Tick counts after which a settle check is made: every [`SETTLE_EVERY_TICKS`] and at the
    /// end.
    fn settle_ticks(&self) -> Vec<u64> {
        let total = self.total_ticks();
        let mut v: Vec<u64> = (1..)
            .map(|k| k * SETTLE_EVERY_TICKS)
            .take_while(|&t| t < total)
            .collect();
        v.push(total);
        v
    }
}

// ---------------------------------------------------------------- random probe path

/// SplitMix64 (Steele, Lea, Flood, OOPSLA 2014): a small, fast, reproducible generator.
#[derive(Debug, Clone)]
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[lo, hi)`.
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        let u = (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        lo + (hi - lo) * u
    }

    /// Uniform integer in `[lo, hi]`.
    fn range(&mut self, lo: u64, hi: u64) -> u64 {
        lo + self.next_u64() % (hi - lo + 1)
    }
}

/// A probe waypoint: a direction on the epicardium and the device depth below it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Waypoint {
    /// Azimuth about the long axis, rad.
    theta_rad: f64,
    /// Height of the surface point, m.
    z_m: f64,
    /// Depth of the device point below the rest surface along the outward normal, m (negative:
    /// clear of it).
    depth_m: f64,
}

impl Waypoint {
    /// The device point: the epicardium point at (azimuth, height), plus the outward normal
    /// times `radius - depth`, so that at depth 0 the probe sphere touches the rest surface.
    fn device_m(&self, probe_radius_m: f64) -> DVec3 {
        let (a, c) = EPI_SEMI_AXES_M;
        let rho = a * (1.0 - (self.z_m / c).powi(2)).sqrt();
        let (s, co) = self.theta_rad.sin_cos();
        let p = DVec3::new(rho * co, rho * s, self.z_m);
        let n = DVec3::new(p.x / (a * a), p.y / (a * a), p.z / (c * c)).normalize();
        p + n * (probe_radius_m - self.depth_m)
    }

    fn lerp(&self, to: &Self, s: f64) -> Self {
        Self {
            theta_rad: self.theta_rad + (to.theta_rad - self.theta_rad) * s,
            z_m: self.z_m + (to.z_m - self.z_m) * s,
            depth_m: self.depth_m + (to.depth_m - self.depth_m) * s,
        }
    }
}

/// An upper estimate of the device path length between two waypoints, m: azimuth at the
/// largest distance from the axis (10 mm + 2 mm radius + 3 mm clearance), height with a factor
/// 1.6 for the meridian slope and the normal offset, depth as is.
fn path_length_bound_m(a: &Waypoint, b: &Waypoint) -> f64 {
    let r_max = EPI_SEMI_AXES_M.0 + 0.002 - CLEAR_DEPTH_M.0;
    let dt = (b.theta_rad - a.theta_rad) * r_max;
    let dz = (b.z_m - a.z_m) * 1.6;
    let dd = b.depth_m - a.depth_m;
    (dt * dt + dz * dz + dd * dd).sqrt()
}

/// One smoothstep segment of the probe path, over ticks `[start, end)`.
#[derive(Debug, Clone, Copy)]
struct Segment {
    start: u64,
    end: u64,
    from: Waypoint,
    to: Waypoint,
}

impl Segment {
    /// Device position (m) and velocity (m/s) at tick `k` (time `k * TICK_S`).
    fn sample(&self, k: u64, probe_radius_m: f64) -> (DVec3, DVec3) {
        let dur_s = (self.end - self.start) as f64 * TICK_S;
        let u = (k - self.start) as f64 * TICK_S / dur_s;
        let s = smoothstep(u);
        let p = self.from.lerp(&self.to, s).device_m(probe_radius_m);
        // d(device)/ds by a central difference (the path is smooth in s), times ds/dt.
        let h = 1e-6;
        let dp_ds = (self.from.lerp(&self.to, s + h).device_m(probe_radius_m)
            - self.from.lerp(&self.to, s - h).device_m(probe_radius_m))
            / (2.0 * h);
        (p, dp_ds * (smoothstep_rate(u) / dur_s))
    }
}

/// The random, reproducible probe path with withdrawals before the settle checks.
struct ProbePath {
    rng: SplitMix64,
    probe_radius_m: f64,
    current: Segment,
    /// Tick counts of the settle checks (see [`SoakConfig::settle_ticks`]).
    settles: Vec<u64>,
    next_settle: usize,
}

impl ProbePath {
    fn new(seed: u64, probe_radius_m: f64, settles: Vec<u64>) -> Self {
        // Start 3 mm clear of the equator, at rest.
        let start = Waypoint {
            theta_rad: 0.0,
            z_m: -0.005,
            depth_m: SETTLE_DEPTH_M,
        };
        Self {
            rng: SplitMix64(seed),
            probe_radius_m,
            current: Segment {
                start: 0,
                end: 0,
                from: start,
                to: start,
            },
            settles,
            next_settle: 0,
        }
    }

    /// The device input of tick `k` (ticks are asked for in order).
    fn input(&mut self, k: u64) -> TickInput {
        while k >= self.current.end {
            self.current = self.next_segment();
        }
        let (p, v) = self.current.sample(k, self.probe_radius_m);
        TickInput {
            device_position_m: Some(p),
            device_velocity_m_per_s: v,
        }
    }

    /// Commanded depth of the device below the rest surface at tick `k`, m.
    fn depth_m(&self, k: u64) -> f64 {
        let c = &self.current;
        let u = (k - c.start) as f64 / (c.end - c.start) as f64;
        c.from.lerp(&c.to, smoothstep(u)).depth_m
    }

    fn next_segment(&mut self) -> Segment {
        let start = self.current.end;
        let from = self.current.to;
        let random = self.random_segment(start, from);
        let Some(&check) = self.settles.get(self.next_settle) else {
            return random;
        };
        let hold_start = check - SETTLE_TICKS;
        if start >= hold_start {
            // Hold still, out of contact, until the check.
            self.next_settle += 1;
            Segment {
                start,
                end: check,
                from,
                to: from,
            }
        } else if random.end + WITHDRAW_MIN_TICKS > hold_start {
            // Withdraw along the normal to the settle clearance.
            let to = Waypoint {
                depth_m: SETTLE_DEPTH_M,
                ..from
            };
            Segment {
                start,
                end: hold_start,
                from,
                to,
            }
        } else {
            random
        }
    }

    fn random_segment(&mut self, start: u64, from: Waypoint) -> Segment {
        let rng = &mut self.rng;
        let ticks = rng.range(SEGMENT_TICKS.0, SEGMENT_TICKS.1);
        let to = if rng.uniform(0.0, 1.0) < P_HOLD {
            from
        } else {
            let depth_m = if rng.uniform(0.0, 1.0) < P_CLEAR {
                rng.uniform(CLEAR_DEPTH_M.0, CLEAR_DEPTH_M.1)
            } else {
                rng.uniform(PRESS_DEPTH_M.0, PRESS_DEPTH_M.1)
            };
            Waypoint {
                theta_rad: from.theta_rad + rng.uniform(-MAX_DTHETA_RAD, MAX_DTHETA_RAD),
                z_m: rng.uniform(Z_RANGE_M.0, Z_RANGE_M.1),
                depth_m,
            }
        };
        // Smoothstep peaks at 1.5 times the mean rate.
        let min_s = 1.5 * path_length_bound_m(&from, &to) / PLAN_SPEED_M_PER_S;
        let ticks = ticks.max((min_s / TICK_S).ceil() as u64);
        Segment {
            start,
            end: start + ticks,
            from,
            to,
        }
    }
}

// ---------------------------------------------------------------- statistics

/// Peaks over one simulated minute.
#[derive(Debug, Clone, Copy, Default)]
struct MinuteStats {
    minute: u64,
    tick_p50_us: f64,
    tick_p99_us: f64,
    tick_max_us: f64,
    ticks_over_1ms: u64,
    max_kinetic_energy_j: f64,
    /// At the [`CADENCE_TICKS`] cadence.
    max_elastic_energy_j: f64,
    max_displacement_m: f64,
    max_force_n: f64,
    /// At the [`CADENCE_TICKS`] cadence.
    max_inverted_elements: usize,
    contact_fraction: f64,
}

impl MinuteStats {
    fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "minute": self.minute,
            "tick_p50_us": num(self.tick_p50_us),
            "tick_p99_us": num(self.tick_p99_us),
            "tick_max_us": num(self.tick_max_us),
            "ticks_over_1ms": self.ticks_over_1ms,
            "max_kinetic_energy_j": num(self.max_kinetic_energy_j),
            "max_elastic_energy_j": num(self.max_elastic_energy_j),
            "max_displacement_mm": num(self.max_displacement_m * 1e3),
            "max_force_n": num(self.max_force_n),
            "max_inverted_elements": self.max_inverted_elements,
            "contact_fraction": num(self.contact_fraction),
        })
    }

    fn absorb(&mut self, o: &Self) {
        self.max_kinetic_energy_j = self.max_kinetic_energy_j.max(o.max_kinetic_energy_j);
        self.max_elastic_energy_j = self.max_elastic_energy_j.max(o.max_elastic_energy_j);
        self.max_displacement_m = self.max_displacement_m.max(o.max_displacement_m);
        self.max_force_n = self.max_force_n.max(o.max_force_n);
        self.max_inverted_elements = self.max_inverted_elements.max(o.max_inverted_elements);
    }
}

/// The state after a withdrawal and [`SETTLE_TICKS`] without contact.
#[derive(Debug, Clone, Copy)]
struct SettleCheck {
    time_s: f64,
    residual_displacement_m: f64,
    kinetic_energy_j: f64,
    elastic_energy_j: f64,
    /// Total energy half-way through the settle, J (for the decay check).
    mid_total_energy_j: f64,
    inverted_elements: usize,
    /// Time since the probe last touched the surface, s.
    out_of_contact_s: f64,
}

impl SettleCheck {
    fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "time_s": self.time_s,
            "max_residual_displacement_mm": num(self.residual_displacement_m * 1e3),
            "kinetic_energy_j": num(self.kinetic_energy_j),
            "elastic_energy_j": num(self.elastic_energy_j),
            "total_energy_j": num(self.total_energy_j()),
            "total_energy_mid_settle_j": num(self.mid_total_energy_j),
            "inverted_elements": self.inverted_elements,
            "out_of_contact_s": self.out_of_contact_s,
        })
    }

    fn total_energy_j(&self) -> f64 {
        self.kinetic_energy_j + self.elastic_energy_j
    }

    /// Energy fell during the second half of the settle (or both values are round-off).
    fn decaying(&self) -> bool {
        let e = self.total_energy_j();
        e < self.mid_total_energy_j || e.max(self.mid_total_energy_j) < ROUND_OFF_ENERGY_J
    }
}

/// The first failure: a tick error or a non-finite quantity.
#[derive(Debug, Clone)]
struct Failure {
    time_s: f64,
    what: String,
}

/// Growth factor of the settled total energy over the run from a least-squares line through
/// `(time, log10 E)` (energies floored at [`AT_REST_ENERGY_J`]); `None` with fewer than 3
/// checks.
fn energy_trend_factor(checks: &[SettleCheck]) -> Option<f64> {
    if checks.len() < 3 {
        return None;
    }
    let pts: Vec<(f64, f64)> = checks
        .iter()
        .map(|c| (c.time_s, c.total_energy_j().max(AT_REST_ENERGY_J).log10()))
        .collect();
    let n = pts.len() as f64;
    let (mt, me) = (
        pts.iter().map(|p| p.0).sum::<f64>() / n,
        pts.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let sxy: f64 = pts.iter().map(|p| (p.0 - mt) * (p.1 - me)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mt).powi(2)).sum();
    let span = pts[pts.len() - 1].0 - pts[0].0;
    Some(10f64.powf(sxy / sxx * span))
}

/// The thresholds the verdicts use.
fn limits_json() -> serde_json::Value {
    serde_json::json!({
        "rest_tolerance_mm": REST_TOLERANCE_M * 1e3,
        "settle_s": SETTLE_TICKS as f64 * TICK_S,
        "settle_every_s": SETTLE_EVERY_TICKS as f64 * TICK_S,
        "settled_energy_limit_j": SETTLED_ENERGY_LIMIT_J,
        "at_rest_energy_j": AT_REST_ENERGY_J,
        "round_off_energy_j": ROUND_OFF_ENERGY_J,
        "max_trend_factor": MAX_TREND_FACTOR,
    })
}

fn num(v: f64) -> serde_json::Value {
    if v.is_finite() {
        serde_json::json!(v)
    } else {
        serde_json::Value::Null
    }
}

fn hms(s: f64) -> String {
    let s = s.max(0.0).round() as u64;
    format!("{}:{:02}:{:02}", s / 3600, s / 60 % 60, s % 60)
}

/// What the summary and the JSON say about the model and the run's setup.
struct Setup {
    commit: String,
    nodes: usize,
    tets: usize,
    material: String,
    integrator: String,
    substeps: u32,
    sub_dt_s: f64,
    critical_dt_s: f64,
    total: u64,
}

/// The accumulators of one run.
struct Run {
    settles: Vec<u64>,
    hist_all: TickTimes,
    hist_min: TickTimes,
    minute: MinuteStats,
    overall: MinuteStats,
    minutes: Vec<MinuteStats>,
    checks: Vec<SettleCheck>,
    failure: Option<Failure>,
    contact_ticks: u64,
    contact_total: u64,
    episodes: u64,
    out_of_contact_ticks: u64,
    max_depth_m: f64,
    max_speed: f64,
    max_stretch_m: f64,
    mid_energy: f64,
    next_settle: usize,
    ticks_run: u64,
    wall_s: f64,
}

impl Run {
    fn new(cfg: &SoakConfig, settles: Vec<u64>) -> Self {
        Self {
            hist_all: TickTimes::new(),
            hist_min: TickTimes::new(),
            minute: MinuteStats::default(),
            overall: MinuteStats::default(),
            minutes: Vec::with_capacity(cfg.minutes as usize),
            checks: Vec::with_capacity(settles.len()),
            settles,
            failure: None,
            contact_ticks: 0,
            contact_total: 0,
            episodes: 0,
            out_of_contact_ticks: u64::MAX,
            max_depth_m: 0.0,
            max_speed: 0.0,
            max_stretch_m: 0.0,
            mid_energy: f64::NAN,
            next_settle: 0,
            ticks_run: 0,
            wall_s: 0.0,
        }
    }

    /// Runs the ticks until the end or the first failure.
    fn run(&mut self, cfg: &SoakConfig, sim: &mut FemBody, path: &mut ProbePath, kc: f64) {
        let total = cfg.total_ticks();
        let wall = Instant::now();
        for k in 0..total {
            if let Err(f) = self.tick(k, sim, path, kc) {
                self.failure = Some(f);
                break;
            }
            let done = k + 1;
            if done % TICKS_PER_MINUTE == 0 {
                self.end_minute(cfg, done, wall.elapsed().as_secs_f64());
            }
        }
        // A run that stopped mid-minute still counts its partial minute in the peaks.
        self.overall.absorb(&self.minute);
        self.overall.contact_fraction =
            (self.contact_total + self.contact_ticks) as f64 / self.ticks_run.max(1) as f64;
        self.wall_s = wall.elapsed().as_secs_f64();
    }

    /// One servo tick `k`: its time, the per-minute peaks, the contact accounting and the state
    /// checks due after it.
    fn tick(
        &mut self,
        k: u64,
        sim: &mut FemBody,
        path: &mut ProbePath,
        kc: f64,
    ) -> Result<(), Failure> {
        let input = path.input(k);
        self.max_depth_m = self.max_depth_m.max(path.depth_m(k));
        self.max_speed = self.max_speed.max(input.device_velocity_m_per_s.length());
        let t0 = Instant::now();
        let result = sim.tick(&input);
        let elapsed = t0.elapsed();
        let time_s = (k + 1) as f64 * TICK_S;
        let out = result.map_err(|e| Failure {
            time_s,
            what: format!("tick returned an error: {e}"),
        })?;
        self.ticks_run = k + 1;
        self.hist_all.record(elapsed);
        self.hist_min.record(elapsed);
        let force = out.force_on_device_n.length();
        let ke = sim.kinetic_energy_j();
        if !force.is_finite() || !ke.is_finite() {
            return Err(Failure {
                time_s,
                what: format!("non-finite device force ({force}) or kinetic energy ({ke})"),
            });
        }
        let minute = &mut self.minute;
        minute.max_force_n = minute.max_force_n.max(force);
        minute.max_kinetic_energy_j = minute.max_kinetic_energy_j.max(ke);
        minute.max_displacement_m = minute.max_displacement_m.max(sim.max_displacement_m());
        if out.in_contact {
            self.contact_ticks += 1;
            // A new episode after at least 10 ms without contact (grazing flicker is not one).
            if self.out_of_contact_ticks >= 10 {
                self.episodes += 1;
            }
            self.out_of_contact_ticks = 0;
            self.max_stretch_m = self.max_stretch_m.max(force / kc);
        } else {
            self.out_of_contact_ticks = self.out_of_contact_ticks.saturating_add(1);
        }
        self.check_state(sim, k + 1, time_s)
    }

    /// The state checks after `done` ticks: at the [`CADENCE_TICKS`] cadence, mid-settle and at
    /// a settle check.
    fn check_state(&mut self, sim: &FemBody, done: u64, time_s: f64) -> Result<(), Failure> {
        let settle_at = self.settles.get(self.next_settle).copied();
        let cadence = done.is_multiple_of(CADENCE_TICKS);
        if !(cadence || settle_at == Some(done) || settle_at == Some(done + SETTLE_TICKS / 2)) {
            return Ok(());
        }
        let st = sim.stability();
        if !st.finite {
            return Err(Failure {
                time_s,
                what: "non-finite position or velocity".into(),
            });
        }
        let minute = &mut self.minute;
        minute.max_elastic_energy_j = minute.max_elastic_energy_j.max(st.elastic_energy_j);
        minute.max_inverted_elements = minute.max_inverted_elements.max(st.inverted_elements);
        let total_e = st.kinetic_energy_j + st.elastic_energy_j;
        if settle_at == Some(done + SETTLE_TICKS / 2) {
            self.mid_energy = total_e;
        }
        if settle_at == Some(done) {
            let c = SettleCheck {
                time_s,
                residual_displacement_m: st.max_displacement_m,
                kinetic_energy_j: st.kinetic_energy_j,
                elastic_energy_j: st.elastic_energy_j,
                mid_total_energy_j: self.mid_energy,
                inverted_elements: st.inverted_elements,
                out_of_contact_s: self.out_of_contact_ticks.min(done) as f64 * TICK_S,
            };
            println!(
                "  settle check at {:>6.1} min: residual {:.3e} mm, kinetic {:.3e} J, elastic {:.3e} J (total {:.3e} J, {:.3e} J mid-settle), {} inverted, {:.2} s out of contact",
                time_s / 60.0,
                c.residual_displacement_m * 1e3,
                c.kinetic_energy_j,
                c.elastic_energy_j,
                c.total_energy_j(),
                c.mid_total_energy_j,
                c.inverted_elements,
                c.out_of_contact_s
            );
            self.checks.push(c);
            self.next_settle += 1;
        }
        Ok(())
    }

    /// Closes the simulated minute ending after `done` ticks: prints its line and starts the
    /// next.
    fn end_minute(&mut self, cfg: &SoakConfig, done: u64, wall_s: f64) {
        let total = cfg.total_ticks();
        let minute = &mut self.minute;
        minute.minute = done / TICKS_PER_MINUTE;
        let p = self.hist_min.percentiles();
        minute.tick_p50_us = p.p50_us;
        minute.tick_p99_us = p.p99_us;
        minute.tick_max_us = p.max_us;
        minute.ticks_over_1ms = self.hist_min.count_at_least_us(1000);
        minute.contact_fraction = self.contact_ticks as f64 / TICKS_PER_MINUTE as f64;
        println!(
            "minute {:>3}/{}: wall {} ETA {} | tick p50 {:>4.0} p99 {:>5.0} max {:>6.0} us | KE max {:.2e} J, elastic max {:.2e} J, disp max {:.2} mm, force max {:.3} N, contact {:>3.0} %, inverted {}",
            minute.minute,
            cfg.minutes,
            hms(wall_s),
            hms(wall_s / done as f64 * (total - done) as f64),
            minute.tick_p50_us,
            minute.tick_p99_us,
            minute.tick_max_us,
            minute.max_kinetic_energy_j,
            minute.max_elastic_energy_j,
            minute.max_displacement_m * 1e3,
            minute.max_force_n,
            minute.contact_fraction * 100.0,
            minute.max_inverted_elements
        );
        self.overall.absorb(&self.minute);
        self.contact_total += self.contact_ticks;
        self.minutes.push(self.minute);
        self.minute = MinuteStats::default();
        self.hist_min.reset();
        self.contact_ticks = 0;
    }
}

/// The run's verdicts.
struct Verdicts {
    no_nan: bool,
    rest_recovered: bool,
    decaying: bool,
    no_energy_growth: bool,
    trend: Option<f64>,
}

impl Verdicts {
    fn of(run: &Run, total: u64) -> Self {
        let checks = &run.checks;
        let completed = run.failure.is_none() && run.ticks_run == total;
        let no_nan = run.failure.is_none();
        let rest_recovered = completed
            && checks.len() == run.settles.len()
            && checks
                .iter()
                .all(|c| c.residual_displacement_m < REST_TOLERANCE_M);
        let trend = energy_trend_factor(checks);
        let energies_small = checks
            .iter()
            .all(|c| c.total_energy_j() < SETTLED_ENERGY_LIMIT_J);
        let decaying = checks.iter().all(SettleCheck::decaying);
        let no_trend = trend.is_none_or(|f| f <= MAX_TREND_FACTOR);
        let no_energy_growth =
            completed && !checks.is_empty() && energies_small && decaying && no_trend;
        Self {
            no_nan,
            rest_recovered,
            decaying,
            no_energy_growth,
            trend,
        }
    }

    fn all_pass(&self) -> bool {
        self.no_nan && self.rest_recovered && self.no_energy_growth
    }
}

/// The summary printed at the end: totals, peaks and the verdict table.
fn summary_table(setup: &Setup, run: &Run, v: &Verdicts) -> String {
    let Percentiles {
        p50_us: p50,
        p99_us: p99,
        max_us: tick_max,
    } = run.hist_all.percentiles();
    let over_budget = run.hist_all.count_at_least_us(1000);
    let (overall, ticks_run) = (&run.overall, run.ticks_run);
    let mut table = String::new();
    let _ = writeln!(
        table,
        "\nsoak of lv ({} nodes, {} tets, {} x{}): {ticks_run} of {} ticks ({:.1} simulated min) in {} wall",
        setup.nodes,
        setup.tets,
        setup.integrator,
        setup.substeps,
        setup.total,
        ticks_run as f64 * TICK_S / 60.0,
        hms(run.wall_s)
    );
    let _ = writeln!(
        table,
        "  tick p50 {p50:.0} us, p99 {p99:.0} us, max {tick_max:.0} us, {over_budget} ticks over 1 ms"
    );
    let _ = writeln!(
        table,
        "  probe: {} contact episodes, in contact {:.1} % of the time, max depth {:.2} mm below rest surface, max force {:.4} N, max device speed {:.3} m/s{}",
        run.episodes,
        overall.contact_fraction * 100.0,
        run.max_depth_m * 1e3,
        overall.max_force_n,
        run.max_speed,
        if run.max_speed > HAND_SPEED_M_PER_S {
            " (ABOVE the 0.1 m/s hand bound)"
        } else {
            ""
        }
    );
    let _ = writeln!(
        table,
        "  peaks: displacement {:.3} mm, kinetic {:.3e} J, elastic {:.3e} J, inverted elements {}",
        overall.max_displacement_m * 1e3,
        overall.max_kinetic_energy_j,
        overall.max_elastic_energy_j,
        overall.max_inverted_elements
    );
    if let Some(f) = &run.failure {
        let _ = writeln!(table, "  FAILURE at {:.3} s: {}", f.time_s, f.what);
    }
    verdict_table(&mut table, run, v);
    table
}

/// The verdict lines of [`summary_table`].
fn verdict_table(table: &mut String, run: &Run, v: &Verdicts) {
    let checks = &run.checks;
    let worst_residual = checks
        .iter()
        .map(|c| c.residual_displacement_m)
        .fold(0.0, f64::max);
    let worst_energy = checks
        .iter()
        .map(SettleCheck::total_energy_j)
        .fold(0.0, f64::max);
    let verdict = |ok: bool| if ok { "PASS" } else { "FAIL" };
    let _ = writeln!(table, "  {:<18} {:<6} detail", "verdict", "");
    let _ = writeln!(
        table,
        "  {:<18} {:<6} {}",
        "no_nan",
        verdict(v.no_nan),
        run.failure
            .as_ref()
            .map_or("every tick Ok and finite".into(), |f| f.what.clone())
    );
    let _ = writeln!(
        table,
        "  {:<18} {:<6} worst residual {:.3e} mm over {} settle checks (limit {} mm)",
        "rest_recovered",
        verdict(v.rest_recovered),
        worst_residual * 1e3,
        checks.len(),
        REST_TOLERANCE_M * 1e3
    );
    let _ = writeln!(
        table,
        "  {:<18} {:<6} worst settled energy {:.3e} J (limit {:.0e} J), decaying in every settle: {}, fitted growth over the run: {}",
        "no_energy_growth",
        verdict(v.no_energy_growth),
        worst_energy,
        SETTLED_ENERGY_LIMIT_J,
        v.decaying,
        v.trend
            .map_or("n/a (fewer than 3 checks)".into(), |f| format!(
                "x{f:.3} (limit x{MAX_TREND_FACTOR})"
            ))
    );
}

/// The result file's content.
fn result_json(cfg: &SoakConfig, setup: &Setup, run: &Run, v: &Verdicts) -> serde_json::Value {
    let mut json = serde_json::json!({
        "benchmark": "soak",
        "command": format!(
            "cargo run --release -p haptic-model --example soak -- --minutes {} --seed {}",
            cfg.minutes, cfg.seed
        ),
        "commit": setup.commit,
        "scene": "lv (built-in, load_builtin(\"lv\"): the daemon's default interactive configuration)",
        "nodes": setup.nodes,
        "tets": setup.tets,
        "material": setup.material,
        "integrator": setup.integrator,
        "substeps": setup.substeps,
        "sub_dt_s": setup.sub_dt_s,
        "critical_dt_s": setup.critical_dt_s,
        "tick_s": TICK_S,
        "seed": cfg.seed,
        "minutes": cfg.minutes,
        "ticks": setup.total,
        "ticks_run": run.ticks_run,
        "wall_s": run.wall_s,
    });
    if let (Some(all), serde_json::Value::Object(r)) = (json.as_object_mut(), results_json(run, v))
    {
        all.extend(r);
    }
    json
}

/// The measured part of [`result_json`].
fn results_json(run: &Run, v: &Verdicts) -> serde_json::Value {
    let Percentiles {
        p50_us: p50,
        p99_us: p99,
        max_us: tick_max,
    } = run.hist_all.percentiles();
    let overall = &run.overall;
    serde_json::json!({
        "tick_p50_us": num(p50),
        "tick_p99_us": num(p99),
        "tick_max_us": num(tick_max),
        "ticks_over_1ms": run.hist_all.count_at_least_us(1000),
        "max_force_n": num(overall.max_force_n),
        "max_depth_mm": num(run.max_depth_m * 1e3),
        "max_coupling_stretch_mm": num(run.max_stretch_m * 1e3),
        "max_device_speed_m_per_s": num(run.max_speed),
        "contact_episodes": run.episodes,
        "contact_fraction": num(overall.contact_fraction),
        "max_displacement_mm": num(overall.max_displacement_m * 1e3),
        "max_kinetic_energy_j": num(overall.max_kinetic_energy_j),
        "max_elastic_energy_j": num(overall.max_elastic_energy_j),
        "max_inverted_elements": overall.max_inverted_elements,
        "settle_checks": run.checks.iter().map(SettleCheck::json).collect::<Vec<_>>(),
        "per_minute": run.minutes.iter().map(MinuteStats::json).collect::<Vec<_>>(),
        "failure": run.failure.as_ref().map(|f| serde_json::json!({"time_s": f.time_s, "what": f.what})),
        "limits": limits_json(),
        "settled_energy_trend_factor": v.trend.map(num),
        "verdicts": {
            "no_nan": v.no_nan,
            "rest_recovered": v.rest_recovered,
            "no_energy_growth": v.no_energy_growth,
        },
    })
}

fn main() {
    let cfg = match SoakConfig::new(Args::parse()) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("soak: {e}");
            std::process::exit(2);
        }
    };
    let commit = git_commit();
    let scene = load_builtin("lv").expect("built-in lv scene");
    assert_eq!(scene.integrator.tick_s, TICK_S, "lv tick changed");
    let mut sim = FemBody::new(&scene).expect("lv simulation");
    let plan = sim.plan();
    let setup = Setup {
        commit,
        nodes: sim.fem().node_count(),
        tets: sim.fem().tets().len(),
        material: scene.material.model.scene_name().to_string(),
        integrator: sim.integrator().name().to_string(),
        substeps: plan.substeps,
        sub_dt_s: plan.sub_dt_s,
        critical_dt_s: plan.critical_dt_s,
        total: cfg.total_ticks(),
    };
    let kc = scene.probe.coupling_stiffness_n_per_m;
    println!(
        "soak: lv ({} nodes, {} tets), {} ({} sub-steps of {:.1} us, critical {:.1} us), {} min = {} ticks, seed {:#x}, commit {}",
        setup.nodes,
        setup.tets,
        setup.integrator,
        plan.substeps,
        plan.sub_dt_s * 1e6,
        plan.critical_dt_s * 1e6,
        cfg.minutes,
        setup.total,
        cfg.seed,
        setup.commit
    );

    let settles = cfg.settle_ticks();
    let mut path = ProbePath::new(cfg.seed, sim.probe_radius_m(), settles.clone());
    let mut run = Run::new(&cfg, settles);
    run.run(&cfg, &mut sim, &mut path, kc);
    let verdicts = Verdicts::of(&run, setup.total);
    print!("{}", summary_table(&setup, &run, &verdicts));

    let json = result_json(&cfg, &setup, &run, &verdicts);
    let file = &cfg.output;
    std::fs::create_dir_all(file.parent().expect("parent")).expect("creating output dir");
    std::fs::write(
        file,
        serde_json::to_string_pretty(&json).expect("json") + "\n",
    )
    .expect("writing soak json");
    println!("wrote {}", file.display());
    if !verdicts.all_pass() {
        std::process::exit(1);
    }
}
