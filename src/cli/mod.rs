//! clap definitions and dispatch. One file per subcommand.
use clap::{Parser, Subcommand};

mod bench;
mod eval_render;
mod export;
mod forward;
mod info;
mod merge;
mod project;
mod render;
mod run;
mod sample;
mod sim;
mod world;

#[derive(Parser, Debug)]
#[command(
    name = "b2dr",
    version,
    about = "Reactive closed-loop driving evaluation with a generative renderer"
)]
pub struct Cli {
    /// Vulkan device: index or name substring (default: B2DR_DEVICE, else discrete > integrated > CPU).
    #[arg(long, global = true)]
    pub device: Option<String>,
    /// llvmpipe/lavapipe worker threads (sets LP_NUM_THREADS before the device is created).
    #[arg(long, global = true)]
    pub lp_threads: Option<u32>,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Print the Vulkan devices, the chosen one and the features b2dr uses.
    Info,
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCmd),
    /// Project a keyframe's boxes (and a map) into its cameras: masks, overlays, projection.json.
    Project(project::ProjectArgs),
    /// Run one model component (unet, controlnet, vae-encoder, vae-decoder), or one B2D-R frame of a model
    /// package (frame), on named input tensors.
    Forward(forward::ForwardArgs),
    /// Run a full guided sampling loop (UNet + ControlNet + VAE decode) and write PNG and EXR.
    Sample(sample::SampleArgs),
    /// Render one Bench2Drive-R frame of a keyframe (layout masks, previous frame, two references).
    Render(render::RenderArgs),
    /// The closed loop with rendered cameras: a planner drives on images of the simulated world.
    Run(run::RunArgs),
    /// Fidelity of a model against the synthetic world's ground truth: PSNR / SSIM / layout score on held-out
    /// scenarios, the deviation sweep, autoregressive drift, ablations and the copy-nearest-frame baseline.
    EvalRender(eval_render::EvalRenderArgs),
    /// Closed-loop simulation of a planner over scenarios, with the nuPlan closed-loop score.
    Sim(sim::SimArgs),
    /// Combine the output folders of `--shard K/N` runs (`sim` or `run`, one configuration) into one
    /// metrics.json: CLS, per-metric means, per-stage timing totals, every scenario.
    Merge(merge::MergeArgs),
    /// Ground truth of a scenario state: camera images, mosaic + BEV, overlays of the projected masks.
    World(world::WorldArgs),
    /// Export training samples (images, references, masks, matrices) as safetensors shards + index.json.
    ExportTraining(export::ExportArgs),
    /// Export imitation data for an image-reading planner: ground-truth cameras at the expert's planner steps
    /// (and displaced), speed, command, and the expert's next 8 poses.
    ExportPlanner(export::ExportPlannerArgs),
}

#[derive(Subcommand, Debug)]
pub enum BenchCmd {
    /// Time Bench2Drive-R frames by stage (encode, denoise, decode) of a model package (default: built-in).
    Frame(bench::FrameArgs),
    /// The speed/accuracy trade: precision, sampler and steps, resolution, guidance and cameras swept on one
    /// device, each point timed and scored against the reference setting and the ground truth.
    Trade(bench::TradeArgs),
    /// Time model components (guided UNet + ControlNet step, VAE decode) of b2dr-tiny at 224 x 400.
    Model {
        #[arg(long)]
        json: bool,
        #[arg(long)]
        filter: Option<String>,
        #[arg(long, default_value_t = 3.0)]
        min_time: f64,
        /// Print GPU time per op (timestamp queries after every dispatch).
        #[arg(long)]
        profile: bool,
    },
    /// Time every op case (ms, GFLOP/s, GB/s) on the chosen device.
    Ops {
        /// One JSON object keyed by case name.
        #[arg(long)]
        json: bool,
        /// Only cases whose name contains this.
        #[arg(long)]
        filter: Option<String>,
        /// Minimum timed seconds per case.
        #[arg(long, default_value_t = 1.0)]
        min_time: f64,
        /// Print GPU time per op (timestamp queries after every dispatch).
        #[arg(long)]
        profile: bool,
    },
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    if let Some(t) = cli.lp_threads {
        anyhow::ensure!(t >= 1, "--lp-threads must be >= 1");
        // SAFETY: single-threaded at this point (before any Vulkan or worker thread exists).
        unsafe { std::env::set_var("LP_NUM_THREADS", t.to_string()) };
    }
    match cli.command {
        Command::Info => info::run(cli.device),
        Command::Bench(BenchCmd::Frame(a)) => bench::run_frame(cli.device, a),
        Command::Bench(BenchCmd::Trade(a)) => bench::run_trade(cli.device, a),
        Command::Bench(BenchCmd::Ops {
            json,
            filter,
            min_time,
            profile,
        }) => bench::run_ops(cli.device, json, filter, min_time, profile),
        Command::Bench(BenchCmd::Model {
            json,
            filter,
            min_time,
            profile,
        }) => bench::run_model(cli.device, json, filter, min_time, profile),
        Command::Project(a) => project::run(a),
        Command::Forward(a) => forward::run(cli.device, a),
        Command::Sample(a) => sample::run(cli.device, a),
        Command::Render(a) => render::run(cli.device, a),
        Command::Run(a) => run::run(cli.device, a),
        Command::EvalRender(a) => eval_render::run(cli.device, a),
        Command::Sim(a) => sim::run(a),
        Command::Merge(a) => merge::run(a),
        Command::World(a) => world::run(a),
        Command::ExportTraining(a) => export::run(a),
        Command::ExportPlanner(a) => export::run_planner(a),
    }
}
