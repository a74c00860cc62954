//! A scenario as projection input: 3D boxes of the objects at a log step and the map layer of its map.
//!
//! Box convention (the one the ground-truth world renders with, so masks and images agree): a track's box sits on
//! the ground plane z = 0, its [`Box3d::center`] is the gravity centre (z = height / 2), its size is
//! (length, width, height) and its yaw the track's heading. The ego's own box is never included (the cameras
//! are mounted on it).
//!
//! Map channels: `drivable_area` = the map's drivable polygons (or every lane and connector polygon when it
//! has none) plus the intersection outlines; `lane` = lane and connector polygons; `crosswalk` = crosswalk
//! polygons; `lane_divider` = the derived lane dividers and centre lines; `road_boundary` = the derived road
//! edges ([`crate::scene::roadlines`]).
use glam::{DVec2, DVec3};

use super::geometry::{Box3d, BoxClass, MapClass, MapElement, MapGeometry, MapLayer};
use crate::scene::roadlines::{road_lines, LineKind};
use crate::scene::{Map, ObjectClass, ObjectState, Scenario, Track};

/// The mask class of a scenario object class (`None`: not drawn into any box channel).
pub fn box_class(c: ObjectClass) -> Option<BoxClass> {
    match c {
        ObjectClass::Vehicle => Some(BoxClass::Car),
        ObjectClass::Pedestrian => Some(BoxClass::Pedestrian),
        ObjectClass::Bicycle => Some(BoxClass::Bicycle),
        ObjectClass::TrafficCone => Some(BoxClass::TrafficCone),
        ObjectClass::Barrier => Some(BoxClass::Barrier),
        ObjectClass::CzoneSign | ObjectClass::GenericObject => None,
    }
}

/// Gravity centre and size of a track in a state (see the module docs).
pub fn track_geometry(track: &Track, s: &ObjectState) -> (DVec3, DVec3) {
    (
        DVec3::new(s.pose.x, s.pose.y, track.height * 0.5),
        DVec3::new(track.length, track.width, track.height),
    )
}

/// The box of a track in a state, if its class has a mask channel.
pub fn track_box(track: &Track, s: &ObjectState) -> Option<Box3d> {
    let class = box_class(track.class)?;
    let (center, size) = track_geometry(track, s);
    Some(Box3d {
        class,
        center,
        size,
        yaw: s.pose.heading,
    })
}

/// `(track index, box)` of every track observed at log step `k` that has a mask channel.
pub fn boxes_at(sc: &Scenario, k: usize) -> Vec<(usize, Box3d)> {
    sc.tracks
        .iter()
        .enumerate()
        .filter_map(|(i, t)| {
            let s = t.states.get(k).copied().flatten()?;
            track_box(t, &s).map(|b| (i, b))
        })
        .collect()
}

fn ring3(r: &[DVec2]) -> Vec<DVec3> {
    r.iter().map(|p| DVec3::new(p.x, p.y, 0.0)).collect()
}

fn polygon(class: MapClass, r: &[DVec2]) -> MapElement {
    MapElement {
        class,
        geometry: MapGeometry::Polygon {
            exterior: ring3(r),
            holes: vec![],
        },
    }
}

/// The map layer of a map (see the module docs for the channels).
pub fn map_layer(map: &Map) -> MapLayer {
    let mut els = Vec::new();
    if map.drivable.is_empty() {
        for l in &map.lanes {
            els.push(polygon(MapClass::DrivableArea, &l.polygon));
        }
    } else if let Some((first, rest)) = map.drivable.rings.split_first() {
        // One polygon over all rings: the set's own even-odd rule.
        els.push(MapElement {
            class: MapClass::DrivableArea,
            geometry: MapGeometry::Polygon {
                exterior: ring3(first),
                holes: rest.iter().map(|r| ring3(r)).collect(),
            },
        });
    }
    for r in &map.intersections {
        els.push(polygon(MapClass::DrivableArea, r));
    }
    for l in &map.lanes {
        els.push(polygon(MapClass::Lane, &l.polygon));
    }
    for c in &map.crosswalks {
        els.push(polygon(MapClass::Crosswalk, &c.polygon));
    }
    // A map with painted lines (nuScenes dividers) draws them as they are; the dividers derived from lane
    // geometry stand in only where a map has none. Road edges are always derived (no source paints them).
    let painted = !map.lines.is_empty();
    for line in road_lines(map) {
        let class = match line.kind {
            LineKind::LaneDivider | LineKind::CentreLine if painted => continue,
            LineKind::LaneDivider | LineKind::CentreLine => MapClass::LaneDivider,
            LineKind::RoadEdge => MapClass::RoadBoundary,
        };
        els.push(MapElement {
            class,
            geometry: MapGeometry::Polyline(ring3(&line.points)),
        });
    }
    for line in map.lines.iter().filter(|l| l.points.len() >= 2) {
        els.push(MapElement {
            class: MapClass::LaneDivider,
            geometry: MapGeometry::Polyline(ring3(&line.points)),
        });
    }
    MapLayer::new(els)
}
