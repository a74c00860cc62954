//! A checkpoint's `scheduler/scheduler_config.json` (diffusers) turned into b2dr's schedule and sampler
//! settings. SD1.5 ships a PNDMScheduler config (`scaled_linear`, 0.00085 .. 0.012, `steps_offset` 1,
//! `set_alpha_to_one` false, `skip_prk_steps` true, no `timestep_spacing` key); diffusers'
//! `UniPCMultistepScheduler.from_config` / `DDIMScheduler.from_config` read the shared keys and keep their
//! own defaults for the rest, and so does this function: keys a sampler does not know are ignored, as in
//! diffusers, but a value b2dr cannot honour (another beta schedule, thresholding, karras sigmas, ...) is an
//! error naming the key.

use super::ddim::DdimConfig;
use super::schedule::{NoiseSchedule, TimestepSpacing};
use super::unipc::{FinalSigmas, SolverType, UniPcConfig};
use super::PredictionType;
use anyhow::{bail, Context, Result};
use serde_json::Value;

/// The schedule and both samplers' settings from one scheduler config.
#[derive(Clone, Debug, PartialEq)]
pub struct SchedulerSettings {
    pub schedule: NoiseSchedule,
    pub unipc: UniPcConfig,
    pub ddim: DdimConfig,
}

fn num(v: &Value, key: &str, default: f64) -> Result<f64> {
    match v.get(key) {
        None | Some(Value::Null) => Ok(default),
        Some(x) => x
            .as_f64()
            .with_context(|| format!("scheduler config: key `{key}` = {x}: expected a number")),
    }
}

fn text<'a>(v: &'a Value, key: &str, default: &'a str) -> Result<&'a str> {
    match v.get(key) {
        None | Some(Value::Null) => Ok(default),
        Some(x) => x
            .as_str()
            .with_context(|| format!("scheduler config: key `{key}` = {x}: expected a string")),
    }
}

fn flag(v: &Value, key: &str) -> Result<bool> {
    match v.get(key) {
        None | Some(Value::Null) => Ok(false),
        Some(x) => x
            .as_bool()
            .with_context(|| format!("scheduler config: key `{key}` = {x}: expected a bool")),
    }
}

/// Reads a diffusers scheduler config. `timestep_spacing`, when absent, stays each sampler's own default
/// (UniPC: linspace, DDIM: leading), as diffusers' `from_config` does.
pub fn from_diffusers_json(v: &Value) -> Result<SchedulerSettings> {
    let n = num(v, "num_train_timesteps", 1000.0)?;
    // bounded: the schedule holds one entry per training timestep (SD: 1000)
    if !(1.0..=100_000.0).contains(&n) || n.fract() != 0.0 {
        bail!("scheduler config: key `num_train_timesteps` = {n}: expected a positive integer (at most 100000)");
    }
    let n = n as usize;
    let b0 = num(v, "beta_start", 0.0001)?;
    let b1 = num(v, "beta_end", 0.02)?;
    let schedule = match text(v, "beta_schedule", "linear")? {
        "scaled_linear" => NoiseSchedule::scaled_linear(b0, b1, n),
        "linear" => NoiseSchedule::linear(b0, b1, n),
        other => bail!("scheduler config: key `beta_schedule` = {other:?} is not supported (scaled_linear, linear)"),
    };
    if v.get("trained_betas").is_some_and(|x| !x.is_null()) {
        bail!("scheduler config: key `trained_betas` is not supported");
    }
    for key in [
        "thresholding",
        "use_karras_sigmas",
        "use_exponential_sigmas",
        "use_beta_sigmas",
        "rescale_betas_zero_snr",
    ] {
        if flag(v, key)? {
            bail!("scheduler config: key `{key}` = true is not supported by b2dr");
        }
    }
    let prediction_type = PredictionType::parse(text(v, "prediction_type", "epsilon")?)
        .context("scheduler config: key `prediction_type`")?;
    let steps_offset = num(v, "steps_offset", 0.0)? as i64;
    let spacing = match v.get("timestep_spacing").and_then(|x| x.as_str()) {
        Some(s) => {
            Some(TimestepSpacing::parse(s).context("scheduler config: key `timestep_spacing`")?)
        }
        None => None,
    };
    let mut unipc = UniPcConfig {
        prediction_type,
        steps_offset,
        ..UniPcConfig::default()
    };
    if let Some(s) = spacing {
        unipc.timestep_spacing = s;
    }
    if let Some(o) = v.get("solver_order").and_then(|x| x.as_u64()) {
        unipc.solver_order = o as usize;
    }
    match text(v, "solver_type", "bh2")? {
        "bh1" => unipc.solver_type = SolverType::Bh1,
        "bh2" | "midpoint" | "heun" | "logrho" => unipc.solver_type = SolverType::Bh2,
        other => {
            bail!("scheduler config: key `solver_type` = {other:?} is not supported (bh1, bh2)")
        }
    }
    if v.get("predict_x0").and_then(|x| x.as_bool()) == Some(false) {
        bail!("scheduler config: key `predict_x0` = false is not supported (b2dr's UniPC predicts x0)");
    }
    if let Some(b) = v.get("lower_order_final").and_then(|x| x.as_bool()) {
        unipc.lower_order_final = b;
    }
    unipc.final_sigmas = match text(v, "final_sigmas_type", "zero")? {
        "zero" => FinalSigmas::Zero,
        "sigma_min" => FinalSigmas::SigmaMin,
        other => bail!("scheduler config: key `final_sigmas_type` = {other:?} is not supported"),
    };
    if let Some(list) = v.get("disable_corrector").and_then(|x| x.as_array()) {
        unipc.disable_corrector = list
            .iter()
            .filter_map(|x| x.as_u64())
            .map(|x| x as usize)
            .collect();
    }
    let mut ddim = DdimConfig {
        prediction_type,
        steps_offset,
        set_alpha_to_one: v
            .get("set_alpha_to_one")
            .and_then(|x| x.as_bool())
            .unwrap_or(true),
        clip_sample: match v
            .get("clip_sample")
            .and_then(|x| x.as_bool())
            .unwrap_or(true)
        {
            true => Some(num(v, "clip_sample_range", 1.0)?),
            false => None,
        },
        ..DdimConfig::default()
    };
    if let Some(s) = spacing {
        ddim.timestep_spacing = s;
    }
    Ok(SchedulerSettings {
        schedule,
        unipc,
        ddim,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn sd15_scheduler_config() {
        // runwayml/stable-diffusion-v1-5 scheduler/scheduler_config.json
        let v = json!({"_class_name": "PNDMScheduler", "_diffusers_version": "0.6.0", "beta_end": 0.012,
            "beta_schedule": "scaled_linear", "beta_start": 0.00085, "num_train_timesteps": 1000,
            "set_alpha_to_one": false, "skip_prk_steps": true, "steps_offset": 1, "trained_betas": null,
            "clip_sample": false});
        let s = from_diffusers_json(&v).unwrap();
        assert_eq!(s.schedule, NoiseSchedule::sd15());
        assert_eq!(s.ddim, DdimConfig::default());
        assert_eq!(s.unipc.timestep_spacing, TimestepSpacing::Linspace);
        assert_eq!(s.unipc.steps_offset, 1);
        let e = from_diffusers_json(&json!({"beta_schedule": "squaredcos_cap_v2"})).unwrap_err();
        assert!(format!("{e:#}").contains("beta_schedule"));
        let e = from_diffusers_json(&json!({"use_karras_sigmas": true})).unwrap_err();
        assert!(format!("{e:#}").contains("use_karras_sigmas"));
    }
}
