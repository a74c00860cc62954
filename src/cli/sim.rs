//! `b2dr sim`: closed-loop runs of a planner over scenarios, writing per scenario a JSON-lines trace, a
//! metrics.json and bird's-eye-view PNG frames, plus the aggregate (CLS) in `<out>/metrics.json`.
//!
//! Layout of `--out`:
//!   <out>/<scenario>/trace.jsonl    one line per step (ego state, command, plan, objects)
//!   <out>/<scenario>/metrics.json   the scenario's score, every metric, the failure reason (written last:
//!                                   its presence marks the scenario done for --resume, which re-checks it
//!                                   against the configuration: `config_fingerprint`)
//!   <out>/<scenario>/bev_<step>.png frames every --bev-every steps
//!   <out>/config.json               the flags that decide the results (not --bev-every); a `--resume`
//!                                   with others is refused
//!   <out>/metrics.json              all scenarios, the aggregate (CLS), per-metric means, timing totals
//!                                   (written at the end: a folder without it is unfinished)
//!
//! Scenarios run in folder-name order; `--shard K/N` runs every N-th of them, and `b2dr merge` combines shard
//! folders (`b2dr::eval::batch`, shared with `b2dr run`).
use anyhow::{bail, Context, Result};
use b2dr::eval::batch::{self, Shard};
use b2dr::metrics::ScoreParams;
use b2dr::scene::import::{resolve, Source};
use b2dr::sim::{self, AgentMode, Controller, PlannerSpec, SimConfig};
use clap::Args;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[derive(Args, Debug)]
pub struct SimArgs {
    /// Scenario(s): builtin:LAYOUT[:seed[:n_vehicles[:palette]]] (LAYOUT: town, cross, tjunction, straight, curve,
    /// multilane), a ScenarioNet .json file, a directory of them, nuscenes:DATAROOT[:VERSION]:SCENE (official
    /// nuScenes tables, docs/nuscenes.md), or a comma-separated list of those.
    #[arg(long, default_value = "builtin:town")]
    pub scenario: String,
    /// Planner: expert, cv, idm or cmd:<command line> (see docs/planner_protocol.md).
    #[arg(long, default_value = "expert")]
    pub planner: PlannerSpec,
    /// Other traffic: idm (reactive, R-CLS), replay (log replay, CLS-NR) or none.
    #[arg(long, default_value = "idm")]
    pub agents: AgentMode,
    /// Ego controller: lqr (LQR tracker + kinematic bicycle, the benchmark's) or perfect (the ego is placed on
    /// the planned trajectory; a diagnostic, like nuPlan's perfect_tracking).
    #[arg(long, default_value = "lqr")]
    pub controller: Controller,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Skip scenarios whose metrics.json already exists in --out (refused when --out holds another
    /// configuration).
    #[arg(long)]
    pub resume: bool,
    /// Run shard K of N (0 <= K < N): every N-th scenario of the name-ordered list, starting at the K-th;
    /// `b2dr merge` combines the shards' folders.
    #[arg(long)]
    pub shard: Option<Shard>,
    /// Steps per scenario (10 Hz; capped by the log length).
    #[arg(long, default_value_t = 150)]
    pub steps: usize,
    /// Seconds an external planner may take per call before the scenario is ended.
    #[arg(long, default_value_t = 10.0)]
    pub planner_timeout: f64,
    /// Write a bird's-eye-view PNG every this many steps (0: none).
    #[arg(long, default_value_t = 25)]
    pub bev_every: usize,
}

/// Runs one scenario and writes its folder; returns its metrics.json value.
fn run_one(src: &Source, args: &SimArgs, cfg: &SimConfig, dir: &Path) -> Result<Value> {
    let t0 = Instant::now();
    let sc = b2dr::world::load(src)?;
    sc.map
        .require_lanes("b2dr sim (IDM agents, the route and the closed-loop score)")?;
    let mut planner = args
        .planner
        .build(Duration::from_secs_f64(args.planner_timeout))?;
    let r = sim::run(&sc, planner.as_mut(), cfg);
    let sim_ms = t0.elapsed().as_secs_f64() * 1e3;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    r.write_trace(&dir.join("trace.jsonl"))?;
    sim::bev::write_frames(&sc, &r, dir, args.bev_every, &sim::bev::BevView::default())?;
    let (score, metrics, metrics_error) =
        match sim::score::score_run(&sc, &r, &ScoreParams::default()) {
            Ok(s) => (s.score, serde_json::to_value(&s)?, None),
            Err(e) => (0.0, Value::Null, Some(format!("{e:#}"))),
        };
    let v = json!({
        "scenario": sc.name,
        "source": sc.source,
        "planner": r.planner,
        "agents": r.agent_mode,
        "steps": r.steps.len().saturating_sub(1),
        "idm_agents": r.idm_agents,
        "failure": r.failure,
        "score": score,
        "metrics": metrics,
        "metrics_error": metrics_error,
        "wall_ms": sim_ms,
    });
    // metrics.json is written by the batch loop, with the configuration's fingerprint, last
    Ok(v)
}

pub fn run(args: SimArgs) -> Result<()> {
    let agents = args.agents;
    if args.steps == 0 {
        bail!("--steps must be at least 1");
    }
    if !(args.planner_timeout > 0.0 && args.planner_timeout <= 86400.0) {
        bail!("--planner-timeout must be in (0, 86400] seconds");
    }
    // Build the planner once before doing any work (an external command line that cannot start fails here).
    args.planner
        .build(Duration::from_secs_f64(args.planner_timeout))?;
    let (sources, list) = batch::select_listed(resolve(&args.scenario)?, args.shard)?;
    let cfg = SimConfig {
        agents,
        controller: args.controller,
        steps: args.steps,
        ..SimConfig::default()
    };
    let mut config = json!({
        "command": "sim", "scenario": args.scenario, "planner": args.planner, "agents": agents,
        "controller": args.controller, "steps": args.steps, "planner_timeout_s": args.planner_timeout,
    });
    if let (Some(s), Some(o)) = (args.shard, config.as_object_mut()) {
        o.insert("shard".into(), serde_json::to_value(s)?);
    }
    batch::check_out_outside_scenarios(&args.out, &sources)?;
    let config = batch::with_inputs(config, &sources, &list, &args.planner.to_string(), &[])?;
    let out = batch::prepare_out(&args.out, &config, args.resume)?;
    let bar = (sources.len() > 1).then(|| {
        let b = indicatif::ProgressBar::new(sources.len() as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{bar:30} {pos}/{len} {msg} [{elapsed_precise}]",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b
    });
    let results = batch::for_each_scenario(
        &out,
        &sources,
        |_, src, dir| {
            if let Some(b) = &bar {
                b.set_message(src.name());
            }
            run_one(src, &args, &cfg, dir)
        },
        |name, v| match &bar {
            // a failed scenario is always named (its score 0 lowers the CLS), on a terminal or not (a hidden
            // bar's println prints nothing)
            Some(b) if !v["failure"].is_null() => {
                b.suspend(|| eprintln!("{}", batch::score_line(name, v)));
                b.inc(1)
            }
            Some(b) => b.inc(1),
            None => eprintln!("{}", batch::score_line(name, v)),
        },
    )?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    let header = json!({
        "planner": args.planner,
        "agents": agents,
        "cls_kind": agents.cls_kind(),
    });
    let summary = batch::summarize(header.as_object().cloned().unwrap_or_default(), results);
    batch::write_summary(&args.out, &summary)?;
    eprintln!(
        "{} scenario(s){}, {} {:.4} -> {}",
        summary["scenarios"]
            .as_array()
            .map(|v| v.len())
            .unwrap_or(0),
        args.shard
            .map(|s| format!(" (shard {s})"))
            .unwrap_or_default(),
        agents.cls_kind(),
        summary["cls"].as_f64().unwrap_or(0.0),
        args.out.join("metrics.json").display()
    );
    batch::ensure_not_all_failed(&summary, &args.out)
}
