//! The system soak's tables, verdicts and JSON (split from `system_soak.rs` to keep files
//! short).

use super::*;

pub(super) struct Report<'a> {
    pub(super) cfg: &'a SoakConfig,
    pub(super) windows: &'a [Window],
    pub(super) cycles: &'a [Value],
    pub(super) bridge_runs: &'a [Value],
    pub(super) forces: (u64, u64),
    pub(super) watchers_failed: usize,
    pub(super) first_rss_mb: f64,
    pub(super) last: &'a SessionStats,
}

/// The four kinds of window, grouped.
struct Groups {
    quiet: Option<Group>,
    steady: Option<Group>,
    switch: Option<Group>,
    with_heavy: Option<Group>,
}

impl Groups {
    fn of(windows: &[Window]) -> Self {
        Self {
            quiet: Group::of(windows.iter().filter(|w| w.presence == Presence::Quiet)),
            steady: Group::of(windows.iter().filter(|w| w.presence == Presence::Heavy)),
            switch: Group::of(windows.iter().filter(|w| w.presence == Presence::Switch)),
            with_heavy: Group::of(windows.iter().filter(|w| w.presence != Presence::Quiet)),
        }
    }
}

/// Prints the tables and verdicts, writes the JSON; `Ok(false)` when a verdict failed.
pub(super) fn report(r: Report<'_>) -> Result<bool> {
    let minutes = minutes_table(r.cfg, r.windows);
    let groups = Groups::of(r.windows);
    groups_table(&groups);
    summary_line(&r);
    let (memory_ok, memory_json) = memory_verdict(r.cfg, r.windows, r.first_rss_mb);
    let (overrun_ok, overrun_json) = overrun_verdict(&groups);
    let last = r.last;
    let fault_ok = !last.faulted && r.windows.iter().all(|w| !w.stats.faulted);
    if !fault_ok {
        println!("the genuine session faulted: {}", last.fault);
    }
    let verdicts = json!({"memory_bounded": memory_json, "no_attributable_overruns": overrun_json,
                          "genuine_faulted": !fault_ok});
    let doc = report_json(&r, &groups, minutes, verdicts);
    let out = results_dir(r.cfg.publish)?.join("system-soak.json");
    std::fs::write(&out, serde_json::to_string_pretty(&doc)? + "\n")
        .with_context(|| format!("writing {}", out.display()))?;
    eprintln!("wrote {}", out.display());
    Ok(memory_ok && overrun_ok && fault_ok)
}

/// Prints the table per minute; its rows for the JSON.
fn minutes_table(cfg: &SoakConfig, windows: &[Window]) -> Vec<Value> {
    println!(
        "| minute | RSS end (MB) | daemon CPU | loop (Hz) | overruns/s quiet / heavy | lost slots/s quiet / heavy | step p99 in windows, quiet / heavy (us) | step p99 over life (us) | frames/s per watcher |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut minutes = Vec::new();
    for m in 0..cfg.minutes {
        let this: Vec<&Window> = windows.iter().filter(|w| w.minute() == m).collect();
        let Some(end) = this.last() else { continue };
        let all = Group::of(this.iter().copied());
        let (q, h) = quiet_and_heavy(&this);
        let fps: Vec<f64> = this.iter().map(|w| w.frames_per_watcher_per_s).collect();
        let fps = percentile(&fps, 0.5);
        println!(
            "| {} | {:.1} | {} % | {} | {} / {} | {} / {} | {} / {} | {:.0} | {fps:.1} |",
            m + 1,
            end.rss_mb,
            opt_cell(all.as_ref().map(|g| g.daemon_cpu_percent), 0),
            opt_cell(all.as_ref().map(|g| g.loop_rate_hz), 0),
            opt_cell(q.as_ref().map(|g| g.overruns_per_s), 0),
            opt_cell(h.as_ref().map(|g| g.overruns_per_s), 0),
            opt_cell(q.as_ref().map(|g| g.lost_slots_per_s), 0),
            opt_cell(h.as_ref().map(|g| g.lost_slots_per_s), 0),
            bound_cell(q.as_ref().and_then(|g| g.steps.as_ref())),
            bound_cell(h.as_ref().and_then(|g| g.steps.as_ref())),
            end.stats.step_p99_us,
        );
        minutes.push(json!({
            "minute": m + 1,
            "daemon_rss_mb": end.rss_mb,
            "quiet": q.as_ref().map(Group::json),
            "with_heavy": h.as_ref().map(Group::json),
            "life_step_p99_us": end.stats.step_p99_us,
            "frames_per_watcher_per_s": fps,
        }));
    }
    minutes
}

/// Prints the table per kind of window.
fn groups_table(groups: &Groups) {
    let Groups {
        quiet,
        steady,
        switch,
        with_heavy,
    } = groups;
    println!();
    println!(
        "| windows ({WINDOW_S} s) | count | overruns/s | lost slots/s | loop (Hz) | daemon CPU | step mean (us) | step p99 (us, bucket) | ticks > 10 ms |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for (name, g) in [
        ("quiet (no heavy session)", &quiet),
        ("heavy session running", &steady),
        ("heavy session started or stopped", &switch),
        ("with heavy (both above)", &with_heavy),
    ] {
        match g {
            Some(g) => println!(
                "| {name} | {} | {:.1} | {:.1} | {:.0} | {:.0} % | {} | {} | {} |",
                g.windows,
                g.overruns_per_s,
                g.lost_slots_per_s,
                g.loop_rate_hz,
                g.daemon_cpu_percent,
                opt_cell(g.steps.as_ref().and_then(WindowSteps::mean_us), 0),
                bound_cell(g.steps.as_ref()),
                g.steps
                    .as_ref()
                    .map_or("-".into(), |s| s.stalls().to_string()),
            ),
            None => println!("| {name} | 0 | - | - | - | - | - | - | - |"),
        }
    }
}

/// Prints the line on the heavy sessions, forces, bridge runs, watchers and the genuine
/// session.
fn summary_line(r: &Report<'_>) {
    let Report {
        cfg,
        windows,
        cycles,
        bridge_runs,
        forces,
        watchers_failed,
        last,
        ..
    } = *r;
    let heavy_p50: Vec<f64> = cycles
        .iter()
        .filter_map(|c| c["step_p50_us"].as_f64())
        .collect();
    let heavy_failed = cycles.iter().filter(|c| c["error"].is_string()).count();
    println!();
    println!("{}", bridge_line(bridge_runs));
    println!(
        "heavy sessions: {} run ({} failed to start), step p50 {} us; forces applied {} ({} failed); bridge runs {}; watchers failed {watchers_failed} of {}; genuine session: {} ticks, {} overruns, step p50 / p99 / max {:.0} / {:.0} / {:.0} us over its life, demoted (SCHED_IDLE) at the end of {} of {} windows; heavy sessions demoted when stopped: {} of {}",
        heavy_p50.len(),
        heavy_failed,
        opt_cell(
            (!heavy_p50.is_empty()).then(|| percentile(&heavy_p50, 0.5)),
            0
        ),
        forces.0,
        forces.1,
        bridge_runs.len(),
        cfg.watchers,
        last.steps,
        last.overruns,
        last.step_p50_us,
        last.step_p99_us,
        last.step_max_us,
        windows.iter().filter(|w| w.stats.demoted).count(),
        windows.len(),
        cycles.iter().filter(|c| c["demoted"] == true).count(),
        heavy_p50.len(),
    );
}

/// Verdict 1, memory bounded: printed; `(pass, JSON)`.
fn memory_verdict(cfg: &SoakConfig, windows: &[Window], first_rss_mb: f64) -> (bool, Value) {
    // Verdict 1: memory bounded.
    let warmup = WARMUP_MINUTES.min(cfg.minutes / 2);
    let base = windows
        .iter()
        .find(|w| w.index + 1 == warmup * WINDOWS_PER_MINUTE)
        .map(|w| w.rss_mb);
    let end_rss = windows.last().map(|w| w.rss_mb);
    let peak_hwm = windows.iter().map(|w| w.hwm_mb).fold(0.0, f64::max);
    match (base, end_rss) {
        (Some(b), Some(e)) if warmup >= 1 => {
            let growth = (e - b) / b;
            let ok = growth < RSS_GROWTH_LIMIT;
            println!(
                "verdict 1, memory bounded: {} — RSS {b:.1} MB at the end of minute {warmup}, {e:.1} MB at the end (minute {}): {:+.1} % (limit {:.0} %); first sample {first_rss_mb:.1} MB, peak (VmHWM) {peak_hwm:.1} MB",
                if ok { "PASS" } else { "FAIL" },
                cfg.minutes,
                100.0 * growth,
                100.0 * RSS_GROWTH_LIMIT,
            );
            (
                ok,
                json!({"pass": ok, "baseline_minute": warmup, "baseline_rss_mb": b, "end_rss_mb": e,
                       "growth_fraction": growth, "limit_fraction": RSS_GROWTH_LIMIT,
                       "first_rss_mb": first_rss_mb, "peak_hwm_mb": peak_hwm}),
            )
        }
        _ => {
            println!(
                "verdict 1, memory bounded: not judged (run shorter than 2 minutes); RSS first {first_rss_mb:.1} MB, end {} MB, peak (VmHWM) {peak_hwm:.1} MB",
                opt_cell(end_rss, 1)
            );
            (
                true,
                json!({"pass": null, "first_rss_mb": first_rss_mb, "end_rss_mb": end_rss, "peak_hwm_mb": peak_hwm}),
            )
        }
    }
}

/// Verdict 2, no overruns attributable to the heavy session: printed; `(pass, JSON)`.
fn overrun_verdict(groups: &Groups) -> (bool, Value) {
    let (quiet, with_heavy) = (&groups.quiet, &groups.with_heavy);
    // Verdict 2: no overruns attributable to the heavy session.
    match (&quiet, &with_heavy) {
        (Some(q), Some(h)) => {
            let ok_overruns = h.overruns_per_s <= q.overruns_per_s + OVERRUN_TOLERANCE_PER_S;
            let ok_lost = h.lost_slots_per_s <= q.lost_slots_per_s + OVERRUN_TOLERANCE_PER_S;
            let ok = ok_overruns && ok_lost;
            println!(
                "verdict 2, no overruns attributable to the others: {} — overruns/s with the heavy session {:.1} vs without {:.1} ({}), lost slots/s {:.1} vs {:.1} ({}); tolerance +{OVERRUN_TOLERANCE_PER_S:.0}/s ({} + {} windows)",
                if ok { "PASS" } else { "FAIL" },
                h.overruns_per_s,
                q.overruns_per_s,
                if ok_overruns { "ok" } else { "larger" },
                h.lost_slots_per_s,
                q.lost_slots_per_s,
                if ok_lost { "ok" } else { "larger" },
                h.windows,
                q.windows,
            );
            (
                ok,
                json!({"pass": ok, "with_heavy": h.json(), "without": q.json(),
                       "tolerance_per_s": OVERRUN_TOLERANCE_PER_S}),
            )
        }
        _ => {
            println!(
                "verdict 2, no overruns attributable to the others: FAIL — not judged: no windows with the heavy session, or none without"
            );
            (
                false,
                json!({"pass": false, "error": "no windows to compare"}),
            )
        }
    }
}

/// The result file's content.
fn report_json(r: &Report<'_>, groups: &Groups, minutes: Vec<Value>, verdicts: Value) -> Value {
    let (cfg, windows, cycles, last) = (r.cfg, r.windows, r.cycles, r.last);
    let (bridge_runs, forces, watchers_failed) = (r.bridge_runs, r.forces, r.watchers_failed);
    let doc = json!({
        "what": "system soak (issue 16): the genuine session's overruns and the daemon's memory with the bridge at 1 kHz, watchers at 30 Hz, scripted forces and a heavy session started and stopped every minute",
        "command": cfg.command(),
        "minutes": cfg.minutes,
        "watchers": cfg.watchers,
        "scene": cfg.scene,
        "heavy_tets": cfg.heavy_tets,
        "realtime": cfg.realtime,
        "window_s": WINDOW_S,
        "heavy_schedule_s": [HEAVY_START_WINDOW * WINDOW_S + ACTION_OFFSET_S, HEAVY_STOP_WINDOW * WINDOW_S + ACTION_OFFSET_S],
        "force": {"period_s": FORCE_PERIOD.as_secs_f64(), "point_m": FORCE_POINT_M, "force_n": FORCE_N,
                  "duration_s": FORCE_DURATION_S, "applied": forces.0, "failed": forces.1},
        "bridge": {"script": "poke", "amplitude_m": POKE_AMPLITUDE_M, "frequency_hz": POKE_FREQUENCY_HZ, "runs": bridge_runs},
        "verdicts": verdicts,
        "summary": {
            "quiet": groups.quiet.as_ref().map(Group::json),
            "heavy": groups.steady.as_ref().map(Group::json),
            "switch": groups.switch.as_ref().map(Group::json),
            "with_heavy": groups.with_heavy.as_ref().map(Group::json),
        },
        "genuine_final": {"steps": last.steps, "overruns": last.overruns, "step_p50_us": last.step_p50_us,
                          "step_p99_us": last.step_p99_us, "step_max_us": last.step_max_us,
                          "faulted": last.faulted, "fault": last.fault, "device_samples": last.device_samples,
                          "peak_force_n": last.peak_force_n},
        "watchers_failed": watchers_failed,
        "heavy_cycles": cycles,
        "minutes_table": minutes,
        "windows": windows.iter().map(Window::json).collect::<Vec<_>>(),
    });
    doc
}
