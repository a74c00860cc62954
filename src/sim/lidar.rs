//! The lidar frame of protocol v2 (docs/planner_protocol.md): the frame end-to-end models trained on nuScenes
//! (UniAD, VAD, SparseDrive) see their cameras from and plan in. It is the scenario rig's top lidar
//! ([`crate::scene::CameraRig::lidar2ego`]) riding on the SIMULATED ego at the request time; with the nuScenes
//! mounting its axes are x right, y forward, z up, origin about 1.84 m above the ground and 1 m ahead of the rear
//! axle.
//!
//! Matrices follow mmdet3d's nuScenes convention: `lidar2img = K4 @ lidar2cam` with `K4` the 3x3 intrinsic
//! padded to 4x4 (`viewpad`) and `lidar2cam = inv(cam2ego) @ inv(image_ego2global) @ ego2global @ lidar2ego`
//! (mmdet3d's `sensor2lidar` chain through the global frame). For rendered images the image's ego pose is the
//! request's, so this is `inv(cam2ego) @ lidar2ego`; a replayed log image keeps the log's pose at its exposure.
use glam::{DAffine3, DMat3, DMat4, DVec2, DVec3, DVec4};

use crate::scene::geometry::wrap_angle;

/// The 3x3 intrinsic padded to 4x4 (`[[K, 0], [0, 0, 0, 1]]`, mmdet3d's `viewpad`).
pub fn intrinsic4(k: &DMat3) -> DMat4 {
    DMat4::from_cols(
        k.x_axis.extend(0.0),
        k.y_axis.extend(0.0),
        k.z_axis.extend(0.0),
        DVec4::W,
    )
}

/// Lidar (of the ego at `ego2global`) -> pixel of a camera whose image was taken from `image_ego2global`
/// (module docs). `k`: the intrinsic at the delivered image size; `cam2ego`: camera (x right, y down, z
/// forward) -> ego. A lidar point `p` projects to `(q.x / q.z, q.y / q.z)` with `q = lidar2img @ [p, 1]`, in
/// front of the camera when `q.z > 0`.
pub fn lidar2img(
    k: &DMat3,
    cam2ego: &DMat4,
    image_ego2global: &DMat4,
    ego2global: &DMat4,
    lidar2ego: &DMat4,
) -> DMat4 {
    // affine products and inverses: the last row stays [0, 0, 0, 1] exactly
    let a = |m: &DMat4| DAffine3::from_mat4(*m);
    let lidar2cam =
        a(cam2ego).inverse() * a(image_ego2global).inverse() * a(ego2global) * a(lidar2ego);
    intrinsic4(k) * DMat4::from(lidar2cam)
}

/// The rear-axle pose expressed in the lidar frame: `inv(lidar2ego)`, which maps ego-frame points (x forward,
/// y left, z up, origin on the ground under the rear axle) into the lidar frame.
pub fn ego_in_lidar(lidar2ego: &DMat4) -> DMat4 {
    DMat4::from(DAffine3::from_mat4(*lidar2ego).inverse())
}

/// A lidar-frame plan point `(x, y)` -> the ego-frame ground point `(x, y)`: the lidar point `(x, y, z)` whose
/// ego-frame height is 0 (a trajectory point lies on the ground: nuScenes models' lidar-frame plans are the
/// ego's future ground positions expressed in the lidar frame, with z dropped). `None` when the lidar's z axis
/// lies in the ground plane (no such point).
pub fn lidar_xy_to_ego(lidar2ego: &DMat4, x: f64, y: f64) -> Option<DVec2> {
    let base = lidar2ego.transform_point3(DVec3::new(x, y, 0.0));
    let up = lidar2ego.transform_vector3(DVec3::Z);
    if up.z.abs() < 1e-6 {
        return None;
    }
    let p = base - up * (base.z / up.z);
    Some(p.truncate())
}

/// A lidar-frame heading (about lidar +z, 0 = lidar +x) -> the ego-frame heading of the same direction (its
/// projection onto the ground plane). The result stays within pi of `heading`, so a planner's unwrapped
/// headings stay unwrapped.
pub fn lidar_heading_to_ego(lidar2ego: &DMat4, heading: f64) -> f64 {
    let (s, c) = heading.sin_cos();
    let d = lidar2ego.transform_vector3(DVec3::new(c, s, 0.0));
    heading + wrap_angle(d.y.atan2(d.x) - heading)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::nuscenes_lidar2ego;

    /// The nominal nuScenes mounting: lidar x points right (ego -y), y forward (ego +x), origin 0.99 m ahead
    /// and 1.84 m up; a lidar-frame ground point straight ahead lands on the ego x axis.
    #[test]
    fn nuscenes_lidar_axes() {
        let m = nuscenes_lidar2ego();
        let x = m.transform_vector3(DVec3::X);
        let y = m.transform_vector3(DVec3::Y);
        assert!(x.abs_diff_eq(DVec3::new(0.0, -1.0, 0.0), 0.05), "{x}");
        assert!(y.abs_diff_eq(DVec3::new(1.0, 0.0, 0.0), 0.05), "{y}");
        assert!(m
            .w_axis
            .truncate()
            .abs_diff_eq(DVec3::new(0.986, 0.0, 1.840), 1e-3));
        // lidar (0, 10) is 10 m ahead of the lidar: ego x = 0.986 + 10 (up to the 2-degree tilt), y ~ 0
        let p = lidar_xy_to_ego(&m, 0.0, 10.0).unwrap();
        assert!((p.x - 10.986).abs() < 0.15 && p.y.abs() < 0.15, "{p}");
        // and its ego height is 0 exactly
        let up = m.transform_vector3(DVec3::Z);
        let base = m.transform_point3(DVec3::new(0.0, 10.0, 0.0));
        let z = base.z - up.z * (base.z / up.z);
        assert!(z.abs() < 1e-12);
        // lidar heading pi/2 (along lidar +y) is ego heading ~0
        let h = lidar_heading_to_ego(&m, std::f64::consts::FRAC_PI_2);
        assert!(h.abs() < 0.05, "{h}");
        // ego_in_lidar maps the rear axle to ~(0, -0.99, -1.84) in the lidar frame
        let o = ego_in_lidar(&m).transform_point3(DVec3::ZERO);
        assert!(o.abs_diff_eq(DVec3::new(0.0, -0.986, -1.840), 0.1), "{o}");
    }
}
