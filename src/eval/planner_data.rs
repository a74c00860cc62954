//! `b2dr export-planner`: imitation data for an image-reading planner (issue: the image-driven planner under
//! test). For every planner step (2 Hz) of each scenario's expert log, and for each ego displacement, the
//! ground-truth cameras the planner would see there (the synthetic world's exact renderer, logged agents), the
//! inputs a protocol-v2 planner gets (speed, acceleration, navigation command) and the target: the expert's
//! next 8 rear-axle poses at 0.5 s in the (displaced) ego frame. A displaced sample's target returns to the
//! logged path: the displacement fades out linearly over [`RECOVERY_S`] (the usual DAgger-free way to teach
//! recovery from off-log states an imitation planner meets in closed loop).
//!
//!   <out>/index.json                         format, size, cameras, offsets, files and sample counts
//!   <out>/NNNN_<scenario>.safetensors        image u8 (S, C, H, W, 3), speed f32 (S), accel f32 (S),
//!                                            command u8 (S) 0 left 1 straight 2 right, target f32 (S, 8, 3),
//!                                            step i32 (S), offset f32 (S, 2) (lateral m, yaw rad)
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::{ensure, Context as _, Result};
use serde_json::json;

use crate::scene::geometry::Pose2;
use crate::scene::import::ego2global;
use crate::scene::Scenario;
use crate::sim::sensors::{navigation_command, Command};
use crate::world::export::shard::Shard;
use crate::world::images::ImageStore;
use crate::world::view::ego_pose;

pub const FORMAT: &str = "b2dr-planner-data";
pub const VERSION: u32 = 1;
/// Poses of the target (the protocol's reply) and their spacing.
pub const POSES: usize = 8;
pub const POSE_DT_S: f64 = 0.5;
/// A displacement fades out over this time along the target.
pub const RECOVERY_S: f64 = 2.0;

#[derive(Clone, Debug)]
pub struct PlannerDataOptions {
    pub scenarios: Vec<String>,
    pub out: PathBuf,
    /// (H, W)
    pub size: (usize, usize),
    /// Empty: CAM_FRONT.
    pub cameras: Vec<String>,
    /// Displacements (lateral m, yaw rad) in the ego frame; (0, 0) is the logged pose.
    pub offsets: Vec<(f64, f64)>,
    /// Planner period in log steps (5 = 2 Hz at 10 Hz).
    pub every: usize,
    pub progress: bool,
}

#[derive(Clone, Debug, PartialEq)]
pub struct PlannerDataSummary {
    pub samples: usize,
    pub files: usize,
    pub skipped_off_map: usize,
}

pub fn command_code(c: Command) -> u8 {
    match c {
        Command::Left => 0,
        Command::Straight => 1,
        Command::Right => 2,
    }
}

/// The ego-frame target of log step `step` displaced by `offset` (lateral m, yaw rad): the logged poses at
/// `step + k * POSE_DT_S / dt` (k = 1..=8), each with the displacement scaled by `1 - t_k / RECOVERY_S`
/// (clamped at 0), seen from the displaced pose. None when the log ends before the last pose.
pub fn target(sc: &Scenario, step: usize, offset: (f64, f64)) -> Option<Vec<[f64; 3]>> {
    let per = (POSE_DT_S / sc.dt).round() as usize;
    let last = step + POSES * per;
    if per == 0 || last >= sc.len() {
        return None;
    }
    let from = sc.ego[step]
        .rear_axle
        .compose(&Pose2::new(0.0, offset.0, offset.1));
    Some(
        (1..=POSES)
            .map(|k| {
                let r = (1.0 - k as f64 * POSE_DT_S / RECOVERY_S).max(0.0);
                let p = sc.ego[step + k * per].rear_axle.compose(&Pose2::new(
                    0.0,
                    offset.0 * r,
                    offset.1 * r,
                ));
                let l = from.relative(&p);
                [l.x, l.y, l.heading]
            })
            .collect(),
    )
}

/// Ego-frame longitudinal speed of log step `step` (the protocol's `ego.vx`).
fn speed(sc: &Scenario, step: usize) -> f64 {
    let e = &sc.ego[step];
    let (s, c) = e.rear_axle.heading.sin_cos();
    c * e.velocity.x + s * e.velocity.y
}

pub fn export(o: &PlannerDataOptions) -> Result<PlannerDataSummary> {
    ensure!(o.every >= 1, "--every must be >= 1");
    ensure!(!o.offsets.is_empty(), "--offsets: no offset given");
    // the bounds of `world --offset` and `export-training --offsets` (issue #36, item 7)
    use crate::world::view::{MAX_OFFSET_DEG, MAX_OFFSET_M};
    for &(lat, yaw) in &o.offsets {
        ensure!(
            lat.is_finite()
                && yaw.is_finite()
                && lat.abs() <= MAX_OFFSET_M
                && yaw.abs() <= MAX_OFFSET_DEG.to_radians(),
            "--offsets {lat},{}: |LATERAL_M| must be <= {MAX_OFFSET_M} m and |YAW_DEG| <= {MAX_OFFSET_DEG} degrees",
            yaw.to_degrees()
        );
    }
    let (h, w) = o.size;
    ensure!(
        (8..=4096).contains(&h) && (8..=4096).contains(&w),
        "--size {h}x{w}: each side must be in 8..=4096"
    );
    std::fs::create_dir_all(&o.out).with_context(|| format!("creating {}", o.out.display()))?;
    let cams_req = if o.cameras.is_empty() {
        vec!["CAM_FRONT".to_string()]
    } else {
        o.cameras.clone()
    };
    let mut scenarios: Vec<Scenario> = vec![];
    for s in &o.scenarios {
        scenarios.extend(crate::world::load_all(s).with_context(|| format!("--scenario {s}"))?);
    }
    ensure!(!scenarios.is_empty(), "--scenario: no scenario given");
    let mut files = vec![];
    let mut total = 0;
    let mut skipped = 0;
    for (k, sc) in scenarios.iter().enumerate() {
        ensure!(
            sc.source.starts_with("builtin:"),
            "{}: planner data needs a synthetic scenario (builtin:...): its ground truth is rendered",
            sc.source
        );
        let cams = sc.select_cameras(&cams_req)?;
        let store = ImageStore::new(sc, None);
        let mut shard = Shard::default();
        for step in (0..sc.len()).step_by(o.every) {
            for &off in &o.offsets {
                let Some(t) = target(sc, step, off) else {
                    continue;
                };
                let Ok(pose) = ego_pose(sc, step, &Pose2::new(0.0, off.0, off.1)) else {
                    skipped += 1;
                    continue;
                };
                let frames = store
                    .world()
                    .render_step(&cams, &ego2global(&pose), step, w, h, 1)?;
                let rgb: Vec<u8> = frames.iter().flat_map(|f| f.rgb.iter().copied()).collect();
                shard.push("image", &[cams.len(), h, w, 3], &rgb)?;
                shard.push("speed", &[], &[speed(sc, step) as f32])?;
                shard.push("accel", &[], &[sc.ego[step].accel as f32])?;
                shard.push(
                    "command",
                    &[],
                    &[command_code(navigation_command(sc, &pose))],
                )?;
                let flat: Vec<f32> = t.iter().flatten().map(|&v| v as f32).collect();
                shard.push("target", &[POSES, 3], &flat)?;
                shard.push("step", &[], &[step as i32])?;
                shard.push("offset", &[2], &[off.0 as f32, off.1 as f32])?;
                shard.rows += 1;
            }
        }
        let n = shard.rows;
        let name = format!("{k:04}_{}.safetensors", crate::scene::safe_name(&sc.name));
        if n > 0 {
            let meta = HashMap::from([
                ("scenario".to_string(), sc.source.clone()),
                ("format".to_string(), FORMAT.to_string()),
            ]);
            shard.write(&o.out.join(&name), meta)?;
            files.push(json!({"file": name, "scenario": sc.source, "samples": n}));
        }
        total += n;
        if o.progress {
            eprintln!("[{}/{}] {}: {n} samples", k + 1, scenarios.len(), sc.source);
        }
    }
    let index = json!({
        "format": FORMAT, "version": VERSION, "size": [h, w],
        "cameras": cams_req, "offsets": o.offsets, "every": o.every,
        "poses": POSES, "pose_dt_s": POSE_DT_S, "recovery_s": RECOVERY_S,
        "commands": ["left", "straight", "right"],
        "samples": total, "skipped_off_map": skipped, "files": files,
    });
    write_json(&o.out.join("index.json"), &index)?;
    Ok(PlannerDataSummary {
        samples: total,
        files: files.len(),
        skipped_off_map: skipped,
    })
}

fn write_json(p: &Path, v: &serde_json::Value) -> Result<()> {
    std::fs::write(p, serde_json::to_string_pretty(v)? + "\n")
        .with_context(|| format!("writing {}", p.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn town() -> Scenario {
        crate::world::load_all("builtin:straight:3")
            .unwrap()
            .remove(0)
    }

    #[test]
    fn logged_target_is_the_expert_future_in_the_ego_frame() {
        let sc = town();
        let t = target(&sc, 10, (0.0, 0.0)).unwrap();
        let from = sc.ego[10].rear_axle;
        for (k, p) in t.iter().enumerate() {
            let g = from.compose(&Pose2::new(p[0], p[1], p[2]));
            let e = sc.ego[10 + 5 * (k + 1)].rear_axle;
            assert!(
                (g.x - e.x).abs() < 1e-9 && (g.y - e.y).abs() < 1e-9,
                "pose {k}"
            );
        }
        assert!(target(&sc, sc.len() - 40, (0.0, 0.0)).is_none());
        assert!(target(&sc, sc.len() - 41, (0.0, 0.0)).is_some());
    }

    #[test]
    fn displaced_target_returns_to_the_log_within_the_recovery_time() {
        let sc = town();
        let (d, y) = (1.5, 0.1);
        let t = target(&sc, 10, (d, y)).unwrap();
        let from = sc.ego[10].rear_axle.compose(&Pose2::new(0.0, d, y));
        // 0.5 s in: three quarters of the displacement left; from 2 s on: on the logged path
        let p1 = from.compose(&Pose2::new(t[0][0], t[0][1], t[0][2]));
        let l1 = sc.ego[15].rear_axle.relative(&p1);
        assert!((l1.y - 0.75 * d).abs() < 1e-9 && (l1.heading - 0.75 * y).abs() < 1e-9);
        for (k, p) in t.iter().enumerate().skip(3) {
            let g = from.compose(&Pose2::new(p[0], p[1], p[2]));
            let e = sc.ego[10 + 5 * (k + 1)].rear_axle;
            assert!(
                (g.x - e.x).abs() < 1e-9 && (g.y - e.y).abs() < 1e-9,
                "pose {k}"
            );
        }
    }

    /// An export size too large to allocate (issue #18) is an error naming --size, before any work.
    #[test]
    fn huge_size_is_refused() {
        let out = std::env::temp_dir().join(format!("b2dr_pd_huge_{}", std::process::id()));
        for size in [(1usize << 40, 64), (64, usize::MAX), (4097, 8)] {
            let e = export(&PlannerDataOptions {
                scenarios: vec!["builtin:straight:3".into()],
                out: out.clone(),
                size,
                cameras: vec![],
                offsets: vec![(0.0, 0.0)],
                every: 5,
                progress: false,
            })
            .unwrap_err();
            assert!(format!("{e:#}").contains("--size"), "{size:?}: {e:#}");
        }
        assert!(!out.exists());
    }
}
