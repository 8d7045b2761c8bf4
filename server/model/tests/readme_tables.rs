//! The README's scene-file table and built-in scene list name everything a scene file may
//! choose (issue 49): every built-in scene, `[mesh] builtin`, material model, model family,
//! integrator and probe contact the code accepts appears in backticks in its row, so a name
//! added to the code without the README fails here. The lists come from the code
//! (`builtin_scene_names`, `BUILTIN_MESHES`, the enums' `ALL`), and the mesh list is checked
//! against the parser's own error for an unknown builtin.

use std::path::Path;

use haptic_model::contact::ContactModel;
use haptic_model::integrate::IntegratorKind;
use haptic_model::material::MaterialModel;
use haptic_model::scene::{BUILTIN_MESHES, ModelFamily, builtin_scene_names, parse_scene_toml};

fn readme() -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../README.md");
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The one line of the README's scene table whose first cell is `` `[section]` ``.
fn row<'a>(readme: &'a str, section: &str) -> &'a str {
    let start = format!("| `[{section}]` |");
    let rows: Vec<&str> = readme.lines().filter(|l| l.starts_with(&start)).collect();
    assert_eq!(rows.len(), 1, "README: one table row for [{section}]");
    rows[0]
}

/// The paragraph (lines up to a blank one) that starts with `start`.
fn paragraph(readme: &str, start: &str) -> String {
    let from = readme
        .find(start)
        .unwrap_or_else(|| panic!("README: no paragraph starting {start:?}"));
    let text = &readme[from..];
    text[..text.find("\n\n").unwrap_or(text.len())].to_string()
}

fn assert_named(text: &str, what: &str, names: impl IntoIterator<Item = &'static str>) {
    let missing: Vec<&str> = names
        .into_iter()
        .filter(|n| !text.contains(&format!("`{n}`")))
        .collect();
    assert!(
        missing.is_empty(),
        "README {what} misses {missing:?}: {text}"
    );
}

#[test]
fn the_scene_table_names_every_choice_the_code_accepts() {
    let r = readme();
    let rows: [(&str, Vec<&'static str>); 5] = [
        ("mesh", BUILTIN_MESHES.to_vec()),
        (
            "material",
            MaterialModel::ALL.map(MaterialModel::scene_name).to_vec(),
        ),
        ("model", ModelFamily::ALL.iter().map(|f| f.name()).collect()),
        (
            "integrator",
            IntegratorKind::ALL.map(IntegratorKind::name).to_vec(),
        ),
        ("probe", ContactModel::ALL.map(ContactModel::name).to_vec()),
    ];
    for (section, names) in rows {
        assert_named(row(&r, section), section, names);
    }
    // The families with their own section have their row.
    row(&r, "hybrid");
    row(&r, "mass_spring");
    assert_named(
        &paragraph(&r, "Built-in scenes, started by name"),
        "built-in scene list",
        builtin_scene_names().iter().map(|(name, _)| *name),
    );
}

/// `BUILTIN_MESHES` is the parser's list: its error for an unknown builtin names exactly these.
#[test]
fn builtin_meshes_is_the_parsers_list() {
    let text = "[mesh]\nbuiltin = \"no-such-mesh\"\n[material]\nyoungs_modulus_pa = 1e4\n\
                poisson_ratio = 0.3\ndensity_kg_per_m3 = 1000.0\n";
    let e = parse_scene_toml(text, Path::new("."))
        .expect_err("an unknown builtin is refused")
        .to_string();
    let listed = e
        .split_once("(expected ")
        .and_then(|(_, rest)| rest.split_once(')'))
        .unwrap_or_else(|| panic!("no list of names in {e:?}"))
        .0
        .replace(" or ", ", ");
    let mut from_error: Vec<&str> = listed.split(", ").collect();
    let mut constant = BUILTIN_MESHES.to_vec();
    from_error.sort_unstable();
    constant.sort_unstable();
    assert_eq!(from_error, constant, "{e}");
}
