//! Scenario importers and the scenario source syntax accepted by `b2dr sim --scenario`:
//! - `builtin:LAYOUT[:seed[:n_vehicles[:palette]]]`: the built-in synthetic towns ([`builtin`] parses the spec;
//!   `crate::world::load` generates them, since their logs are driven by the simulator's IDM agents);
//! - a ScenarioNet JSON file ([`scenarionet`]);
//! - a directory: every `*.json` file in it, sorted by name;
//! - `nuscenes:DATAROOT[:VERSION]:SCENE`: a scene of the official nuScenes tables ([`nuscenes`]);
//! - `nuplan:DB[:SCENARIO_TOKEN]`: a nuPlan log DB, whole or one scenario window ([`nuplan`]).
pub mod bounds;
pub mod builtin;
pub mod nuplan;
pub mod nuscenes;
pub mod scenarionet;

pub use builtin::{BuiltinSpec, DayPalette, Layout};
pub use nuplan::NuplanSpec;
pub use nuscenes::NuscenesSpec;

use super::camera::{Camera, CameraImage, CameraRig, RecordedFrame};
use super::geometry::Pose2;
use anyhow::{bail, Context, Result};
use glam::{DMat3, DMat4, DVec3, DVec4};
use std::path::PathBuf;

/// One scenario to load (`crate::world::load`).
#[derive(Clone, Debug, PartialEq)]
pub enum Source {
    Builtin(BuiltinSpec),
    File(PathBuf),
    Nuscenes(NuscenesSpec),
    Nuplan(NuplanSpec),
}

impl Source {
    /// Stable name used for output folders and `--resume` bookkeeping.
    pub fn name(&self) -> String {
        match self {
            Source::Builtin(b) => b.name(),
            Source::File(p) => p
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
            Source::Nuscenes(n) => n.scene.clone(),
            Source::Nuplan(n) => n.name(),
        }
    }

    /// The folder relative image paths of the scenario's recorded frames are resolved against (none for
    /// generated images and for nuScenes, whose image paths already start with the DATAROOT).
    pub fn image_dir(&self) -> Option<PathBuf> {
        match self {
            Source::Builtin(_) | Source::Nuscenes(_) | Source::Nuplan(_) => None,
            Source::File(p) => p.parent().map(|d| d.to_path_buf()),
        }
    }
}

/// Parses a `--scenario` argument into the scenarios it names: `builtin:...`, a .json file, a folder of them,
/// or a comma-separated list of those (resolved in order; an existing path containing a comma is a path).
pub fn resolve(spec: &str) -> Result<Vec<Source>> {
    if spec.contains(',') && !std::path::Path::new(spec).exists() {
        let mut all = vec![];
        for part in spec.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            all.extend(resolve(part)?);
        }
        if all.is_empty() {
            bail!("scenario list {spec:?} names no scenario");
        }
        return Ok(all);
    }
    if let Some(rest) = spec.strip_prefix("builtin:") {
        return Ok(vec![Source::Builtin(BuiltinSpec::parse(rest, spec)?)]);
    }
    if let Some(rest) = spec.strip_prefix("nuscenes:") {
        return Ok(vec![Source::Nuscenes(NuscenesSpec::parse(rest, spec)?)]);
    }
    if let Some(rest) = spec.strip_prefix("nuplan:") {
        return Ok(vec![Source::Nuplan(NuplanSpec::parse(rest, spec)?)]);
    }
    let p = PathBuf::from(spec);
    if p.is_dir() {
        // an entry that cannot be read is an error, not a scenario silently left out of the CLS
        let mut files: Vec<PathBuf> = std::fs::read_dir(&p)
            .with_context(|| format!("reading scenario directory {}", p.display()))?
            .map(|e| e.map(|e| e.path()))
            .collect::<std::io::Result<Vec<_>>>()
            .with_context(|| format!("reading scenario directory {}", p.display()))?
            .into_iter()
            .filter(|f| f.extension().is_some_and(|x| x == "json"))
            .collect();
        files.sort();
        if files.is_empty() {
            bail!("scenario directory {} holds no .json files", p.display());
        }
        return Ok(files.into_iter().map(Source::File).collect());
    }
    if p.is_file() {
        return Ok(vec![Source::File(p)]);
    }
    bail!("scenario {spec:?} is neither builtin:LAYOUT[:seed[:n[:palette]]], nuscenes:DATAROOT[:VERSION]:SCENE, nuplan:DB[:SCENARIO_TOKEN], an existing .json file nor a directory")
}

/// Ego -> global 4x4 of a rear-axle pose (nuScenes' ego frame sits at the rear axle, z = 0).
pub fn ego2global(p: &Pose2) -> DMat4 {
    let (s, c) = p.heading.sin_cos();
    DMat4::from_cols(
        DVec4::new(c, s, 0.0, 0.0),
        DVec4::new(-s, c, 0.0, 0.0),
        DVec4::new(0.0, 0.0, 1.0, 0.0),
        DVec4::new(p.x, p.y, 0.0, 1.0),
    )
}

/// nuScenes camera channel names in the order of the dataset.
pub const CAMERAS: [&str; 6] = [
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
];

/// A nuScenes-like 6-camera rig: 1600x900, f = 1266.4 px, mounting yaws and positions close to the nuScenes
/// car's (camera frame x right, y down, z forward).
pub fn nuscenes_like_cameras() -> Vec<Camera> {
    // (name, yaw deg, x, y, z) in the ego frame.
    let mounts = [
        ("CAM_FRONT", 0.0, 1.70, 0.02, 1.51),
        ("CAM_FRONT_RIGHT", -55.0, 1.55, -0.49, 1.50),
        ("CAM_FRONT_LEFT", 55.0, 1.52, 0.49, 1.51),
        ("CAM_BACK", 180.0, 0.03, 0.01, 1.58),
        ("CAM_BACK_LEFT", 110.0, 1.04, 0.48, 1.56),
        ("CAM_BACK_RIGHT", -110.0, 1.05, -0.48, 1.56),
    ];
    mounts
        .iter()
        .map(|&(name, yaw_deg, x, y, z)| {
            let yaw: f64 = f64::to_radians(yaw_deg);
            let (s, c) = yaw.sin_cos();
            // Columns: camera x (right), y (down), z (forward) axes and the centre, in the ego frame.
            let cam2ego = DMat4::from_cols(
                DVec4::new(s, -c, 0.0, 0.0),
                DVec4::new(0.0, 0.0, -1.0, 0.0),
                DVec4::new(c, s, 0.0, 0.0),
                DVec4::new(x, y, z, 1.0),
            );
            Camera {
                name: name.to_string(),
                intrinsic: DMat3::from_cols(
                    DVec3::new(1266.417, 0.0, 0.0),
                    DVec3::new(0.0, 1266.417, 0.0),
                    DVec3::new(816.267, 491.507, 1.0),
                ),
                cam2ego,
                width: 1600,
                height: 900,
                distortion: [0.0; 5],
            }
        })
        .collect()
}

/// Recorded frames every `every` log steps (0.5 s at 10 Hz with every = 5) from the ego log. The images are
/// generated ones: their paths are `builtin://<scenario>/<CAM>/<step>` ([`super::camera::ImageRef`]), which the
/// world's image store renders on demand from the scenario at that log step.
pub fn frames_from_ego(
    name: &str,
    ego: &[super::EgoLogState],
    dt: f64,
    every: usize,
) -> Vec<RecordedFrame> {
    (0..ego.len())
        .step_by(every.max(1))
        .map(|k| {
            let t_us = (k as f64 * dt * 1e6).round() as i64;
            let m = ego2global(&ego[k].rear_axle);
            RecordedFrame {
                timestamp_us: t_us,
                ego2global: m,
                images: CAMERAS
                    .iter()
                    .map(|c| CameraImage {
                        camera: c.to_string(),
                        path: super::camera::ImageRef::generated_path(name, c, k),
                        timestamp_us: t_us,
                        ego2global: m,
                    })
                    .collect(),
            }
        })
        .collect()
}

/// The rig of a scenario: nuScenes-like cameras, the nominal nuScenes lidar mounting, frames every 0.5 s.
pub fn default_rig(name: &str, ego: &[super::EgoLogState], dt: f64) -> CameraRig {
    let every = ((0.5 / dt).round() as usize).max(1);
    CameraRig {
        cameras: nuscenes_like_cameras(),
        lidar2ego: super::camera::nuscenes_lidar2ego(),
        frames: frames_from_ego(name, ego, dt, every),
    }
}
