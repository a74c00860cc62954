//! The projection inputs of one log step of any scenario source (`b2dr project --scenario S --step K`): the
//! recorded frame of that step, each of its camera images with the 3D boxes it shows, and the map layer.
//!
//! - Frame: the recorded frame nearest the step's time (`K dt`); with a keyframe at exactly that time (nuScenes
//!   samples land on a step) that one. Each image is projected with its own ego pose (docs/projection.md).
//! - Boxes of an image: for a nuScenes scene the devkit's own boxes, 3D as annotated
//!   ([`nuscenes::boxes_at_image`]: a keyframe image shows its sample's annotations, a sweep the interpolated
//!   ones); for the other sources (whose tracks are planar) the tracks of the frame's step on the ground plane
//!   ([`crate::projection::scene::boxes_at`]). Objects whose category has no mask class are left out.
//! - Map: [`crate::projection::scene::map_layer`] of the scenario's map (empty for a nuScenes scene without the
//!   map expansion pack).
use anyhow::{bail, ensure, Result};

use crate::projection::scene::{boxes_at, map_layer};
use crate::projection::{Box3d, BoxClass, MapLayer};
use crate::scene::camera::{Camera, CameraImage};
use crate::scene::import::{nuscenes, Source};
use crate::scene::Scenario;

/// One camera image of the frame with what it shows.
#[derive(Clone, Debug)]
pub struct ImageView {
    pub camera: Camera,
    pub image: CameraImage,
    pub boxes: Vec<Box3d>,
}

/// The projection inputs of one step.
#[derive(Clone, Debug)]
pub struct StepViews {
    pub scenario: Scenario,
    /// The step asked for.
    pub step: usize,
    /// The recorded frame used: its index in `scenario.rig.frames` and its time (s from the log start).
    pub frame: usize,
    pub frame_time_s: f64,
    /// The log step whose objects the planar boxes are (the frame's time in steps).
    pub frame_step: usize,
    /// "nuscenes annotations" or "scenario tracks".
    pub boxes_from: &'static str,
    pub views: Vec<ImageView>,
    pub map: MapLayer,
}

/// The box of a nuScenes annotation, if its category has a mask class (the gravity centre, size and yaw as
/// annotated).
fn annotation_box(a: &nuscenes::Annotation) -> Option<Box3d> {
    Some(Box3d {
        class: BoxClass::parse(&a.category)?,
        center: a.center,
        size: a.size_lwh,
        yaw: a.yaw,
    })
}

/// Loads `src` and gathers the projection inputs of log step `step` for `cameras` (empty: every camera of the
/// rig); see the module docs.
pub fn step_views(src: &Source, step: usize, cameras: &[String]) -> Result<StepViews> {
    let (scenario, nu) = match src {
        Source::Nuscenes(spec) => {
            let log = nuscenes::load_log(spec)?;
            (log.scenario.clone(), Some(log))
        }
        other => (super::load(other)?, None),
    };
    let sc = &scenario;
    ensure!(
        step < sc.len(),
        "--step {step} is out of range: scenario {} has steps 0..={}",
        sc.name,
        sc.len().saturating_sub(1)
    );
    let frames = &sc.rig.frames;
    if frames.is_empty() {
        bail!("scenario {} has no recorded camera frames", sc.name);
    }
    let t = (step as f64 * sc.dt * 1e6).round() as i64;
    let fi = (0..frames.len())
        .min_by_key(|&i| {
            let keyframe = nu
                .as_ref()
                .is_some_and(|l| l.frame_sample.get(i).copied().flatten().is_some());
            ((frames[i].timestamp_us - t).abs(), !keyframe)
        })
        .unwrap_or(0);
    let frame = &frames[fi];
    let frame_step =
        ((frame.timestamp_us as f64 * 1e-6 / sc.dt).round().max(0.0) as usize).min(sc.len() - 1);
    let planar: Vec<Box3d> = boxes_at(sc, frame_step).into_iter().map(|x| x.1).collect();
    let mut views = Vec::new();
    for cam in sc.select_cameras(cameras)? {
        let Some(img) = frame.image(&cam.name) else {
            continue;
        };
        let boxes = match &nu {
            Some(l) => nuscenes::boxes_at_image(
                &l.keyframes,
                l.frame_sample.get(fi).copied().flatten(),
                img.timestamp_us,
            )
            .iter()
            .filter_map(annotation_box)
            .collect(),
            None => planar.clone(),
        };
        views.push(ImageView {
            camera: cam,
            image: img.clone(),
            boxes,
        });
    }
    if views.is_empty() {
        let have: Vec<&str> = frame.images.iter().map(|i| i.camera.as_str()).collect();
        bail!(
            "the frame of step {step} of {} has no image of the cameras asked for (it has {})",
            sc.name,
            have.join(", ")
        );
    }
    let map = map_layer(&sc.map);
    Ok(StepViews {
        step,
        frame: fi,
        frame_time_s: frame.timestamp_us as f64 * 1e-6,
        frame_step,
        boxes_from: if nu.is_some() {
            "nuscenes annotations"
        } else {
            "scenario tracks"
        },
        views,
        map,
        scenario,
    })
}
