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
    let cfg: serde_json::Value = serde_json::from_str(&b2dr::files::read_regular_string(
        &a.config,
        "model config",
        b2dr::files::JSON_LIMIT,
    )?)
    .with_context(|| format!("{}: invalid JSON", a.config.display()))?;
    // regular files only, read as far as their headers announce (issue #36)
    let w = Weights::load_unchecked(&a.weights)?;
    let inputs = Weights::load_unchecked(&a.inputs)?.tensors;
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
