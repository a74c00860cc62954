//! UniPC against diffusers' `UniPCMultistepScheduler`: timesteps, sigmas and every latent of synthetic
//! loops (tests/golden/sampling.json from tools/make_golden.py), and the numbers diffusers' own
//! tests/schedulers/test_scheduler_unipc.py asserts.

#[path = "golden/common.rs"]
mod common;

use b2dr::sampling::cpu::{run_loop, CpuSampler};
use b2dr::sampling::unipc::{self, FinalSigmas, UniPcConfig};
use b2dr::sampling::{apply_guidance, Buf, NoiseSchedule, PredictionType};
use common::*;
use serde_json::Value;

/// eps = 0.1 x + sin(t / 100) noise, in f32 like the golden generator.
fn synthetic(noise: &[f32]) -> impl FnMut(&[f32], i64) -> anyhow::Result<Vec<f32>> + '_ {
    move |x, t| {
        let s = ((t as f64) / 100.0).sin() as f32;
        Ok(x.iter()
            .zip(noise)
            .map(|(x, n)| 0.1f32 * x + s * n)
            .collect())
    }
}

fn golden() -> Value {
    load_json("sampling.json")
}

fn diffusers_schedule(g: &Value) -> NoiseSchedule {
    NoiseSchedule::from_alphas_cumprod(f64s(&g["alphas_cumprod"])).unwrap()
}

#[test]
fn sd15_alphas_cumprod_match_diffusers() {
    let g = golden();
    let want = f64s(&g["alphas_cumprod"]);
    let ours = NoiseSchedule::sd15();
    for (t, (a, b)) in ours.alphas_cumprod().iter().zip(&want).enumerate() {
        assert!(
            ((a - b) / b).abs() < 2e-6,
            "abar[{t}] = {a}, diffusers {b}; {REGENERATE}"
        );
    }
}

#[test]
fn timesteps_and_sigmas_match_diffusers() {
    let g = golden();
    let s = NoiseSchedule::sd15();
    let cfg = UniPcConfig::default();
    for n in [1usize, 2, 20, 25, 1000] {
        let want = i64s(&g["unipc"]["timesteps"][n.to_string()]);
        let plan = unipc::plan(&s, &cfg, n).unwrap();
        assert_eq!(
            plan.timesteps, want,
            "UniPC timesteps for {n} steps; {REGENERATE}"
        );
        let sig = unipc::sigmas(&s, &cfg, &plan.timesteps).unwrap();
        let want_sig = f64s(&g["unipc"]["sigmas"][n.to_string()]);
        assert_eq!(sig.len(), want_sig.len());
        for (a, b) in sig.iter().zip(&want_sig) {
            assert!(
                (a - b).abs() <= 1e-5 * b.abs().max(1e-3),
                "sigma {a} vs diffusers {b} ({n} steps)"
            );
        }
        // diffusers builds sigmas from f32 (1 - abar): ~3e-6 relative error near t = 0.
        assert_eq!(*sig.last().unwrap(), 0.0);
    }
}

fn check_loop(g: &Value, key: &str, n: usize, schedule: &NoiseSchedule, tol: f64) -> f64 {
    let x_t = f32s(&g["synthetic"]["x_T"]);
    let noise = f32s(&g["synthetic"]["noise"]);
    let plan = unipc::plan(schedule, &UniPcConfig::default(), n).unwrap();
    let ours = run_loop(&plan, x_t, synthetic(&noise)).unwrap();
    let want = g["unipc"][key].as_array().unwrap();
    assert_eq!(want.len(), n);
    let mut worst: f64 = 0.0;
    for (i, (a, b)) in ours.iter().zip(want).enumerate() {
        let b = f32s(b);
        worst = worst.max(nmse(a, &b));
        assert_close(&format!("UniPC {key} step {i}"), a, &b, tol);
    }
    worst
}

#[test]
fn loop20_every_step_matches_diffusers() {
    let g = golden();
    let w = check_loop(&g, "loop20", 20, &NoiseSchedule::sd15(), 1e-5);
    println!("UniPC 20 steps, f64 SD1.5 schedule: worst per-step nMSE {w:.3e}");
    // With diffusers' own f32 alphas_cumprod table the remaining difference is f32 rounding.
    let w = check_loop(&g, "loop20", 20, &diffusers_schedule(&g), 1e-10);
    println!("UniPC 20 steps, diffusers' abar table: worst per-step nMSE {w:.3e}");
}

#[test]
fn loop25_and_loop1_match_diffusers() {
    let g = golden();
    check_loop(&g, "loop25", 25, &NoiseSchedule::sd15(), 1e-5);
    check_loop(&g, "loop1", 1, &NoiseSchedule::sd15(), 1e-5);
}

#[test]
fn loop1000_matches_diffusers_until_its_nan_and_stays_finite() {
    let g = golden();
    let x_t = f32s(&g["synthetic"]["x_T"]);
    let noise = f32s(&g["synthetic"]["noise"]);
    let l = &g["unipc"]["loop1000"];
    let first_nan = l["first_nonfinite_step"].as_u64();
    let plan = unipc::plan(&NoiseSchedule::sd15(), &UniPcConfig::default(), 1000).unwrap();
    let ours = run_loop(&plan, x_t, synthetic(&noise)).unwrap();
    assert!(
        ours.iter().all(|x| x.iter().all(|v| v.is_finite())),
        "1000-step UniPC produced NaN/Inf"
    );
    let mut compared = 0;
    for (k, v) in l["latents_every_10"].as_object().unwrap() {
        let i: usize = k.parse().unwrap();
        assert_close(
            &format!("UniPC 1000-step loop, step {i}"),
            &ours[i],
            &f32s(v),
            1e-5,
        );
        compared += 1;
    }
    assert!(compared >= 40, "only {compared} golden steps");
    println!("1000 steps: diffusers goes NaN at step {first_nan:?} (repeated t = 500); b2dr stays finite");
}

/// diffusers' SchedulerCommonTest.dummy_sample_deter: (4, 3, 8, 8), value = flat index of (c, h, w, b) / 768.
fn dummy_sample_deter(flip: bool) -> Vec<f32> {
    let n = 4 * 3 * 8 * 8;
    let mut v = vec![0f32; n];
    for b in 0..4 {
        for c in 0..3 {
            for h in 0..8 {
                for w in 0..8 {
                    let k = ((c * 8 + h) * 8 + w) * 4 + b;
                    let k = if flip { n - 1 - k } else { k };
                    v[((b * 3 + c) * 8 + h) * 8 + w] = k as f32 / n as f32;
                }
            }
        }
    }
    v
}

/// diffusers' dummy_model: sample * t / (t + 1).
fn dummy_model(x: &[f32], t: i64) -> anyhow::Result<Vec<f32>> {
    let t = t as f32;
    Ok(x.iter().map(|v| v * t / (t + 1.0)).collect())
}

fn test_config(prediction_type: PredictionType) -> UniPcConfig {
    UniPcConfig {
        final_sigmas: FinalSigmas::SigmaMin,
        prediction_type,
        ..UniPcConfig::default()
    }
}

fn mean_abs(x: &[f32]) -> f64 {
    x.iter().map(|v| v.abs() as f64).sum::<f64>() / x.len() as f64
}

#[test]
fn diffusers_scheduler_test_full_loops() {
    let g = golden();
    let sched = NoiseSchedule::linear(0.0001, 0.02, 1000);
    // test_full_loop_no_noise: mean |x| ~ 0.2464 (+-1e-3 in diffusers' test)
    let plan = unipc::plan(&sched, &test_config(PredictionType::Epsilon), 10).unwrap();
    let out = run_loop(&plan, dummy_sample_deter(false), dummy_model).unwrap();
    let x = out.last().unwrap();
    assert!((mean_abs(x) - 0.2464).abs() < 1e-3, "mean {}", mean_abs(x));
    assert_close(
        "diffusers test full_loop",
        x,
        &f32s(&g["diffusers_tests"]["unipc_full_loop"]["result"]),
        1e-10,
    );
    // test_full_loop_with_v_prediction: 0.1014
    let plan = unipc::plan(&sched, &test_config(PredictionType::VPrediction), 10).unwrap();
    let out = run_loop(&plan, dummy_sample_deter(false), dummy_model).unwrap();
    let x = out.last().unwrap();
    assert!(
        (mean_abs(x) - 0.1014).abs() < 1e-3,
        "v-prediction mean {}",
        mean_abs(x)
    );
    let want = f32s(&g["diffusers_tests"]["unipc_full_loop_v_prediction"]["result"]);
    assert_close("diffusers test full_loop v_prediction", x, &want, 1e-10);
}

#[test]
fn diffusers_scheduler_test_full_loop_with_noise() {
    let sched = NoiseSchedule::linear(0.0001, 0.02, 1000);
    let cfg = test_config(PredictionType::Epsilon);
    let (a, s) = unipc::add_noise_coeffs(&sched, &cfg, 10, 8).unwrap();
    let x0 = dummy_sample_deter(false);
    let nz = dummy_sample_deter(true);
    let x: Vec<f32> = x0
        .iter()
        .zip(&nz)
        .map(|(x, n)| (a * *x as f64 + s * *n as f64) as f32)
        .collect();
    let plan = unipc::plan_from(&sched, &cfg, 10, 8).unwrap();
    let out = run_loop(&plan, x, dummy_model).unwrap();
    let x = out.last().unwrap();
    let sum: f64 = x.iter().map(|v| v.abs() as f64).sum();
    // test_full_loop_with_noise: sum 315.5757 (+-1e-2), mean 0.4109 (+-1e-3)
    assert!((sum - 315.5757).abs() < 1e-2, "sum {sum}");
    assert!((mean_abs(x) - 0.4109).abs() < 1e-3);
}

#[test]
fn determinism_bitwise() {
    let g = golden();
    let x_t = f32s(&g["synthetic"]["x_T"]);
    let noise = f32s(&g["synthetic"]["noise"]);
    let plan = unipc::plan(&NoiseSchedule::sd15(), &UniPcConfig::default(), 20).unwrap();
    let a = run_loop(&plan, x_t.clone(), synthetic(&noise)).unwrap();
    let b = run_loop(&plan, x_t, synthetic(&noise)).unwrap();
    for (x, y) in a.iter().zip(&b) {
        assert!(x.iter().zip(y).all(|(p, q)| p.to_bits() == q.to_bits()));
    }
}

#[test]
fn guidance_folded_into_plan_matches_host_guidance() {
    let g = golden();
    let x_t = f32s(&g["synthetic"]["x_T"]);
    let noise = f32s(&g["synthetic"]["noise"]);
    let scale = 7.5;
    let plan = unipc::plan(&NoiseSchedule::sd15(), &UniPcConfig::default(), 20).unwrap();
    let folded = plan.with_guidance(scale);
    let uncond = |x: &[f32]| -> Vec<f32> { x.iter().map(|v| 0.1 * v).collect() };
    let cond = |x: &[f32], t: i64| -> Vec<f32> { synthetic(&noise)(x, t).unwrap() };
    let (mut a, mut b) = (CpuSampler::new(x_t.clone()), CpuSampler::new(x_t));
    for (sa, sb) in plan.steps.iter().zip(&folded.steps) {
        let eps =
            apply_guidance(&uncond(a.sample()), &cond(a.sample(), sa.timestep), scale).unwrap();
        a.set(Buf::Eps, eps).unwrap();
        a.apply(sa).unwrap();
        let (u, c) = (uncond(b.sample()), cond(b.sample(), sb.timestep));
        b.set(Buf::EpsUncond, u).unwrap();
        b.set(Buf::EpsCond, c).unwrap();
        b.apply(sb).unwrap();
    }
    assert!(
        nmse(a.sample(), b.sample()) < 1e-10,
        "{}",
        nmse(a.sample(), b.sample())
    );
}

/// Other diffusers settings (order 1 and 3, bh1, disabled correctors, no lower-order final, leading and
/// trailing spacing, v-prediction), each read through `sampling::config::from_diffusers_json` from the
/// config diffusers ran with.
#[test]
fn unipc_variants_match_diffusers() {
    let g = golden();
    let x_t = f32s(&g["synthetic"]["x_T"]);
    let noise = f32s(&g["synthetic"]["noise"]);
    let variants = g["unipc"]["variants"].as_object().unwrap();
    assert!(variants.len() >= 9);
    for (name, v) in variants {
        let s = b2dr::sampling::config::from_diffusers_json(&v["config"]).unwrap();
        let plan = unipc::plan(&s.schedule, &s.unipc, 20).unwrap();
        assert_eq!(
            plan.timesteps,
            i64s(&v["timesteps"]),
            "UniPC {name} timesteps; {REGENERATE}"
        );
        let ours = run_loop(&plan, x_t.clone(), synthetic(&noise)).unwrap();
        let mut worst: f64 = 0.0;
        for (i, (a, b)) in ours.iter().zip(v["loop20"].as_array().unwrap()).enumerate() {
            assert!(!b.is_null(), "diffusers produced NaN in {name} step {i}");
            let b = f32s(b);
            worst = worst.max(nmse(a, &b));
            assert_close(&format!("UniPC {name} step {i}"), a, &b, 1e-5);
        }
        println!("UniPC {name}: worst per-step nMSE {worst:.3e}");
    }
}
