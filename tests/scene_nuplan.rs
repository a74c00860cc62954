//! The nuPlan importer (`--scenario nuplan:DB[:SCENARIO_TOKEN]`) on a small log DB, GeoPackage map and
//! sensor_blobs folder written at test time from a known hand-made scenario by `python/b2dr_ref/nuplan_fixture.py`
//! (its `expected.json` holds the scenario at 10 Hz): round trip, scenario windows, map / route / drivable area,
//! `b2dr sim`, log replay, malformed inputs, import time. Skips with a printed reason when no Python with numpy
//! is available.
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;
use std::time::Instant;

#[path = "common/fixture_dirs.rs"]
mod fixture_dirs;
mod nuplan_fixture;
use fixture_dirs::{python, remove_stale_fixtures};

use b2dr::scene::import::nuplan::{self, NuplanSpec};
use b2dr::scene::import::{resolve, Source};
use b2dr::scene::map::LaneKind;
use b2dr::scene::TrafficLightStatus;
use glam::DVec2;
use serde_json::Value;

/// Writes a fixture into a fresh temporary folder; None (reason printed) without Python / numpy.
fn write_fixture(name: &str, extra: &[&str]) -> Option<PathBuf> {
    remove_stale_fixtures("b2dr_nuplan_");
    let out = std::env::temp_dir().join(format!("b2dr_nuplan_{name}_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let o = Command::new(python())
        .current_dir(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python"))
        .args(["-m", "b2dr_ref.nuplan_fixture", "--out"])
        .arg(&out)
        .args(extra)
        .output();
    match o {
        Ok(o) if o.status.success() => Some(out),
        Ok(o) => {
            eprintln!(
                "skipping: the fixture writer failed: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            None
        }
        Err(e) => {
            eprintln!("skipping: no Python to write the fixture ({e})");
            None
        }
    }
}

/// The shared 20 s fixture (written once per test process).
fn root() -> Option<&'static Path> {
    static ROOT: OnceLock<Option<PathBuf>> = OnceLock::new();
    ROOT.get_or_init(|| write_fixture("main", &[])).as_deref()
}

fn expected(root: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(root.join("expected.json")).unwrap()).unwrap()
}

fn db_path(root: &Path) -> PathBuf {
    PathBuf::from(expected(root)["db"].as_str().unwrap())
}

fn spec(db: &Path, token: Option<&str>) -> NuplanSpec {
    NuplanSpec {
        db: db.to_path_buf(),
        token: token.map(str::to_string),
        maps_root: None,
        map_version: nuplan::maps_db::DEFAULT_MAP_VERSION.to_string(),
        sensor_root: None,
    }
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

#[test]
fn spec_syntax() {
    let s = resolve("nuplan:/data/x.db").unwrap();
    let Source::Nuplan(n) = &s[0] else { panic!() };
    assert_eq!(
        (n.db.to_str(), n.token.as_deref()),
        (Some("/data/x.db"), None)
    );
    assert_eq!(s[0].name(), "x");
    let s = resolve("nuplan:/data/x.db:5A00000000009e37").unwrap();
    let Source::Nuplan(n) = &s[0] else { panic!() };
    assert_eq!(n.token.as_deref(), Some("5a00000000009e37"));
    assert_eq!(s[0].name(), "x_5a00000000009e37");
    // A colon that is not followed by hex belongs to the path.
    let Source::Nuplan(n) = &resolve("nuplan:/a:b/x.db").unwrap()[0] else {
        panic!()
    };
    assert_eq!(
        (n.db.to_str(), n.token.as_deref()),
        (Some("/a:b/x.db"), None)
    );
    let e = format!("{:#}", resolve("nuplan:").unwrap_err());
    assert!(e.contains("nuplan:DB[:SCENARIO_TOKEN]"), "{e}");
}

/// The whole 20 s log: 401 lidar_pc at 20 Hz -> 201 steps; ego, tracks, lights and cameras equal the known
/// scenario (positions 1e-6 m, angles 1e-9 rad, velocities 1e-9 m/s, calibration 1e-9).
#[test]
fn round_trip_equals_the_known_scenario() {
    let Some(root) = root() else { return };
    let ex = expected(root);
    let log = nuplan::load_log(&spec(&db_path(root), None)).unwrap();
    let sc = &log.scenario;
    let steps = ex["steps"].as_array().unwrap();
    assert_eq!(sc.len(), 201);
    assert_eq!(steps.len(), 201);
    assert_eq!(sc.dt, 0.1);
    assert_eq!(log.t0_us, ex["t0_us"].as_i64().unwrap());
    let tok: std::collections::HashMap<String, String> = ex["tracks"]
        .as_object()
        .unwrap()
        .iter()
        .map(|(k, v)| (v.as_str().unwrap().to_string(), k.clone()))
        .collect();
    assert_eq!(sc.tracks.len(), 4);
    let c21 = sc.map.lane_index("21").unwrap();
    let c22 = sc.map.lane_index("22").unwrap();
    for (k, st) in steps.iter().enumerate() {
        let e = &st["ego"];
        let p = sc.ego[k].rear_axle;
        assert!(
            (p.x - f(&e[0])).abs() < 1e-6 && (p.y - f(&e[1])).abs() < 1e-6,
            "step {k}"
        );
        assert!((p.heading - f(&e[2])).abs() < 1e-9, "step {k}");
        let v = sc.ego[k].velocity;
        let want = DVec2::new(f(&e[2]).cos(), f(&e[2]).sin()) * f(&e[3]);
        assert!(v.distance(want) < 1e-9, "step {k}: {v} vs {want}");
        let trs = st["tracks"].as_object().unwrap();
        for tr in &sc.tracks {
            let name = &tok[&tr.id];
            match (tr.states[k], trs.get(name)) {
                (Some(s), Some(w)) => {
                    assert!((s.pose.x - f(&w[0])).abs() < 1e-6, "{name} step {k}");
                    assert!((s.pose.y - f(&w[1])).abs() < 1e-6, "{name} step {k}");
                    assert!((s.pose.heading - f(&w[2])).abs() < 1e-9);
                    assert!(s.velocity.distance(DVec2::new(f(&w[3]), f(&w[4]))) < 1e-9);
                }
                (None, None) => {}
                (a, b) => panic!("{name} step {k}: imported {a:?}, expected {b:?}"),
            }
        }
        let lights = sc.lights_at(k);
        let want21 = match st["lights"]["21"].as_str().unwrap() {
            "green" => TrafficLightStatus::Green,
            "yellow" => TrafficLightStatus::Yellow,
            _ => TrafficLightStatus::Red,
        };
        assert_eq!(
            lights,
            &[
                (
                    c21.min(c22),
                    if c21 < c22 {
                        want21
                    } else {
                        TrafficLightStatus::Unknown
                    }
                ),
                (
                    c21.max(c22),
                    if c21 < c22 {
                        TrafficLightStatus::Unknown
                    } else {
                        want21
                    }
                )
            ],
            "step {k}"
        );
    }
    for tr in &sc.tracks {
        let s = &ex["track_sizes"][&tok[&tr.id]];
        assert_eq!(
            (tr.length, tr.width, tr.height),
            (f(&s[0]), f(&s[1]), f(&s[2]))
        );
    }
    let class = |n: &str| sc.tracks.iter().find(|t| tok[&t.id] == n).unwrap().class;
    use b2dr::scene::ObjectClass::*;
    assert_eq!(
        [class("car"), class("ped"), class("bike"), class("cone")],
        [Vehicle, Pedestrian, Bicycle, TrafficCone]
    );
    // Cameras: 8 channels in rig order, calibration as pickled.
    let names: Vec<&str> = sc.rig.cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, nuplan::CAMERAS);
    nuplan_fixture::assert_cameras(sc, &ex, "hand-written fixture");
    for cam in &sc.rig.cameras {
        assert_eq!((cam.width, cam.height), (64, 36), "{}", cam.name);
    }
    // Frames: one per step, 8 images each, each image within 35 ms of its step and at its file.
    assert_eq!(sc.rig.frames.len(), 201);
    for (k, fr) in sc.rig.frames.iter().enumerate() {
        assert_eq!(fr.timestamp_us, k as i64 * 100_000);
        assert_eq!(fr.images.len(), 8);
        for im in &fr.images {
            assert!((im.timestamp_us - fr.timestamp_us).abs() <= 35_000);
            assert!(Path::new(&im.path).is_file(), "{}", im.path);
        }
        // Image ego poses are the lidar sweep's ego pose (the fixture's images share it).
        assert!(fr.images[0].ego2global.abs_diff_eq(fr.ego2global, 1e-9));
    }
    eprintln!(
        "nuPlan round trip: 201 steps, {} tracks, {} frames x 8 images, map of {} lanes / connectors",
        sc.tracks.len(),
        sc.rig.frames.len(),
        sc.map.lanes.len()
    );
}

/// SCENARIO_TOKEN = the tagged lidar_pc at t = 4 s: the window runs 15 s from t = 1 s (150 steps).
#[test]
fn scenario_tag_window() {
    let Some(root) = root() else { return };
    let ex = expected(root);
    let tag = &ex["scenario_tags"][1];
    assert!((f(&tag["t"]) - 4.0).abs() < 1e-9);
    let token = tag["lidar_pc"].as_str().unwrap();
    let log = nuplan::load_log(&spec(&db_path(root), Some(token))).unwrap();
    let sc = &log.scenario;
    assert_eq!(sc.len(), 150);
    assert_eq!(log.t0_us, ex["t0_us"].as_i64().unwrap() + 1_000_000);
    let e0 = &ex["steps"][10]["ego"];
    assert!((sc.ego[0].rear_axle.x - f(&e0[0])).abs() < 1e-6);
    assert!(log
        .tags
        .iter()
        .any(|(t, ty)| t == token && ty == "following_lane_with_lead"));
    assert_eq!(sc.rig.frames.len(), 150);
    // A token that is no lidar_pc.
    let e = format!(
        "{:#}",
        nuplan::load(&spec(&db_path(root), Some("00000000000000aa"))).unwrap_err()
    );
    assert!(e.contains("no lidar_pc has token 00000000000000aa"), "{e}");
}

/// Lanes, connectors (exit / entry lane fids), lane groups as roadblocks, the route of the logged ego and the
/// drivable area (lane groups, lane group connectors, the carpark with its hole).
#[test]
fn map_gives_route_and_drivable_area() {
    let Some(root) = root() else { return };
    let sc = nuplan::load(&spec(&db_path(root), None)).unwrap();
    let m = &sc.map;
    let ids = |v: &[usize]| -> Vec<String> { v.iter().map(|&i| m.lanes[i].id.clone()).collect() };
    let l11 = &m.lanes[m.lane_index("11").unwrap()];
    assert_eq!(l11.kind, LaneKind::Lane);
    assert_eq!(ids(&l11.successors), vec!["21"]);
    let c21 = &m.lanes[m.lane_index("21").unwrap()];
    assert_eq!(c21.kind, LaneKind::Connector);
    assert_eq!(ids(&c21.successors), vec!["31"]);
    assert_eq!(ids(&c21.predecessors), vec!["11"]);
    assert!(c21.has_traffic_light);
    assert_eq!(c21.stop_lines.len(), 1);
    assert!(l11
        .speed_limit_mps
        .is_some_and(|v| (v - 13.4112).abs() < 1e-9));
    assert_eq!(m.roadblocks[l11.roadblock].id, "1");
    assert_eq!(m.roadblocks[l11.roadblock].lanes.len(), 2);
    assert_eq!(m.roadblocks[c21.roadblock].id, "2");
    // the route of the log's two scenes ("1 2 3", "3 7"; 7 lies beyond the map), the lanes the ego drives
    assert_eq!(sc.route.roadblock_ids, vec!["1", "2", "3", "7"]);
    assert_eq!(sc.route.lane_ids, vec!["11", "21", "31"]);
    assert_eq!(m.crosswalks.len(), 1);
    assert_eq!(m.intersections.len(), 1);
    let (x0, y0) = (664_400.0, 3_996_800.0);
    for e in &sc.ego {
        assert!(m.in_drivable_area(e.rear_axle.pos()));
    }
    assert!(m.in_drivable_area(DVec2::new(x0 + 110.0, y0 + 4.0))); // lane group connector
    assert!(m.in_drivable_area(DVec2::new(x0 + 25.0, y0 + 10.0))); // carpark
    assert!(!m.in_drivable_area(DVec2::new(x0 + 35.0, y0 + 17.0))); // its hole
    assert!(!m.in_drivable_area(DVec2::new(x0 + 50.0, y0 - 20.0)));
    assert!(m.is_in_intersection(DVec2::new(x0 + 110.0, y0)));
}

/// The one scenario folder of an output folder (its name is the scenario name made file-safe).
fn only_subdir(out: &Path) -> PathBuf {
    let dirs: Vec<PathBuf> = std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir())
        .collect();
    assert_eq!(dirs.len(), 1, "{dirs:?}");
    dirs[0].clone()
}

/// A map stored in EPSG:4326 (longitude, latitude; the meta layer's projectedCoordSystem epsg:32611) is projected
/// to UTM: lanes, connectors, crosswalk and route equal those of the UTM map within 1e-6 m.
#[test]
fn lonlat_map_is_projected_to_utm() {
    let Some(root) = root() else { return };
    let Some(ll) = write_fixture("lonlat", &["--lonlat", "--png", "--seconds", "4"]) else {
        return;
    };
    let a = nuplan::load(&spec(&db_path(root), None)).unwrap();
    let b = nuplan::load(&spec(&db_path(&ll), None)).unwrap();
    assert_eq!(a.map.lanes.len(), b.map.lanes.len());
    let mut worst = 0f64;
    for la in &a.map.lanes {
        let lb = &b.map.lanes[b.map.lane_index(&la.id).unwrap()];
        assert_eq!(la.centre.points.len(), lb.centre.points.len());
        for (p, q) in la.centre.points.iter().zip(&lb.centre.points) {
            worst = worst.max(p.distance(*q));
        }
        for (p, q) in la.polygon.iter().zip(&lb.polygon) {
            worst = worst.max(p.distance(*q));
        }
    }
    for (p, q) in a.map.crosswalks[0]
        .polygon
        .iter()
        .zip(&b.map.crosswalks[0].polygon)
    {
        worst = worst.max(p.distance(*q));
    }
    assert!(worst < 1e-6, "{worst} m");
    assert_eq!(b.route.roadblock_ids, vec!["1", "2", "3", "7"]); // the scenes' routes
    assert_eq!(b.route.lane_ids, vec!["11"]); // 4 s: the ego stays in lane 11
    eprintln!("lon / lat map projected to UTM: largest difference {worst:.2e} m");
    let _ = std::fs::remove_dir_all(&ll);
}

fn b2dr() -> Command {
    Command::new(env!("CARGO_BIN_EXE_b2dr"))
}

#[test]
fn sim_runs_on_a_nuplan_log() {
    let Some(root) = root() else { return };
    let out = std::env::temp_dir().join(format!("b2dr_nuplan_sim_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let scenario = format!("nuplan:{}", db_path(root).display());
    let o = b2dr()
        .args(["sim", "--scenario", &scenario, "--planner", "expert"])
        .args([
            "--agents",
            "idm",
            "--steps",
            "30",
            "--bev-every",
            "0",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let dir = only_subdir(&out);
    let trace = std::fs::read_to_string(dir.join("trace.jsonl")).unwrap();
    assert_eq!(trace.lines().count(), 31);
    let m: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("metrics.json")).unwrap()).unwrap();
    assert!(m["failure"].is_null(), "{m}");
    let score = m["score"].as_f64().unwrap();
    eprintln!("b2dr sim --planner expert on the nuPlan fixture (30 steps): score {score:.3}");
    assert!(score > 0.5, "expert score {score}");
    let _ = std::fs::remove_dir_all(&out);
}

/// `b2dr run --renderer log-replay`: the planner sees the recorded images of sensor_blobs.
#[test]
fn log_replay_uses_the_recorded_images() {
    use b2dr::eval::run::{run, RendererMode, RunConfig};
    let Some(root) = root() else { return };
    let sc = nuplan::load(&spec(&db_path(root), None)).unwrap();
    let out = std::env::temp_dir().join(format!("b2dr_nuplan_lr_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let cfg = RunConfig {
        scenario: format!("nuplan:{}", db_path(root).display()),
        renderer: RendererMode::LogReplay,
        model: None,
        planner: b2dr::sim::PlannerSpec::Expert,
        agents: b2dr::sim::AgentMode::Idm,
        controller: b2dr::sim::closed_loop::Controller::Lqr,
        steps: 4,
        planner_timeout_s: 30.0,
        planner_start_timeout_s: 300.0,
        cameras: vec!["CAM_F0".into(), "CAM_B0".into()],
        size: (18, 32),
        seed: 0,
        dtype: b2dr::tensor::DType::F32,
        gif: false,
        shard: None,
        requests: Default::default(),
    };
    run(None, &cfg, &out, false).unwrap();
    for cam in ["CAM_F0", "CAM_B0"] {
        let got = image::open(only_subdir(&out).join(format!("frames/0000_{cam}.png")))
            .unwrap()
            .to_rgb8();
        let src = image::open(&sc.rig.frames[0].image(cam).unwrap().path)
            .unwrap()
            .to_rgb8();
        // the fixture's lenses are distorted (k1 -0.35): the frame is the undistorted image, resized
        let c = sc.rig.camera(cam).unwrap();
        assert!(c.is_distorted());
        let (w0, h0) = src.dimensions();
        let und = image::RgbImage::from_raw(
            w0,
            h0,
            c.rescaled(w0, h0)
                .undistort_image(src.as_raw(), w0 as usize, h0 as usize),
        )
        .unwrap();
        let want = image::imageops::resize(&und, 32, 18, image::imageops::FilterType::Triangle);
        let plain = image::imageops::resize(&src, 32, 18, image::imageops::FilterType::Triangle);
        assert_ne!(want, plain, "{cam}: undistorting changed nothing");
        assert_eq!(got.into_raw(), want.into_raw(), "{cam}");
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// Copies the fixture's DB and map into a fresh folder, applies `edit` to (db, map) connections, returns the
/// load error.
fn broken(name: &str, edit: impl FnOnce(&rusqlite::Connection, &rusqlite::Connection)) -> String {
    let e = format!(
        "{:#}",
        edited(name, edit, nuplan::load).expect_err("a broken input must fail")
    );
    e
}

/// Copies the fixture's DB and map into a fresh folder, applies `edit` to (db, map) connections and returns what
/// `load` gives on the copy (the images stay in the fixture's sensor_blobs).
fn edited<T>(
    name: &str,
    edit: impl FnOnce(&rusqlite::Connection, &rusqlite::Connection),
    load: impl FnOnce(&NuplanSpec) -> anyhow::Result<T>,
) -> anyhow::Result<T> {
    let root = root().unwrap();
    let ex = expected(root);
    let dst =
        std::env::temp_dir().join(format!("b2dr_nuplan_broken_{name}_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dst);
    let map_rel = format!(
        "maps/{}/{}/map.gpkg",
        ex["map_name"].as_str().unwrap(),
        ex["map_version"].as_str().unwrap()
    );
    let manifest_rel = format!("maps/{}.json", ex["maps_manifest"].as_str().unwrap());
    std::fs::create_dir_all(dst.join(&map_rel).parent().unwrap()).unwrap();
    std::fs::copy(root.join(&map_rel), dst.join(&map_rel)).unwrap();
    std::fs::copy(root.join(&manifest_rel), dst.join(&manifest_rel)).unwrap();
    let db = dst.join("log.db");
    std::fs::copy(db_path(root), &db).unwrap();
    {
        let a = rusqlite::Connection::open(&db).unwrap();
        let b = rusqlite::Connection::open(dst.join(&map_rel)).unwrap();
        // The fixture declares the devkit's foreign keys; the edits break them on purpose.
        a.execute_batch("PRAGMA foreign_keys = OFF").unwrap();
        b.execute_batch("PRAGMA foreign_keys = OFF").unwrap();
        edit(&a, &b);
    }
    let r = load(&NuplanSpec {
        sensor_root: Some(root.join("nuplan-v1.1/sensor_blobs")),
        ..spec(&db, None)
    });
    let _ = std::fs::remove_dir_all(&dst);
    r
}

/// A log without camera rows (nuPlan's non-sensor splits) gets the default generated rig; id columns stored as
/// text or reals (the devkit casts them) read as the integers.
#[test]
fn log_without_cameras_and_text_ids() {
    if root().is_none() {
        return;
    }
    let sc = edited(
        "nocam",
        |db, map| {
            db.execute_batch("DELETE FROM image; DELETE FROM camera").unwrap();
            map.execute_batch(
                "UPDATE lanes_polygons SET lane_group_fid = CAST(lane_group_fid AS TEXT); \
                 UPDATE baseline_paths SET lane_fid = CAST(lane_fid AS REAL) WHERE lane_fid IS NOT NULL",
            )
            .unwrap();
        },
        nuplan::load,
    )
    .unwrap();
    assert_eq!(sc.rig.cameras.len(), 6);
    assert!(sc.rig.frames[0].images[0].path.starts_with("builtin://"));
    assert_eq!(sc.route.roadblock_ids, vec!["1", "2", "3", "7"]);
    // Without the image table at all, too.
    let sc = edited(
        "noimage",
        |db, _| db.execute_batch("DROP TABLE image").unwrap(),
        nuplan::load,
    )
    .unwrap();
    assert!(sc.rig.frames[0].images[0].path.starts_with("builtin://"));
}

#[test]
fn malformed_inputs_give_clear_errors() {
    if root().is_none() {
        return;
    }
    let check = |e: &str, parts: &[&str]| {
        for p in parts {
            assert!(e.contains(p), "error {e:?} lacks {p:?}");
        }
        eprintln!("{e}");
    };
    let e = broken("table", |db, _| {
        db.execute_batch("DROP TABLE lidar_box").unwrap()
    });
    check(&e, &["log.db", "table `lidar_box` is missing"]);
    let e = broken("column", |db, _| {
        db.execute_batch("ALTER TABLE ego_pose DROP COLUMN qz")
            .unwrap()
    });
    check(&e, &["table `ego_pose` has no column `qz`"]);
    let e = broken("type", |db, _| {
        db.execute_batch("UPDATE lidar_box SET x = 'abc' WHERE rowid = 7")
            .unwrap()
    });
    check(
        &e,
        &[
            "table `lidar_box` row token ",
            "column `x`",
            "expected a finite number",
            "\"abc\"",
        ],
    );
    let e = broken("dangling", |db, _| {
        db.execute_batch("UPDATE lidar_pc SET ego_pose_token = X'00000000000000ff' WHERE rowid = 3")
            .unwrap()
    });
    check(
        &e,
        &[
            "table `lidar_pc` row token ",
            "column `ego_pose_token`",
            "00000000000000ff",
            "dangling",
        ],
    );
    let e = broken("track", |db, _| {
        db.execute_batch("UPDATE lidar_box SET track_token = X'00000000000000ee' WHERE rowid = 1")
            .unwrap()
    });
    check(&e, &["table `lidar_box` row token ", "`track`", "dangling"]);
    let e = broken("pickle", |db, _| {
        db.execute_batch("UPDATE camera SET intrinsic = X'8004ff2e' WHERE channel = 'CAM_L1'")
            .unwrap()
    });
    check(
        &e,
        &[
            "table `camera` row token ",
            "column `intrinsic`",
            "pickle",
            "0xff",
        ],
    );
    // a lens model of 3 coefficients (pickled [1, 2, 3])
    let e = broken("distortion", |db, _| {
        db.execute_batch(
            "UPDATE camera SET distortion = X'80025d7100284b014b024b03652e' WHERE channel = 'CAM_R0'",
        )
        .unwrap()
    });
    check(
        &e,
        &[
            "table `camera` row token ",
            "column `distortion`",
            "3 coefficients",
        ],
    );
    let e = broken("pickle_short", |db, _| {
        db.execute_batch(
            "UPDATE camera SET translation = substr(translation, 1, 12) WHERE channel = 'CAM_F0'",
        )
        .unwrap()
    });
    check(
        &e,
        &[
            "table `camera` row token ",
            "column `translation`",
            "truncated",
        ],
    );
    let e = broken("light", |db, _| {
        db.execute_batch("UPDATE traffic_light_status SET status = 'purple' WHERE rowid = 2")
            .unwrap()
    });
    check(
        &e,
        &["table `traffic_light_status` row token ", "\"purple\""],
    );
    let e = broken("wkb", |_, m| {
        m.execute_batch("UPDATE baseline_paths SET geom = substr(geom, 1, 40) WHERE fid = 1011")
            .unwrap()
    });
    check(
        &e,
        &[
            "map.gpkg",
            "table `baseline_paths` row fid 1011",
            "column `geom`",
            "WKB",
        ],
    );
    let e = broken("gp", |_, m| {
        m.execute_batch("UPDATE lanes_polygons SET geom = X'00010203' WHERE fid = 12")
            .unwrap()
    });
    check(&e, &["table `lanes_polygons` row fid 12", "GP"]);
    let e = broken("maplayer", |_, m| {
        m.execute_batch("DROP TABLE lane_connectors").unwrap()
    });
    check(&e, &["map.gpkg", "table `lane_connectors` is missing"]);
    let e = broken("log", |db, _| db.execute_batch("DELETE FROM log").unwrap());
    check(&e, &["table `log` is empty"]);
    // Not a database, no map.
    let dir = std::env::temp_dir().join(format!("b2dr_nuplan_junk_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(
        dir.join("junk.db"),
        b"this is not sqlite, just some text that is long enough",
    )
    .unwrap();
    let e = format!(
        "{:#}",
        nuplan::load(&spec(&dir.join("junk.db"), None)).unwrap_err()
    );
    check(&e, &["junk.db", "not a readable SQLite database"]);
    std::fs::copy(db_path(root().unwrap()), dir.join("log.db")).unwrap();
    let e = format!(
        "{:#}",
        nuplan::load(&spec(&dir.join("log.db"), None)).unwrap_err()
    );
    check(
        &e,
        &[
            "table `log` row token ",
            "column `map_version`",
            "maps manifest nuplan-maps-v1.0.json",
            "NUPLAN_MAPS_ROOT",
        ],
    );
    let e = format!(
        "{:#}",
        nuplan::load(&spec(&dir.join("missing.db"), None)).unwrap_err()
    );
    check(&e, &["missing.db", "no such file"]);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Import time of the 20 s log with its camera index (401 lidar_pc, 1608 images, map): printed, not asserted.
#[test]
fn import_speed() {
    let Some(root) = root() else { return };
    let s = spec(&db_path(root), None);
    let mut times = vec![];
    for _ in 0..3 {
        let t = Instant::now();
        let sc = nuplan::load(&s).unwrap();
        times.push(t.elapsed().as_secs_f64());
        assert_eq!(sc.rig.frames.len(), 201);
    }
    times.sort_by(f64::total_cmp);
    eprintln!(
        "nuPlan import of a 20 s log (401 lidar_pc, 1608 images, 8 cameras, GeoPackage map): median {:.3} s, \
         fastest {:.3} s ({} build)",
        times[1],
        times[0],
        if cfg!(debug_assertions) { "debug" } else { "release" }
    );
}

/// A GeoPackage LineString blob (little endian, no envelope) through `pts`.
fn gpkg_line(pts: &[(f64, f64)]) -> Vec<u8> {
    let mut b = b"GP\x00\x01".to_vec();
    b.extend(0i32.to_le_bytes());
    b.push(1);
    b.extend(2u32.to_le_bytes());
    b.extend((pts.len() as u32).to_le_bytes());
    for (x, y) in pts {
        b.extend(x.to_le_bytes());
        b.extend(y.to_le_bytes());
    }
    b
}

/// Hostile and careless values (issue #18) are refused by the bounds every importer applies
/// (`src/scene/import/bounds.rs`), each error naming the file, the table, the row and the column.
#[test]
fn hostile_values_are_refused() {
    if root().is_none() {
        return;
    }
    let check = |e: &str, parts: &[&str]| {
        for p in parts {
            assert!(e.contains(p), "error {e:?} lacks {p:?}");
        }
        eprintln!("{e}");
    };
    let cases: Vec<(&str, &str, &[&str])> = vec![
        (
            "UPDATE ego_pose SET x = 1e12 WHERE rowid = 5",
            "",
            &["table `ego_pose` row token ", "column `x`", "beyond 1e8"],
        ),
        (
            "UPDATE ego_pose SET vy = -1e7 WHERE rowid = 5",
            "",
            &["table `ego_pose` row token ", "column `vy`", "m/s"],
        ),
        (
            "UPDATE ego_pose SET qw = 1e300, qx = 1e300 WHERE rowid = 1",
            "",
            &[
                "table `ego_pose` row token ",
                "qw, qx, qy, qz",
                "not a rotation",
            ],
        ),
        (
            "UPDATE lidar_box SET y = -3e9 WHERE rowid = 3",
            "",
            &["table `lidar_box` row token ", "column `y`"],
        ),
        (
            "UPDATE lidar_box SET yaw = 1e9 WHERE rowid = 3",
            "",
            &["table `lidar_box` row token ", "column `yaw`", "rad"],
        ),
        (
            "UPDATE track SET width = 1e5 WHERE rowid = 1",
            "",
            &["table `track` row token ", "width", "1000 m"],
        ),
        (
            "UPDATE lidar_pc SET timestamp = 9223372036854775807 WHERE rowid = 9",
            "",
            &["table `lidar_pc` row token ", "column `timestamp`"],
        ),
        (
            "UPDATE log SET map_version = '../../etc'",
            "",
            &[
                "table `log` row token ",
                "column `map_version`",
                "plain name",
            ],
        ),
        (
            "UPDATE camera SET width = 1000000 WHERE channel = 'CAM_R1'",
            "",
            &["table `camera` row token ", "width, height", "16384"],
        ),
        (
            "UPDATE camera SET channel = 'a/b' WHERE channel = 'CAM_R1'",
            "",
            &["table `camera` row token ", "column `channel`"],
        ),
        (
            // LONG_BINPUT 0xffffffff: the memo would be sized from a 4-byte field
            "UPDATE camera SET rotation = X'80045d72ffffffff2e' WHERE channel = 'CAM_F0'",
            "",
            &[
                "table `camera` row token ",
                "column `rotation`",
                "memo key 4294967295",
            ],
        ),
        (
            "UPDATE image SET filename_jpg = '../../../etc/passwd' WHERE rowid = 4",
            "",
            &[
                "table `image` row token ",
                "column `filename_jpg`",
                "relative path",
            ],
        ),
        (
            "",
            "UPDATE lanes_polygons SET speed_limit_mps = -4 WHERE fid = 12",
            &[
                "map.gpkg",
                "table `lanes_polygons` row fid 12",
                "speed_limit_mps",
            ],
        ),
    ];
    for (i, (db_sql, map_sql, parts)) in cases.into_iter().enumerate() {
        let e = broken(&format!("hostile{i}"), |db, map| {
            if !db_sql.is_empty() {
                db.execute_batch(db_sql).unwrap();
            }
            if !map_sql.is_empty() {
                map.execute_batch(map_sql).unwrap();
            }
        });
        check(&e, parts);
    }
    // A map geometry with a point beyond the coordinate bound (and one that is NaN).
    for (k, bad) in [(1e12, 0.0), (f64::NAN, 1.0)].into_iter().enumerate() {
        let e = broken(&format!("hostile_geom{k}"), |_, map| {
            let (x0, y0) = (664_400.0, 3_996_800.0);
            map.execute(
                "UPDATE baseline_paths SET geom = ?1 WHERE fid = 1011",
                [gpkg_line(&[(x0, y0), bad])],
            )
            .unwrap();
        });
        check(
            &e,
            &[
                "map.gpkg",
                "table `baseline_paths` row fid 1011",
                "column `geom`",
                "not finite or lies beyond",
            ],
        );
    }
}

/// The route and mission goal come from the `scene` rows as the devkit reads them (issue #17): a scenario
/// token's lidar_pc -> its scene's space-separated `roadblock_ids` and `goal_ego_pose_token`; the whole log
/// concatenates its scenes' routes. Without a `scene` table, or with NULL `roadblock_ids`, the roadblocks the
/// logged ego drives through; hostile ids and a dangling goal are errors naming the scene row.
#[test]
fn route_and_goal_come_from_the_scene_table() {
    let Some(root) = root() else { return };
    let ex = expected(root);
    let db = db_path(root);
    let scenes = ex["scenes"].as_array().unwrap();
    let goal = |k: usize| -> [f64; 3] {
        let g = &scenes[k]["goal"];
        [f(&g[0]), f(&g[1]), f(&g[2])]
    };
    let same = |p: Option<b2dr::scene::geometry::Pose2>, g: [f64; 3]| {
        let p = p.expect("a goal");
        assert!(
            (p.x - g[0]).abs() < 1e-6
                && (p.y - g[1]).abs() < 1e-6
                && (p.heading - g[2]).abs() < 1e-9,
            "{p:?} vs {g:?}"
        );
    };
    let whole = nuplan::load_log(&spec(&db, None)).unwrap();
    assert_eq!(whole.scenario.route.roadblock_ids, vec!["1", "2", "3", "7"]);
    same(whole.scenario.route.mission_goal, goal(1));
    // the second scene's first lidar_pc: its scene only (the ego drives 1, 2, 3 in that window)
    let second = scenes[1]["first_lidar_pc"].as_str().unwrap();
    let w = nuplan::load_log(&spec(&db, Some(second))).unwrap();
    assert_eq!(w.scenario.route.roadblock_ids, vec!["3", "7"]);
    assert_eq!(w.scenario.route.lane_ids, vec!["11", "21", "31"]);
    same(w.scenario.route.mission_goal, goal(1));
    // a tag in the first scene
    let tag = ex["scenario_tags"][0]["lidar_pc"].as_str().unwrap();
    let w = nuplan::load_log(&spec(&db, Some(tag))).unwrap();
    assert_eq!(w.scenario.route.roadblock_ids, vec!["1", "2", "3"]);
    same(w.scenario.route.mission_goal, goal(0));
    // no scene table / no roadblock ids: the roadblocks the logged ego drives through
    let noscene = edited(
        "noscene",
        |db, _| db.execute_batch("DROP TABLE scene").unwrap(),
        nuplan::load_log,
    )
    .unwrap();
    assert_eq!(noscene.scenario.route.roadblock_ids, vec!["1", "2", "3"]);
    assert!(noscene.scenario.route.mission_goal.is_none());
    let null = edited(
        "nullroute",
        |db, _| {
            db.execute_batch("UPDATE scene SET roadblock_ids = NULL")
                .unwrap()
        },
        nuplan::load,
    )
    .unwrap();
    assert_eq!(null.route.roadblock_ids, vec!["1", "2", "3"]);
    // hostile: 20000 ids, a dangling goal
    let e = broken("manyids", |db, _| {
        let ids: Vec<String> = (0..20_000).map(|i| i.to_string()).collect();
        db.execute("UPDATE scene SET roadblock_ids = ?1", [ids.join(" ")])
            .unwrap();
    });
    assert!(
        e.contains("table `scene` row token ") && e.contains("column `roadblock_ids`"),
        "{e}"
    );
    let e = broken("goal", |db, _| {
        db.execute_batch("UPDATE scene SET goal_ego_pose_token = X'00000000000000ff'")
            .unwrap()
    });
    assert!(
        e.contains("table `scene` row token ")
            && e.contains("column `goal_ego_pose_token`")
            && e.contains("dangling"),
        "{e}"
    );
}

/// `config.json` fingerprints the log DB and its map (for `--resume`, issue #18); a log that cannot be read is
/// recorded as unreadable and fails on its own (score 0, counted in `failures`), not the whole batch.
#[test]
fn inputs_are_fingerprinted_and_a_missing_log_fails_alone() {
    let Some(root) = root() else { return };
    let out = std::env::temp_dir().join(format!("b2dr_nuplan_inputs_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let db = db_path(root);
    let missing = root.join("missing.db");
    let scenario = format!("nuplan:{},nuplan:{}", db.display(), missing.display());
    let o = b2dr()
        .args(["sim", "--scenario", &scenario, "--planner", "cv"])
        .args([
            "--agents",
            "none",
            "--steps",
            "5",
            "--bev-every",
            "0",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let s: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(s["failures"].as_u64(), Some(1), "{s}");
    let cfg: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("config.json")).unwrap()).unwrap();
    let inputs = cfg["input_files"].as_object().unwrap();
    let d = &inputs[&db.display().to_string()];
    assert_eq!(
        d["size"].as_u64(),
        Some(std::fs::metadata(&db).unwrap().len())
    );
    assert!(inputs.keys().any(|k| k.ends_with("map.gpkg")), "{cfg}");
    assert!(
        inputs[&missing.display().to_string()]["unreadable"]
            .as_str()
            .is_some_and(|e| e.contains("no such file")),
        "{cfg}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// The rig's lidar2ego comes from the log's `lidar` row (the fixture's MergedPointCloud: 1.5 m ahead, 1.8 m up,
/// identity rotation); a log without cameras keeps it; a log without a `lidar` table gets the nominal nuScenes
/// mounting (issue #34).
#[test]
fn lidar2ego_comes_from_the_lidar_table() {
    let Some(root) = root() else { return };
    let want = glam::DMat4::from_translation(glam::DVec3::new(1.5, 0.0, 1.8));
    let sc = nuplan::load(&spec(&db_path(root), None)).unwrap();
    assert!(
        sc.rig.lidar2ego.abs_diff_eq(want, 1e-12),
        "{}",
        sc.rig.lidar2ego
    );
    let nocam = edited(
        "lidar_nocam",
        |db, _| {
            db.execute_batch("DELETE FROM image; DELETE FROM camera")
                .unwrap()
        },
        nuplan::load,
    )
    .unwrap();
    assert!(nocam.rig.lidar2ego.abs_diff_eq(want, 1e-12));
    let nolidar = edited(
        "nolidar",
        |db, _| db.execute_batch("DROP TABLE lidar").unwrap(),
        nuplan::load,
    )
    .unwrap();
    assert_eq!(
        nolidar.rig.lidar2ego,
        b2dr::scene::camera::nuscenes_lidar2ego()
    );
    // a hostile calibration is refused naming the column
    let e = broken("lidar_bad", |db, _| {
        db.execute_batch("UPDATE lidar SET rotation = x'00'")
            .unwrap();
    });
    assert!(
        e.contains("table `lidar`") && e.contains("column `rotation`"),
        "{e}"
    );
}
