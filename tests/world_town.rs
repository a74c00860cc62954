//! The built-in towns: `builtin:town[:seed[:n]]` is bit-identical to the original generator (hashes recorded
//! from the generator as it was in `scene::import::synthetic` before the move to `world::town`), and the new
//! layouts load, differ, and keep their invariants.
use b2dr::scene::import::{resolve, Source};
use b2dr::scene::map::LaneKind;
use b2dr::scene::ObjectClass;
use b2dr::world::town::town;
use std::hash::{Hash, Hasher};

fn town_hash(seed: u64, n: Option<usize>) -> u64 {
    let sc = town(seed, n);
    // Fields added since the hashes were recorded are checked at their neutral values and left out of the
    // hashed text, which keeps the Debug text of the original types (Route without `mission_goal`, Camera
    // without `distortion`).
    assert!(sc.route.mission_goal.is_none());
    assert!(sc.rig.cameras.iter().all(|c| !c.is_distorted()));
    let route = format!(
        "Route {{ roadblock_ids: {:?}, lane_ids: {:?} }}",
        sc.route.roadblock_ids, sc.route.lane_ids
    );
    let cameras: Vec<String> = sc
        .rig
        .cameras
        .iter()
        .map(|c| {
            format!(
                "Camera {{ name: {:?}, intrinsic: {:?}, cam2ego: {:?}, width: {:?}, height: {:?} }}",
                c.name, c.intrinsic, c.cam2ego, c.width, c.height
            )
        })
        .collect();
    let cameras = format!("[{}]", cameras.join(", "));
    let frames: Vec<_> = sc
        .rig
        .frames
        .iter()
        .map(|f| (f.timestamp_us, f.ego2global))
        .collect();
    let s = format!(
        "{}|{}|{:?}|{:?}|{}|{:?}|{:?}|{:?}|{:?}|{:?}|{:?}|{:?}|{}",
        sc.name,
        sc.source,
        sc.ego,
        sc.tracks,
        route,
        sc.traffic_lights,
        sc.map.lanes,
        sc.map.roadblocks,
        sc.map.stop_lines,
        sc.map.crosswalks,
        sc.map.intersections,
        frames,
        cameras
    );
    let mut h = std::collections::hash_map::DefaultHasher::new();
    s.hash(&mut h);
    h.finish()
}

/// Hashes of the original generator (commit 526bf52, `scene::import::synthetic::town`), everything but the
/// image paths (which became `builtin://` paths on purpose), except where the original log had the expert
/// crash.
#[test]
fn classic_town_is_bit_identical_to_the_original() {
    for (seed, n, want) in [
        (0u64, None, 0xabddeb15126657a9u64),
        (1, None, 0xd9f211b61cdee5d0),
        (3, None, 0xf3fcf60207df9989),
        (5, None, 0x6be8cc40946e841e),
        (1, Some(200usize), 0x7c8034a3e567004e),
        // the original log (0x3706afc39a424731) had the expert drive into veh_027 at step 27; since session 43 it
        // is driven again with the ego starting slower (the_expert_never_drives_into_a_vehicle, below)
        (2, Some(60), 0xe6dcb87f8b9d18bd),
    ] {
        assert_eq!(
            town_hash(seed, n),
            want,
            "builtin:town:{seed}:{n:?} changed"
        );
    }
}

#[test]
fn new_layouts_load_and_differ() {
    let mut names = Vec::new();
    for spec in [
        "builtin:cross:1",
        "builtin:tjunction:2",
        "builtin:straight:3",
        "builtin:curve:4",
        "builtin:multilane:5",
        "builtin:tjunction:2::evening",
        "builtin:straight:3:12",
    ] {
        let src = resolve(spec).unwrap();
        let Source::Builtin(_) = &src[0] else {
            panic!("{spec}")
        };
        let sc = b2dr::world::load(&src[0]).unwrap();
        assert_eq!(sc.len(), 201, "{spec}");
        assert_eq!(sc.source, spec, "{spec}");
        assert!(
            (sc.ego[150].rear_axle.pos() - sc.ego[0].rear_axle.pos()).length() > 30.0,
            "{spec}: the expert must drive"
        );
        assert!(
            sc.tracks.iter().any(|t| t.class == ObjectClass::Bicycle),
            "{spec}"
        );
        assert!(
            sc.tracks.iter().any(|t| t.class == ObjectClass::Barrier),
            "{spec}"
        );
        for l in sc
            .map
            .lanes
            .iter()
            .filter(|l| l.kind == LaneKind::Connector)
        {
            assert!(
                !l.successors.is_empty() && !l.predecessors.is_empty(),
                "{spec} {}",
                l.id
            );
        }
        names.push(sc.name.clone());
        match spec {
            "builtin:straight:3" | "builtin:curve:4" => {
                assert!(
                    sc.map.intersections.is_empty() && sc.map.stop_lines.is_empty(),
                    "{spec}"
                )
            }
            "builtin:tjunction:2" => {
                assert!(!sc.map.lanes.iter().any(|l| l.id.starts_with("north_in")))
            }
            "builtin:multilane:5" => assert!(sc.map.lanes.iter().any(|l| l.id == "west_in_2")),
            _ => {}
        }
    }
    names.sort();
    names.dedup();
    assert_eq!(names.len(), 7);
    assert!(resolve("builtin:town:1:2:dusk").is_err());
    assert!(resolve("builtin:roundabout").is_err());
}

/// The expert never crashes: in no built-in log does the ego's footprint overlap a vehicle's box at any step.
/// Dense queues used to start 12 m ahead of an ego at 8 m/s (16 m of braking at IDM's 2 m/s^2): in a third of
/// the dense seeds the logged ego drove into the car ahead and sat inside it, its cameras showing the car's
/// inside and its layout masks a car over the whole frame. Such a log is now driven with the ego starting
/// slower; the others are unchanged (the hashes above).
#[test]
fn the_expert_never_drives_into_a_vehicle() {
    use b2dr::scene::geometry::OrientedBox;
    use b2dr::scene::geometry::Shape;
    let mut specs = vec![];
    for l in [
        "town",
        "cross",
        "tjunction",
        "straight",
        "curve",
        "multilane",
    ] {
        for s in [0, 1, 2, 3, 100, 101, 102, 103, 104, 105, 106, 107, 108] {
            specs.push(format!("builtin:{l}:{s}:60"));
        }
        specs.push(format!("builtin:{l}:0"));
    }
    let mut bad = vec![];
    for spec in &specs {
        let sc = b2dr::world::load_all(spec).unwrap().remove(0);
        'steps: for (k, e) in sc.ego.iter().enumerate() {
            let ego = Shape::from_box(&sc.ego_params.footprint(&e.rear_axle));
            for t in sc.tracks.iter().filter(|t| t.class == ObjectClass::Vehicle) {
                if let Some(s) = t.states.get(k).copied().flatten() {
                    if ego.intersects(&Shape::from_box(&OrientedBox::new(
                        s.pose, t.length, t.width,
                    ))) {
                        bad.push(format!("{spec}: step {k}, {}", t.id));
                        break 'steps;
                    }
                }
            }
        }
    }
    assert!(bad.is_empty(), "the expert overlaps a vehicle: {bad:?}");
}
