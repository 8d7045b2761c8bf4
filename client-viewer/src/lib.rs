//! `haptic-client`: the viewer library and scripted client of the haptic server.
//!
//! Three concepts, each in its own module, glued by two thin binaries:
//!
//! - [`raster`]: a small deterministic software rasterizer (z-buffer, Lambert shading) that turns
//!   a deformed surface, the probe and its contact force into an RGB picture and a PNG file,
//!   without a GPU or a display.
//! - [`viewer`]: subscribes to `SurfaceStream.Watch`, keeps the keyframe topology, applies the
//!   position frames, measures rate and frame age, and writes pictures with [`raster`]
//!   (binary `haptic-viewer`).
//! - [`compact`]: the client side of compact streams (quantized deltas against a reference
//!   keyframe), turning each frame into its full form.
//! - [`ctl`]: calls `SessionControl` (scenes, start, stop, sessions, force, stats) and formats
//!   the answers as tables or JSON (binary `hapticctl`).
//! - [`web`]: the browser viewer (`haptic-viewer --web ADDR`), a relay that subscribes once
//!   per session and fans the compact stream out to browsers over WebSocket, with the page
//!   and three.js compiled into the binary; [`web::overview`], its session overview page over one or
//!   more daemons (`--stations FILE`).
//!
//! Neighbours: the wire contract is `haptics_proto::v1`; the server (`haptic-server`) implements
//! it; credentials, connecting, `X,Y,Z` vectors and MCAP recordings are `haptic_cli`'s. This crate never depends on the physics model: everything it knows about a session comes
//! over gRPC.

#![forbid(unsafe_code)]

pub mod compact;
pub mod ctl;
pub mod error;
pub mod raster;
pub mod record;
pub mod viewer;
pub mod web;

pub use error::ClientError;
