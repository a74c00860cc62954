//! Behaviour simulation: the ego controller (nuPlan's LQR tracker + kinematic bicycle), IDM agents, the
//! planners under test and the closed loop, plus bird's-eye-view drawing of runs.
//!
//! Timing (behaviour spec section 0): dt = 0.1 s, 150 steps, planner at 2 Hz; inside a step the ego moves
//! first, then the agents, which see the ego before it moved and the traffic lights of the next step.
pub mod agents;
pub mod bev;
pub mod closed_loop;
pub mod ego;
pub mod external;
pub mod idm;
pub mod lqr;
pub mod planner;
pub mod score;
pub mod sensors;
pub mod trajectory;

pub use closed_loop::{run, AgentMode, Controller, SimConfig, SimResult, StepRecord};
pub use planner::{ConstantVelocityPlanner, ExpertPlanner, IdmPlanner, Planner, PlannerInput};

use anyhow::{bail, Result};
use std::time::Duration;

/// Builds a planner from its command-line name: `expert`, `cv`, `idm` or `cmd:<command line>`.
pub fn planner_from_spec(spec: &str, timeout: Duration) -> Result<Box<dyn Planner>> {
    Ok(match spec {
        "expert" => Box::new(ExpertPlanner),
        "cv" => Box::new(ConstantVelocityPlanner),
        "idm" => Box::new(IdmPlanner::default()),
        s if s.starts_with("cmd:") => Box::new(external::ExternalPlanner::new(&s[4..], timeout)?),
        _ => bail!("unknown planner {spec:?}: expected expert, cv, idm or cmd:<command line>"),
    })
}
