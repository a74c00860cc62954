//! Winograd F(4x4, 3x3) for stride-1 3x3 convs (`kernels/winograd.wgsl`): input transform, 36 batched GEMMs on
//! the tiled matmul, output transform (+ bias). 4x fewer multiply-adds than the implicit GEMM; the transformed
//! tensors are f32 in every mode. Tiles are processed in slabs so the two intermediates stay small (they live
//! in the recorder's scratch buffers, shared by all convs of a recording).
use anyhow::{ensure, Result};

use super::matmul::{gemm, Gemm, MatmulPath};
use super::{expect_shape, Recorder, SCRATCH_WINO_M, SCRATCH_WINO_V};
use crate::kernels::params::WinoParams;
use crate::kernels::KernelId as K;
use crate::tensor::{DType, Tensor};

/// Bytes of each intermediate (V or M) per slab at most.
const SLAB_BYTES: usize = 16 << 20;

/// (input, input4, input4s, output, output4, weight) kernels; `gs`: the inputs with the GroupNorm + SiLU
/// prologue.
fn ids(d: DType, gs: bool) -> [K; 6] {
    match (d, gs) {
        (DType::F32, true) => [
            K::WinogradF32InputGs,
            K::WinogradF32Input4Gs,
            K::WinogradF32Input4sGs,
            K::WinogradF32Output,
            K::WinogradF32Output4,
            K::WinogradF32Weight,
        ],
        (DType::F16, true) => [
            K::WinogradF16InputGs,
            K::WinogradF16Input4Gs,
            K::WinogradF16Input4sGs,
            K::WinogradF16Output,
            K::WinogradF16Output4,
            K::WinogradF16Weight,
        ],
        (DType::F32, false) => [
            K::WinogradF32Input,
            K::WinogradF32Input4,
            K::WinogradF32Input4s,
            K::WinogradF32Output,
            K::WinogradF32Output4,
            K::WinogradF32Weight,
        ],
        (DType::F16, false) => [
            K::WinogradF16Input,
            K::WinogradF16Input4,
            K::WinogradF16Input4s,
            K::WinogradF16Output,
            K::WinogradF16Output4,
            K::WinogradF16Weight,
        ],
    }
}

/// Shape of the transformed weight of w: (O, C, 3, 3): (36, C, O), always f32.
pub fn weight_shape(w: &[usize]) -> [usize; 3] {
    [36, w[1], w[0]]
}

/// w: (O, C, 3, 3) -> u: (36, C, O) f32 = G g G^T per (o, c).
pub fn transform_weight(rec: &mut Recorder, w: &Tensor, u: &Tensor) -> Result<()> {
    let ws = w.shape();
    ensure!(
        ws.len() == 4 && ws[2] == 3 && ws[3] == 3,
        "conv2d winograd: w {ws:?} must be (O, C, 3, 3)"
    );
    ensure!(
        u.dtype() == DType::F32,
        "conv2d winograd: the transformed weight must be f32"
    );
    expect_shape("conv2d winograd", "u", u, &weight_shape(ws))?;
    let p = WinoParams {
        o: ws[0] as u32,
        c: ws[1] as u32,
        ..Default::default()
    };
    let g = super::grid_1d("conv2d winograd weight", ws[0] * ws[1])?;
    rec.dispatch(
        ids(w.dtype(), false)[5],
        &[w.buffer(), u.buffer()],
        bytemuck::bytes_of(&p),
        g,
        "conv2d winograd weight",
    )
}

/// out = conv3x3(x, w) (+ bias (O) or (N, O)) (+ residual) (then SiLU), stride 1, padding (top, bottom, left,
/// right) each <= 2, with u the transformed weight ([`transform_weight`]); everything but `w` from `a`. Shapes
/// were checked by the caller (`conv2d_ex`).
pub(crate) fn conv3x3(rec: &mut Recorder, a: &super::conv2d::Conv2dArgs, u: &Tensor) -> Result<()> {
    let (x, bias, residual, silu, out, pad) = (a.x, a.bias, a.residual, a.silu, a.out, a.pad);
    let (xs, os) = (x.shape(), out.shape());
    // the conv's input size (twice the stored one when x is read through a 2x upsampling)
    let up = a.upsample2x as usize;
    let [n, c, h, w] = [xs[0], xs[1], xs[2] << up, xs[3] << up];
    let (o, oh, ow) = (os[1], os[2], os[3]);
    expect_shape("conv2d winograd", "u", u, &[36, c, o])?;
    let (th, tw) = (oh.div_ceil(4), ow.div_ceil(4));
    let tiles = n * th * tw;
    let per_tile = 36 * c.max(o) * 4;
    let slab = (SLAB_BYTES / per_tile).clamp(1, tiles);
    let [inp1, inp4, inp4s, outp1, outp4, _] = ids(x.dtype(), a.pre_gn_silu.is_some());
    // the prologue's statistics (binding 2 of every input entry; x when there is no prologue)
    let ss = a.pre_gn_silu.unwrap_or(x);
    // vec4 transforms (4 channels per invocation: fewer per-lane access loops on lavapipe) where the layout
    // allows: input C % 4 == 0 (rows loaded as vec4s too when W % 4 == 0 and the left padding is 1); output
    // O % 4 == 0, OW % 4 == 0
    let in4 = c % 4 == 0 && w % 4 == 0 && pad[2] == 1 && !a.upsample2x;
    let out4 = o % 4 == 0 && ow % 4 == 0;
    let (inp, in_items) = if in4 {
        (inp4, c / 4)
    } else if c % 4 == 0 {
        (inp4s, c / 4)
    } else {
        (inp1, c)
    };
    let (outp, out_items) = if out4 { (outp4, o / 4) } else { (outp1, o) };
    let vb = rec.scratch(SCRATCH_WINO_V, (36 * slab * c * 4) as u64)?;
    let mb = rec.scratch(SCRATCH_WINO_M, (36 * slab * o * 4) as u64)?;
    let bias_t = bias.unwrap_or(x);
    let has_bias = match bias {
        Some(b) if b.shape().len() == 2 => 2,
        Some(_) => 1,
        None => 0,
    };
    let res_t = residual.unwrap_or(out);
    let mut t0 = 0;
    while t0 < tiles {
        let nt = slab.min(tiles - t0);
        let p = WinoParams {
            n: n as u32,
            c: c as u32,
            h: h as u32,
            w: w as u32,
            o: o as u32,
            oh: oh as u32,
            ow: ow as u32,
            th: th as u32,
            tw: tw as u32,
            pt: pad[0] as u32,
            pl: pad[2] as u32,
            t0: t0 as u32,
            nt: nt as u32,
            has_bias,
            has_res: residual.is_some() as u32,
            silu: silu as u32,
            up: up as u32,
        };
        let g = super::grid_1d("conv2d winograd", nt * in_items)?;
        // input4 also reads x through a scalar view (binding 3)
        let in_bufs: &[&std::sync::Arc<crate::vk::Buffer>] = if in4 {
            &[x.buffer(), &vb, ss.buffer(), x.buffer()]
        } else {
            &[x.buffer(), &vb, ss.buffer()]
        };
        rec.dispatch(
            inp,
            in_bufs,
            bytemuck::bytes_of(&p),
            g,
            "conv2d winograd in",
        )?;
        // 36 GEMMs: (nt, C) . (C, O) -> (nt, O)
        let gm = Gemm {
            m: nt,
            n: o,
            k: c,
            batch: 36,
            sa: nt * c,
            sb: c * o,
            trans_b: false,
            bias_mode: 0,
            res: false,
            dtype: DType::F32,
            path: MatmulPath::Tiled,
        };
        gemm(
            rec,
            "conv2d winograd gemm",
            &gm,
            [&vb, u.buffer(), &vb, &mb, &mb],
            None,
        )?;
        let g = super::grid_1d("conv2d winograd", nt * out_items)?;
        let bufs = [&mb, bias_t.buffer(), out.buffer(), res_t.buffer()];
        rec.dispatch(
            outp,
            &bufs,
            bytemuck::bytes_of(&p),
            g,
            "conv2d winograd out",
        )?;
        t0 += nt;
    }
    Ok(())
}
