//! diffusers AutoencoderKL (SD): encoder (asymmetric-pad stride-2 downsamples), decoder (nearest 2x
//! upsamples), single-head mid attention, GN eps 1e-6, scaling factor.
use anyhow::{ensure, Result};

use super::config::VaeConfig;
use super::device::{DeviceWeights, Fwd};
use super::layers::{norm_silu_conv, Conv, GroupNorm};
use super::resnet::Resnet;
use super::transformer::VaeAttention;
use crate::tensor::Tensor;

struct Mid {
    r0: Resnet,
    attn: Option<VaeAttention>,
    r1: Resnet,
}

impl Mid {
    fn load(dw: &DeviceWeights, p: &str, cfg: &VaeConfig) -> Result<Self> {
        let (g, eps) = (cfg.norm_num_groups, VaeConfig::NORM_EPS);
        Ok(Self {
            r0: Resnet::load(dw, &format!("{p}.mid_block.resnets.0"), g, eps, false)?,
            attn: if cfg.mid_block_add_attention {
                Some(VaeAttention::load(
                    dw,
                    &format!("{p}.mid_block.attentions.0"),
                    g,
                )?)
            } else {
                None
            },
            r1: Resnet::load(dw, &format!("{p}.mid_block.resnets.1"), g, eps, false)?,
        })
    }

    fn forward(&self, f: &mut Fwd, x: &Tensor) -> Result<Tensor> {
        let mut h = self.r0.forward(f, x, None)?;
        if let Some(a) = &self.attn {
            let y = a.forward(f, &h)?;
            f.ws.release(h);
            h = y;
        }
        let out = self.r1.forward(f, &h, None)?;
        f.ws.release(h);
        Ok(out)
    }
}

pub struct VaeEncoder {
    cfg: VaeConfig,
    conv_in: Conv,
    blocks: Vec<(Vec<Resnet>, Option<Conv>)>,
    mid: Mid,
    norm_out: GroupNorm,
    conv_out: Conv,
    quant: Option<Conv>,
}

impl VaeEncoder {
    pub fn load(dw: &DeviceWeights, cfg: &VaeConfig) -> Result<Self> {
        let (g, eps) = (cfg.norm_num_groups, VaeConfig::NORM_EPS);
        let n = cfg.block_out_channels.len();
        let mut blocks = vec![];
        for i in 0..n {
            let rs = (0..cfg.layers_per_block)
                .map(|j| {
                    Resnet::load(
                        dw,
                        &format!("encoder.down_blocks.{i}.resnets.{j}"),
                        g,
                        eps,
                        false,
                    )
                })
                .collect::<Result<Vec<_>>>()?;
            // diffusers Downsample2D(padding=0): F.pad(x, (0, 1, 0, 1)) then conv stride 2: pad right/bottom only.
            let ds = if i + 1 < n {
                Some(Conv::load(
                    dw,
                    &format!("encoder.down_blocks.{i}.downsamplers.0.conv"),
                    2,
                    [0, 1, 0, 1],
                )?)
            } else {
                None
            };
            blocks.push((rs, ds));
        }
        Ok(Self {
            cfg: cfg.clone(),
            conv_in: Conv::same3(dw, "encoder.conv_in", 1)?,
            blocks,
            mid: Mid::load(dw, "encoder", cfg)?,
            norm_out: GroupNorm::load(dw, "encoder.conv_norm_out", g, eps)?,
            conv_out: Conv::same3(dw, "encoder.conv_out", 1)?,
            quant: if cfg.use_quant_conv {
                Some(Conv::one(dw, "quant_conv")?)
            } else {
                None
            },
        })
    }

    /// image: (N, 3, H, W) in [-1, 1] -> posterior moments (N, 2 * latent, H/8, W/8) (mean = first half).
    pub fn forward(&self, f: &mut Fwd, image: &Tensor) -> Result<Tensor> {
        let s = image.shape();
        ensure!(
            s.len() == 4 && s[1] == self.cfg.in_channels,
            "vae encoder: image {s:?} must be (N, {}, H, W)",
            self.cfg.in_channels
        );
        let mut x = self.conv_in.forward(f, image)?;
        for (rs, ds) in &self.blocks {
            for r in rs {
                let y = r.forward(f, &x, None)?;
                f.ws.release(x);
                x = y;
            }
            if let Some(d) = ds {
                let y = d.forward(f, &x)?;
                f.ws.release(x);
                x = y;
            }
        }
        let m = self.mid.forward(f, &x)?;
        f.ws.release(x);
        let o = norm_silu_conv(
            f,
            &self.norm_out,
            &self.conv_out,
            &m,
            self.conv_out.b.as_ref(),
            None,
        )?;
        f.ws.release(m);
        match &self.quant {
            Some(q) => {
                let y = q.forward(f, &o)?;
                f.ws.release(o);
                Ok(y)
            }
            None => Ok(o),
        }
    }
}

pub struct VaeDecoder {
    cfg: VaeConfig,
    post_quant: Option<Conv>,
    conv_in: Conv,
    mid: Mid,
    blocks: Vec<(Vec<Resnet>, Option<Conv>)>,
    norm_out: GroupNorm,
    conv_out: Conv,
}

impl VaeDecoder {
    pub fn cfg(&self) -> &VaeConfig {
        &self.cfg
    }

    pub fn load(dw: &DeviceWeights, cfg: &VaeConfig) -> Result<Self> {
        let (g, eps) = (cfg.norm_num_groups, VaeConfig::NORM_EPS);
        let n = cfg.block_out_channels.len();
        let mut blocks = vec![];
        for i in 0..n {
            let rs = (0..=cfg.layers_per_block)
                .map(|j| {
                    Resnet::load(
                        dw,
                        &format!("decoder.up_blocks.{i}.resnets.{j}"),
                        g,
                        eps,
                        false,
                    )
                })
                .collect::<Result<Vec<_>>>()?;
            let us = if i + 1 < n {
                Some(Conv::same3(
                    dw,
                    &format!("decoder.up_blocks.{i}.upsamplers.0.conv"),
                    1,
                )?)
            } else {
                None
            };
            blocks.push((rs, us));
        }
        Ok(Self {
            cfg: cfg.clone(),
            post_quant: if cfg.use_post_quant_conv {
                Some(Conv::one(dw, "post_quant_conv")?)
            } else {
                None
            },
            conv_in: Conv::same3(dw, "decoder.conv_in", 1)?,
            mid: Mid::load(dw, "decoder", cfg)?,
            blocks,
            norm_out: GroupNorm::load(dw, "decoder.conv_norm_out", g, eps)?,
            conv_out: Conv::same3(dw, "decoder.conv_out", 1)?,
        })
    }

    /// z: (N, latent, h, w) already divided by the scaling factor -> image (N, 3, 8h, 8w) in about [-1, 1]
    /// (diffusers' `decode(z).sample`, before the caller's clamp(x / 2 + 0.5, 0, 1)).
    pub fn forward(&self, f: &mut Fwd, z: &Tensor) -> Result<Tensor> {
        let s = z.shape();
        ensure!(
            s.len() == 4 && s[1] == self.cfg.latent_channels,
            "vae decoder: latent {s:?} must be (N, {}, h, w)",
            self.cfg.latent_channels
        );
        let pq;
        let z = match &self.post_quant {
            Some(c) => {
                pq = c.forward(f, z)?;
                &pq
            }
            None => z,
        };
        let mut x = self.conv_in.forward(f, z)?;
        let m = self.mid.forward(f, &x)?;
        f.ws.release(x);
        x = m;
        for (rs, us) in &self.blocks {
            for r in rs {
                let y = r.forward(f, &x, None)?;
                f.ws.release(x);
                x = y;
            }
            if let Some(c) = us {
                // Upsample2D: nearest 2x, then the conv (which reads through the upsampling where it can)
                let y = c.forward_upsampled2x(f, &x)?;
                f.ws.release(x);
                x = y;
            }
        }
        let o = norm_silu_conv(
            f,
            &self.norm_out,
            &self.conv_out,
            &x,
            self.conv_out.b.as_ref(),
            None,
        )?;
        f.ws.release(x);
        Ok(o)
    }
}
