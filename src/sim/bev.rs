//! Bird's-eye-view PNG frames of a run (image crate): drivable area, lanes and connectors, crosswalks, stop
//! lines of red lights, objects coloured by class (IDM agents with a white outline), the ego, its latest
//! planned path and the expert's logged path. A plain CPU rasteriser: convex fills and 1-px lines.
use super::closed_loop::{SimResult, StepRecord};
use crate::scene::geometry::{point_in_polygon, Aabb, Pose2};
use crate::scene::{ObjectClass, Scenario, TrafficLightStatus};
use anyhow::{Context, Result};
use glam::DVec2;
use image::{Rgb, RgbImage};
use std::path::Path;

/// View settings: image size in pixels and metres per pixel; the view is centred on the ego.
#[derive(Clone, Copy, Debug)]
pub struct BevView {
    pub size: u32,
    pub metres_per_px: f64,
}

impl Default for BevView {
    fn default() -> Self {
        Self {
            size: 640,
            metres_per_px: 0.15625,
        } // 100 m across
    }
}

struct Canvas {
    img: RgbImage,
    center: DVec2,
    mpp: f64,
}

impl Canvas {
    fn to_px(&self, p: DVec2) -> DVec2 {
        let h = self.img.width() as f64 / 2.0;
        DVec2::new(
            h + (p.x - self.center.x) / self.mpp,
            h - (p.y - self.center.y) / self.mpp,
        )
    }
    fn to_world(&self, x: f64, y: f64) -> DVec2 {
        let h = self.img.width() as f64 / 2.0;
        DVec2::new(
            self.center.x + (x - h) * self.mpp,
            self.center.y - (y - h) * self.mpp,
        )
    }
    fn put(&mut self, x: i64, y: i64, c: Rgb<u8>) {
        if x >= 0 && y >= 0 && (x as u32) < self.img.width() && (y as u32) < self.img.height() {
            self.img.put_pixel(x as u32, y as u32, c);
        }
    }
    fn line(&mut self, a: DVec2, b: DVec2, c: Rgb<u8>) {
        let (pa, pb) = (self.to_px(a), self.to_px(b));
        // a segment wholly off the canvas draws nothing: skip its steps
        let (w, h) = (self.img.width() as f64, self.img.height() as f64);
        if pa.x.max(pb.x) < -1.0
            || pa.x.min(pb.x) > w + 1.0
            || pa.y.max(pb.y) < -1.0
            || pa.y.min(pb.y) > h + 1.0
            || !(pa.is_finite() && pb.is_finite())
        {
            return;
        }
        let n = (pb - pa).abs().max_element().ceil().min(4000.0) as i64;
        for i in 0..=n.max(1) {
            let p = pa + (pb - pa) * (i as f64 / n.max(1) as f64);
            self.put(p.x.round() as i64, p.y.round() as i64, c);
        }
    }
    fn polyline(&mut self, pts: &[DVec2], c: Rgb<u8>, closed: bool) {
        for w in pts.windows(2) {
            self.line(w[0], w[1], c);
        }
        if closed && pts.len() > 2 {
            self.line(pts[pts.len() - 1], pts[0], c);
        }
    }
    fn fill(&mut self, poly: &[DVec2], c: Rgb<u8>) {
        let px: Vec<DVec2> = poly.iter().map(|p| self.to_px(*p)).collect();
        let b = Aabb::from_points(&px);
        let (w, h) = (self.img.width() as f64, self.img.height() as f64);
        let (x0, x1) = (
            b.min.x.max(0.0).floor() as i64,
            b.max.x.min(w - 1.0).ceil() as i64,
        );
        let (y0, y1) = (
            b.min.y.max(0.0).floor() as i64,
            b.max.y.min(h - 1.0).ceil() as i64,
        );
        for y in y0..=y1 {
            for x in x0..=x1 {
                if point_in_polygon(DVec2::new(x as f64 + 0.5, y as f64 + 0.5), &px) {
                    self.put(x, y, c);
                }
            }
        }
    }
}

fn class_colour(c: ObjectClass) -> Rgb<u8> {
    match c {
        ObjectClass::Vehicle => Rgb([60, 120, 230]),
        ObjectClass::Pedestrian => Rgb([240, 160, 40]),
        ObjectClass::Bicycle => Rgb([200, 80, 200]),
        ObjectClass::TrafficCone => Rgb([250, 90, 20]),
        ObjectClass::Barrier => Rgb([150, 150, 60]),
        ObjectClass::CzoneSign | ObjectClass::GenericObject => Rgb([140, 140, 140]),
    }
}

/// Draws one step of a run.
pub fn render_step(
    sc: &Scenario,
    step: &StepRecord,
    last_plan: Option<&[Pose2]>,
    view: &BevView,
) -> RgbImage {
    let mut cv = Canvas {
        img: RgbImage::from_pixel(view.size, view.size, Rgb([25, 25, 28])),
        center: step.ego_center.pos(),
        mpp: view.metres_per_px,
    };
    let map = &sc.map;
    let half = view.size as f64 / 2.0 * view.metres_per_px;
    let q = Aabb {
        min: cv.center - DVec2::splat(half),
        max: cv.center + DVec2::splat(half),
    };
    // Drivable area: one scanline per pixel row over the edges near that row (work in proportion to the
    // view, not to the polygons' vertex counts); a map without a drivable-area layer tests its lanes per pixel.
    let drivable = Rgb([62, 62, 66]);
    if !map.drivable.is_empty() {
        let mut xs = Vec::new();
        for y in 0..view.size {
            xs.clear();
            map.drivable
                .row_crossings(cv.to_world(0.5, y as f64 + 0.5).y, &mut xs);
            xs.sort_unstable_by(f64::total_cmp);
            // inside between the 1st and 2nd crossing, the 3rd and 4th, ... (even-odd), boundary included
            for pair in xs.chunks_exact(2) {
                let (a, b) = (
                    cv.to_px(DVec2::new(pair[0], 0.0)).x,
                    cv.to_px(DVec2::new(pair[1], 0.0)).x,
                );
                let x0 = (a - 0.5).ceil().max(0.0);
                let x1 = (b - 0.5).floor().min(view.size as f64 - 1.0);
                let mut x = x0;
                while x <= x1 {
                    cv.img.put_pixel(x as u32, y, drivable);
                    x += 1.0;
                }
            }
        }
    } else {
        let mut lanes = Vec::new();
        map.lanes_in(&q, |i| lanes.push(i));
        if !lanes.is_empty() {
            for y in 0..view.size {
                for x in 0..view.size {
                    let p = cv.to_world(x as f64 + 0.5, y as f64 + 0.5);
                    if map.in_drivable_area(p) {
                        cv.img.put_pixel(x, y, drivable);
                    }
                }
            }
        }
    }
    let mut lanes = Vec::new();
    map.lanes_in(&q, |i| lanes.push(i as usize));
    lanes.sort_unstable();
    for &i in &lanes {
        let l = &map.lanes[i];
        let c = if l.kind == crate::scene::LaneKind::Lane {
            Rgb([110, 110, 118])
        } else {
            Rgb([90, 90, 100])
        };
        cv.polyline(&l.polygon, c, true);
        cv.polyline(&l.centre.points, Rgb([150, 150, 90]), false);
    }
    for cw in &map.crosswalks {
        // only those in view (each edge is culled again in `line`)
        if Aabb::from_points(&cw.polygon).overlaps(&q) {
            cv.polyline(&cw.polygon, Rgb([220, 220, 220]), true);
        }
    }
    for &(li, s) in sc.lights_at(step.step) {
        let col = match s {
            TrafficLightStatus::Red => Rgb([230, 40, 40]),
            TrafficLightStatus::Yellow => Rgb([230, 200, 40]),
            TrafficLightStatus::Green => Rgb([40, 200, 60]),
            TrafficLightStatus::Unknown => continue,
        };
        for &sl in &map.lanes[li].stop_lines {
            cv.fill(&map.stop_lines[sl].polygon, col);
        }
    }
    // Expert path (whole log) and the latest plan.
    let expert: Vec<DVec2> = sc.ego.iter().map(|e| e.rear_axle.pos()).collect();
    cv.polyline(&expert, Rgb([80, 200, 200]), false);
    if let Some(p) = last_plan {
        let pts: Vec<DVec2> = p.iter().map(|q| q.pos()).collect();
        cv.polyline(&pts, Rgb([250, 80, 200]), false);
    }
    for a in &step.agents {
        let c = a.bbox.corners();
        cv.fill(&c, class_colour(a.class));
        if a.idm {
            cv.polyline(&c, Rgb([255, 255, 255]), true);
        }
        // Heading tick.
        let p = a.bbox.center;
        cv.line(
            p.pos(),
            p.forward(a.bbox.length / 2.0).pos(),
            Rgb([0, 0, 0]),
        );
    }
    let eb = sc.ego_params.footprint(&step.ego.rear_axle).corners();
    cv.fill(&eb, Rgb([40, 210, 90]));
    cv.polyline(&eb, Rgb([255, 255, 255]), true);
    cv.img
}

/// Writes frames every `every` steps (and the last step) as `<dir>/bev_<step>.png`; returns the count.
pub fn write_frames(
    sc: &Scenario,
    r: &SimResult,
    dir: &Path,
    every: usize,
    view: &BevView,
) -> Result<usize> {
    if every == 0 || r.steps.is_empty() {
        return Ok(0);
    }
    let mut n = 0;
    let mut last_plan: Option<&[Pose2]> = None;
    let last = r.steps.len() - 1;
    for (k, s) in r.steps.iter().enumerate() {
        if let Some(p) = &s.plan {
            last_plan = Some(p);
        }
        if k % every == 0 || k == last {
            let img = render_step(sc, s, last_plan, view);
            let f = dir.join(format!("bev_{:04}.png", s.step));
            img.save(&f)
                .with_context(|| format!("writing {}", f.display()))?;
            n += 1;
        }
    }
    Ok(n)
}
