//! Road geometry of the built-in towns: a junction at the origin with up to four straight arms (east, north,
//! west, south), optionally the 90-degree curve continuing the east arm northwards, crosswalks, stop lines and
//! signalised connectors.
//!
//! Invariant: with [`LayoutOptions::classic`] the lane specs, stop lines and crosswalks come out in exactly the
//! order the original `builtin:town` generator produced them (lane indices feed the IDM log generation, so any
//! reordering would change the logs).
use crate::scene::geometry::Polyline;
use crate::scene::index::PolygonSet;
use crate::scene::map::{Crosswalk, LaneKind, LaneSpec, Map, StopLine};
use glam::DVec2;
use std::f64::consts::FRAC_PI_2;

pub const LANE_W: f64 = 3.5;
/// Intersection half size.
pub const H: f64 = 11.0;
const LANE_SPEED: f64 = 12.0;
const CONNECTOR_SPEED: f64 = 9.0;

/// What a layout holds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LayoutOptions {
    /// Arms present: east, north, west, south (index = direction / 90 degrees).
    pub arms: [bool; 4],
    pub curve: bool,
    /// Signalised connectors with stop lines (else free-flowing connectors, no stop lines).
    pub lights: bool,
    pub lanes_per_dir: usize,
    pub arm_len: f64,
}

impl LayoutOptions {
    /// The original town.
    pub fn classic(lanes_per_dir: usize, arm_len: f64) -> Self {
        LayoutOptions {
            arms: [true; 4],
            curve: true,
            lights: true,
            lanes_per_dir,
            arm_len,
        }
    }
}

pub fn sample_line(a: DVec2, b: DVec2) -> Vec<DVec2> {
    let n = ((b - a).length().ceil() as usize).max(2);
    (0..=n)
        .map(|i| a + (b - a) * (i as f64 / n as f64))
        .collect()
}

pub fn sample_bezier(p0: DVec2, d0: DVec2, p3: DVec2, d3: DVec2) -> Vec<DVec2> {
    let k = 0.55 * (p3 - p0).length();
    let (p1, p2) = (p0 + d0 * k, p3 - d3 * k);
    let n = (((p3 - p0).length() * 1.3).ceil() as usize).max(4);
    (0..=n)
        .map(|i| {
            let t = i as f64 / n as f64;
            let u = 1.0 - t;
            p0 * (u * u * u) + p1 * (3.0 * u * u * t) + p2 * (3.0 * u * t * t) + p3 * (t * t * t)
        })
        .collect()
}

pub fn sample_arc(c: DVec2, r: f64, a0: f64, a1: f64) -> Vec<DVec2> {
    let n = ((r * (a1 - a0).abs()).ceil() as usize).max(4);
    (0..=n)
        .map(|i| {
            let a = a0 + (a1 - a0) * i as f64 / n as f64;
            c + DVec2::new(a.cos(), a.sin()) * r
        })
        .collect()
}

pub fn rect(c: DVec2, u: DVec2, half_u: f64, half_n: f64) -> [DVec2; 4] {
    let n = u.perp();
    [
        c + u * half_u + n * half_n,
        c - u * half_u + n * half_n,
        c - u * half_u - n * half_n,
        c + u * half_u - n * half_n,
    ]
}

pub struct TownLayout {
    pub map: Map,
    /// Per arm, per lane: the inbound lane index.
    pub inbound: Vec<Vec<usize>>,
    /// Connector indices with their phase.
    pub connectors: Vec<(usize, usize)>,
    pub options: LayoutOptions,
}

pub fn build_layout(opt: LayoutOptions, map_name: &str) -> TownLayout {
    let (lanes_per_dir, arm_len) = (opt.lanes_per_dir, opt.arm_len);
    let mut specs: Vec<LaneSpec> = Vec::new();
    let mut stop_lines = Vec::new();
    let mut crosswalks = Vec::new();
    let mut inbound = vec![vec![]; 4];
    let mut ends = vec![vec![(DVec2::ZERO, DVec2::ZERO); lanes_per_dir]; 4]; // inbound end (point, dir)
    let mut starts = vec![vec![(DVec2::ZERO, DVec2::ZERO); lanes_per_dir]; 4]; // outbound start
    let off = |i: usize| LANE_W / 2.0 + i as f64 * LANE_W;
    let lane = |id: String, pts: Vec<DVec2>, kind: LaneKind, rb: String, speed: f64| LaneSpec {
        id,
        kind,
        centre: Polyline::new(pts, None),
        polygon: None,
        width: LANE_W,
        speed_limit_mps: Some(speed),
        successors: vec![],
        roadblock: Some(rb),
        has_traffic_light: kind == LaneKind::Connector,
        stop_lines: vec![],
    };
    let names = ["east", "north", "west", "south"];
    for a in 0..4 {
        if !opt.arms[a] {
            continue;
        }
        let th = a as f64 * FRAC_PI_2;
        let u = DVec2::new(th.cos(), th.sin());
        let n = u.perp();
        for i in 0..lanes_per_dir {
            let o = off(i);
            let (p_far, p_near) = (u * (H + arm_len) + n * o, u * H + n * o);
            inbound[a].push(specs.len());
            specs.push(lane(
                format!("{}_in_{i}", names[a]),
                sample_line(p_far, p_near),
                LaneKind::Lane,
                format!("{}_in", names[a]),
                LANE_SPEED,
            ));
            ends[a][i] = (p_near, -u);
            if opt.lights {
                stop_lines.push(StopLine {
                    id: format!("stop_{}_{i}", names[a]),
                    polygon: rect(u * (H + 0.25) + n * o, u, 0.25, LANE_W / 2.0),
                });
            }
            let (q_near, q_far) = (u * H - n * o, u * (H + arm_len) - n * o);
            specs.push(lane(
                format!("{}_out_{i}", names[a]),
                sample_line(q_near, q_far),
                LaneKind::Lane,
                format!("{}_out", names[a]),
                LANE_SPEED,
            ));
            starts[a][i] = (q_near, u);
        }
        let half_road = lanes_per_dir as f64 * LANE_W;
        crosswalks.push(Crosswalk {
            id: format!("crosswalk_{}", names[a]),
            polygon: rect(u * (H + 3.0), u, 2.0, half_road).to_vec(),
        });
    }
    // The curve: east arm outbound lanes turn left (north) around C, then run 40 m north; inbound mirror.
    let r0 = 30.0;
    let c = DVec2::new(H + arm_len, r0);
    let curve_lanes = if opt.curve && opt.arms[0] {
        lanes_per_dir
    } else {
        0
    };
    for i in 0..curve_lanes {
        let o = off(i);
        let ro = r0 + o;
        specs.push(lane(
            format!("curve_out_{i}"),
            sample_arc(c, ro, -FRAC_PI_2, 0.0),
            LaneKind::Lane,
            "curve_out".into(),
            LANE_SPEED,
        ));
        specs.push(lane(
            format!("north_road_out_{i}"),
            sample_line(c + DVec2::new(ro, 0.0), c + DVec2::new(ro, 40.0)),
            LaneKind::Lane,
            "north_road_out".into(),
            LANE_SPEED,
        ));
        let ri = r0 - o;
        specs.push(lane(
            format!("north_road_in_{i}"),
            sample_line(c + DVec2::new(ri, 40.0), c + DVec2::new(ri, 0.0)),
            LaneKind::Lane,
            "north_road_in".into(),
            LANE_SPEED,
        ));
        specs.push(lane(
            format!("curve_in_{i}"),
            sample_arc(c, ri, 0.0, -FRAC_PI_2),
            LaneKind::Lane,
            "curve_in".into(),
            LANE_SPEED,
        ));
    }
    // Connectors: straight for every lane, left from the inner lane, right from the outer lane.
    let mut connectors = Vec::new();
    // Stop line index of (arm, lane): arms are skipped when absent.
    let stop_index =
        |a: usize, i: usize| opt.arms[..a].iter().filter(|&&x| x).count() * lanes_per_dir + i;
    for a in 0..4 {
        if !opt.arms[a] {
            continue;
        }
        let mut add = |specs: &mut Vec<LaneSpec>, i: usize, b: usize, j: usize, kind: &str| {
            if !opt.arms[b] {
                return;
            }
            let (p0, d0) = ends[a][i];
            let (p3, d3) = starts[b][j];
            let pts = if kind == "straight" {
                sample_line(p0, p3)
            } else {
                sample_bezier(p0, d0, p3, d3)
            };
            let mut s = lane(
                format!("conn_{}_{i}_{}_{j}", names[a], names[b]),
                pts,
                LaneKind::Connector,
                format!("conn_{}_{}", names[a], names[b]),
                CONNECTOR_SPEED,
            );
            if opt.lights {
                s.stop_lines = vec![stop_index(a, i)];
                connectors.push((specs.len(), a % 2));
            } else {
                s.has_traffic_light = false;
            }
            specs.push(s);
        };
        for i in 0..lanes_per_dir {
            add(&mut specs, i, (a + 2) % 4, i, "straight");
        }
        add(&mut specs, 0, (a + 3) % 4, 0, "left");
        add(
            &mut specs,
            lanes_per_dir - 1,
            (a + 1) % 4,
            lanes_per_dir - 1,
            "right",
        );
    }
    let n_arms = opt.arms.iter().filter(|&&x| x).count();
    let mut inter = vec![vec![
        DVec2::new(-H, -H),
        DVec2::new(H, -H),
        DVec2::new(H, H),
        DVec2::new(-H, H),
    ]];
    if n_arms < 3 {
        inter.clear(); // a plain road: no junction
    }
    let map = Map::build(
        map_name,
        specs,
        stop_lines,
        crosswalks,
        inter,
        PolygonSet::default(),
        true,
    )
    .expect("the synthetic town is well formed");
    TownLayout {
        map,
        inbound,
        connectors,
        options: opt,
    }
}
