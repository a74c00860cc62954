//! `b2dr run --planner resident:...`: one planner process for a batch of scenarios (docs/planner_protocol.md
//! "Resident planners"), with tests/fixtures/resident_planner.py (the constant-velocity rule, a `load` that
//! appends its pid to a file). One load drives every scenario with the scores of one process per scenario; a
//! crash or a hang mid-scenario fails that scenario only and the next one runs on a restarted process (an error
//! reply keeps the process); the load runs under the start timeout, not the per-call one.
use std::path::{Path, PathBuf};
use std::time::Instant;

use b2dr::eval::run::{run, RendererMode, RunConfig};
use b2dr::sim::AgentMode;
use serde_json::Value;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("b2dr-resident-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// `resident:` or `cmd:` running the fixture with `args`, each load appended to `<dir>/loads`.
fn planner(kind: &str, dir: &Path, args: &str) -> String {
    format!(
        "{kind}:exec python3 {}/tests/fixtures/resident_planner.py --loads {} {args}",
        env!("CARGO_MANIFEST_DIR"),
        dir.join("loads").display()
    )
}

fn cfg(scenario: &str, planner: &str, steps: usize, timeout_s: f64, start_s: f64) -> RunConfig {
    RunConfig {
        scenario: scenario.into(),
        renderer: RendererMode::None,
        model: None,
        planner: planner.parse().unwrap(),
        agents: AgentMode::Idm,
        controller: "lqr".parse().unwrap(),
        steps,
        planner_timeout_s: timeout_s,
        planner_start_timeout_s: start_s,
        cameras: vec![],
        size: (56, 104),
        seed: 0,
        dtype: b2dr::tensor::DType::F32,
        gif: false,
        shard: None,
        requests: Default::default(),
    }
}

/// The processes that loaded (lines of `<dir>/loads`).
fn loads(dir: &Path) -> usize {
    std::fs::read_to_string(dir.join("loads"))
        .map(|s| s.lines().count())
        .unwrap_or(0)
}

fn scenarios(s: &Value) -> &Vec<Value> {
    s["scenarios"].as_array().unwrap()
}

/// The first scenario's failure message ("" when it passed).
fn first_failure(s: &Value) -> String {
    scenarios(s)[0]["failure"]
        .as_str()
        .unwrap_or_default()
        .to_string()
}

/// A scenario's own metrics.json (what the batch wrote to its folder).
fn metrics(out: &Path, folder: &str) -> Value {
    serde_json::from_str(&std::fs::read_to_string(out.join(folder).join("metrics.json")).unwrap())
        .unwrap()
}

const TWO: &str = "builtin:town:2,builtin:town:3";

#[test]
fn one_load_drives_the_batch_with_the_scores_of_one_process_per_scenario() {
    let dir = tmp("equal");
    let (rd, cd) = (dir.join("resident"), dir.join("cmd"));
    std::fs::create_dir_all(&rd).unwrap();
    std::fs::create_dir_all(&cd).unwrap();
    let res = run(
        None,
        &cfg(TWO, &planner("resident", &rd, ""), 20, 10.0, 30.0),
        &rd.join("out"),
        false,
    )
    .unwrap();
    let per = run(
        None,
        &cfg(TWO, &planner("cmd", &cd, ""), 20, 10.0, 30.0),
        &cd.join("out"),
        false,
    )
    .unwrap();
    assert_eq!(
        loads(&rd),
        1,
        "the resident planner loads once for the batch"
    );
    assert_eq!(loads(&cd), 2, "cmd: loads once per scenario");
    let (a, b) = (scenarios(&res), scenarios(&per));
    assert_eq!(a.len(), 2);
    for (x, y) in a.iter().zip(b) {
        assert!(x["failure"].is_null(), "{x}");
        assert!(y["failure"].is_null(), "{y}");
        let (sx, sy) = (x["score"].as_f64().unwrap(), y["score"].as_f64().unwrap());
        assert!(sx > 0.0, "{x}");
        // a deterministic planner on the same pipes: the same score (the acceptance: within 0.02)
        assert_eq!(
            sx, sy,
            "{} resident {sx} vs per scenario {sy}",
            x["scenario"]
        );
        assert_eq!(x["planner_process"]["process"], 1, "{x}");
        assert_eq!(x["planner_process"]["restarted"], false, "{x}");
        assert!(y.get("planner_process").is_none(), "{y}");
    }
}

/// Runs TWO with the planner failing at step 5 of the first scenario (`how`: --die-at or --hang-at); checks
/// that only that scenario failed, with a reason containing `cause`, and that the second ran on a restarted
/// process.
fn fails_one_and_restarts(name: &str, how: &str, cause: &str) {
    let dir = tmp(name);
    // the first scenario (folder-name order) as the planner names it (`Request.scenario`)
    let scenario = b2dr::world::load_all("builtin:town:2")
        .unwrap()
        .remove(0)
        .name;
    let folder = b2dr::eval::run::folder_name(&scenario);
    let out = dir.join("out");
    let t0 = Instant::now();
    let s = run(
        None,
        &cfg(
            TWO,
            &planner("resident", &dir, &format!("{how} {scenario}:5")),
            20,
            2.0,
            30.0,
        ),
        &out,
        false,
    )
    .unwrap();
    assert!(t0.elapsed().as_secs_f64() < 15.0, "{:?}", t0.elapsed());
    let sc = scenarios(&s);
    assert_eq!(sc[0]["scenario"], scenario.as_str());
    let failure = sc[0]["failure"].as_str().unwrap_or_default();
    assert!(
        failure.contains("step 5") && failure.contains(cause),
        "{failure}"
    );
    // the cause is in the scenario's own metrics.json
    assert_eq!(metrics(&out, &folder)["failure"], sc[0]["failure"]);
    assert_eq!(sc[0]["score"], 0.0);
    assert!(sc[1]["failure"].is_null(), "{}", sc[1]);
    assert!(sc[1]["score"].as_f64().unwrap() > 0.0, "{}", sc[1]);
    assert_eq!(
        loads(&dir),
        2,
        "the process is restarted (with its load) for the next scenario"
    );
    let p = &sc[1]["planner_process"];
    assert_eq!(p["process"], 2, "{p}");
    assert_eq!(p["restarted"], true, "{p}");
    assert!(p["restart_cause"].as_str().unwrap().contains(cause), "{p}");
}

#[test]
fn a_crash_mid_scenario_fails_that_scenario_and_the_next_runs_on_a_restarted_process() {
    fails_one_and_restarts("crash", "--die-at", "exited");
}

#[test]
fn a_hang_mid_scenario_times_out_that_scenario_and_the_next_runs_on_a_restarted_process() {
    fails_one_and_restarts("hang", "--hang-at", "timed out");
}

/// The script a resident command line names enters config.json's fingerprinted inputs, as a `cmd:` one's.
#[test]
fn the_resident_planner_script_is_fingerprinted() {
    let script =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/resident_planner.py");
    for kind in ["cmd", "resident"] {
        let files =
            b2dr::eval::batch::planner_files(&format!("{kind}:python3 {}", script.display()));
        assert_eq!(files, vec![script.clone()], "{kind}");
    }
}

/// An `{"error": ...}` reply ends its scenario but leaves the pipes in step: the process serves the next one.
#[test]
fn an_error_reply_fails_that_scenario_and_keeps_the_process() {
    let dir = tmp("error");
    let scenario = b2dr::world::load_all("builtin:town:2")
        .unwrap()
        .remove(0)
        .name;
    let args = format!("--error-at {scenario}:5");
    let s = run(
        None,
        &cfg(TWO, &planner("resident", &dir, &args), 20, 2.0, 30.0),
        &dir.join("out"),
        false,
    )
    .unwrap();
    let sc = scenarios(&s);
    let failure = sc[0]["failure"].as_str().unwrap_or_default();
    assert!(
        failure.contains("step 5") && failure.contains("refusing this step"),
        "{failure}"
    );
    assert!(sc[1]["failure"].is_null(), "{}", sc[1]);
    assert_eq!(loads(&dir), 1, "no restart after a reply in step");
    assert_eq!(sc[1]["planner_process"]["process"], 1, "{}", sc[1]);
    assert_eq!(sc[1]["planner_process"]["restarted"], false, "{}", sc[1]);
}

#[test]
fn the_load_runs_under_the_start_timeout_not_the_per_call_one() {
    let dir = tmp("load");
    let one = "builtin:town:2";
    // a 3 s load with a 1.5 s per-call timeout: accepted resident (start timeout 30 s) ...
    let slow = planner("resident", &dir, "--load-sleep 3");
    let s = run(
        None,
        &cfg(one, &slow, 10, 1.5, 30.0),
        &dir.join("ok"),
        false,
    )
    .unwrap();
    assert!(scenarios(&s)[0]["failure"].is_null(), "{s}");
    assert!(scenarios(&s)[0]["score"].as_f64().unwrap() > 0.0, "{s}");
    // ... and times out as cmd: (the load at the first `start`, under the per-call timeout)
    let per = planner("cmd", &dir, "--load-sleep 3");
    let s = run(
        None,
        &cfg(one, &per, 10, 1.5, 30.0),
        &dir.join("cmd"),
        false,
    )
    .unwrap();
    let failure = first_failure(&s);
    assert!(failure.contains("timed out"), "{failure}");
    // a load longer than the start timeout fails the scenario with a message naming it, within about that time
    let t0 = Instant::now();
    let too_slow = planner("resident", &dir, "--load-sleep 30");
    let s = run(
        None,
        &cfg(one, &too_slow, 10, 1.0, 1.0),
        &dir.join("slow"),
        false,
    )
    .unwrap();
    assert!(t0.elapsed().as_secs_f64() < 10.0, "{:?}", t0.elapsed());
    let failure = first_failure(&s);
    assert!(
        failure.contains("did not answer `hello` (start timeout 1.0 s, --planner-start-timeout)")
            && failure.contains("timed out"),
        "{failure}"
    );
    // a load that raises: serve() answers `hello` with the error, the scenario fails with it
    let broken = planner("resident", &dir, "--load-fails");
    let s = run(
        None,
        &cfg(one, &broken, 10, 1.0, 30.0),
        &dir.join("broken"),
        false,
    )
    .unwrap();
    let failure = first_failure(&s);
    assert!(
        failure.contains("resident planner failed to load") && failure.contains("no weights here"),
        "{failure}"
    );
}
