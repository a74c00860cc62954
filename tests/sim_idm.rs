//! IDM agent manager on hand-built maps: lead selection (agent, stop line of a red connector, free road),
//! the projected-footprint quirk, lane matching, dropping overlapping agents, removal beyond 100 m.
use b2dr::scene::geometry::{OrientedBox, Polyline, Pose2};
use b2dr::scene::index::PolygonSet;
use b2dr::scene::map::{LaneKind, LaneSpec, Map, StopLine};
use b2dr::scene::{
    ObjectClass, ObjectState, Route, Scenario, Track, TrafficLightStatus, VehicleParameters,
};
use b2dr::sim::agents::{EgoObservation, IdmManager, LeaderRef};
use b2dr::sim::idm::{idm_accel, IdmParams, Lead};
use glam::DVec2;

fn line_lane(id: &str, x0: f64, x1: f64, kind: LaneKind) -> LaneSpec {
    let n = ((x1 - x0) as usize).max(1);
    LaneSpec {
        id: id.into(),
        kind,
        centre: Polyline::new(
            (0..=n)
                .map(|i| DVec2::new(x0 + (x1 - x0) * i as f64 / n as f64, 0.0))
                .collect(),
            None,
        ),
        polygon: None,
        width: 3.5,
        speed_limit_mps: None,
        successors: vec![],
        roadblock: None,
        has_traffic_light: kind == LaneKind::Connector,
        stop_lines: if kind == LaneKind::Connector {
            vec![0]
        } else {
            vec![]
        },
    }
}

/// A (0..50) -> connector C (50..60, traffic light, stop line at x 50..50.5) -> B (60..150).
fn map() -> Map {
    let stop = StopLine {
        id: "s".into(),
        polygon: [
            DVec2::new(50.5, 1.75),
            DVec2::new(50.0, 1.75),
            DVec2::new(50.0, -1.75),
            DVec2::new(50.5, -1.75),
        ],
    };
    Map::build(
        "t",
        vec![
            line_lane("A", 0.0, 50.0, LaneKind::Lane),
            line_lane("C", 50.0, 60.0, LaneKind::Connector),
            line_lane("B", 60.0, 150.0, LaneKind::Lane),
        ],
        vec![stop],
        vec![],
        vec![],
        PolygonSet::default(),
        true,
    )
    .unwrap()
}

fn vehicle(id: &str, x: f64, v: f64) -> Track {
    Track {
        id: id.into(),
        class: ObjectClass::Vehicle,
        length: 4.0,
        width: 2.0,
        height: 1.5,
        states: vec![Some(ObjectState {
            pose: Pose2::new(x, 0.0, 0.0),
            velocity: DVec2::new(v, 0.0),
        })],
    }
}

fn scenario(tracks: Vec<Track>) -> Scenario {
    Scenario {
        name: "t".into(),
        source: "test".into(),
        dt: 0.1,
        map: map(),
        ego: vec![],
        ego_params: VehicleParameters::PACIFICA,
        tracks,
        route: Route::default(),
        traffic_lights: vec![],
        rig: Default::default(),
        ego_past: vec![],
    }
}

fn step_v(v: f64, lead: Lead) -> f64 {
    let p = IdmParams::default();
    (v + 0.1 * idm_accel(&p, 10.0, v, &lead).clamp(-p.decel_max, p.accel_max)).max(0.0)
}

#[test]
fn follower_takes_agent_ahead_as_leader() {
    let sc = scenario(vec![vehicle("f", 10.0, 5.0), vehicle("l", 25.0, 3.0)]);
    let mut m = IdmManager::build(&sc, None, 0.0, IdmParams::default());
    assert_eq!(m.agents.len(), 2);
    let green = [(1usize, TrafficLightStatus::Green)];
    m.step(&sc.map, None, &green, &[], 0.1);
    // Follower: leader = agent 1, distance between boxes [8, 12] and [23, 27] = 11, v_lead = 3 cos 0.
    assert_eq!(m.leaders[0], Some(LeaderRef::Agent(1)));
    let f = m.agents[0].as_ref().unwrap();
    assert!(
        (f.velocity
            - step_v(
                5.0,
                Lead {
                    progress: 11.0,
                    velocity: 3.0,
                    length_rear: 0.0
                }
            ))
        .abs()
            < 1e-12
    );
    assert!((f.progress - 10.5).abs() < 1e-12);
    // Leader: the follower's new footprint ends at 10.5 + 2 + v 1.5 < 23: free road. The path runs A -> C -> B
    // (green) and its last state is dropped (quirk): end at 149, so x_lead = 149 - 25, l_r = 2.
    assert_eq!(m.leaders[1], None);
    let l = m.agents[1].as_ref().unwrap();
    assert!(
        (l.path.end() - l.progress - (149.0 - 25.3)).abs() < 1e-9,
        "{}",
        l.path.end() - l.progress
    );
    assert!(
        (l.velocity
            - step_v(
                3.0,
                Lead {
                    progress: 149.0 - 25.0,
                    velocity: 0.0,
                    length_rear: 2.0
                }
            ))
        .abs()
            < 1e-12
    );
}

#[test]
fn projected_footprint_quirk_makes_leader_brake_for_follower() {
    // The fast follower's footprint [p - L/2, p + L/2 + v T] reaches past the front car's centre, so the
    // front car (updated after it) sees it as its nearest obstacle at distance 0 (nuPlan quirk).
    let sc = scenario(vec![vehicle("f", 10.0, 10.0), vehicle("l", 22.0, 3.0)]);
    let mut m = IdmManager::build(&sc, None, 0.0, IdmParams::default());
    m.step(&sc.map, None, &[(1, TrafficLightStatus::Green)], &[], 0.1);
    assert_eq!(m.leaders[1], Some(LeaderRef::Agent(0)));
    let f_v = m.agents[0].as_ref().unwrap().velocity;
    let l = m.agents[1].as_ref().unwrap();
    // x_lead = 0 -> s_alpha = s0; v_lead = the follower's (new) speed projected with cos(0).
    assert!(
        (l.velocity
            - step_v(
                3.0,
                Lead {
                    progress: 0.0,
                    velocity: f_v,
                    length_rear: 0.0
                }
            ))
        .abs()
            < 1e-12
    );
}

#[test]
fn red_connector_stop_line_is_a_static_leader() {
    let sc = scenario(vec![vehicle("a", 30.0, 5.0)]);
    let mut m = IdmManager::build(&sc, None, 0.0, IdmParams::default());
    // Green: the route extends into C and B (progress to go < 20 + 10 * 1.5).
    m.step(&sc.map, None, &[(1, TrafficLightStatus::Green)], &[], 0.1);
    assert_eq!(m.agents[0].as_ref().unwrap().route.len(), 3);
    assert_eq!(m.leaders[0], None);
    // Red: the stop line of C (on the route) becomes the leader; distance from the agent's footprint
    // (box + path to p + L/2 + v T) to the stop line at x = 50.
    let before = m.agents[0].clone().unwrap();
    m.step(&sc.map, None, &[(1, TrafficLightStatus::Red)], &[], 0.1);
    assert_eq!(m.leaders[0], Some(LeaderRef::StopLine(0)));
    let front = before.progress + before.length / 2.0 + before.velocity * 1.5;
    let expected_gap = 50.0 - (30.0 + front - before.progress);
    let a = m.agents[0].as_ref().unwrap();
    assert!(
        (a.velocity
            - step_v(
                before.velocity,
                Lead {
                    progress: expected_gap,
                    velocity: 0.0,
                    length_rear: 0.0
                }
            ))
        .abs()
            < 1e-9
    );
}

#[test]
fn red_connector_is_not_taken_and_overlaps_are_dropped() {
    // "b" overlaps "a" after snapping: dropped. "c" is off the map: dropped.
    let mut c = vehicle("c", 30.0, 5.0);
    c.states[0].as_mut().unwrap().pose.y = 20.0;
    let sc = scenario(vec![vehicle("a", 30.0, 5.0), vehicle("b", 32.0, 5.0), c]);
    let mut m = IdmManager::build(&sc, None, 0.0, IdmParams::default());
    assert_eq!(m.agents.len(), 1);
    m.step(&sc.map, None, &[(1, TrafficLightStatus::Red)], &[], 0.1);
    // With C red at extension time, the route stays on A: free road to A's end (49, last state dropped).
    let a = m.agents[0].as_ref().unwrap();
    assert_eq!(a.route.len(), 1);
    assert_eq!(m.leaders[0], None);
}

#[test]
fn ego_is_a_leader_and_far_agents_are_removed() {
    let sc = scenario(vec![vehicle("a", 10.0, 5.0), vehicle("far", 140.0, 5.0)]);
    let ego_box = OrientedBox::new(Pose2::new(24.0, 0.0, 0.0), 5.0, 2.0);
    let mut m = IdmManager::build(&sc, Some(&ego_box), 0.0, IdmParams::default());
    assert_eq!(m.agents.len(), 2);
    let ego = EgoObservation {
        footprint: ego_box,
        rear_axle_heading: 0.1,
        speed: 4.0,
    };
    m.step(
        &sc.map,
        Some(&ego),
        &[(1, TrafficLightStatus::Green)],
        &[],
        0.1,
    );
    assert_eq!(m.leaders[0], Some(LeaderRef::Ego));
    // Gap from box [8, 12] to the ego box [21.5, 26.5] = 9.5; ego speed projected: 4 cos(0.1 - 0).
    let a = m.agents[0].as_ref().unwrap();
    assert!(
        (a.velocity
            - step_v(
                5.0,
                Lead {
                    progress: 9.5,
                    velocity: 4.0 * 0.1f64.cos(),
                    length_rear: 0.0
                }
            ))
        .abs()
            < 1e-12
    );
    // The agent at x = 140 is 116 m from the ego centre: removed for good.
    assert!(m.agents[1].is_none());
    assert_eq!(m.active(), 1);
}

#[test]
fn open_loop_object_is_a_static_leader() {
    // A moving pedestrian on the lane ahead: open-loop objects count with velocity 0 (nuPlan's "else"
    // branch), whatever their own speed.
    let sc = scenario(vec![vehicle("a", 10.0, 5.0)]);
    let mut m = IdmManager::build(&sc, None, 0.0, IdmParams::default());
    let ped = OrientedBox::new(Pose2::new(30.0, 0.5, 1.0), 0.6, 0.6);
    m.step(
        &sc.map,
        None,
        &[(1, TrafficLightStatus::Green)],
        &[(7, ped)],
        0.1,
    );
    assert_eq!(m.leaders[0], Some(LeaderRef::Object(7)));
    let gap = b2dr::scene::geometry::Shape::from_box(&OrientedBox::new(
        Pose2::new(10.0, 0.0, 0.0),
        4.0,
        2.0,
    ))
    .distance(&b2dr::scene::geometry::Shape::from_box(&ped));
    let a = m.agents[0].as_ref().unwrap();
    assert!(
        (a.velocity
            - step_v(
                5.0,
                Lead {
                    progress: gap,
                    velocity: 0.0,
                    length_rear: 0.0
                }
            ))
        .abs()
            < 1e-12
    );
}
