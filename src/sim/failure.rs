//! Why a simulated scenario ended before its last step: a typed value inside the simulator, turned into text
//! only at the edge (`failure` in metrics.json and summary.json, stderr) by its `Display`, whose wording is
//! the one those files have always carried (tests compare it).
use std::fmt;

/// The reason a run stopped early. `error` fields hold the cause's full chain (anyhow's `{:#}`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SimFailure {
    /// The renderer's `reset` failed before step 0.
    RendererStart { renderer: String, error: String },
    /// The planner's `start` failed before step 0.
    PlannerStart { error: String },
    /// The renderer's `observe` failed at a planner step.
    Renderer {
        step: usize,
        renderer: String,
        error: String,
    },
    /// Handing a step's camera frames to the caller (writing them) failed.
    Frames { step: usize, error: String },
    /// The planner failed at a step: it crashed, timed out, broke the protocol or returned an invalid
    /// trajectory (the error says which).
    Planner { step: usize, error: String },
    /// The scenario cannot be simulated at all (e.g. a non-finite or absurd time step), found before step 0.
    Scenario { scenario: String, error: String },
}

impl SimFailure {
    /// The step the run stopped at (None when it never started).
    pub fn step(&self) -> Option<usize> {
        match self {
            SimFailure::RendererStart { .. }
            | SimFailure::PlannerStart { .. }
            | SimFailure::Scenario { .. } => None,
            SimFailure::Renderer { step, .. }
            | SimFailure::Frames { step, .. }
            | SimFailure::Planner { step, .. } => Some(*step),
        }
    }
}

impl fmt::Display for SimFailure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SimFailure::RendererStart { renderer, error } => {
                write!(f, "renderer {renderer} failed to start: {error}")
            }
            SimFailure::PlannerStart { error } => write!(f, "planner failed to start: {error}"),
            SimFailure::Renderer {
                step,
                renderer,
                error,
            } => write!(f, "step {step}: renderer {renderer} failed: {error}"),
            SimFailure::Frames { step, error } => {
                write!(f, "step {step}: writing the frames: {error}")
            }
            SimFailure::Planner { step, error } => write!(f, "step {step}: {error}"),
            SimFailure::Scenario { scenario, error } => write!(f, "scenario {scenario}: {error}"),
        }
    }
}

/// Serialised as its text (the edge format of metrics.json).
impl serde::Serialize for SimFailure {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The text is what the loop wrote before the reason was typed: anyhow's context chain, `{:#}`.
    #[test]
    fn text_matches_the_anyhow_chain() {
        let e = || anyhow::anyhow!("inner cause").context("middle");
        let cases = [
            (
                SimFailure::RendererStart {
                    renderer: "r".into(),
                    error: format!("{:#}", e()),
                },
                format!("{:#}", e().context("renderer r failed to start")),
            ),
            (
                SimFailure::PlannerStart {
                    error: format!("{:#}", e()),
                },
                format!("{:#}", e().context("planner failed to start")),
            ),
            (
                SimFailure::Renderer {
                    step: 4,
                    renderer: "r".into(),
                    error: format!("{:#}", e()),
                },
                format!("{:#}", e().context("step 4: renderer r failed")),
            ),
            (
                SimFailure::Frames {
                    step: 4,
                    error: format!("{:#}", e()),
                },
                format!("{:#}", e().context("step 4: writing the frames")),
            ),
            (
                SimFailure::Planner {
                    step: 4,
                    error: format!("{:#}", e()),
                },
                format!("{:#}", e().context("step 4")),
            ),
        ];
        for (f, text) in cases {
            assert_eq!(f.to_string(), text);
            assert_eq!(serde_json::to_value(&f).unwrap(), serde_json::json!(text));
        }
    }
}
