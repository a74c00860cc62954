//! `controlnet_conditioning_channel_order: "bgr"` (diffusers flips the condition's channels before the
//! conditioning embedding): a bgr model on the channel-flipped condition equals the rgb model on the original.
mod common;

use b2dr::nn::config::ControlNetConfig;
use b2dr::nn::controlnet::ControlNet;
use b2dr::nn::device::{DeviceWeights, Fwd, Workspace};
use b2dr::nn::weights::{self, Weights};
use b2dr::tensor::{DType, Tensor};
use b2dr::vk::Context;

fn embed(ctx: &Context, cn: &ControlNet, cond: &Tensor, dtype: DType) -> Vec<f32> {
    let mut ws = Workspace::new(ctx, dtype);
    let mut rec = ctx.recorder().unwrap();
    let e = cn
        .embed(
            &mut Fwd {
                rec: &mut rec,
                ws: &mut ws,
            },
            cond,
        )
        .unwrap();
    rec.finish().unwrap().submit_wait().unwrap();
    e.to_f32(ctx).unwrap()
}

fn nmse(a: &[f32], b: &[f32]) -> f64 {
    let num: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
        .sum();
    let den: f64 = b.iter().map(|y| (*y as f64).powi(2)).sum();
    num / den.max(1e-30)
}

#[test]
fn bgr_model_on_flipped_condition_equals_rgb_model() {
    let Some(ctx) = common::ctx() else { return };
    let rgb_cfg = ControlNetConfig::b2dr_tiny();
    let bgr_cfg = ControlNetConfig {
        bgr_conditioning: true,
        ..rgb_cfg.clone()
    };
    let w = Weights::random(&weights::expected_controlnet(&rgb_cfg), 7);
    // (M, 3, 8H, 8W): two images, latent 3 x 5
    let (m, c, h, wd) = (2, rgb_cfg.conditioning_channels, 24, 40);
    // large values: through eight random convs the biases would otherwise swamp the condition's part
    let cond = common::uniform(m * c * h * wd, 100.0, 11);
    let mut flipped = vec![0f32; cond.len()];
    for (src, dst) in cond.chunks(c * h * wd).zip(flipped.chunks_mut(c * h * wd)) {
        for ci in 0..c {
            dst[ci * h * wd..(ci + 1) * h * wd]
                .copy_from_slice(&src[(c - 1 - ci) * h * wd..(c - ci) * h * wd]);
        }
    }
    for (dtype, tol) in [(DType::F32, 1e-10), (DType::F16, 1e-6)] {
        let dw = DeviceWeights::upload(&ctx, &w, "", dtype).unwrap();
        let rgb = ControlNet::load(&dw, &rgb_cfg).unwrap();
        let bgr = ControlNet::load(&dw, &bgr_cfg).unwrap();
        let shape = [m, c, h, wd];
        let x = common::upload(&ctx, &shape, dtype, &cond);
        let xf = common::upload(&ctx, &shape, dtype, &flipped);
        let want = embed(&ctx, &rgb, &x, dtype);
        let got = embed(&ctx, &bgr, &xf, dtype);
        let e = nmse(&got, &want);
        eprintln!("{dtype:?}: bgr(flipped) vs rgb: nmse {e:.3e}");
        assert!(
            e <= tol,
            "{dtype:?}: bgr(flipped) vs rgb(original): nmse {e:e} > {tol:e}"
        );
        // and the order matters: the bgr model on the unflipped condition differs
        let other = embed(&ctx, &bgr, &x, dtype);
        let d = nmse(&other, &want);
        eprintln!("{dtype:?}: bgr(original) vs rgb: nmse {d:.3e}");
        assert!(
            d > 1e-2,
            "{dtype:?}: the channel order changed little (nmse {d:e})"
        );
    }
    common::assert_no_validation_errors();
}
