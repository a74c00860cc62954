//! Camera rig and recorded frames.
//!
//! Conventions (nuScenes): ego frame x forward, y left, z up; camera frame x right, y down, z forward.
//! All geometry in f64. Poses are 4x4 homogeneous transforms `a2b` mapping points of frame a into frame b.
use glam::{DMat3, DMat4, DVec3};

/// One pinhole camera of a rig (images are undistorted).
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

/// A camera rig: the cameras of the vehicle plus the recorded frames of the log.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CameraRig {
    pub cameras: Vec<Camera>,
    pub frames: Vec<RecordedFrame>,
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
        }
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
}
