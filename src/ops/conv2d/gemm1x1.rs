//! 1x1 stride-1 unpadded convs with a per-channel bias as GEMMs: (O, C) x (C, H W) per image -> (O, H W),
//! the weight shared over the batch (`matmul::gemm`, bias and residual in its epilogue).
use anyhow::Result;

use super::{Conv2dArgs, Geometry};
use crate::ops::matmul::{gemm, Gemm, GemmBias, MatmulPath};
use crate::ops::Recorder;

/// x: (N, C, H, W) * w: (O, C, 1, 1) -> out: (N, O, H, W) with everything of `a` (geometry `g`).
pub(super) fn conv(rec: &mut Recorder, a: &Conv2dArgs, g: &Geometry) -> Result<()> {
    let ([n, c, _, _], o, np) = (g.x, g.w[0], g.out[2] * g.out[3]);
    let gm = Gemm {
        m: o,
        n: np,
        k: c,
        batch: n,
        sa: 0,
        sb: c * np,
        trans_b: false,
        bias: GemmBias::per_row(a.bias.is_some()),
        res: a.residual.is_some(),
        dtype: g.dtype,
        path: MatmulPath::Tiled,
    };
    let bufs = [
        a.w.buffer(),
        a.x.buffer(),
        a.bias.unwrap_or(a.x).buffer(),
        a.out.buffer(),
        a.residual.unwrap_or(a.out).buffer(),
    ];
    gemm(rec, "conv2d(1x1 as gemm)", &gm, bufs, None)?;
    if a.silu {
        crate::ops::elementwise::silu(rec, a.out, a.out)?;
    }
    Ok(())
}
