//! The golden B2D-R test config as a model package (tests of `b2dr render` and `b2dr run`); included with
//! `#[path = "golden/b2dr_package.rs"] mod b2dr_package;` next to `mod golden;`.
#![allow(dead_code)]
use super::golden;
use b2dr::nn::b2dr::expected_b2dr;
use b2dr::nn::b2dr_config::B2drConfig;
use b2dr::nn::config::{UNetConfig, VaeConfig};
use b2dr::nn::weights::{expected_unet, expected_vae, Weights};
use b2dr::render::package::{ModelPackage, PackageMeta};

/// The golden test config as a model package at 56 x 104 (6 cameras, one shared context).
pub fn small_package() -> ModelPackage {
    let m = golden::load_json("b2dr_models.json");
    let ucfg = UNetConfig::from_json(m["configs"]["unet"].clone()).unwrap();
    let ccfg = B2drConfig::from_json(m["configs"]["controlnet"].clone()).unwrap();
    let vcfg = VaeConfig::from_json(m["configs"]["vae"].clone()).unwrap();
    let w = |f: &str, e: &[b2dr::nn::weights::Spec]| {
        Weights::load(&golden::golden_dir().join(f), e).unwrap()
    };
    let d = ucfg.enc.cross_attention_dim;
    ModelPackage {
        meta: PackageMeta {
            format: "b2dr-model".into(),
            version: 1,
            render_size: [56, 104],
            cameras: [
                "CAM_FRONT",
                "CAM_FRONT_RIGHT",
                "CAM_FRONT_LEFT",
                "CAM_BACK",
                "CAM_BACK_LEFT",
                "CAM_BACK_RIGHT",
            ]
            .map(String::from)
            .to_vec(),
            sampler: "unipc".into(),
            steps: 2,
            ref_guidance: 2.0,
            dtype: "f32".into(),
            prediction_type: None,
            x0_base: None,
        },
        unet: w("b2dr_weights_unet.safetensors", &expected_unet(&ucfg)),
        control: w("b2dr_weights_controlnet.safetensors", &expected_b2dr(&ccfg)),
        vae: w("b2dr_weights_vae.safetensors", &expected_vae(&vcfg)),
        context: Weights::random(&[("cond".into(), vec![77, d])], 5)
            .get("cond")
            .unwrap()
            .clone(),
        unet_cfg: ucfg,
        control_cfg: ccfg,
        vae_cfg: vcfg,
        source: "test".into(),
    }
}
