//! Projection on hand-built cameras: point projection, near-plane clipping, culling, mask areas, intrinsics
//! rescaling (PyTorch align_corners=False semantics), retrieval on synthetic logs, PETR position encodings.
use b2dr::projection::geometry::{MapClass, MapElement, MapGeometry, BOX_EDGES};
use b2dr::projection::pe::{depth_bins, inverse_sigmoid, position_encoding, PeConfig, PixelGrid};
use b2dr::projection::retrieval::{retrieve, sample_training_references};
use b2dr::projection::{
    box_wireframe, Box3d, BoxClass, CameraProjector, LayoutMasks, LayoutRenderer, MapLayer,
    ProjectionConfig,
};
use b2dr::scene::camera::{Camera, CameraImage, RecordedFrame};
use glam::{DMat3, DMat4, DQuat, DVec3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// A forward-looking camera at `pos` (ego frame): camera z = ego x, camera x = -ego y, camera y = -ego z.
fn front_camera(f: f64, w: u32, h: u32, pos: DVec3) -> Camera {
    let cam2ego = DMat4::from_cols(
        DVec3::new(0.0, -1.0, 0.0).extend(0.0),
        DVec3::new(0.0, 0.0, -1.0).extend(0.0),
        DVec3::new(1.0, 0.0, 0.0).extend(0.0),
        pos.extend(1.0),
    );
    let (cx, cy) = (w as f64 / 2.0 - 0.5, h as f64 / 2.0 - 0.5);
    Camera {
        name: "CAM_FRONT".into(),
        intrinsic: DMat3::from_cols(
            DVec3::new(f, 0.0, 0.0),
            DVec3::new(0.0, f, 0.0),
            DVec3::new(cx, cy, 1.0),
        ),
        cam2ego,
        width: w,
        height: h,
        distortion: [0.0; 5],
    }
}

fn pose(yaw: f64, t: DVec3) -> DMat4 {
    DMat4::from_rotation_translation(DQuat::from_rotation_z(yaw), t)
}

fn count(m: &[u8]) -> usize {
    m.iter().filter(|&&v| v != 0).count()
}

#[test]
fn known_points_project_to_known_pixels() {
    let cam = front_camera(1000.0, 1600, 900, DVec3::new(1.0, 0.0, 1.5));
    // ego at (100, 50) heading +y (yaw 90 deg): ego x = global +y, ego y = global -x
    let e2g = pose(std::f64::consts::FRAC_PI_2, DVec3::new(100.0, 50.0, 0.0));
    let p = CameraProjector::new(&cam, &e2g, 1600, 900).unwrap();
    // ego point (11, 1, 2.0): camera (-1, -0.5, 10) -> u = 799.5 - 100, v = 449.5 - 50
    let g = e2g.transform_point3(DVec3::new(11.0, 1.0, 2.0));
    let (px, d) = p.project(g).unwrap();
    assert!(
        (px.x - 699.5).abs() < 1e-9 && (px.y - 399.5).abs() < 1e-9,
        "{px:?}"
    );
    assert!((d - 10.0).abs() < 1e-12);
    // behind the camera: no projection
    assert!(p
        .project(e2g.transform_point3(DVec3::new(-5.0, 0.0, 1.5)))
        .is_none());
    // the camera centre is where the pose puts it
    assert!((p.position - e2g.transform_point3(DVec3::new(1.0, 0.0, 1.5))).length() < 1e-12);
}

#[test]
fn box_half_behind_camera_is_clipped_not_wrapped() {
    // f = 400 on 1600x900; camera at the ego origin (height 0) looking along ego +x.
    let f = 400.0;
    let cam = front_camera(f, 1600, 900, DVec3::ZERO);
    let p = CameraProjector::new(&cam, &DMat4::IDENTITY, 1600, 900).unwrap();
    // camera-frame box x in [1, 3] (ego y in [-3, -1]), y in [-1, 1], z in [-2, 2]: half behind the camera.
    let b = Box3d {
        class: BoxClass::Car,
        center: DVec3::new(0.0, -2.0, 0.0),
        size: DVec3::new(4.0, 2.0, 2.0),
        yaw: 0.0,
    };
    let cfg = ProjectionConfig {
        near: 0.1,
        ..Default::default()
    };
    let mut r = LayoutRenderer::new(1600, 900);
    let mut m = LayoutMasks::new(1600, 900);
    assert_eq!(r.render(&p, &[b], &MapLayer::default(), &cfg, &mut m), 1);
    let car = m.channel(BoxClass::Car.index());
    // Silhouette of the clipped solid: X = x/z >= 0.5 and |Y| <= min(X, 10) (X, Y normalised coordinates), so in
    // pixels t = u - cx in [200, 800], |v - cy| <= min(t, 450) inside the image: area 477,500 px.
    let n = count(car);
    assert!(
        (n as f64 - 477_500.0).abs() / 477_500.0 < 0.01,
        "covered {n}"
    );
    // nothing on the mirrored side (a wrapped projection of the corners behind the camera would land there)
    for v in 0..900 {
        for u in 0..(799 + 199) {
            assert_eq!(car[v * 1600 + u], 0, "pixel ({u}, {v}) set");
        }
    }
    // wireframe: every clipped edge end lies in the visible wedge u - cx >= 0.5 f
    let segs = box_wireframe(&p, &b, &cfg).unwrap();
    assert!(segs.len() >= 8 && segs.len() < BOX_EDGES.len() + 1);
    for (a, c) in segs {
        assert!(
            a.x >= 799.5 + 0.5 * f - 1e-6 && c.x >= 799.5 + 0.5 * f - 1e-6,
            "{a:?} {c:?}"
        );
    }
}

#[test]
fn culling_by_frustum_and_range() {
    let cam = front_camera(1000.0, 1600, 900, DVec3::new(1.5, 0.0, 1.5));
    let e2g = pose(0.3, DVec3::new(-20.0, 7.0, 0.0));
    let p = CameraProjector::new(&cam, &e2g, 400, 224).unwrap();
    let cfg = ProjectionConfig::default(); // range 80 m
    let at = |x: f64, y: f64| Box3d {
        class: BoxClass::Pedestrian,
        center: e2g.transform_point3(DVec3::new(x, y, 1.0)),
        size: DVec3::new(0.7, 0.7, 1.8),
        yaw: 0.0,
    };
    assert!(
        p.box_corners_camera(&at(20.0, 0.0), &cfg).is_some(),
        "in view"
    );
    assert!(
        p.box_corners_camera(&at(-10.0, 0.0), &cfg).is_none(),
        "behind"
    );
    assert!(
        p.box_corners_camera(&at(5.0, 30.0), &cfg).is_none(),
        "left of the frustum"
    );
    assert!(
        p.box_corners_camera(&at(90.0, 0.0), &cfg).is_none(),
        "beyond range"
    );
    assert!(
        p.box_corners_camera(&at(79.0, 0.0), &cfg).is_some(),
        "just within range"
    );
    let far = ProjectionConfig {
        range: 100.0,
        ..cfg
    };
    assert!(
        p.box_corners_camera(&at(90.0, 0.0), &far).is_some(),
        "range is configurable"
    );
    // half-FOV of this camera is atan(800/1000) = 38.7 deg: a box straddling the edge is kept
    let edge = 20.0 * (800.0f64 / 1000.0);
    assert!(
        p.box_corners_camera(&at(21.5, edge + 0.2), &cfg).is_some(),
        "straddles the left edge"
    );
    let mut r = LayoutRenderer::new(400, 224);
    let mut m = LayoutMasks::new(400, 224);
    let boxes = [at(20.0, 0.0), at(-10.0, 0.0), at(5.0, 30.0), at(90.0, 0.0)];
    assert_eq!(r.render(&p, &boxes, &MapLayer::default(), &cfg, &mut m), 1);
}

#[test]
fn box_mask_covers_expected_pixel_count() {
    // face-on box centred on the optical axis: its silhouette is the near face, 2 m x 1.5 m at 10 m.
    let cam = front_camera(1000.0, 1600, 900, DVec3::ZERO);
    let p = CameraProjector::new(&cam, &DMat4::IDENTITY, 1600, 900).unwrap();
    let b = Box3d {
        class: BoxClass::Truck,
        center: DVec3::new(12.0, 0.0, 0.0),
        size: DVec3::new(4.0, 2.0, 1.5),
        yaw: 0.0,
    };
    let mut r = LayoutRenderer::new(1600, 900);
    let mut m = LayoutMasks::new(1600, 900);
    r.render(
        &p,
        &[b],
        &MapLayer::default(),
        &ProjectionConfig::default(),
        &mut m,
    );
    let n = count(m.channel(BoxClass::Truck.index()));
    assert!(
        (n as f64 - 30_000.0).abs() / 30_000.0 < 0.01,
        "covered {n}, expected 200 x 150"
    );
    assert_eq!(count(m.channel(BoxClass::Car.index())), 0);
    // the same box at render resolution 400x224: (1000 * 0.25 * 0.2) x (1000 * 224/900 * 0.15) px
    let p = CameraProjector::new(&cam, &DMat4::IDENTITY, 400, 224).unwrap();
    let mut r = LayoutRenderer::new(400, 224);
    let mut m = LayoutMasks::new(400, 224);
    let big = Box3d {
        size: DVec3::new(4.0, 6.0, 4.0),
        ..b
    };
    r.render(
        &p,
        &[big],
        &MapLayer::default(),
        &ProjectionConfig::default(),
        &mut m,
    );
    let expect = (250.0 * 0.6) * (1000.0 * 224.0 / 900.0 * 0.4);
    let n = count(m.channel(BoxClass::Truck.index())) as f64;
    assert!(
        (n - expect).abs() / expect < 0.01,
        "covered {n}, expected {expect}"
    );
}

#[test]
fn map_polygons_and_polylines() {
    let cam = front_camera(1000.0, 1600, 900, DVec3::new(0.0, 0.0, 1.5));
    let p = CameraProjector::new(&cam, &DMat4::IDENTITY, 400, 224).unwrap();
    let q = |x: f64, y: f64| DVec3::new(x, y, 0.0);
    let map = MapLayer::new(vec![
        // a road 8 m wide from behind the ego to 200 m ahead (crosses the camera plane, beyond range)
        MapElement {
            class: MapClass::DrivableArea,
            geometry: MapGeometry::Polygon {
                exterior: vec![q(-50.0, -4.0), q(200.0, -4.0), q(200.0, 4.0), q(-50.0, 4.0)],
                holes: vec![],
            },
        },
        // a divider on the left, also starting behind the camera
        MapElement {
            class: MapClass::LaneDivider,
            geometry: MapGeometry::Polyline(vec![q(-20.0, 2.0), q(60.0, 2.0)]),
        },
        // a crosswalk far beyond the range: culled
        MapElement {
            class: MapClass::Crosswalk,
            geometry: MapGeometry::Polygon {
                exterior: vec![q(150.0, -4.0), q(154.0, -4.0), q(154.0, 4.0), q(150.0, 4.0)],
                holes: vec![],
            },
        },
    ]);
    let mut r = LayoutRenderer::new(400, 224);
    let mut m = LayoutMasks::new(400, 224);
    r.render(&p, &[], &map, &ProjectionConfig::default(), &mut m);
    let nb = BoxClass::ALL.len();
    let da = m.channel(nb + MapClass::DrivableArea.index());
    let k = cam.intrinsic_scaled(400, 224);
    let (cx, cy, fy) = (k.z_axis.x, k.z_axis.y, k.y_axis.y);
    // the road lies below the horizon; clipped at 80 m depth: v >= cy + fy * 1.5 / 80
    let v_far = cy + fy * 1.5 / 80.0;
    for v in 0..224 {
        for u in 0..400 {
            if da[v * 400 + u] != 0 {
                assert!(
                    v as f64 >= v_far - 1.0,
                    "drivable pixel above the 80 m line at ({u}, {v})"
                );
            }
        }
    }
    // bottom row centre is road (ground 1.5 m below the camera at depth ~2.8 m): set
    assert_eq!(da[223 * 400 + 200], 1);
    assert!(count(da) > 5_000);
    // divider at y = +2 (left): all its pixels are left of the principal point, none wrapped to the right
    let div = m.channel(nb + MapClass::LaneDivider.index());
    assert!(count(div) > 50);
    for v in 0..224 {
        for u in 0..400 {
            if div[v * 400 + u] != 0 {
                assert!((u as f64) < cx + 2.0, "divider pixel at ({u}, {v})");
            }
        }
    }
    assert_eq!(count(m.channel(nb + MapClass::Crosswalk.index())), 0);
}

/// PyTorch `upsample_bilinear2d(align_corners=False)` source coordinate of output pixel `dst` (scale = in / out),
/// `area_pixel_compute_source_index` in aten/src/ATen/native/UpSample.h, clamped at 0 for linear modes.
fn torch_src_index(dst: usize, in_size: usize, out_size: usize) -> f64 {
    let scale = in_size as f64 / out_size as f64;
    (scale * (dst as f64 + 0.5) - 0.5).max(0.0)
}

/// 1-D bilinear resize (PyTorch semantics) of `x`.
fn torch_resize_1d(x: &[f64], out: usize) -> Vec<f64> {
    (0..out)
        .map(|j| {
            let s = torch_src_index(j, x.len(), out);
            let i0 = (s.floor() as usize).min(x.len() - 1);
            let i1 = (i0 + 1).min(x.len() - 1);
            let l = s - i0 as f64;
            x[i0] * (1.0 - l) + x[i1] * l
        })
        .collect()
}

fn sample_linear(x: &[f64], u: f64) -> f64 {
    let i0 = u.floor() as usize;
    let l = u - i0 as f64;
    x[i0] * (1.0 - l) + x[i0 + 1] * l
}

#[test]
fn intrinsics_rescaling_matches_torch_resize() {
    let mut cam = front_camera(1266.4, 1600, 900, DVec3::ZERO);
    cam.intrinsic.z_axis = DVec3::new(816.27, 491.51, 1.0);
    let k = cam.intrinsic_scaled(400, 224);
    let (sx, sy) = (0.25, 224.0 / 900.0);
    assert!((k.x_axis.x - 1266.4 * sx).abs() < 1e-12 && (k.y_axis.y - 1266.4 * sy).abs() < 1e-12);
    assert!((k.z_axis.x - ((816.27 + 0.5) * sx - 0.5)).abs() < 1e-12);
    assert!((k.z_axis.y - ((491.51 + 0.5) * sy - 0.5)).abs() < 1e-12);
    let r = cam.rescaled(400, 224);
    assert_eq!((r.width, r.height), (400, 224));
    assert!(
        cam.intrinsic_scaled(1600, 900)
            .abs_diff_eq(cam.intrinsic, 1e-9),
        "identity at the native size"
    );

    // Ramp images whose value is the native coordinate (pixel centre i at coordinate i), resized with PyTorch's
    // bilinear rule: sampling the resized ramp at the rescaled projection must give back the native projection.
    for &(nw, nh, rw, rh) in &[
        (1600usize, 900usize, 400usize, 224usize),
        (1920, 1080, 400, 224),
        (640, 480, 1280, 960),
    ] {
        let mut c = cam.clone();
        c.width = nw as u32;
        c.height = nh as u32;
        let f = 0.8 * nw as f64;
        c.intrinsic = DMat3::from_cols(
            DVec3::new(f, 0.0, 0.0),
            DVec3::new(0.0, f, 0.0),
            DVec3::new(nw as f64 * 0.51, nh as f64 * 0.54, 1.0),
        );
        let ramp_u = torch_resize_1d(&(0..nw).map(|i| i as f64).collect::<Vec<_>>(), rw);
        let ramp_v = torch_resize_1d(&(0..nh).map(|i| i as f64).collect::<Vec<_>>(), rh);
        let pn = CameraProjector::new(&c, &DMat4::IDENTITY, nw as u32, nh as u32).unwrap();
        let pr = CameraProjector::new(&c, &DMat4::IDENTITY, rw as u32, rh as u32).unwrap();
        for &(y, z) in &[(1.3, 0.4), (-2.0, -0.7), (0.0, 0.0), (3.1, 1.2)] {
            let g = DVec3::new(10.0, y, z);
            let (un, _) = pn.project(g).unwrap();
            let (ur, _) = pr.project(g).unwrap();
            assert!(ur.x > 1.0 && ur.x < rw as f64 - 2.0 && ur.y > 1.0 && ur.y < rh as f64 - 2.0);
            let (bu, bv) = (sample_linear(&ramp_u, ur.x), sample_linear(&ramp_v, ur.y));
            assert!(
                (bu - un.x).abs() < 1e-9 && (bv - un.y).abs() < 1e-9,
                "{nw}->{rw}: {bu} vs {}",
                un.x
            );
        }
    }
}

fn log_along(points: &[(f64, f64)], yaw: f64) -> Vec<RecordedFrame> {
    points
        .iter()
        .enumerate()
        .map(|(i, &(x, y))| {
            let e2g = pose(yaw, DVec3::new(x, y, 0.0));
            RecordedFrame {
                timestamp_us: i as i64 * 100_000,
                ego2global: e2g,
                images: vec![
                    CameraImage {
                        camera: "CAM_BACK".into(),
                        path: format!("b{i}.jpg"),
                        timestamp_us: 0,
                        ego2global: e2g,
                    },
                    CameraImage {
                        camera: "CAM_FRONT".into(),
                        path: format!("f{i}.jpg"),
                        timestamp_us: 0,
                        // the front camera fires 10 ms later: 5 cm further along
                        ego2global: pose(
                            yaw,
                            DVec3::new(x, y, 0.0)
                                + DQuat::from_rotation_z(yaw) * DVec3::new(0.05, 0.0, 0.0),
                        ),
                    },
                ],
            }
        })
        .collect()
}

#[test]
fn retrieval_front_rear_and_missing_side() {
    let yaw = 1.0f64;
    let dir = DVec3::new(yaw.cos(), yaw.sin(), 0.0);
    let pts: Vec<(f64, f64)> = (0..21)
        .map(|i| (dir.x * i as f64, dir.y * i as f64))
        .collect();
    // shuffle the order: retrieval must not rely on it
    let mut frames = log_along(&pts, yaw);
    frames.reverse();
    let ego = pose(yaw, dir * 10.3 + DVec3::new(-dir.y, dir.x, 0.0) * 0.5); // 0.5 m to the left of the path
    let r = retrieve(&frames, "CAM_FRONT", &ego);
    let (f, b) = (r.front.unwrap(), r.rear.unwrap());
    assert_eq!(frames[f.frame].images[f.image].path, "f11.jpg");
    assert_eq!(frames[b.frame].images[b.image].path, "f10.jpg");
    assert!(
        (f.along - 0.75).abs() < 1e-9 && (b.along + 0.25).abs() < 1e-9,
        "{} {}",
        f.along,
        b.along
    );
    // relative pose: the front reference ego sits 0.75 m ahead and 0.5 m to the right of the current ego
    let t = f.ref2cur.w_axis.truncate();
    assert!((t - DVec3::new(0.75, -0.5, 0.0)).length() < 1e-9, "{t:?}");
    // the reference's camera -> current ego equals the position-encoding helper's
    let cam = front_camera(1000.0, 1600, 900, DVec3::new(1.7, 0.0, 1.5));
    let via_pe =
        b2dr::projection::pe::cam2cur(&cam, &frames[f.frame].images[f.image].ego2global, &ego);
    assert!(f.cam2cur(&cam).abs_diff_eq(via_pe, 1e-9));
    let rb = retrieve(&frames, "CAM_BACK", &ego);
    let rf = rb.front.unwrap();
    assert_eq!(frames[rf.frame].images[rf.image].path, "b11.jpg");
    // beyond the end of the log: nothing ahead
    let r = retrieve(&frames, "CAM_FRONT", &pose(yaw, dir * 25.0));
    assert!(r.front.is_none());
    assert_eq!(
        frames[r.rear.as_ref().unwrap().frame].images[0].path,
        "b20.jpg"
    );
    // turned around: what was ahead is now behind
    let r = retrieve(
        &frames,
        "CAM_FRONT",
        &pose(yaw + std::f64::consts::PI, dir * 10.3),
    );
    assert_eq!(frames[r.front.unwrap().frame].images[1].path, "f10.jpg");
    // unknown camera / empty log: nothing on either side
    assert_eq!(retrieve(&frames, "CAM_X", &ego), Default::default());
    assert_eq!(retrieve(&[], "CAM_FRONT", &ego), Default::default());
}

#[test]
fn hierarchical_training_sampling() {
    let pts: Vec<(f64, f64)> = (0..161).map(|i| (i as f64 * 0.25, 0.0)).collect(); // 0..40 m every 25 cm
    let frames = log_along(&pts, 0.0);
    let train = 80; // at 20 m: 20 m of log on both sides
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut hist = [[0usize; 3]; 2];
    let n = 20_000;
    for _ in 0..n {
        let r = sample_training_references(&frames, "CAM_FRONT", train, &mut rng);
        for (side, rf) in [r.front.unwrap(), r.rear.unwrap()].iter().enumerate() {
            let d = rf.along.abs();
            assert!((2.0..15.0).contains(&d), "distance {d}");
            assert_eq!(rf.along > 0.0, side == 0);
            hist[side][if d < 5.0 {
                0
            } else if d < 10.0 {
                1
            } else {
                2
            }] += 1;
        }
    }
    for h in hist {
        for (k, p) in [0.1, 0.3, 0.6].iter().enumerate() {
            let f = h[k] as f64 / n as f64;
            assert!((f - p).abs() < 0.015, "interval {k}: {f} vs {p}");
        }
    }
    // seeded: same seed, same draws
    let a = sample_training_references(
        &frames,
        "CAM_FRONT",
        train,
        &mut ChaCha8Rng::seed_from_u64(3),
    );
    let b = sample_training_references(
        &frames,
        "CAM_FRONT",
        train,
        &mut ChaCha8Rng::seed_from_u64(3),
    );
    assert_eq!(a, b);
    // at the end of the log nothing ahead; only 3 m of log behind -> only the first interval
    let end = sample_training_references(&frames, "CAM_FRONT", 160, &mut rng);
    assert!(end.front.is_none() && end.rear.is_some());
    let near_start = sample_training_references(&frames, "CAM_FRONT", 12, &mut rng);
    assert!(near_start.rear.unwrap().along.abs() < 3.0 + 1e-9);
}

#[test]
fn position_encoding_matches_direct_computation() {
    let mut cam = front_camera(1266.4, 1600, 900, DVec3::new(1.7, 0.02, 1.5));
    cam.intrinsic.z_axis = DVec3::new(816.3, 491.5, 1.0);
    // a reference image taken 6 m ahead and slightly turned, seen from the current ego
    let cur = pose(0.2, DVec3::new(5.0, 3.0, 0.0));
    let refp = pose(
        0.25,
        DVec3::new(5.0 + 6.0 * 0.2f64.cos(), 3.0 + 6.0 * 0.2f64.sin(), 0.1),
    );
    let c2c = b2dr::projection::pe::cam2cur(&cam, &refp, &cur);
    let (h, w) = (7, 13);
    for grid in [PixelGrid::Centre, PixelGrid::PetrCorner] {
        let cfg = PeConfig {
            grid,
            ..Default::default()
        };
        let k = cam.intrinsic_scaled(400, 224);
        let pe = position_encoding(&k, 400, 224, &c2c, h, w, &cfg).unwrap();
        assert_eq!(pe.len(), 64 * 3 * h * w);
        // direct: plain f64 arithmetic with row-major matrices
        let (fx, fy, cx, cy) = (k.x_axis.x, k.y_axis.y, k.z_axis.x, k.z_axis.y);
        let m = (cur.inverse() * refp * cam.cam2ego).to_cols_array_2d(); // m[col][row]
        let range = [-61.2, -61.2, -10.0, 61.2, 61.2, 10.0];
        let mut maxerr = 0f64;
        for di in 0..64 {
            let d = 1.0 + (61.2 - 1.0) / (64.0 * 65.0) * (di * (di + 1)) as f64;
            for y in 0..h {
                for x in 0..w {
                    let (u, v) = match grid {
                        PixelGrid::Centre => (
                            (x as f64 + 0.5) * 400.0 / w as f64 - 0.5,
                            (y as f64 + 0.5) * 224.0 / h as f64 - 0.5,
                        ),
                        PixelGrid::PetrCorner => {
                            (x as f64 * 400.0 / w as f64, y as f64 * 224.0 / h as f64)
                        }
                    };
                    let pc = [(u - cx) / fx * d, (v - cy) / fy * d, d];
                    for a in 0..3 {
                        let g = m[0][a] * pc[0] + m[1][a] * pc[1] + m[2][a] * pc[2] + m[3][a];
                        let nrm = ((g - range[a]) / (range[a + 3] - range[a])).clamp(0.0, 1.0);
                        let want = (nrm.max(1e-5) / (1.0 - nrm).max(1e-5)).ln();
                        let got = pe[(di * 3 + a) * h * w + y * w + x] as f64;
                        maxerr = maxerr.max((got - want).abs());
                    }
                }
            }
        }
        assert!(maxerr < 1e-4, "{grid:?}: max error {maxerr}");
    }
    let d = depth_bins(&PeConfig::default());
    assert!((d[1] - (1.0 + 60.2 / 4160.0 * 2.0)).abs() < 1e-12);
    assert!((inverse_sigmoid(0.0, 1e-5) + 11.512925464970229).abs() < 1e-9);
}

#[test]
fn box_z_reading_is_detected_from_vehicle_bottoms() {
    use b2dr::projection::geometry::{Box3d, BoxClass};
    use b2dr::projection::keyframe::KeyFrame;
    use glam::{DMat4, DVec3};
    let frame = |z_of: &dyn Fn(f64) -> f64, n: usize| KeyFrame {
        dir: std::path::PathBuf::new(),
        // the ego stands at z = 2 m (a sloped city): bottoms are measured against it
        ego2global: DMat4::from_translation(DVec3::new(10.0, 20.0, 2.0)),
        cameras: vec![],
        boxes: (0..n)
            .map(|i| {
                let h = 1.5 + 0.5 * i as f64;
                Box3d {
                    class: BoxClass::Car,
                    center: DVec3::new(i as f64 * 5.0, 0.0, 2.0 + z_of(h)),
                    size: DVec3::new(4.5, 1.9, h),
                    yaw: 0.0,
                }
            })
            .collect(),
    };
    // documented format: z = gravity centre = h / 2 above the ground
    assert!(!frame(&|h| 0.5 * h, 5).z_looks_like_top());
    // top face: z = h above the ground
    assert!(frame(&|h| h, 5).z_looks_like_top());
    // too few vehicles to tell: the documented reading
    assert!(!frame(&|h| h, 2).z_looks_like_top());
}
