//! The lidar frame of planner protocol v2 (issue #34 item 2): the `lidar2ego` of the `start` message and the
//! per-camera `lidar2img` of the `plan` message project 3D points given in the lidar frame onto the same pixels
//! as b2dr's own projection (`CameraProjector`) of the same global points, within 1 px: on every camera of the
//! synthetic rig (native and delivered sizes), and on the shared real nuScenes keyframe (each camera with its
//! own ego pose at exposure; skipped with a printed reason when `../shared/data` is absent).
mod common;

use std::path::PathBuf;

use b2dr::projection::geometry::mat4_from_rows;
use b2dr::projection::{CameraProjector, KeyFrame};
use b2dr::scene::camera::{nuscenes_lidar2ego, Camera};
use b2dr::scene::import::ego2global;
use b2dr::sim::external::{camera_entry, start_message};
use b2dr::world::town as synthetic;
use common::frame_without_pixels as frame;
use glam::{DMat4, DVec3, DVec4};
use serde_json::Value;

fn rows4(v: &Value) -> DMat4 {
    let rows: [[f64; 4]; 4] = serde_json::from_value(v.clone()).expect("a 4x4 matrix of rows");
    mat4_from_rows(&rows)
}

/// Projects lidar-frame points with a message's `lidar2img` and compares with b2dr's projection of the global
/// points; returns (points compared, largest pixel difference, largest difference with the lidar frame taken
/// for the ego frame).
#[allow(clippy::too_many_arguments)]
fn compare(
    cam: &Camera,
    image_ego2global: DMat4,
    ego2global_now: DMat4,
    lidar2ego: DMat4,
    ego_in_lidar: DMat4,
    points: &[DVec3],
    w: u32,
    h: u32,
) -> (usize, f64, f64) {
    let entry = camera_entry(
        &frame(cam, image_ego2global, w, h),
        &ego2global_now,
        &lidar2ego,
    );
    let l2i = rows4(&entry["lidar2img"]);
    // the last row of lidar2img is [0, 0, 0, 1] and its third row gives the depth
    assert_eq!(l2i.row(3), DVec4::W, "{}", cam.name);
    let proj = CameraProjector::new(cam, &image_ego2global, w, h).unwrap();
    let (mut n, mut worst, mut wrong) = (0, 0f64, 0f64);
    for &p in points {
        let Some((want, depth)) = proj.project(p) else {
            continue;
        };
        if depth < 1.0 || !proj.in_image(want) {
            continue;
        }
        let p_lidar = ego_in_lidar.transform_point3(ego2global_now.inverse().transform_point3(p));
        let q = l2i * p_lidar.extend(1.0);
        assert!(q.z > 0.0, "{}: in front of the camera", cam.name);
        assert!(
            (q.z - depth).abs() < 1e-6,
            "{}: depth {} vs {depth}",
            cam.name,
            q.z
        );
        let got = glam::DVec2::new(q.x / q.z, q.y / q.z);
        worst = worst.max(got.distance(want));
        // the same matrix fed ego-frame points (a lidar frame mistaken for the ego frame) misses by far
        let e = l2i * ego2global_now.inverse().transform_point3(p).extend(1.0);
        if e.z > 0.0 {
            wrong = wrong.max(glam::DVec2::new(e.x / e.z, e.y / e.z).distance(want));
        } else {
            wrong = f64::INFINITY;
        }
        n += 1;
    }
    (n, worst, wrong)
}

#[test]
fn lidar2img_matches_b2dr_projection_on_the_synthetic_rig() {
    let sc = synthetic::town(1, None);
    let start = start_message(&sc);
    let lidar2ego = rows4(&start["lidar2ego"]);
    assert!(lidar2ego.abs_diff_eq(nuscenes_lidar2ego(), 1e-12));
    assert!(sc.rig.lidar2ego.abs_diff_eq(nuscenes_lidar2ego(), 0.0));
    let ego_in_lidar = lidar2ego.inverse();
    let mut total = 0;
    for k in [0usize, 40, 100] {
        let e2g = ego2global(&sc.ego[k].rear_axle);
        // box centres and corners of this log step
        let points: Vec<DVec3> = b2dr::projection::scene::boxes_at(&sc, k)
            .iter()
            .flat_map(|(_, b)| std::iter::once(b.center).chain(b.corners()))
            .collect();
        assert!(points.len() > 40, "step {k}: {} points", points.len());
        for cam in &sc.rig.cameras {
            for (w, h) in [(cam.width, cam.height), (200, 112), (400, 224)] {
                let (n, worst, wrong) =
                    compare(cam, e2g, e2g, lidar2ego, ego_in_lidar, &points, w, h);
                assert!(worst <= 1.0, "step {k} {} at {w}x{h}: {worst} px", cam.name);
                if n > 0 {
                    assert!(wrong > 5.0, "step {k} {}: the frames must matter", cam.name);
                }
                total += n;
            }
        }
    }
    eprintln!("synthetic rig: {total} box points compared within 1 px");
    assert!(total > 300, "{total}");
}

#[test]
fn lidar2img_matches_b2dr_projection_on_the_shared_nuscenes_keyframe() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/nuscenes-mini/keyframe-scene-0061/frame.json");
    if !path.is_file() {
        println!(
            "SKIP: {} absent (the shared nuScenes data lives outside the repository)",
            path.display()
        );
        return;
    }
    let kf = KeyFrame::load(&path).unwrap();
    // frame.json carries no lidar calibration: the nominal nuScenes LIDAR_TOP mounting. The lidar frame rides
    // on the keyframe's (lidar time) ego pose; each camera fired at its own time with its own ego pose.
    let lidar2ego = nuscenes_lidar2ego();
    let points: Vec<DVec3> = kf
        .boxes
        .iter()
        .flat_map(|b| std::iter::once(b.center).chain(b.corners()))
        .collect();
    let (mut total, mut worst_all, mut moved) = (0, 0f64, 0f64);
    for (cam, img) in &kf.cameras {
        for (w, h) in [(cam.width, cam.height), (400, 224)] {
            let (n, worst, _) = compare(
                cam,
                img.ego2global,
                kf.ego2global,
                lidar2ego,
                lidar2ego.inverse(),
                &points,
                w,
                h,
            );
            assert!(worst <= 1.0, "{} at {w}x{h}: {worst} px", cam.name);
            worst_all = worst_all.max(worst);
            total += n;
        }
        // how far the camera's exposure pose is from the keyframe's (what the lidar2img chain accounts for)
        moved = moved.max(
            (img.ego2global.w_axis - kf.ego2global.w_axis)
                .truncate()
                .length(),
        );
    }
    eprintln!(
        "nuScenes keyframe: {total} box points compared, largest difference {worst_all:.2e} px; camera exposure \
         poses up to {moved:.3} m from the keyframe's"
    );
    assert!(total > 200, "{total}");
}
