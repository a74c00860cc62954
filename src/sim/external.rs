//! External planner process (`--planner cmd:<command line>`), speaking JSON lines over stdin/stdout; the
//! protocol is documented in docs/planner_protocol.md. One process per scenario; a reader thread forwards
//! stdout lines so replies can be awaited with a timeout.
use super::planner::{trajectory_from_ego_frame, Planner, PlannerInput, PLAN_POSES};
use super::trajectory::Trajectory;
use crate::scene::geometry::Pose2;
use crate::scene::Scenario;
use anyhow::{anyhow, bail, Context, Result};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::Duration;

/// Protocol version sent in every request.
pub const PROTOCOL_VERSION: u32 = 1;

pub struct ExternalPlanner {
    pub command: String,
    pub timeout: Duration,
    child: Option<Child>,
    stdin: Option<ChildStdin>,
    lines: Option<Receiver<std::io::Result<String>>>,
}

impl ExternalPlanner {
    pub fn new(command: &str, timeout: Duration) -> Result<Self> {
        if command.trim().is_empty() {
            bail!("--planner cmd: needs a command line after `cmd:`");
        }
        Ok(Self {
            command: command.to_string(),
            timeout,
            child: None,
            stdin: None,
            lines: None,
        })
    }

    fn spawn(&mut self) -> Result<()> {
        let mut cmd = Command::new("sh");
        cmd.arg("-c").arg(&self.command);
        // Own process group, so a timeout kills the whole tree (shells and launcher shims such as pyenv's
        // fork the real planner: killing only the direct child would leave it running).
        #[cfg(unix)]
        std::os::unix::process::CommandExt::process_group(&mut cmd, 0);
        let mut child = cmd
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .with_context(|| format!("starting planner process `{}`", self.command))?;
        let stdout = child
            .stdout
            .take()
            .ok_or_else(|| anyhow!("planner stdout unavailable"))?;
        self.stdin = child.stdin.take();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        self.lines = Some(rx);
        self.child = Some(child);
        Ok(())
    }

    fn kill(&mut self) {
        self.stdin = None;
        if let Some(mut c) = self.child.take() {
            #[cfg(unix)]
            if let Ok(pid) = i32::try_from(c.id()) {
                // SAFETY: plain syscall on the process group this planner created (pgid = its pid).
                unsafe {
                    libc::kill(-pid, libc::SIGKILL);
                }
            }
            let _ = c.kill();
            let _ = c.wait();
        }
        self.lines = None;
    }

    fn request(&mut self, msg: &Value) -> Result<Value> {
        let stdin = self
            .stdin
            .as_mut()
            .ok_or_else(|| anyhow!("planner process is not running"))?;
        let mut line = serde_json::to_string(msg)?;
        line.push('\n');
        stdin
            .write_all(line.as_bytes())
            .and_then(|_| stdin.flush())
            .map_err(|e| anyhow!("planner process crashed or closed its input: {e}"))?;
        let rx = self
            .lines
            .as_ref()
            .ok_or_else(|| anyhow!("planner process is not running"))?;
        loop {
            match rx.recv_timeout(self.timeout) {
                Ok(Ok(l)) if l.trim().is_empty() => continue,
                Ok(Ok(l)) => {
                    return serde_json::from_str(&l)
                        .map_err(|e| anyhow!("planner reply is not valid JSON ({e}): {l:.200}"))
                }
                Ok(Err(e)) => bail!("reading the planner's output failed: {e}"),
                Err(RecvTimeoutError::Timeout) => {
                    bail!(
                        "planner timed out: no reply within {:.1} s",
                        self.timeout.as_secs_f64()
                    )
                }
                Err(RecvTimeoutError::Disconnected) => {
                    let status = self.child.as_mut().and_then(|c| c.wait().ok());
                    bail!("planner process exited without replying (status {status:?})")
                }
            }
        }
    }
}

/// Parses a reply `{"poses": [[x, y, heading], ...]}` (ego frame) into poses.
pub fn parse_reply(v: &Value) -> Result<Vec<Pose2>> {
    if let Some(e) = v.get("error") {
        bail!("planner reported an error: {e}");
    }
    let poses = v
        .get("poses")
        .ok_or_else(|| anyhow!("planner reply has no `poses` field"))?;
    let arr = poses
        .as_array()
        .ok_or_else(|| anyhow!("planner reply `poses` is not an array"))?;
    arr.iter()
        .enumerate()
        .map(|(i, p)| {
            let c = p
                .as_array()
                .filter(|c| c.len() == 3)
                .ok_or_else(|| anyhow!("poses[{i}] is not [x, y, heading]"))?;
            let f = |j: usize| {
                c[j].as_f64()
                    .ok_or_else(|| anyhow!("poses[{i}][{j}] is not a number (NaN?)"))
            };
            Ok(Pose2::new(f(0)?, f(1)?, f(2)?))
        })
        .collect()
}

impl Planner for ExternalPlanner {
    fn name(&self) -> String {
        format!("cmd:{}", self.command)
    }
    fn start(&mut self, _scenario: &Scenario) -> Result<()> {
        self.kill();
        self.spawn()
    }
    fn plan(&mut self, input: &PlannerInput) -> Result<Trajectory> {
        let e = input.ego;
        let sc = input.scenario;
        let msg = json!({
            "version": PROTOCOL_VERSION,
            "scenario": sc.name,
            "step": input.step,
            "time_s": input.time_s,
            "ego": {
                "x": e.rear_axle.x, "y": e.rear_axle.y, "heading": e.rear_axle.heading,
                "vx": e.vx, "vy": e.vy, "ax": e.ax, "ay": e.ay,
                "steering": e.steering, "yaw_rate": e.yaw_rate,
                "length": sc.ego_params.length, "width": sc.ego_params.width,
                "wheel_base": sc.ego_params.wheel_base, "rear_axle_to_center": sc.ego_params.rear_axle_to_center,
            },
            "route": { "roadblock_ids": sc.route.roadblock_ids, "lane_ids": sc.route.lane_ids },
            "images": input.images.iter().map(|i| json!({"camera": i.camera, "path": i.path, "timestamp_us": i.timestamp_us})).collect::<Vec<_>>(),
            "reply": { "poses": PLAN_POSES, "dt_s": super::planner::PLAN_DT_S, "frame": "ego_rear_axle" },
        });
        let reply = self.request(&msg)?;
        let local = parse_reply(&reply)?;
        trajectory_from_ego_frame(e, &local, PLAN_POSES)
    }
    fn finish(&mut self) {
        self.kill();
    }
}

impl Drop for ExternalPlanner {
    fn drop(&mut self) {
        self.kill();
    }
}
