//! Implicit GEMM on PyTorch-layout weights (`kernels/conv2d.wgsl`): the register-tiled matmul's tile over
//! (output pixels, output channels), the input gathered per k step; for convs whose O is not a multiple of 4
//! (the packed kernel's vec4 weight rows need it).
use anyhow::Result;

use super::{ensure_tiled, run_kernel, Conv2dArgs, ConvKernel, Geometry};
use crate::kernels::KernelId as K;
use crate::ops::matmul::tile_shape;
use crate::ops::{pick, Recorder};

/// x: (N, C, H, W) * w: (O, C, KH, KW) -> out: (N, O, OH, OW) with everything of `a` (geometry `g`).
pub(super) fn conv(rec: &mut Recorder, a: &Conv2dArgs, g: &Geometry) -> Result<()> {
    ensure_tiled(rec, "implicit-GEMM")?;
    let ([n, c, _, _], [o, _, kh, kw], [_, _, oh, ow]) = (g.x, g.w, g.out);
    let (rows, cols) = tile_shape(rec);
    let k = ConvKernel {
        id: pick(g.dtype, K::Conv2dF32, K::Conv2dF16),
        x: a.x.buffer(),
        w: a.w.buffer(),
        groups: [
            (oh * ow).div_ceil(cols) as u32,
            o.div_ceil(rows) as u32,
            n as u32,
        ],
        edges: kh * kw * (c.div_ceil(8) + 1) + kh,
        fused_epilogue: false,
    };
    run_kernel(rec, a, g, k)
}
