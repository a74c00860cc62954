//! nuPlan no_ego_at_fault_collisions fixtures (tests/fixtures/nuplan/no_ego_at_fault_collisions.json, derived
//! from nuplan-devkit `evaluation_metrics/common/test/json/no_ego_at_fault_collision/*.json`).
use b2dr::metrics::collisions::{at_fault_collisions, CollisionType};
use b2dr::metrics::{EgoDims, EgoStep, ObjectClass, ObjectState};
use glam::DVec2;
use serde::Deserialize;

#[derive(Deserialize)]
struct Ego {
    time_us: i64,
    pose: [f64; 3],
    velocity: [f64; 2],
    acceleration: [f64; 2],
}

#[derive(Deserialize)]
struct Obj {
    id: u64,
    class: ObjectClass,
    pose: [f64; 3],
    size: [f64; 2],
    speed: f64,
}

#[derive(Deserialize)]
struct Expected {
    no_at_fault: bool,
    total: usize,
    vru: usize,
    vehicles: usize,
    objects: usize,
    energy_max_min_mean: Option<[f64; 3]>,
}

#[derive(Deserialize)]
struct Scene {
    source: String,
    ego: Vec<Ego>,
    objects: Vec<Vec<Obj>>,
    expected: Expected,
    in_common_or_connected: Option<Vec<bool>>,
}

#[derive(Deserialize)]
struct Fixture {
    scenes: Vec<Scene>,
}

fn to_ego(e: &Ego) -> EgoStep {
    EgoStep {
        time_s: e.time_us as f64 * 1e-6,
        position: DVec2::new(e.pose[0], e.pose[1]),
        heading: e.pose[2],
        velocity: DVec2::from(e.velocity),
        acceleration: DVec2::from(e.acceleration),
        yaw_rate: 0.0,
        yaw_acceleration: 0.0,
    }
}

fn to_obj(o: &Obj) -> ObjectState {
    ObjectState {
        track_id: o.id,
        class: o.class,
        center: DVec2::new(o.pose[0], o.pose[1]),
        heading: o.pose[2],
        width: o.size[0],
        length: o.size[1],
        velocity: DVec2::new(o.speed, 0.0),
        is_agent: true,
    }
}

fn isclose(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-2 + 1e-5 * b.abs()
}

#[test]
fn nuplan_at_fault_collision_fixtures() {
    let f: Fixture = serde_json::from_str(include_str!(
        "fixtures/nuplan/no_ego_at_fault_collisions.json"
    ))
    .unwrap();
    assert_eq!(f.scenes.len(), 7);
    for s in &f.scenes {
        let ego: Vec<EgoStep> = s.ego.iter().map(to_ego).collect();
        let objects: Vec<Vec<ObjectState>> = s
            .objects
            .iter()
            .map(|v| v.iter().map(to_obj).collect())
            .collect();
        let common = s
            .in_common_or_connected
            .clone()
            .unwrap_or_else(|| vec![true; ego.len()]);
        let r = at_fault_collisions(&ego, &EgoDims::PACIFICA, &objects, &common);
        if s.in_common_or_connected.is_none() {
            // The map-dependent flag must not matter for scenes that do not give it.
            assert!(
                r.collisions
                    .iter()
                    .all(|c| c.kind != CollisionType::ActiveLateral),
                "{}: unexpected lateral collision {:?}",
                s.source,
                r.collisions
            );
        }
        let e = &s.expected;
        let total = r.at_fault_vru + r.at_fault_vehicles + r.at_fault_objects;
        assert_eq!(
            total == 0,
            e.no_at_fault,
            "{}: {:?}",
            s.source,
            r.collisions
        );
        assert_eq!(
            (
                total,
                r.at_fault_vru,
                r.at_fault_vehicles,
                r.at_fault_objects
            ),
            (e.total, e.vru, e.vehicles, e.objects),
            "{}",
            s.source
        );
        let energies: Vec<f64> = r
            .collisions
            .iter()
            .filter(|c| c.at_fault)
            .map(|c| c.ego_delta_v)
            .collect();
        match e.energy_max_min_mean {
            Some([max, min, mean]) => {
                let m = energies.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                let n = energies.iter().copied().fold(f64::INFINITY, f64::min);
                let a = energies.iter().sum::<f64>() / energies.len() as f64;
                assert!(
                    isclose(m, max) && isclose(n, min) && isclose(a, mean),
                    "{}: {energies:?}",
                    s.source
                );
            }
            None => assert!(energies.is_empty()),
        }
        println!(
            "{}: {:?} score {}",
            s.source,
            r.collisions
                .iter()
                .map(|c| (c.step, c.track_id, c.kind))
                .collect::<Vec<_>>(),
            r.score
        );
    }
}
