//! Observation engines: what the driving model under test sees at a planner step. The closed loop calls a
//! [`Sensors`] with the SIMULATED state (the way nuPlan's observation engines are updated and Waymax's
//! `observe(state)` is called); a renderer is one implementation (the generative renderer, the synthetic
//! world's exact renderer, log replay), living above the simulator: this module never touches the GPU.
use std::sync::Arc;

use anyhow::Result;
use glam::{DMat3, DMat4, DVec2};

use super::closed_loop::AgentRecord;
use super::ego::EgoState;
use crate::scene::geometry::Pose2;
use crate::scene::Scenario;

/// One camera image of a planner step, in memory.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraFrame {
    pub camera: String,
    pub width: u32,
    pub height: u32,
    /// RGB8, row-major `(H, W, 3)`.
    pub rgb: Arc<Vec<u8>>,
    /// Pinhole intrinsics at `width x height`.
    pub intrinsic: DMat3,
    pub cam2ego: DMat4,
    /// Ego -> global of this image (the simulated ego for rendered frames, the log's for replayed ones).
    pub ego2global: DMat4,
}

impl CameraFrame {
    /// The frame as an `image` buffer.
    pub fn to_image(&self) -> image::RgbImage {
        image::RgbImage::from_raw(self.width, self.height, self.rgb.as_ref().clone())
            .unwrap_or_else(|| image::RgbImage::new(self.width, self.height))
    }

    /// The frame resized to `width x height` (Catmull-Rom), intrinsics rescaled with the pixel-centre
    /// convention (`u' = (u + 0.5) s - 0.5`).
    pub fn resized(&self, width: u32, height: u32) -> CameraFrame {
        if (width, height) == (self.width, self.height) {
            return self.clone();
        }
        let img = image::imageops::resize(
            &self.to_image(),
            width,
            height,
            image::imageops::FilterType::CatmullRom,
        );
        let (sx, sy) = (
            width as f64 / self.width as f64,
            height as f64 / self.height as f64,
        );
        let s = DMat3::from_cols(
            glam::DVec3::new(sx, 0.0, 0.0),
            glam::DVec3::new(0.0, sy, 0.0),
            glam::DVec3::new(0.5 * sx - 0.5, 0.5 * sy - 0.5, 1.0),
        );
        CameraFrame {
            camera: self.camera.clone(),
            width,
            height,
            rgb: Arc::new(img.into_raw()),
            intrinsic: s * self.intrinsic,
            cam2ego: self.cam2ego,
            ego2global: self.ego2global,
        }
    }
}

/// The simulated state at a planner step: what a renderer draws.
pub struct SensorState<'a> {
    pub scenario: &'a Scenario,
    pub step: usize,
    pub time_s: f64,
    pub ego: &'a EgoState,
    /// The ego box centre pose.
    pub ego_center: Pose2,
    /// Every other object as simulated (IDM agents where they run, replayed objects otherwise).
    pub agents: &'a [AgentRecord],
}

impl SensorState<'_> {
    /// The ego pose as ego -> global (rear axle on the ground plane, the nuScenes ego frame).
    pub fn ego2global(&self) -> DMat4 {
        crate::scene::import::ego2global(&self.ego.rear_axle)
    }
}

/// An observation engine (see the module docs). Called at every planner step with the simulated state.
pub trait Sensors {
    fn name(&self) -> String;
    /// Called once before a scenario (drops any state of the previous one: previous frames, caches).
    fn reset(&mut self, scenario: &Scenario) -> Result<()>;
    /// The camera images of this state. An error ends the scenario with that reason.
    fn observe(&mut self, state: &SensorState) -> Result<Vec<CameraFrame>>;
    /// Wall time per stage of the last `observe` (milliseconds), for the run's timing table.
    fn last_times(&self) -> Vec<(&'static str, f64)> {
        vec![]
    }
}

/// The navigation command an end-to-end model consumes (nuScenes/VAD style: turn left, turn right, go
/// straight), from the route: the route point 20 m ahead of the ego (along the route's lanes, from the
/// ego's projection on them) in the ego frame; lateral offset > 2 m is left, < -2 m right, else straight.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Command {
    Left,
    Right,
    Straight,
}

pub const COMMAND_LOOKAHEAD_M: f64 = 20.0;

/// The route's lane centrelines joined in driving order (None when fewer than two points).
pub(crate) fn route_line(sc: &Scenario) -> Option<crate::scene::geometry::Polyline> {
    let pts: Vec<DVec2> = sc
        .route
        .lane_ids
        .iter()
        .filter_map(|id| sc.map.lane_index(id))
        .flat_map(|l| sc.map.lanes[l].centre.points.iter().copied())
        .collect();
    (pts.len() >= 2).then(|| crate::scene::geometry::Polyline::new(pts, None))
}

pub fn navigation_command(sc: &Scenario, ego: &Pose2) -> Command {
    let Some(line) = route_line(sc) else {
        return Command::Straight;
    };
    let (s, _) = line.project(ego.pos());
    let target = line.point_at((s + COMMAND_LOOKAHEAD_M).min(line.length()));
    let local = ego.relative(&Pose2::new(target.x, target.y, 0.0));
    if local.y > 2.0 {
        Command::Left
    } else if local.y < -2.0 {
        Command::Right
    } else {
        Command::Straight
    }
}
