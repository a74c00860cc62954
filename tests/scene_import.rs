//! Importer and map tests: errors name the file and the field, lane links are inferred from geometry
//! (1 m, 30 deg), the synthetic town is deterministic and well formed, the shared scenes load.
use b2dr::scene::geometry::Polyline;
use b2dr::scene::import::{resolve, scenarionet, BuiltinSpec, Source};
use b2dr::scene::index::PolygonSet;
use b2dr::scene::map::{infer_lane_links, LaneKind, LaneSpec, Map};
use b2dr::world::town as synthetic;
use glam::DVec2;
use serde_json::json;
use std::path::PathBuf;

fn lane(id: &str, pts: &[(f64, f64)]) -> LaneSpec {
    LaneSpec {
        id: id.into(),
        kind: LaneKind::Lane,
        centre: Polyline::new(pts.iter().map(|&(x, y)| DVec2::new(x, y)).collect(), None),
        polygon: None,
        width: 3.5,
        speed_limit_mps: None,
        successors: vec![],
        roadblock: None,
        has_traffic_light: false,
        stop_lines: vec![],
    }
}

#[test]
fn lane_links_inferred_within_1m_and_30deg() {
    let a = 20f64.to_radians();
    let b = 40f64.to_radians();
    let specs = vec![
        lane("A", &[(0.0, 0.0), (10.0, 0.0)]),
        // Starts 0.58 m from A's end, heading 20 deg: linked.
        lane(
            "B",
            &[(10.5, 0.3), (10.5 + 10.0 * a.cos(), 0.3 + 10.0 * a.sin())],
        ),
        // Starts 1.5 m away: not linked.
        lane("C", &[(10.0, 1.5), (20.0, 1.5)]),
        // Starts at A's end but heading 40 deg: not linked.
        lane("D", &[(10.0, 0.0), (10.0 + 10.0 * b.cos(), 10.0 * b.sin())]),
    ];
    let m = Map::build(
        "t",
        specs,
        vec![],
        vec![],
        vec![],
        PolygonSet::default(),
        true,
    )
    .unwrap();
    let links = infer_lane_links(&m.lanes);
    assert_eq!(links, vec![(0, 1)]);
    assert_eq!(m.lanes[0].successors, vec![1]);
    assert_eq!(m.lanes[1].predecessors, vec![0]);
    // Queries: the point (5, 1) is on A's polygon (3.5 m wide) only.
    assert_eq!(m.lanes_at(DVec2::new(5.0, 1.0), None), vec![0]);
    assert!(m.in_drivable_area(DVec2::new(5.0, 1.0)));
    assert!(!m.in_drivable_area(DVec2::new(5.0, 3.0)));
    assert!((m.drivable_distance(DVec2::new(5.0, 3.0), 10.0) - 1.25).abs() < 1e-9);
}

fn minimal_scene() -> serde_json::Value {
    json!({
        "format": "scenarionet-scenario-description/json",
        "id": "tiny", "length": 3,
        "metadata": {"sdc_id": "ego", "map": "nowhere", "sample_rate": 0.1},
        "tracks": {
            "ego": {"type": "VEHICLE", "state": {
                "position": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]],
                "heading": [0.0, 0.0, 0.0], "velocity": [[10.0, 0.0], [10.0, 0.0], [10.0, 0.0]],
                "valid": [1, 1, 1], "length": [[4.5], [4.5], [4.5]], "width": [[1.9], [1.9], [1.9]],
                "height": [[1.5], [1.5], [1.5]]}}
        },
        "map_features": {
            "l1": {"type": "LANE_SURFACE_STREET", "polyline": [[-10.0, 0.0, 0.0], [30.0, 0.0, 0.0]],
                   "polygon": [[-10.0, -2.0], [30.0, -2.0], [30.0, 2.0], [-10.0, 2.0]]}
        },
        "dynamic_map_states": {}
    })
}

fn parse_err(v: &serde_json::Value) -> String {
    format!(
        "{:#}",
        scenarionet::parse(v, "dir/bad.json", None).unwrap_err()
    )
}

#[test]
fn minimal_scene_parses() {
    let sc = scenarionet::parse(&minimal_scene(), "dir/ok.json", None).unwrap();
    assert_eq!(sc.len(), 3);
    assert_eq!(sc.map.lanes.len(), 1);
    assert_eq!(sc.route.lane_ids, vec!["l1".to_string()]);
    assert_eq!(sc.ego_params.length, 4.5);
}

#[test]
fn importer_errors_name_file_and_field() {
    let mut v = minimal_scene();
    v.as_object_mut().unwrap().remove("length");
    let e = parse_err(&v);
    assert!(
        e.contains("dir/bad.json") && e.contains("`length`") && e.contains("missing"),
        "{e}"
    );

    let mut v = minimal_scene();
    v["tracks"]["ego"]["type"] = json!("SPACESHIP");
    let e = parse_err(&v);
    assert!(
        e.contains("dir/bad.json") && e.contains("tracks.ego.type") && e.contains("SPACESHIP"),
        "{e}"
    );

    let mut v = minimal_scene();
    v["tracks"]["ego"]["state"]["heading"] = json!([0.0, 0.0]);
    let e = parse_err(&v);
    assert!(
        e.contains("tracks.ego.state.heading") && e.contains("expected `length` = 3"),
        "{e}"
    );

    let mut v = minimal_scene();
    v["tracks"]["ego"]["state"]["position"][1] = json!(["a", 0.0]);
    let e = parse_err(&v);
    assert!(e.contains("tracks.ego.state.position[1]"), "{e}");

    let mut v = minimal_scene();
    v["metadata"]["sdc_id"] = json!("nobody");
    let e = parse_err(&v);
    assert!(e.contains("metadata.sdc_id") && e.contains("nobody"), "{e}");

    let mut v = minimal_scene();
    v["map_features"]["l1"]["polyline"] = json!([[1.0, 2.0]]);
    let e = parse_err(&v);
    assert!(e.contains("map_features.l1.polyline"), "{e}");

    let mut v = minimal_scene();
    v["format"] = json!("waymo-proto");
    let e = parse_err(&v);
    assert!(e.contains("`format`"), "{e}");
}

#[test]
fn unreadable_files_and_bad_specs_are_errors() {
    let dir = std::env::temp_dir().join(format!("b2dr_scene_import_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let f = dir.join("broken.json");
    std::fs::write(&f, "{ not json").unwrap();
    let e = format!("{:#}", scenarionet::load_file(&f).unwrap_err());
    assert!(
        e.contains("broken.json") && e.contains("not valid JSON"),
        "{e}"
    );
    let e = format!(
        "{:#}",
        scenarionet::load_file(&dir.join("missing.json")).unwrap_err()
    );
    assert!(e.contains("missing.json"), "{e}");
    assert!(resolve("builtin:city").is_err());
    assert!(resolve("builtin:town:x").is_err());
    assert!(resolve(dir.join("nope").to_str().unwrap()).is_err());
    assert_eq!(
        resolve("builtin:town:7:200").unwrap(),
        vec![Source::Builtin(BuiltinSpec::town(7, Some(200)))]
    );
    // comma lists resolve in order; a bad member fails the list; an empty list is an error
    assert_eq!(
        resolve("builtin:town:7:200, builtin:town:8").unwrap(),
        vec![
            Source::Builtin(BuiltinSpec::town(7, Some(200))),
            Source::Builtin(BuiltinSpec::town(8, None))
        ]
    );
    assert!(resolve("builtin:town:7,builtin:city").is_err());
    assert!(resolve(",").is_err());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn synthetic_town_is_deterministic_and_complete() {
    let a = synthetic::town(3, None);
    let b = synthetic::town(3, None);
    assert_eq!(a.ego, b.ego);
    assert_eq!(a.tracks.len(), b.tracks.len());
    for (x, y) in a.tracks.iter().zip(&b.tracks) {
        assert_eq!(x.states, y.states);
    }
    let c = synthetic::town(4, None);
    assert_ne!(a.tracks.len() * 1000 + a.route.lane_ids.len(), 0);
    assert!(
        a.ego != c.ego
            || a.tracks.len() != c.tracks.len()
            || a.tracks[0].states != c.tracks[0].states
    );
    // Map content: connectors with lights, stop lines, crosswalks, a curve, lights that change.
    assert!(a
        .map
        .lanes
        .iter()
        .any(|l| l.kind == LaneKind::Connector && l.has_traffic_light && !l.stop_lines.is_empty()));
    assert_eq!(a.map.crosswalks.len(), 4);
    assert!(a
        .map
        .lanes
        .iter()
        .any(|l| l.id.starts_with("curve") && l.centre.start_curvature() > 0.01));
    let s0 = a.lights_at(0).to_vec();
    assert!(s0.iter().any(|(i, _)| a
        .lights_at(130)
        .iter()
        .any(|(j, t)| i == j && t != &s0.iter().find(|(k, _)| k == i).unwrap().1)));
    // Every connector is linked in and out.
    for l in a.map.lanes.iter().filter(|l| l.kind == LaneKind::Connector) {
        assert!(
            !l.successors.is_empty() && !l.predecessors.is_empty(),
            "{}",
            l.id
        );
    }
    // Rig: 6 cameras, 1600x900, a frame every 0.5 s.
    assert_eq!(a.rig.cameras.len(), 6);
    assert!(a
        .rig
        .cameras
        .iter()
        .all(|c| c.width == 1600 && c.height == 900));
    assert_eq!(
        a.rig.frames[1].timestamp_us - a.rig.frames[0].timestamp_us,
        500_000
    );
    assert_eq!(a.rig.frames[0].images.len(), 6);
    // The expert moves along its route; vehicles and pedestrians exist.
    assert!((a.ego[150].rear_axle.pos() - a.ego[0].rear_axle.pos()).length() > 50.0);
    assert!(a
        .tracks
        .iter()
        .any(|t| t.class == b2dr::scene::ObjectClass::Pedestrian));
    assert!(
        a.tracks
            .iter()
            .filter(|t| t.class == b2dr::scene::ObjectClass::Vehicle)
            .count()
            >= 5
    );
    assert!(a.route.roadblock_ids.len() >= 3, "{:?}", a.route);
    let dense = synthetic::town(1, Some(200));
    assert_eq!(
        dense
            .tracks
            .iter()
            .filter(|t| t.class == b2dr::scene::ObjectClass::Vehicle)
            .count(),
        200
    );
}

#[test]
fn shared_scenes_load() {
    let d = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/nuscenes-mini/scenes");
    if !d.is_dir() {
        println!("SKIP: {} is absent", d.display());
        return;
    }
    for src in resolve(d.to_str().unwrap()).unwrap() {
        let sc = b2dr::world::load(&src).unwrap();
        let links: usize = sc.map.lanes.iter().map(|l| l.successors.len()).sum();
        println!(
            "{}: {} steps, {} tracks, {} lanes ({} connectors), {} links, drivable area {}, route {} lanes",
            sc.name,
            sc.len(),
            sc.tracks.len(),
            sc.map.lanes.len(),
            sc.map.lanes.iter().filter(|l| l.kind == LaneKind::Connector).count(),
            links,
            !sc.map.drivable.is_empty(),
            sc.route.lane_ids.len()
        );
        assert!(sc.len() >= 151);
        assert!(
            links > sc.map.lanes.len() / 2,
            "{}: too few inferred links",
            sc.name
        );
        assert!(!sc.map.drivable.is_empty());
        assert!(!sc.route.lane_ids.is_empty());
    }
}

/// Hostile numbers in a scenario (issue #18): coordinates beyond the world's extent, huge velocities and
/// sizes are errors naming the file and the field, not maps or scores computed from overflowing geometry.
type Edit = Box<dyn Fn(&mut serde_json::Value)>;

#[test]
fn far_and_huge_numbers_are_errors_naming_the_field() {
    let cases: Vec<(&str, Edit)> = vec![
        (
            "map_features.l1.polyline[1]",
            Box::new(|v| v["map_features"]["l1"]["polyline"][1] = json!([1e308, 0.0, 0.0])),
        ),
        (
            "map_features.l1.polygon[2]",
            Box::new(|v| v["map_features"]["l1"]["polygon"][2] = json!([3e9, 2.0])),
        ),
        (
            "tracks.ego.state.position[1]",
            Box::new(|v| v["tracks"]["ego"]["state"]["position"][1] = json!([1e300, 0.0, 0.0])),
        ),
        (
            "tracks.ego.state.velocity[2]",
            Box::new(|v| v["tracks"]["ego"]["state"]["velocity"][2] = json!([1e308, 0.0])),
        ),
        (
            "tracks.ego.state.heading[0]",
            Box::new(|v| v["tracks"]["ego"]["state"]["heading"][0] = json!(1e300)),
        ),
        (
            "tracks.ego.state.length[0]",
            Box::new(|v| v["tracks"]["ego"]["state"]["length"][0] = json!([1e308])),
        ),
    ];
    for (field, edit) in cases {
        let mut v = minimal_scene();
        edit(&mut v);
        let e = parse_err(&v);
        assert!(
            e.contains("dir/bad.json") && e.contains(field),
            "{field}: {e}"
        );
    }
    // far but plausible coordinates (1e5 m) still parse, in bounded time
    let mut v = minimal_scene();
    v["map_features"]["l2"] = json!({"type": "LANE_SURFACE_STREET",
        "polyline": [[-1e5, -1e5], [1e5, 1e5]], "polygon": [[-1e5, -1e5], [1e5, -1e5], [1e5, 1e5]]});
    let t0 = std::time::Instant::now();
    scenarionet::parse(&v, "dir/far.json", None).unwrap();
    assert!(t0.elapsed().as_secs_f64() < 5.0, "{:?}", t0.elapsed());
}

/// A drivable-area GeoJSON with a vertex beyond the world's extent is an error naming the file and field.
#[test]
fn geojson_far_vertex_is_an_error() {
    let dir = std::env::temp_dir().join(format!("b2dr_geojson_far_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let f = dir.join("m.drivable_area.geojson");
    std::fs::write(
        &f,
        r#"{"type": "Polygon", "coordinates": [[[0, 0], [1e308, 0], [1e308, 1e308]]]}"#,
    )
    .unwrap();
    let e = format!("{:#}", scenarionet::load_geojson_polygons(&f).unwrap_err());
    assert!(
        e.contains("m.drivable_area.geojson") && e.contains("coordinates[0][0][1]"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// The map name becomes a file name next to the scenes: a path ("../../etc/x", "/abs", NUL) is an error naming
/// `metadata.map`, not a file read from elsewhere.
#[test]
fn map_names_that_are_paths_are_errors() {
    for bad in [
        "../../etc/passwd",
        "/abs/map",
        "a\\b",
        "nul\0x",
        "",
        ".hidden",
    ] {
        let mut v = minimal_scene();
        v["metadata"]["map"] = json!(bad);
        let e = parse_err(&v);
        assert!(e.contains("metadata.map"), "{bad:?}: {e}");
    }
}
