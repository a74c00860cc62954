//! The nuPlan test fixture: a log DB, GeoPackage map and sensor_blobs folder written at test time from a known
//! hand-made scenario by `python/b2dr_ref/nuplan_fixture.py` (standard library + numpy; `B2DR_PY`, the test
//! virtualenv or `python3`). `tests/scene_nuplan.rs` has its own copy of the writer call (with its stale-folder
//! cleanup); this one serves other test files.
#![allow(dead_code)]
use std::path::{Path, PathBuf};
use std::process::Command;

use b2dr::scene::import::nuplan::NuplanSpec;
use b2dr::scene::Scenario;
use glam::{DMat3, DMat4, DQuat, DVec3};
use serde_json::Value;

// the including test crate declares `fixture_dirs` (tests/common/fixture_dirs.rs) at its root
use crate::fixture_dirs::python;

/// The fixture written into `out` (`extra`: more arguments of the writer); None (reason printed) without
/// Python / numpy.
pub fn write_fixture(out: &Path, extra: &[&str]) -> Option<Fixture> {
    let _ = std::fs::remove_dir_all(out);
    let o = Command::new(python())
        .current_dir(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python"))
        .args(["-m", "b2dr_ref.nuplan_fixture", "--png", "--out"])
        .arg(out)
        .args(extra)
        .output();
    match o {
        Ok(o) if o.status.success() => {
            let ex: Value =
                serde_json::from_str(&std::fs::read_to_string(out.join("expected.json")).ok()?)
                    .ok()?;
            let map = PathBuf::from(ex["map"].as_str()?);
            Some(Fixture {
                root: out.to_path_buf(),
                db: PathBuf::from(ex["db"].as_str()?),
                map,
                sensor_root: out.join("nuplan-v1.1/sensor_blobs"),
                expected: ex,
            })
        }
        Ok(o) => {
            eprintln!(
                "skipping: the nuPlan fixture writer failed: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            None
        }
        Err(e) => {
            eprintln!("skipping: no Python to write the nuPlan fixture ({e})");
            None
        }
    }
}

pub struct Fixture {
    pub root: PathBuf,
    pub db: PathBuf,
    pub map: PathBuf,
    pub sensor_root: PathBuf,
    pub expected: Value,
}

impl Fixture {
    /// The whole log, maps found beside the DB, images in the fixture's sensor_blobs.
    pub fn spec(&self, token: Option<&str>) -> NuplanSpec {
        NuplanSpec {
            db: self.db.clone(),
            token: token.map(str::to_string),
            maps_root: None,
            map_version: b2dr::scene::import::nuplan::maps_db::DEFAULT_MAP_VERSION.to_string(),
            sensor_root: Some(self.sensor_root.clone()),
        }
    }
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

/// The cameras equal the calibration the fixture pickled (1e-9).
pub fn assert_cameras(sc: &Scenario, ex: &Value, form: &str) {
    assert_eq!(sc.rig.cameras.len(), 8, "{form}");
    for c in ex["cameras"].as_array().unwrap() {
        let cam = sc.rig.camera(c["channel"].as_str().unwrap()).unwrap();
        let k: Vec<f64> = c["intrinsic"]
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|r| r.as_array().unwrap().iter().map(num).collect::<Vec<_>>())
            .collect();
        let want_k =
            DMat3::from_cols_array(&[k[0], k[3], k[6], k[1], k[4], k[7], k[2], k[5], k[8]]);
        assert!(
            cam.intrinsic.abs_diff_eq(want_k, 1e-9),
            "{form} {}",
            cam.name
        );
        let (q, t) = (&c["rotation"], &c["translation"]);
        let want = DMat4::from_rotation_translation(
            DQuat::from_xyzw(num(&q[1]), num(&q[2]), num(&q[3]), num(&q[0])).normalize(),
            DVec3::new(num(&t[0]), num(&t[1]), num(&t[2])),
        );
        assert!(cam.cam2ego.abs_diff_eq(want, 1e-9), "{form} {}", cam.name);
        let d: Vec<f64> = c["distortion"]
            .as_array()
            .unwrap()
            .iter()
            .map(num)
            .collect();
        assert_eq!(cam.distortion.to_vec(), d, "{form} {}", cam.name);
    }
}
