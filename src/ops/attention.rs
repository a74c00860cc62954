//! Multi-head attention (self and cross), flash style: one fused kernel, online softmax, f32 accumulation,
//! f32 or f16 storage. Layout (what the UNet's q/k/v projections produce; diffusers' head split is implicit):
//!
//! - q: (B, Lq, H*d), k: (B, Lk, H*d), v: (B, Lk, H*d) -> out: (B, Lq, H*d), all row-major;
//! - head h owns the columns [h*d, (h+1)*d) of every token row;
//! - out[b, i, h*d + e] = sum_j softmax_j(scale * q[b, i, h*d..] . k[b, j, h*d..]) * v[b, j, h*d + e].
//!
//! Requirements: d = width / H with d % 4 == 0 (d % 8 == 0 when d > 160), any Lq, Lk >= 1, and Lk small
//! enough for lavapipe's loop budget (see [`loop_trips`]: about 480,000 keys for d <= 80, 5,900 at d = 160 and
//! 7,300 at d = 512 (the VAE at 224 x 400 has 1,400)).
use anyhow::{ensure, Result};

use super::matmul::{matmul, matmul_ex, tiled_supported, MatmulArgs};
use super::softmax::{fold_groups, softmax_scaled};
use super::{same_dtype, Recorder, SCRATCH_ATTN_P, SCRATCH_ATTN_S};
use crate::kernels::params::AttnParams;
use crate::kernels::KernelId as K;
use crate::kernels::{lookup, Variant};
use crate::tensor::{DType, Tensor};

/// lavapipe stops all loops of an invocation after 65535 back-edges; stay well below.
pub const LOOP_BUDGET: usize = 60_000;

/// One compiled attention kernel: the head dims it takes, query rows per lane, whether it is the sliced entry.
#[derive(Clone, Copy, Debug)]
pub struct AttnKernel {
    pub id: K,
    pub dtype: DType,
    /// Head dim held in registers (`main`: d <= cols) or per output slice (`wide`: any d % 8 == 0).
    pub cols: usize,
    /// Query rows per invocation (R in the kernel).
    pub rows: usize,
    pub wide: bool,
    /// k and v read as packed pairs of f16 chunks (needs d % 8 == 0).
    pub packed: bool,
}

/// The kernel of these axes (`kernels/attention.wgsl`, entry `wide` or `main`); a variant that is not compiled
/// fails the build (the lookup runs in const context).
const fn kern(dtype: DType, cols: usize, rows: usize, wide: bool, packed: bool) -> AttnKernel {
    let entry = if wide {
        lookup::AttentionEntry::Wide
    } else {
        lookup::AttentionEntry::Main
    };
    let v = Variant {
        dtype: Some(dtype),
        packed_f16: packed,
        cols: cols as u32,
        rows: rows as u32,
        ..Variant::NONE
    };
    let Some(id) = lookup::attention(entry, v) else {
        panic!(
            "attention: a kernel of KERNELS is not compiled (kernels/attention.wgsl variant lines)"
        )
    };
    AttnKernel {
        id,
        dtype,
        cols,
        rows,
        wide,
        packed,
    }
}

/// All attention kernels, in order of preference for a given head dim (the first that fits is the default):
/// (dtype, cols, rows, wide, packed) axes, the ids from the generated lookup.
pub const KERNELS: &[AttnKernel] = &[
    kern(DType::F32, 8, 8, false, false),
    kern(DType::F32, 8, 4, false, false),
    kern(DType::F32, 8, 1, false, false),
    kern(DType::F32, 16, 4, false, false),
    kern(DType::F32, 32, 4, false, false),
    kern(DType::F32, 40, 4, false, false),
    kern(DType::F32, 40, 2, false, false),
    kern(DType::F32, 40, 1, false, false),
    kern(DType::F32, 80, 2, false, false),
    kern(DType::F32, 80, 1, false, false),
    kern(DType::F32, 160, 1, false, false),
    kern(DType::F32, 128, 1, true, false),
    kern(DType::F16, 8, 4, false, true),
    kern(DType::F16, 16, 4, false, true),
    kern(DType::F16, 32, 4, false, true),
    kern(DType::F16, 40, 2, false, true),
    kern(DType::F16, 40, 4, false, true),
    kern(DType::F16, 80, 2, false, true),
    kern(DType::F16, 8, 4, false, false),
    kern(DType::F16, 8, 1, false, false),
    kern(DType::F16, 16, 4, false, false),
    kern(DType::F16, 32, 4, false, false),
    kern(DType::F16, 40, 4, false, false),
    kern(DType::F16, 40, 2, false, false),
    kern(DType::F16, 40, 1, false, false),
    kern(DType::F16, 80, 2, false, false),
    kern(DType::F16, 80, 1, false, false),
    kern(DType::F16, 160, 1, false, false),
    kern(DType::F16, 128, 1, true, false),
];

impl AttnKernel {
    /// Whether this kernel computes head dim `d`.
    pub fn fits(&self, d: usize) -> bool {
        if self.wide {
            d % 8 == 0
        } else {
            d <= self.cols && (!self.packed || d % 8 == 0)
        }
    }

    /// Upper bound of loop back-edges one invocation runs for `lk` keys at head dim `d`. lavapipe's NIR
    /// unrolls constant-trip loops of up to 32 trips (llvmpipe's max_unroll_iterations), so the chunk and row
    /// loops of `main` vanish for D4 <= 32 and only the key loop counts; D4 = 40 keeps its chunk loops. The
    /// test `long_keys_440000_h1_d40` runs a shape near the budget and would catch a loop that stayed a loop.
    pub fn loop_trips(&self, lk: usize, d: usize) -> usize {
        let d4 = self.cols / 4;
        let tiles = lk.div_ceil(8);
        if self.wide {
            // q.k: a runtime loop of nc / 2 trips; values: D4 chunk trips unless unrolled; plus the key loop.
            let values = if d4 <= MAX_UNROLL { 0 } else { d4 };
            tiles * (d / 8 + values + 1) + 2 * d4
        } else if d4 <= MAX_UNROLL {
            tiles + 1
        } else {
            self.rows * (tiles * (2 * d4 + 1) + 2 * d4)
        }
    }
}

/// Constant-trip loops up to this length are unrolled by lavapipe's NIR (verified by the long-keys test).
const MAX_UNROLL: usize = 32;

/// The default kernel for `dtype` and head dim `d`.
pub fn choose(dtype: DType, d: usize) -> AttnKernel {
    *KERNELS
        .iter()
        .find(|k| k.dtype == dtype && k.fits(d))
        .expect("the wide kernels take every d % 8 == 0; others are rejected before")
}

/// Loop bound of the default kernel (see [`AttnKernel::loop_trips`]).
pub fn loop_trips(lk: usize, d: usize) -> usize {
    choose(DType::F32, d).loop_trips(lk, d)
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
    attention_with(rec, q, k, v, out, heads, scale, None)
}

/// [`attention`] with an explicit kernel from [`KERNELS`] (benchmarks and tests compare them).
#[allow(clippy::too_many_arguments)]
pub fn attention_with(
    rec: &mut Recorder,
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    out: &Tensor,
    heads: usize,
    scale: Option<f32>,
    kernel: Option<AttnKernel>,
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
    ensure!(
        d % 4 == 0 && (d <= 160 || d % 8 == 0),
        "attention: head dim {d} must be a multiple of 4 (of 8 above 160): {shapes}"
    );
    if kernel.is_none() && gemm_pays(rec, dtype, b, heads, lq, lk, d) {
        return attention_gemm(rec, q, k, v, out, scale);
    }
    let kn = kernel.unwrap_or_else(|| choose(dtype, d));
    ensure!(
        kn.dtype == dtype && kn.fits(d),
        "attention: kernel {:?} does not take {} head dim {d}: {shapes}",
        kn.id,
        dtype.name()
    );
    let trips = kn.loop_trips(lk, d);
    ensure!(
        trips <= LOOP_BUDGET,
        "attention: Lk = {lk} at head dim {d} needs {trips} loop trips per invocation, over lavapipe's \
         budget of {LOOP_BUDGET}: split the keys ({shapes})"
    );
    let qblocks = lq.div_ceil(8 * kn.rows);
    let slices = if kn.wide { d.div_ceil(kn.cols) } else { 1 };
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
        // log2(e) folded in: the kernel's softmax uses exp2 (attention.wgsl `online_step`)
        scale: scale.unwrap_or(1.0 / (d as f32).sqrt()) * std::f32::consts::LOG2_E,
    };
    // k and v through their texel views where the device has them
    let id =
        super::texel_variant(rec, kn.id, &[q.buffer(), k.buffer(), v.buffer()]).unwrap_or(kn.id);
    rec.dispatch(
        id,
        &[q.buffer(), k.buffer(), v.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        fold_groups("attention", groups)?,
        &format!("attention {b}x{heads}x{lq}x{lk}x{d}"),
    )
}

/// Largest score matrix (B Lq Lk f32, bytes) [`attention`] materialises for the single-head GEMM form.
pub const GEMM_SCORES_MAX_BYTES: usize = 64 << 20;

/// Whether [`attention`] runs the single-head GEMM form ([`attention_gemm`]): f32 on CPU devices with subgroups
/// for the tiled GEMM, one head of d >= 64, >= 256 queries, scores within [`GEMM_SCORES_MAX_BYTES`]. There
/// the fused kernel keeps a wide head's output in per-lane registers (the VAE's d = 128 at 28 x 50: ~55 ms on
/// lavapipe), while the two GEMMs and the softmax take ~30 ms.
pub fn gemm_pays(
    rec: &Recorder,
    dtype: DType,
    b: usize,
    heads: usize,
    lq: usize,
    lk: usize,
    d: usize,
) -> bool {
    rec.context().info().is_cpu()
        && tiled_supported(rec)
        && dtype == DType::F32
        && heads == 1
        && d >= 64
        && lq >= 256
        && b * lq * lk * 4 <= GEMM_SCORES_MAX_BYTES
}

/// Single-head attention as S = q k^T, P = softmax(scale S) row-wise, out = P v; q: (B, Lq, d), k, v:
/// (B, Lk, d), out: (B, Lq, d). The scores live in the recording's scratch (B Lq Lk values twice): meant for
/// moderate Lq Lk (see [`gemm_pays`]). Storage dtype as the inputs (f32 scores overflow nothing; f16 scores
/// could, so models run this in f32 only).
pub fn attention_gemm(
    rec: &mut Recorder,
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    out: &Tensor,
    scale: Option<f32>,
) -> Result<()> {
    let dtype = same_dtype("attention gemm", &[q, k, v, out])?;
    let (sq, sk) = (q.shape(), k.shape());
    ensure!(
        sq.len() == 3 && sk.len() == 3 && v.shape() == sk && out.shape() == sq && sk[0] == sq[0] && sk[2] == sq[2],
        "attention gemm: q {sq:?}, k {sk:?}, v {:?}, out {:?} must be (B, Lq, d), (B, Lk, d), (B, Lk, d), (B, Lq, d)",
        v.shape(),
        out.shape()
    );
    let (b, lq, lk, d) = (sq[0], sq[1], sk[1], sq[2]);
    let bytes = (b * lq * lk * dtype.size()) as u64;
    let s = Tensor::on_buffer(rec.scratch(SCRATCH_ATTN_S, bytes)?, &[b, lq, lk], dtype)?;
    let pm = Tensor::on_buffer(rec.scratch(SCRATCH_ATTN_P, bytes)?, &[b, lq, lk], dtype)?;
    matmul_ex(
        rec,
        &MatmulArgs {
            transpose_b: true,
            ..MatmulArgs::new(q, k, &s)
        },
    )?;
    softmax_scaled(rec, &s, scale.unwrap_or(1.0 / (d as f32).sqrt()), &pm)?;
    matmul(rec, &pm, v, None, out)
}
