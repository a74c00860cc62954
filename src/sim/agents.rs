//! The IDM agent manager [simulation/observation/idm/idm_agent_manager.py, idm_agents_builder.py]: builds
//! agents on map rails from the VEHICLE tracks of step 0, and each step picks every agent's leader through
//! an occupancy map (ego footprint, open-loop objects, agents' geometries, red-light stop lines) and moves
//! it one IDM step. Agents are updated in order; later agents see earlier agents' new geometry.
use super::idm::{idm_step, lane_states, IdmAgent, IdmParams, IdmPath, Lead};
use crate::scene::geometry::{Aabb, OrientedBox, Part, PathBuffer, Pose2, Shape};
use crate::scene::map::{LaneKind, Map};
use crate::scene::{ObjectClass, Scenario, TrafficLightStatus};
use glam::DVec2;
use std::collections::VecDeque;

/// What an agent follows in one step.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(tag = "kind", content = "index", rename_all = "snake_case")]
pub enum LeaderRef {
    Ego,
    /// Index into the manager's agents.
    Agent(usize),
    /// Index of the replayed track in the scenario.
    Object(usize),
    /// Index into the map's stop lines.
    StopLine(usize),
}

/// The ego as the agents see it.
#[derive(Clone, Copy, Debug)]
pub struct EgoObservation {
    pub footprint: OrientedBox,
    pub rear_axle_heading: f64,
    /// |rear-axle velocity|.
    pub speed: f64,
}

/// Occupancy map entry kinds, in the order they are scanned.
#[derive(Default)]
struct Occupancy {
    ego: Option<Shape>,
    objects: Vec<(usize, Shape)>,
    agents: Vec<Option<Shape>>,
    stop_lines: Vec<(usize, Shape)>,
}

/// An occupancy entry by position in [`Occupancy`]'s lists.
#[derive(Clone, Copy, Debug)]
enum Entry {
    Ego,
    Agent(usize),
    Object(usize),
    StopLine(usize),
}

impl Occupancy {
    /// The geometry of an entry (entries are looked up right after being listed, so they exist).
    fn shape(&self, r: Entry) -> &Shape {
        static EMPTY: Shape = Shape {
            parts: Vec::new(),
            boxes: Vec::new(),
            chunks: Vec::new(),
            aabb: None,
        };
        match r {
            Entry::Ego => self.ego.as_ref().unwrap_or(&EMPTY),
            Entry::Agent(j) => self.agents[j].as_ref().unwrap_or(&EMPTY),
            Entry::Object(k) => &self.objects[k].1,
            Entry::StopLine(k) => &self.stop_lines[k].1,
        }
    }
    fn leader_ref(&self, r: Entry) -> LeaderRef {
        match r {
            Entry::Ego => LeaderRef::Ego,
            Entry::Agent(j) => LeaderRef::Agent(j),
            Entry::Object(k) => LeaderRef::Object(self.objects[k].0),
            Entry::StopLine(k) => LeaderRef::StopLine(self.stop_lines[k].0),
        }
    }
}

pub struct IdmManager {
    pub params: IdmParams,
    /// None once removed (farther than the radius from the ego).
    pub agents: Vec<Option<IdmAgent>>,
    /// Leader chosen at the last step, per agent.
    pub leaders: Vec<Option<LeaderRef>>,
    occ: Occupancy,
    lights: Vec<Option<TrafficLightStatus>>,
    scratch_poses: Vec<Pose2>,
    scratch_pts: Vec<DVec2>,
    path_shape: PathBuffer,
    /// (bounding-box distance lower bound, scan order, entry) of the current agent's candidates.
    cands: Vec<(f64, usize, Entry)>,
}

/// `get_starting_segment`: lanes containing the centre, else (when in an intersection) connectors containing
/// it; the one with the smallest |nearest-pose heading - agent heading| (NOT wrapped: quirk), with the
/// progress of the nearest point.
pub fn starting_segment(map: &Map, center: &Pose2) -> Option<(usize, f64)> {
    let p = center.pos();
    let mut segs = map.lanes_at(p, Some(LaneKind::Lane));
    if segs.is_empty() {
        if !map.is_in_intersection(p) {
            return None;
        }
        segs = map.lanes_at(p, Some(LaneKind::Connector));
    }
    let mut best: Option<(f64, usize, f64)> = None;
    for i in segs {
        let (s, _) = map.lanes[i].centre.project(p);
        let dh = (map.lanes[i].centre.pose_at(s).heading - center.heading).abs();
        if best.is_none_or(|(b, _, _)| dh < b) {
            best = Some((dh, i, s));
        }
    }
    best.map(|(_, i, s)| (i, s))
}

impl IdmManager {
    /// `build_idm_agents_on_map_rails`: every VEHICLE track valid at step 0 becomes an agent unless it is off
    /// the lanes or its snapped box overlaps the ego, an open-loop object or an earlier agent. Initial speed
    /// |velocity| (the ego's speed when NaN); target speed the lane's limit when known.
    pub fn build(
        sc: &Scenario,
        ego_box: Option<&OrientedBox>,
        ego_speed: f64,
        params: IdmParams,
    ) -> IdmManager {
        let mut init: Vec<Shape> = Vec::new();
        for tr in &sc.tracks {
            if tr.class.replayed_in_reactive_mode() {
                if let Some(b) = tr.box_at(0) {
                    init.push(Shape::from_box(&b));
                }
            }
        }
        if let Some(b) = ego_box {
            init.push(Shape::from_box(b));
        }
        let mut agents = Vec::new();
        for (ti, tr) in sc.tracks.iter().enumerate() {
            if tr.class != ObjectClass::Vehicle {
                continue;
            }
            let Some(st) = tr.states.first().copied().flatten() else {
                continue;
            };
            let Some((lane, progress)) = starting_segment(&sc.map, &st.pose) else {
                continue;
            };
            let snapped = sc.map.lanes[lane].centre.pose_at(progress);
            let b = OrientedBox::new(snapped, tr.length, tr.width);
            let shape = Shape::from_box(&b);
            if init.iter().any(|s| s.intersects(&shape)) {
                continue;
            }
            // A lane too short for a path (fewer than 2 states after the dropped last one) cannot carry an
            // agent; checked before the box is registered.
            let Some(path) = IdmPath::from_states(&lane_states(&sc.map, lane)) else {
                continue;
            };
            init.push(shape);
            let v = st.velocity;
            let velocity = if v.x.is_nan() || v.y.is_nan() {
                ego_speed
            } else {
                v.length()
            };
            let target_velocity = match sc.map.lanes[lane].speed_limit_mps {
                Some(l) if l > 0.0 => l,
                _ => params.target_velocity,
            };
            agents.push(Some(IdmAgent {
                track: ti,
                length: tr.length,
                width: tr.width,
                route: VecDeque::from([lane]),
                path,
                progress,
                velocity,
                target_velocity,
            }));
        }
        let n = agents.len();
        let occ = Occupancy {
            agents: agents
                .iter()
                .map(|a| a.as_ref().map(|a| Shape::from_box(&a.oriented_box())))
                .collect(),
            ..Default::default()
        };
        IdmManager {
            params,
            agents,
            leaders: vec![None; n],
            occ,
            lights: vec![None; sc.map.lanes.len()],
            scratch_poses: Vec::new(),
            scratch_pts: Vec::new(),
            path_shape: PathBuffer::default(),
            cands: Vec::new(),
        }
    }

    /// Number of agents still simulated.
    pub fn active(&self) -> usize {
        self.agents.iter().filter(|a| a.is_some()).count()
    }

    /// `propagate_agents` for one step of `dt`: `ego` is the ego before it moves, `lights` the light states of
    /// the next step, `open_loop` the replayed objects (track index, box) of the next step.
    pub fn step(
        &mut self,
        map: &Map,
        ego: Option<&EgoObservation>,
        lights: &[(usize, TrafficLightStatus)],
        open_loop: &[(usize, OrientedBox)],
        dt: f64,
    ) {
        let p = self.params;
        self.lights.iter_mut().for_each(|l| *l = None);
        for &(i, s) in lights {
            if i < self.lights.len() {
                self.lights[i] = Some(s);
            }
        }
        self.occ.ego = ego.map(|e| Shape::from_box(&e.footprint));
        // Reuse the open-loop shapes' buffers from step to step (no per-step allocation).
        self.occ.objects.truncate(open_loop.len());
        for (k, (ti, b)) in open_loop.iter().enumerate() {
            if k < self.occ.objects.len() {
                let e = &mut self.occ.objects[k];
                e.0 = *ti;
                e.1.clear();
                e.1.push(Part::Quad(b.corners()));
            } else {
                self.occ.objects.push((*ti, Shape::from_box(b)));
            }
        }
        // _filter_agents_out_of_range: distance from the ego centre to the agent centre.
        if let Some(e) = ego {
            let c = e.footprint.center.pos();
            for (i, a) in self.agents.iter_mut().enumerate() {
                if a.as_ref()
                    .is_some_and(|a| (a.pose().pos() - c).length() > p.radius)
                {
                    *a = None;
                    self.occ.agents[i] = None;
                }
            }
        }
        for i in 0..self.agents.len() {
            let Some(mut agent) = self.agents[i].take() else {
                continue;
            };
            agent.plan_route(map, &self.lights, &p, &mut self.scratch_poses);
            // Stop lines of red connectors on this agent's route.
            self.occ.stop_lines.clear();
            for &seg in &agent.route {
                if self.lights[seg] == Some(TrafficLightStatus::Red) {
                    for &sl in &map.lanes[seg].stop_lines {
                        if !self.occ.stop_lines.iter().any(|(k, _)| *k == sl) {
                            let mut s = Shape::new();
                            s.push(Part::Quad(map.stop_lines[sl].polygon));
                            self.occ.stop_lines.push((sl, s));
                        }
                    }
                }
            }
            // Path to go buffered by width/2 with flat caps.
            agent
                .path
                .trim_up_to(agent.bounded_progress(), &mut self.scratch_poses);
            self.path_shape.set(
                self.scratch_poses.iter().map(|q| q.pos()),
                agent.width / 2.0,
            );
            // The nearest geometry (by polygon distance to the agent's own geometry) among those intersecting
            // the buffered path to go, the agent itself excluded. Candidates are visited by increasing
            // bounding-box lower bound, so exact tests stop once no remaining candidate can be nearer; ties
            // go to the earlier entry in scan order (ego, agents, objects, stop lines).
            let own = self.occ.agents[i]
                .take()
                .unwrap_or_else(|| Shape::from_box(&agent.oriented_box()));
            // A degenerate path (fewer than 2 distinct points) meets nothing: the empty box filters all.
            let path_box = self.path_shape.aabb.unwrap_or(Aabb::EMPTY);
            let own_box = own.aabb.unwrap_or(Aabb::EMPTY);
            self.cands.clear();
            let mut order = 0usize;
            let mut add = |r: Entry, s: &Shape, cands: &mut Vec<(f64, usize, Entry)>| {
                order += 1;
                if let Some(b) = s.aabb {
                    if b.overlaps(&path_box) {
                        cands.push((own_box.distance(&b), order, r));
                    }
                }
            };
            if let Some(s) = &self.occ.ego {
                add(Entry::Ego, s, &mut self.cands);
            }
            for (j, s) in self.occ.agents.iter().enumerate() {
                if let Some(s) = s {
                    add(Entry::Agent(j), s, &mut self.cands);
                }
            }
            for (k, (_, s)) in self.occ.objects.iter().enumerate() {
                add(Entry::Object(k), s, &mut self.cands);
            }
            for (k, (_, s)) in self.occ.stop_lines.iter().enumerate() {
                add(Entry::StopLine(k), s, &mut self.cands);
            }
            self.cands
                .sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            let mut nearest: Option<(LeaderRef, f64, usize)> = None;
            for &(lb, ord, r) in &self.cands {
                if let Some((_, d, o)) = nearest {
                    if lb > d || (lb == d && ord > o) {
                        break;
                    }
                }
                let s = self.occ.shape(r);
                if !self.path_shape.intersects(s) {
                    continue;
                }
                let d = own.distance(s);
                if nearest.is_none_or(|(_, bd, bo)| d < bd || (d == bd && ord < bo)) {
                    nearest = Some((self.occ.leader_ref(r), d, ord));
                }
            }
            let nearest = nearest.map(|(r, d, _)| (r, d));
            let lead = match nearest {
                Some((r, dist)) => {
                    let heading = agent.pose().heading;
                    let (v, rel) = match r {
                        LeaderRef::Ego => {
                            let e = ego.expect("ego entry implies an ego");
                            (e.speed, e.rear_axle_heading - heading)
                        }
                        LeaderRef::StopLine(_) | LeaderRef::Object(_) => (0.0, 0.0),
                        LeaderRef::Agent(j) => match &self.agents[j] {
                            Some(o) => (o.velocity, o.pose().heading - heading),
                            None => (0.0, 0.0),
                        },
                    };
                    // rotate_angle(StateSE2(v, 0, 0), principal_value(rel)).x = v cos(rel).
                    let rel = crate::scene::geometry::wrap_angle(rel);
                    self.leaders[i] = Some(r);
                    Lead {
                        progress: dist,
                        velocity: v * rel.cos(),
                        length_rear: 0.0,
                    }
                }
                None => {
                    self.leaders[i] = None;
                    Lead {
                        progress: agent.progress_to_go(),
                        velocity: 0.0,
                        length_rear: agent.length / 2.0,
                    }
                }
            };
            // propagate: the end segment's speed limit replaces the target speed when positive.
            let end = *agent.route.back().expect("route is never empty");
            if let Some(l) = map.lanes[end].speed_limit_mps {
                if l > 0.0 {
                    agent.target_velocity = l;
                }
            }
            let (dp, v) = idm_step(&p, agent.target_velocity, agent.velocity, &lead, dt);
            agent.progress += dp;
            agent.velocity = v;
            // Quirk: the occupancy geometry becomes the projected footprint.
            let mut fp = own;
            agent.projected_footprint(&p, &mut self.scratch_pts, &mut fp);
            self.occ.agents[i] = Some(fp);
            self.agents[i] = Some(agent);
        }
        self.occ.stop_lines.clear();
    }
}
