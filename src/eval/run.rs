//! `b2dr run`: the closed loop with rendered cameras over scenarios (spec loop.md section 1).
//!
//! Layout of `--out`:
//!   <out>/config.json                    the run's configuration (a `--resume` with another one is refused)
//!   <out>/<scenario>/trace.jsonl         one line per 10 Hz step (ego, command, plan, objects)
//!   <out>/<scenario>/frames/<step>_<CAM>.png   every rendered camera image at render size
//!   <out>/<scenario>/mosaic/<step>.png   the cameras + a bird's-eye view per planner step
//!   <out>/<scenario>/run.gif             the mosaics, animated (2 Hz)
//!   <out>/<scenario>/metrics.json        score, every metric, failure, per-stage timing, device memory
//!                                        (written last: its presence marks the scenario done for --resume)
//!   <out>/metrics.json                   all scenarios, the aggregate (R-CLS / CLS-NR), per-metric means and
//!                                        timing totals (written at the end: a folder without it is unfinished)
//!
//! Scenarios run in folder-name order; `RunConfig::shard` runs every N-th of them (`--shard K/N`), and
//! `b2dr merge` combines shard folders (`super::batch`, shared with `b2dr sim`).
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context as _, Result};
use serde_json::{json, Value};

pub use super::batch::folder_name;
use super::batch::{self, Shard};
use super::sensors::{B2dr, B2drEngine, GroundTruth, LogReplay};
use crate::metrics::ScoreParams;
use crate::scene::import::{resolve, Source};
use crate::sim::closed_loop::{run_with_sensors, Controller};
use crate::sim::command::CommandDef;
use crate::sim::external::ExternalPlanner;
use crate::sim::history::{HISTORY_DEFAULT, HISTORY_MAX};
use crate::sim::resident::START_TIMEOUT_DEFAULT_S;
use crate::sim::sensors::{CameraFrame, Sensors};
use crate::sim::{self, AgentMode, Planner, PlannerSpec, SimConfig, SimResult};
use crate::tensor::DType;
use crate::vk::Context;
use crate::world::images::ImageStore;

/// `--renderer`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum RendererMode {
    B2dr,
    B2drNorefNoprev,
    LogReplay,
    Groundtruth,
    None,
}

impl std::str::FromStr for RendererMode {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "b2dr" => Self::B2dr,
            "b2dr-noref-noprev" => Self::B2drNorefNoprev,
            "log-replay" => Self::LogReplay,
            "groundtruth" => Self::Groundtruth,
            "none" => Self::None,
            _ => bail!(
                "--renderer {s:?}: expected b2dr, b2dr-noref-noprev, log-replay, groundtruth or none"
            ),
        })
    }
}

impl RendererMode {
    pub fn name(self) -> &'static str {
        match self {
            Self::B2dr => "b2dr",
            Self::B2drNorefNoprev => "b2dr-noref-noprev",
            Self::LogReplay => "log-replay",
            Self::Groundtruth => "groundtruth",
            Self::None => "none",
        }
    }
    pub fn uses_model(self) -> bool {
        matches!(self, Self::B2dr | Self::B2drNorefNoprev)
    }
}

/// Everything a run depends on (stored in `<out>/config.json`).
#[derive(Clone, Debug, serde::Serialize)]
pub struct RunConfig {
    pub scenario: String,
    pub renderer: RendererMode,
    /// Model package folder (b2dr modes); None: the built-in model.
    pub model: Option<PathBuf>,
    pub planner: PlannerSpec,
    pub agents: AgentMode,
    pub controller: Controller,
    pub steps: usize,
    pub planner_timeout_s: f64,
    /// `--planner-start-timeout`: a resident planner's load (`resident:`; written to config.json only when it
    /// differs from the default, so earlier runs' folders still resume).
    #[serde(skip_serializing_if = "is_default_start_timeout")]
    pub planner_start_timeout_s: f64,
    /// Cameras (empty: the model's for b2dr modes, the rig's otherwise).
    pub cameras: Vec<String>,
    /// Render size (H, W) of groundtruth / log-replay (b2dr modes use the model's).
    pub size: (usize, usize),
    pub seed: u64,
    /// UNet / ControlNet dtype of the b2dr renderers.
    pub dtype: DType,
    /// Write the animated GIF.
    pub gif: bool,
    /// `--shard K/N`: every N-th scenario of the name-ordered list (None: all; not written to config.json).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shard: Option<Shard>,
    /// The planner requests' navigation command definition and ego history (protocol v2; written to
    /// config.json only where they differ from the defaults, so earlier runs' folders still resume).
    #[serde(flatten)]
    pub requests: RequestOptions,
}

/// What protocol-v2 `plan` requests carry besides the state (`--command-def`, `--history`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct RequestOptions {
    #[serde(skip_serializing_if = "is_default_def")]
    pub command_def: CommandDef,
    #[serde(skip_serializing_if = "is_default_history")]
    pub history: usize,
}

impl Default for RequestOptions {
    fn default() -> Self {
        Self {
            command_def: CommandDef::default(),
            history: HISTORY_DEFAULT,
        }
    }
}

fn is_default_def(d: &CommandDef) -> bool {
    *d == CommandDef::default()
}

fn is_default_history(h: &usize) -> bool {
    *h == HISTORY_DEFAULT
}

fn is_default_start_timeout(s: &f64) -> bool {
    *s == START_TIMEOUT_DEFAULT_S
}

/// Stage totals over frames.
#[derive(Default)]
struct Totals(Vec<(String, f64)>);

impl Totals {
    fn add(&mut self, k: &str, v: f64) {
        match self.0.iter_mut().find(|(n, _)| n == k) {
            Some(e) => e.1 += v,
            None => self.0.push((k.to_string(), v)),
        }
    }
    fn json(&self) -> Value {
        Value::Object(self.0.iter().map(|(k, v)| (k.clone(), json!(v))).collect())
    }
}

fn planner(cfg: &RunConfig, dir: &Path) -> Result<Box<dyn Planner>> {
    let timeout = Duration::from_secs_f64(cfg.planner_timeout_s);
    Ok(match &cfg.planner {
        PlannerSpec::Command(c) => {
            Box::new(ExternalPlanner::new(c, timeout)?.v2(Some(dir.join("planner_images"))))
        }
        PlannerSpec::Resident(_) => Box::new(resident_planner(cfg)?.context("internal")?),
        p => p.build(timeout)?,
    })
}

/// The batch's resident planner (`resident:`; None for other planners): one process for every scenario of this
/// `b2dr run` (each shard and each renderer of a comparison runs its own), started at the first scenario.
fn resident_planner(cfg: &RunConfig) -> Result<Option<ExternalPlanner>> {
    let PlannerSpec::Resident(c) = &cfg.planner else {
        return Ok(None);
    };
    ensure!(
        cfg.planner_start_timeout_s > 0.0 && cfg.planner_start_timeout_s <= 86400.0,
        "--planner-start-timeout must be in (0, 86400] seconds"
    );
    let timeout = Duration::from_secs_f64(cfg.planner_timeout_s);
    let start = Duration::from_secs_f64(cfg.planner_start_timeout_s);
    Ok(Some(ExternalPlanner::new(c, timeout)?.resident(start)?))
}

/// The mosaic of one planner step: the cameras in a grid and the bird's-eye view of the state.
fn mosaic(
    sc: &crate::scene::Scenario,
    r: &SimResult,
    step: usize,
    frames: &[CameraFrame],
) -> image::RgbImage {
    let names: Vec<String> = frames.iter().map(|f| f.camera.clone()).collect();
    let imgs: Vec<image::RgbImage> = frames.iter().map(|f| f.to_image()).collect();
    let bev = r
        .steps
        .get(step)
        .map(|s| sim::bev::render_step(sc, s, s.plan.as_deref(), &sim::bev::BevView::default()));
    crate::world::view::mosaic(&names, &imgs, bev.as_ref())
}

fn write_gif(path: &Path, frames: &[image::RgbImage]) -> Result<()> {
    use image::codecs::gif::{GifEncoder, Repeat};
    let f = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = GifEncoder::new_with_speed(std::io::BufWriter::new(f), 10);
    enc.set_repeat(Repeat::Infinite).context("gif: repeat")?;
    for img in frames {
        // half size keeps the file small; 500 ms per frame (the planner's 2 Hz)
        let small = image::imageops::resize(
            img,
            (img.width() / 2).max(1),
            (img.height() / 2).max(1),
            image::imageops::FilterType::Triangle,
        );
        let rgba = image::DynamicImage::ImageRgb8(small).to_rgba8();
        enc.encode_frame(image::Frame::from_parts(
            rgba,
            0,
            0,
            image::Delay::from_numer_denom_ms(500, 1),
        ))
        .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// Runs one scenario; returns its metrics.json value.
fn run_one(
    src: &Source,
    cfg: &RunConfig,
    engine: Option<&mut B2drEngine>,
    resident: Option<&mut ExternalPlanner>,
    dir: &Path,
    progress: &indicatif::ProgressBar,
) -> Result<Value> {
    let t0 = Instant::now();
    let sc = crate::world::load(src)?;
    // Without lanes (a nuScenes scene without its map expansion) the loop runs with replayed or no agents and
    // a planner that needs no map; the score then says why it is missing (`metrics_error`).
    if cfg.agents == AgentMode::Idm {
        sc.map.require_lanes(
            "--agents idm (IDM agents drive along lanes; --agents replay or none do not)",
        )?;
    }
    if matches!(cfg.planner, PlannerSpec::Idm) {
        sc.map.require_lanes("--planner idm")?;
    }
    let base = src.image_dir();
    let store = ImageStore::new(&sc, base);
    let sim_cfg = SimConfig {
        agents: cfg.agents,
        controller: cfg.controller,
        steps: cfg.steps,
        command_def: cfg.requests.command_def,
        history: cfg.requests.history,
        ..SimConfig::default()
    };
    std::fs::create_dir_all(dir.join("frames"))
        .with_context(|| format!("creating {}", dir.display()))?;
    std::fs::create_dir_all(dir.join("mosaic"))?;
    let mut own;
    let mut resident = resident;
    let p: &mut dyn Planner = match resident.as_deref_mut() {
        Some(r) => {
            r.set_image_dir(Some(dir.join("planner_images")));
            r
        }
        None => {
            own = planner(cfg, dir)?;
            own.as_mut()
        }
    };
    let cams = match engine.as_ref() {
        Some(e) => sc.select_cameras(&e.cameras)?,
        None => sc.select_cameras(&cfg.cameras)?,
    };
    let mut gt;
    let mut lr;
    let mut bd;
    let sensors: Option<&mut dyn Sensors> = match cfg.renderer {
        RendererMode::None => None,
        RendererMode::Groundtruth => {
            gt = GroundTruth::new(&store, cams.clone(), cfg.size);
            Some(&mut gt)
        }
        RendererMode::LogReplay => {
            lr = LogReplay {
                store: &store,
                cameras: cams.clone(),
                size: cfg.size,
            };
            Some(&mut lr)
        }
        RendererMode::B2dr | RendererMode::B2drNorefNoprev => {
            let e = engine.context("internal: the b2dr renderer needs its engine")?;
            bd = B2dr::new(e, &store)?;
            Some(&mut bd)
        }
    };
    let mut kept: Vec<(usize, Vec<CameraFrame>)> = vec![];
    let n_plan = cfg.steps.min(sc.len().saturating_sub(1)).div_ceil(5);
    progress.set_length(n_plan as u64);
    progress.set_position(0);
    progress.set_message(sc.name.clone());
    let frames_dir = dir.join("frames");
    let mut write_frames = |k: usize, frames: &[CameraFrame]| -> Result<()> {
        for f in frames {
            let p = frames_dir.join(format!("{k:04}_{}.png", folder_name(&f.camera)));
            f.to_image()
                .save(&p)
                .with_context(|| format!("writing {}", p.display()))?;
        }
        if !frames.is_empty() {
            kept.push((k, frames.to_vec()));
        }
        progress.inc(1);
        Ok(())
    };
    let r = run_with_sensors(
        &sc,
        &mut *p,
        &sim_cfg,
        &sim::closed_loop::images_at,
        sensors,
        &mut write_frames,
    );
    let wall_ms = t0.elapsed().as_secs_f64() * 1e3;
    r.write_trace(&dir.join("trace.jsonl"))?;
    let mut mosaics = vec![];
    for (k, frames) in &kept {
        let m = mosaic(&sc, &r, *k, frames);
        let p = dir.join("mosaic").join(format!("{k:04}.png"));
        m.save(&p)
            .with_context(|| format!("writing {}", p.display()))?;
        mosaics.push(m);
    }
    if cfg.gif && !mosaics.is_empty() {
        write_gif(&dir.join("run.gif"), &mosaics)?;
    }
    let mut totals = Totals::default();
    let mut per_frame = vec![];
    for t in &r.timing {
        totals.add("sim", t.sim_ms);
        totals.add("planner", t.planner_ms);
        totals.add("sensors", t.sensors_ms);
        for (k, v) in &t.sensors {
            totals.add(k, *v);
        }
        per_frame.push(json!({"step": t.step, "sensors_ms": t.sensors_ms, "stages": t.sensors.iter().map(|(k, v)| json!({k: v})).collect::<Vec<_>>(), "planner_ms": t.planner_ms, "sim_ms": t.sim_ms}));
    }
    let (score, metrics, metrics_error) =
        match sim::score::score_run(&sc, &r, &ScoreParams::default()) {
            Ok(s) => (s.score, serde_json::to_value(&s)?, None),
            Err(e) => (0.0, Value::Null, Some(format!("{e:#}"))),
        };
    let mut v = json!({
        "scenario": sc.name, "source": sc.source, "planner": r.planner, "agents": r.agent_mode,
        "renderer": cfg.renderer, "steps": r.steps.len().saturating_sub(1), "frames": kept.len(),
        "idm_agents": r.idm_agents, "failure": r.failure, "score": if r.failure.is_some() { 0.0 } else { score },
        "metrics": metrics, "metrics_error": metrics_error, "wall_ms": wall_ms,
        "timing_ms": totals.json(), "timing_per_frame": per_frame,
    });
    if let Some(res) = resident
        .as_deref()
        .and_then(ExternalPlanner::resident_state)
    {
        v["planner_process"] = res.report();
    }
    // metrics.json is written by the batch loop, with the configuration's fingerprint, last
    Ok(v)
}

/// Runs the configuration over its scenarios (see the module docs); returns the summary.
pub fn run(ctx: Option<&Context>, cfg: &RunConfig, out: &Path, resume: bool) -> Result<Value> {
    ensure!(cfg.steps >= 1, "--steps must be at least 1");
    ensure!(
        cfg.requests.history <= HISTORY_MAX,
        "--history {}: at most {HISTORY_MAX} slots",
        cfg.requests.history
    );
    ensure!(
        cfg.planner_timeout_s > 0.0 && cfg.planner_timeout_s <= 86400.0,
        "--planner-timeout must be in (0, 86400] seconds"
    );
    let (h, w) = cfg.size;
    ensure!(
        (8..=4096).contains(&h) && (8..=4096).contains(&w),
        "--size {h}x{w}: each side in 8..=4096"
    );
    planner(cfg, out)?;
    let mut resident = resident_planner(cfg)?;
    let (sources, list) = batch::select_listed(resolve(&cfg.scenario)?, cfg.shard)?;
    batch::check_out_outside_scenarios(out, &sources)?;
    let model_files = if cfg.renderer.uses_model() {
        crate::render::package::package_files(cfg.model.as_deref())?
    } else {
        vec![]
    };
    let config = batch::with_inputs(
        serde_json::to_value(cfg)?,
        &sources,
        &list,
        &cfg.planner.to_string(),
        &model_files,
    )?;
    let batch_out = batch::prepare_out(out, &config, resume)?;
    let mut engine = if cfg.renderer.uses_model() {
        let ctx = ctx.context("the b2dr renderer needs a Vulkan device")?;
        let pkg = crate::render::package::resolve_model(cfg.model.as_deref())?;
        let cams = if cfg.cameras.is_empty() {
            pkg.meta.cameras.clone()
        } else {
            cfg.cameras.clone()
        };
        let dtype = cfg.dtype;
        Some(B2drEngine::new(
            ctx,
            pkg,
            dtype,
            cams,
            cfg.renderer == RendererMode::B2dr,
            None,
            None,
            cfg.seed,
        )?)
    } else {
        None
    };
    let bar = indicatif::ProgressBar::new(1);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{prefix} {bar:25} {pos}/{len} frames {msg} [{elapsed_precise}]",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let n = sources.len();
    let results = batch::for_each_scenario(
        &batch_out,
        &sources,
        |i, src, dir| {
            bar.set_prefix(format!("scenario {}/{n}", i + 1));
            run_one(src, cfg, engine.as_mut(), resident.as_mut(), dir, &bar)
        },
        // suspend + eprintln, not println: a hidden bar (stderr not a terminal) prints nothing, and a failed
        // scenario must be named in logs too
        |name, v| bar.suspend(|| eprintln!("{}", batch::score_line(name, v))),
    )?;
    bar.finish_and_clear();
    let header = json!({
        "renderer": cfg.renderer, "planner": cfg.planner, "agents": cfg.agents,
        "cls_kind": cfg.agents.cls_kind(),
        "device": ctx.map(|c| c.info().name.clone()),
        "device_bytes": engine.as_ref().map(|e| e.device_bytes()),
        "model": engine.as_ref().map(|e| e.package.source.clone()),
    });
    let summary = batch::summarize(header.as_object().cloned().unwrap_or_default(), results);
    batch::write_summary(out, &summary)?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The request options enter config.json only where they differ from the defaults: a folder written before
    /// they existed resumes under the defaults, and one run with other options is refused.
    #[test]
    fn request_options_are_written_only_when_not_default() {
        assert_eq!(
            serde_json::to_value(RequestOptions::default()).unwrap(),
            json!({})
        );
        let o = RequestOptions {
            command_def: CommandDef::Nuscenes,
            history: 2,
        };
        assert_eq!(
            serde_json::to_value(o).unwrap(),
            json!({"command_def": "nuscenes", "history": 2})
        );
    }
}
