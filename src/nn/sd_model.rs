//! A diffusers Stable Diffusion family model as `b2dr sample` reads it: a UNet, an optional ControlNet, a VAE and
//! the fixed text embedding, on the host ([`SdModel`]), then uploaded ([`SdDevice`]) and assembled into the
//! layers a [`crate::nn::pipeline::Pipeline`] runs.
//!
//! Folder layout (diffusers): `unet/`, optional `controlnet/`, `vae/` (each `config.json` +
//! `diffusion_pytorch_model.safetensors`), `context.safetensors` with `cond` and optional `uncond` (77, D)
//! (a missing `uncond` is zeros). The built-in `b2dr-tiny` has seeded random weights (seeds 1, 2, 3 and 77 for
//! the embedding, as in the goldens).
use std::path::Path;

use anyhow::{Context as _, Result};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

use super::config::{ControlNetConfig, UNetConfig, VaeConfig};
use super::controlnet::ControlNet;
use super::device::DeviceWeights;
use super::run::read_component;
use super::unet::UNet;
use super::vae::VaeDecoder;
use super::weights::{self, Weights};
use crate::tensor::DType;
use crate::vk::Context;

/// A model on the host.
pub struct SdModel {
    pub unet_cfg: UNetConfig,
    pub unet: Weights,
    pub control: Option<(ControlNetConfig, Weights)>,
    pub vae_cfg: VaeConfig,
    pub vae: Weights,
    /// The unconditional embedding (77, D).
    pub uncond: Vec<f32>,
    /// The conditional embedding (77, D).
    pub cond: Vec<f32>,
    /// Where it came from (a folder, or `builtin:b2dr-tiny ...`).
    pub source: String,
}

fn component(
    dir: &Path,
    expected: impl Fn(&serde_json::Value) -> Result<Vec<weights::Spec>>,
) -> Result<(serde_json::Value, Weights)> {
    let (cfg, wpath) = read_component(dir)?;
    let w = Weights::load(&wpath, &expected(&cfg)?)?;
    Ok((cfg, w))
}

/// The VAE of a model folder downsamples by 8 (checked before any weights are read or a device is made: a VAE
/// of another factor would decode images of another size than the one asked for).
pub fn check_vae_folder(dir: &Path) -> Result<()> {
    let vdir = dir.join("vae");
    let (vcj, _) = read_component(&vdir)?;
    let what = vdir.join("config.json").display().to_string();
    VaeConfig::from_json(vcj)
        .with_context(|| what.clone())?
        .check_factor_8(&what)
}

impl SdModel {
    /// Reads a diffusers model folder (see the module docs).
    pub fn load(dir: &Path) -> Result<Self> {
        check_vae_folder(dir)?;
        let (ucj, unet) = component(&dir.join("unet"), |c| {
            Ok(weights::expected_unet(&UNetConfig::from_json(c.clone())?))
        })?;
        let control = if dir.join("controlnet").exists() {
            let (cj, w) = component(&dir.join("controlnet"), |c| {
                Ok(weights::expected_controlnet(&ControlNetConfig::from_json(
                    c.clone(),
                )?))
            })?;
            Some((ControlNetConfig::from_json(cj)?, w))
        } else {
            None
        };
        let (vcj, vae) = component(&dir.join("vae"), |c| {
            Ok(weights::expected_vae(&VaeConfig::from_json(c.clone())?))
        })?;
        let cpath = dir.join("context.safetensors");
        let ctxw = Weights::from_bytes_unchecked(
            &crate::files::read_regular(&cpath, "text context", crate::files::CONTEXT_LIMIT)?,
            &cpath.display().to_string(),
        )?;
        let cond = ctxw.get("cond")?.data.clone();
        let uncond = ctxw
            .get("uncond")
            .map(|t| t.data.clone())
            .unwrap_or_else(|_| vec![0.0; cond.len()]);
        Ok(Self {
            unet_cfg: UNetConfig::from_json(ucj)?,
            unet,
            control,
            vae_cfg: VaeConfig::from_json(vcj)?,
            vae,
            uncond,
            cond,
            source: dir.display().to_string(),
        })
    }

    /// The built-in b2dr-tiny with seeded random weights.
    pub fn seeded_tiny() -> Self {
        let (uc, cc, vc) = (
            UNetConfig::b2dr_tiny(),
            ControlNetConfig::b2dr_tiny(),
            VaeConfig::b2dr_tiny(),
        );
        let unet = Weights::random(&weights::expected_unet(&uc), 1);
        let cw = Weights::random(&weights::expected_controlnet(&cc), 2);
        let vae = Weights::random(&weights::expected_vae(&vc), 3);
        let d = uc.enc.cross_attention_dim;
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(77);
        let cond: Vec<f32> = (0..77 * d).map(|_| StandardNormal.sample(&mut r)).collect();
        Self {
            unet_cfg: uc,
            unet,
            control: Some((cc, cw)),
            vae_cfg: vc,
            vae,
            uncond: vec![0.0; 77 * d],
            cond,
            source: "builtin:b2dr-tiny (seeded random weights)".into(),
        }
    }

    /// Writes the model as a diffusers folder that [`SdModel::load`] reads back (weights in `dtype`).
    pub fn save(&self, dir: &Path, dtype: weights::FileDType) -> Result<()> {
        let mut parts = vec![
            ("unet", self.unet_cfg.to_json(), &self.unet),
            ("vae", self.vae_cfg.to_json(), &self.vae),
        ];
        if let Some((c, w)) = &self.control {
            parts.push(("controlnet", c.to_json(), w));
        }
        for (name, cfg, w) in parts {
            let d = dir.join(name);
            std::fs::create_dir_all(&d).with_context(|| format!("creating {}", d.display()))?;
            std::fs::write(d.join("config.json"), serde_json::to_string_pretty(&cfg)?)
                .with_context(|| format!("writing {}/config.json", d.display()))?;
            w.save(&d.join("diffusion_pytorch_model.safetensors"), dtype)?;
        }
        let tensor = |v: &Vec<f32>| weights::HostTensor {
            shape: vec![77, v.len() / 77],
            data: v.clone(),
            file_dtype: weights::FileDType::F32,
        };
        let ctx = Weights {
            tensors: [
                ("cond".to_string(), tensor(&self.cond)),
                ("uncond".to_string(), tensor(&self.uncond)),
            ]
            .into(),
        };
        ctx.save(&dir.join("context.safetensors"), weights::FileDType::F32)
    }

    /// `--model DIR` or the built-in b2dr-tiny.
    pub fn resolve(dir: Option<&Path>) -> Result<Self> {
        match dir {
            Some(d) => Self::load(d),
            None => Ok(Self::seeded_tiny()),
        }
    }
}

/// A model's weights on the device: the UNet and ControlNet in `dtype`, the VAE in f32.
pub struct SdDevice {
    pub unet: DeviceWeights,
    pub control: Option<DeviceWeights>,
    pub vae: DeviceWeights,
}

/// The layers of an uploaded model.
pub struct SdLayers {
    pub unet: UNet,
    pub control: Option<ControlNet>,
    pub vae: VaeDecoder,
}

impl SdDevice {
    pub fn upload(ctx: &Context, m: &SdModel, dtype: DType) -> Result<Self> {
        Ok(Self {
            unet: DeviceWeights::upload(ctx, &m.unet, "", dtype)?,
            control: m
                .control
                .as_ref()
                .map(|(_, w)| DeviceWeights::upload(ctx, w, "", dtype))
                .transpose()?,
            vae: DeviceWeights::upload(ctx, &m.vae, "", DType::F32)?,
        })
    }

    /// The layers of `m` (the configs this was uploaded from) over these weights.
    pub fn layers(&self, m: &SdModel) -> Result<SdLayers> {
        Ok(SdLayers {
            unet: UNet::load(&self.unet, &m.unet_cfg)?,
            control: match (&m.control, &self.control) {
                (Some((c, _)), Some(d)) => Some(ControlNet::load(d, c)?),
                _ => None,
            },
            vae: VaeDecoder::load(&self.vae, &m.vae_cfg)?,
        })
    }
}
