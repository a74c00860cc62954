//! conv2d launchers: NCHW input, (O, C, KH, KW) weights, any kernel size, stride, asymmetric padding
//! (top, bottom, left, right), fused bias; f32 or f16 storage with f32 accumulation.
//!
//! One algorithm per file, one function that picks it: [`conv2d_ex`] checks the shapes, asks
//! [`strategy::select`] for a [`Conv2dStrategy`] (the whole selection policy: which path pays on which device
//! and shape) and dispatches to that algorithm's launcher:
//! - `gemm1x1.rs`: 1x1 stride-1 unpadded convs as a GEMM (`matmul::gemm`, weights shared over the batch);
//! - `narrow.rs`: 3x3 stride-1 convs with O <= 4 on CPU devices (`kernels/conv3x3_narrow.wgsl`);
//! - `winograd.rs`: Winograd F(4x4, 3x3) / F(6x6, 3x3) where it pays (tile by `winograd::Tile::best`; F(6x6)
//!   can also write group-norm statistics partials of its output, [`stats_parts_shape`]);
//! - `packed.rs`: implicit GEMM on weights repacked to (KH, KW, C, O) for O % 4 == 0
//!   (`kernels/conv2d_packed.wgsl`; with `FastHwnc`, or wide f16 inputs, on an input transposed to
//!   (H, W, N, C) first, entry `hwnc`);
//! - `implicit_gemm.rs`: implicit GEMM on PyTorch-layout weights for other O (`kernels/conv2d.wgsl`);
//! - `direct.rs`: the direct kernel (`kernels/conv2d_direct.wgsl`), the fallback and the tests' oracle.
//!
//! Per-call repacks, transposes and Winograd intermediates live in the recording's shared scratch buffers
//! (`Recorder::scratch`), not in one allocation per call. All fast paths need subgroups of 8..64 lanes. f16
//! outputs saturate at +-65504 (see [`super::matmul`]). Layers that prepare weights once ask
//! [`weight_forms`] which forms their conv's strategies may read.
mod direct;
mod gemm1x1;
mod implicit_gemm;
mod narrow;
mod packed;
pub mod strategy;
pub mod winograd;

use std::sync::Arc;

use anyhow::{ensure, Result};

use super::{expect_shape, same_dtype, Recorder, SCRATCH_CONV_OUT, SCRATCH_UPSAMPLED};
use crate::kernels::params::Conv2dParams;
use crate::kernels::KernelId;
use crate::tensor::{DType, Tensor};
use crate::vk::Buffer;

pub use super::reference::conv2d::ConvGeom;
pub use packed::pack_weight;
pub use strategy::{
    narrow_pays, pre_gn_fusable, stats_parts_shape, weight_forms, winograd_pays, Conv2dStrategy,
    WeightForm,
};

/// Which kernel runs a conv.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ConvPath {
    /// GEMM for 1x1, Winograd for 3x3 stride 1 where [`winograd_pays`], implicit GEMM otherwise when
    /// supported, else direct.
    #[default]
    Auto,
    /// Implicit GEMM (or GEMM for 1x1); error if the device lacks suitable subgroups.
    Fast,
    /// The direct kernel, whatever the shape.
    Direct,
    /// Implicit GEMM on an input transposed to (H, W, N, C) first (vec4 channel loads; C % 4 == 0). `Auto` uses
    /// it only for f16 inputs of >= 256 channels: elsewhere the per-call transpose costs more than it saves
    /// (b2dr-tiny f32 guided step 1.29 s -> 1.06 s and VAE decode 3.08 s -> 2.53 s without it, f16 1.36 s ->
    /// 1.03 s and 3.00 s -> 2.67 s; the f32 320-channel 3x3 case is equal within noise, f16 is 64 vs 73 ms in
    /// its favour; lavapipe, 2026-11-23).
    FastHwnc,
    /// Winograd F(4x4, 3x3) (3x3, stride 1 only; see [`winograd`]). `Auto` uses Winograd for 3x3
    /// stride-1 convs when [`winograd_pays`] says so, with the tile size of [`winograd::Tile::best`].
    Winograd,
    /// Winograd F(6x6, 3x3) (3x3, stride 1 only).
    Winograd6,
    /// The few-output-channel kernel (3x3, stride 1, O <= 4: `kernels/conv3x3_narrow.wgsl`). `Auto` uses it
    /// for such convs on CPU devices ([`narrow_pays`]).
    Narrow,
}

/// lavapipe stops every loop of an invocation after 65535 back-edges in total: stay well below.
const LOOP_BUDGET: usize = 60_000;

/// Arguments of [`conv2d_ex`].
#[derive(Clone, Copy, Debug)]
pub struct Conv2dArgs<'a> {
    /// (N, C, H, W)
    pub x: &'a Tensor,
    /// (O, C, KH, KW)
    pub w: &'a Tensor,
    /// (O), or (N, O): a bias per image and channel (a ResNet block's time embedding folded into its conv)
    pub bias: Option<&'a Tensor>,
    /// (N, O, OH, OW), see [`conv2d_out_shape`]
    pub out: &'a Tensor,
    pub stride: usize,
    /// (top, bottom, left, right)
    pub pad: [usize; 4],
    pub path: ConvPath,
    /// `w` already repacked by [`pack_weight`] ((KH, KW, C, O)); without it the fast path repacks into a
    /// temporary on every call (cheap next to the conv: O C KH KW elements).
    pub packed_w: Option<&'a Tensor>,
    /// 3x3 `w` already transformed by [`super::winograd::transform_weight`] for F(4x4) ((36, C, O), f32);
    /// without it the F(4x4) path transforms into a temporary on every call.
    pub wino_w: Option<&'a Tensor>,
    /// The same for F(6x6) ((64, C, O), f32).
    pub wino_w6: Option<&'a Tensor>,
    /// Also write per-slot statistics partials of the output ((N S, O, 4) f32, see [`stats_parts_shape`]) for
    /// a following group norm (`norm::group_norm_stats_parts`): F(6x6) Winograd with vec4 output rows only; an
    /// error elsewhere.
    pub stats_parts: Option<&'a Tensor>,
    /// (N, O, OH, OW), added to the output (a residual connection; it may be `out` itself). Fused into the
    /// epilogue of the Winograd, packed implicit-GEMM and 1x1 GEMM paths, a separate add elsewhere.
    pub residual: Option<&'a Tensor>,
    /// SiLU on the result (after bias and residual): in the epilogue of the Winograd and packed implicit-GEMM
    /// paths, a separate pass elsewhere.
    pub silu: bool,
    /// (N, C, 4) f32 from `norm::group_norm_stats`: the conv reads silu(group_norm(x)) instead of x (a ResNet
    /// block's GroupNorm + SiLU folded into the conv's input loads; the normalised tensor is never written).
    /// Winograd and few-output-channel paths only ([`pre_gn_fusable`] says where); an error elsewhere.
    pub pre_gn_silu: Option<&'a Tensor>,
    /// x (N, C, H, W) is read as its nearest 2x upsampling (N, C, 2H, 2W), the input size the conv's geometry
    /// refers to (an Upsample2D's conv): through the upsampling on the Winograd path (the upsampled tensor is
    /// never written), from an upsampled copy elsewhere.
    pub upsample2x: bool,
}

impl<'a> Conv2dArgs<'a> {
    /// A plain conv: path `Auto`, no pre-transformed weights, residual, SiLU, prologue or upsampling (set those
    /// with struct update syntax: `Conv2dArgs { residual: Some(r), ..Conv2dArgs::new(..) }`).
    pub fn new(
        x: &'a Tensor,
        w: &'a Tensor,
        bias: Option<&'a Tensor>,
        out: &'a Tensor,
        stride: usize,
        pad: [usize; 4],
    ) -> Self {
        Self {
            x,
            w,
            bias,
            out,
            stride,
            pad,
            path: ConvPath::Auto,
            packed_w: None,
            wino_w: None,
            wino_w6: None,
            stats_parts: None,
            residual: None,
            silu: false,
            pre_gn_silu: None,
            upsample2x: false,
        }
    }
}

/// Output shape of x: (N, C, H, W) convolved with w: (O, C, KH, KW), with checks naming the shapes.
pub fn conv2d_out_shape(
    x: &[usize],
    w: &[usize],
    stride: usize,
    pad: [usize; 4],
) -> Result<[usize; 4]> {
    ensure!(
        x.len() == 4 && w.len() == 4,
        "conv2d: x {x:?} must be (N, C, H, W) and w {w:?} (O, C, KH, KW)"
    );
    ensure!(
        x[1] == w[1],
        "conv2d: input channels differ: x {x:?}, w {w:?}"
    );
    ensure!(
        stride >= 1,
        "conv2d: stride must be >= 1 (x {x:?}, w {w:?})"
    );
    ensure!(
        pad[0] < w[2] && pad[1] < w[2] && pad[2] < w[3] && pad[3] < w[3],
        "conv2d: padding {pad:?} (top, bottom, left, right) must be smaller than the kernel {}x{} (x {x:?})",
        w[2],
        w[3]
    );
    let (hp, wp) = (x[2] + pad[0] + pad[1], x[3] + pad[2] + pad[3]);
    ensure!(
        hp >= w[2] && wp >= w[3],
        "conv2d: kernel {}x{} larger than the padded input {hp}x{wp} (x {x:?}, pad {pad:?})",
        w[2],
        w[3]
    );
    Ok([
        x[0],
        w[0],
        (hp - w[2]) / stride + 1,
        (wp - w[3]) / stride + 1,
    ])
}

/// The checked geometry of one conv: shapes as the conv sees them (x after any 2x upsampling).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Geometry {
    pub dtype: DType,
    /// (N, C, H, W)
    pub x: [usize; 4],
    /// (O, C, KH, KW)
    pub w: [usize; 4],
    /// (N, O, OH, OW)
    pub out: [usize; 4],
    pub stride: usize,
    pub pad: [usize; 4],
    /// The bias is (N, O), one per image and channel.
    pub bias_per_image: bool,
}

impl Geometry {
    pub fn of_shapes(
        dtype: DType,
        x: &[usize],
        w: &[usize],
        stride: usize,
        pad: [usize; 4],
        bias_per_image: bool,
    ) -> Result<Self> {
        let out = conv2d_out_shape(x, w, stride, pad)?;
        Ok(Self {
            dtype,
            x: [x[0], x[1], x[2], x[3]],
            w: [w[0], w[1], w[2], w[3]],
            out,
            stride,
            pad,
            bias_per_image,
        })
    }
}

/// The bias a conv kernel adds (`has_bias` of the WGSL parameter structs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum BiasMode {
    None,
    /// (O): one per output channel.
    PerChannel,
    /// (N, O): one per image and output channel.
    PerImageChannel,
}

impl BiasMode {
    /// The mode of a bias tensor ((O) or (N, O); shapes checked by `conv2d_ex`).
    pub fn of(bias: Option<&Tensor>) -> Self {
        match bias {
            Some(b) if b.shape().len() == 2 => BiasMode::PerImageChannel,
            Some(_) => BiasMode::PerChannel,
            None => BiasMode::None,
        }
    }

    /// The kernels' code.
    pub fn code(self) -> u32 {
        match self {
            BiasMode::None => 0,
            BiasMode::PerChannel => 1,
            BiasMode::PerImageChannel => 2,
        }
    }
}

/// Checks a's tensors against each other and returns the conv's geometry.
fn check(a: &Conv2dArgs) -> Result<Geometry> {
    let mut ts = vec![a.x, a.w, a.out];
    ts.extend(a.bias);
    ts.extend(a.residual);
    let d = same_dtype("conv2d", &ts)?;
    let ws = a.w.shape();
    ensure!(
        a.x.shape().len() == 4,
        "conv2d: x {:?} must be (N, C, H, W)",
        a.x.shape()
    );
    // the input the conv's geometry refers to: x itself, or its 2x upsampling
    let xs_up;
    let xs: &[usize] = if a.upsample2x {
        let s = a.x.shape();
        xs_up = [s[0], s[1], 2 * s[2], 2 * s[3]];
        ensure!(
            a.pre_gn_silu.is_none(),
            "conv2d: a GroupNorm prologue and a 2x upsampling of the input are not combined"
        );
        &xs_up
    } else {
        a.x.shape()
    };
    let os = conv2d_out_shape(xs, ws, a.stride, a.pad)?;
    expect_shape("conv2d", "out", a.out, &os)?;
    let bias_per_image = match a.bias {
        Some(b) if b.shape() == [xs[0], ws[0]] => true,
        Some(b) => {
            ensure!(
                b.shape() == [ws[0]],
                "conv2d: bias {:?} must be ({}) or ({}, {}) (x {xs:?}, w {ws:?})",
                b.shape(),
                ws[0],
                xs[0],
                ws[0]
            );
            false
        }
        None => false,
    };
    if let Some(r) = a.residual {
        expect_shape("conv2d", "residual", r, &os)?;
    }
    if let Some(g) = a.pre_gn_silu {
        expect_shape("conv2d", "pre_gn_silu", g, &[xs[0], xs[1], 4])?;
        ensure!(
            g.dtype() == DType::F32,
            "conv2d: pre_gn_silu must be f32 (from norm::group_norm_stats)"
        );
    }
    Geometry::of_shapes(d, xs, ws, a.stride, a.pad, bias_per_image)
}

/// out = conv2d(x, w) (+ bias) (+ residual) (then SiLU), x optionally read through a GroupNorm + SiLU prologue;
/// see [`Conv2dArgs`]. The algorithm comes from [`strategy::select`].
pub fn conv2d_ex(rec: &mut Recorder, a: &Conv2dArgs) -> Result<()> {
    let g = check(a)?;
    let caps = strategy::Caps {
        dev: rec.context().info(),
        tiled: super::matmul::tiled_supported(rec),
    };
    let s = strategy::select(a.path, &caps, &g)?;
    ensure!(
        matches!(s, Conv2dStrategy::Winograd(_)) || a.stats_parts.is_none(),
        "conv2d: statistics partials come from the F(6x6) Winograd path only (x {:?}, w {:?}; see conv2d::stats_parts_shape)",
        g.x,
        g.w
    );
    if a.upsample2x && !s.reads_upsampled() {
        // this path reads x directly: upsample into the recording's scratch first
        let b = rec.scratch(
            SCRATCH_UPSAMPLED,
            (g.x.iter().product::<usize>() * g.dtype.size()) as u64,
        )?;
        let xu = Tensor::on_buffer(b, &g.x, g.dtype)?;
        super::resample::upsample_nearest(rec, a.x, &xu, (g.x[2], g.x[3]))?;
        return conv2d_ex(
            rec,
            &Conv2dArgs {
                x: &xu,
                upsample2x: false,
                ..*a
            },
        );
    }
    ensure!(
        s.takes_gn_prologue() || a.pre_gn_silu.is_none(),
        "conv2d: a GroupNorm prologue (pre_gn_silu) is fused only on the Winograd and few-output-channel paths (x {:?}, w {:?}, stride {}; see conv2d::pre_gn_fusable)",
        g.x,
        g.w,
        a.stride
    );
    match s {
        Conv2dStrategy::Narrow => narrow::conv3x3(rec, a, &g),
        Conv2dStrategy::Winograd(tile) => winograd::conv(rec, a, &g, tile),
        Conv2dStrategy::Gemm1x1 => gemm1x1::conv(rec, a, &g),
        Conv2dStrategy::Packed { hwnc } => packed::conv(rec, a, &g, hwnc),
        Conv2dStrategy::ImplicitGemm => implicit_gemm::conv(rec, a, &g),
        Conv2dStrategy::Direct => direct::conv(rec, a, &g),
    }
}

/// x: (N, C, H, W) * w: (O, C, KH, KW) (+ bias (O)) -> out: (N, O, OH, OW); pad = (top, bottom, left, right).
pub fn conv2d(
    rec: &mut Recorder,
    x: &Tensor,
    w: &Tensor,
    bias: Option<&Tensor>,
    stride: usize,
    pad: [usize; 4],
    out: &Tensor,
) -> Result<()> {
    conv2d_ex(rec, &Conv2dArgs::new(x, w, bias, out, stride, pad))
}

/// One dispatch of a `Conv2dParams` kernel (direct, implicit GEMM, packed implicit GEMM) as its algorithm
/// file sets it up.
pub(crate) struct ConvKernel<'b> {
    pub id: KernelId,
    /// What binding 0 reads: x, or its (H, W, N, C) transpose.
    pub x: &'b Arc<Buffer>,
    /// What binding 1 reads: w, or its packed form.
    pub w: &'b Arc<Buffer>,
    pub groups: [u32; 3],
    /// Loop back-edges per invocation (lavapipe's budget: [`LOOP_BUDGET`]).
    pub edges: usize,
    /// The kernel adds an (N, O) bias and the residual and applies SiLU in its epilogue (conv2d_packed.wgsl);
    /// the others add the per-channel bias only, the rest runs as separate ops after them.
    pub fused_epilogue: bool,
}

/// Records `k` for `a` (geometry `g`) with the epilogue parts the kernel lacks as separate ops.
pub(crate) fn run_kernel(
    rec: &mut Recorder,
    a: &Conv2dArgs,
    g: &Geometry,
    k: ConvKernel,
) -> Result<()> {
    let ([n, c, h, w], [o, _, kh, kw], os) = (g.x, g.w, g.out);
    let d = g.dtype;
    let bias_mode = BiasMode::of(a.bias);
    let (has_bias, after_bias) = match bias_mode {
        BiasMode::PerImageChannel if !k.fused_epilogue => (BiasMode::None, a.bias),
        m => (m, None),
    };
    let mut p = Conv2dParams {
        n: n as u32,
        c: c as u32,
        h: h as u32,
        w: w as u32,
        o: o as u32,
        oh: os[2] as u32,
        ow: os[3] as u32,
        kh: kh as u32,
        kw: kw as u32,
        stride: a.stride as u32,
        pt: a.pad[0] as u32,
        pl: a.pad[2] as u32,
        has_bias: has_bias.code(),
        has_res: 0,
        silu: 0,
    };
    let bias = a.bias.unwrap_or(a.x);
    let mut bufs = vec![k.x, k.w, bias.buffer(), a.out.buffer()];
    let mut after_res = None;
    let conv_out;
    if k.fused_epilogue {
        p.has_res = a.residual.is_some() as u32;
        p.silu = a.silu as u32;
        bufs.push(a.residual.unwrap_or(a.out).buffer());
    } else if let Some(r) = a.residual {
        after_res = Some(r);
        if Arc::ptr_eq(r.buffer(), a.out.buffer()) {
            // in place: the conv must not overwrite the residual before the add reads it
            let b = rec.scratch(SCRATCH_CONV_OUT, (a.out.numel() * d.size()) as u64)?;
            conv_out = Tensor::on_buffer(b, &os, d)?;
            bufs[3] = conv_out.buffer();
        }
    }
    ensure!(
        k.edges < LOOP_BUDGET,
        "conv2d: x {:?} w {:?} needs {} loop iterations per invocation, past lavapipe's loop budget",
        g.x,
        g.w,
        k.edges
    );
    ensure!(
        k.groups.iter().all(|&g| g <= 65535),
        "conv2d: x {:?} w {:?} is too large for one dispatch",
        g.x,
        g.w
    );
    // per-shape label: `--profile` then splits conv time by shape
    let label = format!("conv2d {n}x{c}x{h}x{w} -> {o} k{kh}x{kw} s{}", a.stride);
    // x and the packed weights through their texel views where the device has them
    let views: Vec<&Buffer> = bufs.iter().map(|b| b.as_ref()).collect();
    let id = super::texel_variant(rec, k.id, &views).unwrap_or(k.id);
    rec.dispatch(id, &bufs, bytemuck::bytes_of(&p), k.groups, &label)?;
    // the conv's output tensor (`out`, or the scratch when the residual is `out`)
    let y = Tensor::on_buffer(bufs[3].clone(), &os, d)?;
    if let Some(b) = after_bias {
        let b4 = b.reshape(&[n, o, 1, 1])?;
        super::elementwise::add(rec, &y, &b4, &y)?;
    }
    if let Some(r) = after_res {
        super::elementwise::add(rec, &y, r, a.out)?;
    }
    if a.silu && !k.fused_epilogue {
        super::elementwise::silu(rec, a.out, a.out)?;
    }
    Ok(())
}

/// The tiled kernels' requirement, as an error naming the device.
pub(crate) fn ensure_tiled(rec: &Recorder, what: &str) -> Result<()> {
    ensure!(
        super::matmul::tiled_supported(rec),
        "conv2d: the {what} kernel needs subgroups of 8 to 64 lanes, which {:?} lacks",
        rec.context().info().name
    );
    Ok(())
}
