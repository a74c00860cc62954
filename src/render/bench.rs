//! `b2dr bench frame`: wall time per stage of Bench2Drive-R frames of a model (default: the built-in one) on
//! seeded random inputs, and with `--profile` the GPU time and dispatch count of every recording a frame
//! replays (the reference encoder and PE MLPs live in the per-frame conditioning, not in the per-step pass).
use anyhow::Result;
use rand::{Rng, SeedableRng};

use super::frame::{FrameInputs, FrameRenderer, FrameShape, FrameTimes, Prev, RefInputs};
use super::inputs::frame_noise;
use super::job::sampler_plan;
use super::package::{DeviceModel, ModelPackage};
use crate::tensor::DType;
use crate::vk::Context;

/// One recording's profile: stage, dispatches, GPU ms (0 without timestamps), replays per frame.
pub struct StageProfile {
    pub stage: String,
    pub dispatches: usize,
    pub gpu_ms: f64,
    pub per_frame: usize,
}

pub struct FrameBench {
    pub cameras: usize,
    pub size: (usize, usize),
    pub steps: usize,
    pub ref_guidance: f64,
    pub plan_ms: f64,
    /// One entry per rendered frame (the first is a warm-up).
    pub frames: Vec<FrameTimes>,
    pub profile: Vec<StageProfile>,
    pub device_bytes: u64,
}

#[allow(clippy::too_many_arguments)]
pub fn run(
    ctx: &Context,
    pkg: &ModelPackage,
    cameras: usize,
    steps: usize,
    ref_guidance: f64,
    dtype: DType,
    frames: usize,
) -> Result<FrameBench> {
    let [h, w] = pkg.meta.render_size;
    anyhow::ensure!((1..=64).contains(&cameras), "--cameras {cameras}: 1..=64");
    anyhow::ensure!(frames >= 1, "--frames must be >= 1");
    let names: Vec<String> = (0..cameras)
        .map(|i| pkg.meta.cameras[i % pkg.meta.cameras.len()].clone())
        .collect();
    let dm = DeviceModel::upload(ctx, pkg, dtype)?;
    let t0 = std::time::Instant::now();
    let r = FrameRenderer::new(
        ctx,
        &dm.as_model(),
        FrameShape {
            cameras,
            size: (h, w),
            refs: true,
            ref_guidance,
            out_size: None,
            prev_noise_level: None,
            prev_blur_sigma: None,
        },
        &pkg.context_for(&names)?,
        sampler_plan(&pkg.meta.sampler, steps, pkg.meta.prediction())?,
    )?;
    let plan_ms = t0.elapsed().as_secs_f64() * 1e3;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
    let mut u = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.gen_range(0.0f32..1.0)).collect() };
    let masks: Vec<f32> = u(cameras * 15 * h * w)
        .iter()
        .map(|v| (*v > 0.8) as u8 as f32)
        .collect();
    let prev = u(cameras * 3 * h * w);
    let refs = u(cameras * 2 * 3 * h * w);
    let cfg = &pkg.control_cfg;
    let d3 = 3 * cfg.pe_depth_num;
    let (pc, pr): (Vec<Vec<f32>>, Vec<Vec<f32>>) = cfg
        .ref_attn
        .iter()
        .map(|&at| {
            let (fh, fw) = cfg.location_size(at, (h / 8, w / 8));
            (u(cameras * d3 * fh * fw), u(2 * cameras * d3 * fh * fw))
        })
        .unzip();
    let mut times = vec![];
    for k in 0..frames {
        let (x_t, eps) = frame_noise(1, k as u64, cameras, r.latent_size());
        times.push(r.render(&FrameInputs {
            masks: &masks,
            prev: if k == 0 {
                Prev::Image(&prev)
            } else {
                Prev::Carried
            },
            refs: Some(RefInputs {
                images: &refs,
                pe_cur: pc.iter().map(|v| &v[..]).collect(),
                pe_ref: pr.iter().map(|v| &v[..]).collect(),
            }),
            x_t: &x_t,
            eps_prev: &eps,
            prev_warp: None,
        })?);
    }
    let mut profile = vec![];
    for (stage, rec) in r.recordings() {
        let gpu_ms = rec.timings()?.iter().map(|t| t.ms).sum();
        let per_frame = if stage.contains("per step") { steps } else { 1 };
        profile.push(StageProfile {
            stage: stage.to_string(),
            dispatches: rec.dispatch_count(),
            gpu_ms,
            per_frame,
        });
    }
    Ok(FrameBench {
        cameras,
        size: (h, w),
        steps,
        ref_guidance,
        plan_ms,
        frames: times,
        profile,
        device_bytes: ctx.allocated_bytes(),
    })
}
