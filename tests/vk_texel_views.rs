//! Texel views (`vk::image`: large buffers read through linear storage images on CPU devices) change how
//! kernels load, never what they compute: b2dr-tiny's VAE decoder (Winograd F(4x4) and F(6x6) transforms, their
//! GEMMs, residuals, attention) gives bitwise the same image with them on and off.
mod common;

use b2dr::nn::config::VaeConfig;
use b2dr::nn::device::{DeviceWeights, Fwd, Workspace};
use b2dr::nn::vae::VaeDecoder;
use b2dr::nn::weights::{self, Weights};
use b2dr::tensor::{DType, Tensor};
use b2dr::vk::{Context, ContextOptions};
use common::*;

fn decode(views: bool, z: &[f32], hw: (usize, usize)) -> Option<(Vec<f32>, bool)> {
    let ctx = Context::new(&ContextOptions {
        validation: Some(true),
        texel_views: Some(views),
        ..Default::default()
    })
    .ok()?;
    let vc = VaeConfig::b2dr_tiny();
    let vw = DeviceWeights::upload(
        &ctx,
        &Weights::random(&weights::expected_vae(&vc), 3),
        "",
        DType::F32,
    )
    .unwrap();
    let dec = VaeDecoder::load(&vw, &vc).unwrap();
    let zt = Tensor::from_f32(
        &ctx,
        &[1, vc.latent_channels, hw.0, hw.1],
        DType::F32,
        z,
        "z",
    )
    .unwrap();
    let mut ws = Workspace::new(&ctx, DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let out = dec
        .forward(
            &mut Fwd {
                rec: &mut rec,
                ws: &mut ws,
            },
            &zt,
        )
        .unwrap();
    rec.finish().unwrap().submit_wait().unwrap();
    let used = ctx.info().linear_images && out.buffer().has_texel_view();
    Some((out.to_f32(&ctx).unwrap(), used))
}

#[test]
fn vae_decode_is_bitwise_the_same_with_and_without_texel_views() {
    let Some(probe) = ctx() else { return };
    // 14 x 25 latents: F(6x6) pairs at 56 x 100 and above, F(4x4) at 14 x 25 and 28 x 50, odd tile counts
    let hw = (14, 25);
    let z = uniform(4 * hw.0 * hw.1, 1.0, 5);
    let (Some((on, used)), Some((off, _))) = (decode(true, &z, hw), decode(false, &z, hw)) else {
        eprintln!("SKIP: could not create a second Vulkan context");
        return;
    };
    let expect = probe.info().linear_images && probe.info().is_cpu();
    if !expect {
        eprintln!(
            "{} has no texel views: both runs take the plain kernels",
            probe.info().name
        );
    }
    // on a device with texel views the first run must have used them (else this compares plain with plain)
    assert_eq!(used, expect, "texel views used: {used}, expected: {expect}");
    assert_eq!(on.len(), 3 * 8 * hw.0 * 8 * hw.1);
    assert!(on.iter().all(|v| v.is_finite()));
    let differ = on
        .iter()
        .zip(&off)
        .filter(|(a, b)| a.to_bits() != b.to_bits())
        .count();
    assert_eq!(differ, 0, "{differ} of {} values differ", on.len());
    assert_no_validation_errors();
}
