//! Lane / lane-connector assignment of poses and of the ego box corners, a port of nuPlan's
//! [planning/metrics/utils/route_extractor.py] and of the shared part of
//! [evaluation_metrics/common/ego_lane_change.py] (`timestamps_in_common_or_connected_route_objs`), plus the
//! per-frame progress along the expert route [evaluation_metrics/common/ego_progress_along_expert_route.py].
use super::geometry::{polyline_length, polyline_project};
use super::input::{LaneId, MapQuery};
use crate::scene::geometry::{point_in_polygon, point_polygon_distance};
use glam::DVec2;
use std::collections::BTreeSet;

/// The lanes / connectors assigned to one pose (nuPlan `List[GraphEdgeMapObject]`); empty when off-lane.
pub type RouteObjs = Vec<LaneId>;

fn contains(map: &dyn MapQuery, id: LaneId, p: DVec2) -> bool {
    map.lane(id).is_some_and(|l| point_in_polygon(p, l.polygon))
}

fn successors(map: &dyn MapQuery, id: LaneId) -> Vec<LaneId> {
    map.lane(id)
        .map(|l| l.successors.to_vec())
        .unwrap_or_default()
}

fn predecessors(map: &dyn MapQuery, id: LaneId) -> Vec<LaneId> {
    map.lane(id)
        .map(|l| l.predecessors.to_vec())
        .unwrap_or_default()
}

/// `get_current_route_objects`: the one lane containing `p` (the first when several do), else all lane
/// connectors containing it.
pub fn current_route_objects(map: &dyn MapQuery, p: DVec2, scratch: &mut Vec<LaneId>) -> RouteObjs {
    scratch.clear();
    map.lanes_at(p, scratch);
    if let Some(lane) = scratch.iter().find(|l| !l.is_connector) {
        return vec![*lane];
    }
    scratch.iter().copied().filter(|l| l.is_connector).collect()
}

/// `get_route_obj_with_candidates`: candidates containing `p`; if none and there is a single candidate, its
/// outgoing edges containing `p`.
pub fn route_obj_with_candidates(map: &dyn MapQuery, p: DVec2, candidates: &[LaneId]) -> RouteObjs {
    let found: RouteObjs = candidates
        .iter()
        .copied()
        .filter(|c| contains(map, *c, p))
        .collect();
    if found.is_empty() && candidates.len() == 1 {
        return successors(map, candidates[0])
            .into_iter()
            .filter(|c| contains(map, *c, p))
            .collect();
    }
    found
}

/// `remove_extra_lane_connectors` (kept verbatim, including `all([])` being true: a multi-connector entry
/// followed by an empty one becomes empty).
fn remove_extra_lane_connectors(map: &dyn MapQuery, route: Vec<RouteObjs>) -> Vec<RouteObjs> {
    let mut rev: Vec<RouteObjs> = route.into_iter().rev().collect();
    for ind in 0..rev.len() {
        let cur = rev[ind].clone();
        if ind == 0 || cur.len() <= 1 {
            continue;
        }
        if cur.len() > rev[ind - 1].len() && rev[ind - 1].iter().all(|o| cur.contains(o)) {
            rev[ind] = rev[ind - 1].clone();
        }
        if let Some(first) = rev[ind - 1].first() {
            if !first.is_connector {
                let incoming = predecessors(map, *first);
                let keep: RouteObjs = cur
                    .iter()
                    .copied()
                    .filter(|o| incoming.contains(o))
                    .collect();
                if !keep.is_empty() {
                    rev[ind] = keep;
                }
            }
        }
    }
    rev.reverse();
    rev
}

/// `get_route`: lanes / connectors along a sequence of poses (box centres).
pub fn get_route(map: &dyn MapQuery, poses: &[DVec2]) -> Vec<RouteObjs> {
    let mut scratch = Vec::new();
    let mut route: Vec<RouteObjs> = Vec::with_capacity(poses.len());
    let mut curr: RouteObjs = Vec::new();
    for (ind, &p) in poses.iter().enumerate() {
        if !curr.is_empty() {
            curr = route_obj_with_candidates(map, p, &curr);
        }
        if curr.is_empty() {
            curr = current_route_objects(map, p, &mut scratch);
            // A pose slightly outside its connector, inside another connector (or in the intersection), stays
            // on the previous connectors within 5 m.
            let prev_is_connector = route
                .last()
                .and_then(|r| r.first())
                .is_some_and(|o| o.is_connector);
            if ind > 1
                && prev_is_connector
                && (curr.first().is_some_and(|o| o.is_connector)
                    || (curr.is_empty() && map.in_intersection(p)))
            {
                let prev = route.last().cloned().unwrap_or_default();
                let proximal: RouteObjs = prev
                    .into_iter()
                    .filter(|o| {
                        map.lane(*o)
                            .is_some_and(|l| point_polygon_distance(p, l.polygon) < 5.0)
                    })
                    .collect();
                if !proximal.is_empty() {
                    curr = proximal;
                }
            }
        }
        route.push(curr.clone());
    }
    remove_extra_lane_connectors(map, route)
}

/// `get_route_simplified`: drop consecutive entries sharing an object with the last kept one.
pub fn route_simplified(route: &[RouteObjs]) -> Vec<RouteObjs> {
    let Some(start) = route.iter().position(|r| !r.is_empty()) else {
        return Vec::new();
    };
    let mut out = vec![route[start].clone()];
    for r in &route[start + 1..] {
        let last = out.last().expect("non-empty");
        if !r.is_empty() && !last.iter().any(|o| r.contains(o)) {
            out.push(r.clone());
        }
    }
    out
}

/// Lanes / connectors under each ego corner (FL, RL, RR, FR) at one step.
pub type CornerObjs = [RouteObjs; 4];

/// `extract_corners_route`, including its quirk of growing the candidate set only at index 1.
pub fn extract_corners_route(map: &dyn MapQuery, corners: &[[DVec2; 4]]) -> Vec<CornerObjs> {
    let mut scratch = Vec::new();
    let mut out = Vec::with_capacity(corners.len());
    let mut curr_candid: Vec<LaneId> = Vec::new();
    for (ind, cs) in corners.iter().enumerate() {
        let mut objs: CornerObjs = Default::default();
        let mut next_candid: Vec<LaneId> = Vec::new();
        for (c, &corner) in cs.iter().enumerate() {
            let mut ro: RouteObjs = Vec::new();
            if !curr_candid.is_empty() {
                ro = route_obj_with_candidates(map, corner, &curr_candid);
            }
            if ro.is_empty() {
                ro = current_route_objects(map, corner, &mut scratch);
                if ind == 1 {
                    for o in &ro {
                        if !curr_candid.contains(o) {
                            curr_candid.push(*o);
                        }
                    }
                }
            }
            for o in &ro {
                if !next_candid.contains(o) {
                    next_candid.push(*o);
                }
            }
            objs[c] = ro;
        }
        out.push(objs);
        curr_candid = next_candid;
    }
    out
}

/// `extract_common_or_connecting_route_objs`: `Some(empty)` when all corners are off-lane, `None` when the
/// corners are in different unconnected objects (or only some are off-lane), else the common / connecting set.
pub fn common_or_connecting(map: &dyn MapQuery, corners: &CornerObjs) -> Option<BTreeSet<LaneId>> {
    if corners.iter().all(|c| c.is_empty()) {
        return Some(BTreeSet::new());
    }
    if corners.iter().any(|c| c.is_empty()) {
        return None;
    }
    let ids: Vec<BTreeSet<LaneId>> = corners
        .iter()
        .map(|c| c.iter().copied().collect())
        .collect();
    let common: BTreeSet<LaneId> = ids[0]
        .iter()
        .filter(|i| ids[1..].iter().all(|s| s.contains(i)))
        .copied()
        .collect();
    if !common.is_empty() {
        return Some(common);
    }
    let (fl, rl, rr, fr) = (&ids[0], &ids[1], &ids[2], &ids[3]);
    let out_edges = |s: &BTreeSet<LaneId>| -> BTreeSet<LaneId> {
        s.iter().flat_map(|o| successors(map, *o)).collect()
    };
    let in_edges = |s: &BTreeSet<LaneId>| -> BTreeSet<LaneId> {
        s.iter().flat_map(|o| predecessors(map, *o)).collect()
    };
    let rr_or_out: BTreeSet<LaneId> = rr.union(&out_edges(rr)).copied().collect();
    let rl_or_out: BTreeSet<LaneId> = rl.union(&out_edges(rl)).copied().collect();
    let rear_connecting =
        rl.iter().any(|o| rr_or_out.contains(o)) || rr.iter().any(|o| rl_or_out.contains(o));
    if rear_connecting {
        let fl_or_in: BTreeSet<LaneId> = fl.union(&in_edges(fl)).copied().collect();
        let fr_or_in: BTreeSet<LaneId> = fr.union(&in_edges(fr)).copied().collect();
        let res: BTreeSet<LaneId> = fl_or_in
            .iter()
            .filter(|o| rr_or_out.contains(o) && fr_or_in.contains(o) && rl_or_out.contains(o))
            .copied()
            .collect();
        if !res.is_empty() {
            return Some(res);
        }
    }
    None
}

/// Per step: true when the ego corners are in a common or connected (non-empty) set of lanes / connectors
/// (nuPlan `timestamps_in_common_or_connected_route_objs`).
pub fn in_common_or_connected(map: &dyn MapQuery, corners_route: &[CornerObjs]) -> Vec<bool> {
    corners_route
        .iter()
        .map(|c| common_or_connecting(map, c).is_some_and(|s| !s.is_empty()))
        .collect()
}

/// One element of nuPlan's `RouteRoadBlockLinkedList`.
#[derive(Clone, Debug)]
pub struct RoadblockPair {
    pub roadblock: u64,
    pub is_connector: bool,
    pub baseline: Vec<DVec2>,
}

/// `get_route_baseline_roadblock_linkedlist`: one pair per change of roadblock id along the simplified route
/// (first object of each entry).
pub fn roadblock_pairs(map: &dyn MapQuery, simplified: &[RouteObjs]) -> Vec<RoadblockPair> {
    let mut out: Vec<RoadblockPair> = Vec::new();
    let mut prev: Option<u64> = None;
    for r in simplified {
        let Some(first) = r.first() else { continue };
        let Some(lane) = map.lane(*first) else {
            continue;
        };
        if prev != Some(lane.roadblock) {
            prev = Some(lane.roadblock);
            out.push(RoadblockPair {
                roadblock: lane.roadblock,
                is_connector: first.is_connector,
                baseline: lane.baseline.to_vec(),
            });
        }
    }
    out
}

/// `PerFrameProgressAlongRouteComputer`: per-frame progress of `poses` along the roadblock chain.
/// `pairs` must be non-empty; returns one value per pose (the first is 0).
pub fn per_frame_progress(
    map: &dyn MapQuery,
    pairs: &[RoadblockPair],
    poses: &[DVec2],
) -> Vec<f64> {
    if pairs.is_empty() || poses.is_empty() {
        return vec![0.0; poses.len()];
    }
    let first = |b: &[DVec2]| b.first().copied().unwrap_or_default();
    let last = |b: &[DVec2]| b.last().copied().unwrap_or_default();
    let inside =
        |k: usize, p: DVec2| map.roadblock_contains(pairs[k].roadblock, pairs[k].is_connector, p);
    let mut curr = 0usize;
    let mut progress = Vec::with_capacity(poses.len());
    progress.push(0.0);
    let mut prev_dist = polyline_project(&pairs[curr].baseline, poses[0]);
    for &p in &poses[1..] {
        if inside(curr, p) {
            let d = polyline_project(&pairs[curr].baseline, p);
            progress.push(d - prev_dist);
            prev_dist = d;
            continue;
        }
        // get_multi_block_progress
        let mut multi = 0.0;
        let mut skipped_total = 0.0;
        let mut next = curr + 1;
        let mut skipped: Option<usize> = None;
        while next < pairs.len() {
            if inside(next, p) {
                // get_progress_including_skipped_roadblocks
                let in_prev = polyline_length(&pairs[curr].baseline) - prev_dist;
                let prev_last = last(&pairs[curr].baseline);
                curr = next;
                let d = polyline_project(&pairs[curr].baseline, p);
                let last_d = polyline_project(&pairs[curr].baseline, prev_last);
                multi = in_prev + (d - last_d) + skipped_total;
                prev_dist = d;
                break;
            } else if next + 1 >= pairs.len() {
                break;
            } else {
                // compute_progress_for_skipped_road_block
                let prev_last = last(&pairs[skipped.unwrap_or(curr)].baseline);
                skipped = Some(next);
                let s = next;
                let skipped_dist = polyline_project(&pairs[s].baseline, prev_last);
                next += 1;
                let next_first = first(&pairs[next].baseline);
                skipped_total += polyline_project(&pairs[s].baseline, next_first) - skipped_dist;
            }
        }
        progress.push(multi);
    }
    progress
}
