//! UniPC multistep (diffusers `UniPCMultistepScheduler`, data prediction `predict_x0 = true`, B(h) = bh1 or
//! bh2), planned as linear combinations with f64 coefficients.
//!
//! Notation (per step `i`, schedule sigma `sigma_i`, last one `sigma_N` = 0 with `final_sigmas = Zero`):
//! `alpha_i = 1/sqrt(sigma_i^2 + 1)`, `s_i = sigma_i alpha_i`, `lambda_i = ln alpha_i - ln s_i`, x0 estimate
//! `m_i = (x_i - s_i eps_i)/alpha_i`. Step `i`: compute `m_i`; if `i > start` apply the corrector UniC-p
//! (p = the previous predictor's order) to get the corrected `x_i` from the previous corrected sample and
//! `m_{i-p} .. m_i`; then the predictor UniP-q to `x_{i+1}` with
//! `q = min(solver_order, N - i [lower_order_final], steps done + 1)`.
//!
//! Deviations from diffusers, all where diffusers produces NaN:
//! - A step to sigma 0 is `x_{i+1} = m_i` (the exact order-1 limit; diffusers gets the same value for
//!   bh2 with order 1 but NaN for bh1 or order >= 2 there, since `lambda = inf`).
//! - Repeated timesteps (linspace spacing with N close to T, e.g. N = 1000 repeats t = 500) give `h = 0`:
//!   the step is the identity, and a multistep term whose ratio `r_k` is 0 or not finite is dropped
//!   (the order falls). diffusers divides by zero there and the whole run becomes NaN.

use super::schedule::{multistep_timesteps, NoiseSchedule, TimestepSpacing};
use super::{solve_small, Buf, Op, PredictionType, SamplerPlan, StepPlan, Term};
use anyhow::{bail, ensure, Result};

/// diffusers' `solver_type`: the `B(h)` of UniPC.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SolverType {
    /// `B(h) = h`.
    Bh1,
    /// `B(h) = e^h - 1` (recommended for guided sampling; SD default).
    Bh2,
}

/// diffusers' `final_sigmas_type`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FinalSigmas {
    /// The last step goes to sigma 0 (SD default).
    Zero,
    /// The last step goes to sigma at t = 0.
    SigmaMin,
}

/// UniPC settings; `Default` is the SD setting the renderer uses.
#[derive(Clone, Debug, PartialEq)]
pub struct UniPcConfig {
    pub solver_order: usize,
    pub solver_type: SolverType,
    pub lower_order_final: bool,
    /// Step indices whose following corrector is disabled (diffusers: corrector at step i is skipped when
    /// `i - 1` is listed).
    pub disable_corrector: Vec<usize>,
    pub prediction_type: PredictionType,
    pub timestep_spacing: TimestepSpacing,
    pub steps_offset: i64,
    pub final_sigmas: FinalSigmas,
}

impl Default for UniPcConfig {
    fn default() -> Self {
        Self {
            solver_order: 2,
            solver_type: SolverType::Bh2,
            lower_order_final: true,
            disable_corrector: Vec::new(),
            prediction_type: PredictionType::Epsilon,
            timestep_spacing: TimestepSpacing::Linspace,
            steps_offset: 0,
            final_sigmas: FinalSigmas::Zero,
        }
    }
}

/// Per-schedule-point quantities.
struct Pt {
    alpha: f64,
    s: f64,
    lambda: f64,
}

fn pt(sigma: f64) -> Pt {
    let alpha = 1.0 / (sigma * sigma + 1.0).sqrt();
    let s = sigma * alpha;
    // sigma = 0 gives lambda = +inf; it is never used in arithmetic (see `final step` below).
    let lambda = if s > 0.0 {
        alpha.ln() - s.ln()
    } else {
        f64::INFINITY
    };
    Pt { alpha, s, lambda }
}

/// Plans `n` UniPC steps over the whole schedule.
pub fn plan(schedule: &NoiseSchedule, cfg: &UniPcConfig, n: usize) -> Result<SamplerPlan> {
    plan_from(schedule, cfg, n, 0)
}

/// The sigmas (one per timestep plus the final one) diffusers' `set_timesteps` builds.
pub fn sigmas(schedule: &NoiseSchedule, cfg: &UniPcConfig, timesteps: &[i64]) -> Result<Vec<f64>> {
    let mut sig = timesteps
        .iter()
        .map(|t| schedule.sigma(*t))
        .collect::<Result<Vec<f64>>>()?;
    sig.push(match cfg.final_sigmas {
        FinalSigmas::Zero => 0.0,
        FinalSigmas::SigmaMin => schedule.sigma(0)?,
    });
    Ok(sig)
}

/// Forward-noising coefficients `(alpha, s)` of `x = alpha x0 + s noise` at step `index` of an `n`-step
/// schedule (diffusers `UniPCMultistepScheduler.add_noise`).
pub fn add_noise_coeffs(
    schedule: &NoiseSchedule,
    cfg: &UniPcConfig,
    n: usize,
    index: usize,
) -> Result<(f64, f64)> {
    let ts = multistep_timesteps(
        n,
        cfg.timestep_spacing,
        cfg.steps_offset,
        schedule.num_train_timesteps(),
    )?;
    let sig = sigmas(schedule, cfg, &ts)?;
    ensure!(index < n, "step index {index} out of range for {n} steps");
    let p = pt(sig[index]);
    Ok((p.alpha, p.s))
}

/// Plans steps `start..n` of an `n`-step schedule (img2img starts at `start > 0`; the multistep history
/// starts empty there, as in diffusers).
pub fn plan_from(
    schedule: &NoiseSchedule,
    cfg: &UniPcConfig,
    n: usize,
    start: usize,
) -> Result<SamplerPlan> {
    ensure!(
        (1..=3).contains(&cfg.solver_order),
        "UniPC solver_order {} is not supported (1..=3)",
        cfg.solver_order
    );
    let timesteps = multistep_timesteps(
        n,
        cfg.timestep_spacing,
        cfg.steps_offset,
        schedule.num_train_timesteps(),
    )?;
    ensure!(start < n, "start step {start} is not below the {n} steps");
    let sig = sigmas(schedule, cfg, &timesteps)?;
    let pts: Vec<Pt> = sig.iter().map(|s| pt(*s)).collect();
    let ring = cfg.solver_order + 1;
    let x0 = |i: usize| Buf::X0((i % ring) as u8);
    let hat = |i: usize| Buf::Hat((i % 2) as u8);

    let mut steps = Vec::with_capacity(n - start);
    let mut prev_order = 0usize;
    for i in start..n {
        let k = i - start;
        let p = &pts[i];
        let mut ops = Vec::with_capacity(3);
        // m_i from the model output and x_i.
        let m_terms = match cfg.prediction_type {
            PredictionType::Epsilon => {
                vec![t(Buf::Sample, 1.0 / p.alpha), t(Buf::Eps, -p.s / p.alpha)]
            }
            PredictionType::VPrediction => vec![t(Buf::Sample, p.alpha), t(Buf::Eps, -p.s)],
            PredictionType::Sample => vec![t(Buf::Eps, 1.0)],
        };
        ops.push(Op::LinComb {
            out: x0(i),
            terms: m_terms,
        });

        // Corrector: corrected x_i into hat(i).
        let mut corrector_order = 0;
        if k > 0 && !cfg.disable_corrector.contains(&(i - 1)) {
            let (terms, used) = corrector(&pts, cfg, i, prev_order, &x0, hat(i - 1))?;
            corrector_order = used;
            ops.push(Op::LinComb { out: hat(i), terms });
        } else {
            ops.push(Op::LinComb {
                out: hat(i),
                terms: vec![t(Buf::Sample, 1.0)],
            });
        }

        // Predictor order.
        let mut q = if cfg.lower_order_final {
            cfg.solver_order.min(n - i)
        } else {
            cfg.solver_order
        };
        q = q.min(k.min(cfg.solver_order) + 1);
        let (terms, q_used) = predictor(&pts, cfg, i, q, &x0, hat(i))?;
        ops.push(Op::LinComb {
            out: Buf::Sample,
            terms,
        });
        prev_order = q_used;
        steps.push(StepPlan {
            index: i,
            timestep: timesteps[i],
            ops,
            predictor_order: q_used,
            corrector_order,
        });
    }
    Ok(SamplerPlan {
        sampler: "unipc",
        timesteps: timesteps[start..].to_vec(),
        steps,
        init_noise_sigma: 1.0,
    })
}

fn t(buf: Buf, coeff: f64) -> Term {
    Term { buf, coeff }
}

/// Ratios `r_k = (lambda_{base-k} - lambda_base) / h` for `k = 1..order`, truncated at the first
/// degenerate one (0 or not finite: repeated timesteps).
fn ratios(pts: &[Pt], base: usize, order: usize, h: f64) -> Vec<f64> {
    let mut rks = Vec::new();
    for k in 1..order {
        let r = (pts[base - k].lambda - pts[base].lambda) / h;
        if !r.is_finite() || r.abs() < 1e-12 {
            break;
        }
        rks.push(r);
    }
    rks
}

/// `h_phi_1 = expm1(hh)`, `B(h)` and the right-hand side `b` of diffusers' order conditions (length `p`).
fn phi_b(hh: f64, solver: SolverType, p: usize) -> (f64, f64, Vec<f64>) {
    let h_phi_1 = hh.exp_m1();
    let b_h = match solver {
        SolverType::Bh1 => hh,
        SolverType::Bh2 => hh.exp_m1(),
    };
    let mut h_phi_k = h_phi_1 / hh - 1.0;
    let mut fact = 1.0;
    let mut b = Vec::with_capacity(p);
    for i in 1..=p {
        b.push(h_phi_k * fact / b_h);
        fact *= (i + 1) as f64;
        h_phi_k = h_phi_k / hh - 1.0 / fact;
    }
    (h_phi_1, b_h, b)
}

/// `R[j][k] = rks[k]^j` with the trailing 1 appended to `rks`.
fn r_matrix(rks: &[f64], p: usize) -> Vec<Vec<f64>> {
    let mut all = rks.to_vec();
    all.push(1.0);
    (0..p)
        .map(|j| all.iter().take(p).map(|r| r.powi(j as i32)).collect())
        .collect()
}

/// Adds `coeff * buf` merging equal buffers.
fn add(terms: &mut Vec<Term>, buf: Buf, coeff: f64) {
    if let Some(x) = terms.iter_mut().find(|x| x.buf == buf) {
        x.coeff += coeff;
    } else {
        terms.push(t(buf, coeff));
    }
}

/// UniP-q from step `i` to `i + 1`: `x_{i+1}` from the corrected `x_i` (in `hat_i`) and `m_i .. m_{i-q+1}`.
fn predictor(
    pts: &[Pt],
    cfg: &UniPcConfig,
    i: usize,
    q: usize,
    x0: &dyn Fn(usize) -> Buf,
    hat_i: Buf,
) -> Result<(Vec<Term>, usize)> {
    let (s0, tt) = (&pts[i], &pts[i + 1]);
    if tt.s == 0.0 {
        // Final step to sigma 0: x_N = m_i (no log(0)).
        return Ok((vec![t(x0(i), 1.0)], 1));
    }
    let h = tt.lambda - s0.lambda;
    if h == 0.0 {
        return Ok((vec![t(hat_i, 1.0)], 1));
    }
    let rks = ratios(pts, i, q, h);
    let q = rks.len() + 1;
    let hh = -h;
    let (h_phi_1, b_h, b) = phi_b(hh, cfg.solver_type, q);
    let mut terms = vec![t(hat_i, tt.s / s0.s)];
    add(&mut terms, x0(i), -tt.alpha * h_phi_1);
    if q >= 2 {
        let rhos = if q == 2 {
            vec![0.5]
        } else {
            let r = r_matrix(&rks, q);
            let r_sub: Vec<Vec<f64>> = r[..q - 1].iter().map(|row| row[..q - 1].to_vec()).collect();
            solve_small(r_sub, b[..q - 1].to_vec())?
        };
        for (k, (rho, rk)) in rhos.iter().zip(&rks).enumerate() {
            // D1_k = (m_{i-k-1} - m_i) / r_k
            let c = -tt.alpha * b_h * rho / rk;
            add(&mut terms, x0(i - k - 1), c);
            add(&mut terms, x0(i), -c);
        }
    }
    check_finite(&terms, i, "predictor")?;
    Ok((terms, q))
}

/// UniC-p at step `i`: corrected `x_i` from the previous corrected sample (`hat_prev`), `m_{i-1} ..` and `m_i`.
fn corrector(
    pts: &[Pt],
    cfg: &UniPcConfig,
    i: usize,
    p: usize,
    x0: &dyn Fn(usize) -> Buf,
    hat_prev: Buf,
) -> Result<(Vec<Term>, usize)> {
    let (s0, tt) = (&pts[i - 1], &pts[i]);
    let h = tt.lambda - s0.lambda;
    if h == 0.0 {
        return Ok((vec![t(hat_prev, 1.0)], 1));
    }
    let rks = ratios(pts, i - 1, p, h);
    let p = rks.len() + 1;
    let hh = -h;
    let (h_phi_1, b_h, b) = phi_b(hh, cfg.solver_type, p);
    let rhos = if p == 1 {
        vec![0.5]
    } else {
        solve_small(r_matrix(&rks, p), b)?
    };
    let mut terms = vec![t(hat_prev, tt.s / s0.s)];
    add(&mut terms, x0(i - 1), -tt.alpha * h_phi_1);
    let g = -tt.alpha * b_h;
    for (k, rk) in rks.iter().enumerate() {
        // D1_k = (m_{i-1-k-1} - m_{i-1}) / r_k
        let c = g * rhos[k] / rk;
        add(&mut terms, x0(i - k - 2), c);
        add(&mut terms, x0(i - 1), -c);
    }
    // rho_last * (m_i - m_{i-1})
    let last = rhos[p - 1];
    add(&mut terms, x0(i), g * last);
    add(&mut terms, x0(i - 1), -g * last);
    check_finite(&terms, i, "corrector")?;
    Ok((terms, p))
}

fn check_finite(terms: &[Term], i: usize, what: &str) -> Result<()> {
    if terms.iter().any(|t| !t.coeff.is_finite()) {
        bail!("UniPC {what} coefficients at step {i} are not finite: {terms:?}");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::cpu::run_loop;

    #[test]
    fn one_and_thousand_steps_are_finite() {
        let s = NoiseSchedule::sd15();
        for n in [1, 2, 3, 20, 999, 1000] {
            let plan = plan(&s, &UniPcConfig::default(), n).unwrap();
            assert_eq!(plan.steps.len(), n);
            let out = run_loop(&plan, vec![1.0, -0.5, 0.25], |x, _| {
                Ok(x.iter().map(|v| 0.1 * v).collect())
            })
            .unwrap();
            assert!(out.last().unwrap().iter().all(|v| v.is_finite()), "n = {n}");
        }
    }

    #[test]
    fn guidance_30_over_100_steps_has_finite_coefficients() {
        let p = plan(&NoiseSchedule::sd15(), &UniPcConfig::default(), 100)
            .unwrap()
            .with_guidance(30.0);
        for op in p.steps.iter().flat_map(|s| &s.ops) {
            if let Op::LinComb { terms, .. } = op {
                assert!(
                    terms
                        .iter()
                        .all(|t| t.coeff.is_finite() && t.coeff.abs() < 1e4),
                    "{terms:?}"
                );
            }
        }
    }

    #[test]
    fn orders_follow_diffusers() {
        let p = plan(&NoiseSchedule::sd15(), &UniPcConfig::default(), 20).unwrap();
        let orders: Vec<(usize, usize)> = p
            .steps
            .iter()
            .map(|s| (s.predictor_order, s.corrector_order))
            .collect();
        assert_eq!(orders[0], (1, 0));
        assert_eq!(orders[1], (2, 1));
        assert_eq!(orders[2], (2, 2));
        assert_eq!(orders[19], (1, 2));
        assert_eq!(p.buffers().len(), 1 + 1 + 3 + 2);
        assert_eq!(p.max_terms(), 4);
        assert_eq!(p.with_guidance(7.5).max_terms(), 4);
    }
}
