//! The README's first command: the `haptic-demo` runner's library against freshly built binaries
//! (shorter hold, output in a temp dir).

use anyhow::Result;
use haptic_e2e::demo::{self, DemoParams};
use haptic_e2e::{built_bin_dir, serial, unique_temp_dir};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn demo_runs_end_to_end_and_writes_its_outputs() -> Result<()> {
    let _serial = serial().await;
    let out = unique_temp_dir("haptic-e2e-demo")?;
    let mut p = DemoParams::new(built_bin_dir()?);
    p.out_dir = out.clone();
    p.hold_s = 1.5;
    p.force_after_s = 1.0;
    let mut lines = Vec::new();
    let s = demo::run(&p, &mut |l| lines.push(l.to_string())).await?;
    assert!(
        lines.iter().any(|l| l.starts_with("starting hapticd")),
        "{lines:?}"
    );
    assert_eq!(s["scene"], "lv");
    assert!(s["steps"].as_u64().unwrap_or(0) > 0, "{s}");
    assert!(s["peak_force_n"].as_f64().unwrap_or(0.0) > 0.03, "{s}");
    assert!(
        s["max_displacement_m"].as_f64().unwrap_or(0.0) > 0.001,
        "{s}"
    );
    assert!(s["pictures_written"].as_u64().unwrap_or(0) >= 1, "{s}");
    for f in ["bridge.csv", "summary.json", "pictures/latest.png"] {
        assert!(out.join(f).is_file(), "{f} missing in {out:?}");
    }
    let text = demo::format_summary(&s, &out.join("summary.json"));
    assert!(
        text.contains("servo loop rate") && text.contains("peak force"),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&out);
    Ok(())
}
