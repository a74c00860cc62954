//! Planar f64 geometry used by the map, the IDM occupancy map and the metrics: angles, poses, oriented boxes,
//! convex polygons (separating-axis tests), polylines with arc length, and composite shapes made of convex
//! parts and discs (how we represent shapely's `buffer(cap_style=flat)` exactly, see [`Shape::buffered_path`]).
use glam::DVec2;
use std::f64::consts::PI;

/// nuPlan's `principal_value` / numpy-style wrap into [-pi, pi): ((a + pi) mod 2pi) - pi with a floored modulo.
#[inline]
pub fn wrap_angle(a: f64) -> f64 {
    (a + PI).rem_euclid(2.0 * PI) - PI
}

/// nuPlan's `angle_diff(x, y, 2pi)`: the wrapped difference x - y.
#[inline]
pub fn angle_diff(x: f64, y: f64) -> f64 {
    wrap_angle(x - y)
}

/// Serialises a DVec2 as `[x, y]` (glam's serde feature is not enabled in this crate).
pub fn ser_dvec2<S: serde::Serializer>(v: &DVec2, s: S) -> Result<S::Ok, S::Error> {
    use serde::ser::SerializeTuple;
    let mut t = s.serialize_tuple(2)?;
    t.serialize_element(&v.x)?;
    t.serialize_element(&v.y)?;
    t.end()
}

/// A planar pose (position and heading, radians about +z, 0 = +x).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pose2 {
    pub x: f64,
    pub y: f64,
    pub heading: f64,
}

impl Pose2 {
    pub const fn new(x: f64, y: f64, heading: f64) -> Self {
        Self { x, y, heading }
    }
    #[inline]
    pub fn pos(&self) -> DVec2 {
        DVec2::new(self.x, self.y)
    }
    #[inline]
    pub fn dir(&self) -> DVec2 {
        DVec2::new(self.heading.cos(), self.heading.sin())
    }
    /// Pose moved by `d` metres along its own heading.
    pub fn forward(&self, d: f64) -> Self {
        let p = self.pos() + self.dir() * d;
        Self::new(p.x, p.y, self.heading)
    }
    /// Maps a pose given in this pose's local frame into the global frame.
    pub fn compose(&self, local: &Pose2) -> Pose2 {
        let (s, c) = self.heading.sin_cos();
        Pose2::new(
            self.x + c * local.x - s * local.y,
            self.y + s * local.x + c * local.y,
            wrap_angle(self.heading + local.heading),
        )
    }
    /// Expresses a global pose in this pose's local frame.
    pub fn relative(&self, global: &Pose2) -> Pose2 {
        let (s, c) = self.heading.sin_cos();
        let d = global.pos() - self.pos();
        Pose2::new(
            c * d.x + s * d.y,
            -s * d.x + c * d.y,
            wrap_angle(global.heading - self.heading),
        )
    }
}

/// Axis-aligned bounding box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: DVec2,
    pub max: DVec2,
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb {
        min: DVec2::splat(f64::INFINITY),
        max: DVec2::splat(f64::NEG_INFINITY),
    };
    pub fn from_points(pts: &[DVec2]) -> Aabb {
        let mut b = Aabb::EMPTY;
        for p in pts {
            b.add(*p);
        }
        b
    }
    #[inline]
    pub fn add(&mut self, p: DVec2) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }
    #[inline]
    pub fn union(&self, o: &Aabb) -> Aabb {
        Aabb {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
        }
    }
    #[inline]
    pub fn expand(&self, r: f64) -> Aabb {
        Aabb {
            min: self.min - DVec2::splat(r),
            max: self.max + DVec2::splat(r),
        }
    }
    #[inline]
    pub fn overlaps(&self, o: &Aabb) -> bool {
        self.min.x <= o.max.x
            && o.min.x <= self.max.x
            && self.min.y <= o.max.y
            && o.min.y <= self.max.y
    }
    #[inline]
    pub fn contains(&self, p: DVec2) -> bool {
        p.x >= self.min.x && p.x <= self.max.x && p.y >= self.min.y && p.y <= self.max.y
    }
    pub fn is_empty(&self) -> bool {
        self.min.x > self.max.x
    }
}

/// An oriented rectangle given by its centre pose (nuPlan `OrientedBox`): the one box type of the crate.
/// Scene tracks, the simulated agents and the ego, the planner's view and the closed-loop score
/// ([`crate::metrics::collisions::in_collision`]) all use it; the camera-space 3D box of the projection
/// module ([`crate::projection::Box3d`]) is a different concept (it has a height and a class).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OrientedBox {
    /// Box centre and heading of the length axis.
    pub center: Pose2,
    /// Extent along the heading (m).
    pub length: f64,
    /// Extent across the heading (m).
    pub width: f64,
}

impl OrientedBox {
    pub fn new(center: Pose2, length: f64, width: f64) -> Self {
        Self {
            center,
            length,
            width,
        }
    }
    /// Box with the given centre point and heading.
    pub fn at(center: DVec2, heading: f64, length: f64, width: f64) -> Self {
        Self::new(Pose2::new(center.x, center.y, heading), length, width)
    }
    /// Corners counter-clockwise in nuPlan's order: front-left, rear-left, rear-right, front-right
    /// [common/actor_state/oriented_box.py `all_corners`].
    pub fn corners(&self) -> [DVec2; 4] {
        let c = self.center.pos();
        let f = self.center.dir() * (self.length / 2.0);
        let l = self.center.dir().perp() * (self.width / 2.0);
        [c + f + l, c - f + l, c - f - l, c + f - l]
    }
    /// Axis-aligned bounds.
    pub fn aabb(&self) -> Aabb {
        let f = self.center.dir();
        let ext = DVec2::new(
            (f.x * self.length / 2.0).abs() + (f.y * self.width / 2.0).abs(),
            (f.y * self.length / 2.0).abs() + (f.x * self.width / 2.0).abs(),
        );
        let c = self.center.pos();
        Aabb {
            min: c - ext,
            max: c + ext,
        }
    }
}

/// Parameter t in [0, 1] of the point of segment [a, b] nearest to p, `a + (b - a) * t` (0 for a
/// degenerate segment): the projection behind every point-segment distance and polyline projection.
#[inline]
pub fn segment_param(p: DVec2, a: DVec2, b: DVec2) -> f64 {
    let ab = b - a;
    let l2 = ab.length_squared();
    if l2 > 0.0 {
        ((p - a).dot(ab) / l2).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

/// Distance from p to segment [a, b].
#[inline]
pub fn point_segment_distance(p: DVec2, a: DVec2, b: DVec2) -> f64 {
    let t = segment_param(p, a, b);
    (a + (b - a) * t - p).length()
}

/// Whether segments [a, b] and [c, d] intersect (touching counts).
pub fn segments_intersect(a: DVec2, b: DVec2, c: DVec2, d: DVec2) -> bool {
    let o = |p: DVec2, q: DVec2, r: DVec2| (q - p).perp_dot(r - p);
    let (d1, d2, d3, d4) = (o(c, d, a), o(c, d, b), o(a, b, c), o(a, b, d));
    if ((d1 > 0.0 && d2 < 0.0) || (d1 < 0.0 && d2 > 0.0))
        && ((d3 > 0.0 && d4 < 0.0) || (d3 < 0.0 && d4 > 0.0))
    {
        return true;
    }
    let on = |p: DVec2, q: DVec2, r: DVec2, v: f64| {
        v == 0.0
            && r.x >= p.x.min(q.x)
            && r.x <= p.x.max(q.x)
            && r.y >= p.y.min(q.y)
            && r.y <= p.y.max(q.y)
    };
    on(c, d, a, d1) || on(c, d, b, d2) || on(a, b, c, d3) || on(a, b, d, d4)
}

/// Whether the horizontal ray from `p` towards +x crosses the edge [a, b] (half-open in y, so a vertex on
/// the ray counts once): the crossing rule of [`point_in_polygon`] and [`crate::scene::index::PolygonSet`].
#[inline]
pub(crate) fn ray_crosses(p: DVec2, a: DVec2, b: DVec2) -> bool {
    (a.y > p.y) != (b.y > p.y) && p.x < (b.x - a.x) * (p.y - a.y) / (b.y - a.y) + a.x
}

/// Point in polygon, the one test every map query, metric and raster fill uses.
///
/// Boundary rule: CLOSED, a point on an edge (its distance to the edge computes to exactly 0) is inside,
/// i.e. shapely `polygon.intersects(point)` / `covers`. Interior: even-odd ray crossings, as GEOS's
/// `RayCrossingCounter` counts them, so self-intersecting rings answer like shapely. (The geo crate's
/// `coord_pos_relative_to_ring` counts a winding number instead: inside a self-overlapping ring's doubly
/// wound part it says inside where GEOS and this function say outside; that is why the score keeps this
/// function rather than geo's.)
///
/// nuPlan's map queries (`get_all_map_objects`, `is_in_layer`: the lanes, roadblocks, intersections and
/// drivable area its metrics read) call shapely `contains`, which EXCLUDES the boundary. The closed-loop
/// score here follows the closed rule ([`crate::metrics::MapQuery::lanes_at`] documents it); the two agree
/// everywhere but exactly on an edge (test `point_in_polygon_rules`). An empty or
/// degenerate polygon (fewer than 3 vertices) contains nothing.
pub fn point_in_polygon(p: DVec2, poly: &[DVec2]) -> bool {
    let n = poly.len();
    if n < 3 {
        return false;
    }
    if (0..n).any(|i| point_segment_distance(p, poly[i], poly[(i + 1) % n]) == 0.0) {
        return true;
    }
    let mut inside = false;
    let mut j = n - 1;
    for i in 0..n {
        if ray_crosses(p, poly[i], poly[j]) {
            inside = !inside;
        }
        j = i;
    }
    inside
}

/// Distance from p to the boundary of a polygon ring (0 inside is NOT applied here).
pub fn point_ring_distance(p: DVec2, ring: &[DVec2]) -> f64 {
    let n = ring.len();
    let mut d = f64::INFINITY;
    for i in 0..n {
        d = d.min(point_segment_distance(p, ring[i], ring[(i + 1) % n]));
    }
    d
}

/// shapely `polygon.distance(point)`: 0 inside or on the boundary, else the distance to the boundary;
/// infinite for an empty polygon.
pub fn point_polygon_distance(p: DVec2, poly: &[DVec2]) -> f64 {
    if point_in_polygon(p, poly) {
        0.0
    } else {
        point_ring_distance(p, poly)
    }
}

/// Separating-axis test for two convex polygons (any orientation; a segment or a point is a degenerate one:
/// zero-length edges give a zero axis, which separates nothing). Touching counts as intersecting; an empty
/// polygon intersects nothing.
pub fn convex_intersect(a: &[DVec2], b: &[DVec2]) -> bool {
    if a.is_empty() || b.is_empty() {
        return false;
    }
    fn separated(a: &[DVec2], b: &[DVec2]) -> bool {
        let n = a.len();
        for i in 0..n {
            let e = a[(i + 1) % n] - a[i];
            let axis = e.perp();
            let (mut amin, mut amax) = (f64::INFINITY, f64::NEG_INFINITY);
            for p in a {
                let v = axis.dot(*p);
                amin = amin.min(v);
                amax = amax.max(v);
            }
            let (mut bmin, mut bmax) = (f64::INFINITY, f64::NEG_INFINITY);
            for p in b {
                let v = axis.dot(*p);
                bmin = bmin.min(v);
                bmax = bmax.max(v);
            }
            if amax < bmin || bmax < amin {
                return true;
            }
        }
        false
    }
    !(separated(a, b) || separated(b, a))
}

/// Distance between two convex polygons (0 when they intersect).
pub fn convex_distance(a: &[DVec2], b: &[DVec2]) -> f64 {
    if convex_intersect(a, b) {
        return 0.0;
    }
    let mut d = f64::INFINITY;
    for p in a {
        d = d.min(point_ring_distance(*p, b));
    }
    for p in b {
        d = d.min(point_ring_distance(*p, a));
    }
    d
}

/// Menger curvature of three points: 4 * area / (|ab| |bc| |ca|), signed (positive = left turn).
pub fn menger_curvature(a: DVec2, b: DVec2, c: DVec2) -> f64 {
    let area2 = (b - a).perp_dot(c - a);
    let denom = (b - a).length() * (c - b).length() * (a - c).length();
    if denom <= 1e-12 {
        0.0
    } else {
        2.0 * area2 / denom
    }
}

/// One convex piece of a [`Shape`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Part {
    /// A convex quadrilateral (boxes, segment rectangles).
    Quad([DVec2; 4]),
    /// A disc (round joins of a buffered path).
    Disc(DVec2, f64),
}

impl Part {
    fn aabb(&self) -> Aabb {
        match self {
            Part::Quad(q) => Aabb::from_points(q),
            Part::Disc(c, r) => Aabb {
                min: *c - DVec2::splat(*r),
                max: *c + DVec2::splat(*r),
            },
        }
    }
    fn distance(&self, o: &Part) -> f64 {
        match (self, o) {
            (Part::Quad(a), Part::Quad(b)) => convex_distance(a, b),
            (Part::Quad(a), Part::Disc(c, r)) | (Part::Disc(c, r), Part::Quad(a)) => {
                (point_polygon_distance(*c, a) - r).max(0.0)
            }
            (Part::Disc(c1, r1), Part::Disc(c2, r2)) => ((*c1 - *c2).length() - r1 - r2).max(0.0),
        }
    }
    fn intersects(&self, o: &Part) -> bool {
        match (self, o) {
            (Part::Quad(a), Part::Quad(b)) => convex_intersect(a, b),
            _ => self.distance(o) <= 0.0,
        }
    }
}

/// Parts are grouped in chunks of this many for bounding-box pruning.
const CHUNK: usize = 8;

impl Aabb {
    /// Distance between two boxes (0 when they overlap): a lower bound of the distance of their contents.
    #[inline]
    pub fn distance(&self, o: &Aabb) -> f64 {
        let dx = (self.min.x - o.max.x).max(o.min.x - self.max.x).max(0.0);
        let dy = (self.min.y - o.max.y).max(o.min.y - self.max.y).max(0.0);
        (dx * dx + dy * dy).sqrt()
    }
}

/// A union of convex parts with cached bounding boxes (per part, per chunk of 8 parts, overall). Distances
/// and intersection tests between shapes are exact for the union (distance between unions = min over part
/// pairs); the boxes only prune pairs that cannot matter.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Shape {
    pub parts: Vec<Part>,
    pub boxes: Vec<Aabb>,
    /// Bounding box of parts [k * 8, k * 8 + 8).
    pub chunks: Vec<Aabb>,
    pub aabb: Option<Aabb>,
}

impl Shape {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn from_box(b: &OrientedBox) -> Self {
        let mut s = Self::new();
        s.push(Part::Quad(b.corners()));
        s
    }
    pub fn clear(&mut self) {
        self.parts.clear();
        self.boxes.clear();
        self.chunks.clear();
        self.aabb = None;
    }
    pub fn push(&mut self, p: Part) {
        let b = p.aabb();
        self.aabb = Some(match self.aabb {
            Some(a) => a.union(&b),
            None => b,
        });
        if self.parts.len() % CHUNK == 0 {
            self.chunks.push(b);
        } else if let Some(c) = self.chunks.last_mut() {
            *c = c.union(&b);
        }
        self.parts.push(p);
        self.boxes.push(b);
    }
    pub fn is_empty(&self) -> bool {
        self.parts.is_empty()
    }
    #[inline]
    fn chunk_range(&self, k: usize) -> std::ops::Range<usize> {
        k * CHUNK..((k + 1) * CHUNK).min(self.parts.len())
    }
    pub fn intersects(&self, o: &Shape) -> bool {
        let (Some(a), Some(b)) = (self.aabb, o.aabb) else {
            return false;
        };
        if !a.overlaps(&b) {
            return false;
        }
        for (ka, ca) in self.chunks.iter().enumerate() {
            if !ca.overlaps(&b) {
                continue;
            }
            for (kb, cb) in o.chunks.iter().enumerate() {
                if !ca.overlaps(cb) {
                    continue;
                }
                for i in self.chunk_range(ka) {
                    let pb = &self.boxes[i];
                    if !pb.overlaps(cb) {
                        continue;
                    }
                    for j in o.chunk_range(kb) {
                        if pb.overlaps(&o.boxes[j]) && self.parts[i].intersects(&o.parts[j]) {
                            return true;
                        }
                    }
                }
            }
        }
        false
    }
    pub fn distance(&self, o: &Shape) -> f64 {
        let mut d = f64::INFINITY;
        for (ka, ca) in self.chunks.iter().enumerate() {
            for (kb, cb) in o.chunks.iter().enumerate() {
                if ca.distance(cb) >= d {
                    continue;
                }
                for i in self.chunk_range(ka) {
                    let pb = &self.boxes[i];
                    if pb.distance(cb) >= d {
                        continue;
                    }
                    for j in o.chunk_range(kb) {
                        if pb.distance(&o.boxes[j]) >= d {
                            continue;
                        }
                        d = d.min(self.parts[i].distance(&o.parts[j]));
                        if d <= 0.0 {
                            return 0.0;
                        }
                    }
                }
            }
        }
        d
    }
    /// Appends shapely's `LineString(pts).buffer(r, cap_style=flat)` (default round joins): one rectangle per
    /// segment plus a disc at every interior vertex. On the inner side of a turn the two rectangles already
    /// cover the disc, on the outer side the disc is the round join, so the union is exact (shapely
    /// approximates the arcs with 16 segments per quarter circle; we keep true circles).
    pub fn push_buffered_path(&mut self, pts: &[DVec2], r: f64) {
        let mut prev: Option<DVec2> = None;
        let mut last_seg_end: Option<DVec2> = None;
        let mut prev_seg_dir = DVec2::X;
        for &p in pts {
            if let Some(a) = prev {
                let d = p - a;
                let len = d.length();
                if len <= 1e-9 {
                    continue;
                }
                let n = d.perp() / len * r;
                if let Some(j) = last_seg_end {
                    // The round join fills the wedge between consecutive rectangles on the outer side; its
                    // width is at most r * |turn angle|. Collinear joins (width < 1e-9 m) need no disc.
                    let prev_dir = prev_seg_dir;
                    // |sin(turn)| r bounds the wedge width for small turns.
                    let turn = prev_dir.perp_dot(d / len).abs();
                    if r * turn > 1e-9 || prev_dir.dot(d) < 0.0 {
                        self.push(Part::Disc(j, r));
                    }
                }
                prev_seg_dir = d / len;
                self.push(Part::Quad([a + n, a - n, p - n, p + n]));
                last_seg_end = Some(p);
            }
            prev = Some(p);
        }
    }
    /// Buffered path as a new shape.
    pub fn buffered_path(pts: &[DVec2], r: f64) -> Self {
        let mut s = Self::new();
        s.push_buffered_path(pts, r);
        s
    }
}

/// A buffered path (`LineString.buffer(r, cap_style=flat)`) tested lazily: only chunk bounding boxes are
/// built up front; segment rectangles and join discs are made on the fly for the chunks and segments whose
/// boxes meet the other shape. Same geometry as [`Shape::push_buffered_path`] (tested against it).
#[derive(Clone, Debug, Default)]
pub struct PathBuffer {
    pts: Vec<DVec2>,
    r: f64,
    /// Per chunk of 8 segments: (first segment, bounding box of its points expanded by r).
    chunks: Vec<(usize, Aabb)>,
    pub aabb: Option<Aabb>,
}

impl PathBuffer {
    /// Rebuilds for a new path (reusing the buffers). Repeated points are skipped.
    pub fn set(&mut self, pts: impl IntoIterator<Item = DVec2>, r: f64) {
        self.pts.clear();
        for p in pts {
            if self
                .pts
                .last()
                .is_none_or(|l: &DVec2| (p - *l).length() > 1e-9)
            {
                self.pts.push(p);
            }
        }
        self.r = r;
        self.chunks.clear();
        self.aabb = None;
        let nseg = self.pts.len().saturating_sub(1);
        let mut k = 0;
        while k < nseg {
            let end = (k + CHUNK).min(nseg);
            let b = Aabb::from_points(&self.pts[k..=end]).expand(r);
            self.aabb = Some(self.aabb.map_or(b, |a| a.union(&b)));
            self.chunks.push((k, b));
            k = end;
        }
    }
    /// Parts of segment k: its rectangle and, for k > 0, the join disc at its start when the path turns.
    fn segment_parts(&self, k: usize) -> (Part, Option<Part>) {
        let (a, p) = (self.pts[k], self.pts[k + 1]);
        let d = p - a;
        let len = d.length();
        let n = d.perp() / len * self.r;
        let quad = Part::Quad([a + n, a - n, p - n, p + n]);
        let disc = if k > 0 {
            let prev = (a - self.pts[k - 1]) / (a - self.pts[k - 1]).length();
            let turn = prev.perp_dot(d / len).abs();
            (self.r * turn > 1e-9 || prev.dot(d) < 0.0).then_some(Part::Disc(a, self.r))
        } else {
            None
        };
        (quad, disc)
    }
    /// Whether the buffered path intersects `o`.
    pub fn intersects(&self, o: &Shape) -> bool {
        let (Some(a), Some(b)) = (self.aabb, o.aabb) else {
            return false;
        };
        if !a.overlaps(&b) {
            return false;
        }
        let nseg = self.pts.len().saturating_sub(1);
        for &(k0, cb) in &self.chunks {
            if !cb.overlaps(&b) {
                continue;
            }
            for k in k0..(k0 + CHUNK).min(nseg) {
                let sb = Aabb::from_points(&self.pts[k..=k + 1]).expand(self.r);
                if !sb.overlaps(&b) {
                    continue;
                }
                let (quad, disc) = self.segment_parts(k);
                for part in std::iter::once(quad).chain(disc) {
                    let pb = part.aabb();
                    for (q, qb) in o.parts.iter().zip(&o.boxes) {
                        if pb.overlaps(qb) && part.intersects(q) {
                            return true;
                        }
                    }
                }
            }
        }
        false
    }
}

/// A polyline with cumulative arc length and per-vertex headings (driving direction).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Polyline {
    pub points: Vec<DVec2>,
    /// Heading at each vertex (radians).
    pub headings: Vec<f64>,
    /// Cumulative arc length at each vertex (s[0] = 0).
    pub s: Vec<f64>,
}

impl Polyline {
    /// Builds a polyline; headings are taken from the segment directions when not given. Repeated points
    /// (zero-length segments) are removed.
    pub fn new(points: Vec<DVec2>, headings: Option<Vec<f64>>) -> Self {
        let mut pts: Vec<DVec2> = Vec::with_capacity(points.len());
        let mut hs = Vec::with_capacity(points.len());
        for (i, p) in points.iter().enumerate() {
            if let Some(last) = pts.last().copied() {
                if (*p - last).length() < 1e-6 {
                    continue;
                }
            }
            pts.push(*p);
            hs.push(
                headings
                    .as_ref()
                    .and_then(|h| h.get(i).copied())
                    .unwrap_or(f64::NAN),
            );
        }
        let n = pts.len();
        for i in 0..n {
            if hs[i].is_nan() {
                let d = if i + 1 < n {
                    pts[i + 1] - pts[i]
                } else if i > 0 {
                    pts[i] - pts[i - 1]
                } else {
                    DVec2::X
                };
                hs[i] = d.y.atan2(d.x);
            }
        }
        let mut s = Vec::with_capacity(n);
        let mut acc = 0.0;
        for i in 0..n {
            if i > 0 {
                acc += (pts[i] - pts[i - 1]).length();
            }
            s.push(acc);
        }
        Self {
            points: pts,
            headings: hs,
            s,
        }
    }
    pub fn length(&self) -> f64 {
        self.s.last().copied().unwrap_or(0.0)
    }
    pub fn first(&self) -> DVec2 {
        self.points[0]
    }
    pub fn last(&self) -> DVec2 {
        self.points[self.points.len() - 1]
    }
    /// Nearest arc length to p and the distance to it (projection onto the polyline, like shapely's project).
    pub fn project(&self, p: DVec2) -> (f64, f64) {
        let mut best = (0.0, f64::INFINITY);
        for i in 0..self.points.len().saturating_sub(1) {
            let (a, b) = (self.points[i], self.points[i + 1]);
            let t = segment_param(p, a, b);
            let d = (a + (b - a) * t - p).length();
            if d < best.1 {
                best = (self.s[i] + t * (self.s[i + 1] - self.s[i]), d);
            }
        }
        if self.points.len() == 1 {
            best = (0.0, (self.points[0] - p).length());
        }
        best
    }
    /// Pose at arc length s (clamped); position interpolated linearly, heading from the segment direction.
    pub fn pose_at(&self, s: f64) -> Pose2 {
        let n = self.points.len();
        if n == 1 {
            return Pose2::new(self.points[0].x, self.points[0].y, self.headings[0]);
        }
        let s = s.clamp(0.0, self.length());
        let i = match self.s.binary_search_by(|v| v.total_cmp(&s)) {
            Ok(i) => i.min(n - 2),
            Err(i) => (i.max(1) - 1).min(n - 2),
        };
        let (a, b) = (self.points[i], self.points[i + 1]);
        let t = (s - self.s[i]) / (self.s[i + 1] - self.s[i]);
        let p = a + (b - a) * t;
        let d = b - a;
        Pose2::new(p.x, p.y, d.y.atan2(d.x))
    }
    /// Point at arc length s (clamped).
    pub fn point_at(&self, s: f64) -> DVec2 {
        self.pose_at(s).pos()
    }
    /// |Menger curvature| of the points at arc lengths 0, 2 and 4 m (clamped to the length); the curvature a
    /// route choice uses at the start of a lane (nuPlan `get_curvature_at_arc_length(0.0)`).
    pub fn start_curvature(&self) -> f64 {
        menger_curvature(self.point_at(0.0), self.point_at(2.0), self.point_at(4.0)).abs()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_matches_numpy_convention() {
        assert!((wrap_angle(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-12);
        assert_eq!(wrap_angle(PI), -PI);
        assert!((angle_diff(0.1, -0.1) - 0.2).abs() < 1e-12);
    }

    /// The boundary and crossing rules [`point_in_polygon`] documents.
    #[test]
    fn point_in_polygon_rules() {
        let sq = [
            DVec2::new(0.0, 0.0),
            DVec2::new(2.0, 0.0),
            DVec2::new(2.0, 2.0),
            DVec2::new(0.0, 2.0),
        ];
        // closed: edges and vertices are inside (shapely `contains` would say false for both)
        for p in [
            (1.0, 1.0),
            (2.0, 1.0),
            (1.0, 0.0),
            (0.0, 0.0),
            (2.0, 2.0),
            (0.0, 1.3),
        ] {
            assert!(point_in_polygon(DVec2::new(p.0, p.1), &sq), "{p:?}");
        }
        for p in [
            (2.0 + 1e-12, 1.0),
            (-1e-12, 0.5),
            (1.0, 2.0 + 1e-12),
            (3.0, 3.0),
        ] {
            assert!(!point_in_polygon(DVec2::new(p.0, p.1), &sq), "{p:?}");
        }
        // winding order does not matter
        let rev: Vec<DVec2> = sq.iter().rev().copied().collect();
        assert!(point_in_polygon(DVec2::new(1.0, 1.0), &rev));
        assert!(point_in_polygon(DVec2::new(2.0, 1.0), &rev));
        // a pentagram (self-intersecting): its centre is crossed twice, so even-odd (GEOS) says outside,
        // where a winding-number rule (geo) would say inside; a tip is inside either way
        let star: Vec<DVec2> = (0..5)
            .map(|k| {
                let a = std::f64::consts::FRAC_PI_2 + k as f64 * 4.0 * PI / 5.0;
                DVec2::new(a.cos(), a.sin()) * 10.0
            })
            .collect();
        assert!(!point_in_polygon(DVec2::ZERO, &star));
        assert!(point_in_polygon(DVec2::new(0.0, 8.0), &star));
        // fewer than 3 vertices: nothing is inside, not even the vertices
        assert!(!point_in_polygon(DVec2::ZERO, &[DVec2::ZERO, DVec2::X]));
        // the distance follows: 0 on the boundary
        assert_eq!(point_polygon_distance(DVec2::new(2.0, 1.0), &sq), 0.0);
        assert_eq!(point_polygon_distance(DVec2::new(3.0, 1.0), &sq), 1.0);
    }

    #[test]
    fn pose_compose_relative_roundtrip() {
        let a = Pose2::new(1.0, 2.0, 0.7);
        let l = Pose2::new(3.0, -1.0, 0.2);
        let g = a.compose(&l);
        let back = a.relative(&g);
        assert!(
            (back.x - 3.0).abs() < 1e-12
                && (back.y + 1.0).abs() < 1e-12
                && (back.heading - 0.2).abs() < 1e-12
        );
    }

    #[test]
    fn box_sat_and_distance() {
        let a = OrientedBox::new(Pose2::new(0.0, 0.0, 0.0), 4.0, 2.0);
        let b = OrientedBox::new(Pose2::new(6.0, 0.0, 0.0), 4.0, 2.0);
        assert!((convex_distance(&a.corners(), &b.corners()) - 2.0).abs() < 1e-12);
        let c = OrientedBox::new(Pose2::new(3.5, 0.0, PI / 4.0), 4.0, 2.0);
        assert!(convex_intersect(&a.corners(), &c.corners()));
    }

    #[test]
    fn flat_buffer_has_flat_caps_and_round_joins() {
        // L-shaped path (0,0)->(10,0)->(10,10), half width 1.
        let s = Shape::buffered_path(
            &[DVec2::ZERO, DVec2::new(10.0, 0.0), DVec2::new(10.0, 10.0)],
            1.0,
        );
        let probe = |x: f64, y: f64| {
            let mut p = Shape::new();
            p.push(Part::Disc(DVec2::new(x, y), 0.0));
            s.distance(&p)
        };
        // Flat cap: a point 0.5 m behind the start is 0.5 m away (a round cap would give 0.5 too on-axis,
        // but at (-0.5, 0.9) flat gives 0.5 and round gives ~0.03).
        assert!((probe(-0.5, 0.9) - 0.5).abs() < 1e-12);
        // Round join at the outer corner (10,0): the point (11.5, -1.5) is sqrt(2)*1.5 - 1 away.
        assert!((probe(11.5, -1.5) - (2.0f64.sqrt() * 1.5 - 1.0)).abs() < 1e-12);
        assert_eq!(probe(9.5, 0.5), 0.0);
    }

    #[test]
    fn lazy_path_buffer_matches_shape() {
        let pts: Vec<DVec2> = (0..40)
            .map(|i| DVec2::new(i as f64, (i as f64 * 0.2).sin() * 3.0))
            .collect();
        let full = Shape::buffered_path(&pts, 1.0);
        let mut lazy = PathBuffer::default();
        lazy.set(pts.iter().copied(), 1.0);
        for ix in -5..45 {
            for iy in -6..7 {
                let b = OrientedBox::new(
                    Pose2::new(ix as f64, iy as f64 * 0.7, 0.3 * ix as f64),
                    1.2,
                    0.4,
                );
                let s = Shape::from_box(&b);
                assert_eq!(full.intersects(&s), lazy.intersects(&s), "{ix} {iy}");
            }
        }
    }

    #[test]
    fn menger_of_circle_points() {
        let r = 5.0;
        let p = |a: f64| DVec2::new(r * a.cos(), r * a.sin());
        assert!((menger_curvature(p(0.0), p(0.3), p(0.7)) - 1.0 / r).abs() < 1e-12);
    }

    #[test]
    fn polyline_project_and_pose() {
        let pl = Polyline::new(
            vec![DVec2::ZERO, DVec2::new(10.0, 0.0), DVec2::new(10.0, 10.0)],
            None,
        );
        assert_eq!(pl.length(), 20.0);
        let (s, d) = pl.project(DVec2::new(12.0, 4.0));
        assert!((s - 14.0).abs() < 1e-12 && (d - 2.0).abs() < 1e-12);
        let q = pl.pose_at(15.0);
        assert!(
            (q.x - 10.0).abs() < 1e-12
                && (q.y - 5.0).abs() < 1e-12
                && (q.heading - PI / 2.0).abs() < 1e-12
        );
    }
}
