//! Reading the workspace's Rust sources as text, for the house tests
//! (`tests/tests/house_rules.rs`; `server/model/tests/module_layers.rs` includes this file by
//! path): the code without comments and string contents, the files of a folder, and the
//! imports between a crate's top-level modules.
//!
//! A scan, not a parser: it knows Rust's comments (line, block, nested block), string literals
//! (plain, byte, raw with any number of `#`), character literals and lifetimes, which is what
//! it takes to find keywords and `crate::` paths in code only.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// `text` with every comment removed and every string or character literal's contents
/// removed (the quotes stay, so `"unsafe"` becomes `""`); line breaks are kept, so line
/// numbers still match.
pub fn strip_comments_and_strings(text: &str) -> String {
    let chars: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        let next = chars.get(i + 1).copied();
        if c == '/' && next == Some('/') {
            while i < chars.len() && chars[i] != '\n' {
                i += 1;
            }
        } else if c == '/' && next == Some('*') {
            i = skip_block_comment(&chars, i, &mut out);
        } else if c == 'r' && is_raw_string_start(&chars, i) {
            i = skip_raw_string(&chars, i, &mut out);
        } else if c == '"' {
            i = skip_string(&chars, i, &mut out);
        } else if c == '\'' {
            i = skip_char_or_lifetime(&chars, i, &mut out);
        } else {
            out.push(c);
            i += 1;
        }
    }
    out
}

/// Skips a (possibly nested) block comment starting at `i`; keeps its line breaks.
fn skip_block_comment(chars: &[char], mut i: usize, out: &mut String) -> usize {
    let mut depth = 0;
    while i < chars.len() {
        if chars[i] == '/' && chars.get(i + 1) == Some(&'*') {
            depth += 1;
            i += 2;
        } else if chars[i] == '*' && chars.get(i + 1) == Some(&'/') {
            depth -= 1;
            i += 2;
            if depth == 0 {
                return i;
            }
        } else {
            if chars[i] == '\n' {
                out.push('\n');
            }
            i += 1;
        }
    }
    i
}

/// `r"`, `r#"`, `br"`... at `i`, not the end of an identifier such as `for"`.
fn is_raw_string_start(chars: &[char], i: usize) -> bool {
    let before = if i > 0 { Some(chars[i - 1]) } else { None };
    let ident_before = before.is_some_and(|c| c.is_alphanumeric() || c == '_');
    let byte_prefix = before == Some('b') && (i < 2 || !is_ident_char(chars[i - 2]));
    if ident_before && !byte_prefix {
        return false;
    }
    let mut j = i + 1;
    while chars.get(j) == Some(&'#') {
        j += 1;
    }
    chars.get(j) == Some(&'"')
}

fn is_ident_char(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// Skips a raw string `r#"..."#` starting at `i` (the `r`); writes `""` and its line breaks.
fn skip_raw_string(chars: &[char], i: usize, out: &mut String) -> usize {
    let mut j = i + 1;
    let mut hashes = 0;
    while chars[j] == '#' {
        hashes += 1;
        j += 1;
    }
    j += 1; // the opening quote
    out.push_str("\"\"");
    while j < chars.len() {
        if chars[j] == '"' && (1..=hashes).all(|k| chars.get(j + k) == Some(&'#')) {
            return j + 1 + hashes;
        }
        if chars[j] == '\n' {
            out.push('\n');
        }
        j += 1;
    }
    j
}

/// Skips a string literal starting at the quote `i` (escapes included); writes `""`.
fn skip_string(chars: &[char], i: usize, out: &mut String) -> usize {
    let mut j = i + 1;
    out.push_str("\"\"");
    while j < chars.len() {
        match chars[j] {
            '\\' => {
                // A line continuation's break is a line of the file too.
                if chars.get(j + 1) == Some(&'\n') {
                    out.push('\n');
                }
                j += 2;
            }
            '"' => return j + 1,
            '\n' => {
                out.push('\n');
                j += 1;
            }
            _ => j += 1,
        }
    }
    j
}

/// A character literal (`'a'`, `'\n'`, `'\u{1F600}'`) becomes `''`; a lifetime or label
/// (`'a`, `'static`) is kept.
fn skip_char_or_lifetime(chars: &[char], i: usize, out: &mut String) -> usize {
    if chars.get(i + 1) == Some(&'\\') {
        let mut j = i + 3; // past the backslash and the escaped character
        while j < chars.len() && chars[j] != '\'' {
            j += 1;
        }
        out.push_str("''");
        return j + 1;
    }
    if chars.get(i + 2) == Some(&'\'') {
        out.push_str("''");
        return i + 3;
    }
    out.push('\'');
    i + 1
}

/// Every `.rs` file below `dir` (recursively, sorted). A missing folder gives none.
pub fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    collect(dir, &mut out);
    out.sort();
    out
}

fn collect(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            collect(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The code of a file up to its first `#[cfg(test)]` (a test module's imports are not the
/// crate's structure), comments and strings stripped.
pub fn code_outside_tests(text: &str) -> String {
    let code = strip_comments_and_strings(text);
    match code.find("#[cfg(test)]") {
        Some(i) => code[..i].to_string(),
        None => code,
    }
}

/// `(from, to)` for every `crate::to` path in the library of the crate whose sources are in
/// `src`: `from` and `to` are top-level modules (`src/from.rs` or `src/from/...`). The crate
/// root (`lib.rs`, `main.rs`) and the binaries in `src/bin/` are not modules of the library
/// and are skipped; grouped imports (`crate::{a, b::c}`) give one edge per group member.
pub fn crate_edges(src: &Path) -> BTreeSet<(String, String)> {
    let mut edges = BTreeSet::new();
    for file in rust_files(src) {
        let rel = file.strip_prefix(src).expect("under src");
        let first = rel.components().next().expect("component");
        let module = first
            .as_os_str()
            .to_string_lossy()
            .trim_end_matches(".rs")
            .to_string();
        if matches!(module.as_str(), "lib" | "main" | "bin") {
            continue;
        }
        let text = std::fs::read_to_string(&file).expect("read a source file");
        for target in crate_paths(&code_outside_tests(&text)) {
            if target != module {
                edges.insert((module.clone(), target));
            }
        }
    }
    edges
}

/// The first segment after every `crate::` in `code` (lower-case names only: modules).
fn crate_paths(code: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (i, _) in code.match_indices("crate::") {
        if code[..i].chars().last().is_some_and(is_ident_char) {
            continue; // `haptic_model_crate::` or the like
        }
        let after = &code[i + "crate::".len()..];
        if let Some(group) = after.strip_prefix('{') {
            let mut depth = 0;
            let mut item = String::new();
            for c in group.chars() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => break,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        out.extend(leading_module(&item));
                        item.clear();
                        continue;
                    }
                    _ => {}
                }
                item.push(c);
            }
            out.extend(leading_module(&item));
        } else {
            out.extend(leading_module(after));
        }
    }
    out
}

/// The identifier `text` starts with (after whitespace), if it names a module (lower case).
fn leading_module(text: &str) -> Option<String> {
    let name: String = text
        .trim_start()
        .chars()
        .take_while(|c| is_ident_char(*c))
        .collect();
    (!name.is_empty() && name.chars().next().is_some_and(|c| c.is_lowercase())).then_some(name)
}

/// Whether the stripped `code` uses the `unsafe` keyword: an `unsafe` block, function,
/// impl, trait, extern block or attribute (`unsafe(no_mangle)`), not a name that contains it
/// (`unsafe_code`).
pub fn uses_unsafe(code: &str) -> bool {
    code.match_indices("unsafe").any(|(i, _)| {
        let before_ok = !code[..i].chars().last().is_some_and(is_ident_char);
        let rest = &code[i + "unsafe".len()..];
        let after_ok = !rest.chars().next().is_some_and(is_ident_char);
        let rest = rest.trim_start();
        let keyword_follows = ["fn", "impl", "extern", "trait"].iter().any(|k| {
            rest.strip_prefix(k)
                .is_some_and(|r| !r.chars().next().is_some_and(is_ident_char))
        });
        before_ok && after_ok && (rest.starts_with('{') || rest.starts_with('(') || keyword_follows)
    })
}

/// The code of a file before its first test module (`#[cfg(test)]` followed by `mod`),
/// comments and strings stripped. Unlike [`code_outside_tests`], a `#[cfg(test)]` on a field,
/// an import or a helper function does not end the code there.
pub fn code_before_test_module(text: &str) -> String {
    let code = strip_comments_and_strings(text);
    let end = code
        .match_indices("#[cfg(test)]")
        .find(|(i, m)| {
            let rest = code[i + m.len()..].trim_start();
            rest.starts_with("mod ")
                || rest.starts_with("pub mod ")
                || rest.starts_with("pub(crate) mod ")
        })
        .map_or(code.len(), |(i, _)| i);
    code[..end].to_string()
}

/// A function with a body in stripped code: its name, the line of its `fn` keyword (1-based)
/// and its length in lines, from that line to the line of its closing brace, both counted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FnSpan {
    /// The function's name.
    pub name: String,
    /// Line of the `fn` keyword, 1-based.
    pub line: usize,
    /// Lines from the `fn` keyword's line to the closing brace's, both included.
    pub lines: usize,
}

/// Every function with a body in the stripped `code` (nested ones too; a declaration ending
/// in `;` and a `fn(..)` pointer type are not functions). The body is the first `{` after the
/// name outside parentheses and brackets (so `-> [u8; 3]` is a return type, not the end),
/// matched to its closing brace.
pub fn function_spans(code: &str) -> Vec<FnSpan> {
    let bytes = code.as_bytes();
    let mut spans = Vec::new();
    for (at, _) in code.match_indices("fn") {
        let before_ok = at == 0 || !is_ident_char(bytes[at - 1] as char);
        let rest = &code[at + 2..];
        let after = rest.trim_start();
        if !before_ok || !rest.starts_with(char::is_whitespace) {
            continue;
        }
        let name: String = after.chars().take_while(|&c| is_ident_char(c)).collect();
        if name.is_empty() || name.starts_with(|c: char| c.is_ascii_digit()) {
            continue;
        }
        let Some(open) = body_start(code, at + 2) else {
            continue;
        };
        let Some(close) = matching_brace(code, open) else {
            continue;
        };
        let line = code[..at].matches('\n').count() + 1;
        let lines = code[at..=close].matches('\n').count() + 1;
        spans.push(FnSpan { name, line, lines });
    }
    spans
}

/// The byte index of the `{` that opens the body of the function whose signature starts at
/// `from`, or `None` for a declaration (`;` first).
fn body_start(code: &str, from: usize) -> Option<usize> {
    let mut depth = 0i32;
    for (i, c) in code[from..].char_indices() {
        match c {
            '(' | '[' => depth += 1,
            ')' | ']' => depth -= 1,
            '{' if depth == 0 => return Some(from + i),
            ';' if depth == 0 => return None,
            _ => {}
        }
    }
    None
}

/// The byte index of the `}` that closes the `{` at `open`.
fn matching_brace(code: &str, open: usize) -> Option<usize> {
    let mut depth = 0usize;
    for (i, c) in code[open..].char_indices() {
        match c {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    return Some(open + i);
                }
            }
            _ => {}
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strips_comments_and_string_contents_but_keeps_code_and_lifetimes() {
        let text = "let a = \"unsafe { // no\"; // unsafe {\nlet b: &'static str = r#\"a \"b\" /* c\"#;\n/* x /* nested */ unsafe { */ let c = '\"'; let d = '\\'';\nfn f<'a>(x: &'a u8) {}\n";
        let code = strip_comments_and_strings(text);
        assert_eq!(
            code,
            "let a = \"\"; \nlet b: &'static str = \"\";\n let c = ''; let d = '';\nfn f<'a>(x: &'a u8) {}\n"
        );
        assert!(!uses_unsafe(&code));
    }

    #[test]
    fn finds_every_form_of_the_keyword_and_no_name_containing_it() {
        for code in [
            "unsafe { f() }",
            "pub unsafe fn f() {}",
            "unsafe impl Send for X {}",
            "unsafe extern \"C\" {}",
            "unsafe trait T {}",
            "#[unsafe(no_mangle)]",
        ] {
            assert!(uses_unsafe(code), "{code}");
        }
        for code in [
            "#![deny(unsafe_code)]",
            "fn not_unsafe() {}",
            "let unsafety = 1;",
        ] {
            assert!(!uses_unsafe(code), "{code}");
        }
    }

    #[test]
    fn measures_functions_from_their_keyword_to_their_closing_brace() {
        let text = "pub fn a(x: [u8; 3]) -> [u8; 3] {\n    let s = \"}{ a \\\n  b\";\n    x\n}\nfn b();\ntype P = fn(u8) -> u8;\nimpl T {\n    fn c<'a>(&'a self) where Self: Sized {\n        fn d() {}\n    }\n}\n#[cfg(test)]\nstruct Only;\nfn e() {}\n#[cfg(test)]\nmod tests {\n    fn f() {}\n}\n";
        let code = code_before_test_module(text);
        let spans: Vec<(String, usize, usize)> = function_spans(&code)
            .into_iter()
            .map(|s| (s.name, s.line, s.lines))
            .collect();
        assert_eq!(
            spans,
            [
                ("a".to_string(), 1, 5),
                ("c".to_string(), 9, 3),
                ("d".to_string(), 10, 1),
                ("e".to_string(), 15, 1),
            ]
        );
    }

    #[test]
    fn reads_plain_and_grouped_crate_paths() {
        let code = "use crate::a::X;\nuse crate::{b, c::{D, E}, Upper};\nlet y = crate::d::f();\nmy_crate::e::g();";
        assert_eq!(crate_paths(code), ["a", "b", "c", "d"]);
    }
}
