//! ego_is_comfortable: port of nuPlan's [evaluation_metrics/common/ego_is_comfortable.py] with its six
//! within-bound metrics (ego_lon_acceleration, ego_lat_acceleration, ego_jerk, ego_lon_jerk, ego_yaw_rate,
//! ego_yaw_acceleration) and the extractors of [metrics/utils/state_extractors.py]:
//! - accelerations: centre acceleration (rear-axle acceleration + (d w^2 + d alpha, 0), d = rear axle to
//!   centre), `savgol_filter(window min(8, n), poly 2)`, rounded to 8 decimals;
//! - jerks: the filtered acceleration (x, or the magnitude of the REAR-AXLE acceleration for ego_jerk),
//!   differentiated by `approximate_derivatives(window min(15, n), poly 2, deriv 1, delta = mean dt)`, rounded;
//! - yaw rate / acceleration: `approximate_derivatives` of the phase-unwrapped heading with window 5 (quirk:
//!   `extract_ego_yaw_rate`'s own window_length default of 15 is never passed on), poly 2 / deriv 1 and
//!   poly 3 / deriv 2, rounded.
//!
//! Bounds are strict: value in (min, max).
use super::input::{EgoDims, EgoStep};
use super::savgol::{np_round, savgol_filter};
use anyhow::{ensure, Result};
use serde::{Deserialize, Serialize};

/// nuPlan's comfort thresholds [config/metrics/low_level/ego_*.yaml].
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct ComfortBounds {
    pub min_lon_accel: f64,
    pub max_lon_accel: f64,
    pub max_abs_lat_accel: f64,
    pub max_abs_mag_jerk: f64,
    pub max_abs_lon_jerk: f64,
    pub max_abs_yaw_rate: f64,
    pub max_abs_yaw_accel: f64,
}

impl Default for ComfortBounds {
    fn default() -> Self {
        ComfortBounds {
            min_lon_accel: -4.05,
            max_lon_accel: 2.40,
            max_abs_lat_accel: 4.89,
            max_abs_mag_jerk: 8.37,
            max_abs_lon_jerk: 4.13,
            max_abs_yaw_rate: 0.95,
            max_abs_yaw_accel: 1.93,
        }
    }
}

/// Filtered signals and the verdict of ego_is_comfortable.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ComfortResult {
    pub lon_acceleration: Vec<f64>,
    pub lat_acceleration: Vec<f64>,
    pub jerk: Vec<f64>,
    pub lon_jerk: Vec<f64>,
    pub yaw_rate: Vec<f64>,
    pub yaw_acceleration: Vec<f64>,
    /// Within-bound flags in the order above.
    pub within_bounds: [bool; 6],
    pub score: f64,
}

const DECIMALS: i32 = 8;

/// `phase_unwrap`: successive differences brought within [-pi, pi] by multiples of 2 pi.
pub fn phase_unwrap(headings: &[f64]) -> Vec<f64> {
    let two_pi = 2.0 * std::f64::consts::PI;
    let mut adj = 0.0;
    let mut out = Vec::with_capacity(headings.len());
    for (i, &h) in headings.iter().enumerate() {
        if i > 0 {
            adj += ((h - headings[i - 1]) / two_pi).round_ties_even();
        }
        out.push(h - two_pi * adj);
    }
    out
}

/// `approximate_derivatives(y, t, window_length, poly_order, deriv_order)`; `t` in seconds.
pub fn approximate_derivatives(
    y: &[f64],
    t: &[f64],
    window_length: usize,
    poly_order: usize,
    deriv: usize,
) -> Result<Vec<f64>> {
    let window_length = window_length.min(t.len());
    ensure!(
        poly_order < window_length,
        "approximate_derivatives: {poly_order} < {window_length} does not hold"
    );
    ensure!(
        t.windows(2).all(|w| w[1] - w[0] > 0.0),
        "approximate_derivatives: time is not increasing"
    );
    let dx = t.windows(2).map(|w| w[1] - w[0]).sum::<f64>() / (t.len() - 1) as f64;
    savgol_filter(y, window_length, poly_order, deriv, dx)
}

/// `extract_ego_acceleration` smoothing: `savgol_filter(a, window min(8, n), poly 2)` then rounding.
fn smooth_acceleration(a: &[f64]) -> Result<Vec<f64>> {
    Ok(savgol_filter(a, 8.min(a.len()), 2, 0, 1.0)?
        .into_iter()
        .map(|v| np_round(v, DECIMALS))
        .collect())
}

fn rounded(v: Vec<f64>) -> Vec<f64> {
    v.into_iter().map(|x| np_round(x, DECIMALS)).collect()
}

fn within(v: &[f64], lo: f64, hi: f64) -> bool {
    v.iter().all(|&x| x > lo && x < hi)
}

/// ego_is_comfortable. Needs at least 4 samples (the yaw acceleration fit is cubic) with increasing times.
pub fn ego_is_comfortable(
    ego: &[EgoStep],
    dims: &EgoDims,
    times_s: &[f64],
    b: &ComfortBounds,
) -> Result<ComfortResult> {
    ensure!(
        ego.len() >= 4,
        "ego_is_comfortable needs at least 4 samples, got {}",
        ego.len()
    );
    let d = dims.cog_position_from_rear_axle;
    // DynamicCarState.center_acceleration_2d = get_acceleration_shifted(...)
    let ax: Vec<f64> = ego
        .iter()
        .map(|e| e.acceleration.x + (d * e.yaw_rate.powi(2) + d * e.yaw_acceleration))
        .collect();
    let ay: Vec<f64> = ego.iter().map(|e| e.acceleration.y).collect();
    let amag: Vec<f64> = ego.iter().map(|e| e.acceleration.length()).collect();
    let lon_acceleration = smooth_acceleration(&ax)?;
    let lat_acceleration = smooth_acceleration(&ay)?;
    let jerk = rounded(approximate_derivatives(
        &smooth_acceleration(&amag)?,
        times_s,
        15,
        2,
        1,
    )?);
    let lon_jerk = rounded(approximate_derivatives(
        &lon_acceleration,
        times_s,
        15,
        2,
        1,
    )?);
    let headings = phase_unwrap(&ego.iter().map(|e| e.heading).collect::<Vec<_>>());
    let yaw_rate = rounded(approximate_derivatives(&headings, times_s, 5, 2, 1)?);
    let yaw_acceleration = rounded(approximate_derivatives(&headings, times_s, 5, 3, 2)?);
    let within_bounds = [
        within(&lon_acceleration, b.min_lon_accel, b.max_lon_accel),
        within(&lat_acceleration, -b.max_abs_lat_accel, b.max_abs_lat_accel),
        within(&jerk, -b.max_abs_mag_jerk, b.max_abs_mag_jerk),
        within(&lon_jerk, -b.max_abs_lon_jerk, b.max_abs_lon_jerk),
        within(&yaw_rate, -b.max_abs_yaw_rate, b.max_abs_yaw_rate),
        within(&yaw_acceleration, -b.max_abs_yaw_accel, b.max_abs_yaw_accel),
    ];
    let score = if within_bounds.iter().all(|&w| w) {
        1.0
    } else {
        0.0
    };
    Ok(ComfortResult {
        lon_acceleration,
        lat_acceleration,
        jerk,
        lon_jerk,
        yaw_rate,
        yaw_acceleration,
        within_bounds,
        score,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec2;

    fn trace(n: usize, f: impl Fn(f64) -> (f64, f64, f64)) -> (Vec<EgoStep>, Vec<f64>) {
        let times: Vec<f64> = (0..n).map(|i| i as f64 * 0.1).collect();
        let ego = times
            .iter()
            .map(|&t| {
                let (a, h, w) = f(t);
                EgoStep {
                    time_s: t,
                    position: DVec2::ZERO,
                    heading: h,
                    velocity: DVec2::new(5.0, 0.0),
                    acceleration: DVec2::new(a, 0.0),
                    yaw_rate: w,
                    yaw_acceleration: 0.0,
                }
            })
            .collect();
        (ego, times)
    }

    #[test]
    fn unwrap_headings() {
        let u = phase_unwrap(&[3.0, -3.0, 3.0]);
        assert!((u[1] - (2.0 * std::f64::consts::PI - 3.0)).abs() < 1e-12);
        assert!((u[2] - 3.0).abs() < 1e-12);
    }

    #[test]
    fn comfortable_and_bounds() {
        let d = EgoDims::PACIFICA;
        // Constant 1 m/s^2, straight: comfortable.
        let (ego, t) = trace(150, |_| (1.0, 0.0, 0.0));
        let r = ego_is_comfortable(&ego, &d, &t, &ComfortBounds::default()).unwrap();
        assert_eq!(r.score, 1.0);
        assert!(r.lon_acceleration.iter().all(|&a| (a - 1.0).abs() < 1e-8));
        assert!(r.jerk.iter().all(|&j| j.abs() < 1e-8));
        // Linear heading 0.5 rad/s -> yaw rate 0.5 exactly (window 5, poly 2 reproduces lines).
        let (ego, t) = trace(30, |t| (0.0, 0.5 * t, 0.0));
        let r = ego_is_comfortable(&ego, &d, &t, &ComfortBounds::default()).unwrap();
        assert!(
            r.yaw_rate.iter().all(|&w| (w - 0.5).abs() < 1e-8),
            "{:?}",
            r.yaw_rate
        );
        assert_eq!(r.score, 1.0);
        // 1.0 rad/s exceeds 0.95.
        let (ego, t) = trace(30, |t| (0.0, 1.0 * t, 0.0));
        let r = ego_is_comfortable(&ego, &d, &t, &ComfortBounds::default()).unwrap();
        assert_eq!(r.within_bounds, [true, true, true, true, false, true]);
        assert_eq!(r.score, 0.0);
        // Hard braking at exactly the bound fails (strict).
        let (ego, t) = trace(30, |_| (-4.05, 0.0, 0.0));
        let r = ego_is_comfortable(&ego, &d, &t, &ComfortBounds::default()).unwrap();
        assert!(!r.within_bounds[0]);
        // Centre acceleration adds d w^2: 2 rad/s yaw rate -> 1.461 * 4 = 5.844 > 2.4.
        let (ego, t) = trace(30, |_| (0.0, 0.0, 2.0));
        let r = ego_is_comfortable(&ego, &d, &t, &ComfortBounds::default()).unwrap();
        assert!((r.lon_acceleration[10] - 5.844).abs() < 1e-8);
        // Too short.
        let (ego, t) = trace(3, |_| (0.0, 0.0, 0.0));
        assert!(ego_is_comfortable(&ego, &d, &t, &ComfortBounds::default()).is_err());
    }
}
