//! A small in-memory [`MapQuery`] implementation (linear scans over polygons), for tests and small synthetic
//! scenarios. Serde-serialisable so fixtures can carry their map.
use super::input::{LaneId, LaneView, MapQuery};
use crate::scene::geometry::{point_in_polygon, point_polygon_distance};
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// One lane or lane connector.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct VecLane {
    pub id: LaneId,
    pub polygon: Vec<DVec2>,
    pub baseline: Vec<DVec2>,
    #[serde(default)]
    pub speed_limit: Option<f64>,
    pub roadblock: u64,
    #[serde(default)]
    pub successors: Vec<LaneId>,
    #[serde(default)]
    pub predecessors: Vec<LaneId>,
}

/// A roadblock (lane group) or roadblock connector polygon.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct VecRoadblock {
    pub id: u64,
    pub is_connector: bool,
    pub polygon: Vec<DVec2>,
}

/// Map made of explicit polygons. Lanes are returned by [`MapQuery::lanes_at`] in insertion order.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct VecMap {
    pub lanes: Vec<VecLane>,
    #[serde(default)]
    pub roadblocks: Vec<VecRoadblock>,
    #[serde(default)]
    pub drivable_areas: Vec<Vec<DVec2>>,
    #[serde(default)]
    pub intersections: Vec<Vec<DVec2>>,
}

impl VecMap {
    /// Adds a straight lane (or connector) from `start` to `end` of the given width; its polygon is the
    /// rectangle around the centre line. Also adds the polygon to the drivable area, and a roadblock polygon
    /// equal to the lane polygon when that roadblock does not exist yet (extend it by hand for wider ones).
    pub fn add_straight_lane(
        &mut self,
        id: LaneId,
        roadblock: u64,
        start: DVec2,
        end: DVec2,
        width: f64,
        speed_limit: Option<f64>,
    ) {
        let d = (end - start).normalize_or_zero();
        let n = DVec2::new(-d.y, d.x) * (width / 2.0);
        let polygon = vec![start + n, start - n, end - n, end + n];
        self.drivable_areas.push(polygon.clone());
        if !self
            .roadblocks
            .iter()
            .any(|r| r.id == roadblock && r.is_connector == id.is_connector)
        {
            self.roadblocks.push(VecRoadblock {
                id: roadblock,
                is_connector: id.is_connector,
                polygon: polygon.clone(),
            });
        }
        self.lanes.push(VecLane {
            id,
            polygon,
            baseline: vec![start, end],
            speed_limit,
            roadblock,
            successors: Vec::new(),
            predecessors: Vec::new(),
        });
    }

    /// Links `from` -> `to` (successor / predecessor edges).
    pub fn connect(&mut self, from: LaneId, to: LaneId) {
        for l in &mut self.lanes {
            if l.id == from && !l.successors.contains(&to) {
                l.successors.push(to);
            }
            if l.id == to && !l.predecessors.contains(&from) {
                l.predecessors.push(from);
            }
        }
    }
}

impl MapQuery for VecMap {
    fn lanes_at(&self, p: DVec2, out: &mut Vec<LaneId>) {
        out.extend(
            self.lanes
                .iter()
                .filter(|l| point_in_polygon(p, &l.polygon))
                .map(|l| l.id),
        );
    }

    fn lane(&self, id: LaneId) -> Option<LaneView<'_>> {
        self.lanes.iter().find(|l| l.id == id).map(|l| LaneView {
            id: l.id,
            polygon: &l.polygon,
            baseline: &l.baseline,
            speed_limit: l.speed_limit,
            roadblock: l.roadblock,
            successors: &l.successors,
            predecessors: &l.predecessors,
        })
    }

    fn in_drivable_area(&self, p: DVec2) -> bool {
        self.drivable_areas.iter().any(|a| point_in_polygon(p, a))
    }

    fn distance_to_drivable_area(&self, p: DVec2) -> f64 {
        self.drivable_areas
            .iter()
            .map(|a| point_polygon_distance(p, a))
            .fold(f64::INFINITY, f64::min)
    }

    fn in_intersection(&self, p: DVec2) -> bool {
        self.intersections.iter().any(|a| point_in_polygon(p, a))
    }

    fn roadblock_contains(&self, roadblock: u64, is_connector: bool, p: DVec2) -> bool {
        self.roadblocks.iter().any(|r| {
            r.id == roadblock && r.is_connector == is_connector && point_in_polygon(p, &r.polygon)
        })
    }
}
