//! A nuScenes DATAROOT without the map expansion pack (issue #35): the main download alone, the devkit's table
//! layout as `python/b2dr_ref/nuscenes_fixture.py --no-map-expansion` writes it from the shared scene-0061 data
//! (no `maps/expansion/` folder; the pack is a separate download the devkit needs only for its map API). Boxes,
//! ego, cameras and images import as with the pack; `run --renderer log-replay` and `export-training` work;
//! what needs lanes (`sim`, IDM agents, the score) says so and names the missing file. Skips with a printed
//! reason when the shared data or Python is absent.
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

#[path = "common/fixture_dirs.rs"]
mod fixture_dirs;
mod nuscenes_fixture;

use b2dr::scene::import::nuscenes;
use nuscenes_fixture::{dataroot, spec, write_fixture};
use serde_json::Value;

/// The DATAROOT without the pack (written once per test process).
fn bare() -> Option<&'static Path> {
    static ROOT: OnceLock<Option<PathBuf>> = OnceLock::new();
    ROOT.get_or_init(|| write_fixture("nomap", &["--no-map-expansion"]))
        .as_deref()
}

const MISSING: &str = "maps/expansion/singapore-onenorth.json";

fn b2dr() -> Command {
    Command::new(env!("CARGO_BIN_EXE_b2dr"))
}

/// Ego, tracks, cameras and recorded frames equal those of the same scene imported with the pack; the map has no
/// lanes and says which file is missing.
#[test]
fn imports_everything_but_lanes() {
    let (Some(full), Some(bare)) = (dataroot(), bare()) else {
        return;
    };
    assert!(!bare.join("maps/expansion").exists());
    let a = nuscenes::load(&spec(full)).unwrap();
    let b = nuscenes::load(&spec(bare)).unwrap();
    assert!(b.map.lanes.is_empty() && b.map.crosswalks.is_empty() && b.map.drivable.is_empty());
    let why = b.map.missing.as_deref().unwrap();
    assert!(
        why.contains(&bare.join(MISSING).display().to_string()) && why.contains("map expansion"),
        "{why}"
    );
    assert!(a.map.missing.is_none() && !a.map.lanes.is_empty());
    assert_eq!(a.ego, b.ego);
    // Track has no PartialEq: its Debug text holds every field.
    assert_eq!(format!("{:?}", a.tracks), format!("{:?}", b.tracks));
    assert_eq!(a.rig.cameras, b.rig.cameras);
    assert_eq!(a.rig.frames.len(), b.rig.frames.len());
    for (fa, fb) in a.rig.frames.iter().zip(&b.rig.frames) {
        assert_eq!(fa.ego2global, fb.ego2global);
        assert_eq!(fa.images.len(), fb.images.len());
        for (ia, ib) in fa.images.iter().zip(&fb.images) {
            assert_eq!(
                (ia.timestamp_us, ia.ego2global),
                (ib.timestamp_us, ib.ego2global)
            );
            assert!(Path::new(&ib.path).is_file(), "{}", ib.path);
        }
    }
    eprintln!(
        "nuScenes without the map expansion: {} steps, {} tracks, {} frames (equal to the import with it)",
        b.ego.len(),
        b.tracks.len(),
        b.rig.frames.len()
    );
}

/// `b2dr sim` refuses the scene: lanes need the expansion pack, and the message says where it looked.
#[test]
fn sim_says_lanes_need_the_expansion_pack() {
    let Some(bare) = bare() else { return };
    let out = bare.join("out_sim");
    let o = b2dr()
        .args([
            "sim",
            "--scenario",
            &format!("nuscenes:{}:scene-0061", bare.display()),
        ])
        .args(["--planner", "expert", "--agents", "replay", "--steps", "5"])
        .args(["--bev-every", "0", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    for want in ["needs lanes", "map expansion", MISSING] {
        assert!(e.contains(want), "{want:?} not in: {e}");
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// Log replay runs (the planner sees the recorded images) with replayed agents; the score says why it is missing;
/// IDM agents are refused with the missing file.
#[test]
fn log_replay_runs_and_idm_agents_refuse() {
    use b2dr::eval::run::{run, RendererMode, RunConfig};
    let Some(bare) = bare() else { return };
    let out = bare.join("out_run");
    let _ = std::fs::remove_dir_all(&out);
    let mut cfg = RunConfig {
        scenario: format!("nuscenes:{}:scene-0061", bare.display()),
        renderer: RendererMode::LogReplay,
        model: None,
        planner: b2dr::sim::PlannerSpec::Expert,
        agents: b2dr::sim::AgentMode::Replay,
        controller: b2dr::sim::closed_loop::Controller::Lqr,
        steps: 10,
        planner_timeout_s: 30.0,
        planner_start_timeout_s: 300.0,
        cameras: vec!["CAM_FRONT".into()],
        size: (56, 100),
        seed: 0,
        dtype: b2dr::tensor::DType::F32,
        gif: false,
        shard: None,
        requests: Default::default(),
    };
    run(None, &cfg, &out, false).unwrap();
    let dir = out.join("scene-0061");
    assert!(dir.join("frames/0000_CAM_FRONT.png").is_file());
    assert!(dir.join("frames/0005_CAM_FRONT.png").is_file());
    let m: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("metrics.json")).unwrap()).unwrap();
    assert!(m["failure"].is_null(), "{m}");
    let e = m["metrics_error"].as_str().unwrap_or_default();
    assert!(
        e.contains("closed-loop score") && e.contains(MISSING),
        "{m}"
    );
    // IDM agents need lanes: the scenario fails, naming the file.
    let out2 = bare.join("out_run_idm");
    let _ = std::fs::remove_dir_all(&out2);
    cfg.agents = b2dr::sim::AgentMode::Idm;
    let r = run(None, &cfg, &out2, false);
    let text = match r {
        Ok(_) => std::fs::read_to_string(out2.join("scene-0061/metrics.json")).unwrap_or_default(),
        Err(e) => format!("{e:#}"),
    };
    assert!(
        text.contains("--agents idm") && text.contains(MISSING),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&out2);
}

/// `b2dr export-training` exports the recorded frames (masks of boxes; no map channels to draw).
#[test]
fn export_training_works() {
    let Some(bare) = bare() else { return };
    let out = bare.join("out_export");
    let _ = std::fs::remove_dir_all(&out);
    let o = b2dr()
        .args([
            "export-training",
            "--scenario",
            &format!("nuscenes:{}:scene-0061", bare.display()),
        ])
        .args(["--size", "56x100", "--samples-per-scenario", "2"])
        .args(["--cameras", "CAM_FRONT", "--quiet", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let idx: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("index.json")).unwrap()).unwrap();
    assert!(idx.to_string().contains("scene-0061"), "{idx}");
    let _ = std::fs::remove_dir_all(&out);
}
