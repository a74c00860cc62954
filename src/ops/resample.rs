//! Resampling launchers: nearest upsample to an explicit size, bicubic resize (PyTorch semantics).
use anyhow::{ensure, Result};

use super::{expect_shape, grid_1d, pick, same_dtype, Recorder};
use crate::kernels::params::ResampleParams;
use crate::kernels::KernelId;
use crate::kernels::KernelId as K;
use crate::tensor::Tensor;

fn resample(
    rec: &mut Recorder,
    op: &str,
    x: &Tensor,
    out: &Tensor,
    size: (usize, usize),
    ids: [KernelId; 2],
) -> Result<()> {
    let d = same_dtype(op, &[x, out])?;
    let s = x.shape();
    ensure!(s.len() == 4, "{op}: x must be (N, C, H, W), got {s:?}");
    ensure!(
        size.0 > 0 && size.1 > 0,
        "{op}: output size {size:?} must be positive"
    );
    expect_shape(op, "out", out, &[s[0], s[1], size.0, size.1])?;
    let p = ResampleParams {
        planes: (s[0] * s[1]) as u32,
        h: s[2] as u32,
        w: s[3] as u32,
        oh: size.0 as u32,
        ow: size.1 as u32,
        // f32 scale exactly as PyTorch computes it (input / output).
        sh: s[2] as f32 / size.0 as f32,
        sw: s[3] as f32 / size.1 as f32,
    };
    rec.dispatch(
        pick(d, ids[0], ids[1]),
        &[x.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        grid_1d(op, out.numel())?,
        op,
    )
}

/// x: (N, C, H, W) -> out: (N, C, OH, OW), nearest neighbour (F.interpolate mode="nearest", size=(OH, OW)).
pub fn upsample_nearest(
    rec: &mut Recorder,
    x: &Tensor,
    out: &Tensor,
    size: (usize, usize),
) -> Result<()> {
    resample(
        rec,
        "upsample_nearest",
        x,
        out,
        size,
        [K::ResampleF32Nearest, K::ResampleF16Nearest],
    )
}

/// x: (N, C, H, W) -> out: (N, C, OH, OW), bicubic (align_corners=False, A=-0.75, border-clamped taps).
pub fn resize_bicubic(
    rec: &mut Recorder,
    x: &Tensor,
    out: &Tensor,
    size: (usize, usize),
) -> Result<()> {
    resample(
        rec,
        "resize_bicubic",
        x,
        out,
        size,
        [K::ResampleF32Bicubic, K::ResampleF16Bicubic],
    )
}
