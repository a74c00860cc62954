//! Winograd F(4x4, 3x3) and F(6x6, 3x3) for stride-1 3x3 convs (`kernels/winograd/`: 00_common, 10_f4, 20_f6,
//! 30_f6_pairs): input transform,
//! 36 (or 64) batched GEMMs on the tiled matmul, output transform (+ bias, residual, SiLU). F(4x4) does 4x
//! fewer multiply-adds than the implicit GEMM, F(6x6) 5.1x; the transformed tensors are f32 in every mode.
//! Tiles are processed in slabs so the two intermediates stay small (they live in the recorder's scratch
//! buffers, shared by all convs of a recording). Which tile size a conv runs follows from its transformed
//! weight: (36, C, O) is F(4x4), (64, C, O) F(6x6) ([`Tile`]).
use anyhow::{bail, ensure, Result};

use super::{BiasMode, Conv2dArgs, Geometry};
use crate::kernels::params::WinoParams;
use crate::kernels::KernelId as K;
use crate::kernels::{lookup, Variant};
use crate::ops::matmul::{gemm, Gemm, GemmBias, MatmulPath};
use crate::ops::{expect_shape, Recorder, SCRATCH_WINO_M, SCRATCH_WINO_V, SCRATCH_WINO_W};
use crate::tensor::{DType, Tensor};

/// Bytes of each intermediate (V or M) per slab at most. Smaller slabs keep V and M in the CPU's caches
/// between the transforms and the GEMMs: b2dr-tiny's decode on lavapipe took 759-767 ms (median) with 16 MiB
/// slabs, 628-651 ms with 4 MiB (alternating runs, 2026-11-23); 1-3 MiB were slower again (more dispatches).
const SLAB_BYTES: usize = 4 << 20;

/// The Winograd output tile.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Tile {
    /// F(4x4, 3x3): 6x6 input windows, 36 products.
    F4,
    /// F(6x6, 3x3): 8x8 input windows, 64 products.
    F6,
}

impl Tile {
    /// Output tile side.
    pub fn m(self) -> usize {
        match self {
            Tile::F4 => 4,
            Tile::F6 => 6,
        }
    }

    /// Products per tile (the GEMM batch): (m + 2)^2.
    pub fn products(self) -> usize {
        (self.m() + 2) * (self.m() + 2)
    }

    /// The tile size of a transformed weight (products, C, O).
    pub fn of_weight(u: &Tensor) -> Result<Tile> {
        match u.shape().first() {
            Some(36) => Ok(Tile::F4),
            Some(64) => Ok(Tile::F6),
            _ => bail!(
                "conv2d winograd: transformed weight {:?} must be (36 or 64, C, O)",
                u.shape()
            ),
        }
    }

    /// The tile size `Auto` runs for O output channels of OH x OW stored in `dtype`: F(6x6) where its output
    /// transform stores vec4 rows (O % 4 == 0, OW % 4 == 0; with per-pixel stores its transforms cost more
    /// than F(4x4)'s, e.g. the 320-channel 28 x 50 op case 31 ms against 23) and it moves fewer transformed
    /// values (tiles x products, partial tiles counted whole, F(6x6) rows padded to whole tile pairs), else
    /// F(4x4). f16 storage keeps F(4x4): the F(6x6) tile-pair output ran 2.3x slower in f16 than in f32 on
    /// lavapipe 22.3 (b2dr-tiny decode, 32 x 224 x 400 outputs: 172 ms against 69-76; its per-pixel-store
    /// form 76 ms), cause not found, and with per-pixel stores F(6x6) gains nothing over F(4x4).
    pub fn best(dtype: DType, o: usize, oh: usize, ow: usize) -> Tile {
        let cost4 = oh.div_ceil(4) * ow.div_ceil(4) * 36;
        let cost6 = oh.div_ceil(6) * ow.div_ceil(12) * 2 * 64;
        if dtype == DType::F32 && o % 4 == 0 && ow % 4 == 0 && cost6 < cost4 {
            Tile::F6
        } else {
            Tile::F4
        }
    }
}

/// Kernels of one dtype, tile size and prologue choice.
struct Ids {
    /// one channel per invocation (any C)
    input: K,
    /// 4 channels per invocation, rows as vec4 loads (C % 4 == 0, W % 4 == 0, left padding 1, no
    /// upsampling; F6: a tile pair per invocation)
    input4: K,
    /// 4 channels per invocation, scalar loads (C % 4 == 0)
    input4s: K,
    output: K,
    /// 4 output channels per invocation, vec4 rows (O % 4 == 0, OW % 4 == 0; F6: a tile pair per invocation)
    output4: K,
    /// 4 output channels per invocation, per-pixel stores (O % 4 == 0)
    output4s: K,
    weight: K,
}

/// The kernels of one dtype, tile size and prologue choice (`gs`: the input entries with the GroupNorm + SiLU
/// prologue), from the generated lookup of `kernels/winograd/`.
fn ids(d: DType, t: Tile, gs: bool) -> Result<Ids> {
    use lookup::WinogradEntry as E;
    let k = |e: E| {
        lookup::winograd(e, Variant::of(d))
            .ok_or_else(|| anyhow::anyhow!("conv2d winograd: no {d:?} kernel {e:?} compiled"))
    };
    // (input, input4, input4s, output, output4, output4s, weight) entries, with or without the prologue
    let e = match (t, gs) {
        (Tile::F4, false) => [
            E::Input,
            E::Input4,
            E::Input4s,
            E::Output,
            E::Output4,
            E::Output4q,
            E::Weight,
        ],
        (Tile::F4, true) => [
            E::InputGs,
            E::Input4Gs,
            E::Input4sGs,
            E::Output,
            E::Output4,
            E::Output4q,
            E::Weight,
        ],
        (Tile::F6, false) => [
            E::Input6,
            E::Input6p,
            E::Input6s,
            E::Output6,
            E::Output6p,
            E::Output6q,
            E::Weight6,
        ],
        (Tile::F6, true) => [
            E::Input6Gs,
            E::Input6pGs,
            E::Input6sGs,
            E::Output6,
            E::Output6p,
            E::Output6q,
            E::Weight6,
        ],
    };
    Ok(Ids {
        input: k(e[0])?,
        input4: k(e[1])?,
        input4s: k(e[2])?,
        output: k(e[3])?,
        output4: k(e[4])?,
        output4s: k(e[5])?,
        weight: k(e[6])?,
    })
}

/// Shape of the transformed weight of w: (O, C, 3, 3): (products, C, O), always f32.
pub fn weight_shape(w: &[usize], t: Tile) -> [usize; 3] {
    [t.products(), w[1], w[0]]
}

/// w: (O, C, 3, 3) -> u: (products, C, O) f32 = G g G^T per (o, c); the tile size from u's shape.
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
    let t = Tile::of_weight(u)?;
    expect_shape("conv2d winograd", "u", u, &weight_shape(ws, t))?;
    let p = WinoParams {
        o: ws[0] as u32,
        c: ws[1] as u32,
        ..Default::default()
    };
    let g = crate::ops::grid_1d("conv2d winograd weight", ws[0] * ws[1])?;
    rec.dispatch(
        ids(w.dtype(), t, false)?.weight,
        &[w.buffer(), u.buffer()],
        bytemuck::bytes_of(&p),
        g,
        "conv2d winograd weight",
    )
}

/// The conv of `a` (geometry `g`) on `tile`: with the transformed weight `a` carries for that tile, else one
/// transformed into the recording's scratch.
pub(super) fn conv(rec: &mut Recorder, a: &Conv2dArgs, g: &Geometry, tile: Tile) -> Result<()> {
    let given = match tile {
        Tile::F4 => a.wino_w,
        Tile::F6 => a.wino_w6,
    };
    let tmp;
    let u = match given {
        Some(u) => u,
        None => {
            let sh = weight_shape(&g.w, tile);
            let b = rec.scratch(SCRATCH_WINO_W, (sh.iter().product::<usize>() * 4) as u64)?;
            tmp = Tensor::on_buffer(b, &sh, DType::F32)?;
            transform_weight(rec, a.w, &tmp)?;
            &tmp
        }
    };
    conv3x3(rec, a, u)
}

/// out = conv3x3(x, w) (+ bias (O) or (N, O)) (+ residual) (then SiLU), stride 1, padding (top, bottom, left,
/// right) each <= 2, with u the transformed weight ([`transform_weight`], F(4x4) or F(6x6) by its shape);
/// everything but `w` from `a`. Shapes were checked by the caller (`conv2d_ex`).
fn conv3x3(rec: &mut Recorder, a: &Conv2dArgs, u: &Tensor) -> Result<()> {
    let (x, bias, residual, silu, out, pad) = (a.x, a.bias, a.residual, a.silu, a.out, a.pad);
    let (xs, os) = (x.shape(), out.shape());
    // the conv's input size (twice the stored one when x is read through a 2x upsampling)
    let up = a.upsample2x as usize;
    let [n, c, h, w] = [xs[0], xs[1], xs[2] << up, xs[3] << up];
    let (o, oh, ow) = (os[1], os[2], os[3]);
    let t = Tile::of_weight(u)?;
    let np = t.products();
    expect_shape("conv2d winograd", "u", u, &[np, c, o])?;
    // F6 runs on horizontal tile pairs: an even tile count per row (a phantom last tile computes on the
    // padding and stores nothing), slabs of whole pairs
    let pairs = t == Tile::F6;
    let (th, mut tw) = (oh.div_ceil(t.m()), ow.div_ceil(t.m()));
    if pairs {
        tw += tw % 2;
    }
    let tiles = n * th * tw;
    let per_tile = np * c.max(o) * 4;
    let mut slab = (SLAB_BYTES / per_tile).clamp(1, tiles);
    if pairs {
        slab = (slab - slab % 2).max(2);
    }
    let k = ids(x.dtype(), t, a.pre_gn_silu.is_some())?;
    // the prologue's statistics (binding 2 of every input entry; x when there is no prologue)
    let ss = a.pre_gn_silu.unwrap_or(x);
    // 4-channel transforms (fewer per-lane access loops on lavapipe) where the layout allows: input
    // C % 4 == 0 (F4: rows loaded as vec4s too when W % 4 == 0 and the left padding is 1); output O % 4 == 0
    // (F4: and OW % 4 == 0)
    let in4 = c % 4 == 0 && w % 4 == 0 && pad[2] == 1 && !a.upsample2x;
    let per_inv = if pairs { 2 } else { 1 };
    // (kernel, invocations per slab tile x per_inv)
    let (inp, in_items) = if in4 {
        (k.input4, c / 4)
    } else if c % 4 == 0 {
        (k.input4s, c / 4 * per_inv)
    } else {
        (k.input, c * per_inv)
    };
    let (outp, out_items) = if o % 4 == 0 && ow % 4 == 0 {
        (k.output4, o / 4)
    } else if o % 4 == 0 {
        (k.output4s, o / 4 * per_inv)
    } else {
        (k.output, o * per_inv)
    };
    // per-kernel labels: `--profile` then splits the transforms' time by kernel and size
    let info = |id: K| id.info().entry;
    let in_label = format!("conv2d winograd in {} {c}x{h}x{w}", info(inp));
    let out_label = format!("conv2d winograd out {} {o}x{oh}x{ow}", info(outp));
    if let Some(pt) = a.stats_parts {
        ensure!(
            outp == k.output4 && pairs,
            "conv2d winograd: statistics partials need the F(6x6) vec4-row output (O % 4 == 0, OW % 4 == 0; x {xs:?}, out {os:?})"
        );
        ensure!(
            pt.dtype() == DType::F32,
            "conv2d winograd: statistics partials must be f32"
        );
        expect_shape("conv2d winograd", "stats_parts", pt, &[tiles / 2, o, 4])?;
    }
    let parts_t = a.stats_parts.unwrap_or(out);
    let vb = rec.scratch(SCRATCH_WINO_V, (np * slab * c * 4) as u64)?;
    let mb = rec.scratch(SCRATCH_WINO_M, (np * slab * o * 4) as u64)?;
    let bias_t = bias.unwrap_or(x);
    let has_bias = BiasMode::of(bias).code();
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
            stats: a.stats_parts.is_some() as u32,
        };
        let g = crate::ops::grid_1d("conv2d winograd", nt / per_inv * in_items)?;
        // input4 also reads x through a scalar view (binding 3)
        let in_bufs: &[&std::sync::Arc<crate::vk::Buffer>] = if in4 {
            &[x.buffer(), &vb, ss.buffer(), x.buffer()]
        } else {
            &[x.buffer(), &vb, ss.buffer()]
        };
        let bufs: Vec<&crate::vk::Buffer> = in_bufs.iter().map(|b| b.as_ref()).collect();
        let inp = crate::ops::texel_variant(rec, inp, &bufs).unwrap_or(inp);
        rec.dispatch(inp, in_bufs, bytemuck::bytes_of(&p), g, &in_label)?;
        // 36 (64) GEMMs: (nt, C) . (C, O) -> (nt, O)
        let gm = Gemm {
            m: nt,
            n: o,
            k: c,
            batch: np,
            sa: nt * c,
            sb: c * o,
            trans_b: false,
            bias: GemmBias::None,
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
        let g = crate::ops::grid_1d("conv2d winograd", nt / per_inv * out_items)?;
        // m, bias, y, residual, the statistics partials (output6p): as many as the kernel binds
        let bufs = [
            &mb,
            bias_t.buffer(),
            out.buffer(),
            res_t.buffer(),
            parts_t.buffer(),
        ];
        // m (and the residual) through texel views where the device has them (CPU devices: one fetch per
        // lane per vec4)
        let views: Vec<&crate::vk::Buffer> = bufs.iter().map(|b| b.as_ref()).collect();
        let outp = crate::ops::texel_variant(rec, outp, &views).unwrap_or(outp);
        let nb = outp.info().bindings.len();
        rec.dispatch(outp, &bufs[..nb], bytemuck::bytes_of(&p), g, &out_label)?;
        t0 += nt;
    }
    Ok(())
}
