//! `b2dr eval-render`: fidelity of a model against the synthetic world's ground truth (see
//! `b2dr::eval::fidelity`).
use std::path::PathBuf;

use anyhow::Result;
use b2dr::eval::fidelity::{eval_render, EvalConfig};
use b2dr::vk::{Context, ContextOptions};

#[derive(clap::Args, Debug)]
pub struct EvalRenderArgs {
    /// Model package folder or builtin:NAME (default: builtin:b2dr-nano)
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Held-out synthetic scenarios (builtin:LAYOUT:SEED...), comma-separated or repeated; the built-in model
    /// trained on seeds 0-3, so use seeds >= 100
    #[arg(long, value_delimiter = ',', required = true)]
    pub scenario: Vec<String>,
    /// Comma-separated cameras scored
    #[arg(long, value_delimiter = ',', default_value = "CAM_FRONT")]
    pub cameras: Vec<String>,
    /// Recorded frames (2 Hz) of the single-frame cases
    #[arg(long, value_delimiter = ',', default_value = "8,20,32")]
    pub frames: Vec<usize>,
    /// Lateral displacements of the sweep (m, to the left)
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0,1,2,4",
        allow_hyphen_values = true
    )]
    pub lateral: Vec<f64>,
    /// Yaw displacements of the sweep (degrees)
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0,5,10",
        allow_hyphen_values = true
    )]
    pub yaw: Vec<f64>,
    /// Reference-guidance scales evaluated (beside the model's own)
    #[arg(long, value_delimiter = ',', default_value = "1,2,3")]
    pub guidance: Vec<f64>,
    /// Frames of the autoregressive drift experiment (0: off)
    #[arg(long, default_value_t = 40)]
    pub drift_frames: usize,
    /// Scenarios (the first N) the drift experiment runs on
    #[arg(long, default_value_t = 1)]
    pub drift_scenarios: usize,
    /// Sampler steps (default: the model's)
    #[arg(long)]
    pub steps: Option<usize>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// UNet/ControlNet dtype of the main runs (f32 or f16); the drift experiment also runs the other one
    #[arg(long, default_value = "f32")]
    pub dtype: String,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(device: Option<String>, a: EvalRenderArgs) -> Result<()> {
    let cfg = EvalConfig {
        model: a.model,
        scenarios: a.scenario,
        cameras: a.cameras,
        frames: a.frames,
        lateral_m: a.lateral,
        yaw_deg: a.yaw,
        guidance: a.guidance,
        drift_frames: a.drift_frames,
        drift_scenarios: a.drift_scenarios,
        steps: a.steps,
        seed: a.seed,
        dtype: a.dtype,
    };
    let ctx = Context::new(&ContextOptions {
        device,
        ..Default::default()
    })?;
    let r = eval_render(&ctx, &cfg, &a.out)?;
    eprintln!(
        "{} single-frame and {} drift images scored ({} skipped) -> {}",
        r.single.len(),
        r.drift.len(),
        r.skipped.len(),
        a.out.join("eval.md").display()
    );
    Ok(())
}
