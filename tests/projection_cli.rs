//! `b2dr project` end to end on the shared keyframe (skips with a printed reason when the data is absent), and its
//! error on a malformed frame.
use std::path::PathBuf;
use std::process::Command;

fn data_dir() -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/nuscenes-mini");
    if p.join("keyframe-scene-0061/frame.json").exists() {
        Some(p)
    } else {
        eprintln!(
            "skipping: {} not found (shared nuScenes data absent)",
            p.display()
        );
        None
    }
}

#[test]
fn project_writes_masks_overlays_and_json() {
    let Some(data) = data_dir() else { return };
    let out = std::env::temp_dir().join(format!("b2dr_project_cli_{}", std::process::id()));
    let st = Command::new(env!("CARGO_BIN_EXE_b2dr"))
        .args(["project", "--frame"])
        .arg(data.join("keyframe-scene-0061/frame.json"))
        .arg("--out")
        .arg(&out)
        .args(["--size", "400x224", "--map"])
        .arg(data.join("maps/singapore-onenorth.drivable_area.geojson"))
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("projection.json")).unwrap())
            .unwrap();
    let cams = j["cameras"].as_object().unwrap();
    assert_eq!(cams.len(), 6);
    for (name, entries) in cams {
        for e in entries.as_array().unwrap() {
            assert!(e["box"].as_u64().unwrap() < 68);
            assert!(e["depth"].as_f64().unwrap() > 0.0);
            assert_eq!(e["corners_px"].as_array().unwrap().len(), 8);
            assert!(e["in_view"].is_boolean());
        }
        let dir = out.join(name);
        assert!(dir.join("overlay.jpg").exists());
        let m = image::open(dir.join("car.png")).unwrap();
        assert_eq!((m.width(), m.height()), (400, 224));
        assert_eq!(
            std::fs::read_dir(&dir)
                .unwrap()
                .filter(|e| e.as_ref().unwrap().path().extension().unwrap() == "png")
                .count(),
            15
        );
    }
    // CAM_FRONT: most listed boxes are in view, and the drivable area covers the bottom of the image
    let front = cams["CAM_FRONT"].as_array().unwrap();
    assert!(
        front
            .iter()
            .filter(|e| e["in_view"].as_bool().unwrap())
            .count()
            >= 20
    );
    let da = image::open(out.join("CAM_FRONT/drivable_area.png"))
        .unwrap()
        .to_luma8();
    assert_eq!(da.get_pixel(200, 220).0[0], 255);
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn project_reports_file_and_field_on_bad_frame() {
    let dir = std::env::temp_dir().join(format!("b2dr_project_cli_bad_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let f = dir.join("frame.json");
    std::fs::write(
        &f,
        r#"{"ego2global": [[1,0,0,0],[0,1,0,0],[0,0,1,0]], "cameras": {}, "boxes": []}"#,
    )
    .unwrap();
    let st = Command::new(env!("CARGO_BIN_EXE_b2dr"))
        .args(["project", "--frame"])
        .arg(&f)
        .arg("--out")
        .arg(dir.join("out"))
        .output()
        .unwrap();
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(
        err.contains("frame.json: ego2global") && err.contains("expected an array of length 4"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// Camera names in a frame file are data: "../../escape" or "a/b" become folder names inside --out, never paths
/// that leave it (issue #18).
#[test]
fn project_camera_names_from_the_frame_stay_inside_out() {
    let dir = std::env::temp_dir().join(format!("b2dr_project_cli_names_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    image::RgbImage::new(16, 9)
        .save(dir.join("cam.png"))
        .unwrap();
    let eye = serde_json::json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
    let cam = serde_json::json!({"image": "cam.png", "width": 16, "height": 9, "timestamp_us": 0,
        "intrinsic": [[10.0, 0.0, 8.0], [0.0, 10.0, 4.5], [0.0, 0.0, 1.0]],
        "cam2ego": [[0, 0, 1, 1.5], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1]], "ego2global": eye});
    let frame = serde_json::json!({"format": "b2dr-shared-keyframe/v1", "ego2global": eye,
        "cameras": {"../../escape": cam, "a/b": cam}, "boxes": []});
    std::fs::write(dir.join("frame.json"), frame.to_string()).unwrap();
    let out = dir.join("x").join("out");
    let st = Command::new(env!("CARGO_BIN_EXE_b2dr"))
        .args(["project", "--frame"])
        .arg(dir.join("frame.json"))
        .arg("--out")
        .arg(&out)
        .args(["--size", "16x8"])
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    assert!(out.join("______escape").is_dir() && out.join("a_b").is_dir());
    assert!(!dir.join("escape").exists() && !out.join("a").exists());
    std::fs::remove_dir_all(&dir).ok();
}
