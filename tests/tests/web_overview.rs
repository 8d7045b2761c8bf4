//! The session overview page (issue 50, section 3) in a real browser: two real `hapticd`
//! daemons (the second with tokens), one session on each, `haptic-viewer --web` on the first
//! with `--stations` naming the second (with its viewer token), the second again without a
//! token, and a daemon that does not exist. Debian's headless Chromium opens `/overview`: one
//! card per session with its scene and a rendered picture of its surface, the station without a
//! token refused (the relay's own token is never sent to another daemon), the missing daemon
//! marked unreachable while the others are shown, and bad picture requests answered 400. Then
//! one `haptic-bridge` drives two simulated tools on the LV session: its card lists both tools
//! ("2 of 2"), each with its device and force.
//!
//! Chromium comes from `tests/install-chromium.sh` as for `web_viewer.rs` (the same skip rule).

use std::time::Duration;

use anyhow::{Context, Result, bail, ensure};
use haptic_e2e::browser::{Browser, Rgb, find_or_install_chromium};
use haptic_e2e::install;
use haptic_e2e::{
    BRIDGE, CTL, Daemon, STEP_TIMEOUT, run_bin_env, serial, spawn_bin, spawn_web_viewer,
    start_session, unique_temp_dir,
};

const WIDTH: u32 = 1000;
const HEIGHT: u32 = 700;

/// Pixels of the displacement colour map's lower end (a surface at rest): clearly blue.
fn bluish(p: [u8; 3]) -> bool {
    let [r, _, b] = p.map(i32::from);
    b > 90 && b > r + 40
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_overview_shows_the_sessions_of_every_station() -> Result<()> {
    let chromium = match find_or_install_chromium() {
        Ok(p) => p,
        Err(missing) => return install::skip_or_fail("web_overview (chromium)", &missing),
    };
    let _serial = serial().await;
    let dir = unique_temp_dir("haptic-overview")?;
    let first = Daemon::spawn(&[])?;
    let lv = start_session(&first.url(), "lv").await?;
    let tokens = dir.join("tokens.toml");
    let second = Daemon::spawn(&["--tokens-file", &tokens.display().to_string()])?;
    let control = dir.join("control.token").display().to_string();
    let started = run_bin_env(
        CTL,
        &["start", "hemisphere-springs"],
        &[
            ("HAPTICD_ADDR", &second.url()),
            ("HAPTICD_TOKEN_FILE", &control),
        ],
        STEP_TIMEOUT,
    )
    .await?
    .success()?;
    let springs = started.stdout.trim().to_string();

    let stations = dir.join("stations.toml");
    std::fs::write(
        &stations,
        format!(
            "[[station]]\nname = \"bench 2\"\nurl = \"{}\"\ntoken_file = \"{}\"\n\n\
             [[station]]\nname = \"no token\"\nurl = \"{}\"\n\n\
             [[station]]\nname = \"offline\"\nurl = \"http://127.0.0.1:1\"\n",
            second.url(),
            dir.join("viewer.token").display(),
            second.url()
        ),
    )?;
    let (_web, addr) = spawn_web_viewer(
        &first.url(),
        &["--stations", &stations.display().to_string()],
    )
    .await?;

    let mut browser = Browser::launch(&chromium, WIDTH, HEIGHT).await?;
    let page = browser
        .open(&format!("http://{addr}/overview"), WIDTH, HEIGHT)
        .await?;
    // Two updates, two cards, and both pictures loaded at their size.
    let ready = "!!(window.hapticOverview && window.hapticOverview.state.updates >= 2 \
                 && document.querySelectorAll('.card').length === 2 \
                 && Array.from(document.querySelectorAll('.card img')).every(i => i.complete && i.naturalWidth === 240))";
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    while browser.eval(&page, ready).await? != serde_json::json!(true) {
        if tokio::time::Instant::now() >= deadline {
            let html = browser
                .eval(&page, "document.getElementById('stations').innerText")
                .await?;
            bail!("the overview did not show two cards with pictures: {html}");
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }

    // The cards: station, session and scene; the refused and the unreachable stations.
    let cards = browser
        .eval(
            &page,
            "Array.from(document.querySelectorAll('.card')).map(c => \
             [c.dataset.station, c.dataset.session, c.querySelector('.scene').textContent])",
        )
        .await?;
    ensure!(
        cards == serde_json::json!([["0", lv, "lv"], ["1", springs, "hemisphere-springs"]]),
        "cards {cards}"
    );
    let errors = browser
        .eval(
            &page,
            "Array.from(document.querySelectorAll('section.station')).map(s => \
             [s.dataset.station, (s.querySelector('.error') || {}).textContent || ''])",
        )
        .await?;
    let error_of = |i: usize| errors[i][1].as_str().unwrap_or("").to_string();
    eprintln!("station errors: {errors}");
    ensure!(
        error_of(0).is_empty() && error_of(1).is_empty(),
        "the reachable stations report errors: {errors}"
    );
    ensure!(
        error_of(2).contains("UNAUTHENTICATED"),
        "the station without a token was not refused: {errors}"
    );
    ensure!(!error_of(3).is_empty(), "the offline station: {errors}");

    // Bad picture requests are refused, never relayed.
    let codes = browser
        .eval(
            &page,
            "Promise.all(['station=9&session=x', 'station=0&session=..%2Fetc', 'station=x&session=a', \
             'station=0'].map(q => fetch('/api/picture?' + q).then(r => r.status)))",
        )
        .await?;
    ensure!(codes == serde_json::json!([400, 400, 400, 400]), "{codes}");

    // The pictures show the surfaces: blue (at rest) inside each picture's box.
    let boxes = browser
        .eval(
            &page,
            "Array.from(document.querySelectorAll('.card img')).map(i => { \
             const r = i.getBoundingClientRect(); return [r.left, r.top, r.width, r.height]; })",
        )
        .await?;
    let shot = Rgb::from_png(&browser.screenshot(&page).await?)?;
    let dpr = shot.width as f64 / f64::from(WIDTH);
    for b in boxes.as_array().context("picture boxes")? {
        let v = |k: usize| b[k].as_f64().unwrap_or(0.0) * dpr;
        let (x0, y0, w, h) = (v(0) as i64, v(1) as i64, v(2) as i64, v(3) as i64);
        let mut blue = 0;
        for y in y0..y0 + h {
            for x in x0..x0 + w {
                if shot.get(x, y).is_some_and(bluish) {
                    blue += 1;
                }
            }
        }
        eprintln!("picture at {b}: {blue} blue pixels of {}", w * h);
        ensure!(
            blue > w * h / 20,
            "picture at {b} shows no surface: {blue} blue pixels"
        );
    }

    // Two tools of one simulated arm press the LV session on opposite sides: its card lists
    // both, each with its device and a force, "2 of 2" connected. The card is read once both
    // rows show contact and a force above 1 mN (the first contact ticks, on a slow machine,
    // can show 1.0 mN while the arm still presses in).
    let _bridge = spawn_bin(
        BRIDGE,
        &[
            "--server",
            &first.url(),
            "--session",
            &lv,
            "--tool",
            "left",
            "--tool",
            "right",
            "--hold-s",
            "30",
            "--rearm",
            "auto",
        ],
    )?;
    let tools_ready = "(() => { const c = document.querySelector('.card[data-station=\"0\"]'); \
                       const rows = c ? Array.from(c.querySelectorAll('table.tools tr[data-tool]')) : []; \
                       return rows.length === 2 && rows.every(r => r.classList.contains('contact') \
                       && parseFloat(r.cells[2].textContent) > 1.0); })()";
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    while browser.eval(&page, tools_ready).await? != serde_json::json!(true) {
        if tokio::time::Instant::now() >= deadline {
            let html = browser
                .eval(&page, "document.getElementById('stations').innerText")
                .await?;
            bail!("the LV card did not show two tools in contact above 1 mN: {html}");
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let rows = browser
        .eval(
            &page,
            "Array.from(document.querySelectorAll('.card[data-station=\"0\"] table.tools tr[data-tool]')) \
             .map(r => Array.from(r.cells).map(c => c.textContent))",
        )
        .await?;
    eprintln!("the LV card's tools: {rows}");
    // Rows in slot order; the two tools of one process connect at once, so either may hold
    // slot 0.
    let mut cells: Vec<[String; 3]> = rows
        .as_array()
        .context("tool rows")?
        .iter()
        .map(|r| [0, 1, 2].map(|j| r[j].as_str().unwrap_or("").to_string()))
        .collect();
    cells.sort();
    let names: Vec<(&str, &str)> = cells
        .iter()
        .map(|c| (c[0].as_str(), c[1].as_str()))
        .collect();
    ensure!(names == [("left", "sim"), ("right", "sim")], "tools {rows}");
    for c in &cells {
        let force: f64 = c[2].trim_end_matches(" mN").parse()?;
        ensure!(force > 1.0, "tool {} force {force} mN: {rows}", c[0]);
    }
    let count = browser
        .eval(
            &page,
            "Array.from(document.querySelectorAll('.card[data-station=\"0\"] dt')) \
             .filter(d => d.textContent === 'tools').map(d => d.nextSibling.textContent)",
        )
        .await?;
    ensure!(count == serde_json::json!(["2 of 2"]), "tools row {count}");
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
