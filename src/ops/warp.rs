//! Bilinear warp of images by a per-pixel source grid (`kernels/warp.wgsl`): the previous frame taken to the
//! current pose (`render::warp` computes the grid).
use anyhow::{ensure, Result};

use super::{expect_shape, grid_1d, Recorder};
use crate::kernels::params::WarpParams;
use crate::kernels::KernelId as K;
use crate::tensor::{DType, Tensor};

/// The grid value the host writes for "no source: keep the pixel" (any value outside the image does).
pub const NO_SOURCE: f32 = -1e9;

/// x: (N, C, H, W) f32, grid: (N, H, W, 2) f32 source (x, y) in pixel-index units (centre of pixel i at i) ->
/// out: (N, C, H, W): bilinear samples of x at the grid, taps clamped to the image; a grid point outside
/// [-0.5, W - 0.5] x [-0.5, H - 0.5] (e.g. [`NO_SOURCE`]) keeps x's own pixel.
pub fn warp_bilinear(rec: &mut Recorder, x: &Tensor, grid: &Tensor, out: &Tensor) -> Result<()> {
    for (what, t) in [("x", x), ("grid", grid), ("out", out)] {
        ensure!(
            t.dtype() == DType::F32,
            "warp_bilinear: {what} must be f32, got {:?}",
            t.dtype()
        );
    }
    let s = x.shape();
    ensure!(
        s.len() == 4 && s.iter().all(|&d| d > 0),
        "warp_bilinear: x must be a non-empty (N, C, H, W), got {s:?}"
    );
    expect_shape("warp_bilinear", "grid", grid, &[s[0], s[2], s[3], 2])?;
    expect_shape("warp_bilinear", "out", out, s)?;
    let p = WarpParams {
        planes: (s[0] * s[1]) as u32,
        c: s[1] as u32,
        h: s[2] as u32,
        w: s[3] as u32,
    };
    rec.dispatch(
        K::WarpF32,
        &[x.buffer(), grid.buffer(), out.buffer()],
        bytemuck::bytes_of(&p),
        grid_1d("warp_bilinear", x.numel())?,
        "warp_bilinear",
    )
}
