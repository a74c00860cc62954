//! The CPU ground-truth camera renderer: per camera, a sky gradient and the ground plane (analytic ray-plane
//! depth, procedural texture, distance fog), the flat ground layers painted in order, then every solid's faces
//! z-buffered with per-pixel depth from the face plane (`1/z` is affine in the pixel coordinates), Lambert-lit
//! (one sun), back-face, frustum and range culled.
//!
//! Conventions are projection's (`crate::projection::geometry`): ego x forward, y left, z up; camera x right,
//! y down, z forward; pixel `(i, j)` has its centre at `(u, v) = (i, j)`; polygons cover the pixels whose centre
//! lies inside (the same scanline rule as the layout masks, [`Rasterizer::fill_spans`]). Depth is the camera z.
//! Deterministic: no randomness, no threads inside one camera; the same inputs give the same bytes.
use super::objects::{object_solid, WorldObject};
use super::palette::{mix64, Palette, Rgb, SemanticClass};
use super::scenery::Scenery;
use super::shapes::Solid;
use crate::projection::geometry::{clip_polygon_z, CameraProjector};
use crate::projection::raster::Rasterizer;
use crate::scene::camera::Camera;
use anyhow::Result;
use glam::{DMat3, DMat4, DVec3};

/// Knobs of a render.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderOptions {
    /// Near plane (camera depth, m).
    pub near: f64,
    /// Range (m): nothing farther is drawn; fog reaches the horizon colour there.
    pub range: f64,
    /// Fog starts at this depth (m).
    pub fog_start: f64,
    /// Draw the static scenery (ground layers and roadside solids); off: sky, bare ground and the objects.
    pub scenery: bool,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            near: 0.1,
            range: 120.0,
            fog_start: 35.0,
            scenery: true,
        }
    }
}

/// One camera's ground truth. Row-major `(H, W)` planes; `rgb: (H, W, 3)` interleaved.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraFrame {
    pub camera: String,
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
    /// Camera depth (m); `f32::INFINITY` for sky.
    pub depth: Vec<f32>,
    /// [`SemanticClass`] ids.
    pub class: Vec<u8>,
    /// Object instance ids (track index + 1), 0 elsewhere.
    pub instance: Vec<u32>,
}

impl CameraFrame {
    /// RGB as planes: `(3, H, W)`.
    pub fn rgb_planar(&self) -> Vec<u8> {
        let n = self.width * self.height;
        let mut out = vec![0u8; 3 * n];
        for p in 0..n {
            for c in 0..3 {
                out[c * n + p] = self.rgb[3 * p + c];
            }
        }
        out
    }
}

/// Camera geometry for one render.
struct View {
    proj: CameraProjector,
    kinv: DMat3,
    /// Camera -> world rotation.
    c2w: DMat3,
    /// Side planes (camera frame, unit normals, inside `n . p >= 0`).
    planes: [DVec3; 4],
}

impl View {
    fn new(cam: &Camera, ego2global: &DMat4, w: u32, h: u32) -> Result<View> {
        let proj = CameraProjector::new(cam, ego2global, w, h)?;
        let kinv = proj.k.inverse();
        let c2w = proj.world2cam.matrix3.inverse();
        let (fx, s, cx, fy, cy) = (
            proj.k.x_axis.x,
            proj.k.y_axis.x,
            proj.k.z_axis.x,
            proj.k.y_axis.y,
            proj.k.z_axis.y,
        );
        let (wf, hf) = (w as f64, h as f64);
        let planes = [
            DVec3::new(fx, s, cx + 0.5),
            DVec3::new(-fx, -s, wf - 0.5 - cx),
            DVec3::new(0.0, fy, cy + 0.5),
            DVec3::new(0.0, -fy, hf - 0.5 - cy),
        ]
        .map(|n| n.normalize());
        Ok(View {
            proj,
            kinv,
            c2w,
            planes,
        })
    }

    /// Whether a sphere (global centre, radius) may be seen within `range`.
    fn sees_sphere(&self, c: DVec3, r: f64, near: f64, range: f64) -> bool {
        let p = self.proj.to_camera(c);
        p.z + r >= near && p.length() - r <= range && self.planes.iter().all(|n| n.dot(p) >= -r)
    }
}

#[inline]
fn smoothstep(a: f32, b: f32, x: f32) -> f32 {
    let t = ((x - a) / (b - a)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

#[inline]
fn lerp3(a: Rgb, b: Rgb, t: f32) -> Rgb {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

#[inline]
fn put(rgb: &mut [u8], p: usize, c: Rgb) {
    for k in 0..3 {
        rgb[3 * p + k] = (c[k].clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    }
}

/// Value in [-1, 1] of a lattice hash at integer cell (x, y).
#[inline]
fn cell_noise(x: f64, y: f64, salt: u64) -> f32 {
    let h = mix64(
        (x.floor() as i64 as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)
            ^ (y.floor() as i64 as u64)
            ^ salt,
    );
    ((h >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
}

/// Scratch state of one camera render (reused across renders of the same size).
pub struct Canvas {
    frame: CameraFrame,
    fog: Vec<f32>,
    shade: Vec<f32>,
    raster: Rasterizer,
    cam_pts: Vec<DVec3>,
    clipped: Vec<DVec3>,
    clipped2: Vec<DVec3>,
    px: Vec<[f32; 2]>,
}

impl Canvas {
    pub fn new(width: usize, height: usize) -> Canvas {
        let n = width * height;
        Canvas {
            frame: CameraFrame {
                camera: String::new(),
                width,
                height,
                rgb: vec![0; 3 * n],
                depth: vec![f32::INFINITY; n],
                class: vec![0; n],
                instance: vec![0; n],
            },
            fog: vec![0.0; n],
            shade: vec![1.0; n],
            raster: Rasterizer::new(width, height),
            cam_pts: Vec::new(),
            clipped: Vec::new(),
            clipped2: Vec::new(),
            px: Vec::new(),
        }
    }

    /// Renders one camera and returns a copy of its frame.
    pub fn render(
        &mut self,
        scenery: &Scenery,
        cam: &Camera,
        ego2global: &DMat4,
        objects: &[WorldObject],
        opt: &RenderOptions,
    ) -> Result<CameraFrame> {
        let (w, h) = (self.frame.width, self.frame.height);
        let view = View::new(cam, ego2global, w as u32, h as u32)?;
        self.frame.camera = cam.name.clone();
        self.base(&view, &scenery.palette, opt);
        if opt.scenery {
            self.ground(&view, scenery, opt);
        }
        let pal = &scenery.palette;
        for o in objects {
            self.contact_shadow(&view, o, opt);
        }
        if opt.scenery {
            for s in &scenery.solids {
                self.solid(&view, s, pal, opt);
            }
        }
        for o in objects {
            let r = o.size.length() * 0.5;
            if view.sees_sphere(o.center, r, opt.near, opt.range) {
                let s = object_solid(o, pal);
                self.solid(&view, &s, pal, opt);
            }
        }
        Ok(self.frame.clone())
    }

    /// Sky gradient and the textured ground plane; fills depth, fog and shade.
    fn base(&mut self, v: &View, pal: &Palette, opt: &RenderOptions) {
        let (w, h) = (self.frame.width, self.frame.height);
        let hc = v.proj.position.z;
        let (cx, cy) = (v.proj.position.x, v.proj.position.y);
        // World direction of pixel (i, j): c2w * kinv * (i, j, 1), affine in i and j.
        let m = v.c2w * v.kinv;
        let (di, dj, d0) = (m.x_axis, m.y_axis, m.z_axis);
        let range = opt.range as f32;
        let light = pal.light(DVec3::Z);
        let grass = pal.grass.map(|c| c * light);
        for j in 0..h {
            let row = d0 + dj * j as f64;
            for i in 0..w {
                let d = row + di * i as f64;
                let p = j * w + i;
                let len = d.length();
                let e = (d.z / len) as f32;
                let hit = if d.z < -1e-9 {
                    hc / -d.z
                } else {
                    f64::INFINITY
                };
                if hit.is_finite() && (hit as f32) < range * 1.5 {
                    let z = hit as f32;
                    let (x, y) = (cx + d.x * hit, cy + d.y * hit);
                    let fog = smoothstep(opt.fog_start as f32, range, z * (len as f32));
                    // Two octaves of cell noise, faded with distance (no shimmer far away).
                    let n = 0.06 * cell_noise(x * 2.0, y * 2.0, 1)
                        + 0.08 * cell_noise(x / 3.0, y / 3.0, 2);
                    let shade = 1.0 + n * (1.0 - fog);
                    self.fog[p] = fog;
                    self.shade[p] = shade;
                    self.frame.depth[p] = z;
                    self.frame.class[p] = SemanticClass::Grass as u8;
                    put(
                        &mut self.frame.rgb,
                        p,
                        lerp3(grass.map(|c| c * shade), pal.sky_horizon, fog),
                    );
                } else {
                    let t = e.max(0.0).sqrt();
                    self.fog[p] = 1.0;
                    self.shade[p] = 1.0;
                    self.frame.depth[p] = f32::INFINITY;
                    self.frame.class[p] = SemanticClass::Sky as u8;
                    put(
                        &mut self.frame.rgb,
                        p,
                        lerp3(pal.sky_horizon, pal.sky_zenith, t),
                    );
                }
                self.frame.instance[p] = 0;
            }
        }
    }

    /// Projects a ring given in the global frame into `self.px` (near- and far-clipped); false when empty.
    fn project_ring(
        &mut self,
        v: &View,
        ring: impl Iterator<Item = DVec3>,
        near: f64,
        far: f64,
    ) -> bool {
        self.cam_pts.clear();
        self.cam_pts.extend(ring.map(|p| v.proj.to_camera(p)));
        clip_polygon_z(&self.cam_pts, near, true, &mut self.clipped);
        clip_polygon_z(&self.clipped, far, false, &mut self.clipped2);
        self.px.clear();
        for p in &self.clipped2 {
            let q = v.proj.pixel_of_camera_point(*p);
            self.px.push([q.x as f32, q.y as f32]);
        }
        self.px.len() >= 3
    }

    fn ground(&mut self, v: &View, sc: &Scenery, opt: &RenderOptions) {
        let pal = &sc.palette;
        let light = pal.light(DVec3::Z);
        let pos = v.proj.position;
        let w = self.frame.width;
        for g in &sc.ground {
            // Range and frustum culling on the bounds.
            let b = &g.bounds;
            let nearest = pos.truncate().clamp(b.min, b.max);
            if nearest.distance(pos.truncate()) > opt.range {
                continue;
            }
            let corners = [
                DVec3::new(b.min.x, b.min.y, 0.0),
                DVec3::new(b.max.x, b.min.y, 0.0),
                DVec3::new(b.max.x, b.max.y, 0.0),
                DVec3::new(b.min.x, b.max.y, 0.0),
            ]
            .map(|p| v.proj.to_camera(p));
            if v.proj.frustum_culls(&corners, opt.near, None) {
                continue;
            }
            let mut any = false;
            for r in &g.rings {
                if self.project_ring(v, r.iter().map(|p| p.extend(0.0)), opt.near, opt.range) {
                    self.raster.add_ring(&self.px);
                    any = true;
                }
            }
            if !any {
                continue;
            }
            let base = g.colour.map(|c| c * light);
            let class = g.class as u8;
            let (fr, fog, shade) = (&mut self.frame, &self.fog, &self.shade);
            self.raster.fill_spans(|j, i0, i1| {
                for p in j * w + i0..=j * w + i1 {
                    if fr.class[p] == SemanticClass::Sky as u8 {
                        continue;
                    }
                    let c = lerp3(base.map(|c| c * shade[p]), pal.sky_horizon, fog[p]);
                    put(&mut fr.rgb, p, c);
                    fr.class[p] = class;
                }
            });
        }
    }

    /// Darkens the ground under an object's footprint (a soft contact shadow; ground pixels only, so ids and
    /// depth stay the ground's).
    fn contact_shadow(&mut self, v: &View, o: &WorldObject, opt: &RenderOptions) {
        let r = o.size.truncate().length() * 0.5;
        if !v.sees_sphere(o.center.truncate().extend(0.0), r, opt.near, opt.range) {
            return;
        }
        let (s, c) = o.yaw.sin_cos();
        let (l, w) = (o.size.x * 0.5, o.size.y * 0.5);
        let ring = [(l, w), (-l, w), (-l, -w), (l, -w)]
            .map(|(x, y)| DVec3::new(o.center.x + c * x - s * y, o.center.y + s * x + c * y, 0.0));
        if !self.project_ring(v, ring.into_iter(), opt.near, opt.range) {
            return;
        }
        self.raster.add_ring(&self.px);
        let w = self.frame.width;
        let fr = &mut self.frame;
        self.raster.fill_spans(|j, i0, i1| {
            for p in j * w + i0..=j * w + i1 {
                if fr.instance[p] == 0 && fr.class[p] != SemanticClass::Sky as u8 {
                    for k in 0..3 {
                        fr.rgb[3 * p + k] = (fr.rgb[3 * p + k] as u16 * 3 / 5) as u8;
                    }
                }
            }
        });
    }

    fn solid(&mut self, v: &View, s: &Solid, pal: &Palette, opt: &RenderOptions) {
        if s.faces.is_empty() || !v.sees_sphere(s.centre, s.radius, opt.near, opt.range) {
            return;
        }
        let w = self.frame.width;
        let r3 = v.proj.world2cam.matrix3;
        let kinv = v.kinv;
        let up_c = r3 * DVec3::Z;
        for f in &s.faces {
            let n_c = r3 * f.normal;
            let v0 = v.proj.to_camera(f.pts[0]);
            let d = n_c.dot(v0);
            if d >= -1e-9 {
                continue; // back-facing or edge-on
            }
            if !self.project_ring(v, f.pts.iter().copied(), opt.near, f64::INFINITY) {
                continue;
            }
            self.raster.add_ring(&self.px);
            // 1/z = (a u + b v + c) / d.
            let (a, b, c) = (
                n_c.dot(kinv.x_axis) / d,
                n_c.dot(kinv.y_axis) / d,
                n_c.dot(kinv.z_axis) / d,
            );
            let win = f.windows.map(|wn| {
                let es = r3 * wn.s_axis;
                let o = v.proj.to_camera(wn.origin);
                let ray_s = DVec3::new(
                    es.dot(kinv.x_axis),
                    es.dot(kinv.y_axis),
                    es.dot(kinv.z_axis),
                );
                let ray_t = DVec3::new(
                    up_c.dot(kinv.x_axis),
                    up_c.dot(kinv.y_axis),
                    up_c.dot(kinv.z_axis),
                );
                (wn, ray_s, es.dot(o), ray_t, up_c.dot(o))
            });
            let (colour, class, inst) = (f.colour, s.class as u8, s.instance);
            let (fs, fe, range) = (opt.fog_start as f32, opt.range as f32, opt.range as f32);
            let fr = &mut self.frame;
            let horizon = pal.sky_horizon;
            self.raster.fill_spans(|j, i0, i1| {
                let jf = j as f64;
                for i in i0..=i1 {
                    let inv_z = a * i as f64 + b * jf + c;
                    if inv_z <= 0.0 {
                        continue;
                    }
                    let z = (1.0 / inv_z) as f32;
                    let p = j * w + i;
                    if z >= fr.depth[p] || z > range {
                        continue;
                    }
                    let mut col = colour;
                    if let Some((wn, rs, os, rt, ot)) = &win {
                        let zf = z as f64;
                        let s_ = zf * (rs.x * i as f64 + rs.y * jf + rs.z) - os;
                        let t_ = zf * (rt.x * i as f64 + rt.y * jf + rt.z) - ot;
                        if wn.is_glass(s_, t_) {
                            col = wn.glass;
                        }
                    }
                    fr.depth[p] = z;
                    fr.class[p] = class;
                    fr.instance[p] = inst;
                    // Fog by distance (as the ground's): z times the length of the pixel's z = 1 ray.
                    let (rx, ry) = (
                        kinv.x_axis.x * i as f64 + kinv.y_axis.x * jf + kinv.z_axis.x,
                        kinv.y_axis.y * jf + kinv.z_axis.y,
                    );
                    let dist = z * ((rx * rx + ry * ry + 1.0).sqrt() as f32);
                    put(
                        &mut fr.rgb,
                        p,
                        lerp3(col, horizon, smoothstep(fs, fe, dist)),
                    );
                }
            });
        }
    }
}

/// Renders every camera of `cams` (each at `width x height`, intrinsics rescaled from its native size) from the
/// ego pose `ego2global`, on up to `threads` threads (results do not depend on the thread count).
#[allow(clippy::too_many_arguments)]
pub fn render_cameras(
    scenery: &Scenery,
    cams: &[Camera],
    ego2global: &DMat4,
    width: usize,
    height: usize,
    objects: &[WorldObject],
    opt: &RenderOptions,
    threads: usize,
) -> Result<Vec<CameraFrame>> {
    anyhow::ensure!(
        (1..=8192).contains(&width) && (1..=8192).contains(&height),
        "render size {height}x{width} (HxW): each side must be in 1..=8192"
    );
    let threads = threads.clamp(1, cams.len().max(1));
    if threads == 1 {
        let mut canvas = Canvas::new(width, height);
        return cams
            .iter()
            .map(|c| canvas.render(scenery, c, ego2global, objects, opt))
            .collect();
    }
    let chunk = cams.len().div_ceil(threads);
    std::thread::scope(|s| {
        let handles: Vec<_> = cams
            .chunks(chunk)
            .map(|part| {
                s.spawn(move || {
                    let mut canvas = Canvas::new(width, height);
                    part.iter()
                        .map(|c| canvas.render(scenery, c, ego2global, objects, opt))
                        .collect::<Result<Vec<_>>>()
                })
            })
            .collect();
        let mut out = Vec::new();
        for h in handles {
            out.extend(
                h.join()
                    .map_err(|_| anyhow::anyhow!("render thread panicked"))??,
            );
        }
        Ok(out)
    })
}
