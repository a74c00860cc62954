//! Planar geometry only the metrics need, standing in for shapely: box and segment overlap (`in_collision` =
//! shapely `intersects`, touching counts) and polyline projection (shapely `LineString.project`). The box
//! type, point-in-polygon (with its boundary rule) and point-to-polygon distance are the scene's
//! ([`crate::scene::geometry`]): one type and one test for the simulator and the score.
use glam::DVec2;

use crate::scene::geometry::{convex_intersect, segment_param, OrientedBox};

/// shapely `intersects` for two oriented boxes (boundaries touching counts) via separating axes.
pub fn boxes_intersect(a: &OrientedBox, b: &OrientedBox) -> bool {
    convex_intersect(&a.corners(), &b.corners())
}

/// shapely `LineString([p, q]).intersects(polygon)` for a convex polygon: the segment is a degenerate convex
/// polygon, so the separating-axis test applies (the segment's own normal is one of the axes).
pub fn segment_intersects_convex(p: DVec2, q: DVec2, poly: &[DVec2]) -> bool {
    convex_intersect(&[p, q], poly)
}

/// Length of a polyline.
pub fn polyline_length(line: &[DVec2]) -> f64 {
    line.windows(2).map(|w| w[0].distance(w[1])).sum()
}

/// shapely `LineString.project(Point)`: arc length of the point of the line nearest to `p` (first nearest
/// segment wins, as in GEOS). 0 for lines with fewer than 2 points.
pub fn polyline_project(line: &[DVec2], p: DVec2) -> f64 {
    let mut best = f64::INFINITY;
    let mut best_s = 0.0;
    let mut s0 = 0.0;
    for w in line.windows(2) {
        let (a, b) = (w[0], w[1]);
        let t = segment_param(p, a, b);
        let d = (a + (b - a) * t).distance(p);
        let seg_len = (b - a).length();
        if d < best {
            best = d;
            best_s = s0 + t * seg_len;
        }
        s0 += seg_len;
    }
    best_s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::geometry::{point_in_polygon, point_polygon_distance, wrap_angle};

    #[test]
    fn corners_order_and_touching() {
        let b = OrientedBox::at(DVec2::ZERO, 0.0, 4.0, 2.0);
        let c = b.corners();
        assert_eq!(c[0], DVec2::new(2.0, 1.0)); // front-left
        assert_eq!(c[1], DVec2::new(-2.0, 1.0)); // rear-left
        assert_eq!(c[2], DVec2::new(-2.0, -1.0)); // rear-right
        assert_eq!(c[3], DVec2::new(2.0, -1.0)); // front-right
                                                 // Touching along an edge intersects (shapely semantics); a hair apart does not.
        let t = OrientedBox::at(DVec2::new(4.0, 0.0), 0.0, 4.0, 2.0);
        assert!(boxes_intersect(&b, &t));
        let f = OrientedBox::at(DVec2::new(4.0 + 1e-9, 0.0), 0.0, 4.0, 2.0);
        assert!(!boxes_intersect(&b, &f));
        // Rotated box whose corner pokes into b.
        let r = OrientedBox::at(DVec2::new(3.3, 0.0), std::f64::consts::FRAC_PI_4, 2.0, 2.0);
        assert!(boxes_intersect(&b, &r));
        let r2 = OrientedBox::at(DVec2::new(3.5, 0.0), std::f64::consts::FRAC_PI_4, 2.0, 2.0);
        assert!(!boxes_intersect(&b, &r2)); // 3.5 - sqrt(2) = 2.086 > 2
    }

    #[test]
    fn polygon_queries() {
        let sq = [
            DVec2::new(0.0, 0.0),
            DVec2::new(2.0, 0.0),
            DVec2::new(2.0, 2.0),
            DVec2::new(0.0, 2.0),
        ];
        assert!(point_in_polygon(DVec2::new(1.0, 1.0), &sq));
        assert!(point_in_polygon(DVec2::new(2.0, 1.0), &sq));
        assert!(!point_in_polygon(DVec2::new(3.0, 1.0), &sq));
        assert_eq!(point_polygon_distance(DVec2::new(1.0, 1.0), &sq), 0.0);
        assert!((point_polygon_distance(DVec2::new(5.0, 6.0), &sq) - 5.0).abs() < 1e-12);
        let line = [
            DVec2::new(0.0, 0.0),
            DVec2::new(10.0, 0.0),
            DVec2::new(10.0, 10.0),
        ];
        assert_eq!(polyline_length(&line), 20.0);
        assert_eq!(polyline_project(&line, DVec2::new(3.0, -4.0)), 3.0);
        assert_eq!(polyline_project(&line, DVec2::new(12.0, 4.0)), 14.0);
        assert_eq!(polyline_project(&line, DVec2::new(-5.0, 0.0)), 0.0);
        assert!(segment_intersects_convex(
            DVec2::new(-1.0, 1.0),
            DVec2::new(0.5, 1.0),
            &sq
        ));
        assert!(!segment_intersects_convex(
            DVec2::new(-1.0, 1.0),
            DVec2::new(-0.5, 1.0),
            &sq
        ));
    }

    #[test]
    fn wrap() {
        assert!((wrap_angle(3.0 * std::f64::consts::PI) + std::f64::consts::PI).abs() < 1e-12);
        assert!((wrap_angle(0.5) - 0.5).abs() < 1e-15);
    }
}
