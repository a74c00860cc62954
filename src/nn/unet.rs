//! diffusers UNet2DConditionModel (SD1.5 block structure) and the encoder half it shares with ControlNetModel.
//! Latent sizes need not be powers of two: each upsample goes to the size of the skip it is concatenated with
//! (28x50 -> 14x25 -> 7x13 -> 4x7 and back).
use anyhow::{ensure, Context as _, Result};

use super::config::{DownBlock, EncoderConfig, UNetConfig, UpBlock};
use super::device::{DeviceWeights, Fwd};
use super::layers::{norm_silu_conv, Conv, GroupNorm, Linear};
use super::resnet::Resnet;
use super::transformer::Transformer2D;
use crate::ops::{cast, elementwise as ew, embedding, resample};
use crate::tensor::{DType, Tensor};

/// diffusers CrossAttnDownBlock2D / DownBlock2D: resnets (interleaved with Transformer2DModels) and an
/// optional stride-2 downsampling conv.
pub struct DownBlock2D {
    resnets: Vec<Resnet>,
    attns: Vec<Transformer2D>,
    downsample: Option<Conv>,
}

impl DownBlock2D {
    /// `down_blocks.{i}` of an encoder config.
    pub fn load(dw: &DeviceWeights, cfg: &EncoderConfig, i: usize) -> Result<Self> {
        let (g, eps) = (cfg.norm_num_groups, cfg.norm_eps);
        let mut resnets = vec![];
        let mut attns = vec![];
        for j in 0..cfg.layers_per_block {
            resnets.push(Resnet::load(
                dw,
                &format!("down_blocks.{i}.resnets.{j}"),
                g,
                eps,
                true,
            )?);
            if cfg.down_blocks[i] == DownBlock::CrossAttn {
                attns.push(Transformer2D::load(
                    dw,
                    &format!("down_blocks.{i}.attentions.{j}"),
                    g,
                    cfg.num_heads[i],
                )?);
            }
        }
        let downsample = if i + 1 < cfg.down_blocks.len() {
            Some(Conv::same3(
                dw,
                &format!("down_blocks.{i}.downsamplers.0.conv"),
                2,
            )?)
        } else {
            None
        };
        Ok(Self {
            resnets,
            attns,
            downsample,
        })
    }

    /// x: (N, C, H, W) (owned by the caller's skip list) -> the block output; each layer output and the
    /// downsample output are pushed to `skips` (the last pushed is the returned tensor).
    pub fn forward(
        &self,
        f: &mut Fwd,
        x: &Tensor,
        silu_temb: &Tensor,
        context: &Tensor,
        skips: &mut Vec<Tensor>,
    ) -> Result<Tensor> {
        let mut x = x.clone();
        for (j, r) in self.resnets.iter().enumerate() {
            x = r.forward(f, &x, Some(silu_temb))?;
            if let Some(a) = self.attns.get(j) {
                let y = a.forward(f, &x, context)?;
                f.ws.release(x);
                x = y;
            }
            skips.push(x.clone());
        }
        if let Some(ds) = &self.downsample {
            x = ds.forward(f, &x)?;
            skips.push(x.clone());
        }
        Ok(x)
    }
}

/// diffusers UNetMidBlock2DCrossAttn: Res, Transformer, Res.
pub struct MidBlock2DCrossAttn {
    res0: Resnet,
    attn: Transformer2D,
    res1: Resnet,
}

impl MidBlock2DCrossAttn {
    pub fn load(dw: &DeviceWeights, cfg: &EncoderConfig) -> Result<Self> {
        let (g, eps) = (cfg.norm_num_groups, cfg.norm_eps);
        let last_heads = *cfg.num_heads.last().context("config without blocks")?;
        Ok(Self {
            res0: Resnet::load(dw, "mid_block.resnets.0", g, eps, true)?,
            attn: Transformer2D::load(dw, "mid_block.attentions.0", g, last_heads)?,
            res1: Resnet::load(dw, "mid_block.resnets.1", g, eps, true)?,
        })
    }

    /// x: (N, C, h, w) -> (N, C, h, w); `x` is not released.
    pub fn forward(
        &self,
        f: &mut Fwd,
        x: &Tensor,
        silu_temb: &Tensor,
        context: &Tensor,
    ) -> Result<Tensor> {
        let m = self.res0.forward(f, x, Some(silu_temb))?;
        let m2 = self.attn.forward(f, &m, context)?;
        f.ws.release(m);
        let out = self.res1.forward(f, &m2, Some(silu_temb))?;
        f.ws.release(m2);
        Ok(out)
    }
}

/// diffusers Timesteps + TimestepEmbedding (`{name}.linear_1`, SiLU, `{name}.linear_2`).
pub struct TimeEmbedding {
    linear_1: Linear,
    linear_2: Linear,
    channels: usize,
    flip_sin_to_cos: bool,
    freq_shift: f64,
}

impl TimeEmbedding {
    pub fn load(dw: &DeviceWeights, name: &str, cfg: &EncoderConfig) -> Result<Self> {
        Ok(Self {
            linear_1: Linear::load(dw, &format!("{name}.linear_1"))?,
            linear_2: Linear::load(dw, &format!("{name}.linear_2"))?,
            channels: cfg.block_out_channels[0],
            flip_sin_to_cos: cfg.flip_sin_to_cos,
            freq_shift: cfg.freq_shift,
        })
    }

    /// t: (N) f32 -> the embedding before the blocks' SiLU: (N, 4 C0) in the workspace dtype.
    pub fn forward(&self, f: &mut Fwd, t: &Tensor) -> Result<Tensor> {
        let c0 = self.channels;
        let e32 = f.ws.alloc_dtype(&[t.shape()[0], c0], DType::F32)?;
        let opts = embedding::TimestepEmbedding {
            flip_sin_to_cos: self.flip_sin_to_cos,
            downscale_freq_shift: self.freq_shift as f32,
            ..Default::default()
        };
        embedding::timestep_embedding(f.rec, t, opts, &e32)?;
        let e = f.ws.alloc(&[t.shape()[0], c0])?;
        cast::cast(f.rec, &e32, &e)?;
        f.ws.release(e32);
        let h = self.linear_1.forward(f, &e)?;
        f.ws.release(e);
        let hs = f.ws.alloc(h.shape())?;
        ew::silu(f.rec, &h, &hs)?;
        f.ws.release(h);
        let emb = self.linear_2.forward(f, &hs)?;
        f.ws.release(hs);
        Ok(emb)
    }
}

/// SiLU of an embedding into a new workspace tensor; `emb` is released.
pub fn silu_released(f: &mut Fwd, emb: Tensor) -> Result<Tensor> {
    let out = f.ws.alloc(emb.shape())?;
    ew::silu(f.rec, &emb, &out)?;
    f.ws.release(emb);
    Ok(out)
}

/// conv_in, time embedding, down blocks and mid block (UNet and ControlNet share this structure).
pub struct EncoderHalf {
    pub(crate) cfg: EncoderConfig,
    pub(crate) time: TimeEmbedding,
    pub(crate) conv_in: Conv,
    pub(crate) down: Vec<DownBlock2D>,
    pub(crate) mid: MidBlock2DCrossAttn,
}

/// Outputs of the encoder half.
pub struct Encoded {
    pub x: Tensor,
    /// 3 * blocks skip tensors (conv_in output, each layer output, each downsample output).
    pub skips: Vec<Tensor>,
    /// SiLU(time embedding): (N, 4 * C0)
    pub silu_temb: Tensor,
}

impl EncoderHalf {
    pub fn load(dw: &DeviceWeights, cfg: &EncoderConfig) -> Result<Self> {
        let down = (0..cfg.down_blocks.len())
            .map(|i| DownBlock2D::load(dw, cfg, i))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            cfg: cfg.clone(),
            time: TimeEmbedding::load(dw, "time_embedding", cfg)?,
            conv_in: Conv::same3(dw, "conv_in", 1)?,
            down,
            mid: MidBlock2DCrossAttn::load(dw, cfg)?,
        })
    }

    /// Checks the inputs of a forward pass: sample (N, Cin, H, W), t (N), context (N, L, Dc).
    pub(crate) fn check_inputs(&self, sample: &Tensor, t: &Tensor, context: &Tensor) -> Result<()> {
        let s = sample.shape();
        ensure!(
            s.len() == 4 && s[1] == self.cfg.in_channels,
            "encoder: sample {s:?} must be (N, {}, H, W)",
            self.cfg.in_channels
        );
        ensure!(
            t.shape() == [s[0]],
            "encoder: timestep {:?} must be ({})",
            t.shape(),
            s[0]
        );
        ensure!(
            context.shape().len() == 3
                && context.shape()[0] == s[0]
                && context.shape()[2] == self.cfg.cross_attention_dim,
            "encoder: context {:?} must be ({}, L, {})",
            context.shape(),
            s[0],
            self.cfg.cross_attention_dim
        );
        Ok(())
    }

    /// conv_in(sample) + `add` (ControlNet's conditioning embedding; it may cover a divisor of the batch: an
    /// (n, ..) addend for an (r n, ..) batch that repeats the same n conditions r times is added to each repeat).
    pub(crate) fn conv_in_add(
        &self,
        f: &mut Fwd,
        sample: &Tensor,
        add: Option<&Tensor>,
    ) -> Result<Tensor> {
        let mut x = self.conv_in.forward(f, sample)?;
        if let Some(a) = add {
            let (xs, as_) = (x.shape().to_vec(), a.shape().to_vec());
            ensure!(
                as_.len() == 4 && as_[1..] == xs[1..] && as_[0] >= 1 && xs[0] % as_[0] == 0,
                "encoder: conditioning embedding {as_:?} does not fit the batch {xs:?}"
            );
            let y = f.ws.alloc(x.shape())?;
            let per = a.numel();
            let r = xs[0] / as_[0];
            ew::add(
                f.rec,
                &x.reshape(&[r, per])?,
                &a.reshape(&[1, per])?,
                &y.reshape(&[r, per])?,
            )?;
            f.ws.release(x);
            x = y;
        }
        Ok(x)
    }

    /// sample: (N, Cin, H, W) in the workspace dtype, t: (N) f32, context: (N, L, Dc); `add` is added after
    /// conv_in (ControlNet's conditioning embedding).
    pub fn forward(
        &self,
        f: &mut Fwd,
        sample: &Tensor,
        t: &Tensor,
        context: &Tensor,
        add: Option<&Tensor>,
    ) -> Result<Encoded> {
        self.check_inputs(sample, t, context)?;
        let emb = self.time.forward(f, t)?;
        let temb = silu_released(f, emb)?;
        let mut x = self.conv_in_add(f, sample, add)?;
        let mut skips = vec![x.clone()];
        for d in &self.down {
            x = d.forward(f, &x, &temb, context, &mut skips)?;
        }
        let out = self.mid.forward(f, &x, &temb, context)?;
        Ok(Encoded {
            x: out,
            skips,
            silu_temb: temb,
        })
    }
}

struct Up {
    resnets: Vec<Resnet>,
    attns: Vec<Transformer2D>,
    upsample: Option<Conv>,
}

/// UNet2DConditionModel.
pub struct UNet {
    pub cfg: UNetConfig,
    enc: EncoderHalf,
    up: Vec<Up>,
    norm_out: GroupNorm,
    conv_out: Conv,
}

/// ControlNet residuals added to the UNet's skips and mid-block output.
pub struct Residuals<'a> {
    pub down: &'a [Tensor],
    pub mid: &'a Tensor,
}

impl UNet {
    pub fn load(dw: &DeviceWeights, cfg: &UNetConfig) -> Result<Self> {
        let enc = EncoderHalf::load(dw, &cfg.enc)?;
        let g = cfg.enc.norm_num_groups;
        let eps = cfg.enc.norm_eps;
        let nb = cfg.up_blocks.len();
        let heads: Vec<usize> = cfg.enc.num_heads.iter().rev().copied().collect();
        let mut up = vec![];
        for (i, kind) in cfg.up_blocks.iter().enumerate() {
            let mut resnets = vec![];
            let mut attns = vec![];
            for j in 0..=cfg.enc.layers_per_block {
                resnets.push(Resnet::load(
                    dw,
                    &format!("up_blocks.{i}.resnets.{j}"),
                    g,
                    eps,
                    true,
                )?);
                if *kind == UpBlock::CrossAttn {
                    attns.push(Transformer2D::load(
                        dw,
                        &format!("up_blocks.{i}.attentions.{j}"),
                        g,
                        heads[i],
                    )?);
                }
            }
            let upsample = if i + 1 < nb {
                Some(Conv::same3(
                    dw,
                    &format!("up_blocks.{i}.upsamplers.0.conv"),
                    1,
                )?)
            } else {
                None
            };
            up.push(Up {
                resnets,
                attns,
                upsample,
            });
        }
        Ok(Self {
            cfg: cfg.clone(),
            enc,
            up,
            norm_out: GroupNorm::load(dw, "conv_norm_out", g, eps)?,
            conv_out: Conv::same3(dw, "conv_out", 1)?,
        })
    }

    /// sample: (N, 4, H, W), t: (N) f32, context: (N, L, Dc) -> noise prediction (N, 4, H, W)
    pub fn forward(
        &self,
        f: &mut Fwd,
        sample: &Tensor,
        t: &Tensor,
        context: &Tensor,
        res: Option<Residuals>,
    ) -> Result<Tensor> {
        let Encoded {
            mut x,
            mut skips,
            silu_temb,
        } = self.enc.forward(f, sample, t, context, None)?;
        if let Some(r) = res {
            ensure!(
                r.down.len() == skips.len(),
                "unet: {} down residuals, expected {}",
                r.down.len(),
                skips.len()
            );
            for (s, d) in skips.iter_mut().zip(r.down) {
                ensure!(
                    s.shape() == d.shape(),
                    "unet: down residual {:?} does not match skip {:?}",
                    d.shape(),
                    s.shape()
                );
                let y = f.ws.alloc(s.shape())?;
                ew::add(f.rec, s, d, &y)?;
                *s = y;
            }
            ensure!(
                r.mid.shape() == x.shape(),
                "unet: mid residual {:?} does not match {:?}",
                r.mid.shape(),
                x.shape()
            );
            let y = f.ws.alloc(x.shape())?;
            ew::add(f.rec, &x, r.mid, &y)?;
            f.ws.release(x);
            x = y;
        }
        for u in &self.up {
            for (j, r) in u.resnets.iter().enumerate() {
                let skip = skips.pop().expect("skip count matches the block structure");
                let s = x.shape();
                let cat = f.ws.alloc(&[s[0], s[1] + skip.shape()[1], s[2], s[3]])?;
                ew::concat_channels(f.rec, &x, &skip, &cat)?;
                f.ws.release(x);
                f.ws.release(skip);
                x = r.forward(f, &cat, Some(&silu_temb))?;
                f.ws.release(cat);
                if let Some(a) = u.attns.get(j) {
                    let y = a.forward(f, &x, context)?;
                    f.ws.release(x);
                    x = y;
                }
            }
            if let Some(conv) = &u.upsample {
                // Upsample to the next skip's size (diffusers' forward_upsample_size for odd latents).
                let target = skips
                    .last()
                    .expect("skips remain before the last block")
                    .shape();
                let s = x.shape();
                if target[2] == 2 * s[2] && target[3] == 2 * s[3] {
                    // exactly 2x: the conv reads through the upsampling where it can
                    let y = conv.forward_upsampled2x(f, &x)?;
                    f.ws.release(x);
                    x = y;
                } else {
                    let upx = f.ws.alloc(&[s[0], s[1], target[2], target[3]])?;
                    resample::upsample_nearest(f.rec, &x, &upx, (target[2], target[3]))?;
                    f.ws.release(x);
                    x = conv.forward(f, &upx)?;
                    f.ws.release(upx);
                }
            }
        }
        let out = norm_silu_conv(
            f,
            &self.norm_out,
            &self.conv_out,
            &x,
            self.conv_out.b.as_ref(),
            None,
        )?;
        f.ws.release(x);
        f.ws.release(silu_temb);
        Ok(out)
    }
}
