//! `b2dr bench ops [--json] [--filter S] [--profile]`: times every op case on the chosen device.
use std::collections::BTreeMap;

use anyhow::{bail, Result};
use b2dr::ops::bench;
use b2dr::vk::{Context, ContextOptions};

pub fn run_ops(
    device: Option<String>,
    json: bool,
    filter: Option<String>,
    min_time_s: f64,
    profile: bool,
) -> Result<()> {
    run_cases(device, bench::cases(), json, filter, min_time_s, profile)
}

/// `b2dr bench model`: the model-level cases of `b2dr::nn::bench`.
pub fn run_model(
    device: Option<String>,
    json: bool,
    filter: Option<String>,
    min_time_s: f64,
    profile: bool,
) -> Result<()> {
    run_cases(
        device,
        b2dr::nn::bench::cases(),
        json,
        filter,
        min_time_s,
        profile,
    )
}

fn run_cases(
    device: Option<String>,
    all: Vec<bench::BenchCase>,
    json: bool,
    filter: Option<String>,
    min_time_s: f64,
    profile: bool,
) -> Result<()> {
    let ctx = Context::new(&ContextOptions {
        device,
        profile,
        ..Default::default()
    })?;
    let cases: Vec<_> = all
        .into_iter()
        .filter(|c| filter.as_deref().is_none_or(|f| c.name.contains(f)))
        .collect();
    if cases.is_empty() {
        bail!("no benchmark case matches {:?}", filter.unwrap_or_default());
    }
    if !json {
        eprintln!("device: {} ({})", ctx.info().name, ctx.info().kind);
        println!(
            "{:<40} {:>10} {:>10} {:>10} {:>9} {:>6}",
            "case", "ms", "min ms", "GFLOP/s", "GB/s", "iters"
        );
    }
    let mut out = BTreeMap::new();
    for c in &cases {
        if !json {
            eprint!("  running {} ...\r", c.name);
        }
        let r = bench::run_case(&ctx, c, 2, 3, min_time_s)?;
        if json {
            out.insert(
                r.name.clone(),
                serde_json::json!({"ms": r.ms, "min_ms": r.min_ms, "gflops": r.gflops, "gbs": r.gbs, "iters": r.iters}),
            );
        } else {
            println!(
                "{:<40} {:>10.3} {:>10.3} {:>10.2} {:>9.2} {:>6}",
                r.name, r.ms, r.min_ms, r.gflops, r.gbs, r.iters
            );
            let top = std::env::var("B2DR_PROFILE_TOP")
                .ok()
                .and_then(|v| v.parse().ok())
                .unwrap_or(15);
            for (label, ms, n) in r.profile.iter().take(top) {
                println!("    {label:<36} {ms:>10.3} ms {n:>5}x");
            }
            if !r.profile.is_empty() {
                let total: f64 = r.profile.iter().map(|p| p.1).sum();
                let n: usize = r.profile.iter().map(|p| p.2).sum();
                println!("    {:<36} {total:>10.3} ms {n:>5}x", "(all dispatches)");
            }
        }
    }
    if json {
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct FrameArgs {
    /// Model package folder or builtin:NAME (default: the built-in b2dr-nano)
    #[arg(long)]
    pub model: Option<std::path::PathBuf>,
    #[arg(long, default_value_t = 6)]
    pub cameras: usize,
    #[arg(long, default_value_t = 20)]
    pub steps: usize,
    #[arg(long, default_value_t = 2.0)]
    pub ref_guidance: f64,
    #[arg(long, default_value = "f32")]
    pub dtype: b2dr::tensor::DType,
    /// Frames to render (the first starts from an image, the others from the carried frame)
    #[arg(long, default_value_t = 2)]
    pub frames: usize,
    #[arg(long)]
    pub json: bool,
    /// GPU time and dispatch count per recording (timestamp queries after every dispatch)
    #[arg(long)]
    pub profile: bool,
}

/// `b2dr bench frame`.
pub fn run_frame(device: Option<String>, a: FrameArgs) -> Result<()> {
    b2dr::sampling::check_guidance("--ref-guidance", a.ref_guidance)?;
    let ctx = Context::new(&ContextOptions {
        device,
        profile: a.profile,
        ..Default::default()
    })?;
    let pkg = b2dr::render::package::resolve_model(a.model.as_deref())?;
    let b = b2dr::render::bench::run(
        &ctx,
        &pkg,
        a.cameras,
        a.steps,
        a.ref_guidance,
        a.dtype,
        a.frames,
    )?;
    let prof: Vec<_> = b
        .profile
        .iter()
        .map(|p| serde_json::json!({"stage": p.stage, "dispatches": p.dispatches, "gpu_ms": p.gpu_ms, "replays_per_frame": p.per_frame}))
        .collect();
    let report = serde_json::json!({
        "device": ctx.info().name, "model": pkg.source, "cameras": b.cameras, "render_size": [b.size.0, b.size.1],
        "steps": b.steps, "ref_guidance": b.ref_guidance, "plan_ms": b.plan_ms, "frames": b.frames,
        "profile": prof, "device_bytes": b.device_bytes,
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "device: {} | model {} | {} cameras at {}x{}, {} steps, ref guidance {} | plan {:.0} ms | device memory {:.1} MiB",
        ctx.info().name, pkg.source, b.cameras, b.size.0, b.size.1, b.steps, b.ref_guidance, b.plan_ms,
        b.device_bytes as f64 / (1 << 20) as f64
    );
    println!(
        "{:<8} {:>12} {:>12} {:>12} {:>12}",
        "frame", "encode ms", "denoise ms", "decode ms", "total ms"
    );
    for (k, t) in b.frames.iter().enumerate() {
        println!(
            "{:<8} {:>12.1} {:>12.1} {:>12.1} {:>12.1}",
            k,
            t.encode_ms,
            t.denoise_ms,
            t.decode_ms,
            t.encode_ms + t.denoise_ms + t.decode_ms
        );
    }
    println!(
        "{:<44} {:>10} {:>12} {:>8}",
        "recording", "dispatches", "GPU ms", "x/frame"
    );
    for p in &b.profile {
        println!(
            "{:<44} {:>10} {:>12.2} {:>8}",
            p.stage, p.dispatches, p.gpu_ms, p.per_frame
        );
    }
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct TradeArgs {
    /// Model package folder or builtin:NAME (default: the built-in b2dr-nano)
    #[arg(long)]
    pub model: Option<std::path::PathBuf>,
    /// One synthetic scenario (its ground truth scores every point); held-out seeds (>= 100) by default
    #[arg(long, default_value = "builtin:town:100")]
    pub scenario: String,
    /// Output folder (trade.json, trade.md, trade.png, trade_truth.png)
    #[arg(long)]
    pub out: std::path::PathBuf,
    /// A reduced sweep that runs in minutes (1 camera, 1 frame, UniPC 4/10/20/50, an 8-frame rollout)
    #[arg(long)]
    pub quick: bool,
    /// Recorded frames every point renders (comma separated; default 8,20, quick: 8)
    #[arg(long, value_delimiter = ',')]
    pub frames: Option<Vec<usize>>,
    /// Cameras of the reference setting (the model's first N; default 6, quick: 1)
    #[arg(long)]
    pub cameras: Option<usize>,
    /// Frames of the autoregressive rollout per precision (default 200, quick: 8; 0 = none)
    #[arg(long)]
    pub rollout_frames: Option<usize>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Print trade.json to stdout instead of the table
    #[arg(long)]
    pub json: bool,
}

/// `b2dr bench trade`.
pub fn run_trade(device: Option<String>, a: TradeArgs) -> Result<()> {
    use b2dr::eval::trade::{bench_trade, TradeConfig};
    let ctx = Context::new(&ContextOptions {
        device,
        ..Default::default()
    })?;
    let mut cfg = TradeConfig::new(a.model, a.scenario, a.quick);
    if let Some(f) = a.frames {
        cfg.frames = f;
    }
    if let Some(c) = a.cameras {
        cfg.cameras = c;
    }
    if let Some(r) = a.rollout_frames {
        cfg.rollout_frames = r;
    }
    cfg.seed = a.seed;
    let r = bench_trade(&ctx, &cfg, &a.out)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        print!("{}", b2dr::eval::trade::markdown(&r));
        eprintln!(
            "wrote {}/{{trade.json, trade.md, trade.png, trade_truth.png}}",
            a.out.display()
        );
    }
    Ok(())
}
