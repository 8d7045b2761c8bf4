//! `hapticctl`'s library against a mock server, the stats formatting against the proto
//! descriptor (every field), and the binary's exit code for gRPC errors.

mod common;

use std::collections::BTreeSet;

use haptic_client::ClientError;
use haptic_client::ctl::{self, Ctl, CtlCommand, SceneSource};
use prost::Message;

/// Field names of `haptics.v1.SessionStats` from the compiled descriptor set.
fn session_stats_fields() -> BTreeSet<String> {
    let fds = prost_types::FileDescriptorSet::decode(haptics_proto::FILE_DESCRIPTOR_SET).unwrap();
    let msg = fds
        .file
        .iter()
        .flat_map(|f| &f.message_type)
        .find(|m| m.name() == "SessionStats")
        .expect("SessionStats in the descriptor");
    msg.field.iter().map(|f| f.name().to_string()).collect()
}

#[test]
fn stats_table_and_json_cover_every_proto_field() {
    let fields = session_stats_fields();
    assert!(fields.len() >= 21);
    let stats = common::canned_stats("s-1");

    let json = ctl::stats_json(&stats);
    let keys: BTreeSet<String> = json.as_object().unwrap().keys().cloned().collect();
    assert_eq!(
        keys, fields,
        "JSON keys must be exactly the proto field names"
    );
    assert_eq!(json["step_p99_us"], 456.7);
    assert_eq!(json["steps"], 100_000);
    assert_eq!(json["faulted"], true);
    assert_eq!(json["fault"], "NaN in node 17");
    assert_eq!(json["tetrahedra"], 1352);

    // Per tool (issue 50): an array of objects keyed by the ToolStats field names.
    let tools = json["tools"].as_array().expect("tools array");
    assert_eq!(tools.len(), 2);
    assert_eq!(tools[0]["tool_id"], "left");
    assert_eq!(tools[0]["pose_to_force_p99_us"], 222.2);
    assert_eq!(tools[1]["slot"], 1);
    assert_eq!(tools[1]["force_n"], 0.25);
    assert_eq!(json["max_tools"], 2);

    let full = ctl::stats_table(&stats);
    // The session's fields, then (after a blank line) one row per tool.
    let (table, tools_table) = full.split_once("\n\n").expect("a tools table");
    let names: BTreeSet<String> = table
        .lines()
        .skip(1)
        .map(|l| l.split_whitespace().next().unwrap().to_string())
        .collect();
    assert_eq!(names, fields, "one table row per proto field");
    let rows: Vec<Vec<&str>> = tools_table
        .lines()
        .map(|l| l.split_whitespace().collect())
        .collect();
    assert_eq!(rows.len(), 3, "{tools_table}");
    assert_eq!(
        rows[0][..5],
        ["TOOL", "SLOT", "CONNECTED", "IN_CONTACT", "FORCE_N"]
    );
    assert_eq!(
        rows[1][..7],
        ["left", "0", "true", "true", "0.125", "44.4", "222.2"]
    );
    assert_eq!(rows[2][..5], ["right", "1", "false", "false", "0.250"]);
    // Units are printed for quantities whose name carries one.
    for line in table.lines().skip(1) {
        let name = line.split_whitespace().next().unwrap();
        let unit = match name.rsplit('_').next().unwrap() {
            "us" => Some("us"),
            "hz" => Some("Hz"),
            "n" => Some("N"),
            "m" => Some("m"),
            "s" if name != "rejected_samples" && name != "device_samples" => Some("s"),
            _ => None,
        };
        if let Some(u) = unit {
            assert!(
                line.ends_with(&format!(" {u}")),
                "{line:?} should end with {u}"
            );
        }
    }
    assert!(table.contains("0.004250"));
}

#[test]
fn vectors_are_parsed_strictly() {
    assert_eq!(ctl::parse_vec3("0.01,-0.02,0").unwrap(), [0.01, -0.02, 0.0]);
    for bad in ["1,2", "1,2,3,", "x,0,0", "0,0,nan", "0,0,1e999", " , , "] {
        let e = ctl::parse_vec3(bad).unwrap_err();
        assert!(
            matches!(e, ClientError::InvalidVector { .. }),
            "{bad:?}: {e}"
        );
        assert!(e.to_string().contains(bad), "{e}");
    }
}

async fn run(ctl: &mut Ctl, cmd: CtlCommand) -> (Result<(), ClientError>, String, String) {
    let (mut out, mut err) = (Vec::new(), Vec::new());
    let r = ctl::execute(ctl, cmd, &mut out, &mut err).await;
    (
        r,
        String::from_utf8(out).unwrap(),
        String::from_utf8(err).unwrap(),
    )
}

#[tokio::test]
async fn commands_against_a_mock_server() {
    let server = common::serve().await;
    let mut ctl = Ctl::connect(&server.url, &Default::default())
        .await
        .unwrap();

    let (r, out, _) = run(&mut ctl, CtlCommand::Scenes).await;
    r.unwrap();
    assert!(out.lines().next().unwrap().starts_with("NAME"));
    assert!(out.contains("ellipsoid") && out.contains("1352") && out.contains("left ventricle"));

    let start = CtlCommand::Start {
        scene: Some("lv".into()),
        scene_file: None,
    };
    let (r, out, err) = run(&mut ctl, start).await;
    r.unwrap();
    assert_eq!(out, "s-1\n", "start prints only the id on stdout");
    assert!(err.contains("412 nodes"), "{err}");

    let (r, out, _) = run(&mut ctl, CtlCommand::Sessions { long: false }).await;
    r.unwrap();
    assert_eq!(out, "s-1\ns-2\n");
    let (r, out, _) = run(&mut ctl, CtlCommand::Sessions { long: true }).await;
    r.unwrap();
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines.len(), 3, "{out}");
    assert!(
        lines[0].starts_with("ID") && lines[0].ends_with("DEVICE"),
        "{out}"
    );
    assert_eq!(
        lines[1].split_whitespace().take(5).collect::<Vec<_>>(),
        ["s-1", "lv", "fem", "1/2:left", "touch"],
        "{out}"
    );
    assert!(
        lines[1].ends_with(
            "touch (6/3 DOF), 3.3 N peak, 0.88 N continuous, 1260 N/m, 1000 Hz, workspace -80,-60,-35..80,60,35 mm"
        ),
        "{out}"
    );
    assert!(lines[2].ends_with("hybrid  0/1       -"), "{out}");

    let force = CtlCommand::Force {
        id: "s-1".into(),
        point: "0.01,0,-0.02".into(),
        force: "0,0,-1.5".into(),
        duration_s: 0.25,
    };
    run(&mut ctl, force).await.0.unwrap();
    {
        let rec = server.mock.recorded.lock().unwrap();
        let f = &rec.forces[0];
        assert_eq!(f.point_m.as_ref().unwrap().to_array(), [0.01, 0.0, -0.02]);
        assert_eq!(f.force_n.as_ref().unwrap().to_array(), [0.0, 0.0, -1.5]);
        assert_eq!(f.duration_s, 0.25);
    }

    let stats = CtlCommand::Stats {
        id: "s-1".into(),
        json: true,
    };
    let (r, out, _) = run(&mut ctl, stats).await;
    r.unwrap();
    assert_eq!(out.lines().count(), 1);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["session_id"], "s-1");

    let watch = CtlCommand::WatchStats {
        id: "s-1".into(),
        interval_s: 0.01,
        count: 2,
        json: true,
    };
    let (r, out, _) = run(&mut ctl, watch).await;
    r.unwrap();
    assert_eq!(out.lines().count(), 2);

    let (r, _, err) = run(&mut ctl, CtlCommand::Stop { id: "s-1".into() }).await;
    r.unwrap();
    assert!(err.contains("stopped session s-1"));
}

#[tokio::test]
async fn scene_file_is_sent_as_text() {
    let server = common::serve().await;
    let mut ctl = Ctl::connect(&server.url, &Default::default())
        .await
        .unwrap();
    let dir = common::out_dir("scene-file");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("scene.toml");
    std::fs::write(&path, "name = \"mine\"\nlength_unit = \"mm\"\n").unwrap();
    let cmd = CtlCommand::Start {
        scene: None,
        scene_file: Some(path),
    };
    let (r, out, _) = run(&mut ctl, cmd).await;
    r.unwrap();
    assert_eq!(out, "s-toml\n");
    let rec = server.mock.recorded.lock().unwrap();
    assert_eq!(
        rec.starts[0].scene_toml,
        "name = \"mine\"\nlength_unit = \"mm\"\n"
    );
    assert!(rec.starts[0].scene.is_empty());
}

#[tokio::test]
async fn not_found_reports_code_and_message() {
    let server = common::serve().await;
    let mut ctl = Ctl::connect(&server.url, &Default::default())
        .await
        .unwrap();
    let e = ctl.stats("nope").await.unwrap_err();
    assert!(e.is_rpc());
    assert_eq!(e.status().unwrap().code(), tonic::Code::NotFound);
    assert_eq!(e.to_string(), "NOT_FOUND: no session 'nope'");

    let e = ctl
        .start(SceneSource::Name("heart".into()))
        .await
        .unwrap_err();
    assert_eq!(e.to_string(), "NOT_FOUND: no scene 'heart'");
    let e = ctl.stop("nope").await.unwrap_err();
    assert_eq!(e.to_string(), "NOT_FOUND: no session 'nope'");
}

#[tokio::test]
async fn bad_vectors_are_refused_before_sending() {
    let server = common::serve().await;
    let mut ctl = Ctl::connect(&server.url, &Default::default())
        .await
        .unwrap();
    let cmd = CtlCommand::Force {
        id: "s-1".into(),
        point: "1,2".into(),
        force: "0,0,1".into(),
        duration_s: 0.1,
    };
    let (r, _, _) = run(&mut ctl, cmd).await;
    assert!(matches!(r, Err(ClientError::InvalidVector { .. })));
    let e = ctl
        .force("s-1", [0.0; 3], [0.0; 3], f64::NAN)
        .await
        .unwrap_err();
    assert!(matches!(e, ClientError::InvalidConfig(_)));
    assert!(server.mock.recorded.lock().unwrap().forces.is_empty());
}

#[tokio::test]
async fn binary_exits_2_with_code_and_message_on_grpc_errors() {
    let server = common::serve().await;
    let out = tokio::process::Command::new(env!("CARGO_BIN_EXE_hapticctl"))
        .args(["--server", &server.url, "stats", "nope"])
        .env_remove("HAPTICD_ADDR")
        .output()
        .await
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains("error: NOT_FOUND: no session 'nope'"), "{err}");
    assert!(out.stdout.is_empty());

    let out = tokio::process::Command::new(env!("CARGO_BIN_EXE_hapticctl"))
        .args(["--server", &server.url, "start", "lv"])
        .output()
        .await
        .unwrap();
    assert_eq!(out.status.code(), Some(0));
    assert_eq!(String::from_utf8(out.stdout).unwrap(), "s-1\n");

    let out = tokio::process::Command::new(env!("CARGO_BIN_EXE_hapticctl"))
        .args([
            "--server",
            &server.url,
            "force",
            "s-1",
            "--point",
            "-1,0",
            "--force",
            "0,0,1",
        ])
        .output()
        .await
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains("invalid vector \"-1,0\""), "{err}");
}
