//! Separable Gaussian blur launcher (two dispatches through a temporary).
use anyhow::{ensure, Result};

use super::{expect_shape, grid_1d, pick, same_dtype, Recorder};
use crate::kernels::params::BlurParams;
use crate::kernels::KernelId as K;
use crate::tensor::Tensor;

/// Radius used for `sigma`: ceil(3 sigma) (kernel size 2r + 1; sigma 1 -> 7 taps).
pub fn blur_radius(sigma: f32) -> usize {
    (3.0 * sigma).ceil() as usize
}

/// x: (N, C, H, W) -> out: (N, C, H, W), Gaussian blur with standard deviation `sigma` pixels, reflect borders.
/// `tmp` holds the horizontal pass (same shape).
pub fn gaussian_blur(
    rec: &mut Recorder,
    x: &Tensor,
    sigma: f32,
    tmp: &Tensor,
    out: &Tensor,
) -> Result<()> {
    let d = same_dtype("gaussian_blur", &[x, tmp, out])?;
    let s = x.shape();
    ensure!(
        s.len() == 4,
        "gaussian_blur: x must be (N, C, H, W), got {s:?}"
    );
    expect_shape("gaussian_blur", "tmp", tmp, s)?;
    expect_shape("gaussian_blur", "out", out, s)?;
    ensure!(
        sigma.is_finite() && sigma > 0.0 && sigma <= 10.0,
        "gaussian_blur: sigma {sigma} must be in (0, 10]"
    );
    let r = blur_radius(sigma);
    ensure!(
        r < s[2] && r < s[3],
        "gaussian_blur: radius {r} (sigma {sigma}) must be smaller than the image {s:?}"
    );
    let k = pick(d, K::BlurF32, K::BlurF16);
    let g = grid_1d("gaussian_blur", x.numel())?;
    for (axis, src, dst) in [(0u32, x, tmp), (1u32, tmp, out)] {
        let p = BlurParams {
            planes: (s[0] * s[1]) as u32,
            h: s[2] as u32,
            w: s[3] as u32,
            axis,
            radius: r as u32,
            sigma,
        };
        rec.dispatch(
            k,
            &[src.buffer(), dst.buffer()],
            bytemuck::bytes_of(&p),
            g,
            "gaussian_blur",
        )?;
    }
    Ok(())
}
