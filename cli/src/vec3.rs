//! The command-line form of a vector, `X,Y,Z` ([`parse_vec3`]), so every binary refuses
//! malformed vectors the same way.
//!
//! Neighbours: the flags of `haptic-bridge`, `haptic-solve` and `hapticctl force`; the result
//! converts to a wire [`haptics_proto::v1::Vec3`] with `From<[f64; 3]>`.

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
/// The one parser behind every `X,Y,Z` flag of the workspace's binaries.
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vectors_parse_with_whitespace_signs_and_exponents() {
        assert_eq!(parse_vec3("1,-2.5, 3e-3").unwrap(), [1.0, -2.5, 0.003]);
        assert_eq!(parse_vec3(" 0 ,+1,\t-0 ").unwrap(), [0.0, 1.0, -0.0]);
        let v = haptics_proto::v1::Vec3::from(parse_vec3("0.014,0,-0.005").unwrap());
        assert_eq!(v, haptics_proto::v1::Vec3::new(0.014, 0.0, -0.005));
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
        assert!(parse_vec3("1,2").is_err());
    }
}
