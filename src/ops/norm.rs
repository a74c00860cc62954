//! Normalisation launchers: group norm (optionally fused SiLU) and layer norm.
use anyhow::{ensure, Result};

use super::{expect_shape, pick, same_dtype, Recorder};
use crate::kernels::params::NormParams;
use crate::kernels::KernelId as K;
use crate::tensor::Tensor;

/// Group-norm segments (channels per group x H W) up to this length run in work groups of 64 instead of 256
/// (b2dr-tiny guided step, 73 group norms mostly at 7 x 13 .. 28 x 50: 40 -> 18 ms on lavapipe).
const SMALL_SEGMENT: u32 = 8192;

/// Segment length of a group norm of x (N, C, H, W) with `groups` groups.
fn cpg_len(s: &[usize], groups: usize) -> usize {
    s[1] / groups * s[2] * s[3]
}

#[allow(clippy::too_many_arguments)]
fn norm(
    rec: &mut Recorder,
    op: &str,
    x: &Tensor,
    gamma: &Tensor,
    beta: &Tensor,
    out: &Tensor,
    segs: usize,
    p: NormParams,
) -> Result<()> {
    let d = same_dtype(op, &[x, gamma, beta, out])?;
    expect_shape(op, "out", out, x.shape())?;
    ensure!(
        p.eps.is_finite() && p.eps >= 0.0,
        "{op}: eps {} must be finite and >= 0",
        p.eps
    );
    let gx = segs.min(65535);
    let grid = [gx as u32, segs.div_ceil(gx) as u32, 1];
    ensure!(
        segs.div_ceil(gx) <= 65535,
        "{op}: {segs} segments is too many"
    );
    ensure!(
        segs % gx == 0 || grid[1] == 1,
        "{op}: {segs} segments cannot be tiled over the grid"
    );
    // vec4 statistics (one Welford pass) for group norms whose segments are whole vec4s; the normalise pass is
    // vec4 too when H W % 4 == 0
    let b = [x.buffer(), gamma.buffer(), beta.buffer(), out.buffer()];
    // (gn4 merges statistics through subgroup operations: devices without them run `main`)
    if p.inner > 1 && p.len % 4 == 0 && rec.context().supports(K::NormF32Gn4) {
        // `gn4` also binds x and out a second time (scalar views, bindings 4 and 5): naga refuses two views of
        // one binding in one entry point
        // small segments run in work groups of 64 (`gn4_64`)
        let k = if p.len <= SMALL_SEGMENT {
            pick(d, K::NormF32Gn464, K::NormF16Gn464)
        } else {
            pick(d, K::NormF32Gn4, K::NormF16Gn4)
        };
        let b6 = [b[0], b[1], b[2], b[3], b[0], b[3]];
        rec.dispatch(k, &b6, bytemuck::bytes_of(&p), grid, op)
    } else {
        let k = pick(d, K::NormF32, K::NormF16);
        rec.dispatch(k, &b, bytemuck::bytes_of(&p), grid, op)
    }
}

#[allow(clippy::too_many_arguments)] // mirrors torch's group_norm signature plus the fused SiLU and out
/// x: (N, C, H, W), gamma/beta: (C) -> out: (N, C, H, W); PyTorch GroupNorm (biased variance), then SiLU if
/// `silu`.
pub fn group_norm(
    rec: &mut Recorder,
    x: &Tensor,
    groups: usize,
    gamma: &Tensor,
    beta: &Tensor,
    eps: f32,
    silu: bool,
    out: &Tensor,
) -> Result<()> {
    group_norm_impl(rec, x, groups, gamma, beta, eps, silu, out, false)
}

#[allow(clippy::too_many_arguments)] // as group_norm
/// [`group_norm`] writing its output as tokens: out (N, H W, C), the layout a transformer block reads (saves
/// the transpose after the norm).
pub fn group_norm_tokens(
    rec: &mut Recorder,
    x: &Tensor,
    groups: usize,
    gamma: &Tensor,
    beta: &Tensor,
    eps: f32,
    silu: bool,
    out: &Tensor,
) -> Result<()> {
    group_norm_impl(rec, x, groups, gamma, beta, eps, silu, out, true)
}

#[allow(clippy::too_many_arguments)]
fn group_norm_impl(
    rec: &mut Recorder,
    x: &Tensor,
    groups: usize,
    gamma: &Tensor,
    beta: &Tensor,
    eps: f32,
    silu: bool,
    out: &Tensor,
    tokens: bool,
) -> Result<()> {
    let s = x.shape();
    ensure!(
        s.len() == 4,
        "group_norm: x must be (N, C, H, W), got {s:?}"
    );
    ensure!(
        groups > 0 && s[1] % groups == 0,
        "group_norm: {groups} groups do not divide {} channels of {s:?}",
        s[1]
    );
    expect_shape("group_norm", "gamma", gamma, &[s[1]])?;
    expect_shape("group_norm", "beta", beta, &[s[1]])?;
    let cpg = s[1] / groups;
    let hw = s[2] * s[3];
    let out = if tokens {
        expect_shape("group_norm (tokens)", "out", out, &[s[0], hw, s[1]])?;
        out.reshape(s)?
    } else {
        out.clone()
    };
    let p = NormParams {
        len: (cpg * hw) as u32,
        segs_per_item: groups as u32,
        ch_per_seg: cpg as u32,
        inner: hw as u32,
        eps,
        silu: silu as u32,
        tokens: tokens as u32,
    };
    norm(rec, "group_norm", x, gamma, beta, &out, s[0] * groups, p)
}

/// x: (.., D), gamma/beta: (D) -> out: (.., D); PyTorch LayerNorm over the last dimension.
/// With subgroups: one subgroup per row and no barriers (kernel `layer_norm_sg`); else a work group per row.
pub fn layer_norm(
    rec: &mut Recorder,
    x: &Tensor,
    gamma: &Tensor,
    beta: &Tensor,
    eps: f32,
    out: &Tensor,
) -> Result<()> {
    let s = x.shape();
    let d = *s.last().unwrap_or(&0);
    expect_shape("layer_norm", "gamma", gamma, &[d])?;
    expect_shape("layer_norm", "beta", beta, &[d])?;
    let rows = x.numel() / d;
    let dt = same_dtype("layer_norm", &[x, gamma, beta, out])?;
    let sg = rec.context().info().subgroup_size as usize;
    let k = pick(dt, K::NormF32LayerNormSg, K::NormF16LayerNormSg);
    if rec.context().supports(k) && (1..=64).contains(&sg) && 64 % sg == 0 {
        expect_shape("layer_norm", "out", out, s)?;
        ensure!(
            eps.is_finite() && eps >= 0.0,
            "layer_norm: eps {eps} must be finite and >= 0"
        );
        let p = NormParams {
            len: d as u32,
            segs_per_item: 1,
            ch_per_seg: rows as u32,
            inner: 1,
            eps,
            silu: 0,
            tokens: 0,
        };
        let groups = rows.div_ceil(64 / sg);
        let gx = groups.min(65535);
        let grid = [gx as u32, groups.div_ceil(gx) as u32, 1];
        // vec4 accesses when the row is a whole number of vec4s
        let k = if d % 4 == 0 {
            pick(dt, K::NormF32LayerNormSg4, K::NormF16LayerNormSg4)
        } else {
            k
        };
        return rec.dispatch(
            k,
            &[x.buffer(), gamma.buffer(), beta.buffer(), out.buffer()],
            bytemuck::bytes_of(&p),
            grid,
            "layer_norm",
        );
    }
    let p = NormParams {
        len: d as u32,
        segs_per_item: 1,
        ch_per_seg: d as u32,
        inner: 1,
        eps,
        silu: 0,
        tokens: 0,
    };
    norm(rec, "layer_norm", x, gamma, beta, out, rows, p)
}

/// GroupNorm statistics as a per-(image, channel) prologue for a following conv: x (N, C, H, W) -> out (N, C, 4)
/// f32 = (scale, shift, x0, 0) per (n, c), such that group_norm(x) = (x - x0) scale + shift (x0 the group's
/// first element; see kernels/norm.wgsl `gn_stats`). A conv given it (`conv2d::Conv2dArgs::pre_gn_silu`) reads
/// silu(group_norm(x)) without the normalised tensor being written.
#[allow(clippy::too_many_arguments)]
pub fn group_norm_stats(
    rec: &mut Recorder,
    x: &Tensor,
    groups: usize,
    gamma: &Tensor,
    beta: &Tensor,
    eps: f32,
    out: &Tensor,
) -> Result<()> {
    let op = "group_norm_stats";
    let s = x.shape();
    same_dtype(op, &[x, gamma, beta])?;
    check_stats_args(op, s, groups, gamma, beta, eps, out)?;
    let k = if cpg_len(s, groups) <= SMALL_SEGMENT as usize {
        pick(x.dtype(), K::NormF32GnStats64, K::NormF16GnStats64)
    } else {
        pick(x.dtype(), K::NormF32GnStats, K::NormF16GnStats)
    };
    ensure!(
        rec.context().supports(k),
        "{op}: needs subgroup operations, which {:?} lacks",
        rec.context().info().name
    );
    let cpg = s[1] / groups;
    let segs = s[0] * groups;
    let p = NormParams {
        len: (cpg * s[2] * s[3]) as u32,
        segs_per_item: groups as u32,
        ch_per_seg: cpg as u32,
        inner: (s[2] * s[3]) as u32,
        eps,
        silu: 0,
        tokens: 0,
    };
    let gx = segs.min(65535);
    ensure!(
        segs % gx == 0,
        "{op}: {segs} segments cannot be tiled over the grid"
    );
    let grid = [gx as u32, (segs / gx) as u32, 1];
    rec.dispatch(
        k,
        &[
            x.buffer(),
            gamma.buffer(),
            beta.buffer(),
            out.buffer(),
            x.buffer(),
        ],
        bytemuck::bytes_of(&p),
        grid,
        op,
    )
}

/// [`group_norm_stats`] of x: (N, C, H, W) from the per-slot partials its producer wrote (`parts`: (N S, C, 4)
/// f32 of (count, mean, M2, -), S slots per image; the Winograd F(6x6) conv writes them with
/// `Conv2dArgs::stats_parts`, see `conv2d::stats_parts_shape`): x itself is not read. Same output as
/// [`group_norm_stats`] up to rounding.
#[allow(clippy::too_many_arguments)] // the norm's parameters, as group_norm_stats, plus the partials
pub fn group_norm_stats_parts(
    rec: &mut Recorder,
    parts: &Tensor,
    x_shape: &[usize],
    groups: usize,
    gamma: &Tensor,
    beta: &Tensor,
    eps: f32,
    out: &Tensor,
) -> Result<()> {
    let op = "group_norm_stats_parts";
    let s = x_shape;
    same_dtype(op, &[gamma, beta])?;
    check_stats_args(op, s, groups, gamma, beta, eps, out)?;
    let ps = parts.shape();
    ensure!(
        ps.len() == 3 && ps[0] % s[0] == 0 && ps[0] > 0 && ps[1] == s[1] && ps[2] == 4,
        "{op}: parts {ps:?} must be (N S, C, 4) for x {s:?}"
    );
    ensure!(
        parts.dtype() == crate::tensor::DType::F32,
        "{op}: parts must be f32"
    );
    let k = pick(
        gamma.dtype(),
        K::NormF32GnStatsParts,
        K::NormF16GnStatsParts,
    );
    ensure!(
        rec.context().supports(k),
        "{op}: needs subgroup operations, which {:?} lacks",
        rec.context().info().name
    );
    let p = NormParams {
        len: (ps[0] / s[0]) as u32,
        segs_per_item: groups as u32,
        ch_per_seg: (s[1] / groups) as u32,
        inner: s[1] as u32,
        eps,
        silu: 0,
        tokens: 0,
    };
    // one work group per (n, group), tiled exactly (the kernel has no bounds check on them)
    let segs = s[0] * groups;
    let gx = segs.min(65535);
    ensure!(
        segs % gx == 0,
        "{op}: {segs} segments cannot be tiled over the grid"
    );
    let grid = [gx as u32, (segs / gx) as u32, 1];
    rec.dispatch(
        k,
        &[parts.buffer(), gamma.buffer(), beta.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        grid,
        op,
    )
}

/// The checks [`group_norm_stats`] and [`group_norm_stats_parts`] share: x shape s (N, C, H, W), groups dividing
/// C, gamma and beta (C), out (N, C, 4) f32, eps finite and >= 0.
fn check_stats_args(
    op: &str,
    s: &[usize],
    groups: usize,
    gamma: &Tensor,
    beta: &Tensor,
    eps: f32,
    out: &Tensor,
) -> Result<()> {
    ensure!(s.len() == 4, "{op}: x must be (N, C, H, W), got {s:?}");
    ensure!(
        groups > 0 && s[1] % groups == 0,
        "{op}: {groups} groups do not divide {} channels of {s:?}",
        s[1]
    );
    expect_shape(op, "gamma", gamma, &[s[1]])?;
    expect_shape(op, "beta", beta, &[s[1]])?;
    expect_shape(op, "out", out, &[s[0], s[1], 4])?;
    ensure!(
        out.dtype() == crate::tensor::DType::F32,
        "{op}: out must be f32, got {}",
        out.dtype().name()
    );
    ensure!(
        eps.is_finite() && eps >= 0.0,
        "{op}: eps {eps} must be finite and >= 0"
    );
    Ok(())
}
