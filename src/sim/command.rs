//! Navigation command definitions, selectable per run (`b2dr run --command-def`). Both give one of
//! [`Command`]'s three values; the protocol-v2 `plan` message names the definition in `command_def`.
//!
//! - `route20` ([`navigation_command`], the default): the route point 20 m ahead of the ego's projection on
//!   the route's lanes, in the ego rear-axle frame; lateral offset > 2 m left, < -2 m right. This is the
//!   navigation command NAVSIM/OpenScene compute for nuPlan (`get_driving_command` in OpenScene's
//!   `DriveEngine/process_data/helpers/driving_command.py`: 20 m along the route centreline, +-2 m).
//! - `nuscenes` ([`nuscenes_command`]): how VAD and UniAD derive the command from a nuScenes sample: the ego's
//!   position 3 s ahead on its logged path (the 6th future keyframe at 2 Hz, or the last one the scene has),
//!   as the future LIDAR_TOP origin expressed in the current LIDAR_TOP frame; lidar x >= 2 m is RIGHT,
//!   <= -2 m LEFT, else straight. Followed: hustvl/VAD `tools/data_converter/vad_nuscenes_converter.py`
//!   (commit 1688c4b, lines 430-457: `get_global_sensor_pose` of each future sample, global -> ego -> lidar of
//!   the current sample, `if ego_fut_trajs[-1][0] >= 2: command = [1, 0, 0]  # Turn Right`,
//!   `elif ... <= -2: [0, 1, 0]  # Turn Left`, else `[0, 0, 1]  # Go Straight`), and OpenDriveLab/UniAD
//!   `projects/mmdet3d_plugin/datasets/data_utils/trajectory_api.py` (`get_sdc_planning_label`: the last valid
//!   of the 6 planning steps, `x >= 2: command = 0 #'RIGHT'`, `x <= -2: 1 #'LEFT'`, else `2 #'FORWARD'`).
//!   nuScenes' LIDAR_TOP has x right, y forward (its rotation is a -90 deg yaw about ego z, plus under 0.03 deg
//!   of tilt), so lidar x = -(ego-frame lateral offset): RIGHT is a target to the ego's right (ego y <= -2).
//!   b2dr measures the offset in the ego ground plane, independent of the rig's lidar axes (a nuPlan lidar
//!   keeps its own axes): `dy` = ego-frame y of the future lidar origin minus that of the current one.
//!
//! In closed loop the simulated ego is not where the expert was, so "3 s ahead on the logged path" is taken
//! along the ROUTE from the SIMULATED ego: the target is the route point at arc length `s_ego + d`, where
//! `s_ego` is the ego's projection on the route's lanes and `d` the distance the expert drove in the 3 s after
//! the current time (the logged rear-axle path length from the log step of the current time to 3 s later,
//! clamped to the log's end, as UniAD/VAD clamp to the scene's last sample); the target's heading is the
//! route's direction there (for the future lidar origin). Not the logged position at t + 3 s itself: an ego
//! running ahead of (or behind) the expert would then look backwards (or too far). A stopped expert gives
//! `d` = 0: the target is the ego's projection on the route, straight unless the ego is over 2 m off it.

use super::ego::EgoState;
use super::sensors::Command;
use crate::scene::geometry::Pose2;
use crate::scene::Scenario;

use super::sensors::route_line;
pub use super::sensors::{navigation_command, COMMAND_LOOKAHEAD_M};

/// Seconds ahead of the nuScenes/VAD command (6 keyframes at 2 Hz).
pub const NUSCENES_HORIZON_S: f64 = 3.0;
/// Lateral threshold (m) of both definitions.
pub const COMMAND_THRESHOLD_M: f64 = 2.0;

/// Which navigation command definition a run uses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum CommandDef {
    /// The route point 20 m ahead (NAVSIM/OpenScene), b2dr's original definition.
    #[default]
    Route20,
    /// The ego's position 3 s ahead on the expert's path, in the lidar frame (VAD / UniAD on nuScenes).
    Nuscenes,
}

impl CommandDef {
    pub fn name(self) -> &'static str {
        match self {
            Self::Route20 => "route20",
            Self::Nuscenes => "nuscenes",
        }
    }

    /// The command at the simulated state `ego` (its `time_s` picks the log step of the expert's travel).
    pub fn command(self, sc: &Scenario, ego: &EgoState) -> Command {
        match self {
            Self::Route20 => navigation_command(sc, &ego.rear_axle),
            Self::Nuscenes => nuscenes_command(sc, ego),
        }
    }
}

impl std::fmt::Display for CommandDef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for CommandDef {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Self> {
        match s {
            "route20" => Ok(Self::Route20),
            "nuscenes" => Ok(Self::Nuscenes),
            _ => anyhow::bail!("unknown command definition {s:?}: expected route20 or nuscenes"),
        }
    }
}

/// The distance the expert drove (logged rear-axle path length) from the log step at `time_s` to
/// [`NUSCENES_HORIZON_S`] later, clamped to the log.
pub fn expert_travel_m(sc: &Scenario, time_s: f64) -> f64 {
    if sc.ego.len() < 2 || sc.dt.is_nan() || sc.dt <= 0.0 || !time_s.is_finite() {
        return 0.0;
    }
    let last = sc.ego.len() - 1;
    let k0 = ((time_s / sc.dt).round().max(0.0) as usize).min(last);
    let k1 = (k0 + (NUSCENES_HORIZON_S / sc.dt).round() as usize).min(last);
    sc.ego[k0..=k1]
        .windows(2)
        .map(|w| (w[1].rear_axle.pos() - w[0].rear_axle.pos()).length())
        .filter(|d| d.is_finite())
        .sum()
}

/// The signed lateral offset (m, ego frame, + left) the nuScenes definition thresholds: the future lidar
/// origin (the rig's lidar mounting on the route pose [`expert_travel_m`] ahead) relative to the current one.
/// None without a route.
pub fn nuscenes_lateral_offset(sc: &Scenario, ego: &EgoState) -> Option<f64> {
    let line = route_line(sc)?;
    let (s, _) = line.project(ego.rear_axle.pos());
    let d = expert_travel_m(sc, ego.time_s);
    let target = line.pose_at((s + d).min(line.length()));
    let t = sc.rig.lidar2ego.w_axis;
    let mount = Pose2::new(t.x, t.y, 0.0);
    let now = ego.rear_axle.compose(&mount);
    let future = target.compose(&mount);
    Some(ego.rear_axle.relative(&future).y - ego.rear_axle.relative(&now).y)
}

/// The nuScenes / VAD / UniAD command (module docs): straight without a route.
pub fn nuscenes_command(sc: &Scenario, ego: &EgoState) -> Command {
    match nuscenes_lateral_offset(sc, ego) {
        // VAD / UniAD: lidar x >= 2 -> right, <= -2 -> left; lidar x = -dy (x right)
        Some(dy) if -dy >= COMMAND_THRESHOLD_M => Command::Right,
        Some(dy) if -dy <= -COMMAND_THRESHOLD_M => Command::Left,
        _ => Command::Straight,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn command_def_names_round_trip_and_unknown_is_an_error() {
        for d in [CommandDef::Route20, CommandDef::Nuscenes] {
            assert_eq!(d.name().parse::<CommandDef>().unwrap(), d);
            assert_eq!(serde_json::to_value(d).unwrap(), d.name());
        }
        assert_eq!(CommandDef::default(), CommandDef::Route20);
        let e = "vad".parse::<CommandDef>().unwrap_err().to_string();
        assert!(e.contains("route20 or nuscenes"), "{e}");
    }
}
