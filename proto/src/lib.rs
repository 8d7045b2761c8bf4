//! The `haptics.v1` wire contract (DESIGN.md section 4): messages, service traits (server side)
//! and clients, generated from `proto/haptics/v1/haptics.proto` by protox + tonic-prost-build.
//!
//! All quantities are SI and say so in their field names (`_m`, `_n`, `_s`, `_us`).
//! The crate also owns the command-line form of a [`v1::Vec3`], `X,Y,Z` ([`parse_vec3`], or
//! `str::parse::<v1::Vec3>`), so every binary refuses malformed vectors the same way.
//!
//! [`client`] is the client side of access control: the token every call carries and TLS.
//!
//! [`delta`] is the compact position encoding of `SURFACE_ENCODING_DELTA` streams, shared by
//! the server that encodes and the clients that decode.
//!
//! Neighbours: `haptic-server` implements the services; `haptic-bridge`, `haptic-client` and the
//! end-to-end tests call them.

pub mod client;
pub mod codec;
pub mod delta;
pub mod recording;

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

/// Why a command-line vector `X,Y,Z` was refused by [`parse_vec3`]. The message names the
/// component and the offending text, not the whole input (callers add it: clap says which
/// flag and value, `haptic-client` wraps it with the input).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParseVec3Error {
    /// Not exactly three comma-separated components.
    #[error("expected X,Y,Z (3 comma-separated numbers), got {found} component(s)")]
    WrongCount {
        /// How many components the text had.
        found: usize,
    },
    /// A component is empty or only whitespace.
    #[error("{axis} is empty")]
    Empty {
        /// `X`, `Y` or `Z`.
        axis: char,
    },
    /// A component is not a decimal number.
    #[error("{axis} ({text:?}) is not a number")]
    NotANumber {
        /// `X`, `Y` or `Z`.
        axis: char,
        /// The component as given (trimmed).
        text: String,
    },
    /// A component is NaN or infinite (including overflow such as `1e999`).
    #[error("{axis} ({text:?}) is not finite")]
    NotFinite {
        /// `X`, `Y` or `Z`.
        axis: char,
        /// The component as given (trimmed).
        text: String,
    },
}

/// Parses `X,Y,Z` (the command-line form of a vector; SI units as the flag using it says)
/// into three finite numbers. Whitespace around a component is allowed; anything else
/// (missing or extra components, empty ones, words, NaN, infinity, overflow) is refused.
///
/// The one parser behind every `X,Y,Z` flag of the workspace's binaries; also available as
/// `"1,2,3".parse::<v1::Vec3>()`.
///
/// # Errors
/// [`ParseVec3Error`] naming the first bad component and why.
pub fn parse_vec3(input: &str) -> Result<[f64; 3], ParseVec3Error> {
    let parts: Vec<&str> = input.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(ParseVec3Error::WrongCount { found: parts.len() });
    }
    let mut v = [0.0; 3];
    for ((axis, part), out) in ['X', 'Y', 'Z'].into_iter().zip(parts).zip(&mut v) {
        if part.is_empty() {
            return Err(ParseVec3Error::Empty { axis });
        }
        let text = || part.to_string();
        let x: f64 = part
            .parse()
            .map_err(|_| ParseVec3Error::NotANumber { axis, text: text() })?;
        if !x.is_finite() {
            return Err(ParseVec3Error::NotFinite { axis, text: text() });
        }
        *out = x;
    }
    Ok(v)
}

impl std::str::FromStr for v1::Vec3 {
    type Err = ParseVec3Error;

    /// As [`parse_vec3`].
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        parse_vec3(s).map(Self::from)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vectors_parse_with_whitespace_signs_and_exponents() {
        assert_eq!(parse_vec3("1,-2.5, 3e-3").unwrap(), [1.0, -2.5, 0.003]);
        assert_eq!(parse_vec3(" 0 ,+1,\t-0 ").unwrap(), [0.0, 1.0, -0.0]);
        let v: v1::Vec3 = "0.014,0,-0.005".parse().unwrap();
        assert_eq!(v, v1::Vec3::new(0.014, 0.0, -0.005));
    }

    #[test]
    fn wrong_counts_are_refused_with_the_count() {
        for (bad, found) in [
            ("", 1),
            ("1,2", 2),
            ("1,2,3,4", 4),
            ("1;2;3", 1),
            ("1,2,3,", 4),
        ] {
            assert_eq!(
                parse_vec3(bad),
                Err(ParseVec3Error::WrongCount { found }),
                "{bad:?}"
            );
        }
        let e = parse_vec3("1,0").unwrap_err().to_string();
        assert!(e.contains("expected X,Y,Z") && e.contains("got 2"), "{e}");
    }

    #[test]
    fn each_bad_component_is_named() {
        assert_eq!(parse_vec3("1,,3"), Err(ParseVec3Error::Empty { axis: 'Y' }));
        assert_eq!(
            parse_vec3(" , , "),
            Err(ParseVec3Error::Empty { axis: 'X' })
        );
        assert_eq!(
            parse_vec3("a,2,3"),
            Err(ParseVec3Error::NotANumber {
                axis: 'X',
                text: "a".into()
            })
        );
        let e = parse_vec3("1,x,3").unwrap_err().to_string();
        assert_eq!(e, "Y (\"x\") is not a number");
        for (bad, axis, text) in [
            ("1,2,NaN", 'Z', "NaN"),
            ("1,nan,0", 'Y', "nan"),
            ("inf,0,0", 'X', "inf"),
            ("0,0,-infinity", 'Z', "-infinity"),
            ("0,0,1e999", 'Z', "1e999"),
        ] {
            assert_eq!(
                parse_vec3(bad),
                Err(ParseVec3Error::NotFinite {
                    axis,
                    text: text.into()
                }),
                "{bad:?}"
            );
        }
        assert!("1,2".parse::<v1::Vec3>().is_err());
    }
}
