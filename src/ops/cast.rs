//! dtype conversion launcher.
use anyhow::Result;

use super::{expect_shape, grid_1d, Recorder};
use crate::kernels::params::CastParams;
use crate::kernels::KernelId as K;
use crate::tensor::{DType, Tensor};

/// x -> out with out's dtype (same shape). Same dtypes record a buffer copy. f32 -> f16 follows IEEE rounding:
/// values beyond +-65504 become +-inf.
pub fn cast(rec: &mut Recorder, x: &Tensor, out: &Tensor) -> Result<()> {
    expect_shape("cast", "out", out, x.shape())?;
    let p = CastParams {
        n: x.numel() as u32,
    };
    let g = grid_1d("cast", x.numel())?;
    match (x.dtype(), out.dtype()) {
        (DType::F32, DType::F16) => rec.dispatch(
            K::CastToF16,
            &[x.buffer(), out.buffer()],
            bytemuck::bytes_of(&p),
            g,
            "cast",
        ),
        (DType::F16, DType::F32) => rec.dispatch(
            K::CastToF32,
            &[x.buffer(), out.buffer()],
            bytemuck::bytes_of(&p),
            g,
            "cast",
        ),
        _ => rec.copy_buffer(
            x.buffer(),
            out.buffer(),
            (x.numel() * x.dtype().size()) as u64,
        ),
    }
}
