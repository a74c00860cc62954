//! Model-level benchmark cases (`b2dr bench model`): one guided denoising step of a UNet + ControlNet
//! (batch 2 = uncond + cond) and one VAE decode, recorded once and replayed, timed after the fence. The
//! conditioning image is given once, as the pipeline does (both guidance halves share it, so its embedding is
//! computed once; diffusers embeds the duplicated image twice: same result). The `_loop` step cases time the
//! step as the pipeline's sampling loop runs it: the conditioning embedding, which depends on the image only,
//! computed once per run before the loop (not timed), the rest per step.
use anyhow::Result;

use super::config::{ControlNetConfig, UNetConfig, VaeConfig};
use super::controlnet::ControlNet;
use super::device::{DeviceWeights, Fwd, Workspace};
use super::unet::{Residuals, UNet};
use super::vae::VaeDecoder;
use super::weights::{self, Weights};
use crate::ops::bench::{random_tensor as rnd, BenchCase, BenchResult};
use crate::tensor::{DType, Tensor};
use crate::vk::Context;

/// UNet + ControlNet forward at batch 2 (one guided step), latent (h, w), context 77 x cross_attention_dim.
/// `loop_step`: the conditioning embedding is computed beforehand, outside the timed recording.
pub fn guided_step_case(
    name: &str,
    uc: UNetConfig,
    cc: ControlNetConfig,
    dtype: DType,
    hw: (usize, usize),
    loop_step: bool,
) -> BenchCase {
    let (h, w) = hw;
    BenchCase {
        name: name.to_string(),
        flops: 0.0,
        bytes: 0.0,
        build: Box::new(move |ctx| {
            let uw = DeviceWeights::upload(
                ctx,
                &Weights::random(&weights::expected_unet(&uc), 1),
                "",
                dtype,
            )?;
            let cw = DeviceWeights::upload(
                ctx,
                &Weights::random(&weights::expected_controlnet(&cc), 2),
                "",
                dtype,
            )?;
            let unet = UNet::load(&uw, &uc)?;
            let cn = ControlNet::load(&cw, &cc)?;
            let x = rnd(ctx, &[2, 4, h, w], dtype, 1)?;
            let t = Tensor::from_f32(ctx, &[2], DType::F32, &[500.0, 500.0], "t")?;
            let c = rnd(ctx, &[2, 77, uc.enc.cross_attention_dim], dtype, 2)?;
            let cond = rnd(ctx, &[1, cc.conditioning_channels, 8 * h, 8 * w], dtype, 3)?;
            let mut ws = Workspace::new(ctx, dtype);
            let emb = if loop_step {
                let mut rec = ctx.recorder()?;
                let e = cn.embed(
                    &mut Fwd {
                        rec: &mut rec,
                        ws: &mut ws,
                    },
                    &cond,
                )?;
                rec.finish()?.submit_wait()?;
                Some(e)
            } else {
                None
            };
            let mut rec = ctx.recorder()?;
            {
                let mut f = Fwd {
                    rec: &mut rec,
                    ws: &mut ws,
                };
                let o = match &emb {
                    Some(e) => cn.forward_embedded(&mut f, &x, &t, &c, e, 1.0)?,
                    None => cn.forward(&mut f, &x, &t, &c, &cond, 1.0)?,
                };
                unet.forward(
                    &mut f,
                    &x,
                    &t,
                    &c,
                    Some(Residuals {
                        down: &o.down,
                        mid: &o.mid,
                    }),
                )?;
            }
            // Weights and activations stay alive in the recording (it keeps every buffer it uses).
            rec.finish()
        }),
    }
}

/// VAE decoder forward of one latent (h, w) to (8h, 8w).
pub fn vae_decode_case(name: &str, vc: VaeConfig, dtype: DType, hw: (usize, usize)) -> BenchCase {
    let (h, w) = hw;
    BenchCase {
        name: name.to_string(),
        flops: 0.0,
        bytes: 0.0,
        build: Box::new(move |ctx| {
            let vw = DeviceWeights::upload(
                ctx,
                &Weights::random(&weights::expected_vae(&vc), 3),
                "",
                dtype,
            )?;
            let dec = VaeDecoder::load(&vw, &vc)?;
            let z = rnd(ctx, &[1, vc.latent_channels, h, w], dtype, 4)?;
            let mut ws = Workspace::new(ctx, dtype);
            let mut rec = ctx.recorder()?;
            dec.forward(
                &mut Fwd {
                    rec: &mut rec,
                    ws: &mut ws,
                },
                &z,
            )?;
            rec.finish()
        }),
    }
}

/// The model cases of `b2dr bench model` (b2dr-tiny at the renderer's 224 x 400).
pub fn cases() -> Vec<BenchCase> {
    let mut v = vec![];
    for dt in [DType::F32, DType::F16] {
        for loop_step in [false, true] {
            v.push(guided_step_case(
                &format!(
                    "guided_step_tiny_{}_28x50_b2{}",
                    dt.name(),
                    if loop_step { "_loop" } else { "" }
                ),
                UNetConfig::b2dr_tiny(),
                ControlNetConfig::b2dr_tiny(),
                dt,
                (28, 50),
                loop_step,
            ));
        }
        v.push(vae_decode_case(
            &format!("vae_decode_tiny_{}_224x400", dt.name()),
            VaeConfig::b2dr_tiny(),
            dt,
            (28, 50),
        ));
    }
    v
}

/// Re-exported for the CLI.
pub fn run(ctx: &Context, c: &BenchCase, min_time_s: f64) -> Result<BenchResult> {
    crate::ops::bench::run_case(ctx, c, 1, 3, min_time_s)
}
