//! The logic of `b2dr world`: the ground truth of any state of a scenario (the logged ego at a step, or that
//! pose displaced in the ego frame), b2dr's projected layout masks of the same state, and the pictures made
//! from them (per-camera images, a 6-camera mosaic with a bird's-eye view, mask overlays).
use super::objects::WorldObject;
use super::render::{render_cameras, CameraFrame, RenderOptions};
use super::{objects_at, World};
use crate::projection::scene::{boxes_at, map_layer};
use crate::projection::{
    box_wireframe, channel_name, CameraProjector, LayoutMasks, LayoutRenderer, MapLayer,
    ProjectionConfig, NUM_MASK_CHANNELS,
};
use crate::scene::camera::Camera;
use crate::scene::geometry::Pose2;
use crate::scene::import::ego2global;
use crate::scene::{safe_name, ObjectClass, Scenario};
use anyhow::{bail, ensure, Context, Result};
use glam::{DMat3, DMat4, DVec2, DVec3, DVec4};
use image::{Rgb, RgbImage};
use std::path::Path;

/// How far from the drivable area (m) a requested ego pose may be.
pub const MAX_OFF_ROAD_M: f64 = 15.0;

/// Parses `HxW` (e.g. `224x400`): each side in 8..=4096.
pub fn parse_size(s: &str) -> Result<(usize, usize)> {
    let (h, w) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("--size {s:?}: expected HEIGHTxWIDTH, e.g. 224x400"))?;
    let h: usize = h
        .trim()
        .parse()
        .with_context(|| format!("--size {s:?}: height {h:?} is not an integer"))?;
    let w: usize = w
        .trim()
        .parse()
        .with_context(|| format!("--size {s:?}: width {w:?} is not an integer"))?;
    ensure!(
        (8..=4096).contains(&h) && (8..=4096).contains(&w),
        "--size {s:?}: each side must be in 8..=4096"
    );
    Ok((h, w))
}

/// Largest ego-frame displacement accepted (m) by `world --offset`, `export-training --offsets` and
/// `export-planner --offsets`.
pub const MAX_OFFSET_M: f64 = 100.0;
/// Largest ego-frame yaw displacement accepted (degrees), as [`MAX_OFFSET_M`].
pub const MAX_OFFSET_DEG: f64 = 180.0;

/// Parses an ego-frame offset `DX,DY,DYAW` (metres, metres, degrees) into a local pose (radians).
pub fn parse_offset(s: &str) -> Result<Pose2> {
    let v: Vec<&str> = s.split(',').collect();
    ensure!(
        v.len() == 3,
        "--offset {s:?}: expected DX,DY,DYAW (metres, metres, degrees), e.g. 0,1.5,5"
    );
    let mut x = [0.0; 3];
    for (i, p) in v.iter().enumerate() {
        x[i] = p
            .trim()
            .parse::<f64>()
            .ok()
            .filter(|f| f.is_finite())
            .with_context(|| format!("--offset {s:?}: {p:?} is not a finite number"))?;
    }
    ensure!(
        x[0].abs() <= MAX_OFFSET_M && x[1].abs() <= MAX_OFFSET_M && x[2].abs() <= MAX_OFFSET_DEG,
        "--offset {s:?}: |DX|, |DY| must be <= {MAX_OFFSET_M} m and |DYAW| <= {MAX_OFFSET_DEG} degrees"
    );
    Ok(Pose2::new(x[0], x[1], x[2].to_radians()))
}

/// The ego rear-axle pose at log step `step` displaced by `offset` (in the ego frame); errors when the step is
/// out of range or the pose is off the map.
pub fn ego_pose(sc: &Scenario, step: usize, offset: &Pose2) -> Result<Pose2> {
    ensure!(!sc.is_empty(), "scenario {} has no logged steps", sc.name);
    ensure!(
        step < sc.len(),
        "--step {step} is out of range: scenario {} has steps 0..={}",
        sc.name,
        sc.len() - 1
    );
    let p = sc.ego[step].rear_axle.compose(offset);
    let d = sc.map.drivable_distance(p.pos(), MAX_OFF_ROAD_M);
    if !d.is_finite() {
        bail!(
            "the ego pose ({:.1}, {:.1}) is off the map: more than {MAX_OFF_ROAD_M} m from any road of {}",
            p.x,
            p.y,
            sc.name
        );
    }
    Ok(p)
}

/// Per-class masks of each camera (`projection::layout`) for the objects of step `step` seen from `ego2global`.
pub fn layout_masks(
    sc: &Scenario,
    layer: &MapLayer,
    cams: &[Camera],
    ego2global: &DMat4,
    step: usize,
    width: usize,
    height: usize,
) -> Result<Vec<LayoutMasks>> {
    let boxes: Vec<_> = boxes_at(sc, step).into_iter().map(|(_, b)| b).collect();
    let cfg = ProjectionConfig::default();
    let mut r = LayoutRenderer::new(width, height);
    cams.iter()
        .map(|c| {
            let proj = CameraProjector::new(c, ego2global, width as u32, height as u32)?;
            let mut m = LayoutMasks::new(width, height);
            r.render(&proj, &boxes, layer, &cfg, &mut m);
            Ok(m)
        })
        .collect()
}

/// One request of `b2dr world`.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewRequest {
    pub step: usize,
    pub offset: Pose2,
    pub height: usize,
    pub width: usize,
    /// Empty: every camera of the rig.
    pub cameras: Vec<String>,
}

/// What `b2dr world` computes.
pub struct ViewOutput {
    pub ego: Pose2,
    pub ego2global: DMat4,
    pub cameras: Vec<Camera>,
    pub frames: Vec<CameraFrame>,
    pub masks: Vec<LayoutMasks>,
    pub bev: RgbImage,
}

/// Renders the ground truth, the masks and the bird's-eye view of one state.
pub fn view(sc: &Scenario, world: &World, req: &ViewRequest) -> Result<ViewOutput> {
    let cams = sc.select_cameras(&req.cameras)?;
    let ego = ego_pose(sc, req.step, &req.offset)?;
    let e2g = ego2global(&ego);
    let frames = world.render_step(&cams, &e2g, req.step, req.width, req.height, 1)?;
    let layer = map_layer(&sc.map);
    let masks = layout_masks(sc, &layer, &cams, &e2g, req.step, req.width, req.height)?;
    let bev = bev(sc, world, &ego, req.step, 2 * req.height)?;
    Ok(ViewOutput {
        ego,
        ego2global: e2g,
        cameras: cams,
        frames,
        masks,
        bev,
    })
}

/// A top-down ground-truth view centred on the ego (a pinhole camera 120 m up looking down, forward = up,
/// about 100 m across), with the ego drawn as an orange car.
pub fn bev(
    sc: &Scenario,
    world: &World,
    ego: &Pose2,
    step: usize,
    size: usize,
) -> Result<RgbImage> {
    let size = size.max(16);
    let alt = 120.0;
    let f = size as f64 * alt / 100.0;
    let c = (size as f64 - 1.0) * 0.5;
    // Camera x = ego right (-y), camera y = ego backward (-x), camera z = down (-z).
    let cam2ego = DMat4::from_cols(
        DVec4::new(0.0, -1.0, 0.0, 0.0),
        DVec4::new(-1.0, 0.0, 0.0, 0.0),
        DVec4::new(0.0, 0.0, -1.0, 0.0),
        DVec4::new(ego_params_center(sc), 0.0, alt, 1.0),
    );
    let cam = Camera {
        name: "BEV".into(),
        intrinsic: DMat3::from_cols(
            DVec3::new(f, 0.0, 0.0),
            DVec3::new(0.0, f, 0.0),
            DVec3::new(c, c, 1.0),
        ),
        cam2ego,
        width: size as u32,
        height: size as u32,
        distortion: [0.0; 5],
    };
    let mut objects = objects_at(sc, step);
    let centre = sc.ego_params.center_of(ego);
    objects.push(WorldObject {
        track: usize::MAX - 1,
        class: ObjectClass::Vehicle,
        center: DVec3::new(centre.x, centre.y, sc.ego_params.height * 0.5),
        size: DVec3::new(
            sc.ego_params.length,
            sc.ego_params.width,
            sc.ego_params.height,
        ),
        yaw: ego.heading,
        look: 7, // VEHICLE_COLOURS[7]: amber
    });
    let opt = RenderOptions {
        range: 400.0,
        fog_start: 390.0,
        ..RenderOptions::default()
    };
    let f = render_cameras(
        &world.scenery,
        &[cam],
        &ego2global(ego),
        size,
        size,
        &objects,
        &opt,
        1,
    )?
    .remove(0);
    Ok(to_image(&f.rgb, size, size))
}

fn ego_params_center(sc: &Scenario) -> f64 {
    sc.ego_params.rear_axle_to_center
}

/// An `(H, W, 3)` buffer as an image.
pub fn to_image(rgb: &[u8], width: usize, height: usize) -> RgbImage {
    RgbImage::from_raw(width as u32, height as u32, rgb.to_vec())
        .unwrap_or_else(|| RgbImage::new(width as u32, height as u32))
}

/// Overlay colours of the mask channels (boxes, then map classes), as `b2dr project`.
pub const MASK_COLOURS: [[u8; 3]; NUM_MASK_CHANNELS] = [
    [255, 158, 0],
    [255, 99, 71],
    [255, 69, 0],
    [255, 140, 0],
    [233, 150, 70],
    [0, 0, 230],
    [255, 61, 99],
    [220, 20, 60],
    [47, 79, 79],
    [112, 128, 144],
    [60, 180, 75],
    [0, 200, 200],
    [255, 255, 255],
    [255, 255, 0],
    [200, 0, 200],
];

/// The image with the masks blended on top: map channels lightly, box channels strongly, and the box
/// wireframes in the box colour.
pub fn overlay(frame: &CameraFrame, masks: &LayoutMasks) -> RgbImage {
    let (w, h) = (frame.width, frame.height);
    let mut img = to_image(&frame.rgb, w, h);
    for c in (0..NUM_MASK_CHANNELS).rev() {
        let alpha = match channel_name(c) {
            "drivable_area" | "lane" => 0.0,
            "crosswalk" => 0.3,
            "lane_divider" | "road_boundary" => 0.8,
            _ => 0.45,
        };
        if alpha == 0.0 {
            continue;
        }
        let m = masks.channel(c);
        let col = MASK_COLOURS[c];
        for (p, &v) in m.iter().enumerate() {
            if v != 0 {
                let px = img.get_pixel_mut((p % w) as u32, (p / w) as u32);
                for (v, c) in px.0.iter_mut().zip(col) {
                    *v = (*v as f32 * (1.0 - alpha) + c as f32 * alpha) as u8;
                }
            }
        }
    }
    // Drivable area outline.
    let d = masks.channel(10);
    for j in 0..h {
        for i in 0..w {
            let p = j * w + i;
            let edge = d[p] != 0
                && ((i + 1 < w && d[p + 1] == 0)
                    || (j + 1 < h && d[p + w] == 0)
                    || (i > 0 && d[p - 1] == 0));
            if edge {
                img.put_pixel(i as u32, j as u32, Rgb(MASK_COLOURS[10]));
            }
        }
    }
    img
}

/// Draws box wireframes (pixel segments) onto an image.
pub fn draw_segments(img: &mut RgbImage, segs: &[(DVec2, DVec2)], c: [u8; 3]) {
    let (w, h) = (img.width() as f64, img.height() as f64);
    for (a, b) in segs {
        let n = (*b - *a).abs().max_element().ceil().clamp(1.0, 4000.0) as usize;
        for i in 0..=n {
            let p = *a + (*b - *a) * (i as f64 / n as f64);
            let (x, y) = (p.x.round(), p.y.round());
            if x >= 0.0 && y >= 0.0 && x < w && y < h {
                img.put_pixel(x as u32, y as u32, Rgb(c));
            }
        }
    }
}

/// The six cameras in a 2 x 3 grid (front-left, front, front-right over back-left, back, back-right; other
/// cameras in rig order), with `side` (the BEV, resized to the grid's height) on the right.
pub fn mosaic(names: &[String], images: &[RgbImage], side: Option<&RgbImage>) -> RgbImage {
    let order = [
        "CAM_FRONT_LEFT",
        "CAM_FRONT",
        "CAM_FRONT_RIGHT",
        "CAM_BACK_LEFT",
        "CAM_BACK",
        "CAM_BACK_RIGHT",
    ];
    let mut idx: Vec<usize> = order
        .iter()
        .filter_map(|o| names.iter().position(|n| n == o))
        .collect();
    for i in 0..names.len() {
        if !idx.contains(&i) {
            idx.push(i);
        }
    }
    let (w, h) = images
        .first()
        .map(|i| (i.width(), i.height()))
        .unwrap_or((1, 1));
    let cols = idx.len().clamp(1, 3) as u32;
    let rows = (idx.len() as u32).div_ceil(cols).max(1);
    let gh = rows * h;
    let side =
        side.map(|s| image::imageops::resize(s, gh, gh, image::imageops::FilterType::Triangle));
    let sw = side.as_ref().map(|s| s.width()).unwrap_or(0);
    let mut out = RgbImage::from_pixel(cols * w + sw, gh, Rgb([0, 0, 0]));
    for (k, &i) in idx.iter().enumerate() {
        let (r, c) = (k as u32 / cols, k as u32 % cols);
        image::imageops::replace(&mut out, &images[i], (c * w) as i64, (r * h) as i64);
    }
    if let Some(s) = side {
        image::imageops::replace(&mut out, &s, (cols * w) as i64, 0);
    }
    out
}

fn save(img: &RgbImage, path: &Path) -> Result<()> {
    img.save(path)
        .with_context(|| format!("writing {}", path.display()))
}

/// Writes `<dir>/<CAM>.png`, `<dir>/<CAM>_overlay.png`, `<dir>/<CAM>_class.png`, `<dir>/<CAM>_depth.png` (16-bit,
/// centimetres, 0 = sky), `<dir>/bev.png`,
/// `<dir>/mosaic.png` (cameras + BEV) and `<dir>/overlay_mosaic.png`.
pub fn write_view(out: &ViewOutput, sc: &Scenario, step: usize, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let names: Vec<String> = out.cameras.iter().map(|c| c.name.clone()).collect();
    let mut images = Vec::new();
    let mut overlays = Vec::new();
    let boxes = boxes_at(sc, step);
    let cfg = ProjectionConfig::default();
    for ((cam, f), m) in out.cameras.iter().zip(&out.frames).zip(&out.masks) {
        let img = to_image(&f.rgb, f.width, f.height);
        save(&img, &dir.join(format!("{}.png", safe_name(&cam.name))))?;
        let mut ov = overlay(f, m);
        let proj = CameraProjector::new(cam, &out.ego2global, f.width as u32, f.height as u32)?;
        for (_, b) in &boxes {
            if let Some(segs) = box_wireframe(&proj, b, &cfg) {
                draw_segments(&mut ov, &segs, MASK_COLOURS[b.class.index()]);
            }
        }
        save(
            &ov,
            &dir.join(format!("{}_overlay.png", safe_name(&cam.name))),
        )?;
        let mut cls = RgbImage::new(f.width as u32, f.height as u32);
        for (p, &c) in f.class.iter().enumerate() {
            let col = super::SemanticClass::ALL
                .get(c as usize)
                .map(|s| s.display_colour())
                .unwrap_or([0, 0, 0]);
            cls.put_pixel((p % f.width) as u32, (p / f.width) as u32, Rgb(col));
        }
        save(
            &cls,
            &dir.join(format!("{}_class.png", safe_name(&cam.name))),
        )?;
        // Depth as 16-bit PNG in centimetres (0 = sky or beyond 655 m).
        let depth: Vec<u16> = f
            .depth
            .iter()
            .map(|&d| {
                if d.is_finite() && d * 100.0 < 65535.0 {
                    (d * 100.0).round() as u16
                } else {
                    0
                }
            })
            .collect();
        let path = dir.join(format!("{}_depth.png", safe_name(&cam.name)));
        image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(
            f.width as u32,
            f.height as u32,
            depth,
        )
        .context("depth image size")?
        .save(&path)
        .with_context(|| format!("writing {}", path.display()))?;
        images.push(img);
        overlays.push(ov);
    }
    save(&out.bev, &dir.join("bev.png"))?;
    save(
        &mosaic(&names, &images, Some(&out.bev)),
        &dir.join("mosaic.png"),
    )?;
    save(
        &mosaic(&names, &overlays, None),
        &dir.join("overlay_mosaic.png"),
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_and_offsets_parse_or_fail_clearly() {
        assert_eq!(parse_size("224x400").unwrap(), (224, 400));
        assert_eq!(parse_size("112X200").unwrap(), (112, 200));
        for bad in ["224", "0x400", "224x5000", "ax400", "224x-1", ""] {
            assert!(parse_size(bad).is_err(), "{bad}");
        }
        let o = parse_offset("1, -2.5, 90").unwrap();
        assert_eq!((o.x, o.y), (1.0, -2.5));
        assert!((o.heading - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        for bad in ["1,2", "1,2,3,4", "nan,0,0", "0,0,inf", "0,500,0", "x,y,z"] {
            assert!(parse_offset(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn mosaic_puts_front_in_the_middle_of_the_top_row() {
        let names: Vec<String> = crate::scene::import::CAMERAS
            .iter()
            .map(|s| s.to_string())
            .collect();
        let imgs: Vec<RgbImage> = (0..6)
            .map(|i| RgbImage::from_pixel(4, 2, Rgb([i as u8 * 40, 0, 0])))
            .collect();
        let m = mosaic(&names, &imgs, None);
        assert_eq!((m.width(), m.height()), (12, 4));
        assert_eq!(m.get_pixel(5, 0).0[0], 0); // CAM_FRONT (index 0) at column 1, row 0
        assert_eq!(m.get_pixel(5, 3).0[0], 3 * 40); // CAM_BACK at column 1, row 1
    }
}
