//! Matmul / linear launchers: batched C = A B (+ bias) with B as (K, N) or transposed (N, K) (PyTorch Linear
//! weight layout), f32 or f16 storage with f32 accumulation.
//!
//! Two kernels: the register-tiled one (`kernels/matmul.wgsl`, needs subgroups of 8..64 lanes) and the
//! direct one (`kernels/matmul_direct.wgsl`, one output per invocation), kept as fallback and test oracle.
//!
//! f16 overflow policy: kernels accumulate in f32; an f16 output whose value exceeds 65504 in magnitude is
//! stored saturated to +-65504 (never Inf; NaN inputs still give NaN). The launcher cannot know values, so a
//! caller that needs to know passes an `overflow` flag tensor (f32, shape [1], zeroed by the caller): the
//! kernel sets it to 1.0 when any output saturated.
use anyhow::{bail, ensure, Result};

use super::{expect_shape, same_dtype, Recorder};
use crate::kernels::params::MatmulParams;
use crate::kernels::KernelId as K;
use crate::kernels::{lookup, Variant};
use crate::tensor::{DType, Tensor};
use crate::vk::Buffer;

/// Which kernel runs a matmul.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum MatmulPath {
    /// The tiled kernel when the device supports it, else the direct one.
    #[default]
    Auto,
    /// The register-tiled kernel (error if unsupported).
    Tiled,
    /// The direct kernel (one output per invocation).
    Direct,
}

/// Work-group size and rows per subgroup (TM) of the tiled kernels (matmul.wgsl, conv2d.wgsl).
pub(crate) const TILED_WG: usize = 64;
pub(crate) const TILED_TM: usize = 16;

/// (rows, columns) of one work group's output tile: (WG / SG) TM rows x 4 SG columns.
pub(crate) fn tile_shape(rec: &Recorder) -> (usize, usize) {
    let sg = rec.context().info().subgroup_size as usize;
    (TILED_WG / sg * TILED_TM, 4 * sg)
}

/// The bias of a GEMM's epilogue (`MatmulParams::bias_mode` of matmul.wgsl).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum GemmBias {
    None,
    /// One value per output column (n): a linear layer's bias.
    PerColumn,
    /// One value per output row (m): a conv's per-channel bias when rows are channels.
    PerRow,
}

impl GemmBias {
    pub fn per_column(present: bool) -> Self {
        if present {
            GemmBias::PerColumn
        } else {
            GemmBias::None
        }
    }

    pub fn per_row(present: bool) -> Self {
        if present {
            GemmBias::PerRow
        } else {
            GemmBias::None
        }
    }

    /// The kernel's code (`bias_mode` in matmul.wgsl).
    pub fn code(self) -> u32 {
        match self {
            GemmBias::None => 0,
            GemmBias::PerColumn => 1,
            GemmBias::PerRow => 2,
        }
    }
}

/// A GEMM on raw buffers: C[z] = A[z] B[z] (+ bias); used by [`matmul_ex`] and by conv2d (1x1 convs).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Gemm {
    pub m: usize,
    pub n: usize,
    pub k: usize,
    pub batch: usize,
    /// Batch strides in elements (0 = shared operand).
    pub sa: usize,
    pub sb: usize,
    /// B given as (N, K).
    pub trans_b: bool,
    pub bias: GemmBias,
    /// Add the residual buffer (laid out as C) in the epilogue.
    pub res: bool,
    pub dtype: DType,
    pub path: MatmulPath,
}

/// B load width of the tiled kernels: scalar, 4-element (vec4) or 8-element rows.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Width {
    W1,
    W4,
    W8,
    /// W4 (nn) / W8 (nt) plus vec4 loads of A (K % 4 == 0): 32-k chunks
    Wide,
    /// Wide with N % 4 == 0: nt lanes own 4 consecutive columns, stored as vec4s
    Wide4,
}

/// The kernel of a GEMM: the direct or tiled file, the entry from the layout and load width, the variant from
/// the dtype and whether an f16 overflow flag is written (f32 never writes one).
fn kernel(d: DType, checked: bool, tiled: bool, trans: bool, w: Width) -> Result<K> {
    use lookup::{MatmulDirectEntry as D, MatmulEntry as E};
    use Width::*;
    let v = Variant {
        overflow_flag: checked && d == DType::F16,
        ..Variant::of(d)
    };
    let id = if tiled {
        let e = match (trans, w) {
            (false, W1) => E::Nn,
            (false, W4 | W8) => E::Nn4,
            (false, Wide | Wide4) => E::Nn4a,
            (true, W1) => E::Nt,
            (true, W4) => E::Nt4,
            (true, W8) => E::Nt8,
            (true, Wide) => E::Nt8a,
            (true, Wide4) => E::Nt8a4,
        };
        lookup::matmul(e, v)
    } else {
        lookup::matmul_direct(if trans { D::Nt } else { D::Nn }, v)
    };
    id.ok_or_else(|| {
        anyhow::anyhow!("matmul: no kernel compiled for {v:?} (tiled {tiled}, nt {trans})")
    })
}

/// Whether the tiled kernels can run here (subgroup broadcast, 8 <= subgroup size <= 64 dividing 64).
pub fn tiled_supported(rec: &Recorder) -> bool {
    tiled_supported_on(rec.context())
}

/// [`tiled_supported`] for a context.
pub fn tiled_supported_on(ctx: &crate::vk::Context) -> bool {
    let sg = ctx.info().subgroup_size as usize;
    ctx.supports(K::MatmulF32Nn) && (8..=TILED_WG).contains(&sg) && TILED_WG % sg == 0
}

/// Records one GEMM. Buffers: a, b, bias (any buffer when `g.bias` is `None`), c, residual (any buffer unless
/// `g.res`; may be c itself), optional overflow flag.
pub(crate) fn gemm(
    rec: &mut Recorder,
    op: &str,
    g: &Gemm,
    bufs: [&std::sync::Arc<Buffer>; 5],
    flag: Option<&std::sync::Arc<Buffer>>,
) -> Result<()> {
    let tiled = match g.path {
        MatmulPath::Direct => false,
        MatmulPath::Tiled => {
            ensure!(
                tiled_supported(rec),
                "{op}: the tiled matmul needs subgroups of 8 to 64 lanes, which {:?} lacks",
                rec.context().info().name
            );
            true
        }
        MatmulPath::Auto => tiled_supported(rec),
    };
    // vector loads need rows (and batch strides) of B aligned to their width
    let row = if g.trans_b { g.k } else { g.n };
    // 32-k chunks with vec4 A loads pay when few of a chunk's loads fall past K: with K = 16 half the chunk's
    // A and B loads are wasted, and the 8-k kernels do fewer loads (lavapipe counts every loaded component)
    let a_vec4 = g.k % 4 == 0 && g.sa % 4 == 0 && (g.k % 32 == 0 || g.k >= 64);
    let width = if g.trans_b && row % 8 == 0 && g.sb % 8 == 0 {
        if a_vec4 && g.n % 4 == 0 {
            Width::Wide4
        } else if a_vec4 {
            Width::Wide
        } else {
            Width::W8
        }
    } else if row % 4 == 0 && g.sb % 4 == 0 {
        if !g.trans_b && a_vec4 {
            Width::Wide
        } else {
            Width::W4
        }
    } else {
        Width::W1
    };
    ensure!(
        g.dtype == DType::F16 || flag.is_none(),
        "{op}: an overflow flag is only meaningful for f16 outputs"
    );
    let id = kernel(g.dtype, flag.is_some(), tiled, g.trans_b, width)?;
    // A and B through their texel views where the kernel has such a variant (CPU devices)
    let id = super::texel_variant(rec, id, &[bufs[0], bufs[1]]).unwrap_or(id);
    let p = MatmulParams {
        m: g.m as u32,
        n: g.n as u32,
        k: g.k as u32,
        sa: g.sa as u32,
        sb: g.sb as u32,
        bias_mode: g.bias.code(),
        batch: g.batch as u32,
        res: g.res as u32,
    };
    let groups = if tiled {
        let (rows, cols) = tile_shape(rec);
        [
            g.n.div_ceil(cols) as u32,
            g.m.div_ceil(rows) as u32,
            g.batch as u32,
        ]
    } else {
        super::grid_1d(op, g.batch * g.m * g.n)?
    };
    ensure!(
        groups.iter().all(|&x| x <= 65535),
        "{op}: ({}, {}, {}) x {} is too large for one dispatch",
        g.batch,
        g.m,
        g.n,
        g.k
    );
    let mut b: Vec<&std::sync::Arc<Buffer>> = bufs.to_vec();
    if let Some(f) = flag {
        b.push(f);
    }
    // per-shape label: `--profile` then splits GEMM time by shape
    let label = format!("{op} {}x{}x{}x{}", g.batch, g.m, g.n, g.k);
    rec.dispatch(id, &b, bytemuck::bytes_of(&p), groups, &label)
}

/// Arguments of [`matmul_ex`].
#[derive(Clone, Copy, Debug)]
pub struct MatmulArgs<'a> {
    /// (M, K) or (B, M, K)
    pub a: &'a Tensor,
    /// (K, N) / (B, K, N), or with `transpose_b` (N, K) / (B, N, K)
    pub b: &'a Tensor,
    /// (N), added to every row
    pub bias: Option<&'a Tensor>,
    /// (M, N) when neither operand is batched, else (B, M, N)
    pub out: &'a Tensor,
    pub transpose_b: bool,
    pub path: MatmulPath,
    /// f16 only: f32 tensor of shape [1], set to 1.0 if any output saturated at +-65504.
    pub overflow: Option<&'a Tensor>,
    /// Shaped as `out`, added to the result in the GEMM's epilogue (a fused residual connection). It may be
    /// `out` itself.
    pub residual: Option<&'a Tensor>,
}

impl<'a> MatmulArgs<'a> {
    /// out = a b: no bias, b not transposed, path `Auto`, no overflow flag or residual (set those with struct
    /// update syntax: `MatmulArgs { transpose_b: true, ..MatmulArgs::new(a, b, out) }`).
    pub fn new(a: &'a Tensor, b: &'a Tensor, out: &'a Tensor) -> Self {
        Self {
            a,
            b,
            bias: None,
            out,
            transpose_b: false,
            path: MatmulPath::Auto,
            overflow: None,
            residual: None,
        }
    }
}

/// out = a b (+ bias), see [`MatmulArgs`] for shapes. Batched operands broadcast against unbatched ones.
pub fn matmul_ex(rec: &mut Recorder, x: &MatmulArgs) -> Result<()> {
    let op = if x.transpose_b {
        "matmul(b^T)"
    } else {
        "matmul"
    };
    let mut ts = vec![x.a, x.b, x.out];
    ts.extend(x.bias);
    ts.extend(x.residual);
    let d = same_dtype(op, &ts)?;
    let (sa, sb) = (x.a.shape(), x.b.shape());
    let split = |s: &[usize], what: &str| -> Result<(usize, usize, usize, bool)> {
        match *s {
            [r, c] => Ok((1, r, c, false)),
            [bt, r, c] => Ok((bt, r, c, true)),
            _ => bail!("{op}: {what} must be 2-D or 3-D, got {s:?} (a {sa:?}, b {sb:?})"),
        }
    };
    let (ba, m, k, a3) = split(sa, "a")?;
    let (bb, r1, r2, b3) = split(sb, "b")?;
    let (kb, n) = if x.transpose_b { (r2, r1) } else { (r1, r2) };
    ensure!(
        k == kb,
        "{op}: inner dimensions differ: a {sa:?}, b {sb:?} (K {k} vs {kb})"
    );
    ensure!(
        !(a3 && b3) || ba == bb,
        "{op}: batch sizes differ: a {sa:?}, b {sb:?}"
    );
    let batch = ba.max(bb);
    let want: Vec<usize> = if a3 || b3 {
        vec![batch, m, n]
    } else {
        vec![m, n]
    };
    expect_shape(op, "out", x.out, &want)?;
    if let Some(bias) = x.bias {
        expect_shape(op, "bias", bias, &[n])?;
    }
    if let Some(r) = x.residual {
        expect_shape(op, "residual", r, &want)?;
    }
    if let Some(f) = x.overflow {
        ensure!(
            f.dtype() == DType::F32 && f.shape() == [1],
            "{op}: the overflow flag must be an f32 tensor of shape [1], got {:?} {}",
            f.shape(),
            f.dtype().name()
        );
    }
    let g = Gemm {
        m,
        n,
        k,
        batch,
        sa: if a3 { m * k } else { 0 },
        sb: if b3 { k * n } else { 0 },
        trans_b: x.transpose_b,
        bias: GemmBias::per_column(x.bias.is_some()),
        res: x.residual.is_some(),
        dtype: d,
        path: x.path,
    };
    let bias = x.bias.unwrap_or(x.a);
    let res = x.residual.unwrap_or(x.out);
    gemm(
        rec,
        op,
        &g,
        [
            x.a.buffer(),
            x.b.buffer(),
            bias.buffer(),
            x.out.buffer(),
            res.buffer(),
        ],
        x.overflow.map(|f| f.buffer()),
    )
}

/// a: (B?, M, K) x b: (B?, K, N) (+ bias (N)) -> out: (B?, M, N)
pub fn matmul(
    rec: &mut Recorder,
    a: &Tensor,
    b: &Tensor,
    bias: Option<&Tensor>,
    out: &Tensor,
) -> Result<()> {
    matmul_ex(
        rec,
        &MatmulArgs {
            bias,
            ..MatmulArgs::new(a, b, out)
        },
    )
}

/// PyTorch Linear: x: (.., in) x w: (out, in)^T (+ bias (out)) -> out: (.., out). Leading dims of x are
/// flattened into rows.
pub fn linear(
    rec: &mut Recorder,
    x: &Tensor,
    w: &Tensor,
    bias: Option<&Tensor>,
    out: &Tensor,
) -> Result<()> {
    linear_residual(rec, x, w, bias, None, out)
}

/// [`linear`] + residual (shaped as out; may be out itself), added in the GEMM's epilogue: one pass instead
/// of a linear and an add.
pub fn linear_residual(
    rec: &mut Recorder,
    x: &Tensor,
    w: &Tensor,
    bias: Option<&Tensor>,
    residual: Option<&Tensor>,
    out: &Tensor,
) -> Result<()> {
    let (xs, ws) = (x.shape(), w.shape());
    ensure!(
        ws.len() == 2 && !xs.is_empty() && xs[xs.len() - 1] == ws[1],
        "linear: x {xs:?} and weight {ws:?} (out, in) do not match"
    );
    let mut os = xs.to_vec();
    *os.last_mut().expect("non-empty") = ws[0];
    expect_shape("linear", "out", out, &os)?;
    let rows = x.numel() / ws[1];
    let (a, o) = (x.reshape(&[rows, ws[1]])?, out.reshape(&[rows, ws[0]])?);
    let r = residual
        .map(|r| {
            expect_shape("linear", "residual", r, &os)?;
            r.reshape(&[rows, ws[0]])
        })
        .transpose()?;
    matmul_ex(
        rec,
        &MatmulArgs {
            bias,
            transpose_b: true,
            residual: r.as_ref(),
            ..MatmulArgs::new(&a, w, &o)
        },
    )
}

/// Tokens back to channels-first through a linear layer: tokens (N, L, C), w (O, C) (+ bias (O)) (+ residual
/// (N, O, L)) -> out (N, O, L) = w tokens[n]^T per image: a transformer's output projection straight into the
/// NCHW layout (no transpose pass), with the block's residual added in the GEMM's epilogue. `out` may be given
/// as (N, O, H, W).
pub fn linear_to_channels(
    rec: &mut Recorder,
    tokens: &Tensor,
    w: &Tensor,
    bias: Option<&Tensor>,
    residual: Option<&Tensor>,
    out: &Tensor,
) -> Result<()> {
    let op = "linear_to_channels";
    let (ts, ws) = (tokens.shape(), w.shape());
    ensure!(
        ts.len() == 3 && ws.len() == 2 && ts[2] == ws[1],
        "{op}: tokens {ts:?} must be (N, L, C) and w {ws:?} (O, C)"
    );
    let (n, l, c, o) = (ts[0], ts[1], ts[2], ws[0]);
    ensure!(
        out.numel() == n * o * l && out.shape().first() == Some(&n) && out.shape().get(1) == Some(&o),
        "{op}: out {:?} must be ({n}, {o}, {l}) or ({n}, {o}, H, W) with H W = {l} (tokens {ts:?}, w {ws:?})",
        out.shape()
    );
    let mut all = vec![tokens, w, out];
    all.extend(bias);
    all.extend(residual);
    let d = same_dtype(op, &all)?;
    if let Some(b) = bias {
        expect_shape(op, "bias", b, &[o])?;
    }
    if let Some(r) = residual {
        expect_shape(op, "residual", r, out.shape())?;
    }
    let g = Gemm {
        m: o,
        n: l,
        k: c,
        batch: n,
        sa: 0,
        sb: l * c,
        trans_b: true,
        bias: GemmBias::per_row(bias.is_some()),
        res: residual.is_some(),
        dtype: d,
        path: MatmulPath::Auto,
    };
    let b = bias.unwrap_or(w);
    let r = residual.unwrap_or(out);
    gemm(
        rec,
        op,
        &g,
        [
            w.buffer(),
            tokens.buffer(),
            b.buffer(),
            out.buffer(),
            r.buffer(),
        ],
        None,
    )
}

/// Row order of a GEGLU feed-forward's first linear weight (2 D, K) for [`linear_geglu`] on a device with
/// subgroups of `sg` lanes: `perm[new] = old`, the same for the bias. None when the fused kernel cannot take
/// the shape (D % (2 sg) != 0).
pub fn geglu_permutation(two_d: usize, sg: usize) -> Option<Vec<usize>> {
    if sg == 0 || two_d % (4 * sg) != 0 {
        return None;
    }
    let d = two_d / 2;
    Some(
        (0..two_d)
            .map(|p| {
                let (b, q) = (p / (4 * sg), p % (4 * sg));
                let (j, l) = (q / sg, q % sg);
                (j % 2) * d + b * 2 * sg + (j / 2) * sg + l
            })
            .collect(),
    )
}

/// Whether [`linear_geglu`] runs here for x (.., K) and a weight of 2 D rows: tiled kernels, K % 8 == 0 and
/// D % (2 subgroup size) == 0.
pub fn geglu_fusable(ctx: &crate::vk::Context, k: usize, two_d: usize) -> bool {
    let sg = ctx.info().subgroup_size as usize;
    tiled_supported_on(ctx) && k % 8 == 0 && geglu_permutation(two_d, sg).is_some()
}

/// GEGLU feed-forward input in one pass: x (.., K), w_perm (2 D, K) and bias_perm (2 D) in the order of
/// [`geglu_permutation`] -> out (.., D) = a * gelu(g) with [a | g] = x W^T + bias (diffusers GEGLU, erf GELU).
/// Errors where [`geglu_fusable`] is false (callers then run [`linear`] and `elementwise::geglu`).
pub fn linear_geglu(
    rec: &mut Recorder,
    x: &Tensor,
    w_perm: &Tensor,
    bias_perm: Option<&Tensor>,
    out: &Tensor,
) -> Result<()> {
    let op = "linear_geglu";
    let (xs, ws) = (x.shape(), w_perm.shape());
    ensure!(
        ws.len() == 2 && !xs.is_empty() && xs[xs.len() - 1] == ws[1] && ws[0] % 2 == 0,
        "{op}: x {xs:?} and weight {ws:?} (2 D, in) do not match"
    );
    let mut os = xs.to_vec();
    *os.last_mut().expect("non-empty") = ws[0] / 2;
    expect_shape(op, "out", out, &os)?;
    let mut all = vec![x, w_perm, out];
    all.extend(bias_perm);
    let d = same_dtype(op, &all)?;
    if let Some(b) = bias_perm {
        expect_shape(op, "bias", b, &[ws[0]])?;
    }
    ensure!(
        geglu_fusable(rec.context(), ws[1], ws[0]),
        "{op}: needs subgroups, K % 8 == 0 and D a multiple of twice the subgroup size (x {xs:?}, w {ws:?})"
    );
    let m = x.numel() / ws[1];
    let p = MatmulParams {
        m: m as u32,
        n: ws[0] as u32,
        k: ws[1] as u32,
        sa: 0,
        sb: 0,
        bias_mode: GemmBias::per_column(bias_perm.is_some()).code(),
        batch: 1,
        res: 0,
    };
    let (rows, cols) = tile_shape(rec);
    let groups = [ws[0].div_ceil(cols) as u32, m.div_ceil(rows) as u32, 1];
    ensure!(
        groups.iter().all(|&g| g <= 65535),
        "{op}: x {xs:?} is too large for one dispatch"
    );
    let id = match d {
        DType::F32 => K::MatmulF32Nt8aGeglu,
        DType::F16 => K::MatmulF16Nt8aGeglu,
    };
    let b = bias_perm.unwrap_or(w_perm);
    let label = format!("{op} {}x{}x{}", m, ws[0], ws[1]);
    rec.dispatch(
        id,
        &[
            x.buffer(),
            w_perm.buffer(),
            b.buffer(),
            out.buffer(),
            out.buffer(),
        ],
        bytemuck::bytes_of(&p),
        groups,
        &label,
    )
}
