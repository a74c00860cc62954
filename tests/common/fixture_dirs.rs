//! Temporary fixture folders written by the Python reference modules (nuPlan and nuScenes fixtures): the
//! interpreter to run and the clean-up of folders left by earlier test processes. Included with `#[path]` by
//! tests that need no Vulkan context (`tests/common/mod.rs` holds the device helpers).
#![allow(dead_code)]
use std::path::{Path, PathBuf};

/// The Python that writes fixtures: $B2DR_PY, else the cached virtualenv of tools/ensure-python.sh, else
/// python3.
pub fn python() -> String {
    if let Ok(p) = std::env::var("B2DR_PY") {
        return p;
    }
    let venv = std::env::var("HOME")
        .map(|h| PathBuf::from(h).join(".cache/b2dr-venv/bin/python"))
        .unwrap_or_default();
    if venv.is_file() {
        venv.display().to_string()
    } else {
        "python3".into()
    }
}

/// Removes fixtures of earlier test processes that have ended (`<prefix><name>_<pid>` in the temporary
/// folder whose /proc/<pid> is gone; nothing is removed where /proc does not exist): a fixture outlives its
/// process, since the tests of that process share it.
pub fn remove_stale_fixtures(prefix: &str) {
    if !Path::new("/proc/self").exists() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(pid) = name
            .strip_prefix(prefix)
            .and_then(|r| r.rsplit('_').next())
            .and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}
