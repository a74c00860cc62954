//! nuPlan closed-loop score (CLS / R-CLS), CPU only. Spec: shared/spec/behaviour.md section 3; reference
//! implementation: motional/nuplan-devkit `nuplan/planning/metrics/` (each file cites the module it ports).
//!
//! Data flow: the simulator fills an [`input::ScenarioTrace`] (ego, objects, expert per step) and provides a
//! map behind [`input::MapQuery`]; [`score::score_scenario`] computes
//! 1. the lane / connector assignment of the ego centre and box corners ([`route`], nuPlan's
//!    `ego_lane_change` products),
//! 2. multipliers: no_ego_at_fault_collisions ([`collisions`]), drivable_area_compliance,
//!    driving_direction_compliance, ego_is_making_progress ([`map_metrics`]),
//! 3. weighted metrics: ego_progress_along_expert_route (5), time_to_collision_within_bound (5),
//!    speed_limit_compliance (4), ego_is_comfortable (2, [`comfort`] with the scipy port in [`savgol`]),
//!
//! and returns every value in a serde-serialisable [`score::ScenarioScore`]; [`score::aggregate`] gives CLS.
//! Everything is deterministic: no hashing, no threads, fixed iteration orders.
//!
//! Geometry: the boxes the score tests ([`collisions::in_collision`], the TTC projection) are the crate's
//! one box type, [`crate::scene::geometry::OrientedBox`] (built by [`input::EgoStep::footprint`] and
//! [`input::ObjectState::footprint`]); lane, roadblock and drivable-area membership uses
//! [`crate::scene::geometry::point_in_polygon`], whose doc states its boundary rule and where it differs from
//! nuPlan's shapely calls. [`geometry`] holds only the shapely stand-ins the metrics alone need.
pub mod collisions;
pub mod comfort;
pub mod geometry;
pub mod input;
pub mod map_metrics;
pub mod route;
pub mod savgol;
pub mod score;
pub mod synthetic;
pub mod vecmap;

pub use input::{
    EgoDims, EgoStep, LaneId, LaneView, MapQuery, ObjectClass, ObjectState, ScenarioTrace,
};
pub use score::{aggregate, score_all, score_scenario, ClsResult, ScenarioScore, ScoreParams};
pub use vecmap::VecMap;
