//! Plan replies of protocol v2 as driving models emit them (docs/planner_protocol.md, "Reply"): a declared pose
//! spacing `dt_s`, a `frame` (the rear axle, or the lidar frame of the request time) and poses `[x, y]` (headings
//! derived from the path) or `[x, y, heading]`. [`parse_plan_reply`] turns one into rear-axle poses in the ego
//! frame of the request time, ready for [`super::planner::trajectory_from_ego_poses`]. Every invalid reply is
//! an error naming the field; version 1 replies keep their own parser ([`super::external::parse_reply`]).
use anyhow::{anyhow, bail, ensure, Result};
use glam::{DMat4, DVec2};
use serde_json::Value;

use super::external::MAX_POSES;
use super::lidar::{lidar_heading_to_ego, lidar_xy_to_ego};
use super::planner::PLAN_DT_S;
use crate::scene::geometry::{wrap_angle, Pose2};

/// Pose spacing when a reply states none (s).
pub const DEFAULT_DT_S: f64 = PLAN_DT_S;
/// Accepted pose spacings (s): at least 10 ms (trajectory times are whole microseconds, and nothing plans
/// faster than 100 Hz), at most 2 s (coarser plans leave the 10 Hz tracker too little path between poses).
pub const MIN_DT_S: f64 = 0.01;
pub const MAX_DT_S: f64 = 2.0;
/// Shortest accepted horizon (poses x dt_s, s): the plan must last until the next plan (0.5 s later) plus the
/// tracker's 1 s look-ahead, with margin; end-to-end models plan 3 s (6 poses at 0.5 s) or more.
pub const MIN_HORIZON_S: f64 = 2.0;
/// A point closer than this to the point that set the previous heading keeps that heading (m): a stopped
/// car's jitter must not spin its heading.
pub const MIN_HEADING_SEGMENT_M: f64 = 0.05;
/// Largest |heading| accepted (rad), as in version 1.
pub const MAX_HEADING_RAD: f64 = 1e3;

/// The frame of a reply's poses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReplyFrame {
    /// The rear axle at the request time: x forward, y left, heading 0 = ego heading (version 1's frame).
    EgoRearAxle,
    /// The rig's lidar at the request time (`lidar2ego` of the `start` message); `[x, y]` are ground points,
    /// headings are about lidar +z from lidar +x.
    Lidar,
}

impl ReplyFrame {
    pub fn name(self) -> &'static str {
        match self {
            ReplyFrame::EgoRearAxle => "ego_rear_axle",
            ReplyFrame::Lidar => "lidar",
        }
    }
}

/// A parsed plan reply: rear-axle poses in the ego frame of the request time at `dt_s k`, k = 1..=n.
#[derive(Clone, Debug, PartialEq)]
pub struct PlanReply {
    pub dt_s: f64,
    pub frame: ReplyFrame,
    /// Whether the headings were derived from the path (`[x, y]` poses).
    pub derived_headings: bool,
    pub poses: Vec<Pose2>,
}

/// Headings of path points (ego frame) from the path itself: point k takes the direction from the last point
/// that set a heading (the current pose (0, 0) at first) to it; a point within [`MIN_HEADING_SEGMENT_M`] of
/// that point keeps the previous heading (0, the current heading, at first) and does not move the anchor.
/// That is a backward difference along the path (the chord arriving at each point: on a curve it lags the
/// tangent by half the chord's turn); it assumes forward driving. Headings are unwrapped along the path.
pub fn headings_from_path(points: &[DVec2]) -> Vec<f64> {
    let (mut anchor, mut heading) = (DVec2::ZERO, 0.0f64);
    points
        .iter()
        .map(|&p| {
            let d = p - anchor;
            if d.length() >= MIN_HEADING_SEGMENT_M {
                heading += wrap_angle(d.y.atan2(d.x) - heading);
                anchor = p;
            }
            heading
        })
        .collect()
}

fn number(v: &Value, what: impl Fn() -> String) -> Result<f64> {
    v.as_f64()
        .ok_or_else(|| anyhow!("planner reply {} = {v} is not a number", what()))
}

/// Parses a version-2 plan reply (module docs); `lidar2ego` converts `"frame": "lidar"` poses.
pub fn parse_plan_reply(v: &Value, lidar2ego: &DMat4) -> Result<PlanReply> {
    if let Some(e) = v.get("error") {
        bail!("planner reported an error: {e}");
    }
    let dt_s = match v.get("dt_s") {
        None | Some(Value::Null) => DEFAULT_DT_S,
        Some(d) => {
            let dt = number(d, || "`dt_s`".into())?;
            ensure!(
                (MIN_DT_S..=MAX_DT_S).contains(&dt),
                "planner reply `dt_s` = {dt}: the pose spacing must be in [{MIN_DT_S}, {MAX_DT_S}] s"
            );
            dt
        }
    };
    let frame = match v.get("frame") {
        None | Some(Value::Null) => ReplyFrame::EgoRearAxle,
        Some(Value::String(s)) if s == "ego_rear_axle" => ReplyFrame::EgoRearAxle,
        Some(Value::String(s)) if s == "lidar" => ReplyFrame::Lidar,
        Some(f) => bail!("planner reply `frame` = {f}: expected \"ego_rear_axle\" or \"lidar\""),
    };
    let arr = v
        .get("poses")
        .ok_or_else(|| anyhow!("planner reply has no `poses` field"))?
        .as_array()
        .ok_or_else(|| anyhow!("planner reply `poses` is not an array"))?;
    ensure!(!arr.is_empty(), "planner reply `poses` is empty");
    ensure!(
        arr.len() <= MAX_POSES,
        "planner reply has {} poses (at most {MAX_POSES} are accepted)",
        arr.len()
    );
    let mut width = 0;
    let mut raw = Vec::with_capacity(arr.len());
    for (i, p) in arr.iter().enumerate() {
        let c = p
            .as_array()
            .filter(|c| c.len() == 2 || c.len() == 3)
            .ok_or_else(|| {
                anyhow!(
                    "planner reply `poses[{i}]` = {:.80} is not [x, y] or [x, y, heading]",
                    p.to_string()
                )
            })?;
        if i == 0 {
            width = c.len();
        }
        ensure!(
            c.len() == width,
            "planner reply `poses`: poses[0] has {width} values but poses[{i}] has {} (all [x, y] or all \
             [x, y, heading])",
            c.len()
        );
        let f = |j: usize| number(&c[j], || format!("`poses[{i}][{j}]`"));
        let h = if width == 3 { f(2)? } else { 0.0 };
        ensure!(
            h.abs() <= MAX_HEADING_RAD,
            "planner reply `poses[{i}][2]` = {h}: |heading| must be <= {MAX_HEADING_RAD} rad"
        );
        raw.push(Pose2::new(f(0)?, f(1)?, h));
    }
    let horizon = raw.len() as f64 * dt_s;
    ensure!(
        horizon >= MIN_HORIZON_S - 1e-9,
        "planner reply `poses`: {} poses x `dt_s` {dt_s} s cover {horizon} s; at least {MIN_HORIZON_S} s are \
         required",
        raw.len()
    );
    let mut poses = raw;
    if frame == ReplyFrame::Lidar {
        for (i, p) in poses.iter_mut().enumerate() {
            let q = lidar_xy_to_ego(lidar2ego, p.x, p.y).ok_or_else(|| {
                anyhow!(
                    "planner reply `frame` \"lidar\": poses[{i}] has no ground point (the rig's lidar z axis \
                     lies in the ground plane)"
                )
            })?;
            let h = lidar_heading_to_ego(lidar2ego, p.heading);
            *p = Pose2::new(q.x, q.y, h);
        }
    }
    let derived_headings = width == 2;
    if derived_headings {
        let pts: Vec<DVec2> = poses.iter().map(|p| p.pos()).collect();
        for (p, h) in poses.iter_mut().zip(headings_from_path(&pts)) {
            p.heading = h;
        }
    }
    Ok(PlanReply {
        dt_s,
        frame,
        derived_headings,
        poses,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;
    use std::f64::consts::FRAC_PI_2;

    /// A lidar mounted 1 m ahead of the rear axle, 1.8 m up, turned -90 degrees about z without tilt (the
    /// nuScenes axes, rounded): lidar (x, y) is ego (1 + y, -x), lidar heading h is ego heading h - pi/2.
    fn lidar2ego() -> DMat4 {
        DMat4::from_rotation_translation(
            glam::DQuat::from_rotation_z(-FRAC_PI_2),
            glam::DVec3::new(1.0, 0.0, 1.8),
        )
    }

    fn assert_poses(got: &[Pose2], want: &[(f64, f64, f64)]) {
        assert_eq!(got.len(), want.len(), "{got:?}");
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g.x - w.0).abs() < 1e-9
                    && (g.y - w.1).abs() < 1e-9
                    && (g.heading - w.2).abs() < 1e-9,
                "poses[{i}]: got ({}, {}, {}), want {w:?}",
                g.x,
                g.y,
                g.heading
            );
        }
    }

    /// dt 0.5 s, six [x, y] points in the lidar frame. By hand, with ego = (1 + y_l, -x_l):
    ///   lidar (0, 1)     -> ego (2, 0)       heading from (0, 0):  atan2(0, 2)     = 0
    ///   lidar (0, 3)     -> ego (4, 0)       from (2, 0):          atan2(0, 2)     = 0
    ///   lidar (0.5, 5)   -> ego (6, -0.5)    from (4, 0):          atan2(-0.5, 2)  = -0.244978663126864
    ///   lidar (1.5, 7)   -> ego (8, -1.5)    from (6, -0.5):       atan2(-1, 2)    = -0.463647609000806
    ///   lidar (1.5, 7.02)-> ego (8.02, -1.5) 0.02 m from (8, -1.5) < 5 cm: keeps     -0.463647609000806
    ///   lidar (3.5, 9)   -> ego (10, -3.5)   from (8, -1.5) (the anchor did not move): atan2(-2, 2) = -pi/4
    #[test]
    fn lidar_xy_points_become_rear_axle_poses_with_derived_headings() {
        let v = json!({"dt_s": 0.5, "frame": "lidar",
            "poses": [[0.0, 1.0], [0.0, 3.0], [0.5, 5.0], [1.5, 7.0], [1.5, 7.02], [3.5, 9.0]]});
        let r = parse_plan_reply(&v, &lidar2ego()).unwrap();
        assert_eq!(
            (r.dt_s, r.frame, r.derived_headings),
            (0.5, ReplyFrame::Lidar, true)
        );
        assert_poses(
            &r.poses,
            &[
                (2.0, 0.0, 0.0),
                (4.0, 0.0, 0.0),
                (6.0, -0.5, -0.244978663126864),
                (8.0, -1.5, -0.463647609000806),
                (8.02, -1.5, -0.463647609000806),
                (10.0, -3.5, -std::f64::consts::FRAC_PI_4),
            ],
        );
        // the same path in the ego frame gives the same poses
        let v = json!({"poses": [[2.0, 0.0], [4.0, 0.0], [6.0, -0.5], [8.0, -1.5], [8.02, -1.5], [10.0, -3.5]]});
        let e = parse_plan_reply(&v, &lidar2ego()).unwrap();
        assert_eq!(e.frame, ReplyFrame::EgoRearAxle);
        for (a, b) in e.poses.iter().zip(&r.poses) {
            assert!(
                (a.x - b.x).abs() < 1e-9
                    && (a.y - b.y).abs() < 1e-9
                    && (a.heading - b.heading).abs() < 1e-9
            );
        }
    }

    /// A first point on the current pose keeps the current heading (0); headings unwrap across +-pi (a path
    /// bending left past pi: pi - 0.1 then pi + 0.1, not -pi + 0.1).
    #[test]
    fn derived_headings_keep_and_unwrap() {
        let h = headings_from_path(&[
            DVec2::new(0.01, 0.0),
            DVec2::new(0.0, 1.0),
            DVec2::new(-1.0, 1.0 + 0.1f64.tan()),
            DVec2::new(-2.0, 1.0 + 0.1f64.tan() - 0.1f64.tan()),
        ]);
        let want = [
            0.0,
            FRAC_PI_2,
            std::f64::consts::PI - 0.1,
            std::f64::consts::PI + 0.1,
        ];
        for (g, w) in h.iter().zip(want) {
            assert!((g - w).abs() < 1e-9, "{h:?}");
        }
    }

    /// dt 1.0 with headings: ego frame as given; lidar frame (x, y, h) -> ego (1 + y, -x, h - pi/2); two poses
    /// at 1 s cover exactly the 2 s minimum.
    #[test]
    fn declared_dt_and_headings() {
        let v =
            json!({"dt_s": 1.0, "poses": [[5.0, 0.0, 0.0], [10.0, 1.0, 0.1], [15.0, 3.0, 0.3]]});
        let r = parse_plan_reply(&v, &lidar2ego()).unwrap();
        assert_eq!((r.dt_s, r.derived_headings), (1.0, false));
        assert_poses(
            &r.poses,
            &[(5.0, 0.0, 0.0), (10.0, 1.0, 0.1), (15.0, 3.0, 0.3)],
        );
        let v = json!({"dt_s": 1.0, "frame": "lidar",
            "poses": [[0.0, 4.0, FRAC_PI_2], [-1.0, 9.0, FRAC_PI_2 + 0.2]]});
        let r = parse_plan_reply(&v, &lidar2ego()).unwrap();
        assert_poses(&r.poses, &[(5.0, 0.0, 0.0), (10.0, 1.0, 0.2)]);
        // the tracker's trajectory uses the declared spacing: poses at t + 1 s, t + 2 s
        let ego = crate::sim::ego::EgoState {
            time_s: 3.0,
            rear_axle: Pose2::new(100.0, 50.0, FRAC_PI_2),
            vx: 0.0,
            vy: 0.0,
            ax: 0.0,
            ay: 0.0,
            steering: 0.0,
            steering_rate: 0.0,
            yaw_rate: 0.0,
            yaw_accel: 0.0,
        };
        let t = crate::sim::planner::trajectory_from_ego_poses(&ego, &r.poses, r.dt_s).unwrap();
        assert_eq!(t.times_us, vec![3_000_000, 4_000_000, 5_000_000]);
        // ego (5, 0) ahead of a rear axle heading north is global (100, 55); (10, 1) is (99, 60)
        assert!((t.poses[1].x - 100.0).abs() < 1e-9 && (t.poses[1].y - 55.0).abs() < 1e-9);
        assert!((t.poses[2].x - 99.0).abs() < 1e-9 && (t.poses[2].y - 60.0).abs() < 1e-9);
        assert!((t.poses[2].heading - (FRAC_PI_2 + 0.2)).abs() < 1e-9);
        // at 1.5 s the tracker's reference is half way between the two poses
        let p = t.pose_at_us(4_500_000);
        assert!(
            (p.x - 99.5).abs() < 1e-9 && (p.y - 57.5).abs() < 1e-9,
            "{p:?}"
        );
    }

    #[test]
    fn defaults_are_version_one_values() {
        let v =
            json!({"poses": [[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0], [4.0, 0.0, 0.0]]});
        let r = parse_plan_reply(&v, &lidar2ego()).unwrap();
        assert_eq!(
            (r.dt_s, r.frame, r.derived_headings),
            (0.5, ReplyFrame::EgoRearAxle, false)
        );
        let v = json!({"dt_s": null, "frame": null, "poses": v["poses"]});
        assert_eq!(parse_plan_reply(&v, &lidar2ego()).unwrap().dt_s, 0.5);
    }

    /// Every invalid reply is an error naming its field.
    #[test]
    fn invalid_replies_name_the_field() {
        let six = json!([[1, 0], [2, 0], [3, 0], [4, 0], [5, 0], [6, 0]]);
        let cases = [
            (
                json!({"dt_s": 0.0, "poses": six}),
                "`dt_s` = 0: the pose spacing must be in [0.01, 2] s",
            ),
            (json!({"dt_s": -0.5, "poses": six}), "`dt_s` = -0.5"),
            (json!({"dt_s": 2.5, "poses": six}), "`dt_s` = 2.5"),
            (json!({"dt_s": 0.001, "poses": six}), "`dt_s` = 0.001"),
            (
                json!({"dt_s": "NaN", "poses": six}),
                "`dt_s` = \"NaN\" is not a number",
            ),
            (
                json!({"frame": "camera", "poses": six}),
                "`frame` = \"camera\": expected \"ego_rear_axle\" or \"lidar\"",
            ),
            (json!({"frame": 1, "poses": six}), "`frame` = 1"),
            (
                json!({"poses": [[1, 0], [2, 0], [3, 0, 0], [4, 0], [5, 0]]}),
                "`poses`: poses[0] has 2 values but poses[2] has 3",
            ),
            (
                json!({"poses": [[1, 0], [2, 0], [3, 0]]}),
                "`poses`: 3 poses x `dt_s` 0.5 s cover 1.5 s; at least 2 s are required",
            ),
            (
                json!({"dt_s": 0.1, "poses": six}),
                "6 poses x `dt_s` 0.1 s cover 0.6000000000000001 s",
            ),
            (json!({"poses": []}), "`poses` is empty"),
            (
                json!({"poses": [[1, 0], [2, 0, 0, 0]]}),
                "`poses[1]` = [2,0,0,0] is not [x, y] or [x, y, heading]",
            ),
            (
                json!({"poses": [[1, 0], [2, "x"]]}),
                "`poses[1][1]` = \"x\" is not a number",
            ),
            (
                json!({"poses": [[1, 0, 1e4], [2, 0, 0]]}),
                "`poses[0][2]` = 10000: |heading| must be <= 1000 rad",
            ),
            (json!({"poses": {"x": 1}}), "`poses` is not an array"),
            (json!({"dt_s": 0.5}), "no `poses` field"),
            (
                json!({"error": "no camera"}),
                "planner reported an error: \"no camera\"",
            ),
        ];
        for (v, needle) in cases {
            let e = parse_plan_reply(&v, &lidar2ego()).unwrap_err().to_string();
            assert!(e.contains(needle), "{v}: {e}");
        }
    }
}
