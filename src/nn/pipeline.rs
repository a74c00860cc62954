//! The guided sampling pipeline: UNet (+ ControlNet) + sampler (+ VAE decode), planned once per shape.
//!
//! Planning records four kinds of command buffers once: the ControlNet's conditioning embedding (it depends on
//! the conditioning images only, so it runs once per run, not once per step), the model pass (the latent
//! duplicated into the [uncond; cond] batch, cast to the model dtype, ControlNet from that embedding, UNet, cast
//! back to f32), one small recording per sampler step (the plan's linear combinations, coefficients baked in),
//! and the VAE decode. Running writes the timestep of each step into a device tensor and replays them; nothing
//! is recorded or allocated per step.
//! Sampler buffers and the VAE are f32; the UNet/ControlNet run in the model dtype (f32 or f16).
use std::collections::BTreeMap;

use anyhow::{bail, ensure, Context as _, Result};

use super::controlnet::ControlNet;
use super::device::{Fwd, Workspace};
use super::unet::{Residuals, UNet};
use super::vae::VaeDecoder;
use crate::ops::cast;
use crate::ops::elementwise as ew;
use crate::ops::elementwise::{lincomb, LinTerm};
use crate::sampling::{Buf, Op, SamplerPlan};
use crate::tensor::{DType, Tensor};
use crate::vk::{Context, Recording};

/// Shapes and options of a planned run.
#[derive(Clone, Debug)]
pub struct PipelineShape {
    /// Images per batch (cameras), N.
    pub batch: usize,
    /// Latent height and width.
    pub latent: (usize, usize),
    /// Context tokens (77) and width.
    pub context: (usize, usize),
    /// Classifier-free guidance scale; None runs the conditional pass only.
    pub guidance: Option<f64>,
    pub conditioning_scale: f32,
}

/// What a run returns.
pub struct SampleOutput {
    /// The latent after every step, (N, C, h, w) each.
    pub latents: Vec<Vec<f32>>,
    /// The decoded image (N, 3, 8h, 8w), clamp(x / 2 + 0.5, 0, 1); empty without a VAE.
    pub image: Vec<f32>,
}

/// The model half of a sampling loop: records the noise prediction of one batch. Everything it reads beyond
/// `x` and `t` (context, conditioning, per-frame tensors) is its own, allocated before planning.
pub trait Denoiser {
    /// x: (mb, C, h, w) in the model dtype, t: (mb) f32 -> eps (mb, C, h, w) in the model dtype.
    fn record(&self, f: &mut Fwd, x: &Tensor, t: &Tensor) -> Result<Tensor>;
}

/// The sampler half, shared by every denoiser: sampler buffers, the model pass recorded once (latent
/// duplicated into the guided batch, cast, the denoiser, cast back), one recording per sampler step, and the
/// VAE decode (whose [0, 1] image stays on the device).
pub struct Sampler {
    ctx: Context,
    plan: SamplerPlan,
    /// Sampler buffers, f32 (N, C, h, w); EpsUncond/EpsCond/Eps are views (offsets) into `eps32`.
    bufs: BTreeMap<Buf, Tensor>,
    t: Tensor,
    model: Recording,
    steps: Vec<Recording>,
    /// The decode and its output clamp(x / 2 + 0.5, 0, 1): (N, 3, 8h, 8w) f32.
    decode: Option<(Recording, Tensor)>,
}

impl Sampler {
    /// Plans the loop for `batch` images of latent `(c, h, w)` (c: the VAE's latent channels, 4 for SD1.5); `guidance` doubles the model batch
    /// ([uncond; cond] halves, combined by the plan). `ws` is the model-dtype workspace the denoiser records in.
    /// `base` (f32, the latent's shape): added to the sampled latent before the decode (a model that diffuses
    /// the residual against a base latent, b2dr.json `x0_base`); `latent()` stays the sampler's own variable.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ctx: &Context,
        ws: &mut Workspace,
        denoiser: &dyn Denoiser,
        vae: Option<(&VaeDecoder, f64)>,
        base: Option<&Tensor>,
        batch: usize,
        latent: (usize, usize, usize),
        guidance: Option<f64>,
        plan: SamplerPlan,
    ) -> Result<Self> {
        let (c, h, w) = latent;
        let n = batch;
        ensure!(
            n > 0 && c > 0 && h > 0 && w > 0,
            "sampler: empty shape {n} x {c} x {h} x {w}"
        );
        let guided = guidance.is_some();
        let plan = match guidance {
            Some(s) => plan.with_guidance(s),
            None => plan,
        };
        let mb = if guided { 2 * n } else { n };
        let lat = [n, c, h, w];
        let per = n * c * h * w;
        let eps32 = Tensor::empty(ctx, &[mb, c, h, w], DType::F32, "eps32")?;
        let mut bufs = BTreeMap::new();
        for b in plan.buffers() {
            match b {
                Buf::Eps | Buf::EpsUncond | Buf::EpsCond => {}
                Buf::Noise => bail!("pipeline: samplers that draw fresh noise per step (DDIM eta > 0) are not supported"),
                other => {
                    bufs.insert(other, Tensor::zeros(ctx, &lat, DType::F32, &format!("{other:?}"))?);
                }
            }
        }
        let sample = bufs
            .get(&Buf::Sample)
            .context("plan without a Sample buffer")?
            .clone();
        let t = Tensor::zeros(ctx, &[mb], DType::F32, "timestep")?;

        // The model pass.
        let mut rec = ctx.recorder()?;
        let x32 = Tensor::empty(ctx, &[mb, c, h, w], DType::F32, "x32")?;
        for k in 0..mb / n {
            lincomb(
                &mut rec,
                &[LinTerm {
                    x: &sample,
                    offset: 0,
                    coeff: 1.0,
                }],
                &x32,
                k * per,
                per,
            )?;
        }
        let x = ws.alloc(&[mb, c, h, w])?;
        cast::cast(&mut rec, &x32, &x)?;
        let eps = denoiser.record(&mut Fwd { rec: &mut rec, ws }, &x, &t)?;
        cast::cast(&mut rec, &eps, &eps32)?;
        let model = rec.finish()?;

        // One recording per sampler step.
        let view = |b: Buf| -> Result<(Tensor, usize)> {
            Ok(match b {
                Buf::Eps => (eps32.clone(), if guided { per } else { 0 }),
                Buf::EpsUncond => (eps32.clone(), 0),
                Buf::EpsCond => (eps32.clone(), per),
                other => (bufs.get(&other).context("buffer")?.clone(), 0),
            })
        };
        let mut steps = vec![];
        for s in &plan.steps {
            let mut rec = ctx.recorder()?;
            for op in &s.ops {
                match op {
                    Op::LinComb { out, terms } => {
                        let (o, oo) = view(*out)?;
                        let views = terms
                            .iter()
                            .map(|t| view(t.buf))
                            .collect::<Result<Vec<_>>>()?;
                        let lt: Vec<LinTerm> = views
                            .iter()
                            .zip(terms)
                            .map(|((x, off), t)| LinTerm {
                                x,
                                offset: *off,
                                coeff: t.coeff as f32,
                            })
                            .collect();
                        lincomb(&mut rec, &lt, &o, oo, per)?;
                    }
                    Op::Clamp { .. } => {
                        bail!("pipeline: clip_sample (DDIM clamp) is not supported on the device")
                    }
                }
            }
            steps.push(rec.finish()?);
        }

        if let Some(b) = base {
            ensure!(
                b.shape() == lat && b.dtype() == DType::F32,
                "sampler: base latent {:?} {:?}, expected {lat:?} f32",
                b.shape(),
                b.dtype()
            );
        }
        // VAE decode (f32) of (sample [+ base]) / scaling, then clamp(x / 2 + 0.5, 0, 1) on the device.
        let decode = match vae {
            Some((dec, scaling)) => {
                let mut vws = Workspace::new(ctx, DType::F32);
                let mut rec = ctx.recorder()?;
                let z = vws.alloc(&lat)?;
                let mut terms = vec![LinTerm {
                    x: &sample,
                    offset: 0,
                    coeff: (1.0 / scaling) as f32,
                }];
                if let Some(b) = base {
                    terms.push(LinTerm {
                        x: b,
                        offset: 0,
                        coeff: (1.0 / scaling) as f32,
                    });
                }
                lincomb(&mut rec, &terms, &z, 0, per)?;
                let img = dec.forward(
                    &mut Fwd {
                        rec: &mut rec,
                        ws: &mut vws,
                    },
                    &z,
                )?;
                let unit = Tensor::empty(ctx, img.shape(), DType::F32, "decoded image")?;
                ew::to_unit(&mut rec, &img, &unit)?;
                Some((rec.finish()?, unit))
            }
            None => None,
        };
        Ok(Self {
            ctx: ctx.clone(),
            plan,
            bufs,
            t,
            model,
            steps,
            decode,
        })
    }

    /// The recordings a run replays, by stage: the model pass (once per step), the first sampler step, the
    /// decode (profiles and dispatch counts).
    pub fn recordings(&self) -> Vec<(&'static str, &Recording)> {
        let mut v = vec![("model pass (per step)", &self.model)];
        if let Some(s) = self.steps.first() {
            v.push(("sampler update (per step)", s));
        }
        if let Some((d, _)) = &self.decode {
            v.push(("vae decode", d));
        }
        v
    }

    /// The current latent (N, C, h, w), read back.
    pub fn latent(&self) -> Result<Vec<f32>> {
        self.bufs[&Buf::Sample].to_f32(&self.ctx)
    }

    /// Runs the VAE decode of the current sample (no-op without a VAE).
    pub fn decode(&self) -> Result<()> {
        if let Some((r, _)) = &self.decode {
            r.submit_wait().context("VAE decode")?;
        }
        Ok(())
    }

    /// The decoded [0, 1] image on the device (N, 3, 8h, 8w), written by [`Self::run`] (None without a VAE).
    pub fn image(&self) -> Option<&Tensor> {
        self.decode.as_ref().map(|(_, t)| t)
    }

    /// Runs the planned loop from `x_t` (N, C, h, w); the denoiser's inputs must be written (and any
    /// per-run preparation submitted) before. `keep_latents` keeps every step's latent; `decode` runs the VAE
    /// (its output stays on the device, see [`Self::image`]).
    pub fn run(
        &self,
        x_t: &[f32],
        keep_latents: bool,
        decode: bool,
        mut progress: Option<&mut dyn FnMut(usize, usize)>,
    ) -> Result<Vec<Vec<f32>>> {
        let sample = &self.bufs[&Buf::Sample];
        ensure!(
            x_t.len() == sample.numel(),
            "pipeline: x_T has {} values, expected {}",
            x_t.len(),
            sample.numel()
        );
        // Reset the sampler state: every run starts from x_T with empty rings.
        for (b, t) in &self.bufs {
            if *b == Buf::Sample {
                t.write_f32(&self.ctx, x_t)?;
            } else {
                t.write_f32(&self.ctx, &vec![0.0; t.numel()])?;
            }
        }
        let mut latents = vec![];
        for (s, rec) in self.plan.steps.iter().zip(&self.steps) {
            self.t
                .write_f32(&self.ctx, &vec![s.timestep as f32; self.t.numel()])?;
            self.model
                .submit_wait()
                .with_context(|| format!("model pass at step {}", s.index))?;
            rec.submit_wait()?;
            if let Some(p) = progress.as_mut() {
                p(s.index + 1, self.plan.steps.len());
            }
            if keep_latents {
                latents.push(sample.to_f32(&self.ctx)?);
            }
        }
        if decode {
            self.decode()?;
        }
        if !keep_latents {
            latents.push(sample.to_f32(&self.ctx)?);
        }
        Ok(latents)
    }
}

/// The plain SD denoiser: UNet (+ ControlNet from a once-per-run conditioning embedding).
struct SdDenoiser<'a> {
    unet: &'a UNet,
    control: Option<(&'a ControlNet, Tensor)>,
    context: &'a Tensor,
    conditioning_scale: f32,
}

impl Denoiser for SdDenoiser<'_> {
    fn record(&self, f: &mut Fwd, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let res = match &self.control {
            Some((c, e)) => {
                Some(c.forward_embedded(f, x, t, self.context, e, self.conditioning_scale)?)
            }
            None => None,
        };
        let r = res.as_ref().map(|o| Residuals {
            down: &o.down,
            mid: &o.mid,
        });
        self.unet.forward(f, x, t, self.context, r)
    }
}

pub struct Pipeline {
    ctx: Context,
    shape: PipelineShape,
    context: Tensor,
    cond: Option<Tensor>,
    /// The conditioning embedding pass (with a ControlNet), run once per run before the steps.
    embed: Option<Recording>,
    sampler: Sampler,
    _ws: Workspace,
    /// Device bytes in use once planned (weights excluded).
    pub planned_bytes: u64,
}

impl Pipeline {
    /// Plans a run. `vae` (with its scaling factor) is optional; `control` needs a conditioning image per run.
    pub fn new(
        ctx: &Context,
        unet: &UNet,
        control: Option<&ControlNet>,
        vae: Option<(&VaeDecoder, f64)>,
        model_dtype: DType,
        shape: PipelineShape,
        plan: SamplerPlan,
    ) -> Result<Self> {
        let (h, w) = shape.latent;
        let n = shape.batch;
        ensure!(n > 0 && h > 0 && w > 0, "pipeline: empty shape {shape:?}");
        ensure!(
            shape.guidance.is_none_or(f64::is_finite) && shape.conditioning_scale.is_finite(),
            "pipeline: guidance {:?} and conditioning scale {} must be finite",
            shape.guidance,
            shape.conditioning_scale
        );
        if let Some((v, scale)) = vae {
            v.cfg().check_factor_8("pipeline: the VAE")?;
            ensure!(
                scale.is_finite() && scale > 0.0,
                "pipeline: VAE scaling factor {scale} must be finite and > 0"
            );
        }
        let mb = if shape.guidance.is_some() { 2 * n } else { n };
        let before = ctx.allocated_bytes();
        let mut ws = Workspace::new(ctx, model_dtype);
        let context = Tensor::zeros(
            ctx,
            &[mb, shape.context.0, shape.context.1],
            model_dtype,
            "context",
        )?;
        let cond = match control {
            // one copy of the conditioning images: both guidance halves share them (ControlNet::forward
            // embeds them once and adds the embedding to each half)
            Some(c) => Some(Tensor::zeros(
                ctx,
                &[n, c.cfg.conditioning_channels, 8 * h, 8 * w],
                model_dtype,
                "cond",
            )?),
            None => None,
        };

        // The conditioning embedding, once per run. Its output stays allocated (never released to the
        // workspace), so the model pass cannot reuse its memory.
        let (embed, emb) = match (control, &cond) {
            (Some(c), Some(cimg)) => {
                let mut rec = ctx.recorder()?;
                let emb = c.embed(
                    &mut Fwd {
                        rec: &mut rec,
                        ws: &mut ws,
                    },
                    cimg,
                )?;
                (Some(rec.finish()?), Some(emb))
            }
            _ => (None, None),
        };
        let den = SdDenoiser {
            unet,
            control: control.zip(emb),
            context: &context,
            conditioning_scale: shape.conditioning_scale,
        };
        let c = unet.cfg.enc.in_channels;
        let sampler = Sampler::new(
            ctx,
            &mut ws,
            &den,
            vae,
            None,
            n,
            (c, h, w),
            shape.guidance,
            plan,
        )?;
        drop(den);
        let planned_bytes = ctx.allocated_bytes().saturating_sub(before);
        Ok(Self {
            ctx: ctx.clone(),
            shape,
            context,
            cond,
            embed,
            sampler,
            _ws: ws,
            planned_bytes,
        })
    }

    /// Runs the planned loop from the initial latent `x_t` (N, C, h, w) (C: the UNet's input channels). `context_uncond`/`context_cond`:
    /// (N, L, D) each (uncond ignored without guidance); `cond_image`: (N, C, 8h, 8w) when a ControlNet is used.
    /// `keep_latents` keeps every step's latent; `progress(done, total)` is called after each step.
    pub fn run(
        &self,
        x_t: &[f32],
        context_uncond: &[f32],
        context_cond: &[f32],
        cond_image: Option<&[f32]>,
        keep_latents: bool,
        progress: Option<&mut dyn FnMut(usize, usize)>,
    ) -> Result<SampleOutput> {
        let guided = self.shape.guidance.is_some();
        let ctx_n = self.context.numel() / if guided { 2 } else { 1 };
        ensure!(
            context_cond.len() == ctx_n,
            "pipeline: context has {} values, expected {ctx_n}",
            context_cond.len()
        );
        let mut c = vec![];
        if guided {
            ensure!(
                context_uncond.len() == ctx_n,
                "pipeline: uncond context has {} values, expected {ctx_n}",
                context_uncond.len()
            );
            c.extend_from_slice(context_uncond);
        }
        c.extend_from_slice(context_cond);
        self.context.write_f32(&self.ctx, &c)?;
        match (&self.cond, cond_image) {
            (Some(t), Some(img)) => {
                ensure!(
                    img.len() == t.numel(),
                    "pipeline: conditioning image has {} values, expected {}",
                    img.len(),
                    t.numel()
                );
                t.write_f32(&self.ctx, img)?;
            }
            (Some(_), None) => bail!("pipeline: the ControlNet needs a conditioning image"),
            (None, _) => {}
        }
        if let Some(e) = &self.embed {
            e.submit_wait().context("conditioning embedding")?;
        }
        let latents = self.sampler.run(x_t, keep_latents, true, progress)?;
        let image = match self.sampler.image() {
            Some(img) => img.to_f32(&self.ctx)?,
            None => vec![],
        };
        Ok(SampleOutput { latents, image })
    }
}
