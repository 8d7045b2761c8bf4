//! The `haptics.v1` wire contract (DESIGN.md section 4): messages, service traits (server side)
//! and clients, generated from `proto/haptics/v1/haptics.proto` by protox + tonic-prost-build.
//!
//! All quantities are SI and say so in their field names (`_m`, `_n`, `_s`, `_us`).
//!
//! [`codec`] is the gRPC codec of every service (an undecodable message is `INVALID_ARGUMENT`).
//! [`delta`] is the compact position encoding of `SURFACE_ENCODING_DELTA` streams, shared by
//! the server that encodes and the clients that decode.
//!
//! Neighbours: `haptic-server` implements the services; `haptic-bridge`, `haptic-client` and the
//! end-to-end tests call them, with the client-side helpers of `haptic-cli` (credentials,
//! connecting, `X,Y,Z` vectors, MCAP recordings).

#![forbid(unsafe_code)]

pub mod codec;
pub mod delta;

/// Package `haptics.v1`.
pub mod v1 {
    #![allow(missing_docs, clippy::all)]
    tonic::include_proto!("haptics.v1");
}

/// Encoded `FileDescriptorSet` of the contract, for gRPC server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/haptics_v1_descriptor.bin"));

impl v1::Vec3 {
    /// Builds a vector from components (SI units as the field using it says).
    pub fn new(x: f64, y: f64, z: f64) -> Self {
        Self { x, y, z }
    }

    /// Components as an array `[x, y, z]`.
    pub fn to_array(&self) -> [f64; 3] {
        [self.x, self.y, self.z]
    }

    /// True when every component is finite (no NaN or infinity).
    pub fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.z.is_finite()
    }
}

impl From<[f64; 3]> for v1::Vec3 {
    fn from(a: [f64; 3]) -> Self {
        Self::new(a[0], a[1], a[2])
    }
}
