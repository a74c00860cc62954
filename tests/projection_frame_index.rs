//! The retrieval index (`projection::frame_index`) against the linear scan (`projection::retrieval::retrieve`):
//! equal results on random data (ties included) and few visited nodes on a driven path.
use b2dr::projection::frame_index::{FrameIndex, LEAF};
use b2dr::projection::retrieval::retrieve;
use b2dr::scene::camera::{CameraImage, RecordedFrame};
use glam::DMat4;
use glam::DVec3;
use rand::{Rng, SeedableRng};

fn pose(x: f64, y: f64, yaw: f64) -> DMat4 {
    DMat4::from_rotation_translation(glam::DQuat::from_rotation_z(yaw), DVec3::new(x, y, 0.0))
}

fn frames_at(pts: &[(f64, f64)], cams: &[&str]) -> Vec<RecordedFrame> {
    pts.iter()
        .enumerate()
        .map(|(k, &(x, y))| RecordedFrame {
            timestamp_us: k as i64,
            ego2global: pose(x, y, 0.0),
            images: cams
                .iter()
                .enumerate()
                .map(|(c, cam)| CameraImage {
                    camera: cam.to_string(),
                    path: String::new(),
                    timestamp_us: k as i64,
                    ego2global: pose(x + c as f64 * 0.01, y, 0.0),
                })
                .collect(),
        })
        .collect()
}

#[test]
fn equals_the_linear_scan_on_random_data() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    for case in 0..40 {
        let n = [0, 1, 5, 9, 50, 300][case % 6];
        // Integer grids make exact ties in P common; the rest is continuous.
        let grid = case % 3 == 0;
        let pts: Vec<(f64, f64)> = (0..n)
            .map(|_| {
                if grid {
                    (rng.gen_range(-5..5) as f64, rng.gen_range(-5..5) as f64)
                } else {
                    (rng.gen_range(-100.0..100.0), rng.gen_range(-100.0..100.0))
                }
            })
            .collect();
        let mut frames = frames_at(&pts, &["CAM_FRONT", "CAM_BACK"]);
        // Some frames lack a camera.
        for f in frames.iter_mut().step_by(7) {
            f.images.retain(|i| i.camera != "CAM_BACK");
        }
        let idx = FrameIndex::new(&frames);
        for _ in 0..50 {
            let yaw = if grid {
                (rng.gen_range(0..8) as f64) * std::f64::consts::FRAC_PI_4
            } else {
                rng.gen_range(-3.2..3.2)
            };
            let (x, y) = if grid {
                (rng.gen_range(-5..5) as f64, rng.gen_range(-5..5) as f64)
            } else {
                (rng.gen_range(-120.0..120.0), rng.gen_range(-120.0..120.0))
            };
            let e2g = pose(x, y, yaw);
            for cam in ["CAM_FRONT", "CAM_BACK", "CAM_NONE"] {
                assert_eq!(
                    idx.retrieve(&frames, cam, &e2g),
                    retrieve(&frames, cam, &e2g),
                    "case {case} cam {cam} pose ({x}, {y}, {yaw})"
                );
            }
        }
    }
}

#[test]
fn a_driven_path_visits_few_nodes() {
    // 20,000 images along a winding road; queries on the road heading along it.
    let n = 20_000;
    let path = |s: f64| (s, 30.0 * (s / 200.0).sin());
    let pts: Vec<(f64, f64)> = (0..n).map(|k| path(k as f64 * 0.5)).collect();
    let frames = frames_at(&pts, &["CAM_FRONT"]);
    let idx = FrameIndex::new(&frames);
    let mut worst = 0;
    for q in 0..200 {
        let s = q as f64 * 49.7 + 0.25;
        let (x, y) = path(s);
        let (x2, y2) = path(s + 0.01);
        let e2g = pose(x, y, (y2 - y).atan2(x2 - x));
        for ahead in [true, false] {
            let (got, visited) = idx.nearest("CAM_FRONT", &e2g, ahead);
            assert!(got.is_some());
            worst = worst.max(visited);
        }
        assert_eq!(
            idx.retrieve(&frames, "CAM_FRONT", &e2g),
            retrieve(&frames, "CAM_FRONT", &e2g)
        );
    }
    // log2(20000 / 8) ~ 11 levels; a linear scan touches 20,000 images.
    assert!(worst < 400, "visited {worst} nodes");
    eprintln!(
        "frame index: at most {worst} of {} nodes visited per query (20,000 images)",
        2 * n / LEAF
    );
}
