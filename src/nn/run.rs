//! Loading whole components (diffusers folder layout or the built-in b2dr-tiny) and running one component on
//! named host tensors (`b2dr forward`).
use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, ensure, Context as _, Result};

use super::config::{ControlNetConfig, UNetConfig, VaeConfig};
use super::controlnet::ControlNet;
use super::device::{DeviceWeights, Fwd, Workspace};
use super::unet::{Residuals, UNet};
use super::vae::{VaeDecoder, VaeEncoder};
use super::weights::{self, FileDType, HostTensor, Weights};
use crate::tensor::{DType, Tensor};
use crate::vk::Context;

/// A component kind of `b2dr forward`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Component {
    Unet,
    ControlNet,
    VaeEncoder,
    VaeDecoder,
}

impl Component {
    /// The name `--component` takes.
    pub fn name(self) -> &'static str {
        match self {
            Self::Unet => "unet",
            Self::ControlNet => "controlnet",
            Self::VaeEncoder => "vae-encoder",
            Self::VaeDecoder => "vae-decoder",
        }
    }
}

impl std::str::FromStr for Component {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "unet" => Self::Unet,
            "controlnet" => Self::ControlNet,
            "vae-encoder" => Self::VaeEncoder,
            "vae-decoder" => Self::VaeDecoder,
            _ => bail!("unknown component {s:?} (unet, controlnet, vae-encoder, vae-decoder)"),
        })
    }
}

fn up(
    ctx: &Context,
    inputs: &BTreeMap<String, HostTensor>,
    name: &str,
    dtype: DType,
) -> Result<Tensor> {
    let h = inputs
        .get(name)
        .with_context(|| format!("input tensor {name:?} is missing"))?;
    Tensor::from_f32(ctx, &h.shape, dtype, &h.data, name)
}

fn down(ctx: &Context, t: &Tensor) -> Result<HostTensor> {
    Ok(HostTensor {
        shape: t.shape().to_vec(),
        data: t.to_f32(ctx)?,
        file_dtype: FileDType::F32,
    })
}

/// The timestep input: a scalar or one value per sample, as f32 (N).
fn timestep(ctx: &Context, inputs: &BTreeMap<String, HostTensor>, n: usize) -> Result<Tensor> {
    let t = inputs
        .get("timestep")
        .context("input tensor \"timestep\" is missing")?;
    let v = match t.data.len() {
        1 => vec![t.data[0]; n],
        k if k == n => t.data.clone(),
        k => bail!("timestep has {k} values; expected 1 or the batch size {n}"),
    };
    Tensor::from_f32(ctx, &[n], DType::F32, &v, "timestep")
}

/// Runs one component; input and output names are documented in the README (`b2dr forward`).
pub fn forward_component(
    ctx: &Context,
    comp: Component,
    config: serde_json::Value,
    w: &Weights,
    inputs: &BTreeMap<String, HostTensor>,
    dtype: DType,
) -> Result<BTreeMap<String, HostTensor>> {
    let mut ws = Workspace::new(ctx, dtype);
    let mut rec = ctx.recorder()?;
    let mut out = BTreeMap::new();
    match comp {
        Component::Unet => {
            let cfg = UNetConfig::from_json(config)?;
            w.check(&weights::expected_unet(&cfg))?;
            let dw = DeviceWeights::upload(ctx, w, "", dtype)?;
            let m = UNet::load(&dw, &cfg)?;
            let s = up(ctx, inputs, "sample", dtype)?;
            let t = timestep(ctx, inputs, s.shape()[0])?;
            let c = up(ctx, inputs, "encoder_hidden_states", dtype)?;
            let down_res: Vec<Tensor> = (0..)
                .map_while(|i| inputs.get(&format!("down_residual_{i}")).map(|_| i))
                .map(|i| up(ctx, inputs, &format!("down_residual_{i}"), dtype))
                .collect::<Result<_>>()?;
            let mid = if inputs.contains_key("mid_residual") {
                Some(up(ctx, inputs, "mid_residual", dtype)?)
            } else {
                None
            };
            ensure!(
                down_res.is_empty() == mid.is_none(),
                "unet: give both down_residual_* and mid_residual, or neither"
            );
            let res = mid.as_ref().map(|m| Residuals {
                down: &down_res,
                mid: m,
            });
            let y = m.forward(
                &mut Fwd {
                    rec: &mut rec,
                    ws: &mut ws,
                },
                &s,
                &t,
                &c,
                res,
            )?;
            rec.finish()?.submit_wait()?;
            out.insert("sample".into(), down(ctx, &y)?);
        }
        Component::ControlNet => {
            let cfg = ControlNetConfig::from_json(config)?;
            w.check(&weights::expected_controlnet(&cfg))?;
            let dw = DeviceWeights::upload(ctx, w, "", dtype)?;
            let m = ControlNet::load(&dw, &cfg)?;
            let s = up(ctx, inputs, "sample", dtype)?;
            let t = timestep(ctx, inputs, s.shape()[0])?;
            let c = up(ctx, inputs, "encoder_hidden_states", dtype)?;
            let cond = up(ctx, inputs, "controlnet_cond", dtype)?;
            let scale = inputs
                .get("conditioning_scale")
                .map(|t| t.data[0])
                .unwrap_or(1.0);
            let o = m.forward(
                &mut Fwd {
                    rec: &mut rec,
                    ws: &mut ws,
                },
                &s,
                &t,
                &c,
                &cond,
                scale,
            )?;
            rec.finish()?.submit_wait()?;
            for (i, d) in o.down.iter().enumerate() {
                out.insert(format!("down_residual_{i}"), down(ctx, d)?);
            }
            out.insert("mid_residual".into(), down(ctx, &o.mid)?);
        }
        Component::VaeEncoder | Component::VaeDecoder => {
            let cfg = VaeConfig::from_json(config)?;
            w.check(&weights::expected_vae(&cfg))?;
            let dw = DeviceWeights::upload(ctx, w, "", dtype)?;
            if comp == Component::VaeEncoder {
                let m = VaeEncoder::load(&dw, &cfg)?;
                let x = up(ctx, inputs, "image", dtype)?;
                let y = m.forward(
                    &mut Fwd {
                        rec: &mut rec,
                        ws: &mut ws,
                    },
                    &x,
                )?;
                rec.finish()?.submit_wait()?;
                let moments = down(ctx, &y)?;
                let (n, c2) = (moments.shape[0], moments.shape[1]);
                let hw: usize = moments.shape[2..].iter().product();
                let mut mean = vec![];
                for b in 0..n {
                    mean.extend_from_slice(&moments.data[b * c2 * hw..(b * c2 + c2 / 2) * hw]);
                }
                let mut ms = moments.shape.clone();
                ms[1] = c2 / 2;
                out.insert(
                    "mean".into(),
                    HostTensor {
                        shape: ms,
                        data: mean,
                        file_dtype: FileDType::F32,
                    },
                );
                out.insert("moments".into(), moments);
            } else {
                let m = VaeDecoder::load(&dw, &cfg)?;
                let z = up(ctx, inputs, "latent", dtype)?;
                let y = m.forward(
                    &mut Fwd {
                        rec: &mut rec,
                        ws: &mut ws,
                    },
                    &z,
                )?;
                rec.finish()?.submit_wait()?;
                out.insert("sample".into(), down(ctx, &y)?);
            }
        }
    }
    Ok(out)
}

/// Reads a diffusers component folder: `config.json` + `diffusion_pytorch_model.safetensors`.
pub fn read_component(dir: &Path) -> Result<(serde_json::Value, std::path::PathBuf)> {
    let cfg_path = dir.join("config.json");
    let cfg: serde_json::Value = serde_json::from_str(&crate::files::read_regular_string(
        &cfg_path,
        "model config",
        crate::files::JSON_LIMIT,
    )?)
    .with_context(|| format!("{}: invalid JSON", cfg_path.display()))?;
    Ok((cfg, dir.join("diffusion_pytorch_model.safetensors")))
}
