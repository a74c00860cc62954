//! One frame of a model package on explicit named host tensors (`b2dr forward --component frame`): the inputs
//! a [`FrameRenderer`] takes, named as the golden files name them (`tools/make_golden_b2dr.py`), so that a frame
//! of a trained package can be compared with the PyTorch reference (`b2dr_ref.frame.render_frame`) on the same
//! noise, masks, images and position encodings. `b2dr render` draws its noise from a seed and projects its
//! inputs from a keyframe; here nothing is drawn or projected.
//!
//! Inputs, for N cameras (the package's, or `cameras`), the package's render size (H, W), the latent (C, h, w)
//! = (the VAE's latent channels, H / 8, W / 8), and per Ref-Attn location j its feature size (h_j, w_j) and 3D
//! (3 x the ControlNet's `pe_depth_num`):
//! - `in.x_T` (N, C, h, w): the initial latent; `in.eps_prev` (N, C, h, w): the noise of the previous-frame latent;
//! - `in.masks` (N, 15, H, W) in {0, 1}; `in.prev_image` (N, 3, H, W) in [0, 1];
//! - with references: `in.ref_images` (N, 2, 3, H, W) in [0, 1] (front, rear), `in.pe_cur.{j}` (N, 3D, h_j, w_j),
//!   `in.pe_ref.{j}` (N, 2, 3D, h_j, w_j);
//! - optional `in.context` (L, D) or (N, L, D) (default: the package's context of those cameras).
//!
//! Outputs (f32): `image` (N, 3, H, W) in [0, 1], `latent` (N, C, h, w) (the final x_0), `prev_latent`
//! (N, C, h, w) (the noised previous-frame latent the ControlNet read). Other tensors in the file are ignored.
use std::collections::BTreeMap;

use anyhow::{Context as _, Result};

use super::frame::{FrameInputs, FrameRenderer, FrameShape, Prev, RefInputs};
use super::job::sampler_plan;
use super::package::{DeviceModel, ModelPackage};
use crate::nn::weights::{FileDType, HostTensor};
use crate::sampling::SamplerPlan;
use crate::tensor::DType;
use crate::vk::Context;

/// The options of a named-input frame (the package's sampler, steps and guidance unless given).
#[derive(Clone, Debug)]
pub struct NamedFrame {
    /// Cameras of the frame (default: all of the package's, in its order); they pick the context rows.
    pub cameras: Option<Vec<String>>,
    pub steps: Option<usize>,
    /// unipc | ddim
    pub sampler: Option<String>,
    pub ref_guidance: Option<f64>,
    /// Masks-only rendering: the reference inputs are not read and the Ref-Attns are skipped.
    pub no_refs: bool,
}

/// The host inputs of a frame, checked against the shapes the package needs, and the sampler they run with.
pub struct CheckedInputs<'a> {
    pub cameras: Vec<String>,
    pub context: Vec<f32>,
    pub plan: SamplerPlan,
    pub ref_guidance: f64,
    x_t: &'a [f32],
    eps_prev: &'a [f32],
    masks: &'a [f32],
    prev: &'a [f32],
    refs: Option<RefInputs<'a>>,
}

fn shape_text(s: &[usize]) -> String {
    let v: Vec<String> = s.iter().map(|d| d.to_string()).collect();
    format!("({})", v.join(", "))
}

/// `name` of `inputs` with exactly `shape`; the error names the tensor, its meaning and the expected shape.
fn take<'a>(
    inputs: &'a BTreeMap<String, HostTensor>,
    name: &str,
    shape: &[usize],
    what: &str,
) -> Result<&'a [f32]> {
    let t = inputs.get(name).with_context(|| {
        format!(
            "input tensor `{name}` is missing: expected {} ({what})",
            shape_text(shape)
        )
    })?;
    anyhow::ensure!(
        t.shape == shape,
        "input tensor `{name}` has shape {}, expected {} ({what})",
        shape_text(&t.shape),
        shape_text(shape)
    );
    Ok(&t.data)
}

/// Checks the options and every input against the package (host only: nothing is uploaded).
pub fn check_inputs<'a>(
    pkg: &ModelPackage,
    inputs: &'a BTreeMap<String, HostTensor>,
    o: &NamedFrame,
) -> Result<CheckedInputs<'a>> {
    let ref_guidance = o.ref_guidance.unwrap_or(pkg.meta.ref_guidance);
    crate::sampling::check_guidance("--ref-guidance", ref_guidance)?;
    let plan = sampler_plan(
        o.sampler.as_deref().unwrap_or(&pkg.meta.sampler),
        o.steps.unwrap_or(pkg.meta.steps),
        pkg.meta.prediction(),
    )?;
    let cameras = o.cameras.clone().unwrap_or(pkg.meta.cameras.clone());
    anyhow::ensure!(!cameras.is_empty(), "--cameras: no cameras");
    let n = cameras.len();
    let [ih, iw] = pkg.meta.render_size;
    let (h, w) = (ih / 8, iw / 8);
    let lc = pkg.vae_cfg.latent_channels;
    let lat = [n, lc, h, w];
    let x_t = take(inputs, "in.x_T", &lat, "the initial latent (N, C, h, w)")?;
    let eps_prev = take(
        inputs,
        "in.eps_prev",
        &lat,
        "the noise of the previous-frame latent (N, C, h, w)",
    )?;
    let masks = take(
        inputs,
        "in.masks",
        &[n, 15, ih, iw],
        "the 15 layout masks at the package's render size (N, 15, H, W)",
    )?;
    let prev = take(
        inputs,
        "in.prev_image",
        &[n, 3, ih, iw],
        "the previous frame in [0, 1] (N, 3, H, W)",
    )?;
    let refs = if o.no_refs {
        None
    } else {
        let cfg = &pkg.control_cfg;
        let d3 = 3 * cfg.pe_depth_num;
        let images = take(
            inputs,
            "in.ref_images",
            &[n, 2, 3, ih, iw],
            "front and rear reference images in [0, 1] (N, 2, 3, H, W); --no-refs renders without",
        )?;
        let mut pe_cur = vec![];
        let mut pe_ref = vec![];
        for (j, &at) in cfg.ref_attn.iter().enumerate() {
            let (fh, fw) = cfg.location_size(at, (h, w));
            pe_cur.push(take(
                inputs,
                &format!("in.pe_cur.{j}"),
                &[n, d3, fh, fw],
                &format!(
                    "the current view's position encoding at Ref-Attn {} (N, 3D, h_j, w_j)",
                    at.name()
                ),
            )?);
            pe_ref.push(take(
                inputs,
                &format!("in.pe_ref.{j}"),
                &[n, 2, d3, fh, fw],
                &format!(
                    "the references' position encoding at Ref-Attn {at:?} (N, 2, 3D, h_j, w_j)"
                ),
            )?);
        }
        Some(RefInputs {
            images,
            pe_cur,
            pe_ref,
        })
    };
    let d = pkg.unet_cfg.enc.cross_attention_dim;
    let context = match inputs.get("in.context") {
        None => pkg.context_for(&cameras)?,
        Some(c) => match c.shape.as_slice() {
            [l, dd] if *dd == d && *l >= 1 => c.data.repeat(n),
            [nn, l, dd] if *nn == n && *dd == d && *l >= 1 => c.data.clone(),
            s => anyhow::bail!(
                "input tensor `in.context` has shape {}, expected (L, {d}) or ({n}, L, {d}) (the text \
                 embedding; absent: the package's)",
                shape_text(s)
            ),
        },
    };
    Ok(CheckedInputs {
        cameras,
        context,
        plan,
        ref_guidance,
        x_t,
        eps_prev,
        masks,
        prev,
        refs,
    })
}

/// Uploads the package in `dtype` (UNet and ControlNet; the VAE in f32), plans and renders one frame; returns
/// `image`, `latent` and `prev_latent`.
pub fn render(
    ctx: &Context,
    pkg: &ModelPackage,
    x: &CheckedInputs,
    dtype: DType,
) -> Result<BTreeMap<String, HostTensor>> {
    let dm = DeviceModel::upload(ctx, pkg, dtype)?;
    let n = x.cameras.len();
    let [ih, iw] = pkg.meta.render_size;
    let r = FrameRenderer::new(
        ctx,
        &dm.as_model(),
        FrameShape {
            cameras: n,
            size: (ih, iw),
            refs: x.refs.is_some(),
            ref_guidance: x.ref_guidance,
            out_size: None,
            prev_noise_level: None,
            prev_blur_sigma: None,
        },
        &x.context,
        x.plan.clone(),
    )?;
    r.render(&FrameInputs {
        masks: x.masks,
        prev: Prev::Image(x.prev),
        refs: x.refs.as_ref().map(|r| RefInputs {
            images: r.images,
            pe_cur: r.pe_cur.clone(),
            pe_ref: r.pe_ref.clone(),
        }),
        x_t: x.x_t,
        eps_prev: x.eps_prev,
        prev_warp: None,
    })?;
    let (lc, h, w) = r.latent_size();
    let host = |shape: Vec<usize>, data: Vec<f32>| HostTensor {
        shape,
        data,
        file_dtype: FileDType::F32,
    };
    Ok(BTreeMap::from([
        ("image".into(), host(vec![n, 3, ih, iw], r.image()?)),
        ("latent".into(), host(vec![n, lc, h, w], r.latent()?)),
        (
            "prev_latent".into(),
            host(vec![n, lc, h, w], r.prev_latent()?),
        ),
    ]))
}
