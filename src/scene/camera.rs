//! Camera rig and recorded frames.
//!
//! Conventions (nuScenes): ego frame x forward, y left, z up; camera frame x right, y down, z forward.
//! All geometry in f64. Poses are 4x4 homogeneous transforms `a2b` mapping points of frame a into frame b.
use glam::{DMat3, DMat4, DVec3};

/// One pinhole camera of a rig. Geometry (projection, masks, rendering) is pinhole; a camera whose recorded
/// images are distorted carries its lens model in `distortion`, and the image store undistorts those images
/// when it reads them ([`Camera::undistort_image`]), so every consumer sees pinhole images.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// Channel name, e.g. `CAM_FRONT`.
    pub name: String,
    /// 3x3 pinhole intrinsics at the native resolution (pixels).
    pub intrinsic: DMat3,
    /// Camera -> ego transform.
    pub cam2ego: DMat4,
    /// Native image size in pixels.
    pub width: u32,
    pub height: u32,
    /// Lens distortion of the recorded images, (k1, k2, p1, p2, k3) of the Brown-Conrady ("Caltech", OpenCV
    /// plumb bob) model nuPlan's `camera.distortion` stores; all zero: the images are pinhole (nuScenes,
    /// synthetic).
    pub distortion: [f64; 5],
}

/// One camera image of a recorded frame: each camera fires at its own time, so it carries its own ego pose.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraImage {
    pub camera: String,
    /// Path of the image file (relative paths are relative to the scenario's directory).
    pub path: String,
    pub timestamp_us: i64,
    /// Ego -> global at this image's exposure time.
    pub ego2global: DMat4,
}

/// A recorded multi-camera frame of a log (what reference retrieval searches).
#[derive(Clone, Debug, PartialEq)]
pub struct RecordedFrame {
    pub timestamp_us: i64,
    /// Ego -> global at the frame's reference time.
    pub ego2global: DMat4,
    pub images: Vec<CameraImage>,
}

/// A camera rig: the cameras of the vehicle, its top lidar's mounting, and the recorded frames of the log.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraRig {
    pub cameras: Vec<Camera>,
    /// Lidar -> ego transform of the vehicle's top lidar: the frame end-to-end models (UniAD, VAD,
    /// SparseDrive) plan in. From the log where it has one (nuScenes: LIDAR_TOP's calibrated_sensor; nuPlan: the
    /// `lidar` table), else [`nuscenes_lidar2ego`].
    pub lidar2ego: DMat4,
    pub frames: Vec<RecordedFrame>,
}

impl Default for CameraRig {
    /// No cameras, no frames, the nominal nuScenes lidar mounting.
    fn default() -> Self {
        CameraRig {
            cameras: vec![],
            lidar2ego: nuscenes_lidar2ego(),
            frames: vec![],
        }
    }
}

/// Translation (m, ego frame) of the default lidar mounting: a real nuScenes v1.0 LIDAR_TOP `calibrated_sensor`
/// record (the value public nuScenes tooling, e.g. mmdet3d-style test-info scripts, hard-codes for every sample;
/// other logs' calibrations differ by a few centimetres and a fraction of a degree): 0.99 m ahead of the rear
/// axle, on the centre line, 1.84 m up.
pub const NUSCENES_LIDAR_TRANSLATION: [f64; 3] = [0.985793, 0.0, 1.84019];
/// Rotation of the same record as a quaternion `[w, x, y, z]` (nuScenes order): about -90 degrees about +z
/// (plus about 2 degrees of roll and pitch), so the lidar frame has x to the right, y forward, z up.
pub const NUSCENES_LIDAR_ROTATION_WXYZ: [f64; 4] = [
    0.706749235646644,
    -0.015300993788500868,
    0.01739745181256607,
    -0.7070846669051719,
];

/// The default lidar -> ego transform (synthetic rigs, logs without a lidar calibration): the nuScenes
/// LIDAR_TOP mounting of [`NUSCENES_LIDAR_TRANSLATION`] and [`NUSCENES_LIDAR_ROTATION_WXYZ`], built as the
/// nuScenes devkit builds `calibrated_sensor` transforms (`transform_matrix(translation, Quaternion(rotation))`).
pub fn nuscenes_lidar2ego() -> DMat4 {
    let [w, x, y, z] = NUSCENES_LIDAR_ROTATION_WXYZ;
    DMat4::from_rotation_translation(
        glam::DQuat::from_xyzw(x, y, z, w).normalize(),
        DVec3::from(NUSCENES_LIDAR_TRANSLATION),
    )
}

impl Camera {
    /// Camera centre in the ego frame.
    pub fn position_ego(&self) -> DVec3 {
        self.cam2ego.w_axis.truncate()
    }
}

impl Camera {
    /// Intrinsics rescaled to an image resized from the native `width x height` to `new_width x new_height`.
    ///
    /// Convention (pixel centres, matching PyTorch `interpolate(..., align_corners=False)` for bilinear and
    /// bicubic): image coordinates put the centre of pixel index `i` at `u = i` (OpenCV / nuScenes), and a resize
    /// by `sx = new_width / width` maps `u' = (u + 0.5) * sx - 0.5` (same for `v` with `sy`). Hence
    /// `fx' = fx sx`, `skew' = skew sx`, `cx' = (cx + 0.5) sx - 0.5`, `fy' = fy sy`, `cy' = (cy + 0.5) sy - 0.5`.
    /// The naive `u' = u sx` is off by `0.5 (1 - sx)` px (0.375 px at 1600 -> 400).
    pub fn intrinsic_scaled(&self, new_width: u32, new_height: u32) -> DMat3 {
        let sx = new_width as f64 / self.width.max(1) as f64;
        let sy = new_height as f64 / self.height.max(1) as f64;
        let k = self.intrinsic;
        // glam is column-major: x_axis = (fx, 0, 0), y_axis = (skew, fy, 0), z_axis = (cx, cy, 1).
        DMat3::from_cols(
            DVec3::new(k.x_axis.x * sx, k.x_axis.y * sy, k.x_axis.z),
            DVec3::new(k.y_axis.x * sx, k.y_axis.y * sy, k.y_axis.z),
            DVec3::new(
                (k.z_axis.x + 0.5) * sx - 0.5,
                (k.z_axis.y + 0.5) * sy - 0.5,
                k.z_axis.z,
            ),
        )
    }

    /// The same camera seen through an image resized to `new_width x new_height` (see [`Camera::intrinsic_scaled`]).
    pub fn rescaled(&self, new_width: u32, new_height: u32) -> Camera {
        Camera {
            name: self.name.clone(),
            intrinsic: self.intrinsic_scaled(new_width, new_height),
            cam2ego: self.cam2ego,
            width: new_width,
            height: new_height,
            distortion: self.distortion,
        }
    }

    /// Whether recorded images of this camera need undistorting.
    pub fn is_distorted(&self) -> bool {
        self.distortion.iter().any(|k| *k != 0.0)
    }

    /// The distorted normalised image coordinates of the pinhole ones `(x, y) = (X / Z, Y / Z)` (OpenCV's
    /// model): `r2 = x^2 + y^2`, `x_d = x (1 + k1 r2 + k2 r2^2 + k3 r2^3) + 2 p1 x y + p2 (r2 + 2 x^2)`,
    /// `y_d = y (...) + p1 (r2 + 2 y^2) + 2 p2 x y`.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// A recorded image of this camera (RGB interleaved, the native `width x height`) as the pinhole camera of
    /// the same intrinsics sees it (what `cv2.undistort(img, K, D)` computes): each output pixel centre is
    /// mapped through [`Camera::distort`] into the recorded image and sampled bilinearly; where that falls
    /// outside the recorded image the pixel is black. A camera without distortion returns the image unchanged.
    pub fn undistort_image(&self, rgb: &[u8], width: usize, height: usize) -> Vec<u8> {
        if !self.is_distorted() {
            return rgb.to_vec();
        }
        let k = self.intrinsic;
        // glam is column-major: (fx, skew, cx; 0, fy, cy)
        let (fx, s, cx) = (k.x_axis.x, k.y_axis.x, k.z_axis.x);
        let (fy, cy) = (k.y_axis.y, k.z_axis.y);
        let mut out = vec![0u8; width * height * 3];
        for v in 0..height {
            for u in 0..width {
                // pixel centre -> normalised pinhole coordinates (inverse of u = fx x + s y + cx, v = fy y + cy)
                let y = (v as f64 - cy) / fy;
                let x = (u as f64 - cx - s * y) / fx;
                let (xd, yd) = self.distort(x, y);
                let (ud, vd) = (fx * xd + s * yd + cx, fy * yd + cy);
                if !(ud > -1.0 && vd > -1.0 && ud < width as f64 && vd < height as f64) {
                    continue;
                }
                let (u0, v0) = (ud.floor(), vd.floor());
                let (a, b) = (ud - u0, vd - v0);
                let px = |uu: f64, vv: f64, c: usize| -> f64 {
                    if uu < 0.0 || vv < 0.0 || uu >= width as f64 || vv >= height as f64 {
                        // the border beyond the last pixel centre: clamp to the edge pixel
                        let (uc, vc) = (
                            uu.clamp(0.0, width as f64 - 1.0),
                            vv.clamp(0.0, height as f64 - 1.0),
                        );
                        return rgb[(vc as usize * width + uc as usize) * 3 + c] as f64;
                    }
                    rgb[(vv as usize * width + uu as usize) * 3 + c] as f64
                };
                for c in 0..3 {
                    let val = (1.0 - b) * ((1.0 - a) * px(u0, v0, c) + a * px(u0 + 1.0, v0, c))
                        + b * ((1.0 - a) * px(u0, v0 + 1.0, c) + a * px(u0 + 1.0, v0 + 1.0, c));
                    out[(v * width + u) * 3 + c] = val.round().clamp(0.0, 255.0) as u8;
                }
            }
        }
        out
    }
}

impl RecordedFrame {
    /// The image of camera `name` in this frame, if recorded.
    pub fn image(&self, name: &str) -> Option<&CameraImage> {
        self.images.iter().find(|i| i.camera == name)
    }
}

impl CameraRig {
    /// The camera called `name`, if the rig has one.
    pub fn camera(&self, name: &str) -> Option<&Camera> {
        self.cameras.iter().find(|c| c.name == name)
    }
}

/// Where the pixels of a [`CameraImage`] come from, decoded from its `path`.
///
/// Recorded images of imported logs are files. Images of generated logs (the built-in towns) are not stored
/// anywhere: their path is `builtin://<scenario>/<CAMERA>/<step>` (`<step>` = the log step, so any step of the
/// log is a valid image, not only the rig's frames) and the world's image store (`crate::world::images`) renders
/// them from the scenario at that step, on demand, cached in memory.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ImageRef<'a> {
    /// A file path (relative paths are relative to the scenario's directory).
    File(&'a str),
    /// A ground-truth image of the scenario's own log.
    Generated {
        scenario: &'a str,
        camera: &'a str,
        step: usize,
    },
}

/// Scheme prefix of generated images.
pub const GENERATED_SCHEME: &str = "builtin://";

impl<'a> ImageRef<'a> {
    /// The path of a generated image.
    pub fn generated_path(scenario: &str, camera: &str, step: usize) -> String {
        format!("{GENERATED_SCHEME}{scenario}/{camera}/{step:04}")
    }

    /// Decodes a path; a malformed `builtin://` path is an error naming it.
    pub fn parse(path: &'a str) -> anyhow::Result<ImageRef<'a>> {
        let Some(rest) = path.strip_prefix(GENERATED_SCHEME) else {
            return Ok(ImageRef::File(path));
        };
        let mut it = rest.rsplitn(3, '/');
        let (step, camera, scenario) = (it.next(), it.next(), it.next());
        match (step.and_then(|s| s.parse::<usize>().ok()), camera, scenario) {
            (Some(step), Some(camera), Some(scenario)) if !camera.is_empty() => {
                Ok(ImageRef::Generated {
                    scenario,
                    camera,
                    step,
                })
            }
            _ => anyhow::bail!(
                "image path {path:?}: expected {GENERATED_SCHEME}<scenario>/<CAMERA>/<step>"
            ),
        }
    }
}

impl CameraImage {
    /// Where this image's pixels come from (see [`ImageRef`]).
    pub fn source(&self) -> anyhow::Result<ImageRef<'_>> {
        ImageRef::parse(&self.path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn image_refs() {
        let p = ImageRef::generated_path("town-0", "CAM_FRONT", 5);
        assert_eq!(p, "builtin://town-0/CAM_FRONT/0005");
        assert_eq!(
            ImageRef::parse(&p).unwrap(),
            ImageRef::Generated {
                scenario: "town-0",
                camera: "CAM_FRONT",
                step: 5
            }
        );
        assert_eq!(
            ImageRef::parse("a/b.jpg").unwrap(),
            ImageRef::File("a/b.jpg")
        );
        assert!(ImageRef::parse("builtin://x/CAM").is_err());
    }

    fn lens(distortion: [f64; 5]) -> Camera {
        Camera {
            name: "CAM".into(),
            intrinsic: DMat3::from_cols(
                DVec3::new(40.0, 0.0, 0.0),
                DVec3::new(0.5, 42.0, 0.0),
                DVec3::new(31.5, 23.5, 1.0),
            ),
            cam2ego: DMat4::IDENTITY,
            width: 64,
            height: 48,
            distortion,
        }
    }

    /// Undistorting samples the recorded image where the lens put each pinhole ray: a recorded image that is a
    /// linear ramp in the recorded (distorted) pixel coordinates becomes, at pinhole pixel (u, v), that ramp at
    /// the distorted position of (u, v) (bilinear sampling is exact on a ramp, up to rounding); mapping the
    /// other way (distorting instead of undistorting) misses by several levels.
    #[test]
    fn undistort_samples_through_the_lens_model() {
        let cam = lens([0.25, 0.05, 0.002, -0.003, 0.0]);
        let (w, h) = (64usize, 48usize);
        let ramp = |u: f64, v: f64| [3.0 * u + 20.0, 4.0 * v + 20.0, 2.0 * u + v + 10.0];
        let mut rec = vec![0u8; w * h * 3];
        for v in 0..h {
            for u in 0..w {
                for (c, val) in ramp(u as f64, v as f64).iter().enumerate() {
                    rec[(v * w + u) * 3 + c] = val.round() as u8;
                }
            }
        }
        let out = cam.undistort_image(&rec, w, h);
        let k = cam.intrinsic;
        let (mut inside, mut outside, mut moved) = (0, 0, 0);
        for v in 0..h {
            for u in 0..w {
                let y = (v as f64 - k.z_axis.y) / k.y_axis.y;
                let x = (u as f64 - k.z_axis.x - k.y_axis.x * y) / k.x_axis.x;
                let (xd, yd) = cam.distort(x, y);
                let (ud, vd) = (
                    k.x_axis.x * xd + k.y_axis.x * yd + k.z_axis.x,
                    k.y_axis.y * yd + k.z_axis.y,
                );
                let got = &out[(v * w + u) * 3..(v * w + u) * 3 + 3];
                if ud >= 0.0 && vd >= 0.0 && ud <= (w - 1) as f64 && vd <= (h - 1) as f64 {
                    inside += 1;
                    for (c, want) in ramp(ud, vd).iter().enumerate() {
                        assert!(
                            (got[c] as f64 - want).abs() <= 1.0,
                            "({u}, {v}) channel {c}: {} vs {want:.2}",
                            got[c]
                        );
                    }
                    if (ud - u as f64).hypot(vd - v as f64) > 1.0 {
                        moved += 1;
                    }
                } else if ud < -1.0 || vd < -1.0 || ud > w as f64 || vd > h as f64 {
                    outside += 1;
                    assert_eq!(got, [0, 0, 0], "({u}, {v}) maps outside: black");
                }
            }
        }
        // (pincushion) the lens moves half the pixels by more than a pixel and sends the corners beyond the
        // recorded image
        assert!(
            inside > w * h / 2 && moved > inside / 2 && outside > 0,
            "{inside} {moved} {outside}"
        );
        // no distortion: the image unchanged
        assert_eq!(lens([0.0; 5]).undistort_image(&rec, w, h), rec);
    }
}
