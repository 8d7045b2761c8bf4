//! The web viewer's relay without a browser (issue 17): the real `hapticd` and `haptic-viewer
//! --web`, WebSocket clients in the test. Three browsers cost the daemon one watcher; each gets
//! a keyframe with the topology first and then compact frames that decode against it; the page
//! and the JSON API answer; bad queries and bad messages get errors, never a crash. When a probe
//! press subdivides a mass-spring surface, a browser gets a keyframe with the new triangles.

use std::time::Duration;

use anyhow::{Context, Result, bail, ensure};
use futures_util::{SinkExt, StreamExt};
use haptic_e2e::{
    Daemon, VIEWER, device_link, serial, session_control, spawn_bin, spawn_web_viewer,
    start_session,
};
use haptics_proto::delta::DeltaCodec;
use haptics_proto::v1::{DeviceSample, GetStatsRequest, SurfaceFrame, Vec3};
use prost::Message as _;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio_tungstenite::tungstenite::Message;

type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// A plain HTTP/1.1 GET on loopback: (status code, body).
async fn get(addr: &str, path: &str) -> Result<(u16, String)> {
    let mut s = tokio::net::TcpStream::connect(addr).await?;
    s.write_all(
        format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes(),
    )
    .await?;
    let mut buf = Vec::new();
    tokio::time::timeout(Duration::from_secs(30), s.read_to_end(&mut buf)).await??;
    let text = String::from_utf8_lossy(&buf).into_owned();
    let code = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .context("no HTTP status")?;
    let body = text
        .split_once("\r\n\r\n")
        .map(|x| x.1)
        .unwrap_or("")
        .to_string();
    Ok((code, body))
}

async fn next_binary(ws: &mut Ws) -> Result<SurfaceFrame> {
    loop {
        let m = tokio::time::timeout(Duration::from_secs(30), ws.next())
            .await
            .context("no message within 30 s")?
            .context("socket closed")??;
        if let Message::Binary(b) = m {
            return Ok(SurfaceFrame::decode(b)?);
        }
    }
}

/// The next JSON text message other than the periodic status.
async fn next_text(ws: &mut Ws) -> Result<serde_json::Value> {
    loop {
        let m = tokio::time::timeout(Duration::from_secs(30), ws.next())
            .await
            .context("no message within 30 s")?
            .context("socket closed")??;
        if let Message::Text(t) = m {
            let v: serde_json::Value = serde_json::from_str(t.as_str())?;
            if v["type"] != "status" {
                return Ok(v);
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_upstream_for_many_browsers_keyframes_first_and_bad_input_answered() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "lv").await?;
    let mut web = spawn_bin(VIEWER, &["--server", &url, "--web", "127.0.0.1:0"])?;
    let stdout = web.child.stdout.take().context("piped stdout")?;
    let mut lines = BufReader::new(stdout).lines();
    let addr = tokio::time::timeout(Duration::from_secs(30), async {
        while let Some(l) = lines.next_line().await? {
            if let Some(a) = l.strip_prefix("listening on ") {
                return anyhow::Ok(a.trim().to_string());
            }
        }
        bail!("no address printed")
    })
    .await??;

    // The page, its script and three.js are served from the binary; the session is listed.
    let (code, body) = get(&addr, "/").await?;
    ensure!(code == 200 && body.contains("importmap"), "{code}");
    for path in [
        "/app.js",
        "/vendor/three.module.js",
        "/vendor/OrbitControls.js",
    ] {
        ensure!(get(&addr, path).await?.0 == 200, "{path}");
    }
    let (code, body) = get(&addr, "/api/sessions").await?;
    let list: serde_json::Value = serde_json::from_str(&body)?;
    ensure!(
        code == 200 && list[0]["session_id"] == id.as_str(),
        "{body}"
    );
    ensure!(get(&addr, "/nope").await?.0 == 404);

    // Bad queries are refused before the upgrade.
    for q in [
        "/ws?session=../etc",
        "/ws",
        &format!("/ws?session={id}&rate=NaN"),
        &format!("/ws?session={id}&rate=1e9"),
    ] {
        let (code, _) = get(&addr, q).await?;
        ensure!(code == 400, "{q}: {code}");
    }

    // Three browsers: each starts with a keyframe carrying the topology.
    let ws_url = format!("ws://{addr}/ws?session={id}&rate=30");
    let mut browsers = Vec::new();
    for _ in 0..3 {
        let (ws, _) = tokio_tungstenite::connect_async(ws_url.as_str()).await?;
        browsers.push(ws);
    }
    let mut first = None;
    for ws in &mut browsers {
        let hello = next_text(ws).await?;
        ensure!(hello["type"] == "hello", "{hello}");
        let k = next_binary(ws).await?;
        ensure!(
            k.keyframe && !k.triangles.is_empty() && k.quantum_m > 0.0,
            "keyframe first"
        );
        first.get_or_insert(k);
    }
    let k = first.context("a keyframe")?;
    let n = k.positions_m.len() / 3;
    let codec = DeltaCodec::new(n, &k.triangles)?;
    // Later frames decode against the keyframe they name.
    let ws = &mut browsers[0];
    let mut reference = (k.keyframe_id, k.positions_m.clone());
    for _ in 0..20 {
        let f = next_binary(ws).await?;
        if f.keyframe && f.positions_m.is_empty() {
            ensure!(
                f.base_keyframe_id == reference.0,
                "chained from an unknown keyframe"
            );
            let mut p = vec![0.0; 3 * n];
            codec.decode(&reference.1, &f.reference_delta, f.quantum_m, &mut p)?;
            reference = (f.keyframe_id, p);
        } else if f.keyframe {
            reference = (f.keyframe_id, f.positions_m.clone());
        }
        ensure!(
            f.keyframe_id == reference.0,
            "delta against an unknown keyframe"
        );
        let mut p = vec![0.0; 3 * n];
        codec.decode(&reference.1, &f.position_delta, f.quantum_m, &mut p)?;
        ensure!(p.iter().all(|v| v.is_finite()));
    }

    // The daemon sees one watcher, whatever the number of browsers.
    let stats = session_control(&url)
        .await?
        .get_stats(GetStatsRequest {
            session_id: id.clone(),
        })
        .await?
        .into_inner();
    ensure!(stats.watchers == 1, "daemon watchers {}", stats.watchers);
    let (_, relay) = get(&addr, "/api/relay").await?;
    let relay: serde_json::Value = serde_json::from_str(&relay)?;
    ensure!(relay["sessions"][0]["browsers"] == 3, "{relay}");

    // Bad messages get an error answer; the socket stays usable, and a keyframe request works.
    let ws = &mut browsers[1];
    for bad in ["garbage", r#"{"type":"rate","hz":-1}"#, r#"{"type":"?"}"#] {
        ws.send(Message::Text(bad.into())).await?;
        let reply = next_text(ws).await?;
        ensure!(reply["type"] == "error", "{bad}: {reply}");
    }
    ws.send(Message::Binary(vec![1, 2, 3].into())).await?;
    ensure!(next_text(ws).await?["type"] == "error");
    ws.send(Message::Text(r#"{"type":"keyframe"}"#.into()))
        .await?;
    let mut got = false;
    for _ in 0..10 {
        let f = next_binary(ws).await?;
        if f.keyframe && !f.triangles.is_empty() {
            got = true;
            break;
        }
    }
    ensure!(got, "no keyframe after the request");

    // An unknown session: an error message, then the socket closes. Every time: the daemon
    // refuses at once, often before the browser's task has subscribed to the relay's status
    // (an error sent then used to be lost, and the browser waited forever).
    for _ in 0..10 {
        let (mut ws, _) =
            tokio_tungstenite::connect_async(format!("ws://{addr}/ws?session=nosuchsession"))
                .await?;
        let _hello = next_text(&mut ws).await?;
        let e = next_text(&mut ws).await?;
        ensure!(
            e["type"] == "error" && e["message"].as_str().unwrap_or("").contains("NOT_FOUND"),
            "{e}"
        );
    }
    drop(browsers);
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_browser_gets_the_new_triangles_when_a_press_subdivides_the_surface() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "hemisphere-springs").await?;
    let (_web, addr) = spawn_web_viewer(&url, &[]).await?;
    let (mut ws, _) =
        tokio_tungstenite::connect_async(format!("ws://{addr}/ws?session={id}&rate=30")).await?;
    ensure!(next_text(&mut ws).await?["type"] == "hello");
    let coarse = next_binary(&mut ws).await?;
    ensure!(
        coarse.keyframe && !coarse.triangles.is_empty(),
        "keyframe first"
    );
    let n0 = coarse.positions_m.len() / 3;
    // The dome's apex (it points up, +z) and the probe's radius.
    let apex = (0..n0)
        .max_by(|&a, &b| coarse.positions_m[3 * a + 2].total_cmp(&coarse.positions_m[3 * b + 2]))
        .context("no vertex")?;
    let [x, y, z] = [0, 1, 2].map(|k| f64::from(coarse.positions_m[3 * apex + k]));
    let r = coarse.probe_radius_m;
    ensure!(r > 0.0, "probe radius {r}");

    // A device at 1 kHz: 10 mm above the apex for 0.2 s, 4 mm into it over 0.2 s, then held
    // (the model subdivides the one-ring around the contact node).
    let (tx, rx) = tokio::sync::mpsc::channel::<DeviceSample>(64);
    let session_id = id.clone();
    let device = tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_millis(1));
        let t0 = tokio::time::Instant::now();
        for seq in 1..=60_000u64 {
            tick.tick().await;
            let t = t0.elapsed().as_secs_f64();
            let depth = if t < 0.2 {
                -0.01
            } else {
                4e-3 * ((t - 0.2) / 0.2).min(1.0)
            };
            let s = DeviceSample {
                session_id: session_id.clone(),
                seq,
                device_time_us: (t * 1e6) as u64,
                position_m: Some(Vec3::new(x, y, z + r - depth)),
                velocity_m_per_s: Some(Vec3::new(0.0, 0.0, 0.0)),
                capabilities: None,
                tool_id: String::new(),
            };
            if tx.send(s).await.is_err() {
                break;
            }
        }
    });
    let mut forces = device_link(&url)
        .await?
        .connect(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await?
        .into_inner();
    tokio::spawn(async move { while let Ok(Some(_)) = forces.message().await {} });

    // Frames of the coarse topology until a keyframe of a new one.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    let (fine, before) = loop {
        ensure!(
            tokio::time::Instant::now() < deadline,
            "no new topology within 60 s"
        );
        let f = next_binary(&mut ws).await?;
        if f.topology_version != coarse.topology_version {
            break (f, coarse.topology_version);
        }
    };
    device.abort();
    ensure!(
        fine.keyframe && !fine.triangles.is_empty() && !fine.rest_positions_m.is_empty(),
        "the first frame of topology {} (was {before}) is not a keyframe with triangles",
        fine.topology_version
    );
    let n = fine.rest_positions_m.len() / 3;
    ensure!(
        fine.positions_m.len() == 3 * n,
        "the keyframe of a new topology carries its positions"
    );
    ensure!(
        n > n0 && fine.triangles.len() > coarse.triangles.len(),
        "subdivided: {n0} -> {n} vertices, {} -> {} triangles",
        coarse.triangles.len() / 3,
        fine.triangles.len() / 3
    );
    ensure!(
        fine.triangles.iter().all(|&i| (i as usize) < n),
        "triangles index the new vertices"
    );
    // The following frames decode against the new topology's keyframe.
    let codec = DeltaCodec::new(n, &fine.triangles)?;
    let mut decoded = 0;
    for _ in 0..5 {
        let f = next_binary(&mut ws).await?;
        if f.topology_version != fine.topology_version {
            break; // coarsened again already
        }
        if f.keyframe_id != fine.keyframe_id {
            break; // a new reference: fine, but not what this loop decodes
        }
        let mut p = vec![0.0; 3 * n];
        codec.decode(&fine.positions_m, &f.position_delta, f.quantum_m, &mut p)?;
        ensure!(p.iter().all(|v| v.is_finite()));
        decoded += 1;
    }
    eprintln!(
        "topology {before} -> {}: {n0} -> {n} vertices; {decoded} later frames decoded",
        fine.topology_version
    );
    Ok(())
}
