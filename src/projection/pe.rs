//! PETR-style 3D position encodings of feature maps (renderer spec 3d), the input of the 1x1-conv MLP.
//!
//! Follows megvii-research/PETR `PETRHead.position_embeding` (projects/mmdet3d_plugin/models/dense_heads/
//! petr_head.py) with `LID=True`:
//! - depth bins `d_i = depth_start + (d_max - depth_start) / (D (D + 1)) * i (i + 1)`, `i = 0..D-1`
//!   (`d_max = position_range[3] = 61.2`, `depth_start = 1`, `D = 64`; so `d_0 = 1`, `d_63 ~= 59.35`);
//! - a pixel `(u, v)` at depth `d` is the homogeneous image point `(u d, v d, d, 1)` lifted with the inverse of the
//!   camera matrix (`d` is the camera z, not the ray length), here `p = cam2cur * (d K^-1 [u v 1])`;
//! - normalisation `(p - lo) / (hi - lo)` per axis with the range (-61.2, -61.2, -10) .. (61.2, 61.2, 10);
//! - `inverse_sigmoid(x, eps = 1e-5)` as mmdet's: `x = clamp(x, 0, 1)`, `log(max(x, eps) / max(1 - x, eps))`
//!   (so outputs lie in about [-11.51, 11.51]);
//! - layout `(D*3, h, w)` with channel `d * 3 + axis` (PETR's `permute(0, 1, 4, 5, 3, 2).view(B*N, -1, H, W)`).
//!
//! One deliberate difference, selectable with [`PixelGrid`]: PETR samples feature cell `j` at image coordinate
//! `j * W / w` (the cell's top-left corner); our default samples the cell centre `(j + 0.5) W / w - 0.5`
//! (the same pixel-centre convention as the intrinsics rescaling). `PixelGrid::PetrCorner` reproduces PETR.
//! The frame is the CURRENT ego frame: for a reference image, `cam2cur` goes through the reference image's own
//! recorded pose, so current and reference encodings live in one frame.
use anyhow::{ensure, Result};
use glam::{DMat3, DMat4, DVec3};

use crate::scene::camera::Camera;

/// Where a feature cell is sampled in image coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PixelGrid {
    /// Cell centre: `u = (j + 0.5) W / w - 0.5` (pixel centres at integer coordinates).
    Centre,
    /// PETR's `u = j W / w`.
    PetrCorner,
}

/// Position-encoding settings (defaults: the spec's, PETR's nuScenes config).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeConfig {
    /// D, the number of depth bins.
    pub depth_num: usize,
    pub depth_start: f64,
    /// (x_min, y_min, z_min, x_max, y_max, z_max) in metres; `x_max` is also `d_max`.
    pub position_range: [f64; 6],
    /// Clamp of the inverse sigmoid.
    pub eps: f64,
    pub grid: PixelGrid,
}

impl Default for PeConfig {
    fn default() -> Self {
        PeConfig {
            depth_num: 64,
            depth_start: 1.0,
            position_range: [-61.2, -61.2, -10.0, 61.2, 61.2, 10.0],
            eps: 1e-5,
            grid: PixelGrid::Centre,
        }
    }
}

/// Feature-map sizes `(h, w)` of the ControlNet blocks for a 224 x 400 render (latent 28 x 50 and its stride-2
/// reductions with padding 1: 14 x 25, 7 x 13, 4 x 7).
pub const LATENT_BLOCK_SIZES: [(usize, usize); 4] = [(28, 50), (14, 25), (7, 13), (4, 7)];

/// LID depth bins: `(D,)`.
pub fn depth_bins(cfg: &PeConfig) -> Vec<f64> {
    let n = cfg.depth_num as f64;
    let bin = (cfg.position_range[3] - cfg.depth_start) / (n * (n + 1.0));
    (0..cfg.depth_num)
        .map(|i| cfg.depth_start + bin * (i as f64) * (i as f64 + 1.0))
        .collect()
}

/// mmdet's `inverse_sigmoid(x, eps)`.
pub fn inverse_sigmoid(x: f64, eps: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    (x.max(eps) / (1.0 - x).max(eps)).ln()
}

/// Camera -> current ego for an image taken with ego pose `image_ego2global`, seen from the current ego pose.
/// For the current frame pass the same pose twice (or the image's own pose as `cur_ego2global`).
pub fn cam2cur(camera: &Camera, image_ego2global: &DMat4, cur_ego2global: &DMat4) -> DMat4 {
    cur_ego2global.inverse() * *image_ego2global * camera.cam2ego
}

/// Position encoding of one feature map.
/// `k`: intrinsics at the image size `img_w x img_h` the feature map covers (e.g. the render size: use
/// [`Camera::intrinsic_scaled`]); `cam2cur`: camera -> current ego; `(h, w)`: feature-map size.
/// Returns `pe: (D*3, h, w)` row-major, channel `d * 3 + axis`.
pub fn position_encoding(
    k: &DMat3,
    img_w: usize,
    img_h: usize,
    cam2cur: &DMat4,
    h: usize,
    w: usize,
    cfg: &PeConfig,
) -> Result<Vec<f32>> {
    ensure!(
        h > 0 && w > 0 && img_w > 0 && img_h > 0,
        "position_encoding: empty size img {img_w}x{img_h} feat {h}x{w}"
    );
    ensure!(
        k.determinant().abs() > 1e-12,
        "position_encoding: singular intrinsics"
    );
    let r = &cfg.position_range;
    ensure!(
        r[3] > r[0] && r[4] > r[1] && r[5] > r[2],
        "position_encoding: empty position range {r:?}"
    );
    let kinv = k.inverse();
    let depths = depth_bins(cfg);
    let (sx, sy) = (img_w as f64 / w as f64, img_h as f64 / h as f64);
    let lo = DVec3::new(r[0], r[1], r[2]);
    let span = DVec3::new(r[3] - r[0], r[4] - r[1], r[5] - r[2]);
    let mut out = vec![0f32; depths.len() * 3 * h * w];
    let plane = h * w;
    for y in 0..h {
        let v = match cfg.grid {
            PixelGrid::Centre => (y as f64 + 0.5) * sy - 0.5,
            PixelGrid::PetrCorner => y as f64 * sy,
        };
        for x in 0..w {
            let u = match cfg.grid {
                PixelGrid::Centre => (x as f64 + 0.5) * sx - 0.5,
                PixelGrid::PetrCorner => x as f64 * sx,
            };
            let ray = kinv * DVec3::new(u, v, 1.0); // z = 1
            for (di, &d) in depths.iter().enumerate() {
                let p = cam2cur.transform_point3(ray * d.max(cfg.eps));
                let n = (p - lo) / span;
                let base = di * 3 * plane + y * w + x;
                out[base] = inverse_sigmoid(n.x, cfg.eps) as f32;
                out[base + plane] = inverse_sigmoid(n.y, cfg.eps) as f32;
                out[base + 2 * plane] = inverse_sigmoid(n.z, cfg.eps) as f32;
            }
        }
    }
    Ok(out)
}

/// The position encoding of one block resolution: `pe: (D*3, h, w)`.
#[derive(Clone, Debug, PartialEq)]
pub struct BlockPe {
    pub h: usize,
    pub w: usize,
    pub pe: Vec<f32>,
}

/// Position encodings of one camera image at the four latent block resolutions of a `render_w x render_h`
/// render (sizes from [`latent_block_sizes`]), finest first.
pub fn position_encodings_for_blocks(
    camera: &Camera,
    render_w: u32,
    render_h: u32,
    cam2cur: &DMat4,
    cfg: &PeConfig,
) -> Result<Vec<BlockPe>> {
    let k = camera.intrinsic_scaled(render_w, render_h);
    latent_block_sizes(render_w as usize, render_h as usize)
        .into_iter()
        .map(|(h, w)| {
            let pe =
                position_encoding(&k, render_w as usize, render_h as usize, cam2cur, h, w, cfg)?;
            Ok(BlockPe { h, w, pe })
        })
        .collect()
}

/// Block resolutions for a render size: latent `(H/8, W/8)` then three stride-2 (pad 1, kernel 3) reductions,
/// `n -> (n + 1) / 2` (224 x 400 -> 28x50, 14x25, 7x13, 4x7).
pub fn latent_block_sizes(render_w: usize, render_h: usize) -> Vec<(usize, usize)> {
    let mut s = (render_h / 8, render_w / 8);
    let mut v = vec![s];
    for _ in 0..3 {
        s = (s.0.div_ceil(2), s.1.div_ceil(2));
        v.push(s);
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bins_and_sizes() {
        let d = depth_bins(&PeConfig::default());
        assert_eq!(d.len(), 64);
        assert_eq!(d[0], 1.0);
        assert!((d[63] - (1.0 + 60.2 * 63.0 / 65.0)).abs() < 1e-9);
        assert_eq!(latent_block_sizes(400, 224), LATENT_BLOCK_SIZES.to_vec());
        assert!((inverse_sigmoid(0.5, 1e-5)).abs() < 1e-12);
        assert!((inverse_sigmoid(2.0, 1e-5) - (1.0f64 / 1e-5).ln()).abs() < 1e-9);
    }
}
