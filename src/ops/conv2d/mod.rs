//! conv2d launchers: NCHW input, (O, C, KH, KW) weights, any kernel size, stride, asymmetric padding
//! (top, bottom, left, right), fused bias; f32 or f16 storage with f32 accumulation.
//!
//! Paths: 1x1 stride-1 unpadded convs run as a GEMM (`matmul::gemm`, weights shared over the batch). On CPU
//! devices, 3x3 stride-1 convs with O <= 4 run the few-output-channel kernel ([`narrow_pays`],
//! `kernels/conv3x3_narrow.wgsl`), and others where it pays ([`winograd_pays`]) run Winograd F(4x4, 3x3) or
//! F(6x6, 3x3) ([`super::winograd`], tile by `winograd::Tile::best`; F(6x6) can also write group-norm
//! statistics partials of its output, [`stats_parts_shape`]). Other convs with O % 4 == 0 run an implicit GEMM
//! on weights repacked to
//! (KH, KW, C, O) (`kernels/conv2d_packed.wgsl`; with `FastHwnc` (or wide f16 inputs) the input is also
//! transposed to (H, W, N, C) first, entry `hwnc`). Per-call repacks, transposes and Winograd intermediates
//! live in the recording's shared scratch buffers (`Recorder::scratch`), not in one allocation per call.
//! Other O run the implicit GEMM on PyTorch-layout weights (`kernels/conv2d.wgsl`). All fast paths need
//! subgroups of 8..64 lanes. The direct kernel (`kernels/conv2d_direct.wgsl`) is the fallback and the tests'
//! oracle for all of them. f16 outputs saturate at +-65504 (see [`super::matmul`]).
use anyhow::{ensure, Result};

use super::matmul::{gemm, tile_shape, tiled_supported, Gemm, MatmulPath};
use super::{expect_shape, same_dtype, Recorder};
use super::{
    SCRATCH_CONV_OUT, SCRATCH_PACKED_W, SCRATCH_UPSAMPLED, SCRATCH_WINO_W, SCRATCH_X_HWNC,
};
use crate::kernels::params::{Conv2dParams, NarrowParams, PackParams};
use crate::kernels::KernelId as K;
use crate::tensor::{DType, Tensor};
use crate::vk::DeviceInfo;

pub use super::reference::conv2d::ConvGeom;

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
    /// Winograd F(4x4, 3x3) (3x3, stride 1 only; see [`super::winograd`]). `Auto` uses Winograd for 3x3
    /// stride-1 convs when [`winograd_pays`] says so, with the tile size of [`super::winograd::Tile::best`].
    Winograd,
    /// Winograd F(6x6, 3x3) (3x3, stride 1 only).
    Winograd6,
    /// The few-output-channel kernel (3x3, stride 1, O <= 4: `kernels/conv3x3_narrow.wgsl`). `Auto` uses it
    /// for such convs on CPU devices ([`narrow_pays`]).
    Narrow,
}

/// Whether `Auto` runs a 3x3 conv with O output channels through the few-output-channel kernel: stride 1,
/// O <= 4, on CPU devices (measured on lavapipe: the VAE decoder's 32 -> 3 conv_out at 224 x 400 took ~50 ms
/// in the implicit GEMM, whose 16-row register tile idles 13 rows at O = 3).
pub fn narrow_pays(dev: &DeviceInfo, kh: usize, kw: usize, stride: usize, o: usize) -> bool {
    dev.is_cpu() && kh == 3 && kw == 3 && stride == 1 && o <= 4
}

/// Whether `Auto` runs a 3x3 stride-1 conv (batch N, C -> O channels, OH x OW output) through Winograd: only on
/// CPU devices (lavapipe), where it was measured (GPUs keep the implicit GEMM; the f32 transformed weights are
/// 4x the 3x3 weights), and only where the transforms pay: wide convs (C, O >= 256: the 320-channel 28x50 op
/// case takes 30 ms instead of 74), >= 180 output tiles of 4x4 (b2dr-tiny VAE decode 2.58 s -> 2.06 s; on the
/// small UNet convs it gained nothing measurable), down to C = 3 (the ControlNet's 3 -> 16 conv at 224 x 400:
/// its 27.6 ms implicit-GEMM profile entry went, the Winograd transform totals rose ~10 ms), or >= 64 tiles
/// with C, O >= 128 (the VAE decoder's ten 128-channel convs at 28 x 50, 91 tiles: 132 ms -> ~68 ms in
/// `--profile`, decode ~1.29 s -> ~1.22 s). lavapipe 22.3, 2026-11-23, see BENCHMARKS.md.
pub fn winograd_pays(dev: &DeviceInfo, n: usize, c: usize, o: usize, oh: usize, ow: usize) -> bool {
    let tiles = n * oh.div_ceil(4) * ow.div_ceil(4);
    dev.is_cpu()
        && c >= 3
        && o >= 8
        && (tiles >= 180 || c.min(o) >= 256 || (tiles >= 64 && c.min(o) >= 128))
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

/// Whether `Auto` runs this conv where a GroupNorm + SiLU prologue (`Conv2dArgs::pre_gn_silu`) can be fused:
/// the Winograd path (3x3, stride 1, [`winograd_pays`], subgroups) or the few-output-channel kernel
/// ([`narrow_pays`]).
pub fn pre_gn_fusable(
    dev: &DeviceInfo,
    x: &[usize],
    w: &[usize],
    stride: usize,
    pad: [usize; 4],
) -> bool {
    let Ok(os) = conv2d_out_shape(x, w, stride, pad) else {
        return false;
    };
    w[2] == 3
        && w[3] == 3
        && stride == 1
        && pad.iter().all(|&p| p <= 2)
        && dev.subgroup_size >= 8
        && dev.subgroup_size <= 64
        && (narrow_pays(dev, w[2], w[3], stride, w[0])
            || winograd_pays(dev, x[0], x[1], w[0], os[2], os[3]))
}

/// The shape of the statistics partials (`Conv2dArgs::stats_parts`) that an `Auto` conv of x (N, C, H, W; the
/// size the conv reads, i.e. after an upsampling; stored in `dtype`) with w writes, or None where its path cannot write them
/// (anything but F(6x6) Winograd with vec4 output rows): (N S, O, 4) with S = ceil(OH / 6) ceil(OW / 12)
/// slots (tile pairs) per image.
pub fn stats_parts_shape(
    dev: &DeviceInfo,
    dtype: DType,
    x: &[usize],
    w: &[usize],
    stride: usize,
    pad: [usize; 4],
) -> Option<[usize; 3]> {
    let os = conv2d_out_shape(x, w, stride, pad).ok()?;
    let (o, oh, ow) = (os[1], os[2], os[3]);
    let wino = w[2] == 3
        && w[3] == 3
        && stride == 1
        && pad.iter().all(|&p| p <= 2)
        && dev.subgroup_size >= 8
        && dev.subgroup_size <= 64
        && !narrow_pays(dev, w[2], w[3], stride, o)
        && winograd_pays(dev, x[0], x[1], o, oh, ow);
    let f6 = super::winograd::Tile::best(dtype, o, oh, ow) == super::winograd::Tile::F6;
    (wino && f6).then(|| [x[0] * oh.div_ceil(6) * ow.div_ceil(12), o, 4])
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
    let id = match d {
        DType::F32 => K::Conv2dPackedF32Pack,
        DType::F16 => K::Conv2dPackedF16Pack,
    };
    let g = super::grid_1d("conv2d pack_weight", w.numel())?;
    rec.dispatch(
        id,
        &[w.buffer(), packed.buffer()],
        bytemuck::bytes_of(&p),
        g,
        "conv2d pack_weight",
    )
}

/// out = conv2d(x, w) (+ bias) (+ residual) (then SiLU), x optionally read through a GroupNorm + SiLU prologue;
/// see [`Conv2dArgs`].
pub fn conv2d_ex(rec: &mut Recorder, a: &Conv2dArgs) -> Result<()> {
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
    let bias_nc = match a.bias {
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
    let [n, c, h, w] = [xs[0], xs[1], xs[2], xs[3]];
    let (o, kh, kw) = (ws[0], ws[2], ws[3]);
    let np = os[2] * os[3];
    let bias = a.bias.unwrap_or(a.x);
    let fast = match a.path {
        ConvPath::Direct => false,
        ConvPath::Fast
        | ConvPath::FastHwnc
        | ConvPath::Winograd
        | ConvPath::Winograd6
        | ConvPath::Narrow => true,
        ConvPath::Auto => tiled_supported(rec),
    };
    let wino_shape = kh == 3 && kw == 3 && a.stride == 1;
    let narrow = match a.path {
        ConvPath::Narrow => {
            ensure!(
                wino_shape && o <= 4 && tiled_supported(rec),
                "conv2d: the few-output-channel path needs a 3x3 stride-1 conv with O <= 4 and subgroups of 8 to 64 lanes (x {xs:?}, w {ws:?}, stride {})",
                a.stride
            );
            true
        }
        ConvPath::Auto => fast && narrow_pays(rec.context().info(), kh, kw, a.stride, o),
        _ => false,
    };
    let wino = !narrow
        && match a.path {
            ConvPath::Winograd | ConvPath::Winograd6 => {
                ensure!(
                wino_shape,
                "conv2d: the Winograd path needs a 3x3 stride-1 conv (x {xs:?}, w {ws:?}, stride {})",
                a.stride
            );
                ensure!(
                    tiled_supported(rec),
                    "conv2d: the Winograd path needs subgroups of 8 to 64 lanes, which {:?} lacks",
                    rec.context().info().name
                );
                true
            }
            ConvPath::Auto => {
                fast && wino_shape && winograd_pays(rec.context().info(), n, c, o, os[2], os[3])
            }
            _ => false,
        };
    ensure!(
        wino || a.stats_parts.is_none(),
        "conv2d: statistics partials come from the F(6x6) Winograd path only (x {xs:?}, w {ws:?}; see conv2d::stats_parts_shape)"
    );
    if a.upsample2x && !wino {
        // this path reads x directly: upsample into the recording's scratch first
        let b = rec.scratch(
            SCRATCH_UPSAMPLED,
            (xs.iter().product::<usize>() * d.size()) as u64,
        )?;
        let xu = Tensor::on_buffer(b, xs, d)?;
        super::resample::upsample_nearest(rec, a.x, &xu, (xs[2], xs[3]))?;
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
        wino || narrow || a.pre_gn_silu.is_none(),
        "conv2d: a GroupNorm prologue (pre_gn_silu) is fused only on the Winograd and few-output-channel paths (x {xs:?}, w {ws:?}, stride {}; see conv2d::pre_gn_fusable)",
        a.stride
    );
    if narrow {
        return conv3x3_narrow(rec, a, &os);
    }
    if wino {
        use super::winograd::Tile;
        let tile = match a.path {
            ConvPath::Winograd => Tile::F4,
            ConvPath::Winograd6 => Tile::F6,
            _ => Tile::best(d, o, os[2], os[3]),
        };
        let given = match tile {
            Tile::F4 => a.wino_w,
            Tile::F6 => a.wino_w6,
        };
        let tmp;
        let u = match given {
            Some(u) => u,
            None => {
                // transformed per call into the recording's shared scratch
                let sh = super::winograd::weight_shape(ws, tile);
                let b = rec.scratch(SCRATCH_WINO_W, (sh.iter().product::<usize>() * 4) as u64)?;
                tmp = Tensor::on_buffer(b, &sh, DType::F32)?;
                super::winograd::transform_weight(rec, a.w, &tmp)?;
                &tmp
            }
        };
        return super::winograd::conv3x3(rec, a, u);
    }
    if fast && kh == 1 && kw == 1 && a.stride == 1 && a.pad == [0; 4] && !bias_nc {
        // (O, C) x (C, H W) per image -> (O, H W) per image
        let g = Gemm {
            m: o,
            n: np,
            k: c,
            batch: n,
            sa: 0,
            sb: c * np,
            trans_b: false,
            bias_mode: if a.bias.is_some() { 2 } else { 0 },
            res: a.residual.is_some(),
            dtype: d,
            path: MatmulPath::Tiled,
        };
        let res = a.residual.unwrap_or(a.out);
        let bufs = [
            a.w.buffer(),
            a.x.buffer(),
            bias.buffer(),
            a.out.buffer(),
            res.buffer(),
        ];
        gemm(rec, "conv2d(1x1 as gemm)", &g, bufs, None)?;
        if a.silu {
            super::elementwise::silu(rec, a.out, a.out)?;
        }
        return Ok(());
    }
    let p = Conv2dParams {
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
        has_bias: a.bias.is_some() as u32,
        has_res: 0,
        silu: 0,
    };
    let mut p = p;
    let mut bufs = vec![a.x.buffer(), a.w.buffer(), bias.buffer(), a.out.buffer()];
    // the packed implicit GEMM adds an (N, O) bias and the residual in its epilogue; the other kernels get
    // the per-channel bias only, the rest is added after them
    let packed_path = fast && o % 4 == 0;
    let mut after_bias = None;
    if bias_nc {
        if packed_path {
            p.has_bias = 2;
        } else {
            p.has_bias = 0;
            after_bias = a.bias;
        }
    }
    let mut after_res = None;
    let conv_out;
    if packed_path {
        p.has_res = a.residual.is_some() as u32;
        p.silu = a.silu as u32;
        bufs.push(a.residual.unwrap_or(a.out).buffer());
    } else if let Some(r) = a.residual {
        after_res = Some(r);
        if std::sync::Arc::ptr_eq(r.buffer(), a.out.buffer()) {
            // in place: the conv must not overwrite the residual before the add reads it
            let b = rec.scratch(SCRATCH_CONV_OUT, (a.out.numel() * d.size()) as u64)?;
            conv_out = Tensor::on_buffer(b, &os, d)?;
            bufs[3] = conv_out.buffer();
        }
    }
    let tmp;
    let xt;
    let (id, groups, edges) = if packed_path {
        ensure!(
            tiled_supported(rec),
            "conv2d: the implicit-GEMM kernel needs subgroups of 8 to 64 lanes, which {:?} lacks",
            rec.context().info().name
        );
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
        bufs[1] = packed.buffer();
        let (rows, cols) = tile_shape(rec);
        let g = [o.div_ceil(cols) as u32, np.div_ceil(rows) as u32, n as u32];
        // The (H, W, N, C) transpose pays off only for wide f16 inputs (320 ch 3x3: 64 vs 73 ms); elsewhere its
        // per-call cost exceeds the gain (see ConvPath::FastHwnc).
        let hwnc = a.path == ConvPath::FastHwnc
            || (a.path == ConvPath::Auto && d == DType::F16 && c >= 256);
        if c % 4 == 0 && hwnc {
            // input transposed to (H, W, N, C) so channels load as vectors (conv2d_packed.wgsl `hwnc`)
            // per-call transpose into the recording's shared scratch
            let b = rec.scratch(SCRATCH_X_HWNC, (h * w * n * c * d.size()) as u64)?;
            xt = Tensor::on_buffer(b, &[h, w, n, c], d)?;
            let pp = PackParams {
                o: (n * c) as u32,
                c: 1,
                kk: (h * w) as u32,
            };
            let pid = match d {
                DType::F32 => K::Conv2dPackedF32Pack,
                DType::F16 => K::Conv2dPackedF16Pack,
            };
            let pg = super::grid_1d("conv2d", a.x.numel())?;
            let pb = [a.x.buffer(), xt.buffer()];
            rec.dispatch(pid, &pb, bytemuck::bytes_of(&pp), pg, "conv2d x->hwnc")?;
            bufs[0] = xt.buffer();
            let id = match d {
                DType::F32 => K::Conv2dPackedF32Hwnc,
                DType::F16 => K::Conv2dPackedF16Hwnc,
            };
            (id, g, kh * kw * (c.div_ceil(32) + 1) + kh)
        } else {
            let id = match d {
                DType::F32 => K::Conv2dPackedF32,
                DType::F16 => K::Conv2dPackedF16,
            };
            (id, g, kh * kw * (c.div_ceil(8) + 1) + kh)
        }
    } else if fast {
        ensure!(
            tiled_supported(rec),
            "conv2d: the implicit-GEMM kernel needs subgroups of 8 to 64 lanes, which {:?} lacks",
            rec.context().info().name
        );
        let id = match d {
            DType::F32 => K::Conv2dF32,
            DType::F16 => K::Conv2dF16,
        };
        let (rows, cols) = tile_shape(rec);
        let g = [np.div_ceil(cols) as u32, o.div_ceil(rows) as u32, n as u32];
        (id, g, kh * kw * (c.div_ceil(8) + 1) + kh)
    } else {
        let id = match d {
            DType::F32 => K::Conv2dDirectF32,
            DType::F16 => K::Conv2dDirectF16,
        };
        let g = super::grid_1d("conv2d", n * o * np)?;
        (id, g, c * (kh * kw + kh + 1))
    };
    ensure!(
        edges < LOOP_BUDGET,
        "conv2d: x {xs:?} w {ws:?} needs {edges} loop iterations per invocation, past lavapipe's loop budget"
    );
    ensure!(
        groups.iter().all(|&g| g <= 65535),
        "conv2d: x {xs:?} w {ws:?} is too large for one dispatch"
    );
    // per-shape label: `--profile` then splits conv time by shape
    let label = format!("conv2d {n}x{c}x{h}x{w} -> {o} k{kh}x{kw} s{}", a.stride);
    // x and the packed weights through their texel views where the device has them
    let views: Vec<&crate::vk::Buffer> = bufs.iter().map(|b| b.as_ref()).collect();
    let id = super::texel_variant(rec, id, &views).unwrap_or(id);
    rec.dispatch(id, &bufs, bytemuck::bytes_of(&p), groups, &label)?;
    // the conv's output tensor (`out`, or the scratch when the residual is `out`)
    let y = Tensor::on_buffer(bufs[3].clone(), &os, d)?;
    if let Some(b) = after_bias {
        let b4 = b.reshape(&[n, o, 1, 1])?;
        super::elementwise::add(rec, &y, &b4, &y)?;
    }
    if let Some(r) = after_res {
        super::elementwise::add(rec, &y, r, a.out)?;
    }
    if a.silu && !packed_path {
        super::elementwise::silu(rec, a.out, a.out)?;
    }
    Ok(())
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

/// The few-output-channel 3x3 conv (`kernels/conv3x3_narrow.wgsl`) with everything of `a` but the upsampling
/// (resolved by the caller); os: the output shape.
fn conv3x3_narrow(rec: &mut Recorder, a: &Conv2dArgs, os: &[usize; 4]) -> Result<()> {
    let xs = a.x.shape();
    let p = NarrowParams {
        n: xs[0] as u32,
        c: xs[1] as u32,
        h: xs[2] as u32,
        w: xs[3] as u32,
        o: os[1] as u32,
        oh: os[2] as u32,
        ow: os[3] as u32,
        pt: a.pad[0] as u32,
        pl: a.pad[2] as u32,
        has_bias: match a.bias {
            Some(b) if b.shape().len() == 2 => 2,
            Some(_) => 1,
            None => 0,
        },
        has_res: a.residual.is_some() as u32,
        silu: a.silu as u32,
        pre: a.pre_gn_silu.is_some() as u32,
        rows4: (xs[3] % 4 == 0 && a.pad[2] == 1) as u32,
    };
    let id = match a.x.dtype() {
        DType::F32 => K::Conv3x3NarrowF32,
        DType::F16 => K::Conv3x3NarrowF16,
    };
    let bufs = [
        a.x.buffer(),
        a.w.buffer(),
        a.bias.unwrap_or(a.x).buffer(),
        a.out.buffer(),
        a.residual.unwrap_or(a.out).buffer(),
        a.pre_gn_silu.unwrap_or(a.x).buffer(),
        a.x.buffer(),
    ];
    let g = super::grid_1d("conv2d narrow", os[0] * os[2] * os[3].div_ceil(8))?;
    let label = format!(
        "conv2d narrow {}x{}x{}x{} -> {}",
        xs[0], xs[1], xs[2], xs[3], os[1]
    );
    rec.dispatch(id, &bufs, bytemuck::bytes_of(&p), g, &label)
}
