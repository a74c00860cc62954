//! Map-based metrics: drivable_area_compliance, driving_direction_compliance, speed_limit_compliance,
//! ego_progress_along_expert_route and ego_is_making_progress. Ports of nuPlan's
//! [evaluation_metrics/common/{drivable_area_compliance, driving_direction_compliance, speed_limit_compliance,
//! ego_progress_along_expert_route, ego_is_making_progress}.py].
use super::geometry::polyline_project;
use super::input::{EgoStep, MapQuery};
use super::route::{per_frame_progress, roadblock_pairs, route_simplified, CornerObjs, RouteObjs};
use crate::scene::geometry::point_polygon_distance;
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// Result of drivable_area_compliance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DrivableAreaResult {
    /// Per step: 1 when all four corners are on a lane / connector or in the drivable area.
    pub corners_in_drivable_area: Vec<f64>,
    /// True when a corner was once off the drivable area by `max_violation_threshold` or more.
    pub far_from_drivable_area: bool,
    pub score: f64,
}

/// drivable_area_compliance (`max_violation_threshold` 0.3 m in nuPlan's config).
pub fn drivable_area_compliance(
    map: &dyn MapQuery,
    corners: &[[DVec2; 4]],
    corners_route: &[CornerObjs],
    center_route: &[RouteObjs],
    max_violation_threshold: f64,
) -> DrivableAreaResult {
    let mut far = false;
    let mut series = Vec::with_capacity(corners.len());
    for ((cs, croute), center) in corners.iter().zip(corners_route).zip(center_route) {
        let outside: Vec<usize> = (0..4)
            .filter(|&i| croute[i].is_empty() && !map.in_drivable_area(cs[i]))
            .collect();
        far = far
            || outside.iter().any(|&i| {
                // is_corner_far_from_drivable_area
                if !center.is_empty() {
                    let d = center
                        .iter()
                        .filter_map(|id| {
                            map.lane(*id)
                                .map(|l| point_polygon_distance(cs[i], l.polygon))
                        })
                        .fold(f64::INFINITY, f64::min);
                    if d < max_violation_threshold {
                        return false;
                    }
                }
                let d = map.distance_to_drivable_area(cs[i]);
                !d.is_finite() || d >= max_violation_threshold
            });
        series.push(if outside.is_empty() { 1.0 } else { 0.0 });
    }
    DrivableAreaResult {
        corners_in_drivable_area: series,
        far_from_drivable_area: far,
        score: if far { 0.0 } else { 1.0 },
    }
}

/// Result of driving_direction_compliance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DrivingDirectionResult {
    /// Progress along the driving direction summed over the trailing window, per step.
    pub progress_over_interval: Vec<f64>,
    /// `-|min(progress_over_interval)|`.
    pub min_progress: f64,
    pub score: f64,
}

/// driving_direction_compliance (thresholds 2 m / 6 m, horizon 1 s). `times_us`: step times in microseconds.
pub fn driving_direction_compliance(
    map: &dyn MapQuery,
    centers: &[DVec2],
    center_route: &[RouteObjs],
    times_us: &[i64],
    compliance_threshold: f64,
    violation_threshold: f64,
    time_horizon: f64,
) -> DrivingDirectionResult {
    let n_horizon = if times_us.len() >= 2 {
        let mean_dt =
            (times_us[times_us.len() - 1] - times_us[0]) as f64 / (times_us.len() - 1) as f64;
        let n = time_horizon * 1e6 / mean_dt;
        if n.is_finite() && n > 0.0 {
            n as usize
        } else {
            0
        }
    } else {
        0
    };
    // _extract_metric
    let mut progress = Vec::with_capacity(centers.len());
    let mut prev_dist: Option<f64> = None;
    let mut prev_id = center_route.first().and_then(|r| r.first()).copied();
    for (p, r) in centers.iter().zip(center_route) {
        let Some(first) = r.first() else {
            progress.push(0.0);
            continue;
        };
        if prev_id == Some(*first) {
            let d = map
                .lane(*first)
                .map(|l| polyline_project(l.baseline, *p))
                .unwrap_or(0.0);
            // Quirk kept: `... if prev is not None and distance_to_start else 0.0` treats a distance of 0 as
            // missing.
            let made = match prev_dist {
                Some(prev) if d != 0.0 => d - prev,
                _ => 0.0,
            };
            progress.push(made);
            prev_dist = Some(d);
        } else {
            prev_dist = None;
            progress.push(0.0);
            prev_id = Some(*first);
        }
    }
    let over: Vec<f64> = (0..progress.len())
        .map(|i| progress[i.saturating_sub(n_horizon)..=i].iter().sum())
        .collect();
    let m = over.iter().copied().fold(f64::INFINITY, f64::min).abs();
    let m = if over.is_empty() { 0.0 } else { m };
    let score = if m < compliance_threshold {
        1.0
    } else if m < violation_threshold {
        0.5
    } else {
        0.0
    };
    DrivingDirectionResult {
        progress_over_interval: over,
        min_progress: -m,
        score,
    }
}

/// Result of speed_limit_compliance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpeedLimitResult {
    /// Over-speed (m/s) per step, 0 when not exceeding or unknown.
    pub violation_depths: Vec<f64>,
    /// Number of violation intervals.
    pub number_of_violations: usize,
    pub score: f64,
}

/// speed_limit_compliance (`max_overspeed_value_threshold` 2.23 m/s).
pub fn speed_limit_compliance(
    map: &dyn MapQuery,
    ego: &[EgoStep],
    center_route: &[RouteObjs],
    times_us: &[i64],
    max_overspeed_value_threshold: f64,
) -> SpeedLimitResult {
    let mut depths = Vec::with_capacity(ego.len());
    let mut intervals = 0usize;
    let mut open = false;
    for (e, r) in ego.iter().zip(center_route) {
        let violation = speed_limit_violation(map, e, r);
        match violation {
            Some(v) => {
                if !open {
                    intervals += 1;
                    open = true;
                }
                depths.push(v);
            }
            None => {
                depths.push(0.0);
                open = false;
            }
        }
    }
    let score = if intervals == 0 || times_us.len() < 2 {
        1.0
    } else {
        let n = times_us.len();
        let dt = (times_us[n - 1] - times_us[0]) as f64 / (n - 1) as f64 * 1e-6;
        let duration = (times_us[n - 1] - times_us[0]) as f64 * 1e-6;
        if duration <= 0.0 {
            1.0
        } else {
            let thr = max_overspeed_value_threshold.max(1e-3);
            let loss = depths.iter().sum::<f64>() * dt / (thr * duration);
            (1.0 - loss).max(0.0)
        }
    };
    SpeedLimitResult {
        violation_depths: depths,
        number_of_violations: intervals,
        score,
    }
}

/// `_get_speed_limit_violation`: by how much the ego exceeds the limit of its lane (for connectors: the
/// largest limit of their incoming and outgoing lanes). `None` when not exceeding or a limit is unknown
/// (nuPlan: `all(speed_limits)` fails on None or 0). A connector without edges has no limit here (nuPlan
/// would raise on `max([])`).
fn speed_limit_violation(map: &dyn MapQuery, e: &EgoStep, r: &RouteObjs) -> Option<f64> {
    let first = r.first()?;
    let mut limits: Vec<Option<f64>> = Vec::new();
    if !first.is_connector {
        limits.push(map.lane(*first).and_then(|l| l.speed_limit));
    } else {
        for id in r {
            if let Some(l) = map.lane(*id) {
                for edge in l.successors.iter().chain(l.predecessors) {
                    limits.push(map.lane(*edge).and_then(|x| x.speed_limit));
                }
            }
        }
    }
    if limits.is_empty()
        || limits
            .iter()
            .any(|l| l.is_none_or(|v| v == 0.0 || v.is_nan()))
    {
        return None;
    }
    let max = limits
        .iter()
        .map(|l| l.unwrap_or(0.0))
        .fold(f64::NEG_INFINITY, f64::max);
    let exceeding = e.speed() - max;
    (exceeding > 0.0).then_some(exceeding)
}

/// Result of ego_progress_along_expert_route.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProgressResult {
    pub ego_progress: f64,
    pub expert_progress: f64,
    /// Per-frame ego progress (empty without a route).
    pub ego_per_frame: Vec<f64>,
    pub ratio: f64,
}

/// ego_progress_along_expert_route (`score_progress_threshold` 2 m). `ego_centers` / `expert_centers`: box
/// centres; `expert_route`: `get_route` of the expert centres.
pub fn progress_along_expert_route(
    map: &dyn MapQuery,
    ego_centers: &[DVec2],
    expert_centers: &[DVec2],
    expert_route: &[RouteObjs],
    score_progress_threshold: f64,
) -> ProgressResult {
    let simplified = route_simplified(expert_route);
    let pairs = roadblock_pairs(map, &simplified);
    if pairs.is_empty() || ego_centers.is_empty() || expert_centers.is_empty() {
        return ProgressResult {
            ego_progress: 0.0,
            expert_progress: 0.0,
            ego_per_frame: Vec::new(),
            ratio: 1.0,
        };
    }
    let ego_pf = per_frame_progress(map, &pairs, ego_centers);
    let expert_pf = per_frame_progress(map, &pairs, expert_centers);
    let ego: f64 = ego_pf.iter().sum();
    let expert: f64 = expert_pf.iter().sum();
    let ratio = if ego < -score_progress_threshold {
        0.0
    } else {
        (ego.max(score_progress_threshold) / expert.max(score_progress_threshold)).min(1.0)
    };
    ProgressResult {
        ego_progress: ego,
        expert_progress: expert,
        ego_per_frame: ego_pf,
        ratio,
    }
}

/// ego_is_making_progress: 1 when the progress ratio is >= `min_progress_threshold` (0.2).
pub fn is_making_progress(ratio: f64, min_progress_threshold: f64) -> f64 {
    if ratio >= min_progress_threshold {
        1.0
    } else {
        0.0
    }
}
