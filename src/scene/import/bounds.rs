//! Bounds every importer applies to what it reads (issue #18, hostile and careless inputs): a value beyond them
//! is an error naming the file, table or field, not a scenario whose geometry overflows or whose world takes
//! unbounded memory. Shared by [`super::scenarionet`], [`super::nuscenes`] and [`super::nuplan`].
use std::path::{Component, Path};

/// Largest coordinate accepted (metres from the map origin; UTM northings stay below 1e7).
pub const MAX_COORD_M: f64 = 1e8;
/// Largest speed accepted in a logged (or, for nuScenes, differenced) velocity (m/s).
pub const MAX_SPEED_MPS: f64 = 1e3;
/// Largest object dimension accepted (m); also the largest sensor offset from the ego (m).
pub const MAX_SIZE_M: f64 = 1e3;
/// Largest heading accepted (rad): a larger one is not an angle.
pub const MAX_ANGLE_RAD: f64 = 1e3;
/// Largest camera image side accepted (pixels; as projection keyframe files).
pub const MAX_IMAGE_SIDE_PX: u32 = 16384;
/// Shortest log time step accepted (s): a subnormal one (5e-324 s) made a world or a simulation of a 3-step
/// log allocate gigabytes (found by `hostile_inputs::scenario_numbers_parse_or_err_and_run`).
pub const MIN_DT_S: f64 = 1e-3;
/// Largest timestamp accepted (us, absolute: about the year 5100), so that differences cannot overflow.
pub const MAX_TIMESTAMP_US: i64 = 100_000_000_000_000_000;
/// Largest focal length or principal point coordinate accepted in camera intrinsics (pixels).
pub const MAX_INTRINSIC_PX: f64 = 1e6;

/// Longest log time step accepted (s).
pub const MAX_DT_S: f64 = 10.0;

/// `Err(why)` unless `dt` is a log time step in [`MIN_DT_S`]..[`MAX_DT_S`] seconds (NaN, infinities, zero,
/// negative and subnormal steps are not): checked where a scenario's dt is read (ScenarioNet's
/// `metadata.sample_rate`; nuScenes and nuPlan logs are resampled to a fixed 0.1 s) and again by the
/// simulator, for scenarios built in code.
pub fn check_dt(dt: f64) -> Result<(), String> {
    if !(MIN_DT_S..MAX_DT_S).contains(&dt) {
        return Err(format!(
            "must be a time step in seconds in {MIN_DT_S}..{MAX_DT_S}, found {dt}"
        ));
    }
    Ok(())
}

/// Largest table or map file read whole (bytes): nuScenes' largest trainval table is well under 1 GiB.
pub const MAX_TABLE_BYTES: u64 = 4 << 30;

/// `Err(why)` unless `path`, symbolic links followed, is a regular file (not a FIFO, device, socket or folder:
/// reading one would block or never end). Only metadata is read, so a FIFO is not opened.
pub fn regular_file(path: &Path) -> Result<u64, String> {
    let m = std::fs::metadata(path).map_err(|e| format!("{}: {e}", path.display()))?;
    if !m.is_file() {
        return Err(format!(
            "{} is not a regular file (symbolic links are followed; a FIFO, device, socket or folder is refused)",
            path.display()
        ));
    }
    Ok(m.len())
}

/// The text of a regular file ([`regular_file`]) of at most [`MAX_TABLE_BYTES`].
pub fn read_table_text(path: &Path) -> Result<String, String> {
    let n = regular_file(path)?;
    if n > MAX_TABLE_BYTES {
        return Err(format!(
            "{} holds {n} bytes, more than {MAX_TABLE_BYTES} (the largest table file accepted)",
            path.display()
        ));
    }
    std::fs::read_to_string(path).map_err(|e| format!("reading {}: {e}", path.display()))
}

/// A coordinate within [`MAX_COORD_M`] (false for NaN and infinities).
pub fn coord_ok(x: f64) -> bool {
    x.is_finite() && x.abs() <= MAX_COORD_M
}

/// An object dimension in 0..=[`MAX_SIZE_M`] in absolute value (false for NaN and infinities).
pub fn size_ok(d: f64) -> bool {
    d.is_finite() && d.abs() <= MAX_SIZE_M
}

/// A heading that is an angle (finite, within [`MAX_ANGLE_RAD`]).
pub fn angle_ok(h: f64) -> bool {
    h.is_finite() && h.abs() <= MAX_ANGLE_RAD
}

/// `Err(why)` unless `name` may become a file name as is: non-empty, no path separator, NUL or leading dot
/// (map names, nuScenes locations and scene names).
pub fn plain_name(name: &str) -> Result<(), String> {
    if name.is_empty()
        || name.starts_with('.')
        || name.chars().any(|ch| matches!(ch, '/' | '\\' | '\0'))
    {
        return Err(format!(
            "{name:?} is not a plain name (no separators, NUL or leading dot)"
        ));
    }
    Ok(())
}

/// `Err(why)` unless `path` is a relative path that stays inside the folder it is joined to: non-empty, only
/// normal components (no `..`, `.`, root or drive prefix, no backslash or NUL).
pub fn inside_relative(path: &str) -> Result<(), String> {
    let bad = path.is_empty()
        || path.contains('\0')
        || path.contains('\\')
        || !Path::new(path)
            .components()
            .all(|c| matches!(c, Component::Normal(_)));
    if bad {
        return Err(format!(
            "{path:?} is not a relative path inside the data folder (no `..`, absolute path, backslash or NUL)"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_paths() {
        assert!(plain_name("singapore-onenorth").is_ok());
        for bad in ["", ".hidden", "..", "a/b", "a\\b", "a\0b"] {
            assert!(plain_name(bad).is_err(), "{bad:?}");
        }
        assert!(inside_relative("samples/CAM_FRONT/x.jpg").is_ok());
        for bad in [
            "",
            "/etc/passwd",
            "../x.jpg",
            "samples/../../x",
            "./x",
            "a\\..\\b",
            "a\0",
        ] {
            assert!(inside_relative(bad).is_err(), "{bad:?}");
        }
        assert!(coord_ok(1e7) && !coord_ok(1e9) && !coord_ok(f64::NAN));
        assert!(size_ok(5.0) && !size_ok(1e4) && !size_ok(f64::INFINITY));
        for dt in [0.1, 0.5, 1e-3, 9.99] {
            assert!(check_dt(dt).is_ok(), "{dt}");
        }
        for dt in [
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            0.0,
            -0.1,
            5e-324,
            1e-4,
            10.0,
            1e300,
        ] {
            assert!(check_dt(dt).is_err(), "{dt}");
        }
    }
}
