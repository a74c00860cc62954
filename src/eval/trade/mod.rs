//! `b2dr bench trade`: what each rendering choice costs and buys, measured in one run on one device.
//!
//! A sweep over precision (f32, f16 storage), sampler and steps (UniPC 4 / 8 / 10 / 20 / 50, DDIM 20 / 50), render
//! resolution (the model's and about half of it), reference guidance (off = 1, 2) and cameras (1, 3, 6), each
//! point varied one axis at a time from the model's default setting, all on the same frames of a synthetic
//! scenario with the same initial noise. Per point: wall time per frame (and per stage: conditioning,
//! denoising, decoding), device memory, and the error (a) against the reference setting (f32, UniPC 50 steps,
//! full resolution, all cameras: NMSE and PSNR of the decoded images) and (b) against the synthetic world's
//! ground truth (PSNR, the layout score of `eval-render`). Then the numerical extremes (f16 at guidance 2 and
//! 7.5, one step) and an autoregressive rollout per precision: every value must stay finite.
//!
//! Pairing: every point draws its initial noise for all of the reference's cameras and keeps the first
//! `cameras` of them, so a 1-camera point renders the reference's first camera from the same noise. A point
//! at another resolution draws noise of its own latent size (it is another sample, not an approximation of the
//! reference's) and is compared after the renderer's bicubic upsample to the full size.
mod report;

use std::path::{Path, PathBuf};

use anyhow::{ensure, Context as _, Result};
use serde::Serialize;

use crate::eval::fidelity::metrics::{psnr, IouCounts, PaletteClassifier};
use crate::eval::fidelity::scene;
use crate::projection::scene::map_layer;
use crate::render::frame::{FrameInputs, FrameRenderer, FrameShape, Prev, RefInputs};
use crate::render::inputs::{self};
use crate::render::job::sampler_plan;
use crate::render::package::{DeviceModel, ModelPackage};
use crate::scene::camera::Camera;
use crate::scene::import::resolve;
use crate::tensor::DType;
use crate::vk::Context;
use crate::world::images::ImageStore;

pub use report::{markdown, pareto};

/// What `bench trade` measures.
#[derive(Clone, Debug, Serialize)]
pub struct TradeConfig {
    /// Model package folder or `builtin:NAME`; None: the built-in default.
    pub model: Option<PathBuf>,
    /// One synthetic scenario (`builtin:...`): the ground truth is the world's renderer.
    pub scenario: String,
    /// Recorded-frame indices rendered by every point (each needs a frame before it: its previous frame).
    pub frames: Vec<usize>,
    /// Cameras of the reference setting (the first N of the model's); the camera axis sweeps 1, 3 and this.
    pub cameras: usize,
    /// Frames of the autoregressive rollout per precision (0: none).
    pub rollout_frames: usize,
    /// The reduced sweep (a few points, minutes on lavapipe).
    pub quick: bool,
    pub seed: u64,
}

impl TradeConfig {
    /// The full sweep's defaults (`--quick` changes the frames, cameras, rollout and points).
    pub fn new(model: Option<PathBuf>, scenario: String, quick: bool) -> Self {
        Self {
            model,
            scenario,
            frames: if quick { vec![8] } else { vec![8, 20] },
            cameras: if quick { 1 } else { 6 },
            rollout_frames: if quick { 8 } else { 200 },
            quick,
            seed: 0,
        }
    }
}

/// One setting of the sweep.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Point {
    pub name: String,
    /// The axis this point varies ("reference", "default", "dtype", "steps", "resolution", "guidance",
    /// "cameras", "extreme").
    pub axis: String,
    pub dtype: String,
    pub sampler: String,
    pub steps: usize,
    /// Render size (H, W).
    pub size: (usize, usize),
    /// Reference guidance w (1 = off: the reference half only).
    pub guidance: f64,
    pub cameras: usize,
}

/// One measured point.
#[derive(Clone, Debug, Serialize)]
pub struct PointResult {
    pub point: Point,
    /// Wall time per frame, mean over the frames, and its stages.
    pub ms_per_frame: f64,
    pub conditioning_ms: f64,
    pub denoise_ms: f64,
    pub decode_ms: f64,
    /// Planning the renderer (pipelines, workspace), once per setting.
    pub plan_ms: f64,
    /// Device memory of the weights and the planned frame.
    pub device_bytes: u64,
    /// Against the reference setting's images of the same cameras: sum (x - r)^2 / sum r^2 and PSNR (None:
    /// identical).
    pub nmse_vs_reference: f64,
    pub psnr_vs_reference: Option<f64>,
    /// Against the ground truth (8-bit images): PSNR (mean over images), the vehicle IoU and mean IoU of the
    /// palette classifier (colour exactness), the vehicle and lane-marking IoU of the layout segmenter
    /// (drawing: docs/eval_render.md).
    pub psnr_vs_truth: Option<f64>,
    pub vehicle_iou: Option<f64>,
    pub mean_iou: Option<f64>,
    pub seg_vehicle_iou: Option<f64>,
    pub seg_marking_iou: Option<f64>,
    /// Non-finite values in the decoded images (must be 0).
    pub nonfinite: usize,
    /// On the time / error Pareto front of the sweep (extremes excluded).
    pub pareto: bool,
    #[serde(skip)]
    iou: IouCounts,
    #[serde(skip)]
    seg_iou: IouCounts,
}

/// An autoregressive rollout of one precision.
#[derive(Clone, Debug, Serialize)]
pub struct Rollout {
    pub dtype: String,
    pub frames: usize,
    pub cameras: usize,
    pub nonfinite: usize,
    /// PSNR vs the ground truth of the first and last tenth of the frames.
    pub psnr_first: Option<f64>,
    pub psnr_last: Option<f64>,
    pub ms_per_frame: f64,
}

/// The whole sweep (trade.json).
#[derive(Debug, Serialize)]
pub struct TradeResults {
    pub config: TradeConfig,
    pub model: String,
    pub device: String,
    pub date_utc: String,
    pub render_size: [usize; 2],
    pub half_size: Option<[usize; 2]>,
    pub cameras: Vec<String>,
    pub points: Vec<PointResult>,
    pub extremes: Vec<PointResult>,
    pub rollouts: Vec<Rollout>,
    pub wall_s: f64,
}

impl TradeResults {
    pub fn reference(&self) -> Option<&PointResult> {
        self.points.iter().find(|p| p.point.axis == "reference")
    }
    pub fn default_point(&self) -> Option<&PointResult> {
        self.points.iter().find(|p| p.point.axis == "default")
    }
}

/// About half the render size, on the 8-pixel grid the VAE needs (None when that is the full size or empty).
pub fn half_size((h, w): (usize, usize)) -> Option<(usize, usize)> {
    let r = |v: usize| ((v / 2 + 4) / 8) * 8;
    let s = (r(h), r(w));
    (s.0 >= 8 && s.1 >= 8 && s != (h, w)).then_some(s)
}

/// The sweep's points: the reference, the model's default, then one axis at a time from the default.
pub fn sweep(pkg: &ModelPackage, cfg: &TradeConfig) -> (Vec<Point>, Vec<Point>) {
    let [h, w] = pkg.meta.render_size;
    let full = (h, w);
    let wd = pkg.meta.ref_guidance;
    let mk =
        |name: &str, axis: &str, dtype: &str, sampler: &str, steps, size, guidance, cameras| {
            Point {
                name: name.into(),
                axis: axis.into(),
                dtype: dtype.into(),
                sampler: sampler.into(),
                steps,
                size,
                guidance,
                cameras,
            }
        };
    let (ds, dn) = (pkg.meta.sampler.as_str(), pkg.meta.steps);
    let c = cfg.cameras;
    let mut pts = vec![
        mk("reference", "reference", "f32", "unipc", 50, full, wd, c),
        mk("default", "default", "f32", ds, dn, full, wd, c),
    ];
    let mut push = |p: Point| {
        let same = |q: &Point| {
            (&q.dtype, &q.sampler, q.steps, q.size, q.guidance, q.cameras)
                == (&p.dtype, &p.sampler, p.steps, p.size, p.guidance, p.cameras)
        };
        if !pts.iter().any(same) {
            pts.push(p);
        }
    };
    let steps: &[usize] = if cfg.quick {
        &[4, 10, 20]
    } else {
        &[4, 8, 10, 20]
    };
    for &s in steps {
        push(mk(
            &format!("unipc {s}"),
            "steps",
            "f32",
            "unipc",
            s,
            full,
            wd,
            c,
        ));
    }
    if !cfg.quick {
        for s in [20, 50] {
            push(mk(
                &format!("ddim {s}"),
                "steps",
                "f32",
                "ddim",
                s,
                full,
                wd,
                c,
            ));
        }
    }
    push(mk("f16", "dtype", "f16", ds, dn, full, wd, c));
    push(mk("f16 unipc 50", "dtype", "f16", "unipc", 50, full, wd, c));
    if let Some(hs) = half_size(full) {
        push(mk(
            "half resolution",
            "resolution",
            "f32",
            ds,
            dn,
            hs,
            wd,
            c,
        ));
    }
    for g in [1.0, 2.0] {
        let name = if g == 1.0 {
            "guidance off".to_string()
        } else {
            format!("guidance {g}")
        };
        push(mk(&name, "guidance", "f32", ds, dn, full, g, c));
    }
    for k in [1, 3] {
        if k < c {
            push(mk(
                &format!("{k} cameras"),
                "cameras",
                "f32",
                ds,
                dn,
                full,
                wd,
                k,
            ));
        }
    }
    let extremes = vec![
        mk("f16 w 2", "extreme", "f16", ds, dn, full, 2.0, c),
        mk("f16 w 7.5", "extreme", "f16", ds, dn, full, 7.5, c),
        mk("f16 1 step", "extreme", "f16", "unipc", 1, full, wd, c),
        mk("f32 1 step", "extreme", "f32", "unipc", 1, full, wd, c),
    ];
    (pts, extremes)
}

/// The inputs of one frame at one render size, for the reference's cameras (a point takes a prefix).
struct FrameData {
    /// (N, 15, H, W) per size.
    masks: Vec<f32>,
    /// (N, 3, H, W) previous frame (the ground truth one recorded frame earlier).
    prev: Vec<f32>,
    refs: (Vec<f32>, inputs::Geometry),
}

/// Per frame: the ground truth at full size (RGB8 and class ids per camera) and the inputs per render size.
struct Frames {
    truth_rgb: Vec<Vec<Vec<u8>>>,
    truth_class: Vec<Vec<Vec<u8>>>,
    by_size: Vec<((usize, usize), Vec<FrameData>)>,
    ids: Vec<u64>,
}

impl Frames {
    fn inputs(&self, size: (usize, usize), frame: usize) -> Result<&FrameData> {
        self.by_size
            .iter()
            .find(|(s, _)| *s == size)
            .map(|(_, v)| &v[frame])
            .context("internal: no inputs at this size")
    }
}

/// A prefix of `k` cameras of a per-camera tensor of `n` cameras.
fn prefix(v: &[f32], n: usize, k: usize) -> &[f32] {
    &v[..v.len() / n * k]
}

/// The per-camera slices of a geometry (every tensor is camera-major).
fn geometry_prefix(g: &inputs::Geometry, n: usize, k: usize) -> (Vec<&[f32]>, Vec<&[f32]>) {
    (
        g.pe_cur.iter().map(|v| prefix(v, n, k)).collect(),
        g.pe_ref.iter().map(|v| prefix(v, n, k)).collect(),
    )
}

/// Sum of squares of differences and of the reference (for NMSE).
fn sq_err(x: &[f32], r: &[f32]) -> (f64, f64) {
    x.iter().zip(r).fold((0.0, 0.0), |(e, s), (a, b)| {
        let d = *a as f64 - *b as f64;
        (e + d * d, s + (*b as f64) * (*b as f64))
    })
}

struct Measured {
    result: PointResult,
    /// Decoded images per frame at full size (N, 3, H, W).
    images: Vec<Vec<f32>>,
    rgb: Vec<Vec<Vec<u8>>>,
}

#[allow(clippy::too_many_arguments)]
fn measure(
    ctx: &Context,
    pkg: &ModelPackage,
    cams: &[String],
    p: &Point,
    frames: &Frames,
    full: (usize, usize),
    seed: u64,
    reference: Option<&[Vec<f32>]>,
) -> Result<Measured> {
    let n_all = cams.len();
    ensure!(
        p.cameras >= 1 && p.cameras <= n_all,
        "internal: {} cameras",
        p.cameras
    );
    let dtype: DType = p.dtype.parse()?;
    let before = ctx.allocated_bytes();
    let dm = DeviceModel::upload(ctx, pkg, dtype)?;
    let t0 = std::time::Instant::now();
    let fr = FrameRenderer::new(
        ctx,
        &dm.as_model(),
        FrameShape {
            cameras: p.cameras,
            size: p.size,
            refs: true,
            ref_guidance: p.guidance,
            out_size: (p.size != full).then_some(full),
            prev_noise_level: None,
            prev_blur_sigma: None,
        },
        &pkg.context_for(&cams[..p.cameras])?,
        sampler_plan(&p.sampler, p.steps, pkg.meta.prediction())?,
    )
    .with_context(|| format!("planning {}", p.name))?;
    let plan_ms = t0.elapsed().as_secs_f64() * 1e3;
    let device_bytes = ctx.allocated_bytes().saturating_sub(before);
    let (mut cond, mut den, mut dec) = (0.0, 0.0, 0.0);
    let (mut err, mut sum) = (0.0, 0.0);
    let mut nonfinite = 0usize;
    let mut images = vec![];
    let mut rgbs = vec![];
    let mut psnrs = vec![];
    for (fi, id) in frames.ids.iter().enumerate() {
        let x = frames.inputs(p.size, fi)?;
        let (x_t, eps) = inputs::frame_noise(seed, *id, n_all, fr.latent_size());
        let (pc, pr) = geometry_prefix(&x.refs.1, n_all, p.cameras);
        let t = fr.render(&FrameInputs {
            masks: prefix(&x.masks, n_all, p.cameras),
            prev: Prev::Image(prefix(&x.prev, n_all, p.cameras)),
            refs: Some(RefInputs {
                images: prefix(&x.refs.0, n_all, p.cameras),
                pe_cur: pc,
                pe_ref: pr,
            }),
            x_t: prefix(&x_t, n_all, p.cameras),
            eps_prev: prefix(&eps, n_all, p.cameras),
            prev_warp: None,
        })?;
        cond += t.encode_ms;
        den += t.denoise_ms;
        dec += t.decode_ms;
        let img = match fr.upsampled()? {
            Some(u) => u,
            None => fr.image()?,
        };
        nonfinite += img.iter().filter(|v| !v.is_finite()).count();
        if let Some(r) = reference {
            let (e, s) = sq_err(&img, prefix(&r[fi], n_all, p.cameras));
            err += e;
            sum += s;
        }
        let per = 3 * full.0 * full.1;
        let rgb: Vec<Vec<u8>> = (0..p.cameras)
            .map(|k| inputs::to_rgb(&img[k * per..(k + 1) * per], full).into_raw())
            .collect();
        for (k, px) in rgb.iter().enumerate() {
            if let Some(v) = psnr(px, &frames.truth_rgb[fi][k])? {
                psnrs.push(v);
            }
        }
        images.push(img);
        rgbs.push(rgb);
    }
    let nf = frames.ids.len() as f64;
    let nmse = if reference.is_some() && sum > 0.0 {
        err / sum
    } else {
        0.0
    };
    let mse = err / (nf * (p.cameras * 3 * full.0 * full.1) as f64);
    Ok(Measured {
        result: PointResult {
            point: p.clone(),
            ms_per_frame: (cond + den + dec) / nf,
            conditioning_ms: cond / nf,
            denoise_ms: den / nf,
            decode_ms: dec / nf,
            plan_ms,
            device_bytes,
            nmse_vs_reference: nmse,
            psnr_vs_reference: (mse > 0.0).then(|| -10.0 * mse.log10()),
            psnr_vs_truth: (!psnrs.is_empty())
                .then(|| psnrs.iter().sum::<f64>() / psnrs.len() as f64),
            vehicle_iou: None,
            mean_iou: None,
            seg_vehicle_iou: None,
            seg_marking_iou: None,
            nonfinite,
            pareto: false,
            iou: IouCounts::default(),
            seg_iou: IouCounts::default(),
        },
        images,
        rgb: rgbs,
    })
}

/// A progress line above the bar, or on stderr when the bar is hidden (stderr not a terminal: a background or
/// batch run, which would otherwise see nothing for hours).
fn say(bar: &indicatif::ProgressBar, line: &str) {
    if bar.is_hidden() {
        eprintln!("{line}");
    } else {
        bar.println(line);
    }
}

/// An autoregressive rollout: frame 1 from the recorded previous frame, then the renderer's own output; the
/// masks and references of recorded frame `(k mod (frames - 1)) + 1` (a log shorter than the rollout is
/// walked again from its start).
#[allow(clippy::too_many_arguments)]
fn rollout(
    ctx: &Context,
    pkg: &ModelPackage,
    sc: &crate::scene::Scenario,
    store: &ImageStore,
    cams: &[Camera],
    dtype: &str,
    frames: usize,
    seed: u64,
    bar: &indicatif::ProgressBar,
) -> Result<Rollout> {
    let [h, w] = pkg.meta.render_size;
    let size = (h, w);
    let names: Vec<String> = cams.iter().map(|c| c.name.clone()).collect();
    let dm = DeviceModel::upload(ctx, pkg, dtype.parse()?)?;
    let fr = FrameRenderer::new(
        ctx,
        &dm.as_model(),
        FrameShape {
            cameras: cams.len(),
            size,
            refs: true,
            ref_guidance: pkg.meta.ref_guidance,
            out_size: None,
            prev_noise_level: None,
            prev_blur_sigma: None,
        },
        &pkg.context_for(&names)?,
        sampler_plan(&pkg.meta.sampler, pkg.meta.steps, pkg.meta.prediction())?,
    )?;
    let map = map_layer(&sc.map);
    let nrec = sc.rig.frames.len();
    ensure!(
        nrec >= 2,
        "{}: the rollout needs two recorded frames",
        sc.name
    );
    let tenth = (frames / 10).max(1);
    let (mut first, mut last) = (vec![], vec![]);
    let mut nonfinite = 0;
    let mut ms = 0.0;
    for k in 0..frames {
        let fi = k % (nrec - 1) + 1;
        let step = scene::frame_step(sc, fi);
        let e2g = sc.rig.frames[fi].ego2global;
        let masks = scene::masks(sc, &map, cams, &e2g, step, size)?;
        let refs = scene::refs(store, &pkg.control_cfg, cams, &e2g, size)?;
        let prev0 = if k == 0 {
            let pgt = scene::truth(
                store,
                cams,
                &sc.rig.frames[0].ego2global,
                scene::frame_step(sc, 0),
                size,
            )?;
            Some(scene::planar_all(&pgt.rgb, size))
        } else {
            None
        };
        let (x_t, eps) =
            inputs::frame_noise(seed, 5_000_000 + k as u64, cams.len(), fr.latent_size());
        let t = fr.render(&FrameInputs {
            masks: &masks,
            prev: match &prev0 {
                Some(p) => Prev::Image(p),
                None => Prev::Carried,
            },
            refs: Some(RefInputs {
                images: &refs.images,
                pe_cur: refs.geom.pe_cur.iter().map(|v| &v[..]).collect(),
                pe_ref: refs.geom.pe_ref.iter().map(|v| &v[..]).collect(),
            }),
            x_t: &x_t,
            eps_prev: &eps,
            prev_warp: None,
        })?;
        ms += t.encode_ms + t.denoise_ms + t.decode_ms;
        let img = fr.image()?;
        nonfinite += img.iter().filter(|v| !v.is_finite()).count();
        if k < tenth || k >= frames - tenth {
            let gt = scene::truth(store, cams, &e2g, step, size)?;
            let per = 3 * h * w;
            for (c, g) in gt.rgb.iter().enumerate() {
                let px = inputs::to_rgb(&img[c * per..(c + 1) * per], size).into_raw();
                if let Some(v) = psnr(&px, g)? {
                    if k < tenth {
                        first.push(v)
                    } else {
                        last.push(v)
                    }
                }
            }
        }
        bar.inc(1);
        if (k + 1) % 100 == 0 && k + 1 < frames {
            say(
                bar,
                &format!(
                    "bench trade: rollout {dtype}: {}/{frames} frames, {nonfinite} non-finite values so far, \
                     {:.0} ms/frame",
                    k + 1,
                    ms / (k + 1) as f64
                ),
            );
        }
    }
    let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    let db = |v: Option<f64>| v.map_or("-".into(), |x| format!("{x:.2} dB"));
    say(
        bar,
        &format!(
            "bench trade: rollout {dtype} done: {frames} frames, {nonfinite} non-finite values, PSNR first 10 % {} \
             -> last 10 % {}",
            db(mean(&first)),
            db(mean(&last))
        ),
    );
    Ok(Rollout {
        dtype: dtype.into(),
        frames,
        cameras: cams.len(),
        nonfinite,
        psnr_first: mean(&first),
        psnr_last: mean(&last),
        ms_per_frame: ms / frames.max(1) as f64,
    })
}

fn check(cfg: &TradeConfig, pkg: &ModelPackage) -> Result<()> {
    ensure!(!cfg.frames.is_empty(), "bench trade: no --frames");
    ensure!(
        cfg.cameras >= 1 && cfg.cameras <= pkg.meta.cameras.len(),
        "--cameras {}: 1..={} (the model renders {:?})",
        cfg.cameras,
        pkg.meta.cameras.len(),
        pkg.meta.cameras
    );
    ensure!(
        cfg.rollout_frames <= 10_000,
        "--rollout-frames {}: at most 10000",
        cfg.rollout_frames
    );
    Ok(())
}

/// Runs the sweep and writes `<out>/{trade.json, trade.md, trade.png, trade_truth.png}`.
pub fn bench_trade(ctx: &Context, cfg: &TradeConfig, out: &Path) -> Result<TradeResults> {
    let t_start = std::time::Instant::now();
    let pkg = crate::render::package::resolve_model(cfg.model.as_deref())?;
    check(cfg, &pkg)?;
    let [h, w] = pkg.meta.render_size;
    let full = (h, w);
    let names: Vec<String> = pkg.meta.cameras[..cfg.cameras].to_vec();
    let sources = resolve(&cfg.scenario)?;
    ensure!(
        sources.len() == 1,
        "--scenario {}: names {} scenarios; bench trade takes one",
        cfg.scenario,
        sources.len()
    );
    let sc = crate::world::load(&sources[0])?;
    ensure!(
        sc.source.starts_with("builtin:"),
        "bench trade needs a synthetic scenario (builtin:...): the ground truth is the world's renderer; {} is {}",
        sc.name,
        sc.source
    );
    let store = ImageStore::new(&sc, None);
    let cams = sc.select_cameras(&names)?;
    let map = map_layer(&sc.map);
    let nrec = sc.rig.frames.len();
    for &fi in &cfg.frames {
        ensure!(
            fi >= 1 && fi < nrec,
            "--frames {fi}: {} has recorded frames 0..{nrec} and a frame needs the one before it",
            sc.name
        );
    }
    let (points, extremes) = sweep(&pkg, cfg);
    let mut sizes: Vec<(usize, usize)> = vec![];
    for p in points.iter().chain(&extremes) {
        if !sizes.contains(&p.size) {
            sizes.push(p.size);
        }
    }
    // the scene side of every frame, once
    let mut frames = Frames {
        truth_rgb: vec![],
        truth_class: vec![],
        by_size: sizes.iter().map(|s| (*s, vec![])).collect(),
        ids: vec![],
    };
    for &fi in &cfg.frames {
        let step = scene::frame_step(&sc, fi);
        let e2g = sc.rig.frames[fi].ego2global;
        let pe2g = sc.rig.frames[fi - 1].ego2global;
        let gt = scene::truth(&store, &cams, &e2g, step, full)?;
        frames.truth_rgb.push(gt.rgb);
        frames.truth_class.push(gt.class);
        frames.ids.push(fi as u64);
        for (s, v) in frames.by_size.iter_mut() {
            let pgt = scene::truth(&store, &cams, &pe2g, scene::frame_step(&sc, fi - 1), *s)?;
            v.push(FrameData {
                masks: scene::masks(&sc, &map, &cams, &e2g, step, *s)?,
                prev: scene::planar_all(&pgt.rgb, *s),
                refs: scene::refs(&store, &pkg.control_cfg, &cams, &e2g, *s)
                    .map(|r| (r.images, r.geom))?,
            });
        }
    }
    let total = points.len() + extremes.len() + 2 * cfg.rollout_frames;
    let bar = indicatif::ProgressBar::new(total as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "bench trade {bar:25} {pos}/{len} {msg} [{elapsed_precise} / eta {eta}]",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let mut measured: Vec<Measured> = vec![];
    let mut reference: Option<Vec<Vec<f32>>> = None;
    for p in &points {
        bar.set_message(p.name.clone());
        // the reference (the first point) is rendered twice: the first run's images are the reference, the
        // second run is timed warm and must equal them exactly
        if reference.is_none() {
            let first = measure(ctx, &pkg, &names, p, &frames, full, cfg.seed, None)?;
            reference = Some(first.images);
        }
        let r = reference.as_deref().context("internal: no reference")?;
        let m = measure(ctx, &pkg, &names, p, &frames, full, cfg.seed, Some(r))?;
        say(
            &bar,
            &format!(
                "bench trade: {}: {:.0} ms/frame",
                p.name, m.result.ms_per_frame
            ),
        );
        measured.push(m);
        bar.inc(1);
    }
    let r = reference.context("internal: no reference")?;
    let mut ext: Vec<Measured> = vec![];
    for p in &extremes {
        bar.set_message(p.name.clone());
        ext.push(measure(
            ctx,
            &pkg,
            &names,
            p,
            &frames,
            full,
            cfg.seed,
            Some(&r),
        )?);
        bar.inc(1);
    }
    // the layout score: a palette classifier fitted on this run's ground truth
    let pairs: Vec<(&[u8], &[u8])> = frames
        .truth_rgb
        .iter()
        .zip(&frames.truth_class)
        .flat_map(|(r, c)| r.iter().zip(c).map(|(a, b)| (&a[..], &b[..])))
        .collect();
    let clf = PaletteClassifier::fit(&pairs)?;
    let mut ceiling = IouCounts::default();
    for (r, c) in &pairs {
        ceiling.add(&clf.classify(r), c);
    }
    let classes = crate::eval::fidelity::scored_classes(&ceiling);
    // and the layout segmenter's (a judge of drawing that noise and small colour shifts do not move)
    let seg = crate::eval::fidelity::segmenter::LayoutSegmenter::builtin()?;
    let score = |m: Measured| -> Result<PointResult> {
        let mut res = m.result;
        for (fi, rgb) in m.rgb.iter().enumerate() {
            for (k, px) in rgb.iter().enumerate() {
                let truth = &frames.truth_class[fi][k];
                res.iou.add(&clf.classify(px), truth);
                res.seg_iou.add(&seg.classify(px, full.0, full.1)?, truth);
            }
        }
        res.vehicle_iou = res.iou.iou(crate::eval::fidelity::VEHICLE);
        res.mean_iou = res.iou.mean_iou(&classes);
        res.seg_vehicle_iou = res.seg_iou.iou(crate::eval::fidelity::VEHICLE);
        res.seg_marking_iou = res.seg_iou.iou(crate::eval::fidelity::LANE_MARKING);
        Ok(res)
    };
    let mut points = measured
        .into_iter()
        .map(score)
        .collect::<Result<Vec<PointResult>>>()?;
    let extremes = ext
        .into_iter()
        .map(score)
        .collect::<Result<Vec<PointResult>>>()?;
    // the front among points that render all the reference's cameras (fewer cameras is less work, not a
    // cheaper way to the same frame)
    let front = pareto(
        &points
            .iter()
            .map(|p| {
                if p.point.cameras == cfg.cameras {
                    (p.ms_per_frame, p.nmse_vs_reference)
                } else {
                    (f64::NAN, f64::NAN)
                }
            })
            .collect::<Vec<_>>(),
    );
    for (p, f) in points.iter_mut().zip(front) {
        p.pareto = f;
    }
    let mut rollouts = vec![];
    if cfg.rollout_frames > 0 {
        for dt in ["f32", "f16"] {
            bar.set_message(format!("rollout {dt}"));
            rollouts.push(rollout(
                ctx,
                &pkg,
                &sc,
                &store,
                &cams[..1],
                dt,
                cfg.rollout_frames,
                cfg.seed,
                &bar,
            )?);
        }
    }
    bar.finish_and_clear();
    let res = TradeResults {
        config: cfg.clone(),
        model: pkg.source.clone(),
        device: ctx.info().name.clone(),
        date_utc: report::now_utc(),
        render_size: [h, w],
        half_size: half_size(full).map(|(a, b)| [a, b]),
        cameras: names,
        points,
        extremes,
        rollouts,
        wall_s: t_start.elapsed().as_secs_f64(),
    };
    report::write(out, &res)?;
    Ok(res)
}
