//! The previous frame's warp to the current pose (b2dr.json `prev_warp_max_depth` D > 0; the training side is
//! python/b2dr_ref/warp.py, which computes the same grid).
//!
//! Every pixel of the current camera is taken along its ray to the flat ground (the plane z = the current ego
//! origin's global z: nuScenes' ego frame sits on the ground), or to depth D
//! (metres along the optical axis) where the ray meets the ground beyond D or never (sky; buildings become a
//! plane D ahead), and projected into the camera at the previous frame's pose. The device samples the previous
//! image there ([`crate::ops::warp::warp_bilinear`]); a pixel whose source lies outside the previous image or
//! behind its camera keeps its own value. Ground detail (lane markings, crosswalks, kerbs) then lands where the
//! current frame shows it after any ego motion: the logged 0.5 s between frames, or a displacement off the log.
//! Vehicles and tall structures do not; the model corrects them from the layout. Nothing here touches the device.
use anyhow::{ensure, Result};
use glam::{DMat4, DVec3};

use crate::ops::warp::NO_SOURCE;
use crate::projection::CameraProjector;
use crate::scene::camera::Camera;

/// Rays this close to parallel with the ground never meet it (metres of height per metre of depth).
const MIN_DOWN: f64 = 1e-6;
/// A point nearer than this (metres along the previous camera's axis) is behind it: no source.
const MIN_Z: f64 = 0.1;

/// (H, W, 2) source (x, y) of every pixel of `camera` at `cur` (its ego2global) in its image at `prev`, in
/// pixel-index units (centre of pixel i at i, the projection's convention), [`NO_SOURCE`] where the pixel keeps
/// its own value. `size` (H, W) is the render size; `max_depth` D > 0 metres.
pub fn ground_warp_grid(
    camera: &Camera,
    cur: &DMat4,
    prev: &DMat4,
    size: (usize, usize),
    max_depth: f64,
) -> Result<Vec<f32>> {
    ensure!(
        max_depth.is_finite() && max_depth > 0.0,
        "warp: max depth {max_depth} must be a finite number of metres > 0"
    );
    let (h, w) = size;
    let pc = CameraProjector::new(camera, cur, w as u32, h as u32)?;
    let pp = CameraProjector::new(camera, prev, w as u32, h as u32)?;
    let kinv = pc.k.inverse();
    let cam2global = pc.world2cam.inverse();
    let o = pc.position;
    let ground_z = cur.w_axis.z;
    let mut out = Vec::with_capacity(h * w * 2);
    for y in 0..h {
        for x in 0..w {
            // camera-frame ray at depth 1, then its global direction per metre of depth
            let d = cam2global.transform_vector3(kinv * DVec3::new(x as f64, y as f64, 1.0));
            let ground = if d.z < -MIN_DOWN {
                (ground_z - o.z) / d.z
            } else {
                f64::INFINITY
            };
            let q = pp.to_camera(o + d * ground.min(max_depth));
            let src = (q.z > MIN_Z)
                .then(|| pp.pixel_of_camera_point(q))
                .filter(|s| {
                    (-0.5..=w as f64 - 0.5).contains(&s.x) && (-0.5..=h as f64 - 0.5).contains(&s.y)
                });
            match src {
                Some(s) => out.extend([s.x as f32, s.y as f32]),
                None => out.extend([NO_SOURCE, NO_SOURCE]),
            }
        }
    }
    Ok(out)
}

/// [`ground_warp_grid`] of each camera, stacked (N, H, W, 2); `cur[i]` / `prev[i]` camera i's ego2global now and
/// at the previous frame.
pub fn ground_warp_grids(
    cameras: &[Camera],
    cur: &[DMat4],
    prev: &[DMat4],
    size: (usize, usize),
    max_depth: f64,
) -> Result<Vec<f32>> {
    ensure!(
        cameras.len() == cur.len() && cameras.len() == prev.len(),
        "warp: {} cameras, {} current and {} previous poses",
        cameras.len(),
        cur.len(),
        prev.len()
    );
    let mut out = Vec::with_capacity(cameras.len() * size.0 * size.1 * 2);
    for ((c, a), b) in cameras.iter().zip(cur).zip(prev) {
        out.extend(ground_warp_grid(c, a, b, size, max_depth)?);
    }
    Ok(out)
}

/// Which of a camera's two references (0: the front one, 1: the rear one, as retrieved) is its previous-frame
/// base when the model takes it from the references (b2dr.json `prev_source` "reference"): the one whose camera
/// centre lies farthest BEHIND the current camera along its optical axis, so that what the current camera sees
/// lies ahead of it too (CAM_FRONT: the rear reference; CAM_BACK: the front one). Ties: the rear one.
pub fn reference_base_choice(camera: &Camera, cur: &DMat4, refs: [&DMat4; 2]) -> usize {
    let cam = |e2g: &DMat4| *e2g * camera.cam2ego;
    let c = cam(cur);
    let axis = c.z_axis.truncate();
    let depth = |e2g: &DMat4| (cam(e2g).w_axis.truncate() - c.w_axis.truncate()).dot(axis);
    // within a millimetre the two stand level: take the rear one
    if depth(refs[0]) < depth(refs[1]) - 1e-3 {
        0
    } else {
        1
    }
}
