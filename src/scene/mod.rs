//! Scenario model: map, objects, ego log, route, traffic lights, camera rig and recorded frames. Importers
//! live in [`import`] (ScenarioNet JSON, the built-in synthetic town). Never imports `ash`.
//!
//! Conventions: global map frame in metres, headings in radians about +z (0 = +x), f64 everywhere. Object
//! positions are box centres; the ego's reference point is the rear axle (like nuPlan), its box centre is
//! `rear_axle_to_center` metres ahead.
pub mod camera;
pub mod geometry;
pub mod import;
pub mod index;
pub mod map;

use geometry::{OrientedBox, Pose2};
use glam::DVec2;

pub use camera::{Camera, CameraImage, CameraRig, RecordedFrame};
pub use map::{Lane, LaneKind, Map};

/// Object classes (nuPlan's TrackedObjectType, with bicycles for ScenarioNet's CYCLIST).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ObjectClass {
    Vehicle,
    Pedestrian,
    Bicycle,
    TrafficCone,
    Barrier,
    CzoneSign,
    GenericObject,
}

impl ObjectClass {
    /// Whether the object is an agent (moves by itself) rather than a static object (nuPlan `Agent` vs
    /// `StaticObject`).
    pub fn is_agent(self) -> bool {
        matches!(
            self,
            ObjectClass::Vehicle | ObjectClass::Pedestrian | ObjectClass::Bicycle
        )
    }
    /// Open-loop (replayed) classes in reactive mode (nuPlan idm_agents_observation.yaml
    /// `open_loop_detections_types`): everything but vehicles (simulated) and bicycles (dropped: quirk).
    pub fn replayed_in_reactive_mode(self) -> bool {
        !matches!(self, ObjectClass::Vehicle | ObjectClass::Bicycle)
    }
}

/// Traffic-light state of a lane connector at one step.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrafficLightStatus {
    Green,
    Yellow,
    Red,
    Unknown,
}

/// State of a tracked object at one step.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ObjectState {
    /// Box centre pose.
    pub pose: Pose2,
    /// Global-frame velocity (m/s); NaN components when unknown.
    #[serde(serialize_with = "crate::scene::geometry::ser_dvec2")]
    pub velocity: DVec2,
}

/// A tracked object of the log; `states[k]` is None where the object is not observed at step k.
#[derive(Clone, Debug)]
pub struct Track {
    pub id: String,
    pub class: ObjectClass,
    pub length: f64,
    pub width: f64,
    pub height: f64,
    pub states: Vec<Option<ObjectState>>,
}

impl Track {
    pub fn box_at(&self, k: usize) -> Option<OrientedBox> {
        self.states
            .get(k)
            .copied()
            .flatten()
            .map(|s| OrientedBox::new(s.pose, self.length, self.width))
    }
}

/// Vehicle geometry (nuPlan `VehicleParameters`); the reference point is the rear axle.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct VehicleParameters {
    pub width: f64,
    pub length: f64,
    pub height: f64,
    pub wheel_base: f64,
    /// Rear axle to box centre, along the heading.
    pub rear_axle_to_center: f64,
}

impl VehicleParameters {
    /// nuPlan's Pacifica (`get_pacifica_parameters`).
    pub const PACIFICA: VehicleParameters = VehicleParameters {
        width: 2.297,
        length: 5.176,
        height: 1.777,
        wheel_base: 3.089,
        rear_axle_to_center: 1.461,
    };
    /// Box centre pose of a rear-axle pose.
    pub fn center_of(&self, rear_axle: &Pose2) -> Pose2 {
        rear_axle.forward(self.rear_axle_to_center)
    }
    /// Rear-axle pose of a box-centre pose.
    pub fn rear_axle_of(&self, center: &Pose2) -> Pose2 {
        center.forward(-self.rear_axle_to_center)
    }
    pub fn footprint(&self, rear_axle: &Pose2) -> OrientedBox {
        OrientedBox::new(self.center_of(rear_axle), self.length, self.width)
    }
}

/// One logged ego state (rear axle).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct EgoLogState {
    pub rear_axle: Pose2,
    /// Global-frame rear-axle velocity.
    #[serde(serialize_with = "crate::scene::geometry::ser_dvec2")]
    pub velocity: DVec2,
    /// Longitudinal acceleration (m/s^2), from the log or finite differences.
    pub accel: f64,
}

/// The route the expert drove: roadblocks in order and the lanes the expert used.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Route {
    pub roadblock_ids: Vec<String>,
    pub lane_ids: Vec<String>,
}

/// A complete scenario.
#[derive(Clone, Debug)]
pub struct Scenario {
    pub name: String,
    /// Where it came from (file path or `builtin:...`).
    pub source: String,
    /// Log step (s).
    pub dt: f64,
    pub map: Map,
    pub ego: Vec<EgoLogState>,
    pub ego_params: VehicleParameters,
    pub tracks: Vec<Track>,
    pub route: Route,
    /// Per step: (connector index, status) for every connector with a known light state.
    pub traffic_lights: Vec<Vec<(usize, TrafficLightStatus)>>,
    pub rig: CameraRig,
}

impl Scenario {
    /// Number of logged steps.
    pub fn len(&self) -> usize {
        self.ego.len()
    }
    pub fn is_empty(&self) -> bool {
        self.ego.is_empty()
    }
    /// Light states at step k (clamped to the last logged step; empty when none).
    pub fn lights_at(&self, k: usize) -> &[(usize, TrafficLightStatus)] {
        if self.traffic_lights.is_empty() {
            return &[];
        }
        &self.traffic_lights[k.min(self.traffic_lights.len() - 1)]
    }
}
