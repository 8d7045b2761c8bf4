//! The Prometheus endpoint in process: a running LV session shows up with its labels, counters
//! agree with GetStats' snapshot, the histograms are well formed (cumulative buckets, `+Inf`
//! equal to `_count`, the step-time count equal to the steps of the same snapshot), and
//! `GET /metrics` over HTTP serves the same text with the OpenMetrics content type.

use std::sync::Arc;
use std::time::{Duration, Instant};

use haptic_server::ServerConfig;
use haptic_server::metrics;
use haptic_server::session::SessionManager;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// The value of the sample line `name{labels}` (labels as printed, without braces).
fn sample(text: &str, name: &str, labels: &str) -> Option<f64> {
    let key = if labels.is_empty() {
        format!("{name} ")
    } else {
        format!("{name}{{{labels}}} ")
    };
    text.lines()
        .find_map(|l| l.strip_prefix(key.as_str()))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
}

/// `(le, cumulative count)` of histogram `name` for `labels`, in printed order (the encoder
/// puts `le` first: `name_bucket{le="0.001",session=...} 12`).
fn buckets(text: &str, name: &str, labels: &str) -> Vec<(String, f64)> {
    let prefix = format!("{name}_bucket{{le=\"");
    let suffix = format!(",{labels}}}");
    text.lines()
        .filter_map(|l| l.strip_prefix(prefix.as_str()))
        .filter_map(|rest| {
            let (le, rest) = rest.split_once('"')?;
            let value = rest.strip_prefix(suffix.as_str())?.trim();
            Some((le.to_string(), value.parse().expect("bucket count")))
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_are_scraped_with_consistent_counters_and_histograms() {
    let manager = Arc::new(SessionManager::new(ServerConfig::default()));
    let scene = manager.load_scene("lv", "").unwrap();
    let session = manager.start(&scene).unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    while session.stats().steps < 300 && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let registry = metrics::registry(manager.clone());
    let text = metrics::render(&registry).unwrap();
    let labels = format!(r#"session="{}",scene="lv",family="fem""#, session.id);

    assert_eq!(sample(&text, "hapticd_sessions", ""), Some(1.0), "{text}");
    let steps = sample(&text, "hapticd_steps_total", &labels).expect("steps counter");
    assert!(steps >= 300.0, "steps {steps}");
    let rate = sample(&text, "hapticd_loop_rate_hz", &labels).expect("loop rate");
    assert!(rate > 0.0 && rate < 2000.0, "loop rate {rate}");
    assert_eq!(sample(&text, "hapticd_faulted", &labels), Some(0.0));

    let b = buckets(&text, "hapticd_step_time_seconds", &labels);
    assert_eq!(
        b.len(),
        haptic_server::servo::LATENCY_BUCKET_BOUNDS_US.len() + 1,
        "{text}"
    );
    assert_eq!(b.last().unwrap().0, "+Inf");
    assert_eq!(b[6].0, "0.001", "bounds in seconds: {b:?}");
    assert!(
        b.windows(2).all(|w| w[1].1 >= w[0].1),
        "not cumulative: {b:?}"
    );
    let count = sample(&text, "hapticd_step_time_seconds_count", &labels).unwrap();
    assert_eq!(b.last().unwrap().1, count);
    // Step times and the steps counter come from the same snapshot: one record per tick.
    assert_eq!(count, steps);
    let sum = sample(&text, "hapticd_step_time_seconds_sum", &labels).unwrap();
    let mean = sum / count;
    assert!(mean > 1e-6 && mean < 0.1, "mean step {mean} s");
    // No device: no pose-to-force records, no contact, no companion.
    assert_eq!(
        sample(&text, "hapticd_pose_to_force_seconds_count", &labels),
        Some(0.0)
    );
    assert_eq!(
        sample(&text, "hapticd_contact_ticks_total", &labels),
        Some(0.0)
    );
    assert_eq!(
        sample(&text, "hapticd_companion_ticks_total", &labels),
        Some(0.0)
    );
    assert_eq!(
        sample(&text, "hapticd_out_of_workspace_samples_total", &labels),
        Some(0.0)
    );
    // The default LV asks for one thread ("auto" gives it one): no pool, no wait.
    assert_eq!(
        sample(&text, "hapticd_session_threads", &labels),
        Some(f64::from(session.tick_threads))
    );
    assert_eq!(session.tick_threads, 1);
    assert_eq!(
        sample(&text, "hapticd_pool_wait_max_seconds", &labels),
        Some(0.0)
    );
    // The default scene does not follow the probe: no region swaps. Counter names end in
    // one `_total` (the encoder adds it), never two.
    assert_eq!(
        sample(&text, "hapticd_region_swaps_total", &labels),
        Some(0.0)
    );
    assert!(!text.contains("_total_total"), "{text}");
    // Nor a region cache.
    assert_eq!(sample(&text, "hapticd_region_tiles", &labels), Some(0.0));
    assert_eq!(
        sample(&text, "hapticd_region_tiles_ready", &labels),
        Some(0.0)
    );
    assert_eq!(
        sample(&text, "hapticd_region_tiles_loaded", &labels),
        Some(0.0)
    );
    assert_eq!(
        sample(&text, "hapticd_region_tiles_refused", &labels),
        Some(0.0)
    );

    // Over HTTP.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(metrics::serve(listener, manager.clone()));
    let mut tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    tcp.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .await
        .unwrap();
    let mut response = String::new();
    tokio::time::timeout(Duration::from_secs(10), tcp.read_to_string(&mut response))
        .await
        .expect("metrics answer within 10 s")
        .unwrap();
    assert!(response.starts_with("HTTP/1.1 200"), "{response}");
    assert!(
        response
            .to_ascii_lowercase()
            .contains("content-type: application/openmetrics-text"),
        "{response}"
    );
    assert!(response.contains(&format!("hapticd_steps_total{{{labels}}}")));
    assert!(response.trim_end().ends_with("# EOF"));

    // Every metric the shipped Grafana dashboard queries is one the endpoint serves.
    let dashboard = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/grafana/hapticd.json"),
    )
    .unwrap();
    let mut queried = 0;
    for (i, _) in dashboard.match_indices("hapticd_") {
        let name: String = dashboard[i..]
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect();
        if name == "hapticd_" {
            continue; // the dashboard's own uid/title
        }
        queried += 1;
        assert!(
            text.lines().any(|l| l.starts_with(&name)),
            "the dashboard queries {name}, which /metrics does not serve"
        );
    }
    assert!(
        queried >= 10,
        "only {queried} metric references in the dashboard"
    );

    manager.stop(&session.id).unwrap();
    let after = metrics::render(&registry).unwrap();
    assert_eq!(sample(&after, "hapticd_sessions", ""), Some(0.0), "{after}");
}
