//! Which algorithm runs a conv: [`select`] turns a requested [`ConvPath`] and the conv's geometry into one
//! [`Conv2dStrategy`] (the single place the policy lives; `conv2d_ex` dispatches on it), and
//! [`weight_forms`] says which once-prepared weights the strategies that a layer's conv may take use (what
//! `nn::layers::Conv` prepares at load, when the input size is not known yet).
use anyhow::{ensure, Result};

use super::winograd::Tile;
use super::{ConvPath, Geometry};
use crate::tensor::DType;
use crate::vk::DeviceInfo;

/// The algorithm one conv runs (see `conv2d/<name>.rs`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Conv2dStrategy {
    /// 1x1, stride 1, unpadded, per-channel bias: one GEMM per image on the tiled matmul (`gemm1x1.rs`).
    Gemm1x1,
    /// Winograd F(4x4, 3x3) or F(6x6, 3x3) (3x3, stride 1; `winograd.rs`).
    Winograd(Tile),
    /// The few-output-channel 3x3 kernel (stride 1, O <= 4; `narrow.rs`).
    Narrow,
    /// Implicit GEMM on weights repacked to (KH, KW, C, O) (O % 4 == 0; `packed.rs`); `hwnc`: the input is
    /// transposed to (H, W, N, C) first.
    Packed { hwnc: bool },
    /// Implicit GEMM on PyTorch-layout weights (any O; `implicit_gemm.rs`).
    ImplicitGemm,
    /// One output per invocation (`direct.rs`): the fallback and the tests' oracle.
    Direct,
}

/// A prepared form of a conv weight (O, C, KH, KW) that a strategy reads instead of the weight itself.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WeightForm {
    /// (KH, KW, C, O) in the weight's dtype ([`super::pack_weight`]).
    Packed,
    /// (products, C, O) f32 ([`super::winograd::transform_weight`]).
    Winograd(Tile),
}

impl WeightForm {
    /// The prepared tensor's shape and dtype for weight w (O, C, KH, KW) stored in `dtype`.
    pub fn shape(self, w: &[usize], dtype: DType) -> (Vec<usize>, DType) {
        match self {
            WeightForm::Packed => (vec![w[2], w[3], w[1], w[0]], dtype),
            WeightForm::Winograd(t) => (super::winograd::weight_shape(w, t).to_vec(), DType::F32),
        }
    }
}

impl Conv2dStrategy {
    /// The prepared weight this strategy reads (it prepares one per call into scratch when none is given).
    pub fn weight_form(self) -> Option<WeightForm> {
        match self {
            Conv2dStrategy::Packed { .. } => Some(WeightForm::Packed),
            Conv2dStrategy::Winograd(t) => Some(WeightForm::Winograd(t)),
            _ => None,
        }
    }

    /// Whether the strategy reads its input through a GroupNorm + SiLU prologue (`Conv2dArgs::pre_gn_silu`).
    pub fn takes_gn_prologue(self) -> bool {
        matches!(self, Conv2dStrategy::Winograd(_) | Conv2dStrategy::Narrow)
    }

    /// Whether the strategy reads x through a nearest 2x upsampling itself (`Conv2dArgs::upsample2x`); the
    /// others get an upsampled copy.
    pub fn reads_upsampled(self) -> bool {
        matches!(self, Conv2dStrategy::Winograd(_))
    }

    /// Whether the strategy can write group-norm statistics partials of its output
    /// (`Conv2dArgs::stats_parts`): F(6x6) Winograd with vec4 output rows.
    fn writes_stats_parts(self, o: usize, ow: usize) -> bool {
        self == Conv2dStrategy::Winograd(Tile::F6) && o % 4 == 0 && ow % 4 == 0
    }
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

/// What the selection needs to know of the device.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Caps<'a> {
    pub dev: &'a DeviceInfo,
    /// The tiled (subgroup) kernels run here (`matmul::tiled_supported`).
    pub tiled: bool,
}

impl<'a> Caps<'a> {
    /// From the device description alone (subgroups of 8 to 64 lanes): for planning before a recorder exists.
    pub fn of_info(dev: &'a DeviceInfo) -> Self {
        Self {
            dev,
            tiled: dev.subgroup_size >= 8 && dev.subgroup_size <= 64,
        }
    }
}

/// The strategy for conv geometry `g` (x: the size the conv reads, after any upsampling) requested as `path`;
/// an error when an explicit path cannot run this conv here.
pub(crate) fn select(path: ConvPath, caps: &Caps, g: &Geometry) -> Result<Conv2dStrategy> {
    use Conv2dStrategy as S;
    let ([n, c, _, _], [o, _, kh, kw], [_, _, oh, ow]) = (g.x, g.w, g.out);
    let k3s1 = kh == 3 && kw == 3 && g.stride == 1;
    let one = kh == 1 && kw == 1 && g.stride == 1 && g.pad == [0; 4] && !g.bias_per_image;
    let implicit = |hwnc: bool| {
        if one {
            S::Gemm1x1
        } else if o % 4 == 0 {
            S::Packed {
                hwnc: hwnc && c % 4 == 0,
            }
        } else {
            S::ImplicitGemm
        }
    };
    Ok(match path {
        ConvPath::Direct => S::Direct,
        ConvPath::Auto if !caps.tiled => S::Direct,
        ConvPath::Auto if narrow_pays(caps.dev, kh, kw, g.stride, o) => S::Narrow,
        ConvPath::Auto if k3s1 && winograd_pays(caps.dev, n, c, o, oh, ow) => {
            S::Winograd(Tile::best(g.dtype, o, oh, ow))
        }
        // the (H, W, N, C) transpose pays off only for wide f16 inputs (see ConvPath::FastHwnc)
        ConvPath::Auto => implicit(g.dtype == DType::F16 && c >= 256),
        ConvPath::Fast => implicit(false),
        ConvPath::FastHwnc => implicit(true),
        ConvPath::Narrow => {
            ensure!(
                k3s1 && o <= 4 && caps.tiled,
                "conv2d: the few-output-channel path needs a 3x3 stride-1 conv with O <= 4 and subgroups of 8 to 64 lanes (x {:?}, w {:?}, stride {})",
                g.x, g.w, g.stride
            );
            S::Narrow
        }
        ConvPath::Winograd | ConvPath::Winograd6 => {
            ensure!(
                k3s1,
                "conv2d: the Winograd path needs a 3x3 stride-1 conv (x {:?}, w {:?}, stride {})",
                g.x,
                g.w,
                g.stride
            );
            ensure!(
                caps.tiled,
                "conv2d: the Winograd path needs subgroups of 8 to 64 lanes, which {:?} lacks",
                caps.dev.name
            );
            S::Winograd(if path == ConvPath::Winograd {
                Tile::F4
            } else {
                Tile::F6
            })
        }
    })
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
    let Ok(g) = Geometry::of_shapes(DType::F32, x, w, stride, pad, false) else {
        return false;
    };
    select(ConvPath::Auto, &Caps::of_info(dev), &g).is_ok_and(|s| s.takes_gn_prologue())
}

/// The shape of the statistics partials (`Conv2dArgs::stats_parts`) that an `Auto` conv of x (N, C, H, W; the
/// size the conv reads, i.e. after an upsampling; stored in `dtype`) with w writes, or None where its path
/// cannot write them (anything but F(6x6) Winograd with vec4 output rows): (N S, O, 4) with
/// S = ceil(OH / 6) ceil(OW / 12) slots (tile pairs) per image.
pub fn stats_parts_shape(
    dev: &DeviceInfo,
    dtype: DType,
    x: &[usize],
    w: &[usize],
    stride: usize,
    pad: [usize; 4],
) -> Option<[usize; 3]> {
    let g = Geometry::of_shapes(dtype, x, w, stride, pad, false).ok()?;
    let s = select(ConvPath::Auto, &Caps::of_info(dev), &g).ok()?;
    let [_, o, oh, ow] = g.out;
    s.writes_stats_parts(o, ow)
        .then(|| [g.x[0] * oh.div_ceil(6) * ow.div_ceil(12), o, 4])
}

/// The prepared weights that `Auto` convs of weight w (O, C, KH, KW) stored in `dtype` with `stride` may read,
/// whatever their input size: the packed weight of the implicit GEMM (kernels larger than 1x1, O % 4 == 0),
/// and on CPU devices, for 3x3 stride-1 convs, the F(4x4) Winograd weight and (f32 only: `Auto` never runs
/// F(6x6) on f16 storage) the F(6x6) one.
pub fn weight_forms(dev: &DeviceInfo, dtype: DType, w: &[usize], stride: usize) -> Vec<WeightForm> {
    let mut v = vec![];
    if w[2] * w[3] > 1 && w[0] % 4 == 0 {
        v.push(WeightForm::Packed);
    }
    if dev.is_cpu() && w[2] == 3 && w[3] == 3 && stride == 1 {
        v.push(WeightForm::Winograd(Tile::F4));
        if dtype == DType::F32 {
            v.push(WeightForm::Winograd(Tile::F6));
        }
    }
    v
}
