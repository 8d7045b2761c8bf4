//! `haptic-cli`: what every client-side binary of the workspace shares, beside the wire
//! contract (`haptics-proto`):
//!
//! - [`credentials`]: the client side of access control (bearer token, TLS files, their flags
//!   and environment variables);
//! - [`connect`]: opening an authenticated channel to `hapticd` ([`connect::connect`]);
//! - [`vec3`]: the command-line form `X,Y,Z` of a vector ([`vec3::parse_vec3`]);
//! - [`recording`]: MCAP recordings of `haptics.v1` messages;
//! - [`vtu`]: the one VTK XML unstructured-grid writer (`.vtu`, ParaView) and its `.pvd`
//!   time series.
//!
//! Neighbours: `hapticctl`, `haptic-viewer` (`haptic-client`), `haptic-bridge`, the end-to-end
//! tests and `haptic-solve` (`haptic-server`) use it; it depends on `haptics-proto` only.

#![forbid(unsafe_code)]

pub mod connect;
pub mod credentials;
pub mod recording;
pub mod vec3;
pub mod vtu;
