//! `b2dr run`: the closed loop with rendered cameras (see `b2dr::eval::run`).
use std::path::PathBuf;

use anyhow::Result;
use b2dr::eval::run::{self, RendererMode, RunConfig};
use b2dr::vk::{Context, ContextOptions};

#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// Scenario(s): builtin:LAYOUT[:SEED[:VEHICLES[:PALETTE]]], a ScenarioNet .json file, a folder of them, or a
    /// comma-separated list of those
    #[arg(long, default_value = "builtin:town")]
    pub scenario: String,
    /// b2dr (generative renderer), b2dr-noref-noprev (masks only), log-replay, groundtruth (synthetic
    /// scenarios), none (boxes only, as `b2dr sim`); a comma-separated list runs each and writes the
    /// comparison table (comparison.md) and side-by-side frames
    #[arg(long, default_value = "b2dr")]
    pub renderer: String,
    /// Model package folder or builtin:NAME for the b2dr renderers (default: builtin:b2dr-nano)
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// expert, cv, idm, cmd:<command line> (protocol v2, docs/planner_protocol.md: one process per scenario) or
    /// resident:<command line> (one process for the whole batch, loaded once; "Resident planners" there)
    #[arg(long, default_value = "expert")]
    pub planner: b2dr::sim::PlannerSpec,
    /// idm (reactive, R-CLS), replay (CLS-NR) or none
    #[arg(long, default_value = "idm")]
    pub agents: String,
    /// lqr or perfect
    #[arg(long, default_value = "lqr")]
    pub controller: b2dr::sim::closed_loop::Controller,
    /// Steps per scenario (10 Hz)
    #[arg(long, default_value_t = 150)]
    pub steps: usize,
    /// Seconds each message to and from an external planner may take (a crash or hang ends the scenario)
    #[arg(long, default_value_t = 60.0)]
    pub planner_timeout: f64,
    /// Seconds a resident planner may take to answer `hello` (its model load), at start and at each restart
    #[arg(long, default_value_t = b2dr::sim::resident::START_TIMEOUT_DEFAULT_S)]
    pub planner_start_timeout: f64,
    /// Navigation command definition of the planner requests: route20 (the route point 20 m ahead, NAVSIM's)
    /// or nuscenes (the expert's position 3 s ahead, in the lidar frame: VAD / UniAD); docs/planner_protocol.md
    #[arg(long, default_value = "route20")]
    pub command_def: b2dr::sim::command::CommandDef,
    /// Past ego states per planner request (0.5 s apart, newest first; at most 120)
    #[arg(long, default_value_t = b2dr::sim::history::HISTORY_DEFAULT)]
    pub history: usize,
    /// Comma-separated cameras (default: the model's / the rig's)
    #[arg(long, value_delimiter = ',')]
    pub cameras: Vec<String>,
    /// Render size HxW of groundtruth and log-replay (the b2dr renderers use the model's)
    #[arg(long, default_value = "112x200")]
    pub size: String,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// UNet/ControlNet dtype of the b2dr renderers
    #[arg(long, default_value = "f32")]
    pub dtype: b2dr::tensor::DType,
    /// Skip the animated GIF
    #[arg(long)]
    pub no_gif: bool,
    /// Skip scenarios already done in --out (refused when --out holds another configuration)
    #[arg(long)]
    pub resume: bool,
    /// Run shard K of N (0 <= K < N): every N-th scenario of the name-ordered list, starting at the K-th;
    /// `b2dr merge` combines the shards' folders (with several renderers: per renderer folder)
    #[arg(long)]
    pub shard: Option<b2dr::eval::batch::Shard>,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(device: Option<String>, a: RunArgs) -> Result<()> {
    let modes: Vec<RendererMode> = a
        .renderer
        .split(',')
        .map(|m| m.trim().parse())
        .collect::<Result<_>>()?;
    anyhow::ensure!(!modes.is_empty(), "--renderer: no renderer given");
    let renderer = modes[0];
    let any_model = modes.iter().any(|m| m.uses_model());
    let size = b2dr::world::view::parse_size(&a.size).map_err(|e| e.context("--size"))?;
    let mut cfg = RunConfig {
        scenario: a.scenario,
        renderer,
        model: a.model,
        planner: a.planner,
        agents: a.agents.parse()?,
        controller: a.controller,
        steps: a.steps,
        planner_timeout_s: a.planner_timeout,
        planner_start_timeout_s: a.planner_start_timeout,
        cameras: a.cameras,
        size,
        seed: a.seed,
        dtype: a.dtype,
        gif: !a.no_gif,
        shard: a.shard,
        requests: run::RequestOptions {
            command_def: a.command_def,
            history: a.history,
        },
    };
    let ctx = if any_model {
        Some(Context::new(&ContextOptions {
            device,
            ..Default::default()
        })?)
    } else {
        None
    };
    if any_model {
        // the model's render size is the run's
        // (a folder, builtin:NAME, or the default built-in model, exactly as the run resolves it)
        let pkg_size = b2dr::render::package::resolve_model(cfg.model.as_deref())?
            .meta
            .render_size;
        cfg.size = (pkg_size[0], pkg_size[1]);
    }
    if modes.len() > 1 {
        b2dr::eval::compare::compare(ctx.as_ref(), &cfg, &modes, &a.out, a.resume)?;
        eprintln!("comparison -> {}", a.out.join("comparison.md").display());
        return Ok(());
    }
    let s = run::run(ctx.as_ref(), &cfg, &a.out, a.resume)?;
    eprintln!(
        "{} scenario(s){}, {} {:.4} (renderer {}) -> {}",
        s["scenarios"].as_array().map(|v| v.len()).unwrap_or(0),
        a.shard.map(|s| format!(" (shard {s})")).unwrap_or_default(),
        s["cls_kind"].as_str().unwrap_or("CLS"),
        s["cls"].as_f64().unwrap_or(0.0),
        renderer.name(),
        a.out.join("metrics.json").display()
    );
    b2dr::eval::batch::ensure_not_all_failed(&s, &a.out)
}
