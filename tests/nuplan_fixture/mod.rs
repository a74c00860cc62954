//! The nuPlan test fixture: a log DB, GeoPackage map and sensor_blobs folder written at test time from a known
//! hand-made scenario by `python/b2dr_ref/nuplan_fixture.py` (standard library + numpy; `B2DR_PY`, the test
//! virtualenv or `python3`). `tests/scene_nuplan.rs` has its own copy of the writer call (with its stale-folder
//! cleanup); this one serves other test files.
#![allow(dead_code)]
use std::path::{Path, PathBuf};
use std::process::Command;

use b2dr::scene::import::nuplan::NuplanSpec;
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
