//! `b2dr forward` and `b2dr sample` end to end (the binary): a diffusers component and a whole B2D-R frame of a
//! model package checked against their golden outputs through the CLI, the files `sample` writes, and clear
//! errors for bad input files.
#[path = "golden/b2dr_package.rs"]
mod b2dr_package;
mod common;
#[path = "golden/common.rs"]
mod golden;

use std::collections::BTreeMap;
use std::process::Command;

use b2dr::nn::weights::{FileDType, Weights};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_b2dr"))
}

#[test]
fn forward_vae_decoder_matches_diffusers_through_the_cli() {
    if common::ctx().is_none() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("b2dr-forward-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let m = golden::load_json("models.json");
    let set = &m["sets"]["dtest"];
    std::fs::write(
        dir.join("config.json"),
        serde_json::to_string(&set["configs"]["vae"]).unwrap(),
    )
    .unwrap();
    let weights = golden::golden_dir().join(set["weights"]["vae"]["file"].as_str().unwrap());
    let case = std::fs::read(golden::golden_dir().join("case_dtest_7x13.safetensors")).unwrap();
    let io = Weights::from_bytes_unchecked(&case, "case")
        .unwrap()
        .tensors;
    let inputs = Weights {
        tensors: BTreeMap::from([("latent".to_string(), io["in.z"].clone())]),
    };
    inputs
        .save(&dir.join("in.safetensors"), FileDType::F32)
        .unwrap();
    let out = bin()
        .args(["forward", "--component", "vae-decoder", "--config"])
        .arg(dir.join("config.json"))
        .arg("--weights")
        .arg(&weights)
        .arg("--inputs")
        .arg(dir.join("in.safetensors"))
        .arg("--out")
        .arg(dir.join("out.safetensors"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let got =
        Weights::from_bytes_unchecked(&std::fs::read(dir.join("out.safetensors")).unwrap(), "out")
            .unwrap();
    golden::assert_close(
        "cli vae-decoder",
        &got.tensors["sample"].data,
        &io["out.vae_decoder.sample"].data,
        1e-5,
    );

    // A missing input is an error naming the tensor, not a panic.
    let bad = Weights {
        tensors: BTreeMap::from([("z".to_string(), io["in.z"].clone())]),
    };
    bad.save(&dir.join("bad.safetensors"), FileDType::F32)
        .unwrap();
    let out = bin()
        .args(["forward", "--component", "vae-decoder", "--config"])
        .arg(dir.join("config.json"))
        .arg("--weights")
        .arg(&weights)
        .arg("--inputs")
        .arg(dir.join("bad.safetensors"))
        .arg("--out")
        .arg(dir.join("o2.safetensors"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("\"latent\""), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn sample_writes_png_exr_and_report() {
    if common::ctx().is_none() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("b2dr-sample-{}", std::process::id()));
    let out = bin()
        .args(["sample", "--steps", "2", "--size", "32x56", "--out"])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let img = image::open(dir.join("sample.png")).unwrap();
    assert_eq!((img.width(), img.height()), (56, 32));
    assert!(std::fs::metadata(dir.join("sample.exr")).unwrap().len() > 0);
    let rep: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("sample.json")).unwrap()).unwrap();
    assert_eq!(rep["steps"], 2);
    assert!(rep["device_bytes_total"].as_u64().unwrap() > 0);
    // Bad arguments are clear errors.
    let out = bin()
        .args(["sample", "--size", "30x56", "--out"])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        !out.status.success() && String::from_utf8_lossy(&out.stderr).contains("multiples of 8")
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The built-in b2dr-tiny written as a diffusers folder (`SdModel::save`) and sampled from that folder draws the
/// same image, bit for bit, as the built-in: the folder reader and the built-in assemble the same model.
#[test]
fn sample_from_a_saved_folder_equals_the_builtin() {
    use b2dr::nn::sd_model::SdModel;
    let dir = std::env::temp_dir().join(format!("b2dr-sample-folder-{}", std::process::id()));
    let model = dir.join("model");
    SdModel::seeded_tiny()
        .save(&model, b2dr::nn::weights::FileDType::F32)
        .unwrap();
    let back = SdModel::load(&model).unwrap();
    let tiny = SdModel::seeded_tiny();
    assert_eq!(back.unet_cfg, tiny.unet_cfg);
    assert_eq!(back.vae_cfg, tiny.vae_cfg);
    assert_eq!(back.cond, tiny.cond);
    assert_eq!(back.unet.tensors.len(), tiny.unet.tensors.len());
    let sample = |m: Option<&std::path::Path>, out: &str| {
        let mut c = bin();
        c.args(["sample", "--steps", "2", "--size", "32x56", "--seed", "3"]);
        if let Some(m) = m {
            c.arg("--model").arg(m);
        }
        let o = c.arg("--out").arg(dir.join(out)).output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        image::open(dir.join(out).join("sample.png"))
            .unwrap()
            .to_rgb8()
            .into_raw()
    };
    let (a, b) = (sample(None, "builtin"), sample(Some(&model), "folder"));
    assert_eq!(a, b, "the saved folder samples another image");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A model folder whose VAE does not downsample by 8, and NaN or infinite guidance / conditioning scales, are
/// clear errors naming the file or flag (issue #18), found before any device work.
#[test]
fn sample_refuses_a_vae_of_another_factor_and_non_finite_scales() {
    let dir = std::env::temp_dir().join(format!("b2dr-sample-hostile-{}", std::process::id()));
    let model = dir.join("model");
    std::fs::create_dir_all(model.join("vae")).unwrap();
    let mut vae = b2dr::nn::config::VaeConfig::b2dr_tiny();
    vae.block_out_channels = vec![16, 32, 64];
    std::fs::write(
        model.join("vae/config.json"),
        serde_json::to_string(&vae.to_json()).unwrap(),
    )
    .unwrap();
    let out = bin()
        .args(["sample", "--steps", "1", "--size", "16x16", "--model"])
        .arg(&model)
        .arg("--out")
        .arg(dir.join("out"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success()
            && err.contains("vae/config.json")
            && err.contains("downsamples by 4"),
        "{err}"
    );
    for (flag, val) in [("--guidance", "NaN"), ("--conditioning-scale", "inf")] {
        let out = bin()
            .args([
                "sample", "--steps", "1", "--size", "16x16", flag, val, "--out",
            ])
            .arg(dir.join("out"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(flag) && err.contains("finite"),
            "{flag}: {err}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `forward --component frame`: the golden B2D-R config saved as a one-camera model package renders, through the
/// CLI on the golden case's named inputs (its own context), the golden frame of tools/make_golden_b2dr.py (UniPC 3
/// steps, reference guidance 2); and missing or mis-shaped inputs, and options of the other mode, are errors
/// naming the tensor (and its expected shape) or the flag, found before a device is opened.
#[test]
fn forward_frame_renders_the_golden_frame_and_names_bad_inputs() {
    let dir = std::env::temp_dir().join(format!("b2dr-forward-frame-{}", std::process::id()));
    let model = dir.join("model");
    let case = golden::golden_case("b2dr_case_n1_7x13.safetensors");
    let mut pkg = b2dr_package::small_package();
    pkg.meta.cameras = vec!["CAM_FRONT".into()];
    pkg.meta.steps = 3;
    pkg.context = case.get("in.context").unwrap().clone();
    pkg.save(&model, FileDType::F32).unwrap();
    let frame = |inputs: &Weights, extra: &[&str]| {
        let path = dir.join("in.safetensors");
        inputs.save(&path, FileDType::F32).unwrap();
        bin()
            .env("B2DR_VALIDATION", "1")
            .args(["forward", "--component", "frame", "--model"])
            .arg(&model)
            .args(extra)
            .arg("--inputs")
            .arg(&path)
            .arg("--out")
            .arg(dir.join("out.safetensors"))
            .output()
            .unwrap()
    };
    let fails = |o: &std::process::Output, want: &[&str]| {
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && want.iter().all(|w| err.contains(w)),
            "want {want:?} in: {err}"
        );
        assert!(!err.contains("panicked"), "{err}");
    };
    let without = |name: &str| {
        let mut w = case.clone();
        w.tensors.remove(name);
        w
    };
    fails(
        &frame(&without("in.eps_prev"), &[]),
        &["`in.eps_prev` is missing", "(1, 4, 7, 13)"],
    );
    fails(
        &frame(&without("in.pe_ref.2"), &[]),
        &["`in.pe_ref.2` is missing", "(1, 2, "],
    );
    let mut bad = case.clone();
    let m = bad.tensors.get_mut("in.masks").unwrap();
    m.shape = vec![1, 15, 104, 56];
    fails(
        &frame(&bad, &[]),
        &["`in.masks` has shape (1, 15, 104, 56), expected (1, 15, 56, 104)"],
    );
    // two cameras need two rows of every input
    fails(
        &frame(&case, &["--cameras", "CAM_FRONT,CAM_BACK"]),
        &["`in.x_T` has shape (1, 4, 7, 13), expected (2, 4, 7, 13)"],
    );
    fails(
        &frame(&case, &["--config", "unet/config.json"]),
        &["--config and --weights are for one component"],
    );
    let o = bin()
        .args(["forward", "--component", "unet", "--steps", "2", "--inputs"])
        .arg(dir.join("in.safetensors"))
        .arg("--out")
        .arg(dir.join("o.safetensors"))
        .output()
        .unwrap();
    fails(&o, &["--steps is an option of --component frame"]);

    if common::ctx().is_none() {
        return;
    }
    let o = frame(
        &case,
        &["--steps", "3", "--sampler", "unipc", "--ref-guidance", "2"],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(!err.contains("[vulkan validation error]"), "{err}");
    let got =
        Weights::from_bytes_unchecked(&std::fs::read(dir.join("out.safetensors")).unwrap(), "out")
            .unwrap();
    for (out, want) in [
        ("image", "out.frame_w2.image"),
        ("latent", "out.frame_w2.latent.2"),
        ("prev_latent", "out.prev.z"),
    ] {
        let (g, w) = (&got.tensors[out], case.get(want).unwrap());
        assert_eq!(g.shape, w.shape, "{out}");
        eprintln!(
            "cli frame {out}: nmse {:.2e}",
            golden::nmse(&g.data, &w.data)
        );
        golden::assert_close(&format!("cli frame {out}"), &g.data, &w.data, 1e-5);
    }
    let _ = std::fs::remove_dir_all(&dir);
}
