//! The closed loop: 10 Hz steps, planner every 5th step (the latest trajectory keeps being tracked), ego first
//! (LQR + bicycle), then the agents, which see the ego before it moved and the lights/objects of the next step.
use super::agents::{EgoObservation, IdmManager, LeaderRef};
use super::command::CommandDef;
use super::ego::{BicycleModel, EgoState};
use super::failure::SimFailure;
use super::history::{ego_history, HistoryEntry, HISTORY_DEFAULT};
use super::idm::IdmParams;
use super::lqr::{LqrParams, LqrTracker, TrackerCommand};
use super::planner::{ObjectView, Planner, PlannerInput};
use super::sensors::{CameraFrame, SensorState, Sensors};
use super::trajectory::Trajectory;
use crate::scene::geometry::{OrientedBox, Pose2};
use crate::scene::{CameraImage, ObjectClass, Scenario};
use glam::DVec2;

/// How other traffic behaves.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AgentMode {
    /// IDM vehicles + replayed pedestrians and static objects (R-CLS).
    Idm,
    /// Everything replayed from the log (CLS-NR).
    Replay,
    /// No other objects.
    None,
}

impl AgentMode {
    /// The name of the aggregate score under this mode: R-CLS (reactive), CLS-NR (replay), or plain CLS.
    pub fn cls_kind(self) -> &'static str {
        match self {
            AgentMode::Idm => "R-CLS",
            AgentMode::Replay => "CLS-NR",
            AgentMode::None => "CLS (no agents)",
        }
    }
}

impl std::str::FromStr for AgentMode {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Self> {
        Ok(match s {
            "idm" => AgentMode::Idm,
            "replay" => AgentMode::Replay,
            "none" => AgentMode::None,
            _ => anyhow::bail!("unknown agent mode {s:?}: expected idm, replay or none"),
        })
    }
}

#[derive(Clone, Copy, Debug)]
pub struct SimConfig {
    pub agents: AgentMode,
    /// How the ego follows the planned trajectory.
    pub controller: Controller,
    /// Steps to simulate (150 = 15 s), capped by the log length.
    pub steps: usize,
    /// The planner runs every this many steps (5 = 2 Hz).
    pub planner_every: usize,
    pub idm: IdmParams,
    /// The navigation command definition of the planner requests (`--command-def`).
    pub command_def: CommandDef,
    /// Ego history slots per planner request (`--history`; protocol v2 sends them).
    pub history: usize,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            agents: AgentMode::Idm,
            controller: Controller::Lqr,
            steps: 150,
            planner_every: 5,
            idm: IdmParams::default(),
            command_def: CommandDef::Route20,
            history: HISTORY_DEFAULT,
        }
    }
}

/// The ego controller (nuPlan's `two_stage_controller` or `perfect_tracking`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Controller {
    /// LQR tracker + kinematic bicycle (the benchmark's controller).
    Lqr,
    /// The ego is placed on the planned trajectory at the next step (nuPlan's PerfectTrackingController):
    /// velocity, acceleration and yaw rates from differences of the trajectory. Diagnostic: it separates what
    /// the planner asks for from what the tracker does.
    Perfect,
}

impl std::str::FromStr for Controller {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Self> {
        match s {
            "lqr" => Ok(Self::Lqr),
            "perfect" => Ok(Self::Perfect),
            _ => anyhow::bail!("unknown controller {s:?} (lqr or perfect)"),
        }
    }
}

/// The ego state on trajectory `t` at time `time_s`, with rates from differences (perfect tracking).
fn state_on_trajectory(t: &Trajectory, prev: &EgoState, time_s: f64, dt: f64) -> EgoState {
    let us = |x: f64| (x * 1e6).round() as i64;
    let p = t.pose_at_us(us(time_s));
    let a = t.pose_at_us(us(time_s - dt));
    let b = t.pose_at_us(us(time_s + dt));
    let (s, c) = p.heading.sin_cos();
    let (dx, dy) = ((b.x - a.x) / (2.0 * dt), (b.y - a.y) / (2.0 * dt));
    let vx = c * dx + s * dy;
    let vy = -s * dx + c * dy;
    let yaw_rate = crate::scene::geometry::wrap_angle(b.heading - a.heading) / (2.0 * dt);
    EgoState {
        time_s,
        rear_axle: p,
        vx,
        vy,
        ax: (vx - prev.vx) / dt,
        ay: (vy - prev.vy) / dt,
        steering: prev.steering,
        steering_rate: 0.0,
        yaw_rate,
        yaw_accel: (yaw_rate - prev.yaw_rate) / dt,
    }
}

/// One object in a trace step.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct AgentRecord {
    /// Index of the log track.
    pub track: usize,
    pub class: ObjectClass,
    pub bbox: OrientedBox,
    #[serde(serialize_with = "crate::scene::geometry::ser_dvec2")]
    pub velocity: DVec2,
    /// Simulated by IDM (else replayed).
    pub idm: bool,
    /// Index in the IDM manager (what [`LeaderRef::Agent`] refers to).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub manager_index: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub leader: Option<LeaderRef>,
}

/// One trace line: the state at `step` and the command applied from it.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct StepRecord {
    pub step: usize,
    pub time_s: f64,
    pub ego: EgoState,
    /// Ego box centre pose.
    pub ego_center: Pose2,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub command: Option<TrackerCommand>,
    /// The trajectory returned by the planner at this step (global rear-axle poses), if it planned.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub plan: Option<Vec<Pose2>>,
    pub agents: Vec<AgentRecord>,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct SimResult {
    pub scenario: String,
    pub planner: String,
    pub agent_mode: AgentMode,
    pub steps: Vec<StepRecord>,
    /// Why the scenario ended early (planner crash, timeout, invalid trajectory, renderer error).
    pub failure: Option<SimFailure>,
    /// IDM agents built at step 0.
    pub idm_agents: usize,
    /// Wall time per planner step (not part of the trace).
    #[serde(skip)]
    pub timing: Vec<StepTiming>,
}

impl SimResult {
    /// Writes the trace: one JSON line per step record (`<scenario>/trace.jsonl` of `b2dr sim` and `b2dr run`).
    pub fn write_trace(&self, path: &std::path::Path) -> anyhow::Result<()> {
        use anyhow::Context as _;
        use std::io::Write as _;
        let f =
            std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
        let mut w = std::io::BufWriter::new(f);
        for s in &self.steps {
            serde_json::to_writer(&mut w, s)?;
            w.write_all(b"\n")?;
        }
        w.flush()
            .with_context(|| format!("writing {}", path.display()))
    }
}

fn replay_objects(
    sc: &Scenario,
    k: usize,
    filter: impl Fn(ObjectClass) -> bool,
) -> Vec<AgentRecord> {
    let mut out = Vec::new();
    for (ti, tr) in sc.tracks.iter().enumerate() {
        if !filter(tr.class) {
            continue;
        }
        if let Some(s) = tr.states.get(k).copied().flatten() {
            let v = if s.velocity.is_finite() {
                s.velocity
            } else {
                DVec2::ZERO
            };
            out.push(AgentRecord {
                track: ti,
                class: tr.class,
                bbox: OrientedBox::new(s.pose, tr.length, tr.width),
                velocity: v,
                idm: false,
                manager_index: None,
                leader: None,
            });
        }
    }
    out
}

fn objects_at(
    sc: &Scenario,
    mode: AgentMode,
    k: usize,
    idm: Option<&IdmManager>,
) -> Vec<AgentRecord> {
    match mode {
        AgentMode::None => vec![],
        AgentMode::Replay => replay_objects(sc, k, |_| true),
        AgentMode::Idm => {
            let mut out = Vec::new();
            if let Some(m) = idm {
                for (i, a) in m.agents.iter().enumerate() {
                    if let Some(a) = a {
                        out.push(AgentRecord {
                            track: a.track,
                            class: ObjectClass::Vehicle,
                            bbox: a.oriented_box(),
                            velocity: a.velocity_vec(),
                            idm: true,
                            manager_index: Some(i),
                            leader: m.leaders[i],
                        });
                    }
                }
            }
            out.extend(replay_objects(sc, k, |c| c.replayed_in_reactive_mode()));
            out
        }
    }
}

/// Images recorded at step k (a frame whose timestamp matches), empty otherwise.
pub fn images_at(sc: &Scenario, k: usize) -> Vec<CameraImage> {
    let t_us = (k as f64 * sc.dt * 1e6).round() as i64;
    sc.rig
        .frames
        .iter()
        .find(|f| f.timestamp_us == t_us)
        .map(|f| f.images.clone())
        .unwrap_or_default()
}

/// Runs one scenario in closed loop. Planner failures end the run with `failure` set; the steps simulated
/// so far are kept.
pub fn run(sc: &Scenario, planner: &mut dyn Planner, cfg: &SimConfig) -> SimResult {
    run_with_images(sc, planner, cfg, &|sc, k| images_at(sc, k))
}

/// Like [`run`], with a callback giving the recorded camera images (paths) for a planning step.
pub fn run_with_images(
    sc: &Scenario,
    planner: &mut dyn Planner,
    cfg: &SimConfig,
    images: &dyn Fn(&Scenario, usize) -> Vec<CameraImage>,
) -> SimResult {
    run_with_sensors(sc, planner, cfg, images, None, &mut |_, _| Ok(()))
}

/// Wall time of one planner step's stages (not part of the trace: traces stay bit-identical across runs).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct StepTiming {
    pub step: usize,
    /// The sensors' own stages (e.g. projection, encode, denoise, decode).
    pub sensors: Vec<(String, f64)>,
    pub sensors_ms: f64,
    pub planner_ms: f64,
    /// Behaviour (tracker, bicycle, IDM) of the steps up to the next planner call.
    pub sim_ms: f64,
}

/// The state the loop carries from step to step.
struct LoopState {
    ego: EgoState,
    idm: Option<IdmManager>,
    traj: Option<Trajectory>,
    agents: Vec<AgentRecord>,
}

/// The fixed parts of a run.
struct LoopCtx<'a> {
    sc: &'a Scenario,
    cfg: &'a SimConfig,
    tracker: LqrTracker,
    bicycle: BicycleModel,
}

/// What a planner step observed and decided; `Err` ends the scenario with that reason.
#[allow(clippy::too_many_arguments)] // the loop's parts, each borrowed differently
fn plan_step(
    c: &LoopCtx,
    st: &LoopState,
    rec: &mut StepRecord,
    planner: &mut dyn Planner,
    images: &dyn Fn(&Scenario, usize) -> Vec<CameraImage>,
    sensors: Option<&mut dyn Sensors>,
    on_frames: &mut dyn FnMut(usize, &[CameraFrame]) -> anyhow::Result<()>,
    timing: &mut StepTiming,
    history: &[HistoryEntry],
) -> Result<Trajectory, SimFailure> {
    let k = rec.step;
    let views: Vec<ObjectView> = rec
        .agents
        .iter()
        .map(|a| ObjectView {
            track: a.track,
            class: a.class,
            bbox: a.bbox,
            velocity: a.velocity,
        })
        .collect();
    let t0 = std::time::Instant::now();
    let frames = match sensors {
        Some(s) => {
            let state = SensorState {
                scenario: c.sc,
                step: k,
                time_s: st.ego.time_s,
                ego: &st.ego,
                ego_center: rec.ego_center,
                agents: &rec.agents,
            };
            let f = s.observe(&state).map_err(|e| SimFailure::Renderer {
                step: k,
                renderer: s.name().to_string(),
                error: format!("{e:#}"),
            })?;
            timing.sensors = s
                .last_times()
                .into_iter()
                .map(|(n, ms)| (n.to_string(), ms))
                .collect();
            f
        }
        None => vec![],
    };
    timing.sensors_ms = t0.elapsed().as_secs_f64() * 1e3;
    on_frames(k, &frames).map_err(|e| SimFailure::Frames {
        step: k,
        error: format!("{e:#}"),
    })?;
    let imgs = images(c.sc, k);
    let input = PlannerInput {
        scenario: c.sc,
        step: k,
        time_s: st.ego.time_s,
        ego: &st.ego,
        objects: &views,
        images: &imgs,
        frames: &frames,
        command: c.cfg.command_def.command(c.sc, &st.ego),
        command_def: c.cfg.command_def,
        history,
    };
    let t1 = std::time::Instant::now();
    let t = planner.plan(&input).map_err(|e| SimFailure::Planner {
        step: k,
        error: format!("{e:#}"),
    })?;
    timing.planner_ms = t1.elapsed().as_secs_f64() * 1e3;
    rec.plan = Some(
        t.poses
            .iter()
            .map(|p| Pose2::new(p.x, p.y, crate::scene::geometry::wrap_angle(p.heading)))
            .collect(),
    );
    Ok(t)
}

/// One 10 Hz behaviour step from `st` at step `k`: the tracker command on the current trajectory, the ego
/// (LQR + bicycle or perfect tracking), then the IDM agents; `st` becomes step k + 1.
fn advance(c: &LoopCtx, st: &mut LoopState, k: usize, rec: &mut StepRecord) -> bool {
    let (sc, dt) = (c.sc, c.sc.dt);
    let params = sc.ego_params;
    let Some(t) = st.traj.as_ref() else {
        return false;
    };
    let cmd = c.tracker.track(st.ego.time_s, &st.ego, t);
    rec.command = Some(cmd);
    let next_ego = match c.cfg.controller {
        Controller::Lqr => c
            .bicycle
            .propagate(&st.ego, cmd.accel, cmd.steering_rate, dt),
        Controller::Perfect => state_on_trajectory(t, &st.ego, (k + 1) as f64 * dt, dt),
    };
    if let Some(m) = st.idm.as_mut() {
        let obs = EgoObservation {
            footprint: params.footprint(&st.ego.rear_axle),
            rear_axle_heading: st.ego.rear_axle.heading,
            speed: st.ego.vx.hypot(st.ego.vy),
        };
        let open: Vec<(usize, OrientedBox)> = sc
            .tracks
            .iter()
            .enumerate()
            .filter(|(_, tr)| tr.class.replayed_in_reactive_mode())
            .filter_map(|(i, tr)| tr.box_at(k + 1).map(|b| (i, b)))
            .collect();
        m.step(&sc.map, Some(&obs), sc.lights_at(k + 1), &open, dt);
    }
    st.ego = next_ego;
    // Keep the time on the 0.1 s grid (no drift from repeated additions).
    st.ego.time_s = (k + 1) as f64 * dt;
    st.agents = objects_at(sc, c.cfg.agents, k + 1, st.idm.as_ref());
    true
}

/// The closed loop with an observation engine: at every planner step `sensors` (when given) renders the
/// simulated state, `on_frames` sees the images (a run writes them), and the planner gets them in memory.
/// A sensor or planner failure ends the scenario with the reason.
pub fn run_with_sensors(
    sc: &Scenario,
    planner: &mut dyn Planner,
    cfg: &SimConfig,
    images: &dyn Fn(&Scenario, usize) -> Vec<CameraImage>,
    mut sensors: Option<&mut dyn Sensors>,
    on_frames: &mut dyn FnMut(usize, &[CameraFrame]) -> anyhow::Result<()>,
) -> SimResult {
    let n = cfg.steps.min(sc.len().saturating_sub(1));
    let dt = sc.dt;
    // dt guard (issue #18): the importers refuse such a step; a scenario built in code is refused here, before
    // the tracker's and the planners' horizons (seconds / dt poses) are sized from it.
    if let Err(why) = crate::scene::import::bounds::check_dt(dt) {
        return SimResult {
            scenario: sc.name.clone(),
            planner: planner.name(),
            agent_mode: cfg.agents,
            steps: vec![],
            failure: Some(SimFailure::Scenario {
                scenario: sc.name.clone(),
                error: format!("dt {why}"),
            }),
            idm_agents: 0,
            timing: vec![],
        };
    }
    let params = sc.ego_params;
    let c = LoopCtx {
        sc,
        cfg,
        tracker: LqrTracker::new(LqrParams {
            dt,
            ..LqrParams::nuplan(params.wheel_base)
        }),
        bicycle: BicycleModel::new(&params),
    };
    let ego = EgoState::from_log(&sc.ego, 0, dt);
    let idm = (cfg.agents == AgentMode::Idm).then(|| {
        IdmManager::build(
            sc,
            Some(&params.footprint(&ego.rear_axle)),
            ego.speed(),
            cfg.idm,
        )
    });
    let mut result = SimResult {
        scenario: sc.name.clone(),
        planner: planner.name(),
        agent_mode: cfg.agents,
        steps: Vec::with_capacity(n + 1),
        failure: None,
        idm_agents: idm.as_ref().map_or(0, |m| m.agents.len()),
        timing: vec![],
    };
    if let Some(s) = sensors.as_deref_mut() {
        if let Err(e) = s.reset(sc) {
            result.failure = Some(SimFailure::RendererStart {
                renderer: s.name().to_string(),
                error: format!("{e:#}"),
            });
            return result;
        }
    }
    if let Err(e) = planner.start(sc) {
        result.failure = Some(SimFailure::PlannerStart {
            error: format!("{e:#}"),
        });
        return result;
    }
    let agents = objects_at(sc, cfg.agents, 0, idm.as_ref());
    let mut st = LoopState {
        ego,
        idm,
        traj: None,
        agents,
    };
    for k in 0..=n {
        let mut rec = StepRecord {
            step: k,
            time_s: st.ego.time_s,
            ego: st.ego,
            ego_center: params.center_of(&st.ego.rear_axle),
            command: None,
            plan: None,
            agents: std::mem::take(&mut st.agents),
        };
        if k == n {
            result.steps.push(rec);
            break;
        }
        if k % cfg.planner_every.max(1) == 0 || st.traj.is_none() {
            let mut timing = StepTiming {
                step: k,
                ..Default::default()
            };
            let steps = &result.steps;
            let history = ego_history(
                &st.ego,
                k,
                dt,
                &|j| steps.get(j).map_or(st.ego, |r| r.ego),
                &sc.ego_past,
                cfg.history,
            );
            match plan_step(
                &c,
                &st,
                &mut rec,
                planner,
                images,
                match sensors {
                    Some(ref mut s) => Some(&mut **s),
                    None => None,
                },
                on_frames,
                &mut timing,
                &history,
            ) {
                Ok(t) => st.traj = Some(t),
                Err(e) => {
                    result.failure = Some(e);
                    result.steps.push(rec);
                    result.timing.push(timing);
                    planner.finish();
                    return result;
                }
            }
            result.timing.push(timing);
        }
        let t0 = std::time::Instant::now();
        let moved = advance(&c, &mut st, k, &mut rec);
        if let Some(t) = result.timing.last_mut() {
            t.sim_ms += t0.elapsed().as_secs_f64() * 1e3;
        }
        result.steps.push(rec);
        if !moved {
            break;
        }
    }
    planner.finish();
    result
}
