//! DDIM (diffusers `DDIMScheduler`), planned as linear combinations with f64 coefficients.
//!
//! Step at timestep `t`: `prev = t - T // n` (diffusers uses this for every spacing, so with `linspace`
//! spacing `prev` is not the next listed timestep — reproduced as is); `a_t = abar_t`,
//! `a_prev = abar_prev` or, when `prev < 0`, `1` (`set_alpha_to_one`) or `abar_0`;
//! `x0 = (x - sqrt(1 - a_t) eps) / sqrt(a_t)`, `std = eta sqrt((1-a_prev)/(1-a_t) (1 - a_t/a_prev))`,
//! `x_prev = sqrt(a_prev) x0 + sqrt(1 - a_prev - std^2) eps + std noise`.
//!
//! Spacing: b2dr's default is SD1.5's own `scheduler_config.json` as diffusers' `DDIMScheduler` reads it:
//! `leading` spacing, `steps_offset = 1`, `set_alpha_to_one = false`, `clip_sample = false`
//! (20 steps: 951, 901, ..., 1). With that setting 1000 steps would need `abar_1000`, outside the table
//! (diffusers raises an IndexError): planning returns an error naming the spacing; use `Linspace` or
//! `Trailing` (selectable in [`DdimConfig`]) for 1000 steps.

use super::schedule::{ddim_timesteps, NoiseSchedule, TimestepSpacing};
use super::{Buf, Op, PredictionType, SamplerPlan, StepPlan, Term};
use anyhow::{ensure, Result};

/// DDIM settings; `Default` is SD1.5's scheduler config.
#[derive(Clone, Debug, PartialEq)]
pub struct DdimConfig {
    /// 0 = deterministic DDIM; > 0 adds `std * Noise` per step.
    pub eta: f64,
    pub set_alpha_to_one: bool,
    pub steps_offset: i64,
    pub timestep_spacing: TimestepSpacing,
    pub prediction_type: PredictionType,
    /// `Some(r)`: clamp the x0 estimate to `[-r, r]` (diffusers `clip_sample` / `clip_sample_range`).
    pub clip_sample: Option<f64>,
}

impl Default for DdimConfig {
    fn default() -> Self {
        Self {
            eta: 0.0,
            set_alpha_to_one: false,
            steps_offset: 1,
            timestep_spacing: TimestepSpacing::Leading,
            prediction_type: PredictionType::Epsilon,
            clip_sample: None,
        }
    }
}

/// Plans `n` DDIM steps.
pub fn plan(schedule: &NoiseSchedule, cfg: &DdimConfig, n: usize) -> Result<SamplerPlan> {
    ensure!(
        cfg.eta >= 0.0 && cfg.eta.is_finite(),
        "DDIM eta {} must be >= 0",
        cfg.eta
    );
    let num_train = schedule.num_train_timesteps();
    let timesteps = ddim_timesteps(n, cfg.timestep_spacing, cfg.steps_offset, num_train)?;
    let final_alpha = if cfg.set_alpha_to_one {
        1.0
    } else {
        schedule.alpha_bar(0)?
    };
    let stride = (num_train / n) as i64;
    let mut steps = Vec::with_capacity(n);
    for (i, &ts) in timesteps.iter().enumerate() {
        let prev = ts - stride;
        let a_t = schedule.alpha_bar(ts)?;
        let a_prev = if prev >= 0 {
            schedule.alpha_bar(prev)?
        } else {
            final_alpha
        };
        let (sa, sb) = (a_t.sqrt(), (1.0 - a_t).sqrt());
        // x0 = x0x * Sample + x0e * Eps; eps_pred = ex * Sample + ee * Eps
        let (x0x, x0e, ex, ee) = match cfg.prediction_type {
            PredictionType::Epsilon => (1.0 / sa, -sb / sa, 0.0, 1.0),
            PredictionType::VPrediction => (sa, -sb, sb, sa),
            PredictionType::Sample => (0.0, 1.0, 1.0 / sb, -sa / sb),
        };
        let variance = (1.0 - a_prev) / (1.0 - a_t) * (1.0 - a_t / a_prev);
        let std = cfg.eta * variance.max(0.0).sqrt();
        let dir = (1.0 - a_prev - std * std).max(0.0).sqrt();
        let sp = a_prev.sqrt();
        let mut ops = Vec::new();
        let mut terms = if let Some(r) = cfg.clip_sample {
            // With clipping, diffusers keeps eps_pred from the unclipped estimate (use_clipped_model_output false).
            ops.push(Op::LinComb {
                out: Buf::X0(0),
                terms: nz(&[(Buf::Sample, x0x), (Buf::Eps, x0e)]),
            });
            ops.push(Op::Clamp {
                buf: Buf::X0(0),
                lo: -r,
                hi: r,
            });
            nz(&[
                (Buf::X0(0), sp),
                (Buf::Sample, dir * ex),
                (Buf::Eps, dir * ee),
            ])
        } else {
            nz(&[
                (Buf::Sample, sp * x0x + dir * ex),
                (Buf::Eps, sp * x0e + dir * ee),
            ])
        };
        if std > 0.0 {
            terms.push(Term {
                buf: Buf::Noise,
                coeff: std,
            });
        }
        ops.push(Op::LinComb {
            out: Buf::Sample,
            terms,
        });
        steps.push(StepPlan {
            index: i,
            timestep: ts,
            ops,
            predictor_order: 1,
            corrector_order: 0,
        });
    }
    Ok(SamplerPlan {
        sampler: "ddim",
        timesteps,
        steps,
        init_noise_sigma: 1.0,
    })
}

/// Terms with non-zero coefficients.
fn nz(v: &[(Buf, f64)]) -> Vec<Term> {
    v.iter()
        .filter(|(_, c)| *c != 0.0)
        .map(|(buf, coeff)| Term {
            buf: *buf,
            coeff: *coeff,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sd15_default_timesteps() {
        let p = plan(&NoiseSchedule::sd15(), &DdimConfig::default(), 20).unwrap();
        assert_eq!(p.timesteps[0], 951);
        assert_eq!(*p.timesteps.last().unwrap(), 1);
        let err = plan(&NoiseSchedule::sd15(), &DdimConfig::default(), 1000).unwrap_err();
        assert!(format!("{err:#}").contains("Leading"), "{err:#}");
        let cfg = DdimConfig {
            timestep_spacing: TimestepSpacing::Linspace,
            ..DdimConfig::default()
        };
        assert_eq!(
            plan(&NoiseSchedule::sd15(), &cfg, 1000)
                .unwrap()
                .steps
                .len(),
            1000
        );
    }
}
