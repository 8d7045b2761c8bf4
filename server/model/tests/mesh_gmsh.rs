//! Gmsh reader: the idealized left-ventricle meshes in `shared/data/lv` and malformed inputs.

use std::collections::BTreeSet;
use std::path::PathBuf;

use haptic_model::ModelError;
use haptic_model::mesh::TetMesh;
use haptic_model::mesh::gmsh::{load_msh, read_msh};

fn lv_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/lv")
}

fn load(name: &str) -> TetMesh {
    load_msh(&lv_dir().join(name)).unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// (file, nodes, tets, volume mm^3) from the README table.
const TABLE: [(&str, usize, usize, f64); 4] = [
    ("lv_h3.msh", 363, 1047, 3204.2),
    ("lv_h3_v41.msh", 363, 1047, 3204.2),
    ("lv_h2.msh", 776, 2262, 3225.6),
    ("lv_h1.msh", 4398, 17924, 3232.5),
];

fn sorted(t: [u32; 3]) -> [u32; 3] {
    let mut k = t;
    k.sort_unstable();
    k
}

#[test]
fn every_lv_file_loads_with_readme_counts_and_volume() {
    let mut files: Vec<String> = std::fs::read_dir(lv_dir())
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| n.ends_with(".msh"))
        .collect();
    files.sort();
    assert_eq!(files.len(), TABLE.len(), "{files:?}");
    for (name, nodes, tets, vol) in TABLE {
        assert!(files.iter().any(|f| f == name), "{name} missing");
        let m = load(name);
        assert_eq!(m.node_count(), nodes, "{name} nodes");
        assert_eq!(m.tet_count(), tets, "{name} tets");
        assert!(
            (m.volume() - vol).abs() < 0.1,
            "{name} volume {} vs {vol}",
            m.volume()
        );
        for g in ["ENDO", "EPI", "BASE"] {
            assert!(!m.surface(g).unwrap().triangles.is_empty(), "{name}: {g}");
        }
        for g in ["ENDOPT", "EPIPT"] {
            assert_eq!(m.node_group(g).unwrap().nodes.len(), 1, "{name}: {g}");
        }
        let endopt = m.nodes[m.node_group("ENDOPT").unwrap().nodes[0] as usize];
        assert!((endopt.z + 17.0).abs() < 1e-9, "{name}: ENDOPT {endopt}");
        let epipt = m.nodes[m.node_group("EPIPT").unwrap().nodes[0] as usize];
        assert!((epipt.z + 20.0).abs() < 1e-9, "{name}: EPIPT {epipt}");
    }
}

#[test]
fn v22_and_v41_give_identical_meshes() {
    assert_eq!(load("lv_h3.msh"), load("lv_h3_v41.msh"));
}

#[test]
fn base_nodes_lie_on_z_5() {
    for (name, ..) in TABLE {
        let m = load(name);
        for t in &m.surface("BASE").unwrap().triangles {
            for &i in t {
                assert!((m.nodes[i as usize].z - 5.0).abs() < 1e-9, "{name}");
            }
        }
    }
}

#[test]
fn surface_normals_point_away_from_long_axis_on_epi_and_toward_it_on_endo() {
    for (name, ..) in TABLE {
        let m = load(name);
        let radial = |g: &str| -> f64 {
            let tris = &m.surface(g).unwrap().triangles;
            tris.iter()
                .map(|t| {
                    let [a, b, c] = t.map(|i| m.nodes[i as usize]);
                    let n = (b - a).cross(c - a).normalize();
                    let centre = (a + b + c) / 3.0;
                    let r = glam::DVec3::new(centre.x, centre.y, 0.0).normalize_or_zero();
                    n.dot(r)
                })
                .sum::<f64>()
                / tris.len() as f64
        };
        assert!(radial("EPI") > 0.5, "{name}: EPI {}", radial("EPI"));
        assert!(radial("ENDO") < -0.5, "{name}: ENDO {}", radial("ENDO"));
        // BASE faces +z.
        for t in &m.surface("BASE").unwrap().triangles {
            let [a, b, c] = t.map(|i| m.nodes[i as usize]);
            assert!((b - a).cross(c - a).z > 0.0, "{name}: BASE normal");
        }
    }
}

#[test]
fn named_surfaces_are_exactly_the_boundary() {
    for (name, ..) in TABLE {
        let m = load(name);
        let boundary: BTreeSet<[u32; 3]> = m.boundary_triangles().into_iter().collect();
        let named: BTreeSet<[u32; 3]> = ["ENDO", "EPI", "BASE"]
            .iter()
            .flat_map(|g| m.surface(g).unwrap().triangles.iter().copied())
            .collect();
        // Same oriented triangles (orient_surfaces_outward matched them to the boundary).
        assert_eq!(boundary, named, "{name}");
        let unsorted: BTreeSet<[u32; 3]> = boundary.iter().map(|&t| sorted(t)).collect();
        assert_eq!(unsorted.len(), boundary.len());
    }
}

#[test]
fn tets_are_positive_and_nodes_compact() {
    let m = load("lv_h2.msh");
    let mut used = vec![false; m.node_count()];
    for t in &m.tets {
        let [a, b, c, d] = t.map(|i| m.nodes[i as usize]);
        assert!(haptic_model::mesh::tet_signed_volume(a, b, c, d) > 0.0);
        for &i in t {
            used[i as usize] = true;
        }
    }
    assert!(used.iter().all(|&u| u));
}

// ----- malformed inputs -----

const TINY_22: &str = "$MeshFormat
2.2 0 8
$EndMeshFormat
$PhysicalNames
2
2 1 \"SKIN\"
3 2 \"BODY\"
$EndPhysicalNames
$Nodes
5
1 0 0 0
2 1 0 0
3 0 1 0
4 0 0 1
9 5 5 5
$EndNodes
$Elements
4
1 4 2 2 1 1 2 3 4
2 2 2 1 1 1 2 3
3 2 2 7 7 1 2 9
4 1 2 0 0 1 2
$EndElements
";

fn line_of(e: &ModelError) -> Option<usize> {
    match e {
        ModelError::MeshFormat { line, .. } => *line,
        _ => None,
    }
}

#[test]
fn tiny_mesh_parses_and_compacts() {
    let m = read_msh(TINY_22, "tiny").unwrap();
    assert_eq!(m.node_count(), 4, "node 9 is not used by a tet");
    assert_eq!(m.tet_count(), 1);
    assert_eq!(m.surface("SKIN").unwrap().triangles.len(), 1);
    // The triangle with the dropped node vanishes with its group.
    assert!(m.surface("surface_7").is_none());
    assert!((m.volume() - 1.0 / 6.0).abs() < 1e-15);
}

#[test]
fn truncated_file_names_a_line() {
    let cut: String = TINY_22.lines().take(18).collect::<Vec<_>>().join("\n");
    let e = read_msh(&cut, "cut").unwrap_err();
    assert!(line_of(&e).is_some(), "{e}");
    assert!(e.to_string().contains("line"), "{e}");
}

#[test]
fn bad_number_names_its_line() {
    let bad = TINY_22.replace("3 0 1 0", "3 0 1x 0");
    let e = read_msh(&bad, "bad").unwrap_err();
    assert_eq!(line_of(&e), Some(13), "{e}");
    // What was expected, never what was found (issue 47).
    assert!(
        e.to_string().contains("expected a number as field 3")
            && e.to_string().contains("line 13")
            && !e.to_string().contains("1x"),
        "{e}"
    );
}

#[test]
fn missing_elements_section_is_reported() {
    let cut: String = TINY_22.lines().take(16).collect::<Vec<_>>().join("\n");
    let e = read_msh(&cut, "noelems").unwrap_err();
    assert!(
        e.to_string().contains("$Elements") && line_of(&e).is_some(),
        "{e}"
    );
    let e = read_msh("$Nodes\n1\n1 0 0 0\n$EndNodes\n", "nofmt").unwrap_err();
    assert!(
        e.to_string().contains("$MeshFormat") && line_of(&e) == Some(1),
        "{e}"
    );
}

#[test]
fn binary_and_unsupported_versions_are_rejected() {
    let e = read_msh(&TINY_22.replace("2.2 0 8", "2.2 1 8"), "bin").unwrap_err();
    assert!(
        e.to_string().contains("binary") && line_of(&e) == Some(2),
        "{e}"
    );
    let e = read_msh(&TINY_22.replace("2.2 0 8", "4.0 0 8"), "v40").unwrap_err();
    assert!(
        e.to_string().contains("2.2 or 4.1")
            && !e.to_string().contains("4.0")
            && line_of(&e) == Some(2),
        "{e}"
    );
    // A real binary file: header then raw bytes that are not UTF-8.
    let dir = std::env::temp_dir().join(format!("haptic_gmsh_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("bin.msh");
    let mut bytes = b"$MeshFormat\n4.1 1 8\n".to_vec();
    bytes.extend_from_slice(&[1, 0, 0, 0, 0xff, 0xfe, 0x80]);
    std::fs::write(&p, bytes).unwrap();
    let e = load_msh(&p).unwrap_err();
    assert!(
        e.to_string().contains("binary") && line_of(&e) == Some(2),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn element_count_mismatch_and_bad_node_reference() {
    let e = read_msh(
        &TINY_22.replace("1 4 2 2 1 1 2 3 4", "1 4 2 2 1 1 2 3"),
        "short",
    )
    .unwrap_err();
    assert_eq!(line_of(&e), Some(19), "{e}");
    let e = read_msh(
        &TINY_22.replace("1 4 2 2 1 1 2 3 4", "1 4 2 2 1 1 2 3 8"),
        "undef",
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("defined in $Nodes") && line_of(&e) == Some(19),
        "{e}"
    );
}

/// Every token and every whole line of a valid mesh replaced, in turn, by a marker: no error
/// message quotes it (issue 47: a daemon parses files a client names, and must never send a
/// line of a file that is not a mesh back). The format's keywords and the file name are the
/// only text a message may repeat.
#[test]
fn no_message_quotes_the_file() {
    const MARK: &str = "S3cr3tMark";
    let v41 = std::fs::read_to_string(lv_dir().join("lv_h3_v41.msh")).unwrap();
    let v41_head: String = v41.lines().take(60).collect::<Vec<_>>().join("\n");
    let mut tried = 0;
    for text in [TINY_22, v41_head.as_str()] {
        let lines: Vec<&str> = text.lines().collect();
        for i in 0..lines.len() {
            let words: Vec<&str> = lines[i].split_whitespace().collect();
            let mut variants = vec![MARK.to_string(), format!("{MARK} {MARK}:x")];
            for j in 0..words.len() {
                let mut w = words.clone();
                w[j] = MARK;
                variants.push(w.join(" "));
            }
            for v in variants {
                let mut l = lines.clone();
                l[i] = &v;
                if let Err(e) = read_msh(&l.join("\n"), "client.msh") {
                    tried += 1;
                    let m = e.to_string();
                    assert!(!m.contains(MARK), "line {}: {m}", i + 1);
                    assert!(m.contains("client.msh"), "{m}");
                }
            }
        }
    }
    // Files that are not meshes at all.
    for text in [
        format!("root:x:0:0:{MARK}:/root:/bin/bash\n"),
        format!("SHELL=/bin/bash\0{MARK}=1\0"),
        format!("$MeshFormat\n{MARK}\n$EndMeshFormat\n"),
        format!("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n{MARK}\n"),
        format!("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n${MARK}\n"),
    ] {
        let m = read_msh(&text, "client.msh").unwrap_err().to_string();
        tried += 1;
        assert!(!m.contains(MARK), "{m}");
    }
    assert!(tried > 100, "only {tried} malformed variants");
}

#[test]
fn missing_file_is_an_io_error_with_its_path() {
    let e = load_msh(&lv_dir().join("nope.msh")).unwrap_err();
    assert!(
        matches!(&e, ModelError::Io { path, .. } if path.contains("nope.msh")),
        "{e}"
    );
}
