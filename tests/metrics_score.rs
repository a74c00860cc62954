//! Whole-scenario score: aggregation formula, determinism, serde round trip and error handling.
use b2dr::metrics::synthetic::{busy_scenario, straight_road};
use b2dr::metrics::{aggregate, score_all, score_scenario, EgoStep, ScenarioTrace, ScoreParams};
use glam::DVec2;

/// Ego = expert: straight in lane 0 at speed `v` for 3 s, no objects.
fn clean(v: f64) -> ScenarioTrace {
    let ego: Vec<EgoStep> = (0..31)
        .map(|i| {
            let t = i as f64 * 0.1;
            EgoStep {
                time_s: t,
                position: DVec2::new(10.0 + v * t, 0.0),
                heading: 0.0,
                velocity: DVec2::new(v, 0.0),
                acceleration: DVec2::ZERO,
                yaw_rate: 0.0,
                yaw_acceleration: 0.0,
            }
        })
        .collect();
    ScenarioTrace {
        name: format!("clean_{v}"),
        ego_dims: Default::default(),
        objects: vec![Vec::new(); ego.len()],
        expert: ego.clone(),
        ego,
        route_roadblocks: vec![0, 1],
    }
}

#[test]
fn clean_drive_scores_one_and_overspeed_is_weighted() {
    let map = straight_road(2, 2);
    let p = ScoreParams::default();
    let s = score_scenario(&map, &clean(10.0), &p).unwrap();
    assert_eq!(
        [
            s.no_ego_at_fault_collisions,
            s.drivable_area_compliance,
            s.driving_direction_compliance,
            s.ego_is_making_progress,
            s.ego_progress_along_expert_route,
            s.time_to_collision_within_bound,
            s.speed_limit_compliance,
            s.ego_is_comfortable
        ],
        [1.0; 8]
    );
    assert_eq!(s.score, 1.0);
    // 17 m/s in a 15 m/s lane for all 31 steps: speed score = 1 - 31 * 2 * 0.1 / (2.23 * 3.0); the scenario
    // score is the weighted mean (5 + 5 + 4 s + 2) / 16 (all multipliers 1).
    let s = score_scenario(&map, &clean(17.0), &p).unwrap();
    let speed = 1.0 - 31.0 * 2.0 * 0.1 / (2.23 * 3.0);
    assert!(
        (s.speed_limit_compliance - speed).abs() < 1e-9,
        "{}",
        s.speed_limit_compliance
    );
    assert!((s.score - (12.0 + 4.0 * speed) / 16.0).abs() < 1e-9);
    // CLS = mean of scenario scores.
    let all = score_all(&map, &[clean(10.0), clean(17.0)], &p).unwrap();
    assert!((all.cls - (1.0 + (12.0 + 4.0 * speed) / 16.0) / 2.0).abs() < 1e-12);
    assert_eq!(aggregate(Vec::new()).cls, 0.0);
}

#[test]
fn stationary_obstacle_ahead_hits_multipliers() {
    // A stopped vehicle in the ego's lane: the ego drives into it -> stopped-track collision (at fault) -> 0.
    let map = straight_road(2, 2);
    let mut t = clean(10.0);
    let car = b2dr::metrics::ObjectState {
        track_id: 7,
        class: b2dr::metrics::ObjectClass::Vehicle,
        center: DVec2::new(35.0, 0.0),
        heading: 0.0,
        length: 4.7,
        width: 2.0,
        velocity: DVec2::ZERO,
        is_agent: true,
    };
    t.objects = vec![vec![car]; t.ego.len()];
    let s = score_scenario(&map, &t, &ScoreParams::default()).unwrap();
    assert_eq!(s.no_ego_at_fault_collisions, 0.0);
    assert_eq!(s.time_to_collision_within_bound, 0.0);
    assert_eq!(s.score, 0.0);
    assert_eq!(s.details.collisions.collisions.len(), 1);
}

#[test]
fn deterministic_and_serde_round_trip() {
    let (map, trace) = busy_scenario(150, 200, 7);
    let p = ScoreParams::default();
    let a = score_scenario(&map, &trace, &p).unwrap();
    let b = score_scenario(&map, &trace, &p).unwrap();
    let ja = serde_json::to_string(&a).unwrap();
    assert!(ja == serde_json::to_string(&b).unwrap(), "two runs differ");
    assert_eq!(a.score.to_bits(), b.score.to_bits());
    let back: b2dr::metrics::ScenarioScore = serde_json::from_str(&ja).unwrap();
    assert!(back == a, "serde round trip changed the result");
    for v in [
        a.ego_progress_along_expert_route,
        a.speed_limit_compliance,
        a.score,
    ] {
        assert!((0.0..=1.0).contains(&v));
    }
    // The trace itself round-trips too (the simulator may hand traces over as JSON).
    let tj = serde_json::to_string(&trace).unwrap();
    let t2: ScenarioTrace = serde_json::from_str(&tj).unwrap();
    assert!(
        serde_json::to_string(&score_scenario(&map, &t2, &p).unwrap()).unwrap() == ja,
        "trace round trip changed the score"
    );
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let map = straight_road(2, 2);
    let p = ScoreParams::default();
    let empty = ScenarioTrace::default();
    assert!(score_scenario(&map, &empty, &p).is_err());
    let mut one = clean(10.0);
    one.ego.truncate(1);
    one.objects.truncate(1);
    assert!(score_scenario(&map, &one, &p).is_err());
    let mut nan = clean(10.0);
    nan.ego[3].position.x = f64::NAN;
    assert!(score_scenario(&map, &nan, &p).is_err());
    let mut mismatch = clean(10.0);
    mismatch.objects.pop();
    assert!(score_scenario(&map, &mismatch, &p).is_err());
    let mut back_in_time = clean(10.0);
    back_in_time.ego[5].time_s = 0.0;
    assert!(score_scenario(&map, &back_in_time, &p).is_err());
    let mut no_expert = clean(10.0);
    no_expert.expert.clear();
    assert!(score_scenario(&map, &no_expert, &p).is_err());
    // Off every lane (empty map): defined result, no panic.
    let s = score_scenario(&b2dr::metrics::VecMap::default(), &clean(10.0), &p).unwrap();
    assert_eq!(s.drivable_area_compliance, 0.0);
    assert_eq!(s.ego_progress_along_expert_route, 1.0);
}
