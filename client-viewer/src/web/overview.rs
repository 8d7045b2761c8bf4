//! `overview`: the session overview page of the web viewer (issue 50, section 3): every running
//! session of one or more daemons as a card (scene, device, loop rate, step p99, contact and
//! peak force, a small live picture), for a teacher watching a room of stations, each station a
//! daemon next to its arm.
//!
//! The relay's own daemon (`--server`) is station 0; `--stations FILE` adds others:
//!
//! ```toml
//! [[station]]
//! name = "bench 2"                           # optional, shown on its cards (default: the URL)
//! url = "http://10.0.0.12:50051"
//! token_file = "/etc/haptics/bench2.token"   # optional: a viewer token of that daemon
//! tls_ca = "/etc/haptics/ca.pem"             # for an https:// URL
//! ```
//!
//! A station's token comes only from its `token_file` (never from `HAPTICD_TOKEN`, which
//! belongs to `--server`), so one daemon's token is never sent to another.
//!
//! Routes (added to [`super::router`]):
//! - `GET /overview`: the page (`web/overview.html`, self-contained);
//! - `GET /api/overview`: `{"stations": [{"station", "name", "url", "error", "sessions":
//!   [...]}]}`, each session the statistics of `/api/sessions` plus `device` (the connected
//!   device's name, or null); stations are asked concurrently, each within
//!   [`STATION_TIMEOUT`], so one unreachable station only marks its own entry;
//! - `GET /api/picture?station=I&session=ID`: a PNG of the session's surface
//!   ([`PICTURE_WIDTH`] x [`PICTURE_HEIGHT`], the PNG viewer's renderer), from the first full
//!   frame of a short `Watch`; kept [`PICTURE_MAX_AGE`] and rendered at most
//!   [`PICTURE_RENDERS`] at a time, so browsers cannot make the relay hammer the daemons.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::extract::{Query, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::surface_stream_client::SurfaceStreamClient;
use haptics_proto::v1::{GetStatsRequest, ListSessionsRequest, SurfaceEncoding, WatchRequest};
use serde::Deserialize;
use serde_json::{Value, json};
use tokio::sync::Semaphore;

use super::Relay;
use crate::ClientError;
use crate::raster::{Camera, ProbeView, RenderParams, SurfaceView, bounding_box, render_surface};

/// Most stations a relay shows.
pub const MAX_STATIONS: usize = 64;
/// Largest stations file read, bytes.
pub const MAX_STATIONS_FILE_BYTES: u64 = 64 << 10;
/// Longest a station may take to list its sessions and their statistics.
pub const STATION_TIMEOUT: Duration = Duration::from_secs(2);
/// Picture size, pixels.
pub const PICTURE_WIDTH: u32 = 240;
/// Picture size, pixels.
pub const PICTURE_HEIGHT: u32 = 160;
/// How long a picture is served again before it is made anew.
pub const PICTURE_MAX_AGE: Duration = Duration::from_secs(1);
/// Pictures rendered at the same time (the rest wait).
pub const PICTURE_RENDERS: usize = 2;
/// Pictures kept (the oldest go first).
const PICTURE_CACHE: usize = 256;

const OVERVIEW_HTML: &[u8] = include_bytes!("../../web/overview.html");

/// One daemon of the overview besides the relay's own.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StationConfig {
    /// Shown on the station's cards (default: the URL).
    #[serde(default)]
    pub name: Option<String>,
    /// The daemon's URL, `http://host:port` or `https://host:port`.
    pub url: String,
    /// File holding a token of that daemon (a `viewer` token is enough).
    #[serde(default)]
    pub token_file: Option<PathBuf>,
    /// CA certificate (PEM) that signed that daemon's certificate (`https://` URLs).
    #[serde(default)]
    pub tls_ca: Option<PathBuf>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct StationsFile {
    #[serde(default)]
    station: Vec<StationConfig>,
}

/// Reads a stations file (module documentation).
///
/// # Errors
/// [`ClientError::InvalidConfig`] naming the file: unreadable, larger than
/// [`MAX_STATIONS_FILE_BYTES`], not valid TOML of that form, more than [`MAX_STATIONS`]
/// stations, an empty or non-`http(s)://` URL, or an empty name.
pub fn read_stations(path: &Path) -> Result<Vec<StationConfig>, ClientError> {
    use std::io::Read as _;
    let bad = |m: String| ClientError::InvalidConfig(format!("{}: {m}", path.display()));
    let file = std::fs::File::open(path).map_err(|e| bad(e.to_string()))?;
    let mut text = String::new();
    file.take(MAX_STATIONS_FILE_BYTES + 1)
        .read_to_string(&mut text)
        .map_err(|e| bad(e.to_string()))?;
    if text.len() as u64 > MAX_STATIONS_FILE_BYTES {
        return Err(bad(format!("larger than {MAX_STATIONS_FILE_BYTES} bytes")));
    }
    let parsed: StationsFile = toml::from_str(&text).map_err(|e| bad(e.to_string()))?;
    if parsed.station.len() > MAX_STATIONS {
        return Err(bad(format!(
            "{} stations: at most {MAX_STATIONS}",
            parsed.station.len()
        )));
    }
    for (i, s) in parsed.station.iter().enumerate() {
        if !(s.url.starts_with("http://") || s.url.starts_with("https://")) {
            return Err(bad(format!(
                "station {}: url {:?} must start with http:// or https://",
                i + 1,
                s.url
            )));
        }
        if s.name.as_deref().is_some_and(|n| n.trim().is_empty()) {
            return Err(bad(format!("station {}: an empty name", i + 1)));
        }
    }
    Ok(parsed.station)
}

/// A connected station (connections are made on first use).
pub(crate) struct StationLink {
    pub(crate) name: String,
    pub(crate) url: String,
    pub(crate) channel: haptic_cli::credentials::AuthChannel,
}

impl StationLink {
    /// The link to `s`: its own token file or none, its own CA.
    pub(crate) fn new(s: &StationConfig) -> Result<Self, ClientError> {
        let url = haptic_cli::connect::normalize_url(&s.url);
        let token = match &s.token_file {
            Some(f) => haptic_cli::credentials::ClientCredentials {
                token_file: Some(f.clone()),
                ..Default::default()
            }
            .interceptor()?,
            None => haptic_cli::credentials::BearerToken::none(),
        };
        let credentials = haptic_cli::credentials::ClientCredentials {
            tls_ca: s.tls_ca.clone(),
            ..Default::default()
        };
        let channel = token.wrap(
            credentials
                .endpoint(&url)?
                .connect_timeout(Duration::from_secs(2))
                .tcp_nodelay(true)
                .connect_lazy(),
        );
        Ok(Self {
            name: s.name.clone().unwrap_or_else(|| s.url.clone()),
            url,
            channel,
        })
    }
}

/// A picture's key (station index, session id) and what is kept of it (when made, the PNG).
type PictureCache = HashMap<(usize, String), (Instant, Arc<Vec<u8>>)>;

/// The pictures made lately and the limit on making them.
pub(crate) struct Pictures {
    cache: Mutex<PictureCache>,
    renders: Semaphore,
}

impl Default for Pictures {
    fn default() -> Self {
        Self {
            cache: Mutex::new(HashMap::new()),
            renders: Semaphore::new(PICTURE_RENDERS),
        }
    }
}

impl Pictures {
    fn fresh(&self, key: &(usize, String)) -> Option<Arc<Vec<u8>>> {
        let cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        cache
            .get(key)
            .filter(|(t, _)| t.elapsed() < PICTURE_MAX_AGE)
            .map(|(_, png)| png.clone())
    }

    fn keep(&self, key: (usize, String), png: Arc<Vec<u8>>) {
        let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        if cache.len() >= PICTURE_CACHE && !cache.contains_key(&key) {
            let oldest = cache
                .iter()
                .min_by_key(|(_, (t, _))| *t)
                .map(|(k, _)| k.clone());
            if let Some(k) = oldest {
                cache.remove(&k);
            }
        }
        cache.insert(key, (Instant::now(), png));
    }
}

/// One station's sessions with their statistics, or why not.
async fn station_json(index: usize, link: &StationLink) -> Value {
    let mut ctl = SessionControlClient::new(link.channel.clone());
    let listed = async {
        let list = ctl
            .list_sessions(ListSessionsRequest {})
            .await?
            .into_inner();
        let mut sessions = Vec::new();
        for summary in list.sessions {
            let request = GetStatsRequest {
                session_id: summary.session_id.clone(),
            };
            // A session that ended between the two calls is left out.
            if let Ok(r) = ctl.get_stats(request).await {
                let mut v = super::stats_json(&r.into_inner());
                v["device"] = summary.device.map_or(Value::Null, |d| json!(d.name));
                v["device_connected"] = json!(summary.device_connected);
                sessions.push(v);
            }
        }
        Ok::<_, tonic::Status>(sessions)
    };
    let (sessions, error) = match tokio::time::timeout(STATION_TIMEOUT, listed).await {
        Ok(Ok(s)) => (s, Value::Null),
        Ok(Err(status)) => (Vec::new(), json!(ClientError::from(status).to_string())),
        Err(_) => (
            Vec::new(),
            json!(format!(
                "no answer within {} s",
                STATION_TIMEOUT.as_secs_f64()
            )),
        ),
    };
    json!({
        "station": index,
        "name": link.name,
        "url": link.url,
        "error": error,
        "sessions": sessions,
    })
}

pub(crate) async fn page() -> Response {
    (
        [(header::CONTENT_TYPE, "text/html; charset=utf-8")],
        OVERVIEW_HTML,
    )
        .into_response()
}

pub(crate) async fn api_overview(State(relay): State<Arc<Relay>>) -> Response {
    let stations = relay.stations();
    let answers = futures_util::future::join_all(
        stations
            .iter()
            .enumerate()
            .map(|(i, link)| station_json(i, link)),
    )
    .await;
    axum::Json(json!({ "stations": answers })).into_response()
}

pub(crate) async fn api_picture(
    State(relay): State<Arc<Relay>>,
    Query(q): Query<HashMap<String, String>>,
) -> Response {
    let station = q.get("station").and_then(|s| s.parse::<usize>().ok());
    let id = q.get("session").cloned().unwrap_or_default();
    let Some(station) = station.filter(|&s| s < relay.stations().len()) else {
        return (
            StatusCode::BAD_REQUEST,
            "station: the index of a station of /api/overview",
        )
            .into_response();
    };
    if !super::valid_session_id(&id) {
        return (
            StatusCode::BAD_REQUEST,
            "session: give the id of a running session (letters, digits, - and _)",
        )
            .into_response();
    }
    let key = (station, id);
    let pictures = relay.pictures();
    let png = match pictures.fresh(&key) {
        Some(png) => Ok(png),
        None => {
            let _permit = pictures.renders.acquire().await;
            match pictures.fresh(&key) {
                Some(png) => Ok(png),
                None => picture(&relay.stations()[station], &key.1)
                    .await
                    .map(|png| {
                        let png = Arc::new(png);
                        pictures.keep(key.clone(), png.clone());
                        png
                    }),
            }
        }
    };
    match png {
        Ok(png) => (
            [
                (header::CONTENT_TYPE, "image/png"),
                (header::CACHE_CONTROL, "no-store"),
            ],
            png.as_ref().clone(),
        )
            .into_response(),
        Err(e) => (StatusCode::BAD_GATEWAY, e).into_response(),
    }
}

/// The session's surface now, as a PNG: the first frame of a full-precision `Watch`; the
/// error says why not (no frame in time, the stream ended, a refusal, a bad frame).
async fn picture(link: &StationLink, id: &str) -> Result<Vec<u8>, String> {
    let params = RenderParams {
        width: PICTURE_WIDTH,
        height: PICTURE_HEIGHT,
        legend: false,
        ..RenderParams::default()
    };
    let mut client =
        SurfaceStreamClient::new(link.channel.clone()).max_decoding_message_size(64 << 20);
    let request = WatchRequest {
        session_id: id.to_string(),
        max_rate_hz: 10.0,
        encoding: SurfaceEncoding::Full as i32,
        quantum_m: 0.0,
    };
    let first = tokio::time::timeout(STATION_TIMEOUT, async {
        let mut stream = client.watch(request).await?.into_inner();
        stream.message().await
    })
    .await
    .map_err(|_| format!("no frame within {} s", STATION_TIMEOUT.as_secs_f64()))?
    .map_err(|status| ClientError::from(status).to_string())?
    .ok_or("the session's stream ended")?;
    tokio::task::spawn_blocking(move || render_first(&first, &params))
        .await
        .map_err(|e| format!("the picture worker failed: {e}"))?
}

/// Renders a full keyframe (positions, triangles, optionally rest positions) to a PNG; a
/// frame that is not one, or is malformed, is an error (nothing is drawn from it).
fn render_first(
    f: &haptics_proto::v1::SurfaceFrame,
    params: &RenderParams,
) -> Result<Vec<u8>, String> {
    let p = &f.positions_m;
    let n = p.len() / 3;
    if !f.keyframe || p.is_empty() || !p.len().is_multiple_of(3) {
        return Err("the first frame is not a full keyframe".into());
    }
    if !f.triangles.len().is_multiple_of(3) || f.triangles.iter().any(|&i| i as usize >= n) {
        return Err("the keyframe's triangles do not fit its vertices".into());
    }
    if p.iter().any(|v| !v.is_finite()) {
        return Err("the keyframe has a non-finite position".into());
    }
    let rest_ok =
        f.rest_positions_m.len() == p.len() && f.rest_positions_m.iter().all(|v| v.is_finite());
    let rest = if rest_ok { &f.rest_positions_m } else { p };
    let (min, max) = bounding_box(p).ok_or("the keyframe has no finite vertex")?;
    let probe = f.probe_position_m.as_ref().map(|pos| ProbeView {
        position_m: glam::DVec3::from_array(pos.to_array()),
        radius_m: f.probe_radius_m,
        force_n: f
            .contact_force_n
            .as_ref()
            .map_or(glam::DVec3::ZERO, |v| glam::DVec3::from_array(v.to_array())),
        in_contact: f.in_contact,
    });
    let view = SurfaceView {
        rest_m: rest,
        positions_m: p,
        triangles: &f.triangles,
        probe,
    };
    render_surface(&view, &Camera::auto_frame(min, max, params), params)
        .encode_png()
        .map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(text: &str) -> Result<Vec<StationConfig>, ClientError> {
        let dir = std::env::temp_dir().join(format!("overview-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(format!("s{}.toml", text.len()));
        std::fs::write(&path, text).unwrap();
        let r = read_stations(&path);
        let _ = std::fs::remove_file(&path);
        r
    }

    #[test]
    fn a_stations_file_is_read_and_checked() {
        let ok = read(
            "[[station]]\nurl = \"http://10.0.0.12:50051\"\ntoken_file = \"/t\"\n\n\
             [[station]]\nname = \"b\"\nurl = \"https://h:1\"\ntls_ca = \"/ca.pem\"\n",
        )
        .unwrap();
        assert_eq!(ok.len(), 2);
        assert_eq!(ok[0].token_file.as_deref(), Some(Path::new("/t")));
        assert_eq!(ok[1].name.as_deref(), Some("b"));
        assert!(read("").unwrap().is_empty());
        for (text, says) in [
            ("[[station]]\nurl = \"ftp://x\"\n", "http:// or https://"),
            (
                "[[station]]\nurl = \"http://x:1\"\nname = \" \"\n",
                "empty name",
            ),
            (
                "[[station]]\nurl = \"http://x:1\"\ntoken = \"secret\"\n",
                "unknown field",
            ),
            ("[[station]]\nname = \"no url\"\n", "url"),
        ] {
            let e = read(text).unwrap_err().to_string();
            assert!(e.contains(says), "{text:?}: {e}");
        }
        let many = "[[station]]\nurl = \"http://x:1\"\n".repeat(MAX_STATIONS + 1);
        let e = read(&many).unwrap_err().to_string();
        assert!(e.contains("at most 64"), "{e}");
        let e = read_stations(Path::new("/no/such/stations.toml")).unwrap_err();
        assert!(e.to_string().contains("/no/such/stations.toml"), "{e}");
    }
}
