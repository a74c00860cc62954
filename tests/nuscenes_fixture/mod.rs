//! The nuScenes test fixture: a nuScenes-mini-style DATAROOT written at test time from the shared scene-0061 data
//! by `python/b2dr_ref/nuscenes_fixture.py` (plain Python; `B2DR_PY`, the test virtualenv or `python3`).
#![allow(dead_code)]
// the including test crate declares `fixture_dirs` (tests/common/fixture_dirs.rs) at its root
use crate::fixture_dirs;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use b2dr::scene::import::nuscenes::NuscenesSpec;

pub fn shared() -> Option<PathBuf> {
    let candidates = [
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/nuscenes-mini"),
        PathBuf::from("/work/shared/data/nuscenes-mini"),
    ];
    let found = candidates
        .iter()
        .find(|p| p.join("scenes/scene-0061.json").is_file())
        .cloned();
    if found.is_none() {
        eprintln!("skipping: shared nuScenes data absent (../shared/data/nuscenes-mini)");
    }
    found
}

pub use fixture_dirs::python;

/// Writes a fixture DATAROOT (`extra`: more arguments of the writer); None (with the reason printed) when the
/// shared data or Python is absent.
pub fn write_fixture(name: &str, extra: &[&str]) -> Option<PathBuf> {
    let shared = shared()?;
    fixture_dirs::remove_stale_fixtures("b2dr_nuscenes_");
    let out = std::env::temp_dir().join(format!("b2dr_nuscenes_{name}_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let o = Command::new(python())
        .current_dir(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python"))
        .args(["-m", "b2dr_ref.nuscenes_fixture", "--shared"])
        .arg(&shared)
        .arg("--out")
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

/// The fixture DATAROOT (written once per test process).
pub fn dataroot() -> Option<&'static Path> {
    static ROOT: OnceLock<Option<PathBuf>> = OnceLock::new();
    ROOT.get_or_init(|| write_fixture("main", &[])).as_deref()
}

pub fn spec(root: &Path) -> NuscenesSpec {
    NuscenesSpec {
        dataroot: root.to_path_buf(),
        version: "v1.0-mini".into(),
        scene: "scene-0061".into(),
    }
}
