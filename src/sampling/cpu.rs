//! CPU executor of a [`SamplerPlan`] on `f32` host buffers: the oracle for the device executor and the
//! sampler used in CPU-only tests. Each output element is accumulated in f64 and rounded once to f32.

use super::{Buf, Op, SamplerPlan, StepPlan};
use anyhow::{anyhow, bail, ensure, Context, Result};
use std::collections::BTreeMap;

/// Host buffers of one sampling run, all of the latent's length.
#[derive(Clone, Debug)]
pub struct CpuSampler {
    len: usize,
    bufs: BTreeMap<Buf, Vec<f32>>,
}

impl CpuSampler {
    /// Starts from the initial sample `x_T` (already scaled by `init_noise_sigma`), `(N, C, H, W)` flat.
    pub fn new(sample: Vec<f32>) -> Self {
        let len = sample.len();
        let mut bufs = BTreeMap::new();
        bufs.insert(Buf::Sample, sample);
        Self { len, bufs }
    }

    /// The current sample.
    pub fn sample(&self) -> &[f32] {
        &self.bufs[&Buf::Sample]
    }

    /// A buffer's contents, if it was written.
    pub fn get(&self, buf: Buf) -> Option<&[f32]> {
        self.bufs.get(&buf).map(|v| v.as_slice())
    }

    /// Sets an input buffer (the model output, noise); its length must match the sample's.
    pub fn set(&mut self, buf: Buf, data: Vec<f32>) -> Result<()> {
        ensure!(
            data.len() == self.len,
            "{buf:?} has {} values, the sample {}",
            data.len(),
            self.len
        );
        self.bufs.insert(buf, data);
        Ok(())
    }

    /// Applies a step's ops (the model output must already be set).
    pub fn apply(&mut self, step: &StepPlan) -> Result<()> {
        for op in &step.ops {
            match op {
                Op::LinComb { out, terms } => {
                    let mut acc = vec![0f64; self.len];
                    for t in terms {
                        let src = self.bufs.get(&t.buf).ok_or_else(|| {
                            anyhow!("step {}: buffer {:?} was never written", step.index, t.buf)
                        })?;
                        for (a, s) in acc.iter_mut().zip(src) {
                            *a += t.coeff * *s as f64;
                        }
                    }
                    self.bufs
                        .insert(*out, acc.into_iter().map(|a| a as f32).collect());
                }
                Op::Clamp { buf, lo, hi } => {
                    let v = self.bufs.get_mut(buf).ok_or_else(|| {
                        anyhow!("step {}: buffer {buf:?} was never written", step.index)
                    })?;
                    for x in v.iter_mut() {
                        *x = (*x as f64).clamp(*lo, *hi) as f32;
                    }
                }
            }
        }
        Ok(())
    }
}

/// Runs a whole (unguided, noise-free) plan with a host model `eps = model(x, t)`; returns the sample after
/// every step (the last one is the result). `x_t`: `(N, C, H, W)` flat initial sample.
pub fn run_loop(
    plan: &SamplerPlan,
    x_t: Vec<f32>,
    mut model: impl FnMut(&[f32], i64) -> Result<Vec<f32>>,
) -> Result<Vec<Vec<f32>>> {
    if plan.needs_noise() {
        bail!("this plan needs per-step noise (DDIM eta > 0): drive CpuSampler step by step");
    }
    let mut s = CpuSampler::new(x_t);
    let mut out = Vec::with_capacity(plan.steps.len());
    for step in &plan.steps {
        let eps = model(s.sample(), step.timestep)
            .with_context(|| format!("model at step {}", step.index))?;
        s.set(Buf::Eps, eps)?;
        s.apply(step)?;
        out.push(s.sample().to_vec());
    }
    Ok(out)
}
