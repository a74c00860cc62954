//! The built-in synthetic towns (`builtin:LAYOUT[:seed[:n_vehicles[:palette]]]`), deterministic by spec.
//! `builtin:town` is the original: a 4-way signalised intersection with four straight arms (2 lanes per
//! direction, 3 in dense scenes), a 90-degree curve continuing the east arm northwards, crosswalks, stop lines,
//! traffic lights cycling over time, vehicles, pedestrians and traffic cones, a nuScenes-like 6-camera rig with
//! frames every 0.5 s. The other layouts ([`Layout`]) vary the arms, the curve, the lights and the lane count,
//! and add cyclists and barriers.
//!
//! Logs are generated, not scripted: the vehicles and the expert ego are driven by the IDM agent manager
//! itself (lane following, car following, stopping at red lights) for [`LOG_STEPS`] steps and recorded. This is
//! why the generator lives in `world` (above `sim`), not in `scene::import`.
//!
//! Invariant: `builtin:town[:seed[:n]]` must stay bit-identical to the original generator (the sim tests and
//! recorded scores depend on it): its random draws happen in the original order, and the layout-specific
//! additions only draw from a second generator. The one exception: a log whose expert the original generator
//! drove into a vehicle (a third of the dense seeds) is driven again with the ego starting slower.
pub mod layout;

use crate::scene::geometry::{OrientedBox, Pose2, Shape};
use crate::scene::import::{BuiltinSpec, Layout};
use crate::scene::map::LaneKind;
use crate::scene::{
    EgoLogState, ObjectClass, ObjectState, Route, Scenario, Track, TrafficLightStatus,
    VehicleParameters,
};
use crate::sim::agents::IdmManager;
use crate::sim::idm::IdmParams;
use glam::DVec2;
use layout::{build_layout, LayoutOptions, TownLayout, H, LANE_W};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::FRAC_PI_2;

/// Logged steps (20 s at 10 Hz: room for a 15 s run plus the expert's 4 s look-ahead).
pub const LOG_STEPS: usize = 201;
pub const DT: f64 = 0.1;

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

/// The original town (`builtin:town:SEED[:N]`).
pub fn town(seed: u64, n_vehicles: Option<usize>) -> Scenario {
    generate(&BuiltinSpec::town(seed, n_vehicles))
}

/// Layout options of a spec: (options, default vehicle count range).
fn options(spec: &BuiltinSpec) -> (LayoutOptions, std::ops::RangeInclusive<usize>) {
    let dense = spec.n_vehicles.is_some_and(|n| n > 40);
    let lanes_per_dir = if dense { 3 } else { 2 };
    let arm_len = if dense { 75.0 } else { 90.0 };
    let classic = LayoutOptions::classic(lanes_per_dir, arm_len);
    match spec.layout {
        Layout::Town => (classic, 8..=15),
        Layout::Cross => (
            LayoutOptions {
                curve: false,
                ..classic
            },
            8..=15,
        ),
        Layout::TJunction => (
            LayoutOptions {
                arms: [true, false, true, true],
                ..classic
            },
            6..=12,
        ),
        Layout::Straight => (
            LayoutOptions {
                arms: [true, false, true, false],
                curve: false,
                lights: false,
                ..classic
            },
            4..=9,
        ),
        Layout::Curve => (
            LayoutOptions {
                arms: [true, false, true, false],
                lights: false,
                ..classic
            },
            4..=9,
        ),
        Layout::Multilane => (
            // Three lanes per direction (a fourth would not fit the junction's right turns).
            LayoutOptions {
                lanes_per_dir: 3,
                ..classic
            },
            14..=24,
        ),
    }
}

fn lights_at(layout: &TownLayout, t: f64) -> Vec<(usize, TrafficLightStatus)> {
    layout
        .connectors
        .iter()
        .map(|&(c, ph)| (c, light_state(ph, t)))
        .collect()
}

/// Generates a built-in scenario. `n_vehicles` None gives a light scene (a layout-dependent count drawn from
/// the seed, 8-15 for the town); Some(n) n vehicles (dense scenes above 40: 3 lanes, shorter arms).
pub fn generate(spec: &BuiltinSpec) -> Scenario {
    let (seed, n_vehicles) = (spec.seed, spec.n_vehicles);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // Draws of the non-classic additions (cyclists, barriers): a generator of their own, so the town's draws
    // stay in their original order.
    let mut extra_rng = ChaCha8Rng::seed_from_u64(seed ^ 0x9e37_79b9_7f4a_7c15);
    let dense = n_vehicles.is_some_and(|n| n > 40);
    let (opt, default_count) = options(spec);
    let lanes_per_dir = opt.lanes_per_dir;
    let map_name = match spec.layout {
        Layout::Town => "synthetic-town".to_string(),
        l => format!("synthetic-{}", l.name()),
    };
    let layout = build_layout(opt, &map_name);
    let map = &layout.map;
    let n_veh = n_vehicles.unwrap_or_else(|| rng.gen_range(default_count));
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
    // Generate the vehicle logs with IDM on a provisional scenario. The expert must not crash: where the ego,
    // started at 8 m/s, would drive into a vehicle (a dense queue closer than its 16 m braking distance at IDM's
    // 2 m/s^2), the log is driven again with the ego starting slower. A log without a collision at 8 m/s is the
    // original one, bit for bit (nothing here draws from the generators).
    let drive = |tracks: &[Track]| drive_log(map, &layout, ego_params, tracks);
    let (mut logs, mut route_lanes, mut ego_agent) = drive(&tracks);
    for v0 in EGO_RESTART_SPEEDS {
        if ego_agent.is_none() || !ego_collides(&logs, &tracks) {
            break;
        }
        if let Some(s) = tracks[0].states[0].as_mut() {
            s.velocity = DVec2::new(s.pose.heading.cos(), s.pose.heading.sin()) * v0;
        }
        (logs, route_lanes, ego_agent) = drive(&tracks);
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
    crate::scene::import::scenarionet::fill_ego_accel(&mut ego, DT);
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
        let mut a = [1usize, 3, 0, 2][p % 4];
        if !opt.arms[a] {
            a = (a + 1) % 4; // north/south arm absent: the east/west one (both exist in every layout)
        }
        let th = a as f64 * FRAC_PI_2;
        let u = DVec2::new(th.cos(), th.sin());
        let n = u.perp();
        let speed = rng.gen_range(1.1..1.5);
        let phase = rng.gen_range(0.0..1.0);
        // Crosswalk walkers only where lights stop the traffic (the logs' vehicles do not yield to them).
        let (c, dir, span) = if p % 4 < 2 && opt.lights {
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
    if spec.layout != Layout::Town {
        add_extras(&mut out_tracks, &opt, &mut extra_rng);
    }
    let name = spec.name();
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
    let rig = crate::scene::import::default_rig(&name, &ego, DT);
    Scenario {
        name: name.clone(),
        source: spec.source(),
        dt: DT,
        map: layout.map,
        ego,
        ego_params,
        tracks: out_tracks,
        route,
        traffic_lights,
        rig,
        ego_past: vec![],
    }
}

/// The ego's start speeds tried in turn (m/s) when its log at 8 m/s would drive into a vehicle.
const EGO_RESTART_SPEEDS: [f64; 4] = [4.0, 2.0, 1.0, 0.0];

/// Per-track IDM logs of `tracks` (track 0 the ego) over [`LOG_STEPS`], the ego's route lanes, and the ego's
/// agent index (None: the IDM builder could not place it).
#[allow(clippy::type_complexity)]
fn drive_log(
    map: &crate::scene::map::Map,
    layout: &TownLayout,
    ego_params: VehicleParameters,
    tracks: &[Track],
) -> (Vec<Vec<Option<ObjectState>>>, Vec<usize>, Option<usize>) {
    let provisional = Scenario {
        name: "town-gen".into(),
        source: String::new(),
        dt: DT,
        map: map.clone(),
        ego: vec![],
        ego_params,
        tracks: tracks.to_vec(),
        route: Route::default(),
        traffic_lights: vec![],
        rig: Default::default(),
        ego_past: vec![],
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
        mgr.step(map, None, &lights_at(layout, k as f64 * DT), &[], DT);
        record(&mgr, k, &mut logs, &mut route_lanes);
    }
    (logs, route_lanes, ego_agent)
}

/// Whether the ego's logged footprint (track 0, centre poses) overlaps another track's at any step.
fn ego_collides(logs: &[Vec<Option<ObjectState>>], tracks: &[Track]) -> bool {
    let shape =
        |s: &ObjectState, t: &Track| Shape::from_box(&OrientedBox::new(s.pose, t.length, t.width));
    (0..LOG_STEPS).any(|k| {
        let Some(e) = &logs[0][k] else { return false };
        let ego = shape(e, &tracks[0]);
        (1..tracks.len()).any(|ti| {
            logs[ti][k]
                .as_ref()
                .is_some_and(|s| ego.intersects(&shape(s, &tracks[ti])))
        })
    })
}

/// Cyclists riding along the west arm's kerb and barriers on the east arm's shoulder (non-classic layouts).
fn add_extras(tracks: &mut Vec<Track>, opt: &LayoutOptions, rng: &mut ChaCha8Rng) {
    let half_road = opt.lanes_per_dir as f64 * LANE_W;
    for c in 0..2 {
        // Along the outer lane's right edge: eastbound on the south side (y < 0), westbound on the north side.
        let (y, dir) = if c == 0 {
            (-(half_road - 0.8), 1.0)
        } else {
            (half_road - 0.8, -1.0)
        };
        let x0 = -(H + rng.gen_range(10.0..60.0)) * dir;
        let speed = rng.gen_range(3.5..5.5);
        let states = (0..LOG_STEPS)
            .map(|k| {
                let x = x0 + dir * speed * k as f64 * DT;
                Some(ObjectState {
                    pose: Pose2::new(x, y, if dir > 0.0 { 0.0 } else { std::f64::consts::PI }),
                    velocity: DVec2::new(dir * speed, 0.0),
                })
            })
            .collect();
        tracks.push(Track {
            id: format!("cyclist_{c}"),
            class: ObjectClass::Bicycle,
            length: 1.8,
            width: 0.7,
            height: 1.75,
            states,
        });
    }
    for b in 0..3 {
        let pos = DVec2::new(H + 25.0 + 2.2 * b as f64, half_road + 0.7);
        tracks.push(Track {
            id: format!("barrier_{b}"),
            class: ObjectClass::Barrier,
            length: 2.0,
            width: 0.5,
            height: 1.0,
            states: vec![
                Some(ObjectState {
                    pose: Pose2::new(pos.x, pos.y, 0.0),
                    velocity: DVec2::ZERO
                });
                LOG_STEPS
            ],
        });
    }
}
