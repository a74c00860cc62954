//! The model package (`docs/b2dr_controlnet.md` section 5): `b2dr.json`, `unet/`, `controlnet/` (a B2D-R
//! ControlNet), `vae/`, `context.safetensors`; and the built-in model with seeded weights.
use std::path::Path;

use anyhow::{bail, ensure, Context as _, Result};
use serde::{Deserialize, Serialize};

use super::frame::B2drModel;
use crate::nn::b2dr::{expected_b2dr, B2drControlNet};
use crate::nn::b2dr_config::{B2drConfig, ControlNetKind};
use crate::nn::config::{UNetConfig, VaeConfig};
use crate::nn::device::DeviceWeights;
use crate::nn::run::read_component;
use crate::nn::unet::UNet;
use crate::nn::vae::{VaeDecoder, VaeEncoder};
use crate::nn::weights::{expected_unet, expected_vae, FileDType, HostTensor, Weights};
use crate::sampling::PredictionType;
use crate::tensor::DType;
use crate::vk::Context;

/// `b2dr.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PackageMeta {
    pub format: String,
    pub version: u32,
    /// [H, W]
    pub render_size: [usize; 2],
    pub cameras: Vec<String>,
    pub sampler: String,
    pub steps: usize,
    pub ref_guidance: f64,
    /// Storage dtype of the weights (f32 or f16).
    pub dtype: String,
    /// What the UNet predicts: "epsilon" or "v_prediction" (diffusers' `prediction_type`); absent in packages
    /// written before it existed, which predict epsilon.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prediction_type: Option<String>,
    /// What the sampled latent is added to before the decode: "none" (absent) or "prev", the previous frame's
    /// clean blurred latent (a model that diffuses the residual against it; docs/training.md session 28).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x0_base: Option<String>,
}

impl PackageMeta {
    pub fn check(&self, where_: &str) -> Result<()> {
        ensure!(
            self.format == "b2dr-model" && self.version == 1,
            "{where_}: format {:?} version {}, expected \"b2dr-model\" version 1",
            self.format,
            self.version
        );
        let [h, w] = self.render_size;
        ensure!(
            h >= 8 && w >= 8 && h % 8 == 0 && w % 8 == 0 && h <= 4096 && w <= 4096,
            "{where_}: render_size [{h}, {w}] must be multiples of 8 in 8..=4096"
        );
        ensure!(
            !self.cameras.is_empty()
                && self.cameras.len() <= 64
                && (1..self.cameras.len()).all(|i| !self.cameras[..i].contains(&self.cameras[i])),
            "{where_}: cameras must be 1 to 64 distinct names"
        );
        ensure!(
            self.sampler == "unipc" || self.sampler == "ddim",
            "{where_}: sampler {:?} (unipc or ddim)",
            self.sampler
        );
        ensure!(
            (1..=1000).contains(&self.steps),
            "{where_}: steps {} must be in 1..=1000",
            self.steps
        );
        ensure!(
            self.ref_guidance.is_finite() && self.ref_guidance > 0.0 && self.ref_guidance <= 100.0,
            "{where_}: ref_guidance {} must be in (0, 100]",
            self.ref_guidance
        );
        ensure!(
            self.dtype == "f32" || self.dtype == "f16",
            "{where_}: dtype {:?} (f32 or f16)",
            self.dtype
        );
        ensure!(
            matches!(
                self.prediction_type.as_deref(),
                None | Some("epsilon") | Some("v_prediction")
            ),
            "{where_}: prediction_type {:?} (epsilon or v_prediction)",
            self.prediction_type.as_deref().unwrap_or_default()
        );
        ensure!(
            matches!(self.x0_base.as_deref(), None | Some("none") | Some("prev")),
            "{where_}: x0_base {:?} (none or prev)",
            self.x0_base.as_deref().unwrap_or_default()
        );
        Ok(())
    }

    /// Whether the model diffuses the residual against the previous frame's latent (`check` has accepted it).
    pub fn x0_base_prev(&self) -> bool {
        self.x0_base.as_deref() == Some("prev")
    }

    /// The sampler's reading of the model output (`check` has accepted the value).
    pub fn prediction(&self) -> PredictionType {
        match self.prediction_type.as_deref() {
            Some("v_prediction") => PredictionType::VPrediction,
            _ => PredictionType::Epsilon,
        }
    }
}

/// A model package on the host.
#[derive(Clone, Debug)]
pub struct ModelPackage {
    pub meta: PackageMeta,
    pub unet_cfg: UNetConfig,
    pub unet: Weights,
    pub control_cfg: B2drConfig,
    pub control: Weights,
    pub vae_cfg: VaeConfig,
    pub vae: Weights,
    /// "cond": (77, D) (all cameras) or (n_cameras, 77, D) (one per camera of `meta.cameras`).
    pub context: HostTensor,
    /// Where it came from (a folder, or `builtin:NAME`).
    pub source: String,
}

/// The built-in model names. `b2dr-nano` is the model trained here (python/b2dr_ref/nano.py; its trained
/// package, when committed, is `models/b2dr-nano/` of the repository); `b2dr-tiny` is b2dr-tiny's UNet with a
/// B2D-R ControlNet, seeded random weights (timing).
pub const BUILTIN: &[&str] = &["b2dr-nano", "b2dr-tiny"];

/// The default built-in model.
pub const DEFAULT_MODEL: &str = "b2dr-nano";

/// The environment variable naming a folder that holds the built-in packages (`$B2DR_MODELS/b2dr-nano`).
pub const MODELS_ENV: &str = "B2DR_MODELS";

/// Where the built-in package `name` may live, in the order searched: `$B2DR_MODELS/NAME` when the variable is
/// set (then nothing else: an explicit setting is not second-guessed); else `models/NAME` of the source tree the
/// binary was built from, then, for an installed or copied binary, `<exe dir>/../share/b2dr/models/NAME` and
/// `<exe dir>/models/NAME`.
pub fn builtin_candidates(
    name: &str,
    env: Option<&std::ffi::OsStr>,
    exe: Option<&Path>,
    source_tree: &Path,
) -> Vec<std::path::PathBuf> {
    if let Some(e) = env.filter(|e| !e.is_empty()) {
        return vec![Path::new(e).join(name)];
    }
    let mut v = vec![source_tree.join("models").join(name)];
    if let Some(dir) = exe.and_then(|e| e.parent()) {
        v.push(dir.join("../share/b2dr/models").join(name));
        v.push(dir.join("models").join(name));
    }
    v
}

/// The folders searched for the trained b2dr-nano package (see [`builtin_candidates`]).
fn nano_candidates() -> Vec<std::path::PathBuf> {
    builtin_candidates(
        "b2dr-nano",
        std::env::var_os(MODELS_ENV).as_deref(),
        std::env::current_exe().ok().as_deref(),
        Path::new(env!("CARGO_MANIFEST_DIR")),
    )
}

/// The trained b2dr-nano package: the first candidate that holds one, else the first candidate (the loader then
/// names what was searched).
pub fn nano_dir() -> std::path::PathBuf {
    let c = nano_candidates();
    c.iter()
        .find(|d| d.join("b2dr.json").is_file())
        .unwrap_or(&c[0])
        .clone()
}

/// The model of `--model`: a folder, `builtin:NAME`, or (None) the default built-in model.
pub fn resolve_model(spec: Option<&Path>) -> Result<ModelPackage> {
    match spec
        .and_then(|p| p.to_str())
        .and_then(|s| s.strip_prefix("builtin:"))
    {
        Some(name) => ModelPackage::builtin(name),
        None => match spec {
            Some(d) => ModelPackage::load(d),
            None => ModelPackage::builtin(DEFAULT_MODEL),
        },
    }
}

/// The files of the model package a `--model` spec names (as [`resolve_model`] reads it), for `--resume`'s
/// fingerprints: every regular file of the folder and its component folders (sorted); a built-in model: its committed folder when it has
/// one (b2dr-nano), else none (seeded weights, a pure function of the binary).
pub fn package_files(spec: Option<&Path>) -> Result<Vec<std::path::PathBuf>> {
    let dir = match spec
        .and_then(|p| p.to_str())
        .and_then(|s| s.strip_prefix("builtin:"))
    {
        Some("b2dr-nano") => nano_dir(),
        Some(_) => return Ok(vec![]),
        None => match spec {
            Some(d) => d.to_path_buf(),
            None if DEFAULT_MODEL == "b2dr-nano" => nano_dir(),
            None => return Ok(vec![]),
        },
    };
    if !dir.is_dir() {
        // a missing folder is the loader's error to name; a built-in without its folder has none
        return Ok(vec![]);
    }
    let mut out = vec![];
    // a package is the folder and its component folders (unet/, controlnet/, vae/): two levels
    let mut stack = vec![(dir, 0)];
    while let Some((d, depth)) = stack.pop() {
        for e in std::fs::read_dir(&d)
            .with_context(|| format!("listing the model package {}", d.display()))?
            .flatten()
        {
            let p = e.path();
            if p.is_file() {
                out.push(p);
            } else if p.is_dir() && depth < 2 {
                stack.push((p, depth + 1));
            }
        }
    }
    out.sort();
    Ok(out)
}

impl ModelPackage {
    /// Reads a package folder; every error names the file.
    pub fn load(dir: &Path) -> Result<Self> {
        ensure!(
            dir.is_dir(),
            "--model {}: not a folder (a model package holds b2dr.json, unet/, controlnet/, vae/, \
             context.safetensors)",
            dir.display()
        );
        let mp = dir.join("b2dr.json");
        let text = crate::files::read_regular_string(&mp, "model file", crate::files::JSON_LIMIT)?;
        let meta: PackageMeta =
            serde_json::from_str(&text).with_context(|| format!("{}: invalid", mp.display()))?;
        meta.check(&mp.display().to_string())?;
        let comp = |name: &str| -> Result<(serde_json::Value, std::path::PathBuf)> {
            read_component(&dir.join(name))
        };
        let (uj, uw) = comp("unet")?;
        let unet_cfg = UNetConfig::from_json(uj)
            .with_context(|| format!("in {}", dir.join("unet/config.json").display()))?;
        let unet = Weights::load(&uw, &expected_unet(&unet_cfg))?;
        let cpath = dir.join("controlnet/config.json");
        let control_cfg = match ControlNetKind::from_file(&cpath)? {
            ControlNetKind::B2dr(c) => c,
            ControlNetKind::Plain(_) => bail!(
                "{}: a plain ControlNetModel; the renderer needs a B2DRControlNetModel (15 mask channels, \
                 8-channel conv_in, references)",
                cpath.display()
            ),
        };
        let control = Weights::load(
            &dir.join("controlnet/diffusion_pytorch_model.safetensors"),
            &expected_b2dr(&control_cfg),
        )?;
        let (vj, vw) = comp("vae")?;
        let vae_cfg = VaeConfig::from_json(vj)
            .with_context(|| format!("in {}", dir.join("vae/config.json").display()))?;
        let vae = Weights::load(&vw, &expected_vae(&vae_cfg))?;
        let xp = dir.join("context.safetensors");
        let xw = Weights::from_bytes_unchecked(
            &crate::files::read_regular(&xp, "text context", crate::files::CONTEXT_LIMIT)?,
            &xp.display().to_string(),
        )?;
        ensure!(
            xw.tensors.len() == 1 && xw.tensors.contains_key("cond"),
            "{}: tensors {:?}, expected only `cond`",
            xp.display(),
            xw.tensors.keys().collect::<Vec<_>>()
        );
        let context = xw.get("cond")?.clone();
        let p = Self {
            meta,
            unet_cfg,
            unet,
            control_cfg,
            control,
            vae_cfg,
            vae,
            context,
            source: dir.display().to_string(),
        };
        p.check()
            .with_context(|| format!("model package {}", dir.display()))?;
        Ok(p)
    }

    /// Consistency of the parts with each other.
    pub fn check(&self) -> Result<()> {
        let d = self.unet_cfg.enc.cross_attention_dim;
        let s = &self.context.shape;
        let ok = (s.len() == 2 && s[1] == d && s[0] >= 1)
            || (s.len() == 3 && s[0] == self.meta.cameras.len() && s[2] == d && s[1] >= 1);
        ensure!(
            ok,
            "context.safetensors: cond {s:?} must be (L, {d}) or ({}, L, {d}) (one per camera)",
            self.meta.cameras.len()
        );
        ensure!(
            self.context.data.iter().all(|v| v.is_finite()),
            "context.safetensors: cond holds NaN or infinite values"
        );
        let (ue, ce) = (&self.unet_cfg.enc, &self.control_cfg.base.enc);
        ensure!(
            ue.block_out_channels == ce.block_out_channels
                && ue.layers_per_block == ce.layers_per_block
                && ue.down_blocks == ce.down_blocks
                && ue.cross_attention_dim == ce.cross_attention_dim,
            "controlnet/config.json: its encoder (blocks {:?}, layers {}, cross-attention {}) does not match the \
             UNet's ({:?}, {}, {})",
            ce.block_out_channels,
            ce.layers_per_block,
            ce.cross_attention_dim,
            ue.block_out_channels,
            ue.layers_per_block,
            ue.cross_attention_dim
        );
        // the UNet denoises the VAE's latent; the ControlNet reads [x_t, z_prev]: twice that
        let lc = self.vae_cfg.latent_channels;
        ensure!(
            lc >= 1 && ue.in_channels == lc && self.unet_cfg.out_channels == lc,
            "unet/config.json: in_channels {} and out_channels {} must be the VAE's {lc} latent channels",
            ue.in_channels,
            self.unet_cfg.out_channels
        );
        ensure!(
            ce.in_channels == 2 * lc,
            "controlnet/config.json: in_channels {} must be {} (x_t and the previous-frame latent, {lc} channels \
             each)",
            ce.in_channels,
            2 * lc
        );
        ensure!(
            self.vae_cfg.block_out_channels.len() == 4,
            "vae/config.json: {} blocks: the renderer needs a VAE that downsamples by 8 (4 blocks)",
            self.vae_cfg.block_out_channels.len()
        );
        for (what, w) in [
            ("unet", &self.unet),
            ("controlnet", &self.control),
            ("vae", &self.vae),
        ] {
            if let Some((n, _)) = w
                .tensors
                .iter()
                .find(|(_, t)| t.data.iter().any(|v| !v.is_finite()))
            {
                bail!("{what}/diffusion_pytorch_model.safetensors: tensor `{n}` holds NaN or infinite values");
            }
        }
        Ok(())
    }

    /// The built-in model `name`: b2dr-nano, the trained package committed in the repository (an error when the
    /// binary's source tree no longer has it); b2dr-tiny, seeded random weights (an untrained renderer for tests
    /// and timing).
    pub fn builtin(name: &str) -> Result<Self> {
        match name {
            "b2dr-nano" => Self::trained_nano(&nano_candidates()),
            "b2dr-tiny" => {
                let u = UNetConfig::b2dr_tiny();
                let c = B2drConfig::from_unet(&u, vec![16, 32, 96, 256]);
                Self::seeded(
                    u,
                    c,
                    VaeConfig::b2dr_tiny(),
                    false,
                    "builtin:b2dr-tiny (seeded random weights)",
                )
            }
            other => bail!("unknown built-in model {other:?} (built-in: {BUILTIN:?})"),
        }
    }

    /// b2dr-nano from the first of `candidates` that holds its trained package. When none does (the source tree
    /// moved or was deleted, an installed binary without its share folder), refuse: falling back to seeded
    /// weights drew noise silently (a release binary built from a since-deleted clone did exactly that in a
    /// closed-loop table).
    fn trained_nano(candidates: &[std::path::PathBuf]) -> Result<Self> {
        let Some(dir) = candidates.iter().find(|d| d.join("b2dr.json").is_file()) else {
            let list: Vec<String> = candidates.iter().map(|d| d.display().to_string()).collect();
            bail!(
                "the built-in model b2dr-nano is a trained package (models/b2dr-nano of the repository), and it \
                 is not there; searched: {}. Pass --model path/to/models/b2dr-nano, set {MODELS_ENV} to the \
                 folder holding b2dr-nano, copy it to <install prefix>/share/b2dr/models/, or rebuild b2dr in \
                 the repository",
                list.join(", ")
            );
        };
        let mut p = Self::load(dir)?;
        p.source = format!("builtin:b2dr-nano (trained, {})", dir.display());
        Ok(p)
    }

    /// A package of seeded random weights (unet 1, controlnet 4, vae 3, context 77) at 112 x 200 for the
    /// nuScenes-like rig; `per_camera` gives each camera its own context.
    fn seeded(
        unet_cfg: UNetConfig,
        control_cfg: B2drConfig,
        vae_cfg: VaeConfig,
        per_camera: bool,
        source: &str,
    ) -> Result<Self> {
        let cameras: Vec<String> = crate::scene::import::nuscenes_like_cameras()
            .into_iter()
            .map(|c| c.name)
            .collect();
        let d = unet_cfg.enc.cross_attention_dim;
        let shape = if per_camera {
            vec![cameras.len(), 77, d]
        } else {
            vec![77, d]
        };
        let ctxw = Weights::random(&[("cond".to_string(), shape)], 77);
        Ok(Self {
            meta: PackageMeta {
                format: "b2dr-model".into(),
                version: 1,
                render_size: [112, 200],
                cameras,
                sampler: "unipc".into(),
                steps: 20,
                ref_guidance: 2.0,
                dtype: "f32".into(),
                prediction_type: None,
                x0_base: None,
            },
            unet: Weights::random(&expected_unet(&unet_cfg), 1),
            control: Weights::random(&expected_b2dr(&control_cfg), 4),
            vae: Weights::random(&expected_vae(&vae_cfg), 3),
            context: ctxw.get("cond")?.clone(),
            unet_cfg,
            control_cfg,
            vae_cfg,
            source: source.into(),
        })
    }

    /// Writes the package folder (weights in `dtype`).
    pub fn save(&self, dir: &Path, dtype: FileDType) -> Result<()> {
        let write_json = |p: &Path, v: &serde_json::Value| -> Result<()> {
            std::fs::write(p, serde_json::to_string_pretty(v)?)
                .with_context(|| format!("writing {}", p.display()))
        };
        for (name, cfg, w) in [
            ("unet", self.unet_cfg.to_json(), &self.unet),
            ("controlnet", self.control_cfg.to_json(), &self.control),
            ("vae", self.vae_cfg.to_json(), &self.vae),
        ] {
            let d = dir.join(name);
            std::fs::create_dir_all(&d).with_context(|| format!("creating {}", d.display()))?;
            write_json(&d.join("config.json"), &cfg)?;
            w.save(&d.join("diffusion_pytorch_model.safetensors"), dtype)?;
        }
        let mut meta = self.meta.clone();
        meta.dtype = match dtype {
            FileDType::F16 => "f16".into(),
            _ => "f32".into(),
        };
        write_json(&dir.join("b2dr.json"), &serde_json::to_value(&meta)?)?;
        let mut c = Weights::default();
        c.tensors.insert("cond".into(), self.context.clone());
        c.save(&dir.join("context.safetensors"), dtype)
    }

    /// The context rows of `cameras` (N, L, D): the shared embedding repeated, or each camera's own.
    pub fn context_for(&self, cameras: &[String]) -> Result<Vec<f32>> {
        let s = &self.context.shape;
        let mut out = vec![];
        for c in cameras {
            if s.len() == 2 {
                out.extend_from_slice(&self.context.data);
            } else {
                let i = self
                    .meta
                    .cameras
                    .iter()
                    .position(|m| m == c)
                    .with_context(|| {
                        format!(
                            "camera {c:?} is not one the model was trained for ({:?}): its context is per camera",
                            self.meta.cameras
                        )
                    })?;
                let per = s[1] * s[2];
                out.extend_from_slice(&self.context.data[i * per..(i + 1) * per]);
            }
        }
        Ok(out)
    }
}

/// A package's modules on the device.
pub struct DeviceModel {
    pub unet: UNet,
    pub control: B2drControlNet,
    pub vae_encoder: VaeEncoder,
    pub vae_decoder: VaeDecoder,
    pub scaling_factor: f64,
    pub dtype: DType,
    /// b2dr.json `x0_base` "prev" (`PackageMeta::x0_base_prev`).
    pub x0_base_prev: bool,
    /// Device bytes of the weights.
    pub weight_bytes: u64,
    _weights: Vec<DeviceWeights>,
}

impl DeviceModel {
    /// Uploads a package: UNet and ControlNet in `dtype`, the VAE in f32.
    pub fn upload(ctx: &Context, p: &ModelPackage, dtype: DType) -> Result<Self> {
        let u = DeviceWeights::upload(ctx, &p.unet, "", dtype)?;
        let c = DeviceWeights::upload(ctx, &p.control, "", dtype)?;
        let v = DeviceWeights::upload(ctx, &p.vae, "", DType::F32)?;
        let m = Self {
            unet: UNet::load(&u, &p.unet_cfg).context("unet")?,
            control: B2drControlNet::load(&c, &p.control_cfg).context("controlnet")?,
            vae_encoder: VaeEncoder::load(&v, &p.vae_cfg).context("vae encoder")?,
            vae_decoder: VaeDecoder::load(&v, &p.vae_cfg).context("vae decoder")?,
            scaling_factor: p.vae_cfg.scaling_factor,
            dtype,
            x0_base_prev: p.meta.x0_base_prev(),
            weight_bytes: u.bytes() + c.bytes() + v.bytes(),
            _weights: vec![u, c, v],
        };
        Ok(m)
    }

    pub fn as_model(&self) -> B2drModel<'_> {
        B2drModel {
            unet: &self.unet,
            control: &self.control,
            vae_encoder: &self.vae_encoder,
            vae_decoder: &self.vae_decoder,
            scaling_factor: self.scaling_factor,
            dtype: self.dtype,
            x0_base_prev: self.x0_base_prev,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::job::sampler_plan;

    fn meta(extra: &str) -> Result<PackageMeta> {
        let text = format!(
            r#"{{"format": "b2dr-model", "version": 1, "render_size": [112, 200], "cameras": ["CAM_FRONT"],
                "sampler": "unipc", "steps": 20, "ref_guidance": 2.0, "dtype": "f16"{extra}}}"#
        );
        let m: PackageMeta = serde_json::from_str(&text)?;
        m.check("b2dr.json")?;
        Ok(m)
    }

    #[test]
    fn x0_base_is_read_and_checked() {
        assert!(!meta("").unwrap().x0_base_prev());
        assert!(!meta(r#", "x0_base": "none""#).unwrap().x0_base_prev());
        assert!(meta(r#", "x0_base": "prev""#).unwrap().x0_base_prev());
        let err = meta(r#", "x0_base": "next""#).unwrap_err().to_string();
        assert!(err.contains("x0_base \"next\" (none or prev)"), "{err}");
    }

    #[test]
    fn prediction_type_reaches_the_sampler() {
        // absent (packages written before the key) and "epsilon" predict epsilon
        assert_eq!(meta("").unwrap().prediction(), PredictionType::Epsilon);
        let eps = meta(r#", "prediction_type": "epsilon""#).unwrap();
        assert_eq!(eps.prediction(), PredictionType::Epsilon);
        let v = meta(r#", "prediction_type": "v_prediction""#).unwrap();
        assert_eq!(v.prediction(), PredictionType::VPrediction);
        let err = meta(r#", "prediction_type": "sample""#)
            .unwrap_err()
            .to_string();
        assert!(err.contains("prediction_type \"sample\""), "{err}");
        // the plans differ exactly where the model output becomes x0
        for s in ["unipc", "ddim"] {
            let pe = sampler_plan(s, 4, eps.prediction()).unwrap();
            let pv = sampler_plan(s, 4, v.prediction()).unwrap();
            assert_eq!(pe.steps.len(), pv.steps.len());
            assert_ne!(format!("{:?}", pe.steps), format!("{:?}", pv.steps), "{s}");
        }
        // a meta written with the key round-trips; one without it is written without it
        let text = serde_json::to_string(&v).unwrap();
        assert!(text.contains("\"prediction_type\":\"v_prediction\""));
        assert!(!serde_json::to_string(&eps.clone())
            .unwrap()
            .contains("null"));
    }

    #[test]
    fn builtin_packages_are_searched_in_the_source_tree_then_beside_the_binary() {
        let (src, exe) = (Path::new("/src"), Path::new("/opt/b2dr/bin/b2dr"));
        let c = builtin_candidates("b2dr-nano", None, Some(exe), src);
        assert_eq!(
            c,
            vec![
                Path::new("/src/models/b2dr-nano").to_path_buf(),
                Path::new("/opt/b2dr/bin/../share/b2dr/models/b2dr-nano").to_path_buf(),
                Path::new("/opt/b2dr/bin/models/b2dr-nano").to_path_buf(),
            ]
        );
        // an explicit B2DR_MODELS is the only place searched; an empty one is unset
        let env = std::ffi::OsStr::new("/data/models");
        assert_eq!(
            builtin_candidates("b2dr-nano", Some(env), Some(exe), src),
            vec![Path::new("/data/models/b2dr-nano").to_path_buf()]
        );
        let empty = std::ffi::OsStr::new("");
        assert_eq!(
            builtin_candidates("b2dr-nano", Some(empty), Some(exe), src),
            c
        );
        // a copy of the package beside an installed binary is found when the source tree is gone
        let root = std::env::temp_dir().join(format!("b2dr-prefix-{}", std::process::id()));
        let share = root.join("share/b2dr/models/b2dr-nano");
        std::fs::create_dir_all(root.join("bin")).unwrap(); // the binary's folder (`bin/..` needs it)
        copy_dir(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("models/b2dr-nano"),
            &share,
        );
        let c = builtin_candidates(
            "b2dr-nano",
            None,
            Some(&root.join("bin/b2dr")),
            &root.join("gone"),
        );
        let p = ModelPackage::trained_nano(&c).unwrap();
        assert!(
            p.source.contains("share/b2dr/models/b2dr-nano"),
            "{}",
            p.source
        );
        std::fs::remove_dir_all(&root).unwrap();
    }

    fn copy_dir(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap() {
            let e = e.unwrap();
            let t = to.join(e.file_name());
            if e.file_type().unwrap().is_dir() {
                copy_dir(&e.path(), &t);
            } else {
                std::fs::copy(e.path(), t).unwrap();
            }
        }
    }

    #[test]
    fn builtin_nano_without_its_package_is_an_error_not_noise() {
        let gone = std::env::temp_dir().join("b2dr-no-such-source-tree");
        let exe = std::env::temp_dir().join("b2dr-no-such-prefix/bin/b2dr");
        let c = builtin_candidates("b2dr-nano", None, Some(&exe), &gone);
        let err = ModelPackage::trained_nano(&c).unwrap_err().to_string();
        assert!(
            err.contains("not there") && err.contains("--model") && err.contains(MODELS_ENV),
            "{err}"
        );
        assert!(err.contains("b2dr-no-such-source-tree"), "{err}");
        assert!(
            err.contains("b2dr-no-such-prefix/bin/../share/b2dr/models/b2dr-nano"),
            "{err}"
        );
        // the repository's own package loads as the built-in (it is committed)
        let p = ModelPackage::builtin("b2dr-nano").unwrap();
        assert!(
            p.source.starts_with("builtin:b2dr-nano (trained"),
            "{}",
            p.source
        );
    }
}
