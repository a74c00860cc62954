//! The scene side of one evaluated frame: the ego pose (logged or displaced), the ground truth of the synthetic
//! world there, the layout masks, the references retrieved from the log, and the copy-nearest-frame baseline.
//! Nothing here touches the device.
use anyhow::{ensure, Context as _, Result};
use glam::DMat4;

use crate::eval::sensors::{planar, recorded_pixels, references, Retrieved};
use crate::nn::b2dr_config::B2drConfig;
use crate::projection::scene::boxes_at;
use crate::projection::{MapLayer, ProjectionConfig};
use crate::render::inputs;
use crate::scene::camera::{Camera, CameraImage};
use crate::scene::geometry::Pose2;
use crate::scene::import::ego2global;
use crate::scene::Scenario;
use crate::world::images::ImageStore;
use crate::world::view::ego_pose;

/// A displacement of the ego from its logged pose, in the ego frame (lateral: to the left).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Deviation {
    pub lateral_m: f64,
    pub yaw_deg: f64,
}

impl Deviation {
    pub const NONE: Deviation = Deviation {
        lateral_m: 0.0,
        yaw_deg: 0.0,
    };

    pub fn is_none(&self) -> bool {
        self.lateral_m == 0.0 && self.yaw_deg == 0.0
    }

    pub fn label(&self) -> String {
        match (self.lateral_m, self.yaw_deg) {
            (l, 0.0) => format!("lateral {l} m"),
            (0.0, y) => format!("yaw {y} deg"),
            (l, y) => format!("lateral {l} m, yaw {y} deg"),
        }
    }

    fn offset(&self) -> Pose2 {
        Pose2::new(0.0, self.lateral_m, self.yaw_deg.to_radians())
    }
}

/// The log step of recorded frame `i`.
pub fn frame_step(sc: &Scenario, i: usize) -> usize {
    crate::world::export::plan::frame_step(sc, &sc.rig.frames[i])
}

/// Ego -> global at recorded frame `i` displaced by `d` (errors off the map).
pub fn pose_at(sc: &Scenario, i: usize, d: &Deviation) -> Result<DMat4> {
    if d.is_none() {
        return Ok(sc.rig.frames[i].ego2global);
    }
    Ok(ego2global(&ego_pose(sc, frame_step(sc, i), &d.offset())?))
}

/// Ground truth of every camera: interleaved RGB8 `(H, W, 3)` and class ids `(H, W)` per camera.
pub struct Truth {
    pub rgb: Vec<Vec<u8>>,
    pub class: Vec<Vec<u8>>,
}

pub fn truth(
    store: &ImageStore,
    cams: &[Camera],
    e2g: &DMat4,
    step: usize,
    size: (usize, usize),
) -> Result<Truth> {
    let (h, w) = size;
    let f = store.world().render_step(cams, e2g, step, w, h, 1)?;
    Ok(Truth {
        rgb: f.iter().map(|c| c.rgb.clone()).collect(),
        class: f.into_iter().map(|c| c.class).collect(),
    })
}

/// Interleaved per-camera RGB8 -> planar `(N, 3, H, W)` f32 in [0, 1].
pub fn planar_all(rgb: &[Vec<u8>], size: (usize, usize)) -> Vec<f32> {
    rgb.iter().flat_map(|x| planar(x, size)).collect()
}

/// The layout masks `(N, 15, H, W)` of the logged objects of `step` seen from `e2g`.
pub fn masks(
    sc: &Scenario,
    map: &MapLayer,
    cams: &[Camera],
    e2g: &DMat4,
    step: usize,
    size: (usize, usize),
) -> Result<Vec<f32>> {
    let boxes: Vec<_> = boxes_at(sc, step).into_iter().map(|(_, b)| b).collect();
    inputs::masks(
        cams,
        &vec![*e2g; cams.len()],
        &boxes,
        map,
        size,
        &ProjectionConfig::default(),
    )
}

/// The references retrieved from the log at `e2g` (images, geometry and their poses).
pub fn refs(
    store: &ImageStore,
    cfg: &B2drConfig,
    cams: &[Camera],
    e2g: &DMat4,
    size: (usize, usize),
) -> Result<Retrieved> {
    references(store, cfg, cams, size, e2g)
}

/// The recorded image of `camera` whose ego position is nearest to `e2g`'s on the ground plane (ties: the
/// earliest): log replay by position.
pub fn nearest_by_position<'s>(
    sc: &'s Scenario,
    camera: &str,
    e2g: &DMat4,
) -> Option<&'s CameraImage> {
    let p = e2g.w_axis.truncate().truncate();
    let mut best: Option<(f64, &CameraImage)> = None;
    for f in &sc.rig.frames {
        if let Some(img) = f.images.iter().find(|i| i.camera == camera) {
            let d = (img.ego2global.w_axis.truncate().truncate() - p).length();
            if best.is_none_or(|(b, _)| d < b) {
                best = Some((d, img));
            }
        }
    }
    best.map(|(_, i)| i)
}

/// The copy-nearest-frame baseline of every camera (interleaved RGB8).
pub fn copy_nearest(
    store: &ImageStore,
    cams: &[Camera],
    e2g: &DMat4,
    size: (usize, usize),
) -> Result<Vec<Vec<u8>>> {
    let sc = store.world().scenario;
    cams.iter()
        .map(|c| {
            let img = nearest_by_position(sc, &c.name, e2g)
                .with_context(|| format!("{}: no recorded image of {}", sc.name, c.name))?;
            let px = recorded_pixels(store, img, size)?;
            ensure!(px.len() == 3 * size.0 * size.1, "recorded image size");
            Ok(px)
        })
        .collect()
}
