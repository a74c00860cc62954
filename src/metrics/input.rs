//! What the simulator hands to the closed-loop score: one [`ScenarioTrace`] per simulated scenario plus a
//! map behind the [`MapQuery`] trait.
//!
//! Conventions (all `f64`, metres / seconds / radians, global map frame, `glam::DVec2`):
//! - the ego pose is the REAR AXLE (nuPlan's reference point); its box is derived from [`EgoDims`];
//! - ego velocity / acceleration are given at the rear axle in the EGO frame (x forward, y left), like nuPlan's
//!   `DynamicCarState.rear_axle_velocity_2d` / `rear_axle_acceleration_2d`;
//! - objects are oriented boxes given by their CENTRE, heading, length (along heading) and width, and their
//!   velocity in the GLOBAL frame (nuPlan's `Agent.velocity`);
//! - headings are not required to be wrapped; the metrics wrap/unwrap where nuPlan does.
//!
//! This interface is meant to stay stable; additions go at the end of structs with `#[serde(default)]`.
use crate::scene::geometry::OrientedBox;
use crate::scene::pacifica;
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// Ego box geometry relative to the rear axle. Defaults: nuPlan's Pacifica ([`crate::scene::pacifica`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EgoDims {
    /// Box width (m).
    pub width: f64,
    /// Rear axle to front bumper (m).
    pub front_length: f64,
    /// Rear axle to rear bumper (m).
    pub rear_length: f64,
    /// Wheel base (m).
    pub wheel_base: f64,
    /// Rear axle to box centre, along the heading (m). nuPlan: 1.461 for the Pacifica.
    pub cog_position_from_rear_axle: f64,
}

impl Default for EgoDims {
    fn default() -> Self {
        Self::PACIFICA
    }
}

impl EgoDims {
    /// nuPlan's Chrysler Pacifica ([`crate::scene::pacifica`]).
    pub const PACIFICA: EgoDims = EgoDims {
        width: pacifica::WIDTH,
        front_length: pacifica::FRONT_LENGTH,
        rear_length: pacifica::REAR_LENGTH,
        wheel_base: pacifica::WHEEL_BASE,
        cog_position_from_rear_axle: pacifica::REAR_AXLE_TO_CENTER,
    };

    /// Box length = front_length + rear_length.
    pub fn length(&self) -> f64 {
        self.front_length + self.rear_length
    }

    /// Build from a box (length, width) whose centre is `rear_to_center` ahead of the rear axle
    /// (e.g. for nuScenes logs, where the data gives the ego box size).
    pub fn from_box(length: f64, width: f64, rear_to_center: f64, wheel_base: f64) -> Self {
        EgoDims {
            width,
            front_length: length / 2.0 + rear_to_center,
            rear_length: length / 2.0 - rear_to_center,
            wheel_base,
            cog_position_from_rear_axle: rear_to_center,
        }
    }
}

/// One ego sample (nuPlan `EgoState`), rear-axle referenced.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EgoStep {
    /// Time (s), strictly increasing along a trace.
    pub time_s: f64,
    /// Rear-axle position, global frame.
    pub position: DVec2,
    /// Heading (rad), global frame.
    pub heading: f64,
    /// Rear-axle velocity in the ego frame (x longitudinal, y lateral).
    pub velocity: DVec2,
    /// Rear-axle acceleration in the ego frame (x longitudinal, y lateral).
    pub acceleration: DVec2,
    /// Yaw rate (rad/s).
    pub yaw_rate: f64,
    /// Yaw acceleration (rad/s^2).
    pub yaw_acceleration: f64,
}

/// The object class of a trace: the scene's one class enum (nuPlan `TrackedObjectType`).
pub use crate::scene::ObjectClass;

/// One observed object at one step (nuPlan `Agent` / `StaticObject`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectState {
    /// Track id, stable over the scenario.
    pub track_id: u64,
    pub class: ObjectClass,
    /// Box centre, global frame.
    pub center: DVec2,
    /// Heading (rad), global frame.
    pub heading: f64,
    /// Box length along the heading (m).
    pub length: f64,
    /// Box width (m).
    pub width: f64,
    /// Velocity, global frame (zero for static objects).
    pub velocity: DVec2,
    /// True for nuPlan `Agent`s (vehicles, pedestrians, bicycles); false for static objects. A non-agent is
    /// always a "stopped track" in the collision classification.
    pub is_agent: bool,
}

/// Everything the score needs about one simulated scenario.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct ScenarioTrace {
    /// Scenario name / token (for the report).
    pub name: String,
    #[serde(default)]
    pub ego_dims: EgoDims,
    /// Simulated ego, one entry per step.
    pub ego: Vec<EgoStep>,
    /// Observed objects per step; `objects.len() == ego.len()`.
    pub objects: Vec<Vec<ObjectState>>,
    /// Expert (logged) ego over the same time span (at least the same start and end).
    pub expert: Vec<EgoStep>,
    /// Route: roadblock ids in driving order (nuPlan `scenario.get_route_roadblock_ids()`); may be empty.
    /// Carried for reports: nuPlan's closed-loop metrics derive the route from the expert's driven lanes
    /// (ego_progress_along_expert_route), not from this list.
    #[serde(default)]
    pub route_roadblocks: Vec<u64>,
}

/// A lane or a lane connector. nuPlan keeps them in two tables; ids are only unique within one kind.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct LaneId {
    pub id: u64,
    pub is_connector: bool,
}

/// What the metrics read about one lane / lane connector.
#[derive(Clone, Copy, Debug)]
pub struct LaneView<'a> {
    pub id: LaneId,
    /// Polygon, one ring, no repeated closing point needed.
    pub polygon: &'a [DVec2],
    /// Centre line (nuPlan baseline path), in driving direction, at least 2 points.
    pub baseline: &'a [DVec2],
    /// Speed limit (m/s) if known.
    pub speed_limit: Option<f64>,
    /// Roadblock (lane group / lane group connector) id; for a connector, its lane-group-connector id.
    pub roadblock: u64,
    /// Outgoing edges (lanes or connectors that follow).
    pub successors: &'a [LaneId],
    /// Incoming edges.
    pub predecessors: &'a [LaneId],
}

/// Map queries the metrics need. Implemented by the simulator's map and by the metrics' own test map (`vecmap`).
pub trait MapQuery {
    /// Lanes and lane connectors whose polygon contains `p` (boundary included), appended to `out` in a
    /// deterministic order.
    fn lanes_at(&self, p: DVec2, out: &mut Vec<LaneId>);
    /// Lane / connector by id.
    fn lane(&self, id: LaneId) -> Option<LaneView<'_>>;
    /// True if `p` lies in the drivable area (nuPlan DRIVABLE_AREA: road segments, intersections, generic
    /// drivable areas, car parks).
    fn in_drivable_area(&self, p: DVec2) -> bool;
    /// Distance from `p` to the nearest drivable-area polygon (0 inside); `f64::INFINITY` when there is none.
    fn distance_to_drivable_area(&self, p: DVec2) -> f64;
    /// True if `p` lies in an intersection polygon.
    fn in_intersection(&self, p: DVec2) -> bool;
    /// True if `p` lies in the polygon of roadblock `roadblock` (a lane group when `is_connector` is false,
    /// a lane group connector when true), as named by [`LaneView::roadblock`].
    fn roadblock_contains(&self, roadblock: u64, is_connector: bool, p: DVec2) -> bool;
}

impl EgoStep {
    /// nuPlan `dynamic_car_state.speed`: magnitude of the rear-axle velocity.
    pub fn speed(&self) -> f64 {
        self.velocity.length()
    }

    /// Box centre (nuPlan `ego_state.center`): the rear axle moved `cog_position_from_rear_axle` forward.
    pub fn center(&self, dims: &EgoDims) -> DVec2 {
        self.position
            + DVec2::new(self.heading.cos(), self.heading.sin()) * dims.cog_position_from_rear_axle
    }

    /// Ego footprint (nuPlan `car_footprint.oriented_box`).
    pub fn footprint(&self, dims: &EgoDims) -> OrientedBox {
        OrientedBox::at(self.center(dims), self.heading, dims.length(), dims.width)
    }
}

impl ObjectState {
    /// Oriented box of the object.
    pub fn footprint(&self) -> OrientedBox {
        OrientedBox::at(self.center, self.heading, self.length, self.width)
    }

    /// nuPlan `velocity.magnitude()` for agents, 0 for static objects.
    pub fn speed(&self) -> f64 {
        if self.is_agent {
            self.velocity.length()
        } else {
            0.0
        }
    }
}
