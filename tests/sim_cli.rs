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
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("town-1/metrics.json")).unwrap())
            .unwrap();
    assert!(m["failure"].as_str().unwrap().contains("planner"), "{m}");
    assert_eq!(m["score"].as_f64(), Some(0.0));
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
