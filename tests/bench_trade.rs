//! `b2dr bench trade --quick` on the built-in trained model: the reference setting's error against itself is
//! exactly 0, every point and extreme is finite (f16 included), and on a fixed seed more UniPC steps never move
//! the image further from the 50-step reference (beyond a 10 % margin for rounding noise); both layout judges
//! (colour classifier, segmenter) score every point.
mod common;

use b2dr::eval::trade::{bench_trade, TradeConfig};

#[test]
fn quick_sweep_is_exact_at_the_reference_finite_and_monotone_in_steps() {
    let Some(ctx) = common::ctx() else { return };
    let out = std::env::temp_dir().join(format!("b2dr-trade-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let mut cfg = TradeConfig::new(None, "builtin:straight:100".into(), true);
    cfg.rollout_frames = 3;
    let r = bench_trade(&ctx, &cfg, &out).unwrap();
    let reference = r.reference().unwrap();
    assert_eq!(reference.nmse_vs_reference, 0.0);
    assert!(reference.psnr_vs_reference.is_none());
    assert!(
        reference.pareto,
        "the reference has error 0: it is on the front"
    );
    for p in r.points.iter().chain(&r.extremes) {
        assert_eq!(p.nonfinite, 0, "{}", p.point.name);
        assert!(p.nmse_vs_reference.is_finite(), "{}", p.point.name);
        assert!(
            p.ms_per_frame > 0.0 && p.device_bytes > 0,
            "{}",
            p.point.name
        );
        // both layout judges score every point (straight:100 has vehicles and lane markings)
        for v in [p.vehicle_iou, p.seg_vehicle_iou, p.seg_marking_iou] {
            let v = v.unwrap_or_else(|| panic!("{}: no IoU", p.point.name));
            assert!((0.0..=1.0).contains(&v), "{}: {v}", p.point.name);
        }
    }
    let f16 = r
        .points
        .iter()
        .find(|p| p.point.name == "f16 unipc 50")
        .unwrap();
    assert!(
        f16.nmse_vs_reference > 0.0 && f16.nmse_vs_reference < 1e-3,
        "{}",
        f16.nmse_vs_reference
    );
    // UniPC steps 4 < 10 < 20 (the model's default) < 50 (the reference)
    let err = |steps: usize| {
        r.points
            .iter()
            .find(|p| {
                p.point.sampler == "unipc"
                    && p.point.steps == steps
                    && p.point.dtype == "f32"
                    && p.point.guidance == r.default_point().unwrap().point.guidance
                    && p.point.size == r.reference().unwrap().point.size
            })
            .unwrap()
            .nmse_vs_reference
    };
    let errs: Vec<f64> = [4, 10, 20, 50].iter().map(|&s| err(s)).collect();
    for w in errs.windows(2) {
        assert!(w[1] <= w[0] * 1.1, "error vs steps not monotone: {errs:?}");
    }
    assert!(
        errs[0] > 10.0 * errs[2],
        "4 steps should be far from the reference: {errs:?}"
    );
    assert_eq!(r.rollouts.len(), 2);
    for o in &r.rollouts {
        assert_eq!(o.nonfinite, 0, "{}", o.dtype);
    }
    for f in ["trade.json", "trade.md", "trade.png", "trade_truth.png"] {
        assert!(out.join(f).exists(), "{f}");
    }
    let md = std::fs::read_to_string(out.join("trade.md")).unwrap();
    assert!(md.contains("(default)") && md.contains("| reference *"));
    let _ = std::fs::remove_dir_all(&out);
    common::assert_no_validation_errors();
}

#[test]
fn bad_configurations_are_errors() {
    let Some(ctx) = common::ctx() else { return };
    let out = std::env::temp_dir().join(format!("b2dr-trade-bad-{}", std::process::id()));
    let mut cfg = TradeConfig::new(None, "builtin:straight:100".into(), true);
    cfg.frames = vec![0];
    let e = bench_trade(&ctx, &cfg, &out).unwrap_err().to_string();
    assert!(e.contains("--frames 0"), "{e}");
    cfg.frames = vec![8];
    cfg.cameras = 7;
    let e = bench_trade(&ctx, &cfg, &out).unwrap_err().to_string();
    assert!(e.contains("--cameras 7"), "{e}");
    cfg.cameras = 1;
    cfg.rollout_frames = 20_000;
    let e = bench_trade(&ctx, &cfg, &out).unwrap_err().to_string();
    assert!(e.contains("--rollout-frames"), "{e}");
}
