//! Wake-up jitter of a 1 kHz loop on this machine, as the servo's clock-paced loop sleeps
//! (`spin_sleep` to absolute 1 ms deadlines), with the daemon's real-time options: how late
//! each wake-up is, in microseconds (p50, p99, p99.9, max) and how many ticks were a full
//! period late. Run it once per setting and compare (docs/deploy.md):
//!
//! ```text
//! cargo run --release -p haptic-server --example jitter -- --seconds 20
//! cargo run --release -p haptic-server --example jitter -- --seconds 20 --cpu 1
//! cargo run --release -p haptic-server --example jitter -- --seconds 20 --cpu 1 --realtime --mlockall
//! ```
//!
//! The loop does no work: this measures the scheduler and the sleep, not a model step.

use std::time::{Duration, Instant};

use clap::Parser;
use haptic_server::config::ServoConfig;

/// Wake-up lateness of a 1 kHz loop.
#[derive(Parser, Debug)]
struct Args {
    /// Seconds to run.
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    /// Pin the loop to this CPU.
    #[arg(long)]
    cpu: Option<usize>,
    /// SCHED_FIFO at priority 80 (needs root or CAP_SYS_NICE).
    #[arg(long)]
    realtime: bool,
    /// Lock memory.
    #[arg(long)]
    mlockall: bool,
    /// Period, µs.
    #[arg(long, default_value_t = 1000)]
    period_us: u64,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    anyhow::ensure!(
        args.seconds.is_finite() && args.seconds > 0.0 && args.period_us > 0,
        "--seconds and --period-us must be positive"
    );
    let cfg = ServoConfig {
        realtime: args.realtime,
        mlockall: args.mlockall,
        cpu: args.cpu,
        ..ServoConfig::default()
    };
    let ticks = (args.seconds * 1e6 / args.period_us as f64) as u64;
    let handle = std::thread::spawn(move || {
        let warnings = haptic_server::servo::setup_realtime(&cfg);
        let mut hist = hdrhistogram::Histogram::<u64>::new_with_bounds(1, 10_000_000, 3)
            .expect("static bounds");
        let sleeper = spin_sleep::SpinSleeper::default();
        let period = Duration::from_micros(args.period_us);
        let start = Instant::now();
        let mut missed = 0u64;
        for k in 1..=ticks {
            let deadline = start + period * k as u32;
            sleeper.sleep_until(deadline);
            let late_us = Instant::now()
                .saturating_duration_since(deadline)
                .as_micros() as u64;
            hist.saturating_record(late_us.max(1));
            if late_us >= args.period_us {
                missed += 1;
            }
        }
        (warnings, hist, missed)
    });
    let (warnings, hist, missed) = handle
        .join()
        .map_err(|_| anyhow::anyhow!("the loop thread panicked"))?;
    for w in warnings {
        eprintln!("warning: {w}");
    }
    println!(
        "cpu={:?} realtime={} mlockall={} ticks={} wake-up lateness us: p50 {} p99 {} p99.9 {} max {}; late by a full period: {}",
        args.cpu,
        args.realtime,
        args.mlockall,
        hist.len(),
        hist.value_at_quantile(0.5),
        hist.value_at_quantile(0.99),
        hist.value_at_quantile(0.999),
        hist.max(),
        missed
    );
    Ok(())
}
