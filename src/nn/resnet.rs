//! diffusers ResnetBlock2D: GN, SiLU, conv3x3, + Linear(SiLU(temb)), GN, SiLU, conv3x3, + skip (1x1 conv when
//! the channel count changes). output_scale_factor 1.
//!
//! Both adds are fused into convs (one pass over the activations each instead of a conv and an add): the time
//! embedding projection, whose bias has conv1's folded in at load, is conv1's per-image bias (N, O); the skip
//! is the residual of conv2, or conv2's output is the residual of the 1x1 shortcut conv. Where a conv runs
//! Winograd, its GroupNorm + SiLU is folded into its input loads too (`layers::norm_silu_conv`).
use anyhow::Result;

use super::device::{DeviceWeights, Fwd};
use super::layers::{norm_silu_conv, Conv, GroupNorm, Linear};
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
        let conv1 = Conv::same3(dw, &format!("{name}.conv1"), 1)?;
        let time_emb_proj = if temb {
            let mut p = Linear::load(dw, &format!("{name}.time_emb_proj"))?;
            // conv1's bias folded into the projection's: conv1 then takes the projection's output as its bias
            p.b = match (&p.b, &conv1.b) {
                (Some(bp), Some(bc)) => {
                    anyhow::ensure!(
                        bp.shape() == bc.shape(),
                        "{name}: time_emb_proj.bias {:?} and conv1.bias {:?} differ in shape",
                        bp.shape(),
                        bc.shape()
                    );
                    let sum = Tensor::empty(
                        &dw.ctx,
                        bp.shape(),
                        bp.dtype(),
                        &format!("{name}.temb_bias"),
                    )?;
                    let mut rec = dw.ctx.recorder()?;
                    ew::add(&mut rec, bp, bc, &sum)?;
                    rec.finish()?.submit_wait()?;
                    Some(sum)
                }
                (None, bc) => bc.clone(),
                (bp, None) => bp.clone(),
            };
            Some(p)
        } else {
            None
        };
        Ok(Self {
            norm1: GroupNorm::load(dw, &format!("{name}.norm1"), groups, eps)?,
            conv1,
            time_emb_proj,
            norm2: GroupNorm::load(dw, &format!("{name}.norm2"), groups, eps)?,
            conv2: Conv::same3(dw, &format!("{name}.conv2"), 1)?,
            shortcut,
        })
    }

    /// x: (N, C, H, W), silu_temb: (N, T) = SiLU(temb) or None -> (N, O, H, W)
    pub fn forward(&self, f: &mut Fwd, x: &Tensor, silu_temb: Option<&Tensor>) -> Result<Tensor> {
        let tp = match (&self.time_emb_proj, silu_temb) {
            (Some(p), Some(t)) => Some(p.forward(f, t)?), // (N, O), conv1's bias included
            _ => None,
        };
        let bias1 = tp.as_ref().or(self.conv1.b.as_ref());
        let h1 = norm_silu_conv(f, &self.norm1, &self.conv1, x, bias1, None)?;
        if let Some(t) = tp {
            f.ws.release(t);
        }
        let out = match &self.shortcut {
            Some(sc) => {
                let h3 = norm_silu_conv(
                    f,
                    &self.norm2,
                    &self.conv2,
                    &h1,
                    self.conv2.b.as_ref(),
                    None,
                )?;
                let y = sc.forward_ex(f, x, sc.b.as_ref(), Some(&h3), false, None)?;
                f.ws.release(h3);
                y
            }
            None => norm_silu_conv(
                f,
                &self.norm2,
                &self.conv2,
                &h1,
                self.conv2.b.as_ref(),
                Some(x),
            )?,
        };
        f.ws.release(h1);
        Ok(out)
    }
}
