//! diffusers ControlNetModel: the UNet encoder half + mid block, a conditioning embedding added after conv_in,
//! zero-initialised 1x1 convs on the 12 skips and the mid output, scaled by conditioning_scale.
use anyhow::{ensure, Result};

use super::config::ControlNetConfig;
use super::device::{DeviceWeights, Fwd};
use super::layers::Conv;
use super::unet::{Encoded, EncoderHalf};

use crate::ops::elementwise as ew;
use crate::tensor::Tensor;

pub struct ControlNet {
    pub cfg: ControlNetConfig,
    enc: EncoderHalf,
    cond: CondEmbedding,
    zero: ZeroConvs,
}

/// diffusers ControlNetConditioningEmbedding (`controlnet_cond_embedding.*`): conv3x3 + SiLU, then per
/// channel pair conv c -> c + SiLU, conv c -> c' stride 2 + SiLU, then a zero-initialised conv to C0.
pub struct CondEmbedding {
    channels: usize,
    cond_in: Conv,
    cond_blocks: Vec<Conv>,
    cond_out: Conv,
}

impl CondEmbedding {
    pub fn load(dw: &DeviceWeights, cfg: &ControlNetConfig) -> Result<Self> {
        let n = cfg.conditioning_embedding_out_channels.len();
        let mut cond_blocks = vec![];
        for k in 0..2 * (n - 1) {
            // blocks alternate conv c -> c (stride 1) and conv c -> c' (stride 2)
            cond_blocks.push(Conv::same3(
                dw,
                &format!("controlnet_cond_embedding.blocks.{k}"),
                1 + k % 2,
            )?);
        }
        let cond_in = if cfg.bgr_conditioning {
            // diffusers flips the condition's channels (`torch.flip(controlnet_cond, dims=[1])`) before the
            // embedding: reversing conv_in's input channels once at load computes the same products
            let name = "controlnet_cond_embedding.conv_in";
            let w = reverse_input_channels(dw, dw.get(&format!("{name}.weight"))?)?;
            let b = dw.get(&format!("{name}.bias")).ok().cloned();
            Conv::from_tensors(dw, name, w, b, 1, [1; 4])?
        } else {
            Conv::same3(dw, "controlnet_cond_embedding.conv_in", 1)?
        };
        Ok(Self {
            channels: cfg.conditioning_channels,
            cond_in,
            cond_blocks,
            cond_out: Conv::same3(dw, "controlnet_cond_embedding.conv_out", 1)?,
        })
    }

    /// cond: (M, Cc, 8H, 8W) -> (M, C0, H, W); with `controlnet_conditioning_channel_order: "bgr"` the
    /// channels of cond are taken in reverse order (through conv_in's weight, reversed at load).
    pub fn forward(&self, f: &mut Fwd, cond: &Tensor) -> Result<Tensor> {
        let c = cond.shape();
        ensure!(
            c.len() == 4 && c[0] >= 1 && c[1] == self.channels,
            "controlnet: controlnet_cond {c:?} must be (M, {}, H, W)",
            self.channels
        );
        // conv + SiLU pairs, the SiLU in the conv's epilogue
        let mut e = self
            .cond_in
            .forward_ex(f, cond, self.cond_in.b.as_ref(), None, true, None)?;
        for b in &self.cond_blocks {
            let y = b.forward_ex(f, &e, b.b.as_ref(), None, true, None)?;
            f.ws.release(e);
            e = y;
        }
        let emb = self.cond_out.forward(f, &e)?;
        f.ws.release(e);
        Ok(emb)
    }
}

/// The zero-initialised 1x1 convs on the skips (`controlnet_down_blocks.k`) and the mid output
/// (`controlnet_mid_block`), scaled by conditioning_scale.
pub struct ZeroConvs {
    down: Vec<Conv>,
    mid: Conv,
}

impl ZeroConvs {
    pub fn load(dw: &DeviceWeights, cfg: &ControlNetConfig) -> Result<Self> {
        let e = &cfg.enc;
        let nskips = 1 + e.down_blocks.len() * e.layers_per_block + e.down_blocks.len() - 1;
        let down = (0..nskips)
            .map(|k| Conv::one(dw, &format!("controlnet_down_blocks.{k}")))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            down,
            mid: Conv::one(dw, "controlnet_mid_block")?,
        })
    }

    /// The residuals of the skips and the mid output; `skips` and `x` are released.
    pub fn forward(
        &self,
        f: &mut Fwd,
        skips: Vec<Tensor>,
        x: Tensor,
        scale: f32,
    ) -> Result<ControlOut> {
        ensure!(
            skips.len() == self.down.len(),
            "controlnet: {} skips for {} zero convs",
            skips.len(),
            self.down.len()
        );
        // scale 1 (the default) multiplies by one: no pass
        let scaled = |f: &mut Fwd, r: Tensor| -> Result<Tensor> {
            if scale == 1.0 {
                return Ok(r);
            }
            let y = f.ws.alloc(r.shape())?;
            ew::scale_add(f.rec, scale, &r, 0.0, &r, &y)?;
            f.ws.release(r);
            Ok(y)
        };
        let mut down = vec![];
        for (z, sk) in self.down.iter().zip(&skips) {
            let r = z.forward(f, sk)?;
            down.push(scaled(f, r)?);
        }
        let m = self.mid.forward(f, &x)?;
        let mid = scaled(f, m)?;
        f.ws.release(x);
        Ok(ControlOut { down, mid })
    }
}

/// ControlNet outputs: 12 down residuals and the mid residual (already scaled).
pub struct ControlOut {
    pub down: Vec<Tensor>,
    pub mid: Tensor,
}

impl ControlNet {
    pub fn load(dw: &DeviceWeights, cfg: &ControlNetConfig) -> Result<Self> {
        Ok(Self {
            cfg: cfg.clone(),
            enc: EncoderHalf::load(dw, &cfg.enc)?,
            cond: CondEmbedding::load(dw, cfg)?,
            zero: ZeroConvs::load(dw, cfg)?,
        })
    }

    /// cond: (M, Cc, 8H, 8W) -> the conditioning embedding (M, C0, H, W). It depends on the conditioning
    /// images only, so a sampling loop computes it once and hands it to every step's [`Self::forward_embedded`].
    pub fn embed(&self, f: &mut Fwd, cond: &Tensor) -> Result<Tensor> {
        self.cond.forward(f, cond)
    }

    /// sample: (N, Cin, H, W), t: (N) f32, context: (N, L, Dc), cond: (M, Cc, 8H, 8W) -> residuals. M = N, or M
    /// divides N when the batch repeats the same M images (a guided batch [uncond; cond] shares its
    /// conditioning images): the conditioning embedding then runs once per image.
    pub fn forward(
        &self,
        f: &mut Fwd,
        sample: &Tensor,
        t: &Tensor,
        context: &Tensor,
        cond: &Tensor,
        scale: f32,
    ) -> Result<ControlOut> {
        let (s, c) = (sample.shape(), cond.shape());
        ensure!(
            c.len() == 4
                && c[0] >= 1
                && s[0] % c[0] == 0
                && c[1] == self.cfg.conditioning_channels,
            "controlnet: controlnet_cond {c:?} must be ({}, {}, H, W) or cover a divisor of that batch",
            s[0],
            self.cfg.conditioning_channels
        );
        let emb = self.embed(f, cond)?;
        let out = self.forward_embedded(f, sample, t, context, &emb, scale);
        f.ws.release(emb);
        out
    }

    /// [`Self::forward`] from a conditioning embedding computed by [`Self::embed`] ((M, C0, H, W), M dividing N).
    pub fn forward_embedded(
        &self,
        f: &mut Fwd,
        sample: &Tensor,
        t: &Tensor,
        context: &Tensor,
        emb: &Tensor,
        scale: f32,
    ) -> Result<ControlOut> {
        let (s, e) = (sample.shape(), emb.shape());
        ensure!(
            e.len() == 4 && e[0] >= 1 && s.len() == 4 && s[0] % e[0] == 0,
            "controlnet: conditioning embedding {e:?} must cover a divisor of the batch of the sample {s:?}"
        );
        ensure!(
            e[2..] == s[2..],
            "controlnet: the conditioning image embeds to {e:?}, which does not match the latent {s:?} (it must be 8x the latent size)"
        );
        let Encoded {
            x,
            skips,
            silu_temb,
        } = self.enc.forward(f, sample, t, context, Some(emb))?;
        f.ws.release(silu_temb);
        self.zero.forward(f, skips, x, scale)
    }
}

/// w: (O, C, KH, KW) -> the same weight with its input channels in reverse order (a new device tensor).
fn reverse_input_channels(dw: &DeviceWeights, w: &Tensor) -> Result<Tensor> {
    let s = w.shape();
    ensure!(
        s.len() == 4,
        "controlnet: conv_in weight {s:?} must be (O, C, KH, KW)"
    );
    let (c, kk) = (s[1], s[2] * s[3]);
    // host round trip at load: exact in f32 and f16 (f16 -> f32 -> f16 is the identity)
    let v = w.to_f32(&dw.ctx)?;
    let mut r = vec![0f32; v.len()];
    for (src, dst) in v.chunks(c * kk).zip(r.chunks_mut(c * kk)) {
        for ci in 0..c {
            dst[ci * kk..(ci + 1) * kk].copy_from_slice(&src[(c - 1 - ci) * kk..(c - ci) * kk]);
        }
    }
    Tensor::from_f32(
        &dw.ctx,
        s,
        w.dtype(),
        &r,
        "controlnet_cond_embedding.conv_in.weight.bgr",
    )
}
