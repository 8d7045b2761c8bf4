//! Does a heavy session starve the LV? (issue 16, section 2: "a heavy session next to the LV
//! leaves the LV's loop rate and step p99 within 10 %".)
//!
//! In process, on the session manager the daemon uses: a genuine LV that fits in 1 ms here
//! (`lv-surface-springs`, about 0.1 ms a tick) runs for `--run-s` alone, then beside
//! `--heavy N` heavy sessions (the default LV plus 3 ms of CPU spinning a tick: about 220 Hz,
//! never keeping up), interleaved `--repeat` times, with the servo's yielding on (the default:
//! overrunning sessions go to `SCHED_IDLE` while another session runs) and off. Each window is a
//! fresh LV session, so its step histogram is its own. The table gives the median over the
//! repetitions of the LV's loop rate and step p99 for each set-up, and the ratios beside/alone.
//!
//! Run: `cargo bench -p haptic-server --bench yielding` (`-- --repeat 5 --heavy 6 --run-s 3`).
//! Writes `target/bench/yielding.json`; `-- --publish` writes `docs/bench/yielding.json`.

#[path = "../tests/common/mod.rs"]
mod common;

use std::time::Duration;

use common::{genuine_run, start_heavy, wait_for};
use haptic_server::ServerConfig;
use haptic_server::session::SessionManager;

struct Args {
    repeat: usize,
    heavy: usize,
    run: Duration,
    publish: bool,
}

fn args() -> Result<Args, String> {
    let mut a = Args {
        repeat: 5,
        heavy: 6,
        run: Duration::from_secs(3),
        publish: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag} needs a value"));
        match flag.as_str() {
            "--repeat" => a.repeat = value()?.parse().map_err(|e| format!("--repeat: {e}"))?,
            "--heavy" => a.heavy = value()?.parse().map_err(|e| format!("--heavy: {e}"))?,
            "--run-s" => {
                let s: f64 = value()?.parse().map_err(|e| format!("--run-s: {e}"))?;
                if !(s.is_finite() && (0.5..=600.0).contains(&s)) {
                    return Err("--run-s: expected 0.5..=600".into());
                }
                a.run = Duration::from_secs_f64(s);
            }
            "--publish" => a.publish = true,
            // cargo bench passes --bench.
            "--bench" => {}
            other => return Err(format!("unknown argument {other}")),
        }
    }
    if a.repeat == 0 || a.heavy == 0 {
        return Err("--repeat and --heavy must be at least 1".into());
    }
    Ok(a)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// One repetition: the LV alone, then beside `heavy` heavy sessions. Returns
/// `[(rate, p99) alone, (rate, p99) beside]` and whether the heavy sessions were demoted.
async fn repetition(yielding: bool, a: &Args) -> ([(f64, f64); 2], bool) {
    let mut config = ServerConfig::default();
    config.servo.stats_every_ticks = 20;
    config.servo.yield_when_overrunning = yielding;
    config.max_sessions = a.heavy + 1;
    let manager = SessionManager::new(config);
    let alone = genuine_run(&manager, a.run).await;
    let heavy = start_heavy(&manager, a.heavy);
    // Judged after a second below 90 % of the rate (and demoted, when yielding).
    let judged = wait_for(
        || heavy.iter().all(|h| h.stats().overrunning),
        Duration::from_secs(30),
    )
    .await;
    // A demotion shows in the statistics published after it (20 ticks of a slow session).
    let demoted = judged
        && yielding
        && wait_for(
            || heavy.iter().all(|h| h.stats().demoted),
            Duration::from_secs(10),
        )
        .await;
    let beside = genuine_run(&manager, a.run).await;
    manager.stop_all();
    ([alone, beside], demoted)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let a = match args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(2);
        }
    };
    let mut rows = Vec::new();
    let mut samples: [[Vec<(f64, f64)>; 2]; 2] = Default::default();
    let mut demoted_all = [true, true];
    for r in 0..a.repeat {
        for (k, yielding) in [true, false].into_iter().enumerate() {
            let (pair, demoted) = repetition(yielding, &a).await;
            eprintln!(
                "repetition {}/{} yielding {}: alone {:.0} Hz p99 {} us, beside {} heavy {:.0} Hz p99 {} us{}",
                r + 1,
                a.repeat,
                if yielding { "on" } else { "off" },
                pair[0].0,
                pair[0].1,
                a.heavy,
                pair[1].0,
                pair[1].1,
                if yielding && !demoted {
                    " (NOT all demoted)"
                } else {
                    ""
                }
            );
            demoted_all[k] &= demoted;
            samples[k][0].push(pair[0]);
            samples[k][1].push(pair[1]);
        }
    }
    println!(
        "\n| yielding | LV alone: rate, step p99 | LV beside {} heavy: rate, step p99 | rate ratio | p99 ratio |",
        a.heavy
    );
    println!("|---|---|---|---|---|");
    for (k, name) in ["on (default)", "off"].into_iter().enumerate() {
        let m = |w: usize, f: fn(&(f64, f64)) -> f64| median(samples[k][w].iter().map(f).collect());
        let (ra, pa, rb, pb) = (m(0, |s| s.0), m(0, |s| s.1), m(1, |s| s.0), m(1, |s| s.1));
        println!(
            "| {name} | {ra:.0} Hz, {pa:.0} us | {rb:.0} Hz, {pb:.0} us | {:.3} | {:.3} |",
            rb / ra,
            pb / pa
        );
        rows.push(serde_json::json!({
            "yielding": k == 0,
            "heavy_sessions": a.heavy,
            "repetitions": a.repeat,
            "run_s": a.run.as_secs_f64(),
            "alone_rate_hz_median": ra,
            "alone_step_p99_us_median": pa,
            "beside_rate_hz_median": rb,
            "beside_step_p99_us_median": pb,
            "rate_ratio": rb / ra,
            "p99_ratio": pb / pa,
            "heavy_all_demoted": k == 0 && demoted_all[0],
            "alone": samples[k][0],
            "beside": samples[k][1],
        }));
    }
    let dir = if a.publish {
        concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/bench")
    } else {
        concat!(env!("CARGO_MANIFEST_DIR"), "/../target/bench")
    };
    let path = std::path::Path::new(dir).join("yielding.json");
    let text = serde_json::to_string_pretty(&serde_json::json!({ "rows": rows }))
        .expect("json of numbers");
    match std::fs::create_dir_all(dir).and_then(|_| std::fs::write(&path, text)) {
        Ok(()) => println!("\nwrote {}", path.display()),
        Err(e) => eprintln!("writing {}: {e}", path.display()),
    }
}
