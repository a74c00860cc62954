//! `b2dr sample`: a full guided sampling loop (UNet + ControlNet + VAE decode) writing PNG and EXR images.
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context as _, Result};
use b2dr::nn::pipeline::{Pipeline, PipelineShape};
use b2dr::nn::sd_model::{check_vae_folder, SdDevice, SdLayers, SdModel};
use b2dr::render::inputs;
use b2dr::sampling::{NoiseSchedule, PredictionType, SamplerKind};
use b2dr::tensor::DType;
use b2dr::vk::{Context, ContextOptions};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

#[derive(clap::Args, Debug)]
pub struct SampleArgs {
    /// diffusers model folder (unet/, optional controlnet/, vae/, context.safetensors with "cond" and optional
    /// "uncond" (77, D)); default: the built-in b2dr-tiny with seeded random weights
    #[arg(long)]
    pub model: Option<PathBuf>,
    #[arg(long, default_value_t = 20)]
    pub steps: usize,
    /// unipc | ddim
    #[arg(long, default_value = "unipc")]
    pub sampler: SamplerKind,
    /// classifier-free guidance scale (<= 1 disables the unconditional pass)
    #[arg(long, default_value_t = 7.5)]
    pub guidance: f64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// image size HxW (multiples of 8)
    #[arg(long, default_value = "224x400")]
    pub size: String,
    /// conditioning image for the ControlNet (PNG/JPEG, resized to the image size); default: black
    #[arg(long)]
    pub cond: Option<PathBuf>,
    #[arg(long, default_value_t = 1.0)]
    pub conditioning_scale: f32,
    /// UNet/ControlNet dtype (the sampler and VAE run in f32)
    #[arg(long, default_value = "f32")]
    pub dtype: DType,
    #[arg(long)]
    pub out: PathBuf,
}

fn parse_size(s: &str) -> Result<(usize, usize)> {
    let (h, w) = s
        .split_once('x')
        .with_context(|| format!("--size {s:?}: expected HxW, e.g. 224x400"))?;
    let (h, w): (usize, usize) = (
        h.parse().context("--size height")?,
        w.parse().context("--size width")?,
    );
    ensure!(
        h >= 8 && w >= 8 && h % 8 == 0 && w % 8 == 0,
        "--size {s}: height and width must be multiples of 8"
    );
    Ok((h, w))
}

pub fn run(device: Option<String>, a: SampleArgs) -> Result<()> {
    let (ih, iw) = parse_size(&a.size)?;
    let (h, w) = (ih / 8, iw / 8);
    ensure!(a.steps >= 1, "--steps must be >= 1");
    b2dr::sampling::check_guidance("--guidance", a.guidance)?;
    b2dr::sampling::check_conditioning_scale("--conditioning-scale", a.conditioning_scale.into())?;
    if let Some(dir) = &a.model {
        // before the device (a VAE that does not downsample by 8 would decode images of another size)
        check_vae_folder(dir)?;
    }
    let ctx = Context::new(&ContextOptions {
        device,
        profile: false,
        ..Default::default()
    })?;
    let dt = a.dtype;
    let model = SdModel::resolve(a.model.as_deref())?;
    let dev = SdDevice::upload(&ctx, &model, dt)?;
    let SdLayers { unet, control, vae } = dev.layers(&model)?;
    let (uc, vc) = (&model.unet_cfg, &model.vae_cfg);
    let context = (&model.uncond, &model.cond);
    let sched = NoiseSchedule::sd15();
    let plan = a.sampler.plan(&sched, PredictionType::Epsilon, a.steps)?;
    let shape = PipelineShape {
        batch: 1,
        latent: (h, w),
        context: (77, uc.enc.cross_attention_dim),
        guidance: (a.guidance > 1.0).then_some(a.guidance),
        conditioning_scale: a.conditioning_scale,
    };
    let t0 = std::time::Instant::now();
    let p = Pipeline::new(
        &ctx,
        &unet,
        control.as_ref(),
        Some((&vae, vc.scaling_factor)),
        dt,
        shape,
        plan,
    )?;
    let plan_ms = t0.elapsed().as_secs_f64() * 1e3;
    let cond_img = match (&control, &a.cond) {
        (Some(c), Some(path)) => Some(read_image(path, ih, iw, c.cfg.conditioning_channels)?),
        (Some(c), None) => Some(vec![0.0; c.cfg.conditioning_channels * ih * iw]),
        (None, Some(_)) => bail!("--cond given but the model has no ControlNet"),
        (None, None) => None,
    };
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(a.seed);
    let x_t: Vec<f32> = (0..uc.enc.in_channels * h * w)
        .map(|_| StandardNormal.sample(&mut r))
        .collect();
    let bar = indicatif::ProgressBar::new(a.steps as u64);
    let t1 = std::time::Instant::now();
    let mut prog = |d: usize, _n: usize| bar.set_position(d as u64);
    let out = p.run(
        &x_t,
        context.0,
        context.1,
        cond_img.as_deref(),
        false,
        Some(&mut prog),
    )?;
    bar.finish_and_clear();
    let run_s = t1.elapsed().as_secs_f64();
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let png = a.out.join("sample.png");
    inputs::to_rgb(&out.image, (ih, iw))
        .save(&png)
        .with_context(|| format!("writing {}", png.display()))?;
    inputs::write_exr(&a.out.join("sample.exr"), &out.image, (ih, iw))?;
    let report = serde_json::json!({
        "device": ctx.info().name, "steps": a.steps, "sampler": a.sampler, "guidance": a.guidance, "seed": a.seed,
        "size": [ih, iw], "dtype": dt.name(), "plan_ms": plan_ms, "run_s": run_s,
        "ms_per_step": run_s * 1e3 / a.steps as f64,
        "device_bytes_planned": p.planned_bytes, "device_bytes_total": ctx.allocated_bytes(),
        "model": model.source,
    });
    std::fs::write(
        a.out.join("sample.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    eprintln!(
        "wrote {}/sample.png and sample.exr: {} steps in {:.2} s ({:.0} ms/step), device memory {:.1} MiB",
        a.out.display(),
        a.steps,
        run_s,
        run_s * 1e3 / a.steps as f64,
        ctx.allocated_bytes() as f64 / (1 << 20) as f64
    );
    Ok(())
}

/// image (1, 3, H, W) in [0, 1] (CHW) -> values
fn read_image(path: &Path, h: usize, w: usize, channels: usize) -> Result<Vec<f32>> {
    ensure!(
        channels == 3,
        "conditioning images with {channels} channels are not supported (3 expected)"
    );
    let img = image::open(path)
        .with_context(|| format!("reading {}", path.display()))?
        .to_rgb8();
    let img = image::imageops::resize(
        &img,
        w as u32,
        h as u32,
        image::imageops::FilterType::CatmullRom,
    );
    let mut v = vec![0.0; 3 * h * w];
    for (x, y, p) in img.enumerate_pixels() {
        for c in 0..3 {
            v[(c * h + y as usize) * w + x as usize] = p[c] as f32 / 255.0;
        }
    }
    Ok(v)
}
