//! Resident planners (`b2dr run --planner resident:<command line>`, docs/planner_protocol.md "Resident
//! planners"): one planner process for a whole batch of scenarios. b2dr starts it once, says `hello` and waits
//! for `{"ready": true}` under the start timeout (the model load), then runs each scenario as a session (the
//! protocol-v2 start / plan... / end messages) on the same pipes. A process that crashed, hung or broke the
//! protocol ends its scenario and is restarted, with its start timeout, for the next one.
//!
//! This module holds the bookkeeping and the hello exchange's messages; the process itself is
//! [`super::external::ExternalPlanner`]'s.
use anyhow::{bail, ensure, Result};
use serde_json::{json, Value};
use std::time::Duration;

/// Default `--planner-start-timeout` (seconds): the time a resident planner may take to load its model.
pub const START_TIMEOUT_DEFAULT_S: f64 = 300.0;

/// Resident-mode state of an external planner.
#[derive(Clone, Debug)]
pub struct Resident {
    /// Limit on the `hello` exchange (the model load); every later message is under the per-call timeout.
    pub start_timeout: Duration,
    /// Processes started so far (1 after the first load; each restart adds one).
    pub starts: usize,
    /// Why the process serving the current scenario replaced an earlier one (that one's failure); None when it
    /// served an earlier scenario too, or is the first.
    pub restart_cause: Option<String>,
    /// The failure that ended the last process, waiting for the next start.
    pub(super) ended_by: Option<String>,
}

impl Resident {
    pub fn new(start_timeout: Duration) -> Result<Self> {
        ensure!(
            start_timeout > Duration::ZERO && start_timeout <= Duration::from_secs(24 * 3600),
            "planner start timeout {:?} must be in (0, 24 h]",
            start_timeout
        );
        Ok(Self {
            start_timeout,
            starts: 0,
            restart_cause: None,
            ended_by: None,
        })
    }

    /// What metrics.json records of the process that served a scenario (`planner_process`).
    pub fn report(&self) -> Value {
        json!({
            "resident": true,
            "process": self.starts,
            "restarted": self.restart_cause.is_some(),
            "restart_cause": self.restart_cause,
        })
    }
}

/// The `hello` message (b2dr -> planner), sent once per process before its first session.
pub fn hello_message(timeout: Duration, start_timeout: Duration) -> Value {
    json!({
        "type": "hello", "version": super::external::PROTOCOL_VERSION, "resident": true,
        "timeout_s": timeout.as_secs_f64(), "start_timeout_s": start_timeout.as_secs_f64(),
    })
}

/// Checks the reply to `hello`: `{"ready": true}`, or `{"error": "..."}` (the load failed).
pub fn check_ready(reply: &Value) -> Result<()> {
    if let Some(e) = reply.get("error") {
        bail!("resident planner failed to load: {e}");
    }
    match reply.get("ready") {
        Some(Value::Bool(true)) => Ok(()),
        _ => bail!(
            "resident planner answered `hello` with {:.200} (expected {{\"ready\": true}})",
            reply.to_string()
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ready_reply_is_checked() {
        assert!(check_ready(&json!({"ready": true})).is_ok());
        let e = check_ready(&json!({"ready": false}))
            .unwrap_err()
            .to_string();
        assert!(e.contains("expected {\"ready\": true}"), "{e}");
        let e = check_ready(&json!({"error": "no weights"}))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("failed to load") && e.contains("no weights"),
            "{e}"
        );
        assert!(Resident::new(Duration::ZERO).is_err());
    }
}
