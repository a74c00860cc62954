//! Road lines derived from the lane geometry of a map (maps here carry lanes, not painted lines): the
//! boundaries between lanes and the edges of the road, classified by what lies on the other side.
//!
//! For every lane (kind [`LaneKind::Lane`]; connectors carry no markings) both edges are the centre line offset
//! by the lane's half width (estimated from its polygon), sampled at the centre line's vertices. At each sample a
//! probe 1 m beyond the edge decides the type: another lane with a similar heading = [`LineKind::LaneDivider`]
//! (white dashed), a lane with an opposite heading = [`LineKind::CentreLine`] (yellow), nothing = the road edge
//! [`LineKind::RoadEdge`] (white solid, kerb and sidewalk beyond). A boundary shared by two lanes is emitted once
//! (by the lower lane index). Consecutive samples of one type form one line.
use super::geometry::{angle_diff, point_ring_distance, Polyline};
use super::map::{LaneKind, Map};
use glam::DVec2;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LineKind {
    /// Between two lanes of the same direction (white, dashed).
    LaneDivider,
    /// Between opposite directions (yellow, solid).
    CentreLine,
    /// Edge of the road (white, solid; kerb beyond).
    RoadEdge,
}

/// One road line: points in the global frame and the side of the road it bounds (unit normals pointing away
/// from the lane it was derived from, one per point).
#[derive(Clone, Debug, PartialEq)]
pub struct RoadLine {
    pub kind: LineKind,
    pub points: Vec<DVec2>,
    pub outward: Vec<DVec2>,
}

/// Half width of a lane: the distance from the middle of its centre line to its outline.
pub fn half_width(centre: &Polyline, polygon: &[DVec2]) -> f64 {
    let p = centre.point_at(centre.length() / 2.0);
    let d = point_ring_distance(p, polygon);
    if d.is_finite() && d > 0.2 {
        d
    } else {
        1.75
    }
}

/// The road lines of a map, in lane order (deterministic).
pub fn road_lines(map: &Map) -> Vec<RoadLine> {
    let mut out = Vec::new();
    for (li, lane) in map.lanes.iter().enumerate() {
        if lane.kind != LaneKind::Lane || lane.centre.points.len() < 2 {
            continue;
        }
        let hw = half_width(&lane.centre, &lane.polygon);
        for side in [1.0f64, -1.0] {
            let mut cur: Option<RoadLine> = None;
            for (i, &c) in lane.centre.points.iter().enumerate() {
                let h = lane.centre.headings[i];
                let n = DVec2::new(-h.sin(), h.cos()) * side;
                let edge = c + n * hw;
                let probe = edge + n * 1.0;
                // The neighbour beyond this edge: (lane index, same direction).
                let mut neighbour: Option<(usize, bool)> = None;
                map.for_lanes_at(probe, Some(LaneKind::Lane), |j| {
                    if j == li {
                        return;
                    }
                    let (s, _) = map.lanes[j].centre.project(probe);
                    let hj = map.lanes[j].centre.pose_at(s).heading;
                    let same = angle_diff(hj, h).abs() < std::f64::consts::FRAC_PI_2;
                    if neighbour.is_none_or(|(b, _)| j < b) {
                        neighbour = Some((j, same));
                    }
                });
                let kind = match neighbour {
                    // Shared boundary: emitted by the lower lane index only.
                    Some((j, _)) if j < li => None,
                    Some((_, true)) => Some(LineKind::LaneDivider),
                    Some((_, false)) => Some(LineKind::CentreLine),
                    None => Some(LineKind::RoadEdge),
                };
                match (&mut cur, kind) {
                    (Some(l), Some(k)) if l.kind == k => {
                        l.points.push(edge);
                        l.outward.push(n);
                    }
                    _ => {
                        if let Some(l) = cur.take() {
                            if l.points.len() >= 2 {
                                out.push(l);
                            }
                        }
                        cur = kind.map(|k| RoadLine {
                            kind: k,
                            points: vec![edge],
                            outward: vec![n],
                        });
                    }
                }
            }
            if let Some(l) = cur.take() {
                if l.points.len() >= 2 {
                    out.push(l);
                }
            }
        }
    }
    out
}
