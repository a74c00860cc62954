//! `b2dr eval-render` (world.md 4) on a small seeded package: reruns write the same bytes; the copy-nearest
//! baseline is the ground truth on the logged path and not when displaced; the copy-prev baseline (the frame
//! 0.5 s earlier) is scored on and off the log and is not the truth; the inference-time noise-level and
//! blur overrides change the rendered frames; bad configurations are errors.
#[path = "golden/b2dr_package.rs"]
mod b2dr_package;
mod common;
#[path = "golden/common.rs"]
mod golden;

use std::path::PathBuf;

use b2dr::eval::fidelity::{eval_render, EvalConfig};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("b2dr-eval-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn small_cfg(pkg: &std::path::Path) -> EvalConfig {
    EvalConfig {
        model: Some(pkg.to_path_buf()),
        scenarios: vec!["builtin:straight:100".into()],
        cameras: vec!["CAM_FRONT".into()],
        frames: vec![0, 3],
        lateral_m: vec![0.0, 2.0],
        yaw_deg: vec![],
        guidance: vec![2.0],
        drift_frames: 3,
        drift_scenarios: 1,
        steps: None,
        seed: 3,
        dtype: "f32".into(),
    }
}

fn files(dir: &std::path::Path) -> Vec<(String, Vec<u8>)> {
    let mut v = vec![];
    for sub in ["", "strips"] {
        let d = dir.join(sub);
        let mut names: Vec<_> = std::fs::read_dir(&d)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file() && !p.ends_with("timing.json"))
            .collect();
        names.sort();
        for p in names {
            v.push((p.display().to_string(), std::fs::read(&p).unwrap()));
        }
    }
    v
}

#[test]
fn eval_render_scores_reruns_identically_and_baselines_behave() {
    let Some(ctx) = common::ctx() else { return };
    let pkg = tmp("pkg");
    b2dr_package::small_package()
        .save(&pkg, b2dr::nn::weights::FileDType::F32)
        .unwrap();
    let cfg = small_cfg(&pkg);
    let (o1, o2) = (tmp("a"), tmp("b"));
    let r = eval_render(&ctx, &cfg, &o1).unwrap();
    eval_render(&ctx, &cfg, &o2).unwrap();
    common::assert_no_validation_errors();
    // bit-identical reruns (every output but timing.json)
    let (f1, f2) = (files(&o1), files(&o2));
    assert!(
        f1.len() >= 8,
        "outputs: {:?}",
        f1.iter().map(|f| &f.0).collect::<Vec<_>>()
    );
    assert_eq!(f1.len(), f2.len());
    for ((n1, b1), (_, b2)) in f1.iter().zip(&f2) {
        assert!(b1 == b2, "{n1} differs between reruns");
    }
    // frame 0 has no previous frame: skipped, and said so
    assert!(
        r.skipped.iter().any(|s| s.contains("frame 0")),
        "{:?}",
        r.skipped
    );
    let get = |setting: &str, lateral: f64| {
        r.single
            .iter()
            .find(|s| s.setting == setting && s.deviation.lateral_m == lateral)
            .unwrap_or_else(|| panic!("no {setting} at {lateral} m"))
    };
    // the copy of the nearest recorded frame is the ground truth on the logged path, not when displaced
    assert_eq!(get("copy-nearest", 0.0).psnr, None);
    assert_eq!(get("copy-nearest", 0.0).ssim, 1.0);
    let displaced = get("copy-nearest", 2.0);
    assert!(displaced.psnr.unwrap() < 30.0, "{:?}", displaced.psnr);
    // the previous frame shown unchanged: scored, not the truth, displaced as well
    let prev0 = get("copy-prev", 0.0);
    assert!(
        prev0.psnr.unwrap().is_finite() && prev0.ssim < 1.0,
        "{prev0:?}"
    );
    assert!(get("copy-prev", 2.0).psnr.unwrap().is_finite());
    // every setting of the logged path was rendered and scored
    for s in ["b2dr", "no-refs", "no-prev", "masks-only"] {
        let x = get(s, 0.0);
        assert!(x.psnr.unwrap().is_finite() && x.ssim.is_finite(), "{s}");
        assert!(x.mean_iou.is_some(), "{s}");
    }
    assert!(get("masks-only", 2.0).psnr.is_some());
    assert!(get("no-prev", 2.0).psnr.is_some());
    // drift: 3 frames of each setting; the n = 0 and blur overrides change the frames; no NaN / Inf
    let drift = |s: &str| -> Vec<f64> {
        r.drift
            .iter()
            .filter(|x| x.setting == s)
            .map(|x| x.psnr.unwrap())
            .collect()
    };
    let base = drift("b2dr");
    assert_eq!(base.len(), 3);
    for s in ["n=0", "blur 0", "blur 2", "f16"] {
        let d = drift(s);
        assert_eq!(d.len(), 3, "{s}");
        assert_ne!(
            d, base,
            "{s} renders the same frames as the model's setting"
        );
    }
    assert!(
        r.drift_nonfinite.values().all(|&n| n == 0),
        "{:?}",
        r.drift_nonfinite
    );
    // the classifier on the ground truth itself is good but not perfect
    let ceiling = r.classifier_ceiling["mean"].unwrap();
    assert!(ceiling > 0.5 && ceiling <= 1.0, "{ceiling}");
    let md = std::fs::read_to_string(o1.join("eval.md")).unwrap();
    assert!(
        md.contains("| copy-nearest | 1 | exact (= truth) | 1.0000 |"),
        "{md}"
    );
    // the falloff table: each setting's PSNR at 2 m minus its PSNR on the logged path (one frame), and the
    // references' gain with and without the previous frame
    let drop = |s: &str| get(s, 2.0).psnr.unwrap() - get(s, 0.0).psnr.unwrap();
    let (b, nr, np, mo) = (
        drop("b2dr"),
        drop("no-refs"),
        drop("no-prev"),
        drop("masks-only"),
    );
    let row = format!(
        "| lateral 2 m | 1 | {b:.2} | {nr:.2} | {:.2} | {np:.2} | {mo:.2} | {:.2} |",
        b - nr,
        np - mo
    );
    assert!(md.contains(&row), "{row} not in\n{md}");
}

#[test]
fn eval_render_refuses_bad_configurations() {
    let Some(ctx) = common::ctx() else { return };
    let pkg = tmp("pkg-bad");
    b2dr_package::small_package()
        .save(&pkg, b2dr::nn::weights::FileDType::F32)
        .unwrap();
    let out = tmp("bad");
    let bad = |f: &dyn Fn(&mut EvalConfig), want: &str| {
        let mut c = small_cfg(&pkg);
        c.drift_frames = 0;
        f(&mut c);
        let e = format!("{:#}", eval_render(&ctx, &c, &out).unwrap_err());
        assert!(e.contains(want), "{e}");
    };
    bad(&|c| c.scenarios.clear(), "no --scenario");
    bad(&|c| c.lateral_m = vec![f64::NAN], "--lateral");
    bad(&|c| c.guidance = vec![0.0], "--guidance");
    bad(&|c| c.cameras = vec!["CAM_NOPE".into()], "CAM_NOPE");
    bad(&|c| c.drift_frames = 500, "--drift-frames 500");
    bad(&|c| c.dtype = "f64".into(), "f64");
    bad(&|c| c.scenarios = vec!["builtin:nowhere".into()], "nowhere");
}
