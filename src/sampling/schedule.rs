//! The training noise schedule (betas, cumulative alphas) and inference timestep spacings.
//!
//! Everything is f64. diffusers builds its betas in f32 (`torch.linspace(..., dtype=float32)`); the values
//! here differ from diffusers' by ~1e-7 relative, far below the f32 latent tolerance. Where bitwise
//! agreement with a diffusers table matters (goldens), [`NoiseSchedule::from_alphas_cumprod`] takes the
//! table as diffusers computed it.

use anyhow::{bail, ensure, Result};

/// How inference timesteps are spread over the training range (diffusers' `timestep_spacing`, Table 2 of
/// "Common Diffusion Noise Schedules and Sample Steps are Flawed").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TimestepSpacing {
    /// Evenly spaced over `[0, T-1]`, rounded (ties to even, like numpy).
    Linspace,
    /// Multiples of `T // n` (integer ratio) plus `steps_offset`.
    Leading,
    /// `round(arange(T, 0, -T/n)) - 1`.
    Trailing,
}

impl TimestepSpacing {
    /// Parses diffusers' config value (`"linspace"`, `"leading"`, `"trailing"`).
    pub fn parse(s: &str) -> Result<Self> {
        Ok(match s {
            "linspace" => Self::Linspace,
            "leading" => Self::Leading,
            "trailing" => Self::Trailing,
            other => {
                bail!("timestep_spacing {other:?} is not supported (linspace, leading, trailing)")
            }
        })
    }
}

/// A discrete variance-preserving noise schedule: `x_t = sqrt(abar_t) x_0 + sqrt(1 - abar_t) eps`.
#[derive(Clone, Debug, PartialEq)]
pub struct NoiseSchedule {
    alphas_cumprod: Vec<f64>,
}

/// numpy's `linspace(start, stop, num)`: `start + k * step`, last element exactly `stop`.
pub(crate) fn np_linspace(start: f64, stop: f64, num: usize) -> Vec<f64> {
    if num == 0 {
        return Vec::new();
    }
    if num == 1 {
        return vec![start];
    }
    let step = (stop - start) / (num - 1) as f64;
    let mut v: Vec<f64> = (0..num).map(|k| start + k as f64 * step).collect();
    v[num - 1] = stop;
    v
}

impl NoiseSchedule {
    /// Stable Diffusion 1.5's schedule: `scaled_linear`, beta 0.00085 .. 0.012, 1000 training steps.
    pub fn sd15() -> Self {
        Self::scaled_linear(0.00085, 0.012, 1000)
    }

    /// `betas = linspace(sqrt(b0), sqrt(b1), n)^2` (diffusers' `scaled_linear`).
    pub fn scaled_linear(beta_start: f64, beta_end: f64, n: usize) -> Self {
        let betas: Vec<f64> = np_linspace(beta_start.sqrt(), beta_end.sqrt(), n)
            .iter()
            .map(|b| b * b)
            .collect();
        Self::from_betas(&betas)
    }

    /// `betas = linspace(b0, b1, n)` (diffusers' `linear`; the schedule of diffusers' scheduler tests).
    pub fn linear(beta_start: f64, beta_end: f64, n: usize) -> Self {
        Self::from_betas(&np_linspace(beta_start, beta_end, n))
    }

    fn from_betas(betas: &[f64]) -> Self {
        let mut acc = 1.0;
        let alphas_cumprod = betas
            .iter()
            .map(|b| {
                acc *= 1.0 - b;
                acc
            })
            .collect();
        Self { alphas_cumprod }
    }

    /// A schedule from an explicit `alphas_cumprod` table (e.g. diffusers' own f32 table from a golden file).
    pub fn from_alphas_cumprod(alphas_cumprod: Vec<f64>) -> Result<Self> {
        ensure!(!alphas_cumprod.is_empty(), "alphas_cumprod is empty");
        for (t, a) in alphas_cumprod.iter().enumerate() {
            ensure!(
                *a > 0.0 && *a < 1.0 && a.is_finite(),
                "alphas_cumprod[{t}] = {a} is not in (0, 1)"
            );
        }
        Ok(Self { alphas_cumprod })
    }

    /// Number of training timesteps `T`.
    pub fn num_train_timesteps(&self) -> usize {
        self.alphas_cumprod.len()
    }

    /// The whole `abar` table.
    pub fn alphas_cumprod(&self) -> &[f64] {
        &self.alphas_cumprod
    }

    /// `abar_t`; errors when `t` is outside `[0, T)`.
    pub fn alpha_bar(&self, t: i64) -> Result<f64> {
        usize::try_from(t)
            .ok()
            .and_then(|i| self.alphas_cumprod.get(i).copied())
            .ok_or_else(|| {
                anyhow::anyhow!(
                    "timestep {t} outside the training range [0, {})",
                    self.alphas_cumprod.len()
                )
            })
    }

    /// The VE-style noise level `sigma_t = sqrt((1 - abar_t) / abar_t)`.
    pub fn sigma(&self, t: i64) -> Result<f64> {
        let a = self.alpha_bar(t)?;
        Ok(((1.0 - a) / a).sqrt())
    }

    /// Coefficients `(sqrt(abar_t), sqrt(1 - abar_t))` of `z_t = c0 z_0 + c1 eps` (forward noising; used for
    /// the previous-frame latent and img2img starts).
    pub fn add_noise_coeffs(&self, t: i64) -> Result<(f64, f64)> {
        let a = self.alpha_bar(t)?;
        Ok((a.sqrt(), (1.0 - a).sqrt()))
    }
}

/// numpy `round` (half to even) of a non-negative float, as i64.
fn round_even(x: f64) -> i64 {
    x.round_ties_even() as i64
}

/// UniPC / DPM-Solver style timesteps (diffusers `UniPCMultistepScheduler.set_timesteps`): `n` descending
/// timesteps, sampled from `n + 1` points with the last (0) dropped.
pub fn multistep_timesteps(
    n: usize,
    spacing: TimestepSpacing,
    steps_offset: i64,
    num_train: usize,
) -> Result<Vec<i64>> {
    ensure!(n >= 1, "the number of inference steps must be at least 1");
    ensure!(
        n <= num_train,
        "{n} inference steps exceed the {num_train} training timesteps"
    );
    let t_max = num_train as f64 - 1.0;
    let ts: Vec<i64> = match spacing {
        TimestepSpacing::Linspace => {
            let mut v: Vec<i64> = np_linspace(0.0, t_max, n + 1)
                .iter()
                .map(|x| round_even(*x))
                .collect();
            v.reverse();
            v.truncate(n);
            v
        }
        TimestepSpacing::Leading => {
            let ratio = (num_train / (n + 1)) as i64;
            (0..=n as i64)
                .rev()
                .take(n)
                .map(|k| k * ratio + steps_offset)
                .collect()
        }
        TimestepSpacing::Trailing => trailing(n, num_train),
    };
    check_range(&ts, num_train, spacing, steps_offset)?;
    Ok(ts)
}

/// DDIM timesteps (diffusers `DDIMScheduler.set_timesteps`): `n` descending timesteps.
pub fn ddim_timesteps(
    n: usize,
    spacing: TimestepSpacing,
    steps_offset: i64,
    num_train: usize,
) -> Result<Vec<i64>> {
    ensure!(n >= 1, "the number of inference steps must be at least 1");
    ensure!(
        n <= num_train,
        "{n} inference steps exceed the {num_train} training timesteps"
    );
    let ts: Vec<i64> = match spacing {
        TimestepSpacing::Linspace => {
            let mut v: Vec<i64> = np_linspace(0.0, num_train as f64 - 1.0, n)
                .iter()
                .map(|x| round_even(*x))
                .collect();
            v.reverse();
            v
        }
        TimestepSpacing::Leading => {
            let ratio = (num_train / n) as i64;
            (0..n as i64)
                .rev()
                .map(|k| k * ratio + steps_offset)
                .collect()
        }
        TimestepSpacing::Trailing => trailing(n, num_train),
    };
    check_range(&ts, num_train, spacing, steps_offset)?;
    Ok(ts)
}

/// `round(arange(T, 0, -T/n)) - 1` (numpy arange: `T - k * step` while `> 0`).
fn trailing(n: usize, num_train: usize) -> Vec<i64> {
    let step = num_train as f64 / n as f64;
    let count = (num_train as f64 / step).ceil() as usize;
    (0..count)
        .map(|k| round_even(num_train as f64 - k as f64 * step) - 1)
        .collect()
}

fn check_range(ts: &[i64], num_train: usize, spacing: TimestepSpacing, offset: i64) -> Result<()> {
    for t in ts {
        if *t < 0 || *t >= num_train as i64 {
            bail!(
                "timestep {t} is outside [0, {num_train}) ({} steps, {spacing:?} spacing, steps_offset {offset}); \
                 use linspace or trailing spacing for this many steps",
                ts.len()
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_timesteps_20() {
        let ts = multistep_timesteps(20, TimestepSpacing::Linspace, 0, 1000).unwrap();
        assert_eq!(ts[0], 999);
        assert_eq!(ts[1], 949);
        assert_eq!(ts[18], 100);
        assert_eq!(ts[19], 50);
    }

    #[test]
    fn ddim_leading_offset_matches_diffusers_test() {
        // diffusers tests/schedulers/test_scheduler_ddim.py::test_steps_offset
        let ts = ddim_timesteps(5, TimestepSpacing::Leading, 1, 1000).unwrap();
        assert_eq!(ts, vec![801, 601, 401, 201, 1]);
        assert!(ddim_timesteps(1000, TimestepSpacing::Leading, 1, 1000).is_err());
    }

    #[test]
    fn sd15_alphas() {
        let s = NoiseSchedule::sd15();
        assert_eq!(s.num_train_timesteps(), 1000);
        assert!((s.alpha_bar(0).unwrap() - (1.0 - 0.00085)).abs() < 1e-12);
        assert!(s.alpha_bar(1000).is_err());
        assert!(s.alpha_bar(-1).is_err());
    }
}
