//! The device a session's `DeviceLink` stream introduced (issue 50, section 2): the capabilities
//! the bridge sends with its first sample (`DeviceCapabilities`, in the spirit of IEEE
//! 1918.1.1's capability exchange), checked before the session is touched, and what the daemon
//! does with them: the forwarder clamps each force command to the device's force limit and its
//! contact stiffness to the device's stiffness limit, and the stream task drops poses outside
//! the declared workspace. A bridge that sends no capabilities (older ones) changes nothing.

use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use haptic_model::DVec3;
use haptics_proto::v1::DeviceCapabilities;

/// Longest device name accepted, bytes.
pub const MAX_NAME_BYTES: usize = 64;
/// Most degrees of freedom a device may declare (sensed or actuated).
pub const MAX_DEGREES_OF_FREEDOM: u32 = 16;
/// Largest force a device may declare, N (a HapticMaster renders 250 N).
pub const MAX_DECLARED_FORCE_N: f64 = 10_000.0;
/// Largest stiffness a device may declare, N/m.
pub const MAX_DECLARED_STIFFNESS_N_PER_M: f64 = 1e7;
/// Largest rate a device may declare, Hz.
pub const MAX_DECLARED_RATE_HZ: f64 = 100_000.0;
/// Largest workspace coordinate a device may declare, m.
pub const MAX_WORKSPACE_COORDINATE_M: f64 = 100.0;

/// Checks capabilities before they are used.
///
/// # Errors
/// A message naming the field: a name longer than [`MAX_NAME_BYTES`] or with control
/// characters; degrees of freedom above [`MAX_DEGREES_OF_FREEDOM`]; a limit that is negative,
/// not finite or above its `MAX_DECLARED_*` bound (zero: not declared); a workspace with one
/// corner only, a coordinate not finite or beyond [`MAX_WORKSPACE_COORDINATE_M`], or a lower
/// corner not below the upper one on every axis.
pub fn check(c: &DeviceCapabilities) -> Result<(), String> {
    if c.name.len() > MAX_NAME_BYTES || c.name.chars().any(char::is_control) {
        return Err(format!(
            "capabilities.name must be at most {MAX_NAME_BYTES} bytes without control characters"
        ));
    }
    for (field, dof) in [
        ("sensed_degrees_of_freedom", c.sensed_degrees_of_freedom),
        ("actuated_degrees_of_freedom", c.actuated_degrees_of_freedom),
    ] {
        if dof > MAX_DEGREES_OF_FREEDOM {
            return Err(format!(
                "capabilities.{field} is {dof}; at most {MAX_DEGREES_OF_FREEDOM}"
            ));
        }
    }
    for (field, v, max) in [
        ("max_force_n", c.max_force_n, MAX_DECLARED_FORCE_N),
        (
            "max_continuous_force_n",
            c.max_continuous_force_n,
            MAX_DECLARED_FORCE_N,
        ),
        (
            "max_stiffness_n_per_m",
            c.max_stiffness_n_per_m,
            MAX_DECLARED_STIFFNESS_N_PER_M,
        ),
        ("native_rate_hz", c.native_rate_hz, MAX_DECLARED_RATE_HZ),
    ] {
        if !(v.is_finite() && (0.0..=max).contains(&v)) {
            return Err(format!(
                "capabilities.{field} is {v}; it must be in [0, {max}] (0: not declared)"
            ));
        }
    }
    match (&c.workspace_min_m, &c.workspace_max_m) {
        (None, None) => Ok(()),
        (Some(lo), Some(hi)) => {
            let (lo, hi) = ([lo.x, lo.y, lo.z], [hi.x, hi.y, hi.z]);
            let sane = |v: f64| v.is_finite() && v.abs() <= MAX_WORKSPACE_COORDINATE_M;
            if !lo.iter().chain(&hi).all(|&v| sane(v)) {
                return Err(format!(
                    "capabilities.workspace coordinates must be finite and within \
                     {MAX_WORKSPACE_COORDINATE_M} m"
                ));
            }
            if lo.iter().zip(&hi).any(|(l, h)| l >= h) {
                return Err(
                    "capabilities.workspace_min_m must be below workspace_max_m on every axis"
                        .into(),
                );
            }
            Ok(())
        }
        _ => Err("capabilities: give both workspace_min_m and workspace_max_m, or neither".into()),
    }
}

/// The force limit capabilities declare, N: the peak force, else the continuous one, else
/// none (`f64::INFINITY`).
pub fn force_limit_n(c: &DeviceCapabilities) -> f64 {
    [c.max_force_n, c.max_continuous_force_n]
        .into_iter()
        .find(|&f| f > 0.0)
        .unwrap_or(f64::INFINITY)
}

/// The declared workspace box (lower, upper corner), if any.
pub fn workspace(c: &DeviceCapabilities) -> Option<(DVec3, DVec3)> {
    let (lo, hi) = (c.workspace_min_m.as_ref()?, c.workspace_max_m.as_ref()?);
    Some((DVec3::new(lo.x, lo.y, lo.z), DVec3::new(hi.x, hi.y, hi.z)))
}

/// Whether `p` lies in the box `ws` (faces included).
pub fn in_workspace(ws: (DVec3, DVec3), p: DVec3) -> bool {
    p.cmpge(ws.0).all() && p.cmple(ws.1).all()
}

/// The device attached to a session and the limits the forwarder applies for it (shared by
/// the stream task, which sets it, the forwarder thread and `GetStats`).
#[derive(Debug)]
pub struct DeviceShared {
    capabilities: Mutex<Option<DeviceCapabilities>>,
    /// Force limit, N, as `f64` bits (`+inf`: none).
    max_force_bits: AtomicU64,
    /// Stiffness limit, N/m, as `f64` bits (`+inf`: none).
    max_stiffness_bits: AtomicU64,
}

impl Default for DeviceShared {
    fn default() -> Self {
        Self {
            capabilities: Mutex::new(None),
            max_force_bits: AtomicU64::new(f64::INFINITY.to_bits()),
            max_stiffness_bits: AtomicU64::new(f64::INFINITY.to_bits()),
        }
    }
}

impl DeviceShared {
    /// A device attached: `caps` (checked by [`check`]) or `None` for one that did not
    /// introduce itself.
    pub fn attach(&self, caps: Option<DeviceCapabilities>) {
        let (force, stiffness) = caps.as_ref().map_or((f64::INFINITY, f64::INFINITY), |c| {
            let k = c.max_stiffness_n_per_m;
            (force_limit_n(c), if k > 0.0 { k } else { f64::INFINITY })
        });
        self.max_force_bits
            .store(force.to_bits(), Ordering::Relaxed);
        self.max_stiffness_bits
            .store(stiffness.to_bits(), Ordering::Relaxed);
        if let Ok(mut slot) = self.capabilities.lock() {
            *slot = caps;
        }
    }

    /// The device detached: no capabilities, no limits.
    pub fn detach(&self) {
        self.attach(None);
    }

    /// The attached device's capabilities, if it sent any.
    pub fn capabilities(&self) -> Option<DeviceCapabilities> {
        self.capabilities.lock().ok().and_then(|c| c.clone())
    }

    /// (force limit N, stiffness limit N/m); `+inf` where none. Lock-free.
    pub fn limits(&self) -> (f64, f64) {
        (
            f64::from_bits(self.max_force_bits.load(Ordering::Relaxed)),
            f64::from_bits(self.max_stiffness_bits.load(Ordering::Relaxed)),
        )
    }
}

/// `force` scaled down to magnitude `max_n` if above it.
pub fn clamp_force(force: DVec3, max_n: f64) -> DVec3 {
    let m = force.length();
    if m > max_n {
        force * (max_n / m)
    } else {
        force
    }
}

/// A 3x3 row-major stiffness scaled down so that its Frobenius norm (a bound on its largest
/// eigenvalue's magnitude) is at most `max_n_per_m`.
pub fn clamp_stiffness(k: [f64; 9], max_n_per_m: f64) -> [f64; 9] {
    let norm = k.iter().map(|v| v * v).sum::<f64>().sqrt();
    if norm > max_n_per_m {
        k.map(|v| v * (max_n_per_m / norm))
    } else {
        k
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use haptics_proto::v1::Vec3;

    fn touch() -> DeviceCapabilities {
        DeviceCapabilities {
            name: "touch".into(),
            sensed_degrees_of_freedom: 6,
            actuated_degrees_of_freedom: 3,
            workspace_min_m: Some(Vec3::from([-0.08, -0.06, -0.035])),
            workspace_max_m: Some(Vec3::from([0.08, 0.06, 0.035])),
            max_force_n: 3.3,
            max_continuous_force_n: 0.88,
            max_stiffness_n_per_m: 1260.0,
            native_rate_hz: 1000.0,
        }
    }

    #[test]
    fn sane_capabilities_pass_and_each_bad_field_is_named() {
        assert_eq!(check(&touch()), Ok(()));
        assert_eq!(
            check(&DeviceCapabilities::default()),
            Ok(()),
            "nothing declared"
        );
        type Spoil = fn(&mut DeviceCapabilities);
        let bad: [(&str, Spoil); 8] = [
            ("name", |c| c.name = "x\u{1b}[31m".into()),
            ("name", |c| c.name = "n".repeat(65)),
            ("sensed_degrees_of_freedom", |c| {
                c.sensed_degrees_of_freedom = 17;
            }),
            ("max_force_n", |c| c.max_force_n = f64::NAN),
            ("max_continuous_force_n", |c| {
                c.max_continuous_force_n = -1.0
            }),
            ("max_stiffness_n_per_m", |c| c.max_stiffness_n_per_m = 1e12),
            ("workspace_min_m", |c| c.workspace_max_m = None),
            ("workspace_min_m", |c| {
                c.workspace_min_m = Some(Vec3::from([0.1, 0.0, 0.0]));
            }),
        ];
        for (field, spoil) in bad {
            let mut c = touch();
            spoil(&mut c);
            let e = check(&c).expect_err(field);
            assert!(e.contains(field), "{field}: {e}");
        }
    }

    #[test]
    fn limits_follow_the_declared_values() {
        let shared = DeviceShared::default();
        assert_eq!(shared.limits(), (f64::INFINITY, f64::INFINITY));
        shared.attach(Some(touch()));
        assert_eq!(shared.limits(), (3.3, 1260.0));
        assert_eq!(shared.capabilities().unwrap().name, "touch");
        // Only a continuous rating: that is the limit; no stiffness: none.
        shared.attach(Some(DeviceCapabilities {
            max_continuous_force_n: 0.88,
            ..DeviceCapabilities::default()
        }));
        assert_eq!(shared.limits(), (0.88, f64::INFINITY));
        shared.detach();
        assert_eq!(shared.limits(), (f64::INFINITY, f64::INFINITY));
        assert!(shared.capabilities().is_none());
    }

    #[test]
    fn forces_and_stiffness_are_scaled_to_the_limits_and_the_box_includes_its_faces() {
        let f = clamp_force(DVec3::new(3.0, 4.0, 0.0), 2.5);
        assert!((f - DVec3::new(1.5, 2.0, 0.0)).length() < 1e-12);
        assert_eq!(clamp_force(DVec3::X, 2.5), DVec3::X);
        let k = clamp_stiffness([300.0, 0.0, 0.0, 0.0, 400.0, 0.0, 0.0, 0.0, 0.0], 250.0);
        assert!(
            (k[0] - 150.0).abs() < 1e-9 && (k[4] - 200.0).abs() < 1e-9,
            "{k:?}"
        );
        let ws = workspace(&touch()).unwrap();
        assert!(in_workspace(ws, DVec3::new(0.08, 0.0, -0.035)));
        assert!(!in_workspace(ws, DVec3::new(0.0801, 0.0, 0.0)));
        assert!(workspace(&DeviceCapabilities::default()).is_none());
    }
}
