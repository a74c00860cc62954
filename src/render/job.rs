//! `b2dr render`: one frame of a keyframe (the shared keyframe JSON format) rendered by a model package, with
//! the frame's projected layout, a previous frame and two references; writes per-camera PNG/EXR and a report.
use std::path::PathBuf;

use anyhow::{bail, ensure, Context as _, Result};
use serde_json::json;

use super::frame::{FrameInputs, FrameRenderer, FrameShape, Prev, RefInputs};
use super::inputs;
use super::package::DeviceModel;
use crate::projection::keyframe::drivable_area_from_geojson;
use crate::projection::{KeyFrame, MapLayer, ProjectionConfig};
use crate::sampling::{NoiseSchedule, PredictionType, SamplerKind, SamplerPlan};
use crate::tensor::DType;
use crate::vk::Context;

/// What to render.
#[derive(Clone, Debug)]
pub struct RenderJob {
    /// A model package folder, or None for the built-in model.
    pub model: Option<PathBuf>,
    pub frame: PathBuf,
    /// Previous frames: one image per camera (in camera order), or one folder holding `<CAMERA>.png`; empty:
    /// the frame's own recorded images (the first frame of a run).
    pub prev: Vec<PathBuf>,
    /// Two keyframes whose images of the same camera are the front and rear references; None: the frame's
    /// own images on both sides.
    pub refs: Option<[PathBuf; 2]>,
    pub no_refs: bool,
    /// Cameras (default: the model's cameras present in the frame).
    pub cameras: Option<Vec<String>>,
    pub steps: Option<usize>,
    pub sampler: Option<String>,
    pub ref_guidance: Option<f64>,
    pub seed: u64,
    pub dtype: DType,
    /// Optional drivable-area GeoJSON (global frame).
    pub map: Option<PathBuf>,
    /// `auto`, `center` or `top` (how to read the keyframe's box z, see `b2dr project`).
    pub box_z: String,
    pub out: PathBuf,
}

/// The sampler plan named in a package or on the command line, for a model that predicts `prediction`.
pub fn sampler_plan(name: &str, steps: usize, prediction: PredictionType) -> Result<SamplerPlan> {
    ensure!(
        (1..=1000).contains(&steps),
        "--steps {steps} must be in 1..=1000"
    );
    let kind: SamplerKind = name.parse()?;
    kind.plan(&NoiseSchedule::sd15(), prediction, steps)
}

/// Renders the job's frame; returns the report written to `out/render.json`.
pub fn run(ctx: &Context, j: &RenderJob) -> Result<serde_json::Value> {
    let t0 = std::time::Instant::now();
    let pkg = super::package::resolve_model(j.model.as_deref())?;
    let [ih, iw] = pkg.meta.render_size;
    let size = (ih, iw);
    let mut frame = KeyFrame::load(&j.frame)?;
    let top = match j.box_z.as_str() {
        "top" => true,
        "center" => false,
        "auto" => frame.z_looks_like_top(),
        other => bail!("--box-z {other:?}: expected auto, center or top"),
    };
    if top {
        frame.boxes_z_from_top();
    }
    let names: Vec<String> = match &j.cameras {
        Some(c) => c.clone(),
        None => pkg
            .meta
            .cameras
            .iter()
            .filter(|c| frame.cameras.iter().any(|(k, _)| &k.name == *c))
            .cloned()
            .collect(),
    };
    ensure!(
        !names.is_empty(),
        "{}: none of the model's cameras {:?} is in the frame",
        j.frame.display(),
        pkg.meta.cameras
    );
    let mut cams = vec![];
    for n in &names {
        let (c, img) = frame
            .cameras
            .iter()
            .find(|(c, _)| &c.name == n)
            .with_context(|| {
                format!(
                    "--cameras: {n:?} is not a camera of {} (it has {:?})",
                    j.frame.display(),
                    frame
                        .cameras
                        .iter()
                        .map(|(c, _)| &c.name)
                        .collect::<Vec<_>>()
                )
            })?;
        cams.push((c.clone(), img.clone()));
    }
    let n = cams.len();
    let cfg = &pkg.control_cfg;
    let map = match &j.map {
        Some(p) => MapLayer::new(drivable_area_from_geojson(p, frame.ego2global.w_axis.z)?),
        None => MapLayer::default(),
    };
    let cameras: Vec<_> = cams.iter().map(|(c, _)| c.clone()).collect();
    let poses: Vec<_> = cams.iter().map(|(_, i)| i.ego2global).collect();
    let masks = inputs::masks(
        &cameras,
        &poses,
        &frame.boxes,
        &map,
        size,
        &ProjectionConfig::default(),
    )?;
    // previous frames
    let mut prev = vec![];
    match j.prev.as_slice() {
        [] => {
            for (_, img) in &cams {
                prev.extend(inputs::read_planar(&frame.image_path(img), size)?);
            }
        }
        [d] if d.is_dir() => {
            for (c, _) in &cams {
                prev.extend(inputs::read_planar(
                    &d.join(format!("{}.png", crate::scene::safe_name(&c.name))),
                    size,
                )?);
            }
        }
        list => {
            ensure!(
                list.len() == n,
                "--prev: {} images for {n} cameras {names:?} (give one per camera, or a folder of <CAMERA>.png)",
                list.len()
            );
            for p in list {
                prev.extend(inputs::read_planar(p, size)?);
            }
        }
    }
    // references
    let ref_frames = match &j.refs {
        Some([a, b]) => Some([KeyFrame::load(a)?, KeyFrame::load(b)?]),
        None => None,
    };
    let mut ref_imgs = vec![];
    let mut geoms = vec![];
    if !j.no_refs {
        for (c, img) in &cams {
            let pick = |kf: &KeyFrame| -> Result<(PathBuf, glam::DMat4)> {
                let (_, ri) = kf
                    .cameras
                    .iter()
                    .find(|(k, _)| k.name == c.name)
                    .with_context(|| {
                        format!("--refs: {} has no camera {}", kf.dir.display(), c.name)
                    })?;
                Ok((kf.image_path(ri), ri.ego2global))
            };
            let pair = match &ref_frames {
                Some([a, b]) => [pick(a)?, pick(b)?],
                None => [pick(&frame)?, pick(&frame)?],
            };
            for (p, _) in &pair {
                ref_imgs.extend(inputs::read_planar(p, size)?);
            }
            geoms.push(inputs::geometry(
                cfg,
                c,
                size,
                &img.ego2global,
                [&pair[0].1, &pair[1].1],
            )?);
        }
    }
    let geom = inputs::stack(&geoms);
    let steps = j.steps.unwrap_or(pkg.meta.steps);
    let sampler = j.sampler.clone().unwrap_or(pkg.meta.sampler.clone());
    let w = j.ref_guidance.unwrap_or(pkg.meta.ref_guidance);
    let plan = sampler_plan(&sampler, steps, pkg.meta.prediction())?;
    let dm = DeviceModel::upload(ctx, &pkg, j.dtype)?;
    let context = pkg.context_for(&names)?;
    let load_s = t0.elapsed().as_secs_f64();
    let t1 = std::time::Instant::now();
    let r = FrameRenderer::new(
        ctx,
        &dm.as_model(),
        FrameShape {
            cameras: n,
            size,
            refs: !j.no_refs,
            ref_guidance: w,
            out_size: None,
            prev_noise_level: None,
            prev_blur_sigma: None,
        },
        &context,
        plan,
    )?;
    let plan_ms = t1.elapsed().as_secs_f64() * 1e3;
    let (x_t, eps) = inputs::frame_noise(j.seed, 0, n, r.latent_size());
    let times = r.render(&FrameInputs {
        masks: &masks,
        prev: Prev::Image(&prev),
        refs: (!j.no_refs).then(|| RefInputs {
            images: &ref_imgs,
            pe_cur: geom.pe_cur.iter().map(|v| &v[..]).collect(),
            pe_ref: geom.pe_ref.iter().map(|v| &v[..]).collect(),
        }),
        x_t: &x_t,
        eps_prev: &eps,
        prev_warp: None,
    })?;
    let img = r.image()?;
    std::fs::create_dir_all(&j.out).with_context(|| format!("creating {}", j.out.display()))?;
    let per = 3 * ih * iw;
    for (k, name) in names.iter().enumerate() {
        let chw = &img[k * per..(k + 1) * per];
        let stem = crate::scene::safe_name(name);
        let p = j.out.join(format!("{stem}.png"));
        inputs::to_rgb(chw, size)
            .save(&p)
            .with_context(|| format!("writing {}", p.display()))?;
        inputs::write_exr(&j.out.join(format!("{stem}.exr")), chw, size)?;
    }
    let report = json!({
        "device": ctx.info().name, "model": pkg.source, "frame": j.frame.display().to_string(),
        "cameras": names, "render_size": [ih, iw], "steps": steps, "sampler": sampler, "ref_guidance": w,
        "references": !j.no_refs, "seed": j.seed, "dtype": j.dtype.name(),
        "load_s": load_s, "plan_ms": plan_ms, "times_ms": times,
        "device_bytes_weights": dm.weight_bytes, "device_bytes_planned": r.planned_bytes,
        "device_bytes_total": ctx.allocated_bytes(),
    });
    std::fs::write(
        j.out.join("render.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    Ok(report)
}
