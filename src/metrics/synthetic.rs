//! Synthetic busy scenario (straight multi-lane road, many agents) for benches and tests; seeded and
//! deterministic.
use super::input::{EgoDims, EgoStep, LaneId, ObjectClass, ObjectState, ScenarioTrace};
use super::vecmap::{VecMap, VecRoadblock};
use glam::DVec2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Lane width (m) of the synthetic road.
pub const LANE_WIDTH: f64 = 3.5;
/// Roadblock length (m).
pub const BLOCK_LEN: f64 = 100.0;

/// A straight road along +x with `lanes` lanes and `blocks` roadblocks of 100 m; lane ids are
/// `block * 100 + lane`, roadblock ids `block`; speed limit 15 m/s.
pub fn straight_road(lanes: usize, blocks: usize) -> VecMap {
    let mut m = VecMap::default();
    for b in 0..blocks {
        let x0 = b as f64 * BLOCK_LEN;
        for l in 0..lanes {
            let y = l as f64 * LANE_WIDTH;
            let id = LaneId {
                id: (b * 100 + l) as u64,
                is_connector: false,
            };
            m.add_straight_lane(
                id,
                b as u64,
                DVec2::new(x0, y),
                DVec2::new(x0 + BLOCK_LEN, y),
                LANE_WIDTH,
                Some(15.0),
            );
            if b > 0 {
                m.connect(
                    LaneId {
                        id: ((b - 1) * 100 + l) as u64,
                        is_connector: false,
                    },
                    id,
                );
            }
        }
        m.roadblocks.retain(|r| r.id != b as u64);
        let h = LANE_WIDTH / 2.0;
        let top = (lanes as f64 - 1.0) * LANE_WIDTH + h;
        m.roadblocks.push(VecRoadblock {
            id: b as u64,
            is_connector: false,
            polygon: vec![
                DVec2::new(x0, -h),
                DVec2::new(x0 + BLOCK_LEN, -h),
                DVec2::new(x0 + BLOCK_LEN, top),
                DVec2::new(x0, top),
            ],
        });
    }
    m
}

/// `steps` steps at 10 Hz, `objects` agents around the ego on a 4-lane road; the ego weaves gently in
/// lane 1 at about 10 m/s, the expert drives straight at 11 m/s.
pub fn busy_scenario(steps: usize, objects: usize, seed: u64) -> (VecMap, ScenarioTrace) {
    let map = straight_road(4, 6);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let dims = EgoDims::PACIFICA;
    let dt = 0.1;
    let ego: Vec<EgoStep> = (0..steps)
        .map(|i| {
            let t = i as f64 * dt;
            let y = LANE_WIDTH + 0.4 * (0.5 * t).sin();
            let vy = 0.2 * (0.5 * t).cos();
            let heading = (vy / 10.0).atan();
            EgoStep {
                time_s: t,
                position: DVec2::new(20.0 + 10.0 * t, y),
                heading,
                velocity: DVec2::new(10.0, 0.0),
                acceleration: DVec2::new(0.0, -0.1 * (0.5 * t).sin()),
                yaw_rate: -0.01 * (0.5 * t).sin(),
                yaw_acceleration: 0.0,
            }
        })
        .collect();
    let expert: Vec<EgoStep> = (0..steps)
        .map(|i| {
            let t = i as f64 * dt;
            EgoStep {
                time_s: t,
                position: DVec2::new(20.0 + 11.0 * t, LANE_WIDTH),
                heading: 0.0,
                velocity: DVec2::new(11.0, 0.0),
                acceleration: DVec2::ZERO,
                yaw_rate: 0.0,
                yaw_acceleration: 0.0,
            }
        })
        .collect();
    // Initial object states: vehicles in lanes, pedestrians and cones on the verge.
    struct Init {
        class: ObjectClass,
        p: DVec2,
        v: f64,
        h: f64,
        l: f64,
        w: f64,
    }
    let inits: Vec<Init> = (0..objects)
        .map(|_| {
            let r: f64 = rng.gen();
            if r < 0.8 {
                let lane = rng.gen_range(0..4) as f64;
                Init {
                    class: ObjectClass::Vehicle,
                    p: DVec2::new(
                        rng.gen_range(-50.0..450.0),
                        lane * LANE_WIDTH + rng.gen_range(-0.3..0.3),
                    ),
                    v: rng.gen_range(0.0..14.0),
                    h: rng.gen_range(-0.05..0.05),
                    l: 4.7,
                    w: 2.0,
                }
            } else if r < 0.9 {
                Init {
                    class: ObjectClass::Pedestrian,
                    p: DVec2::new(rng.gen_range(0.0..400.0), -3.0 - rng.gen_range(0.0..3.0)),
                    v: rng.gen_range(0.0..1.5),
                    h: rng.gen_range(-3.0..3.0),
                    l: 0.6,
                    w: 0.6,
                }
            } else {
                Init {
                    class: ObjectClass::TrafficCone,
                    p: DVec2::new(
                        rng.gen_range(0.0..400.0),
                        4.0 * LANE_WIDTH + rng.gen_range(0.0..2.0),
                    ),
                    v: 0.0,
                    h: 0.0,
                    l: 0.5,
                    w: 0.5,
                }
            }
        })
        .collect();
    let frames: Vec<Vec<ObjectState>> = (0..steps)
        .map(|i| {
            let t = i as f64 * dt;
            inits
                .iter()
                .enumerate()
                .map(|(k, o)| {
                    let dir = DVec2::new(o.h.cos(), o.h.sin());
                    ObjectState {
                        track_id: k as u64,
                        class: o.class,
                        center: o.p + dir * o.v * t,
                        heading: o.h,
                        length: o.l,
                        width: o.w,
                        velocity: dir * o.v,
                        is_agent: !o.class.is_static(),
                    }
                })
                .collect()
        })
        .collect();
    let trace = ScenarioTrace {
        name: format!("synthetic_{steps}x{objects}_{seed}"),
        ego_dims: dims,
        ego,
        objects: frames,
        expert,
        route_roadblocks: (0..6).collect(),
    };
    (map, trace)
}
