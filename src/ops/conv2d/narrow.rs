//! The few-output-channel 3x3 stride-1 conv (`kernels/conv3x3_narrow.wgsl`, O <= 4): eight output pixels of
//! every output channel per invocation, bias, residual, SiLU and a GroupNorm + SiLU prologue fused. On CPU
//! devices the implicit GEMM's 16-row register tile idles most rows at such O (the VAE decoder's conv_out).
use anyhow::Result;

use super::{BiasMode, Conv2dArgs, Geometry};
use crate::kernels::params::NarrowParams;
use crate::kernels::KernelId as K;
use crate::ops::{grid_1d, pick, Recorder};

/// x: (N, C, H, W) * w: (O, C, 3, 3) -> out: (N, O, H', W') with everything of `a` but the upsampling
/// (resolved by the caller; geometry `g`).
pub(super) fn conv3x3(rec: &mut Recorder, a: &Conv2dArgs, g: &Geometry) -> Result<()> {
    let (xs, os) = (g.x, g.out);
    let p = NarrowParams {
        n: xs[0] as u32,
        c: xs[1] as u32,
        h: xs[2] as u32,
        w: xs[3] as u32,
        o: os[1] as u32,
        oh: os[2] as u32,
        ow: os[3] as u32,
        pt: a.pad[0] as u32,
        pl: a.pad[2] as u32,
        has_bias: BiasMode::of(a.bias).code(),
        has_res: a.residual.is_some() as u32,
        silu: a.silu as u32,
        pre: a.pre_gn_silu.is_some() as u32,
        rows4: (xs[3] % 4 == 0 && a.pad[2] == 1) as u32,
    };
    let bufs = [
        a.x.buffer(),
        a.w.buffer(),
        a.bias.unwrap_or(a.x).buffer(),
        a.out.buffer(),
        a.residual.unwrap_or(a.out).buffer(),
        a.pre_gn_silu.unwrap_or(a.x).buffer(),
        a.x.buffer(),
    ];
    let grid = grid_1d("conv2d narrow", os[0] * os[2] * os[3].div_ceil(8))?;
    let label = format!(
        "conv2d narrow {}x{}x{}x{} -> {}",
        xs[0], xs[1], xs[2], xs[3], os[1]
    );
    let id = pick(g.dtype, K::Conv3x3NarrowF32, K::Conv3x3NarrowF16);
    rec.dispatch(id, &bufs, bytemuck::bytes_of(&p), grid, &label)
}
