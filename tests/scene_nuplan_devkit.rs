//! nuPlan data written and laid out the way motional/nuplan-devkit writes the real dataset (issue #35), by
//! `python/b2dr_ref/nuplan_fixture.py`:
//! - calibration: the devkit's `SimplePickleType.process_bind_param` (`pickle.dumps(value)`,
//!   nuplan/database/common/sql_types.py) of its own `nuplan.database.common.data_types` classes `Translation`,
//!   `Rotation`, `CameraIntrinsic` (vendored unmodified in python/tests/fixtures/nuplan_devkit), with Python's
//!   default protocol and with protocols 0 and 2; `camera.distortion` a `PickleType` list; and the hand-written
//!   forms other writers produce (plain lists, numpy arrays);
//! - maps: `GPKGMapsDB`'s layout (nuplan/database/maps_db/gpkg_mapsdb.py), the manifest
//!   `maps/nuplan-maps-v1.0.json` giving the log's `map_version` (`us-nv-las-vegas-strip`) its version
//!   (`9.15.1915`), the GeoPackage at `maps/us-nv-las-vegas-strip/9.15.1915/map.gpkg`; `log.location` is the city
//!   `las_vegas`, which names no folder.
//!
//! Skips with a printed reason when no Python with numpy is available.
use std::path::{Path, PathBuf};
use std::process::Command;

#[path = "common/fixture_dirs.rs"]
mod fixture_dirs;
mod nuplan_fixture;

use b2dr::scene::import::nuplan::{self, maps_db, NuplanSpec};
use serde_json::Value;

fn fixture(name: &str, extra: &[&str]) -> Option<nuplan_fixture::Fixture> {
    fixture_dirs::remove_stale_fixtures("b2dr_nuplan_devkit_");
    let out =
        std::env::temp_dir().join(format!("b2dr_nuplan_devkit_{name}_{}", std::process::id()));
    nuplan_fixture::write_fixture(&out, extra)
}

/// The ego rear axle of every second lidar_pc, read straight from the DB's `ego_pose` rows (x, y, yaw of the
/// quaternion), independent of the importer.
fn db_ego(db: &Path) -> Vec<(f64, f64, f64)> {
    let c = rusqlite::Connection::open(db).unwrap();
    let mut st = c
        .prepare(
            "SELECT e.x, e.y, e.qw, e.qz FROM lidar_pc p JOIN ego_pose e ON p.ego_pose_token = e.token \
             ORDER BY p.timestamp",
        )
        .unwrap();
    let rows: Vec<(f64, f64, f64, f64)> = st
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))
        .unwrap()
        .map(Result::unwrap)
        .collect();
    // The fixture's ego quaternions turn about z only: yaw = 2 atan2(qz, qw).
    rows.into_iter()
        .step_by(2)
        .map(|(x, y, qw, qz)| (x, y, 2.0 * qz.atan2(qw)))
        .collect()
}

/// The devkit-written log (default fixture: the devkit's classes, the manifest layout, maps found by searching
/// up from the DB) imports; its ego equals the DB's ego_pose to 1 cm (measured: exact to 1e-9 m), its cameras
/// the pickled calibration; and `b2dr sim` scores the expert on it.
#[test]
fn devkit_written_log_imports_and_its_ego_equals_the_db() {
    let Some(fx) = fixture("main", &["--seconds", "6"]) else {
        return;
    };
    let ex = &fx.expected;
    assert_eq!(ex["calibration"], "devkit");
    // The fixture holds the devkit's pickles: the class names its module.
    let c = rusqlite::Connection::open(&fx.db).unwrap();
    let t: Vec<u8> = c
        .query_row("SELECT translation FROM camera LIMIT 1", [], |r| r.get(0))
        .unwrap();
    let has = |b: &[u8], s: &[u8]| b.windows(s.len()).any(|w| w == s);
    assert!(has(&t, b"nuplan.database.common.data_types") && has(&t, b"Translation"));
    let (loc, mv): (String, String) = c
        .query_row("SELECT location, map_version FROM log", [], |r| {
            Ok((r.get(0)?, r.get(1)?))
        })
        .unwrap();
    assert_eq!(
        (loc.as_str(), mv.as_str()),
        ("las_vegas", "us-nv-las-vegas-strip")
    );

    let log = nuplan::load_log(&fx.spec(None)).unwrap();
    assert_eq!(log.map_path, fx.map);
    assert!(log
        .map_path
        .ends_with("maps/us-nv-las-vegas-strip/9.15.1915/map.gpkg"));
    let sc = &log.scenario;
    let want = db_ego(&fx.db);
    assert_eq!(sc.ego.len(), want.len());
    let mut worst = 0.0f64;
    for (e, (x, y, yaw)) in sc.ego.iter().zip(&want) {
        let p = e.rear_axle;
        worst = worst.max((p.x - x).hypot(p.y - y));
        assert!((p.heading - yaw).abs() < 1e-9);
    }
    assert!(worst < 0.01, "ego differs from the DB's by {worst} m");
    eprintln!(
        "devkit-written nuPlan log: {} steps, ego vs DB largest difference {worst:.1e} m",
        sc.ego.len()
    );
    nuplan_fixture::assert_cameras(sc, ex, "devkit classes, default protocol");
    assert!(sc.map.lane_index("21").is_some());

    let out = fx.root.join("sim");
    let o = Command::new(env!("CARGO_BIN_EXE_b2dr"))
        .args(["sim", "--scenario", &format!("nuplan:{}", fx.db.display())])
        .args(["--planner", "expert", "--agents", "idm", "--steps", "30"])
        .args(["--bev-every", "0", "--out"])
        .arg(&out)
        .env_remove("NUPLAN_MAPS_ROOT")
        .env_remove("NUPLAN_MAP_VERSION")
        .env("NUPLAN_SENSOR_ROOT", &fx.sensor_root)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // One folder per scenario (named after the log).
    let dir = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.is_dir())
        .unwrap();
    let m: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("metrics.json")).unwrap()).unwrap();
    assert!(m["failure"].is_null(), "{m}");
    let score = m["score"].as_f64().unwrap();
    eprintln!("b2dr sim --planner expert on the devkit-written log (30 steps): score {score:.3}");
    assert!(score > 0.5, "expert score {score}");
    let _ = std::fs::remove_dir_all(&fx.root);
}

/// Every form `list(pickle.loads(blob))` accepts imports with the same calibration: plain lists, numpy arrays,
/// and the devkit's classes under protocols 0 (text opcodes, `copy_reg._reconstructor`) and 2 (NEWOBJ +
/// APPENDS, the GLOBAL opcode).
#[test]
fn calibration_in_every_pickled_form() {
    let forms: [(&str, &[&str]); 4] = [
        ("lists", &["--calibration", "lists"]),
        ("numpy", &["--calibration", "numpy"]),
        ("devkit_p0", &["--pickle-protocol", "0"]),
        ("devkit_p2", &["--pickle-protocol", "2"]),
    ];
    for (name, args) in forms {
        let mut a = vec!["--seconds", "1"];
        a.extend_from_slice(args);
        let Some(fx) = fixture(name, &a) else { return };
        let sc = nuplan::load(&fx.spec(None)).unwrap_or_else(|e| panic!("{name}: {e:#}"));
        nuplan_fixture::assert_cameras(&sc, &fx.expected, name);
        let _ = std::fs::remove_dir_all(&fx.root);
    }
}

/// A calibration blob that is not a number array: the error names the table, the row, the column and what was
/// found (here a pickled dict subclass of data_types, `RLE`).
#[test]
fn other_pickled_objects_are_named() {
    let Some(fx) = fixture("rle", &["--seconds", "1"]) else {
        return;
    };
    // pickle.dumps(RLE({"size": [1, 2]})) with the devkit's class
    let rle: &[u8] = b"\x80\x04\x95@\x00\x00\x00\x00\x00\x00\x00\x8c!nuplan.database.common.data_types\x94\x8c\x03RLE\x94\x93\x94)\x81\x94\x8c\x04size\x94]\x94(K\x01K\x02es.";
    let c = rusqlite::Connection::open(&fx.db).unwrap();
    c.execute(
        "UPDATE camera SET intrinsic = ?1 WHERE channel = 'CAM_L0'",
        [rle],
    )
    .unwrap();
    drop(c);
    let e = format!("{:#}", nuplan::load(&fx.spec(None)).unwrap_err());
    for want in [
        "table `camera` row token ",
        "column `intrinsic`",
        "an object built by nuplan.database.common.data_types.RLE",
    ] {
        assert!(e.contains(want), "{want:?} not in: {e}");
    }
    let _ = std::fs::remove_dir_all(&fx.root);
}

fn spec_with(
    fx: &nuplan_fixture::Fixture,
    maps_root: Option<PathBuf>,
    manifest: &str,
) -> NuplanSpec {
    NuplanSpec {
        maps_root,
        map_version: manifest.to_string(),
        ..fx.spec(None)
    }
}

/// The map is found as GPKGMapsDB finds it, and each way of not finding it says what was looked for: b2dr's
/// former layout `maps/<location>/<map_version>/map.gpkg` without a manifest, a manifest without the log's map,
/// a manifest version with no folder; `NUPLAN_MAP_VERSION` (here the spec's `map_version`, and the variable
/// itself through the CLI) selects another manifest.
#[test]
fn maps_are_found_as_gpkg_mapsdb_finds_them() {
    let Some(fx) = fixture("maps", &["--seconds", "1"]) else {
        return;
    };
    let maps = fx.root.join("maps");
    let err = |s: &NuplanSpec| format!("{:#}", nuplan::load(s).unwrap_err());
    let check = |e: &str, wants: &[&str]| {
        for w in wants {
            assert!(e.contains(w), "{w:?} not in: {e}");
        }
    };
    // The former layout: location / map_version folders, no manifest.
    let old = fx.root.join("old");
    let old_map = old.join("maps/las_vegas/us-nv-las-vegas-strip/map.gpkg");
    std::fs::create_dir_all(old_map.parent().unwrap()).unwrap();
    std::fs::copy(&fx.map, &old_map).unwrap();
    let e = err(&spec_with(
        &fx,
        Some(old.join("maps")),
        maps_db::DEFAULT_MAP_VERSION,
    ));
    check(
        &e,
        &[
            "column `map_version`",
            "nuplan-maps-v1.0.json not found",
            "NUPLAN_MAP_VERSION",
        ],
    );
    // A manifest without the log's map: names it and lists the manifest's maps.
    std::fs::write(
        old.join("maps/nuplan-maps-v1.0.json"),
        r#"{"us-ma-boston": {"version": "9.12.1817"}}"#,
    )
    .unwrap();
    let e = err(&spec_with(
        &fx,
        Some(old.join("maps")),
        maps_db::DEFAULT_MAP_VERSION,
    ));
    check(
        &e,
        &["has no map \"us-nv-las-vegas-strip\"", "[us-ma-boston]"],
    );
    // A version whose folder is missing: the path looked for and the versions present.
    std::fs::write(
        old.join("maps/nuplan-maps-v1.0.json"),
        r#"{"us-nv-las-vegas-strip": {"version": "9.99.0"}}"#,
    )
    .unwrap();
    std::fs::create_dir_all(old.join("maps/us-nv-las-vegas-strip/9.15.1915")).unwrap();
    let e = err(&spec_with(
        &fx,
        Some(old.join("maps")),
        maps_db::DEFAULT_MAP_VERSION,
    ));
    check(
        &e,
        &[
            "us-nv-las-vegas-strip/9.99.0/map.gpkg not found",
            "present: [9.15.1915]",
        ],
    );
    // Another manifest (NUPLAN_MAP_VERSION) with another version of the map.
    std::fs::write(
        maps.join("nuplan-maps-v2.0.json"),
        r#"{"us-nv-las-vegas-strip": {"version": "10.0.1"}}"#,
    )
    .unwrap();
    let v2 = maps.join("us-nv-las-vegas-strip/10.0.1/map.gpkg");
    std::fs::create_dir_all(v2.parent().unwrap()).unwrap();
    std::fs::copy(&fx.map, &v2).unwrap();
    let log = nuplan::load_log(&spec_with(&fx, None, "nuplan-maps-v2.0")).unwrap();
    assert_eq!(log.map_path, v2);
    // ... through the CLI's environment: NUPLAN_MAP_VERSION is read, and a missing manifest is named.
    let sim = |manifest: &str| {
        Command::new(env!("CARGO_BIN_EXE_b2dr"))
            .args(["sim", "--scenario", &format!("nuplan:{}", fx.db.display())])
            .args(["--planner", "cv", "--agents", "none", "--steps", "3"])
            .args(["--bev-every", "0", "--out"])
            .arg(fx.root.join(format!("sim_{manifest}")))
            .env("NUPLAN_MAPS_ROOT", &maps)
            .env("NUPLAN_MAP_VERSION", manifest)
            .env("NUPLAN_SENSOR_ROOT", &fx.sensor_root)
            .output()
            .unwrap()
    };
    let o = sim("nuplan-maps-v2.0");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = sim("nuplan-maps-v9.9");
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    check(
        &e,
        &[
            "nuplan-maps-v9.9.json not found",
            "nuplan-maps-v1.0.json",
            "nuplan-maps-v2.0.json",
        ],
    );
    let _ = std::fs::remove_dir_all(&fx.root);
}
