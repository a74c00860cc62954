//! One Bench2Drive-R frame on the device (`docs/b2dr_controlnet.md` sections 3 and 4), planned once per
//! shape and replayed every frame:
//! - `prev`: previous frame (N, 3, H, W) -> [warp to the current pose (`prev_warp_max_depth` > 0)] ->
//!   Gaussian blur -> 2x - 1 -> VAE encode -> posterior mean x scaling -> `sqrt(abar_n) z + sqrt(1 - abar_n)
//!   eps_prev` -> model dtype, repeated for each guidance half;
//! - `cond`: the masks' conditioning embedding, the noise-level embedding, and with references their VAE
//!   latents -> reference encoder, the position-encoding MLPs and the Ref-Attn keys/values (once per frame);
//! - the sampler half ([`Sampler`]) with the B2D-R denoiser (UNet + B2D-R ControlNet; batch `[no-ref; ref]`
//!   under reference guidance), then the VAE decode to [0, 1], which stays on the device: the next frame's
//!   `prev` can be copied from it (`Prev::Carried`) without leaving the device;
//! - optionally a bicubic upsample of the decoded frame (the planner's size).
use anyhow::{bail, ensure, Context as _, Result};

use crate::nn::b2dr::{B2drControlNet, FrameTensors, PreparedFrame, RefRows};
use crate::nn::device::{Fwd, Workspace};
use crate::nn::pipeline::{Denoiser, Sampler};
use crate::nn::unet::{Residuals, UNet};
use crate::nn::vae::{VaeDecoder, VaeEncoder};
use crate::ops::elementwise::{self as ew, lincomb, LinTerm};
use crate::ops::warp::{self, NO_SOURCE};
use crate::ops::{blur, cast, resample};
use crate::sampling::{NoiseSchedule, SamplerPlan};
use crate::tensor::{DType, Tensor};
use crate::vk::{Context, Recording};

/// The noise level used when a frame has no previous frame (its latent input is zero): the end of the
/// schedule, where the noised latent carries no information.
pub const NO_PREV_NOISE_LEVEL: usize = 999;

/// The model on the device: what a frame needs.
pub struct B2drModel<'a> {
    pub unet: &'a UNet,
    pub control: &'a B2drControlNet,
    pub vae_encoder: &'a VaeEncoder,
    pub vae_decoder: &'a VaeDecoder,
    pub scaling_factor: f64,
    pub dtype: DType,
    /// The model diffuses the residual against the previous frame's clean latent (b2dr.json `x0_base` "prev"):
    /// the frame decodes sampled latent + blur -> encode of the previous frame (zero without one).
    pub x0_base_prev: bool,
}

/// The shape and options of a planned frame.
#[derive(Clone, Debug)]
pub struct FrameShape {
    /// Cameras N.
    pub cameras: usize,
    /// Render size (H, W), multiples of 8.
    pub size: (usize, usize),
    /// Whether the frame uses references (Ref-Attn); false is the masks-only model.
    pub refs: bool,
    /// Reference guidance scale w (used with references; 1 runs the reference half only).
    pub ref_guidance: f64,
    /// Optional bicubic upsample of the decoded frame (H', W').
    pub out_size: Option<(usize, usize)>,
    /// Inference-time override of the previous-frame noise level `n` (default: the model's
    /// `prev_noise_level`; evaluation of noise modulation, world.md 4).
    pub prev_noise_level: Option<usize>,
    /// Inference-time override of the previous-frame blur sigma (default: the model's `prev_blur_sigma`; 0 = no
    /// blur).
    pub prev_blur_sigma: Option<f64>,
}

/// The previous frame of a frame.
pub enum Prev<'a> {
    /// An image (N, 3, H, W) in [0, 1] (the recorded frame at the first step, or any given image).
    Image(&'a [f32]),
    /// The frame this renderer decoded last (it stayed on the device).
    Carried,
    /// No previous frame: the latent input is zero and the noise level [`NO_PREV_NOISE_LEVEL`].
    None,
}

/// The references of a frame: images (N, 2, 3, H, W) in [0, 1] (front, rear per camera) and per Ref-Attn
/// location the PETR geometry `pe_cur: (N, 3D, h_j, w_j)`, `pe_ref: (N, 2, 3D, h_j, w_j)`.
pub struct RefInputs<'a> {
    pub images: &'a [f32],
    pub pe_cur: Vec<&'a [f32]>,
    pub pe_ref: Vec<&'a [f32]>,
}

/// One frame's host inputs.
pub struct FrameInputs<'a> {
    /// (N, 15, H, W) in {0, 1}
    pub masks: &'a [f32],
    pub prev: Prev<'a>,
    /// Required iff the shape has references.
    pub refs: Option<RefInputs<'a>>,
    /// Initial latent (N, C, h, w).
    pub x_t: &'a [f32],
    /// The noise of the previous-frame latent (N, C, h, w).
    pub eps_prev: &'a [f32],
    /// The previous frame's warp to this frame's pose (N, H, W, 2) (`render::warp::ground_warp_grids`), for a
    /// model that warps it (b2dr.json `prev_warp_max_depth` > 0); None: the previous frame is used as given
    /// (it already is at this pose). An error for a model that does not warp.
    pub prev_warp: Option<&'a [f32]>,
}

/// Wall time per stage of one frame (milliseconds; each stage ends with a fence wait).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct FrameTimes {
    pub encode_ms: f64,
    pub denoise_ms: f64,
    pub decode_ms: f64,
}

struct B2drDenoiser<'a> {
    unet: &'a UNet,
    control: &'a B2drControlNet,
    context: &'a Tensor,
    zprev: &'a Tensor,
    frame: &'a PreparedFrame,
    rows: RefRows,
}

impl Denoiser for B2drDenoiser<'_> {
    fn record(&self, f: &mut Fwd, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let s = x.shape();
        // [x_t, z_prev]: (B, 2C, h, w)
        let xz = f.ws.alloc(&[s[0], 2 * s[1], s[2], s[3]])?;
        ew::concat_channels(f.rec, x, self.zprev, &xz)?;
        let res = self
            .control
            .forward(f, &xz, t, self.context, self.frame, self.rows, 1.0)?;
        f.ws.release(xz);
        self.unet.forward(
            f,
            x,
            t,
            self.context,
            Some(Residuals {
                down: &res.down,
                mid: &res.mid,
            }),
        )
    }
}

/// A planned Bench2Drive-R frame (see the module docs).
pub struct FrameRenderer {
    ctx: Context,
    shape: FrameShape,
    /// (C, h, w): the VAE's latent channels and the latent size.
    latent: (usize, usize, usize),
    noise_level: usize,
    abar: Vec<f64>,
    // host-written inputs
    masks: Tensor,
    prev_img: Tensor,
    /// (N, H, W, 2) the previous frame's warp grid (a model with `prev_warp_max_depth` > 0).
    warp_grid: Option<Tensor>,
    eps_prev: Tensor,
    noise_t: Tensor,
    ref_imgs: Option<Tensor>,
    pe_cur: Vec<Tensor>,
    pe_ref: Vec<Tensor>,
    /// The repeated, noised previous-frame latent in the model dtype (mb, C, h, w).
    zprev: Tensor,
    /// The noised latent before the cast (N, C, h, w) f32 (kept for checks).
    zprev32: Tensor,
    zbase32: Option<Tensor>,
    prev_rec: Recording,
    cond_rec: Recording,
    carry: Recording,
    sampler: Sampler,
    upsample: Option<(Recording, Tensor)>,
    _ws: Workspace,
    _vws: Workspace,
    _prepared: PreparedFrame,
    /// Device bytes in use once planned (weights excluded).
    pub planned_bytes: u64,
}

impl FrameRenderer {
    /// Plans a frame. `context`: (N, L, D) text embedding rows (one per camera); `plan`: the sampler plan.
    pub fn new(
        ctx: &Context,
        m: &B2drModel,
        shape: FrameShape,
        context: &[f32],
        plan: SamplerPlan,
    ) -> Result<Self> {
        let cfg = &m.control.cfg;
        let (ih, iw) = shape.size;
        let n = shape.cameras;
        ensure!(n >= 1, "render: no cameras");
        ensure!(
            ih >= 8 && iw >= 8 && ih % 8 == 0 && iw % 8 == 0,
            "render: size {ih}x{iw} must be multiples of 8"
        );
        ensure!(
            shape.ref_guidance.is_finite() && shape.ref_guidance > 0.0,
            "render: reference guidance {} must be a finite number > 0",
            shape.ref_guidance
        );
        let (h, w) = (ih / 8, iw / 8);
        let guided = shape.refs && shape.ref_guidance != 1.0;
        let mb = if guided { 2 * n } else { n };
        let rows = match (shape.refs, guided) {
            (false, _) => RefRows::None,
            (true, false) => RefRows::All,
            (true, true) => RefRows::SecondHalf,
        };
        let before = ctx.allocated_bytes();
        let dt = m.dtype;
        let f32t = |s: &[usize], name: &str| Tensor::zeros(ctx, s, DType::F32, name);
        let masks32 = f32t(&[n, 15, ih, iw], "masks")?;
        let prev_img = f32t(&[n, 3, ih, iw], "prev image")?;
        let warp_grid = if cfg.prev_warp_max_depth > 0.0 {
            Some(f32t(&[n, ih, iw, 2], "previous-frame warp grid")?)
        } else {
            None
        };
        let lc = m.vae_decoder.cfg().latent_channels;
        let eps_prev = f32t(&[n, lc, h, w], "eps prev")?;
        let noise_t = f32t(&[1], "noise level")?;
        let zprev32 = f32t(&[n, lc, h, w], "z prev")?;
        let zbase32 = if m.x0_base_prev {
            Some(f32t(&[n, lc, h, w], "z prev, clean (x0 base)")?)
        } else {
            None
        };
        let zprev = Tensor::zeros(ctx, &[mb, lc, h, w], dt, "z prev (model dtype)")?;
        let uc = &m.unet.cfg.enc;
        let l = context.len() / (n * uc.cross_attention_dim).max(1);
        ensure!(
            l >= 1 && context.len() == n * l * uc.cross_attention_dim,
            "render: context has {} values, not ({n}, L, {})",
            context.len(),
            uc.cross_attention_dim
        );
        let mut crep = vec![];
        for _ in 0..mb / n {
            crep.extend_from_slice(context);
        }
        let ctx_t = Tensor::from_f32(ctx, &[mb, l, uc.cross_attention_dim], dt, &crep, "context")?;
        let ones = Tensor::from_f32(
            ctx,
            &[n * 2, 3, ih, iw],
            DType::F32,
            &vec![1.0; n * 2 * 3 * ih * iw],
            "ones",
        )?;
        let mut vws = Workspace::new(ctx, DType::F32);
        let mut ws = Workspace::new(ctx, dt);
        let sched = NoiseSchedule::sd15();
        let abar: Vec<f64> = sched.alphas_cumprod().to_vec();
        let noise_level = shape.prev_noise_level.unwrap_or(cfg.prev_noise_level);
        ensure!(
            noise_level < abar.len(),
            "render: previous-frame noise level {noise_level} is not a step of the schedule (0..{})",
            abar.len()
        );
        let blur_sigma = shape.prev_blur_sigma.unwrap_or(cfg.prev_blur_sigma);
        ensure!(
            blur_sigma.is_finite() && blur_sigma >= 0.0,
            "render: previous-frame blur sigma {blur_sigma} must be a finite number >= 0"
        );

        // VAE encode of images in [0, 1] -> (M, C, h, w) f32 = posterior mean x scaling.
        let encode = |rec: &mut crate::vk::Recorder,
                      vws: &mut Workspace,
                      img: &Tensor|
         -> Result<Tensor> {
            let s = img.shape().to_vec();
            let ones = ones.reshape(&[2 * n * 3 * ih * iw])?;
            let ones = if s[0] == 2 * n {
                ones.reshape(&s)?
            } else {
                // the first n images' worth of ones
                let o = vws.alloc(&s)?;
                lincomb(
                    rec,
                    &[LinTerm {
                        x: &ones,
                        offset: 0,
                        coeff: 1.0,
                    }],
                    &o,
                    0,
                    o.numel(),
                )?;
                o
            };
            let x = vws.alloc(&s)?;
            ew::scale_add(rec, 2.0, img, -1.0, &ones, &x)?;
            let mom = m.vae_encoder.forward(&mut Fwd { rec, ws: vws }, &x)?;
            vws.release(x);
            let ms = mom.shape().to_vec();
            ensure!(
                ms[1] == 2 * lc && ms[2] == h && ms[3] == w,
                "render: the VAE encodes {ih}x{iw} to {ms:?}; the model needs (M, {}, {h}, {w}) (a VAE that \
                 downsamples by 8 with {lc} latent channels: mean and log-variance)",
                2 * lc
            );
            let z = vws.alloc(&[s[0], lc, h, w])?;
            let plane = lc * h * w;
            for k in 0..s[0] {
                lincomb(
                    rec,
                    &[LinTerm {
                        x: &mom,
                        offset: k * 2 * plane,
                        coeff: m.scaling_factor as f32,
                    }],
                    &z,
                    k * plane,
                    plane,
                )?;
            }
            vws.release(mom);
            Ok(z)
        };

        // prev chain
        let prev_rec = {
            let mut rec = ctx.recorder()?;
            let warped = match &warp_grid {
                Some(g) => {
                    let wp = vws.alloc(&[n, 3, ih, iw])?;
                    warp::warp_bilinear(&mut rec, &prev_img, g, &wp)?;
                    Some(wp)
                }
                None => None,
            };
            let src = warped.as_ref().unwrap_or(&prev_img);
            let z = if blur_sigma > 0.0 {
                let tmp = vws.alloc(&[n, 3, ih, iw])?;
                let bl = vws.alloc(&[n, 3, ih, iw])?;
                blur::gaussian_blur(&mut rec, src, blur_sigma as f32, &tmp, &bl)?;
                vws.release(tmp);
                let z = encode(&mut rec, &mut vws, &bl)?;
                vws.release(bl);
                z
            } else {
                encode(&mut rec, &mut vws, src)?
            };
            if let Some(wp) = warped {
                vws.release(wp);
            }
            if let Some(b) = &zbase32 {
                lincomb(
                    &mut rec,
                    &[LinTerm {
                        x: &z,
                        offset: 0,
                        coeff: 1.0,
                    }],
                    b,
                    0,
                    z.numel(),
                )?;
            }
            let a = abar[noise_level.min(abar.len() - 1)];
            lincomb(
                &mut rec,
                &[
                    LinTerm {
                        x: &z,
                        offset: 0,
                        coeff: (a as f32).sqrt(),
                    },
                    LinTerm {
                        x: &eps_prev,
                        offset: 0,
                        coeff: (1.0 - a as f32).sqrt(),
                    },
                ],
                &zprev32,
                0,
                z.numel(),
            )?;
            vws.release(z);
            let zc = ws.alloc(&[n, lc, h, w])?;
            cast::cast(&mut rec, &zprev32, &zc)?;
            for k in 0..mb / n {
                lincomb(
                    &mut rec,
                    &[LinTerm {
                        x: &zc,
                        offset: 0,
                        coeff: 1.0,
                    }],
                    &zprev,
                    k * zc.numel(),
                    zc.numel(),
                )?;
            }
            ws.release(zc);
            rec.finish()?
        };

        // the frame-constant conditioning
        let masks = Tensor::zeros(ctx, &[n, 15, ih, iw], dt, "masks (model dtype)")?;
        let mut ref_imgs = None;
        let mut pe_cur = vec![];
        let mut pe_ref = vec![];
        let (cond_rec, prepared) = {
            let mut rec = ctx.recorder()?;
            cast::cast(&mut rec, &masks32, &masks)?;
            let d3 = 3 * cfg.pe_depth_num;
            let lat = if shape.refs {
                let imgs = f32t(&[2 * n, 3, ih, iw], "reference images")?;
                let z = encode(&mut rec, &mut vws, &imgs)?;
                let zc = Tensor::zeros(ctx, &[2 * n, lc, h, w], dt, "reference latents")?;
                cast::cast(&mut rec, &z, &zc)?;
                vws.release(z);
                ref_imgs = Some(imgs);
                for &at in &cfg.ref_attn {
                    let (fh, fw) = cfg.location_size(at, (h, w));
                    let c32 = f32t(&[n, d3, fh, fw], "pe cur")?;
                    let r32 = f32t(&[2 * n, d3, fh, fw], "pe ref")?;
                    pe_cur.push(c32);
                    pe_ref.push(r32);
                }
                Some(zc)
            } else {
                None
            };
            let mut pcur_md = vec![];
            let mut pref_md = vec![];
            for (c32, r32) in pe_cur.iter().zip(&pe_ref) {
                let c = Tensor::zeros(ctx, c32.shape(), dt, "pe cur (model dtype)")?;
                let r = Tensor::zeros(ctx, r32.shape(), dt, "pe ref (model dtype)")?;
                cast::cast(&mut rec, c32, &c)?;
                cast::cast(&mut rec, r32, &r)?;
                pcur_md.push(c);
                pref_md.push(r);
            }
            let ft = FrameTensors {
                masks: &masks,
                noise_level: &noise_t,
                refs: lat.as_ref().map(|l| (l, &pcur_md[..], &pref_md[..])),
            };
            let prepared = m.control.prepare(
                &mut Fwd {
                    rec: &mut rec,
                    ws: &mut ws,
                },
                &ft,
            )?;
            (rec.finish()?, prepared)
        };

        let den = B2drDenoiser {
            unet: m.unet,
            control: m.control,
            context: &ctx_t,
            zprev: &zprev,
            frame: &prepared,
            rows,
        };
        let sampler = Sampler::new(
            ctx,
            &mut ws,
            &den,
            Some((m.vae_decoder, m.scaling_factor)),
            zbase32.as_ref(),
            n,
            (lc, h, w),
            guided.then_some(shape.ref_guidance),
            plan,
        )?;
        let img = sampler.image().context("decode")?.clone();
        ensure!(
            img.shape() == [n, 3, ih, iw],
            "render: the VAE decodes to {:?}, expected ({n}, 3, {ih}, {iw})",
            img.shape()
        );
        let carry = {
            let mut rec = ctx.recorder()?;
            lincomb(
                &mut rec,
                &[LinTerm {
                    x: &img,
                    offset: 0,
                    coeff: 1.0,
                }],
                &prev_img,
                0,
                img.numel(),
            )?;
            rec.finish()?
        };
        let upsample = match shape.out_size {
            None => None,
            Some((oh, ow)) => {
                ensure!(oh >= 1 && ow >= 1, "render: empty output size");
                let out = Tensor::zeros(ctx, &[n, 3, oh, ow], DType::F32, "upsampled")?;
                let mut rec = ctx.recorder()?;
                resample::resize_bicubic(&mut rec, &img, &out, (oh, ow))?;
                Some((rec.finish()?, out))
            }
        };
        let planned_bytes = ctx.allocated_bytes().saturating_sub(before);
        Ok(Self {
            ctx: ctx.clone(),
            shape,
            latent: (lc, h, w),
            noise_level,
            abar,
            masks: masks32,
            prev_img,
            warp_grid,
            eps_prev,
            noise_t,
            ref_imgs,
            pe_cur,
            pe_ref,
            zprev,
            zprev32,
            zbase32,
            prev_rec,
            cond_rec,
            carry,
            sampler,
            upsample,
            _ws: ws,
            _vws: vws,
            _prepared: prepared,
            planned_bytes,
        })
    }

    pub fn shape(&self) -> &FrameShape {
        &self.shape
    }

    /// Latent (C, h, w): channels (the VAE's latent channels), height, width.
    pub fn latent_size(&self) -> (usize, usize, usize) {
        self.latent
    }

    /// `abar` of the SD1.5 schedule at the configured previous-frame noise level.
    pub fn prev_alpha_bar(&self) -> f64 {
        self.abar[self.noise_level]
    }

    fn write(&self, t: &Tensor, v: &[f32], what: &str) -> Result<()> {
        ensure!(
            v.len() == t.numel(),
            "render: {what} has {} values, expected {} {:?}",
            v.len(),
            t.numel(),
            t.shape()
        );
        ensure!(
            v.iter().all(|x| x.is_finite()),
            "render: {what} holds NaN or infinite values"
        );
        t.write_f32(&self.ctx, v)
    }

    /// Renders one frame; the decoded [0, 1] image (N, 3, H, W) stays on the device ([`Self::image`]).
    pub fn render(&self, x: &FrameInputs) -> Result<FrameTimes> {
        let t0 = std::time::Instant::now();
        self.write(&self.masks, x.masks, "masks (N, 15, H, W)")?;
        self.write(
            &self.eps_prev,
            x.eps_prev,
            "previous-frame noise (N, C, h, w)",
        )?;
        let level = match x.prev {
            Prev::None => NO_PREV_NOISE_LEVEL,
            _ => self.noise_level,
        };
        self.noise_t.write_f32(&self.ctx, &[level as f32])?;
        match (x.prev_warp, &self.warp_grid) {
            (Some(g), Some(t)) => self.write(t, g, "previous-frame warp grid (N, H, W, 2)")?,
            // a previous frame already at this pose: every pixel keeps its own value
            (None, Some(t)) => t.write_f32(&self.ctx, &vec![NO_SOURCE; t.numel()])?,
            (Some(_), None) => bail!(
                "render: a previous-frame warp was given, but the model does not warp its previous frame \
                 (b2dr.json prev_warp_max_depth is 0)"
            ),
            (None, None) => {}
        }
        match x.prev {
            Prev::Image(img) => {
                self.write(&self.prev_img, img, "previous frame (N, 3, H, W)")?;
                self.prev_rec
                    .submit_wait()
                    .context("previous-frame chain")?;
            }
            Prev::Carried => {
                self.carry.submit_wait()?;
                self.prev_rec
                    .submit_wait()
                    .context("previous-frame chain")?;
            }
            Prev::None => {
                self.zprev
                    .write_f32(&self.ctx, &vec![0.0; self.zprev.numel()])?;
                self.zprev32
                    .write_f32(&self.ctx, &vec![0.0; self.zprev32.numel()])?;
                if let Some(b) = &self.zbase32 {
                    b.write_f32(&self.ctx, &vec![0.0; b.numel()])?;
                }
            }
        }
        match (&x.refs, &self.ref_imgs) {
            (Some(r), Some(t)) => {
                self.write(t, r.images, "reference images (N, 2, 3, H, W)")?;
                ensure!(
                    r.pe_cur.len() == self.pe_cur.len() && r.pe_ref.len() == self.pe_ref.len(),
                    "render: {} / {} position encodings for {} Ref-Attn locations",
                    r.pe_cur.len(),
                    r.pe_ref.len(),
                    self.pe_cur.len()
                );
                for (j, (c, rr)) in r.pe_cur.iter().zip(&r.pe_ref).enumerate() {
                    self.write(&self.pe_cur[j], c, &format!("pe_cur[{j}]"))?;
                    self.write(&self.pe_ref[j], rr, &format!("pe_ref[{j}]"))?;
                }
            }
            (None, None) => {}
            (Some(_), None) => {
                bail!("render: references given, but the frame was planned without them")
            }
            (None, Some(_)) => bail!("render: the frame was planned with references, none given"),
        }
        self.cond_rec.submit_wait().context("frame conditioning")?;
        let t1 = std::time::Instant::now();
        self.sampler.run(x.x_t, false, false, None)?;
        let t2 = std::time::Instant::now();
        self.sampler.decode()?;
        if let Some((r, _)) = &self.upsample {
            r.submit_wait().context("bicubic upsample")?;
        }
        let t3 = std::time::Instant::now();
        let ms = |a: std::time::Instant, b: std::time::Instant| (b - a).as_secs_f64() * 1e3;
        Ok(FrameTimes {
            encode_ms: ms(t0, t1),
            denoise_ms: ms(t1, t2),
            decode_ms: ms(t2, t3),
        })
    }

    /// The last decoded frame (N, 3, H, W) in [0, 1], read back.
    pub fn image(&self) -> Result<Vec<f32>> {
        self.sampler.image().context("decode")?.to_f32(&self.ctx)
    }

    /// The last frame upsampled to `out_size` (N, 3, H', W'), when planned with one.
    pub fn upsampled(&self) -> Result<Option<Vec<f32>>> {
        self.upsample
            .as_ref()
            .map(|(_, t)| t.to_f32(&self.ctx))
            .transpose()
    }

    /// The recordings a frame replays, by stage (profiles and dispatch counts): the previous-frame chain and
    /// the frame conditioning (references, PE MLPs: once per frame), then the sampler's.
    pub fn recordings(&self) -> Vec<(&'static str, &Recording)> {
        let mut v = vec![
            ("previous frame (per frame)", &self.prev_rec),
            ("conditioning + references (per frame)", &self.cond_rec),
        ];
        v.extend(self.sampler.recordings());
        v
    }

    /// The last frame's final latent (N, C, h, w), read back.
    pub fn latent(&self) -> Result<Vec<f32>> {
        self.sampler.latent()
    }

    /// The noised previous-frame latent of the last frame (N, C, h, w), read back (checks).
    pub fn prev_latent(&self) -> Result<Vec<f32>> {
        self.zprev32.to_f32(&self.ctx)
    }

    /// The base the last frame's latent was added to before the decode (x0 base "prev": the previous frame's
    /// clean blurred latent, (N, C, h, w)); None for a model without a base.
    pub fn base_latent(&self) -> Result<Option<Vec<f32>>> {
        self.zbase32
            .as_ref()
            .map(|b| b.to_f32(&self.ctx))
            .transpose()
    }
}
