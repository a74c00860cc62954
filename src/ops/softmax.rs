//! Softmax over the last dimension (f32 math, f32 or f16 storage).
use anyhow::{ensure, Result};

use super::{expect_shape, pick, same_dtype, Recorder};
use crate::kernels::params::SoftmaxParams;
use crate::kernels::KernelId as K;
use crate::tensor::Tensor;

/// Longest row: the kernel's two passes take about 3n/16 loop trips per invocation, kept well below lavapipe's
/// budget of 65535 loop back-edges per invocation (beyond it loops silently stop).
pub const MAX_ROW: usize = 262_144;

/// Work groups for `n` groups folded into (x, y) with x, y <= 65535.
pub(crate) fn fold_groups(op: &str, n: usize) -> Result<[u32; 3]> {
    ensure!(n >= 1, "{op}: empty grid");
    let x = n.min(65535);
    let y = n.div_ceil(x);
    ensure!(
        y <= 65535,
        "{op}: {n} work groups is too many for one dispatch"
    );
    Ok([x as u32, y as u32, 1])
}

/// x: (.., n) -> out: (.., n) = exp(x - max) / sum exp(x - max) along the last dimension.
pub fn softmax(rec: &mut Recorder, x: &Tensor, out: &Tensor) -> Result<()> {
    softmax_scaled(rec, x, 1.0, out)
}

/// [`softmax`] of scale * x (attention scores with their 1 / sqrt(d)).
pub fn softmax_scaled(rec: &mut Recorder, x: &Tensor, scale: f32, out: &Tensor) -> Result<()> {
    ensure!(scale.is_finite(), "softmax: scale {scale} must be finite");
    let d = same_dtype("softmax", &[x, out])?;
    expect_shape("softmax", "out", out, x.shape())?;
    let n = *x.shape().last().unwrap_or(&0);
    ensure!(n >= 1, "softmax: empty input {:?}", x.shape());
    ensure!(
        n <= MAX_ROW,
        "softmax: rows of {n} in {:?} exceed {MAX_ROW} (lavapipe loop budget)",
        x.shape()
    );
    let rows = x.numel() / n;
    let p = SoftmaxParams {
        rows: rows as u32,
        n: n as u32,
        scale,
    };
    rec.dispatch(
        pick(d, K::SoftmaxF32, K::SoftmaxF16),
        &[x.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        fold_groups("softmax", rows)?,
        "softmax",
    )
}
