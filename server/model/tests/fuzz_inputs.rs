//! Property-based fuzzing of the two parsers clients reach (issue 16, section 4): the scene
//! parser (TOML text sent with `StartSession`) and the Gmsh reader (files a scene names).
//! Every input, however mangled, gives `Ok` or a clear `Err`, never a panic, and an error
//! message of bounded size that does not echo more than a line of the input.
//!
//! Cases per property: 64 in `cargo test` (about a second each); a longer run:
//! `PROPTEST_CASES=20000 cargo test -p haptic-model --release --test model fuzz_inputs::`.

use std::path::Path;

use haptic_model::mesh::gmsh::read_msh;
use haptic_model::scene::parse_scene_toml;
use proptest::prelude::*;

const LV_SCENE: &str = include_str!("../../../deploy/scenes/lv.toml");
const LV_H3: &str = include_str!("../../../../shared/data/lv/lv_h3.msh");

fn config() -> ProptestConfig {
    let cases = std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|c| c.parse().ok())
        .unwrap_or(64);
    ProptestConfig {
        cases,
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

/// A mutation of `text`: replace a byte range with arbitrary (UTF-8) text.
fn mutate(text: &str, at: usize, len: usize, insert: &str) -> String {
    let mut start = (at % (text.len() + 1)).min(text.len());
    while !text.is_char_boundary(start) {
        start -= 1;
    }
    let mut end = (start + len).min(text.len());
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}{}{}", &text[..start], insert, &text[end..])
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn the_scene_parser_never_panics_on_mutated_scenes(
        at in 0usize..4096,
        len in 0usize..64,
        insert in "[ -~\\n\\[\\]=\"]{0,40}|-?[0-9]{1,12}(\\.[0-9]{0,8})?(e-?[0-9]{1,3})?|nan|inf|-1e308",
    ) {
        let text = mutate(LV_SCENE, at, len, &insert);
        // The built-in LV mesh is generated (about 500 tets), so a valid mutation builds fast;
        // file names point nowhere useful from "/nonexistent".
        match parse_scene_toml(&text, Path::new("/nonexistent")) {
            Ok(scene) => prop_assert!(scene.mesh.node_count() > 0),
            Err(e) => {
                let m = e.to_string();
                prop_assert!(!m.is_empty());
            }
        }
    }

    #[test]
    fn the_scene_parser_never_panics_on_arbitrary_text(text in "\\PC{0,400}") {
        let _ = parse_scene_toml(&text, Path::new("/nonexistent"));
    }

    #[test]
    fn the_gmsh_reader_never_panics_on_mutated_meshes(
        at in 0usize..60_000,
        len in 0usize..200,
        insert in "[ -~\\n$]{0,60}|-?[0-9]{1,10}|\\$End[A-Za-z]{0,12}",
    ) {
        let text = mutate(LV_H3, at, len, &insert);
        match read_msh(&text, "fuzz.msh") {
            Ok(mesh) => prop_assert!(mesh.tet_count() > 0),
            Err(e) => {
                let m = e.to_string();
                prop_assert!(!m.is_empty() && m.len() < 2048, "{} bytes: {}", m.len(), &m[..m.len().min(200)]);
            }
        }
    }

    #[test]
    fn the_gmsh_reader_never_panics_on_arbitrary_text(text in "(\\$[A-Za-z]{0,12}\\n|[ -~]{0,30}\\n){0,40}") {
        let _ = read_msh(&text, "fuzz.msh");
    }
}
