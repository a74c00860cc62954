//! External planner process (`--planner cmd:<command line>`), speaking JSON lines over stdin/stdout; the
//! protocol (v1 and v2) is documented in docs/planner_protocol.md. One process per scenario, or one per batch in
//! resident mode (`resident:`, [`super::resident`]: a session per scenario, restarted after a failure that left
//! the pipes out of step). A writer thread owns the planner's stdin and a reader thread its stdout, so that
//! every write AND read is under the timeout: a planner that never reads its input, or closes its stdout but
//! lives on, is ended at the timeout.
//! The planner runs in its own process group, killed at the end of its scenario; on Linux, processes holding its
//! pipes are killed as well, so a descendant that escaped the group (`setsid`) and keeps the pipes open neither
//! outlives the scenario nor keeps the reader thread blocked (the reads time out in any case).
use super::planner::{
    trajectory_from_ego_frame, trajectory_from_ego_poses, Planner, PlannerInput, PLAN_POSES,
};
use super::reply::{parse_plan_reply, MIN_HORIZON_S};
use super::resident::{check_ready, hello_message, Resident};
use super::sensors::CameraFrame;
use super::trajectory::Trajectory;
use crate::scene::geometry::Pose2;
use crate::scene::Scenario;
use anyhow::{anyhow, bail, ensure, Context, Result};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Read, Write};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, TryRecvError};
use std::time::{Duration, Instant};

/// Newest protocol version.
pub const PROTOCOL_VERSION: u32 = 2;
/// Longest reply line accepted (bytes); a longer one ends the scenario.
pub const MAX_REPLY_BYTES: usize = 4 << 20;
/// Most poses accepted in a reply (500 s at 0.5 s).
pub const MAX_POSES: usize = 1000;

/// How a v2 planner wants its images.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageMode {
    /// PNG files written before the request; the request carries their paths.
    Paths,
    /// Raw RGB bytes after the request line (`inline_bytes` of them, cameras in request order).
    Inline,
    /// No images (a planner that reads boxes only).
    None,
}

pub struct ExternalPlanner {
    pub command: String,
    pub timeout: Duration,
    /// 1 or 2.
    pub protocol: u32,
    /// Where v2 image files go (`Paths` mode); a temporary folder when None.
    pub image_dir: Option<PathBuf>,
    child: Option<Child>,
    writer: Option<Sender<Vec<u8>>>,
    acks: Option<Receiver<std::io::Result<()>>>,
    lines: Option<Receiver<std::result::Result<String, String>>>,
    mode: ImageMode,
    size: Option<(u32, u32)>,
    scenario: String,
    /// Inodes of the planner's stdin and stdout pipes (Linux): a descendant that left the process group
    /// (`setsid`) and keeps them open is found by them and killed with the group.
    pipes: Vec<u64>,
    /// Resident mode (`resident:<command line>`): one process for many scenarios; None: one per scenario.
    resident: Option<Resident>,
    /// The transport failure after which the pipes may be out of step (a timeout, a crash, a line no request
    /// asked for): a resident process is then ended with its scenario and restarted for the next one.
    desynced: Option<String>,
}

/// FNV-1a 64 of a byte string (the image checksum of the protocol: over the RGB bytes, row-major (H, W, 3)).
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in bytes {
        h ^= *b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

fn rows3(m: &glam::DMat3) -> [[f64; 3]; 3] {
    let c = m.to_cols_array_2d();
    [0, 1, 2].map(|r| [c[0][r], c[1][r], c[2][r]])
}

fn rows4(m: &glam::DMat4) -> [[f64; 4]; 4] {
    let c = m.to_cols_array_2d();
    [0, 1, 2, 3].map(|r| [c[0][r], c[1][r], c[2][r], c[3][r]])
}

/// Reads `\n`-terminated lines of at most [`MAX_REPLY_BYTES`] (a longer one is an error, not an allocation).
fn read_lines(out: impl Read, tx: Sender<std::result::Result<String, String>>) {
    let mut r = BufReader::new(out);
    loop {
        let mut buf = Vec::new();
        let mut limited = (&mut r).take(MAX_REPLY_BYTES as u64 + 1);
        match limited.read_until(b'\n', &mut buf) {
            Ok(0) => break,
            Ok(_) if buf.len() > MAX_REPLY_BYTES => {
                let _ = tx.send(Err(format!(
                    "planner reply line longer than {MAX_REPLY_BYTES} bytes"
                )));
                break;
            }
            Ok(_) => {
                let s = String::from_utf8_lossy(&buf).trim_end().to_string();
                if tx.send(Ok(s)).is_err() {
                    break;
                }
            }
            Err(e) => {
                let _ = tx.send(Err(format!("reading the planner's output failed: {e}")));
                break;
            }
        }
    }
}

/// The inode of a pipe end of ours (Linux: `/proc/self/fd/N` names it), None elsewhere.
#[cfg(target_os = "linux")]
fn pipe_inode(fd: &impl std::os::fd::AsRawFd) -> Option<u64> {
    use std::os::unix::fs::MetadataExt;
    std::fs::metadata(format!("/proc/self/fd/{}", fd.as_raw_fd()))
        .ok()
        .map(|m| m.ino())
}
#[cfg(not(target_os = "linux"))]
fn pipe_inode<T>(_: &T) -> Option<u64> {
    None
}

/// SIGKILLs every other process holding one of the pipes `inodes` (Linux: `/proc/<pid>/fd/*` reading
/// `pipe:[<inode>]`). Our pipes are created close-on-exec, so only the planner's own descendants hold them.
#[cfg(target_os = "linux")]
fn kill_pipe_holders(inodes: &[u64]) {
    if inodes.is_empty() {
        return;
    }
    let names: Vec<String> = inodes.iter().map(|i| format!("pipe:[{i}]")).collect();
    let me = std::process::id();
    // Twice: a holder may have forked between the scan and its kill.
    for _ in 0..2 {
        let Ok(procs) = std::fs::read_dir("/proc") else {
            return;
        };
        for p in procs.flatten() {
            let Some(pid) = p.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else {
                continue;
            };
            // Our own fds, and children of ours: another planner being spawned holds copies of every fd of
            // ours until its exec (close-on-exec); an escaped descendant's parent is not us.
            if pid == me || parent_of(&p.path()) == Some(me) {
                continue;
            }
            let Ok(fds) = std::fs::read_dir(p.path().join("fd")) else {
                continue;
            };
            let holds = fds.flatten().any(|fd| {
                std::fs::read_link(fd.path())
                    .is_ok_and(|l| names.iter().any(|n| l.as_os_str() == n.as_str()))
            });
            if let (true, Ok(pid)) = (holds, i32::try_from(pid)) {
                // SAFETY: plain syscall; the process holds this planner's pipe (its descendant).
                unsafe {
                    libc::kill(pid, libc::SIGKILL);
                }
            }
        }
    }
}
#[cfg(not(target_os = "linux"))]
fn kill_pipe_holders(_: &[u64]) {}

/// The parent pid of `/proc/<pid>` (its `stat`: the field after the parenthesised command name).
#[cfg(target_os = "linux")]
fn parent_of(proc_dir: &std::path::Path) -> Option<u32> {
    let stat = std::fs::read_to_string(proc_dir.join("stat")).ok()?;
    let rest = &stat[stat.rfind(')')? + 1..];
    rest.split_whitespace().nth(1)?.parse().ok()
}

impl ExternalPlanner {
    pub fn new(command: &str, timeout: Duration) -> Result<Self> {
        if command.trim().is_empty() {
            bail!("--planner cmd: (or resident:) needs a command line after the colon");
        }
        ensure!(
            timeout > Duration::ZERO && timeout <= Duration::from_secs(24 * 3600),
            "planner timeout {:?} must be in (0, 24 h]",
            timeout
        );
        Ok(Self {
            command: command.to_string(),
            timeout,
            protocol: 1,
            image_dir: None,
            child: None,
            writer: None,
            acks: None,
            lines: None,
            mode: ImageMode::None,
            size: None,
            scenario: String::new(),
            pipes: vec![],
            resident: None,
            desynced: None,
        })
    }

    /// Protocol v2 (start/plan/end messages, images), files under `image_dir`.
    pub fn v2(mut self, image_dir: Option<PathBuf>) -> Self {
        self.protocol = 2;
        self.image_dir = image_dir;
        self
    }

    /// Resident mode (protocol v2): one process for every scenario this planner runs, loaded under
    /// `start_timeout` (docs/planner_protocol.md "Resident planners").
    pub fn resident(mut self, start_timeout: Duration) -> Result<Self> {
        self.protocol = 2;
        self.resident = Some(Resident::new(start_timeout)?);
        Ok(self)
    }

    /// Where the next scenario's v2 image files go (`Paths` mode).
    pub fn set_image_dir(&mut self, dir: Option<PathBuf>) {
        self.image_dir = dir;
    }

    /// The resident-mode state (None: one process per scenario).
    pub fn resident_state(&self) -> Option<&Resident> {
        self.resident.as_ref()
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
        let mut stdin = child
            .stdin
            .take()
            .ok_or_else(|| anyhow!("planner stdin unavailable"))?;
        self.pipes = [pipe_inode(&stdout), pipe_inode(&stdin)]
            .into_iter()
            .flatten()
            .collect();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || read_lines(stdout, tx));
        let (wtx, wrx) = std::sync::mpsc::channel::<Vec<u8>>();
        let (atx, arx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for msg in wrx {
                let r = stdin.write_all(&msg).and_then(|_| stdin.flush());
                let failed = r.is_err();
                if atx.send(r).is_err() || failed {
                    break;
                }
            }
        });
        self.lines = Some(rx);
        self.writer = Some(wtx);
        self.acks = Some(arx);
        self.child = Some(child);
        self.desynced = None;
        Ok(())
    }

    fn kill(&mut self) {
        self.writer = None;
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
        // Descendants in their own session or group (setsid, double fork) escape the group kill; those holding
        // the planner's pipes would keep the reader thread (and themselves) alive: end them too.
        kill_pipe_holders(&std::mem::take(&mut self.pipes));
        self.lines = None;
        self.acks = None;
    }

    fn status(&mut self) -> String {
        match self.child.as_mut().map(|c| c.try_wait()) {
            Some(Ok(Some(s))) => format!("exited with {s}"),
            Some(Ok(None)) => "still running".into(),
            _ => "unknown".into(),
        }
    }

    /// Writes `bytes` under the deadline (`limit`: the timeout it stands for, for the message).
    fn send(&mut self, bytes: Vec<u8>, deadline: Instant, limit: Duration) -> Result<()> {
        let w = self
            .writer
            .as_ref()
            .ok_or_else(|| anyhow!("planner process is not running"))?;
        w.send(bytes)
            .map_err(|_| anyhow!("planner process crashed or closed its input"))?;
        let acks = self
            .acks
            .as_ref()
            .ok_or_else(|| anyhow!("planner process is not running"))?;
        match acks.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => bail!("planner process crashed or closed its input: {e}"),
            Err(RecvTimeoutError::Timeout) => bail!(
                "planner timed out: it did not read its input within {:.1} s",
                limit.as_secs_f64()
            ),
            Err(RecvTimeoutError::Disconnected) => {
                bail!("planner process crashed or closed its input")
            }
        }
    }

    /// One reply line under the deadline (`limit`: the timeout it stands for, for the message).
    fn receive(&mut self, deadline: Instant, limit: Duration) -> Result<Value> {
        loop {
            let rx = self
                .lines
                .as_ref()
                .ok_or_else(|| anyhow!("planner process is not running"))?;
            match rx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
                Ok(Ok(l)) if l.trim().is_empty() => continue,
                Ok(Ok(l)) => {
                    return serde_json::from_str(&l)
                        .map_err(|e| anyhow!("planner reply is not valid JSON ({e}): {:.200}", l))
                }
                Ok(Err(e)) => bail!("{e}"),
                Err(RecvTimeoutError::Timeout) => bail!(
                    "planner timed out: no reply within {:.1} s",
                    limit.as_secs_f64()
                ),
                Err(RecvTimeoutError::Disconnected) => {
                    let s = self.status();
                    bail!("planner closed its output or exited without replying (process {s})")
                }
            }
        }
    }

    /// Fails if the planner wrote a line nobody asked for (e.g. two replies to one request).
    fn check_no_pending(&mut self) -> Result<()> {
        if let Some(rx) = self.lines.as_ref() {
            loop {
                match rx.try_recv() {
                    Ok(Ok(l)) if l.trim().is_empty() => continue,
                    Ok(Ok(l)) => bail!(
                        "planner wrote a line no request asked for (two replies to one request?): {:.200}",
                        l
                    ),
                    Ok(Err(e)) => bail!("{e}"),
                    Err(TryRecvError::Empty) | Err(TryRecvError::Disconnected) => break,
                }
            }
        }
        Ok(())
    }

    /// Sends `msg` (and `extra` bytes) and reads its reply, all under `limit`; a failure leaves the pipes out
    /// of step (`desynced`).
    fn exchange(
        &mut self,
        msg: &Value,
        extra: &[u8],
        want_reply: bool,
        limit: Duration,
    ) -> Result<Option<Value>> {
        let r = (|| {
            self.check_no_pending()?;
            let deadline = Instant::now() + limit;
            let mut bytes = serde_json::to_vec(msg)?;
            bytes.push(b'\n');
            bytes.extend_from_slice(extra);
            self.send(bytes, deadline, limit)?;
            if !want_reply {
                return Ok(None);
            }
            self.receive(deadline, limit).map(Some)
        })();
        if let Err(e) = &r {
            self.desync(e);
        }
        r
    }

    fn request(&mut self, msg: &Value, extra: &[u8], want_reply: bool) -> Result<Option<Value>> {
        self.exchange(msg, extra, want_reply, self.timeout)
    }

    fn desync(&mut self, e: &anyhow::Error) {
        if self.desynced.is_none() {
            self.desynced = Some(format!("{e:#}"));
        }
    }

    /// Resident mode: keeps the running process, or (first scenario, or the last one ended it) starts one and
    /// waits for its `hello` reply under the start timeout.
    fn ensure_resident(&mut self) -> Result<()> {
        let Some(start_timeout) = self.resident.as_ref().map(|r| r.start_timeout) else {
            bail!("internal: not a resident planner");
        };
        let running = matches!(self.child.as_mut().map(|c| c.try_wait()), Some(Ok(None)));
        if running && self.desynced.is_none() {
            if let Some(r) = self.resident.as_mut() {
                r.restart_cause = None;
            }
            return Ok(());
        }
        if self.child.is_some() {
            // it exited (or broke the protocol) between scenarios
            let cause = match self.desynced.take() {
                Some(d) => d,
                None => format!("process {} between scenarios", self.status()),
            };
            self.kill();
            if let Some(r) = self.resident.as_mut() {
                r.ended_by.get_or_insert(cause);
            }
        }
        self.spawn()?;
        let (n, cause) = match self.resident.as_mut() {
            Some(r) => {
                r.starts += 1;
                r.restart_cause = r.ended_by.take();
                (r.starts, r.restart_cause.clone())
            }
            None => bail!("internal: not a resident planner"),
        };
        if let Some(c) = cause {
            eprintln!(
                "resident planner restarted (process {n}) for scenario {}: the previous one ended with: {c}",
                self.scenario
            );
        }
        let hello = hello_message(self.timeout, start_timeout);
        let r = self
            .exchange(&hello, &[], true, start_timeout)
            .with_context(|| {
                format!(
                    "resident planner did not answer `hello` (start timeout {:.1} s, --planner-start-timeout)",
                    start_timeout.as_secs_f64()
                )
            })
            .and_then(|v| check_ready(&v.context("no reply to hello")?));
        if let Err(e) = &r {
            let cause = format!("failed to start: {e:#}");
            self.kill();
            if let Some(res) = self.resident.as_mut() {
                res.ended_by = Some(cause);
            }
        }
        r
    }

    /// Resident mode, at the end of a scenario: `end` on pipes still in step, the process lives on; else the
    /// process is ended (and restarted at the next scenario).
    fn end_session(&mut self) {
        if self.desynced.is_none() && self.writer.is_some() {
            let line = json!({"type": "end", "version": 2, "scenario": self.scenario});
            let _ = self.request(&line, &[], false);
        }
        if let Some(d) = self.desynced.take() {
            self.kill();
            if let Some(r) = self.resident.as_mut() {
                r.ended_by = Some(d);
            }
        }
    }

    /// The v2 `cameras` entries of a request (files written or bytes appended); `ego2global`: the request's
    /// (simulated) ego pose, `lidar2ego`: the rig's lidar.
    fn cameras(
        &self,
        step: usize,
        frames: &[CameraFrame],
        ego2global: &glam::DMat4,
        lidar2ego: &glam::DMat4,
        inline: &mut Vec<u8>,
    ) -> Result<Vec<Value>> {
        let mut out = vec![];
        for f in frames {
            let f = match self.size {
                Some((h, w)) => f.resized(w, h),
                None => f.clone(),
            };
            let mut e = camera_entry(&f, ego2global, lidar2ego);
            match self.mode {
                ImageMode::Paths => {
                    let dir = self
                        .image_dir
                        .clone()
                        .unwrap_or_else(|| std::env::temp_dir().join("b2dr-planner-images"));
                    std::fs::create_dir_all(&dir)
                        .with_context(|| format!("creating {}", dir.display()))?;
                    // camera names come from data (a model package, a frame file): file-name safe
                    let p = dir.join(format!(
                        "{}_{step:04}_{}.png",
                        self.scenario,
                        crate::scene::safe_name(&f.camera)
                    ));
                    f.to_image()
                        .save(&p)
                        .with_context(|| format!("writing {}", p.display()))?;
                    e["path"] = json!(p.display().to_string());
                }
                ImageMode::Inline => {
                    e["offset"] = json!(inline.len());
                    e["bytes"] = json!(f.rgb.len());
                    inline.extend_from_slice(&f.rgb);
                }
                ImageMode::None => {}
            }
            out.push(e);
        }
        Ok(out)
    }
}

/// The v2 `start` message of a scenario (docs/planner_protocol.md).
pub fn start_message(sc: &Scenario) -> Value {
    let p = &sc.ego_params;
    let rig: Vec<Value> = sc
        .rig
        .cameras
        .iter()
        .map(|c| {
            json!({"camera": c.name, "width": c.width, "height": c.height,
            "intrinsic": rows3(&c.intrinsic), "cam2ego": rows4(&c.cam2ego)})
        })
        .collect();
    json!({
        "type": "start", "version": 2, "scenario": sc.name, "map": sc.source,
        "dt_s": sc.dt, "rig": rig, "lidar2ego": rows4(&sc.rig.lidar2ego),
        "ego": {"length": p.length, "width": p.width, "wheel_base": p.wheel_base, "rear_axle_to_center": p.rear_axle_to_center},
        "route": sc.route,
    })
}

/// The calibration part of a v2 `cameras` entry for a frame as delivered (its size, its intrinsic):
/// `ego2global` is the request's ego pose, `lidar2ego` the rig's lidar ([`super::lidar::lidar2img`]).
pub fn camera_entry(f: &CameraFrame, ego2global: &glam::DMat4, lidar2ego: &glam::DMat4) -> Value {
    let l2i = super::lidar::lidar2img(
        &f.intrinsic,
        &f.cam2ego,
        &f.ego2global,
        ego2global,
        lidar2ego,
    );
    json!({
        "camera": f.camera, "width": f.width, "height": f.height,
        "intrinsic": rows3(&f.intrinsic), "cam2ego": rows4(&f.cam2ego), "ego2global": rows4(&f.ego2global),
        "lidar2img": rows4(&l2i),
        "fnv1a64": fnv1a64(&f.rgb).to_string(),
    })
}

/// Parses a version-1 reply `{"poses": [[x, y, heading], ...]}` (ego frame) into poses (version 2:
/// [`super::reply::parse_plan_reply`]).
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
    ensure!(
        arr.len() <= MAX_POSES,
        "planner reply has {} poses (at most {MAX_POSES} are accepted)",
        arr.len()
    );
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
        match self.resident {
            Some(_) => format!("resident:{}", self.command),
            None => format!("cmd:{}", self.command),
        }
    }
    fn start(&mut self, sc: &Scenario) -> Result<()> {
        self.scenario = crate::scene::safe_name(&sc.name);
        if self.resident.is_none() {
            self.kill();
            self.spawn()?;
            if self.protocol < 2 {
                return Ok(());
            }
            return self.start_session(sc);
        }
        self.ensure_resident()?;
        let r = self.start_session(sc);
        if r.is_err() {
            // the loop does not call `finish` after a failed start
            self.end_session();
        }
        r
    }
    fn plan(&mut self, input: &PlannerInput) -> Result<Trajectory> {
        self.plan_request(input)
    }
    fn finish(&mut self) {
        if self.resident.is_some() {
            self.end_session();
            return;
        }
        if self.protocol >= 2 && self.writer.is_some() {
            // best effort, for at most a second: the process is killed right after
            let mut line =
                json!({"type": "end", "version": 2, "scenario": self.scenario}).to_string();
            line.push('\n');
            let limit = self.timeout.min(Duration::from_secs(1));
            let _ = self.send(line.into_bytes(), Instant::now() + limit, limit);
        }
        self.kill();
    }
}

impl ExternalPlanner {
    /// The v2 `start` message and its reply (the scenario's image mode and size).
    fn start_session(&mut self, sc: &Scenario) -> Result<()> {
        let msg = start_message(sc);
        let reply = self
            .request(&msg, &[], true)?
            .context("no reply to start")?;
        if let Some(e) = reply.get("error") {
            bail!("planner refused the scenario: {e}");
        }
        self.mode = match reply
            .get("images")
            .and_then(Value::as_str)
            .unwrap_or("paths")
        {
            "paths" => ImageMode::Paths,
            "inline" => ImageMode::Inline,
            "none" => ImageMode::None,
            other => bail!("planner start reply: images {other:?} (paths, inline or none)"),
        };
        self.size = match reply.get("size") {
            None | Some(Value::Null) => None,
            Some(v) => {
                let s: Option<Vec<u32>> = v.as_array().map(|a| {
                    a.iter()
                        .filter_map(|x| x.as_u64().map(|x| x as u32))
                        .collect()
                });
                match s.as_deref() {
                    Some([h, w]) if (1..=4096).contains(h) && (1..=4096).contains(w) => {
                        Some((*h, *w))
                    }
                    _ => bail!("planner start reply: size {v} must be [height, width] in 1..=4096"),
                }
            }
        };
        Ok(())
    }

    /// One `plan` request and its reply as a trajectory.
    fn plan_request(&mut self, input: &PlannerInput) -> Result<Trajectory> {
        let e = input.ego;
        let sc = input.scenario;
        let mut msg = json!({
            "version": self.protocol,
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
            "route": sc.route,
            "images": input.images.iter().map(|i| json!({"camera": i.camera, "path": i.path, "timestamp_us": i.timestamp_us})).collect::<Vec<_>>(),
            "reply": { "poses": PLAN_POSES, "dt_s": super::planner::PLAN_DT_S, "frame": "ego_rear_axle" },
        });
        let mut inline = vec![];
        if self.protocol >= 2 {
            let ego2global = crate::scene::import::ego2global(&e.rear_axle);
            let lidar2ego = sc.rig.lidar2ego;
            msg["type"] = json!("plan");
            msg["command"] = json!(input.command);
            msg["command_def"] = json!(input.command_def);
            msg["history"] = json!(input.history);
            msg["ego_in_lidar"] = json!(rows4(&super::lidar::ego_in_lidar(&lidar2ego)));
            msg["reply"]["min_horizon_s"] = json!(MIN_HORIZON_S);
            msg["cameras"] = json!(self.cameras(
                input.step,
                input.frames,
                &ego2global,
                &lidar2ego,
                &mut inline
            )?);
            msg["inline_bytes"] = json!(inline.len());
        }
        let reply = self.request(&msg, &inline, true)?.context("no reply")?;
        // A reply may echo the request's step; when it does it must be this request's. Without it a second
        // reply to an earlier request that arrives late would be taken for this one's.
        if let Some(s) = reply.get("step").filter(|s| !s.is_null()) {
            if s.as_u64() != Some(input.step as u64) {
                let e = anyhow!(
                    "planner replied for step {s} to the request of step {} (two replies to one request?)",
                    input.step
                );
                self.desync(&e);
                return Err(e);
            }
        }
        if self.protocol >= 2 {
            let r = parse_plan_reply(&reply, &sc.rig.lidar2ego)?;
            return trajectory_from_ego_poses(e, &r.poses, r.dt_s);
        }
        let local = parse_reply(&reply)?;
        trajectory_from_ego_frame(e, &local, PLAN_POSES)
    }
}

impl Drop for ExternalPlanner {
    fn drop(&mut self) {
        self.kill();
    }
}
