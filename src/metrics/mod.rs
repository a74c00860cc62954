//! nuPlan closed-loop score (CLS / R-CLS), CPU only. Spec: shared/spec/behaviour.md section 3; reference
//! implementation: motional/nuplan-devkit `nuplan/planning/metrics/`.
//!
//! - [`input`]: what the simulator provides (ego trace, objects, expert, route) and the [`input::MapQuery`] trait.
pub mod input;

pub use input::{
    EgoDims, EgoStep, LaneId, LaneView, MapQuery, ObjectClass, ObjectState, ScenarioTrace,
};
