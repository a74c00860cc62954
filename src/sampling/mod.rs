//! Samplers: the SD1.5 noise schedule, UniPC multistep and DDIM, planned on the host in f64.
//!
//! ## Design: a sampler is a plan of scale-and-add operations
//! Every sampler step used here is linear in the tensors it has seen (the current sample, the model
//! output, earlier x0 estimates), so a whole sampling run is planned once on the host:
//! [`SamplerPlan`] lists, per step, the timestep to evaluate the model at and a short sequence of
//! [`Op`]s, each `out = sum_k c_k * buf_k` with f64 coefficients (or, for DDIM's optional `clip_sample`,
//! a clamp). The device side applies each op with one scale-and-add kernel over buffers it allocated once
//! ([`SamplerPlan::buffers`]); [`cpu::CpuSampler`] applies the same plan on `f32` host slices and is the
//! oracle in tests. Classifier-free guidance is folded in with [`SamplerPlan::with_guidance`]
//! (`eps = eps_u + s (eps_c - eps_u)` becomes two terms per use of `eps`).
//!
//! Buffers: `Sample` is the model input and, after the last step, the result; `Eps` is the model output
//! (or `EpsUncond`/`EpsCond` after guidance folding); `X0(k)` is a ring of x0 estimates (UniPC keeps
//! `solver_order + 1`), `Hat(k)` a ring of two corrected samples (UniPC's `last_sample`), `Noise` the
//! per-step noise for DDIM with `eta > 0`.
//!
//! Numerics follow diffusers' `UniPCMultistepScheduler` / `DDIMScheduler` (their source is the reference);
//! deviations, all in degenerate cases where diffusers returns NaN or raises, are documented in
//! [`unipc`] and [`ddim`].

pub mod config;
pub mod cpu;
pub mod ddim;
pub mod schedule;
pub mod unipc;

pub use schedule::{NoiseSchedule, TimestepSpacing};

/// Largest guidance scale accepted anywhere (a model package's `ref_guidance` in `b2dr.json`, `--ref-guidance`
/// of `render` and `bench frame`, `--guidance` and `--conditioning-scale` of `sample`): beyond it the guided
/// prediction is noise scaled past anything f16 holds.
pub const MAX_GUIDANCE: f64 = 100.0;

/// `Err` naming `flag` unless `w` is a guidance scale in (0, [`MAX_GUIDANCE`]] (issue #36, item 7: the same
/// bound as `b2dr.json`'s `ref_guidance`).
pub fn check_guidance(flag: &str, w: f64) -> Result<()> {
    anyhow::ensure!(
        w.is_finite() && w > 0.0 && w <= MAX_GUIDANCE,
        "{flag} {w}: must be a finite guidance scale in (0, {MAX_GUIDANCE}]"
    );
    Ok(())
}

/// `Err` naming `flag` unless `s` is a ControlNet conditioning scale in [0, [`MAX_GUIDANCE`]] (0: the
/// ControlNet off).
pub fn check_conditioning_scale(flag: &str, s: f64) -> Result<()> {
    anyhow::ensure!(
        s.is_finite() && (0.0..=MAX_GUIDANCE).contains(&s),
        "{flag} {s}: must be a finite conditioning scale in [0, {MAX_GUIDANCE}]"
    );
    Ok(())
}

use anyhow::{bail, Result};

/// What the model predicts (diffusers' `prediction_type`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PredictionType {
    /// The noise `eps` (SD1.5).
    Epsilon,
    /// `v = alpha eps - sigma x0`.
    VPrediction,
    /// The clean sample `x0`.
    Sample,
}

impl PredictionType {
    /// Parses diffusers' config value.
    pub fn parse(s: &str) -> Result<Self> {
        Ok(match s {
            "epsilon" => Self::Epsilon,
            "v_prediction" => Self::VPrediction,
            "sample" => Self::Sample,
            other => {
                bail!("prediction_type {other:?} is not supported (epsilon, v_prediction, sample)")
            }
        })
    }
}

/// The sampler families (`--sampler`, a model package's `sampler`): parsed once where the name is read,
/// written back by `Display` / serde as the same lowercase name.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SamplerKind {
    /// UniPC (diffusers `UniPCMultistepScheduler`, the renderer's default).
    Unipc,
    /// DDIM (diffusers `DDIMScheduler`).
    Ddim,
}

impl std::str::FromStr for SamplerKind {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "unipc" => Self::Unipc,
            "ddim" => Self::Ddim,
            other => bail!("--sampler {other:?}: expected unipc or ddim"),
        })
    }
}

impl std::fmt::Display for SamplerKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Unipc => "unipc",
            Self::Ddim => "ddim",
        })
    }
}

impl SamplerKind {
    /// The host plan of `steps` steps on schedule `s` for a model that predicts `prediction` (the other
    /// settings: each sampler's `Default`).
    pub fn plan(
        self,
        s: &NoiseSchedule,
        prediction: PredictionType,
        steps: usize,
    ) -> Result<SamplerPlan> {
        match self {
            Self::Unipc => unipc::plan(
                s,
                &unipc::UniPcConfig {
                    prediction_type: prediction,
                    ..Default::default()
                },
                steps,
            ),
            Self::Ddim => ddim::plan(
                s,
                &ddim::DdimConfig {
                    prediction_type: prediction,
                    ..Default::default()
                },
                steps,
            ),
        }
    }
}

/// A sampler buffer, all of the latent's shape `(N, C, H, W)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Buf {
    /// The current sample: model input before a step, the next sample after it.
    Sample,
    /// The model output at this step (guided, if guidance is applied outside the plan).
    Eps,
    /// The unconditional half of a guided batch (after [`SamplerPlan::with_guidance`]).
    EpsUncond,
    /// The conditional half of a guided batch (after [`SamplerPlan::with_guidance`]).
    EpsCond,
    /// Fresh standard normal noise for this step (DDIM with `eta > 0`).
    Noise,
    /// Ring slot of x0 estimates.
    X0(u8),
    /// Ring slot of corrected samples.
    Hat(u8),
}

/// One term `coeff * buf` of a linear combination.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Term {
    pub buf: Buf,
    pub coeff: f64,
}

/// One operation of a step; applied in order after the model output of the step is in `Eps`.
#[derive(Clone, Debug, PartialEq)]
pub enum Op {
    /// `out = sum terms` (element-wise; `out` may also appear among the inputs).
    LinComb { out: Buf, terms: Vec<Term> },
    /// `buf = clamp(buf, lo, hi)` (DDIM `clip_sample`).
    Clamp { buf: Buf, lo: f64, hi: f64 },
}

/// Everything about one sampler step.
#[derive(Clone, Debug, PartialEq)]
pub struct StepPlan {
    /// Index of the step in the full schedule.
    pub index: usize,
    /// Timestep the model is evaluated at (on `Sample`).
    pub timestep: i64,
    /// Operations to apply once the model output is available.
    pub ops: Vec<Op>,
    /// UniPC: predictor order of this step; DDIM: 1.
    pub predictor_order: usize,
    /// UniPC: order of the corrector applied at the start of this step (0 = none); DDIM: 0.
    pub corrector_order: usize,
}

/// A whole sampling run, planned for a number of steps.
#[derive(Clone, Debug, PartialEq)]
pub struct SamplerPlan {
    /// `"unipc"` or `"ddim"`.
    pub sampler: &'static str,
    /// The timesteps of the steps, in order.
    pub timesteps: Vec<i64>,
    /// Per-step operations.
    pub steps: Vec<StepPlan>,
    /// Standard deviation of the initial noise (1 for both samplers here).
    pub init_noise_sigma: f64,
}

impl SamplerPlan {
    /// All buffers the plan reads or writes (sorted; `Sample` and the model-output buffers included).
    pub fn buffers(&self) -> Vec<Buf> {
        let mut v: Vec<Buf> = vec![Buf::Sample];
        for op in self.steps.iter().flat_map(|s| s.ops.iter()) {
            match op {
                Op::LinComb { out, terms } => {
                    v.push(*out);
                    v.extend(terms.iter().map(|t| t.buf));
                }
                Op::Clamp { buf, .. } => v.push(*buf),
            }
        }
        v.sort();
        v.dedup();
        v
    }

    /// The largest number of terms of one op (sizes the scale-and-add kernel's parameter block; UniPC
    /// order 2: 4, or 4 with guidance folded in).
    pub fn max_terms(&self) -> usize {
        self.steps
            .iter()
            .flat_map(|s| &s.ops)
            .map(|op| match op {
                Op::LinComb { terms, .. } => terms.len(),
                Op::Clamp { .. } => 1,
            })
            .max()
            .unwrap_or(0)
    }

    /// Whether a step reads [`Buf::Noise`].
    pub fn needs_noise(&self) -> bool {
        self.buffers().contains(&Buf::Noise)
    }

    /// Folds classifier-free guidance `eps = eps_u + scale (eps_c - eps_u)` into the plan: every
    /// `c * Eps` term becomes `c (1 - scale) * EpsUncond + c scale * EpsCond`.
    pub fn with_guidance(&self, scale: f64) -> SamplerPlan {
        let mut plan = self.clone();
        for op in plan.steps.iter_mut().flat_map(|s| s.ops.iter_mut()) {
            if let Op::LinComb { terms, .. } = op {
                let mut out = Vec::with_capacity(terms.len() + 1);
                for t in terms.iter() {
                    if t.buf == Buf::Eps {
                        let [u, c] = guidance_coeffs(scale);
                        out.push(Term {
                            buf: Buf::EpsUncond,
                            coeff: t.coeff * u,
                        });
                        out.push(Term {
                            buf: Buf::EpsCond,
                            coeff: t.coeff * c,
                        });
                    } else {
                        out.push(*t);
                    }
                }
                *terms = out;
            }
        }
        plan
    }
}

/// Coefficients `[c_uncond, c_cond]` of classifier-free guidance: `eps = c_u eps_u + c_c eps_c`.
pub fn guidance_coeffs(scale: f64) -> [f64; 2] {
    [1.0 - scale, scale]
}

/// Applies classifier-free guidance on the host, diffusers' way: `eps_u + s (eps_c - eps_u)`.
/// `eps_u`, `eps_c`: `(N, C, H, W)` halves of the guided batch.
pub fn apply_guidance(eps_u: &[f32], eps_c: &[f32], scale: f64) -> Result<Vec<f32>> {
    if eps_u.len() != eps_c.len() {
        bail!(
            "guidance: uncond has {} values, cond {}",
            eps_u.len(),
            eps_c.len()
        );
    }
    Ok(eps_u
        .iter()
        .zip(eps_c)
        .map(|(u, c)| (*u as f64 + scale * (*c as f64 - *u as f64)) as f32)
        .collect())
}

/// Solves the small dense system `a x = b` (Gaussian elimination with partial pivoting, f64).
pub(crate) fn solve_small(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Result<Vec<f64>> {
    let n = b.len();
    for col in 0..n {
        let piv = (col..n)
            .max_by(|i, j| a[*i][col].abs().total_cmp(&a[*j][col].abs()))
            .unwrap_or(col);
        if a[piv][col].abs() < 1e-300 || !a[piv][col].is_finite() {
            bail!("singular {n}x{n} system in the UniPC coefficients");
        }
        a.swap(col, piv);
        b.swap(col, piv);
        let pivot = a[col].clone();
        for row in col + 1..n {
            let f = a[row][col] / pivot[col];
            for (x, p) in a[row].iter_mut().zip(&pivot).skip(col) {
                *x -= f * p;
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = vec![0.0; n];
    for row in (0..n).rev() {
        let s: f64 = (row + 1..n).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    Ok(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solve_2x2() {
        let x = solve_small(vec![vec![1.0, 1.0], vec![-0.5, 1.0]], vec![3.0, 0.0]).unwrap();
        assert!((x[0] - 2.0).abs() < 1e-12 && (x[1] - 1.0).abs() < 1e-12);
        assert!(solve_small(vec![vec![1.0, 1.0], vec![1.0, 1.0]], vec![1.0, 2.0]).is_err());
    }

    #[test]
    fn guidance_fold() {
        let plan = SamplerPlan {
            sampler: "test",
            timesteps: vec![1],
            steps: vec![StepPlan {
                index: 0,
                timestep: 1,
                ops: vec![Op::LinComb {
                    out: Buf::Sample,
                    terms: vec![
                        Term {
                            buf: Buf::Sample,
                            coeff: 1.0,
                        },
                        Term {
                            buf: Buf::Eps,
                            coeff: 2.0,
                        },
                    ],
                }],
                predictor_order: 1,
                corrector_order: 0,
            }],
            init_noise_sigma: 1.0,
        };
        let g = plan.with_guidance(7.5);
        assert_eq!(g.buffers(), vec![Buf::Sample, Buf::EpsUncond, Buf::EpsCond]);
        let Op::LinComb { terms, .. } = &g.steps[0].ops[0] else {
            panic!()
        };
        assert_eq!(terms[1].coeff, 2.0 * (1.0 - 7.5));
        assert_eq!(terms[2].coeff, 15.0);
    }
}
