//! The previous frame's warp grid (render::warp) against closed-form flat-ground geometry: a level camera at
//! height h sees the ground at depth Z = h f / (v - cy); after the ego drives dx forward, the camera 0.5 s
//! earlier saw that point at depth Z + dx.
use b2dr::ops::warp::NO_SOURCE;
use b2dr::render::warp::{ground_warp_grid, ground_warp_grids};
use b2dr::scene::camera::Camera;
use glam::{DMat3, DMat4, DVec3};

const H: usize = 112;
const W: usize = 200;
const F: f64 = 100.0;
const CX: f64 = 99.5;
const CY: f64 = 55.5;
const CAM_H: f64 = 1.5;

fn front() -> Camera {
    Camera {
        name: "CAM_FRONT".into(),
        intrinsic: DMat3::from_cols(
            DVec3::new(F, 0.0, 0.0),
            DVec3::new(0.0, F, 0.0),
            DVec3::new(CX, CY, 1.0),
        ),
        // x_cam = -y_ego (right), y_cam = -z_ego (down), z_cam = x_ego (forward), CAM_H above the ego origin
        cam2ego: DMat4::from_cols_array_2d(&[
            [0.0, -1.0, 0.0, 0.0],
            [0.0, 0.0, -1.0, 0.0],
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, CAM_H, 1.0],
        ]),
        width: W as u32,
        height: H as u32,
        distortion: [0.0; 5],
    }
}

fn at(g: &[f32], x: usize, y: usize) -> (f64, f64) {
    let i = 2 * (y * W + x);
    (g[i] as f64, g[i + 1] as f64)
}

#[test]
fn same_pose_is_the_identity() {
    let pose = DMat4::from_translation(DVec3::new(12.0, -3.0, 0.4)) * DMat4::from_rotation_z(0.3);
    let g = ground_warp_grid(&front(), &pose, &pose, (H, W), 30.0).unwrap();
    for y in 0..H {
        for x in 0..W {
            let (sx, sy) = at(&g, x, y);
            assert!(
                (sx - x as f64).abs() < 1e-3 && (sy - y as f64).abs() < 1e-3,
                "({x}, {y}) -> ({sx}, {sy})"
            );
        }
    }
}

#[test]
fn forward_motion_matches_flat_ground_geometry() {
    let (dx, d) = (5.0, 30.0);
    // the ground plane is the current ego origin's height (here 2 m above global zero)
    let cur = DMat4::from_translation(DVec3::new(40.0, 7.0, 2.0));
    let prev = DMat4::from_translation(DVec3::new(40.0 - dx, 7.0, 2.0));
    let g = ground_warp_grid(&front(), &cur, &prev, (H, W), d).unwrap();
    let mut checked = (0, 0);
    for y in 0..H {
        for x in (0..W).step_by(7) {
            let (sx, sy) = at(&g, x, y);
            let (u, v) = (x as f64 - CX, y as f64 - CY);
            // depth along the axis: the ground, or the cap D (above the horizon, or ground beyond D)
            let z = if v > 0.0 { (CAM_H * F / v).min(d) } else { d };
            let (wx, wy) = (CX + u * z / (z + dx), CY + v * z / (z + dx));
            assert!(
                (sx - wx).abs() < 1e-3 && (sy - wy).abs() < 1e-3,
                "({x}, {y}): ({sx}, {sy}), want ({wx}, {wy})"
            );
            if v > 0.0 && CAM_H * F / v < d {
                checked.0 += 1;
            } else {
                checked.1 += 1;
            }
        }
    }
    assert!(
        checked.0 > 100 && checked.1 > 100,
        "ground and capped pixels both checked: {checked:?}"
    );
}

#[test]
fn sources_outside_or_behind_the_previous_camera_keep_the_pixel() {
    // the previous frame was taken 20 m AHEAD: the near ground lies behind its camera, the image's edges
    // outside it
    let cur = DMat4::IDENTITY;
    let prev = DMat4::from_translation(DVec3::new(20.0, 0.0, 0.0));
    let g = ground_warp_grid(&front(), &cur, &prev, (H, W), 30.0).unwrap();
    let bottom = at(&g, W / 2, H - 1);
    assert_eq!(bottom, (NO_SOURCE as f64, NO_SOURCE as f64));
    for v in g.chunks(2) {
        let ok = (-0.5..=W as f64 - 0.5).contains(&(v[0] as f64))
            && (-0.5..=H as f64 - 0.5).contains(&(v[1] as f64));
        assert!(ok || (v[0] == NO_SOURCE && v[1] == NO_SOURCE), "{v:?}");
    }
    // a pixel above the horizon (depth capped at 30 m, 10 m from the camera ahead) still has its source
    let (sx, sy) = at(&g, 110, 50);
    let (wx, wy) = (CX + (110.0 - CX) * 3.0, CY + (50.0 - CY) * 3.0);
    assert!(
        (sx - wx).abs() < 1e-3 && (sy - wy).abs() < 1e-3,
        "({sx}, {sy}), want ({wx}, {wy})"
    );
}

#[test]
fn bad_arguments_are_errors() {
    let c = front();
    let p = DMat4::IDENTITY;
    for d in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        assert!(
            ground_warp_grid(&c, &p, &p, (H, W), d).is_err(),
            "depth {d}"
        );
    }
    let e = ground_warp_grids(&[c.clone(), c], &[p], &[p, p], (H, W), 30.0).unwrap_err();
    assert!(format!("{e:#}").contains("2 cameras, 1 current"), "{e:#}");
}

#[test]
fn the_config_key_is_read_checked_and_written() {
    use b2dr::nn::b2dr_config::B2drConfig;
    use b2dr::nn::config::UNetConfig;
    let base = B2drConfig::from_unet(&UNetConfig::b2dr_tiny(), vec![16, 32, 96, 256]);
    assert_eq!(
        base.prev_warp_max_depth, 0.0,
        "no warp unless the package says so"
    );
    let mut v = base.to_json();
    v["prev_warp_max_depth"] = serde_json::json!(30.0);
    let c = B2drConfig::from_json(v.clone()).unwrap();
    assert_eq!(c.prev_warp_max_depth, 30.0);
    assert_eq!(B2drConfig::from_json(c.to_json()).unwrap(), c);
    for bad in [
        serde_json::json!(-1.0),
        serde_json::json!(2000.0),
        serde_json::json!("far"),
    ] {
        v["prev_warp_max_depth"] = bad.clone();
        let e = format!("{:#}", B2drConfig::from_json(v.clone()).unwrap_err());
        assert!(e.contains("prev_warp_max_depth"), "{bad}: {e}");
    }
}

/// The engine's grid equals python/b2dr_ref/warp.py's (the training side) on a camera of the synthetic towns'
/// rig, a yawed and displaced current pose and a raised ground: values printed by
/// `ground_warp_grid(K, cam2ego, pose(-54.05, -0.25, 0.3, 0.1), pose(-58.278, -1.75, 0.3, 0), (112, 200), 30)`.
#[test]
fn grid_matches_the_training_side() {
    let cam = Camera {
        name: "CAM_FRONT".into(),
        intrinsic: DMat3::from_cols(
            DVec3::new(158.302125, 0.0, 0.0),
            DVec3::new(0.0, 157.59856, 0.0),
            DVec3::new(101.595875, 60.72753778, 1.0),
        ),
        cam2ego: DMat4::from_cols_array_2d(&[
            [0.0, -1.0, 0.0, 0.0],
            [0.0, 0.0, -1.0, 0.0],
            [1.0, 0.0, 0.0, 0.0],
            [1.7, 0.02, 1.51, 1.0],
        ]),
        width: W as u32,
        height: H as u32,
        distortion: [0.0; 5],
    };
    let pose = |x: f64, y: f64, yaw: f64| {
        DMat4::from_translation(DVec3::new(x, y, 0.3)) * DMat4::from_rotation_z(yaw)
    };
    let g = ground_warp_grid(
        &cam,
        &pose(-54.05, -0.25, 0.1),
        &pose(-58.278, -1.75, 0.0),
        (H, W),
        30.0,
    )
    .unwrap();
    for (x, y, wx, wy) in [
        (10, 100, 9.411622047424316, 84.77314758300781),
        (101, 80, 73.30523681640625, 75.1510238647461),
        (150, 30, 121.78972625732422, 34.377166748046875),
        (190, 111, 110.00282287597656, 86.61830139160156),
        (100, 62, 78.50200653076172, 61.849063873291016),
    ] {
        let (sx, sy) = at(&g, x, y);
        assert!(
            (sx - wx).abs() < 1e-3 && (sy - wy).abs() < 1e-3,
            "({x}, {y}): ({sx}, {sy}), python ({wx}, {wy})"
        );
    }
    assert_eq!(
        at(&g, 5, 5),
        (NO_SOURCE as f64, NO_SOURCE as f64),
        "python: NaN (no source)"
    );
}

/// b2dr.json's `prev_source`: "previous" unless the package says otherwise, "reference" and "composite" read and
/// written back,
/// refused without a warp (an unwarped reference does not line up with the current frame) and for other values.
#[test]
fn the_prev_source_key_is_read_checked_and_written() {
    use b2dr::nn::b2dr_config::{B2drConfig, PrevSource};
    use b2dr::nn::config::UNetConfig;
    let base = B2drConfig::from_unet(&UNetConfig::b2dr_tiny(), vec![16, 32, 96, 256]);
    assert_eq!(base.prev_source, PrevSource::Previous);
    let mut v = base.to_json();
    assert_eq!(v["prev_source"], "previous");
    v.as_object_mut().unwrap().remove("prev_source");
    assert_eq!(
        B2drConfig::from_json(v.clone()).unwrap().prev_source,
        PrevSource::Previous,
        "an older package without the key"
    );
    for (name, want) in [
        ("reference", PrevSource::Reference),
        ("composite", PrevSource::Composite),
    ] {
        v["prev_warp_max_depth"] = serde_json::json!(0.0);
        v["prev_source"] = serde_json::json!(name);
        let e = format!("{:#}", B2drConfig::from_json(v.clone()).unwrap_err());
        assert!(
            e.contains("prev_source") && e.contains("prev_warp_max_depth") && e.contains(name),
            "{e}"
        );
        v["prev_warp_max_depth"] = serde_json::json!(30.0);
        let c = B2drConfig::from_json(v.clone()).unwrap();
        assert_eq!(c.prev_source, want);
        assert!(want.from_references());
        assert_eq!(B2drConfig::from_json(c.to_json()).unwrap(), c);
    }
    for bad in [serde_json::json!("carried"), serde_json::json!(1)] {
        v["prev_source"] = bad.clone();
        let e = format!("{:#}", B2drConfig::from_json(v.clone()).unwrap_err());
        assert!(e.contains("prev_source"), "{bad}: {e}");
    }
}

/// The reference a camera starts from (`prev_source` "reference") is the one whose camera stands behind it
/// along its optical axis: for a forward camera the reference behind the ego, for a backward one the reference
/// ahead, whatever order they are given in; level: the rear one.
#[test]
fn the_reference_base_is_the_one_behind_the_camera() {
    use b2dr::render::warp::reference_base_choice;
    let at = |x: f64, y: f64| DMat4::from_translation(DVec3::new(x, y, 0.0));
    let cur = at(100.0, 5.0);
    let (ahead, behind) = (at(110.0, 5.0), at(92.0, 5.0));
    let f = front();
    assert_eq!(reference_base_choice(&f, &cur, [&ahead, &behind]), 1);
    assert_eq!(reference_base_choice(&f, &cur, [&behind, &ahead]), 0);
    // a camera looking backwards: the same rig turned by 180 degrees about the ego's z axis
    let mut back = front();
    back.cam2ego = DMat4::from_rotation_z(std::f64::consts::PI) * back.cam2ego;
    assert_eq!(reference_base_choice(&back, &cur, [&ahead, &behind]), 0);
    // a yawed ego: "behind" is along the camera's axis, not the global x axis
    let yawed = DMat4::from_rotation_z(std::f64::consts::FRAC_PI_2);
    let cur_y = at(0.0, 0.0) * yawed;
    let (north, south) = (at(0.0, 12.0) * yawed, at(0.0, -7.0) * yawed);
    assert_eq!(reference_base_choice(&f, &cur_y, [&north, &south]), 1);
    // side by side (a lateral offset only): level, the rear one
    let (left, right) = (at(100.0, 8.0), at(100.0, 2.0));
    assert_eq!(reference_base_choice(&f, &cur, [&left, &right]), 1);
}
