//! The renderer modes of `b2dr run` as observation engines ([`Sensors`]) of the closed loop:
//! - [`GroundTruth`]: the synthetic world's exact renderer at the simulated state (perfect sensors);
//! - [`LogReplay`]: the recorded image nearest in time (the paper's log-replay baseline);
//! - [`B2dr`]: the generative renderer (masks of the simulated state, references retrieved at the simulated
//!   ego pose, the previous rendered frame), or masks only (`b2dr-noref-noprev`).
//!
//! Each is built per scenario over that scenario's [`ImageStore`]; the B2D-R device model and its planned
//! frame ([`B2drEngine`]) live across scenarios.
use std::sync::Arc;

use anyhow::{bail, ensure, Context as _, Result};
use glam::{DMat4, DVec3};

use crate::eval::prev_base::{agents_for, reference_base, AgentPixels};
use crate::projection::scene::{box_class, map_layer};
use crate::projection::{Box3d, MapLayer, ProjectionConfig};
use crate::render::frame::{FrameInputs, FrameRenderer, FrameShape, Prev, RefInputs};
use crate::render::inputs;
use crate::render::job::sampler_plan;
use crate::render::package::{DeviceModel, ModelPackage};
use crate::render::warp::ground_warp_grids;
use crate::scene::camera::{Camera, CameraImage};
use crate::scene::Scenario;
use crate::sim::closed_loop::AgentRecord;
use crate::sim::sensors::{CameraFrame, SensorState, Sensors};
use crate::tensor::DType;
use crate::vk::Context;
use crate::world::images::ImageStore;
use crate::world::palette::hash_bytes;
use crate::world::{render_cameras, RenderOptions, WorldObject};

/// The simulated objects as world solids (height from the track, gravity centre at height / 2).
pub fn world_objects(sc: &Scenario, agents: &[AgentRecord]) -> Vec<WorldObject> {
    agents
        .iter()
        .filter_map(|a| {
            let t = sc.tracks.get(a.track)?;
            Some(WorldObject {
                track: a.track,
                class: a.class,
                center: DVec3::new(a.bbox.center.x, a.bbox.center.y, t.height * 0.5),
                size: DVec3::new(a.bbox.length, a.bbox.width, t.height),
                yaw: a.bbox.center.heading,
                look: hash_bytes(t.id.as_bytes()),
            })
        })
        .collect()
}

/// The simulated objects as projection boxes (the same geometry as [`world_objects`]).
pub fn boxes(sc: &Scenario, agents: &[AgentRecord]) -> Vec<Box3d> {
    world_objects(sc, agents)
        .into_iter()
        .filter_map(|o| {
            Some(Box3d {
                class: box_class(o.class)?,
                center: o.center,
                size: o.size,
                yaw: o.yaw,
            })
        })
        .collect()
}

fn frame_of(cam: &Camera, w: u32, h: u32, rgb: Vec<u8>, e2g: DMat4) -> CameraFrame {
    CameraFrame {
        camera: cam.name.clone(),
        width: w,
        height: h,
        rgb: Arc::new(rgb),
        intrinsic: cam.intrinsic_scaled(w, h),
        cam2ego: cam.cam2ego,
        ego2global: e2g,
    }
}

/// The exact renderer of the synthetic world at the simulated state.
pub struct GroundTruth<'a> {
    pub store: &'a ImageStore<'a>,
    pub cameras: Vec<Camera>,
    /// (H, W)
    pub size: (usize, usize),
    times: Vec<(&'static str, f64)>,
}

impl<'a> GroundTruth<'a> {
    pub fn new(store: &'a ImageStore<'a>, cameras: Vec<Camera>, size: (usize, usize)) -> Self {
        Self {
            store,
            cameras,
            size,
            times: vec![],
        }
    }
}

/// The ground truth of a simulated state (what `--renderer groundtruth` gives the planner).
pub fn ground_truth(
    store: &ImageStore,
    cameras: &[Camera],
    size: (usize, usize),
    sc: &Scenario,
    ego2global: &DMat4,
    agents: &[AgentRecord],
) -> Result<Vec<CameraFrame>> {
    ensure!(
        !sc.source.is_empty() && store.world().scenario.name == sc.name,
        "ground truth: the image store is of another scenario"
    );
    let objs = world_objects(sc, agents);
    let (h, w) = size;
    let frames = render_cameras(
        &store.world().scenery,
        cameras,
        ego2global,
        w,
        h,
        &objs,
        &RenderOptions::default(),
        1,
    )?;
    Ok(frames
        .into_iter()
        .zip(cameras)
        .map(|(f, c)| frame_of(c, w as u32, h as u32, f.rgb, *ego2global))
        .collect())
}

impl Sensors for GroundTruth<'_> {
    fn name(&self) -> String {
        "groundtruth".into()
    }
    fn reset(&mut self, sc: &Scenario) -> Result<()> {
        ensure!(
            sc.source.starts_with("builtin:"),
            "--renderer groundtruth needs a synthetic scenario (builtin:...); {} is {}",
            sc.name,
            sc.source
        );
        Ok(())
    }
    fn observe(&mut self, s: &SensorState) -> Result<Vec<CameraFrame>> {
        let t0 = std::time::Instant::now();
        let f = ground_truth(
            self.store,
            &self.cameras,
            self.size,
            s.scenario,
            &s.ego2global(),
            s.agents,
        )?;
        self.times = vec![("render", t0.elapsed().as_secs_f64() * 1e3)];
        Ok(f)
    }
    fn last_times(&self) -> Vec<(&'static str, f64)> {
        self.times.clone()
    }
}

/// The recorded image of `camera` nearest in time to `time_s` (ties: the earlier), with its recorded pose.
pub fn nearest_recorded<'s>(
    sc: &'s Scenario,
    camera: &str,
    time_s: f64,
) -> Option<&'s CameraImage> {
    let t = (time_s * 1e6).round() as i64;
    sc.rig
        .frames
        .iter()
        .filter_map(|f| f.images.iter().find(|i| i.camera == camera))
        .min_by_key(|i| (i.timestamp_us - t).unsigned_abs())
}

pub fn recorded_pixels(
    store: &ImageStore,
    img: &CameraImage,
    size: (usize, usize),
) -> Result<Vec<u8>> {
    let px = store.image(img, size.1, size.0)?;
    Ok(px.data.clone())
}

/// Log replay: the recorded image nearest in time, whatever the simulated state.
pub struct LogReplay<'a> {
    pub store: &'a ImageStore<'a>,
    pub cameras: Vec<Camera>,
    pub size: (usize, usize),
}

impl Sensors for LogReplay<'_> {
    fn name(&self) -> String {
        "log-replay".into()
    }
    fn reset(&mut self, sc: &Scenario) -> Result<()> {
        ensure!(
            !sc.rig.frames.is_empty(),
            "--renderer log-replay: {} has no recorded camera frames",
            sc.name
        );
        Ok(())
    }
    fn observe(&mut self, s: &SensorState) -> Result<Vec<CameraFrame>> {
        let (h, w) = self.size;
        self.cameras
            .iter()
            .map(|c| {
                let img = nearest_recorded(s.scenario, &c.name, s.time_s)
                    .with_context(|| format!("no recorded image of {}", c.name))?;
                Ok(frame_of(
                    c,
                    w as u32,
                    h as u32,
                    recorded_pixels(self.store, img, self.size)?,
                    img.ego2global,
                ))
            })
            .collect()
    }
}

/// The references of each camera retrieved from the log at `e2g` (front and rear; one image twice when the
/// log has images on one side only).
pub struct Retrieved {
    /// `(N, 2, 3, H, W)` in [0, 1].
    pub images: Vec<f32>,
    /// Their PETR geometry.
    pub geom: inputs::Geometry,
    /// Per camera the ego2global of each reference image.
    pub poses: Vec<[DMat4; 2]>,
    /// Per camera the log frame (index into the rig's frames) of each reference image.
    pub frames: Vec<[usize; 2]>,
}

/// [`Retrieved`] of `cameras` at `e2g`, at the render size `size`.
pub fn references(
    store: &ImageStore,
    cfg: &crate::nn::b2dr_config::B2drConfig,
    cameras: &[Camera],
    size: (usize, usize),
    e2g: &DMat4,
) -> Result<Retrieved> {
    let sc = store.world().scenario;
    let (mut ref_imgs, mut geoms, mut poses, mut frames) = (vec![], vec![], vec![], vec![]);
    for c in cameras {
        let r = store.frame_index().retrieve(&sc.rig.frames, &c.name, e2g);
        let pick = |x: &Option<crate::projection::retrieval::Reference>| {
            x.as_ref()
                .map(|r| (&sc.rig.frames[r.frame].images[r.image], r.frame))
        };
        let ((a, fa), (b, fb)) = match (pick(&r.front), pick(&r.rear)) {
            (Some(a), Some(b)) => (a, b),
            (Some(a), None) | (None, Some(a)) => (a, a),
            (None, None) => bail!("no recorded image of {} to retrieve", c.name),
        };
        frames.push([fa, fb]);
        for img in [a, b] {
            ref_imgs.extend(planar(&recorded_pixels(store, img, size)?, size));
        }
        geoms.push(inputs::geometry(
            cfg,
            c,
            size,
            e2g,
            [&a.ego2global, &b.ego2global],
        )?);
        poses.push([a.ego2global, b.ego2global]);
    }
    Ok(Retrieved {
        images: ref_imgs,
        geom: inputs::stack(&geoms),
        poses,
        frames,
    })
}

/// The renderer's output `(N, 3, H, W)` as the next frame reads it back: clamped to [0, 1] and rounded to 8 bits
/// (what a planner is shown).
pub fn as_8bit(img: &[f32]) -> Vec<f32> {
    img.iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() / 255.0)
        .collect()
}

/// The B2D-R model on the device with its planned frame, kept across scenarios.
pub struct B2drEngine {
    pub package: ModelPackage,
    model: DeviceModel,
    renderer: Option<FrameRenderer>,
    pub cameras: Vec<String>,
    pub refs_and_prev: bool,
    pub seed: u64,
    pub steps: usize,
    pub ref_guidance: f64,
    ctx: Context,
}

impl B2drEngine {
    /// `cameras`: the cameras rendered (each must be one of the model's); `refs_and_prev` false is the
    /// `b2dr-noref-noprev` baseline (masks only).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ctx: &Context,
        package: ModelPackage,
        dtype: DType,
        cameras: Vec<String>,
        refs_and_prev: bool,
        steps: Option<usize>,
        ref_guidance: Option<f64>,
        seed: u64,
    ) -> Result<Self> {
        for c in &cameras {
            ensure!(
                package.meta.cameras.contains(c),
                "camera {c:?} is not one the model renders ({:?})",
                package.meta.cameras
            );
        }
        let model = DeviceModel::upload(ctx, &package, dtype)?;
        Ok(Self {
            steps: steps.unwrap_or(package.meta.steps),
            ref_guidance: ref_guidance.unwrap_or(package.meta.ref_guidance),
            package,
            model,
            renderer: None,
            cameras,
            refs_and_prev,
            seed,
            ctx: ctx.clone(),
        })
    }

    pub fn size(&self) -> (usize, usize) {
        let [h, w] = self.package.meta.render_size;
        (h, w)
    }

    fn renderer(&mut self) -> Result<&FrameRenderer> {
        if self.renderer.is_none() {
            let r = self.standalone()?;
            self.renderer = Some(r);
        }
        self.renderer.as_ref().context("renderer")
    }

    /// A fresh, separately planned renderer of the same shape (a standalone `render` of the same inputs).
    pub fn standalone(&self) -> Result<FrameRenderer> {
        self.plan(self.refs_and_prev, self.ref_guidance, None, None)
    }

    /// A renderer of this engine's cameras with other options (evaluation ablations): references on or off,
    /// reference guidance, and the previous-frame noise level / blur sigma (None: the model's).
    pub fn plan(
        &self,
        refs: bool,
        ref_guidance: f64,
        prev_noise_level: Option<usize>,
        prev_blur_sigma: Option<f64>,
    ) -> Result<FrameRenderer> {
        FrameRenderer::new(
            &self.ctx,
            &self.model.as_model(),
            FrameShape {
                cameras: self.cameras.len(),
                size: self.size(),
                refs,
                ref_guidance,
                out_size: None,
                prev_noise_level,
                prev_blur_sigma,
            },
            &self.package.context_for(&self.cameras)?,
            sampler_plan(
                &self.package.meta.sampler,
                self.steps,
                self.package.meta.prediction(),
            )?,
        )
    }

    /// Device bytes in use (weights + the planned frame).
    pub fn device_bytes(&self) -> u64 {
        self.ctx.allocated_bytes()
    }
}

/// The host inputs of one rendered frame, as the renderer got them (`prev` is None when the frame started
/// from the carried previous frame, or had none).
#[derive(Clone, Debug, PartialEq)]
pub struct FrameRecord {
    pub masks: Vec<f32>,
    pub prev: Option<Vec<f32>>,
    pub ref_images: Vec<f32>,
    pub pe_cur: Vec<Vec<f32>>,
    pub pe_ref: Vec<Vec<f32>>,
    pub x_t: Vec<f32>,
    pub eps_prev: Vec<f32>,
    /// The previous frame's warp grid (N, H, W, 2) (a model that warps it).
    pub prev_warp: Option<Vec<f32>>,
    /// A `prev_source` "reference" / "composite" model: per camera whether `prev` is (built on) its reference
    /// (else the fallback).
    pub took_reference: Vec<bool>,
    /// The decoded frame (N, 3, H, W) in [0, 1].
    pub image: Vec<f32>,
}

/// The generative renderer on one scenario.
pub struct B2dr<'a> {
    pub engine: &'a mut B2drEngine,
    pub store: &'a ImageStore<'a>,
    cameras: Vec<Camera>,
    map: MapLayer,
    frame: u64,
    /// Per camera the ego2global of the previous frame (what a warping model warps from).
    prev_poses: Vec<DMat4>,
    /// The last frame's output (`as_8bit`), the fallback of a reference-source model's cameras.
    last_output: Vec<f32>,
    /// Per camera whether the last frame started from a reference (a `prev_source` "reference" model).
    pub took_reference: Vec<bool>,
    times: Vec<(&'static str, f64)>,
    /// When set, every frame's inputs and output are kept (tests).
    pub record: Option<Vec<FrameRecord>>,
}

impl<'a> B2dr<'a> {
    pub fn new(engine: &'a mut B2drEngine, store: &'a ImageStore<'a>) -> Result<Self> {
        let sc = store.world().scenario;
        let cameras = sc.select_cameras(&engine.cameras)?;
        Ok(Self {
            engine,
            store,
            cameras,
            map: map_layer(&sc.map),
            frame: 0,
            prev_poses: vec![],
            last_output: vec![],
            took_reference: vec![],
            times: vec![],
            record: None,
        })
    }
}

impl Sensors for B2dr<'_> {
    fn name(&self) -> String {
        if self.engine.refs_and_prev {
            "b2dr".into()
        } else {
            "b2dr-noref-noprev".into()
        }
    }
    fn reset(&mut self, sc: &Scenario) -> Result<()> {
        ensure!(
            !self.engine.refs_and_prev || !sc.rig.frames.is_empty(),
            "--renderer b2dr: {} has no recorded camera frames to retrieve references from",
            sc.name
        );
        self.frame = 0;
        self.prev_poses.clear();
        Ok(())
    }
    fn observe(&mut self, s: &SensorState) -> Result<Vec<CameraFrame>> {
        let sc = s.scenario;
        let size = self.engine.size();
        let e2g = s.ego2global();
        let t0 = std::time::Instant::now();
        let bx = boxes(sc, s.agents);
        let poses = vec![e2g; self.cameras.len()];
        let masks = inputs::masks(
            &self.cameras,
            &poses,
            &bx,
            &self.map,
            size,
            &ProjectionConfig::default(),
        )?;
        let t1 = std::time::Instant::now();
        let refs_on = self.engine.refs_and_prev;
        let source = self.engine.package.control_cfg.prev_source;
        let from_refs = source.from_references();
        let (mut ref_imgs, mut geom, mut prev) = (vec![], inputs::stack(&[]), vec![]);
        let mut ref_warp: Option<Vec<f32>> = None;
        if refs_on {
            let r = references(
                self.store,
                &self.engine.package.control_cfg,
                &self.cameras,
                size,
                &e2g,
            )?;
            if self.frame == 0 {
                self.prev_poses.clear();
                for c in &self.cameras {
                    let img = nearest_recorded(sc, &c.name, s.time_s)
                        .with_context(|| format!("no recorded image of {}", c.name))?;
                    prev.extend(planar(&recorded_pixels(self.store, img, size)?, size));
                    self.prev_poses.push(img.ego2global);
                }
            } else if from_refs {
                prev = std::mem::take(&mut self.last_output);
            }
            if from_refs {
                // each camera starts from a logged image where its reference covers the frame, else from the
                // frame before (the first frame: the recorded one); the input is given as an image every frame
                let refs_agents = agents_for(source, sc, &self.cameras, &r, size)?;
                let agents = refs_agents.as_ref().map(|a| AgentPixels {
                    masks: &masks,
                    refs: a,
                });
                let (img, grid, took) = reference_base(
                    &self.cameras,
                    &e2g,
                    &r,
                    size,
                    self.engine.package.control_cfg.prev_warp_max_depth,
                    &prev,
                    &self.prev_poses,
                    agents.as_ref(),
                )?;
                (prev, ref_warp, self.took_reference) = (img, Some(grid), took);
            }
            (ref_imgs, geom) = (r.images, r.geom);
        }
        let max_depth = self.engine.package.control_cfg.prev_warp_max_depth;
        let warp = if ref_warp.is_some() {
            ref_warp
        } else if refs_on && max_depth > 0.0 {
            Some(ground_warp_grids(
                &self.cameras,
                &poses,
                &self.prev_poses,
                size,
                max_depth,
            )?)
        } else {
            None
        };
        let t2 = std::time::Instant::now();
        let n = self.cameras.len();
        let seed = self.engine.seed;
        let frame = self.frame;
        let r = self.engine.renderer()?;
        let (x_t, eps) = inputs::frame_noise(seed, frame, n, r.latent_size());
        let fresh_prev = frame == 0 || from_refs;
        let prev_in = if !refs_on {
            Prev::None
        } else if fresh_prev {
            Prev::Image(&prev)
        } else {
            Prev::Carried
        };
        let ft = r.render(&FrameInputs {
            masks: &masks,
            prev: prev_in,
            refs: refs_on.then(|| RefInputs {
                images: &ref_imgs,
                pe_cur: geom.pe_cur.iter().map(|v| &v[..]).collect(),
                pe_ref: geom.pe_ref.iter().map(|v| &v[..]).collect(),
            }),
            x_t: &x_t,
            eps_prev: &eps,
            prev_warp: warp.as_deref(),
        })?;
        let img = r.image()?;
        ensure!(
            img.iter().all(|v| v.is_finite()),
            "the renderer produced NaN or infinite pixels"
        );
        if from_refs {
            self.last_output = as_8bit(&img);
        }
        if let Some(rec) = self.record.as_mut() {
            rec.push(FrameRecord {
                masks: masks.clone(),
                prev: (refs_on && fresh_prev).then(|| prev.clone()),
                ref_images: ref_imgs.clone(),
                pe_cur: geom.pe_cur.clone(),
                pe_ref: geom.pe_ref.clone(),
                x_t: x_t.clone(),
                eps_prev: eps.clone(),
                prev_warp: warp.clone(),
                took_reference: self.took_reference.clone(),
                image: img.clone(),
            });
        }
        self.frame += 1;
        self.prev_poses = poses;
        let (h, w) = size;
        let per = 3 * h * w;
        let out = self
            .cameras
            .iter()
            .enumerate()
            .map(|(k, c)| {
                let rgb = inputs::to_rgb(&img[k * per..(k + 1) * per], size).into_raw();
                frame_of(c, w as u32, h as u32, rgb, e2g)
            })
            .collect();
        let ms = |a: std::time::Instant, b: std::time::Instant| (b - a).as_secs_f64() * 1e3;
        self.times = vec![
            ("projection", ms(t0, t1)),
            ("retrieval", ms(t1, t2)),
            ("encode", ft.encode_ms),
            ("denoise", ft.denoise_ms),
            ("decode", ft.decode_ms),
        ];
        Ok(out)
    }
    fn last_times(&self) -> Vec<(&'static str, f64)> {
        self.times.clone()
    }
}

/// Interleaved RGB8 (H, W, 3) -> planar (3, H, W) f32 in [0, 1].
pub fn planar(rgb: &[u8], size: (usize, usize)) -> Vec<f32> {
    let (h, w) = size;
    let n = h * w;
    let mut v = vec![0.0; 3 * n];
    for p in 0..n.min(rgb.len() / 3) {
        for c in 0..3 {
            v[c * n + p] = rgb[3 * p + c] as f32 / 255.0;
        }
    }
    v
}
