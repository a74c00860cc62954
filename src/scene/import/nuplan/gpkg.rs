//! nuPlan maps: the GeoPackage `MAPS_ROOT/<map name>/<version>/map.gpkg` found by [`super::maps_db`] (layouts of
//! motional/nuplan-devkit common/maps/nuplan_map). Read: `lanes_polygons` (fid, geom, lane_group_fid, speed_limit_mps),
//! `baseline_paths` (geom, lane_fid | lane_connector_fid: the centre lines), `lane_connectors` (fid,
//! exit_lane_fid = predecessor, entry_lane_fid = successor, lane_group_connector_fid, speed_limit_mps,
//! traffic_light_stop_line_fids), `gen_lane_connectors_scaled_width_polygons` (connector outlines, optional),
//! `lane_groups_polygons` and `lane_group_connectors` (roadblocks: their outlines form the drivable area with
//! `carpark_areas` and `generic_drivable_areas` when present), `intersections`, `crosswalks`, `stop_polygons`
//! (optional). Only elements whose bounding box meets the region of interest are kept.
//!
//! Coordinates: a layer whose SRS (`gpkg_geometry_columns.srs_id` -> `gpkg_spatial_ref_sys`) is EPSG:4326 is
//! projected into the UTM zone named by the `meta` layer's `projectedCoordSystem` (`epsg:326NN` or a PROJ
//! `+proj=utm +zone=NN` string), as the devkit's `to_crs(projectedCoordSystem)`; a layer already in that zone (or
//! in an undefined SRS) is used as stored; another projected SRS is an error. The geometry column is the one
//! `gpkg_geometry_columns` names (`geom` without it).
use super::db::{Db, Rec};
use super::utm::{self, Zone};
use super::wkb::{open_ring, Geometry};
use crate::scene::geometry::{Aabb, Polyline};
use crate::scene::import::bounds;
use crate::scene::index::PolygonSet;
use crate::scene::map::{Crosswalk, LaneKind, LaneSpec, Map, StopLine};
use anyhow::{anyhow, bail, Context, Result};
use glam::DVec2;
use std::cell::RefCell;
use std::collections::HashMap;
use std::path::Path;

/// Width given to a connector without an outline (its centre line is buffered).
pub const DEFAULT_LANE_WIDTH_M: f64 = 3.5;

fn overlaps(region: &Aabb, pts: &[DVec2]) -> bool {
    !pts.is_empty() && region.overlaps(&Aabb::from_points(pts))
}

fn fid(r: &Rec, col: &str) -> Result<Option<String>> {
    r.opt_id(col)
}

/// Column `speed_limit_mps`: NULL, or a speed in 0..=[`bounds::MAX_SPEED_MPS`].
fn speed_limit(r: &Rec) -> Result<Option<f64>> {
    let v = r.opt_f64("speed_limit_mps")?;
    if let Some(x) = v {
        if !(0.0..=bounds::MAX_SPEED_MPS).contains(&x) {
            bail!(
                "{}: column `speed_limit_mps`: {x} m/s is not in 0..={} m/s",
                r.at(),
                bounds::MAX_SPEED_MPS
            );
        }
    }
    Ok(v)
}

/// The coordinate systems of the map: the UTM zone of the `meta` layer's `projectedCoordSystem` and, per layer,
/// its geometry column and whether it is stored in longitude / latitude (then projected into the zone, as the
/// devkit's `to_crs`).
struct Geo<'a> {
    db: &'a Db,
    zone: Option<Zone>,
    meta_crs: Option<String>,
    layers: RefCell<HashMap<String, (String, bool)>>,
}

impl<'a> Geo<'a> {
    fn new(db: &'a Db) -> Result<Geo<'a>> {
        let mut meta_crs = None;
        if db.has_table("meta")? {
            for r in db.select("meta", &["key", "value"], "", &[])? {
                if r.opt_text("key")? == Some("projectedCoordSystem") {
                    meta_crs = r.opt_text("value")?.map(str::to_string);
                }
            }
        }
        Ok(Geo {
            db,
            zone: meta_crs.as_deref().and_then(Zone::parse),
            meta_crs,
            layers: RefCell::new(HashMap::new()),
        })
    }

    /// (geometry column, stored in longitude / latitude) of `layer`.
    fn layer(&self, layer: &str) -> Result<(String, bool)> {
        if let Some(v) = self.layers.borrow().get(layer) {
            return Ok(v.clone());
        }
        let mut col = "geom".to_string();
        let mut lonlat = false;
        if self.db.has_table("gpkg_geometry_columns")? {
            let rows = self.db.select(
                "gpkg_geometry_columns",
                &["table_name", "column_name", "srs_id"],
                "WHERE table_name = ?1",
                &[&layer as &dyn rusqlite::ToSql],
            )?;
            if let Some(r) = rows.first() {
                col = r.text("column_name")?.to_string();
                let srs = r.i64("srs_id")?;
                let mut def = String::new();
                let mut code = srs;
                if self.db.has_table("gpkg_spatial_ref_sys")? {
                    for s in self.db.select(
                        "gpkg_spatial_ref_sys",
                        &[
                            "srs_id",
                            "organization",
                            "organization_coordsys_id",
                            "definition",
                        ],
                        "WHERE srs_id = ?1",
                        &[&srs as &dyn rusqlite::ToSql],
                    )? {
                        if s.opt_text("organization")?
                            .is_some_and(|o| o.eq_ignore_ascii_case("epsg"))
                        {
                            code = s.i64("organization_coordsys_id")?;
                        }
                        def = s.opt_text("definition")?.unwrap_or("").to_ascii_uppercase();
                    }
                }
                lonlat = code == 4326 || def.starts_with("GEOGCS") || def.starts_with("GEOGCRS");
                let projected_other = !lonlat
                    && code > 0
                    && self.zone.is_some_and(|z| z.epsg() as i64 != code)
                    && Zone::parse(&format!("epsg:{code}")).is_some();
                if projected_other {
                    bail!(
                        "{}: layer `{layer}` is in EPSG:{code}, the meta layer's projectedCoordSystem is {:?}: \
                         only longitude / latitude or the meta zone itself are supported",
                        self.db.what,
                        self.meta_crs
                    );
                }
                if lonlat && self.zone.is_none() {
                    bail!(
                        "{}: layer `{layer}` is in longitude / latitude but the `meta` layer names no UTM \
                         projectedCoordSystem (found {:?})",
                        self.db.what,
                        self.meta_crs
                    );
                }
            }
        }
        self.layers
            .borrow_mut()
            .insert(layer.to_string(), (col.clone(), lonlat));
        Ok((col, lonlat))
    }

    /// The geometry of row `r` (selected with the layer's geometry column), in UTM metres.
    fn geom(&self, r: &Rec, col: &str) -> Result<Geometry> {
        let g = r.geometry(col)?;
        let (_, lonlat) = self.layer(&r.table)?;
        let g = match (lonlat, self.zone) {
            (true, Some(z)) => g
                .try_map(&|p| utm::project(&z, p))
                .map_err(|e| anyhow!("{}: column `{col}`: {e}", r.at()))?,
            _ => g,
        };
        // Every point within the bounds of every importer (issue #18).
        g.try_map(&|p| {
            if bounds::coord_ok(p.x) && bounds::coord_ok(p.y) {
                Ok(p)
            } else {
                bail!(
                    "point ({}, {}) is not finite or lies beyond {:e} m of the map origin",
                    p.x,
                    p.y,
                    bounds::MAX_COORD_M
                )
            }
        })
        .map_err(|e| anyhow!("{}: column `{col}`: {e}", r.at()))
    }
}

/// Polygons (exterior + holes, open rings) of the rows of `layer` meeting `region`.
fn polygons(geo: &Geo, layer: &str, region: &Aabb, optional: bool) -> Result<Vec<Vec<DVec2>>> {
    if optional && !geo.db.has_table(layer)? {
        return Ok(vec![]);
    }
    let gc = geo.layer(layer)?.0;
    let mut rings = Vec::new();
    for r in geo.db.select(layer, &["fid", &gc], "", &[])? {
        for p in geo.geom(&r, &gc)?.polygons() {
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
    let geo = Geo::new(&db)?;
    // Centre lines by lane / connector fid.
    let mut lane_line: HashMap<String, Vec<DVec2>> = HashMap::new();
    let mut conn_line: HashMap<String, Vec<DVec2>> = HashMap::new();
    let gc = geo.layer("baseline_paths")?.0;
    for r in db.select(
        "baseline_paths",
        &["fid", &gc, "lane_fid", "lane_connector_fid"],
        "",
        &[],
    )? {
        let line = geo
            .geom(&r, &gc)?
            .lines()
            .into_iter()
            .next()
            .ok_or_else(|| anyhow!("{}: column `{gc}`: expected a LineString", r.at()))?;
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
        let gc = geo.layer("gen_lane_connectors_scaled_width_polygons")?.0;
        for r in db.select(
            "gen_lane_connectors_scaled_width_polygons",
            &["fid", &gc, "lane_connector_fid"],
            "",
            &[],
        )? {
            if let (Some(c), Some(p)) = (
                fid(&r, "lane_connector_fid")?,
                geo.geom(&r, &gc)?.polygons().into_iter().next(),
            ) {
                conn_poly.insert(c, open_ring(p[0].clone()));
            }
        }
    }
    // Stop polygons (convex quadrilaterals only: the map model's stop lines).
    let mut stop_lines: Vec<StopLine> = Vec::new();
    let mut stop_idx: HashMap<String, usize> = HashMap::new();
    if db.has_table("stop_polygons")? {
        let gc = geo.layer("stop_polygons")?.0;
        for r in db.select("stop_polygons", &["fid", &gc], "", &[])? {
            let id = r.i64("fid")?.to_string();
            if let Some(p) = geo.geom(&r, &gc)?.polygons().into_iter().next() {
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
            speed_limit_mps: speed_limit(r)?,
            successors: entry.into_iter().collect(),
            roadblock: fid(r, "lane_group_connector_fid")?,
            has_traffic_light: has_light,
            stop_lines: lights,
        });
    }
    let gc = geo.layer("lanes_polygons")?.0;
    for r in db.select(
        "lanes_polygons",
        &["fid", &gc, "lane_group_fid", "speed_limit_mps"],
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
        let poly = geo
            .geom(&r, &gc)?
            .polygons()
            .into_iter()
            .next()
            .map(|p| open_ring(p[0].clone()))
            .ok_or_else(|| anyhow!("{}: column `{gc}`: expected a Polygon", r.at()))?;
        specs.push(LaneSpec {
            id: id.clone(),
            kind: LaneKind::Lane,
            centre: Polyline::new(line.clone(), None),
            polygon: (poly.len() >= 3).then_some(poly),
            width: DEFAULT_LANE_WIDTH_M,
            speed_limit_mps: speed_limit(&r)?,
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
    let mut drivable = polygons(&geo, "lane_groups_polygons", region, false)?;
    drivable.extend(polygons(&geo, "lane_group_connectors", region, false)?);
    drivable.extend(polygons(&geo, "carpark_areas", region, true)?);
    drivable.extend(polygons(&geo, "generic_drivable_areas", region, true)?);
    let intersections = polygons(&geo, "intersections", region, true)?;
    let mut crosswalks = Vec::new();
    if db.has_table("crosswalks")? {
        let gc = geo.layer("crosswalks")?.0;
        for r in db.select("crosswalks", &["fid", &gc], "", &[])? {
            for p in geo.geom(&r, &gc)?.polygons() {
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
