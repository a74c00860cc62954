//! Elementwise launchers: silu, gelu (erf), relu, to_unit, add/mul with broadcasting, scale-and-add, GEGLU, channel concat.
use anyhow::{ensure, Result};

use super::{expect_shape, grid_1d, pick, same_dtype, Recorder};
use crate::kernels::params::{
    BinaryParams, ConcatParams, GegluParams, LinCombParams, ScaleAddParams, TransposeParams,
    UnaryParams,
};
use crate::kernels::KernelId as K;
use crate::tensor::Tensor;

fn unary(rec: &mut Recorder, name: &str, op: u32, x: &Tensor, out: &Tensor) -> Result<()> {
    let d = same_dtype(name, &[x, out])?;
    expect_shape(name, "out", out, x.shape())?;
    // 4 elements per invocation when the count allows (vec4 accesses, see elementwise.wgsl)
    let v4 = x.numel() % 4 == 0;
    let n = if v4 { x.numel() / 4 } else { x.numel() };
    let p = UnaryParams { n: n as u32, op };
    let k = if v4 {
        pick(d, K::ElementwiseF32Unary4, K::ElementwiseF16Unary4)
    } else {
        pick(d, K::ElementwiseF32Unary, K::ElementwiseF16Unary)
    };
    rec.dispatch(
        k,
        &[x.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        grid_1d(name, n)?,
        name,
    )
}

/// out = x * sigmoid(x)
pub fn silu(rec: &mut Recorder, x: &Tensor, out: &Tensor) -> Result<()> {
    unary(rec, "silu", 0, x, out)
}

/// out = 0.5 x (1 + erf(x / sqrt 2))
pub fn gelu(rec: &mut Recorder, x: &Tensor, out: &Tensor) -> Result<()> {
    unary(rec, "gelu", 1, x, out)
}

/// out = max(x, 0)
pub fn relu(rec: &mut Recorder, x: &Tensor, out: &Tensor) -> Result<()> {
    unary(rec, "relu", 2, x, out)
}

/// out = clamp(x / 2 + 0.5, 0, 1): a decoded image in [-1, 1] to [0, 1] (`x * 0.5 + 0.5` in f32, then clamped)
pub fn to_unit(rec: &mut Recorder, x: &Tensor, out: &Tensor) -> Result<()> {
    unary(rec, "to_unit", 3, x, out)
}

/// Right-aligned broadcast of `s` to `out` (<= 4 dims): element strides, 0 on broadcast dimensions.
fn bcast_strides(op: &str, s: &[usize], out: &[usize]) -> Result<[u32; 4]> {
    ensure!(
        s.len() <= out.len(),
        "{op}: operand {s:?} has more dims than the output {out:?}"
    );
    let mut st = [0u32; 4];
    let mut acc = 1usize;
    for k in 0..s.len() {
        let (si, oi) = (s[s.len() - 1 - k], out[out.len() - 1 - k]);
        ensure!(
            si == oi || si == 1,
            "{op}: cannot broadcast {s:?} to {out:?}"
        );
        st[3 - k] = if si == 1 { 0 } else { acc as u32 };
        acc *= si;
    }
    Ok(st)
}

/// Merges adjacent output dimensions that both operands traverse the same way (contiguously, or both
/// broadcast), keeping 4 right-aligned dims: e.g. a (N, C, H, W) + (N, C, 1, 1) add becomes (1, 1, N C, H W),
/// so the last dimension is long enough for the vec4 kernel.
fn merge_dims(o: [usize; 4], sa: [u32; 4], sb: [u32; 4]) -> ([usize; 4], [u32; 4], [u32; 4]) {
    let mut dims: Vec<(usize, u32, u32)> = vec![];
    for k in 0..4 {
        if o[k] == 1 {
            continue;
        }
        if let Some(last) = dims.last_mut() {
            let d = o[k] as u32;
            if last.1 == sa[k] * d && last.2 == sb[k] * d {
                *last = (last.0 * o[k], sa[k], sb[k]);
                continue;
            }
        }
        dims.push((o[k], sa[k], sb[k]));
    }
    if dims.is_empty() {
        // every dimension is 1
        return (o, sa, sb);
    }
    let (mut no, mut na, mut nb) = ([1usize; 4], [0u32; 4], [0u32; 4]);
    let off = 4 - dims.len();
    for (i, (d, x, y)) in dims.into_iter().enumerate() {
        no[off + i] = d;
        na[off + i] = x;
        nb[off + i] = y;
    }
    (no, na, nb)
}

/// Broadcast shape of two shapes (numpy rules).
pub fn broadcast_shape(op: &str, a: &[usize], b: &[usize]) -> Result<Vec<usize>> {
    let n = a.len().max(b.len());
    let mut out = vec![0; n];
    for k in 0..n {
        let x = if k < a.len() { a[a.len() - 1 - k] } else { 1 };
        let y = if k < b.len() { b[b.len() - 1 - k] } else { 1 };
        ensure!(
            x == y || x == 1 || y == 1,
            "{op}: shapes {a:?} and {b:?} do not broadcast"
        );
        out[n - 1 - k] = x.max(y);
    }
    Ok(out)
}

fn binary(
    rec: &mut Recorder,
    name: &str,
    op: u32,
    a: &Tensor,
    b: &Tensor,
    out: &Tensor,
) -> Result<()> {
    let d = same_dtype(name, &[a, b, out])?;
    let shape = broadcast_shape(name, a.shape(), b.shape())?;
    expect_shape(name, "out", out, &shape)?;
    ensure!(shape.len() <= 4, "{name}: at most 4 dims, got {shape:?}");
    let mut o = [1usize; 4];
    o[4 - shape.len()..].copy_from_slice(&shape);
    let sa = bcast_strides(name, a.shape(), &shape)?;
    let sb = bcast_strides(name, b.shape(), &shape)?;
    let (o, sa, sb) = merge_dims(o, sa, sb);
    // vec4 kernel: whole vec4s along the last dimension, each operand contiguous (aligned) or broadcast there
    let vec_ok = |s: &[u32; 4]| s[3] == 0 || (s[3] == 1 && s[..3].iter().all(|&x| x % 4 == 0));
    let v4 = o[3] % 4 == 0 && vec_ok(&sa) && vec_ok(&sb);
    let n = if v4 { out.numel() / 4 } else { out.numel() };
    let p = BinaryParams {
        op,
        n: n as u32,
        d1: o[1] as u32,
        d2: o[2] as u32,
        d3: o[3] as u32,
        sa0: sa[0],
        sa1: sa[1],
        sa2: sa[2],
        sa3: sa[3],
        sb0: sb[0],
        sb1: sb[1],
        sb2: sb[2],
        sb3: sb[3],
    };
    let k = if v4 {
        pick(d, K::ElementwiseF32Binary4, K::ElementwiseF16Binary4)
    } else {
        pick(d, K::ElementwiseF32Binary, K::ElementwiseF16Binary)
    };
    rec.dispatch(
        k,
        &[a.buffer(), b.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        grid_1d(name, n)?,
        name,
    )
}

/// out = a + b (numpy broadcasting, <= 4 dims)
pub fn add(rec: &mut Recorder, a: &Tensor, b: &Tensor, out: &Tensor) -> Result<()> {
    binary(rec, "add", 0, a, b, out)
}

/// out = a * b (numpy broadcasting, <= 4 dims)
pub fn mul(rec: &mut Recorder, a: &Tensor, b: &Tensor, out: &Tensor) -> Result<()> {
    binary(rec, "mul", 1, a, b, out)
}

/// out = alpha * x + beta * y (same shapes). `out` may not alias `x` or `y`.
pub fn scale_add(
    rec: &mut Recorder,
    alpha: f32,
    x: &Tensor,
    beta: f32,
    y: &Tensor,
    out: &Tensor,
) -> Result<()> {
    let d = same_dtype("scale_add", &[x, y, out])?;
    expect_shape("scale_add", "y", y, x.shape())?;
    expect_shape("scale_add", "out", out, x.shape())?;
    let p = ScaleAddParams {
        n: x.numel() as u32,
        alpha,
        beta,
    };
    let k = pick(d, K::ElementwiseF32ScaleAdd, K::ElementwiseF16ScaleAdd);
    let g = grid_1d("scale_add", x.numel())?;
    rec.dispatch(
        k,
        &[x.buffer(), y.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        g,
        "scale_add",
    )
}

/// x: (.., 2d) -> out: (.., d) = x[.., :d] * gelu(x[.., d:])
pub fn geglu(rec: &mut Recorder, x: &Tensor, out: &Tensor) -> Result<()> {
    let d = same_dtype("geglu", &[x, out])?;
    let s = x.shape();
    let last = *s.last().unwrap_or(&0);
    ensure!(last % 2 == 0, "geglu: last dim of {s:?} must be even");
    let mut os = s.to_vec();
    *os.last_mut().expect("non-empty") = last / 2;
    expect_shape("geglu", "out", out, &os)?;
    let p = GegluParams {
        rows: (x.numel() / last) as u32,
        d: (last / 2) as u32,
    };
    // vec4 kernel when the half width is a whole number of vec4s
    let (k, n) = if last % 8 == 0 {
        (
            pick(d, K::ElementwiseF32Geglu4, K::ElementwiseF16Geglu4),
            out.numel() / 4,
        )
    } else {
        (
            pick(d, K::ElementwiseF32Geglu, K::ElementwiseF16Geglu),
            out.numel(),
        )
    };
    rec.dispatch(
        k,
        &[x.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        grid_1d("geglu", n)?,
        "geglu",
    )
}

/// a: (N, C1, H, W), b: (N, C2, H, W) -> out: (N, C1 + C2, H, W)
pub fn concat_channels(rec: &mut Recorder, a: &Tensor, b: &Tensor, out: &Tensor) -> Result<()> {
    let d = same_dtype("concat", &[a, b, out])?;
    let (sa, sb) = (a.shape(), b.shape());
    ensure!(
        sa.len() == 4 && sb.len() == 4 && sa[0] == sb[0] && sa[2..] == sb[2..],
        "concat: shapes {sa:?} and {sb:?} must be (N, C, H, W) with equal N, H, W"
    );
    expect_shape("concat", "out", out, &[sa[0], sa[1] + sb[1], sa[2], sa[3]])?;
    let p = ConcatParams {
        n: out.numel() as u32,
        c1: sa[1] as u32,
        c2: sb[1] as u32,
        hw: (sa[2] * sa[3]) as u32,
    };
    let k = pick(d, K::ElementwiseF32Concat, K::ElementwiseF16Concat);
    rec.dispatch(
        k,
        &[a.buffer(), b.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        grid_1d("concat", out.numel())?,
        "concat",
    )
}

/// x: (B, R, C) -> out: (B, C, R) (batched matrix transpose; NCHW <-> token-major (N, HW, C) conversions).
pub fn transpose(rec: &mut Recorder, x: &Tensor, out: &Tensor) -> Result<()> {
    let d = same_dtype("transpose", &[x, out])?;
    let s = x.shape();
    ensure!(s.len() == 3, "transpose: x must be (B, R, C), got {s:?}");
    expect_shape("transpose", "out", out, &[s[0], s[2], s[1]])?;
    let p = TransposeParams {
        n: x.numel() as u32,
        r: s[1] as u32,
        c: s[2] as u32,
    };
    let k = pick(d, K::ElementwiseF32Transpose, K::ElementwiseF16Transpose);
    rec.dispatch(
        k,
        &[x.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        grid_1d("transpose", x.numel())?,
        "transpose",
    )
}

/// One term of [`lincomb`]: `coeff * x[offset..offset + n]`.
pub struct LinTerm<'a> {
    pub x: &'a Tensor,
    pub offset: usize,
    pub coeff: f32,
}

/// out[o_out + i] = sum_k coeff_k * x_k[offset_k + i] for i < n (1 to 4 terms, one dtype). Offsets are in
/// elements; every range must lie inside its tensor. `out` may alias an input element-for-element.
pub fn lincomb(
    rec: &mut Recorder,
    terms: &[LinTerm],
    out: &Tensor,
    o_out: usize,
    n: usize,
) -> Result<()> {
    ensure!(
        (1..=4).contains(&terms.len()),
        "lincomb: {} terms (1 to 4 supported)",
        terms.len()
    );
    let mut ts: Vec<&Tensor> = terms.iter().map(|t| t.x).collect();
    ts.push(out);
    let d = same_dtype("lincomb", &ts)?;
    ensure!(
        n > 0 && o_out + n <= out.numel(),
        "lincomb: out range {o_out}..{} exceeds {:?}",
        o_out + n,
        out.shape()
    );
    for (k, t) in terms.iter().enumerate() {
        ensure!(
            t.offset + n <= t.x.numel(),
            "lincomb: term {k} range {}..{} exceeds {:?}",
            t.offset,
            t.offset + n,
            t.x.shape()
        );
        ensure!(
            t.coeff.is_finite(),
            "lincomb: term {k} coefficient {} is not finite",
            t.coeff
        );
    }
    let g = |k: usize| terms.get(k).unwrap_or(&terms[0]);
    let p = LinCombParams {
        n: n as u32,
        terms: terms.len() as u32,
        o_out: o_out as u32,
        o0: g(0).offset as u32,
        o1: g(1).offset as u32,
        o2: g(2).offset as u32,
        o3: g(3).offset as u32,
        c0: g(0).coeff,
        c1: if terms.len() > 1 { g(1).coeff } else { 0.0 },
        c2: if terms.len() > 2 { g(2).coeff } else { 0.0 },
        c3: if terms.len() > 3 { g(3).coeff } else { 0.0 },
    };
    let k = pick(d, K::ElementwiseF32Lincomb, K::ElementwiseF16Lincomb);
    let bufs = [
        g(0).x.buffer(),
        g(1).x.buffer(),
        g(2).x.buffer(),
        g(3).x.buffer(),
        out.buffer(),
    ];
    rec.dispatch(
        k,
        &bufs,
        bytemuck::bytes_of(&p),
        grid_1d("lincomb", n)?,
        "lincomb",
    )
}
