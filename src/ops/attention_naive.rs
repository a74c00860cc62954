//! Fallback attention launcher for small head dims (d <= 8, any value), see kernels/attention_naive.wgsl.
use anyhow::{ensure, Result};

use super::{expect_shape, grid_1d, pick, same_dtype, Recorder};
use crate::kernels::params::AttnNaiveParams;
use crate::kernels::KernelId as K;
use crate::tensor::Tensor;

/// lavapipe stops every loop of an invocation after 65535 back-edges in total; stay well below.
const LOOP_BUDGET: usize = 60_000;

/// q: (B, Lq, H*d), k, v: (B, Lk, H*d) -> out: (B, Lq, H*d); scale defaults to 1/sqrt(d). d <= 8.
pub fn attention_naive(
    rec: &mut Recorder,
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    out: &Tensor,
    heads: usize,
    scale: Option<f32>,
) -> Result<()> {
    let d = same_dtype("attention_naive", &[q, k, v, out])?;
    let (sq, sk) = (q.shape(), k.shape());
    ensure!(
        sq.len() == 3 && sk.len() == 3,
        "attention_naive: q {sq:?}, k {sk:?} must be (B, L, H*d)"
    );
    ensure!(
        sk[0] == sq[0] && sk[2] == sq[2],
        "attention_naive: k {sk:?} does not match q {sq:?}"
    );
    expect_shape("attention_naive", "v", v, sk)?;
    expect_shape("attention_naive", "out", out, sq)?;
    ensure!(
        heads >= 1 && sq[2] % heads == 0,
        "attention_naive: {heads} heads do not divide the width {}",
        sq[2]
    );
    let hd = sq[2] / heads;
    ensure!(
        hd <= 8,
        "attention_naive: head dim {hd} > 8 (use ops::attention)"
    );
    let trips = sk[1] * (2 * hd + 1) + 3 * hd;
    ensure!(
        trips < LOOP_BUDGET,
        "attention_naive: {} keys x head dim {hd} needs {trips} loop iterations per invocation, over lavapipe's budget",
        sk[1]
    );
    let p = AttnNaiveParams {
        b: sq[0] as u32,
        h: heads as u32,
        lq: sq[1] as u32,
        lk: sk[1] as u32,
        d: hd as u32,
        scale: scale.unwrap_or(1.0 / (hd as f32).sqrt()),
    };
    let kid = pick(d, K::AttentionNaiveF32, K::AttentionNaiveF16);
    let bufs = [q.buffer(), k.buffer(), v.buffer(), out.buffer()];
    rec.dispatch(
        kid,
        &bufs,
        bytemuck::bytes_of(&p),
        grid_1d("attention_naive", sq[0] * heads * sq[1])?,
        "attention_naive",
    )
}
