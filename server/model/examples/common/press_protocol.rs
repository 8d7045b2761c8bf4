//! The press protocols the `feel` and `hybrid_feel` examples share as clap subcommands
//! ([`haptic_model::press`]: staircase holds, the demo's constant-speed press, the left
//! ventricle's half-turn stroke). Included with `#[path]`.

use clap::Subcommand;

/// A scripted press (depths in mm, speeds in mm/s, times in s).
#[derive(Debug, Subcommand)]
pub enum Protocol {
    /// Ramps to each depth in turn and holds it.
    Staircase {
        /// Device depths past first contact, mm.
        #[arg(long, value_delimiter = ',', default_value = "0.25,0.5,1,1.5,2,3,4")]
        depths: Vec<f64>,
        /// Ramp time, s.
        #[arg(long, default_value_t = 0.5)]
        ramp_s: f64,
        /// Hold time, s.
        #[arg(long, default_value_t = 1.5)]
        hold_s: f64,
    },
    /// The demo's press: constant speed to a depth, then a hold.
    Demo {
        /// Depth, mm.
        #[arg(long, default_value_t = 3.7)]
        depth: f64,
        /// Speed, mm/s.
        #[arg(long, default_value_t = 10.0)]
        speed: f64,
        /// Hold, s.
        #[arg(long, default_value_t = 3.0)]
        hold_s: f64,
    },
    /// The left ventricle's stroke: pressed to a depth on the lv-probe line, then half way round
    /// the ventricle at z = -5 mm.
    Stroke {
        /// Depth, mm.
        #[arg(long, default_value_t = 2.0)]
        depth: f64,
        /// Speed, mm/s.
        #[arg(long, default_value_t = 20.0)]
        speed: f64,
    },
}
