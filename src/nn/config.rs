//! diffusers `config.json` parsing for UNet2DConditionModel, ControlNetModel and AutoencoderKL.
//!
//! Each parser takes every key diffusers' `__init__` knows (defaults as in diffusers 0.42), checks that
//! the value is one b2dr implements, and resolves the per-block quantities (heads, head dims) the way
//! diffusers does. A key b2dr does not implement with a non-default value, an unknown key, or a bad value
//! is an error naming the key. Keys starting with `_` (`_class_name`, `_diffusers_version`,
//! `_name_or_path`) are metadata; `_class_name`, when present, must name the expected class.
//!
//! Head count: in SD1.x configs `attention_head_dim` is (for historical reasons) the number of heads
//! (diffusers: `num_attention_heads = num_attention_heads or attention_head_dim`); the head dimension of a
//! block is `channels / heads` (SD1.5: 8 heads, dims 40, 80, 160, 160). diffusers rejects
//! `num_attention_heads` for UNet2DConditionModel, and so does b2dr.

use anyhow::{anyhow, bail, ensure, Context, Result};
use serde_json::{json, Map, Value};
use std::path::Path;

/// Down block kinds of the SD1.5 family.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DownBlock {
    /// `CrossAttnDownBlock2D`: resnets interleaved with Transformer2DModels.
    CrossAttn,
    /// `DownBlock2D`: resnets only.
    Plain,
}

/// Up block kinds of the SD1.5 family.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UpBlock {
    /// `CrossAttnUpBlock2D`.
    CrossAttn,
    /// `UpBlock2D`.
    Plain,
}

/// The encoder half shared by the UNet and the ControlNet (conv_in, time embedding, down and mid blocks).
#[derive(Clone, Debug, PartialEq)]
pub struct EncoderConfig {
    pub in_channels: usize,
    pub flip_sin_to_cos: bool,
    pub freq_shift: f64,
    pub down_blocks: Vec<DownBlock>,
    pub block_out_channels: Vec<usize>,
    pub layers_per_block: usize,
    pub norm_num_groups: usize,
    pub norm_eps: f64,
    pub cross_attention_dim: usize,
    /// Attention heads per down block (the mid block uses the last).
    pub num_heads: Vec<usize>,
    pub upcast_attention: bool,
}

impl EncoderConfig {
    /// Time embedding width `4 * block_out_channels[0]` (SD1.5: 1280).
    pub fn time_embed_dim(&self) -> usize {
        4 * self.block_out_channels[0]
    }

    /// Head dimension of down block `i` (`channels / heads`).
    pub fn head_dim(&self, i: usize) -> usize {
        self.block_out_channels[i] / self.num_heads[i]
    }
}

/// UNet2DConditionModel (SD1.5 family).
#[derive(Clone, Debug, PartialEq)]
pub struct UNetConfig {
    pub enc: EncoderConfig,
    pub out_channels: usize,
    pub up_blocks: Vec<UpBlock>,
}

/// ControlNetModel (SD1.5 family).
#[derive(Clone, Debug, PartialEq)]
pub struct ControlNetConfig {
    pub enc: EncoderConfig,
    pub conditioning_channels: usize,
    pub conditioning_embedding_out_channels: Vec<usize>,
    /// `controlnet_conditioning_channel_order == "bgr"`: the condition's channels are flipped first (applied in
    /// `controlnet::CondEmbedding::load`, which reverses conv_in's input channels; tests/nn_controlnet_bgr.rs).
    pub bgr_conditioning: bool,
}

/// AutoencoderKL (SD family). Norm eps is fixed at 1e-6 by diffusers (not a config key).
#[derive(Clone, Debug, PartialEq)]
pub struct VaeConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    pub block_out_channels: Vec<usize>,
    pub layers_per_block: usize,
    pub latent_channels: usize,
    pub norm_num_groups: usize,
    pub scaling_factor: f64,
    pub shift_factor: Option<f64>,
    pub use_quant_conv: bool,
    pub use_post_quant_conv: bool,
    pub mid_block_add_attention: bool,
}

impl VaeConfig {
    /// GroupNorm eps inside the VAE (diffusers hard-codes 1e-6).
    pub const NORM_EPS: f64 = 1e-6;

    /// How much the encoder downsamples (and the decoder upsamples): 2 per block after the first.
    pub fn downsample_factor(&self) -> usize {
        1usize << self.block_out_channels.len().saturating_sub(1).min(16)
    }

    /// The SD pipeline's latent grid is the image's / 8: a VAE of another factor is an error naming `what`
    /// (the config file), not images of the wrong size.
    pub fn check_factor_8(&self, what: &str) -> Result<()> {
        ensure!(
            self.downsample_factor() == 8,
            "{what}: block_out_channels {:?} give a VAE that downsamples by {}; b2dr's pipeline needs 8 (4 blocks)",
            self.block_out_channels,
            self.downsample_factor()
        );
        Ok(())
    }
}

/// Largest integer a config key may hold (channels, groups, layers; SD1.5's largest is 1280): a larger one
/// is an error naming the key, not a model sized from it (allocations of 2^40 channels, overflowing shape
/// products, loops over 2^60 layers).
pub const MAX_CONFIG_INT: u64 = 1 << 16;
/// Most entries of a per-block list (SD1.5: 4 blocks).
pub const MAX_BLOCKS: usize = 16;

/// Reads a key map, tracking which keys were consumed.
struct Keys {
    class: &'static str,
    map: Map<String, Value>,
}

impl Keys {
    fn new(v: Value, class: &'static str) -> Result<Self> {
        let Value::Object(map) = v else {
            bail!("{class} config: expected a JSON object")
        };
        if let Some(c) = map.get("_class_name") {
            ensure!(
                c.as_str() == Some(class),
                "{class} config: _class_name is {c}, expected {class:?}"
            );
        }
        let map = map
            .into_iter()
            .filter(|(k, _)| !k.starts_with('_'))
            .collect();
        Ok(Self { class, map })
    }

    fn err(&self, key: &str, v: &Value, what: &str) -> anyhow::Error {
        anyhow!("{} config: key `{key}` = {v}: {what}", self.class)
    }

    fn take(&mut self, key: &str) -> Option<Value> {
        self.map.remove(key).filter(|v| !v.is_null())
    }

    fn usize(&mut self, key: &str, default: usize) -> Result<usize> {
        match self.take(key) {
            None => Ok(default),
            Some(v) => match v.as_u64() {
                Some(x) if x > 0 && x <= MAX_CONFIG_INT => Ok(x as usize),
                _ => Err(self.err(
                    key,
                    &v,
                    &format!("expected a positive integer (at most {MAX_CONFIG_INT})"),
                )),
            },
        }
    }

    fn f64(&mut self, key: &str, default: f64) -> Result<f64> {
        match self.take(key) {
            None => Ok(default),
            Some(v) => v
                .as_f64()
                .filter(|x| x.is_finite())
                .ok_or_else(|| self.err(key, &v, "expected a number")),
        }
    }

    fn bool(&mut self, key: &str, default: bool) -> Result<bool> {
        match self.take(key) {
            None => Ok(default),
            Some(v) => v
                .as_bool()
                .ok_or_else(|| self.err(key, &v, "expected true or false")),
        }
    }

    fn usize_list(&mut self, key: &str, default: &[usize]) -> Result<Vec<usize>> {
        match self.take(key) {
            None => Ok(default.to_vec()),
            Some(v) => {
                let arr = v
                    .as_array()
                    .ok_or_else(|| self.err(key, &v, "expected a list of positive integers"))?;
                let out: Option<Vec<usize>> = arr
                    .iter()
                    .map(|x| {
                        x.as_u64()
                            .filter(|x| *x > 0 && *x <= MAX_CONFIG_INT)
                            .map(|x| x as usize)
                    })
                    .collect();
                let out = out.ok_or_else(|| {
                    self.err(
                        key,
                        &v,
                        &format!("expected a list of positive integers (at most {MAX_CONFIG_INT})"),
                    )
                })?;
                ensure!(!out.is_empty(), self.err(key, &v, "must not be empty"));
                ensure!(
                    out.len() <= MAX_BLOCKS,
                    self.err(key, &v, &format!("at most {MAX_BLOCKS} entries"))
                );
                Ok(out)
            }
        }
    }

    /// An integer or a per-block list of integers.
    fn per_block(&mut self, key: &str, default: usize, n: usize) -> Result<Vec<usize>> {
        match self.take(key) {
            None => Ok(vec![default; n]),
            Some(v) if v.is_u64() => {
                let x = v.as_u64().unwrap_or(0);
                ensure!(
                    x > 0 && x <= MAX_CONFIG_INT,
                    self.err(
                        key,
                        &v,
                        &format!("expected a positive integer (at most {MAX_CONFIG_INT})")
                    )
                );
                let x = x as usize;
                Ok(vec![x; n])
            }
            Some(v) => {
                self.map.insert(key.to_string(), v.clone());
                let l = self.usize_list(key, &[])?;
                ensure!(
                    l.len() == n,
                    self.err(key, &v, &format!("expected {n} entries, one per block"))
                );
                Ok(l)
            }
        }
    }

    fn str_list(&mut self, key: &str, default: &[&str]) -> Result<Vec<String>> {
        match self.take(key) {
            None => Ok(default.iter().map(|s| s.to_string()).collect()),
            Some(v) => {
                let arr = v
                    .as_array()
                    .ok_or_else(|| self.err(key, &v, "expected a list of strings"))?;
                ensure!(
                    arr.len() <= MAX_BLOCKS,
                    self.err(key, &v, &format!("at most {MAX_BLOCKS} entries"))
                );
                arr.iter()
                    .map(|x| {
                        x.as_str()
                            .map(str::to_string)
                            .ok_or_else(|| self.err(key, &v, "expected strings"))
                    })
                    .collect()
            }
        }
    }

    /// A key b2dr accepts only with one of `allowed` values (absent/null counts as the default `allowed[0]`).
    fn only(&mut self, key: &str, allowed: &[Value], why: &str) -> Result<Value> {
        match self.take(key) {
            None => Ok(allowed[0].clone()),
            Some(v) => {
                // `true`/`[true, true]` style per-block flags: accept lists of one allowed value.
                let ok = allowed.contains(&v)
                    || v.as_array()
                        .is_some_and(|a| !a.is_empty() && a.iter().all(|x| allowed.contains(x)));
                if ok {
                    Ok(v)
                } else {
                    Err(self.err(
                        key,
                        &v,
                        &format!("not supported by b2dr ({why}; supported: {allowed:?})"),
                    ))
                }
            }
        }
    }

    /// Ignores a key whose value does not affect inference (sample_size, dropout, ...).
    fn ignore(&mut self, key: &str) {
        self.map.remove(key);
    }

    fn finish(self) -> Result<()> {
        if let Some(k) = self.map.keys().next() {
            bail!(
                "{} config: unknown key `{k}` (not a diffusers {} key b2dr knows)",
                self.class,
                self.class
            );
        }
        Ok(())
    }
}

const SD_DOWN: [&str; 4] = [
    "CrossAttnDownBlock2D",
    "CrossAttnDownBlock2D",
    "CrossAttnDownBlock2D",
    "DownBlock2D",
];
const SD_UP: [&str; 4] = [
    "UpBlock2D",
    "CrossAttnUpBlock2D",
    "CrossAttnUpBlock2D",
    "CrossAttnUpBlock2D",
];

/// The keys shared by UNet and ControlNet.
fn parse_encoder(k: &mut Keys) -> Result<EncoderConfig> {
    let in_channels = k.usize("in_channels", 4)?;
    let flip_sin_to_cos = k.bool("flip_sin_to_cos", true)?;
    let freq_shift = k.f64("freq_shift", 0.0)?;
    let down_names = k.str_list("down_block_types", &SD_DOWN)?;
    let mut down_blocks = Vec::new();
    for n in &down_names {
        down_blocks.push(match n.as_str() {
            "CrossAttnDownBlock2D" => DownBlock::CrossAttn,
            "DownBlock2D" => DownBlock::Plain,
            other => bail!(
                "{} config: key `down_block_types` has {other:?}: not supported by b2dr \
                 (CrossAttnDownBlock2D, DownBlock2D)",
                k.class
            ),
        });
    }
    k.only(
        "mid_block_type",
        &[json!("UNetMidBlock2DCrossAttn")],
        "SD1.5 mid block",
    )?;
    k.only(
        "only_cross_attention",
        &[json!(false)],
        "self-attention is always present",
    )?;
    let block_out_channels = k.usize_list("block_out_channels", &[320, 640, 1280, 1280])?;
    ensure!(
        block_out_channels.len() == down_blocks.len(),
        "{} config: key `block_out_channels` has {} entries but `down_block_types` {}",
        k.class,
        block_out_channels.len(),
        down_blocks.len()
    );
    let layers_per_block = k.usize("layers_per_block", 2)?;
    k.only(
        "downsample_padding",
        &[json!(1)],
        "stride-2 conv with padding 1",
    )?;
    k.only(
        "mid_block_scale_factor",
        &[json!(1), json!(1.0)],
        "mid block output scale 1",
    )?;
    k.only("act_fn", &[json!("silu")], "SiLU activations")?;
    let norm_num_groups = k.usize("norm_num_groups", 32)?;
    for c in &block_out_channels {
        ensure!(
            c % norm_num_groups == 0,
            "{} config: key `norm_num_groups` = {norm_num_groups} does not divide block channel count {c}",
            k.class
        );
    }
    let norm_eps = k.f64("norm_eps", 1e-5)?;
    ensure!(
        norm_eps > 0.0,
        "{} config: key `norm_eps` must be > 0",
        k.class
    );
    let cross_attention_dim = k.usize("cross_attention_dim", 1280)?;
    k.only(
        "transformer_layers_per_block",
        &[json!(1)],
        "one transformer layer per attention",
    )?;
    k.only("encoder_hid_dim", &[Value::Null], "no encoder_hid_proj")?;
    k.only(
        "encoder_hid_dim_type",
        &[Value::Null],
        "no encoder_hid_proj",
    )?;
    k.only(
        "num_attention_heads",
        &[Value::Null],
        "diffusers uses attention_head_dim as the head count",
    )?;
    let num_heads = k.per_block("attention_head_dim", 8, block_out_channels.len())?;
    let n = block_out_channels.len();
    for (i, (c, h)) in block_out_channels.iter().zip(&num_heads).enumerate() {
        // Only blocks with attention use the head count (the mid block uses the last one).
        if down_blocks[i] == DownBlock::Plain && i + 1 != n {
            continue;
        }
        ensure!(
            c % h == 0,
            "{} config: key `attention_head_dim` (head count {h}) does not divide block {i}'s {c} channels",
            k.class
        );
    }
    k.only(
        "use_linear_projection",
        &[json!(false)],
        "1x1-conv proj_in/proj_out (SD1.x)",
    )?;
    k.only("class_embed_type", &[Value::Null], "no class embedding")?;
    k.only(
        "addition_embed_type",
        &[Value::Null],
        "no addition embedding",
    )?;
    k.only(
        "addition_time_embed_dim",
        &[Value::Null],
        "no addition embedding",
    )?;
    k.only("num_class_embeds", &[Value::Null], "no class embedding")?;
    k.only(
        "projection_class_embeddings_input_dim",
        &[Value::Null],
        "no class embedding",
    )?;
    k.ignore("addition_embed_type_num_heads");
    let upcast_attention = k.bool("upcast_attention", false)?;
    k.only(
        "resnet_time_scale_shift",
        &[json!("default")],
        "additive time embedding in resnets",
    )?;
    let enc = EncoderConfig {
        in_channels,
        flip_sin_to_cos,
        freq_shift,
        down_blocks,
        block_out_channels,
        layers_per_block,
        norm_num_groups,
        norm_eps,
        cross_attention_dim,
        num_heads,
        upcast_attention,
    };
    Ok(enc)
}

fn read_json(path: &Path) -> Result<Value> {
    let text = crate::files::read_regular_string(path, "model config", crate::files::JSON_LIMIT)?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

impl UNetConfig {
    /// Parses a diffusers UNet2DConditionModel config.
    pub fn from_json(v: Value) -> Result<Self> {
        let mut k = Keys::new(v, "UNet2DConditionModel")?;
        let enc = parse_encoder(&mut k)?;
        let out_channels = k.usize("out_channels", 4)?;
        let up_names = k.str_list("up_block_types", &SD_UP)?;
        let mut up_blocks = Vec::new();
        for n in &up_names {
            up_blocks.push(match n.as_str() {
                "CrossAttnUpBlock2D" => UpBlock::CrossAttn,
                "UpBlock2D" => UpBlock::Plain,
                other => bail!(
                    "UNet2DConditionModel config: key `up_block_types` has {other:?}: not supported by b2dr \
                     (CrossAttnUpBlock2D, UpBlock2D)"
                ),
            });
        }
        ensure!(
            up_blocks.len() == enc.down_blocks.len(),
            "UNet2DConditionModel config: key `up_block_types` has {} entries, `down_block_types` {}",
            up_blocks.len(),
            enc.down_blocks.len()
        );
        k.ignore("sample_size");
        k.ignore("dropout");
        k.only("center_input_sample", &[json!(false)], "input used as is")?;
        k.only(
            "reverse_transformer_layers_per_block",
            &[Value::Null],
            "one transformer layer",
        )?;
        k.only(
            "dual_cross_attention",
            &[json!(false)],
            "single cross-attention",
        )?;
        k.only("resnet_skip_time_act", &[json!(false)], "SD1.5 resnets")?;
        k.only(
            "resnet_out_scale_factor",
            &[json!(1.0), json!(1)],
            "SD1.5 resnets",
        )?;
        k.only(
            "time_embedding_type",
            &[json!("positional")],
            "sinusoidal time embedding",
        )?;
        k.only(
            "time_embedding_dim",
            &[Value::Null],
            "time embedding 4 x block_out_channels[0]",
        )?;
        k.only(
            "time_embedding_act_fn",
            &[Value::Null],
            "no extra time activation",
        )?;
        k.only("timestep_post_act", &[Value::Null], "no post activation")?;
        k.only(
            "time_cond_proj_dim",
            &[Value::Null],
            "no time condition projection",
        )?;
        k.only("conv_in_kernel", &[json!(3)], "3x3 conv_in")?;
        k.only("conv_out_kernel", &[json!(3)], "3x3 conv_out")?;
        k.only("attention_type", &[json!("default")], "plain attention")?;
        k.only(
            "class_embeddings_concat",
            &[json!(false)],
            "no class embedding",
        )?;
        k.only(
            "mid_block_only_cross_attention",
            &[Value::Null, json!(false)],
            "mid block self-attention",
        )?;
        k.only(
            "cross_attention_norm",
            &[Value::Null],
            "no cross-attention norm",
        )?;
        k.finish()?;
        Ok(Self {
            enc,
            out_channels,
            up_blocks,
        })
    }

    /// Reads `config.json` from a path.
    pub fn from_file(path: &Path) -> Result<Self> {
        Self::from_json(read_json(path)?).with_context(|| format!("in {}", path.display()))
    }

    /// Stable Diffusion 1.5's UNet.
    pub fn sd15() -> Self {
        Self::from_json(json!({
            "block_out_channels": [320, 640, 1280, 1280], "cross_attention_dim": 768, "attention_head_dim": 8,
            "layers_per_block": 2, "norm_num_groups": 32, "in_channels": 4, "out_channels": 4,
            "down_block_types": SD_DOWN, "up_block_types": SD_UP,
        }))
        .expect("built-in SD1.5 UNet config is valid")
    }

    /// The built-in tiny model "b2dr-tiny": SD1.5's structure, channels (32, 64, 128, 128), 4 heads,
    /// cross-attention dim 64, 8 norm groups.
    pub fn b2dr_tiny() -> Self {
        Self::from_json(json!({
            "block_out_channels": [32, 64, 128, 128], "cross_attention_dim": 64, "attention_head_dim": 4,
            "layers_per_block": 2, "norm_num_groups": 8, "in_channels": 4, "out_channels": 4,
            "down_block_types": SD_DOWN, "up_block_types": SD_UP,
        }))
        .expect("built-in b2dr-tiny UNet config is valid")
    }

    /// The config as diffusers' `config.json` (loadable with `UNet2DConditionModel.from_config`).
    pub fn to_json(&self) -> Value {
        let mut v = encoder_json(&self.enc, "UNet2DConditionModel");
        v["out_channels"] = json!(self.out_channels);
        v["up_block_types"] = json!(self
            .up_blocks
            .iter()
            .map(|b| match b {
                UpBlock::CrossAttn => "CrossAttnUpBlock2D",
                UpBlock::Plain => "UpBlock2D",
            })
            .collect::<Vec<_>>());
        v
    }
}

fn encoder_json(e: &EncoderConfig, class: &str) -> Value {
    json!({
        "_class_name": class,
        "in_channels": e.in_channels,
        "flip_sin_to_cos": e.flip_sin_to_cos,
        "freq_shift": e.freq_shift,
        "down_block_types": e.down_blocks.iter().map(|b| match b {
            DownBlock::CrossAttn => "CrossAttnDownBlock2D",
            DownBlock::Plain => "DownBlock2D",
        }).collect::<Vec<_>>(),
        "block_out_channels": e.block_out_channels,
        "layers_per_block": e.layers_per_block,
        "norm_num_groups": e.norm_num_groups,
        "norm_eps": e.norm_eps,
        "cross_attention_dim": e.cross_attention_dim,
        "attention_head_dim": e.num_heads,
        "upcast_attention": e.upcast_attention,
        "act_fn": "silu",
    })
}

impl ControlNetConfig {
    /// Parses a diffusers ControlNetModel config.
    pub fn from_json(v: Value) -> Result<Self> {
        let mut k = Keys::new(v, "ControlNetModel")?;
        let enc = parse_encoder(&mut k)?;
        let conditioning_channels = k.usize("conditioning_channels", 3)?;
        let conditioning_embedding_out_channels =
            k.usize_list("conditioning_embedding_out_channels", &[16, 32, 96, 256])?;
        let order = k.only(
            "controlnet_conditioning_channel_order",
            &[json!("rgb"), json!("bgr")],
            "rgb or bgr",
        )?;
        k.only(
            "global_pool_conditions",
            &[json!(false)],
            "spatial residuals",
        )?;
        k.finish()?;
        Ok(Self {
            enc,
            conditioning_channels,
            conditioning_embedding_out_channels,
            bgr_conditioning: order == json!("bgr"),
        })
    }

    /// Reads `config.json` from a path.
    pub fn from_file(path: &Path) -> Result<Self> {
        Self::from_json(read_json(path)?).with_context(|| format!("in {}", path.display()))
    }

    /// The SD1.5 ControlNet (lllyasviel/sd-controlnet-* structure).
    pub fn sd15() -> Self {
        Self::from_unet(&UNetConfig::sd15(), 3, vec![16, 32, 96, 256])
    }

    /// b2dr-tiny's ControlNet: the tiny UNet's encoder, embedding channels (16, 32, 96, 256), 3 condition channels.
    pub fn b2dr_tiny() -> Self {
        Self::from_unet(&UNetConfig::b2dr_tiny(), 3, vec![16, 32, 96, 256])
    }

    /// A ControlNet with a UNet's encoder (diffusers `ControlNetModel.from_unet`).
    pub fn from_unet(unet: &UNetConfig, conditioning_channels: usize, embed: Vec<usize>) -> Self {
        Self {
            enc: unet.enc.clone(),
            conditioning_channels,
            conditioning_embedding_out_channels: embed,
            bgr_conditioning: false,
        }
    }

    /// The config as diffusers' `config.json`.
    pub fn to_json(&self) -> Value {
        let mut v = encoder_json(&self.enc, "ControlNetModel");
        v["conditioning_channels"] = json!(self.conditioning_channels);
        v["conditioning_embedding_out_channels"] = json!(self.conditioning_embedding_out_channels);
        v["controlnet_conditioning_channel_order"] =
            json!(if self.bgr_conditioning { "bgr" } else { "rgb" });
        v
    }
}

impl VaeConfig {
    /// Parses a diffusers AutoencoderKL config.
    pub fn from_json(v: Value) -> Result<Self> {
        let mut k = Keys::new(v, "AutoencoderKL")?;
        let in_channels = k.usize("in_channels", 3)?;
        let out_channels = k.usize("out_channels", 3)?;
        let block_out_channels = k.usize_list("block_out_channels", &[64])?;
        let n = block_out_channels.len();
        for (key, want) in [
            ("down_block_types", "DownEncoderBlock2D"),
            ("up_block_types", "UpDecoderBlock2D"),
        ] {
            let names = k.str_list(key, &[want])?;
            ensure!(
                names.len() == n,
                "AutoencoderKL config: key `{key}` has {} entries, `block_out_channels` {n}",
                names.len()
            );
            if let Some(bad) = names.iter().find(|s| s.as_str() != want) {
                bail!("AutoencoderKL config: key `{key}` has {bad:?}: not supported by b2dr (only {want})");
            }
        }
        let layers_per_block = k.usize("layers_per_block", 1)?;
        k.only("act_fn", &[json!("silu")], "SiLU activations")?;
        let latent_channels = k.usize("latent_channels", 4)?;
        let norm_num_groups = k.usize("norm_num_groups", 32)?;
        for c in &block_out_channels {
            ensure!(
                c % norm_num_groups == 0,
                "AutoencoderKL config: key `norm_num_groups` = {norm_num_groups} does not divide channel count {c}"
            );
        }
        k.ignore("sample_size");
        k.ignore("force_upcast");
        let scaling_factor = k.f64("scaling_factor", 0.18215)?;
        ensure!(
            scaling_factor > 0.0,
            "AutoencoderKL config: key `scaling_factor` must be > 0"
        );
        let shift_factor = match k.take("shift_factor") {
            None => None,
            Some(v) => Some(
                v.as_f64()
                    .ok_or_else(|| k.err("shift_factor", &v, "expected a number"))?,
            ),
        };
        k.only(
            "latents_mean",
            &[Value::Null],
            "no per-channel latent statistics",
        )?;
        k.only(
            "latents_std",
            &[Value::Null],
            "no per-channel latent statistics",
        )?;
        let use_quant_conv = k.bool("use_quant_conv", true)?;
        let use_post_quant_conv = k.bool("use_post_quant_conv", true)?;
        let mid_block_add_attention = k.bool("mid_block_add_attention", true)?;
        k.finish()?;
        Ok(Self {
            in_channels,
            out_channels,
            block_out_channels,
            layers_per_block,
            latent_channels,
            norm_num_groups,
            scaling_factor,
            shift_factor,
            use_quant_conv,
            use_post_quant_conv,
            mid_block_add_attention,
        })
    }

    /// Reads `config.json` from a path.
    pub fn from_file(path: &Path) -> Result<Self> {
        Self::from_json(read_json(path)?).with_context(|| format!("in {}", path.display()))
    }

    /// SD1.5's VAE: channels (128, 256, 512, 512), 2 layers per block, 32 groups.
    pub fn sd15() -> Self {
        Self::tiny_or_sd(&[128, 256, 512, 512], 32)
    }

    /// b2dr-tiny's VAE: channels (32, 64, 128, 128), 2 layers per block, 8 groups.
    pub fn b2dr_tiny() -> Self {
        Self::tiny_or_sd(&[32, 64, 128, 128], 8)
    }

    fn tiny_or_sd(ch: &[usize], groups: usize) -> Self {
        Self {
            in_channels: 3,
            out_channels: 3,
            block_out_channels: ch.to_vec(),
            layers_per_block: 2,
            latent_channels: 4,
            norm_num_groups: groups,
            scaling_factor: 0.18215,
            shift_factor: None,
            use_quant_conv: true,
            use_post_quant_conv: true,
            mid_block_add_attention: true,
        }
    }

    /// The config as diffusers' `config.json`.
    pub fn to_json(&self) -> Value {
        let n = self.block_out_channels.len();
        json!({
            "_class_name": "AutoencoderKL",
            "in_channels": self.in_channels,
            "out_channels": self.out_channels,
            "down_block_types": vec!["DownEncoderBlock2D"; n],
            "up_block_types": vec!["UpDecoderBlock2D"; n],
            "block_out_channels": self.block_out_channels,
            "layers_per_block": self.layers_per_block,
            "act_fn": "silu",
            "latent_channels": self.latent_channels,
            "norm_num_groups": self.norm_num_groups,
            "scaling_factor": self.scaling_factor,
            "shift_factor": self.shift_factor,
            "use_quant_conv": self.use_quant_conv,
            "use_post_quant_conv": self.use_post_quant_conv,
            "mid_block_add_attention": self.mid_block_add_attention,
        })
    }
}
