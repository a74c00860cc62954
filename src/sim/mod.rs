//! Behaviour simulation: the ego controller (nuPlan's LQR tracker + kinematic bicycle), IDM agents, the
//! planners under test and the closed loop, plus bird's-eye-view drawing of runs.
//!
//! Timing (behaviour spec section 0): dt = 0.1 s, 150 steps, planner at 2 Hz; inside a step the ego moves
//! first, then the agents, which see the ego before it moved and the traffic lights of the next step.
pub mod agents;
pub mod bev;
pub mod closed_loop;
pub mod command;
pub mod ego;
pub mod external;
pub mod failure;
pub mod history;
pub mod idm;
pub mod lidar;
pub mod lqr;
pub mod planner;
pub mod reply;
pub mod resident;
pub mod score;
pub mod sensors;
pub mod trajectory;

pub use closed_loop::{run, AgentMode, Controller, SimConfig, SimResult, StepRecord};
pub use failure::SimFailure;
pub use planner::{ConstantVelocityPlanner, ExpertPlanner, IdmPlanner, Planner, PlannerInput};

use anyhow::{bail, Result};
use std::time::Duration;

/// A planner named on the command line: `expert`, `cv`, `idm` or `cmd:<command line>` (an external process
/// speaking docs/planner_protocol.md). Parsed once where arguments are parsed; its `Display` gives the name
/// back (config.json, reports).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PlannerSpec {
    /// The logged expert.
    Expert,
    /// Constant velocity along the heading.
    ConstantVelocity,
    /// nuPlan's IDM planner.
    Idm,
    /// An external planner process started with this command line.
    Command(String),
    /// A resident external planner: one process for a whole batch of scenarios (`b2dr run` only; protocol v2,
    /// docs/planner_protocol.md "Resident planners").
    Resident(String),
}

impl std::str::FromStr for PlannerSpec {
    type Err = anyhow::Error;
    fn from_str(spec: &str) -> Result<Self> {
        Ok(match spec {
            "expert" => PlannerSpec::Expert,
            "cv" => PlannerSpec::ConstantVelocity,
            "idm" => PlannerSpec::Idm,
            s if s.starts_with("cmd:") => PlannerSpec::Command(s[4..].to_string()),
            s if s.starts_with("resident:") => PlannerSpec::Resident(s[9..].to_string()),
            _ => bail!(
                "unknown planner {spec:?}: expected expert, cv, idm, cmd:<command line> or resident:<command line>"
            ),
        })
    }
}

impl std::fmt::Display for PlannerSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlannerSpec::Expert => f.write_str("expert"),
            PlannerSpec::ConstantVelocity => f.write_str("cv"),
            PlannerSpec::Idm => f.write_str("idm"),
            PlannerSpec::Command(c) => write!(f, "cmd:{c}"),
            PlannerSpec::Resident(c) => write!(f, "resident:{c}"),
        }
    }
}

impl serde::Serialize for PlannerSpec {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl PlannerSpec {
    /// The planner (an external one is given `timeout` per call).
    pub fn build(&self, timeout: Duration) -> Result<Box<dyn Planner>> {
        Ok(match self {
            PlannerSpec::Expert => Box::new(ExpertPlanner),
            PlannerSpec::ConstantVelocity => Box::new(ConstantVelocityPlanner),
            PlannerSpec::Idm => Box::new(IdmPlanner::default()),
            PlannerSpec::Command(c) => Box::new(external::ExternalPlanner::new(c, timeout)?),
            PlannerSpec::Resident(_) => bail!(
                "--planner resident: needs protocol v2 sessions (`b2dr run`); `b2dr sim` runs cmd: planners"
            ),
        })
    }
}

/// Builds a planner from its command-line name ([`PlannerSpec`]).
pub fn planner_from_spec(spec: &str, timeout: Duration) -> Result<Box<dyn Planner>> {
    spec.parse::<PlannerSpec>()?.build(timeout)
}

#[cfg(test)]
mod tests {
    use super::PlannerSpec;

    #[test]
    fn planner_spec_round_trips() {
        for s in [
            "expert",
            "cv",
            "idm",
            "cmd:python3 -u p.py --x 1",
            "resident:python3 p.py",
        ] {
            assert_eq!(s.parse::<PlannerSpec>().unwrap().to_string(), s);
        }
        let e = "magic".parse::<PlannerSpec>().unwrap_err().to_string();
        assert!(e.contains("unknown planner"), "{e}");
    }
}
