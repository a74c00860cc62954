//! DDIM against diffusers' `DDIMScheduler`: timesteps per spacing, every latent of the synthetic 20-step
//! loop (tests/golden/sampling.json from tools/make_golden.py), and diffusers' own test_scheduler_ddim.py
//! full-loop numbers.

#[path = "golden/common.rs"]
mod common;

use b2dr::sampling::cpu::run_loop;
use b2dr::sampling::ddim::{self, DdimConfig};
use b2dr::sampling::{NoiseSchedule, PredictionType, TimestepSpacing};
use common::*;

fn synthetic(noise: &[f32]) -> impl FnMut(&[f32], i64) -> anyhow::Result<Vec<f32>> + '_ {
    move |x, t| {
        let s = ((t as f64) / 100.0).sin() as f32;
        Ok(x.iter()
            .zip(noise)
            .map(|(x, n)| 0.1f32 * x + s * n)
            .collect())
    }
}

fn variant(name: &str) -> DdimConfig {
    let spacing = match name {
        "sd15_leading" => TimestepSpacing::Leading,
        "linspace" => TimestepSpacing::Linspace,
        _ => TimestepSpacing::Trailing,
    };
    DdimConfig {
        timestep_spacing: spacing,
        ..DdimConfig::default()
    }
}

#[test]
fn timesteps_and_loops_match_diffusers() {
    let g = load_json("sampling.json");
    let x_t = f32s(&g["synthetic"]["x_T"]);
    let noise = f32s(&g["synthetic"]["noise"]);
    let s = NoiseSchedule::sd15();
    for name in ["sd15_leading", "linspace", "trailing"] {
        let v = &g["ddim"]["variants"][name];
        let cfg = variant(name);
        for n in [1usize, 2, 20, 25, 1000] {
            let want = i64s(&v["timesteps"][n.to_string()]);
            match ddim::plan(&s, &cfg, n) {
                Ok(p) => assert_eq!(
                    p.timesteps, want,
                    "DDIM {name} timesteps, {n} steps; {REGENERATE}"
                ),
                // leading + steps_offset 1 at 1000 steps lists t = 1000, outside the table (diffusers: IndexError)
                Err(e) => assert!(
                    n == 1000 && v.get("loop1000_error").is_some(),
                    "{name} {n}: {e:#}"
                ),
            }
        }
        let plan = ddim::plan(&s, &cfg, 20).unwrap();
        let ours = run_loop(&plan, x_t.clone(), synthetic(&noise)).unwrap();
        for (i, (a, b)) in ours.iter().zip(v["loop20"].as_array().unwrap()).enumerate() {
            assert_close(&format!("DDIM {name} step {i}"), a, &f32s(b), 1e-5);
        }
        if let Some(last) = v.get("loop1000_last") {
            let plan = ddim::plan(&s, &cfg, 1000).unwrap();
            let ours = run_loop(&plan, x_t.clone(), synthetic(&noise)).unwrap();
            assert_close(
                &format!("DDIM {name} 1000 steps"),
                ours.last().unwrap(),
                &f32s(last),
                1e-5,
            );
        }
    }
}

fn dummy_sample_deter() -> Vec<f32> {
    let n = 4 * 3 * 8 * 8;
    let mut v = vec![0f32; n];
    for b in 0..4 {
        for c in 0..3 {
            for h in 0..8 {
                for w in 0..8 {
                    v[((b * 3 + c) * 8 + h) * 8 + w] =
                        (((c * 8 + h) * 8 + w) * 4 + b) as f32 / n as f32;
                }
            }
        }
    }
    v
}

fn dummy_model(x: &[f32], t: i64) -> anyhow::Result<Vec<f32>> {
    let t = t as f32;
    Ok(x.iter().map(|v| v * t / (t + 1.0)).collect())
}

#[test]
fn diffusers_scheduler_test_full_loops() {
    // DDIMScheduler defaults in that test: leading, steps_offset 0, set_alpha_to_one true, clip_sample true.
    let base = DdimConfig {
        set_alpha_to_one: true,
        steps_offset: 0,
        clip_sample: Some(1.0),
        ..DdimConfig::default()
    };
    let cases = [
        (
            NoiseSchedule::linear(0.0001, 0.02, 1000),
            base.clone(),
            172.0067,
            0.223967,
        ),
        (
            NoiseSchedule::linear(0.0001, 0.02, 1000),
            DdimConfig {
                prediction_type: PredictionType::VPrediction,
                ..base.clone()
            },
            52.5302,
            0.0684,
        ),
        (
            NoiseSchedule::linear(0.01, 0.02, 1000),
            base.clone(),
            149.8295,
            0.1951,
        ),
        (
            NoiseSchedule::linear(0.01, 0.02, 1000),
            DdimConfig {
                set_alpha_to_one: false,
                ..base
            },
            149.0784,
            0.1941,
        ),
    ];
    for (i, (sched, cfg, want_sum, want_mean)) in cases.into_iter().enumerate() {
        let plan = ddim::plan(&sched, &cfg, 10).unwrap();
        let out = run_loop(&plan, dummy_sample_deter(), dummy_model).unwrap();
        let x = out.last().unwrap();
        let sum: f64 = x.iter().map(|v| v.abs() as f64).sum();
        assert!(
            (sum - want_sum).abs() < 1e-2,
            "case {i}: sum {sum} vs {want_sum}"
        );
        assert!((sum / x.len() as f64 - want_mean).abs() < 1e-3, "case {i}");
    }
}

#[test]
fn eta_needs_noise_and_is_finite() {
    let cfg = DdimConfig {
        eta: 1.0,
        ..DdimConfig::default()
    };
    let plan = ddim::plan(&NoiseSchedule::sd15(), &cfg, 20).unwrap();
    assert!(plan.needs_noise());
    assert!(run_loop(&plan, vec![0.5; 8], |x, _| Ok(x.to_vec())).is_err());
    let one = ddim::plan(&NoiseSchedule::sd15(), &DdimConfig::default(), 1).unwrap();
    let out = run_loop(&one, vec![0.5; 8], |x, _| Ok(x.to_vec())).unwrap();
    assert!(out[0].iter().all(|v| v.is_finite()));
}
