//! The direct conv (`kernels/conv2d_direct.wgsl`): one output per invocation, any shape and device. The
//! fallback where subgroups are missing, and the oracle the tests hold the fast paths to.
use anyhow::Result;

use super::{run_kernel, Conv2dArgs, ConvKernel, Geometry};
use crate::kernels::KernelId as K;
use crate::ops::{grid_1d, pick, Recorder};

/// x: (N, C, H, W) * w: (O, C, KH, KW) -> out: (N, O, OH, OW) with everything of `a` (geometry `g`).
pub(super) fn conv(rec: &mut Recorder, a: &Conv2dArgs, g: &Geometry) -> Result<()> {
    let ([n, c, _, _], [o, _, kh, kw], [_, _, oh, ow]) = (g.x, g.w, g.out);
    let k = ConvKernel {
        id: pick(g.dtype, K::Conv2dDirectF32, K::Conv2dDirectF16),
        x: a.x.buffer(),
        w: a.w.buffer(),
        groups: grid_1d("conv2d", n * o * oh * ow)?,
        edges: c * (kh * kw + kh + 1),
        fused_epilogue: false,
    };
    run_kernel(rec, a, g, k)
}
