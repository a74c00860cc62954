//! The map: lanes and lane connectors (centre lines, polygons, speed limits, successor/predecessor links),
//! roadblocks (groups of parallel lanes, the unit of a route), stop lines, crosswalks, intersections and the
//! drivable area. Every point/area query goes through a [`BoxIndex`]; nothing scans all elements per query.
use super::geometry::{angle_diff, point_in_polygon, point_polygon_distance, Aabb, Polyline};
use super::index::{BoxIndex, PolygonSet};
use glam::DVec2;
use std::collections::HashMap;

/// Lane (a road lane) or connector (a path through an intersection).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum LaneKind {
    Lane,
    Connector,
}

#[derive(Clone, Debug)]
pub struct Lane {
    pub id: String,
    pub kind: LaneKind,
    /// Centre line in driving direction.
    pub centre: Polyline,
    /// Surface outline (closed ring, not repeated).
    pub polygon: Vec<DVec2>,
    pub speed_limit_mps: Option<f64>,
    pub successors: Vec<usize>,
    pub predecessors: Vec<usize>,
    /// Index into [`Map::roadblocks`].
    pub roadblock: usize,
    /// Connectors controlled by a traffic light (nuPlan `has_traffic_lights`).
    pub has_traffic_light: bool,
    /// Indices into [`Map::stop_lines`] guarding the entry of this connector.
    pub stop_lines: Vec<usize>,
    pub aabb: Aabb,
}

/// A group of parallel lanes (nuPlan lane group) or of connectors; the unit of a route.
#[derive(Clone, Debug)]
pub struct Roadblock {
    pub id: String,
    pub lanes: Vec<usize>,
}

#[derive(Clone, Debug)]
pub struct StopLine {
    pub id: String,
    /// Convex quadrilateral.
    pub polygon: [DVec2; 4],
}

#[derive(Clone, Debug)]
pub struct Crosswalk {
    pub id: String,
    pub polygon: Vec<DVec2>,
}

/// Which painted line a [`MapLine`] is (nuScenes map expansion `road_divider` / `lane_divider`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum MapLineKind {
    /// Divides the two directions of a road.
    RoadDivider,
    /// Divides lanes of one direction.
    LaneDivider,
}

/// A painted line read from a source map that has them (nuScenes dividers). Layout masks draw them as the
/// map's dividers (`projection::scene::map_layer`); maps without them get dividers derived from lane geometry
/// (`scene::roadlines`), and road edges are derived for every source.
#[derive(Clone, Debug)]
pub struct MapLine {
    pub id: String,
    pub kind: MapLineKind,
    pub points: Vec<DVec2>,
}

/// Input description of a lane for [`Map::build`].
#[derive(Clone, Debug)]
pub struct LaneSpec {
    pub id: String,
    pub kind: LaneKind,
    pub centre: Polyline,
    /// Outline; when None the centre line is buffered by `width / 2`.
    pub polygon: Option<Vec<DVec2>>,
    pub width: f64,
    pub speed_limit_mps: Option<f64>,
    /// Explicit links by lane id (ignored when links are inferred).
    pub successors: Vec<String>,
    /// Roadblock id; lanes without one get a roadblock of their own (named after the lane).
    pub roadblock: Option<String>,
    pub has_traffic_light: bool,
    pub stop_lines: Vec<usize>,
}

#[derive(Clone, Debug)]
pub struct Map {
    pub name: String,
    pub lanes: Vec<Lane>,
    pub roadblocks: Vec<Roadblock>,
    pub stop_lines: Vec<StopLine>,
    pub crosswalks: Vec<Crosswalk>,
    /// Intersection outlines (empty for sources without them: then "in an intersection" means "on a connector").
    pub intersections: Vec<Vec<DVec2>>,
    /// The drivable area; when empty the union of lane polygons is used.
    pub drivable: PolygonSet,
    /// Painted lines of sources that have them (empty otherwise; set after [`Map::build`]).
    pub lines: Vec<MapLine>,
    /// Why the map holds no lanes when its source has none to give: Some(the missing file and where it was looked
    /// for), e.g. a nuScenes scene without the map expansion pack ([`Map::without_lanes`]). What needs lanes
    /// (IDM agents, routes, the closed-loop score) refuses such a map with this text ([`Map::require_lanes`]).
    pub missing: Option<String>,
    lane_by_id: HashMap<String, usize>,
    lane_tree: BoxIndex,
    intersection_tree: BoxIndex,
}

/// Tolerances of lane-link inference: end of one lane within 1 m of the start of the next, headings within 30 deg.
pub const LINK_MAX_GAP_M: f64 = 1.0;
pub const LINK_MAX_HEADING_RAD: f64 = 30.0 * std::f64::consts::PI / 180.0;

/// Buffers a centre line into a lane outline: left offsets forward, right offsets backward.
pub fn buffer_centre_line(c: &Polyline, half_width: f64) -> Vec<DVec2> {
    let n = c.points.len();
    let mut left = Vec::with_capacity(n);
    let mut right = Vec::with_capacity(n);
    for i in 0..n {
        // Normal from the average of adjacent segment directions (the vertex heading).
        let d = if n == 1 {
            DVec2::new(c.headings[0].cos(), c.headings[0].sin())
        } else {
            let a = if i > 0 {
                (c.points[i] - c.points[i - 1]).normalize_or_zero()
            } else {
                DVec2::ZERO
            };
            let b = if i + 1 < n {
                (c.points[i + 1] - c.points[i]).normalize_or_zero()
            } else {
                DVec2::ZERO
            };
            (a + b).normalize_or(DVec2::X)
        };
        let nrm = d.perp() * half_width;
        left.push(c.points[i] + nrm);
        right.push(c.points[i] - nrm);
    }
    right.reverse();
    left.extend(right);
    left
}

impl Map {
    /// Builds a map and its indices. With `infer_links` the successor/predecessor links are inferred from
    /// geometry ([`LINK_MAX_GAP_M`], [`LINK_MAX_HEADING_RAD`]) instead of taken from the specs.
    pub fn build(
        name: &str,
        specs: Vec<LaneSpec>,
        stop_lines: Vec<StopLine>,
        crosswalks: Vec<Crosswalk>,
        intersections: Vec<Vec<DVec2>>,
        drivable: PolygonSet,
        infer_links: bool,
    ) -> anyhow::Result<Map> {
        let mut lane_by_id = HashMap::new();
        let mut roadblocks: Vec<Roadblock> = Vec::new();
        let mut rb_by_id: HashMap<String, usize> = HashMap::new();
        let mut lanes = Vec::with_capacity(specs.len());
        for (i, s) in specs.iter().enumerate() {
            anyhow::ensure!(
                s.centre.points.len() >= 2,
                "lane {}: centre line needs at least 2 distinct points",
                s.id
            );
            anyhow::ensure!(
                lane_by_id.insert(s.id.clone(), i).is_none(),
                "duplicate lane id {}",
                s.id
            );
            let rb_name = s.roadblock.clone().unwrap_or_else(|| s.id.clone());
            let rb = *rb_by_id.entry(rb_name.clone()).or_insert_with(|| {
                roadblocks.push(Roadblock {
                    id: rb_name.clone(),
                    lanes: vec![],
                });
                roadblocks.len() - 1
            });
            roadblocks[rb].lanes.push(i);
            let polygon = match &s.polygon {
                Some(p) if p.len() >= 3 => p.clone(),
                _ => buffer_centre_line(&s.centre, s.width / 2.0),
            };
            let mut aabb = Aabb::from_points(&polygon);
            aabb = aabb.union(&Aabb::from_points(&s.centre.points));
            lanes.push(Lane {
                id: s.id.clone(),
                kind: s.kind,
                centre: s.centre.clone(),
                polygon,
                speed_limit_mps: s.speed_limit_mps,
                successors: vec![],
                predecessors: vec![],
                roadblock: rb,
                has_traffic_light: s.has_traffic_light,
                stop_lines: s.stop_lines.clone(),
                aabb,
            });
        }
        let lane_tree = BoxIndex::new(lanes.iter().map(|l| l.aabb));
        if infer_links {
            let links = infer_lane_links(&lanes);
            for (a, b) in links {
                lanes[a].successors.push(b);
                lanes[b].predecessors.push(a);
            }
        } else {
            for (i, s) in specs.iter().enumerate() {
                for succ in &s.successors {
                    let j = *lane_by_id.get(succ).ok_or_else(|| {
                        anyhow::anyhow!("lane {}: unknown successor {succ}", s.id)
                    })?;
                    lanes[i].successors.push(j);
                    lanes[j].predecessors.push(i);
                }
            }
        }
        let intersection_tree = BoxIndex::new(intersections.iter().map(|p| Aabb::from_points(p)));
        Ok(Map {
            name: name.to_string(),
            lanes,
            roadblocks,
            stop_lines,
            crosswalks,
            intersections,
            drivable,
            lines: vec![],
            missing: None,
            lane_by_id,
            lane_tree,
            intersection_tree,
        })
    }

    /// A map with no lanes, crosswalks or drivable area, and the reason (`missing`: what file is missing and
    /// where it was looked for).
    pub fn without_lanes(name: &str, missing: String) -> Map {
        let mut m = Map::build(
            name,
            vec![],
            vec![],
            vec![],
            vec![],
            PolygonSet::default(),
            false,
        )
        .expect("an empty map always builds");
        m.missing = Some(missing);
        m
    }

    /// `Err` naming the missing map file when the map is one of [`Map::without_lanes`]; `what` says what needs
    /// the lanes.
    pub fn require_lanes(&self, what: &str) -> anyhow::Result<()> {
        match &self.missing {
            Some(m) => anyhow::bail!("{what} needs lanes, and this scenario has none: {m}"),
            None => Ok(()),
        }
    }

    pub fn lane_index(&self, id: &str) -> Option<usize> {
        self.lane_by_id.get(id).copied()
    }

    /// Lanes and/or connectors whose polygon contains p, in index order.
    pub fn lanes_at(&self, p: DVec2, kind: Option<LaneKind>) -> Vec<usize> {
        let mut out = Vec::new();
        self.for_lanes_at(p, kind, |i| out.push(i));
        out.sort_unstable();
        out
    }

    /// Like [`Map::lanes_at`] without allocating (callback order is unspecified).
    pub fn for_lanes_at(&self, p: DVec2, kind: Option<LaneKind>, mut f: impl FnMut(usize)) {
        self.lane_tree.query_point(p, |i| {
            let l = &self.lanes[i as usize];
            if kind.is_none_or(|k| k == l.kind) && point_in_polygon(p, &l.polygon) {
                f(i as usize)
            }
        });
    }

    /// Lanes whose bounding box overlaps `q`.
    pub fn lanes_in(&self, q: &Aabb, f: impl FnMut(u32)) {
        self.lane_tree.query(q, f)
    }

    /// nuPlan `is_in_layer(point, INTERSECTION)`; without intersection outlines: on any connector.
    pub fn is_in_intersection(&self, p: DVec2) -> bool {
        if self.intersections.is_empty() {
            let mut hit = false;
            self.for_lanes_at(p, Some(LaneKind::Connector), |_| hit = true);
            return hit;
        }
        let mut hit = false;
        self.intersection_tree.query_point(p, |i| {
            hit |= point_in_polygon(p, &self.intersections[i as usize])
        });
        hit
    }

    /// Whether p lies in the drivable area (or, without one, on any lane/connector).
    pub fn in_drivable_area(&self, p: DVec2) -> bool {
        if self.drivable.is_empty() {
            let mut hit = false;
            self.for_lanes_at(p, None, |_| hit = true);
            hit
        } else {
            self.drivable.contains(p)
        }
    }

    /// Distance from p to the drivable area (0 inside), searched up to `max_dist` (INFINITY beyond).
    pub fn drivable_distance(&self, p: DVec2, max_dist: f64) -> f64 {
        if !self.drivable.is_empty() {
            return self.drivable.distance(p, max_dist);
        }
        let mut d = f64::INFINITY;
        let q = Aabb {
            min: p - DVec2::splat(max_dist),
            max: p + DVec2::splat(max_dist),
        };
        self.lane_tree.query(&q, |i| {
            d = d.min(point_polygon_distance(p, &self.lanes[i as usize].polygon))
        });
        if d <= max_dist {
            d
        } else {
            f64::INFINITY
        }
    }

    /// The lane/connector best matching a pose: among those containing the point, the smallest wrapped
    /// heading difference; else the nearest centre line within `max_dist` with a heading within 90 deg.
    pub fn match_lane(&self, p: DVec2, heading: f64, max_dist: f64) -> Option<usize> {
        let mut best: Option<(f64, usize)> = None;
        self.for_lanes_at(p, None, |i| {
            let (s, _) = self.lanes[i].centre.project(p);
            let dh = angle_diff(self.lanes[i].centre.pose_at(s).heading, heading).abs();
            if best.is_none_or(|(b, bi)| dh < b || (dh == b && i < bi)) {
                best = Some((dh, i));
            }
        });
        if let Some((dh, i)) = best {
            if dh < std::f64::consts::FRAC_PI_2 {
                return Some(i);
            }
        }
        let mut best: Option<(f64, usize)> = None;
        let q = Aabb {
            min: p - DVec2::splat(max_dist),
            max: p + DVec2::splat(max_dist),
        };
        self.lane_tree.query(&q, |i| {
            let i = i as usize;
            let (s, d) = self.lanes[i].centre.project(p);
            let dh = angle_diff(self.lanes[i].centre.pose_at(s).heading, heading).abs();
            if d <= max_dist && dh < std::f64::consts::FRAC_PI_2 {
                let cost = d + 2.0 * dh;
                if best.is_none_or(|(b, bi)| cost < b || (cost == b && i < bi)) {
                    best = Some((cost, i));
                }
            }
        });
        best.map(|b| b.1)
    }

    /// Map bounding box (lanes only).
    pub fn bounds(&self) -> Aabb {
        self.lanes.iter().fold(Aabb::EMPTY, |a, l| a.union(&l.aabb))
    }
}

/// Infers successor links: lane a -> b when b starts within [`LINK_MAX_GAP_M`] of a's end and the headings
/// there differ by at most [`LINK_MAX_HEADING_RAD`]. Uses an R-tree over start points. Returns (a, b) pairs sorted.
pub fn infer_lane_links(lanes: &[Lane]) -> Vec<(usize, usize)> {
    let starts = BoxIndex::new(lanes.iter().map(|l| {
        let p = l.centre.first();
        Aabb { min: p, max: p }
    }));
    let mut out = Vec::new();
    for (a, la) in lanes.iter().enumerate() {
        let end = la.centre.last();
        let h_end = *la.centre.headings.last().unwrap_or(&0.0);
        let q = Aabb {
            min: end - DVec2::splat(LINK_MAX_GAP_M),
            max: end + DVec2::splat(LINK_MAX_GAP_M),
        };
        starts.query(&q, |b| {
            let b = b as usize;
            if b == a {
                return;
            }
            let lb = &lanes[b];
            if (lb.centre.first() - end).length() <= LINK_MAX_GAP_M
                && angle_diff(lb.centre.headings[0], h_end).abs() <= LINK_MAX_HEADING_RAD
            {
                out.push((a, b));
            }
        });
    }
    out.sort_unstable();
    out
}
