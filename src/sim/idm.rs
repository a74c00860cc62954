//! IDM policy, interpolated paths and single IDM agents [simulation/observation/idm/idm_policy.py,
//! idm_agent.py, simulation/path/{interpolated_path,utils}.py]. The manager that moves all agents and picks
//! leaders lives in [`super::agents`].
use crate::scene::geometry::{wrap_angle, OrientedBox, Part, Pose2, Shape};
use crate::scene::map::Map;
use crate::scene::TrafficLightStatus;
use glam::DVec2;
use std::collections::VecDeque;

/// IDM parameters (idm_agents_observation.yaml).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IdmParams {
    pub target_velocity: f64,
    pub min_gap: f64,
    pub headway_time: f64,
    pub accel_max: f64,
    pub decel_max: f64,
    pub minimum_path_length: f64,
    /// Agents farther than this from the ego centre are removed for good.
    pub radius: f64,
}

impl Default for IdmParams {
    fn default() -> Self {
        Self {
            target_velocity: 10.0,
            min_gap: 1.0,
            headway_time: 1.5,
            accel_max: 1.0,
            decel_max: 2.0,
            minimum_path_length: 20.0,
            radius: 100.0,
        }
    }
}

/// The leader as the IDM sees it (IDMLeadAgentState): progress, velocity, rear length.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Lead {
    pub progress: f64,
    pub velocity: f64,
    pub length_rear: f64,
}

/// IDM acceleration (before clipping) for an agent at progress 0 with speed v (`IDMPolicy.idm_model`).
pub fn idm_accel(p: &IdmParams, target_velocity: f64, v: f64, lead: &Lead) -> f64 {
    let s_star = p.min_gap
        + v * p.headway_time
        + v * (v - lead.velocity) / (2.0 * (p.accel_max * p.decel_max).sqrt());
    let s_alpha = (lead.progress - 0.0 - lead.length_rear).max(p.min_gap);
    p.accel_max * (1.0 - (v / target_velocity).powi(4) - (s_star / s_alpha).powi(2))
}

/// One forward-Euler step (`solve_forward_euler_idm_policy` + `IDMAgent.propagate`): returns (progress
/// increment, new speed) with the acceleration clipped to [-decel_max, accel_max] and the speed floored at 0.
pub fn idm_step(p: &IdmParams, target_velocity: f64, v: f64, lead: &Lead, dt: f64) -> (f64, f64) {
    let a = idm_accel(p, target_velocity, v, lead);
    (
        dt * v,
        (v + dt * a.clamp(-p.decel_max, p.accel_max)).max(0.0),
    )
}

/// nuPlan's InterpolatedPath: poses with progress, linear interpolation of x, y and the unwrapped heading.
#[derive(Clone, Debug, PartialEq)]
pub struct IdmPath {
    pub pts: Vec<DVec2>,
    /// Unwrapped headings (np.unwrap).
    pub heading: Vec<f64>,
    pub prog: Vec<f64>,
}

impl IdmPath {
    /// `create_path_from_se2`: progress = cumulative distance; a state whose next state has the same
    /// progress is dropped. Quirk kept: the `zip` with the (n-1)-long mask also drops the LAST state.
    /// None when fewer than 2 states remain.
    pub fn from_states(states: &[Pose2]) -> Option<IdmPath> {
        let n = states.len();
        if n < 3 {
            return None;
        }
        let mut prog = Vec::with_capacity(n);
        let mut acc = 0.0;
        prog.push(0.0);
        for i in 1..n {
            acc += (states[i].pos() - states[i - 1].pos()).length();
            prog.push(acc);
        }
        let mut p = IdmPath {
            pts: Vec::with_capacity(n),
            heading: Vec::with_capacity(n),
            prog: Vec::with_capacity(n),
        };
        for i in 0..n - 1 {
            if (prog[i + 1] - prog[i]).abs() <= 1e-8 {
                continue;
            }
            p.pts.push(states[i].pos());
            let h = states[i].heading;
            let h = match p.heading.last() {
                Some(&prev) => prev + wrap_angle(h - prev),
                None => h,
            };
            p.heading.push(h);
            p.prog.push(prog[i]);
        }
        (p.pts.len() >= 2).then_some(p)
    }
    pub fn start(&self) -> f64 {
        self.prog[0]
    }
    pub fn end(&self) -> f64 {
        self.prog[self.prog.len() - 1]
    }
    pub fn clamp(&self, s: f64) -> f64 {
        s.min(self.end()).max(self.start())
    }
    /// State at a progress inside [start, end].
    pub fn state_at(&self, s: f64) -> Pose2 {
        let n = self.prog.len();
        let i = (self.prog.partition_point(|&v| v <= s).max(1) - 1).min(n - 2);
        let (s0, s1) = (self.prog[i], self.prog[i + 1]);
        let a = ((s - s0) / (s1 - s0)).clamp(0.0, 1.0);
        let p = self.pts[i] + (self.pts[i + 1] - self.pts[i]) * a;
        let h = self.heading[i] + a * (self.heading[i + 1] - self.heading[i]);
        Pose2::new(p.x, p.y, wrap_angle(h))
    }
    /// `trim_path_up_to_progress`: the state at s followed by the sampled states after s; at the very end,
    /// the last two sampled states. Output as poses.
    pub fn trim_up_to(&self, s: f64, out: &mut Vec<Pose2>) {
        out.clear();
        let i = self.prog.partition_point(|&v| v <= s);
        if i < self.prog.len() {
            out.push(self.state_at(s));
            for k in i..self.prog.len() {
                out.push(self.sample(k));
            }
        } else {
            let n = self.prog.len();
            out.push(self.sample(n - 2));
            out.push(self.sample(n - 1));
        }
    }
    /// `trim_path(start, end)` as points (what the footprint buffer uses).
    pub fn trim(&self, start: f64, end: f64, out: &mut Vec<DVec2>) {
        out.clear();
        let n = self.prog.len();
        let front = self.prog.partition_point(|&v| v <= start);
        if front >= n {
            out.push(self.pts[n - 2]);
            out.push(self.pts[n - 1]);
            return;
        }
        let tail = self.prog.partition_point(|&v| v < end);
        if tail == 0 {
            out.push(self.pts[0]);
            out.push(self.pts[1]);
            return;
        }
        out.push(self.state_at(start).pos());
        for k in front..tail {
            out.push(self.pts[k]);
        }
        out.push(self.state_at(end).pos());
    }
    fn sample(&self, k: usize) -> Pose2 {
        Pose2::new(self.pts[k].x, self.pts[k].y, wrap_angle(self.heading[k]))
    }
}

/// Poses of a lane centre line (the `baseline_path.discrete_path`).
pub fn lane_states(map: &Map, lane: usize) -> Vec<Pose2> {
    let c = &map.lanes[lane].centre;
    c.points
        .iter()
        .zip(&c.headings)
        .map(|(p, h)| Pose2::new(p.x, p.y, *h))
        .collect()
}

/// One IDM agent on map rails.
#[derive(Clone, Debug)]
pub struct IdmAgent {
    /// Index of the log track it was built from.
    pub track: usize,
    pub length: f64,
    pub width: f64,
    /// Route: at most 5 lanes/connectors (deque with maxlen 5).
    pub route: VecDeque<usize>,
    pub path: IdmPath,
    pub progress: f64,
    pub velocity: f64,
    pub target_velocity: f64,
}

pub const MAX_ROUTE_LEN: usize = 5;

impl IdmAgent {
    pub fn bounded_progress(&self) -> f64 {
        self.path.clamp(self.progress)
    }
    /// Box-centre pose (`to_se2`).
    pub fn pose(&self) -> Pose2 {
        self.path.state_at(self.bounded_progress())
    }
    pub fn oriented_box(&self) -> OrientedBox {
        OrientedBox::new(self.pose(), self.length, self.width)
    }
    /// Global-frame velocity along the path heading.
    pub fn velocity_vec(&self) -> DVec2 {
        let h = self.pose().heading;
        DVec2::new(h.cos(), h.sin()) * self.velocity
    }
    pub fn progress_to_go(&self) -> f64 {
        self.path.end() - self.progress
    }

    /// `plan_route`: while the path to go is shorter than minimum_path_length + v0 T, append the outgoing
    /// edge of smallest |curvature| at its start. Connectors with traffic lights are taken only when GREEN,
    /// other edges unless RED. The path is rebuilt from the path to go and the progress reset to 0.
    pub fn plan_route(
        &mut self,
        map: &Map,
        lights: &[Option<TrafficLightStatus>],
        p: &IdmParams,
        scratch: &mut Vec<Pose2>,
    ) {
        while self.progress_to_go() < p.minimum_path_length + self.target_velocity * p.headway_time
        {
            let end = *self.route.back().expect("route is never empty");
            let mut best: Option<(f64, usize)> = None;
            for &e in &map.lanes[end].successors {
                let st = lights.get(e).copied().flatten();
                let ok = if map.lanes[e].has_traffic_light {
                    st == Some(TrafficLightStatus::Green)
                } else {
                    st != Some(TrafficLightStatus::Red)
                };
                if !ok {
                    continue;
                }
                let k = map.lanes[e].centre.start_curvature();
                // np.argmin: first minimum wins.
                if best.is_none_or(|(b, _)| k < b) {
                    best = Some((k, e));
                }
            }
            let Some((_, next)) = best else { break };
            if self.route.len() == MAX_ROUTE_LEN {
                self.route.pop_front();
            }
            self.route.push_back(next);
            self.path.trim_up_to(self.bounded_progress(), scratch);
            scratch.extend(lane_states(map, next));
            match IdmPath::from_states(scratch) {
                Some(np) => self.path = np,
                None => break,
            }
            self.progress = 0.0;
        }
    }

    /// `projected_footprint`: the box united with the path from p - L/2 to p + L/2 + v T buffered by W/2
    /// (flat caps). Written into `out`.
    pub fn projected_footprint(&self, p: &IdmParams, pts: &mut Vec<DVec2>, out: &mut Shape) {
        let s0 = self.path.clamp(self.progress - self.length / 2.0);
        let s1 = self
            .path
            .clamp(self.progress + self.length / 2.0 + self.velocity * p.headway_time);
        self.path.trim(s0, s1, pts);
        out.clear();
        out.push(Part::Quad(self.oriented_box().corners()));
        out.push_buffered_path(pts, self.width / 2.0);
    }
}
