//! Shared test helpers: a Vulkan context (validation layer on when installed), seeded inputs, error metrics.
#![allow(dead_code)]
use std::sync::OnceLock;

use b2dr::tensor::{DType, Tensor};
use b2dr::vk::{Context, ContextOptions, Recorder};
use rand::{Rng, SeedableRng};

static CTX: OnceLock<Option<Context>> = OnceLock::new();

/// The test context, or None (with a printed reason) when no Vulkan device exists.
pub fn ctx() -> Option<Context> {
    CTX.get_or_init(|| {
        match Context::new(&ContextOptions {
            validation: Some(true),
            ..Default::default()
        }) {
            Ok(c) => {
                eprintln!(
                    "test device: {} ({}), validation: {}",
                    c.info().name,
                    c.info().kind,
                    c.validation_enabled()
                );
                Some(c)
            }
            Err(e) => {
                eprintln!(
                    "SKIP: no Vulkan device ({e:#}); install mesa-vulkan-drivers for lavapipe"
                );
                None
            }
        }
    })
    .clone()
}

/// Fails the test if the validation layer reported any error so far.
pub fn assert_no_validation_errors() {
    let (n, msgs) = b2dr::vk::validation_errors();
    assert_eq!(n, 0, "Vulkan validation errors: {msgs:#?}");
}

/// Uniform values in [-scale, scale), seeded.
pub fn uniform(n: usize, scale: f32, seed: u64) -> Vec<f32> {
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| r.gen_range(-1.0f32..1.0) * scale).collect()
}

/// The values a tensor of `dtype` actually stores (f16 rounding), as f64 for the reference.
pub fn stored(v: &[f32], dtype: DType) -> Vec<f64> {
    match dtype {
        DType::F32 => v.iter().map(|&x| x as f64).collect(),
        DType::F16 => v.iter().map(|&x| half::f16::from_f32(x).to_f64()).collect(),
    }
}

pub fn upload(ctx: &Context, shape: &[usize], dtype: DType, v: &[f32]) -> Tensor {
    Tensor::from_f32(ctx, shape, dtype, v, "test-input").expect("upload")
}

pub fn empty(ctx: &Context, shape: &[usize], dtype: DType) -> Tensor {
    Tensor::empty(ctx, shape, dtype, "test-output").expect("alloc")
}

/// Records with `f`, submits, waits.
pub fn run(ctx: &Context, f: impl FnOnce(&mut Recorder) -> anyhow::Result<()>) {
    let mut rec = ctx.recorder().expect("recorder");
    f(&mut rec).expect("recording failed");
    rec.finish().expect("finish").submit_wait().expect("submit");
}

// Not every test binary uses it (each includes this module).
#[allow(unused_imports)]
pub use b2dr::ops::reference::nmse;

/// Threshold for an elementwise result stored in `dtype`: the spec's 1e-7 in f32; in f16 the output rounding
/// alone (unit roundoff 2^-11, nMSE up to 2.4e-7) exceeds that, so 1e-6 for f16 storage.
pub fn elementwise_tol(dtype: DType) -> f64 {
    match dtype {
        DType::F32 => 1e-7,
        DType::F16 => 1e-6,
    }
}

/// A camera delivered at `w x h` (intrinsic rescaled as the renderer's frames are), no pixels: what the protocol's
/// camera entry is computed from.
pub fn frame_without_pixels(
    cam: &b2dr::scene::camera::Camera,
    image_ego2global: glam::DMat4,
    w: u32,
    h: u32,
) -> b2dr::sim::sensors::CameraFrame {
    b2dr::sim::sensors::CameraFrame {
        camera: cam.name.clone(),
        width: w,
        height: h,
        rgb: std::sync::Arc::new(vec![]),
        intrinsic: cam.intrinsic_scaled(w, h),
        cam2ego: cam.cam2ego,
        ego2global: image_ego2global,
    }
}
