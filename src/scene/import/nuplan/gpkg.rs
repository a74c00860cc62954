//! nuPlan maps: `MAPS_ROOT/<location>/<map_version>/map.gpkg` (GeoPackage; layouts of motional/nuplan-devkit
//! common/maps/nuplan_map). Read: `lanes_polygons` (fid, geom, lane_group_fid, speed_limit_mps),
//! `baseline_paths` (geom, lane_fid | lane_connector_fid: the centre lines), `lane_connectors` (fid,
//! exit_lane_fid = predecessor, entry_lane_fid = successor, lane_group_connector_fid, speed_limit_mps,
//! traffic_light_stop_line_fids), `gen_lane_connectors_scaled_width_polygons` (connector outlines, optional),
//! `lane_groups_polygons` and `lane_group_connectors` (roadblocks: their outlines form the drivable area with
//! `carpark_areas` and `generic_drivable_areas` when present), `intersections`, `crosswalks`, `stop_polygons`
//! (optional). Only elements whose bounding box meets the region of interest are kept.
use super::db::{Db, Rec};
use super::wkb::open_ring;
use crate::scene::geometry::{Aabb, Polyline};
use crate::scene::index::PolygonSet;
use crate::scene::map::{Crosswalk, LaneKind, LaneSpec, Map, StopLine};
use anyhow::{anyhow, bail, Context, Result};
use glam::DVec2;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Width given to a connector without an outline (its centre line is buffered).
pub const DEFAULT_LANE_WIDTH_M: f64 = 3.5;

/// The GeoPackage of a location and map version.
pub fn map_path(maps_root: &Path, location: &str, version: &str) -> PathBuf {
    maps_root.join(location).join(version).join("map.gpkg")
}

fn overlaps(region: &Aabb, pts: &[DVec2]) -> bool {
    !pts.is_empty() && region.overlaps(&Aabb::from_points(pts))
}

fn fid(r: &Rec, col: &str) -> Result<Option<String>> {
    Ok(r.opt_i64(col)?.map(|v| v.to_string()))
}

/// Polygons (exterior + holes, open rings) of the rows of `layer` meeting `region`.
fn polygons(db: &Db, layer: &str, region: &Aabb, optional: bool) -> Result<Vec<Vec<DVec2>>> {
    if optional && !db.has_table(layer)? {
        return Ok(vec![]);
    }
    let mut rings = Vec::new();
    for r in db.select(layer, &["fid", "geom"], "", &[])? {
        for p in r.geometry("geom")?.polygons() {
            let ext = open_ring(p[0].clone());
            if ext.len() >= 3 && overlaps(region, &ext) {
                rings.extend(p.into_iter().map(open_ring).filter(|x| x.len() >= 3));
            }
        }
    }
    Ok(rings)
}

/// Loads the map elements meeting `region`.
pub fn load(path: &Path, name: &str, region: &Aabb) -> Result<Map> {
    let db = Db::open(path, "nuPlan map")?;
    let what = db.what.clone();
    db.require("gpkg_contents", &["table_name"])
        .context("not a GeoPackage")?;
    // Centre lines by lane / connector fid.
    let mut lane_line: HashMap<String, Vec<DVec2>> = HashMap::new();
    let mut conn_line: HashMap<String, Vec<DVec2>> = HashMap::new();
    for r in db.select(
        "baseline_paths",
        &["fid", "geom", "lane_fid", "lane_connector_fid"],
        "",
        &[],
    )? {
        let line = r.geometry("geom")?.lines().into_iter().next().ok_or_else(|| {
            anyhow!("{}: column `geom`: expected a LineString", r.at())
        })?;
        match (fid(&r, "lane_fid")?, fid(&r, "lane_connector_fid")?) {
            (Some(l), _) => lane_line.insert(l, line),
            (None, Some(c)) => conn_line.insert(c, line),
            (None, None) => bail!(
                "{}: neither `lane_fid` nor `lane_connector_fid` is set",
                r.at()
            ),
        };
    }
    let mut specs: Vec<LaneSpec> = Vec::new();
    let mut successors: HashMap<String, Vec<String>> = HashMap::new();
    // Connectors first: their exit lanes gain them as successors.
    let conns = db.select(
        "lane_connectors",
        &[
            "fid",
            "exit_lane_fid",
            "entry_lane_fid",
            "lane_group_connector_fid",
            "speed_limit_mps",
            "traffic_light_stop_line_fids",
        ],
        "",
        &[],
    )?;
    let mut conn_poly: HashMap<String, Vec<DVec2>> = HashMap::new();
    if db.has_table("gen_lane_connectors_scaled_width_polygons")? {
        for r in db.select(
            "gen_lane_connectors_scaled_width_polygons",
            &["fid", "geom", "lane_connector_fid"],
            "",
            &[],
        )? {
            if let (Some(c), Some(p)) = (
                fid(&r, "lane_connector_fid")?,
                r.geometry("geom")?.polygons().into_iter().next(),
            ) {
                conn_poly.insert(c, open_ring(p[0].clone()));
            }
        }
    }
    // Stop polygons (convex quadrilaterals only: the map model's stop lines).
    let mut stop_lines: Vec<StopLine> = Vec::new();
    let mut stop_idx: HashMap<String, usize> = HashMap::new();
    if db.has_table("stop_polygons")? {
        for r in db.select("stop_polygons", &["fid", "geom"], "", &[])? {
            let id = r.i64("fid")?.to_string();
            if let Some(p) = r.geometry("geom")?.polygons().into_iter().next() {
                let ring = open_ring(p[0].clone());
                if ring.len() == 4 && overlaps(region, &ring) {
                    stop_idx.insert(id.clone(), stop_lines.len());
                    stop_lines.push(StopLine {
                        id,
                        polygon: [ring[0], ring[1], ring[2], ring[3]],
                    });
                }
            }
        }
    }
    for r in &conns {
        let id = r.i64("fid")?.to_string();
        let exit = fid(r, "exit_lane_fid")?;
        let entry = fid(r, "entry_lane_fid")?;
        if let Some(e) = &exit {
            successors.entry(e.clone()).or_default().push(id.clone());
        }
        let Some(line) = conn_line.get(&id) else {
            continue;
        };
        if line.len() < 2 || !overlaps(region, line) {
            continue;
        }
        let lights: Vec<usize> = r
            .opt_text("traffic_light_stop_line_fids")?
            .unwrap_or("")
            .split(',')
            .filter_map(|s| stop_idx.get(s.trim()).copied())
            .collect();
        let has_light = !r
            .opt_text("traffic_light_stop_line_fids")?
            .unwrap_or("")
            .trim()
            .is_empty();
        specs.push(LaneSpec {
            id: id.clone(),
            kind: LaneKind::Connector,
            centre: Polyline::new(line.clone(), None),
            polygon: conn_poly.get(&id).filter(|p| p.len() >= 3).cloned(),
            width: DEFAULT_LANE_WIDTH_M,
            speed_limit_mps: r.opt_f64("speed_limit_mps")?,
            successors: entry.into_iter().collect(),
            roadblock: fid(r, "lane_group_connector_fid")?,
            has_traffic_light: has_light,
            stop_lines: lights,
        });
    }
    for r in db.select(
        "lanes_polygons",
        &["fid", "geom", "lane_group_fid", "speed_limit_mps"],
        "",
        &[],
    )? {
        let id = r.i64("fid")?.to_string();
        let Some(line) = lane_line.get(&id) else {
            continue;
        };
        if line.len() < 2 || !overlaps(region, line) {
            continue;
        }
        let poly = r
            .geometry("geom")?
            .polygons()
            .into_iter()
            .next()
            .map(|p| open_ring(p[0].clone()))
            .ok_or_else(|| anyhow!("{}: column `geom`: expected a Polygon", r.at()))?;
        specs.push(LaneSpec {
            id: id.clone(),
            kind: LaneKind::Lane,
            centre: Polyline::new(line.clone(), None),
            polygon: (poly.len() >= 3).then_some(poly),
            width: DEFAULT_LANE_WIDTH_M,
            speed_limit_mps: r.opt_f64("speed_limit_mps")?,
            successors: successors.remove(&id).unwrap_or_default(),
            roadblock: fid(&r, "lane_group_fid")?,
            has_traffic_light: false,
            stop_lines: vec![],
        });
    }
    // Links to lanes outside the region are dropped.
    let kept: std::collections::HashSet<String> = specs.iter().map(|s| s.id.clone()).collect();
    for s in &mut specs {
        s.successors.retain(|t| kept.contains(t));
    }
    let mut drivable = polygons(&db, "lane_groups_polygons", region, false)?;
    drivable.extend(polygons(&db, "lane_group_connectors", region, false)?);
    drivable.extend(polygons(&db, "carpark_areas", region, true)?);
    drivable.extend(polygons(&db, "generic_drivable_areas", region, true)?);
    let intersections = polygons(&db, "intersections", region, true)?;
    let mut crosswalks = Vec::new();
    if db.has_table("crosswalks")? {
        for r in db.select("crosswalks", &["fid", "geom"], "", &[])? {
            for p in r.geometry("geom")?.polygons() {
                let ring = open_ring(p[0].clone());
                if ring.len() >= 3 && overlaps(region, &ring) {
                    crosswalks.push(Crosswalk {
                        id: r.i64("fid")?.to_string(),
                        polygon: ring,
                    });
                }
            }
        }
    }
    Map::build(
        name,
        specs,
        stop_lines,
        crosswalks,
        intersections,
        PolygonSet::new(drivable),
        false,
    )
    .with_context(|| format!("{what}: building the map"))
}
