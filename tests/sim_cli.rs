//! `b2dr sim` end to end: output layout, metrics.json contents, --resume skipping finished scenarios, and
//! clear errors for bad arguments.
use std::path::PathBuf;
use std::process::Command;

fn b2dr() -> Command {
    Command::new(env!("CARGO_BIN_EXE_b2dr"))
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("b2dr_sim_cli_{}_{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

#[test]
fn sim_writes_trace_metrics_and_frames_then_resumes() {
    let out = tmp("run");
    let o = b2dr()
        .args([
            "sim",
            "--scenario",
            "builtin:town:3",
            "--planner",
            "expert",
            "--agents",
            "idm",
            "--steps",
            "30",
        ])
        .args(["--bev-every", "15", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let dir = out.join("town-3");
    let trace = std::fs::read_to_string(dir.join("trace.jsonl")).unwrap();
    assert_eq!(trace.lines().count(), 31);
    let first: serde_json::Value = serde_json::from_str(trace.lines().next().unwrap()).unwrap();
    assert!(first["ego"]["rear_axle"]["x"].is_number() && first["command"]["accel"].is_number());
    assert!(first["agents"]
        .as_array()
        .unwrap()
        .iter()
        .any(|a| a["idm"] == true));
    for f in ["bev_0000.png", "bev_0015.png", "bev_0030.png"] {
        assert!(dir.join(f).is_file(), "{f}");
    }
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("metrics.json")).unwrap()).unwrap();
    assert!(m["score"].as_f64().unwrap() >= 0.0 && m["failure"].is_null());
    for k in [
        "no_ego_at_fault_collisions",
        "drivable_area_compliance",
        "ego_progress_along_expert_route",
        "ego_is_comfortable",
    ] {
        assert!(m["metrics"][k].is_number(), "{k}");
    }
    let all: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(all["cls_kind"], "R-CLS");
    assert!((all["cls"].as_f64().unwrap() - m["score"].as_f64().unwrap()).abs() < 1e-12);
    // --resume: the finished scenario is not rerun (its metrics.json is untouched).
    let t_before = std::fs::metadata(dir.join("metrics.json"))
        .unwrap()
        .modified()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(20));
    let o = b2dr()
        .args([
            "sim",
            "--scenario",
            "builtin:town:3",
            "--planner",
            "expert",
            "--agents",
            "idm",
            "--steps",
            "30",
            "--resume",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success());
    assert_eq!(
        std::fs::metadata(dir.join("metrics.json"))
            .unwrap()
            .modified()
            .unwrap(),
        t_before
    );
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn failing_planner_is_recorded_and_the_run_continues() {
    let out = tmp("fail");
    let o = b2dr()
        .args([
            "sim",
            "--scenario",
            "builtin:town:1",
            "--planner",
            "cmd:exit 3",
            "--steps",
            "20",
            "--bev-every",
            "0",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    // every scenario failed: a non-zero exit status (issue #18), the failure still recorded
    assert!(
        !o.status.success(),
        "a run where every scenario failed exited 0"
    );
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("every scenario failed (1 of 1"), "{e}");
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("town-1/metrics.json")).unwrap())
            .unwrap();
    assert!(m["failure"].as_str().unwrap().contains("planner"), "{m}");
    assert_eq!(m["score"].as_f64(), Some(0.0));
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(s["failures"].as_u64(), Some(1), "{s}");
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn bad_arguments_give_clear_errors() {
    let out = tmp("bad");
    for (args, needle) in [
        (vec!["--planner", "magic"], "unknown planner"),
        (vec!["--agents", "ghosts"], "unknown agent mode"),
        (
            vec!["--scenario", "builtin:city"],
            "unknown builtin scenario",
        ),
        (vec!["--scenario", "/no/such/file.json"], "neither"),
        (vec!["--steps", "0"], "--steps"),
        // timeouts that Duration::from_secs_f64 would panic on (issue #18)
        (vec!["--planner-timeout", "1e300"], "--planner-timeout"),
        (vec!["--planner-timeout", "NaN"], "--planner-timeout"),
        (vec!["--planner-timeout=-1"], "--planner-timeout"),
        (vec!["--planner-timeout", "inf"], "--planner-timeout"),
    ] {
        let o = b2dr()
            .arg("sim")
            .args(&args)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(!o.status.success(), "{args:?}");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains(needle), "{args:?}: {e}");
    }
    std::fs::remove_dir_all(&out).ok();
}

/// A three-step ScenarioNet scenario on one straight lane.
fn tiny_scenario(id: &str) -> String {
    serde_json::json!({
        "format": "scenarionet-scenario-description/json",
        "id": id, "length": 3,
        "metadata": {"sdc_id": "ego", "map": "nowhere", "sample_rate": 0.1},
        "tracks": {
            "ego": {"type": "VEHICLE", "state": {
                "position": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]],
                "heading": [0.0, 0.0, 0.0], "velocity": [[10.0, 0.0], [10.0, 0.0], [10.0, 0.0]],
                "valid": [1, 1, 1], "length": [[4.5], [4.5], [4.5]], "width": [[1.9], [1.9], [1.9]],
                "height": [[1.5], [1.5], [1.5]]}}
        },
        "map_features": {
            "l1": {"type": "LANE_SURFACE_STREET", "polyline": [[-10.0, 0.0, 0.0], [30.0, 0.0, 0.0]],
                   "polygon": [[-10.0, -2.0], [30.0, -2.0], [30.0, 2.0], [-10.0, 2.0]]}
        },
        "dynamic_map_states": {}
    })
    .to_string()
}

fn sim_folder(
    scenarios: &std::path::Path,
    out: &std::path::Path,
    resume: bool,
) -> std::process::Output {
    let mut c = b2dr();
    c.args([
        "sim",
        "--planner",
        "expert",
        "--agents",
        "none",
        "--bev-every",
        "0",
        "--scenario",
    ])
    .arg(scenarios)
    .arg("--out")
    .arg(out);
    if resume {
        c.arg("--resume");
    }
    c.output().unwrap()
}

/// An unreadable scenario file of a folder run is named on stderr (even behind the progress bar) and counted
/// in metrics.json's failures; the run still ends 0 as one scenario ran.
#[test]
fn unreadable_scenario_in_a_folder_is_reported() {
    let dir = tmp("folder");
    let (scenarios, out) = (dir.join("scenarios"), dir.join("out"));
    std::fs::create_dir_all(&scenarios).unwrap();
    std::fs::write(scenarios.join("a_good.json"), tiny_scenario("good")).unwrap();
    std::fs::write(scenarios.join("b_broken.json"), "{ not json").unwrap();
    let o = sim_folder(&scenarios, &out, false);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{e}");
    assert!(
        e.contains("b_broken") && e.contains("failed") && e.contains("not valid JSON"),
        "{e}"
    );
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(s["failures"].as_u64(), Some(1), "{s}");
    let failed: Vec<&serde_json::Value> = s["scenarios"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|v| !v["failure"].is_null())
        .collect();
    assert!(
        failed[0]["failure"]
            .as_str()
            .unwrap()
            .contains("b_broken.json"),
        "{s}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// `--out` equal to the scenario folder is refused: its config.json and metrics.json would be read back as
/// scenarios by the next run over the folder.
#[test]
fn out_in_the_scenario_folder_is_refused() {
    let dir = tmp("outin");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("good.json"), tiny_scenario("good")).unwrap();
    let o = sim_folder(&dir, &dir, false);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("holds the scenario file"),
        "{e}"
    );
    assert!(!dir.join("config.json").exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// `--resume` on a folder with results but no config.json cannot check which planner made them: refused.
#[test]
fn resume_refuses_results_without_a_configuration() {
    let dir = tmp("resume_noconfig");
    let (scenarios, out) = (dir.join("scenarios"), dir.join("out"));
    std::fs::create_dir_all(&scenarios).unwrap();
    std::fs::write(scenarios.join("good.json"), tiny_scenario("good")).unwrap();
    std::fs::create_dir_all(out.join("good")).unwrap();
    std::fs::write(
        out.join("good/metrics.json"),
        r#"{"scenario": "good", "planner": "cv", "score": 1.0, "failure": null}"#,
    )
    .unwrap();
    let o = sim_folder(&scenarios, &out, true);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("no config.json"), "{e}");
    // with its config.json, another planner's folder is refused too (naming the field)
    let o = sim_folder(&scenarios, &out, false);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut c = b2dr();
    c.args([
        "sim",
        "--planner",
        "cv",
        "--agents",
        "none",
        "--bev-every",
        "0",
        "--resume",
        "--scenario",
    ])
    .arg(&scenarios)
    .arg("--out")
    .arg(&out);
    let o = c.output().unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("planner"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}

/// `b2dr run` too: every scenario failed (one renderer, or every renderer of a comparison) is a non-zero exit
/// status, the results still written.
#[test]
fn run_exits_non_zero_when_every_scenario_failed() {
    for renderers in ["none", "none,groundtruth"] {
        let out = tmp(&format!("run_all_failed_{}", renderers.replace(',', "_")));
        let o = b2dr()
            .args([
                "run",
                "--scenario",
                "builtin:town:1",
                "--renderer",
                renderers,
            ])
            .args([
                "--planner",
                "cmd:exit 3",
                "--agents",
                "none",
                "--steps",
                "10",
                "--no-gif",
            ])
            .args(["--size", "16x24", "--out"])
            .arg(&out)
            .output()
            .unwrap();
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{renderers}: exited 0: {e}");
        assert!(
            e.contains("every scenario failed (1 of 1"),
            "{renderers}: {e}"
        );
        let first = renderers.split(',').next().unwrap();
        let summary = if renderers.contains(',') {
            out.join(first).join("metrics.json")
        } else {
            out.join("metrics.json")
        };
        assert!(summary.is_file(), "{renderers}: {}", summary.display());
        std::fs::remove_dir_all(&out).ok();
    }
}

/// A comparison writes comparison.json into --out itself: --out equal to the scenario folder is refused before
/// any renderer runs.
#[test]
fn comparison_out_in_the_scenario_folder_is_refused() {
    let dir = tmp("cmp_outin");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("good.json"), tiny_scenario("good")).unwrap();
    let o = b2dr()
        .args([
            "run",
            "--renderer",
            "none,log-replay",
            "--planner",
            "cv",
            "--agents",
            "none",
        ])
        .arg("--scenario")
        .arg(&dir)
        .arg("--out")
        .arg(&dir)
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("holds the scenario file"),
        "{e}"
    );
    assert!(!dir.join("comparison.json").exists() && !dir.join("none").exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// `--resume` checks the content of its inputs (issue #18): config.json records each scenario file's and the
/// planner script's size and hash; a resume after either changed is refused naming the file; unchanged inputs
/// resume (skipping the finished scenario).
#[test]
fn resume_refuses_changed_scenario_or_planner_files() {
    let dir = tmp("resume_inputs");
    let (scenarios, out) = (dir.join("scenarios"), dir.join("out"));
    std::fs::create_dir_all(&scenarios).unwrap();
    let a = scenarios.join("a.json");
    std::fs::write(&a, tiny_scenario("a")).unwrap();
    std::fs::write(scenarios.join("b.json"), tiny_scenario("b")).unwrap();
    let script = dir.join("planner.sh");
    let client = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/planner_client.py");
    let body = format!("exec python3 {} --mode cv\n", client.display());
    std::fs::write(&script, &body).unwrap();
    let run = |resume: bool| {
        let mut c = b2dr();
        c.args(["sim", "--agents", "none", "--bev-every", "0", "--planner"])
            .arg(format!("cmd:sh {}", script.display()))
            .arg("--scenario")
            .arg(&scenarios)
            .arg("--out")
            .arg(&out);
        if resume {
            c.arg("--resume");
        }
        c.output().unwrap()
    };
    let o = run(false);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("config.json")).unwrap()).unwrap();
    let inputs = cfg["input_files"].as_object().unwrap();
    assert_eq!(inputs.len(), 3, "{cfg}");
    let key = a.display().to_string();
    assert_eq!(inputs[&key]["role"], "scenario", "{cfg}");
    assert_eq!(inputs[&script.display().to_string()]["role"], "planner");
    // unchanged: resumes
    let o = run(true);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // a scenario file changed in place (same size: one digit)
    let text = tiny_scenario("a");
    let changed = text.replacen("1.0", "2.0", 1);
    assert_eq!(changed.len(), text.len());
    assert_ne!(changed, text);
    std::fs::write(&a, &changed).unwrap();
    let o = run(true);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success()
            && e.contains("--resume")
            && e.contains(&format!("the scenario {key} changed")),
        "{e}"
    );
    std::fs::write(&a, &text).unwrap();
    assert!(run(true).status.success());
    // the planner script changed
    std::fs::write(&script, format!("# v2\n{body}")).unwrap();
    let o = run(true);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains(&format!("the planner {} changed", script.display())),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
