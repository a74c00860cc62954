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

/// How a device evaluates f16 arithmetic and conversions: `cast.wgsl`'s `f16_probe` ([`f16_probe`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct F16Probe {
    /// Every f16 operation rounds to f16 (IEEE half arithmetic, in hardware or emulated op by op: what an f16
    /// accumulation really loses); false: f16 expressions run in f32 and round only where they are stored.
    pub rounds_per_op: bool,
    /// `f32(f16(x))` of an f32 x rounds x to a half (to nearest even); false: the compiler drops the round trip
    /// and gives x back (Mesa 25's lavapipe). A kernel that needs the f32 value of what it stores as f16 must
    /// not rely on that conversion (kernels/winograd `as_stored4`).
    pub round_trip_kept: bool,
}

/// Probes how the device evaluates f16 (one dispatch of `cast.wgsl`'s `f16_probe`, 2 halves in, 3 floats out);
/// None without f16 support. b2dr's kernels do their arithmetic in f32 whatever the storage type; `b2dr info`
/// and the test logs print the answer so a run says which kind of driver it tested.
pub fn f16_probe(ctx: &crate::vk::Context) -> Result<Option<F16Probe>> {
    if !ctx.info().f16 {
        return Ok(None);
    }
    let x = Tensor::from_f32(ctx, &[2], DType::F16, &[2048.0, 1.0], "f16_probe_x")?;
    let y = Tensor::zeros(ctx, &[3], DType::F32, "f16_probe_y")?;
    let mut rec = ctx.recorder()?;
    rec.dispatch(
        K::CastF16Probe,
        &[x.buffer(), y.buffer()],
        bytemuck::bytes_of(&CastParams { n: 2 }),
        [1, 1, 1],
        "f16_probe",
    )?;
    rec.finish()?.submit_wait()?;
    let v = y.to_f32(ctx)?;
    // (2048 + 1) + 1 in f16: 2048 rounding per op, 2050 in f32; 2048 + 1: 2048; f32(f16(2049.5)): 2050 (to
    // nearest even), 2049.5 (round trip dropped); anything else (2048: a truncating conversion) is not a
    // behaviour b2dr's f16 kernels are written for
    anyhow::ensure!(
        v[1] == 2048.0 && (v[0] == 2048.0 || v[0] == 2050.0) && (v[2] == 2050.0 || v[2] == 2049.5),
        "f16 probe: (2048 + 1) + 1 = {}, 2048 + 1 = {}, f32(f16(2049.5)) = {} (want 2048 or 2050, 2048, 2050 or 2049.5)",
        v[0],
        v[1],
        v[2]
    );
    Ok(Some(F16Probe {
        rounds_per_op: v[0] == 2048.0,
        round_trip_kept: v[2] == 2050.0,
    }))
}
