//! Property tests over the entry points that read files and replies (issue #18): safetensors headers, model
//! and scheduler configs, ScenarioNet scenarios, GeoJSON drivable areas, nuScenes tables and map expansion (on the
//! fixture DATAROOT; skipped when the shared data is absent), nuPlan log DBs and GeoPackage maps (on the fixture
//! written by python/b2dr_ref/nuplan_fixture.py; skipped without Python / numpy), keyframe files and planner replies.
//! Every input either parses or is an `Err`, within a time bound, never a panic. Inputs are valid documents
//! with one value replaced by an arbitrary one (wrong types, huge and negative numbers, deep nesting), and
//! arbitrary documents. Case counts are bounded (a minute or two in all on a CI machine).
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use b2dr::nn::b2dr_config::ControlNetKind;
use b2dr::nn::config::{ControlNetConfig, UNetConfig, VaeConfig};
use b2dr::nn::weights::Weights;
use b2dr::projection::keyframe::{drivable_area_from_geojson, KeyFrame};
use b2dr::scene::geometry::Pose2;
use b2dr::scene::import::{nuscenes, scenarionet};
use b2dr::sim::ego::EgoState;
use b2dr::sim::external::parse_reply;
use b2dr::sim::planner::{trajectory_from_ego_frame, trajectory_from_ego_poses};
use b2dr::sim::reply::parse_plan_reply;
use proptest::prelude::*;
use proptest::sample::Index;

#[path = "common/fixture_dirs.rs"]
mod fixture_dirs;
mod nuplan_fixture;
mod nuscenes_fixture;
use serde_json::{json, Value};

/// Longest one parse may take.
const BOUND: Duration = Duration::from_secs(5);

/// `cases` per property, or `$PROPTEST_CASES` when set (long local fuzz runs: every property then runs that many).
fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases: std::env::var("PROPTEST_CASES")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(cases),
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

/// Numbers that break naive code: huge, tiny, negative, zero, integers past usize and f64 extremes.
fn nasty_number() -> impl Strategy<Value = Value> {
    prop_oneof![
        Just(json!(0)),
        Just(json!(-1)),
        Just(json!(1u64 << 40)),
        Just(json!(u64::MAX)),
        Just(json!(i64::MIN)),
        Just(json!(1e308)),
        Just(json!(-1e308)),
        Just(json!(1e5)),
        Just(json!(5e-324)),
        Just(json!(0.5)),
        any::<i64>().prop_map(|i| json!(i)),
        any::<f64>().prop_filter_map("finite", |f| serde_json::Number::from_f64(f)
            .map(Value::Number)),
    ]
}

/// Arbitrary JSON (bounded depth and width).
fn arb_json() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        nasty_number(),
        "[A-Za-z_./\\\\]{0,10}".prop_map(Value::String),
    ];
    leaf.prop_recursive(3, 24, 5, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..5).prop_map(Value::Array),
            prop::collection::btree_map("[a-z_]{1,8}", inner, 0..5)
                .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
}

/// Every JSON pointer of a document (the root included).
fn pointers(v: &Value, at: String, out: &mut Vec<String>) {
    match v {
        Value::Array(a) => a
            .iter()
            .enumerate()
            .for_each(|(i, x)| pointers(x, format!("{at}/{i}"), out)),
        Value::Object(o) => o.iter().for_each(|(k, x)| {
            pointers(
                x,
                format!("{at}/{}", k.replace('~', "~0").replace('/', "~1")),
                out,
            )
        }),
        _ => {}
    }
    out.push(at);
}

/// `base` with the value at one pointer replaced (or, for `delete`, removed from its object/array).
fn mutate(base: &Value, at: Index, new: Value, delete: bool) -> Value {
    let mut v = base.clone();
    let mut ps = vec![];
    pointers(base, String::new(), &mut ps);
    let p = &ps[at.index(ps.len())];
    if delete && !p.is_empty() {
        let (parent, key) = p.rsplit_once('/').unwrap_or(("", p));
        match v.pointer_mut(parent) {
            Some(Value::Object(o)) => {
                o.remove(&key.replace("~1", "/").replace("~0", "~"));
            }
            Some(Value::Array(a)) => {
                if let Ok(i) = key.parse::<usize>() {
                    if i < a.len() {
                        a.remove(i);
                    }
                }
            }
            _ => {}
        }
    } else if let Some(slot) = v.pointer_mut(p) {
        *slot = new;
    }
    v
}

/// `base` with one of its numbers replaced (documents that still parse more often than `mutate`'s).
fn mutate_number(base: &Value, at: Index, new: Value) -> Value {
    let mut ps = vec![];
    pointers(base, String::new(), &mut ps);
    ps.retain(|p| base.pointer(p).is_some_and(Value::is_number));
    let mut v = base.clone();
    if let Some(slot) = v.pointer_mut(&ps[at.index(ps.len())]) {
        *slot = new;
    }
    v
}

/// Runs `f`, asserting that it returns (Ok or Err, never a panic: the property fails on one) within BOUND.
fn bounded<T>(what: &str, f: impl FnOnce() -> T) -> T {
    let t0 = Instant::now();
    let r = f();
    assert!(t0.elapsed() < BOUND, "{what} took {:?}", t0.elapsed());
    r
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("b2dr_hostile_{}_{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

// ------------------------------------------------------------------------------------------------ safetensors

/// A safetensors buffer from a header value and data bytes.
fn safetensors(header: &Value, data: &[u8]) -> Vec<u8> {
    let h = serde_json::to_vec(header).unwrap();
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&h);
    out.extend_from_slice(data);
    out
}

fn arb_entry() -> impl Strategy<Value = Value> {
    let dim = prop_oneof![0u64..5, Just(1u64 << 32), Just(1u64 << 62), Just(u64::MAX)];
    let off = prop_oneof![0u64..40, Just(u64::MAX), Just(1u64 << 63)];
    (
        prop::sample::select(vec!["F32", "F16", "BF16", "I64", "F64", ""]),
        prop::collection::vec(dim, 0..4),
        off.clone(),
        off,
    )
        .prop_map(|(d, s, a, b)| json!({"dtype": d, "shape": s, "data_offsets": [a, b]}))
}

proptest! {
    #![proptest_config(config(256))]

    #[test]
    fn safetensors_headers_parse_or_err(
        entries in prop::collection::btree_map("[a-z.]{1,6}", arb_entry(), 0..4),
        data in prop::collection::vec(any::<u8>(), 0..48),
        junk in arb_json(),
        raw in prop::collection::vec(any::<u8>(), 0..64),
        declared in prop_oneof![0u64..80, Just(u64::MAX)],
    ) {
        let header = Value::Object(entries.into_iter().collect());
        let _ = bounded("safetensors", || Weights::from_bytes_unchecked(&safetensors(&header, &data), "p.safetensors"));
        let _ = bounded("safetensors junk", || Weights::from_bytes_unchecked(&safetensors(&junk, &data), "p.safetensors"));
        // a declared header length that lies
        let mut lying = declared.to_le_bytes().to_vec();
        lying.extend_from_slice(&raw);
        let _ = bounded("safetensors raw", || Weights::from_bytes_unchecked(&lying, "p.safetensors"));
        let _ = bounded("safetensors bytes", || Weights::from_bytes_unchecked(&raw, "p.safetensors"));
    }
}

// ---------------------------------------------------------------------------------------------------- configs

fn scheduler_json() -> Value {
    json!({"_class_name": "UniPCMultistepScheduler", "num_train_timesteps": 1000, "beta_start": 0.00085,
        "beta_end": 0.012, "beta_schedule": "scaled_linear", "prediction_type": "epsilon",
        "timestep_spacing": "linspace", "steps_offset": 1, "solver_order": 2})
}

proptest! {
    #![proptest_config(config(192))]

    #[test]
    fn model_configs_parse_or_err(at in any::<Index>(), new in arb_json(), delete in any::<bool>(), doc in arb_json()) {
        let bases = [
            UNetConfig::b2dr_tiny().to_json(),
            ControlNetConfig::b2dr_tiny().to_json(),
            VaeConfig::b2dr_tiny().to_json(),
            b2dr::nn::b2dr_config::B2drConfig::from_unet(&UNetConfig::b2dr_tiny(), vec![16, 32, 96, 256]).to_json(),
            scheduler_json(),
        ];
        for base in &bases {
            let v = mutate(base, at, new.clone(), delete);
            let _ = bounded("unet config", || UNetConfig::from_json(v.clone()));
            let _ = bounded("controlnet config", || ControlNetKind::from_json(v.clone()));
            let _ = bounded("vae config", || VaeConfig::from_json(v.clone()));
            let _ = bounded("scheduler config", || b2dr::sampling::config::from_diffusers_json(&v));
        }
        let _ = bounded("unet config", || UNetConfig::from_json(doc.clone()));
        let _ = bounded("vae config", || VaeConfig::from_json(doc.clone()));
        let _ = bounded("scheduler config", || b2dr::sampling::config::from_diffusers_json(&doc));
    }
}

/// A config that parses yields expected weight lists whose sizes are computable (bounded integers).
#[test]
fn huge_scheduler_timesteps_are_an_error() {
    let mut v = scheduler_json();
    v["num_train_timesteps"] = json!(1e15);
    let e = format!(
        "{:#}",
        b2dr::sampling::config::from_diffusers_json(&v).unwrap_err()
    );
    assert!(e.contains("num_train_timesteps"), "{e}");
}

// ------------------------------------------------------------------------------------------------- scenarios

fn scenario_json() -> Value {
    json!({
        "format": "scenarionet-scenario-description/json",
        "id": "tiny", "length": 3,
        "metadata": {"sdc_id": "ego", "map": "nowhere", "sample_rate": 0.1},
        "tracks": {
            "ego": {"type": "VEHICLE", "state": {
                "position": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]],
                "heading": [0.0, 0.0, 0.0], "velocity": [[10.0, 0.0], [10.0, 0.0], [10.0, 0.0]],
                "valid": [1, 1, 1], "length": [[4.5], [4.5], [4.5]], "width": [[1.9], [1.9], [1.9]],
                "height": [[1.5], [1.5], [1.5]]}},
            "car": {"type": "VEHICLE", "state": {
                "position": [[10.0, 0.0, 0.0], [11.0, 0.0, 0.0], [12.0, 0.0, 0.0]],
                "heading": [0.0, 0.0, 0.0], "velocity": [[10.0, 0.0], [10.0, 0.0], [10.0, 0.0]],
                "valid": [1, 0, 1], "length": [[4.5], [4.5], [4.5]], "width": [[1.9], [1.9], [1.9]],
                "height": [[1.5], [1.5], [1.5]]}}
        },
        "map_features": {
            "l1": {"type": "LANE_SURFACE_STREET", "polyline": [[-10.0, 0.0, 0.0], [30.0, 0.0, 0.0]],
                   "polygon": [[-10.0, -2.0], [30.0, -2.0], [30.0, 2.0], [-10.0, 2.0]]},
            "c1": {"type": "LANE_SURFACE_STREET", "polyline": [[30.0, 0.0], [40.0, 5.0]]},
            "x1": {"type": "CROSSWALK", "polygon": [[0.0, -2.0], [2.0, -2.0], [2.0, 2.0]]}
        },
        "dynamic_map_states": {"t1": {"lane": "c1", "state": {"object_state": ["LANE_STATE_STOP", null, "GO"]}}}
    })
}

fn geojson() -> Value {
    json!({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Polygon",
            "coordinates": [[[-20.0, -5.0], [50.0, -5.0], [50.0, 5.0], [-20.0, 5.0]], [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]]}},
        {"type": "Feature", "geometry": {"type": "MultiPolygon",
            "coordinates": [[[[100.0, 100.0], [110.0, 100.0], [110.0, 110.0]]]]}}
    ]})
}

proptest! {
    #![proptest_config(config(192))]

    #[test]
    fn scenarios_parse_or_err(at in any::<Index>(), new in prop_oneof![arb_json(), nasty_number()], delete in any::<bool>(), doc in arb_json()) {
        let v = mutate(&scenario_json(), at, new, delete);
        if let Ok(sc) = bounded("scenario", || scenarionet::parse(&v, "p.json", None)) {
            // what parses also builds its world, simulates (reactive agents) and scores without a panic
            bounded("world", || b2dr::world::World::new(&sc));
            let cfg = b2dr::sim::SimConfig { agents: b2dr::sim::AgentMode::Idm, steps: 3, ..Default::default() };
            let r = bounded("sim", || b2dr::sim::run(&sc, &mut b2dr::sim::ConstantVelocityPlanner, &cfg));
            let s = bounded("score", || {
                b2dr::sim::score::score_run(&sc, &r, &b2dr::metrics::ScoreParams::default())
            });
            if let Ok(s) = s {
                prop_assert!(s.score.is_finite() && (0.0..=1.0).contains(&s.score), "score {}", s.score);
            }
        }
        let _ = bounded("scenario doc", || scenarionet::parse(&doc, "p.json", None));
    }

    #[test]
    fn scenario_numbers_parse_or_err_and_run(at in prop::collection::vec(any::<Index>(), 1..4), new in prop::collection::vec(nasty_number(), 3)) {
        let mut v = scenario_json();
        for (a, n) in at.into_iter().zip(new) {
            v = mutate_number(&v, a, n);
        }
        if let Ok(sc) = bounded("scenario", || scenarionet::parse(&v, "p.json", None)) {
            bounded("world", || b2dr::world::World::new(&sc));
            let cfg = b2dr::sim::SimConfig { agents: b2dr::sim::AgentMode::Idm, steps: 3, ..Default::default() };
            let r = bounded("sim", || b2dr::sim::run(&sc, &mut b2dr::sim::ConstantVelocityPlanner, &cfg));
            if let Ok(s) = bounded("score", || b2dr::sim::score::score_run(&sc, &r, &b2dr::metrics::ScoreParams::default())) {
                prop_assert!(s.score.is_finite() && (0.0..=1.0).contains(&s.score), "score {}", s.score);
            }
        }
    }

    #[test]
    fn scenarios_with_a_drivable_area_parse_or_err(at in any::<Index>(), new in prop_oneof![arb_json(), nasty_number()], delete in any::<bool>()) {
        // <root>/scenes/s.json with <root>/maps/nowhere.drivable_area.geojson
        let root = tmp("geo");
        std::fs::create_dir_all(root.join("maps")).unwrap();
        std::fs::create_dir_all(root.join("scenes")).unwrap();
        let g = mutate(&geojson(), at, new, delete);
        let gpath = root.join("maps/nowhere.drivable_area.geojson");
        std::fs::write(&gpath, g.to_string()).unwrap();
        let s = root.join("scenes/s.json");
        std::fs::write(&s, scenario_json().to_string()).unwrap();
        let _ = bounded("geojson", || scenarionet::load_geojson_polygons(&gpath));
        let _ = bounded("geojson (projection)", || drivable_area_from_geojson(&gpath, 0.0));
        let _ = bounded("scenario + geojson", || scenarionet::load_file(&s));
    }
}

/// A subnormal sample_rate (5e-324 s: `scenario_numbers_parse_or_err_and_run` drew it) parsed, and the constant
/// velocity planner's horizon (4 s / dt poses) then asked for an 8 GiB allocation: it is an error naming the field.
#[test]
fn tiny_sample_rate_is_an_error() {
    for dt in [5e-324, 1e-9, 0.0, -0.1, 10.0] {
        let mut v = scenario_json();
        v["metadata"]["sample_rate"] = json!(dt);
        let e = format!("{:#}", scenarionet::parse(&v, "p.json", None).unwrap_err());
        assert!(e.contains("metadata.sample_rate"), "{dt}: {e}");
    }
    let mut v = scenario_json();
    v["metadata"]["sample_rate"] = json!(0.05);
    assert!(scenarionet::parse(&v, "p.json", None).is_ok());
}

// ------------------------------------------------------------------------------------------ nuScenes tables

/// The tables the nuScenes importer reads (the importer's own list: a table added there is fuzzed here).
use nuscenes::tables::TABLES as NUSCENES_TABLES;

const NUSCENES_MAP: &str = "maps/expansion/singapore-onenorth.json";
/// Longest one nuScenes import may take (an import takes about 0.3 s; this catches unbounded work, not speed).
const NUSCENES_BOUND: Duration = Duration::from_secs(30);

/// A private copy of the fixture DATAROOT's tables and map (`name` tells the copies of two tests apart), its
/// documents (relative path, parsed, text) and every token of the tables.
struct NuCopy {
    root: PathBuf,
    docs: Vec<(String, Value, String)>,
    tokens: Vec<String>,
}

fn nuscenes_copy(name: &str) -> Option<NuCopy> {
    let src = nuscenes_fixture::dataroot()?;
    let root = tmp(&format!("nuscenes_{name}"));
    std::fs::create_dir_all(root.join("v1.0-mini")).unwrap();
    std::fs::create_dir_all(root.join("maps/expansion")).unwrap();
    let mut docs = vec![];
    let mut tokens = vec![];
    let rels = NUSCENES_TABLES
        .iter()
        .map(|t| format!("v1.0-mini/{t}.json"))
        .chain([NUSCENES_MAP.to_string()]);
    for rel in rels {
        let text = std::fs::read_to_string(src.join(&rel)).unwrap();
        std::fs::write(root.join(&rel), &text).unwrap();
        let v: Value = serde_json::from_str(&text).unwrap();
        if let Value::Array(rows) = &v {
            tokens.extend(
                rows.iter()
                    .filter_map(|r| r["token"].as_str().map(String::from)),
            );
        }
        docs.push((rel, v, text));
    }
    Some(NuCopy { root, docs, tokens })
}

fn has_number(v: &Value) -> bool {
    match v {
        Value::Number(_) => true,
        Value::Array(a) => a.iter().any(has_number),
        Value::Object(o) => o.values().any(has_number),
        _ => false,
    }
}

/// Writes document `doc` of `c` mutated (`mode` 0: a value replaced by `new` or deleted, 1: a number replaced by
/// `num`, 2: a value replaced by a token of some table), imports scene-0061 within the bound, restores the file.
#[allow(clippy::too_many_arguments)]
fn nuscenes_mutated_import(
    c: &NuCopy,
    doc: usize,
    mode: u8,
    at: Index,
    new: Value,
    num: Value,
    delete: bool,
    tok: Index,
) {
    let (rel, base, text) = &c.docs[doc];
    let v = match mode {
        1 if has_number(base) => mutate_number(base, at, num),
        0 | 1 => mutate(base, at, new, delete),
        _ => mutate(
            base,
            at,
            Value::String(c.tokens[tok.index(c.tokens.len())].clone()),
            false,
        ),
    };
    let path = c.root.join(rel);
    std::fs::write(&path, serde_json::to_string(&v).unwrap()).unwrap();
    let spec = nuscenes_fixture::spec(&c.root);
    let t0 = Instant::now();
    let r = nuscenes::load(&spec);
    let took = t0.elapsed();
    std::fs::write(&path, text).unwrap();
    assert!(took < NUSCENES_BOUND, "{rel} mutated: import took {took:?}");
    if let Err(e) = r {
        // errors say where
        let e = format!("{e:#}");
        assert!(
            e.contains("nuScenes") || e.contains("map expansion") || e.contains("building the map"),
            "{rel}: {e}"
        );
    }
}

proptest! {
    #![proptest_config(config(40))]

    /// Mutated nuScenes tables (one value replaced by arbitrary JSON, a nasty number or another row's token, or
    /// deleted): the import of the scene returns Ok or Err within the bound, never panics.
    #[test]
    fn nuscenes_tables_import_or_err(
        doc in 0..NUSCENES_TABLES.len(), mode in 0u8..3, at in any::<Index>(),
        new in prop_oneof![arb_json(), nasty_number()], num in nasty_number(), delete in any::<bool>(),
        tok in any::<Index>(),
    ) {
        static COPY: std::sync::OnceLock<Option<NuCopy>> = std::sync::OnceLock::new();
        let Some(c) = COPY.get_or_init(|| nuscenes_copy("tables")) else { return Ok(()) };
        nuscenes_mutated_import(c, doc, mode, at, new, num, delete, tok);
    }
}

proptest! {
    #![proptest_config(config(12))]

    /// The same over the map expansion file.
    #[test]
    fn nuscenes_map_expansion_imports_or_err(
        mode in 0u8..3, at in any::<Index>(), new in prop_oneof![arb_json(), nasty_number()],
        num in nasty_number(), delete in any::<bool>(), tok in any::<Index>(),
    ) {
        static COPY: std::sync::OnceLock<Option<NuCopy>> = std::sync::OnceLock::new();
        let Some(c) = COPY.get_or_init(|| nuscenes_copy("map")) else { return Ok(()) };
        nuscenes_mutated_import(c, NUSCENES_TABLES.len(), mode, at, new, num, delete, tok);
    }
}

// -------------------------------------------------------------------------------------- nuPlan DB and GPKG

/// Longest one nuPlan import (with a 3-step simulation of what imports) may take: an import takes about 0.05 s.
const NUPLAN_BOUND: Duration = Duration::from_secs(30);

/// The fixture's log DB and map copied into a private folder, with their pristine bytes (restored after every
/// case).
struct NpCopy {
    fx: nuplan_fixture::Fixture,
    db_bytes: Vec<u8>,
    map_bytes: Vec<u8>,
}

fn nuplan_copy() -> Option<NpCopy> {
    let fx = nuplan_fixture::write_fixture(&tmp("nuplan"), &["--seconds", "4"])?;
    Some(NpCopy {
        db_bytes: std::fs::read(&fx.db).unwrap(),
        map_bytes: std::fs::read(&fx.map).unwrap(),
        fx,
    })
}

/// A value written into one cell: wrong types, NaN / infinities / absurd magnitudes, text, random or corrupted
/// blobs (WKB geometries and pickles: bytes flipped, a 4-byte count made huge, truncated, arbitrary).
#[derive(Clone, Debug)]
enum Cell {
    Null,
    Int(i64),
    Real(f64),
    /// The cell's own number times a factor (absurd coordinates, sizes, speeds, timestamps).
    Scale(f64),
    Text(String),
    Blob(Vec<u8>),
    /// The cell's own blob with bytes replaced at (position, byte).
    Flip(Vec<(Index, u8)>),
    /// The cell's own blob with a little-endian u32 (a WKB / pickle count or length) written at a position.
    Count(Index, u32),
    /// The cell's own blob cut at a position.
    Cut(Index),
}

fn arb_cell() -> impl Strategy<Value = Cell> {
    prop_oneof![
        Just(Cell::Null),
        prop_oneof![
            Just(0i64),
            Just(-1),
            Just(i64::MIN),
            Just(i64::MAX),
            Just(1 << 53),
            any::<i64>()
        ]
        .prop_map(Cell::Int),
        prop_oneof![
            Just(f64::NAN),
            Just(f64::INFINITY),
            Just(f64::NEG_INFINITY),
            Just(1e300),
            Just(-1e300),
            Just(5e-324),
            Just(-0.0),
            Just(1e9),
            any::<f64>()
        ]
        .prop_map(Cell::Real),
        prop_oneof![
            Just(1e6),
            Just(1e12),
            Just(-1e20),
            Just(0.0),
            Just(1e-12),
            Just(f64::MAX)
        ]
        .prop_map(Cell::Scale),
        prop_oneof![
            "[a-z0-9 ./,]{0,12}".prop_map(|s| s),
            Just("NaN".to_string()),
            Just("../../etc/passwd".to_string()),
            Just("/abs".to_string()),
            Just("1e999".to_string()),
        ]
        .prop_map(Cell::Text),
        prop::collection::vec(any::<u8>(), 0..64).prop_map(Cell::Blob),
        prop::collection::vec((any::<Index>(), any::<u8>()), 1..6).prop_map(Cell::Flip),
        (
            any::<Index>(),
            prop_oneof![
                Just(u32::MAX),
                Just(1 << 31),
                Just(1 << 24),
                Just(0x7fff_ffff),
                any::<u32>()
            ]
        )
            .prop_map(|(i, n)| Cell::Count(i, n)),
        any::<Index>().prop_map(Cell::Cut),
    ]
}

/// One change to the DB or the map.
#[derive(Clone, Debug)]
enum NpEdit {
    /// A cell of (file, table, row, column) replaced.
    Set(bool, Index, Index, Index, Cell),
    DropTable(bool, Index),
    RenameTable(bool, Index),
    RenameColumn(bool, Index, Index),
    /// Every row, or every other row, of a table deleted.
    Delete(bool, Index, bool),
}

fn arb_edit() -> impl Strategy<Value = NpEdit> {
    let file = any::<bool>();
    prop_oneof![
        6 => (file, any::<Index>(), any::<Index>(), any::<Index>(), arb_cell())
            .prop_map(|(f, t, r, c, v)| NpEdit::Set(f, t, r, c, v)),
        1 => (file, any::<Index>()).prop_map(|(f, t)| NpEdit::DropTable(f, t)),
        1 => (file, any::<Index>()).prop_map(|(f, t)| NpEdit::RenameTable(f, t)),
        1 => (file, any::<Index>(), any::<Index>()).prop_map(|(f, t, c)| NpEdit::RenameColumn(f, t, c)),
        1 => (file, any::<Index>(), any::<bool>()).prop_map(|(f, t, all)| NpEdit::Delete(f, t, all)),
    ]
}

/// Applies `edit` to the DB (`map` false) or the map; a statement SQLite refuses leaves the file as it was.
/// Returns the table edited.
fn apply_edit(db: &rusqlite::Connection, map: &rusqlite::Connection, edit: &NpEdit) -> String {
    use rusqlite::types::Value as V;
    let (is_map, t) = match edit {
        NpEdit::Set(m, t, ..)
        | NpEdit::DropTable(m, t)
        | NpEdit::RenameTable(m, t)
        | NpEdit::RenameColumn(m, t, _)
        | NpEdit::Delete(m, t, _) => (*m, *t),
    };
    let c = if is_map { map } else { db };
    c.execute_batch("PRAGMA foreign_keys = OFF").unwrap();
    let tables: Vec<String> = c
        .prepare("SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%' ORDER BY name")
        .unwrap()
        .query_map([], |r| r.get(0))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    let table = tables[t.index(tables.len())].clone();
    let cols: Vec<String> = c
        .prepare(&format!("PRAGMA table_info(\"{table}\")"))
        .unwrap()
        .query_map([], |r| r.get(1))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    let _ = match edit {
        NpEdit::Set(_, _, row, col, cell) => {
            let rowids: Vec<i64> = c
                .prepare(&format!("SELECT rowid FROM \"{table}\" ORDER BY rowid"))
                .unwrap()
                .query_map([], |r| r.get(0))
                .unwrap()
                .collect::<Result<_, _>>()
                .unwrap();
            if rowids.is_empty() || cols.is_empty() {
                return table;
            }
            let rowid = rowids[row.index(rowids.len())];
            let col = &cols[col.index(cols.len())];
            let old: V = c
                .query_row(
                    &format!("SELECT \"{col}\" FROM \"{table}\" WHERE rowid = ?1"),
                    [rowid],
                    |r| r.get(0),
                )
                .unwrap();
            let blob = |v: &V| match v {
                V::Blob(b) => b.clone(),
                V::Text(t) => t.as_bytes().to_vec(),
                _ => vec![],
            };
            let new = match cell {
                Cell::Null => V::Null,
                Cell::Int(i) => V::Integer(*i),
                Cell::Real(f) => V::Real(*f),
                Cell::Scale(k) => match old {
                    V::Integer(i) => V::Real(i as f64 * k),
                    V::Real(f) => V::Real(f * k),
                    other => other,
                },
                Cell::Text(s) => V::Text(s.clone()),
                Cell::Blob(b) => V::Blob(b.clone()),
                Cell::Flip(flips) => {
                    let mut b = blob(&old);
                    for (at, x) in flips {
                        if !b.is_empty() {
                            let i = at.index(b.len());
                            b[i] = *x;
                        }
                    }
                    V::Blob(b)
                }
                Cell::Count(at, n) => {
                    let mut b = blob(&old);
                    if b.len() >= 4 {
                        let i = at.index(b.len() - 3);
                        b[i..i + 4].copy_from_slice(&n.to_le_bytes());
                    }
                    V::Blob(b)
                }
                Cell::Cut(at) => {
                    let b = blob(&old);
                    V::Blob(b[..at.index(b.len() + 1)].to_vec())
                }
            };
            c.execute(
                &format!("UPDATE \"{table}\" SET \"{col}\" = ?1 WHERE rowid = ?2"),
                rusqlite::params![new, rowid],
            )
            .map(|_| ())
        }
        NpEdit::DropTable(..) => c.execute_batch(&format!("DROP TABLE \"{table}\"")),
        NpEdit::RenameTable(..) => c.execute_batch(&format!(
            "ALTER TABLE \"{table}\" RENAME TO \"{table}_old\""
        )),
        NpEdit::RenameColumn(_, _, col) => {
            let col = &cols[col.index(cols.len())];
            c.execute_batch(&format!(
                "ALTER TABLE \"{table}\" RENAME COLUMN \"{col}\" TO \"{col}_x\""
            ))
        }
        NpEdit::Delete(_, _, all) => c.execute_batch(&format!(
            "DELETE FROM \"{table}\"{}",
            if *all { "" } else { " WHERE rowid % 2 = 0" }
        )),
    };
    table
}

/// Writes the pristine copy, applies `edits`, imports the whole log (or the window of a tagged lidar_pc) within
/// the bound; what imports is simulated for 3 steps and scored. An error must name the file and a table.
fn nuplan_mutated_import(c: &NpCopy, edits: &[NpEdit], window: bool) {
    std::fs::write(&c.fx.db, &c.db_bytes).unwrap();
    std::fs::write(&c.fx.map, &c.map_bytes).unwrap();
    let mut touched = vec![];
    {
        let db = rusqlite::Connection::open(&c.fx.db).unwrap();
        let map = rusqlite::Connection::open(&c.fx.map).unwrap();
        for e in edits {
            touched.push(apply_edit(&db, &map, e));
        }
    }
    let token = window
        .then(|| {
            c.fx.expected["scenario_tags"][0]["lidar_pc"]
                .as_str()
                .map(str::to_string)
        })
        .flatten();
    let spec = c.fx.spec(token.as_deref());
    let t0 = Instant::now();
    let r = b2dr::scene::import::nuplan::load(&spec);
    match r {
        Ok(sc) => {
            let cfg = b2dr::sim::SimConfig {
                agents: b2dr::sim::AgentMode::Idm,
                steps: 3,
                ..Default::default()
            };
            let run = b2dr::sim::run(&sc, &mut b2dr::sim::ConstantVelocityPlanner, &cfg);
            if let Ok(s) =
                b2dr::sim::score::score_run(&sc, &run, &b2dr::metrics::ScoreParams::default())
            {
                assert!(
                    s.score.is_finite() && (0.0..=1.0).contains(&s.score),
                    "{edits:?}: score {}",
                    s.score
                );
            }
        }
        Err(e) => {
            let e = format!("{e:#}");
            assert!(
                e.contains("nuPlan log DB") || e.contains("nuPlan map"),
                "{edits:?} ({touched:?}): the error names no file: {e}"
            );
            assert!(
                e.contains("table `") || e.contains("layer `"),
                "{edits:?} ({touched:?}): the error names no table: {e}"
            );
        }
    }
    let took = t0.elapsed();
    assert!(
        took < NUPLAN_BOUND,
        "{edits:?} ({touched:?}): import and simulation took {took:?}"
    );
}

proptest! {
    #![proptest_config(config(96))]

    /// Mutated nuPlan log DB and GeoPackage map (1 to 3 edits: a cell replaced by a wrong type, NaN, an infinity,
    /// an absurd magnitude, arbitrary text or bytes, a corrupted WKB geometry or pickle (bytes flipped, a count
    /// made huge, truncated); a table dropped, renamed, emptied or halved; a column renamed): the import
    /// returns Ok (and then simulates and scores) or an error naming the file and a table, within the bound,
    /// never a panic.
    #[test]
    fn nuplan_db_and_map_import_or_err(edits in prop::collection::vec(arb_edit(), 1..4), window in any::<bool>()) {
        static COPY: std::sync::OnceLock<Option<NpCopy>> = std::sync::OnceLock::new();
        let Some(c) = COPY.get_or_init(nuplan_copy) else { return Ok(()) };
        static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
        let _g = LOCK.lock().unwrap_or_else(|p| p.into_inner());
        nuplan_mutated_import(c, &edits, window);
    }
}

// ---------------------------------------------------------------------------------------------- frame files

fn frame_json() -> Value {
    let eye = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
    let cam = json!({"image": "cam.png", "width": 16, "height": 9, "timestamp_us": 0,
        "intrinsic": [[10.0, 0.0, 8.0], [0.0, 10.0, 4.5], [0.0, 0.0, 1.0]],
        "cam2ego": [[0, 0, 1, 1.5], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1]], "ego2global": eye});
    json!({"format": "b2dr-shared-keyframe/v1", "ego2global": eye, "cameras": {"CAM_FRONT": cam},
        "boxes": [{"category": "vehicle.car", "center": [10.0, 0.0, 1.0], "size_lwh": [4.0, 2.0, 1.5], "yaw": 0.0,
                   "velocity": [1.0, 0.0, 0.0]}]})
}

fn load_frame(dir: &Path, text: &str) -> anyhow::Result<KeyFrame> {
    let p = dir.join("frame.json");
    std::fs::write(&p, text).unwrap();
    KeyFrame::load(&p)
}

proptest! {
    #![proptest_config(config(192))]

    #[test]
    fn frame_files_parse_or_err(at in any::<Index>(), new in prop_oneof![arb_json(), nasty_number()], delete in any::<bool>(), cut in any::<Index>()) {
        let dir = tmp("frame");
        let v = mutate(&frame_json(), at, new, delete);
        let _ = bounded("frame", || load_frame(&dir, &v.to_string()));
        // truncated files and NaN literals (the reader maps NaN to null)
        let text = frame_json().to_string().replace("10.0", "NaN");
        let _ = bounded("frame NaN", || load_frame(&dir, &text));
        let _ = bounded("frame cut", || load_frame(&dir, &text[..cut.index(text.len())]));
    }
}

/// A keyframe's camera too large to render an overlay at (4e9 pixels wide) is an error naming the field.
#[test]
fn huge_keyframe_camera_is_an_error() {
    let dir = tmp("frame_huge");
    let mut v = frame_json();
    v["cameras"]["CAM_FRONT"]["width"] = json!(4_000_000_000u32);
    let e = format!("{:#}", load_frame(&dir, &v.to_string()).unwrap_err());
    assert!(e.contains("cameras.CAM_FRONT.width"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}

// ------------------------------------------------------------------------------------------- planner replies

fn ego() -> EgoState {
    EgoState {
        time_s: 1.0,
        rear_axle: Pose2::new(100.0, -50.0, 0.3),
        vx: 5.0,
        vy: 0.0,
        ax: 0.0,
        ay: 0.0,
        steering: 0.0,
        steering_rate: 0.0,
        yaw_rate: 0.0,
        yaw_accel: 0.0,
    }
}

proptest! {
    #![proptest_config(config(256))]

    #[test]
    fn planner_replies_parse_or_err(
        doc in arb_json(),
        poses in prop::collection::vec(prop::collection::vec(nasty_number(), 0..5), 0..12),
        extra in arb_json(),
    ) {
        let _ = bounded("reply", || parse_reply(&doc));
        // version 2: any document, and the poses with a nasty spacing in either frame
        let l2e = b2dr::scene::camera::nuscenes_lidar2ego();
        let _ = bounded("v2 reply", || parse_plan_reply(&doc, &l2e));
        for frame in ["ego_rear_axle", "lidar"] {
            for dt in [json!(0.5), extra.clone(), poses.first().and_then(|p| p.first()).cloned().unwrap_or(Value::Null)] {
                let reply = json!({"poses": poses, "dt_s": dt, "frame": frame});
                if let Ok(r) = bounded("v2 reply poses", || parse_plan_reply(&reply, &l2e)) {
                    if let Ok(t) = bounded("v2 trajectory", || trajectory_from_ego_poses(&ego(), &r.poses, r.dt_s)) {
                        for p in &t.poses {
                            prop_assert!(p.x.is_finite() && p.y.is_finite() && p.heading.is_finite());
                        }
                    }
                }
            }
        }
        let reply = json!({"poses": poses, "step": extra});
        if let Ok(local) = bounded("reply poses", || parse_reply(&reply)) {
            // whatever parses either becomes a finite trajectory or is refused
            if let Ok(t) = bounded("trajectory", || trajectory_from_ego_frame(&ego(), &local, 1)) {
                for p in &t.poses {
                    prop_assert!(p.x.is_finite() && p.y.is_finite() && p.heading.is_finite());
                }
            }
        }
    }
}

// ------------------------------------------------------------------------------------ far geometry, end to end

/// A scenario with map features and objects far away (9e7 m) and huge (a 999 m box next to the ego) loads,
/// and its layout masks (what the b2dr renderer projects each frame) are computed in bounded time.
#[test]
fn far_and_huge_geometry_projects_in_bounded_time() {
    let mut v = scenario_json();
    v["map_features"]["far"] = json!({"type": "LANE_SURFACE_STREET", "polyline": [[-9e7, -9e7], [9e7, 9e7]],
        "polygon": [[-9e7, -9e7], [9e7, -9e7], [9e7, 9e7]]});
    v["map_features"]["farx"] =
        json!({"type": "CROSSWALK", "polygon": [[-9e7, -9e7], [9e7, -9e7], [9e7, 9e7]]});
    v["tracks"]["huge"] = json!({"type": "VEHICLE", "state": {
        "position": [[15.0, 0.5], [15.0, 0.5], [15.0, 0.5]], "heading": [0.0, 0.0, 0.0],
        "velocity": [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]], "valid": [1, 1, 1],
        "length": [[999.0], [999.0], [999.0]], "width": [[999.0], [999.0], [999.0]],
        "height": [[999.0], [999.0], [999.0]]}});
    v["tracks"]["far"] = json!({"type": "VEHICLE", "state": {
        "position": [[9e7, 9e7], [-9e7, 9e7], [9e7, -9e7]], "heading": [0.0, 0.0, 0.0],
        "velocity": [[999.0, 0.0], [0.0, 0.0], [0.0, 0.0]], "valid": [1, 1, 1],
        "length": [[4.0], [4.0], [4.0]], "width": [[2.0], [2.0], [2.0]], "height": [[1.5], [1.5], [1.5]]}});
    let sc = bounded("far scenario", || scenarionet::parse(&v, "far.json", None)).unwrap();
    let t0 = Instant::now();
    let map = b2dr::projection::scene::map_layer(&sc.map);
    let boxes: Vec<_> = b2dr::projection::scene::boxes_at(&sc, 0)
        .into_iter()
        .map(|(_, b)| b)
        .collect();
    let e2g = b2dr::scene::import::ego2global(&sc.ego[0].rear_axle);
    let cams = sc.rig.cameras.clone();
    let poses = vec![e2g; cams.len()];
    let m =
        b2dr::render::inputs::masks(&cams, &poses, &boxes, &map, (56, 100), &Default::default())
            .unwrap();
    assert!(m.iter().all(|x| x.is_finite()));
    assert!(t0.elapsed() < BOUND, "masks took {:?}", t0.elapsed());
}

/// The world of a scenario file with a 2.5e8 m lane (what `b2dr run` builds for every scenario: its ground
/// layers and roadside objects placed along the road edges) is built in bounded time and size; the built-in
/// towns stay far below the caps, so their worlds are unchanged.
#[test]
fn far_roads_build_a_bounded_world() {
    use b2dr::world::scenery::{MAX_GROUND, MAX_SOLIDS};
    let mut v = scenario_json();
    v["map_features"]["far"] = json!({"type": "LANE_SURFACE_STREET", "polyline": [[-9e7, -9e7], [9e7, 9e7]],
        "polygon": [[-9e7, -9e7], [9e7, -9e7], [9e7, 9e7]]});
    v["map_features"]["farx"] = json!({"type": "CROSSWALK",
        "polygon": [[-9e7, -9e7], [9e7, -9e7], [9e7, -9e7 + 3.0], [-9e7, -9e7 + 3.0]]});
    let sc = scenarionet::parse(&v, "far.json", None).unwrap();
    let t0 = Instant::now();
    let w = b2dr::world::World::new(&sc);
    assert!(
        t0.elapsed() < Duration::from_secs(60),
        "world took {:?}",
        t0.elapsed()
    );
    assert!(w.scenery.ground.len() <= MAX_GROUND && w.scenery.solids.len() <= MAX_SOLIDS);
    for spec in ["builtin:town:0", "builtin:multilane:1"] {
        let sc = b2dr::world::load_all(spec).unwrap().remove(0);
        let w = b2dr::world::World::new(&sc);
        assert!(
            w.scenery.ground.len() < MAX_GROUND / 10 && w.scenery.solids.len() < MAX_SOLIDS / 10,
            "{spec}: {} ground, {} solids",
            w.scenery.ground.len(),
            w.scenery.solids.len()
        );
    }
}

// ------------------------------------------------------------------------------------------ issue #36: trust

/// safetensors byte ranges must tile the data section (issue #36, item 4): overlaps, gaps and trailing bytes are
/// errors naming the tensors, not silently shared or ignored bytes.
#[test]
fn safetensors_ranges_must_tile_the_data_section() {
    let e = |a: [u64; 2], b: [u64; 2], data: usize| {
        let h = json!({
            "a": {"dtype": "F32", "shape": [(a[1] - a[0]) / 4], "data_offsets": a},
            "b": {"dtype": "F32", "shape": [(b[1] - b[0]) / 4], "data_offsets": b},
        });
        Weights::from_bytes_unchecked(&safetensors(&h, &vec![0u8; data]), "t.safetensors")
    };
    // tiled: fine, in either order of the header
    assert!(e([0, 8], [8, 16], 16).is_ok());
    assert!(e([8, 16], [0, 8], 16).is_ok());
    // overlap: both tensors read bytes 4..8
    let m = format!("{:#}", e([0, 8], [4, 12], 12).unwrap_err());
    assert!(
        m.contains("overlaps") && m.contains("`a`") && m.contains("`b`"),
        "{m}"
    );
    // two tensors on the same bytes
    let m = format!("{:#}", e([0, 8], [0, 8], 8).unwrap_err());
    assert!(m.contains("overlaps"), "{m}");
    // gap: bytes 8..12 belong to no tensor
    let m = format!("{:#}", e([0, 8], [12, 20], 20).unwrap_err());
    assert!(m.contains("8..12") && m.contains("no tensor"), "{m}");
    // a gap at the start
    let m = format!("{:#}", e([4, 12], [12, 20], 20).unwrap_err());
    assert!(m.contains("0..4"), "{m}");
    // trailing bytes after the last tensor
    let m = format!("{:#}", e([0, 8], [8, 16], 24).unwrap_err());
    assert!(m.contains("16..24"), "{m}");
    // past the end: truncated
    let m = format!("{:#}", e([0, 8], [8, 16], 12).unwrap_err());
    assert!(m.contains("truncated"), "{m}");
    // the file reader: the same rules, and the data is read only when the sizes agree
    let d = tmp("tiling");
    let h = json!({"a": {"dtype": "F32", "shape": [2], "data_offsets": [0, 8]}});
    std::fs::write(d.join("ok.safetensors"), safetensors(&h, &[0u8; 8])).unwrap();
    let spec = [("a".to_string(), vec![2usize])];
    assert!(Weights::load(&d.join("ok.safetensors"), &spec).is_ok());
    std::fs::write(d.join("tail.safetensors"), safetensors(&h, &[0u8; 4096])).unwrap();
    let m = format!(
        "{:#}",
        Weights::load(&d.join("tail.safetensors"), &spec).unwrap_err()
    );
    assert!(m.contains("8..4096"), "{m}");
}

/// nuPlan time order (issue #36, item 6): two lidar_pc sweeps at one instant, or ego poses whose timestamps go
/// back while the sweeps go forward, are errors naming the rows (as nuScenes samples must increase strictly).
#[test]
fn nuplan_timestamps_must_increase_strictly() {
    let Some(fx) = nuplan_fixture::write_fixture(&tmp("nuplan_time"), &["--seconds", "4"]) else {
        return;
    };
    let pristine = std::fs::read(&fx.db).unwrap();
    let load = |sql: &str| {
        std::fs::write(&fx.db, &pristine).unwrap();
        rusqlite::Connection::open(&fx.db)
            .unwrap()
            .execute_batch(sql)
            .unwrap();
        b2dr::scene::import::nuplan::load(&fx.spec(None)).map(|_| ())
    };
    load("").unwrap();
    // the fifth sweep at the fourth's instant (rows are written 50 ms apart in time order)
    let m = format!(
        "{:#}",
        load("UPDATE lidar_pc SET timestamp = timestamp - 50000 WHERE rowid = 5").unwrap_err()
    );
    assert!(
        m.contains("table `lidar_pc`")
            && m.contains("increase strictly")
            && m.contains("same instant"),
        "{m}"
    );
    // the first step's ego pose moved after the second's (sweeps 0 and 2, 100 ms apart)
    let m = format!(
        "{:#}",
        load("UPDATE ego_pose SET timestamp = timestamp + 150000 WHERE rowid = 1").unwrap_err()
    );
    assert!(
        m.contains("table `ego_pose`") && m.contains("increase strictly") && m.contains("before"),
        "{m}"
    );
}

/// Runs `f` on another thread; panics naming `what` when it has not returned within [`BOUND`] (a read of a FIFO
/// blocks until a writer comes, forever here).
fn within_bound<T: Send + 'static>(what: &str, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(BOUND)
        .unwrap_or_else(|_| panic!("{what}: no answer within {BOUND:?} (blocked on a FIFO?)"))
}

/// A FIFO at `path` (no writer ever opens it); false (skipping) where mkfifo is missing.
fn mkfifo(path: &Path) -> bool {
    let _ = std::fs::remove_file(path);
    std::process::Command::new("mkfifo")
        .arg(path)
        .status()
        .is_ok_and(|s| s.success())
}

/// Files that must be regular files (issue #36, item 3): a FIFO given as a model weight file, a scenario file,
/// a keyframe file, a `--map` GeoJSON, a nuPlan log DB or a recorded image is refused at once, naming the
/// path and what it is, instead of blocking forever on the read.
#[test]
fn special_files_are_refused_at_once() {
    let d = tmp("fifo");
    let fifo = |name: &str| {
        let p = d.join(name);
        mkfifo(&p).then_some(p)
    };
    let check = |what: &str, r: anyhow::Result<()>, path: &Path| {
        let m = format!("{:#}", r.expect_err(what));
        assert!(
            m.contains("FIFO") && m.contains(&*path.to_string_lossy()),
            "{what}: {m}"
        );
    };
    let Some(p) = fifo("w.safetensors") else {
        eprintln!("skipping: no mkfifo");
        return;
    };
    let q = p.clone();
    check(
        "weights",
        within_bound("weights", move || Weights::load(&q, &[]).map(|_| ())),
        &p,
    );
    let p = fifo("s.json").unwrap();
    let q = p.clone();
    check(
        "scenario",
        within_bound("scenario", move || scenarionet::load_file(&q).map(|_| ())),
        &p,
    );
    let p = fifo("frame.json").unwrap();
    let q = p.clone();
    check(
        "keyframe",
        within_bound("keyframe", move || KeyFrame::load(&q).map(|_| ())),
        &p,
    );
    let p = fifo("map.geojson").unwrap();
    let q = p.clone();
    check(
        "map",
        within_bound("map", move || {
            drivable_area_from_geojson(&q, 0.0).map(|_| ())
        }),
        &p,
    );
    let p = fifo("log.db").unwrap();
    let q = p.clone();
    check(
        "nuPlan DB",
        within_bound("nuPlan DB", move || {
            let spec = b2dr::scene::import::nuplan::NuplanSpec {
                db: q,
                token: None,
                maps_root: None,
                map_version: "x".into(),
                sensor_root: None,
            };
            b2dr::scene::import::nuplan::load(&spec).map(|_| ())
        }),
        &p,
    );
}

/// A model package's own small files (b2dr.json, a component's config.json, context.safetensors) are read as
/// regular files too (issue #36, item 3): each, replaced by a FIFO in a copy of the committed package, is
/// refused at once naming that file, instead of blocking the package load forever.
#[test]
fn package_files_that_are_fifos_are_refused_at_once() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/b2dr-nano");
    if !src.join("b2dr.json").is_file() {
        eprintln!("skipping: no models/b2dr-nano");
        return;
    }
    for (k, name) in [
        "b2dr.json",
        "unet/config.json",
        "controlnet/config.json",
        "context.safetensors",
    ]
    .iter()
    .enumerate()
    {
        let d = tmp(&format!("fifo-pkg-{k}"));
        for sub in ["unet", "controlnet", "vae"] {
            std::fs::create_dir_all(d.join(sub)).unwrap();
            for f in ["config.json", "diffusion_pytorch_model.safetensors"] {
                std::os::unix::fs::symlink(src.join(sub).join(f), d.join(sub).join(f)).unwrap();
            }
        }
        for f in ["b2dr.json", "context.safetensors"] {
            std::os::unix::fs::symlink(src.join(f), d.join(f)).unwrap();
        }
        let p = d.join(name);
        std::fs::remove_file(&p).unwrap();
        if !mkfifo(&p) {
            eprintln!("skipping: no mkfifo");
            return;
        }
        let q = d.clone();
        let r = within_bound(name, move || {
            b2dr::render::package::ModelPackage::load(&q).map(|_| ())
        });
        let m = format!("{:#}", r.expect_err(name));
        assert!(
            m.contains("FIFO") && m.contains(&*p.to_string_lossy()),
            "{name}: {m}"
        );
    }
}

/// Recorded images checked against their table (issue #36, items 3 and 5): an image file of another size than
/// its camera's calibration (a 1x1 PNG where the table says the fixture's size), or a FIFO in its place, is an
/// error naming the file in the image store that log replay, retrieval and export read through, not a resized
/// blur.
#[test]
fn recorded_images_must_have_their_tables_size() {
    let Some(fx) = nuplan_fixture::write_fixture(&tmp("nuplan_images"), &["--seconds", "2"]) else {
        return;
    };
    let sc = b2dr::scene::import::nuplan::load(&fx.spec(None)).unwrap();
    let imgs = &sc.rig.frames[0].images;
    let path = |i: usize| fx.sensor_root.join(&imgs[i].path);
    let store = b2dr::world::images::ImageStore::new(&sc, None);
    // pristine: fine
    store.image(&imgs[0], 64, 36).unwrap();
    // a 1x1 PNG in place of the second image
    let mut one = Vec::new();
    image::RgbImage::new(1, 1)
        .write_to(&mut std::io::Cursor::new(&mut one), image::ImageFormat::Png)
        .unwrap();
    let p1 = if path(1).is_file() {
        path(1)
    } else {
        PathBuf::from(&imgs[1].path)
    };
    std::fs::write(&p1, &one).unwrap();
    let m = format!("{:#}", store.image(&imgs[1], 64, 36).unwrap_err());
    assert!(
        m.contains("1x1") && m.contains(&*p1.to_string_lossy()),
        "{m}"
    );
    // a FIFO in place of the third
    let p2 = if path(2).is_file() {
        path(2)
    } else {
        PathBuf::from(&imgs[2].path)
    };
    std::fs::remove_file(&p2).unwrap();
    if !mkfifo(&p2) {
        return;
    }
    let sc2 = sc.clone();
    let img = imgs[2].clone();
    let m = within_bound("image FIFO", move || {
        let store = b2dr::world::images::ImageStore::new(&sc2, None);
        store
            .image(&img, 64, 36)
            .map(|_| ())
            .map_err(|e| format!("{e:#}"))
    })
    .unwrap_err();
    assert!(m.contains("FIFO"), "{m}");
}

/// Bounds where the same value is bounded elsewhere (issue #36, item 7): guidance and conditioning scales of
/// `render`, `sample` and `bench frame` as `b2dr.json`'s `ref_guidance` (0, 100]; export-planner's offsets as
/// `world --offset` (|lateral| <= 100 m, |yaw| <= 180 degrees). Refused before any device or work, naming the
/// flag.
#[test]
fn guidance_and_offsets_are_bounded_on_every_command() {
    let d = tmp("bounds");
    let b2dr = |args: &[&str]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_b2dr"))
            .args(args)
            .env("B2DR_VALIDATION", "0")
            .output()
            .unwrap();
        assert!(!o.status.success(), "{args:?} succeeded");
        String::from_utf8_lossy(&o.stderr).to_string()
    };
    let out = d.join("o");
    let out = out.to_str().unwrap();
    for (args, flag) in [
        (
            vec![
                "render",
                "--frame",
                "nowhere.json",
                "--ref-guidance",
                "1e9",
                "--out",
                out,
            ],
            "--ref-guidance",
        ),
        (
            vec![
                "render",
                "--frame",
                "nowhere.json",
                "--ref-guidance=-2",
                "--out",
                out,
            ],
            "--ref-guidance",
        ),
        // a model that does not exist: without the bound the command fails on it, not on the flag
        (
            vec![
                "sample",
                "--model",
                "/nonexistent",
                "--guidance",
                "1e300",
                "--out",
                out,
            ],
            "--guidance",
        ),
        (
            vec![
                "sample",
                "--model",
                "/nonexistent",
                "--conditioning-scale",
                "1e30",
                "--out",
                out,
            ],
            "--conditioning-scale",
        ),
        (
            vec![
                "bench",
                "frame",
                "--model",
                "/nonexistent",
                "--ref-guidance",
                "0",
            ],
            "--ref-guidance",
        ),
    ] {
        let e = b2dr(&args);
        assert!(
            e.contains(flag) && (e.contains("(0, 100]") || e.contains("[0, 100]")),
            "{args:?}: {e}"
        );
    }
    for off in [(500.0, 0.0), (0.0, 7.0), (f64::NAN, 0.0)] {
        let e = b2dr::eval::planner_data::export(&b2dr::eval::planner_data::PlannerDataOptions {
            scenarios: vec!["builtin:straight:3".into()],
            out: d.join("planner"),
            size: (16, 16),
            cameras: vec![],
            offsets: vec![(0.0, 0.0), off],
            every: 50,
            progress: false,
        })
        .expect_err("an offset beyond the bounds");
        assert!(format!("{e:#}").contains("--offsets"), "{off:?}: {e:#}");
    }
}

/// Work in proportion to what a frame shows (issue #36, item 8): the bird's-eye view of a scenario whose
/// drivable area is one polygon of 10^6 vertices (a 30 m disc round the ego) is drawn in well under a second
/// (it took about a minute: a point test per pixel over the tens of thousands of edges near each row), and
/// the disc is where it should be.
#[test]
fn bev_of_a_million_vertex_polygon_is_fast() {
    let mut sc = b2dr::world::load_all("builtin:straight:1:0")
        .unwrap()
        .remove(0);
    let cfg = b2dr::sim::SimConfig {
        agents: b2dr::sim::AgentMode::None,
        steps: 1,
        ..Default::default()
    };
    let run = b2dr::sim::run(&sc, &mut b2dr::sim::ExpertPlanner, &cfg);
    let step = &run.steps[0];
    let c = step.ego_center.pos();
    let n = 1_000_000;
    let disc: Vec<glam::DVec2> = (0..n)
        .map(|i| {
            let a = i as f64 / n as f64 * std::f64::consts::TAU;
            c + 30.0 * glam::DVec2::new(a.cos(), a.sin())
        })
        .collect();
    sc.map.drivable = b2dr::scene::index::PolygonSet::new(vec![disc]);
    sc.map.crosswalks.clear();
    let view = b2dr::sim::bev::BevView::default();
    let t0 = Instant::now();
    let img = b2dr::sim::bev::render_step(&sc, step, None, &view);
    let took = t0.elapsed();
    assert!(took < Duration::from_secs(2), "bev took {took:?}");
    // pixels left as background or drivable agree with the disc away from its rim
    let h = view.size as f64 / 2.0;
    let (mut checked, mut wrong) = (0, 0);
    for (x, y, p) in img.enumerate_pixels() {
        let is_drivable = p.0 == [62, 62, 66];
        if !(is_drivable || p.0 == [25, 25, 28]) {
            continue;
        }
        let w = glam::DVec2::new(
            c.x + (x as f64 + 0.5 - h) * view.metres_per_px,
            c.y - (y as f64 + 0.5 - h) * view.metres_per_px,
        );
        let r = (w - c).length();
        if (r - 30.0).abs() < 0.3 {
            continue;
        }
        checked += 1;
        if is_drivable != (r < 30.0) {
            wrong += 1;
        }
    }
    assert!(
        checked > 100_000 && wrong == 0,
        "{wrong} of {checked} pixels wrong"
    );
}
