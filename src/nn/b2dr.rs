//! The Bench2Drive-R ControlNet on the engine (`docs/b2dr_controlnet.md`): the diffusers ControlNet with an
//! 8-channel conv_in ([x_t, z_prev]), a previous-frame noise-level embedding, a reference encoder on reference
//! latents, PETR position-encoding MLPs and residual Ref-Attn after the down blocks and the mid block.
//!
//! It runs in two parts. [`B2drControlNet::prepare`] records what depends on the frame only (the masks'
//! conditioning embedding, the noise-level embedding, the reference features, the position-encoding MLPs and
//! the Ref-Attn key/value projections): once per frame. [`B2drControlNet::forward`] records one denoising
//! step on top of a [`PreparedFrame`]: once per step. Its own loop over the shared blocks
//! ([`DownBlock2D`], [`MidBlock2DCrossAttn`]) places the Ref-Attns.
use anyhow::{ensure, Context as _, Result};

use super::b2dr_config::{B2drConfig, RefAttnAt};
use super::controlnet::{CondEmbedding, ControlOut, ZeroConvs};
use super::device::{DeviceWeights, Fwd};
use super::layers::{Conv, GroupNorm, Linear};
use super::resnet::Resnet;
use super::unet::{silu_released, EncoderHalf, TimeEmbedding};
use super::weights::{expected_controlnet, Spec};
use crate::ops::elementwise::{lincomb, LinTerm};
use crate::ops::{attention, attention_naive, elementwise as ew};
use crate::tensor::Tensor;

/// Every tensor of a B2D-R ControlNet: the diffusers ControlNetModel's, then the B2D-R parts (the names and
/// shapes the `load` functions below read).
pub fn expected_b2dr(cfg: &B2drConfig) -> Vec<Spec> {
    let mut v = expected_controlnet(&cfg.base);
    let e = &cfg.base.enc;
    let c0 = e.block_out_channels[0];
    let t = e.time_embed_dim();
    let mut add = |n: String, s: &[usize]| v.push((n, s.to_vec()));
    add("noise_embedding.linear_1.weight".into(), &[t, c0]);
    add("noise_embedding.linear_1.bias".into(), &[t]);
    add("noise_embedding.linear_2.weight".into(), &[t, t]);
    add("noise_embedding.linear_2.bias".into(), &[t]);
    let r = &cfg.ref_encoder_channels;
    add(
        "ref_encoder.conv_in.weight".into(),
        &[r[0], cfg.latent_channels(), 3, 3],
    );
    add("ref_encoder.conv_in.bias".into(), &[r[0]]);
    let mut prev = r[0];
    for (i, &c) in r.iter().enumerate() {
        let p = format!("ref_encoder.blocks.{i}.resnet");
        add(format!("{p}.norm1.weight"), &[prev]);
        add(format!("{p}.norm1.bias"), &[prev]);
        add(format!("{p}.conv1.weight"), &[c, prev, 3, 3]);
        add(format!("{p}.conv1.bias"), &[c]);
        add(format!("{p}.norm2.weight"), &[c]);
        add(format!("{p}.norm2.bias"), &[c]);
        add(format!("{p}.conv2.weight"), &[c, c, 3, 3]);
        add(format!("{p}.conv2.bias"), &[c]);
        if prev != c {
            add(format!("{p}.conv_shortcut.weight"), &[c, prev, 1, 1]);
            add(format!("{p}.conv_shortcut.bias"), &[c]);
        }
        if i + 1 < r.len() {
            add(
                format!("ref_encoder.blocks.{i}.downsample.weight"),
                &[c, c, 3, 3],
            );
            add(format!("ref_encoder.blocks.{i}.downsample.bias"), &[c]);
        }
        prev = c;
    }
    let d3 = 3 * cfg.pe_depth_num;
    for (j, &at) in cfg.ref_attn.iter().enumerate() {
        let (c, _) = cfg.location_channels(at);
        add(format!("pos_embed.{j}.conv_1.weight"), &[4 * c, d3, 1, 1]);
        add(format!("pos_embed.{j}.conv_1.bias"), &[4 * c]);
        add(format!("pos_embed.{j}.conv_2.weight"), &[c, 4 * c, 1, 1]);
        add(format!("pos_embed.{j}.conv_2.bias"), &[c]);
        let p = format!("ref_attn.{j}");
        add(format!("{p}.norm.weight"), &[c]);
        add(format!("{p}.norm.bias"), &[c]);
        for q in ["to_q", "to_k", "to_v"] {
            add(format!("{p}.{q}.weight"), &[c, c]);
        }
        add(format!("{p}.to_out.0.weight"), &[c, c]);
        add(format!("{p}.to_out.0.bias"), &[c]);
    }
    v
}

/// The reference encoder (`ref_encoder.*`): conv_in 4 -> R0, then per down block a ResnetBlock2D without
/// time embedding and, but for the last block, a stride-2 conv.
pub struct RefEncoder {
    conv_in: Conv,
    blocks: Vec<(Resnet, Option<Conv>)>,
    latent_channels: usize,
}

impl RefEncoder {
    pub fn load(dw: &DeviceWeights, cfg: &B2drConfig) -> Result<Self> {
        let e = &cfg.base.enc;
        let n = cfg.ref_encoder_channels.len();
        let blocks = (0..n)
            .map(|i| {
                let r = Resnet::load(
                    dw,
                    &format!("ref_encoder.blocks.{i}.resnet"),
                    e.norm_num_groups,
                    e.norm_eps,
                    false,
                )?;
                let d = if i + 1 < n {
                    Some(Conv::same3(
                        dw,
                        &format!("ref_encoder.blocks.{i}.downsample"),
                        2,
                    )?)
                } else {
                    None
                };
                Ok((r, d))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            conv_in: Conv::same3(dw, "ref_encoder.conv_in", 1)?,
            blocks,
            latent_channels: cfg.latent_channels(),
        })
    }

    /// z: (M, C, h, w) -> the features after each block, `F_i: (M, C_i, h_i, w_i)`.
    pub fn forward(&self, f: &mut Fwd, z: &Tensor) -> Result<Vec<Tensor>> {
        let s = z.shape();
        let c = self.latent_channels;
        ensure!(
            s.len() == 4 && s[1] == c,
            "ref encoder: reference latents {s:?} must be (M, {c}, h, w)"
        );
        let mut x = self.conv_in.forward(f, z)?;
        let mut out: Vec<Tensor> = vec![];
        for (r, d) in &self.blocks {
            let y = r.forward(f, &x, None)?;
            // each block's output is a returned feature: only conv_in's output is released
            if out.is_empty() {
                f.ws.release(x);
            }
            x = match d {
                Some(d) => {
                    let z = d.forward(f, &y)?;
                    f.ws.release(y);
                    z
                }
                None => y,
            };
            out.push(x.clone());
        }
        Ok(out)
    }
}

/// The position-encoding MLP of one Ref-Attn location (`pos_embed.{j}`): conv1x1 3D -> 4C, ReLU, 4C -> C.
pub struct PosEmbed {
    conv_1: Conv,
    conv_2: Conv,
}

impl PosEmbed {
    pub fn load(dw: &DeviceWeights, j: usize) -> Result<Self> {
        Ok(Self {
            conv_1: Conv::one(dw, &format!("pos_embed.{j}.conv_1"))?,
            conv_2: Conv::one(dw, &format!("pos_embed.{j}.conv_2"))?,
        })
    }

    /// pe: (M, 3D, h, w) -> (M, C, h, w)
    pub fn forward(&self, f: &mut Fwd, pe: &Tensor) -> Result<Tensor> {
        let a = self.conv_1.forward(f, pe)?;
        let r = f.ws.alloc(a.shape())?;
        ew::relu(f.rec, &a, &r)?;
        f.ws.release(a);
        let out = self.conv_2.forward(f, &r)?;
        f.ws.release(r);
        Ok(out)
    }
}

/// One Ref-Attn (`ref_attn.{j}`): `H' = H + to_out(Attn(to_q(norm(H) + P_cur), to_k(F + P_ref), to_v(F)))`.
pub struct RefAttn {
    norm: GroupNorm,
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
    heads: usize,
}

/// The frame-constant inputs of one Ref-Attn: projected keys and values over both references' tokens
/// `(N, 2hw, C)`, and the current camera's encoding as tokens `(N, hw, C)`.
pub struct RefKv {
    pub k: Tensor,
    pub v: Tensor,
    pub p_cur: Tensor,
}

/// (M, C, h, w) -> tokens (M, hw, C)
fn tokens(f: &mut Fwd, x: &Tensor) -> Result<Tensor> {
    let s = x.shape();
    let t = f.ws.alloc(&[s[0], s[2] * s[3], s[1]])?;
    ew::transpose(f.rec, &x.reshape(&[s[0], s[1], s[2] * s[3]])?, &t)?;
    Ok(t)
}

impl RefAttn {
    pub fn load(
        dw: &DeviceWeights,
        j: usize,
        groups: usize,
        eps: f64,
        heads: usize,
    ) -> Result<Self> {
        let p = format!("ref_attn.{j}");
        Ok(Self {
            norm: GroupNorm::load(dw, &format!("{p}.norm"), groups, eps)?,
            to_q: Linear::load(dw, &format!("{p}.to_q"))?,
            to_k: Linear::load(dw, &format!("{p}.to_k"))?,
            to_v: Linear::load(dw, &format!("{p}.to_v"))?,
            to_out: Linear::load(dw, &format!("{p}.to_out.0"))?,
            heads,
        })
    }

    /// feats, p_ref: (2N, C, h, w), rows camera-major (camera 0 front, camera 0 rear, camera 1 front, ...);
    /// p_cur: (N, C, h, w) -> the frame-constant [`RefKv`]. `feats` and the encodings are not released.
    pub fn prepare(
        &self,
        f: &mut Fwd,
        feats: &Tensor,
        p_ref: &Tensor,
        p_cur: &Tensor,
    ) -> Result<RefKv> {
        let (fs, ps) = (feats.shape().to_vec(), p_cur.shape().to_vec());
        ensure!(
            fs.len() == 4 && p_ref.shape() == fs && ps.len() == 4 && fs[0] == 2 * ps[0] && fs[1..] == ps[1..],
            "ref attn: reference features {fs:?}, their encodings {:?} and the current encoding {ps:?} must be \
             (2N, C, h, w), (2N, C, h, w) and (N, C, h, w)",
            p_ref.shape()
        );
        let (n, c, hw) = (ps[0], ps[1], ps[2] * ps[3]);
        let kin = f.ws.alloc(&fs)?;
        ew::add(f.rec, feats, p_ref, &kin)?;
        let kt = tokens(f, &kin)?;
        f.ws.release(kin);
        let k = self.to_k.forward(f, &kt.reshape(&[n, 2 * hw, c])?)?;
        f.ws.release(kt);
        let vt = tokens(f, feats)?;
        let v = self.to_v.forward(f, &vt.reshape(&[n, 2 * hw, c])?)?;
        f.ws.release(vt);
        let p_cur = tokens(f, p_cur)?;
        Ok(RefKv { k, v, p_cur })
    }

    /// h: (N, C, h, w) -> H' (N, C, h, w); `h` is not released.
    pub fn forward(&self, f: &mut Fwd, h: &Tensor, kv: &RefKv) -> Result<Tensor> {
        let s = h.shape();
        ensure!(
            s.len() == 4 && kv.p_cur.shape() == [s[0], s[2] * s[3], s[1]],
            "ref attn: hidden state {s:?} does not match the prepared encodings {:?}",
            kv.p_cur.shape()
        );
        let nt = self.norm.forward_tokens(f, h, false)?;
        let qin = f.ws.alloc(nt.shape())?;
        ew::add(f.rec, &nt, &kv.p_cur, &qin)?;
        f.ws.release(nt);
        let q = self.to_q.forward(f, &qin)?;
        f.ws.release(qin);
        let o = f.ws.alloc(q.shape())?;
        let head_dim = s[1] / self.heads;
        if head_dim % 4 == 0 {
            attention::attention(f.rec, &q, &kv.k, &kv.v, &o, self.heads, None)?;
        } else {
            attention_naive::attention_naive(f.rec, &q, &kv.k, &kv.v, &o, self.heads, None)?;
        }
        f.ws.release(q);
        let out = self
            .to_out
            .forward_to_channels(f, &o, Some(h), s[2], s[3])?;
        f.ws.release(o);
        Ok(out)
    }
}

/// Which rows of a model batch get references.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RefRows {
    /// No references (the unconditional model; Ref-Attn skipped).
    None,
    /// Every row (one half, or w = 1).
    All,
    /// The batch is `[no-ref; ref]` (reference guidance): the second half.
    SecondHalf,
}

/// What [`B2drControlNet::prepare`] computes once per frame; every tensor stays allocated.
pub struct PreparedFrame {
    /// Conditioning embedding of the masks (N, C0, h, w).
    pub emb: Tensor,
    /// Noise-level embedding before SiLU (1, 4 C0).
    pub noise_temb: Tensor,
    /// Per Ref-Attn location (None without references).
    pub refs: Option<Vec<RefKv>>,
}

/// The per-frame inputs of [`B2drControlNet::prepare`], on the device in the model dtype.
pub struct FrameTensors<'a> {
    /// (N, 15, 8h, 8w)
    pub masks: &'a Tensor,
    /// (1) f32: the previous frame's noise level n.
    pub noise_level: &'a Tensor,
    /// Reference latents (2N, 4, h, w) (camera-major, front then rear), and per Ref-Attn location the
    /// geometry `pe_cur: (N, 3D, h_j, w_j)` and `pe_ref: (2N, 3D, h_j, w_j)`.
    pub refs: Option<(&'a Tensor, &'a [Tensor], &'a [Tensor])>,
}

pub struct B2drControlNet {
    pub cfg: B2drConfig,
    enc: EncoderHalf,
    noise_embedding: TimeEmbedding,
    cond: CondEmbedding,
    zero: ZeroConvs,
    ref_encoder: RefEncoder,
    pos_embed: Vec<PosEmbed>,
    ref_attn: Vec<RefAttn>,
}

impl B2drControlNet {
    pub fn load(dw: &DeviceWeights, cfg: &B2drConfig) -> Result<Self> {
        let e = &cfg.base.enc;
        let mut pos_embed = vec![];
        let mut ref_attn = vec![];
        for (j, &at) in cfg.ref_attn.iter().enumerate() {
            let (_, i) = cfg.location_channels(at);
            pos_embed.push(PosEmbed::load(dw, j)?);
            ref_attn.push(RefAttn::load(
                dw,
                j,
                e.norm_num_groups,
                e.norm_eps,
                e.num_heads[i],
            )?);
        }
        Ok(Self {
            cfg: cfg.clone(),
            enc: EncoderHalf::load(dw, e)?,
            noise_embedding: TimeEmbedding::load(dw, "noise_embedding", e)?,
            cond: CondEmbedding::load(dw, &cfg.base)?,
            zero: ZeroConvs::load(dw, &cfg.base)?,
            ref_encoder: RefEncoder::load(dw, cfg)?,
            pos_embed,
            ref_attn,
        })
    }

    pub fn ref_encoder(&self) -> &RefEncoder {
        &self.ref_encoder
    }

    pub fn pos_embed(&self, j: usize) -> Option<&PosEmbed> {
        self.pos_embed.get(j)
    }

    pub fn ref_attn(&self, j: usize) -> Option<&RefAttn> {
        self.ref_attn.get(j)
    }

    /// The noise-level embedding (before the blocks' SiLU): n (M) f32 -> (M, 4 C0).
    pub fn noise_embedding(&self, f: &mut Fwd, n: &Tensor) -> Result<Tensor> {
        self.noise_embedding.forward(f, n)
    }

    /// The frame-constant part (see the module docs). Inputs are not released.
    pub fn prepare(&self, f: &mut Fwd, x: &FrameTensors) -> Result<PreparedFrame> {
        let emb = self.cond.forward(f, x.masks)?;
        ensure!(
            x.noise_level.shape() == [1],
            "b2dr controlnet: the noise level must be one value, got {:?}",
            x.noise_level.shape()
        );
        let noise_temb = self.noise_embedding.forward(f, x.noise_level)?;
        let n = x.masks.shape()[0];
        let refs = match x.refs {
            None => None,
            Some((lat, pe_cur, pe_ref)) => {
                ensure!(
                    lat.shape().len() == 4 && lat.shape()[0] == 2 * n,
                    "b2dr controlnet: reference latents {:?} must be (2 x {n} cameras, C, h, w)",
                    lat.shape()
                );
                let locs = self.cfg.ref_attn.len();
                ensure!(
                    pe_cur.len() == locs && pe_ref.len() == locs,
                    "b2dr controlnet: {} / {} position encodings for {locs} Ref-Attn locations",
                    pe_cur.len(),
                    pe_ref.len()
                );
                let feats = self.ref_encoder.forward(f, lat)?;
                let blocks = feats.len();
                let mut kvs = vec![];
                for (j, &at) in self.cfg.ref_attn.iter().enumerate() {
                    let fi = match at {
                        RefAttnAt::Down(i) => &feats[i],
                        RefAttnAt::Mid => &feats[blocks - 1],
                    };
                    let pc = self.pos_embed[j].forward(f, &pe_cur[j])?;
                    let pr = self.pos_embed[j].forward(f, &pe_ref[j])?;
                    ensure!(
                        pr.shape() == fi.shape(),
                        "b2dr controlnet: Ref-Attn {} position encoding {:?} does not match the reference \
                         features {:?} (the geometry must be at the location's feature size)",
                        at.name(),
                        pe_ref[j].shape(),
                        fi.shape()
                    );
                    kvs.push(self.ref_attn[j].prepare(f, fi, &pr, &pc)?);
                    f.ws.release(pc);
                    f.ws.release(pr);
                }
                for t in feats {
                    f.ws.release(t);
                }
                Some(kvs)
            }
        };
        Ok(PreparedFrame {
            emb,
            noise_temb,
            refs,
        })
    }

    /// Applies Ref-Attn `j` to the rows `rows` of `x` (B, C, h, w); returns the new hidden state (`x` itself
    /// when no row gets references). `x` is not released.
    fn apply_ref_attn(
        &self,
        f: &mut Fwd,
        j: usize,
        x: &Tensor,
        frame: &PreparedFrame,
        rows: RefRows,
    ) -> Result<Option<Tensor>> {
        let kv = match (&frame.refs, rows) {
            (_, RefRows::None) => return Ok(None),
            (None, _) => {
                anyhow::bail!("b2dr controlnet: references asked for, but the frame has none")
            }
            (Some(k), _) => &k[j],
        };
        match rows {
            RefRows::All => Ok(Some(self.ref_attn[j].forward(f, x, kv)?)),
            _ => {
                // [no-ref; ref]: the second half through Ref-Attn, the first copied as is (exactly the
                // no-reference model's hidden state)
                let s = x.shape();
                ensure!(s[0] % 2 == 0, "b2dr controlnet: guided batch {s:?} is odd");
                let per = x.numel() / 2;
                let half = f.ws.alloc(&[s[0] / 2, s[1], s[2], s[3]])?;
                let copy = |f: &mut Fwd, src: &Tensor, so: usize, dst: &Tensor, o: usize| {
                    lincomb(
                        f.rec,
                        &[LinTerm {
                            x: src,
                            offset: so,
                            coeff: 1.0,
                        }],
                        dst,
                        o,
                        per,
                    )
                };
                copy(f, x, per, &half, 0)?;
                let y = self.ref_attn[j].forward(f, &half, kv)?;
                f.ws.release(half);
                let out = f.ws.alloc(s)?;
                copy(f, x, 0, &out, 0)?;
                copy(f, &y, 0, &out, per)?;
                f.ws.release(y);
                Ok(Some(out))
            }
        }
    }

    /// One step. sample: (B, 2C, h, w) = [x_t, z_prev] in the model dtype, t: (B) f32, context: (B, L, D);
    /// B = N, or 2N for `RefRows::SecondHalf` (the frame's tensors cover N cameras and are added to each half).
    #[allow(clippy::too_many_arguments)] // the step's inputs, named as diffusers' ControlNetModel.forward
    pub fn forward(
        &self,
        f: &mut Fwd,
        sample: &Tensor,
        t: &Tensor,
        context: &Tensor,
        frame: &PreparedFrame,
        rows: RefRows,
        scale: f32,
    ) -> Result<ControlOut> {
        self.enc.check_inputs(sample, t, context)?;
        let (s, e) = (sample.shape(), frame.emb.shape());
        ensure!(
            e[2..] == s[2..] && s[0] % e[0] == 0,
            "b2dr controlnet: the masks embed to {e:?}, which does not fit the latent {s:?} (masks must be 8x \
             the latent size, one per camera)"
        );
        if let Some(r) = &frame.refs {
            ensure!(
                rows == RefRows::None
                    || r.first().is_none_or(|kv| {
                        kv.k.shape()[0] * if rows == RefRows::SecondHalf { 2 } else { 1 } == s[0]
                    }),
                "b2dr controlnet: batch {} does not match the prepared references for {rows:?}",
                s[0]
            );
        }
        let temb = self.enc.time.forward(f, t)?;
        let sum = f.ws.alloc(temb.shape())?;
        ew::add(f.rec, &temb, &frame.noise_temb, &sum)?;
        f.ws.release(temb);
        let temb = silu_released(f, sum)?;
        let mut x = self.enc.conv_in_add(f, sample, Some(&frame.emb))?;
        let mut skips = vec![x.clone()];
        let locs = &self.cfg.ref_attn;
        let at = |a: RefAttnAt| locs.iter().position(|&l| l == a);
        for (i, d) in self.enc.down.iter().enumerate() {
            x = d.forward(f, &x, &temb, context, &mut skips)?;
            if let Some(j) = at(RefAttnAt::Down(i)) {
                if let Some(y) = self.apply_ref_attn(f, j, &x, frame, rows)? {
                    // H' replaces the block output: the next block's input and the block's last skip
                    let last = skips.last_mut().context("skips")?;
                    let old = std::mem::replace(last, y.clone());
                    f.ws.release(old);
                    x = y;
                }
            }
        }
        let mut m = self.enc.mid.forward(f, &x, &temb, context)?;
        if let Some(j) = at(RefAttnAt::Mid) {
            if let Some(y) = self.apply_ref_attn(f, j, &m, frame, rows)? {
                f.ws.release(std::mem::replace(&mut m, y));
            }
        }
        f.ws.release(temb);
        self.zero.forward(f, skips, m, scale)
    }
}
