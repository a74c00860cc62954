//! Each model component (UNet, ControlNet, UNet + ControlNet residuals, VAE encoder, VAE decoder) against
//! diffusers on the same weights and inputs (tests/golden, written by tools/make_golden.py).
//! Thresholds (normalised MSE): 1e-5 in f32, 1e-3 in f16 (the acceptance criteria).
mod common;
#[path = "golden/common.rs"]
mod golden;

use std::collections::BTreeMap;

use b2dr::nn::config::{ControlNetConfig, UNetConfig, VaeConfig};
use b2dr::nn::controlnet::ControlNet;
use b2dr::nn::device::{DeviceWeights, Fwd, Workspace};
use b2dr::nn::unet::{Residuals, UNet};
use b2dr::nn::vae::{VaeDecoder, VaeEncoder};
use b2dr::nn::weights::{self, HostTensor, Weights};
use b2dr::tensor::{DType, Tensor};
use b2dr::vk::Context;
use serde_json::Value;

fn set_weights(set: &Value, comp: &str, expected: &[weights::Spec]) -> Weights {
    let w = &set["weights"][comp];
    if let Some(file) = w["file"].as_str() {
        Weights::load(&golden::golden_dir().join(file), expected)
            .unwrap_or_else(|e| panic!("{file}: {e:#}; {}", golden::REGENERATE))
    } else {
        let seed = w["seed"].as_u64().expect("seed");
        let ws = Weights::random(expected, seed);
        // Both sides must run the same weights: compare every tensor's fingerprint.
        for (name, fp) in w["fingerprints"].as_object().expect("fingerprints") {
            let t = ws.get(name).unwrap_or_else(|e| panic!("{e:#}"));
            assert_eq!(
                Weights::fingerprint(t).to_string(),
                fp.as_str().unwrap(),
                "weights differ at {name}; {}",
                golden::REGENERATE
            );
        }
        ws
    }
}

struct Io {
    t: BTreeMap<String, HostTensor>,
}

impl Io {
    fn up(&self, ctx: &Context, name: &str, dtype: DType) -> Tensor {
        let h = &self.t[name];
        Tensor::from_f32(ctx, &h.shape, dtype, &h.data, name).unwrap()
    }
    fn up32(&self, ctx: &Context, name: &str) -> Tensor {
        self.up(ctx, name, DType::F32)
    }
}

/// Records one forward pass with `f`, submits it and waits.
fn record<T>(
    ctx: &Context,
    ws: &mut Workspace,
    f: impl FnOnce(&mut Fwd) -> anyhow::Result<T>,
) -> T {
    let mut rec = ctx.recorder().unwrap();
    let out = f(&mut Fwd { rec: &mut rec, ws }).unwrap();
    rec.finish().unwrap().submit_wait().unwrap();
    out
}

fn check(what: &str, got: &Tensor, ctx: &Context, want: &HostTensor, tol: f64) -> f64 {
    assert_eq!(got.shape(), &want.shape[..], "{what}: shape");
    let g = got.to_f32(ctx).unwrap();
    let e = golden::nmse(&g, &want.data);
    eprintln!("  {what}: nmse {e:.3e} (tol {tol:e})");
    assert!(
        e <= tol,
        "{what}: nmse {e:e} > {tol:e}; {}",
        golden::REGENERATE
    );
    e
}

fn run_case(ctx: &Context, models: &Value, case: &Value, dtype: DType) {
    let set_name = case["set"].as_str().unwrap();
    let set = &models["sets"][set_name];
    let file = case["file"].as_str().unwrap();
    let bytes = std::fs::read(golden::golden_dir().join(file)).unwrap();
    let io = Io {
        t: Weights::from_bytes_unchecked(&bytes, file).unwrap().tensors,
    };
    let tol = if dtype == DType::F32 { 1e-5 } else { 1e-3 };
    eprintln!("case {file} as {dtype:?}");
    let comps = case["components"].as_object().unwrap();
    let cfgs = &set["configs"];

    let unet = cfgs.get("unet").filter(|v| !v.is_null()).map(|c| {
        let cfg = UNetConfig::from_json(c.clone()).unwrap();
        let w = set_weights(set, "unet", &weights::expected_unet(&cfg));
        let dw = DeviceWeights::upload(ctx, &w, "", dtype).unwrap();
        (UNet::load(&dw, &cfg).unwrap(), dw)
    });
    let control = cfgs.get("controlnet").filter(|v| !v.is_null()).map(|c| {
        let cfg = ControlNetConfig::from_json(c.clone()).unwrap();
        let w = set_weights(set, "controlnet", &weights::expected_controlnet(&cfg));
        let dw = DeviceWeights::upload(ctx, &w, "", dtype).unwrap();
        (ControlNet::load(&dw, &cfg).unwrap(), dw)
    });
    let vae = cfgs.get("vae").filter(|v| !v.is_null()).map(|c| {
        let cfg = VaeConfig::from_json(c.clone()).unwrap();
        let w = set_weights(set, "vae", &weights::expected_vae(&cfg));
        let dw = DeviceWeights::upload(ctx, &w, "", dtype).unwrap();
        (
            VaeEncoder::load(&dw, &cfg).unwrap(),
            VaeDecoder::load(&dw, &cfg).unwrap(),
            cfg,
        )
    });

    let sample = || io.up(ctx, "in.sample", dtype);
    let t = io.up32(ctx, "in.timestep");
    let ehs = || io.up(ctx, "in.encoder_hidden_states", dtype);
    let mut ws = Workspace::new(ctx, dtype);

    if comps.contains_key("unet") {
        let (u, _) = unet.as_ref().unwrap();
        let (s, c) = (sample(), ehs());
        let out = record(ctx, &mut ws, |f| u.forward(f, &s, &t, &c, None));
        check("unet", &out, ctx, &io.t["out.unet.sample"], tol);
    }
    if comps.contains_key("controlnet") {
        let (cn, _) = control.as_ref().unwrap();
        let (s, c) = (sample(), ehs());
        let cond = io.up(ctx, "in.controlnet_cond", dtype);
        let scale = io.t["in.conditioning_scale"].data[0];
        let o = record(ctx, &mut ws, |f| cn.forward(f, &s, &t, &c, &cond, scale));
        for (i, d) in o.down.iter().enumerate() {
            check(
                &format!("controlnet down_residual_{i}"),
                d,
                ctx,
                &io.t[&format!("out.controlnet.down_residual_{i}")],
                tol,
            );
        }
        check(
            "controlnet mid_residual",
            &o.mid,
            ctx,
            &io.t["out.controlnet.mid_residual"],
            tol,
        );
    }
    if comps.contains_key("unet_with_residuals") {
        let (u, _) = unet.as_ref().unwrap();
        let (s, c) = (sample(), ehs());
        let n = comps["unet_with_residuals"]["inputs"]
            .as_array()
            .unwrap()
            .len()
            - 4;
        let down: Vec<Tensor> = (0..n)
            .map(|i| io.up(ctx, &format!("out.controlnet.down_residual_{i}"), dtype))
            .collect();
        let mid = io.up(ctx, "out.controlnet.mid_residual", dtype);
        let out = record(ctx, &mut ws, |f| {
            u.forward(
                f,
                &s,
                &t,
                &c,
                Some(Residuals {
                    down: &down,
                    mid: &mid,
                }),
            )
        });
        check(
            "unet with residuals",
            &out,
            ctx,
            &io.t["out.unet_with_residuals.sample"],
            tol,
        );
    }
    if comps.contains_key("vae_encoder") {
        let (enc, _, _) = vae.as_ref().unwrap();
        let input = comps["vae_encoder"]["inputs"][0].as_str().unwrap();
        let img = io.up(ctx, input, dtype);
        let out = record(ctx, &mut ws, |f| enc.forward(f, &img));
        check(
            "vae encoder moments",
            &out,
            ctx,
            &io.t["out.vae_encoder.moments"],
            tol,
        );
    }
    if comps.contains_key("vae_decoder") {
        let (_, dec, _) = vae.as_ref().unwrap();
        let z = io.up(ctx, "in.z", dtype);
        let out = record(ctx, &mut ws, |f| dec.forward(f, &z));
        check(
            "vae decoder",
            &out,
            ctx,
            &io.t["out.vae_decoder.sample"],
            tol,
        );
    }
    common::assert_no_validation_errors();
}

fn cases(filter: impl Fn(&Value) -> bool) -> (Value, Vec<Value>) {
    let models = golden::load_json("models.json");
    let cs = models["cases"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| filter(c))
        .cloned()
        .collect();
    (models, cs)
}

#[test]
fn diffusers_test_configs_match_in_f32() {
    let Some(ctx) = common::ctx() else { return };
    let (m, cs) = cases(|c| c["set"].as_str().unwrap().starts_with("dtest"));
    assert!(!cs.is_empty());
    for c in &cs {
        run_case(&ctx, &m, c, DType::F32);
    }
}

#[test]
fn b2dr_tiny_matches_in_f32_at_7x13() {
    let Some(ctx) = common::ctx() else { return };
    let (m, cs) = cases(|c| c["set"] == "tiny" && c["latent_hw"][0] == 7);
    assert_eq!(cs.len(), 1);
    run_case(&ctx, &m, &cs[0], DType::F32);
}

#[test]
fn b2dr_tiny_matches_at_28x50_in_f32_and_f16() {
    let Some(ctx) = common::ctx() else { return };
    let (m, cs) = cases(|c| c["set"] == "tiny" && c["latent_hw"][0] == 28);
    assert_eq!(cs.len(), 1);
    run_case(&ctx, &m, &cs[0], DType::F32);
    run_case(&ctx, &m, &cs[0], DType::F16);
}
