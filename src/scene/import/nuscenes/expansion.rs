//! The nuScenes map expansion (`DATAROOT/maps/expansion/<location>.json`, version >= 1.3; layout of
//! nutonomy/nuscenes-devkit map_expansion/map_api.py): geometric layers `node` (x, y), `line` (node_tokens) and
//! `polygon` (exterior_node_tokens, holes[].node_tokens); `lane` and `lane_connector` records point at their
//! polygon, their centre lines are the `arcline_path_3` paths of their token and their links the
//! `connectivity` entry (`outgoing` = successors); `drivable_area` records list polygon_tokens; `ped_crossing`
//! records point at a polygon. Only elements whose bounding box meets the region of interest are kept.
use super::tables::{Row, Table};
use crate::scene::geometry::{wrap_angle, Aabb, Polyline};
use crate::scene::import::bounds;
use crate::scene::index::PolygonSet;
use crate::scene::map::{Crosswalk, LaneKind, LaneSpec, Map, MapLine, MapLineKind, StopLine};
use anyhow::{anyhow, bail, Context, Result};
use glam::DVec2;
use serde_json::Value;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Spacing of centre-line points sampled from arcline paths (the devkit's default resolution).
pub const ARCLINE_RESOLUTION_M: f64 = 0.5;
/// Width given to a lane whose polygon is missing (its centre line is buffered).
pub const DEFAULT_LANE_WIDTH_M: f64 = 3.5;
/// Longest arcline piece accepted (m; the map expansion's are tens of metres): each is sampled every
/// [`ARCLINE_RESOLUTION_M`].
pub const MAX_ARCLINE_PIECE_M: f64 = 1e4;
/// Smallest arcline turning radius accepted (m).
pub const MIN_ARCLINE_RADIUS_M: f64 = 1e-3;
/// Most centre-line points kept for one map (the largest nuScenes map keeps well under a million).
pub const MAX_MAP_POINTS: usize = 10_000_000;

/// One arcline path: three pieces (arc, arc or straight, arc) of the given lengths, turning left, right or
/// going straight according to `shape` (e.g. `LSR`), with one turning `radius`.
#[derive(Clone, Debug, PartialEq)]
pub struct ArclinePath {
    pub start: [f64; 3],
    pub shape: String,
    pub radius: f64,
    pub lengths: [f64; 3],
}

impl ArclinePath {
    /// Curvature signs of the three pieces (+1 left, -1 right, 0 straight), as the devkit's
    /// `compute_segment_sign`.
    pub fn signs(&self) -> Result<[f64; 3]> {
        let s = self.shape.as_bytes();
        if s.len() != 3 {
            bail!("arcline shape {:?}: expected three letters", self.shape);
        }
        let mut out = [0.0; 3];
        for (i, c) in s.iter().enumerate() {
            out[i] = match (i, c) {
                (_, b'L') => 1.0,
                (_, b'R') => -1.0,
                (1, b'S') => 0.0,
                _ => bail!(
                    "arcline shape {:?}: unknown piece {:?}",
                    self.shape,
                    *c as char
                ),
            };
        }
        Ok(out)
    }

    pub fn length(&self) -> f64 {
        self.lengths.iter().sum()
    }

    /// Pose (x, y, yaw) `s` metres along the path (clamped to [0, length]).
    pub fn pose_at(&self, signs: &[f64; 3], s: f64) -> [f64; 3] {
        let mut p = self.start;
        let mut left = s.clamp(0.0, self.length());
        for (k, &len) in self.lengths.iter().enumerate() {
            let step = left.min(len);
            let kappa = signs[k] / self.radius;
            let (x, y, h) = (p[0], p[1], p[2]);
            if (kappa * step).abs() < 1e-9 {
                p = [x + step * h.cos(), y + step * h.sin(), h];
            } else {
                let h2 = h + kappa * step;
                p = [
                    x + (h2.sin() - h.sin()) / kappa,
                    y - (h2.cos() - h.cos()) / kappa,
                    wrap_angle(h2),
                ];
            }
            left -= step;
            if left <= 0.0 {
                break;
            }
        }
        p
    }

    /// Points every about `resolution` metres, both ends included (at least 2).
    pub fn discretize(&self, resolution: f64) -> Result<Vec<[f64; 3]>> {
        let signs = self.signs()?;
        let len = self.length();
        let n = ((len / resolution).ceil() as usize + 1).max(2);
        Ok((0..n)
            .map(|i| self.pose_at(&signs, len * i as f64 / (n - 1) as f64))
            .collect())
    }
}

fn arcline_of(v: &Value, ctx: &str) -> Result<ArclinePath> {
    let f = |k: &str| v.get(k).ok_or_else(|| anyhow!("{ctx}: `{k}` is missing"));
    let de = |k: &str| -> Result<Value> { Ok(f(k)?.clone()) };
    let start: [f64; 3] = serde_json::from_value(de("start_pose")?)
        .map_err(|e| anyhow!("{ctx}: `start_pose`: {e}"))?;
    let shape: String =
        serde_json::from_value(de("shape")?).map_err(|e| anyhow!("{ctx}: `shape`: {e}"))?;
    let radius: f64 =
        serde_json::from_value(de("radius")?).map_err(|e| anyhow!("{ctx}: `radius`: {e}"))?;
    let lengths: [f64; 3] = serde_json::from_value(de("segment_length")?)
        .map_err(|e| anyhow!("{ctx}: `segment_length`: {e}"))?;
    if !(radius >= MIN_ARCLINE_RADIUS_M
        && lengths
            .iter()
            .all(|l| *l >= 0.0 && *l <= MAX_ARCLINE_PIECE_M))
    {
        bail!(
            "{ctx}: needs a radius of at least {MIN_ARCLINE_RADIUS_M} m and segment lengths in 0..={MAX_ARCLINE_PIECE_M} m, found {radius} and {lengths:?}"
        );
    }
    if !(bounds::coord_ok(start[0]) && bounds::coord_ok(start[1]) && bounds::angle_ok(start[2])) {
        bail!(
            "{ctx}: `start_pose` {start:?}: coordinates beyond {:e} m or a heading that is not an angle",
            bounds::MAX_COORD_M
        );
    }
    Ok(ArclinePath {
        start,
        shape,
        radius,
        lengths,
    })
}

/// The geometric layers and records of one map file.
struct MapFile {
    file: String,
    json: serde_json::Map<String, Value>,
    nodes: HashMap<String, DVec2>,
    polygon: Table,
    /// The `line` layer, read when a divider layer needs it.
    line: Option<Table>,
}

impl MapFile {
    fn layer(&mut self, name: &str) -> Result<Table> {
        let v = self
            .json
            .remove(name)
            .ok_or_else(|| anyhow!("map expansion {}: layer `{name}` is missing", self.file))?;
        Table::from_value(name, &self.file, v)
    }

    fn ring(&self, r: &Row, tokens: &[String], what: &str) -> Result<Vec<DVec2>> {
        tokens
            .iter()
            .map(|t| {
                self.nodes.get(t).copied().ok_or_else(|| {
                    anyhow!(
                        "{}: {what}: no row of layer `node` has token {t:?} (dangling token)",
                        r.at()
                    )
                })
            })
            .collect()
    }

    /// The points of line `token` (referenced from `from`'s column `col`).
    fn line(&self, from: &Row, col: &str, token: &str) -> Result<Vec<DVec2>> {
        let l = self
            .line
            .as_ref()
            .and_then(|t| t.find(token))
            .ok_or_else(|| {
                anyhow!(
                "{}: column `{col}`: no row of layer `line` has token {token:?} (dangling token)",
                from.at()
            )
            })?;
        let toks: Vec<String> = l.get("node_tokens")?;
        self.ring(&l, &toks, "node_tokens")
    }

    /// Exterior and holes of polygon `token` (referenced from `from`'s column `col`).
    fn polygon(&self, from: &Row, col: &str, token: &str) -> Result<Vec<Vec<DVec2>>> {
        let p = self.polygon.find(token).ok_or_else(|| {
            anyhow!(
                "{}: column `{col}`: no row of layer `polygon` has token {token:?} (dangling token)",
                from.at()
            )
        })?;
        let ext: Vec<String> = p.get("exterior_node_tokens")?;
        let mut rings = vec![self.ring(&p, &ext, "exterior_node_tokens")?];
        let holes: Vec<Value> = p.get("holes")?;
        for (k, h) in holes.iter().enumerate() {
            let toks: Vec<String> = h
                .get("node_tokens")
                .cloned()
                .map(serde_json::from_value)
                .transpose()
                .map_err(|e| anyhow!("{}: column `holes[{k}].node_tokens`: {e}", p.at()))?
                .unwrap_or_default();
            if toks.len() >= 3 {
                rings.push(self.ring(&p, &toks, "holes")?);
            }
        }
        Ok(rings)
    }
}

fn overlaps(region: &Aabb, pts: &[DVec2]) -> bool {
    region.overlaps(&Aabb::from_points(pts))
}

/// Loads the map of `location` from `<dataroot>/maps/expansion/<location>.json`, keeping what meets `region`.
/// `DATAROOT/maps/expansion/<location>.json`, where the devkit's `NuScenesMap` finds the expansion pack.
pub fn path(dataroot: &Path, location: &str) -> PathBuf {
    dataroot
        .join("maps")
        .join("expansion")
        .join(format!("{location}.json"))
}

pub fn load(dataroot: &Path, location: &str, region: &Aabb) -> Result<Map> {
    let path = path(dataroot, location);
    let file = path.display().to_string();
    let text = bounds::read_table_text(&path).map_err(|why| {
        anyhow!("nuScenes map expansion of {location:?}: {why} (the map expansion pack is needed for lanes)")
    })?;
    let v: Value = serde_json::from_str(&text)
        .with_context(|| format!("map expansion {file}: not valid JSON"))?;
    let Value::Object(mut json) = v else {
        bail!("map expansion {file}: expected a JSON object of layers");
    };
    if let Some(ver) = json.get("version").and_then(Value::as_str) {
        if ver < "1.3" {
            bail!(
                "map expansion {file}: version {ver} is older than 1.3 (the devkit refuses it too)"
            );
        }
    }
    let node_v = json
        .remove("node")
        .ok_or_else(|| anyhow!("map expansion {file}: layer `node` is missing"))?;
    let node_t = Table::from_value("node", &file, node_v)?;
    let mut nodes = HashMap::with_capacity(node_t.len());
    for r in node_t.iter() {
        let r = r?;
        let (x, y): (f64, f64) = (r.get("x")?, r.get("y")?);
        if !(bounds::coord_ok(x) && bounds::coord_ok(y)) {
            bail!(
                "{}: columns `x`, `y`: ({x}, {y}) lies beyond {:e} m of the origin",
                r.at(),
                bounds::MAX_COORD_M
            );
        }
        nodes.insert(r.str("token")?.to_string(), DVec2::new(x, y));
    }
    let poly_v = json
        .remove("polygon")
        .ok_or_else(|| anyhow!("map expansion {file}: layer `polygon` is missing"))?;
    let polygon = Table::from_value("polygon", &file, poly_v)?;
    let mut mf = MapFile {
        file: file.clone(),
        json,
        nodes,
        polygon,
        line: None,
    };
    let arcs = match mf.json.remove("arcline_path_3") {
        Some(Value::Object(o)) => o,
        Some(other) => bail!(
            "map expansion {file}: layer `arcline_path_3`: expected an object keyed by lane token, found {}",
            super::tables::kind(&other)
        ),
        None => bail!("map expansion {file}: layer `arcline_path_3` is missing"),
    };
    let connectivity = match mf.json.remove("connectivity") {
        Some(Value::Object(o)) => o,
        _ => serde_json::Map::new(),
    };

    let mut specs: Vec<LaneSpec> = Vec::new();
    let mut n_points = 0usize;
    for (layer, kind) in [
        ("lane", LaneKind::Lane),
        ("lane_connector", LaneKind::Connector),
    ] {
        let t = mf.layer(layer)?;
        for r in t.iter() {
            let r = r?;
            let tok = r.str("token")?;
            let Some(paths) = arcs.get(tok) else { continue };
            let ctx = format!("map expansion {file}: arcline_path_3[{tok:?}]");
            let paths = paths
                .as_array()
                .ok_or_else(|| anyhow!("{ctx}: expected an array of arcline paths"))?;
            let paths = paths
                .iter()
                .enumerate()
                .map(|(k, p)| arcline_of(p, &format!("{ctx}[{k}]")))
                .collect::<Result<Vec<_>>>()?;
            // Every point of a path lies within its length of its start: lanes whose paths cannot meet the
            // region are skipped before sampling them.
            let near = paths.iter().any(|p| {
                let (c, l) = (DVec2::new(p.start[0], p.start[1]), p.length());
                region.overlaps(&Aabb {
                    min: c - DVec2::splat(l),
                    max: c + DVec2::splat(l),
                })
            });
            if !near {
                continue;
            }
            let (mut pts, mut hs) = (Vec::new(), Vec::new());
            for p in &paths {
                for q in p.discretize(ARCLINE_RESOLUTION_M)? {
                    pts.push(DVec2::new(q[0], q[1]));
                    hs.push(q[2]);
                }
            }
            if pts.len() < 2 || !overlaps(region, &pts) {
                continue;
            }
            n_points += pts.len();
            if n_points > MAX_MAP_POINTS {
                bail!(
                    "map expansion {file}: layer `{layer}` row {} (token {tok}): the lane centre lines near the scene exceed {MAX_MAP_POINTS} points",
                    r.index
                );
            }
            let centre = Polyline::new(pts, Some(hs));
            if centre.points.len() < 2 {
                continue;
            }
            let polygon = mf
                .polygon(&r, "polygon_token", r.str("polygon_token")?)?
                .swap_remove(0);
            let successors = match connectivity.get(tok).and_then(|c| c.get("outgoing")) {
                Some(o) => serde_json::from_value::<Vec<String>>(o.clone()).map_err(|e| {
                    anyhow!("map expansion {file}: connectivity[{tok:?}].outgoing: {e}")
                })?,
                None => vec![],
            };
            specs.push(LaneSpec {
                id: tok.to_string(),
                kind,
                centre,
                polygon: (polygon.len() >= 3).then_some(polygon),
                width: DEFAULT_LANE_WIDTH_M,
                speed_limit_mps: None,
                successors,
                roadblock: None,
                has_traffic_light: false,
                stop_lines: vec![],
            });
        }
    }
    // Links to lanes outside the region are dropped.
    let kept: std::collections::HashSet<String> = specs.iter().map(|s| s.id.clone()).collect();
    for s in &mut specs {
        s.successors.retain(|t| kept.contains(t));
    }
    let mut rings = Vec::new();
    let da = mf.layer("drivable_area")?;
    for r in da.iter() {
        let r = r?;
        let toks: Vec<String> = r.get("polygon_tokens")?;
        for t in &toks {
            let p = mf.polygon(&r, "polygon_tokens", t)?;
            if p[0].len() >= 3 && overlaps(region, &p[0]) {
                rings.extend(p);
            }
        }
    }
    let mut crosswalks = Vec::new();
    if mf.json.contains_key("ped_crossing") {
        let pc = mf.layer("ped_crossing")?;
        for r in pc.iter() {
            let r = r?;
            let p = mf.polygon(&r, "polygon_token", r.str("polygon_token")?)?;
            if p[0].len() >= 3 && overlaps(region, &p[0]) {
                crosswalks.push(Crosswalk {
                    id: r.str("token")?.to_string(),
                    polygon: p[0].clone(),
                });
            }
        }
    }
    // Stop lines (their polygons as convex quadrilaterals, the map model's stop lines; not tied to lanes:
    // nuScenes has no traffic lights to stop for).
    let mut stop_lines = Vec::new();
    if mf.json.contains_key("stop_line") {
        let sl = mf.layer("stop_line")?;
        for r in sl.iter() {
            let r = r?;
            let p = mf.polygon(&r, "polygon_token", r.str("polygon_token")?)?;
            if p[0].len() >= 3 && overlaps(region, &p[0]) {
                if let Some(q) = quadrilateral(&p[0]) {
                    stop_lines.push(StopLine {
                        id: r.str("token")?.to_string(),
                        polygon: q,
                    });
                }
            }
        }
    }
    // Dividers: their `line` geometry (node tokens).
    let mut lines = Vec::new();
    for (layer, kind) in [
        ("road_divider", MapLineKind::RoadDivider),
        ("lane_divider", MapLineKind::LaneDivider),
    ] {
        if !mf.json.contains_key(layer) {
            continue;
        }
        let t = mf.layer(layer)?;
        if mf.line.is_none() {
            let v = mf.json.remove("line").ok_or_else(|| {
                anyhow!("map expansion {file}: layer `line` is missing (layer `{layer}` needs it)")
            })?;
            mf.line = Some(Table::from_value("line", &file, v)?);
        }
        for r in t.iter() {
            let r = r?;
            let pts = mf.line(&r, "line_token", r.str("line_token")?)?;
            if pts.len() >= 2 && overlaps(region, &pts) {
                lines.push(MapLine {
                    id: r.str("token")?.to_string(),
                    kind,
                    points: pts,
                });
            }
        }
    }
    let mut map = Map::build(
        location,
        specs,
        stop_lines,
        crosswalks,
        vec![],
        PolygonSet::new(rings),
        false,
    )
    .with_context(|| format!("map expansion {file}: building the map"))?;
    map.lines = lines;
    Ok(map)
}

/// A convex quadrilateral standing for a stop line polygon: its ring when it has 4 corners, else the rectangle
/// along its longest edge enclosing it; None for a ring without extent.
pub fn quadrilateral(ring: &[DVec2]) -> Option<[DVec2; 4]> {
    let mut r = ring.to_vec();
    if r.len() > 1 && r.first() == r.last() {
        r.pop();
    }
    if r.len() == 4 {
        return Some([r[0], r[1], r[2], r[3]]);
    }
    let n = r.len();
    let (i, _) = (0..n)
        .map(|i| (i, (r[(i + 1) % n] - r[i]).length()))
        .max_by(|a, b| a.1.total_cmp(&b.1))?;
    let u = (r[(i + 1) % n] - r[i]).normalize_or_zero();
    if u == DVec2::ZERO {
        return None;
    }
    let v = u.perp();
    let (mut a0, mut a1, mut b0, mut b1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for p in &r {
        let (a, b) = (p.dot(u), p.dot(v));
        (a0, a1, b0, b1) = (a0.min(a), a1.max(a), b0.min(b), b1.max(b));
    }
    let at = |a: f64, b: f64| u * a + v * b;
    Some([at(a0, b0), at(a1, b0), at(a1, b1), at(a0, b1)])
}
