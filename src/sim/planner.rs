//! Planners: the `Planner` trait for in-process users and the built-in planners (expert log replay,
//! constant velocity, IDM lane following). The external-process planner is in [`super::external`].
use super::ego::EgoState;
use super::idm::{idm_step, lane_states, IdmParams, IdmPath, Lead};
use super::trajectory::Trajectory;
use crate::scene::geometry::{OrientedBox, Part, Pose2, Shape};
use crate::scene::{CameraImage, Scenario, TrafficLightStatus};
use anyhow::{ensure, Result};
use glam::DVec2;

/// Number of poses and spacing of a planner reply (ego frame, excluding the current pose).
pub const PLAN_POSES: usize = 8;
pub const PLAN_DT_S: f64 = 0.5;

/// An object as planners see it.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ObjectView {
    pub track: usize,
    pub class: crate::scene::ObjectClass,
    pub bbox: OrientedBox,
    #[serde(serialize_with = "crate::scene::geometry::ser_dvec2")]
    pub velocity: DVec2,
}

/// Everything a planner receives at a planning step.
pub struct PlannerInput<'a> {
    pub scenario: &'a Scenario,
    pub step: usize,
    pub time_s: f64,
    pub ego: &'a EgoState,
    pub objects: &'a [ObjectView],
    /// Recorded camera images of this step (paths into the log; empty where the log has none).
    pub images: &'a [CameraImage],
    /// The images of the simulated state from the run's sensors (renderer), in memory; empty without one.
    pub frames: &'a [super::sensors::CameraFrame],
    /// The navigation command from the route, by the run's definition (`command_def`).
    pub command: super::sensors::Command,
    pub command_def: super::command::CommandDef,
    /// The last ego states at 0.5 s, newest first, in the current ego frame ([`super::history`]).
    pub history: &'a [super::history::HistoryEntry],
}

/// A driving model under test. `plan` returns a global-frame rear-axle trajectory starting at the current
/// time (its first pose may be the current pose).
pub trait Planner {
    fn name(&self) -> String;
    /// Called once before a scenario starts.
    fn start(&mut self, _scenario: &Scenario) -> Result<()> {
        Ok(())
    }
    fn plan(&mut self, input: &PlannerInput) -> Result<Trajectory>;
    /// Called once after a scenario ends (also after a failure).
    fn finish(&mut self) {}
}

/// Largest ego-frame coordinate of a planned pose (m).
pub const MAX_PLAN_EXTENT_M: f64 = 1e4;

/// Converts an ego-frame reply (poses at t + 0.5 k, k = 1..=8) into a global trajectory that starts at the
/// current rear-axle pose. Checks count, finiteness and magnitude.
pub fn trajectory_from_ego_frame(
    ego: &EgoState,
    local: &[Pose2],
    min_poses: usize,
) -> Result<Trajectory> {
    ensure!(
        local.is_empty() || local.len() >= min_poses,
        "planner returned {} poses, at least {min_poses} are required",
        local.len()
    );
    trajectory_from_ego_poses(ego, local, PLAN_DT_S)
}

/// Converts ego-frame rear-axle poses at `t + dt_s k`, k = 1..=n, into a global trajectory that starts at the
/// current rear-axle pose (what the 10 Hz tracker follows between plans). Checks finiteness and magnitude;
/// `dt_s` must be positive and finite (a planner's declared spacing is checked where it is parsed).
pub fn trajectory_from_ego_poses(ego: &EgoState, local: &[Pose2], dt_s: f64) -> Result<Trajectory> {
    ensure!(!local.is_empty(), "planner returned an empty trajectory");
    ensure!(
        dt_s.is_finite() && dt_s > 0.0,
        "pose spacing dt_s = {dt_s} s must be a positive number"
    );
    for (i, p) in local.iter().enumerate() {
        ensure!(
            p.x.is_finite() && p.y.is_finite() && p.heading.is_finite(),
            "planner returned a non-finite pose: poses[{i}] = ({}, {}, {})",
            p.x,
            p.y,
            p.heading
        );
        // beyond these the controller and the metrics would compute with overflowing squares
        ensure!(
            p.x.abs() <= MAX_PLAN_EXTENT_M && p.y.abs() <= MAX_PLAN_EXTENT_M && p.heading.abs() <= 1e3,
            "planner returned poses[{i}] = ({}, {}, {}): |x|, |y| must be <= {MAX_PLAN_EXTENT_M} m (ego frame) \
             and |heading| <= 1000 rad",
            p.x,
            p.y,
            p.heading
        );
    }
    let t0 = (ego.time_s * 1e6).round() as i64;
    let mut times = vec![t0];
    let mut poses = vec![ego.rear_axle];
    for (k, p) in local.iter().enumerate() {
        // each time from its own product: no rounding error accumulates along the trajectory
        times.push(t0 + (dt_s * 1e6 * (k + 1) as f64).round() as i64);
        poses.push(ego.rear_axle.compose(p));
    }
    Trajectory::new(times, poses)
}

/// Expert: replays the logged ego poses from the current step over the next 4 s (nuPlan's log future
/// trajectory, current logged pose included).
pub struct ExpertPlanner;

impl Planner for ExpertPlanner {
    fn name(&self) -> String {
        "expert".into()
    }
    fn plan(&mut self, input: &PlannerInput) -> Result<Trajectory> {
        let sc = input.scenario;
        let horizon = (PLAN_POSES as f64 * PLAN_DT_S / sc.dt).round() as usize;
        let k0 = input.step.min(sc.len() - 1);
        let k1 = (k0 + horizon).min(sc.len() - 1);
        ensure!(k1 > k0, "expert log ends at step {k0}");
        let times = (k0..=k1)
            .map(|k| (k as f64 * sc.dt * 1e6).round() as i64)
            .collect();
        let poses = (k0..=k1).map(|k| sc.ego[k].rear_axle).collect();
        Trajectory::new(times, poses)
    }
}

/// Constant velocity: keeps the current speed and heading for 4 s.
pub struct ConstantVelocityPlanner;

impl Planner for ConstantVelocityPlanner {
    fn name(&self) -> String {
        "cv".into()
    }
    fn plan(&mut self, input: &PlannerInput) -> Result<Trajectory> {
        let v = input.ego.vx;
        let local: Vec<Pose2> = (1..=PLAN_POSES)
            .map(|k| Pose2::new(v * PLAN_DT_S * k as f64, 0.0, 0.0))
            .collect();
        trajectory_from_ego_frame(input.ego, &local, PLAN_POSES)
    }
}

/// Privileged IDM lane follower: follows the expert route's lanes from the lane under the ego, with IDM
/// speed control behind the nearest object on its path (or a red light's stop line).
#[derive(Default)]
pub struct IdmPlanner {
    pub params: IdmParams,
}

impl Planner for IdmPlanner {
    fn name(&self) -> String {
        "idm".into()
    }
    fn plan(&mut self, input: &PlannerInput) -> Result<Trajectory> {
        let sc = input.scenario;
        let map = &sc.map;
        let ego = input.ego;
        let center = sc.ego_params.center_of(&ego.rear_axle);
        let Some(lane) = map.match_lane(center.pos(), center.heading, 5.0) else {
            // Off the map: fall back to constant velocity.
            return ConstantVelocityPlanner.plan(input);
        };
        // Lanes ahead: along the route when it continues from this lane, else straightest successors.
        let route: Vec<usize> = sc
            .route
            .lane_ids
            .iter()
            .filter_map(|id| map.lane_index(id))
            .collect();
        let mut lanes = vec![lane];
        let mut total = map.lanes[lane].centre.length();
        while total < 120.0 && lanes.len() < 12 {
            let last = *lanes.last().unwrap_or(&lane);
            let succ = &map.lanes[last].successors;
            let next = succ
                .iter()
                .copied()
                .find(|s| route.contains(s))
                .or_else(|| {
                    succ.iter().copied().min_by(|a, b| {
                        map.lanes[*a]
                            .centre
                            .start_curvature()
                            .total_cmp(&map.lanes[*b].centre.start_curvature())
                    })
                });
            let Some(n) = next else { break };
            total += map.lanes[n].centre.length();
            lanes.push(n);
        }
        let mut states = Vec::new();
        for &l in &lanes {
            states.extend(lane_states(map, l));
        }
        states.push(*states.last().unwrap_or(&center));
        let Some(path) = IdmPath::from_states(&states) else {
            return ConstantVelocityPlanner.plan(input);
        };
        let arc = crate::scene::geometry::Polyline::new(path.pts.clone(), None);
        let (s0, _) = arc.project(center.pos());
        // Leader: nearest object whose box meets the path ahead buffered by half the ego width.
        let ahead: Vec<DVec2> = {
            let mut v = vec![arc.point_at(s0)];
            v.extend(
                arc.points
                    .iter()
                    .zip(&arc.s)
                    .filter(|(_, s)| **s > s0)
                    .map(|(p, _)| *p),
            );
            v
        };
        let buf = Shape::buffered_path(&ahead, sc.ego_params.width / 2.0);
        let mut lead = Lead {
            progress: arc.length() - s0,
            velocity: 0.0,
            length_rear: 0.0,
        };
        let half = sc.ego_params.length / 2.0;
        let mut consider = |shape: &Shape, pos: DVec2, vel: DVec2, len: f64| {
            if shape.intersects(&buf) {
                let (s, _) = arc.project(pos);
                let gap = s - s0 - half - len / 2.0;
                if s > s0 && gap < lead.progress {
                    let dir = arc.pose_at(s).dir();
                    lead = Lead {
                        progress: gap.max(0.0),
                        velocity: vel.dot(dir).max(0.0),
                        length_rear: 0.0,
                    };
                }
            }
        };
        for o in input.objects {
            consider(
                &Shape::from_box(&o.bbox),
                o.bbox.center.pos(),
                o.velocity,
                o.bbox.length,
            );
        }
        let lights = sc.lights_at(input.step);
        for &l in &lanes {
            if lights
                .iter()
                .any(|&(i, s)| i == l && s == TrafficLightStatus::Red)
            {
                for &sl in &map.lanes[l].stop_lines {
                    let mut s = Shape::new();
                    s.push(Part::Quad(map.stop_lines[sl].polygon));
                    let c = map.stop_lines[sl].polygon.iter().copied().sum::<DVec2>() / 4.0;
                    consider(&s, c, DVec2::ZERO, 0.0);
                }
            }
        }
        let target = map.lanes[lane]
            .speed_limit_mps
            .filter(|v| *v > 0.0)
            .unwrap_or(self.params.target_velocity);
        let (mut s, mut v) = (s0, ego.vx.max(0.0));
        let mut lead_pos = lead.progress;
        let mut local = Vec::with_capacity(PLAN_POSES);
        for k in 1..=PLAN_POSES * 5 {
            let l = Lead {
                progress: lead_pos,
                velocity: lead.velocity,
                length_rear: 0.0,
            };
            let (ds, nv) = idm_step(&self.params, target, v, &l, 0.1);
            s += ds;
            v = nv;
            // The leader keeps its speed: the gap changes by (v_lead - v_ego) dt.
            lead_pos += (lead.velocity - ds / 0.1) * 0.1;
            if k % 5 == 0 {
                let c = arc.pose_at(s);
                let rear = sc.ego_params.rear_axle_of(&c);
                local.push(ego.rear_axle.relative(&rear));
            }
        }
        trajectory_from_ego_frame(ego, &local, PLAN_POSES)
    }
}
