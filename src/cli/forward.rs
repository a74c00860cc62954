//! `b2dr forward`: runs one model component, or one B2D-R frame of a model package, on named input tensors and
//! writes its outputs (to check a converted checkpoint or a trained package against the PyTorch reference).
use std::path::PathBuf;

use anyhow::{bail, Context as _, Result};
use b2dr::nn::run::{forward_component, Component};
use b2dr::nn::weights::{FileDType, Weights};
use b2dr::render::named::{self, NamedFrame};
use b2dr::tensor::DType;
use b2dr::vk::{Context, ContextOptions};

/// What `--component` names: a diffusers component, or a whole frame of a package.
#[derive(Clone, Copy, Debug)]
pub enum What {
    Component(Component),
    Frame,
}

impl std::str::FromStr for What {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "frame" => Ok(Self::Frame),
            _ => s.parse().map(Self::Component).map_err(|e| {
                anyhow::anyhow!("{e:#}; or frame (a whole B2D-R frame of a --model package)")
            }),
        }
    }
}

#[derive(clap::Args, Debug)]
pub struct ForwardArgs {
    /// unet | controlnet | vae-encoder | vae-decoder (with --config and --weights), or frame: one B2D-R frame
    /// of a --model package (inputs in.x_T, in.eps_prev, in.masks, in.prev_image, in.ref_images,
    /// in.pe_cur.{j}, in.pe_ref.{j}, optional in.context; outputs image, latent, prev_latent; see the README)
    #[arg(long)]
    pub component: What,
    /// diffusers config.json of the component
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// diffusers safetensors weights (f32, f16 or bf16)
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// frame: model package folder or builtin:NAME (as `b2dr render --model`; default: the built-in model)
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// frame: comma-separated cameras, the context rows (default: the package's; N = their count)
    #[arg(long, value_delimiter = ',')]
    pub cameras: Option<Vec<String>>,
    /// frame: sampling steps (default: the package's)
    #[arg(long)]
    pub steps: Option<usize>,
    /// frame: unipc | ddim (default: the package's)
    #[arg(long)]
    pub sampler: Option<String>,
    /// frame: reference guidance scale w (default: the package's; 1 = references without guidance)
    #[arg(long)]
    pub ref_guidance: Option<f64>,
    /// frame: masks only (the reference inputs are not read, the Ref-Attns skipped)
    #[arg(long)]
    pub no_refs: bool,
    /// safetensors file of named inputs (see the README)
    #[arg(long)]
    pub inputs: PathBuf,
    /// where to write the outputs (safetensors, f32)
    #[arg(long)]
    pub out: PathBuf,
    /// model dtype (frame: UNet and ControlNet; its VAE runs in f32)
    #[arg(long, default_value = "f32")]
    pub dtype: DType,
}

pub fn run(device: Option<String>, a: ForwardArgs) -> Result<()> {
    let frame_only = [
        ("--model", a.model.is_some()),
        ("--cameras", a.cameras.is_some()),
        ("--steps", a.steps.is_some()),
        ("--sampler", a.sampler.is_some()),
        ("--ref-guidance", a.ref_guidance.is_some()),
        ("--no-refs", a.no_refs),
    ];
    let (out, what) = match a.component {
        What::Frame => {
            if a.config.is_some() || a.weights.is_some() {
                bail!("--component frame reads a --model package; --config and --weights are for one component");
            }
            (frame(device, &a)?, "frame".to_string())
        }
        What::Component(c) => {
            if let Some((flag, _)) = frame_only.iter().find(|(_, given)| *given) {
                bail!("{flag} is an option of --component frame");
            }
            let (Some(config), Some(weights)) = (&a.config, &a.weights) else {
                bail!(
                    "--component {} needs --config and --weights (a diffusers component)",
                    c.name()
                );
            };
            (
                component(device, c, config, weights, &a)?,
                c.name().to_string(),
            )
        }
    };
    for (k, v) in &out {
        eprintln!("  {what} {k}: {:?}", v.shape);
    }
    Weights { tensors: out }.save(&a.out, FileDType::F32)
}

type Outputs = std::collections::BTreeMap<String, b2dr::nn::weights::HostTensor>;

fn context(device: Option<String>) -> Result<Context> {
    Context::new(&ContextOptions {
        device,
        profile: false,
        ..Default::default()
    })
}

fn component(
    device: Option<String>,
    c: Component,
    config: &std::path::Path,
    weights: &std::path::Path,
    a: &ForwardArgs,
) -> Result<Outputs> {
    let cfg: serde_json::Value = serde_json::from_str(&b2dr::files::read_regular_string(
        config,
        "model config",
        b2dr::files::JSON_LIMIT,
    )?)
    .with_context(|| format!("{}: invalid JSON", config.display()))?;
    // regular files only, read as far as their headers announce (issue #36)
    let w = Weights::load_unchecked(weights)?;
    let inputs = Weights::load_unchecked(&a.inputs)?.tensors;
    let ctx = context(device)?;
    let t = std::time::Instant::now();
    let out = forward_component(&ctx, c, cfg, &w, &inputs, a.dtype)
        .with_context(|| format!("{} forward", c.name()))?;
    eprintln!(
        "{} on {}: {:.1} ms (with upload)",
        c.name(),
        ctx.info().name,
        t.elapsed().as_secs_f64() * 1e3
    );
    Ok(out)
}

fn frame(device: Option<String>, a: &ForwardArgs) -> Result<Outputs> {
    let o = NamedFrame {
        cameras: a.cameras.clone(),
        steps: a.steps,
        sampler: a.sampler.clone(),
        ref_guidance: a.ref_guidance,
        no_refs: a.no_refs,
    };
    let pkg = b2dr::render::package::resolve_model(a.model.as_deref())?;
    let inputs = Weights::load_unchecked(&a.inputs)?.tensors;
    // every input is checked on the host before a device is opened
    let x = named::check_inputs(&pkg, &inputs, &o).with_context(|| {
        format!(
            "--component frame of {} on {}",
            pkg.source,
            a.inputs.display()
        )
    })?;
    let ctx = context(device)?;
    let t = std::time::Instant::now();
    let out = named::render(&ctx, &pkg, &x, a.dtype).context("frame")?;
    eprintln!(
        "frame of {} ({} cameras {:?}) on {}: {:.1} ms (with upload and planning)",
        pkg.source,
        x.cameras.len(),
        x.cameras,
        ctx.info().name,
        t.elapsed().as_secs_f64() * 1e3
    );
    Ok(out)
}
