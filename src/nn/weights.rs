//! diffusers safetensors weights on the host: the expected tensor list per component, loading with checks,
//! seeded random weights, and saving.
//!
//! [`expected_unet`], [`expected_controlnet`] and [`expected_vae`] list every tensor of a component with
//! diffusers' exact names and shapes, derived from the config the way diffusers builds the modules
//! (e.g. `down_blocks.0.attentions.0.transformer_blocks.0.attn1.to_q.weight: [320, 320]`).
//! [`Weights::load`] reads a `.safetensors` file (F32, F16, or BF16, all kept as f32 on the host) and
//! checks it against such a list: a missing, extra or mis-shaped tensor, an unsupported dtype or a
//! truncated file is an error naming the tensor. Old VAE checkpoints that name the mid-block attention
//! `query/key/value/proj_attn` are renamed to `to_q/to_k/to_v/to_out.0` (diffusers does the same on load).
//!
//! [`Weights::random`] makes deterministic weights from a seed: each tensor is drawn from its own
//! counter-based SplitMix64 stream keyed by `seed ^ fnv1a64(name)`, so a tensor's values do not depend on
//! the others, and the generator is simple enough for tools/make_golden.py to reproduce bit for bit
//! (the b2dr-tiny goldens use this instead of storing 70 MB of weights; the golden stores per-tensor
//! [`Weights::fingerprint`]s so both sides provably use the same values).
//! Weights and biases are uniform in `±1/sqrt(fan_in)` (PyTorch's default bound); norm scales are
//! `1 + U(±0.1)` and norm shifts `U(±0.1)`. Everything is random, including the convs diffusers
//! zero-initialises in a ControlNet (`controlnet_cond_embedding.conv_out`, `controlnet_down_blocks.*`,
//! `controlnet_mid_block`): zero convs would make the ControlNet's residuals 0 and hide errors in tests.

use super::config::{ControlNetConfig, DownBlock, EncoderConfig, UNetConfig, UpBlock, VaeConfig};
use anyhow::{anyhow, bail, ensure, Context, Result};
use half::{bf16, f16};
use serde_json::{json, Map, Value};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// A tensor name and shape.
pub type Spec = (String, Vec<usize>);

/// Storage dtype of a tensor in a file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileDType {
    F32,
    F16,
    Bf16,
}

impl FileDType {
    fn name(self) -> &'static str {
        match self {
            Self::F32 => "F32",
            Self::F16 => "F16",
            Self::Bf16 => "BF16",
        }
    }

    fn size(self) -> usize {
        match self {
            Self::F32 => 4,
            _ => 2,
        }
    }
}

/// A host tensor (values widened to f32), row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct HostTensor {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
    /// The dtype the tensor had in its file (F32 for generated weights).
    pub file_dtype: FileDType,
}

/// A named set of host tensors.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Weights {
    pub tensors: BTreeMap<String, HostTensor>,
}

// ---------------------------------------------------------------------------------------------------------
// Expected tensor lists
// ---------------------------------------------------------------------------------------------------------

struct List(Vec<Spec>);

impl List {
    fn add(&mut self, name: String, shape: &[usize]) {
        self.0.push((name, shape.to_vec()));
    }
    fn conv(&mut self, p: &str, out: usize, inp: usize, k: usize) {
        self.add(format!("{p}.weight"), &[out, inp, k, k]);
        self.add(format!("{p}.bias"), &[out]);
    }
    fn linear(&mut self, p: &str, out: usize, inp: usize, bias: bool) {
        self.add(format!("{p}.weight"), &[out, inp]);
        if bias {
            self.add(format!("{p}.bias"), &[out]);
        }
    }
    fn norm(&mut self, p: &str, c: usize) {
        self.add(format!("{p}.weight"), &[c]);
        self.add(format!("{p}.bias"), &[c]);
    }
    /// ResnetBlock2D; `temb`: time embedding width (None in the VAE).
    fn resnet(&mut self, p: &str, inp: usize, out: usize, temb: Option<usize>) {
        self.norm(&format!("{p}.norm1"), inp);
        self.conv(&format!("{p}.conv1"), out, inp, 3);
        if let Some(t) = temb {
            self.linear(&format!("{p}.time_emb_proj"), out, t, true);
        }
        self.norm(&format!("{p}.norm2"), out);
        self.conv(&format!("{p}.conv2"), out, out, 3);
        if inp != out {
            self.conv(&format!("{p}.conv_shortcut"), out, inp, 1);
        }
    }
    /// Transformer2DModel (1x1-conv projections, one BasicTransformerBlock, GEGLU feed-forward).
    fn transformer(&mut self, p: &str, c: usize, cross: usize) {
        self.norm(&format!("{p}.norm"), c);
        self.conv(&format!("{p}.proj_in"), c, c, 1);
        let b = format!("{p}.transformer_blocks.0");
        self.norm(&format!("{b}.norm1"), c);
        for (attn, kv) in [("attn1", c), ("attn2", cross)] {
            self.linear(&format!("{b}.{attn}.to_q"), c, c, false);
            self.linear(&format!("{b}.{attn}.to_k"), c, kv, false);
            self.linear(&format!("{b}.{attn}.to_v"), c, kv, false);
            self.linear(&format!("{b}.{attn}.to_out.0"), c, c, true);
            if attn == "attn1" {
                self.norm(&format!("{b}.norm2"), c);
            }
        }
        self.norm(&format!("{b}.norm3"), c);
        self.linear(&format!("{b}.ff.net.0.proj"), 8 * c, c, true);
        self.linear(&format!("{b}.ff.net.2"), c, 4 * c, true);
        self.conv(&format!("{p}.proj_out"), c, c, 1);
    }
    /// VAE mid-block single-head attention.
    fn vae_attention(&mut self, p: &str, c: usize) {
        self.norm(&format!("{p}.group_norm"), c);
        for q in ["to_q", "to_k", "to_v", "to_out.0"] {
            self.linear(&format!("{p}.{q}"), c, c, true);
        }
    }
}

/// conv_in, time embedding, down blocks and mid block (UNet and ControlNet share these names).
fn encoder(l: &mut List, e: &EncoderConfig) {
    let c0 = e.block_out_channels[0];
    let t = e.time_embed_dim();
    l.conv("conv_in", c0, e.in_channels, 3);
    l.linear("time_embedding.linear_1", t, c0, true);
    l.linear("time_embedding.linear_2", t, t, true);
    let n = e.block_out_channels.len();
    let mut prev = c0;
    for (i, kind) in e.down_blocks.iter().enumerate() {
        let out = e.block_out_channels[i];
        for j in 0..e.layers_per_block {
            let inp = if j == 0 { prev } else { out };
            l.resnet(&format!("down_blocks.{i}.resnets.{j}"), inp, out, Some(t));
            if *kind == DownBlock::CrossAttn {
                l.transformer(
                    &format!("down_blocks.{i}.attentions.{j}"),
                    out,
                    e.cross_attention_dim,
                );
            }
        }
        if i + 1 < n {
            l.conv(&format!("down_blocks.{i}.downsamplers.0.conv"), out, out, 3);
        }
        prev = out;
    }
    let cl = e.block_out_channels[n - 1];
    l.resnet("mid_block.resnets.0", cl, cl, Some(t));
    l.transformer("mid_block.attentions.0", cl, e.cross_attention_dim);
    l.resnet("mid_block.resnets.1", cl, cl, Some(t));
}

/// Every tensor of a UNet2DConditionModel, diffusers names, in module order.
pub fn expected_unet(cfg: &UNetConfig) -> Vec<Spec> {
    let mut l = List(Vec::new());
    encoder(&mut l, &cfg.enc);
    let e = &cfg.enc;
    let t = e.time_embed_dim();
    let rev: Vec<usize> = e.block_out_channels.iter().rev().copied().collect();
    let n = rev.len();
    let mut prev_out = rev[0];
    for (i, kind) in cfg.up_blocks.iter().enumerate() {
        let out = rev[i];
        let inp = rev[(i + 1).min(n - 1)];
        let layers = e.layers_per_block + 1;
        for j in 0..layers {
            let skip = if j == layers - 1 { inp } else { out };
            let res_in = if j == 0 { prev_out } else { out };
            l.resnet(
                &format!("up_blocks.{i}.resnets.{j}"),
                res_in + skip,
                out,
                Some(t),
            );
            if *kind == UpBlock::CrossAttn {
                l.transformer(
                    &format!("up_blocks.{i}.attentions.{j}"),
                    out,
                    e.cross_attention_dim,
                );
            }
        }
        if i + 1 < n {
            l.conv(&format!("up_blocks.{i}.upsamplers.0.conv"), out, out, 3);
        }
        prev_out = out;
    }
    let c0 = e.block_out_channels[0];
    l.norm("conv_norm_out", c0);
    l.conv("conv_out", cfg.out_channels, c0, 3);
    l.0
}

/// Every tensor of a ControlNetModel, diffusers names.
pub fn expected_controlnet(cfg: &ControlNetConfig) -> Vec<Spec> {
    let mut l = List(Vec::new());
    encoder(&mut l, &cfg.enc);
    let emb = &cfg.conditioning_embedding_out_channels;
    let e = &cfg.enc;
    l.conv(
        "controlnet_cond_embedding.conv_in",
        emb[0],
        cfg.conditioning_channels,
        3,
    );
    for k in 0..emb.len() - 1 {
        l.conv(
            &format!("controlnet_cond_embedding.blocks.{}", 2 * k),
            emb[k],
            emb[k],
            3,
        );
        l.conv(
            &format!("controlnet_cond_embedding.blocks.{}", 2 * k + 1),
            emb[k + 1],
            emb[k],
            3,
        );
    }
    l.conv(
        "controlnet_cond_embedding.conv_out",
        e.block_out_channels[0],
        emb[emb.len() - 1],
        3,
    );
    let mut k = 0;
    let mut zero = |l: &mut List, c: usize| {
        l.conv(&format!("controlnet_down_blocks.{k}"), c, c, 1);
        k += 1;
    };
    zero(&mut l, e.block_out_channels[0]);
    let n = e.block_out_channels.len();
    for (i, c) in e.block_out_channels.iter().enumerate() {
        for _ in 0..e.layers_per_block {
            zero(&mut l, *c);
        }
        if i + 1 < n {
            zero(&mut l, *c);
        }
    }
    let cl = e.block_out_channels[n - 1];
    l.conv("controlnet_mid_block", cl, cl, 1);
    l.0
}

/// Every tensor of an AutoencoderKL, diffusers names.
pub fn expected_vae(cfg: &VaeConfig) -> Vec<Spec> {
    let mut l = List(Vec::new());
    let ch = &cfg.block_out_channels;
    let n = ch.len();
    let (c0, cl, z) = (ch[0], ch[n - 1], cfg.latent_channels);
    l.conv("encoder.conv_in", c0, cfg.in_channels, 3);
    let mut prev = c0;
    for (i, out) in ch.iter().enumerate() {
        for j in 0..cfg.layers_per_block {
            let inp = if j == 0 { prev } else { *out };
            l.resnet(
                &format!("encoder.down_blocks.{i}.resnets.{j}"),
                inp,
                *out,
                None,
            );
        }
        if i + 1 < n {
            l.conv(
                &format!("encoder.down_blocks.{i}.downsamplers.0.conv"),
                *out,
                *out,
                3,
            );
        }
        prev = *out;
    }
    let mid = |l: &mut List, p: &str| {
        l.resnet(&format!("{p}.mid_block.resnets.0"), cl, cl, None);
        if cfg.mid_block_add_attention {
            l.vae_attention(&format!("{p}.mid_block.attentions.0"), cl);
        }
        l.resnet(&format!("{p}.mid_block.resnets.1"), cl, cl, None);
    };
    mid(&mut l, "encoder");
    l.norm("encoder.conv_norm_out", cl);
    l.conv("encoder.conv_out", 2 * z, cl, 3);
    if cfg.use_quant_conv {
        l.conv("quant_conv", 2 * z, 2 * z, 1);
    }
    if cfg.use_post_quant_conv {
        l.conv("post_quant_conv", z, z, 1);
    }
    l.conv("decoder.conv_in", cl, z, 3);
    mid(&mut l, "decoder");
    let mut prev = cl;
    for (i, out) in ch.iter().rev().enumerate() {
        for j in 0..cfg.layers_per_block + 1 {
            let inp = if j == 0 { prev } else { *out };
            l.resnet(
                &format!("decoder.up_blocks.{i}.resnets.{j}"),
                inp,
                *out,
                None,
            );
        }
        if i + 1 < n {
            l.conv(
                &format!("decoder.up_blocks.{i}.upsamplers.0.conv"),
                *out,
                *out,
                3,
            );
        }
        prev = *out;
    }
    l.norm("decoder.conv_norm_out", c0);
    l.conv("decoder.conv_out", cfg.out_channels, c0, 3);
    l.0
}

// ---------------------------------------------------------------------------------------------------------
// safetensors I/O
// ---------------------------------------------------------------------------------------------------------

/// One tensor entry of a safetensors header.
struct Entry {
    dtype: String,
    shape: Vec<usize>,
    begin: usize,
    end: usize,
}

/// Parses the safetensors header; returns the entries and the data section's start.
fn parse_header(bytes: &[u8], what: &str) -> Result<(BTreeMap<String, Entry>, usize)> {
    ensure!(
        bytes.len() >= 8,
        "{what}: {} bytes, too short for a safetensors file (truncated?)",
        bytes.len()
    );
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap_or([0; 8])) as usize;
    ensure!(
        n <= bytes.len() - 8,
        "{what}: header of {n} bytes runs past the end of the {}-byte file (truncated?)",
        bytes.len()
    );
    let header: Map<String, Value> = serde_json::from_slice(&bytes[8..8 + n])
        .with_context(|| format!("{what}: the safetensors header is not a JSON object"))?;
    let mut out = BTreeMap::new();
    for (name, v) in header {
        if name == "__metadata__" {
            continue;
        }
        let bad = || anyhow!("{what}: tensor `{name}` has a malformed header entry: {v}");
        let dtype = v["dtype"].as_str().ok_or_else(bad)?.to_string();
        let shape: Option<Vec<usize>> = v["shape"]
            .as_array()
            .ok_or_else(bad)?
            .iter()
            .map(|x| x.as_u64().map(|x| x as usize))
            .collect();
        let offs = v["data_offsets"].as_array().ok_or_else(bad)?;
        ensure!(offs.len() == 2, bad());
        let begin = offs[0].as_u64().ok_or_else(bad)? as usize;
        let end = offs[1].as_u64().ok_or_else(bad)? as usize;
        ensure!(begin <= end, bad());
        out.insert(
            name.clone(),
            Entry {
                dtype,
                shape: shape.ok_or_else(bad)?,
                begin,
                end,
            },
        );
    }
    Ok((out, 8 + n))
}

/// The tensors' byte ranges must tile the data section exactly, as the safetensors format says: sorted by
/// offset, each begins where the previous ends, the first at 0, the last at the section's end (`data_len`). An
/// overlap (two tensors sharing bytes), a gap (bytes no tensor owns) or bytes past the last tensor are errors
/// naming the tensors; a range past the section's end is a truncated file.
fn check_tiling(entries: &BTreeMap<String, Entry>, data_len: usize, what: &str) -> Result<()> {
    let mut order: Vec<(&String, &Entry)> = entries.iter().collect();
    order.sort_by_key(|(_, e)| (e.begin, e.end));
    let mut cursor = 0usize;
    let mut prev: Option<&str> = None;
    for (name, e) in order {
        ensure!(
            e.end <= data_len,
            "{what}: tensor `{name}` (bytes {}..{} of the data section) lies past the end of the file \
             ({data_len} data bytes): the file is truncated",
            e.begin,
            e.end
        );
        let after = prev.map_or("the start of the data section".to_string(), |p| {
            format!("the end of `{p}`")
        });
        ensure!(
            e.begin >= cursor,
            "{what}: tensor `{name}` (bytes {}..{}) overlaps the bytes before {after} (byte {cursor}): \
             safetensors tensors must not share bytes",
            e.begin,
            e.end
        );
        ensure!(
            e.begin == cursor,
            "{what}: bytes {cursor}..{} between {after} and tensor `{name}` belong to no tensor: \
             safetensors tensors must tile the data section without gaps",
            e.begin
        );
        cursor = e.end;
        prev = Some(name);
    }
    ensure!(
        cursor == data_len,
        "{what}: the data section holds {data_len} bytes but its tensors cover only {cursor} (bytes \
         {cursor}..{data_len} belong to no tensor: trailing bytes or a missing header entry)"
    );
    Ok(())
}

fn decode(name: &str, e: &Entry, raw: &[u8], what: &str) -> Result<HostTensor> {
    let dtype = match e.dtype.as_str() {
        "F32" => FileDType::F32,
        "F16" => FileDType::F16,
        "BF16" => FileDType::Bf16,
        other => bail!("{what}: tensor `{name}` has dtype {other}; b2dr reads F32, F16 and BF16"),
    };
    // checked: a hostile header's shape product overflows usize
    let need = e
        .shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .and_then(|c| c.checked_mul(dtype.size()));
    ensure!(
        need == Some(raw.len()),
        "{what}: tensor `{name}` {:?} {} needs {} bytes, the file gives {}",
        e.shape,
        dtype.name(),
        need.map_or("more than 2^64".to_string(), |n| n.to_string()),
        raw.len()
    );
    let data = match dtype {
        FileDType::F32 => raw
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect(),
        FileDType::F16 => raw
            .chunks_exact(2)
            .map(|b| f16::from_le_bytes([b[0], b[1]]).to_f32())
            .collect(),
        FileDType::Bf16 => raw
            .chunks_exact(2)
            .map(|b| bf16::from_le_bytes([b[0], b[1]]).to_f32())
            .collect(),
    };
    Ok(HostTensor {
        shape: e.shape.clone(),
        data,
        file_dtype: dtype,
    })
}

/// Old AutoencoderKL attention names -> current diffusers names.
fn rename_legacy(name: &str) -> String {
    for (old, new) in [
        (".query.", ".to_q."),
        (".key.", ".to_k."),
        (".value.", ".to_v."),
        (".proj_attn.", ".to_out.0."),
    ] {
        if name.contains("mid_block.attentions.") && name.contains(old) {
            return name.replacen(old, new, 1);
        }
    }
    name.to_string()
}

impl Weights {
    /// Reads every tensor of a safetensors buffer without checking names (`what` names the source in errors).
    pub fn from_bytes_unchecked(bytes: &[u8], what: &str) -> Result<Self> {
        let (entries, start) = parse_header(bytes, what)?;
        check_tiling(&entries, bytes.len() - start, what)?;
        let mut tensors = BTreeMap::new();
        for (name, e) in &entries {
            let t = decode(name, e, &bytes[start + e.begin..start + e.end], what)?;
            tensors.insert(rename_legacy(name), t);
        }
        Ok(Self { tensors })
    }

    /// Reads a safetensors buffer and checks it against the expected list.
    pub fn from_bytes(bytes: &[u8], expected: &[Spec], what: &str) -> Result<Self> {
        let w = Self::from_bytes_unchecked(bytes, what)?;
        w.check(expected).with_context(|| what.to_string())?;
        // a NaN weight makes every image NaN: refuse the file, naming the tensor
        if let Some((n, _)) = w
            .tensors
            .iter()
            .find(|(_, t)| t.data.iter().any(|v| !v.is_finite()))
        {
            bail!("{what}: tensor `{n}` holds NaN or infinite values");
        }
        Ok(w)
    }

    /// Loads a `.safetensors` file and checks it against the expected list.
    pub fn load(path: &Path, expected: &[Spec]) -> Result<Self> {
        let bytes = Self::read_file(path)?;
        Self::from_bytes(&bytes, expected, &path.display().to_string())
    }

    /// Loads a `.safetensors` file without checking names.
    pub fn load_unchecked(path: &Path) -> Result<Self> {
        let bytes = Self::read_file(path)?;
        Self::from_bytes_unchecked(&bytes, &path.display().to_string())
    }

    /// Reads a safetensors file, bounded by what its header announces (issue #36): a FIFO, device or socket is
    /// refused before it is opened; the header is read first, and the data section is read only when the file's
    /// size is the size the header's byte ranges announce (they must tile it), so trailing bytes or a file that
    /// keeps growing are never read.
    pub fn read_file(path: &Path) -> Result<Vec<u8>> {
        use std::io::Read;
        let what = path.display().to_string();
        let (f, len) = crate::files::open_regular(path, "safetensors file")?;
        let mut f = f.take(len);
        let mut head = [0u8; 8];
        f.read_exact(&mut head).map_err(|_| {
            anyhow!("{what}: {len} bytes, too short for a safetensors file (truncated?)")
        })?;
        let n = u64::from_le_bytes(head);
        // the safetensors crate's own bound on a header (MAX_HEADER_SIZE)
        ensure!(
            n <= 100_000_000,
            "{what}: a header of {n} bytes, more than the 100000000 the safetensors format allows"
        );
        ensure!(
            n <= len - 8,
            "{what}: header of {n} bytes runs past the end of the {len}-byte file (truncated?)"
        );
        let mut bytes = head.to_vec();
        bytes.resize(8 + n as usize, 0);
        f.read_exact(&mut bytes[8..])
            .with_context(|| format!("reading {what}"))?;
        let (entries, start) = parse_header(&bytes, &what)?;
        let data_len = (len - start as u64) as usize;
        // the ranges must tile exactly the file's data section (so the header announces the file's size):
        // checked, naming what is wrong, before a data byte is read
        check_tiling(&entries, data_len, &what)?;
        bytes.reserve(data_len);
        let got = f
            .read_to_end(&mut bytes)
            .with_context(|| format!("reading {what}"))?;
        ensure!(
            got == data_len,
            "{what}: {got} data bytes read, the header announces {data_len} (the file changed while read)"
        );
        Ok(bytes)
    }

    /// Checks names and shapes: every expected tensor present with its shape, nothing else.
    pub fn check(&self, expected: &[Spec]) -> Result<()> {
        let want: BTreeSet<&str> = expected.iter().map(|(n, _)| n.as_str()).collect();
        let mut missing = Vec::new();
        for (name, shape) in expected {
            match self.tensors.get(name) {
                None => missing.push(name.as_str()),
                Some(t) if &t.shape != shape => {
                    bail!(
                        "tensor `{name}` has shape {:?}, the config needs {shape:?}",
                        t.shape
                    )
                }
                Some(_) => {}
            }
        }
        if !missing.is_empty() {
            bail!(
                "missing tensor `{}`{}",
                missing[0],
                if missing.len() > 1 {
                    format!(" (and {} more)", missing.len() - 1)
                } else {
                    String::new()
                }
            );
        }
        let extra: Vec<&String> = self
            .tensors
            .keys()
            .filter(|k| !want.contains(k.as_str()))
            .collect();
        if !extra.is_empty() {
            bail!(
                "unexpected tensor `{}` not in the config's model{}",
                extra[0],
                if extra.len() > 1 {
                    format!(" (and {} more)", extra.len() - 1)
                } else {
                    String::new()
                }
            );
        }
        Ok(())
    }

    /// A tensor by name.
    pub fn get(&self, name: &str) -> Result<&HostTensor> {
        self.tensors
            .get(name)
            .ok_or_else(|| anyhow!("missing tensor `{name}`"))
    }

    /// Deterministic random weights for the expected list (see the module docs for the distribution and
    /// the generator, which `tools/make_golden.py` reproduces bit for bit).
    pub fn random(expected: &[Spec], seed: u64) -> Self {
        let shapes: BTreeMap<&str, &Vec<usize>> =
            expected.iter().map(|(n, s)| (n.as_str(), s)).collect();
        let mut tensors = BTreeMap::new();
        for (name, shape) in expected {
            let key = seed ^ fnv1a(name);
            let count: usize = shape.iter().product();
            let u = (0..count as u64).map(|i| uniform_pm1(key, i));
            let data: Vec<f32> = if is_norm_param(name) {
                let base = if name.ends_with(".weight") {
                    1.0f32
                } else {
                    0.0
                };
                u.map(|x| base + 0.1f32 * x).collect()
            } else {
                let weight_shape = if name.ends_with(".bias") {
                    shapes
                        .get(name.replace(".bias", ".weight").as_str())
                        .copied()
                } else {
                    Some(shape)
                };
                let fan_in: usize = weight_shape
                    .map(|s| s.iter().skip(1).product())
                    .unwrap_or(1)
                    .max(1);
                let bound = 1.0f32 / (fan_in as f32).sqrt();
                u.map(|x| x * bound).collect()
            };
            tensors.insert(
                name.clone(),
                HostTensor {
                    shape: shape.clone(),
                    data,
                    file_dtype: FileDType::F32,
                },
            );
        }
        Self { tensors }
    }

    /// Order-sensitive fingerprint of a tensor's exact f32 bits: `sum_i bits(v_i) * (i + 1)` mod 2^64
    /// (the golden files store it for generated weights).
    pub fn fingerprint(t: &HostTensor) -> u64 {
        t.data.iter().enumerate().fold(0u64, |acc, (i, v)| {
            acc.wrapping_add((v.to_bits() as u64).wrapping_mul(i as u64 + 1))
        })
    }

    /// Serialises to safetensors bytes (F32 or F16), tensors sorted by name.
    pub fn to_bytes(&self, dtype: FileDType) -> Result<Vec<u8>> {
        ensure!(
            dtype != FileDType::Bf16,
            "b2dr writes F32 or F16 safetensors"
        );
        let mut header = Map::new();
        let mut offset = 0usize;
        for (name, t) in &self.tensors {
            let n = t.data.len() * dtype.size();
            header.insert(
                name.clone(),
                json!({"dtype": dtype.name(), "shape": t.shape, "data_offsets": [offset, offset + n]}),
            );
            offset += n;
        }
        let mut h = serde_json::to_vec(&Value::Object(header))?;
        while h.len() % 8 != 0 {
            h.push(b' ');
        }
        let mut out = Vec::with_capacity(8 + h.len() + offset);
        out.extend_from_slice(&(h.len() as u64).to_le_bytes());
        out.extend_from_slice(&h);
        for t in self.tensors.values() {
            match dtype {
                FileDType::F32 => t
                    .data
                    .iter()
                    .for_each(|v| out.extend_from_slice(&v.to_le_bytes())),
                _ => t
                    .data
                    .iter()
                    .for_each(|v| out.extend_from_slice(&f16::from_f32(*v).to_le_bytes())),
            }
        }
        Ok(out)
    }

    /// Writes a `.safetensors` file.
    pub fn save(&self, path: &Path, dtype: FileDType) -> Result<()> {
        std::fs::write(path, self.to_bytes(dtype)?)
            .with_context(|| format!("writing {}", path.display()))
    }
}

/// GroupNorm / LayerNorm parameters (scale and shift), by diffusers' naming.
fn is_norm_param(name: &str) -> bool {
    let module = name.rsplit_once('.').map(|(m, _)| m).unwrap_or(name);
    let last = module.rsplit('.').next().unwrap_or(module);
    last.starts_with("norm") || last == "conv_norm_out" || last == "group_norm"
}

/// Element `i` of the counter-based stream `key`: SplitMix64 of `key + (i + 1) * gamma`, top 24 bits mapped
/// to `[-1, 1)` exactly (`2 u - 1`, `u = k / 2^24`).
fn uniform_pm1(key: u64, i: u64) -> f32 {
    let mut z = key.wrapping_add((i + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    let u = (z >> 40) as f32 / 16_777_216.0;
    2.0 * u - 1.0
}

/// 64-bit FNV-1a (stable across platforms and Rust versions, unlike `DefaultHasher`).
fn fnv1a(s: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in s.bytes() {
        h ^= b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sd15_counts() {
        // Tensor counts of diffusers' SD1.5 checkpoints (runwayml/stable-diffusion-v1-5, lllyasviel ControlNets).
        assert_eq!(expected_unet(&UNetConfig::sd15()).len(), 686);
        assert_eq!(expected_vae(&VaeConfig::sd15()).len(), 248);
        assert_eq!(expected_controlnet(&ControlNetConfig::sd15()).len(), 340);
        let params: usize = expected_unet(&UNetConfig::sd15())
            .iter()
            .map(|(_, s)| s.iter().product::<usize>())
            .sum();
        assert_eq!(params, 859_520_964);
    }

    #[test]
    fn norm_names() {
        assert!(is_norm_param("down_blocks.0.resnets.0.norm1.weight"));
        assert!(is_norm_param("conv_norm_out.bias"));
        assert!(is_norm_param(
            "encoder.mid_block.attentions.0.group_norm.weight"
        ));
        assert!(!is_norm_param(
            "down_blocks.0.attentions.0.transformer_blocks.0.attn1.to_q.weight"
        ));
    }
}
