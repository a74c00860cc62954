//! `b2dr forward`: runs one model component on named input tensors and writes its outputs (to check a
//! converted checkpoint against diffusers).
use std::path::PathBuf;

use anyhow::{Context as _, Result};
use b2dr::nn::run::{forward_component, Component};
use b2dr::nn::weights::{FileDType, Weights};
use b2dr::tensor::DType;
use b2dr::vk::{Context, ContextOptions};

#[derive(clap::Args, Debug)]
pub struct ForwardArgs {
    /// unet | controlnet | vae-encoder | vae-decoder
    #[arg(long)]
    pub component: Component,
    /// diffusers config.json of the component
    #[arg(long)]
    pub config: PathBuf,
    /// diffusers safetensors weights (f32, f16 or bf16)
    #[arg(long)]
    pub weights: PathBuf,
    /// safetensors file of named inputs (see the README)
    #[arg(long)]
    pub inputs: PathBuf,
    /// where to write the outputs (safetensors, f32)
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value = "f32")]
    pub dtype: DType,
}

pub fn run(device: Option<String>, a: ForwardArgs) -> Result<()> {
    let cfg: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&a.config)
            .with_context(|| format!("reading {}", a.config.display()))?,
    )
    .with_context(|| format!("{}: invalid JSON", a.config.display()))?;
    let bytes =
        std::fs::read(&a.weights).with_context(|| format!("reading {}", a.weights.display()))?;
    let w = Weights::from_bytes_unchecked(&bytes, &a.weights.display().to_string())?;
    let ib = std::fs::read(&a.inputs).with_context(|| format!("reading {}", a.inputs.display()))?;
    let inputs = Weights::from_bytes_unchecked(&ib, &a.inputs.display().to_string())?.tensors;
    let ctx = Context::new(&ContextOptions {
        device,
        profile: false,
        ..Default::default()
    })?;
    let t = std::time::Instant::now();
    let out = forward_component(&ctx, a.component, cfg, &w, &inputs, a.dtype)
        .with_context(|| format!("{:?} forward", a.component))?;
    eprintln!(
        "{:?} on {}: {:.1} ms (with upload)",
        a.component,
        ctx.info().name,
        t.elapsed().as_secs_f64() * 1e3
    );
    for (k, v) in &out {
        eprintln!("  {k}: {:?}", v.shape);
    }
    Weights { tensors: out }.save(&a.out, FileDType::F32)
}
