//! Sinusoidal timestep embedding launcher (diffusers `get_timestep_embedding`).
use anyhow::{ensure, Result};

use super::{expect_shape, grid_1d, Recorder};
use crate::kernels::params::EmbParams;
use crate::kernels::KernelId as K;
use crate::tensor::{DType, Tensor};

/// Options of diffusers' `Timesteps` module (SD1.5: flip_sin_to_cos = true, downscale_freq_shift = 0).
#[derive(Clone, Copy, Debug)]
pub struct TimestepEmbedding {
    pub flip_sin_to_cos: bool,
    pub downscale_freq_shift: f32,
    pub max_period: f32,
    pub scale: f32,
}

impl Default for TimestepEmbedding {
    fn default() -> Self {
        Self {
            flip_sin_to_cos: true,
            downscale_freq_shift: 0.0,
            max_period: 10000.0,
            scale: 1.0,
        }
    }
}

/// t: (B) f32 -> out: (B, dim) f32
pub fn timestep_embedding(
    rec: &mut Recorder,
    t: &Tensor,
    opts: TimestepEmbedding,
    out: &Tensor,
) -> Result<()> {
    ensure!(
        t.dtype() == DType::F32 && out.dtype() == DType::F32,
        "timestep_embedding: t and out must be f32 (got {} and {})",
        t.dtype().name(),
        out.dtype().name()
    );
    ensure!(
        t.shape().len() == 1,
        "timestep_embedding: t must be (B), got {:?}",
        t.shape()
    );
    let s = out.shape();
    ensure!(
        s.len() == 2 && s[1] >= 2,
        "timestep_embedding: out must be (B, dim >= 2), got {s:?}"
    );
    expect_shape("timestep_embedding", "out", out, &[t.shape()[0], s[1]])?;
    ensure!(
        (s[1] / 2) as f32 - opts.downscale_freq_shift != 0.0,
        "timestep_embedding: dim {} with downscale_freq_shift {} divides by zero",
        s[1],
        opts.downscale_freq_shift
    );
    let p = EmbParams {
        b: s[0] as u32,
        dim: s[1] as u32,
        flip: opts.flip_sin_to_cos as u32,
        shift: opts.downscale_freq_shift,
        max_period: opts.max_period,
        scale: opts.scale,
    };
    rec.dispatch(
        K::EmbeddingTimestep,
        &[t.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        grid_1d("timestep_embedding", out.numel())?,
        "timestep_embedding",
    )
}
