//! The built-in synthetic town (`builtin:town[:seed[:n_vehicles]]`), deterministic by seed: a 4-way
//! signalised intersection with four straight arms (2 lanes per direction, 3 in dense scenes), a 90-degree
//! curve continuing the east arm northwards, crosswalks, stop lines, traffic lights cycling over time,
//! vehicles, pedestrians and traffic cones, a nuScenes-like 6-camera rig with frames every 0.5 s.
//!
//! Logs are generated, not scripted: the vehicles and the expert ego are driven by the IDM agent manager
//! itself (lane following, car following, stopping at red lights) for [`LOG_STEPS`] steps and recorded.
use crate::scene::geometry::{Polyline, Pose2};
use crate::scene::index::PolygonSet;
use crate::scene::map::{Crosswalk, LaneKind, LaneSpec, Map, StopLine};
use crate::scene::{
    EgoLogState, ObjectClass, ObjectState, Route, Scenario, Track, TrafficLightStatus,
    VehicleParameters,
};
use crate::sim::agents::IdmManager;
use crate::sim::idm::IdmParams;
use glam::DVec2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::FRAC_PI_2;

/// Logged steps (20 s at 10 Hz: room for a 15 s run plus the expert's 4 s look-ahead).
pub const LOG_STEPS: usize = 201;
pub const DT: f64 = 0.1;
const LANE_W: f64 = 3.5;
/// Intersection half size.
const H: f64 = 11.0;
const LANE_SPEED: f64 = 12.0;
const CONNECTOR_SPEED: f64 = 9.0;

/// Light state of a phase at time t: phase 0 (east-west) green 0-10 s, yellow 10-12, red 12-20; phase 1
/// (north-south) red 0-12.5, green 12.5-17.5, yellow 17.5-19.5, red 19.5-20; cycle 20 s.
pub fn light_state(phase: usize, t: f64) -> TrafficLightStatus {
    let c = t.rem_euclid(20.0);
    use TrafficLightStatus::*;
    if phase == 0 {
        if c < 10.0 {
            Green
        } else if c < 12.0 {
            Yellow
        } else {
            Red
        }
    } else if (12.5..17.5).contains(&c) {
        Green
    } else if (17.5..19.5).contains(&c) {
        Yellow
    } else {
        Red
    }
}

fn sample_line(a: DVec2, b: DVec2) -> Vec<DVec2> {
    let n = ((b - a).length().ceil() as usize).max(2);
    (0..=n)
        .map(|i| a + (b - a) * (i as f64 / n as f64))
        .collect()
}

fn sample_bezier(p0: DVec2, d0: DVec2, p3: DVec2, d3: DVec2) -> Vec<DVec2> {
    let k = 0.55 * (p3 - p0).length();
    let (p1, p2) = (p0 + d0 * k, p3 - d3 * k);
    let n = (((p3 - p0).length() * 1.3).ceil() as usize).max(4);
    (0..=n)
        .map(|i| {
            let t = i as f64 / n as f64;
            let u = 1.0 - t;
            p0 * (u * u * u) + p1 * (3.0 * u * u * t) + p2 * (3.0 * u * t * t) + p3 * (t * t * t)
        })
        .collect()
}

fn sample_arc(c: DVec2, r: f64, a0: f64, a1: f64) -> Vec<DVec2> {
    let n = ((r * (a1 - a0).abs()).ceil() as usize).max(4);
    (0..=n)
        .map(|i| {
            let a = a0 + (a1 - a0) * i as f64 / n as f64;
            c + DVec2::new(a.cos(), a.sin()) * r
        })
        .collect()
}

fn rect(c: DVec2, u: DVec2, half_u: f64, half_n: f64) -> [DVec2; 4] {
    let n = u.perp();
    [
        c + u * half_u + n * half_n,
        c - u * half_u + n * half_n,
        c - u * half_u - n * half_n,
        c + u * half_u - n * half_n,
    ]
}

struct TownLayout {
    map: Map,
    /// Per arm, per lane: the inbound lane index.
    inbound: Vec<Vec<usize>>,
    /// Connector indices with their phase.
    connectors: Vec<(usize, usize)>,
}

fn build_layout(lanes_per_dir: usize, arm_len: f64) -> TownLayout {
    let mut specs: Vec<LaneSpec> = Vec::new();
    let mut stop_lines = Vec::new();
    let mut crosswalks = Vec::new();
    let mut inbound = vec![vec![]; 4];
    let mut ends = vec![vec![(DVec2::ZERO, DVec2::ZERO); lanes_per_dir]; 4]; // inbound end (point, dir)
    let mut starts = vec![vec![(DVec2::ZERO, DVec2::ZERO); lanes_per_dir]; 4]; // outbound start
    let off = |i: usize| LANE_W / 2.0 + i as f64 * LANE_W;
    let lane = |id: String, pts: Vec<DVec2>, kind: LaneKind, rb: String, speed: f64| LaneSpec {
        id,
        kind,
        centre: Polyline::new(pts, None),
        polygon: None,
        width: LANE_W,
        speed_limit_mps: Some(speed),
        successors: vec![],
        roadblock: Some(rb),
        has_traffic_light: kind == LaneKind::Connector,
        stop_lines: vec![],
    };
    let names = ["east", "north", "west", "south"];
    for a in 0..4 {
        let th = a as f64 * FRAC_PI_2;
        let u = DVec2::new(th.cos(), th.sin());
        let n = u.perp();
        for i in 0..lanes_per_dir {
            let o = off(i);
            let (p_far, p_near) = (u * (H + arm_len) + n * o, u * H + n * o);
            inbound[a].push(specs.len());
            specs.push(lane(
                format!("{}_in_{i}", names[a]),
                sample_line(p_far, p_near),
                LaneKind::Lane,
                format!("{}_in", names[a]),
                LANE_SPEED,
            ));
            ends[a][i] = (p_near, -u);
            stop_lines.push(StopLine {
                id: format!("stop_{}_{i}", names[a]),
                polygon: rect(u * (H + 0.25) + n * o, u, 0.25, LANE_W / 2.0),
            });
            let (q_near, q_far) = (u * H - n * o, u * (H + arm_len) - n * o);
            specs.push(lane(
                format!("{}_out_{i}", names[a]),
                sample_line(q_near, q_far),
                LaneKind::Lane,
                format!("{}_out", names[a]),
                LANE_SPEED,
            ));
            starts[a][i] = (q_near, u);
        }
        let half_road = lanes_per_dir as f64 * LANE_W;
        crosswalks.push(Crosswalk {
            id: format!("crosswalk_{}", names[a]),
            polygon: rect(u * (H + 3.0), u, 2.0, half_road).to_vec(),
        });
    }
    // The curve: east arm outbound lanes turn left (north) around C, then run 40 m north; inbound mirror.
    let r0 = 30.0;
    let c = DVec2::new(H + arm_len, r0);
    for i in 0..lanes_per_dir {
        let o = off(i);
        let ro = r0 + o;
        specs.push(lane(
            format!("curve_out_{i}"),
            sample_arc(c, ro, -FRAC_PI_2, 0.0),
            LaneKind::Lane,
            "curve_out".into(),
            LANE_SPEED,
        ));
        specs.push(lane(
            format!("north_road_out_{i}"),
            sample_line(c + DVec2::new(ro, 0.0), c + DVec2::new(ro, 40.0)),
            LaneKind::Lane,
            "north_road_out".into(),
            LANE_SPEED,
        ));
        let ri = r0 - o;
        specs.push(lane(
            format!("north_road_in_{i}"),
            sample_line(c + DVec2::new(ri, 40.0), c + DVec2::new(ri, 0.0)),
            LaneKind::Lane,
            "north_road_in".into(),
            LANE_SPEED,
        ));
        specs.push(lane(
            format!("curve_in_{i}"),
            sample_arc(c, ri, 0.0, -FRAC_PI_2),
            LaneKind::Lane,
            "curve_in".into(),
            LANE_SPEED,
        ));
    }
    // Connectors: straight for every lane, left from the inner lane, right from the outer lane.
    let mut connectors = Vec::new();
    for a in 0..4 {
        let mut add = |specs: &mut Vec<LaneSpec>, i: usize, b: usize, j: usize, kind: &str| {
            let (p0, d0) = ends[a][i];
            let (p3, d3) = starts[b][j];
            let pts = if kind == "straight" {
                sample_line(p0, p3)
            } else {
                sample_bezier(p0, d0, p3, d3)
            };
            let mut s = lane(
                format!("conn_{}_{i}_{}_{j}", names[a], names[b]),
                pts,
                LaneKind::Connector,
                format!("conn_{}_{}", names[a], names[b]),
                CONNECTOR_SPEED,
            );
            s.stop_lines = vec![a * lanes_per_dir + i];
            connectors.push((specs.len(), a % 2));
            specs.push(s);
        };
        for i in 0..lanes_per_dir {
            add(&mut specs, i, (a + 2) % 4, i, "straight");
        }
        add(&mut specs, 0, (a + 3) % 4, 0, "left");
        add(
            &mut specs,
            lanes_per_dir - 1,
            (a + 1) % 4,
            lanes_per_dir - 1,
            "right",
        );
    }
    let inter = vec![vec![
        DVec2::new(-H, -H),
        DVec2::new(H, -H),
        DVec2::new(H, H),
        DVec2::new(-H, H),
    ]];
    let map = Map::build(
        "synthetic-town",
        specs,
        stop_lines,
        crosswalks,
        inter,
        PolygonSet::default(),
        true,
    )
    .expect("the synthetic town is well formed");
    TownLayout {
        map,
        inbound,
        connectors,
    }
}

fn lights_at(layout: &TownLayout, t: f64) -> Vec<(usize, TrafficLightStatus)> {
    layout
        .connectors
        .iter()
        .map(|&(c, ph)| (c, light_state(ph, t)))
        .collect()
}

/// Generates the town. `n_vehicles` None gives a light scene (8-15 vehicles by seed); Some(n) a dense one.
pub fn town(seed: u64, n_vehicles: Option<usize>) -> Scenario {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let dense = n_vehicles.is_some_and(|n| n > 40);
    let lanes_per_dir = if dense { 3 } else { 2 };
    let arm_len = if dense { 75.0 } else { 90.0 };
    let layout = build_layout(lanes_per_dir, arm_len);
    let map = &layout.map;
    let n_veh = n_vehicles.unwrap_or_else(|| rng.gen_range(8..=15));
    let ego_params = VehicleParameters::PACIFICA;

    // Ego: west arm, inbound (eastbound) inner lane, heading east through the intersection into the curve.
    let west = 2;
    let ego_lane = layout.inbound[west][0];
    let ego_s = if dense { 40.0 } else { 25.0 };
    let ego_center = map.lanes[ego_lane].centre.pose_at(ego_s);
    let mut tracks: Vec<Track> = Vec::new();
    let mk_vehicle = |id: String, pose: Pose2, v: f64, len: f64, wid: f64| Track {
        id,
        class: ObjectClass::Vehicle,
        length: len,
        width: wid,
        height: 1.6,
        states: vec![Some(ObjectState {
            pose,
            velocity: DVec2::new(pose.heading.cos(), pose.heading.sin()) * v,
        })],
    };
    tracks.push(mk_vehicle(
        "ego".into(),
        ego_center,
        8.0,
        ego_params.length,
        ego_params.width,
    ));
    // Candidate slots on arm lanes (not connectors, not the far curve), evenly spaced, shuffled by seed.
    let mut slots: Vec<(usize, f64)> = Vec::new();
    let spacing = if dense { 7.6 } else { 12.0 };
    for (li, l) in map.lanes.iter().enumerate() {
        if l.kind != LaneKind::Lane || l.id.starts_with("curve") || l.id.starts_with("north_road") {
            continue;
        }
        let mut s = 3.0;
        while s < l.centre.length() - 3.0 {
            slots.push((li, s));
            s += spacing;
        }
    }
    // Keep the ego's surroundings free: no slot within 12 m of the ego.
    slots.retain(|&(li, s)| (map.lanes[li].centre.point_at(s) - ego_center.pos()).length() > 12.0);
    for i in (1..slots.len()).rev() {
        let j = rng.gen_range(0..=i);
        slots.swap(i, j);
    }
    for (k, &(li, s)) in slots.iter().take(n_veh).enumerate() {
        let pose = map.lanes[li].centre.pose_at(s + rng.gen_range(-0.8..0.8));
        let len = rng.gen_range(4.2..5.2);
        let wid = rng.gen_range(1.8..2.05);
        // Dense scenes start as slow queues: with nuPlan's footprint quirk a fast follower closer than
        // L + vT makes its leader brake for it, and the pair collides (see sim::agents).
        let v = if dense {
            rng.gen_range(0.0..1.5)
        } else {
            rng.gen_range(3.0..9.0)
        };
        tracks.push(mk_vehicle(format!("veh_{k:03}"), pose, v, len, wid));
    }
    // Generate the vehicle logs with IDM on a provisional scenario.
    let provisional = Scenario {
        name: "town-gen".into(),
        source: String::new(),
        dt: DT,
        map: map.clone(),
        ego: vec![],
        ego_params,
        tracks: tracks.clone(),
        route: Route::default(),
        traffic_lights: vec![],
        rig: Default::default(),
    };
    let params = IdmParams {
        radius: f64::INFINITY,
        ..IdmParams::default()
    };
    let mut mgr = IdmManager::build(&provisional, None, 0.0, params);
    let ego_agent = mgr
        .agents
        .iter()
        .position(|a| a.as_ref().is_some_and(|a| a.track == 0));
    let mut logs: Vec<Vec<Option<ObjectState>>> = vec![vec![None; LOG_STEPS]; tracks.len()];
    let mut route_lanes: Vec<usize> = Vec::new();
    let record = |mgr: &IdmManager,
                  k: usize,
                  logs: &mut Vec<Vec<Option<ObjectState>>>,
                  route: &mut Vec<usize>| {
        for a in mgr.agents.iter().flatten() {
            logs[a.track][k] = Some(ObjectState {
                pose: a.pose(),
                velocity: a.velocity_vec(),
            });
            if a.track == 0 {
                for &l in &a.route {
                    if !route.contains(&l) {
                        route.push(l);
                    }
                }
            }
        }
    };
    record(&mgr, 0, &mut logs, &mut route_lanes);
    for k in 1..LOG_STEPS {
        mgr.step(map, None, &lights_at(&layout, k as f64 * DT), &[], DT);
        record(&mgr, k, &mut logs, &mut route_lanes);
    }
    // Ego log (rear axle) from the ego agent; if it could not be placed, a standstill log.
    let mut ego: Vec<EgoLogState> = (0..LOG_STEPS)
        .map(|k| {
            let s = if ego_agent.is_some() {
                logs[0][k]
            } else {
                None
            }
            .unwrap_or(ObjectState {
                pose: ego_center,
                velocity: DVec2::ZERO,
            });
            EgoLogState {
                rear_axle: ego_params.rear_axle_of(&s.pose),
                velocity: s.velocity,
                accel: 0.0,
            }
        })
        .collect();
    super::scenarionet::fill_ego_accel(&mut ego, DT);
    let mut out_tracks: Vec<Track> = Vec::new();
    for (ti, tr) in tracks.iter().enumerate().skip(1) {
        if logs[ti].iter().all(|s| s.is_none()) {
            continue; // dropped by the IDM builder (overlap): not part of the log
        }
        out_tracks.push(Track {
            states: logs[ti].clone(),
            ..tr.clone()
        });
    }
    // Pedestrians: crossing the north and south arms' crosswalks back and forth, and walking on sidewalks.
    let half_road = lanes_per_dir as f64 * LANE_W;
    let n_ped = 4 + (seed % 3) as usize;
    for p in 0..n_ped {
        let a = [1usize, 3, 0, 2][p % 4];
        let th = a as f64 * FRAC_PI_2;
        let u = DVec2::new(th.cos(), th.sin());
        let n = u.perp();
        let speed = rng.gen_range(1.1..1.5);
        let phase = rng.gen_range(0.0..1.0);
        let (c, dir, span) = if p % 4 < 2 {
            (u * (H + 3.0), n, half_road + 2.0) // crosswalk
        } else {
            (u * (H + 20.0) + n * (half_road + 2.0), u, 15.0) // sidewalk
        };
        let states = (0..LOG_STEPS)
            .map(|k| {
                // Triangle wave along dir between -span and +span.
                let d = (phase * 4.0 * span + speed * k as f64 * DT).rem_euclid(4.0 * span);
                let (x, sgn) = if d < 2.0 * span {
                    (d - span, 1.0)
                } else {
                    (3.0 * span - d, -1.0)
                };
                let pos = c + dir * x;
                let h = (dir * sgn).y.atan2((dir * sgn).x);
                Some(ObjectState {
                    pose: Pose2::new(pos.x, pos.y, h),
                    velocity: dir * sgn * speed,
                })
            })
            .collect();
        out_tracks.push(Track {
            id: format!("ped_{p:02}"),
            class: ObjectClass::Pedestrian,
            length: 0.6,
            width: 0.6,
            height: 1.75,
            states,
        });
    }
    // Traffic cones on the west arm's shoulder.
    for c in 0..3 {
        let pos = DVec2::new(-(H + 30.0 + 2.0 * c as f64), -(half_road + 0.6));
        out_tracks.push(Track {
            id: format!("cone_{c}"),
            class: ObjectClass::TrafficCone,
            length: 0.4,
            width: 0.4,
            height: 0.7,
            states: vec![
                Some(ObjectState {
                    pose: Pose2::new(pos.x, pos.y, 0.0),
                    velocity: DVec2::ZERO
                });
                LOG_STEPS
            ],
        });
    }
    let name = match n_vehicles {
        Some(n) => format!("town-{seed}-{n}v"),
        None => format!("town-{seed}"),
    };
    let mut route = Route::default();
    for &l in &route_lanes {
        route.lane_ids.push(map.lanes[l].id.clone());
        let rb = &map.roadblocks[map.lanes[l].roadblock].id;
        if route.roadblock_ids.last() != Some(rb) {
            route.roadblock_ids.push(rb.clone());
        }
    }
    let traffic_lights = (0..LOG_STEPS)
        .map(|k| lights_at(&layout, k as f64 * DT))
        .collect();
    let rig = super::default_rig(&name, &ego, DT);
    Scenario {
        name: name.clone(),
        source: format!(
            "builtin:town:{seed}{}",
            n_vehicles.map(|n| format!(":{n}")).unwrap_or_default()
        ),
        dt: DT,
        map: layout.map,
        ego,
        ego_params,
        tracks: out_tracks,
        route,
        traffic_lights,
        rig,
    }
}
