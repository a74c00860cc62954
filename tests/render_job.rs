//! `b2dr render` end to end on a small model package (the golden test config, saved as a package folder):
//! package save/load round trip, per-camera outputs and report, determinism, and clear errors on bad model
//! folders and inputs.
mod common;
#[path = "golden/common.rs"]
mod golden;

use std::path::{Path, PathBuf};

use b2dr::nn::b2dr::expected_b2dr;
use b2dr::nn::b2dr_config::B2drConfig;
use b2dr::nn::config::{UNetConfig, VaeConfig};
use b2dr::nn::weights::{expected_unet, expected_vae, FileDType, Weights};
use b2dr::render::job::{self, RenderJob};
use b2dr::render::package::{ModelPackage, PackageMeta};
use b2dr::tensor::DType;

fn keyframe() -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/nuscenes-mini/keyframe-scene-0061/frame.json");
    if p.exists() {
        Some(p)
    } else {
        eprintln!("SKIP: {} is absent (shared data)", p.display());
        None
    }
}

/// The golden test config as a model package at 56 x 104 (6 cameras, one shared context).
fn small_package() -> ModelPackage {
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
        },
        unet: w("b2dr_weights_unet.safetensors", &expected_unet(&ucfg)),
        control: w(
            "b2dr_weights_controlnet.safetensors",
            &expected_b2dr(&ccfg),
        ),
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

fn job(model: &Path, frame: &Path, out: &Path) -> RenderJob {
    RenderJob {
        model: Some(model.to_path_buf()),
        frame: frame.to_path_buf(),
        prev: vec![],
        refs: None,
        no_refs: false,
        cameras: Some(vec!["CAM_FRONT".into(), "CAM_BACK".into()]),
        steps: None,
        sampler: None,
        ref_guidance: None,
        seed: 3,
        dtype: DType::F32,
        map: None,
        box_z: "auto".into(),
        out: out.to_path_buf(),
    }
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("b2dr-render-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn render_job_writes_cameras_and_is_deterministic() {
    let Some(ctx) = common::ctx() else { return };
    let Some(frame) = keyframe() else { return };
    let dir = tmp("pkg");
    let pkg = small_package();
    pkg.save(&dir, FileDType::F32).unwrap();
    let back = ModelPackage::load(&dir).unwrap();
    assert_eq!(back.meta, pkg.meta);
    assert_eq!(back.control_cfg, pkg.control_cfg);
    assert_eq!(back.control.tensors, pkg.control.tensors, "weights round trip");
    let o1 = tmp("o1");
    let o2 = tmp("o2");
    let r = job::run(&ctx, &job(&dir, &frame, &o1)).unwrap();
    job::run(&ctx, &job(&dir, &frame, &o2)).unwrap();
    for c in ["CAM_FRONT", "CAM_BACK"] {
        let a = std::fs::read(o1.join(format!("{c}.exr"))).unwrap();
        let b = std::fs::read(o2.join(format!("{c}.exr"))).unwrap();
        assert_eq!(a, b, "{c}: reruns differ");
        let img = image::open(o1.join(format!("{c}.png"))).unwrap();
        assert_eq!((img.width(), img.height()), (104, 56));
    }
    assert_eq!(r["cameras"].as_array().unwrap().len(), 2);
    for k in ["encode_ms", "denoise_ms", "decode_ms"] {
        assert!(r["times_ms"][k].as_f64().unwrap() > 0.0, "{k}");
    }
    assert!(r["device_bytes_planned"].as_u64().unwrap() > 0);
    // references change the frame; another seed changes it
    let o3 = tmp("o3");
    let mut j = job(&dir, &frame, &o3);
    j.no_refs = true;
    job::run(&ctx, &j).unwrap();
    let o4 = tmp("o4");
    let mut j = job(&dir, &frame, &o4);
    j.seed = 4;
    job::run(&ctx, &j).unwrap();
    let a = std::fs::read(o1.join("CAM_FRONT.exr")).unwrap();
    assert_ne!(a, std::fs::read(o3.join("CAM_FRONT.exr")).unwrap(), "--no-refs changes nothing");
    assert_ne!(a, std::fs::read(o4.join("CAM_FRONT.exr")).unwrap(), "--seed changes nothing");
    common::assert_no_validation_errors();
}

fn err(ctx: &b2dr::vk::Context, j: &RenderJob) -> String {
    format!("{:#}", job::run(ctx, j).expect_err("must fail"))
}

#[test]
fn render_job_rejects_bad_models_and_inputs() {
    let Some(ctx) = common::ctx() else { return };
    let Some(frame) = keyframe() else { return };
    let pkg = small_package();
    let out = tmp("bad-out");
    // a folder that is no package
    let e = err(&ctx, &job(Path::new("/nonexistent/model"), &frame, &out));
    assert!(e.contains("not a folder"), "{e}");
    // a plain ControlNet where the B2D-R one belongs
    let d = tmp("plain");
    pkg.save(&d, FileDType::F32).unwrap();
    let plain = pkg.control_cfg.base.to_json();
    std::fs::write(d.join("controlnet/config.json"), plain.to_string()).unwrap();
    let e = err(&ctx, &job(&d, &frame, &out));
    assert!(e.contains("plain ControlNetModel") || e.contains("in_channels"), "{e}");
    // a missing B2D-R tensor
    let d = tmp("missing");
    let mut p2 = pkg.clone();
    p2.control.tensors.remove("ref_attn.0.to_q.weight");
    p2.save(&d, FileDType::F32).unwrap();
    let e = err(&ctx, &job(&d, &frame, &out));
    assert!(e.contains("ref_attn.0.to_q.weight"), "{e}");
    // NaN in the weights
    let d = tmp("nan");
    let mut p3 = pkg.clone();
    p3.control
        .tensors
        .get_mut("noise_embedding.linear_1.weight")
        .unwrap()
        .data[0] = f32::NAN;
    p3.save(&d, FileDType::F32).unwrap();
    let e = err(&ctx, &job(&d, &frame, &out));
    assert!(e.contains("NaN"), "{e}");
    // a non-finite noise level and an unknown key in the config
    let d = tmp("cfg");
    pkg.save(&d, FileDType::F32).unwrap();
    let cpath = d.join("controlnet/config.json");
    let mut c: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&cpath).unwrap()).unwrap();
    c["prev_noise_level"] = serde_json::json!(1e9);
    std::fs::write(&cpath, c.to_string()).unwrap();
    let e = err(&ctx, &job(&d, &frame, &out));
    assert!(e.contains("prev_noise_level") && e.contains("config.json"), "{e}");
    c["prev_noise_level"] = serde_json::json!(200);
    c["ref_attn_heads"] = serde_json::json!(3);
    std::fs::write(&cpath, c.to_string()).unwrap();
    let e = err(&ctx, &job(&d, &frame, &out));
    assert!(e.contains("ref_attn_heads"), "{e}");
    // inputs: guidance, cameras, previous frames
    let good = tmp("good");
    pkg.save(&good, FileDType::F32).unwrap();
    let mut j = job(&good, &frame, &out);
    j.ref_guidance = Some(f64::NAN);
    let e = err(&ctx, &j);
    assert!(e.contains("guidance"), "{e}");
    let mut j = job(&good, &frame, &out);
    j.cameras = Some(vec!["CAM_UP".into()]);
    let e = err(&ctx, &j);
    assert!(e.contains("CAM_UP"), "{e}");
    let mut j = job(&good, &frame, &out);
    j.prev = vec![frame.clone(), frame.clone(), frame.clone()];
    let e = err(&ctx, &j);
    assert!(e.contains("--prev") && e.contains("3 images for 2 cameras"), "{e}");
    let mut j = job(&good, &frame, &out);
    j.steps = Some(0);
    let e = err(&ctx, &j);
    assert!(e.contains("--steps"), "{e}");
    common::assert_no_validation_errors();
}
