//! A headless Chromium driven over the Chrome DevTools Protocol, for the browser test of the web
//! viewer: start Debian's `chromium` (installing it with `tests/install-chromium.sh` when it is
//! missing), open a page, evaluate JavaScript, move and click the mouse, take PNG screenshots.
//!
//! The flags are those that work on the project's machines (`../shared/DEPENDENCIES.md`):
//! `--headless --no-sandbox --disable-gpu` with WebGL through SwiftShader
//! (`--enable-unsafe-swiftshader`), no background networking, a fresh profile directory.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::{Context, Result, anyhow, bail};
use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

use crate::install::{self, Missing};

/// Finds `chromium` on PATH, or runs the project's install script (unless
/// `HAPTIC_SKIP_BROWSER_INSTALL` is set) and looks again.
///
/// # Errors
/// Why there is no browser; the caller passes it to [`crate::install::skip_or_fail`].
pub fn find_or_install_chromium() -> Result<PathBuf, Missing> {
    install::find_or_install(
        "chromium",
        "install-chromium.sh",
        Some("HAPTIC_SKIP_BROWSER_INSTALL"),
    )
}

/// A running headless Chromium (killed on drop) and its DevTools connection.
pub struct Browser {
    child: Child,
    _profile: TempDir,
    ws: tokio_tungstenite::WebSocketStream<
        tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>,
    >,
    next_id: u64,
}

struct TempDir(PathBuf);

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// An open page (a DevTools target session).
pub struct Page {
    session: String,
}

impl Browser {
    /// Starts `exe` headless with a `width` x `height` window and connects to it.
    ///
    /// # Errors
    /// Chromium does not start or print its DevTools address within 60 s.
    pub async fn launch(exe: &Path, width: u32, height: u32) -> Result<Browser> {
        let profile = TempDir(crate::unique_temp_dir("chromium-profile")?);
        let mut child = Command::new(exe)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--enable-unsafe-swiftshader",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--disable-extensions",
                "--remote-debugging-port=0",
                "--remote-allow-origins=*",
                &format!("--window-size={width},{height}"),
                &format!("--user-data-dir={}", profile.0.display()),
                "about:blank",
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .with_context(|| format!("starting {}", exe.display()))?;
        let stderr = child.stderr.take().context("piped stderr")?;
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut tx = Some(tx);
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if let Some(url) = line.trim().strip_prefix("DevTools listening on ")
                    && let Some(tx) = tx.take()
                {
                    let _ = tx.send(url.trim().to_string());
                }
            }
        });
        let url = match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(u) => u,
            Err(_) => {
                let _ = child.kill();
                let _ = child.wait();
                bail!("chromium did not print its DevTools address within 60 s");
            }
        };
        let (ws, _) = tokio_tungstenite::connect_async(url.as_str())
            .await
            .with_context(|| format!("connecting to DevTools at {url}"))?;
        Ok(Browser {
            child,
            _profile: profile,
            ws,
            next_id: 1,
        })
    }

    /// Sends one DevTools command (on `session` when given) and returns its `result`.
    ///
    /// # Errors
    /// The connection fails, no answer within 60 s, or the browser answers an error.
    pub async fn call(
        &mut self,
        session: Option<&str>,
        method: &str,
        params: Value,
    ) -> Result<Value> {
        let id = self.next_id;
        self.next_id += 1;
        let mut msg = json!({"id": id, "method": method, "params": params});
        if let Some(s) = session {
            msg["sessionId"] = json!(s);
        }
        self.ws.send(Message::Text(msg.to_string().into())).await?;
        let answer = tokio::time::timeout(Duration::from_secs(60), async {
            while let Some(m) = self.ws.next().await {
                if let Message::Text(t) = m? {
                    let v: Value = serde_json::from_str(t.as_str())?;
                    if v["id"] == json!(id) {
                        return Ok(v);
                    }
                }
            }
            Err(anyhow!("DevTools connection closed"))
        })
        .await
        .with_context(|| format!("no answer to {method} within 60 s"))??;
        if let Some(e) = answer.get("error") {
            bail!("{method} failed: {e}");
        }
        Ok(answer["result"].clone())
    }

    /// Opens `url` in a new `width` x `height` page.
    ///
    /// # Errors
    /// As [`Browser::call`].
    pub async fn open(&mut self, url: &str, width: u32, height: u32) -> Result<Page> {
        let t = self
            .call(None, "Target.createTarget", json!({"url": "about:blank"}))
            .await?;
        let target = t["targetId"].as_str().context("no targetId")?.to_string();
        let a = self
            .call(
                None,
                "Target.attachToTarget",
                json!({"targetId": target, "flatten": true}),
            )
            .await?;
        let session = a["sessionId"].as_str().context("no sessionId")?.to_string();
        // A fixed viewport at one device pixel per CSS pixel, then the page.
        self.call(
            Some(&session),
            "Emulation.setDeviceMetricsOverride",
            json!({"width": width, "height": height, "deviceScaleFactor": 1, "mobile": false}),
        )
        .await?;
        self.call(Some(&session), "Page.navigate", json!({"url": url}))
            .await?;
        Ok(Page { session })
    }

    /// Evaluates a JavaScript expression in `page` and returns its value (JSON); a promise is
    /// awaited and its result returned.
    ///
    /// # Errors
    /// As [`Browser::call`], or the expression threw.
    pub async fn eval(&mut self, page: &Page, expression: &str) -> Result<Value> {
        let r = self
            .call(
                Some(&page.session),
                "Runtime.evaluate",
                json!({"expression": expression, "returnByValue": true, "awaitPromise": true}),
            )
            .await?;
        if let Some(e) = r.get("exceptionDetails") {
            bail!("{expression} threw: {e}");
        }
        Ok(r["result"]["value"].clone())
    }

    /// One DevTools mouse event on `page` at CSS pixel `(x, y)`: `kind` is `mousePressed`,
    /// `mouseMoved` or `mouseReleased`; `buttons` the pressed buttons' mask (1: left) while
    /// the left button is the one acting.
    ///
    /// # Errors
    /// As [`Browser::call`].
    pub async fn mouse(
        &mut self,
        page: &Page,
        kind: &str,
        (x, y): (f64, f64),
        buttons: u32,
    ) -> Result<()> {
        let button = if buttons & 1 == 1 || kind == "mouseReleased" {
            "left"
        } else {
            "none"
        };
        self.call(
            Some(&page.session),
            "Input.dispatchMouseEvent",
            json!({"type": kind, "x": x, "y": y, "button": button, "buttons": buttons,
                   "clickCount": 1}),
        )
        .await?;
        Ok(())
    }

    /// A left-button drag on `page` from `from` to `to` (CSS pixels) in `steps` moves.
    ///
    /// # Errors
    /// As [`Browser::call`].
    pub async fn drag(
        &mut self,
        page: &Page,
        from: (f64, f64),
        to: (f64, f64),
        steps: u32,
    ) -> Result<()> {
        self.mouse(page, "mouseMoved", from, 0).await?;
        self.mouse(page, "mousePressed", from, 1).await?;
        for k in 1..=steps.max(1) {
            let s = f64::from(k) / f64::from(steps.max(1));
            let p = (from.0 + s * (to.0 - from.0), from.1 + s * (to.1 - from.1));
            self.mouse(page, "mouseMoved", p, 1).await?;
        }
        self.mouse(page, "mouseReleased", to, 0).await
    }

    /// A left click on `page` at `at` (CSS pixels).
    ///
    /// # Errors
    /// As [`Browser::call`].
    pub async fn click(&mut self, page: &Page, at: (f64, f64)) -> Result<()> {
        self.mouse(page, "mouseMoved", at, 0).await?;
        self.mouse(page, "mousePressed", at, 1).await?;
        self.mouse(page, "mouseReleased", at, 0).await
    }

    /// A PNG screenshot of `page`.
    ///
    /// # Errors
    /// As [`Browser::call`], or the answer is not base64 PNG data.
    pub async fn screenshot(&mut self, page: &Page) -> Result<Vec<u8>> {
        let r = self
            .call(
                Some(&page.session),
                "Page.captureScreenshot",
                json!({"format": "png"}),
            )
            .await?;
        let data = r["data"].as_str().context("no screenshot data")?;
        base64_decode(data)
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Standard base64 (with padding), as DevTools sends screenshots.
fn base64_decode(s: &str) -> Result<Vec<u8>> {
    let mut out = Vec::with_capacity(s.len() * 3 / 4);
    let (mut acc, mut bits) = (0u32, 0u32);
    for c in s.bytes() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            b'=' | b'\n' | b'\r' => continue,
            _ => bail!("not base64: byte {c}"),
        };
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    Ok(out)
}

/// An RGB picture decoded from PNG bytes.
pub struct Rgb {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Row-major RGB bytes.
    pub data: Vec<u8>,
}

impl Rgb {
    /// Decodes a PNG (RGB or RGBA, 8 bits).
    ///
    /// # Errors
    /// Not a PNG of that kind.
    pub fn from_png(bytes: &[u8]) -> Result<Rgb> {
        let mut dec = png::Decoder::new(std::io::Cursor::new(bytes));
        dec.set_transformations(png::Transformations::normalize_to_color8());
        let mut reader = dec.read_info()?;
        let mut buf = vec![0; reader.output_buffer_size().context("PNG too large")?];
        let info = reader.next_frame(&mut buf)?;
        let channels = match info.color_type {
            png::ColorType::Rgb => 3,
            png::ColorType::Rgba => 4,
            other => bail!("unexpected PNG colour type {other:?}"),
        };
        let (w, h) = (info.width as usize, info.height as usize);
        let mut data = Vec::with_capacity(w * h * 3);
        for px in buf[..w * h * channels].chunks_exact(channels) {
            data.extend_from_slice(&px[..3]);
        }
        Ok(Rgb {
            width: w,
            height: h,
            data,
        })
    }

    /// The pixel at `(x, y)`, `None` outside.
    pub fn get(&self, x: i64, y: i64) -> Option<[u8; 3]> {
        if x < 0 || y < 0 || x as usize >= self.width || y as usize >= self.height {
            return None;
        }
        let i = 3 * (y as usize * self.width + x as usize);
        Some([self.data[i], self.data[i + 1], self.data[i + 2]])
    }
}
