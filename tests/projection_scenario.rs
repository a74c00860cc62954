//! `b2dr project --scenario S --step K` (issue #35) for every scenario source, and the projection of an imported
//! nuScenes scene against nuscenes-devkit's own projection of the annotated boxes.
//!
//! The devkit reference (`devkit_corners_px`) is a port of nutonomy/nuscenes-devkit
//! python-sdk/nuscenes/utils/data_classes.py `Box.corners` and geometry_utils.py `view_points`, applied as
//! `NuScenes.get_sample_data` does (box to the ego frame of the image's ego pose, then to the sensor:
//! `translate(-t)`, `rotate(q.inverse)` twice; then `view_points(corners, K, normalize=True)`), reading the
//! fixture's tables directly, not through b2dr's importer:
//! <https://github.com/nutonomy/nuscenes-devkit/blob/master/python-sdk/nuscenes/utils/data_classes.py>,
//! <https://github.com/nutonomy/nuscenes-devkit/blob/master/python-sdk/nuscenes/utils/geometry_utils.py>.
//! The nuScenes DATAROOT is the fixture without the map expansion (`nuscenes_fixture.py --no-map-expansion`, from
//! the shared scene-0061 data; skipped with a printed reason when absent).
use std::path::{Path, PathBuf};
use std::process::Command;

#[path = "common/fixture_dirs.rs"]
mod fixture_dirs;
mod nuplan_fixture;
mod nuscenes_fixture;

use glam::{DMat3, DQuat, DVec2, DVec3};
use serde_json::Value;

fn project(scenario: &str, step: usize, extra: &[&str], out: &Path) -> Value {
    let _ = std::fs::remove_dir_all(out);
    let o = Command::new(env!("CARGO_BIN_EXE_b2dr"))
        .args(["project", "--scenario", scenario, "--step"])
        .arg(step.to_string())
        .args(extra)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_str(&std::fs::read_to_string(out.join("projection.json")).unwrap()).unwrap()
}

fn tmp(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!(
        "b2dr_project_scenario_{name}_{}",
        std::process::id()
    ))
}

/// Masks, overlays and projection.json for a built-in town, a ScenarioNet file and a nuPlan log, as `--frame`
/// writes them.
#[test]
fn every_scenario_source_projects() {
    let out = tmp("builtin");
    let j = project(
        "builtin:town",
        40,
        &["--cameras", "CAM_FRONT,CAM_BACK"],
        &out,
    );
    assert_eq!(
        (j["step"].as_u64(), j["frame_step"].as_u64()),
        (Some(40), Some(40))
    );
    let cams = j["cameras"].as_object().unwrap();
    assert_eq!(cams.len(), 2);
    assert!(!cams["CAM_FRONT"].as_array().unwrap().is_empty());
    for cam in ["CAM_FRONT", "CAM_BACK"] {
        assert!(out.join(cam).join("overlay.jpg").is_file());
        let pngs = std::fs::read_dir(out.join(cam))
            .unwrap()
            .filter(|e| e.as_ref().unwrap().path().extension().unwrap() == "png")
            .count();
        assert_eq!(pngs, 15);
    }
    // the car mask of the front camera shows the cars listed in view
    let car = image::open(out.join("CAM_FRONT/car.png"))
        .unwrap()
        .to_luma8();
    assert!(car.pixels().any(|p| p.0[0] == 255));
    let _ = std::fs::remove_dir_all(&out);

    if let Some(shared) = nuscenes_fixture::shared() {
        let out = tmp("scenarionet");
        let f = shared.join("scenes/scene-0061.json");
        let j = project(f.to_str().unwrap(), 10, &["--cameras", "CAM_FRONT"], &out);
        assert_eq!(j["boxes_from"], "scenario tracks");
        assert!(!j["cameras"]["CAM_FRONT"].as_array().unwrap().is_empty());
        let _ = std::fs::remove_dir_all(&out);
    }

    let root = tmp("nuplan_fx");
    if let Some(fx) = nuplan_fixture::write_fixture(&root, &["--seconds", "2"]) {
        let out = tmp("nuplan");
        let j = project(&format!("nuplan:{}", fx.db.display()), 10, &[], &out);
        assert_eq!(j["cameras"].as_object().unwrap().len(), 8);
        // the car ahead (30 m + 10 m/s) is in front of CAM_F0
        assert!(j["cameras"]["CAM_F0"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e["class"] == "car" && e["in_view"] == true));
        let _ = std::fs::remove_dir_all(&out);
        let _ = std::fs::remove_dir_all(&root);
    }
}

/// nuscenes-devkit's `Box.corners()` (data_classes.py): x = l/2 [1 1 1 1 -1 -1 -1 -1], y = w/2 [1 -1 -1 1 1 -1 -1 1],
/// z = h/2 [1 1 -1 -1 1 1 -1 -1], rotated by the box's orientation, translated to its centre. `size` is the
/// devkit's `wlh`.
fn devkit_box_corners(center: DVec3, wlh: DVec3, q: DQuat) -> [DVec3; 8] {
    let (w, l, h) = (wlh.x, wlh.y, wlh.z);
    let xs = [1., 1., 1., 1., -1., -1., -1., -1.];
    let ys = [1., -1., -1., 1., 1., -1., -1., 1.];
    let zs = [1., 1., -1., -1., 1., 1., -1., -1.];
    std::array::from_fn(|i| q * DVec3::new(l / 2. * xs[i], w / 2. * ys[i], h / 2. * zs[i]) + center)
}

/// nuscenes-devkit's `view_points(points, view, normalize=True)` (geometry_utils.py) for a 3x3 `view`.
fn devkit_view_point(p: DVec3, k: DMat3) -> DVec2 {
    let v = k * p;
    DVec2::new(v.x / v.z, v.y / v.z)
}

fn vec3(v: &Value) -> DVec3 {
    DVec3::new(
        v[0].as_f64().unwrap(),
        v[1].as_f64().unwrap(),
        v[2].as_f64().unwrap(),
    )
}

fn quat(v: &Value) -> DQuat {
    // nuScenes stores w, x, y, z
    DQuat::from_xyzw(
        v[1].as_f64().unwrap(),
        v[2].as_f64().unwrap(),
        v[3].as_f64().unwrap(),
        v[0].as_f64().unwrap(),
    )
}

fn table(root: &Path, name: &str) -> Vec<Value> {
    serde_json::from_str(
        &std::fs::read_to_string(root.join(format!("v1.0-mini/{name}.json"))).unwrap(),
    )
    .unwrap()
}

/// At the first keyframe (step 0) of the imported scene, every annotated box `b2dr project --scenario` lists (all 8
/// corners in front of the camera) lands within 3 px of the devkit's projection of that annotation, corner by
/// corner, in all six cameras.
#[test]
fn nuscenes_step_lands_on_the_devkits_projection() {
    let Some(root) = nuscenes_fixture::write_fixture("project", &["--no-map-expansion"]) else {
        return;
    };
    let out = tmp("nuscenes");
    let j = project(
        &format!("nuscenes:{}:scene-0061", root.display()),
        0,
        &[],
        &out,
    );
    assert_eq!(j["boxes_from"], "nuscenes annotations");
    assert!(j["map_missing"]
        .as_str()
        .is_some_and(|m| m.contains("maps/expansion")));
    // The devkit side, from the tables.
    let scene = &table(&root, "scene")[0];
    let sample = scene["first_sample_token"].as_str().unwrap();
    fn find(t: &[Value], tok: &str) -> Value {
        t.iter()
            .find(|r| r["token"] == tok)
            .cloned()
            .unwrap_or_else(|| panic!("token {tok}"))
    }
    let (sds, cs, sensors, eps) = (
        table(&root, "sample_data"),
        table(&root, "calibrated_sensor"),
        table(&root, "sensor"),
        table(&root, "ego_pose"),
    );
    let (insts, cats) = (table(&root, "instance"), table(&root, "category"));
    // annotations of the first sample whose category has a mask class (the others are not drawn)
    let anns: Vec<Value> = table(&root, "sample_annotation")
        .into_iter()
        .filter(|a| a["sample_token"] == sample)
        .filter(|a| {
            let i = find(&insts, a["instance_token"].as_str().unwrap());
            let c = find(&cats, i["category_token"].as_str().unwrap());
            b2dr::projection::BoxClass::parse(c["name"].as_str().unwrap()).is_some()
        })
        .collect();
    let (mut compared, mut worst) = (0usize, 0.0f64);
    for sd in sds
        .iter()
        .filter(|s| s["sample_token"] == sample && s["is_key_frame"] == true)
    {
        let c = find(&cs, sd["calibrated_sensor_token"].as_str().unwrap());
        let sensor = find(&sensors, c["sensor_token"].as_str().unwrap());
        if sensor["modality"] != "camera" {
            continue;
        }
        let ch = sensor["channel"].as_str().unwrap();
        let ep = find(&eps, sd["ego_pose_token"].as_str().unwrap());
        let k = &c["camera_intrinsic"];
        let kk =
            DMat3::from_cols_array(&std::array::from_fn(|i| k[i % 3][i / 3].as_f64().unwrap()));
        let ours = j["cameras"][ch].as_array().unwrap();
        for a in &anns {
            // get_sample_data: global -> ego (translate(-t), rotate(q^-1)) -> sensor (the same)
            let to_cam = |p: DVec3| {
                let e = quat(&ep["rotation"]).inverse() * (p - vec3(&ep["translation"]));
                quat(&c["rotation"]).inverse() * (e - vec3(&c["translation"]))
            };
            let corners = devkit_box_corners(
                vec3(&a["translation"]),
                vec3(&a["size"]),
                quat(&a["rotation"]),
            )
            .map(to_cam);
            if corners.iter().any(|p| p.z <= 0.1) {
                continue;
            }
            let centre = devkit_view_point(to_cam(vec3(&a["translation"])), kk);
            let px: Vec<DVec2> = corners.iter().map(|p| devkit_view_point(*p, kk)).collect();
            // our entry of this box: the one whose centre lands nearest the devkit's
            let e = ours.iter().min_by(|x, y| {
                let d = |e: &Value| {
                    DVec2::new(
                        e["center_px"][0].as_f64().unwrap(),
                        e["center_px"][1].as_f64().unwrap(),
                    )
                    .distance(centre)
                };
                d(x).total_cmp(&d(y))
            });
            let e = e.unwrap_or_else(|| panic!("{ch}: no box listed"));
            let c_ours = DVec2::new(
                e["center_px"][0].as_f64().unwrap(),
                e["center_px"][1].as_f64().unwrap(),
            );
            assert!(
                c_ours.distance(centre) < 3.0,
                "{ch}: no listed box within 3 px of the devkit's centre {centre} (annotation {})",
                a["token"]
            );
            let ours_px: Vec<DVec2> = e["corners_px"]
                .as_array()
                .unwrap()
                .iter()
                .map(|q| DVec2::new(q[0].as_f64().unwrap(), q[1].as_f64().unwrap()))
                .collect();
            for p in &px {
                let d = ours_px
                    .iter()
                    .map(|q| q.distance(*p))
                    .fold(f64::INFINITY, f64::min);
                worst = worst.max(d);
                assert!(d < 3.0, "{ch}: devkit corner {p} is {d} px from ours");
            }
            worst = worst.max(c_ours.distance(centre));
            compared += 1;
        }
    }
    eprintln!(
        "nuScenes step 0 vs nuscenes-devkit view_points: {compared} boxes, largest corner distance {worst:.2e} px"
    );
    assert!(compared > 50, "only {compared} boxes compared");
    let _ = std::fs::remove_dir_all(&out);
}
