//! Where a log's map is, as motional/nuplan-devkit's `GPKGMapsDB` (nuplan/database/maps_db/gpkg_mapsdb.py)
//! finds it:
//! - the map name is the log's `map_version` column (e.g. `us-nv-las-vegas-strip`; `NuPlanMapFactory`
//!   drops a `.gpkg` suffix); `log.location` (e.g. `las_vegas`) is not part of the path;
//! - the manifest is `MAPS_ROOT/<NUPLAN_MAP_VERSION>.json` (`GPKGMapsDB.__init__`: `blob_store.get(f"{map_version}.json")`,
//!   default `nuplan-maps-v1.0`), an object whose entry per map name holds `"version"` (e.g. `9.15.1915`:
//!   `get_version(location) = str(metadata[location]["version"])`);
//! - the GeoPackage is `MAPS_ROOT/<map name>/<version>/map.gpkg` (`_get_gpkg_file_path`).
//!
//! Every failure lists what was looked for: the manifest path, the names it holds, the GeoPackage path and the
//! versions found on disk.
use crate::scene::import::bounds;
use anyhow::{anyhow, bail, Result};
use serde_json::Value;
use std::path::{Path, PathBuf};

/// The devkit's default `NUPLAN_MAP_VERSION` (its scenario builder config: `map_version: nuplan-maps-v1.0`).
pub const DEFAULT_MAP_VERSION: &str = "nuplan-maps-v1.0";
/// Largest manifest read (the devkit's holds, per map, its version and raster layer metadata: kilobytes).
pub const MAX_MANIFEST_BYTES: u64 = 16 << 20;

/// The map name of a `log.map_version` value (`NuPlanMapFactory.build_map_from_name`: `replace('.gpkg', '')`).
pub fn map_name(log_map_version: &str) -> String {
    log_map_version.replace(".gpkg", "")
}

/// `MAPS_ROOT/<map_version>.json`.
pub fn manifest_path(maps_root: &Path, map_version: &str) -> PathBuf {
    maps_root.join(format!("{map_version}.json"))
}

/// Sorted names of the entries of `dir` that pass `keep` (empty when it cannot be read), for error messages.
fn listing(dir: &Path, keep: impl Fn(&Path) -> bool) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.flatten()
                .filter(|e| keep(&e.path()))
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v.truncate(20);
    v
}

/// The version string of `map_name` in the manifest at `path` (`str(metadata[map_name]["version"])`).
pub fn manifest_version(path: &Path, map_name: &str) -> Result<String> {
    if !path.is_file() {
        let dir = path.parent().unwrap_or(Path::new("."));
        let found = listing(dir, |p| p.extension().is_some_and(|e| e == "json"));
        bail!(
            "nuPlan maps manifest {} not found (GPKGMapsDB reads MAPS_ROOT/<NUPLAN_MAP_VERSION>.json; \
             NUPLAN_MAP_VERSION selects another; manifests in {}: [{}])",
            path.display(),
            dir.display(),
            found.join(", ")
        );
    }
    let n = bounds::regular_file(path).map_err(|why| anyhow!("nuPlan maps manifest: {why}"))?;
    if n > MAX_MANIFEST_BYTES {
        bail!(
            "nuPlan maps manifest {} holds {n} bytes (at most {MAX_MANIFEST_BYTES} are read)",
            path.display()
        );
    }
    let text = std::fs::read_to_string(path)
        .map_err(|e| anyhow!("nuPlan maps manifest {}: {e}", path.display()))?;
    let v: Value = serde_json::from_str(&text)
        .map_err(|e| anyhow!("nuPlan maps manifest {}: not JSON: {e}", path.display()))?;
    let Value::Object(maps) = &v else {
        bail!(
            "nuPlan maps manifest {}: expected an object with one entry per map name",
            path.display()
        );
    };
    let entry = maps.get(map_name).ok_or_else(|| {
        let mut names: Vec<&str> = maps.keys().map(String::as_str).collect();
        names.sort();
        anyhow!(
            "nuPlan maps manifest {} has no map {map_name:?} (the log's map_version); it lists [{}]",
            path.display(),
            names.join(", ")
        )
    })?;
    let version = match entry.get("version") {
        Some(Value::String(s)) => s.clone(),
        Some(Value::Number(n)) => n.to_string(),
        other => bail!(
            "nuPlan maps manifest {}: map {map_name:?}: `version` is {}, expected a string",
            path.display(),
            other.map_or("missing".to_string(), |x| x.to_string())
        ),
    };
    bounds::plain_name(&version).map_err(|why| {
        anyhow!(
            "nuPlan maps manifest {}: map {map_name:?}: version {version:?}: {why}",
            path.display()
        )
    })?;
    Ok(version)
}

/// The GeoPackage of the log whose `map_version` column is `log_map_version`, under `maps_root`, with the
/// manifest `<map_version>.json` (module docs). The file must exist.
pub fn locate(maps_root: &Path, map_version: &str, log_map_version: &str) -> Result<PathBuf> {
    let name = map_name(log_map_version);
    let manifest = manifest_path(maps_root, map_version);
    let version = manifest_version(&manifest, &name)?;
    let gpkg = maps_root.join(&name).join(&version).join("map.gpkg");
    if !gpkg.is_file() {
        let versions = listing(&maps_root.join(&name), Path::is_dir);
        bail!(
            "nuPlan map {name:?} version {version:?} (from {}): {} not found (versions of {name:?} present: [{}])",
            manifest.display(),
            gpkg.display(),
            versions.join(", ")
        );
    }
    Ok(gpkg)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lookup_follows_the_manifest() {
        let d = std::env::temp_dir().join(format!("b2dr_maps_db_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(d.join("us-ma-boston/9.12.1817")).unwrap();
        std::fs::write(d.join("us-ma-boston/9.12.1817/map.gpkg"), b"x").unwrap();
        std::fs::write(
            d.join("nuplan-maps-v1.0.json"),
            r#"{"us-ma-boston": {"version": "9.12.1817", "layers": {}}, "sg-one-north": {"version": "9.17.1964"}}"#,
        )
        .unwrap();
        let p = locate(&d, DEFAULT_MAP_VERSION, "us-ma-boston.gpkg").unwrap();
        assert_eq!(p, d.join("us-ma-boston/9.12.1817/map.gpkg"));
        let e = format!(
            "{:#}",
            locate(&d, DEFAULT_MAP_VERSION, "boston").unwrap_err()
        );
        assert!(
            e.contains("no map \"boston\"") && e.contains("sg-one-north, us-ma-boston"),
            "{e}"
        );
        let e = format!(
            "{:#}",
            locate(&d, DEFAULT_MAP_VERSION, "sg-one-north").unwrap_err()
        );
        assert!(
            e.contains("sg-one-north/9.17.1964/map.gpkg not found"),
            "{e}"
        );
        let e = format!(
            "{:#}",
            locate(&d, "nuplan-maps-v2.0", "us-ma-boston").unwrap_err()
        );
        assert!(
            e.contains("nuplan-maps-v2.0.json not found") && e.contains("[nuplan-maps-v1.0.json]"),
            "{e}"
        );
        std::fs::write(d.join("bad.json"), r#"{"m": {"version": "../../etc"}}"#).unwrap();
        let e = format!("{:#}", locate(&d, "bad", "m").unwrap_err());
        assert!(e.contains("version \"../../etc\""), "{e}");
        let _ = std::fs::remove_dir_all(&d);
    }
}
