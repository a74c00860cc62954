//! The nuScenes importer (`--scenario nuscenes:DATAROOT[:VERSION]:SCENE`) on a nuScenes-mini-style folder written
//! at test time from the shared scene-0061 data by `python/b2dr_ref/nuscenes_fixture.py` (plain Python): the
//! keyframe projection oracle, the ScenarioNet log of the same scene, `b2dr sim`, malformed tables, import time.
//! Skips with a printed reason when the shared data (or a Python interpreter) is absent.
use std::path::Path;
use std::process::Command;
use std::time::Instant;

#[path = "common/fixture_dirs.rs"]
mod fixture_dirs;
mod nuscenes_fixture;

use b2dr::projection::{Box3d, BoxClass, CameraProjector, KeyFrame};
use b2dr::scene::geometry::angle_diff;
use b2dr::scene::import::nuscenes::expansion::ArclinePath;
use b2dr::scene::import::nuscenes::{self, NuscenesSpec};
use b2dr::scene::import::{resolve, scenarionet, Source};
use b2dr::scene::Scenario;
use nuscenes_fixture::{dataroot, shared, spec, write_fixture};

#[test]
fn spec_syntax() {
    let s = resolve("nuscenes:/data/sets/nuscenes:scene-0061").unwrap();
    assert_eq!(
        s,
        vec![Source::Nuscenes(NuscenesSpec {
            dataroot: "/data/sets/nuscenes".into(),
            version: "v1.0-mini".into(),
            scene: "scene-0061".into()
        })]
    );
    assert_eq!(s[0].name(), "scene-0061");
    let s = resolve("nuscenes:/d:v1.0-trainval:cc8c0bf57f984915a77078b10eb33198").unwrap();
    let Source::Nuscenes(n) = &s[0] else { panic!() };
    assert_eq!(
        (n.dataroot.to_str(), n.version.as_str()),
        (Some("/d"), "v1.0-trainval")
    );
    // A middle field that is not a version belongs to the DATAROOT.
    let Source::Nuscenes(n) = &resolve("nuscenes:/a:b:scene-1").unwrap()[0] else {
        panic!()
    };
    assert_eq!(
        (n.dataroot.to_str(), n.version.as_str()),
        (Some("/a:b"), "v1.0-mini")
    );
    // Two scenes as a list.
    assert_eq!(
        resolve("nuscenes:/d:scene-0061,nuscenes:/d:scene-0103")
            .unwrap()
            .len(),
        2
    );
    for bad in [
        "nuscenes:",
        "nuscenes:/d",
        "nuscenes:/d:",
        "nuscenes::scene-1",
    ] {
        let e = format!("{:#}", resolve(bad).unwrap_err());
        assert!(
            e.contains("nuscenes:DATAROOT[:VERSION]:SCENE"),
            "{bad}: {e}"
        );
    }
}

/// The oracle's boxes matched to the importer's annotations of the first keyframe; the importer's camera,
/// calibration and per-camera ego pose project them within 3 px of `b2dr project`'s chain on frame.json.
#[test]
fn keyframe_projection_matches_the_oracle() {
    let Some(root) = dataroot() else { return };
    let shared = shared().unwrap();
    let log = nuscenes::load_log(&spec(root)).unwrap();
    let sc = &log.scenario;
    let mut oracle = KeyFrame::load(&shared.join("keyframe-scene-0061/frame.json")).unwrap();
    if oracle.z_looks_like_top() {
        oracle.boxes_z_from_top();
    }
    let kf = &log.keyframes[0];
    assert_eq!(kf.time_us, 0);
    let frame0 = &sc.rig.frames[0];
    assert_eq!(frame0.timestamp_us, 0);
    assert_eq!(frame0.images.len(), 6);
    // Boxes: nearest annotation centre.
    let ours: Vec<Box3d> = kf
        .annotations
        .iter()
        .map(|a| Box3d {
            class: BoxClass::parse(&a.category).unwrap(),
            center: a.center,
            size: a.size_lwh,
            yaw: a.yaw,
        })
        .collect();
    let mut pairs = vec![];
    let mut worst_match = 0f64;
    for b in &oracle.boxes {
        let (i, d) = ours
            .iter()
            .enumerate()
            .map(|(i, o)| (i, o.center.truncate().distance(b.center.truncate())))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        assert!(
            d < 0.15,
            "oracle box at {:?}: nearest annotation {d} m",
            b.center
        );
        assert_eq!(ours[i].class, b.class);
        worst_match = worst_match.max(d);
        pairs.push((b, &ours[i]));
    }
    assert_eq!(pairs.len(), 68);
    let (mut compared, mut worst) = (0, 0f64);
    for (cam_o, img_o) in &oracle.cameras {
        let cam = sc.rig.camera(&cam_o.name).unwrap();
        let img = frame0.image(&cam_o.name).unwrap();
        // Calibration and pose as stored (the fixture writes frame.json's matrices as quaternions).
        assert!(cam.intrinsic.abs_diff_eq(cam_o.intrinsic, 1e-9));
        assert!(cam.cam2ego.abs_diff_eq(cam_o.cam2ego, 1e-6), "{}", cam.name);
        assert!(img.ego2global.abs_diff_eq(img_o.ego2global, 1e-6));
        assert_eq!((cam.width, cam.height), (cam_o.width, cam_o.height));
        let (mine, theirs) = (
            CameraProjector::new(cam, &img.ego2global, cam.width, cam.height).unwrap(),
            CameraProjector::new(cam_o, &img_o.ego2global, cam_o.width, cam_o.height).unwrap(),
        );
        for (b, o) in &pairs {
            let pts_o = std::iter::once(b.center).chain(b.corners());
            let pts = std::iter::once(o.center).chain(o.corners());
            for (p_o, p) in pts_o.zip(pts) {
                let (Some((want, d_o)), Some((got, d))) = (theirs.project(p_o), mine.project(p))
                else {
                    continue;
                };
                if d_o < 1.0 || d < 1.0 || !theirs.in_image(want) {
                    continue;
                }
                let e = want.distance(got);
                worst = worst.max(e);
                assert!(e <= 3.0, "{} box at {:?}: {e:.2} px", cam.name, b.center);
                compared += 1;
            }
        }
    }
    eprintln!(
        "oracle: {compared} box centres/corners compared in 6 cameras, largest difference {worst:.2} px; \
         nearest-centre match within {worst_match:.3} m"
    );
    assert!(compared > 200, "{compared}");
}

fn scenarionet_log() -> Option<Scenario> {
    Some(scenarionet::load_file(&shared()?.join("scenes/scene-0061.json")).unwrap())
}

/// Tracks, ego and map against the ScenarioNet log of the same scene at the keyframe steps.
#[test]
fn tracks_equal_the_scenarionet_log_at_keyframes() {
    let Some(root) = dataroot() else { return };
    let sn = scenarionet_log().unwrap();
    let sc = nuscenes::load(&spec(root)).unwrap();
    assert_eq!(sc.name, "scene-0061");
    assert_eq!(sc.len(), sn.len());
    assert_eq!(sc.dt, 0.1);
    let (mut n, mut worst_p, mut worst_h) = (0, 0f64, 0f64);
    for k in (0..sn.len()).step_by(5) {
        let (a, b) = (sc.ego[k].rear_axle, sn.ego[k].rear_axle);
        worst_p = worst_p.max(a.pos().distance(b.pos()));
        worst_h = worst_h.max(angle_diff(a.heading, b.heading).abs());
        for t in &sn.tracks {
            let ours = sc.tracks.iter().find(|x| x.id == t.id);
            let want = t.states[k];
            let got = ours.and_then(|x| x.states[k]);
            assert_eq!(want.is_some(), got.is_some(), "track {} at step {k}", t.id);
            let (Some(w), Some(g)) = (want, got) else {
                continue;
            };
            let o = ours.unwrap();
            assert_eq!(o.class, t.class, "{}", t.id);
            assert!((o.length - t.length).abs() < 1e-9 && (o.width - t.width).abs() < 1e-9);
            worst_p = worst_p.max(w.pose.pos().distance(g.pose.pos()));
            worst_h = worst_h.max(angle_diff(w.pose.heading, g.pose.heading).abs());
            n += 1;
        }
    }
    // No track the ScenarioNet log lacks (tracks never valid at a keyframe are not annotations).
    for t in &sc.tracks {
        assert!(sn.tracks.iter().any(|x| x.id == t.id), "{}", t.id);
    }
    eprintln!(
        "{n} object states + ego at keyframes: largest difference {:.2e} m, {:.2e} deg",
        worst_p,
        worst_h.to_degrees()
    );
    assert!(n > 4000, "{n}");
    assert!(worst_p < 0.01 && worst_h.to_degrees() < 0.1);
    // Between keyframes: the devkit's interpolation against ScenarioNet's own (printed, not asserted).
    let mut between = 0f64;
    for k in 0..sn.len() {
        for t in &sn.tracks {
            if let (Some(w), Some(g)) = (
                t.states[k],
                sc.tracks
                    .iter()
                    .find(|x| x.id == t.id)
                    .and_then(|x| x.states[k]),
            ) {
                between = between.max(w.pose.pos().distance(g.pose.pos()));
            }
        }
    }
    eprintln!("all steps: largest position difference to ScenarioNet {between:.3} m");
    // Map: the expansion's lanes are ScenarioNet's lanes, with their links.
    assert!(sc.map.lanes.len() > 300, "{}", sc.map.lanes.len());
    for l in &sc.map.lanes {
        let i = sn.map.lane_index(&l.id).unwrap();
        let s = &sn.map.lanes[i];
        assert_eq!(l.kind, s.kind, "{}", l.id);
        assert!(l.centre.first().distance(s.centre.first()) < 1e-6);
        assert!(l.centre.last().distance(s.centre.last()) < 1e-6);
    }
    let links: usize = sc.map.lanes.iter().map(|l| l.successors.len()).sum();
    assert!(links > 100, "{links}");
    assert!(!sc.map.drivable.is_empty());
    let c = sc.ego_params.center_of(&sc.ego[0].rear_axle);
    assert!(sc.map.in_drivable_area(c.pos()));
    assert!(!sc.route.lane_ids.is_empty());
    // Rig: six cameras, one frame per sample, every image on disk with its own pose.
    assert_eq!(sc.rig.cameras.len(), 6);
    assert_eq!(sc.rig.frames.len(), 39);
    for (j, f) in sc.rig.frames.iter().enumerate() {
        assert_eq!(f.timestamp_us, j as i64 * 500_000);
        assert_eq!(f.images.len(), 6);
        for im in &f.images {
            assert!(Path::new(&im.path).is_file(), "{}", im.path);
            assert!((im.timestamp_us - f.timestamp_us).abs() < 50_000);
        }
    }
}

fn b2dr() -> Command {
    Command::new(env!("CARGO_BIN_EXE_b2dr"))
}

#[test]
fn sim_runs_on_a_nuscenes_scene() {
    let Some(root) = dataroot() else { return };
    let out = std::env::temp_dir().join(format!("b2dr_nuscenes_sim_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let scenario = format!("nuscenes:{}:v1.0-mini:scene-0061", root.display());
    for planner in ["expert", "cv"] {
        let o = b2dr()
            .args(["sim", "--scenario", &scenario, "--planner", planner])
            .args([
                "--agents",
                "idm",
                "--steps",
                "20",
                "--bev-every",
                "0",
                "--out",
            ])
            .arg(out.join(planner))
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let dir = out.join(planner).join("scene-0061");
        let trace = std::fs::read_to_string(dir.join("trace.jsonl")).unwrap();
        assert_eq!(trace.lines().count(), 21);
        let m: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("metrics.json")).unwrap())
                .unwrap();
        assert!(m["failure"].is_null(), "{m}");
        let score = m["score"].as_f64().unwrap();
        eprintln!(
            "b2dr sim --planner {planner} on nuScenes scene-0061 (20 steps): score {score:.3}"
        );
        assert!((0.0..=1.0).contains(&score));
        if planner == "expert" {
            assert!(score > 0.5, "expert score {score}");
        }
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// Copies the tables into `<root>/<version>`, applies `edit` to table `name`, returns the load error.
fn broken(root: &Path, version: &str, edit: impl FnOnce(&Path)) -> String {
    broken_scene(root, version, "scene-0061", edit)
}

/// [`broken`] loading scene `scene` (a name or token).
fn broken_scene(root: &Path, version: &str, scene: &str, edit: impl FnOnce(&Path)) -> String {
    let dst = root.join(version);
    let _ = std::fs::remove_dir_all(&dst);
    std::fs::create_dir_all(&dst).unwrap();
    for e in std::fs::read_dir(root.join("v1.0-mini")).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, dst.join(p.file_name().unwrap())).unwrap();
    }
    edit(&dst);
    let s = NuscenesSpec {
        version: version.into(),
        scene: scene.into(),
        ..spec(root)
    };
    let e = format!(
        "{:#}",
        nuscenes::load(&s).expect_err("a broken table must fail")
    );
    let _ = std::fs::remove_dir_all(&dst);
    e
}

fn edit_row(dir: &Path, table: &str, row: usize, f: impl FnOnce(&mut serde_json::Value)) {
    let p = dir.join(format!("{table}.json"));
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    f(&mut v[row]);
    std::fs::write(&p, serde_json::to_string(&v).unwrap()).unwrap();
}

/// A change made to a copy of the tables.
type Edit = Box<dyn FnOnce(&Path)>;

#[test]
fn malformed_tables_give_clear_errors() {
    let Some(root) = dataroot() else { return };
    let cases: Vec<(&str, Edit, Vec<&str>)> = vec![
        (
            "missing table",
            Box::new(|d: &Path| std::fs::remove_file(d.join("ego_pose.json")).unwrap()),
            vec!["table `ego_pose`", "ego_pose.json"],
        ),
        (
            "wrong column type",
            Box::new(|d: &Path| edit_row(d, "sample_data", 3, |r| r["timestamp"] = "soon".into())),
            vec![
                "table `sample_data`",
                "row 3",
                "column `timestamp`",
                "invalid type",
            ],
        ),
        (
            "wrong array length",
            Box::new(|d: &Path| {
                edit_row(d, "sample_annotation", 10, |r| {
                    r["size"] = serde_json::json!([1.0, 2.0])
                })
            }),
            vec!["table `sample_annotation`", "row 10", "column `size`"],
        ),
        (
            "dangling ego pose",
            Box::new(|d: &Path| {
                edit_row(d, "sample_data", 5, |r| {
                    r["ego_pose_token"] = "0123456789abcdef0123456789abcdef".into()
                })
            }),
            vec![
                "table `sample_data`",
                "row 5",
                "column `ego_pose_token`",
                "dangling",
                "`ego_pose`",
            ],
        ),
        (
            "dangling category",
            Box::new(|d: &Path| {
                edit_row(d, "instance", 0, |r| r["category_token"] = "nope".into())
            }),
            vec![
                "table `instance`",
                "row 0",
                "column `category_token`",
                "dangling",
            ],
        ),
        (
            "missing column",
            Box::new(|d: &Path| {
                edit_row(d, "calibrated_sensor", 0, |r| {
                    r.as_object_mut().unwrap().remove("rotation");
                })
            }),
            vec![
                "table `calibrated_sensor`",
                "row 0",
                "column `rotation` is missing",
            ],
        ),
        (
            "not a rotation",
            Box::new(|d: &Path| {
                edit_row(d, "ego_pose", 2, |r| {
                    r["rotation"] = serde_json::json!([0, 0, 0, 0])
                })
            }),
            vec![
                "table `ego_pose`",
                "row 2",
                "column `rotation`",
                "not a rotation",
            ],
        ),
        (
            "table not an array",
            Box::new(|d: &Path| std::fs::write(d.join("sample.json"), "{}").unwrap()),
            vec!["table `sample`", "expected a JSON array"],
        ),
        (
            "invalid JSON",
            Box::new(|d: &Path| std::fs::write(d.join("log.json"), "[{").unwrap()),
            vec!["table `log`", "not valid JSON"],
        ),
        (
            "duplicate token",
            Box::new(|d: &Path| {
                let p = d.join("sensor.json");
                let mut v: Vec<serde_json::Value> =
                    serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
                v.push(v[0].clone());
                std::fs::write(&p, serde_json::to_string(&v).unwrap()).unwrap();
            }),
            vec!["table `sensor`", "duplicate token"],
        ),
    ];
    for (k, (what, edit, want)) in cases.into_iter().enumerate() {
        let e = broken(root, &format!("v9-bad{k}"), edit);
        for w in want {
            assert!(e.contains(w), "{what}: {w:?} not in: {e}");
        }
        eprintln!("{what}: {e}");
    }
    // Unknown scene: the error lists the scenes.
    let e = nuscenes::load(&NuscenesSpec {
        scene: "scene-9999".into(),
        ..spec(root)
    })
    .unwrap_err();
    let e = format!("{e:#}");
    assert!(e.contains("scene-9999") && e.contains("scene-0061"), "{e}");
    // No version folder.
    let e = format!(
        "{:#}",
        nuscenes::load(&NuscenesSpec {
            version: "v1.0-nope".into(),
            ..spec(root)
        })
        .unwrap_err()
    );
    assert!(
        e.contains("v1.0-nope") && e.contains("not a directory"),
        "{e}"
    );
    let bare = std::env::temp_dir().join(format!("b2dr_nuscenes_nomap_{}", std::process::id()));
    std::fs::create_dir_all(bare.join("v1.0-mini")).unwrap();
    for e in std::fs::read_dir(root.join("v1.0-mini")).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, bare.join("v1.0-mini").join(p.file_name().unwrap())).unwrap();
    }
    // Without the map expansion pack the scene loads without lanes and says where it looked
    // (tests/scene_nuscenes_nomap.rs: what works and what refuses).
    let sc = nuscenes::load(&spec(&bare)).unwrap();
    let e = sc.map.missing.clone().unwrap_or_default();
    assert!(sc.map.lanes.is_empty());
    assert!(
        e.contains("maps/expansion/singapore-onenorth.json") && e.contains("map expansion"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&bare);
}

fn read_table(dir: &Path, table: &str) -> Vec<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(dir.join(format!("{table}.json"))).unwrap())
        .unwrap()
}

/// The first row index of `table` for which `pred` holds.
fn row_where(dir: &Path, table: &str, pred: impl Fn(&serde_json::Value) -> bool) -> usize {
    read_table(dir, table).iter().position(pred).unwrap()
}

/// sample_data of the LIDAR_TOP (ego poses) and of a camera (images, calibration).
fn lidar(r: &serde_json::Value) -> bool {
    r["filename"].as_str().unwrap().contains("LIDAR_TOP")
}
fn camera(r: &serde_json::Value) -> bool {
    r["filename"].as_str().unwrap().contains("CAM_FRONT")
}
/// The ego_pose row of a LIDAR_TOP sample_data in the middle of the scene.
fn mid_lidar_pose(d: &Path) -> usize {
    let sd = read_table(d, "sample_data");
    let rows: Vec<&serde_json::Value> = sd.iter().filter(|r| lidar(r)).collect();
    let tok = rows[rows.len() / 2]["ego_pose_token"].clone();
    row_where(d, "ego_pose", |r| r["token"] == tok)
}

/// Issue #18 on the nuScenes tables: far, huge, non-finite and absurd values, paths that leave the DATAROOT and
/// names that are paths are refused with errors naming the table, the row and the column.
#[test]
fn hostile_tables_are_refused() {
    use serde_json::json;
    let Some(root) = dataroot() else { return };
    let cases: Vec<(&str, Edit, Vec<&str>)> = vec![
        (
            "far ego pose",
            Box::new(|d: &Path| {
                edit_row(d, "ego_pose", 2, |r| {
                    r["translation"] = json!([1e9, 0.0, 0.0])
                })
            }),
            vec![
                "table `ego_pose`",
                "row 2",
                "column `translation`",
                "beyond",
            ],
        ),
        (
            "NaN in a table (Python's json writes it)",
            Box::new(|d: &Path| {
                let p = d.join("ego_pose.json");
                let t = std::fs::read_to_string(&p).unwrap();
                let i = t
                    .find("\"translation\": [")
                    .or_else(|| t.find("\"translation\":["))
                    .unwrap();
                let j = i + t[i..].find('[').unwrap() + 1;
                std::fs::write(&p, format!("{}NaN, {}", &t[..j], &t[j..])).unwrap();
            }),
            vec!["table `ego_pose`", "not valid JSON"],
        ),
        (
            "huge quaternion",
            Box::new(|d: &Path| {
                edit_row(d, "ego_pose", 3, |r| {
                    r["rotation"] = json!([1e300, 0, 0, 1e300])
                })
            }),
            vec![
                "table `ego_pose`",
                "row 3",
                "column `rotation`",
                "not a rotation",
            ],
        ),
        (
            "ego jump (speed beyond 1000 m/s)",
            Box::new(|d: &Path| {
                let i = mid_lidar_pose(d);
                edit_row(d, "ego_pose", i, |r| {
                    r["translation"][0] = json!(r["translation"][0].as_f64().unwrap() + 1e6)
                })
            }),
            vec![
                "table `ego_pose`",
                "column `translation`",
                "m/s",
                "table `sample_data`",
            ],
        ),
        (
            "far annotation",
            Box::new(|d: &Path| {
                edit_row(d, "sample_annotation", 7, |r| {
                    r["translation"] = json!([0.0, -2e8, 0.0])
                })
            }),
            vec![
                "table `sample_annotation`",
                "row 7",
                "column `translation`",
                "beyond",
            ],
        ),
        (
            "huge annotation",
            Box::new(|d: &Path| {
                edit_row(d, "sample_annotation", 8, |r| {
                    r["size"] = json!([2.0, 1e4, 1.5])
                })
            }),
            vec![
                "table `sample_annotation`",
                "row 8",
                "column `size`",
                "at most 1000 m",
            ],
        ),
        (
            "annotation jump (box velocity beyond 1000 m/s)",
            Box::new(|d: &Path| {
                let i = row_where(d, "sample_annotation", |r| {
                    r["prev"] != "" && r["next"] != ""
                });
                edit_row(d, "sample_annotation", i, |r| {
                    r["translation"][1] = json!(r["translation"][1].as_f64().unwrap() + 1e6)
                })
            }),
            vec![
                "table `sample_annotation`",
                "column `translation`",
                "box velocity",
                "m/s",
            ],
        ),
        (
            "camera 10 km from the ego",
            Box::new(|d: &Path| {
                let i = row_where(d, "calibrated_sensor", |r| {
                    r["camera_intrinsic"] != json!([])
                });
                edit_row(d, "calibrated_sensor", i, |r| {
                    r["translation"] = json!([1e4, 0.0, 1.5])
                })
            }),
            vec![
                "table `calibrated_sensor`",
                "column `translation`",
                "beyond",
            ],
        ),
        (
            "absurd intrinsics",
            Box::new(|d: &Path| {
                let i = row_where(d, "calibrated_sensor", |r| {
                    r["camera_intrinsic"] != json!([])
                });
                edit_row(d, "calibrated_sensor", i, |r| {
                    r["camera_intrinsic"][0][0] = json!(1e300)
                })
            }),
            vec![
                "table `calibrated_sensor`",
                "column `camera_intrinsic`",
                "beyond",
            ],
        ),
        (
            "huge image",
            Box::new(|d: &Path| {
                let i = row_where(d, "sample_data", camera);
                edit_row(d, "sample_data", i, |r| {
                    r["width"] = json!(4_000_000_000u32)
                })
            }),
            vec!["table `sample_data`", "`width`", "4000000000x", "1..=16384"],
        ),
        (
            "image outside the DATAROOT (..)",
            Box::new(|d: &Path| {
                let i = row_where(d, "sample_data", camera);
                edit_row(d, "sample_data", i, |r| {
                    r["filename"] = json!("samples/../../../etc/passwd")
                })
            }),
            vec![
                "table `sample_data`",
                "column `filename`",
                "not a relative path inside",
            ],
        ),
        (
            "image outside the DATAROOT (absolute)",
            Box::new(|d: &Path| {
                let i = row_where(d, "sample_data", camera);
                edit_row(d, "sample_data", i, |r| {
                    r["filename"] = json!("/etc/passwd")
                })
            }),
            vec![
                "table `sample_data`",
                "column `filename`",
                "\"/etc/passwd\"",
            ],
        ),
        (
            "location that is a path",
            Box::new(|d: &Path| edit_row(d, "log", 0, |r| r["location"] = json!("../../../tmp/x"))),
            vec![
                "table `log`",
                "row 0",
                "column `location`",
                "not a plain name",
            ],
        ),
        (
            "channel that is a path",
            Box::new(|d: &Path| edit_row(d, "sensor", 0, |r| r["channel"] = json!("../CAM"))),
            vec![
                "table `sensor`",
                "row 0",
                "column `channel`",
                "not a plain name",
            ],
        ),
        (
            "far-future timestamp",
            Box::new(|d: &Path| {
                edit_row(d, "sample_data", 4, |r| r["timestamp"] = json!(i64::MIN))
            }),
            vec![
                "table `sample_data`",
                "row 4",
                "column `timestamp`",
                "beyond",
            ],
        ),
        (
            "a scene of years (10^7 steps)",
            Box::new(|d: &Path| {
                let n = read_table(d, "sample").len();
                let i = row_where(d, "sample", |r| r["next"] == "");
                assert!(n > 1);
                edit_row(d, "sample", i, |r| {
                    r["timestamp"] = json!(r["timestamp"].as_i64().unwrap() + 1_000_000_000_000)
                })
            }),
            vec!["table `sample`", "column `timestamp`", "more than 600 s"],
        ),
    ];
    for (k, (what, edit, want)) in cases.into_iter().enumerate() {
        let t = Instant::now();
        let e = broken(root, &format!("v9-hostile{k}"), edit);
        for w in want {
            assert!(e.contains(w), "{what}: {w:?} not in: {e}");
        }
        assert!(
            t.elapsed().as_secs_f64() < 30.0,
            "{what}: {:?}",
            t.elapsed()
        );
        eprintln!("{what}: {e}");
    }
    // A scene name that is a path (selected by token).
    let tok = read_table(&root.join("v1.0-mini"), "scene")[0]["token"]
        .as_str()
        .unwrap()
        .to_string();
    let e = broken_scene(root, "v9-hostile-scene", &tok, |d| {
        edit_row(d, "scene", 0, |r| r["name"] = json!("../../scene"))
    });
    assert!(
        e.contains("table `scene`")
            && e.contains("column `name`")
            && e.contains("not a plain name"),
        "{e}"
    );
}

/// A copy of the fixture DATAROOT's tables with the map expansion edited; returns the load error.
fn broken_map(root: &Path, name: &str, edit: impl FnOnce(&mut serde_json::Value)) -> String {
    let d = std::env::temp_dir().join(format!("b2dr_nuscenes_map{name}_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(d.join("v1.0-mini")).unwrap();
    std::fs::create_dir_all(d.join("maps/expansion")).unwrap();
    for e in std::fs::read_dir(root.join("v1.0-mini")).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, d.join("v1.0-mini").join(p.file_name().unwrap())).unwrap();
    }
    let mp = "maps/expansion/singapore-onenorth.json";
    let mut m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.join(mp)).unwrap()).unwrap();
    edit(&mut m);
    std::fs::write(d.join(mp), serde_json::to_string(&m).unwrap()).unwrap();
    let t = Instant::now();
    let e = format!(
        "{:#}",
        nuscenes::load(&spec(&d)).expect_err("a broken map must fail")
    );
    assert!(t.elapsed().as_secs_f64() < 30.0, "{:?}", t.elapsed());
    let _ = std::fs::remove_dir_all(&d);
    e
}

/// Issue #18 on the map expansion: far nodes, absurd arcline paths (a 10^9 m piece would be sampled into
/// 2 * 10^9 points; a 1e-300 m radius gives non-finite poses) are refused naming the layer and row.
#[test]
fn hostile_map_expansion_is_refused() {
    use serde_json::json;
    let Some(root) = dataroot() else { return };
    let e = broken_map(root, "node", |m| m["node"][5]["x"] = json!(-3e8));
    assert!(
        e.contains("`node`") && e.contains("row 5") && e.contains("columns `x`, `y`"),
        "{e}"
    );
    let first_lane = |m: &serde_json::Value| m["lane"][0]["token"].as_str().unwrap().to_string();
    let e = broken_map(root, "len", |m| {
        let t = first_lane(m);
        m["arcline_path_3"][&t][0]["segment_length"] = json!([1e9, 0.0, 0.0]);
    });
    assert!(
        e.contains("arcline_path_3") && e.contains("segment lengths"),
        "{e}"
    );
    let e = broken_map(root, "radius", |m| {
        let t = first_lane(m);
        m["arcline_path_3"][&t][0]["radius"] = json!(1e-300);
    });
    assert!(e.contains("arcline_path_3") && e.contains("radius"), "{e}");
    let e = broken_map(root, "start", |m| {
        let t = first_lane(m);
        m["arcline_path_3"][&t][0]["start_pose"] = json!([1e12, 0.0, 0.0]);
    });
    assert!(
        e.contains("arcline_path_3") && e.contains("start_pose"),
        "{e}"
    );
    let e = broken_map(root, "heading", |m| {
        let t = first_lane(m);
        m["arcline_path_3"][&t][0]["start_pose"][2] = json!(1e200);
    });
    assert!(
        e.contains("start_pose") && e.contains("not an angle"),
        "{e}"
    );
}

/// Import time of scene-0061 (printed; a benchmark, not an assertion on time).
#[test]
fn import_speed() {
    let Some(root) = dataroot() else { return };
    let mut times = vec![];
    for _ in 0..3 {
        let t = Instant::now();
        let log = nuscenes::load_log(&spec(root)).unwrap();
        times.push(t.elapsed().as_secs_f64());
        assert_eq!(log.keyframes.len(), 39);
    }
    times.sort_by(f64::total_cmp);
    eprintln!(
        "nuScenes import of scene-0061 (39 samples, 4664 annotations, 615 sample_data, map expansion): \
         median {:.3} s, fastest {:.3} s ({} build)",
        times[1],
        times[0],
        if cfg!(debug_assertions) { "debug" } else { "release" }
    );
}

fn path(shape: &str, radius: f64, lengths: [f64; 3]) -> ArclinePath {
    ArclinePath {
        start: [1.0, 2.0, 0.0],
        shape: shape.into(),
        radius,
        lengths,
    }
}

#[test]
fn arcline_quarter_circle_and_straight() {
    let r = 10.0;
    let q = std::f64::consts::FRAC_PI_2 * r;
    // A left quarter circle from (1, 2) heading +x ends at (1 + r, 2 + r) heading +y.
    let p = path("LSL", r, [q, 0.0, 0.0]);
    let pts = p.discretize(0.5).unwrap();
    let end = pts.last().unwrap();
    assert!(
        (end[0] - 11.0).abs() < 1e-9 && (end[1] - 12.0).abs() < 1e-9,
        "{end:?}"
    );
    assert!((end[2] - std::f64::consts::FRAC_PI_2).abs() < 1e-9);
    for w in pts.windows(2) {
        let d = ((w[1][0] - w[0][0]).powi(2) + (w[1][1] - w[0][1]).powi(2)).sqrt();
        assert!(d <= 0.5 + 1e-9);
    }
    // Right turn, then 5 m straight, then a left turn back: ends heading +x again, 2 r + 5 m ahead.
    let p = path("RSL", r, [q, 5.0, q]);
    let end = *p.discretize(1.0).unwrap().last().unwrap();
    assert!((end[0] - (1.0 + 2.0 * r)).abs() < 1e-9, "{end:?}");
    assert!((end[1] - (2.0 - 2.0 * r - 5.0)).abs() < 1e-9, "{end:?}");
    assert!(end[2].abs() < 1e-9);
    assert!(path("LXL", r, [1.0, 1.0, 1.0]).signs().is_err());
    assert!(path("LR", r, [1.0, 1.0, 1.0]).signs().is_err());
}

/// `b2dr run --renderer log-replay` on the nuScenes scene: the planner sees the recorded JPEGs (the image nearest
/// in time, read from DATAROOT), and reference retrieval over the real rig equals the linear scan.
#[test]
fn log_replay_and_retrieval_use_the_recorded_images() {
    use b2dr::eval::run::{run, RendererMode, RunConfig};
    use b2dr::projection::{retrieve, FrameIndex};
    let Some(root) = dataroot() else { return };
    let shared = shared().unwrap();
    let sc = nuscenes::load(&spec(root)).unwrap();
    let out = std::env::temp_dir().join(format!("b2dr_nuscenes_lr_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let cfg = RunConfig {
        scenario: format!("nuscenes:{}:v1.0-mini:scene-0061", root.display()),
        renderer: RendererMode::LogReplay,
        model: None,
        planner: b2dr::sim::PlannerSpec::Expert,
        agents: b2dr::sim::AgentMode::Idm,
        controller: b2dr::sim::closed_loop::Controller::Lqr,
        steps: 6,
        planner_timeout_s: 30.0,
        planner_start_timeout_s: 300.0,
        cameras: vec!["CAM_FRONT".into(), "CAM_BACK".into()],
        size: (56, 104),
        seed: 0,
        dtype: b2dr::tensor::DType::F32,
        gif: false,
        shard: None,
        requests: Default::default(),
    };
    run(None, &cfg, &out, false).unwrap();
    for cam in ["CAM_FRONT", "CAM_BACK"] {
        // Step 0 shows the first keyframe's real image, resized as the image store does.
        let got = image::open(out.join(format!("scene-0061/frames/0000_{cam}.png")))
            .unwrap()
            .to_rgb8();
        let jpg = image::open(shared.join(format!("keyframe-scene-0061/{cam}.jpg")))
            .unwrap()
            .to_rgb8();
        let want = image::imageops::resize(&jpg, 104, 56, image::imageops::FilterType::Triangle);
        assert_eq!(got.into_raw(), want.into_raw(), "{cam}");
    }
    let _ = std::fs::remove_dir_all(&out);
    let idx = FrameIndex::new(&sc.rig.frames);
    let mut found = 0;
    for (k, e) in sc.ego.iter().enumerate() {
        let e2g = b2dr::scene::import::ego2global(&e.rear_axle);
        for c in &sc.rig.cameras {
            let r = idx.retrieve(&sc.rig.frames, &c.name, &e2g);
            assert_eq!(
                r,
                retrieve(&sc.rig.frames, &c.name, &e2g),
                "step {k} {}",
                c.name
            );
            found += usize::from(r.front.is_some()) + usize::from(r.rear.is_some());
        }
    }
    assert!(found > sc.len() * 6, "{found}");
}

/// Non-key camera sample_data (12 Hz sweeps) become frames of one image per camera between the keyframe frames;
/// the keyframe frames stay on the log steps, and log replay can pick a sweep image.
#[test]
fn camera_sweeps_become_frames() {
    let Some(root) = write_fixture("sweeps", &["--camera-sweeps"]) else {
        return;
    };
    let sc = nuscenes::load(&spec(&root)).unwrap();
    assert_eq!(sc.rig.frames.len(), 39 + 38 * 5);
    let mut keyframes = 0;
    for w in sc.rig.frames.windows(2) {
        assert!(w[0].timestamp_us < w[1].timestamp_us);
    }
    for f in &sc.rig.frames {
        assert_eq!(f.images.len(), 6);
        let ts: Vec<i64> = f.images.iter().map(|i| i.timestamp_us).collect();
        assert!(ts.iter().max().unwrap() - ts.iter().min().unwrap() < 60_000);
        let mut cams: Vec<&str> = f.images.iter().map(|i| i.camera.as_str()).collect();
        cams.sort_unstable();
        cams.dedup();
        assert_eq!(cams.len(), 6);
        if f.timestamp_us % 500_000 == 0 {
            keyframes += 1;
        }
    }
    assert_eq!(keyframes, 39);
    // 0.25 s: the nearest CAM_FRONT image is a sweep (keyframes fire at about -35 ms and 465 ms).
    let img = b2dr::eval::sensors::nearest_recorded(&sc, "CAM_FRONT", 0.25).unwrap();
    assert!(img.path.contains("/sweeps/CAM_FRONT/"), "{}", img.path);
    assert!((img.timestamp_us - 250_000).abs() < 42_000);
    let _ = std::fs::remove_dir_all(&root);
}

/// Makes a FIFO at `p` (`mkfifo`); false when that fails.
fn mkfifo(p: &Path) -> bool {
    Command::new("mkfifo")
        .arg(p)
        .status()
        .is_ok_and(|s| s.success())
}

/// Symbolic links in a DATAROOT (issue #18; docs/nuscenes.md "Symbolic links"): links that point outside the
/// DATAROOT are followed (the tables folder, the maps and the images of this copy all live in the fixture's
/// DATAROOT), while a link (or a file) that is not a regular file once followed (a FIFO here: reading it would
/// block) is an error naming the table, or the sample_data row and its filename, and fails fast.
#[test]
fn symlinks_in_the_dataroot() {
    let Some(root) = dataroot() else { return };
    let dst = std::env::temp_dir().join(format!("b2dr_nuscenes_links_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dst);
    std::fs::create_dir_all(&dst).unwrap();
    for d in ["v1.0-mini", "maps", "samples"] {
        std::os::unix::fs::symlink(root.join(d), dst.join(d)).unwrap();
    }
    let log = nuscenes::load_log(&spec(&dst)).unwrap();
    let img = &log.scenario.rig.frames[0].images[0];
    assert!(img.path.starts_with(dst.to_str().unwrap()), "{}", img.path);
    assert!(Path::new(&img.path).is_file(), "{}", img.path);
    let want = nuscenes::load(&spec(root)).unwrap();
    assert_eq!(log.scenario.ego.len(), want.ego.len());
    assert_eq!(log.scenario.tracks.len(), want.tracks.len());

    // A table that is a link to a FIFO outside the DATAROOT.
    let fifo = std::env::temp_dir().join(format!("b2dr_nuscenes_fifo_{}", std::process::id()));
    let _ = std::fs::remove_file(&fifo);
    if !mkfifo(&fifo) {
        eprintln!("skipping the FIFO part: mkfifo failed");
        let _ = std::fs::remove_dir_all(&dst);
        return;
    }
    std::fs::remove_file(dst.join("v1.0-mini")).unwrap();
    std::fs::create_dir_all(dst.join("v1.0-mini")).unwrap();
    for e in std::fs::read_dir(root.join("v1.0-mini")).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, dst.join("v1.0-mini").join(p.file_name().unwrap())).unwrap();
    }
    let ego = dst.join("v1.0-mini/ego_pose.json");
    std::fs::remove_file(&ego).unwrap();
    std::os::unix::fs::symlink(&fifo, &ego).unwrap();
    let t0 = Instant::now();
    let e = format!("{:#}", nuscenes::load(&spec(&dst)).unwrap_err());
    assert!(
        e.contains("table `ego_pose`") && e.contains("not a regular file"),
        "{e}"
    );
    std::fs::remove_file(&ego).unwrap();
    std::fs::copy(root.join("v1.0-mini/ego_pose.json"), &ego).unwrap();

    // An image that is a link to the FIFO.
    std::fs::remove_file(dst.join("samples")).unwrap();
    let cams = dst.join("samples/CAM_FRONT");
    std::fs::create_dir_all(&cams).unwrap();
    let first = std::fs::read_dir(root.join("samples/CAM_FRONT"))
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .min()
        .unwrap();
    std::os::unix::fs::symlink(&fifo, cams.join(&first)).unwrap();
    let e = format!("{:#}", nuscenes::load(&spec(&dst)).unwrap_err());
    assert!(
        e.contains("table `sample_data`")
            && e.contains("column `filename`")
            && e.contains(first.to_str().unwrap())
            && e.contains("not a regular file"),
        "{e}"
    );
    assert!(t0.elapsed() < std::time::Duration::from_secs(30));
    let _ = std::fs::remove_dir_all(&dst);
    let _ = std::fs::remove_file(&fifo);
}

/// Dividers (`road_divider`, `lane_divider`: their `line` geometry) and stop lines (`stop_line` polygons as
/// convex quadrilaterals) of the map expansion come into the scene map (issue #17): exactly the fixture's
/// records that meet the region, with their points.
#[test]
fn dividers_and_stop_lines_come_from_the_map_expansion() {
    use b2dr::scene::geometry::Aabb;
    use b2dr::scene::map::MapLineKind;
    use glam::DVec2;
    use std::collections::HashMap;
    let Some(root) = dataroot() else { return };
    let sc = nuscenes::load(&spec(root)).unwrap();
    assert!(!sc.map.lines.is_empty() && !sc.map.stop_lines.is_empty());
    let region = Aabb::from_points(&sc.ego.iter().map(|e| e.rear_axle.pos()).collect::<Vec<_>>())
        .expand(200.0);
    let map = nuscenes::expansion::load(root, "singapore-onenorth", &region).unwrap();
    let file: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(root.join("maps/expansion/singapore-onenorth.json")).unwrap(),
    )
    .unwrap();
    let nodes: HashMap<&str, DVec2> = file["node"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| {
            (
                n["token"].as_str().unwrap(),
                DVec2::new(n["x"].as_f64().unwrap(), n["y"].as_f64().unwrap()),
            )
        })
        .collect();
    let pts = |toks: &serde_json::Value| -> Vec<DVec2> {
        toks.as_array()
            .unwrap()
            .iter()
            .map(|t| nodes[t.as_str().unwrap()])
            .collect()
    };
    let lines: HashMap<&str, Vec<DVec2>> = file["line"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| (l["token"].as_str().unwrap(), pts(&l["node_tokens"])))
        .collect();
    let polys: HashMap<&str, Vec<DVec2>> = file["polygon"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| {
            (
                p["token"].as_str().unwrap(),
                pts(&p["exterior_node_tokens"]),
            )
        })
        .collect();
    let meets = |p: &[DVec2]| region.overlaps(&Aabb::from_points(p));
    let mut want = vec![];
    for (layer, kind) in [
        ("road_divider", MapLineKind::RoadDivider),
        ("lane_divider", MapLineKind::LaneDivider),
    ] {
        for r in file[layer].as_array().unwrap() {
            let p = &lines[r["line_token"].as_str().unwrap()];
            if meets(p) {
                want.push((r["token"].as_str().unwrap().to_string(), kind, p.clone()));
            }
        }
    }
    assert!(want.iter().any(|w| w.1 == MapLineKind::RoadDivider));
    assert!(want.iter().any(|w| w.1 == MapLineKind::LaneDivider));
    let got: Vec<_> = map
        .lines
        .iter()
        .map(|l| (l.id.clone(), l.kind, l.points.clone()))
        .collect();
    assert_eq!(got, want);
    let want_stop: Vec<(String, Vec<DVec2>)> = file["stop_line"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            (
                r["token"].as_str().unwrap().to_string(),
                polys[r["polygon_token"].as_str().unwrap()].clone(),
            )
        })
        .filter(|(_, p)| meets(p))
        .collect();
    assert!(!want_stop.is_empty());
    let got_stop: Vec<(String, Vec<DVec2>)> = map
        .stop_lines
        .iter()
        .map(|s| (s.id.clone(), s.polygon.to_vec()))
        .collect();
    assert_eq!(got_stop, want_stop);
    // the layout masks draw the painted dividers (not dividers derived from the lanes): the layer's divider
    // polylines are exactly the map's lines
    use b2dr::projection::{MapClass, MapGeometry};
    let layer = b2dr::projection::scene::map_layer(&map);
    let dividers: Vec<Vec<DVec2>> = layer
        .elements()
        .iter()
        .filter(|e| e.class == MapClass::LaneDivider)
        .map(|e| match &e.geometry {
            MapGeometry::Polyline(p) => p.iter().map(|v| v.truncate()).collect(),
            other => panic!("a divider drawn as {other:?}"),
        })
        .collect();
    let painted: Vec<Vec<DVec2>> = map
        .lines
        .iter()
        .filter(|l| l.points.len() >= 2)
        .map(|l| l.points.clone())
        .collect();
    assert_eq!(dividers, painted);
    // a stop line polygon that is not a quadrilateral: the rectangle along its longest edge enclosing it
    let q = nuscenes::expansion::quadrilateral(&[
        DVec2::new(0.0, 0.0),
        DVec2::new(4.0, 0.0),
        DVec2::new(4.0, 1.0),
        DVec2::new(2.0, 1.5),
        DVec2::new(0.0, 1.0),
    ])
    .unwrap();
    let near = |a: DVec2, b: DVec2| a.distance(b) < 1e-12;
    assert!(
        near(q[0], DVec2::new(0.0, 0.0)) && near(q[2], DVec2::new(4.0, 1.5)),
        "{q:?}"
    );
}

/// The rig's lidar2ego is the calibration of the scene's LIDAR_TOP (the fixture writes a real nuScenes
/// LIDAR_TOP record: translation (0.943713, 0, 1.84023), rotation w, x, y, z below), not the nominal mounting
/// (issue #34).
#[test]
fn lidar2ego_is_the_lidar_top_calibration() {
    let Some(root) = dataroot() else { return };
    let sc = nuscenes::load(&spec(root)).unwrap();
    let q = glam::DQuat::from_xyzw(
        -0.006492242056004365,
        0.010646214713995808,
        -0.7063073142877817,
        0.7077955119163518,
    );
    let want = glam::DMat4::from_rotation_translation(
        q.normalize(),
        glam::DVec3::new(0.943713, 0.0, 1.84023),
    );
    assert!(
        sc.rig.lidar2ego.abs_diff_eq(want, 1e-9),
        "{}",
        sc.rig.lidar2ego
    );
    assert!(!sc
        .rig
        .lidar2ego
        .abs_diff_eq(b2dr::scene::camera::nuscenes_lidar2ego(), 1e-3));
}
