//! The thermal / continuous-force limit (devices.md S8): a peak force the motors can give for a
//! moment is not one they can hold. An adaptive clamp starts at the device's peak force and
//! moves per tick:
//!
//! - **hot**: lowered by x0.999 per tick toward the continuous rating;
//! - **cool**: raised by x1.001 per tick back toward the peak;
//! - in between: held (hysteresis).
//!
//! "Hot" and "cool" come from the device's normalised motor temperature when the driver reports
//! one (OpenHaptics `HD_MOTOR_TEMPERATURE`: hot above 0.7, cool below 0.5, as the vendor's
//! PreventWarmMotors example does), otherwise from the force actually rendered: its RMS over
//! the last second (an exponential average of |F|^2 with a 1 s time constant, no buffer), hot
//! above the continuous rating, cool below 0.5/0.7 of it (the same hysteresis ratio).
//!
//! A device whose continuous rating is not below its peak (or unknown: reported as the peak)
//! is never limited. Allocation-free; one per guard.
//!
//! Neighbours: [`crate::guard::ForceGuard`] asks for the clamp each tick (step 8) and feeds back
//! the force it wrote.

/// Per-tick factor while hot (S8).
pub const COOL_DOWN_FACTOR: f64 = 0.999;
/// Per-tick factor while cool (S8).
pub const WARM_UP_FACTOR: f64 = 1.001;
/// Normalised motor temperature above which the clamp is lowered.
pub const HOT_TEMPERATURE: f64 = 0.7;
/// Normalised motor temperature below which the clamp is raised.
pub const COOL_TEMPERATURE: f64 = 0.5;
/// Averaging time of the RMS force for devices without temperature data, s.
pub const RMS_WINDOW_S: f64 = 1.0;

/// The adaptive clamp.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThermalLimit {
    peak_n: f64,
    continuous_n: f64,
    clamp_n: f64,
    mean_square_n2: f64,
}

impl ThermalLimit {
    /// A limit between `peak_n` and `continuous_n` (N), starting at the peak.
    pub fn new(peak_n: f64, continuous_n: f64) -> Self {
        let continuous_n = if continuous_n.is_finite() && continuous_n > 0.0 {
            continuous_n.min(peak_n)
        } else {
            peak_n
        };
        Self {
            peak_n,
            continuous_n,
            clamp_n: peak_n,
            mean_square_n2: 0.0,
        }
    }

    /// The clamp in force now, N.
    pub fn clamp_n(&self) -> f64 {
        self.clamp_n
    }

    /// The RMS of the rendered force over about the last second, N.
    pub fn rms_force_n(&self) -> f64 {
        self.mean_square_n2.sqrt()
    }

    /// True while the clamp is below the peak.
    pub fn limiting(&self) -> bool {
        self.clamp_n < self.peak_n
    }

    /// One tick: `rendered_n` is the magnitude of the force written on the previous tick,
    /// `dt_s` the time since, `temperature` the normalised motor temperature if the device
    /// reports one (the hottest motor). Returns the clamp for this tick, N.
    pub fn update(&mut self, rendered_n: f64, dt_s: f64, temperature: Option<f64>) -> f64 {
        if self.continuous_n >= self.peak_n {
            return self.clamp_n;
        }
        let w = if dt_s.is_finite() && dt_s > 0.0 {
            (dt_s / RMS_WINDOW_S).min(1.0)
        } else {
            0.0
        };
        let f2 = if rendered_n.is_finite() {
            rendered_n * rendered_n
        } else {
            0.0
        };
        self.mean_square_n2 += (f2 - self.mean_square_n2) * w;
        let (hot, cool) = match temperature.filter(|t| t.is_finite()) {
            Some(t) => (t > HOT_TEMPERATURE, t < COOL_TEMPERATURE),
            None => {
                let rms = self.rms_force_n();
                (
                    rms > self.continuous_n,
                    rms < self.continuous_n * COOL_TEMPERATURE / HOT_TEMPERATURE,
                )
            }
        };
        if hot {
            self.clamp_n = (self.clamp_n * COOL_DOWN_FACTOR).max(self.continuous_n);
        } else if cool {
            self.clamp_n = (self.clamp_n * WARM_UP_FACTOR).min(self.peak_n);
        }
        self.clamp_n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_hot_motor_lowers_the_clamp_geometrically_to_the_continuous_rating_and_back() {
        let mut t = ThermalLimit::new(3.3, 0.88);
        for _ in 0..100 {
            t.update(0.0, 0.001, Some(0.8));
        }
        assert!((t.clamp_n() - 3.3 * 0.999f64.powi(100)).abs() < 1e-12);
        for _ in 0..10_000 {
            t.update(0.0, 0.001, Some(0.8));
        }
        assert_eq!(t.clamp_n(), 0.88, "floor at the continuous rating");
        // Between the thresholds: held.
        t.update(0.0, 0.001, Some(0.6));
        assert_eq!(t.clamp_n(), 0.88);
        for _ in 0..50 {
            t.update(0.0, 0.001, Some(0.4));
        }
        assert!((t.clamp_n() - 0.88 * 1.001f64.powi(50)).abs() < 1e-12);
        for _ in 0..10_000 {
            t.update(0.0, 0.001, Some(0.4));
        }
        assert_eq!(t.clamp_n(), 3.3, "back to the peak");
    }

    #[test]
    fn without_temperature_a_held_force_above_the_rating_is_limited_and_a_short_peak_is_not() {
        // A 0.2 s burst at the peak: RMS over 1 s = 3.3 * sqrt(1 - e^-0.2) = 1.40 N > 0.88 N,
        // so it does start limiting, but only for the tail of the burst.
        let mut t = ThermalLimit::new(3.3, 0.88);
        let mut first_limited = None;
        for i in 0..200 {
            let c = t.update(3.3, 0.001, None);
            if c < 3.3 && first_limited.is_none() {
                first_limited = Some(i);
            }
        }
        // RMS crosses 0.88 N when 1 - e^-t = (0.88/3.3)^2: t = 73.7 ms.
        let i = first_limited.expect("limited during the burst");
        assert!((72..=76).contains(&i), "limited from tick {i}");
        assert!(t.clamp_n() > 3.3 * 0.999f64.powi(130) - 1e-9);

        // A held 2 N: the clamp falls to the rating and the RMS of what is rendered (the
        // clamped force) settles at the rating.
        let mut t = ThermalLimit::new(3.3, 0.88);
        let mut rendered = 0.0;
        for _ in 0..20_000 {
            let clamp = t.update(rendered, 0.001, None);
            rendered = f64::min(2.0, clamp);
        }
        assert_eq!(t.clamp_n(), 0.88);
        assert!((t.rms_force_n() - 0.88).abs() < 1e-3, "{}", t.rms_force_n());
        // Released: RMS falls below 0.629 N after ln(0.88^2/0.629^2) = 0.67 s, then the clamp
        // climbs back.
        for _ in 0..5_000 {
            t.update(0.0, 0.001, None);
        }
        assert_eq!(t.clamp_n(), 3.3);
    }

    #[test]
    fn devices_without_a_lower_continuous_rating_are_never_limited() {
        let mut t = ThermalLimit::new(10.0, 10.0);
        for _ in 0..10_000 {
            assert_eq!(t.update(10.0, 0.001, Some(1.0)), 10.0);
        }
        let mut t = ThermalLimit::new(10.0, f64::NAN);
        assert_eq!(t.update(10.0, 0.001, None), 10.0);
        assert!(!t.limiting());
    }
}
