//! Map-based metrics on a small hand-built map, every expected value computed by hand.
//!
//! Map (all straight, width 4 m, centre lines on y = 0 / y = 4):
//! - lane 1: (0,0)->(100,0), roadblock 10, 10 m/s;   lane 2: (0,4)->(100,4), roadblock 10, 10 m/s
//! - connector 3: (100,0)->(120,0), roadblock-connector 20, no limit of its own, 1 -> 3 -> 4
//! - lane 4: (120,0)->(220,0), roadblock 30, 15 m/s
use b2dr::metrics::map_metrics::{
    drivable_area_compliance, driving_direction_compliance, progress_along_expert_route,
    speed_limit_compliance,
};
use b2dr::metrics::route::{extract_corners_route, get_route, in_common_or_connected};
use b2dr::metrics::vecmap::VecRoadblock;
use b2dr::metrics::{EgoDims, EgoStep, LaneId, VecMap};
use glam::DVec2;

const L1: LaneId = LaneId {
    id: 1,
    is_connector: false,
};
const L2: LaneId = LaneId {
    id: 2,
    is_connector: false,
};
const C3: LaneId = LaneId {
    id: 3,
    is_connector: true,
};
const L4: LaneId = LaneId {
    id: 4,
    is_connector: false,
};

pub fn test_map() -> VecMap {
    let mut m = VecMap::default();
    m.add_straight_lane(
        L1,
        10,
        DVec2::new(0.0, 0.0),
        DVec2::new(100.0, 0.0),
        4.0,
        Some(10.0),
    );
    m.add_straight_lane(
        L2,
        10,
        DVec2::new(0.0, 4.0),
        DVec2::new(100.0, 4.0),
        4.0,
        Some(10.0),
    );
    m.add_straight_lane(
        C3,
        20,
        DVec2::new(100.0, 0.0),
        DVec2::new(120.0, 0.0),
        4.0,
        None,
    );
    m.add_straight_lane(
        L4,
        30,
        DVec2::new(120.0, 0.0),
        DVec2::new(220.0, 0.0),
        4.0,
        Some(15.0),
    );
    m.connect(L1, C3);
    m.connect(C3, L4);
    // Roadblock 10 spans both lanes.
    m.roadblocks.retain(|r| r.id != 10);
    m.roadblocks.push(VecRoadblock {
        id: 10,
        is_connector: false,
        polygon: vec![
            DVec2::new(0.0, -2.0),
            DVec2::new(100.0, -2.0),
            DVec2::new(100.0, 6.0),
            DVec2::new(0.0, 6.0),
        ],
    });
    m
}

/// Ego whose BOX CENTRE is at (x, y), heading h, speed v (rear axle = centre - 1.461 along h).
fn ego_center(t: f64, x: f64, y: f64, h: f64, v: f64) -> EgoStep {
    let d = EgoDims::PACIFICA.cog_position_from_rear_axle;
    EgoStep {
        time_s: t,
        position: DVec2::new(x - d * h.cos(), y - d * h.sin()),
        heading: h,
        velocity: DVec2::new(v, 0.0),
        acceleration: DVec2::ZERO,
        yaw_rate: 0.0,
        yaw_acceleration: 0.0,
    }
}

fn prep(ego: &[EgoStep]) -> (Vec<DVec2>, Vec<[DVec2; 4]>, Vec<i64>) {
    let d = EgoDims::PACIFICA;
    (
        ego.iter().map(|e| e.center(&d)).collect(),
        ego.iter().map(|e| e.footprint(&d).corners()).collect(),
        ego.iter()
            .map(|e| (e.time_s * 1e6).round() as i64)
            .collect(),
    )
}

#[test]
fn routes_and_common_or_connected() {
    let m = test_map();
    // Centred in lane 1; straddling lanes 1 and 2 (lane change); across the lane 1 -> connector 3 boundary.
    let ego = [
        ego_center(0.0, 50.0, 0.0, 0.0, 5.0),
        ego_center(0.1, 50.0, 2.0, 0.0, 5.0),
        ego_center(0.2, 100.5, 0.0, 0.0, 5.0),
    ];
    let (centers, corners, _) = prep(&ego);
    let route = get_route(&m, &centers);
    assert_eq!(route[0], vec![L1]);
    let cr = extract_corners_route(&m, &corners);
    assert_eq!(in_common_or_connected(&m, &cr), vec![true, false, true]);
}

#[test]
fn drivable_area() {
    let m = test_map();
    // Half width 1.1485: centre y = -0.9 puts the right corners at -2.0485 (0.0485 m out, within 0.3 of lane 1).
    let ego = [
        ego_center(0.0, 50.0, 0.0, 0.0, 5.0),
        ego_center(0.1, 50.0, -0.9, 0.0, 5.0),
    ];
    let (centers, corners, _) = prep(&ego);
    let r = drivable_area_compliance(
        &m,
        &corners,
        &extract_corners_route(&m, &corners),
        &get_route(&m, &centers),
        0.3,
    );
    assert_eq!(r.corners_in_drivable_area, vec![1.0, 0.0]);
    assert_eq!(r.score, 1.0);
    // Centre y = -1.2: corners at -2.3485, 0.3485 m from lane 1 and from the drivable area -> violation.
    let ego = [
        ego_center(0.0, 50.0, 0.0, 0.0, 5.0),
        ego_center(0.1, 50.0, -1.2, 0.0, 5.0),
    ];
    let (centers, corners, _) = prep(&ego);
    let r = drivable_area_compliance(
        &m,
        &corners,
        &extract_corners_route(&m, &corners),
        &get_route(&m, &centers),
        0.3,
    );
    assert!(r.far_from_drivable_area);
    assert_eq!(r.score, 0.0);
}

#[test]
fn driving_direction() {
    let m = test_map();
    // Reversing along lane 1 at v m/s for 2 s at 10 Hz: per-step progress -0.1 v; nuPlan sums 11 samples per
    // 1 s window (quirk), so the worst window is -1.1 v.
    for (v, score) in [(1.5, 1.0), (3.0, 0.5), (6.0, 0.0)] {
        let ego: Vec<EgoStep> = (0..21)
            .map(|i| ego_center(i as f64 * 0.1, 60.0 - 0.1 * v * i as f64, 0.0, 0.0, v))
            .collect();
        let (centers, _, times) = prep(&ego);
        let r = driving_direction_compliance(
            &m,
            &centers,
            &get_route(&m, &centers),
            &times,
            2.0,
            6.0,
            1.0,
        );
        assert!(
            (r.min_progress + 1.1 * v).abs() < 1e-9,
            "v={v}: {}",
            r.min_progress
        );
        assert_eq!(r.score, score, "v={v}");
    }
}

#[test]
fn speed_limit() {
    let m = test_map();
    // 12 m/s on lane 1 (limit 10) for 21 steps: loss = 21 * 2 * 0.1 / (2.23 * 2.0).
    let ego: Vec<EgoStep> = (0..21)
        .map(|i| ego_center(i as f64 * 0.1, 20.0 + 1.2 * i as f64, 0.0, 0.0, 12.0))
        .collect();
    let (centers, _, times) = prep(&ego);
    let r = speed_limit_compliance(&m, &ego, &get_route(&m, &centers), &times, 2.23);
    let want = 1.0 - 21.0 * 2.0 * 0.1 / (2.23 * 2.0);
    assert!((r.score - want).abs() < 1e-12, "{} vs {want}", r.score);
    assert_eq!(r.number_of_violations, 1);
    // On connector 3 the limit is the max of its neighbours (10, 15): 12 m/s is fine.
    let ego: Vec<EgoStep> = (0..5)
        .map(|i| ego_center(i as f64 * 0.1, 105.0 + 1.2 * i as f64, 0.0, 0.0, 12.0))
        .collect();
    let (centers, _, times) = prep(&ego);
    let route = get_route(&m, &centers);
    assert!(route.iter().all(|r| r == &vec![C3]));
    let r = speed_limit_compliance(&m, &ego, &route, &times, 2.23);
    assert_eq!(r.score, 1.0);
    assert!(r.violation_depths.iter().all(|&d| d == 0.0));
}

#[test]
fn progress_along_route() {
    let m = test_map();
    let line = |x0: f64, x1: f64, n: usize| -> Vec<DVec2> {
        (0..n)
            .map(|i| DVec2::new(x0 + (x1 - x0) * i as f64 / (n - 1) as f64, 0.0))
            .collect()
    };
    // Expert 90 -> 130 crosses roadblock 10 -> connector 20 -> roadblock 30: 40 m.
    let expert = line(90.0, 130.0, 41);
    let route = get_route(&m, &expert);
    let ego = line(90.0, 110.0, 41);
    let r = progress_along_expert_route(&m, &ego, &expert, &route, 2.0);
    assert!(
        (r.expert_progress - 40.0).abs() < 1e-9,
        "{}",
        r.expert_progress
    );
    assert!((r.ego_progress - 20.0).abs() < 1e-9, "{}", r.ego_progress);
    assert!((r.ratio - 0.5).abs() < 1e-12);
    // Ego jumping straight from roadblock 10 into roadblock 30 (skipping the connector) still gets the distance.
    let ego = vec![DVec2::new(95.0, 0.0), DVec2::new(125.0, 0.0)];
    let r = progress_along_expert_route(&m, &ego, &expert, &route, 2.0);
    assert!((r.ego_progress - 30.0).abs() < 1e-9, "{}", r.ego_progress);
    // Driving backwards more than 2 m -> 0; standing still -> max(0, 2) / 40.
    let r = progress_along_expert_route(&m, &line(100.0, 95.0, 6), &expert, &route, 2.0);
    assert_eq!(r.ratio, 0.0);
    let r = progress_along_expert_route(&m, &line(95.0, 95.0, 6), &expert, &route, 2.0);
    assert!((r.ratio - 2.0 / 40.0).abs() < 1e-12);
    // Expert off every lane: no route -> ratio 1.
    let off = line(0.0, 0.0, 3)
        .into_iter()
        .map(|p| p + DVec2::new(0.0, 50.0))
        .collect::<Vec<_>>();
    let r = progress_along_expert_route(&m, &ego, &off, &get_route(&m, &off), 2.0);
    assert_eq!(r.ratio, 1.0);
}
