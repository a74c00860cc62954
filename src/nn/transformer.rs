//! diffusers Transformer2DModel (SD1.5: GN eps 1e-6, conv 1x1 proj_in/proj_out, one BasicTransformerBlock with
//! self-attention, cross-attention and a GEGLU feed-forward) and the VAE's single-head mid-block attention.
//!
//! Layout: the group norm writes tokens (N, H W, C) directly, proj_in runs as a linear on them, and proj_out
//! (the VAE attention's output projection) computes straight back into (N, C, H, W) with the block's
//! residual added in the same GEMM: no transpose passes. Every residual add of the blocks is fused into the
//! GEMM producing its branch.
use anyhow::Result;

use super::device::{DeviceWeights, Fwd};
use super::layers::{GroupNorm, LayerNorm, Linear};
use crate::ops::{attention, attention_naive, elementwise as ew, matmul};
use crate::tensor::Tensor;

/// diffusers Attention (q/k/v projections, multi-head attention, output projection).
struct Attn {
    q: Linear,
    k: Linear,
    v: Linear,
    out: Linear,
    heads: usize,
}

impl Attn {
    fn load(dw: &DeviceWeights, name: &str, heads: usize) -> Result<Self> {
        Ok(Self {
            q: Linear::load(dw, &format!("{name}.to_q"))?,
            k: Linear::load(dw, &format!("{name}.to_k"))?,
            v: Linear::load(dw, &format!("{name}.to_v"))?,
            out: Linear::load(dw, &format!("{name}.to_out.0"))?,
            heads,
        })
    }

    /// x: (B, L, D), ctx: (B, Lk, Dc) or None (self-attention) -> (B, L, D) (+ residual, added in the output
    /// projection's GEMM)
    fn forward(
        &self,
        f: &mut Fwd,
        x: &Tensor,
        ctx: Option<&Tensor>,
        residual: Option<&Tensor>,
    ) -> Result<Tensor> {
        let o = self.attend(f, x, ctx)?;
        let r = self.out.forward_res(f, &o, residual)?;
        f.ws.release(o);
        Ok(r)
    }

    /// The attention of [`Self::forward`] without the output projection: (B, L, D) before `to_out`.
    fn attend(&self, f: &mut Fwd, x: &Tensor, ctx: Option<&Tensor>) -> Result<Tensor> {
        let c = ctx.unwrap_or(x);
        let q = self.q.forward(f, x)?;
        let k = self.k.forward(f, c)?;
        let v = self.v.forward(f, c)?;
        let o = f.ws.alloc(q.shape())?;
        let head_dim = q.shape()[2] / self.heads;
        if head_dim % 4 == 0 {
            attention::attention(f.rec, &q, &k, &v, &o, self.heads, None)?;
        } else {
            // The fast kernel takes head dims in multiples of 4; tiny test configs use 1 or 2.
            attention_naive::attention_naive(f.rec, &q, &k, &v, &o, self.heads, None)?;
        }
        for t in [q, k, v] {
            f.ws.release(t);
        }
        Ok(o)
    }
}

/// diffusers GEGLU (`ff.net.0`): Linear to 2 D, then value * gelu(gate). Where the device takes it
/// (`matmul::geglu_fusable`) the weight rows are permuted once at load and one GEMM writes the activation
/// (`matmul::linear_geglu`); elsewhere a linear and `elementwise::geglu`.
struct Geglu {
    proj: Linear,
    fused: bool,
}

impl Geglu {
    fn load(dw: &DeviceWeights, name: &str) -> Result<Self> {
        let mut proj = Linear::load(dw, name)?;
        let ws = proj.w.shape().to_vec();
        anyhow::ensure!(ws.len() == 2, "{name}.weight {ws:?} must be (2 D, in)");
        let sg = dw.ctx.info().subgroup_size as usize;
        let fused = matmul::geglu_fusable(&dw.ctx, ws[1], ws[0]);
        if fused {
            let perm = matmul::geglu_permutation(ws[0], sg).expect("fusable");
            let permute = |t: &Tensor, row: usize| -> Result<Tensor> {
                let v = t.to_f32(&dw.ctx)?;
                let p: Vec<f32> = perm
                    .iter()
                    .flat_map(|&o| v[o * row..(o + 1) * row].iter().copied())
                    .collect();
                Tensor::from_f32(
                    &dw.ctx,
                    t.shape(),
                    t.dtype(),
                    &p,
                    &format!("{name} (GEGLU order)"),
                )
            };
            proj.w = permute(&proj.w, ws[1])?;
            proj.b = proj.b.as_ref().map(|b| permute(b, 1)).transpose()?;
        }
        Ok(Self { proj, fused })
    }

    /// x: (.., in) -> (.., D)
    fn forward(&self, f: &mut Fwd, x: &Tensor) -> Result<Tensor> {
        let mut s = x.shape().to_vec();
        *s.last_mut().expect("dims") = self.proj.w.shape()[0] / 2;
        if self.fused {
            let out = f.ws.alloc(&s)?;
            matmul::linear_geglu(f.rec, x, &self.proj.w, self.proj.b.as_ref(), &out)?;
            return Ok(out);
        }
        let g = self.proj.forward(f, x)?;
        let out = f.ws.alloc(&s)?;
        ew::geglu(f.rec, &g, &out)?;
        f.ws.release(g);
        Ok(out)
    }
}

struct Block {
    norm1: LayerNorm,
    attn1: Attn,
    norm2: LayerNorm,
    attn2: Attn,
    norm3: LayerNorm,
    ff_in: Geglu,
    ff_out: Linear,
}

pub struct Transformer2D {
    norm: GroupNorm,
    proj_in: Linear,
    blocks: Vec<Block>,
    proj_out: Linear,
}

impl Transformer2D {
    pub fn load(dw: &DeviceWeights, name: &str, groups: usize, heads: usize) -> Result<Self> {
        let mut blocks = vec![];
        let mut i = 0;
        while dw.has(&format!("{name}.transformer_blocks.{i}.norm1.weight")) {
            let b = format!("{name}.transformer_blocks.{i}");
            blocks.push(Block {
                norm1: LayerNorm::load(dw, &format!("{b}.norm1"), 1e-5)?,
                attn1: Attn::load(dw, &format!("{b}.attn1"), heads)?,
                norm2: LayerNorm::load(dw, &format!("{b}.norm2"), 1e-5)?,
                attn2: Attn::load(dw, &format!("{b}.attn2"), heads)?,
                norm3: LayerNorm::load(dw, &format!("{b}.norm3"), 1e-5)?,
                ff_in: Geglu::load(dw, &format!("{b}.ff.net.0.proj"))?,
                ff_out: Linear::load(dw, &format!("{b}.ff.net.2"))?,
            });
            i += 1;
        }
        anyhow::ensure!(!blocks.is_empty(), "{name}: no transformer_blocks found");
        Ok(Self {
            norm: GroupNorm::load(dw, &format!("{name}.norm"), groups, 1e-6)?,
            proj_in: Linear::load_projection(dw, &format!("{name}.proj_in"))?,
            blocks,
            proj_out: Linear::load_projection(dw, &format!("{name}.proj_out"))?,
        })
    }

    /// x: (N, C, H, W), context: (N, 77, Dc) -> (N, C, H, W)
    pub fn forward(&self, f: &mut Fwd, x: &Tensor, context: &Tensor) -> Result<Tensor> {
        let (h, w) = (x.shape()[2], x.shape()[3]);
        let n = self.norm.forward_tokens(f, x, false)?;
        let mut t = self.proj_in.forward(f, &n)?;
        f.ws.release(n);
        for b in &self.blocks {
            // each residual add is fused into the GEMM that produces the branch
            let n1 = b.norm1.forward(f, &t)?;
            let a1 = b.attn1.forward(f, &n1, None, Some(&t))?;
            f.ws.release(n1);
            f.ws.release(std::mem::replace(&mut t, a1));
            let n2 = b.norm2.forward(f, &t)?;
            let a2 = b.attn2.forward(f, &n2, Some(context), Some(&t))?;
            f.ws.release(n2);
            f.ws.release(std::mem::replace(&mut t, a2));
            let n3 = b.norm3.forward(f, &t)?;
            let gg = b.ff_in.forward(f, &n3)?;
            f.ws.release(n3);
            let ff = b.ff_out.forward_res(f, &gg, Some(&t))?;
            f.ws.release(gg);
            f.ws.release(std::mem::replace(&mut t, ff));
        }
        let out = self.proj_out.forward_to_channels(f, &t, Some(x), h, w)?;
        f.ws.release(t);
        Ok(out)
    }
}

/// The VAE mid-block attention: GN (eps 1e-6), single head over the spatial tokens, residual.
pub struct VaeAttention {
    norm: GroupNorm,
    attn: Attn,
}

impl VaeAttention {
    pub fn load(dw: &DeviceWeights, name: &str, groups: usize) -> Result<Self> {
        Ok(Self {
            norm: GroupNorm::load(dw, &format!("{name}.group_norm"), groups, 1e-6)?,
            attn: Attn::load(dw, name, 1)?,
        })
    }

    /// x: (N, C, H, W) -> (N, C, H, W)
    pub fn forward(&self, f: &mut Fwd, x: &Tensor) -> Result<Tensor> {
        let (h, w) = (x.shape()[2], x.shape()[3]);
        let t = self.norm.forward_tokens(f, x, false)?;
        let a = self.attn.attend(f, &t, None)?;
        f.ws.release(t);
        let out = self.attn.out.forward_to_channels(f, &a, Some(x), h, w)?;
        f.ws.release(a);
        Ok(out)
    }
}
