//! Implicit GEMM on weights repacked to (KH, KW, C, O) (`kernels/conv2d_packed.wgsl`), for O % 4 == 0: vec4
//! weight rows, the (N, O) bias, residual and SiLU in its epilogue. Entry `hwnc` reads an input transposed to
//! (H, W, N, C) first (vec4 channel loads; C % 4 == 0), which pays only for wide f16 inputs
//! (`ConvPath::FastHwnc`).
use anyhow::{ensure, Result};

use super::{ensure_tiled, run_kernel, Conv2dArgs, ConvKernel, Geometry};
use crate::kernels::params::PackParams;
use crate::kernels::KernelId as K;
use crate::ops::matmul::tile_shape;
use crate::ops::{
    expect_shape, grid_1d, pick, same_dtype, Recorder, SCRATCH_PACKED_W, SCRATCH_X_HWNC,
};
use crate::tensor::{DType, Tensor};

/// w: (O, C, KH, KW) -> packed: (KH, KW, C, O), the weight layout of the fast conv kernel (conv2d_packed.wgsl).
pub fn pack_weight(rec: &mut Recorder, w: &Tensor, packed: &Tensor) -> Result<()> {
    let d = same_dtype("conv2d pack_weight", &[w, packed])?;
    let ws = w.shape();
    ensure!(
        ws.len() == 4,
        "conv2d pack_weight: w {ws:?} must be (O, C, KH, KW)"
    );
    expect_shape(
        "conv2d pack_weight",
        "packed",
        packed,
        &[ws[2], ws[3], ws[1], ws[0]],
    )?;
    let p = PackParams {
        o: ws[0] as u32,
        c: ws[1] as u32,
        kk: (ws[2] * ws[3]) as u32,
    };
    let g = grid_1d("conv2d pack_weight", w.numel())?;
    rec.dispatch(
        pack_kernel(d),
        &[w.buffer(), packed.buffer()],
        bytemuck::bytes_of(&p),
        g,
        "conv2d pack_weight",
    )
}

fn pack_kernel(d: DType) -> K {
    pick(d, K::Conv2dPackedF32Pack, K::Conv2dPackedF16Pack)
}

/// x: (N, C, H, W) * w: (O, C, KH, KW) -> out: (N, O, OH, OW) with everything of `a` (geometry `g`); `hwnc`:
/// through the (H, W, N, C) transpose of x (C % 4 == 0, checked by the selection).
pub(super) fn conv(rec: &mut Recorder, a: &Conv2dArgs, g: &Geometry, hwnc: bool) -> Result<()> {
    ensure_tiled(rec, "implicit-GEMM")?;
    let ([n, c, h, w], [o, _, kh, kw], [_, _, oh, ow]) = (g.x, g.w, g.out);
    let d = g.dtype;
    let tmp;
    let packed = match a.packed_w {
        Some(pw) => {
            expect_shape("conv2d", "packed_w", pw, &[kh, kw, c, o])?;
            ensure!(pw.dtype() == d, "conv2d: packed_w dtype differs from x");
            pw
        }
        None => {
            // repacked per call into the recording's shared scratch
            let b = rec.scratch(SCRATCH_PACKED_W, (kh * kw * c * o * d.size()) as u64)?;
            tmp = Tensor::on_buffer(b, &[kh, kw, c, o], d)?;
            pack_weight(rec, a.w, &tmp)?;
            &tmp
        }
    };
    let (rows, cols) = tile_shape(rec);
    let groups = [
        o.div_ceil(cols) as u32,
        (oh * ow).div_ceil(rows) as u32,
        n as u32,
    ];
    let xt;
    let k = if hwnc {
        // input transposed per call to (H, W, N, C) into the recording's shared scratch, so channels load as
        // vectors (entry `hwnc`)
        let b = rec.scratch(SCRATCH_X_HWNC, (h * w * n * c * d.size()) as u64)?;
        xt = Tensor::on_buffer(b, &[h, w, n, c], d)?;
        let pp = PackParams {
            o: (n * c) as u32,
            c: 1,
            kk: (h * w) as u32,
        };
        let pg = grid_1d("conv2d", a.x.numel())?;
        let pb = [a.x.buffer(), xt.buffer()];
        rec.dispatch(
            pack_kernel(d),
            &pb,
            bytemuck::bytes_of(&pp),
            pg,
            "conv2d x->hwnc",
        )?;
        ConvKernel {
            id: pick(d, K::Conv2dPackedF32Hwnc, K::Conv2dPackedF16Hwnc),
            x: xt.buffer(),
            w: packed.buffer(),
            groups,
            edges: kh * kw * (c.div_ceil(32) + 1) + kh,
            fused_epilogue: true,
        }
    } else {
        ConvKernel {
            id: pick(d, K::Conv2dPackedF32, K::Conv2dPackedF16),
            x: a.x.buffer(),
            w: packed.buffer(),
            groups,
            edges: kh * kw * (c.div_ceil(8) + 1) + kh,
            fused_epilogue: true,
        }
    };
    run_kernel(rec, a, g, k)
}
