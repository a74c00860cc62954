//! Host-side inputs of a frame, from a scene state: layout masks of each camera (projection), the PETR
//! geometry of the current camera and its two references at the Ref-Attn feature sizes, images as planar
//! (3, H, W) f32 in [0, 1], and the seeded noise of a frame. Nothing here touches the device.
use anyhow::{ensure, Context as _, Result};
use glam::DMat4;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

use crate::nn::b2dr_config::B2drConfig;
use crate::projection::pe::{cam2cur, position_encoding};
use crate::projection::{
    Box3d, CameraProjector, LayoutMasks, LayoutRenderer, MapLayer, ProjectionConfig,
    NUM_MASK_CHANNELS,
};
use crate::scene::camera::Camera;

/// Layout masks of each camera `(N, 15, H, W)` in {0, 1}; `poses[i]` is camera i's ego2global at exposure.
pub fn masks(
    cameras: &[Camera],
    poses: &[DMat4],
    boxes: &[Box3d],
    map: &MapLayer,
    size: (usize, usize),
    cfg: &ProjectionConfig,
) -> Result<Vec<f32>> {
    ensure!(
        cameras.len() == poses.len(),
        "masks: {} cameras, {} poses",
        cameras.len(),
        poses.len()
    );
    let (h, w) = size;
    let mut r = LayoutRenderer::new(w, h);
    let mut m = LayoutMasks::new(w, h);
    let mut out = Vec::with_capacity(cameras.len() * NUM_MASK_CHANNELS * h * w);
    for (c, p) in cameras.iter().zip(poses) {
        let proj = CameraProjector::new(c, p, w as u32, h as u32)?;
        r.render(&proj, boxes, map, cfg, &mut m);
        out.extend(m.data.iter().map(|&v| v as f32));
    }
    Ok(out)
}

/// PETR geometry of one camera and its references at every Ref-Attn location:
/// `pe_cur[j]: (3D, h_j, w_j)`, `pe_ref[j]: (2, 3D, h_j, w_j)` (front then rear), all in the current ego frame.
pub struct Geometry {
    pub pe_cur: Vec<Vec<f32>>,
    pub pe_ref: Vec<Vec<f32>>,
}

/// `cur`: the camera's ego2global at this frame; `refs`: the ego2global of the two reference images.
pub fn geometry(
    cfg: &B2drConfig,
    camera: &Camera,
    size: (usize, usize),
    cur: &DMat4,
    refs: [&DMat4; 2],
) -> Result<Geometry> {
    let (ih, iw) = size;
    let latent = (ih / 8, iw / 8);
    let k = camera.intrinsic_scaled(iw as u32, ih as u32);
    let pc = cfg.pe_config();
    let mut out = Geometry {
        pe_cur: vec![],
        pe_ref: vec![],
    };
    for &at in &cfg.ref_attn {
        let (h, w) = cfg.location_size(at, latent);
        out.pe_cur.push(position_encoding(
            &k,
            iw,
            ih,
            &cam2cur(camera, cur, cur),
            h,
            w,
            &pc,
        )?);
        let mut r = vec![];
        for p in refs {
            r.extend(position_encoding(
                &k,
                iw,
                ih,
                &cam2cur(camera, p, cur),
                h,
                w,
                &pc,
            )?);
        }
        out.pe_ref.push(r);
    }
    Ok(out)
}

/// Concatenates per-camera geometry into the frame layout: `pe_cur[j]: (N, 3D, h, w)`, `pe_ref[j]: (N, 2, ...)`.
pub fn stack(per_camera: &[Geometry]) -> Geometry {
    let locs = per_camera.first().map(|g| g.pe_cur.len()).unwrap_or(0);
    let cat = |f: &dyn Fn(&Geometry) -> &Vec<Vec<f32>>, j: usize| -> Vec<f32> {
        per_camera
            .iter()
            .flat_map(|g| f(g)[j].iter().copied())
            .collect()
    };
    Geometry {
        pe_cur: (0..locs).map(|j| cat(&|g| &g.pe_cur, j)).collect(),
        pe_ref: (0..locs).map(|j| cat(&|g| &g.pe_ref, j)).collect(),
    }
}

/// An RGB image as planar (3, H, W) f32 in [0, 1], resized to `size` (H, W) with Catmull-Rom when it differs.
pub fn planar(img: &image::RgbImage, size: (usize, usize)) -> Vec<f32> {
    let (h, w) = size;
    let resized;
    let img = if img.dimensions() != (w as u32, h as u32) {
        resized = image::imageops::resize(
            img,
            w as u32,
            h as u32,
            image::imageops::FilterType::CatmullRom,
        );
        &resized
    } else {
        img
    };
    let mut v = vec![0.0; 3 * h * w];
    for (x, y, p) in img.enumerate_pixels() {
        for c in 0..3 {
            v[(c * h + y as usize) * w + x as usize] = p[c] as f32 / 255.0;
        }
    }
    v
}

/// Reads an image file as planar (3, H, W) at `size`.
pub fn read_planar(path: &std::path::Path, size: (usize, usize)) -> Result<Vec<f32>> {
    let img = image::open(path)
        .with_context(|| format!("reading {}", path.display()))?
        .to_rgb8();
    Ok(planar(&img, size))
}

/// Planar (3, H, W) in [0, 1] -> an RGB image (rounded).
pub fn to_rgb(chw: &[f32], size: (usize, usize)) -> image::RgbImage {
    let (h, w) = size;
    image::RgbImage::from_fn(w as u32, h as u32, |x, y| {
        let g = |c: usize| {
            (chw[(c * h + y as usize) * w + x as usize] * 255.0)
                .round()
                .clamp(0.0, 255.0) as u8
        };
        image::Rgb([g(0), g(1), g(2)])
    })
}

/// Writes planar (3, H, W) f32 as an RGB EXR, byte-identical across runs: scan lines in increasing order,
/// compressed on one thread (the crate's default writes parallel-compressed tiles in completion order, so the
/// same pixels gave different files).
pub fn write_exr(path: &std::path::Path, chw: &[f32], size: (usize, usize)) -> Result<()> {
    use exr::prelude::*;
    let (h, w) = size;
    let channels = SpecificChannels::rgb(|Vec2(x, y): Vec2<usize>| {
        (
            chw[y * w + x],
            chw[(h + y) * w + x],
            chw[(2 * h + y) * w + x],
        )
    });
    let layer = Layer::new(
        (w, h),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        channels,
    );
    Image::from_layer(layer)
        .write()
        .non_parallel()
        .to_file(path)
        .with_context(|| format!("writing {}", path.display()))
}

/// The seeded noise of frame `frame` of a run with seed `seed`: x_T and eps_prev, each (N, C, h, w) for
/// `latent` = (C, h, w). Stable across runs, threads and machines (ChaCha8 seeded from (seed, frame)); the
/// draws are one sequence, so a 4-channel model gets the values it always got.
pub fn frame_noise(
    seed: u64,
    frame: u64,
    n: usize,
    latent: (usize, usize, usize),
) -> (Vec<f32>, Vec<f32>) {
    let mut r =
        rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ frame.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let len = n * latent.0 * latent.1 * latent.2;
    let mut draw = || -> Vec<f32> { (0..len).map(|_| StandardNormal.sample(&mut r)).collect() };
    let x_t = draw();
    let eps = draw();
    (x_t, eps)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The same pixels give the same file (the parallel tile writer did not), and the file holds those pixels.
    #[test]
    fn exr_files_are_byte_identical_and_exact() {
        let (h, w) = (150, 260);
        let chw: Vec<f32> = (0..3 * h * w).map(|i| (i as f32 * 0.618).fract()).collect();
        let dir = std::env::temp_dir().join(format!("b2dr-exr-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let files: Vec<Vec<u8>> = (0..4)
            .map(|k| {
                let p = dir.join(format!("{k}.exr"));
                write_exr(&p, &chw, (h, w)).unwrap();
                std::fs::read(&p).unwrap()
            })
            .collect();
        assert!(files.iter().all(|f| f == &files[0]), "reruns differ");
        let img = exr::prelude::read_first_rgba_layer_from_file(
            dir.join("0.exr"),
            |res, _| vec![[0f32; 3]; res.width() * res.height()],
            move |px: &mut Vec<[f32; 3]>, p, (r, g, b, _a): (f32, f32, f32, f32)| {
                px[p.y() * w + p.x()] = [r, g, b]
            },
        )
        .unwrap();
        let px = &img.layer_data.channel_data.pixels;
        for (i, v) in px.iter().enumerate() {
            for (c, &x) in v.iter().enumerate() {
                assert_eq!(x, chw[c * h * w + i], "pixel {i} channel {c}");
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
