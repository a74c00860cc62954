//! Scene geometry for projection: classes, 3D boxes, map elements, and the per-camera projector (transform,
//! frustum/range culling, near/far-plane clipping in 3D).
//!
//! Frames: global (map, metres) -> ego (x forward, y left, z up; the pose at the image's exposure time) ->
//! camera (x right, y down, z forward) -> pixels `u = (K p)_x / p_z` with pixel centres at integer coordinates.
//! Clipping happens in the camera frame against the plane `z = near` (and `z = range` for map geometry), before
//! the division by depth, so geometry crossing the camera plane is cut, never wrapped through infinity.
use anyhow::{ensure, Result};
use glam::{DAffine3, DMat3, DMat4, DVec2, DVec3, DVec4};

use crate::scene::camera::Camera;

/// Box classes, one mask channel each, in channel order (nuScenes detection categories).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BoxClass {
    Car,
    Truck,
    Bus,
    Trailer,
    ConstructionVehicle,
    Pedestrian,
    Motorcycle,
    Bicycle,
    TrafficCone,
    Barrier,
}

impl BoxClass {
    pub const ALL: [BoxClass; 10] = [
        BoxClass::Car,
        BoxClass::Truck,
        BoxClass::Bus,
        BoxClass::Trailer,
        BoxClass::ConstructionVehicle,
        BoxClass::Pedestrian,
        BoxClass::Motorcycle,
        BoxClass::Bicycle,
        BoxClass::TrafficCone,
        BoxClass::Barrier,
    ];

    /// The nuScenes detection name (also the mask file stem).
    pub fn name(self) -> &'static str {
        match self {
            BoxClass::Car => "car",
            BoxClass::Truck => "truck",
            BoxClass::Bus => "bus",
            BoxClass::Trailer => "trailer",
            BoxClass::ConstructionVehicle => "construction_vehicle",
            BoxClass::Pedestrian => "pedestrian",
            BoxClass::Motorcycle => "motorcycle",
            BoxClass::Bicycle => "bicycle",
            BoxClass::TrafficCone => "traffic_cone",
            BoxClass::Barrier => "barrier",
        }
    }

    /// Parses a detection name (`car`) or a full nuScenes category (`vehicle.car`, `human.pedestrian.adult`,
    /// `movable_object.trafficcone`, ...).
    pub fn parse(s: &str) -> Option<BoxClass> {
        if let Some(c) = BoxClass::ALL.into_iter().find(|c| c.name() == s) {
            return Some(c);
        }
        let c = match s {
            s if s.starts_with("human.pedestrian") => BoxClass::Pedestrian,
            "vehicle.car" | "vehicle.emergency.police" => BoxClass::Car,
            "vehicle.truck" => BoxClass::Truck,
            "vehicle.bus.bendy" | "vehicle.bus.rigid" => BoxClass::Bus,
            "vehicle.trailer" => BoxClass::Trailer,
            "vehicle.construction" => BoxClass::ConstructionVehicle,
            "vehicle.motorcycle" => BoxClass::Motorcycle,
            "vehicle.bicycle" => BoxClass::Bicycle,
            "movable_object.trafficcone" => BoxClass::TrafficCone,
            "movable_object.barrier" => BoxClass::Barrier,
            _ => return None,
        };
        Some(c)
    }

    pub fn index(self) -> usize {
        self as usize
    }
}

/// Map classes, one mask channel each, in channel order after the box channels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum MapClass {
    /// Polygon: the drivable surface.
    DrivableArea,
    /// Polygon: one lane's surface.
    Lane,
    /// Polygon: a pedestrian crossing.
    Crosswalk,
    /// Polyline: a marking between lanes.
    LaneDivider,
    /// Polyline: the edge of the road.
    RoadBoundary,
}

impl MapClass {
    pub const ALL: [MapClass; 5] = [
        MapClass::DrivableArea,
        MapClass::Lane,
        MapClass::Crosswalk,
        MapClass::LaneDivider,
        MapClass::RoadBoundary,
    ];

    pub fn name(self) -> &'static str {
        match self {
            MapClass::DrivableArea => "drivable_area",
            MapClass::Lane => "lane",
            MapClass::Crosswalk => "crosswalk",
            MapClass::LaneDivider => "lane_divider",
            MapClass::RoadBoundary => "road_boundary",
        }
    }

    pub fn index(self) -> usize {
        self as usize
    }
}

/// Number of mask channels: box classes then map classes.
pub const NUM_MASK_CHANNELS: usize = BoxClass::ALL.len() + MapClass::ALL.len();

/// Name of mask channel `c` (box classes first, then map classes).
pub fn channel_name(c: usize) -> &'static str {
    if c < BoxClass::ALL.len() {
        BoxClass::ALL[c].name()
    } else {
        MapClass::ALL[c - BoxClass::ALL.len()].name()
    }
}

/// An oriented 3D box in the global frame (yaw about +z only, as nuScenes annotations).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Box3d {
    pub class: BoxClass,
    /// Gravity centre (global, metres).
    pub center: DVec3,
    /// (length along the heading, width, height).
    pub size: DVec3,
    /// Heading about +z (rad, 0 = +x).
    pub yaw: f64,
}

/// Box corner order (nuScenes `Box.corners()`): 0..4 the front face (+length/2), 4..8 the rear face;
/// within a face: (+w,+h), (-w,+h), (-w,-h), (+w,-h) with w along +y (left) and h along +z (up).
pub const BOX_EDGES: [(usize, usize); 12] = [
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 0),
    (4, 5),
    (5, 6),
    (6, 7),
    (7, 4),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
];

/// The six faces of a box as corner indices (see [`BOX_EDGES`] for the order).
pub const BOX_FACES: [[usize; 4]; 6] = [
    [0, 1, 2, 3],
    [4, 5, 6, 7],
    [0, 1, 5, 4],
    [1, 2, 6, 5],
    [2, 3, 7, 6],
    [3, 0, 4, 7],
];

impl Box3d {
    /// The 8 corners in the global frame, in the order of [`BOX_EDGES`].
    pub fn corners(&self) -> [DVec3; 8] {
        let (l, w, h) = (self.size.x * 0.5, self.size.y * 0.5, self.size.z * 0.5);
        let xs = [l, l, l, l, -l, -l, -l, -l];
        let ys = [w, -w, -w, w, w, -w, -w, w];
        let zs = [h, h, -h, -h, h, h, -h, -h];
        let (s, c) = self.yaw.sin_cos();
        std::array::from_fn(|i| {
            self.center + DVec3::new(c * xs[i] - s * ys[i], s * xs[i] + c * ys[i], zs[i])
        })
    }
}

/// Geometry of one map element, in the global frame (metres; z is the ground height).
#[derive(Clone, Debug, PartialEq)]
pub enum MapGeometry {
    /// An open polyline (drawn as a thick line).
    Polyline(Vec<DVec3>),
    /// A polygon: exterior ring plus holes (any orientation; filled with the even-odd rule).
    Polygon {
        exterior: Vec<DVec3>,
        holes: Vec<Vec<DVec3>>,
    },
}

/// One map element with its class.
#[derive(Clone, Debug, PartialEq)]
pub struct MapElement {
    pub class: MapClass,
    pub geometry: MapGeometry,
}

/// A map ready for projection: elements plus their axis-aligned bounds (for culling without touching vertices).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MapLayer {
    elements: Vec<MapElement>,
    bounds: Vec<(DVec3, DVec3)>,
}

impl MapLayer {
    /// Builds the layer; elements without vertices are dropped.
    pub fn new(elements: Vec<MapElement>) -> Self {
        let mut layer = MapLayer::default();
        for e in elements {
            layer.push(e);
        }
        layer
    }

    pub fn push(&mut self, e: MapElement) {
        let pts: &[DVec3] = match &e.geometry {
            MapGeometry::Polyline(p) => p,
            MapGeometry::Polygon { exterior, .. } => exterior,
        };
        if pts.is_empty() {
            return;
        }
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for p in pts {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
        self.bounds.push((lo, hi));
        self.elements.push(e);
    }

    pub fn elements(&self) -> &[MapElement] {
        &self.elements
    }

    /// Axis-aligned bounds `(min, max)` of element `i`'s vertices (exterior ring for polygons).
    pub fn bounds(&self, i: usize) -> (DVec3, DVec3) {
        self.bounds[i]
    }

    pub fn len(&self) -> usize {
        self.elements.len()
    }

    pub fn is_empty(&self) -> bool {
        self.elements.is_empty()
    }
}

/// Knobs of the projection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectionConfig {
    /// Near clipping plane (camera depth, metres).
    pub near: f64,
    /// Culling range (metres): boxes whose centre is farther than this from the camera are dropped; map geometry
    /// is dropped when its bounds are farther, and clipped at camera depth `range`.
    pub range: f64,
    /// Thickness of map polylines in pixels of the mask image.
    pub line_width_px: f32,
}

impl Default for ProjectionConfig {
    fn default() -> Self {
        ProjectionConfig {
            near: 0.1,
            range: 80.0,
            line_width_px: 2.0,
        }
    }
}

/// One camera ready for projection at a given image size: global -> camera transform and intrinsics at that size.
#[derive(Clone, Debug)]
pub struct CameraProjector {
    pub name: String,
    /// Intrinsics at `width x height` (rescaled from the native size with the pixel-centre convention).
    pub k: DMat3,
    pub width: u32,
    pub height: u32,
    /// Global -> camera.
    pub world2cam: DAffine3,
    /// Camera centre in the global frame.
    pub position: DVec3,
    /// Side planes of the view frustum in the camera frame: `n . p >= 0` inside (left, right, top, bottom).
    planes: [DVec3; 4],
}

impl CameraProjector {
    /// `ego2global`: the ego pose at this camera's exposure time. `width x height`: the image size to project to
    /// (the native size or a render size; intrinsics are rescaled accordingly).
    pub fn new(camera: &Camera, ego2global: &DMat4, width: u32, height: u32) -> Result<Self> {
        ensure!(
            width > 0 && height > 0,
            "camera {}: image size {width}x{height} must be positive",
            camera.name
        );
        ensure!(
            camera.width > 0 && camera.height > 0,
            "camera {}: native size must be positive",
            camera.name
        );
        let k = camera.intrinsic_scaled(width, height);
        ensure!(
            k.x_axis.x > 0.0 && k.y_axis.y > 0.0 && k.z_axis.z == 1.0 && k.x_axis.y == 0.0 && k.x_axis.z == 0.0,
            "camera {}: intrinsic must be upper-triangular with positive focal lengths and K[2][2] = 1",
            camera.name
        );
        let cam2global = DAffine3::from_mat4(*ego2global * camera.cam2ego);
        ensure!(
            cam2global.matrix3.determinant().abs() > 1e-9,
            "camera {}: singular pose",
            camera.name
        );
        let world2cam = cam2global.inverse();
        let (fx, s, cx, fy, cy) = (k.x_axis.x, k.y_axis.x, k.z_axis.x, k.y_axis.y, k.z_axis.y);
        // u = (fx x + s y)/z + cx in [-0.5, W - 0.5]  <=>  fx x + s y + (cx + 0.5) z >= 0 and
        // -(fx x + s y) + (W - 0.5 - cx) z >= 0; same for v.
        let (w, h) = (width as f64, height as f64);
        let planes = [
            DVec3::new(fx, s, cx + 0.5),
            DVec3::new(-fx, -s, w - 0.5 - cx),
            DVec3::new(0.0, fy, cy + 0.5),
            DVec3::new(0.0, -fy, h - 0.5 - cy),
        ];
        Ok(CameraProjector {
            name: camera.name.clone(),
            k,
            width,
            height,
            world2cam,
            position: cam2global.translation,
            planes,
        })
    }

    /// Global point -> camera frame.
    #[inline]
    pub fn to_camera(&self, p: DVec3) -> DVec3 {
        self.world2cam.transform_point3(p)
    }

    /// Camera-frame point -> pixel (no depth check: the caller guarantees `p.z > 0`).
    #[inline]
    pub fn pixel_of_camera_point(&self, p: DVec3) -> DVec2 {
        let q = self.k * p;
        DVec2::new(q.x / q.z, q.y / q.z)
    }

    /// Global point -> (pixel, depth) when in front of the camera (`depth > 0`), pixel possibly outside the image.
    pub fn project(&self, p: DVec3) -> Option<(DVec2, f64)> {
        let c = self.to_camera(p);
        (c.z > 0.0).then(|| (self.pixel_of_camera_point(c), c.z))
    }

    /// Whether a pixel lies in the image (`-0.5 <= u < W - 0.5`, same for v).
    pub fn in_image(&self, px: DVec2) -> bool {
        px.x >= -0.5
            && px.y >= -0.5
            && px.x < self.width as f64 - 0.5
            && px.y < self.height as f64 - 0.5
    }

    /// True when every point of `pts` (camera frame) is outside one same plane of the frustum (near plane
    /// `z >= near`, the four side planes, and `z <= far` when given): the convex hull of `pts` cannot be seen.
    pub fn frustum_culls(&self, pts: &[DVec3], near: f64, far: Option<f64>) -> bool {
        if pts.iter().all(|p| p.z < near) {
            return true;
        }
        if let Some(f) = far {
            if pts.iter().all(|p| p.z > f) {
                return true;
            }
        }
        self.planes
            .iter()
            .any(|n| pts.iter().all(|p| n.dot(*p) < 0.0))
    }

    /// Camera-frame corners of `b`, or `None` when the box is culled (centre beyond `cfg.range` from the camera,
    /// or entirely outside the view frustum).
    pub fn box_corners_camera(&self, b: &Box3d, cfg: &ProjectionConfig) -> Option<[DVec3; 8]> {
        if b.center.distance_squared(self.position) > cfg.range * cfg.range {
            return None;
        }
        let cs = b.corners().map(|p| self.to_camera(p));
        (!self.frustum_culls(&cs, cfg.near, None)).then_some(cs)
    }
}

/// Sutherland-Hodgman clip of a polygon (camera frame) against the half-space `sign * (z - plane) >= 0`,
/// appending the result to `out` (cleared first).
pub fn clip_polygon_z(poly: &[DVec3], plane: f64, keep_greater: bool, out: &mut Vec<DVec3>) {
    out.clear();
    let n = poly.len();
    if n == 0 {
        return;
    }
    let d = |p: &DVec3| {
        if keep_greater {
            p.z - plane
        } else {
            plane - p.z
        }
    };
    let mut prev = poly[n - 1];
    let mut dp = d(&prev);
    for &cur in poly {
        let dc = d(&cur);
        if dc >= 0.0 {
            if dp < 0.0 {
                out.push(prev + (cur - prev) * (dp / (dp - dc)));
            }
            out.push(cur);
        } else if dp >= 0.0 {
            out.push(prev + (cur - prev) * (dp / (dp - dc)));
        }
        prev = cur;
        dp = dc;
    }
}

/// Clips segment `a-b` (camera frame) to `near <= z <= far`; `None` when nothing remains.
pub fn clip_segment_z(a: DVec3, b: DVec3, near: f64, far: f64) -> Option<(DVec3, DVec3)> {
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    let dz = b.z - a.z;
    // near: a.z + t dz >= near ; far: a.z + t dz <= far
    for (num, den) in [(a.z - near, dz), (far - a.z, -dz)] {
        // num + t den >= 0
        if den == 0.0 {
            if num < 0.0 {
                return None;
            }
        } else {
            let t = -num / den;
            if den > 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
        }
    }
    (t0 <= t1).then(|| (a + (b - a) * t0, a + (b - a) * t1))
}

/// Homogeneous helper: row-major 4x4 (as in JSON files) -> glam matrix.
pub fn mat4_from_rows(rows: &[[f64; 4]; 4]) -> DMat4 {
    DMat4::from_cols_array_2d(rows).transpose()
}

/// Row-major 3x3 -> glam matrix.
pub fn mat3_from_rows(rows: &[[f64; 3]; 3]) -> DMat3 {
    DMat3::from_cols_array_2d(rows).transpose()
}

/// `v` as a point in homogeneous coordinates.
pub fn point4(v: DVec3) -> DVec4 {
    v.extend(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn segment_clip_keeps_front_part() {
        let (a, b) = clip_segment_z(
            DVec3::new(0.0, 0.0, -1.0),
            DVec3::new(0.0, 0.0, 3.0),
            1.0,
            100.0,
        )
        .unwrap();
        assert!((a.z - 1.0).abs() < 1e-12 && (b.z - 3.0).abs() < 1e-12);
        assert!(clip_segment_z(
            DVec3::new(0.0, 0.0, -1.0),
            DVec3::new(1.0, 0.0, 0.5),
            1.0,
            100.0
        )
        .is_none());
    }

    #[test]
    fn polygon_clip_half_behind() {
        let sq = [
            DVec3::new(-1.0, 0.0, -1.0),
            DVec3::new(1.0, 0.0, -1.0),
            DVec3::new(1.0, 0.0, 3.0),
            DVec3::new(-1.0, 0.0, 3.0),
        ];
        let mut out = Vec::new();
        clip_polygon_z(&sq, 1.0, true, &mut out);
        assert_eq!(out.len(), 4);
        assert!(out.iter().all(|p| p.z >= 1.0 - 1e-12));
    }

    #[test]
    fn class_parsing() {
        assert_eq!(BoxClass::parse("vehicle.car"), Some(BoxClass::Car));
        assert_eq!(
            BoxClass::parse("human.pedestrian.adult"),
            Some(BoxClass::Pedestrian)
        );
        assert_eq!(BoxClass::parse("traffic_cone"), Some(BoxClass::TrafficCone));
        assert_eq!(BoxClass::parse("animal"), None);
        assert_eq!(channel_name(10), "drivable_area");
    }
}
