//! Scenario score and CLS: nuPlan's closed-loop aggregation
//! [metrics/aggregator/weighted_average_metric_aggregator.py, config closed_loop_*_weighted_average]:
//! `score = prod(multipliers) * sum(w_i s_i) / sum(w_i)`; CLS = mean of scenario scores.
use super::collisions::{
    at_fault_collisions, time_to_collision, CollisionResult, TtcParams, TtcResult,
};
use super::comfort::{ego_is_comfortable, ComfortBounds, ComfortResult};
use super::input::{MapQuery, ScenarioTrace};
use super::map_metrics::{
    drivable_area_compliance, driving_direction_compliance, is_making_progress,
    progress_along_expert_route, speed_limit_compliance, DrivableAreaResult,
    DrivingDirectionResult, ProgressResult, SpeedLimitResult,
};
use super::route::{extract_corners_route, get_route, in_common_or_connected};
use anyhow::{ensure, Context, Result};
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// Metric parameters, defaulting to nuPlan's closed-loop configuration.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct ScoreParams {
    pub drivable_area_max_violation: f64,
    pub driving_direction_compliance_threshold: f64,
    pub driving_direction_violation_threshold: f64,
    pub driving_direction_time_horizon: f64,
    pub min_progress_ratio: f64,
    pub score_progress_threshold: f64,
    pub max_overspeed_value_threshold: f64,
    pub ttc: TtcParams,
    pub comfort: ComfortBounds,
    pub weight_progress: f64,
    pub weight_ttc: f64,
    pub weight_speed_limit: f64,
    pub weight_comfort: f64,
}

impl Default for ScoreParams {
    fn default() -> Self {
        ScoreParams {
            drivable_area_max_violation: 0.3,
            driving_direction_compliance_threshold: 2.0,
            driving_direction_violation_threshold: 6.0,
            driving_direction_time_horizon: 1.0,
            min_progress_ratio: 0.2,
            score_progress_threshold: 2.0,
            max_overspeed_value_threshold: 2.23,
            ttc: TtcParams::default(),
            comfort: ComfortBounds::default(),
            weight_progress: 5.0,
            weight_ttc: 5.0,
            weight_speed_limit: 4.0,
            weight_comfort: 2.0,
        }
    }
}

/// Every metric of one scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScenarioScore {
    pub name: String,
    pub no_ego_at_fault_collisions: f64,
    pub drivable_area_compliance: f64,
    pub driving_direction_compliance: f64,
    pub ego_is_making_progress: f64,
    pub ego_progress_along_expert_route: f64,
    pub time_to_collision_within_bound: f64,
    pub speed_limit_compliance: f64,
    pub ego_is_comfortable: f64,
    /// prod(multipliers) x weighted mean.
    pub score: f64,
    pub details: ScenarioDetails,
}

/// Intermediate results, for reports and debugging.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScenarioDetails {
    pub collisions: CollisionResult,
    pub drivable_area: DrivableAreaResult,
    pub driving_direction: DrivingDirectionResult,
    pub progress: ProgressResult,
    pub ttc: TtcResult,
    pub speed_limit: SpeedLimitResult,
    pub comfort: ComfortResult,
    /// Per step: ego corners in a common or connected lane / connector set.
    pub in_common_or_connected: Vec<bool>,
}

/// The aggregate over scenarios.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClsResult {
    pub scenarios: Vec<ScenarioScore>,
    /// Mean of scenario scores (0 scenarios: NaN is avoided, the value is 0).
    pub cls: f64,
}

fn validate(trace: &ScenarioTrace) -> Result<()> {
    let n = trace.ego.len();
    ensure!(
        n >= 4,
        "scenario '{}': need at least 4 ego steps, got {n}",
        trace.name
    );
    ensure!(
        trace.objects.len() == n,
        "scenario '{}': {} object frames for {n} ego steps",
        trace.name,
        trace.objects.len()
    );
    ensure!(
        !trace.expert.is_empty(),
        "scenario '{}': empty expert trajectory",
        trace.name
    );
    let finite_ego = trace.ego.iter().chain(&trace.expert).all(|e| {
        e.time_s.is_finite()
            && e.position.is_finite()
            && e.heading.is_finite()
            && e.velocity.is_finite()
            && e.acceleration.is_finite()
            && e.yaw_rate.is_finite()
            && e.yaw_acceleration.is_finite()
    });
    ensure!(
        finite_ego,
        "scenario '{}': non-finite ego or expert state",
        trace.name
    );
    let finite_obj = trace.objects.iter().flatten().all(|o| {
        o.center.is_finite()
            && o.heading.is_finite()
            && o.length.is_finite()
            && o.width.is_finite()
            && o.velocity.is_finite()
    });
    ensure!(
        finite_obj,
        "scenario '{}': non-finite object state",
        trace.name
    );
    ensure!(
        trace.ego.windows(2).all(|w| w[1].time_s > w[0].time_s),
        "scenario '{}': ego times must increase strictly",
        trace.name
    );
    Ok(())
}

/// Scores one scenario. Errors on traces shorter than 4 steps, mismatched lengths, non-finite values or
/// non-increasing times.
pub fn score_scenario(
    map: &dyn MapQuery,
    trace: &ScenarioTrace,
    p: &ScoreParams,
) -> Result<ScenarioScore> {
    validate(trace)?;
    let dims = &trace.ego_dims;
    let ego = &trace.ego;
    let times_us: Vec<i64> = ego
        .iter()
        .map(|e| (e.time_s * 1e6).round() as i64)
        .collect();
    let times_s: Vec<f64> = times_us.iter().map(|&t| t as f64 / 1e6).collect();
    let centers: Vec<DVec2> = ego.iter().map(|e| e.center(dims)).collect();
    let corners: Vec<[DVec2; 4]> = ego.iter().map(|e| e.footprint(dims).corners()).collect();
    let expert_centers: Vec<DVec2> = trace.expert.iter().map(|e| e.center(dims)).collect();

    // ego_lane_change's shared products.
    let center_route = get_route(map, &centers);
    let corners_route = extract_corners_route(map, &corners);
    let common = in_common_or_connected(map, &corners_route);

    let collisions = at_fault_collisions(ego, dims, &trace.objects, &common);
    let drivable = drivable_area_compliance(
        map,
        &corners,
        &corners_route,
        &center_route,
        p.drivable_area_max_violation,
    );
    let direction = driving_direction_compliance(
        map,
        &centers,
        &center_route,
        &times_us,
        p.driving_direction_compliance_threshold,
        p.driving_direction_violation_threshold,
        p.driving_direction_time_horizon,
    );
    let expert_route = get_route(map, &expert_centers);
    let progress = progress_along_expert_route(
        map,
        &centers,
        &expert_centers,
        &expert_route,
        p.score_progress_threshold,
    );
    let making_progress = is_making_progress(progress.ratio, p.min_progress_ratio);
    let ttc = time_to_collision(
        map,
        ego,
        dims,
        &trace.objects,
        &common,
        &collisions.collisions,
        &p.ttc,
    );
    let speed = speed_limit_compliance(
        map,
        ego,
        &center_route,
        &times_us,
        p.max_overspeed_value_threshold,
    );
    let comfort = ego_is_comfortable(ego, dims, &times_s, &p.comfort)
        .with_context(|| format!("scenario '{}'", trace.name))?;

    let multipliers = collisions.score * drivable.score * direction.score * making_progress;
    let weighted = (p.weight_progress * progress.ratio
        + p.weight_ttc * ttc.score
        + p.weight_speed_limit * speed.score
        + p.weight_comfort * comfort.score)
        / (p.weight_progress + p.weight_ttc + p.weight_speed_limit + p.weight_comfort);
    Ok(ScenarioScore {
        name: trace.name.clone(),
        no_ego_at_fault_collisions: collisions.score,
        drivable_area_compliance: drivable.score,
        driving_direction_compliance: direction.score,
        ego_is_making_progress: making_progress,
        ego_progress_along_expert_route: progress.ratio,
        time_to_collision_within_bound: ttc.score,
        speed_limit_compliance: speed.score,
        ego_is_comfortable: comfort.score,
        score: multipliers * weighted,
        details: ScenarioDetails {
            collisions,
            drivable_area: drivable,
            driving_direction: direction,
            progress,
            ttc,
            speed_limit: speed,
            comfort,
            in_common_or_connected: common,
        },
    })
}

/// CLS over already scored scenarios.
pub fn aggregate(scenarios: Vec<ScenarioScore>) -> ClsResult {
    let cls = if scenarios.is_empty() {
        0.0
    } else {
        scenarios.iter().map(|s| s.score).sum::<f64>() / scenarios.len() as f64
    };
    ClsResult { scenarios, cls }
}

/// Scores every scenario (in order) and aggregates.
pub fn score_all(
    map: &dyn MapQuery,
    traces: &[ScenarioTrace],
    p: &ScoreParams,
) -> Result<ClsResult> {
    let scored = traces
        .iter()
        .map(|t| score_scenario(map, t, p))
        .collect::<Result<Vec<_>>>()?;
    Ok(aggregate(scored))
}
