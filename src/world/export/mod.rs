//! `b2dr export-training`: training samples of the B2D-R renderer (spec world.md section 2) as safetensors
//! shards plus a JSON index; the format is documented in docs/training_data.md and read by
//! python/b2dr_ref/dataset.py.
//!
//! The same code that conditions the renderer at inference computes every input here: masks from
//! `projection::layout` (via [`crate::world::view::layout_masks`]), references from `projection::retrieval`,
//! intrinsics from `Camera::intrinsic_scaled`, and the matrices `pe.rs`'s `cam2cur` takes.
pub mod plan;
pub mod shard;

use super::images::ImageStore;
use super::render::{render_cameras, RenderOptions};
use super::view::{layout_masks, MAX_OFF_ROAD_M};
use super::{load, objects_at};
use crate::projection::layout::LayoutMasks;
use crate::projection::scene::map_layer;
use crate::projection::{channel_name, MapLayer, NUM_MASK_CHANNELS};
use crate::scene::camera::{Camera, RecordedFrame};
use crate::scene::geometry::Pose2;
use crate::scene::import::{ego2global, resolve, Source};
use crate::scene::Scenario;
use anyhow::{bail, ensure, Context, Result};
use glam::{DMat3, DMat4};
use plan::{candidate_frames, frame_step, plan_samples, SamplePlan, PREV_GAP_S};
use serde_json::{json, Value};
use shard::Shard;
use std::collections::HashMap;
use std::path::PathBuf;

/// Format name and version written into the index.
pub const FORMAT: &str = "b2dr-training";
pub const VERSION: u32 = 1;

/// What to export.
#[derive(Clone, Debug)]
pub struct ExportOptions {
    /// `--scenario` arguments (each may name several scenarios).
    pub scenarios: Vec<String>,
    pub out: PathBuf,
    pub height: usize,
    pub width: usize,
    /// Targets per scenario (each exported once per offset).
    pub samples_per_scenario: usize,
    /// Ego-frame offsets (dx m, dy m, dyaw rad); the zero offset is the logged pose.
    pub offsets: Vec<Pose2>,
    pub seed: u64,
    /// Empty: the rig's cameras.
    pub cameras: Vec<String>,
    /// Samples per shard.
    pub shard_samples: usize,
    pub progress: bool,
    /// Only targets with a two-frame chain (previous frame and ITS previous frame), and per sample the
    /// previous frame's own inputs: `prev_masks_packed` (its layout at its logged pose) and `prev2` (the log's
    /// image 0.5 s before it). For training on the model's own rollout (train --self-prev-pose chain).
    pub prev_chain: bool,
}

/// What was written.
#[derive(Clone, Debug, PartialEq)]
pub struct ExportSummary {
    pub samples: usize,
    pub shards: usize,
    pub skipped_off_map: usize,
    pub index: PathBuf,
}

/// One rendered sample (per-camera tensors concatenated in camera order).
struct SampleData {
    target: Vec<u8>,
    prev: Vec<u8>,
    refs: Vec<u8>,
    masks: Vec<u16>,
    intrinsics: Vec<f64>,
    cam2ego: Vec<f64>,
    e2g: Vec<f64>,
    prev_e2g: Vec<f64>,
    ref_e2g: Vec<f64>,
    ref_distance: Vec<f32>,
    ref_step: Vec<i32>,
    prev_step: usize,
    /// With `prev_chain` (else empty / None): the previous frame's previous image, its logged pose (the
    /// chain's first hop warps it to the previous frame's pose) and the previous frame's own layout masks.
    prev2: Vec<u8>,
    prev2_e2g: Vec<f64>,
    prev_masks: Vec<u16>,
    prev2_step: Option<usize>,
}

fn rows3(m: &DMat3) -> [f64; 9] {
    m.transpose().to_cols_array()
}

fn rows4(m: &DMat4) -> [f64; 16] {
    m.transpose().to_cols_array()
}

/// `(H, W, 3)` -> `(3, H, W)` appended to `out`.
fn push_planar(rgb: &[u8], out: &mut Vec<u8>) {
    let n = rgb.len() / 3;
    for c in 0..3 {
        out.extend((0..n).map(|p| rgb[3 * p + c]));
    }
}

/// One camera's masks, bit k = channel k.
fn pack_masks(m: &LayoutMasks, out: &mut Vec<u16>) {
    let mut packed = vec![0u16; m.width * m.height];
    for c in 0..NUM_MASK_CHANNELS {
        for (p, &v) in m.channel(c).iter().enumerate() {
            packed[p] |= (v as u16 & 1) << c;
        }
    }
    out.extend_from_slice(&packed);
}

/// Rear-axle pose of an ego -> global matrix (yaw from its x axis).
fn pose_of(m: &DMat4) -> Pose2 {
    Pose2::new(m.w_axis.x, m.w_axis.y, m.x_axis.y.atan2(m.x_axis.x))
}

/// A scenario ready for export.
struct Job<'a> {
    sc: &'a Scenario,
    store: ImageStore<'a>,
    frames: Vec<RecordedFrame>,
    cams: Vec<Camera>,
    layer: MapLayer,
    generated: bool,
}

impl Job<'_> {
    /// Renders one sample; `Ok(None)` when its displaced pose is off the map.
    fn sample(&self, s: &SamplePlan, h: usize, w: usize) -> Result<Option<SampleData>> {
        let sc = self.sc;
        let (f, pf) = (&self.frames[s.frame], &self.frames[s.prev]);
        let zero = s.offset == Pose2::default();
        ensure!(
            zero || self.generated,
            "{}: ego offsets need a generated log (builtin:); this log's images are files",
            sc.name
        );
        let mut d = SampleData {
            target: Vec::new(),
            prev: Vec::new(),
            refs: Vec::new(),
            masks: Vec::new(),
            intrinsics: Vec::new(),
            cam2ego: Vec::new(),
            e2g: Vec::new(),
            prev_e2g: Vec::new(),
            ref_e2g: Vec::new(),
            ref_distance: Vec::new(),
            ref_step: Vec::new(),
            prev_step: frame_step(sc, pf),
            prev2: Vec::new(),
            prev2_e2g: Vec::new(),
            prev_masks: Vec::new(),
            prev2_step: s.prev2.map(|i| frame_step(sc, &self.frames[i])),
        };
        let objects = objects_at(sc, s.step);
        for (ci, cam) in self.cams.iter().enumerate() {
            let img = f.image(&cam.name).context("target frame lacks a camera")?;
            let pimg = pf
                .image(&cam.name)
                .context("previous frame lacks a camera")?;
            let cur = if zero {
                img.ego2global
            } else {
                let p = pose_of(&img.ego2global).compose(&s.offset);
                if !sc
                    .map
                    .drivable_distance(p.pos(), MAX_OFF_ROAD_M)
                    .is_finite()
                {
                    return Ok(None);
                }
                ego2global(&p)
            };
            if zero {
                push_planar(&self.store.image(img, w, h)?.data, &mut d.target);
            } else {
                let fr = render_cameras(
                    &self.store.world().scenery,
                    std::slice::from_ref(cam),
                    &cur,
                    w,
                    h,
                    &objects,
                    &RenderOptions::default(),
                    1,
                )?;
                push_planar(&fr[0].rgb, &mut d.target);
            }
            push_planar(&self.store.image(pimg, w, h)?.data, &mut d.prev);
            let m = layout_masks(
                sc,
                &self.layer,
                std::slice::from_ref(cam),
                &cur,
                s.step,
                w,
                h,
            )?;
            pack_masks(&m[0], &mut d.masks);
            if let Some(p2) = s.prev2 {
                let p2img = self.frames[p2]
                    .image(&cam.name)
                    .context("the previous frame's previous frame lacks a camera")?;
                push_planar(&self.store.image(p2img, w, h)?.data, &mut d.prev2);
                d.prev2_e2g.extend(rows4(&p2img.ego2global));
                // the previous frame's layout where the log drew it: its logged pose and step
                let pm = layout_masks(
                    sc,
                    &self.layer,
                    std::slice::from_ref(cam),
                    &pimg.ego2global,
                    d.prev_step,
                    w,
                    h,
                )?;
                pack_masks(&pm[0], &mut d.prev_masks);
            }
            d.intrinsics
                .extend(rows3(&cam.intrinsic_scaled(w as u32, h as u32)));
            d.cam2ego.extend(rows4(&cam.cam2ego));
            d.e2g.extend(rows4(&cur));
            d.prev_e2g.extend(rows4(&pimg.ego2global));
            for r in &s.refs[ci] {
                let rimg = &self.frames[r.frame].images[r.image];
                push_planar(&self.store.image(rimg, w, h)?.data, &mut d.refs);
                d.ref_e2g.extend(rows4(&rimg.ego2global));
                d.ref_distance.push(r.along as f32);
                d.ref_step
                    .push(frame_step(sc, &self.frames[r.frame]) as i32);
            }
        }
        Ok(Some(d))
    }
}

fn append(
    shard: &mut Shard,
    d: &SampleData,
    s: &SamplePlan,
    scenario: usize,
    nc: usize,
    h: usize,
    w: usize,
) -> Result<()> {
    shard.push("target", &[nc, 3, h, w], &d.target)?;
    shard.push("prev", &[nc, 3, h, w], &d.prev)?;
    shard.push("ref", &[nc, 2, 3, h, w], &d.refs)?;
    shard.push("masks_packed", &[nc, h, w], &d.masks)?;
    shard.push("intrinsics", &[nc, 3, 3], &d.intrinsics)?;
    shard.push("cam2ego", &[nc, 4, 4], &d.cam2ego)?;
    shard.push("ego2global", &[nc, 4, 4], &d.e2g)?;
    shard.push("prev_ego2global", &[nc, 4, 4], &d.prev_e2g)?;
    shard.push("ref_ego2global", &[nc, 2, 4, 4], &d.ref_e2g)?;
    shard.push("ref_distance", &[nc, 2], &d.ref_distance)?;
    shard.push("ref_step", &[nc, 2], &d.ref_step)?;
    shard.push("step", &[], &[s.step as i32])?;
    shard.push("prev_step", &[], &[d.prev_step as i32])?;
    shard.push("scenario_index", &[], &[scenario as i32])?;
    if let Some(p2) = d.prev2_step {
        shard.push("prev2", &[nc, 3, h, w], &d.prev2)?;
        shard.push("prev2_ego2global", &[nc, 4, 4], &d.prev2_e2g)?;
        shard.push("prev_masks_packed", &[nc, h, w], &d.prev_masks)?;
        shard.push("prev2_step", &[], &[p2 as i32])?;
    }
    shard.push(
        "offset",
        &[3],
        &[s.offset.x, s.offset.y, s.offset.heading.to_degrees()],
    )?;
    shard.rows += 1;
    Ok(())
}

fn metadata() -> HashMap<String, String> {
    HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("version".to_string(), VERSION.to_string()),
    ])
}

/// Exports the training samples (see the module docs and docs/training_data.md).
pub fn export_training(opt: &ExportOptions) -> Result<ExportSummary> {
    ensure!(!opt.scenarios.is_empty(), "no --scenario given");
    ensure!(
        opt.samples_per_scenario > 0,
        "--samples-per-scenario must be at least 1"
    );
    ensure!(
        !opt.offsets.is_empty(),
        "no offsets (the zero offset is 0,0,0)"
    );
    ensure!(opt.shard_samples > 0, "--shard-samples must be at least 1");
    ensure!(
        (8..=4096).contains(&opt.height) && (8..=4096).contains(&opt.width),
        "size {}x{}: each side must be in 8..=4096",
        opt.height,
        opt.width
    );
    let mut sources: Vec<Source> = Vec::new();
    for s in &opt.scenarios {
        sources.extend(resolve(s)?);
    }
    std::fs::create_dir_all(&opt.out).with_context(|| format!("creating {}", opt.out.display()))?;
    let (h, w) = (opt.height, opt.width);
    let mut scen_json = Vec::new();
    let mut samples_json = Vec::new();
    let mut shards_json = Vec::new();
    let mut shard = Shard::default();
    let mut skipped = 0;
    let mut cam_names: Option<Vec<String>> = None;
    let flush = |shard: &mut Shard, shards_json: &mut Vec<Value>| -> Result<()> {
        if shard.rows == 0 {
            return Ok(());
        }
        let name = format!("shard_{:05}.safetensors", shards_json.len());
        let rows = shard.rows;
        shard.write(&opt.out.join(&name), metadata())?;
        shards_json.push(json!({"file": name, "samples": rows}));
        Ok(())
    };
    // Plan everything first (cheap), so the progress bar knows the total.
    let mut scenarios = Vec::new();
    for src in &sources {
        scenarios.push((src.clone(), load(src)?));
    }
    let mut plans = Vec::new();
    for (si, (src, sc)) in scenarios.iter().enumerate() {
        let cams = sc.select_cameras(&opt.cameras)?;
        let names: Vec<String> = cams.iter().map(|c| c.name.clone()).collect();
        match &cam_names {
            Some(n) if *n != names => bail!(
                "{}: cameras {names:?} differ from the first scenario's {n:?}",
                sc.name
            ),
            _ => cam_names = Some(names),
        }
        let frames = candidate_frames(sc);
        let seed = opt.seed ^ super::palette::hash_bytes(sc.name.as_bytes());
        let p = plan_samples(
            sc,
            &frames,
            &cams,
            opt.samples_per_scenario,
            &opt.offsets,
            seed,
            opt.prev_chain,
        );
        let generated = matches!(src, Source::Builtin(_));
        if !generated && opt.offsets.iter().any(|o| *o != Pose2::default()) {
            bail!(
                "{}: ego offsets need a generated log (builtin:); this log's images are files",
                sc.name
            );
        }
        plans.push((si, cams, frames, p, generated));
    }
    let total: usize = plans.iter().map(|p| p.3.len()).sum();
    let bar = if opt.progress {
        indicatif::ProgressBar::new(total as u64)
    } else {
        indicatif::ProgressBar::hidden()
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{bar:40} {pos}/{len} samples, {elapsed} elapsed, ETA {eta} {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let nc = cam_names.as_ref().map(|n| n.len()).unwrap_or(0);
    for (si, cams, frames, plan, generated) in plans {
        let (src, sc) = &scenarios[si];
        bar.set_message(sc.name.clone());
        let base = src.image_dir();
        let job = Job {
            sc,
            store: ImageStore::new(sc, base),
            frames,
            cams,
            layer: map_layer(&sc.map),
            generated,
        };
        scen_json
            .push(json!({"name": sc.name, "source": sc.source, "steps": sc.len(), "dt": sc.dt}));
        // One thread: the map's spatial index keeps per-query scratch (not Sync); the renderer itself
        // parallelises over cameras elsewhere.
        for s in &plan {
            {
                let d = job.sample(s, h, w)?;
                bar.inc(1);
                let Some(d) = d else {
                    skipped += 1;
                    continue;
                };
                append(&mut shard, &d, s, si, nc, h, w)?;
                let refs: Vec<Value> = s
                    .refs
                    .iter()
                    .map(|pair| {
                        json!(pair
                            .iter()
                            .map(|r| json!({
                                "step": frame_step(sc, &job.frames[r.frame]),
                                "distance": r.along,
                                "side": if r.along > 0.0 { "ahead" } else { "behind" },
                            }))
                            .collect::<Vec<_>>())
                    })
                    .collect();
                samples_json.push(json!({
                    "shard": shards_json.len(),
                    "row": shard.rows - 1,
                    "scenario": sc.name,
                    "scenario_index": si,
                    "step": s.step,
                    "prev_step": d.prev_step,
                    "prev2_step": d.prev2_step,
                    "offset": [s.offset.x, s.offset.y, s.offset.heading.to_degrees()],
                    "perturbed": s.offset != Pose2::default(),
                    "refs": refs,
                }));
                if shard.rows == opt.shard_samples {
                    flush(&mut shard, &mut shards_json)?;
                }
            }
        }
    }
    flush(&mut shard, &mut shards_json)?;
    bar.finish_and_clear();
    let index = json!({
        "format": FORMAT,
        "version": VERSION,
        "height": h,
        "width": w,
        "cameras": cam_names.unwrap_or_default(),
        "mask_channels": (0..NUM_MASK_CHANNELS).map(channel_name).collect::<Vec<_>>(),
        "mask_packing": "masks_packed[s, c, y, x] bit k = mask channel k (order of mask_channels)",
        "matrices": "row-major; cam2cur(ref r of camera c) = inv(ego2global[c]) @ ref_ego2global[c, r] @ cam2ego[c]; current camera: cam2cur = cam2ego[c]",
        "prev_gap_s": PREV_GAP_S,
        "prev_chain": opt.prev_chain,
        "reference_intervals": crate::projection::retrieval::TRAINING_INTERVALS
            .iter()
            .map(|&(lo, hi, p)| json!([lo, hi, p]))
            .collect::<Vec<_>>(),
        "seed": opt.seed,
        "scenarios": scen_json,
        "shards": shards_json,
        "samples": samples_json,
        "skipped_off_map": skipped,
    });
    let path = opt.out.join("index.json");
    let tmp = opt.out.join("index.json.tmp");
    std::fs::write(&tmp, serde_json::to_string_pretty(&index)?)
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, &path).with_context(|| format!("writing {}", path.display()))?;
    Ok(ExportSummary {
        samples: samples_json.len(),
        shards: shards_json.len(),
        skipped_off_map: skipped,
        index: path,
    })
}
