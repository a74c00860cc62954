//! Bridge to the closed-loop score ([`crate::metrics`]): the simulator's [`Map`] behind the metrics'
//! [`MapQuery`] trait, and a [`ScenarioTrace`] built from a [`SimResult`].
//!
//! Ids: a lane's [`LaneId::id`] is its index in [`Map::lanes`] (unique across lanes and connectors), a
//! roadblock id is its index in [`Map::roadblocks`].
use super::closed_loop::SimResult;
use super::ego::EgoState;
use crate::metrics::{
    score_scenario, EgoDims, EgoStep, LaneId, LaneView, MapQuery, ObjectState as MObject,
    ScenarioScore, ScenarioTrace, ScoreParams,
};
use crate::scene::geometry::point_in_polygon;
use crate::scene::map::{LaneKind, Map};
use crate::scene::Scenario;
use glam::DVec2;

/// The scenario map as the metrics query it (successor/predecessor id lists precomputed).
pub struct MetricsMap<'a> {
    pub map: &'a Map,
    succ: Vec<Vec<LaneId>>,
    pred: Vec<Vec<LaneId>>,
}

fn lane_id(map: &Map, i: usize) -> LaneId {
    LaneId {
        id: i as u64,
        is_connector: map.lanes[i].kind == LaneKind::Connector,
    }
}

impl<'a> MetricsMap<'a> {
    pub fn new(map: &'a Map) -> Self {
        let succ = map
            .lanes
            .iter()
            .map(|l| l.successors.iter().map(|&j| lane_id(map, j)).collect())
            .collect();
        let pred = map
            .lanes
            .iter()
            .map(|l| l.predecessors.iter().map(|&j| lane_id(map, j)).collect())
            .collect();
        Self { map, succ, pred }
    }
}

/// Search radius for drivable-area distances (the metrics only compare against 0.3 m).
const DRIVABLE_SEARCH_M: f64 = 50.0;

impl MapQuery for MetricsMap<'_> {
    fn lanes_at(&self, p: DVec2, out: &mut Vec<LaneId>) {
        for i in self.map.lanes_at(p, None) {
            out.push(lane_id(self.map, i));
        }
    }
    fn lane(&self, id: LaneId) -> Option<LaneView<'_>> {
        let i = usize::try_from(id.id).ok()?;
        let l = self.map.lanes.get(i)?;
        if (l.kind == LaneKind::Connector) != id.is_connector {
            return None;
        }
        Some(LaneView {
            id,
            polygon: &l.polygon,
            baseline: &l.centre.points,
            speed_limit: l.speed_limit_mps,
            roadblock: l.roadblock as u64,
            successors: &self.succ[i],
            predecessors: &self.pred[i],
        })
    }
    fn in_drivable_area(&self, p: DVec2) -> bool {
        self.map.in_drivable_area(p)
    }
    fn distance_to_drivable_area(&self, p: DVec2) -> f64 {
        self.map.drivable_distance(p, DRIVABLE_SEARCH_M)
    }
    fn in_intersection(&self, p: DVec2) -> bool {
        self.map.is_in_intersection(p)
    }
    fn roadblock_contains(&self, roadblock: u64, is_connector: bool, p: DVec2) -> bool {
        let Some(rb) = usize::try_from(roadblock)
            .ok()
            .and_then(|r| self.map.roadblocks.get(r))
        else {
            return false;
        };
        rb.lanes.iter().any(|&i| {
            let l = &self.map.lanes[i];
            (l.kind == LaneKind::Connector) == is_connector && point_in_polygon(p, &l.polygon)
        })
    }
}

fn ego_step(e: &EgoState) -> EgoStep {
    EgoStep {
        time_s: e.time_s,
        position: e.rear_axle.pos(),
        heading: e.rear_axle.heading,
        velocity: DVec2::new(e.vx, e.vy),
        acceleration: DVec2::new(e.ax, e.ay),
        yaw_rate: e.yaw_rate,
        yaw_acceleration: e.yaw_accel,
    }
}

/// The metrics input for a run: simulated ego and objects per step, the logged expert over the same steps,
/// the route's roadblocks.
pub fn trace_of(sc: &Scenario, r: &SimResult) -> ScenarioTrace {
    let p = &sc.ego_params;
    let ego: Vec<EgoStep> = r.steps.iter().map(|s| ego_step(&s.ego)).collect();
    let objects = r
        .steps
        .iter()
        .map(|s| {
            s.agents
                .iter()
                .map(|a| MObject {
                    track_id: a.track as u64,
                    class: a.class,
                    center: a.bbox.center.pos(),
                    heading: a.bbox.center.heading,
                    length: a.bbox.length,
                    width: a.bbox.width,
                    velocity: if a.class.is_agent() {
                        a.velocity
                    } else {
                        DVec2::ZERO
                    },
                    is_agent: a.class.is_agent(),
                })
                .collect()
        })
        .collect();
    let n = r.steps.len().max(1);
    let mut expert: Vec<EgoStep> = (0..n.min(sc.len()))
        .map(|k| ego_step(&EgoState::from_log(&sc.ego, k, sc.dt)))
        .collect();
    // Yaw acceleration of the log by differences of the yaw rate.
    for k in 1..expert.len() {
        expert[k].yaw_acceleration = (expert[k].yaw_rate - expert[k - 1].yaw_rate) / sc.dt;
    }
    let route_roadblocks = sc
        .route
        .roadblock_ids
        .iter()
        .filter_map(|id| {
            sc.map
                .roadblocks
                .iter()
                .position(|rb| rb.id == *id)
                .map(|i| i as u64)
        })
        .collect();
    ScenarioTrace {
        name: sc.name.clone(),
        ego_dims: EgoDims::from_box(p.length, p.width, p.rear_axle_to_center, p.wheel_base),
        ego,
        objects,
        expert,
        route_roadblocks,
    }
}

/// Scores a run. A run that ended early (planner failure) still gets its metrics computed on the steps it
/// has (when there are enough), but its score is 0: a planner that crashes earns nothing.
pub fn score_run(
    sc: &Scenario,
    r: &SimResult,
    params: &ScoreParams,
) -> anyhow::Result<ScenarioScore> {
    sc.map.require_lanes(
        "the closed-loop score (drivable area, driving direction, route progress)",
    )?;
    let trace = trace_of(sc, r);
    let map = MetricsMap::new(&sc.map);
    let mut s = score_scenario(&map, &trace, params)?;
    if r.failure.is_some() {
        s.score = 0.0;
    }
    Ok(s)
}
