//! Basic layers on the ops: Conv2d, Linear, GroupNorm, LayerNorm, loaded by diffusers name.
use anyhow::{Context as _, Result};

use super::device::{DeviceWeights, Fwd};
use crate::ops::conv2d::winograd::{self, Tile};
use crate::ops::conv2d::WeightForm;
use crate::ops::{conv2d, matmul, norm};
use crate::tensor::{DType, Tensor};

/// torch.nn.Conv2d with symmetric or explicit padding.
pub struct Conv {
    pub w: Tensor,
    /// The weight repacked once at load to (KH, KW, C, O) for the packed implicit GEMM, where
    /// `conv2d::weight_forms` lists it.
    packed: Option<Tensor>,
    /// The weight Winograd-transformed once at load for F(4x4) ((36, C, O) f32) and F(6x6) ((64, C, O)),
    /// where `conv2d::weight_forms` lists them and each copy stays under 16 MiB (larger ones are transformed
    /// per call when used).
    wino: [Option<Tensor>; 2],
    pub b: Option<Tensor>,
    pub stride: usize,
    pub pad: [usize; 4],
    name: String,
}

impl Conv {
    /// `name.weight` (O, C, KH, KW) and optional `name.bias`; padding (top, bottom, left, right).
    pub fn load(dw: &DeviceWeights, name: &str, stride: usize, pad: [usize; 4]) -> Result<Self> {
        let w = dw.get(&format!("{name}.weight"))?.clone();
        let b = dw.get(&format!("{name}.bias")).ok().cloned();
        Self::from_tensors(dw, name, w, b, stride, pad)
    }

    /// A conv on the given weight (O, C, KH, KW) and bias (O) (`name` for messages and buffer names); see
    /// [`Self::load`].
    pub fn from_tensors(
        dw: &DeviceWeights,
        name: &str,
        w: Tensor,
        b: Option<Tensor>,
        stride: usize,
        pad: [usize; 4],
    ) -> Result<Self> {
        let s = w.shape().to_vec();
        anyhow::ensure!(
            s.len() == 4,
            "conv {name}: weight {s:?} must be (O, C, KH, KW)"
        );
        // the prepared weights the conv's strategies may read (the selection says which; whether a conv
        // uses one, and which Winograd tile, depends on the input size, unknown here)
        let (mut packed, mut wino) = (None, [None, None]);
        for form in conv2d::weight_forms(dw.ctx.info(), w.dtype(), &s, stride) {
            let (shape, dtype) = form.shape(&s, w.dtype());
            match form {
                WeightForm::Packed => {
                    let p =
                        Tensor::empty(&dw.ctx, &shape, dtype, &format!("{name}.weight.packed"))?;
                    let mut rec = dw.ctx.recorder()?;
                    if conv2d::pack_weight(&mut rec, &w, &p).is_ok() {
                        rec.finish()?.submit_wait()?;
                        packed = Some(p);
                    }
                }
                // each Winograd copy only while it stays under 16 MiB (larger ones are transformed per call)
                WeightForm::Winograd(t) if shape.iter().product::<usize>() * 4 <= 16 << 20 => {
                    let u = Tensor::empty(
                        &dw.ctx,
                        &shape,
                        dtype,
                        &format!("{name}.weight.winograd{}", t.m()),
                    )?;
                    let mut rec = dw.ctx.recorder()?;
                    winograd::transform_weight(&mut rec, &w, &u)?;
                    rec.finish()?.submit_wait()?;
                    wino[(t == Tile::F6) as usize] = Some(u);
                }
                WeightForm::Winograd(_) => {}
            }
        }
        Ok(Self {
            w,
            packed,
            wino,
            b,
            stride,
            pad,
            name: name.to_string(),
        })
    }

    /// 3x3, padding 1.
    pub fn same3(dw: &DeviceWeights, name: &str, stride: usize) -> Result<Self> {
        Self::load(dw, name, stride, [1; 4])
    }

    /// 1x1, no padding.
    pub fn one(dw: &DeviceWeights, name: &str) -> Result<Self> {
        Self::load(dw, name, 1, [0; 4])
    }

    /// x: (N, C, H, W) -> (N, O, OH, OW)
    pub fn forward(&self, f: &mut Fwd, x: &Tensor) -> Result<Tensor> {
        self.forward_ex(f, x, self.b.as_ref(), None, false, None)
    }

    /// x (N, C, H, W) -> the conv of its nearest 2x upsampling (Upsample2D), reading through the upsampling
    /// where the conv runs Winograd (see `conv2d::Conv2dArgs::upsample2x`).
    pub fn forward_upsampled2x(&self, f: &mut Fwd, x: &Tensor) -> Result<Tensor> {
        self.run(f, x, self.b.as_ref(), true, None, false, None)
    }

    /// Allocates the output and runs the conv on x (read through a 2x upsampling if `up`) with this layer's
    /// weights and the given bias, residual, SiLU and prologue (see [`Self::forward_ex`]).
    #[allow(clippy::too_many_arguments)] // the conv's optional parts, named
    fn run(
        &self,
        f: &mut Fwd,
        x: &Tensor,
        bias: Option<&Tensor>,
        up: bool,
        residual: Option<&Tensor>,
        silu: bool,
        pre_gn_silu: Option<&Tensor>,
    ) -> Result<Tensor> {
        let s = x.shape();
        anyhow::ensure!(
            s.len() == 4,
            "conv {}: x {s:?} must be (N, C, H, W)",
            self.name
        );
        let k = up as usize;
        let xs = [s[0], s[1], s[2] << k, s[3] << k];
        let os = conv2d::conv2d_out_shape(&xs, self.w.shape(), self.stride, self.pad)
            .with_context(|| format!("conv {}", self.name))?;
        let out = f.ws.alloc(&os)?;
        // statistics partials for a following group norm, where this conv's path writes them
        let parts = match conv2d::stats_parts_shape(
            f.rec.context().info(),
            x.dtype(),
            &xs,
            self.w.shape(),
            self.stride,
            self.pad,
        ) {
            Some(ps) => Some(f.ws.alloc_dtype(&ps, DType::F32)?),
            None => None,
        };
        let args = conv2d::Conv2dArgs {
            packed_w: self.packed.as_ref(),
            wino_w: self.wino[0].as_ref(),
            wino_w6: self.wino[1].as_ref(),
            stats_parts: parts.as_ref(),
            upsample2x: up,
            residual,
            silu,
            pre_gn_silu,
            ..conv2d::Conv2dArgs::new(x, &self.w, bias, &out, self.stride, self.pad)
        };
        conv2d::conv2d_ex(f.rec, &args).with_context(|| format!("conv {}", self.name))?;
        if let Some(p) = parts {
            f.ws.attach_parts(&out, p);
        }
        Ok(out)
    }

    /// Whether [`Self::forward_ex`] can take a GroupNorm + SiLU prologue for input x (N, C, H, W).
    pub fn takes_gn_prologue(&self, ctx: &crate::vk::Context, x: &[usize]) -> bool {
        conv2d::pre_gn_fusable(ctx.info(), x, self.w.shape(), self.stride, self.pad)
    }

    /// [`Self::forward`] with the bias replaced by `bias` ((O) or (N, O), e.g. the layer's bias plus a time
    /// embedding, or None), `residual` ((N, O, OH, OW)) added and SiLU applied if `silu`, in the conv's
    /// epilogue where its kernel allows, and with x read through a GroupNorm + SiLU prologue when
    /// `pre_gn_silu` (statistics from [`GroupNorm::stats`]; only where `conv2d::pre_gn_fusable`). See
    /// `conv2d::Conv2dArgs`.
    pub fn forward_ex(
        &self,
        f: &mut Fwd,
        x: &Tensor,
        bias: Option<&Tensor>,
        residual: Option<&Tensor>,
        silu: bool,
        pre_gn_silu: Option<&Tensor>,
    ) -> Result<Tensor> {
        self.run(f, x, bias, false, residual, silu, pre_gn_silu)
    }
}

/// torch.nn.Linear: weight (out, in), optional bias.
pub struct Linear {
    pub w: Tensor,
    pub b: Option<Tensor>,
    name: String,
}

impl Linear {
    pub fn load(dw: &DeviceWeights, name: &str) -> Result<Self> {
        let w = dw.get(&format!("{name}.weight"))?.clone();
        let b = dw.get(&format!("{name}.bias")).ok().cloned();
        Ok(Self {
            w,
            b,
            name: name.to_string(),
        })
    }

    /// A token-wise projection stored either as a Linear (O, C) or as a 1x1 Conv2d (O, C, 1, 1) weight
    /// (diffusers' `use_linear_projection` false / true): the same map on tokens.
    pub fn load_projection(dw: &DeviceWeights, name: &str) -> Result<Self> {
        let mut l = Self::load(dw, name)?;
        let s = l.w.shape().to_vec();
        match s.len() {
            2 => {}
            4 if s[2] == 1 && s[3] == 1 => l.w = l.w.reshape(&[s[0], s[1]])?,
            _ => anyhow::bail!("{name}.weight {s:?} must be (O, C) or (O, C, 1, 1)"),
        }
        Ok(l)
    }

    /// tokens (N, H W, in) -> (N, out, H, W) (+ residual (N, out, H, W)): the projection computed straight into
    /// the channels-first layout, the residual added in the GEMM.
    pub fn forward_to_channels(
        &self,
        f: &mut Fwd,
        tokens: &Tensor,
        residual: Option<&Tensor>,
        h: usize,
        w: usize,
    ) -> Result<Tensor> {
        let n = tokens.shape()[0];
        let out = f.ws.alloc(&[n, self.w.shape()[0], h, w])?;
        matmul::linear_to_channels(f.rec, tokens, &self.w, self.b.as_ref(), residual, &out)
            .with_context(|| format!("linear {}", self.name))?;
        Ok(out)
    }

    /// x: (.., in) -> (.., out)
    pub fn forward(&self, f: &mut Fwd, x: &Tensor) -> Result<Tensor> {
        self.forward_res(f, x, None)
    }

    /// x: (.., in) -> (.., out) + residual (shaped as the output), the add fused into the GEMM.
    pub fn forward_res(
        &self,
        f: &mut Fwd,
        x: &Tensor,
        residual: Option<&Tensor>,
    ) -> Result<Tensor> {
        let mut s = x.shape().to_vec();
        *s.last_mut().expect("non-empty") = self.w.shape()[0];
        let out = f.ws.alloc(&s)?;
        matmul::linear_residual(f.rec, x, &self.w, self.b.as_ref(), residual, &out)
            .with_context(|| format!("linear {}", self.name))?;
        Ok(out)
    }
}

/// torch.nn.GroupNorm (+ optional fused SiLU).
pub struct GroupNorm {
    pub gamma: Tensor,
    pub beta: Tensor,
    pub groups: usize,
    pub eps: f32,
}

impl GroupNorm {
    pub fn load(dw: &DeviceWeights, name: &str, groups: usize, eps: f64) -> Result<Self> {
        Ok(Self {
            gamma: dw.get(&format!("{name}.weight"))?.clone(),
            beta: dw.get(&format!("{name}.bias"))?.clone(),
            groups,
            eps: eps as f32,
        })
    }

    /// x: (N, C, H, W) -> (N, C, 4) f32 statistics for a following conv's GroupNorm + SiLU prologue
    /// (`Conv::forward_ex`'s `pre_gn_silu`): the normalised tensor is never written.
    pub fn stats(&self, f: &mut Fwd, x: &Tensor) -> Result<Tensor> {
        let s = x.shape();
        let out = f.ws.alloc_dtype(&[s[0], s[1], 4], DType::F32)?;
        if let Some(parts) = f.ws.parts_of(x) {
            // from the partials x's conv wrote: x is not read again
            norm::group_norm_stats_parts(
                f.rec,
                parts,
                s,
                self.groups,
                &self.gamma,
                &self.beta,
                self.eps,
                &out,
            )?;
            return Ok(out);
        }
        norm::group_norm_stats(
            f.rec,
            x,
            self.groups,
            &self.gamma,
            &self.beta,
            self.eps,
            &out,
        )?;
        Ok(out)
    }

    /// x: (N, C, H, W) -> tokens (N, H W, C), normalised (the transformer's input layout, no transpose pass)
    pub fn forward_tokens(&self, f: &mut Fwd, x: &Tensor, silu: bool) -> Result<Tensor> {
        let s = x.shape();
        let out = f.ws.alloc(&[s[0], s[2] * s[3], s[1]])?;
        norm::group_norm_tokens(
            f.rec,
            x,
            self.groups,
            &self.gamma,
            &self.beta,
            self.eps,
            silu,
            &out,
        )?;
        Ok(out)
    }

    /// x: (N, C, H, W) -> (N, C, H, W)
    pub fn forward(&self, f: &mut Fwd, x: &Tensor, silu: bool) -> Result<Tensor> {
        let out = f.ws.alloc(x.shape())?;
        norm::group_norm(
            f.rec,
            x,
            self.groups,
            &self.gamma,
            &self.beta,
            self.eps,
            silu,
            &out,
        )?;
        Ok(out)
    }
}

/// torch.nn.LayerNorm over the last dimension.
pub struct LayerNorm {
    pub gamma: Tensor,
    pub beta: Tensor,
    pub eps: f32,
}

impl LayerNorm {
    pub fn load(dw: &DeviceWeights, name: &str, eps: f64) -> Result<Self> {
        Ok(Self {
            gamma: dw.get(&format!("{name}.weight"))?.clone(),
            beta: dw.get(&format!("{name}.bias"))?.clone(),
            eps: eps as f32,
        })
    }

    /// x: (.., D) -> (.., D)
    pub fn forward(&self, f: &mut Fwd, x: &Tensor) -> Result<Tensor> {
        let out = f.ws.alloc(x.shape())?;
        norm::layer_norm(f.rec, x, &self.gamma, &self.beta, self.eps, &out)?;
        Ok(out)
    }
}

/// conv(silu(norm(x))) (+ bias) (+ residual): where the conv takes the prologue (Winograd, few-output-channel
/// kernel; [`Conv::takes_gn_prologue`]), the norm's statistics only and the conv applies GroupNorm + SiLU as it
/// loads x (the normalised tensor is never written); else GroupNorm + SiLU into a temporary first.
pub fn norm_silu_conv(
    f: &mut Fwd,
    norm: &GroupNorm,
    conv: &Conv,
    x: &Tensor,
    bias: Option<&Tensor>,
    residual: Option<&Tensor>,
) -> Result<Tensor> {
    if conv.takes_gn_prologue(f.rec.context(), x.shape()) {
        let st = norm.stats(f, x)?;
        let y = conv.forward_ex(f, x, bias, residual, false, Some(&st))?;
        f.ws.release(st);
        return Ok(y);
    }
    let h = norm.forward(f, x, true)?;
    let y = conv.forward_ex(f, &h, bias, residual, false, None)?;
    f.ws.release(h);
    Ok(y)
}
