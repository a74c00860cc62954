//! Reader of the shared keyframe format (`b2dr-shared-keyframe/v1`, e.g.
//! `nuscenes-mini/keyframe-scene-0061/frame.json`): cameras with intrinsics, extrinsics and their own ego pose at
//! exposure, plus annotated 3D boxes in the global frame. Matrices are row-major in the file.
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use glam::{DMat4, DVec3};
use serde::Deserialize;

use super::geometry::{mat3_from_rows, mat4_from_rows, Box3d, BoxClass};
use crate::scene::camera::{Camera, CameraImage};

#[derive(Deserialize)]
struct RawFrame {
    ego2global: [[f64; 4]; 4],
    cameras: serde_json::Map<String, serde_json::Value>,
    boxes: Vec<RawBox>,
}

#[derive(Deserialize)]
struct RawCamera {
    image: String,
    width: u32,
    height: u32,
    #[serde(default)]
    timestamp_us: i64,
    intrinsic: [[f64; 3]; 3],
    cam2ego: [[f64; 4]; 4],
    ego2global: [[f64; 4]; 4],
}

#[derive(Deserialize)]
struct RawBox {
    category: String,
    center: [f64; 3],
    size_lwh: [f64; 3],
    yaw: f64,
}

/// One loaded keyframe.
#[derive(Clone, Debug)]
pub struct KeyFrame {
    /// Directory of `frame.json` (image paths are relative to it).
    pub dir: PathBuf,
    /// Ego pose at the keyframe (lidar) time.
    pub ego2global: DMat4,
    /// Cameras sorted by name, each with its image (own ego pose at exposure).
    pub cameras: Vec<(Camera, CameraImage)>,
    /// Boxes in file order (indices match `boxes[]` in the file).
    pub boxes: Vec<Box3d>,
}

fn check_pose(m: &DMat4, what: &str) -> Result<()> {
    ensure!(m.to_cols_array().iter().all(|v| v.is_finite()), "{what}: non-finite value");
    let r = glam::DMat3::from_mat4(*m);
    ensure!((r.determinant() - 1.0).abs() < 1e-3, "{what}: rotation part is not a rotation (det {})", r.determinant());
    ensure!(m.row(3) == glam::DVec4::new(0.0, 0.0, 0.0, 1.0), "{what}: last row must be [0, 0, 0, 1]");
    Ok(())
}

impl KeyFrame {
    /// Reads and validates `frame.json`; errors name the file and the field.
    pub fn load(path: &Path) -> Result<KeyFrame> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let raw: RawFrame = serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        let ctx = |field: String| format!("{}: {field}", path.display());
        let ego2global = mat4_from_rows(&raw.ego2global);
        check_pose(&ego2global, &ctx("ego2global".into()))?;
        let mut cameras = Vec::new();
        for (name, v) in &raw.cameras {
            let c: RawCamera =
                serde_json::from_value(v.clone()).with_context(|| ctx(format!("cameras.{name}")))?;
            let cam = Camera {
                name: name.clone(),
                intrinsic: mat3_from_rows(&c.intrinsic),
                cam2ego: mat4_from_rows(&c.cam2ego),
                width: c.width,
                height: c.height,
            };
            ensure!(c.width > 0 && c.height > 0, "{}: size {}x{}", ctx(format!("cameras.{name}.width/height")), c.width, c.height);
            let k = &c.intrinsic;
            ensure!(
                k[0][0] > 0.0 && k[1][1] > 0.0 && k[1][0] == 0.0 && k[2] == [0.0, 0.0, 1.0],
                "{}: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {k:?}",
                ctx(format!("cameras.{name}.intrinsic"))
            );
            check_pose(&cam.cam2ego, &ctx(format!("cameras.{name}.cam2ego")))?;
            let e2g = mat4_from_rows(&c.ego2global);
            check_pose(&e2g, &ctx(format!("cameras.{name}.ego2global")))?;
            let image = CameraImage { camera: name.clone(), path: c.image, timestamp_us: c.timestamp_us, ego2global: e2g };
            cameras.push((cam, image));
        }
        ensure!(!cameras.is_empty(), "{}: no cameras", ctx("cameras".into()));
        cameras.sort_by(|a, b| a.0.name.cmp(&b.0.name));
        let mut boxes = Vec::with_capacity(raw.boxes.len());
        for (i, b) in raw.boxes.iter().enumerate() {
            let Some(class) = BoxClass::parse(&b.category) else {
                bail!("{}: unknown category {:?}", ctx(format!("boxes[{i}].category")), b.category);
            };
            ensure!(
                b.size_lwh.iter().all(|s| s.is_finite() && *s > 0.0),
                "{}: sizes must be positive, got {:?}",
                ctx(format!("boxes[{i}].size_lwh")),
                b.size_lwh
            );
            ensure!(
                b.center.iter().all(|s| s.is_finite()) && b.yaw.is_finite(),
                "{}: non-finite centre or yaw",
                ctx(format!("boxes[{i}]"))
            );
            boxes.push(Box3d { class, center: DVec3::from(b.center), size: DVec3::from(b.size_lwh), yaw: b.yaw });
        }
        let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        Ok(KeyFrame { dir, ego2global, cameras, boxes })
    }

    /// Path of a camera's image file.
    pub fn image_path(&self, img: &CameraImage) -> PathBuf {
        self.dir.join(&img.path)
    }
}
