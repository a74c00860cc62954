//! The Bench2Drive-R ControlNet config: diffusers' ControlNetModel keys plus the B2D-R keys
//! (`docs/b2dr_controlnet.md` section 5). A config whose `_class_name` is not "B2DRControlNetModel" is a
//! plain ControlNet ([`ControlNetKind::Plain`]).
use anyhow::{bail, ensure, Context, Result};
use serde_json::{json, Map, Value};
use std::path::Path;

use super::config::{ControlNetConfig, UNetConfig};
use crate::projection::geometry::{channel_name, NUM_MASK_CHANNELS};

pub const CLASS_NAME: &str = "B2DRControlNetModel";

/// Where a Ref-Attn sits: after down block `i`, or after the mid block.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RefAttnAt {
    Down(usize),
    Mid,
}

impl RefAttnAt {
    pub fn name(self) -> String {
        match self {
            RefAttnAt::Down(i) => format!("down.{i}"),
            RefAttnAt::Mid => "mid".to_string(),
        }
    }

    fn parse(s: &str, blocks: usize) -> Option<Self> {
        if s == "mid" {
            return Some(RefAttnAt::Mid);
        }
        let i: usize = s.strip_prefix("down.")?.parse().ok()?;
        (i < blocks).then_some(RefAttnAt::Down(i))
    }

    /// Order along the forward pass (down blocks, then mid).
    fn order(self) -> usize {
        match self {
            RefAttnAt::Down(i) => i,
            RefAttnAt::Mid => usize::MAX,
        }
    }
}

/// The largest previous-frame warp depth cap (metres; b2dr_ref/controlnet.py MAX_WARP_DEPTH).
pub const MAX_WARP_DEPTH: f64 = 1000.0;

/// What a B2D-R model is given as its previous frame (b2dr.json ControlNet key `prev_source`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PrevSource {
    /// "previous": the frame rendered before (in the loop: the model's own last output, carried on the
    /// device; the first frame and eval-render's single frames: the logged previous frame).
    #[default]
    Previous,
    /// "reference": every frame's previous-frame input is one of its own retrieved references (a logged
    /// image), the one whose camera stands farthest behind the current camera along its optical axis, warped
    /// to the current pose (needs `prev_warp_max_depth` > 0). Nothing rendered is carried from frame to frame,
    /// so a rollout cannot accumulate its own errors (`eval::prev_base::reference_base`).
    Reference,
    /// "composite": as "reference" for the scenery, but where the current layout or the reference's own logged
    /// agents hold a vehicle or a person, the pixels of the frame rendered before (warped to the current pose):
    /// a reference keeps showing the log's agents where the simulation has moved them
    /// (`eval::prev_base::reference_base`). Needs `prev_warp_max_depth` > 0.
    Composite,
}

impl PrevSource {
    pub fn name(self) -> &'static str {
        match self {
            PrevSource::Previous => "previous",
            PrevSource::Reference => "reference",
            PrevSource::Composite => "composite",
        }
    }

    /// Whether the previous-frame input starts from a retrieved reference ("reference", "composite").
    pub fn from_references(self) -> bool {
        self != PrevSource::Previous
    }
}

/// A B2D-R ControlNet config.
#[derive(Clone, Debug, PartialEq)]
pub struct B2drConfig {
    /// The diffusers ControlNetModel part (`in_channels` 2 C = 8 for SD1.5, `conditioning_channels` 15).
    pub base: ControlNetConfig,
    pub mask_channels: Vec<String>,
    /// The previous frame's noise level `n` at inference (a training timestep, 0..999).
    pub prev_noise_level: usize,
    /// `N_max` of training's `n ~ U[0, N_max]`.
    pub prev_noise_max: usize,
    pub prev_blur_sigma: f64,
    /// Metres: > 0 warps the previous frame to the current pose over the flat ground, rays capped at this depth
    /// (`render::warp`); 0: no warp.
    pub prev_warp_max_depth: f64,
    /// Where the previous-frame input comes from in a rollout (the closed loop, eval-render's drift).
    pub prev_source: PrevSource,
    pub ref_encoder_channels: Vec<usize>,
    pub ref_attn: Vec<RefAttnAt>,
    pub pe_depth_num: usize,
    pub pe_depth_start: f64,
    pub pe_position_range: [f64; 6],
    pub ref_dropout: f64,
}

/// A ControlNet config as found in a model folder.
#[derive(Clone, Debug, PartialEq)]
pub enum ControlNetKind {
    Plain(ControlNetConfig),
    B2dr(B2drConfig),
}

impl ControlNetKind {
    pub fn from_json(v: Value) -> Result<Self> {
        let is_b2dr = v.get("_class_name").and_then(Value::as_str) == Some(CLASS_NAME);
        Ok(if is_b2dr {
            ControlNetKind::B2dr(B2drConfig::from_json(v)?)
        } else {
            ControlNetKind::Plain(ControlNetConfig::from_json(v)?)
        })
    }

    pub fn from_file(path: &Path) -> Result<Self> {
        let text =
            crate::files::read_regular_string(path, "model config", crate::files::JSON_LIMIT)?;
        let v: Value =
            serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        Self::from_json(v).with_context(|| format!("in {}", path.display()))
    }
}

fn default_mask_channels() -> Vec<String> {
    (0..NUM_MASK_CHANNELS)
        .map(|c| channel_name(c).to_string())
        .collect()
}

/// Removes `key` from `m` (null counts as absent).
fn take(m: &mut Map<String, Value>, key: &str) -> Option<Value> {
    m.remove(key).filter(|v| !v.is_null())
}

fn err(key: &str, v: &Value, what: &str) -> anyhow::Error {
    anyhow::anyhow!("{CLASS_NAME} config: key `{key}` = {v}: {what}")
}

fn take_uint(m: &mut Map<String, Value>, key: &str, default: usize, max: usize) -> Result<usize> {
    match take(m, key) {
        None => Ok(default),
        Some(v) => match v.as_u64() {
            Some(x) if x as usize <= max => Ok(x as usize),
            _ => Err(err(key, &v, &format!("expected an integer in 0..={max}"))),
        },
    }
}

fn take_f64(m: &mut Map<String, Value>, key: &str, default: f64) -> Result<f64> {
    match take(m, key) {
        None => Ok(default),
        Some(v) => v
            .as_f64()
            .filter(|x| x.is_finite())
            .ok_or_else(|| err(key, &v, "expected a finite number")),
    }
}

impl B2drConfig {
    pub fn from_json(v: Value) -> Result<Self> {
        let Value::Object(mut m) = v else {
            bail!("{CLASS_NAME} config: expected a JSON object")
        };
        let mask_channels = match take(&mut m, "mask_channels") {
            None => default_mask_channels(),
            Some(v) => {
                let names: Option<Vec<String>> = v
                    .as_array()
                    .and_then(|a| a.iter().map(|x| x.as_str().map(str::to_string)).collect());
                names.ok_or_else(|| err("mask_channels", &v, "expected a list of strings"))?
            }
        };
        ensure!(
            mask_channels == default_mask_channels(),
            "{CLASS_NAME} config: key `mask_channels` = {mask_channels:?}: b2dr's projection writes the 15 \
             channels {:?} in that order",
            default_mask_channels()
        );
        let prev_noise_level = take_uint(&mut m, "prev_noise_level", 200, 999)?;
        let prev_noise_max = take_uint(&mut m, "prev_noise_max", 400, 999)?;
        let prev_blur_sigma = take_f64(&mut m, "prev_blur_sigma", 1.0)?;
        ensure!(
            prev_blur_sigma > 0.0 && prev_blur_sigma <= 10.0,
            "{CLASS_NAME} config: key `prev_blur_sigma` = {prev_blur_sigma} must be in (0, 10]"
        );
        let prev_warp_max_depth = take_f64(&mut m, "prev_warp_max_depth", 0.0)?;
        ensure!(
            (0.0..=MAX_WARP_DEPTH).contains(&prev_warp_max_depth),
            "{CLASS_NAME} config: key `prev_warp_max_depth` = {prev_warp_max_depth} must be in [0, \
             {MAX_WARP_DEPTH}] metres (0: no warp)"
        );
        let prev_source = match take(&mut m, "prev_source") {
            None => PrevSource::Previous,
            Some(v) => match v.as_str() {
                Some("previous") => PrevSource::Previous,
                Some("reference") => PrevSource::Reference,
                Some("composite") => PrevSource::Composite,
                _ => {
                    return Err(err(
                        "prev_source",
                        &v,
                        "expected \"previous\", \"reference\" or \"composite\"",
                    ))
                }
            },
        };
        ensure!(
            !prev_source.from_references() || prev_warp_max_depth > 0.0,
            "{CLASS_NAME} config: key `prev_source` = \"{}\" needs `prev_warp_max_depth` > 0 (a reference \
             was taken at another pose; unwarped it would not line up with the current frame)",
            prev_source.name()
        );
        let ref_enc = take(&mut m, "ref_encoder_channels");
        let ref_attn_v = take(&mut m, "ref_attn");
        let pe_depth_num = take_uint(&mut m, "pe_depth_num", 64, 4096)?;
        ensure!(
            pe_depth_num > 0,
            "{CLASS_NAME} config: key `pe_depth_num` must be > 0"
        );
        let pe_depth_start = take_f64(&mut m, "pe_depth_start", 1.0)?;
        let pe_position_range = match take(&mut m, "pe_position_range") {
            None => [-61.2, -61.2, -10.0, 61.2, 61.2, 10.0],
            Some(v) => {
                let r: Option<Vec<f64>> = v.as_array().and_then(|a| {
                    a.iter()
                        .map(|x| x.as_f64().filter(|f| f.is_finite()))
                        .collect()
                });
                let r = r
                    .filter(|r| r.len() == 6)
                    .ok_or_else(|| err("pe_position_range", &v, "expected 6 finite numbers"))?;
                ensure!(
                    r[3] > r[0] && r[4] > r[1] && r[5] > r[2],
                    err("pe_position_range", &v, "each max must exceed its min")
                );
                [r[0], r[1], r[2], r[3], r[4], r[5]]
            }
        };
        ensure!(
            pe_depth_start > 0.0 && pe_depth_start < pe_position_range[3],
            "{CLASS_NAME} config: key `pe_depth_start` = {pe_depth_start} must be in (0, x_max)"
        );
        let ref_dropout = take_f64(&mut m, "ref_dropout", 0.2)?;
        ensure!(
            (0.0..=1.0).contains(&ref_dropout),
            "{CLASS_NAME} config: key `ref_dropout` = {ref_dropout} must be in [0, 1]"
        );
        m.insert("_class_name".into(), json!("ControlNetModel"));
        let base = ControlNetConfig::from_json(Value::Object(m))
            .map_err(|e| anyhow::anyhow!("{e}").context(format!("{CLASS_NAME} config")))?;
        ensure!(
            base.enc.in_channels >= 2 && base.enc.in_channels % 2 == 0,
            "{CLASS_NAME} config: key `in_channels` = {} must be twice the latent channels ([x_t, noised \
             previous-frame latent]; 8 for SD1.5's 4-channel VAE)",
            base.enc.in_channels
        );
        ensure!(
            base.conditioning_channels == NUM_MASK_CHANNELS,
            "{CLASS_NAME} config: key `conditioning_channels` = {} must be {NUM_MASK_CHANNELS} (the layout masks)",
            base.conditioning_channels
        );
        ensure!(
            !base.bgr_conditioning,
            "{CLASS_NAME} config: masks are not colour images: controlnet_conditioning_channel_order must be rgb"
        );
        let blocks = base.enc.block_out_channels.len();
        let ref_encoder_channels = match ref_enc {
            None => base.enc.block_out_channels.clone(),
            Some(v) => {
                let l: Option<Vec<usize>> = v
                    .as_array()
                    .and_then(|a| a.iter().map(|x| x.as_u64().map(|x| x as usize)).collect());
                l.ok_or_else(|| err("ref_encoder_channels", &v, "expected a list of integers"))?
            }
        };
        ensure!(
            ref_encoder_channels == base.enc.block_out_channels,
            "{CLASS_NAME} config: key `ref_encoder_channels` = {ref_encoder_channels:?} must equal \
             block_out_channels {:?} (the features are attended at the ControlNet's widths)",
            base.enc.block_out_channels
        );
        let ref_attn = match ref_attn_v {
            None => (0..blocks)
                .map(RefAttnAt::Down)
                .chain([RefAttnAt::Mid])
                .collect(),
            Some(v) => {
                let a = v
                    .as_array()
                    .ok_or_else(|| err("ref_attn", &v, "expected a list of locations"))?;
                let mut out: Vec<RefAttnAt> = vec![];
                for x in a {
                    let s = x.as_str().unwrap_or("");
                    let at = RefAttnAt::parse(s, blocks).ok_or_else(|| {
                        err(
                            "ref_attn",
                            &v,
                            &format!("{x} is not \"down.0\"..\"down.{}\" or \"mid\"", blocks - 1),
                        )
                    })?;
                    ensure!(
                        out.last().is_none_or(|p| p.order() < at.order()),
                        err(
                            "ref_attn",
                            &v,
                            "locations must be distinct and in forward order"
                        )
                    );
                    out.push(at);
                }
                out
            }
        };
        Ok(Self {
            base,
            mask_channels,
            prev_noise_level,
            prev_noise_max,
            prev_blur_sigma,
            prev_warp_max_depth,
            prev_source,
            ref_encoder_channels,
            ref_attn,
            pe_depth_num,
            pe_depth_start,
            pe_position_range,
            ref_dropout,
        })
    }

    pub fn from_file(path: &Path) -> Result<Self> {
        match ControlNetKind::from_file(path)? {
            ControlNetKind::B2dr(c) => Ok(c),
            ControlNetKind::Plain(_) => bail!(
                "{}: a plain ControlNetModel config, not a {CLASS_NAME} (its _class_name)",
                path.display()
            ),
        }
    }

    /// C: the VAE's latent channels (`in_channels` = 2 C: x_t and the previous-frame latent).
    pub fn latent_channels(&self) -> usize {
        self.base.enc.in_channels / 2
    }

    /// A B2D-R ControlNet on a UNet's encoder (in_channels 2 x the UNet's, 15 mask channels), default B2D-R
    /// keys.
    pub fn from_unet(unet: &UNetConfig, embed: Vec<usize>) -> Self {
        let mut base = ControlNetConfig::from_unet(unet, NUM_MASK_CHANNELS, embed);
        base.enc.in_channels = 2 * unet.enc.in_channels;
        let blocks = base.enc.block_out_channels.len();
        Self {
            ref_encoder_channels: base.enc.block_out_channels.clone(),
            base,
            mask_channels: default_mask_channels(),
            prev_noise_level: 200,
            prev_noise_max: 400,
            prev_blur_sigma: 1.0,
            prev_warp_max_depth: 0.0,
            prev_source: PrevSource::Previous,
            ref_attn: (0..blocks)
                .map(RefAttnAt::Down)
                .chain([RefAttnAt::Mid])
                .collect(),
            pe_depth_num: 64,
            pe_depth_start: 1.0,
            pe_position_range: [-61.2, -61.2, -10.0, 61.2, 61.2, 10.0],
            ref_dropout: 0.2,
        }
    }

    /// Channel count and (block index for the head count) of a Ref-Attn location.
    pub fn location_channels(&self, at: RefAttnAt) -> (usize, usize) {
        let c = &self.base.enc.block_out_channels;
        let i = match at {
            RefAttnAt::Down(i) => i,
            RefAttnAt::Mid => c.len() - 1,
        };
        (c[i], i)
    }

    /// Feature size `(h, w)` at a Ref-Attn location for latent `(h0, w0)`: after down block i the map has
    /// been reduced min(i + 1, B - 1) times (`n -> ceil(n / 2)`).
    pub fn location_size(&self, at: RefAttnAt, latent: (usize, usize)) -> (usize, usize) {
        let b = self.base.enc.block_out_channels.len();
        let k = match at {
            RefAttnAt::Down(i) => (i + 1).min(b - 1),
            RefAttnAt::Mid => b - 1,
        };
        let mut s = latent;
        for _ in 0..k {
            s = (s.0.div_ceil(2), s.1.div_ceil(2));
        }
        s
    }

    /// The PETR geometry settings of the position encodings.
    pub fn pe_config(&self) -> crate::projection::pe::PeConfig {
        crate::projection::pe::PeConfig {
            depth_num: self.pe_depth_num,
            depth_start: self.pe_depth_start,
            position_range: self.pe_position_range,
            ..Default::default()
        }
    }

    pub fn to_json(&self) -> Value {
        let mut v = self.base.to_json();
        v["_class_name"] = json!(CLASS_NAME);
        v["mask_channels"] = json!(self.mask_channels);
        v["prev_noise_level"] = json!(self.prev_noise_level);
        v["prev_noise_max"] = json!(self.prev_noise_max);
        v["prev_blur_sigma"] = json!(self.prev_blur_sigma);
        v["prev_warp_max_depth"] = json!(self.prev_warp_max_depth);
        v["prev_source"] = json!(self.prev_source.name());
        v["ref_encoder_channels"] = json!(self.ref_encoder_channels);
        v["ref_attn"] = json!(self.ref_attn.iter().map(|a| a.name()).collect::<Vec<_>>());
        v["pe_depth_num"] = json!(self.pe_depth_num);
        v["pe_depth_start"] = json!(self.pe_depth_start);
        v["pe_position_range"] = json!(self.pe_position_range);
        v["ref_dropout"] = json!(self.ref_dropout);
        v
    }
}
