//! Multi-head attention (self and cross), flash style: one fused kernel, online softmax, f32 accumulation,
//! f32 or f16 storage. Layout (what the UNet's q/k/v projections produce; diffusers' head split is implicit):
//!
//! - q: (B, Lq, H*d), k: (B, Lk, H*d), v: (B, Lk, H*d) -> out: (B, Lq, H*d), all row-major;
//! - head h owns the columns [h*d, (h+1)*d) of every token row;
//! - out[b, i, h*d + e] = sum_j softmax_j(scale * q[b, i, h*d..] . k[b, j, h*d..]) * v[b, j, h*d + e].
//!
//! Requirements: d = width / H with d % 4 == 0 (d % 8 == 0 when d > 160), any Lq, Lk >= 1, and Lk small
//! enough for lavapipe's loop budget (see [`loop_trips`]; about 5,900 keys at d = 160 and 16,000 at d = 512).
use anyhow::{ensure, Result};

use super::softmax::fold_groups;
use super::{same_dtype, Recorder};
use crate::kernels::params::AttnParams;
use crate::kernels::KernelId as K;
use crate::tensor::{DType, Tensor};

/// lavapipe stops all loops of an invocation after 65535 back-edges; stay well below.
pub const LOOP_BUDGET: usize = 60_000;

/// `main` variants by the head dim they hold in registers (the smallest that fits is used).
const VARIANTS: [(usize, K, K); 4] = [
    (8, K::AttentionF32D8, K::AttentionF16D8),
    (40, K::AttentionF32D40, K::AttentionF16D40),
    (80, K::AttentionF32D80, K::AttentionF16D80),
    (160, K::AttentionF32D160, K::AttentionF16D160),
];

/// The kernel chosen for head dim `d`: (kernel, columns per work group, whether it is the sliced `wide` entry).
fn choose(dtype: DType, d: usize) -> (K, usize, bool) {
    for (cols, f32_id, f16_id) in VARIANTS {
        if d <= cols {
            return (super::pick(dtype, f32_id, f16_id), cols, false);
        }
    }
    let wide = super::pick(dtype, K::AttentionF32D160Wide, K::AttentionF16D160Wide);
    (wide, 160, true)
}

/// Upper bound of loop back-edges one invocation runs (counting the constant-trip chunk loops as loops, in case
/// the driver does not unroll them).
pub fn loop_trips(lk: usize, d: usize) -> usize {
    let (_, cols, wide) = choose(DType::F32, d);
    let d4 = cols / 4;
    let tiles = lk.div_ceil(8);
    if wide {
        tiles * (d / 8 + d4 + 1) + 2 * d4
    } else {
        tiles * (2 * d4 + 1) + 2 * d4
    }
}

/// Multi-head attention, see the module docs for the layout. `scale` defaults to 1/sqrt(d).
pub fn attention(
    rec: &mut Recorder,
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    out: &Tensor,
    heads: usize,
    scale: Option<f32>,
) -> Result<()> {
    let (sq, sk, sv, so) = (q.shape(), k.shape(), v.shape(), out.shape());
    let shapes = format!("q {sq:?}, k {sk:?}, v {sv:?}, out {so:?}, heads {heads}");
    let dtype =
        same_dtype("attention", &[q, k, v, out]).map_err(|e| anyhow::anyhow!("{e} ({shapes})"))?;
    ensure!(
        sq.len() == 3 && sk.len() == 3 && sv.len() == 3,
        "attention: q, k, v must be (B, L, H*d): {shapes}"
    );
    let (b, lq, w) = (sq[0], sq[1], sq[2]);
    let lk = sk[1];
    ensure!(
        sk[0] == b && sk[2] == w && sv == sk,
        "attention: k and v must be (B, Lk, H*d) matching q: {shapes}"
    );
    ensure!(so == sq, "attention: out must have q's shape: {shapes}");
    ensure!(
        heads >= 1 && w % heads == 0,
        "attention: {heads} heads do not divide the width {w}: {shapes}"
    );
    let d = w / heads;
    let (kernel, cols, wide) = choose(dtype, d);
    ensure!(
        d % 4 == 0 && (!wide || d % 8 == 0),
        "attention: head dim {d} must be a multiple of 4 (of 8 above 160): {shapes}"
    );
    let trips = loop_trips(lk, d);
    ensure!(
        trips <= LOOP_BUDGET,
        "attention: Lk = {lk} at head dim {d} needs {trips} loop trips per invocation, over lavapipe's \
         budget of {LOOP_BUDGET}: split the keys ({shapes})"
    );
    let qblocks = lq.div_ceil(8);
    let slices = if wide { d.div_ceil(cols) } else { 1 };
    let groups = b * heads * qblocks * slices;
    let p = AttnParams {
        lq: lq as u32,
        lk: lk as u32,
        heads: heads as u32,
        nc: (d / 4) as u32,
        w4: (w / 4) as u32,
        qblocks: qblocks as u32,
        slices: slices as u32,
        groups: groups as u32,
        scale: scale.unwrap_or(1.0 / (d as f32).sqrt()),
    };
    rec.dispatch(
        kernel,
        &[q.buffer(), k.buffer(), v.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        fold_groups("attention", groups)?,
        "attention",
    )
}
