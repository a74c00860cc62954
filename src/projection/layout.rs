//! The projected layout condition: boxes and map elements of one camera rasterised as per-class binary masks.
//!
//! Channel order: [`BoxClass::ALL`] (10 channels) then [`MapClass::ALL`] (5 channels); see
//! [`crate::projection::geometry::channel_name`]. Boxes are filled solids: the union of a convex box's projected
//! faces is the convex hull of its projected (near-clipped) vertices, so each box is filled as one convex polygon
//! (the same pixels as filling its six Sutherland-Hodgman-clipped faces, at a sixth of the cost).
use glam::{DVec2, DVec3};

use super::geometry::{
    clip_polygon_z, clip_segment_z, Box3d, CameraProjector, MapGeometry, MapLayer,
    ProjectionConfig, BOX_EDGES, BOX_FACES, NUM_MASK_CHANNELS,
};
use super::raster::{convex_hull, Rasterizer};
use crate::projection::geometry::BoxClass;

/// Per-class binary masks of one camera. `data: (C, H, W)` row-major, values 0 or 1, `C = NUM_MASK_CHANNELS`.
#[derive(Clone, Debug, PartialEq)]
pub struct LayoutMasks {
    pub width: usize,
    pub height: usize,
    pub data: Vec<u8>,
}

impl LayoutMasks {
    pub fn new(width: usize, height: usize) -> Self {
        LayoutMasks {
            width,
            height,
            data: vec![0; NUM_MASK_CHANNELS * width * height],
        }
    }

    /// Channel `c`: `(H, W)`.
    pub fn channel(&self, c: usize) -> &[u8] {
        let n = self.width * self.height;
        &self.data[c * n..(c + 1) * n]
    }

    pub fn channel_mut(&mut self, c: usize) -> &mut [u8] {
        let n = self.width * self.height;
        &mut self.data[c * n..(c + 1) * n]
    }

    pub fn clear(&mut self) {
        self.data.fill(0);
    }

    /// Masks as f32 in {0, 1}: `(C, H, W)` (the ControlNet conditioning input of one camera).
    pub fn to_f32(&self) -> Vec<f32> {
        self.data.iter().map(|&v| v as f32).collect()
    }
}

/// Rasterises layouts; holds reusable scratch buffers (one per thread / image size).
#[derive(Clone, Debug)]
pub struct LayoutRenderer {
    raster: Rasterizer,
    face: Vec<DVec3>,
    clipped: Vec<DVec3>,
    clipped2: Vec<DVec3>,
    pts: Vec<[f32; 2]>,
    hull: Vec<[f32; 2]>,
    cam_pts: Vec<DVec3>,
}

impl LayoutRenderer {
    pub fn new(width: usize, height: usize) -> Self {
        LayoutRenderer {
            raster: Rasterizer::new(width, height),
            face: Vec::with_capacity(8),
            clipped: Vec::with_capacity(16),
            clipped2: Vec::with_capacity(16),
            pts: Vec::with_capacity(32),
            hull: Vec::with_capacity(32),
            cam_pts: Vec::new(),
        }
    }

    /// Renders all boxes and map elements seen by `proj` into `out` (cleared first). `proj` must have the
    /// renderer's image size. Returns the number of boxes that survived culling.
    pub fn render(
        &mut self,
        proj: &CameraProjector,
        boxes: &[Box3d],
        map: &MapLayer,
        cfg: &ProjectionConfig,
        out: &mut LayoutMasks,
    ) -> usize {
        debug_assert_eq!(
            (proj.width as usize, proj.height as usize),
            (out.width, out.height)
        );
        debug_assert_eq!(
            (out.width, out.height),
            (self.raster.width(), self.raster.height())
        );
        out.clear();
        let nbox = BoxClass::ALL.len();
        for i in 0..map.len() {
            let e = &map.elements()[i];
            self.draw_map_element(
                proj,
                &e.geometry,
                map.bounds(i),
                cfg,
                out.channel_mut(nbox + e.class.index()),
            );
        }
        let mut drawn = 0;
        for b in boxes {
            if let Some(cs) = proj.box_corners_camera(b, cfg) {
                self.fill_box(proj, &cs, cfg.near, out.channel_mut(b.class.index()));
                drawn += 1;
            }
        }
        drawn
    }

    /// Fills a (non-culled) box given by its camera-frame corners into `mask: (H, W)`.
    pub fn fill_box(
        &mut self,
        proj: &CameraProjector,
        cs: &[DVec3; 8],
        near: f64,
        mask: &mut [u8],
    ) -> usize {
        self.pts.clear();
        if cs.iter().all(|p| p.z >= near) {
            for p in cs {
                self.pts.push(px32(proj.pixel_of_camera_point(*p)));
            }
        } else {
            for f in BOX_FACES {
                self.face.clear();
                self.face.extend(f.iter().map(|&i| cs[i]));
                clip_polygon_z(&self.face, near, true, &mut self.clipped);
                for p in &self.clipped {
                    self.pts.push(px32(proj.pixel_of_camera_point(*p)));
                }
            }
        }
        convex_hull(&mut self.pts, &mut self.hull);
        self.raster.add_ring(&self.hull);
        self.raster.fill(mask)
    }

    fn draw_map_element(
        &mut self,
        proj: &CameraProjector,
        g: &MapGeometry,
        (lo, hi): (DVec3, DVec3),
        cfg: &ProjectionConfig,
        mask: &mut [u8],
    ) {
        // range culling on the bounds: distance from the camera to the nearest point of the box
        let nearest = proj.position.clamp(lo, hi);
        if nearest.distance_squared(proj.position) > cfg.range * cfg.range {
            return;
        }
        let corners: [DVec3; 8] = std::array::from_fn(|i| {
            proj.to_camera(DVec3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            ))
        });
        if proj.frustum_culls(&corners, cfg.near, Some(cfg.range)) {
            return;
        }
        match g {
            MapGeometry::Polyline(line) => {
                self.cam_pts.clear();
                self.cam_pts.extend(line.iter().map(|p| proj.to_camera(*p)));
                for s in self.cam_pts.windows(2) {
                    if proj.frustum_culls(s, cfg.near, Some(cfg.range)) {
                        continue;
                    }
                    if let Some((a, b)) = clip_segment_z(s[0], s[1], cfg.near, cfg.range) {
                        let (pa, pb) =
                            (proj.pixel_of_camera_point(a), proj.pixel_of_camera_point(b));
                        self.raster
                            .draw_segment(px32(pa), px32(pb), cfg.line_width_px, mask);
                    }
                }
            }
            MapGeometry::Polygon { exterior, holes } => {
                for ring in std::iter::once(exterior).chain(holes.iter()) {
                    self.cam_pts.clear();
                    self.cam_pts.extend(ring.iter().map(|p| proj.to_camera(*p)));
                    clip_polygon_z(&self.cam_pts, cfg.near, true, &mut self.clipped);
                    clip_polygon_z(&self.clipped, cfg.range, false, &mut self.clipped2);
                    self.pts.clear();
                    for p in &self.clipped2 {
                        self.pts.push(px32(proj.pixel_of_camera_point(*p)));
                    }
                    self.raster.add_ring(&self.pts);
                }
                self.raster.fill(mask);
            }
        }
    }
}

#[inline]
fn px32(p: DVec2) -> [f32; 2] {
    [p.x as f32, p.y as f32]
}

/// The 12 edges of a box as pixel segments, each clipped against the near plane (edges entirely behind it are
/// left out). `None` when the box is culled (range or frustum).
pub fn box_wireframe(
    proj: &CameraProjector,
    b: &Box3d,
    cfg: &ProjectionConfig,
) -> Option<Vec<(DVec2, DVec2)>> {
    let cs = proj.box_corners_camera(b, cfg)?;
    let mut out = Vec::with_capacity(12);
    for (i, j) in BOX_EDGES {
        if let Some((a, c)) = clip_segment_z(cs[i], cs[j], cfg.near, f64::INFINITY) {
            out.push((proj.pixel_of_camera_point(a), proj.pixel_of_camera_point(c)));
        }
    }
    Some(out)
}
