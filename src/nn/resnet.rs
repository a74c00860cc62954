//! diffusers ResnetBlock2D: GN, SiLU, conv3x3, + Linear(SiLU(temb)), GN, SiLU, conv3x3, + skip (1x1 conv when
//! the channel count changes). output_scale_factor 1.
use anyhow::Result;

use super::device::{DeviceWeights, Fwd};
use super::layers::{Conv, GroupNorm, Linear};
use crate::ops::elementwise as ew;
use crate::tensor::Tensor;

pub struct Resnet {
    norm1: GroupNorm,
    conv1: Conv,
    time_emb_proj: Option<Linear>,
    norm2: GroupNorm,
    conv2: Conv,
    shortcut: Option<Conv>,
}

impl Resnet {
    /// `name` like `down_blocks.0.resnets.1`; `temb` whether the block has a time-embedding projection.
    pub fn load(
        dw: &DeviceWeights,
        name: &str,
        groups: usize,
        eps: f64,
        temb: bool,
    ) -> Result<Self> {
        let shortcut = if dw.has(&format!("{name}.conv_shortcut.weight")) {
            Some(Conv::one(dw, &format!("{name}.conv_shortcut"))?)
        } else {
            None
        };
        Ok(Self {
            norm1: GroupNorm::load(dw, &format!("{name}.norm1"), groups, eps)?,
            conv1: Conv::same3(dw, &format!("{name}.conv1"), 1)?,
            time_emb_proj: if temb {
                Some(Linear::load(dw, &format!("{name}.time_emb_proj"))?)
            } else {
                None
            },
            norm2: GroupNorm::load(dw, &format!("{name}.norm2"), groups, eps)?,
            conv2: Conv::same3(dw, &format!("{name}.conv2"), 1)?,
            shortcut,
        })
    }

    /// x: (N, C, H, W), silu_temb: (N, T) = SiLU(temb) or None -> (N, O, H, W)
    pub fn forward(&self, f: &mut Fwd, x: &Tensor, silu_temb: Option<&Tensor>) -> Result<Tensor> {
        let h = self.norm1.forward(f, x, true)?;
        let mut h1 = self.conv1.forward(f, &h)?;
        f.ws.release(h);
        if let (Some(p), Some(t)) = (&self.time_emb_proj, silu_temb) {
            let tp = p.forward(f, t)?; // (N, O)
            let s = h1.shape().to_vec();
            let t4 = tp.reshape(&[s[0], s[1], 1, 1])?;
            let sum = f.ws.alloc(&s)?;
            ew::add(f.rec, &h1, &t4, &sum)?;
            f.ws.release(tp);
            f.ws.release(std::mem::replace(&mut h1, sum));
        }
        let h2 = self.norm2.forward(f, &h1, true)?;
        f.ws.release(h1);
        let h3 = self.conv2.forward(f, &h2)?;
        f.ws.release(h2);
        let out = f.ws.alloc(h3.shape())?;
        match &self.shortcut {
            Some(sc) => {
                let s = sc.forward(f, x)?;
                ew::add(f.rec, &s, &h3, &out)?;
                f.ws.release(s);
            }
            None => ew::add(f.rec, x, &h3, &out)?,
        }
        f.ws.release(h3);
        Ok(out)
    }
}
