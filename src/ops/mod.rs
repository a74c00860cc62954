//! Op launchers, one file per kernel family (mirroring `kernels/`). Each launcher checks shapes and dtypes,
//! picks the pipeline variant, computes the grid, pushes the parameters and records one or more dispatches into
//! a [`Recorder`]. Outputs are caller-allocated so whole models can be planned once and replayed.
//! Plain CPU f64 references for every op live in [`reference`].
pub mod attention;
pub mod attention_naive;
pub mod bench;
pub mod blur;
pub mod cast;
pub mod conv2d;
pub mod elementwise;
pub mod embedding;
pub mod matmul;
pub mod norm;
pub mod reference;
pub mod resample;
pub mod softmax;
pub mod warp;
/// Winograd F(4x4, 3x3) / F(6x6, 3x3), one of the conv algorithms (`conv2d/winograd.rs`).
pub use conv2d::winograd;

use anyhow::{ensure, Result};

// `Recorder::scratch` slots of the ops' per-call temporaries (one buffer per slot and recording).
pub(crate) const SCRATCH_WINO_V: usize = 0;
pub(crate) const SCRATCH_WINO_M: usize = 1;
pub(crate) const SCRATCH_WINO_W: usize = 2;
pub(crate) const SCRATCH_X_HWNC: usize = 3;
pub(crate) const SCRATCH_PACKED_W: usize = 4;
/// conv2d output before a separate residual add when the residual is the output itself
pub(crate) const SCRATCH_CONV_OUT: usize = 5;
/// conv2d input upsampled 2x, on paths that cannot read through the upsampling
pub(crate) const SCRATCH_UPSAMPLED: usize = 6;
/// attention scores (B, Lq, Lk) of the single-head GEMM attention, and their softmax
pub(crate) const SCRATCH_ATTN_S: usize = 7;
pub(crate) const SCRATCH_ATTN_P: usize = 8;

use crate::kernels::KernelId;
use crate::tensor::{DType, Tensor};
pub use crate::vk::Recorder;

/// Work-group count for `n` invocations at 256 per group, folded into (x, y) with x <= 65535.
pub(crate) fn grid_1d(op: &str, n: usize) -> Result<[u32; 3]> {
    let groups = n.div_ceil(256);
    ensure!(
        groups <= 65535 * 65535,
        "{op}: {n} elements is too many for one dispatch"
    );
    let x = groups.min(65535);
    Ok([x as u32, groups.div_ceil(x) as u32, 1])
}

/// The texel-view variant of a kernel (the same entry with the `texel` axis set, [`KernelId::with_variant`]):
/// the same kernel reading some bindings through the buffers' texel views (`vk::image`; one fetch per lane
/// per vec4 on lavapipe). Taken when it is compiled (build.rs compiles only entries that read through at least
/// one image), the device supports it and every buffer it reads as an image (`bufs[i]` for binding i) has a
/// texel view.
pub(crate) fn texel_variant(
    rec: &Recorder,
    id: KernelId,
    bufs: &[&crate::vk::Buffer],
) -> Option<KernelId> {
    let axes = id.info().axes;
    let t = id.with_variant(crate::kernels::Variant {
        texel: true,
        ..axes
    })?;
    let images = t.info().images;
    let ok = images.contains(&true)
        && images
            .iter()
            .enumerate()
            .all(|(i, &img)| !img || bufs.get(i).is_some_and(|b| b.has_texel_view()))
        && rec.context().supports(t);
    ok.then_some(t)
}

/// Checks that all tensors share one dtype and returns it.
pub(crate) fn same_dtype(op: &str, ts: &[&Tensor]) -> Result<DType> {
    let d = ts[0].dtype();
    for t in ts {
        ensure!(
            t.dtype() == d,
            "{op}: dtype mismatch: {:?}",
            ts.iter().map(|t| t.dtype().name()).collect::<Vec<_>>()
        );
    }
    Ok(d)
}

/// Picks the f32 or f16 variant.
pub(crate) fn pick(d: DType, f32_id: KernelId, f16_id: KernelId) -> KernelId {
    match d {
        DType::F32 => f32_id,
        DType::F16 => f16_id,
    }
}

/// Requires an exact shape.
pub(crate) fn expect_shape(op: &str, what: &str, t: &Tensor, shape: &[usize]) -> Result<()> {
    ensure!(
        t.shape() == shape,
        "{op}: {what} has shape {:?}, expected {shape:?}",
        t.shape()
    );
    Ok(())
}
