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
