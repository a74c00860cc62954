//! ScenarioNet "scenario description" JSON (as in ../shared/data/nuscenes-mini/scenes).
//!
//! Mapping decisions (ScenarioNet's nuScenes converter):
//! - `LANE_*` features with a `polygon` are lanes; those without one are nuScenes lane connectors (the
//!   converter writes no polygon for them): we buffer their centre line by [`CONNECTOR_WIDTH_M`].
//! - The converter writes a constant `speed_limit_kmh: 100` on every connector and nothing on lanes; nuScenes
//!   has no speed limits, so that placeholder is ignored and all speed limits are unknown (IDM then uses its
//!   default target speed).
//! - Lane links are not given: they are inferred from geometry ([`crate::scene::map::infer_lane_links`]).
//! - Roadblocks: nuScenes has no lane groups, so every lane is its own roadblock.
//! - The ego track's `length`/`width` are swapped in these files (length 1.73, width 4.08): the larger value
//!   is taken as the length.
//! - The ego `position` is the nuScenes ego pose, which sits on the rear axle.
//! - Drivable area from `../maps/<map>.drivable_area.geojson` next to the scenes folder when present, else
//!   the union of lane polygons.
use crate::scene::geometry::{Polyline, Pose2};
use crate::scene::index::PolygonSet;
use crate::scene::map::{Crosswalk, LaneKind, LaneSpec, Map};
use crate::scene::{
    EgoLogState, ObjectClass, ObjectState, Route, Scenario, Track, TrafficLightStatus,
    VehicleParameters,
};
use anyhow::{anyhow, bail, Context, Result};
use glam::DVec2;
use serde_json::Value;
use std::path::Path;

/// Width given to connector polygons (nuScenes lanes are about 3-3.5 m wide).
pub const CONNECTOR_WIDTH_M: f64 = 3.5;

pub use super::bounds::{MAX_ANGLE_RAD, MAX_COORD_M, MAX_SIZE_M, MAX_SPEED_MPS};

/// Field access with errors that name the file and the JSON path.
struct Ctx<'a> {
    file: &'a str,
}

impl Ctx<'_> {
    fn err(&self, field: &str, what: &str) -> anyhow::Error {
        anyhow!("{}: field `{}`: {}", self.file, field, what)
    }
    fn get<'v>(&self, v: &'v Value, key: &str, path: &str) -> Result<&'v Value> {
        v.get(key)
            .ok_or_else(|| self.err(format!("{path}.{key}").trim_start_matches('.'), "missing"))
    }
    fn f64(&self, v: &Value, path: &str) -> Result<f64> {
        match v {
            Value::Number(n) => n.as_f64().ok_or_else(|| self.err(path, "not a number")),
            Value::Array(a) if a.len() == 1 => self.f64(&a[0], path),
            Value::Bool(b) => Ok(if *b { 1.0 } else { 0.0 }),
            _ => Err(self.err(path, &format!("expected a number, found {}", kind(v)))),
        }
    }
    fn arr<'v>(&self, v: &'v Value, path: &str) -> Result<&'v Vec<Value>> {
        v.as_array()
            .ok_or_else(|| self.err(path, &format!("expected an array, found {}", kind(v))))
    }
    fn str<'v>(&self, v: &'v Value, path: &str) -> Result<&'v str> {
        v.as_str()
            .ok_or_else(|| self.err(path, &format!("expected a string, found {}", kind(v))))
    }
    /// An array of points (each [x, y] or [x, y, z/heading]); returns (xy, third column if present).
    fn points(&self, v: &Value, path: &str) -> Result<(Vec<DVec2>, Option<Vec<f64>>)> {
        let a = self.arr(v, path)?;
        let mut pts = Vec::with_capacity(a.len());
        let mut third = Vec::with_capacity(a.len());
        for (i, p) in a.iter().enumerate() {
            let pp = format!("{path}[{i}]");
            let c = self.arr(p, &pp)?;
            if c.len() < 2 {
                return Err(self.err(&pp, "a point needs at least 2 coordinates"));
            }
            let x = self.f64(&c[0], &pp)?;
            let y = self.f64(&c[1], &pp)?;
            if !x.is_finite() || !y.is_finite() {
                return Err(self.err(&pp, "non-finite coordinate"));
            }
            self.within_world(x, y, &pp)?;
            pts.push(DVec2::new(x, y));
            if c.len() >= 3 {
                third.push(self.f64(&c[2], &pp)?);
            }
        }
        let third = (third.len() == pts.len() && !pts.is_empty()).then_some(third);
        Ok((pts, third))
    }
    /// A coordinate pair within [`MAX_COORD_M`].
    fn within_world(&self, x: f64, y: f64, path: &str) -> Result<()> {
        if x.abs() > MAX_COORD_M || y.abs() > MAX_COORD_M {
            return Err(self.err(
                path,
                &format!("coordinate ({x}, {y}) lies beyond {MAX_COORD_M:e} m of the origin"),
            ));
        }
        Ok(())
    }
    /// A per-step array of length exactly t.
    fn steps<'v>(&self, v: &'v Value, key: &str, path: &str, t: usize) -> Result<&'v Vec<Value>> {
        let p = format!("{path}.{key}");
        let a = self.arr(self.get(v, key, path)?, &p)?;
        if a.len() != t {
            return Err(self.err(
                &p,
                &format!("has {} entries, expected `length` = {t}", a.len()),
            ));
        }
        Ok(a)
    }
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

fn class_of(t: &str) -> Option<ObjectClass> {
    Some(match t {
        "VEHICLE" => ObjectClass::Vehicle,
        "PEDESTRIAN" => ObjectClass::Pedestrian,
        "CYCLIST" => ObjectClass::Bicycle,
        "TRAFFIC_CONE" => ObjectClass::TrafficCone,
        "TRAFFIC_BARRIER" => ObjectClass::Barrier,
        "TRAFFIC_OBJECT" | "OTHER" | "UNSET" => ObjectClass::GenericObject,
        _ => return None,
    })
}

fn light_of(s: &str) -> TrafficLightStatus {
    let s = s.to_ascii_uppercase();
    if s.contains("RED") || s.contains("STOP") {
        TrafficLightStatus::Red
    } else if s.contains("GREEN") || s.contains("GO") {
        TrafficLightStatus::Green
    } else if s.contains("YELLOW") || s.contains("CAUTION") {
        TrafficLightStatus::Yellow
    } else {
        TrafficLightStatus::Unknown
    }
}

/// Loads one ScenarioNet JSON file.
pub fn load_file(path: &Path) -> Result<Scenario> {
    let text = crate::files::read_regular_string(path, "scenario file", crate::files::JSON_LIMIT)?;
    let v: Value = serde_json::from_str(&text)
        .with_context(|| format!("{}: not valid JSON", path.display()))?;
    let maps_dir = path
        .parent()
        .and_then(|p| p.parent())
        .map(|p| p.join("maps"));
    parse(&v, &path.display().to_string(), maps_dir.as_deref())
}

/// Parses a ScenarioNet scenario. `file` names the source in errors; `maps_dir` is searched for
/// `<map>.drivable_area.geojson`.
pub fn parse(v: &Value, file: &str, maps_dir: Option<&Path>) -> Result<Scenario> {
    let c = Ctx { file };
    if !v.is_object() {
        bail!("{file}: expected a JSON object at the top level");
    }
    if let Some(fmt) = v.get("format").and_then(|f| f.as_str()) {
        if !fmt.starts_with("scenarionet") {
            return Err(c.err("format", &format!("unsupported format {fmt:?}")));
        }
    }
    let t = c.f64(c.get(v, "length", "")?, "length")?;
    if !(t >= 2.0 && t.fract() == 0.0) {
        return Err(c.err("length", "must be an integer >= 2"));
    }
    let t = t as usize;
    let meta = c.get(v, "metadata", "")?;
    let sdc = c
        .str(c.get(meta, "sdc_id", "metadata")?, "metadata.sdc_id")?
        .to_string();
    let map_name = c
        .str(c.get(meta, "map", "metadata")?, "metadata.map")?
        .to_string();
    // the map name becomes a file name (`<map>.drivable_area.geojson` in maps_dir): a plain name only
    if let Err(why) = super::bounds::plain_name(&map_name) {
        return Err(c.err("metadata.map", &why));
    }
    let dt = match meta.get("sample_rate") {
        Some(s) => c.f64(s, "metadata.sample_rate")?,
        None => 0.1,
    };
    if let Err(why) = super::bounds::check_dt(dt) {
        return Err(c.err("metadata.sample_rate", &why));
    }
    let name = v
        .get("id")
        .and_then(|s| s.as_str())
        .map(String::from)
        .unwrap_or_else(|| {
            Path::new(file)
                .file_stem()
                .map(|s| s.to_string_lossy().into())
                .unwrap_or_default()
        });

    // --- tracks
    let tracks_v = c
        .get(v, "tracks", "")?
        .as_object()
        .ok_or_else(|| c.err("tracks", "expected an object"))?;
    let mut ids: Vec<&String> = tracks_v.keys().collect();
    ids.sort();
    let mut tracks = Vec::new();
    let mut ego_track = None;
    for id in ids {
        let tv = &tracks_v[id.as_str()];
        let p = format!("tracks.{id}");
        let ty = c.str(c.get(tv, "type", &p)?, &format!("{p}.type"))?;
        let class = class_of(ty)
            .ok_or_else(|| c.err(&format!("{p}.type"), &format!("unknown object type {ty:?}")))?;
        let st = c.get(tv, "state", &p)?;
        let sp = format!("{p}.state");
        let pos = c.steps(st, "position", &sp, t)?;
        let head = c.steps(st, "heading", &sp, t)?;
        let vel = c.steps(st, "velocity", &sp, t)?;
        let valid = c.steps(st, "valid", &sp, t)?;
        let len = c.steps(st, "length", &sp, t)?;
        let wid = c.steps(st, "width", &sp, t)?;
        let hei = c.steps(st, "height", &sp, t)?;
        let mut states = Vec::with_capacity(t);
        let mut size = None;
        for k in 0..t {
            let ok = c.f64(&valid[k], &format!("{sp}.valid[{k}]"))? != 0.0;
            if !ok {
                states.push(None);
                continue;
            }
            let pp = format!("{sp}.position[{k}]");
            let pa = c.arr(&pos[k], &pp)?;
            if pa.len() < 2 {
                return Err(c.err(&pp, "needs x and y"));
            }
            let (x, y) = (c.f64(&pa[0], &pp)?, c.f64(&pa[1], &pp)?);
            let h = c.f64(&head[k], &format!("{sp}.heading[{k}]"))?;
            let vp = format!("{sp}.velocity[{k}]");
            let va = c.arr(&vel[k], &vp)?;
            if va.len() < 2 {
                return Err(c.err(&vp, "needs vx and vy"));
            }
            let (vx, vy) = (c.f64(&va[0], &vp)?, c.f64(&va[1], &vp)?);
            if !(x.is_finite() && y.is_finite() && h.is_finite()) {
                return Err(c.err(&pp, "non-finite position or heading at a valid step"));
            }
            c.within_world(x, y, &pp)?;
            if !super::bounds::angle_ok(h) {
                return Err(c.err(
                    &format!("{sp}.heading[{k}]"),
                    &format!("heading {h} rad is not an angle"),
                ));
            }
            // NaN (unknown) velocities are kept; a finite one must be a speed
            if vx.abs() > MAX_SPEED_MPS
                || vy.abs() > MAX_SPEED_MPS
                || vx.is_infinite()
                || vy.is_infinite()
            {
                return Err(c.err(
                    &vp,
                    &format!("velocity ({vx}, {vy}) beyond {MAX_SPEED_MPS} m/s"),
                ));
            }
            if size.is_none() {
                let dim = |a: &Value, what: &str| -> Result<f64> {
                    let path = format!("{sp}.{what}[{k}]");
                    let d = c.f64(a, &path)?;
                    if !super::bounds::size_ok(d) {
                        return Err(c.err(&path, &format!("size {d} m is not in 0..={MAX_SIZE_M}")));
                    }
                    Ok(d)
                };
                size = Some((
                    dim(&len[k], "length")?,
                    dim(&wid[k], "width")?,
                    dim(&hei[k], "height")?,
                ));
            }
            states.push(Some(ObjectState {
                pose: Pose2::new(x, y, h),
                velocity: DVec2::new(vx, vy),
            }));
        }
        let Some((l, w, hgt)) = size else { continue };
        if !(l > 0.0 && w > 0.0) {
            return Err(c.err(&format!("{sp}.length"), "object size must be positive"));
        }
        let tr = Track {
            id: id.clone(),
            class,
            length: l,
            width: w,
            height: hgt,
            states,
        };
        if *id == sdc {
            ego_track = Some(tr);
        } else {
            tracks.push(tr);
        }
    }
    let ego_tr = ego_track
        .ok_or_else(|| c.err("metadata.sdc_id", &format!("no track {sdc:?} in `tracks`")))?;
    let mut ego = Vec::with_capacity(t);
    for (k, s) in ego_tr.states.iter().enumerate() {
        let s = s.ok_or_else(|| {
            c.err(
                &format!("tracks.{sdc}.state.valid[{k}]"),
                "the ego must be valid at every step",
            )
        })?;
        ego.push(EgoLogState {
            rear_axle: s.pose,
            velocity: s.velocity,
            accel: 0.0,
        });
    }
    fill_ego_accel(&mut ego, dt);
    let (el, ew) = if ego_tr.width > ego_tr.length {
        (ego_tr.width, ego_tr.length)
    } else {
        (ego_tr.length, ego_tr.width)
    };
    let ego_params = VehicleParameters {
        width: ew,
        length: el,
        height: ego_tr.height,
        ..VehicleParameters::PACIFICA
    };

    // --- map
    let feats = c
        .get(v, "map_features", "")?
        .as_object()
        .ok_or_else(|| c.err("map_features", "expected an object"))?;
    let mut fids: Vec<&String> = feats.keys().collect();
    fids.sort();
    let mut specs = Vec::new();
    let mut crosswalks = Vec::new();
    for id in fids {
        let f = &feats[id.as_str()];
        let p = format!("map_features.{id}");
        let ty = c.str(c.get(f, "type", &p)?, &format!("{p}.type"))?;
        if ty.starts_with("LANE_") {
            let (pts, third) = c.points(c.get(f, "polyline", &p)?, &format!("{p}.polyline"))?;
            let centre = Polyline::new(pts, third);
            if centre.points.len() < 2 {
                return Err(c.err(
                    &format!("{p}.polyline"),
                    "a lane needs at least 2 distinct points",
                ));
            }
            let polygon = match f.get("polygon") {
                Some(pg) => {
                    let (pp, _) = c.points(pg, &format!("{p}.polygon"))?;
                    (pp.len() >= 3).then_some(pp)
                }
                None => None,
            };
            let kind = if polygon.is_some() {
                LaneKind::Lane
            } else {
                LaneKind::Connector
            };
            specs.push(LaneSpec {
                id: id.clone(),
                kind,
                centre,
                polygon,
                width: CONNECTOR_WIDTH_M,
                speed_limit_mps: None,
                successors: vec![],
                roadblock: None,
                has_traffic_light: false,
                stop_lines: vec![],
            });
        } else if ty == "CROSSWALK" {
            if let Some(pg) = f.get("polygon") {
                let (pp, _) = c.points(pg, &format!("{p}.polygon"))?;
                crosswalks.push(Crosswalk {
                    id: id.clone(),
                    polygon: pp,
                });
            }
        }
    }
    let drivable = match maps_dir.map(|d| d.join(format!("{map_name}.drivable_area.geojson"))) {
        Some(f) if f.is_file() => load_geojson_polygons(&f)?,
        _ => PolygonSet::default(),
    };
    let mut map = Map::build(&map_name, specs, vec![], crosswalks, vec![], drivable, true)
        .with_context(|| format!("{file}: building the map"))?;

    // --- traffic lights
    let mut lights = vec![Vec::new(); t];
    if let Some(dms) = v.get("dynamic_map_states") {
        let o = dms
            .as_object()
            .ok_or_else(|| c.err("dynamic_map_states", "expected an object"))?;
        let mut keys: Vec<&String> = o.keys().collect();
        keys.sort();
        for id in keys {
            let d = &o[id.as_str()];
            let p = format!("dynamic_map_states.{id}");
            let lane = c.str(c.get(d, "lane", &p)?, &format!("{p}.lane"))?;
            let li = map
                .lane_index(lane)
                .ok_or_else(|| c.err(&format!("{p}.lane"), &format!("unknown lane {lane:?}")))?;
            let st = c.get(
                c.get(d, "state", &p)?,
                "object_state",
                &format!("{p}.state"),
            )?;
            let arr = c.arr(st, &format!("{p}.state.object_state"))?;
            map.lanes[li].has_traffic_light = true;
            for (k, s) in arr.iter().enumerate().take(t) {
                if let Some(s) = s.as_str() {
                    lights[k].push((li, light_of(s)));
                }
            }
        }
    }
    let route = route_from_ego(&map, &ego, &ego_params);
    let rig = super::default_rig(&name, &ego, dt);
    Ok(Scenario {
        name,
        source: file.to_string(),
        dt,
        map,
        ego,
        ego_params,
        tracks,
        route,
        traffic_lights: lights,
        rig,
        ego_past: vec![],
    })
}

/// Longitudinal acceleration: least-squares slope of the speed along the heading over a window of +-5 steps
/// (clamped at the ends). Logged nuScenes velocities are noisy (0.5 m/s step to step), so plain differences
/// would give accelerations of +-10 m/s^2.
pub fn fill_ego_accel(ego: &mut [EgoLogState], dt: f64) {
    let n = ego.len();
    let v: Vec<f64> = ego
        .iter()
        .map(|e| e.velocity.dot(e.rear_axle.dir()))
        .collect();
    const HALF: usize = 5;
    for (k, e) in ego.iter_mut().enumerate() {
        let (a, b) = (k.saturating_sub(HALF), (k + HALF).min(n - 1));
        let m = (b - a + 1) as f64;
        let tm = (a..=b).map(|i| i as f64).sum::<f64>() / m;
        let vm = v[a..=b].iter().sum::<f64>() / m;
        let (mut num, mut den) = (0.0, 0.0);
        for (i, vi) in v.iter().enumerate().take(b + 1).skip(a) {
            let t = i as f64 - tm;
            num += t * (vi - vm);
            den += t * t;
        }
        e.accel = if den > 0.0 && num.is_finite() {
            num / den / dt
        } else {
            0.0
        };
    }
}

/// The expert route: the lanes under the logged ego box centre (matched by heading), consecutive duplicates
/// removed, and their roadblocks.
pub fn route_from_ego(map: &Map, ego: &[EgoLogState], params: &VehicleParameters) -> Route {
    let mut route = Route::default();
    for e in ego {
        let c = params.center_of(&e.rear_axle);
        if let Some(l) = map.match_lane(c.pos(), c.heading, 3.0) {
            let id = &map.lanes[l].id;
            if route.lane_ids.last() != Some(id) {
                route.lane_ids.push(id.clone());
            }
            let rb = &map.roadblocks[map.lanes[l].roadblock].id;
            if route.roadblock_ids.last() != Some(rb) {
                route.roadblock_ids.push(rb.clone());
            }
        }
    }
    route
}

/// Reads a GeoJSON Polygon / MultiPolygon (or a FeatureCollection of them) into a polygon set.
pub fn load_geojson_polygons(path: &Path) -> Result<PolygonSet> {
    let file = path.display().to_string();
    let text = crate::files::read_regular_string(path, "map file", crate::files::JSON_LIMIT)?;
    let v: Value =
        serde_json::from_str(&text).with_context(|| format!("{file}: not valid JSON"))?;
    let c = Ctx { file: &file };
    let mut rings = Vec::new();
    fn geometry(c: &Ctx, g: &Value, path: &str, rings: &mut Vec<Vec<DVec2>>) -> Result<()> {
        let ty = c.str(c.get(g, "type", path)?, &format!("{path}.type"))?;
        let coords = c.get(g, "coordinates", path)?;
        let polys: Vec<&Value> = match ty {
            "Polygon" => vec![coords],
            "MultiPolygon" => c
                .arr(coords, &format!("{path}.coordinates"))?
                .iter()
                .collect(),
            other => {
                return Err(c.err(
                    &format!("{path}.type"),
                    &format!("unsupported geometry {other:?}"),
                ))
            }
        };
        for (i, poly) in polys.iter().enumerate() {
            for (j, ring) in c
                .arr(poly, &format!("{path}.coordinates[{i}]"))?
                .iter()
                .enumerate()
            {
                let (pts, _) = c.points(ring, &format!("{path}.coordinates[{i}][{j}]"))?;
                rings.push(pts);
            }
        }
        Ok(())
    }
    match v.get("type").and_then(|t| t.as_str()) {
        Some("FeatureCollection") => {
            for (i, f) in c
                .arr(c.get(&v, "features", "")?, "features")?
                .iter()
                .enumerate()
            {
                geometry(
                    &c,
                    c.get(f, "geometry", &format!("features[{i}]"))?,
                    &format!("features[{i}].geometry"),
                    &mut rings,
                )?;
            }
        }
        Some("Feature") => geometry(&c, c.get(&v, "geometry", "")?, "geometry", &mut rings)?,
        _ => geometry(&c, &v, "", &mut rings)?,
    }
    Ok(PolygonSet::new(rings))
}
