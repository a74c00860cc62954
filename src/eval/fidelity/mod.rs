//! `b2dr eval-render`: the fidelity of a B2D-R model against the synthetic world's ground-truth renderer
//! (world.md 4), on scenarios it was not trained on.
//!
//! Three experiments, every image scored by PSNR, SSIM and the layout score ([`metrics`]):
//! - single frames at recorded frames `--frames`, on the logged path and displaced (`--lateral`, `--yaw`): the
//!   objects of the log at that step, the previous frame = the ground truth 0.5 s earlier at the same
//!   displacement (teacher forcing), references retrieved from the log at the displaced pose; settings: the
//!   model as packaged ("b2dr"), reference guidance `--guidance`, no references, no previous frame, masks only,
//!   and two baselines without a model: copy-nearest (the recorded image nearest by position: on the logged path
//!   it IS the ground truth, the ceiling) and copy-prev (the previous frame the model is given, shown unchanged:
//!   what a renderer must beat to have drawn anything new). Displaced cases run b2dr, no-refs, no-prev,
//!   masks-only, copy-prev and copy-nearest;
//!   the report pairs each with its logged-path score to show how fast PSNR falls off with and without
//!   references (with the previous frame: b2dr vs no-refs; without it: no-prev vs masks-only).
//! - autoregressive drift: `--drift-frames` consecutive frames of the logged path (2 Hz), frame 1 from the
//!   recorded image, then each frame's previous frame is the model's own last output; settings: the model's
//!   noise modulation and blur, n = 0 (inference-time proxy of a model trained without noise modulation),
//!   blur sigma 0 / 1 / 2, and the other precision (f16 when evaluating f32).
//! - the classifier ceiling: the layout classifier applied to the ground truth itself.
//!
//! Every setting of a case gets the same initial noise (paired comparison). Outputs are deterministic: a rerun
//! writes the same eval.json, eval.md and images (timing goes to timing.json).
pub mod metrics;
pub mod plot;
mod report;
pub use report::{scored_classes, LANE_MARKING, VEHICLE};
pub mod scene;
pub mod segmenter;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{ensure, Context as _, Result};
use serde::Serialize;

use self::metrics::{IouCounts, PaletteClassifier};
use self::scene::Deviation;
use crate::eval::prev_base::{agents_for, reference_base, AgentPixels};
use crate::eval::sensors::{B2drEngine, Retrieved};
use crate::projection::scene::map_layer;
use crate::render::frame::{FrameInputs, FrameRenderer, Prev, RefInputs};
use crate::render::inputs::{self, Geometry};
use crate::render::warp::ground_warp_grids;
use crate::scene::camera::Camera;
use crate::scene::import::{resolve, Source};
use crate::tensor::DType;
use crate::vk::Context;
use crate::world::images::ImageStore;

/// What `eval-render` measures (stored in `<out>/config.json`).
#[derive(Clone, Debug, Serialize)]
pub struct EvalConfig {
    /// Model package folder or `builtin:NAME`; None: the built-in default.
    pub model: Option<PathBuf>,
    /// Scenario specs (each may name several, e.g. a folder).
    pub scenarios: Vec<String>,
    /// Cameras scored (each must be one the model renders).
    pub cameras: Vec<String>,
    /// Recorded-frame indices of the single-frame cases (each needs a frame before it).
    pub frames: Vec<usize>,
    pub lateral_m: Vec<f64>,
    pub yaw_deg: Vec<f64>,
    /// Reference-guidance scales evaluated beside the model's own.
    pub guidance: Vec<f64>,
    /// Frames of the drift experiment (0: off); run on the first `drift_scenarios` scenarios.
    pub drift_frames: usize,
    pub drift_scenarios: usize,
    /// Sampler steps (None: the model's).
    pub steps: Option<usize>,
    pub seed: u64,
    /// Compute precision of the main runs: f32 or f16.
    pub dtype: String,
}

impl Default for EvalConfig {
    fn default() -> Self {
        Self {
            model: None,
            scenarios: vec![],
            cameras: vec!["CAM_FRONT".into()],
            frames: vec![8, 20, 32],
            lateral_m: vec![0.0, 1.0, 2.0, 4.0],
            yaw_deg: vec![0.0, 5.0, 10.0],
            guidance: vec![1.0, 2.0, 3.0],
            drift_frames: 40,
            drift_scenarios: 1,
            steps: None,
            seed: 0,
            dtype: "f32".into(),
        }
    }
}

/// How one image is made.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Setting {
    pub name: String,
    pub refs: bool,
    pub prev: bool,
    pub guidance: f64,
    pub noise_level: Option<usize>,
    pub blur_sigma: Option<f64>,
    /// Runs on the other precision's engine.
    pub other_dtype: bool,
    /// A baseline without a model: the image is a copy, not a render.
    pub copy: Option<CopyOf>,
}

/// What a no-model baseline copies.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum CopyOf {
    /// The recorded image nearest by ego position (log replay by position).
    Nearest,
    /// The previous frame as the model receives it (ground truth 0.5 s earlier, same displacement).
    Prev,
}

impl Setting {
    fn model(name: &str, refs: bool, prev: bool, guidance: f64) -> Self {
        Self {
            name: name.into(),
            refs,
            prev,
            guidance,
            noise_level: None,
            blur_sigma: None,
            other_dtype: false,
            copy: None,
        }
    }

    fn key(&self) -> String {
        format!(
            "{}|{}|{:?}|{:?}|{}",
            self.refs,
            if self.refs { self.guidance } else { 1.0 },
            self.noise_level,
            self.blur_sigma,
            self.other_dtype
        )
    }
}

/// One scored image.
#[derive(Clone, Debug, Serialize)]
pub struct Score {
    pub scenario: String,
    pub camera: String,
    /// Recorded frame index.
    pub frame: usize,
    pub step: usize,
    pub deviation: Deviation,
    pub setting: String,
    /// None: identical to the ground truth.
    pub psnr: Option<f64>,
    pub ssim: f64,
    pub vehicle_iou: Option<f64>,
    /// IoU of the lane-marking class (None: no marking in the truth nor in the image).
    pub marking_iou: Option<f64>,
    pub mean_iou: Option<f64>,
    /// Vehicle and lane-marking IoU of the layout segmenter's class image ([`segmenter`]).
    pub seg_vehicle_iou: Option<f64>,
    pub seg_marking_iou: Option<f64>,
    #[serde(skip)]
    iou: IouCounts,
    #[serde(skip)]
    seg_iou: IouCounts,
}

/// A scored image with its pixels (kept until the classifier is fitted).
struct Kept {
    score: Score,
    rgb: Vec<u8>,
    truth: usize,
}

struct Renderers<'e> {
    main: &'e B2drEngine,
    other: Option<&'e B2drEngine>,
    planned: BTreeMap<String, FrameRenderer>,
}

impl Renderers<'_> {
    fn get(&mut self, s: &Setting) -> Result<&FrameRenderer> {
        let k = s.key();
        if !self.planned.contains_key(&k) {
            let e = if s.other_dtype {
                self.other
                    .context("internal: no engine of the other precision")?
            } else {
                self.main
            };
            let r = e
                .plan(s.refs, s.guidance, s.noise_level, s.blur_sigma)
                .with_context(|| format!("planning setting {}", s.name))?;
            self.planned.insert(k.clone(), r);
        }
        self.planned.get(&k).context("internal: renderer")
    }
}

/// The model's inputs of one case (shared by its settings).
struct CaseInputs<'a> {
    masks: &'a [f32],
    prev: Option<&'a [f32]>,
    refs: Option<&'a (Vec<f32>, Geometry)>,
    /// The previous frame's warp grid (a model that warps it).
    warp: Option<&'a [f32]>,
    /// A model that takes its previous frame from its references: that frame and its grid, for the settings
    /// with references (those without get `prev` / `warp`, the logged previous frame: no reference at all).
    ref_prev: Option<(&'a [f32], &'a [f32])>,
    noise_id: u64,
}

/// The previous frame's warp from `prev` to `cur` (every camera at that ego pose) when the model warps it.
fn warp_grid(
    engine: &B2drEngine,
    cams: &[Camera],
    cur: &glam::DMat4,
    prev: &glam::DMat4,
    size: (usize, usize),
) -> Result<Option<Vec<f32>>> {
    let d = engine.package.control_cfg.prev_warp_max_depth;
    if d <= 0.0 {
        return Ok(None);
    }
    let n = cams.len();
    ground_warp_grids(cams, &vec![*cur; n], &vec![*prev; n], size, d).map(Some)
}

/// For a model that takes its previous frame from its references (b2dr.json `prev_source` "reference" or
/// "composite"): per camera the reference [`reference_base`] chooses (or, where it covers too little of the
/// frame, `fallback` (planar) from `fallback_pose`; "composite": the fallback also where `masks` or the
/// reference's logged agents hold one) and the warp grids to `e2g`; None for any other model.
#[allow(clippy::too_many_arguments)]
fn reference_prev(
    engine: &B2drEngine,
    sc: &crate::scene::Scenario,
    cams: &[Camera],
    e2g: &glam::DMat4,
    refs: &Retrieved,
    masks: &[f32],
    size: (usize, usize),
    fallback: &[f32],
    fallback_pose: &glam::DMat4,
) -> Result<Option<(Vec<f32>, Vec<f32>)>> {
    let cfg = &engine.package.control_cfg;
    if !cfg.prev_source.from_references() {
        return Ok(None);
    }
    let n = cams.len();
    let ra = agents_for(cfg.prev_source, sc, cams, refs, size)?;
    let agents = ra.as_ref().map(|a| AgentPixels { masks, refs: a });
    let (img, g, _) = reference_base(
        cams,
        e2g,
        refs,
        size,
        cfg.prev_warp_max_depth,
        fallback,
        &vec![*fallback_pose; n],
        agents.as_ref(),
    )?;
    Ok(Some((img, g)))
}

/// Renders one setting of a case; per camera interleaved RGB8.
fn render(
    r: &mut Renderers,
    s: &Setting,
    x: &CaseInputs,
    carried: bool,
    seed: u64,
    size: (usize, usize),
    n: usize,
) -> Result<Vec<Vec<u8>>> {
    let fr = r.get(s)?;
    let (x_t, eps) = inputs::frame_noise(seed, x.noise_id, n, fr.latent_size());
    let (prev_img, warp) = match (s.refs, x.ref_prev) {
        (true, Some((p, g))) => (Some(p), Some(g)),
        _ => (x.prev, x.warp),
    };
    let prev = match (s.prev, carried, prev_img) {
        (false, _, _) => Prev::None,
        (true, true, _) => Prev::Carried,
        (true, false, Some(p)) => Prev::Image(p),
        (true, false, None) => Prev::None,
    };
    let refs = match (s.refs, x.refs) {
        (true, Some((imgs, g))) => Some(RefInputs {
            images: imgs,
            pe_cur: g.pe_cur.iter().map(|v| &v[..]).collect(),
            pe_ref: g.pe_ref.iter().map(|v| &v[..]).collect(),
        }),
        _ => None,
    };
    fr.render(&FrameInputs {
        masks: x.masks,
        prev,
        refs,
        x_t: &x_t,
        eps_prev: &eps,
        prev_warp: warp,
    })?;
    let img = fr.image()?;
    let per = 3 * size.0 * size.1;
    ensure!(
        img.len() == n * per,
        "internal: decoded {} values",
        img.len()
    );
    Ok((0..n)
        .map(|k| {
            // Non-finite pixels become 0 here; they are counted separately (drift) so they cannot hide.
            inputs::to_rgb(&img[k * per..(k + 1) * per], size).into_raw()
        })
        .collect())
}

/// Scores one setting's images of a case (scenario, frame, step, deviation, setting) against the truths
/// `truth` (whose class images sit at `truths[t0 + k]`) and keeps them for the layout score.
fn keep(
    out: &mut Vec<Kept>,
    (scenario, frame, step, dev, setting): (&str, usize, usize, Deviation, &str),
    cams: &[Camera],
    imgs: &[Vec<u8>],
    truth: &[Vec<u8>],
    t0: usize,
    size: (usize, usize),
) -> Result<()> {
    for (k, img) in imgs.iter().enumerate() {
        out.push(Kept {
            score: report::score(
                scenario,
                &cams[k].name,
                frame,
                step,
                dev,
                setting,
                img,
                &truth[k],
                size,
            )?,
            rgb: img.clone(),
            truth: t0 + k,
        });
    }
    Ok(())
}

/// The whole evaluation's results (eval.json).
#[derive(Debug, Serialize)]
pub struct Results {
    pub config: EvalConfig,
    pub model: String,
    pub render_size: [usize; 2],
    pub single: Vec<Score>,
    pub drift: Vec<Score>,
    /// Non-finite pixel values seen per drift setting.
    pub drift_nonfinite: BTreeMap<String, usize>,
    pub classifier_ceiling: BTreeMap<String, Option<f64>>,
    /// The layout segmenter on the ground truth itself, per class.
    pub segmenter_ceiling: BTreeMap<String, Option<f64>>,
    pub skipped: Vec<String>,
}

fn single_settings(default_w: f64, guidance: &[f64]) -> Vec<Setting> {
    let mut v = vec![Setting::model("b2dr", true, true, default_w)];
    for &g in guidance {
        if g != default_w {
            v.push(Setting::model(&format!("b2dr w={g}"), true, true, g));
        }
    }
    v.push(Setting::model("no-refs", false, true, 1.0));
    v.push(Setting::model("no-prev", true, false, default_w));
    v.push(Setting::model("masks-only", false, false, 1.0));
    v
}

fn deviated_settings(default_w: f64) -> Vec<Setting> {
    vec![
        Setting::model("b2dr", true, true, default_w),
        Setting::model("no-refs", false, true, 1.0),
        Setting::model("no-prev", true, false, default_w),
        Setting::model("masks-only", false, false, 1.0),
    ]
}

fn drift_settings(default_w: f64, blur: f64, other: &str) -> Vec<Setting> {
    let base = Setting::model("b2dr", true, true, default_w);
    let mut v = vec![base.clone()];
    v.push(Setting {
        name: "n=0".into(),
        noise_level: Some(0),
        ..base.clone()
    });
    for b in [0.0, 1.0, 2.0] {
        if b != blur {
            v.push(Setting {
                name: format!("blur {b}"),
                blur_sigma: Some(b),
                ..base.clone()
            });
        }
    }
    v.push(Setting {
        name: other.into(),
        other_dtype: true,
        ..base
    });
    v
}

/// The no-model baselines of every single-frame case, in report order.
fn copy_settings() -> [Setting; 2] {
    [
        Setting {
            copy: Some(CopyOf::Prev),
            ..Setting::model("copy-prev", false, false, 1.0)
        },
        Setting {
            copy: Some(CopyOf::Nearest),
            ..Setting::model("copy-nearest", false, false, 1.0)
        },
    ]
}

fn check(cfg: &EvalConfig) -> Result<()> {
    ensure!(
        !cfg.scenarios.is_empty(),
        "eval-render: no --scenario given"
    );
    ensure!(!cfg.cameras.is_empty(), "eval-render: no --cameras given");
    for &l in &cfg.lateral_m {
        ensure!(
            l.is_finite() && l.abs() <= 20.0,
            "--lateral {l}: metres in [-20, 20]"
        );
    }
    for &y in &cfg.yaw_deg {
        ensure!(
            y.is_finite() && y.abs() <= 90.0,
            "--yaw {y}: degrees in [-90, 90]"
        );
    }
    for &g in &cfg.guidance {
        ensure!(
            g.is_finite() && g > 0.0 && g <= 20.0,
            "--guidance {g}: in (0, 20]"
        );
    }
    ensure!(cfg.drift_frames <= 1000, "--drift-frames: at most 1000");
    if let Some(s) = cfg.steps {
        ensure!((1..=1000).contains(&s), "--steps {s}: in 1..=1000");
    }
    Ok(())
}

fn deviations(cfg: &EvalConfig) -> Vec<Deviation> {
    let mut v: Vec<Deviation> = vec![];
    let mut push = |d: Deviation| {
        if !v.contains(&d) {
            v.push(d)
        }
    };
    push(Deviation::NONE);
    for &l in &cfg.lateral_m {
        push(Deviation {
            lateral_m: l,
            yaw_deg: 0.0,
        });
    }
    for &y in &cfg.yaw_deg {
        push(Deviation {
            lateral_m: 0.0,
            yaw_deg: y,
        });
    }
    v
}

/// Runs the evaluation and writes `<out>/{config.json, eval.json, eval.md, timing.json, *.png, strips/}`.
pub fn eval_render(ctx: &Context, cfg: &EvalConfig, out: &Path) -> Result<Results> {
    check(cfg)?;
    let t_start = std::time::Instant::now();
    let pkg = crate::render::package::resolve_model(cfg.model.as_deref())?;
    let model_name = pkg.source.clone();
    let dtype: DType = cfg.dtype.parse()?;
    let (other_dtype, other_name) = match dtype {
        DType::F32 => (DType::F16, "f16"),
        _ => (DType::F32, "f32"),
    };
    let default_w = pkg.meta.ref_guidance;
    let blur = pkg.control_cfg.prev_blur_sigma;
    let from_refs = pkg.control_cfg.prev_source.from_references();
    let mk = |dt: DType, pkg| {
        B2drEngine::new(
            ctx,
            pkg,
            dt,
            cfg.cameras.clone(),
            true,
            cfg.steps,
            None,
            cfg.seed,
        )
    };
    let main = mk(dtype, pkg.clone())?;
    let other = if cfg.drift_frames > 0 {
        Some(mk(other_dtype, pkg)?)
    } else {
        None
    };
    let size = main.size();
    let n = cfg.cameras.len();
    let mut rs = Renderers {
        main: &main,
        other: other.as_ref(),
        planned: BTreeMap::new(),
    };
    let mut sources: Vec<Source> = vec![];
    for s in &cfg.scenarios {
        sources.extend(resolve(s)?);
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    std::fs::write(out.join("config.json"), serde_json::to_string_pretty(cfg)?)?;
    let devs = deviations(cfg);
    let single = single_settings(default_w, &cfg.guidance);
    let deviated = deviated_settings(default_w);
    let drift = drift_settings(default_w, blur, other_name);
    let per_scenario = cfg.frames.len() * (single.len() + (devs.len() - 1) * deviated.len());
    let drift_total = cfg.drift_frames * drift.len() * cfg.drift_scenarios.min(sources.len());
    let bar = indicatif::ProgressBar::new((per_scenario * sources.len() + drift_total) as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "eval-render {bar:25} {pos}/{len} renders {msg} [{elapsed_precise} / eta {eta}]",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let mut truths: Vec<(Vec<u8>, Vec<u8>)> = vec![];
    let mut kept: Vec<Kept> = vec![];
    let mut drift_kept: Vec<Kept> = vec![];
    let mut nonfinite: BTreeMap<String, usize> = BTreeMap::new();
    let mut skipped = vec![];
    let mut strips = report::Strips::default();
    // the strips show the first case evaluated (first scenario, first frame that has a previous frame)
    let mut strip_case: Option<(usize, usize)> = None;
    for (si, src) in sources.iter().enumerate() {
        let sc = crate::world::load(src)?;
        ensure!(
            sc.source.starts_with("builtin:"),
            "eval-render needs synthetic scenarios (builtin:...): the ground truth is the world's renderer; {} \
             is {}",
            sc.name,
            sc.source
        );
        let store = ImageStore::new(&sc, None);
        let cams: Vec<Camera> = sc.select_cameras(&cfg.cameras)?;
        let map = map_layer(&sc.map);
        let nf = sc.rig.frames.len();
        bar.set_message(sc.name.clone());
        for &fi in &cfg.frames {
            if fi == 0 || fi >= nf {
                skipped.push(format!(
                    "{}: frame {fi} (the log has frames 0..{nf}; a case needs a frame before it)",
                    sc.name
                ));
                bar.inc((single.len() + (devs.len() - 1) * deviated.len()) as u64);
                continue;
            }
            let step = scene::frame_step(&sc, fi);
            let pstep = scene::frame_step(&sc, fi - 1);
            if si == 0 && strip_case.is_none() {
                strip_case = Some((si, fi));
            }
            for (di, d) in devs.iter().enumerate() {
                let settings = if d.is_none() { &single } else { &deviated };
                let poses = scene::pose_at(&sc, fi, d)
                    .and_then(|e| Ok((e, scene::pose_at(&sc, fi - 1, d)?)));
                let (e2g, pe2g) = match poses {
                    Ok(p) => p,
                    Err(e) => {
                        skipped.push(format!("{} frame {fi} {}: {e:#}", sc.name, d.label()));
                        bar.inc(settings.len() as u64);
                        continue;
                    }
                };
                let gt = scene::truth(&store, &cams, &e2g, step, size)?;
                let pgt = scene::truth(&store, &cams, &pe2g, pstep, size)?;
                let masks = scene::masks(&sc, &map, &cams, &e2g, step, size)?;
                let r = scene::refs(&store, &main.package.control_cfg, &cams, &e2g, size)?;
                let prev = scene::planar_all(&pgt.rgb, size);
                let warp = warp_grid(&main, &cams, &e2g, &pe2g, size)?;
                let rp = reference_prev(&main, &sc, &cams, &e2g, &r, &masks, size, &prev, &pe2g)?;
                let refs = (r.images, r.geom);
                let x = CaseInputs {
                    masks: &masks,
                    prev: Some(&prev),
                    refs: Some(&refs),
                    warp: warp.as_deref(),
                    ref_prev: rp.as_ref().map(|(p, g)| (&p[..], &g[..])),
                    noise_id: 1_000_000 + (fi as u64) * 64 + di as u64,
                };
                let t0 = truths.len();
                for k in 0..n {
                    truths.push((gt.rgb[k].clone(), gt.class[k].clone()));
                }
                let copy = scene::copy_nearest(&store, &cams, &e2g, size)?;
                let mut row: Vec<(String, Vec<Vec<u8>>)> = vec![];
                for s in settings.iter().chain(copy_settings().iter()) {
                    let imgs = match s.copy {
                        Some(CopyOf::Nearest) => copy.clone(),
                        Some(CopyOf::Prev) => pgt.rgb.clone(),
                        None => {
                            let v = render(&mut rs, s, &x, false, cfg.seed, size, n)?;
                            bar.inc(1);
                            v
                        }
                    };
                    let id = (sc.name.as_str(), fi, step, *d, s.name.as_str());
                    keep(&mut kept, id, &cams, &imgs, &gt.rgb, t0, size)?;
                    row.push((s.name.clone(), imgs));
                }
                if strip_case == Some((si, fi)) {
                    strips.single.push((d.label(), gt.rgb.clone(), row));
                }
            }
        }
        if si < cfg.drift_scenarios && cfg.drift_frames > 0 {
            ensure!(
                cfg.drift_frames < nf,
                "--drift-frames {}: {} has {nf} recorded frames (frame 0 starts the drift)",
                cfg.drift_frames,
                sc.name
            );
            let rec0: Vec<Vec<u8>> = cams
                .iter()
                .map(|c| {
                    let img = sc.rig.frames[0]
                        .images
                        .iter()
                        .find(|i| i.camera == c.name)
                        .with_context(|| format!("{}: frame 0 has no {}", sc.name, c.name))?;
                    crate::eval::sensors::recorded_pixels(&store, img, size)
                })
                .collect::<Result<_>>()?;
            let prev0 = scene::planar_all(&rec0, size);
            for s in &drift {
                let mut bad = 0usize;
                let mut last_out: Option<Vec<f32>> = None;
                for fi in 1..=cfg.drift_frames {
                    let step = scene::frame_step(&sc, fi);
                    let e2g = sc.rig.frames[fi].ego2global;
                    let gt = scene::truth(&store, &cams, &e2g, step, size)?;
                    let masks = scene::masks(&sc, &map, &cams, &e2g, step, size)?;
                    let r = scene::refs(&store, &main.package.control_cfg, &cams, &e2g, size)?;
                    // frame 1's previous frame is the recorded frame 0, later ones the last output (a model
                    // that takes it from its references: a reference every frame, nothing carried)
                    let pe2g = sc.rig.frames[fi - 1].ego2global;
                    let warp = warp_grid(&main, &cams, &e2g, &pe2g, size)?;
                    // a reference-source model's fallback: the last output (frame 1: the recorded frame 0)
                    let last = match &last_out {
                        Some(l) => l,
                        None => &prev0,
                    };
                    let rp =
                        reference_prev(&main, &sc, &cams, &e2g, &r, &masks, size, last, &pe2g)?;
                    let refs = (r.images, r.geom);
                    let x = CaseInputs {
                        masks: &masks,
                        prev: Some(&prev0),
                        refs: Some(&refs),
                        warp: warp.as_deref(),
                        ref_prev: rp.as_ref().map(|(p, g)| (&p[..], &g[..])),
                        noise_id: fi as u64,
                    };
                    let carried = fi > 1 && !from_refs;
                    let fr_bad = {
                        let imgs = render(&mut rs, s, &x, carried, cfg.seed, size, n)?;
                        last_out = Some(scene::planar_all(&imgs, size));
                        let raw = rs.get(s)?.image()?;
                        let t0 = truths.len();
                        for k in 0..n {
                            truths.push((gt.rgb[k].clone(), gt.class[k].clone()));
                        }
                        let id = (sc.name.as_str(), fi, step, Deviation::NONE, s.name.as_str());
                        keep(&mut drift_kept, id, &cams, &imgs, &gt.rgb, t0, size)?;
                        if si == 0 && s.name == "b2dr" {
                            strips.drift.push((fi, gt.rgb.clone(), imgs));
                        }
                        raw.iter().filter(|v| !v.is_finite()).count()
                    };
                    bad += fr_bad;
                    bar.inc(1);
                }
                *nonfinite.entry(s.name.clone()).or_default() += bad;
            }
        }
    }
    bar.finish_and_clear();
    // The layout classifier, fitted on every ground-truth image of this evaluation, then applied to all.
    let pairs: Vec<(&[u8], &[u8])> = truths.iter().map(|(r, c)| (&r[..], &c[..])).collect();
    let clf = PaletteClassifier::fit(&pairs)?;
    let mut ceiling = IouCounts::default();
    for (r, c) in &truths {
        ceiling.add(&clf.classify(r), c);
    }
    let classes = report::scored_classes(&ceiling);
    let seg = segmenter::LayoutSegmenter::builtin()?;
    let mut seg_ceiling = IouCounts::default();
    for (r, c) in &truths {
        seg_ceiling.add(&seg.classify(r, size.0, size.1)?, c);
    }
    let finish = |v: Vec<Kept>| -> Result<Vec<Score>> {
        v.into_iter()
            .map(|k| {
                let mut s = k.score;
                s.iou.add(&clf.classify(&k.rgb), &truths[k.truth].1);
                s.vehicle_iou = s.iou.iou(report::VEHICLE);
                s.marking_iou = s.iou.iou(report::LANE_MARKING);
                s.mean_iou = s.iou.mean_iou(&classes);
                s.seg_iou
                    .add(&seg.classify(&k.rgb, size.0, size.1)?, &truths[k.truth].1);
                s.seg_vehicle_iou = s.seg_iou.iou(report::VEHICLE);
                s.seg_marking_iou = s.seg_iou.iou(report::LANE_MARKING);
                Ok(s)
            })
            .collect()
    };
    let res = Results {
        config: cfg.clone(),
        model: model_name,
        render_size: [size.0, size.1],
        single: finish(kept)?,
        drift: finish(drift_kept)?,
        drift_nonfinite: nonfinite,
        classifier_ceiling: report::class_table(&ceiling, &classes),
        segmenter_ceiling: report::class_table(&seg_ceiling, &classes),
        skipped,
    };
    report::write(out, &res, &classes, &strips, size)?;
    let timing = serde_json::json!({
        "wall_s": t_start.elapsed().as_secs_f64(),
        "device": ctx.info().name.clone(),
        "renders": per_scenario * sources.len() + drift_total,
    });
    std::fs::write(
        out.join("timing.json"),
        serde_json::to_string_pretty(&timing)?,
    )?;
    Ok(res)
}
