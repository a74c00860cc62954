//! Planner protocol v2 end to end with a Python planner (tests/fixtures/protocol_planner.py, served by the
//! planner package python/b2dr_planner): images by path and inline
//! reach the planner with the checksum the request states, intrinsics match the delivered size, and hostile
//! planners (never reads, closes stdout but lives, two replies, 10^5 poses) end only their scenario, within the
//! timeout, with a reason.
use std::sync::Arc;
use std::time::{Duration, Instant};

use b2dr::scene::geometry::{angle_diff, Pose2};
use b2dr::scene::Scenario;
use b2dr::sim::closed_loop::run_with_sensors;
use b2dr::sim::ego::EgoState;
use b2dr::sim::external::ExternalPlanner;
use b2dr::sim::sensors::Command;
use b2dr::sim::sensors::{CameraFrame, SensorState, Sensors};
use b2dr::sim::trajectory::Trajectory;
use b2dr::sim::{AgentMode, SimConfig};
use b2dr::sim::{Planner, PlannerInput};
use b2dr::world::town as synthetic;
use glam::DVec2;

fn python() -> bool {
    std::process::Command::new("python3")
        .arg("--version")
        .output()
        .is_ok()
}

/// A test camera source: a deterministic gradient per camera and step at 112 x 200 from the scenario rig.
struct Gradient;

impl Sensors for Gradient {
    fn name(&self) -> String {
        "gradient".into()
    }
    fn reset(&mut self, _: &Scenario) -> anyhow::Result<()> {
        Ok(())
    }
    fn observe(&mut self, s: &SensorState) -> anyhow::Result<Vec<CameraFrame>> {
        let (w, h) = (200u32, 112u32);
        Ok(s.scenario
            .rig
            .cameras
            .iter()
            .enumerate()
            .map(|(ci, c)| {
                let mut rgb = Vec::with_capacity((w * h * 3) as usize);
                for y in 0..h {
                    for x in 0..w {
                        rgb.extend([(x % 256) as u8, (y * 2) as u8, (ci * 40 + s.step) as u8]);
                    }
                }
                CameraFrame {
                    camera: c.name.clone(),
                    width: w,
                    height: h,
                    rgb: Arc::new(rgb),
                    intrinsic: c.intrinsic_scaled(w, h),
                    cam2ego: c.cam2ego,
                    ego2global: s.ego2global(),
                }
            })
            .collect())
    }
}

fn planner(args: &str, timeout_s: f64, dir: &std::path::Path) -> ExternalPlanner {
    let cmd = format!(
        // exec: the shell is replaced, so the planner process itself holds the pipes (a closed stdout is seen)
        "exec python3 {}/tests/fixtures/protocol_planner.py {args}",
        env!("CARGO_MANIFEST_DIR")
    );
    ExternalPlanner::new(&cmd, Duration::from_secs_f64(timeout_s))
        .unwrap()
        .v2(Some(dir.to_path_buf()))
}

fn cfg() -> SimConfig {
    SimConfig {
        agents: AgentMode::Idm,
        steps: 12,
        ..SimConfig::default()
    }
}

fn run(sc: &Scenario, p: &mut ExternalPlanner) -> b2dr::sim::SimResult {
    run_with_sensors(
        sc,
        p,
        &cfg(),
        &|_, _| vec![],
        Some(&mut Gradient),
        &mut |_, _| Ok(()),
    )
}

fn tmp(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("b2dr-proto-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn images_reach_the_planner_exactly() {
    if !python() {
        println!("SKIP: python3 not available");
        return;
    }
    let sc = synthetic::town(1, None);
    for images in ["paths", "inline"] {
        let d = tmp(images);
        let r = run(
            &sc,
            &mut planner(&format!("--mode checksum --images {images}"), 20.0, &d),
        );
        assert!(r.failure.is_none(), "{images}: {:?}", r.failure);
        assert_eq!(r.steps.len(), 13);
        if images == "paths" {
            assert!(
                std::fs::read_dir(&d).unwrap().count() >= 6 * 3,
                "image files written"
            );
        }
    }
    // a requested size: the planner gets images and intrinsics at that size; its projection of an ego point
    // equals b2dr's at that size
    let d = tmp("size");
    let dump = d.join("dump.jsonl");
    let r = run(
        &sc,
        &mut planner(
            &format!(
                "--mode project --images inline --size 56x100 --dump {}",
                dump.display()
            ),
            20.0,
            &d,
        ),
    );
    assert!(r.failure.is_none(), "{:?}", r.failure);
    let text = std::fs::read_to_string(&dump).unwrap();
    let mut n = 0;
    for line in text.lines() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        assert_eq!(v["size"], serde_json::json!([56, 100]));
        let cam = sc
            .rig
            .cameras
            .iter()
            .find(|c| c.name == v["camera"].as_str().unwrap())
            .unwrap();
        // b2dr's projection of the ego point through the camera at 100 x 56
        let k = cam.intrinsic_scaled(100, 56);
        let pc = cam
            .cam2ego
            .inverse()
            .transform_point3(glam::DVec3::new(10.0, 0.0, 0.5));
        if pc.z <= 1e-6 {
            assert!(v["uv"].is_null(), "{line}");
            continue;
        }
        let p = k * (pc / pc.z);
        // the planner's projections: through cam2ego + intrinsic, and through the lidar frame (ego_in_lidar)
        // and lidar2img of the same message; the start message's lidar2ego reached it
        for key in ["uv", "uv_lidar"] {
            let uv = v[key].as_array().unwrap();
            let (u, vv) = (uv[0].as_f64().unwrap(), uv[1].as_f64().unwrap());
            assert!(
                (u - p.x).abs() < 1e-6 && (vv - p.y).abs() < 1e-6,
                "{key}: {line} vs {p:?}"
            );
        }
        let l2e: [[f64; 4]; 4] = serde_json::from_value(v["lidar2ego"].clone()).unwrap();
        assert!(
            b2dr::projection::geometry::mat4_from_rows(&l2e).abs_diff_eq(sc.rig.lidar2ego, 1e-12)
        );
        n += 1;
    }
    assert!(n >= 3, "the point is in front of several cameras ({n})");
}

#[test]
fn hostile_planners_end_only_their_scenario() {
    if !python() {
        println!("SKIP: python3 not available");
        return;
    }
    let sc = synthetic::town(1, None);
    for (mode, needle) in [
        ("noread", "timed out"),
        ("closeout", "closed its output"),
        ("tworeplies", "two replies"),
        ("manyposes", "at most 1000"),
        ("badframe", "planner reply `frame` = \"camera\""),
        ("baddt", "planner reply `dt_s` = 0"),
        ("mixed", "poses[0] has 2 values but poses[1] has 3"),
        (
            "short",
            "3 poses x `dt_s` 0.5 s cover 1.5 s; at least 2 s are required",
        ),
    ] {
        let d = tmp(mode);
        let t0 = Instant::now();
        let r = run(
            &sc,
            &mut planner(&format!("--mode {mode} --images inline"), 2.0, &d),
        );
        let f = r
            .failure
            .as_ref()
            .map(ToString::to_string)
            .unwrap_or_default();
        println!("{mode}: {f} ({:.2} s)", t0.elapsed().as_secs_f64());
        assert!(f.contains(needle), "{mode}: {f}");
        assert!(
            t0.elapsed() < Duration::from_secs(12),
            "{mode} took too long"
        );
    }
    // the next scenario runs normally
    let d = tmp("after");
    let r = run(&sc, &mut planner("--mode cv --images none", 20.0, &d));
    assert!(r.failure.is_none(), "{:?}", r.failure);
}

/// Camera names come from data (a model package, a frame file): one with separators or `..` becomes a plain
/// file name inside the image folder (issue #18), and the scenario runs.
#[test]
fn camera_names_from_data_stay_inside_the_image_folder() {
    if !python() {
        println!("SKIP: python3 not available");
        return;
    }
    let mut sc = synthetic::town(1, None);
    sc.rig.cameras[0].name = "../../escape".into();
    sc.rig.cameras[1].name = "/tmp/b2dr-abs".into();
    let d = tmp("names").join("images");
    std::fs::create_dir_all(&d).unwrap();
    let r = run(
        &sc,
        &mut planner("--mode checksum --images paths", 20.0, &d),
    );
    assert!(r.failure.is_none(), "{:?}", r.failure);
    let names: Vec<String> = std::fs::read_dir(&d)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    assert!(
        names.iter().any(|n| n.ends_with("______escape.png")),
        "{names:?}"
    );
    assert!(
        names.iter().any(|n| n.ends_with("_tmp_b2dr-abs.png")),
        "{names:?}"
    );
    assert!(std::fs::read_dir(d.parent().unwrap()).unwrap().count() == 1);
}

/// One plan of a v2 planner process on the synthetic town's first step: (the request's ego, the trajectory).
fn plan_once(mode: &str) -> anyhow::Result<(EgoState, Trajectory)> {
    let sc = synthetic::town(1, None);
    let d = tmp(mode);
    let mut p = planner(&format!("--mode {mode} --images none"), 20.0, &d);
    p.start(&sc)?;
    let ego = EgoState::from_log(&sc.ego, 0, sc.dt);
    let t = p.plan(&PlannerInput {
        scenario: &sc,
        step: 0,
        time_s: 0.0,
        ego: &ego,
        objects: &[],
        images: &[],
        frames: &[],
        command: Command::Straight,
        command_def: Default::default(),
        history: &[],
    });
    p.finish();
    Ok((ego, t?))
}

/// Replies as end-to-end models emit them (issue #34 item 3), through the Python client's `reply` helper:
/// six xy points 0.5 s apart in the lidar frame become rear-axle poses with path headings; three poses 1 s
/// apart keep their spacing in the tracker's trajectory.
#[test]
fn replies_as_models_emit_them() {
    if !python() {
        println!("SKIP: python3 not available");
        return;
    }
    let (ego, t) = plan_once("lidarxy").unwrap();
    // the planner's ego-frame ground points (v dt k, 0.02 k^2), k = 1..6, v = max(2, vx), sent as lidar xy
    let v = ego.vx.max(2.0);
    let local: Vec<DVec2> = (1..=6)
        .map(|k| DVec2::new(v * 0.5 * k as f64, 0.02 * (k * k) as f64))
        .collect();
    assert_eq!(
        t.times_us,
        (0..=6).map(|k| k * 500_000).collect::<Vec<i64>>()
    );
    let mut prev = DVec2::ZERO;
    for (k, q) in local.iter().enumerate() {
        // heading: the chord arriving at the point (all chords are longer than 5 cm)
        let h = (q.y - prev.y).atan2(q.x - prev.x);
        prev = *q;
        let want = ego.rear_axle.compose(&Pose2::new(q.x, q.y, h));
        let got = t.poses[k + 1];
        assert!(
            (got.x - want.x).abs() < 1e-6
                && (got.y - want.y).abs() < 1e-6
                && angle_diff(got.heading, want.heading).abs() < 1e-9,
            "pose {}: {got:?} vs {want:?}",
            k + 1
        );
    }
    // dt 1.0: the trajectory's poses are 1 s apart
    let (ego, t) = plan_once("dt1").unwrap();
    assert_eq!(t.times_us, vec![0, 1_000_000, 2_000_000, 3_000_000]);
    let v = ego.vx.max(2.0);
    let end = ego.rear_axle.compose(&Pose2::new(3.0 * v, 0.0, 0.0));
    assert!((t.poses[3].x - end.x).abs() < 1e-9 && (t.poses[3].y - end.y).abs() < 1e-9);
    // a refused reply is an error naming the field
    let e = plan_once("badframe").unwrap_err().to_string();
    assert!(e.contains("`frame`"), "{e}");
}
