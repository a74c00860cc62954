//! Planar geometry the metrics need, standing in for shapely: oriented boxes (nuPlan `OrientedBox`), convex
//! overlap tests (`in_collision` = shapely `intersects`, touching counts), point-in-polygon, point-to-polygon
//! distance and polyline projection (shapely `LineString.project`).
use glam::DVec2;

use crate::scene::geometry as sg;
/// shapely `polygon.distance(Point)`: 0 inside (the boundary included: its distance is 0 anyway), else the
/// distance to the boundary; infinite for an empty polygon.
pub use sg::point_polygon_distance as dist_point_polygon;
/// Distance from a point to the segment [a, b].
pub use sg::point_segment_distance as dist_point_segment;
/// Intersection test for two convex polygons (any winding), touching counts; false if either is empty.
pub use sg::{convex_intersect, wrap_angle};

/// An oriented rectangle given by its centre (nuPlan `OrientedBox`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OrientedBox {
    pub center: DVec2,
    pub heading: f64,
    pub length: f64,
    pub width: f64,
}

impl OrientedBox {
    pub fn new(center: DVec2, heading: f64, length: f64, width: f64) -> Self {
        OrientedBox {
            center,
            heading,
            length,
            width,
        }
    }

    /// Unit vector along the heading.
    pub fn forward(&self) -> DVec2 {
        DVec2::new(self.heading.cos(), self.heading.sin())
    }

    /// Corners in nuPlan's order: front-left, rear-left, rear-right, front-right
    /// [common/actor_state/oriented_box.py `all_corners`].
    pub fn corners(&self) -> [DVec2; 4] {
        let f = self.forward();
        let l = DVec2::new(-f.y, f.x);
        let hl = self.length / 2.0;
        let hw = self.width / 2.0;
        let c = self.center;
        [
            c + f * hl + l * hw,
            c - f * hl + l * hw,
            c - f * hl - l * hw,
            c + f * hl - l * hw,
        ]
    }

    /// Axis-aligned bounds (min, max).
    pub fn aabb(&self) -> (DVec2, DVec2) {
        let f = self.forward();
        let ext = DVec2::new(
            (f.x * self.length / 2.0).abs() + (f.y * self.width / 2.0).abs(),
            (f.y * self.length / 2.0).abs() + (f.x * self.width / 2.0).abs(),
        );
        (self.center - ext, self.center + ext)
    }
}

/// shapely `intersects` for two oriented boxes (boundaries touching counts) via separating axes.
pub fn boxes_intersect(a: &OrientedBox, b: &OrientedBox) -> bool {
    convex_intersect(&a.corners(), &b.corners())
}

/// shapely `LineString([p, q]).intersects(polygon)` for a convex polygon: the segment is a degenerate convex
/// polygon, so the separating-axis test applies (the segment's own normal is one of the axes).
pub fn segment_intersects_convex(p: DVec2, q: DVec2, poly: &[DVec2]) -> bool {
    convex_intersect(&[p, q], poly)
}

/// Point in a simple polygon (even-odd rule); points on the boundary count as inside (the scene module's ray
/// cast leaves them either way).
pub fn point_in_polygon(p: DVec2, poly: &[DVec2]) -> bool {
    let n = poly.len();
    n >= 3
        && ((0..n).any(|i| dist_point_segment(p, poly[i], poly[(i + 1) % n]) == 0.0)
            || sg::point_in_polygon(p, poly))
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
        let ab = b - a;
        let len2 = ab.length_squared();
        let t = if len2 > 0.0 {
            ((p - a).dot(ab) / len2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let d = (a + ab * t).distance(p);
        let seg_len = len2.sqrt();
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

    #[test]
    fn corners_order_and_touching() {
        let b = OrientedBox::new(DVec2::ZERO, 0.0, 4.0, 2.0);
        let c = b.corners();
        assert_eq!(c[0], DVec2::new(2.0, 1.0)); // front-left
        assert_eq!(c[1], DVec2::new(-2.0, 1.0)); // rear-left
        assert_eq!(c[2], DVec2::new(-2.0, -1.0)); // rear-right
        assert_eq!(c[3], DVec2::new(2.0, -1.0)); // front-right
                                                 // Touching along an edge intersects (shapely semantics); a hair apart does not.
        let t = OrientedBox::new(DVec2::new(4.0, 0.0), 0.0, 4.0, 2.0);
        assert!(boxes_intersect(&b, &t));
        let f = OrientedBox::new(DVec2::new(4.0 + 1e-9, 0.0), 0.0, 4.0, 2.0);
        assert!(!boxes_intersect(&b, &f));
        // Rotated box whose corner pokes into b.
        let r = OrientedBox::new(DVec2::new(3.3, 0.0), std::f64::consts::FRAC_PI_4, 2.0, 2.0);
        assert!(boxes_intersect(&b, &r));
        let r2 = OrientedBox::new(DVec2::new(3.5, 0.0), std::f64::consts::FRAC_PI_4, 2.0, 2.0);
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
        assert_eq!(dist_point_polygon(DVec2::new(1.0, 1.0), &sq), 0.0);
        assert!((dist_point_polygon(DVec2::new(5.0, 6.0), &sq) - 5.0).abs() < 1e-12);
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
