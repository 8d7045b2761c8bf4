//! Scene TOML errors in the scene's own terms (issue 47): a value of the wrong type, an
//! unknown key or an unknown variant names its dotted field, like every other scene error
//! (`scene field `material.poisson_ratio`: expected a number (line 7)`), and says what was
//! expected, never what was found; text that is not TOML at all gives the line and column and
//! what the TOML grammar expected there, without the quoted source line.
//!
//! Neighbours: `raw` deserializes the scene through [`deserialize`]; [`ModelError::SceneField`]
//! and [`ModelError::SceneSyntax`] are the results.

use serde::de::DeserializeOwned;
use serde_path_to_error::Segment;

use crate::ModelError;

/// Deserializes scene text into `T`, with errors as described in the module docs.
///
/// # Errors
/// [`ModelError::SceneSyntax`] for text that is not TOML; [`ModelError::SceneField`] naming
/// the field for a wrong type, an unknown key, an unknown variant or a missing field.
pub(super) fn deserialize<T: DeserializeOwned>(text: &str) -> Result<T, ModelError> {
    let de = toml::Deserializer::parse(text).map_err(|e| syntax(text, &e))?;
    serde_path_to_error::deserialize(de).map_err(|e| {
        let mut field = e.path().iter().fold(String::new(), |mut out, segment| {
            match segment {
                Segment::Map { key } => {
                    if !out.is_empty() {
                        out.push('.');
                    }
                    out.push_str(key);
                }
                Segment::Seq { index } => out.push_str(&format!("[{index}]")),
                Segment::Enum { .. } | Segment::Unknown => {}
            }
            out
        });
        let inner = e.into_inner();
        let (named, message) = reword(inner.message());
        // An unknown key is already the path's last segment; a missing one is not.
        if let Some(key) = named.filter(|k| field != *k && !field.ends_with(&format!(".{k}"))) {
            if !field.is_empty() {
                field.push('.');
            }
            field.push_str(&key);
        }
        let at = inner
            .span()
            .map(|s| format!(" (line {})", line_of(text, s.start)))
            .unwrap_or_default();
        if field.is_empty() {
            ModelError::SceneSyntax(format!("{message}{at}"))
        } else {
            ModelError::field(field, format!("{message}{at}"))
        }
    })
}

/// A TOML grammar error: its line and column and what was expected, without the source line.
fn syntax(text: &str, e: &toml::de::Error) -> ModelError {
    ModelError::SceneSyntax(describe_toml_error(text, e))
}

/// Any TOML error of `text` (a scene, the daemon's configuration, a tokens file) as `line N,
/// column M: what was expected`, naming keys but never quoting a value or the source line:
/// serde's `invalid type: string "x", expected f64` becomes `expected a number`.
pub fn describe_toml_error(text: &str, e: &toml::de::Error) -> String {
    let at = e.span().map_or(String::new(), |s| {
        let start = s.start.min(text.len());
        let line = line_of(text, start);
        let line_start = text.as_bytes()[..start]
            .iter()
            .rposition(|&b| b == b'\n')
            .map_or(0, |i| i + 1);
        let column = String::from_utf8_lossy(&text.as_bytes()[line_start..start])
            .chars()
            .count()
            + 1;
        format!("line {line}, column {column}: ")
    });
    let (key, message) = reword(e.message());
    match key {
        Some(k) => format!("{at}`{k}`: {message}"),
        None => format!("{at}{message}"),
    }
}

/// 1-based line of byte `offset` in `text`.
fn line_of(text: &str, offset: usize) -> usize {
    text.as_bytes()[..offset.min(text.len())]
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
        + 1
}

/// The key a message names (an unknown or missing field) and the message reworded to say what
/// was expected: serde's `invalid type: string "x", expected f64` becomes `expected a number`.
fn reword(message: &str) -> (Option<String>, String) {
    let quoted = |m: &str| -> Option<String> {
        let start = m.find('`')? + 1;
        let len = m[start..].find('`')?;
        Some(m[start..start + len].to_string())
    };
    let expected_part = |m: &str| -> String {
        m.split_once(", expected ")
            .map_or_else(String::new, |(_, e)| expected(e.trim()))
    };
    let m = message.trim();
    if m.starts_with("invalid type:") || m.starts_with("invalid value:") {
        let wanted = expected_part(m);
        return (
            None,
            if wanted.is_empty() {
                "has the wrong type".into()
            } else {
                format!("expected {wanted}")
            },
        );
    }
    if m.starts_with("invalid length") {
        return (None, format!("expected {}", expected_part(m)));
    }
    if let Some(rest) = m.strip_prefix("unknown field") {
        let wanted = rest
            .split_once(", expected ")
            .map_or("no other key here".to_string(), |(_, e)| {
                e.trim().to_string()
            });
        return (quoted(rest), format!("unknown key; expected {wanted}"));
    }
    if let Some(rest) = m.strip_prefix("unknown variant") {
        let wanted = rest
            .split_once(", expected ")
            .map_or(String::new(), |(_, e)| e.trim().to_string());
        return (None, format!("unknown value; expected {wanted}"));
    }
    if let Some(rest) = m.strip_prefix("missing field") {
        return (quoted(rest), "is required".into());
    }
    (None, m.to_string())
}

/// Serde's name of an expected type in words.
fn expected(serde_name: &str) -> String {
    match serde_name {
        "f64" | "f32" => "a number".into(),
        "u8" | "u16" | "u32" | "u64" | "u128" | "usize" => "a whole number of 0 or more".into(),
        "i8" | "i16" | "i32" | "i64" | "i128" | "isize" => "a whole number".into(),
        "a sequence" => "an array".into(),
        "a map" => "a table".into(),
        s if s.starts_with("struct ") => "a table".into(),
        s if s.starts_with("an array of length") => s.into(),
        s => s.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Doc {
        a: Option<Inner>,
        list: Option<Vec<Inner>>,
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Inner {
        x: Option<f64>,
        n: Option<u32>,
        v: Option<[f64; 3]>,
    }

    fn err(text: &str) -> ModelError {
        deserialize::<Doc>(text).unwrap_err()
    }

    #[test]
    fn wrong_types_unknown_keys_and_syntax_name_the_field_and_line_not_the_value() {
        for (text, field, message) in [
            ("[a]\nx = \"s3cret\"\n", "a.x", "expected a number (line 2)"),
            (
                "[a]\nn = -4\n",
                "a.n",
                "expected a whole number of 0 or more (line 2)",
            ),
            (
                "[a]\nv = [1.0, 2.0]\n",
                "a.v",
                "expected an array of length 3",
            ),
            (
                "[[list]]\nx = 1.0\n[[list]]\nx = true\n",
                "list[1].x",
                "expected a number (line 4)",
            ),
            (
                "[a]\ns3cret = 1\n",
                "a.s3cret",
                "unknown key; expected one of `x`, `n`, `v`",
            ),
            ("a = 3\n", "a", "expected a table"),
        ] {
            match err(text) {
                ModelError::SceneField {
                    field: f,
                    message: m,
                } => {
                    assert_eq!(f, field, "{text}");
                    assert!(m.contains(message), "{text}: {m}");
                    if !field.contains("s3cret") {
                        assert!(!m.contains("s3cret") && !m.contains("-4"), "{m}");
                    }
                }
                other => panic!("{text}: {other:?}"),
            }
        }
        match err("[a]\nx = 1.0\ny = = s3cret\n") {
            ModelError::SceneSyntax(m) => {
                assert!(m.starts_with("line 3, column"), "{m}");
                assert!(!m.contains("s3cret"), "{m}");
            }
            other => panic!("{other:?}"),
        }
    }
}
