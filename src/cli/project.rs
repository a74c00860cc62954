//! `b2dr project`: projects a keyframe's boxes (and optionally a drivable-area map), or those of one log step of
//! any scenario with its map, into each camera; writes per-class masks at render resolution, an overlay on the
//! real image, and `projection.json` (native pixels; each box with its global centre, and each camera as a
//! protocol-v2 `plan` request describes it at the native size, `lidar2img` included, beside the lidar frame's
//! `ego2global` and `lidar2ego`: what `python/tests/test_b2dr_planner_adapters.py` checks the adapter against).
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use b2dr::projection::keyframe::drivable_area_from_geojson;
use b2dr::projection::{
    box_wireframe, channel_name, Box3d, CameraProjector, KeyFrame, LayoutMasks, LayoutRenderer,
    MapLayer, ProjectionConfig, NUM_MASK_CHANNELS,
};
use b2dr::scene::camera::{Camera, CameraImage};
use b2dr::scene::import::resolve;
use b2dr::sim::external::camera_entry;
use b2dr::sim::sensors::CameraFrame;
use b2dr::world::images::ImageStore;
use b2dr::world::step_views::step_views;
use b2dr::world::view::MASK_COLOURS;
use glam::DVec2;
use image::{Rgb, RgbImage};
use serde_json::json;

#[derive(clap::Args, Debug)]
pub struct ProjectArgs {
    /// Keyframe JSON (format of nuscenes-mini/keyframe-scene-0061/frame.json); images are read next to it.
    #[arg(
        long,
        required_unless_present = "scenario",
        conflicts_with = "scenario"
    )]
    pub frame: Option<PathBuf>,
    /// A scenario instead of a keyframe: builtin:..., a ScenarioNet file, nuscenes:..., nuplan:... (one).
    #[arg(long, requires = "step")]
    pub scenario: Option<String>,
    /// The log step of --scenario to project (its recorded frame: the one nearest the step's time).
    #[arg(long, requires = "scenario")]
    pub step: Option<usize>,
    /// Cameras of --scenario (comma-separated; default: every camera of its rig).
    #[arg(long, value_delimiter = ',', requires = "scenario")]
    pub cameras: Vec<String>,
    /// Output directory (created).
    #[arg(long)]
    pub out: PathBuf,
    /// Mask resolution WIDTHxHEIGHT.
    #[arg(long, default_value = "400x224")]
    pub size: String,
    /// Culling range in metres.
    #[arg(long, default_value_t = 80.0)]
    pub range: f64,
    /// Optional drivable-area GeoJSON (global frame) drawn as the drivable_area channel (with --frame; a
    /// scenario brings its own map).
    #[arg(long, conflicts_with = "scenario")]
    pub map: Option<PathBuf>,
    /// Width of the overlay images (default: the camera's native width).
    #[arg(long)]
    pub overlay_width: Option<u32>,
    /// How to read `boxes[].center[2]`: `center` (the format's gravity centre), `top` (the box's top face; what
    /// the shared keyframe-scene-0061/frame.json actually holds, see docs/projection.md), or `auto` (decide from
    /// where vehicle bottoms land relative to the ego's ground plane; prints the choice).
    #[arg(long, default_value = "auto", value_parser = ["auto", "center", "top"])]
    pub box_z: String,
    /// Write the overlays as PNG (overlay.png) instead of JPEG (overlay.jpg).
    #[arg(long)]
    pub overlay_png: bool,
}

fn parse_size(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s
        .split_once('x')
        .with_context(|| format!("--size {s:?}: expected WIDTHxHEIGHT"))?;
    let w: u32 = w
        .trim()
        .parse()
        .with_context(|| format!("--size {s:?}: width"))?;
    let h: u32 = h
        .trim()
        .parse()
        .with_context(|| format!("--size {s:?}: height"))?;
    if w == 0 || h == 0 || w > 8192 || h > 8192 {
        bail!("--size {s:?}: each side must be in 1..=8192");
    }
    Ok((w, h))
}

/// The ego pose "now" (the keyframe's lidar time, or the scenario's log step) and the rig's lidar: the frame of
/// the protocol-v2 `lidar2img` written beside each camera's boxes (docs/planner_protocol.md "Frames").
struct LidarFrame {
    ego2global: glam::DMat4,
    lidar2ego: glam::DMat4,
}

/// One camera image to project: its camera, the image (with its ego pose), the boxes it shows and its pixels at
/// the camera's native size.
struct View {
    cam: Camera,
    img: CameraImage,
    boxes: Vec<Box3d>,
    photo: RgbImage,
}

pub fn run(args: ProjectArgs) -> Result<()> {
    let (rw, rh) = parse_size(&args.size)?;
    anyhow::ensure!(
        args.range > 0.0 && args.range.is_finite(),
        "--range must be positive"
    );
    if let Some(w) = args.overlay_width {
        anyhow::ensure!(
            (1..=8192).contains(&w),
            "--overlay-width {w}: must be in 1..=8192"
        );
    }
    let (views, map, about, lidar) = match (&args.frame, &args.scenario) {
        (Some(f), None) => frame_views(&args, f)?,
        (None, Some(s)) => scenario_views(s, args.step.unwrap_or(0), &args.cameras)?,
        _ => bail!("give either --frame FRAME.json or --scenario S --step K"),
    };
    let cfg = ProjectionConfig {
        range: args.range,
        ..ProjectionConfig::default()
    };
    write_views(&args, &views, &map, &cfg, (rw, rh), about, &lidar)
}

/// The views of a keyframe file (every camera shows the file's boxes) and the optional GeoJSON map.
fn frame_views(
    args: &ProjectArgs,
    path: &std::path::Path,
) -> Result<(Vec<View>, MapLayer, serde_json::Value, LidarFrame)> {
    let mut frame = KeyFrame::load(path)?;
    let top = match args.box_z.as_str() {
        "top" => true,
        "center" => false,
        _ => {
            let t = frame.z_looks_like_top();
            eprintln!(
                "--box-z auto: reading boxes[].center[2] as the {} (vehicle bottoms land nearest the ego's ground plane)",
                if t { "top face" } else { "gravity centre" }
            );
            t
        }
    };
    if top {
        frame.boxes_z_from_top();
    }
    let map = match &args.map {
        Some(p) => MapLayer::new(drivable_area_from_geojson(p, frame.ego2global.w_axis.z)?),
        None => MapLayer::default(),
    };
    let mut views = Vec::new();
    for (cam, img) in &frame.cameras {
        let img_path = frame.image_path(img);
        let photo = b2dr::world::images::read_recorded_image(
            &img_path,
            (cam.width, cam.height),
            &format!("cameras.{}", cam.name),
        )?;
        views.push(View {
            cam: cam.clone(),
            img: img.clone(),
            boxes: frame.boxes.clone(),
            photo,
        });
    }
    // frame.json carries no lidar calibration: the nominal nuScenes LIDAR_TOP mounting, riding on the keyframe's
    // (lidar time) ego pose
    let lidar = LidarFrame {
        ego2global: frame.ego2global,
        lidar2ego: b2dr::scene::camera::nuscenes_lidar2ego(),
    };
    Ok((
        views,
        map,
        json!({ "frame": path.display().to_string() }),
        lidar,
    ))
}

/// The views of log step `step` of one scenario (`b2dr::world::step_views`), images through the scenario's
/// image store (files read and undistorted, built-in ones rendered) at each camera's native size.
fn scenario_views(
    spec: &str,
    step: usize,
    cameras: &[String],
) -> Result<(Vec<View>, MapLayer, serde_json::Value, LidarFrame)> {
    let srcs = resolve(spec)?;
    let [src] = srcs.as_slice() else {
        bail!(
            "--scenario {spec:?} names {} scenarios; project takes one",
            srcs.len()
        );
    };
    let sv = step_views(src, step, cameras)?;
    let store = ImageStore::new(&sv.scenario, src.image_dir());
    let mut views = Vec::new();
    for v in &sv.views {
        let (w, h) = (v.camera.width, v.camera.height);
        let px = store.image(&v.image, w as usize, h as usize)?;
        let photo = RgbImage::from_raw(w, h, px.data.clone())
            .with_context(|| format!("image {} of {}x{}", v.image.path, w, h))?;
        views.push(View {
            cam: v.camera.clone(),
            img: v.image.clone(),
            boxes: v.boxes.clone(),
            photo,
        });
    }
    let about = json!({
        "scenario": sv.scenario.source, "step": sv.step, "frame": sv.frame, "frame_time_s": sv.frame_time_s,
        "frame_step": sv.frame_step, "boxes_from": sv.boxes_from,
        "map_missing": sv.scenario.map.missing,
    });
    if let Some(m) = &sv.scenario.map.missing {
        eprintln!("no map channels: {m}");
    }
    let ego = sv
        .scenario
        .ego
        .get(sv.frame_step)
        .with_context(|| format!("log step {} of {spec}", sv.frame_step))?;
    let lidar = LidarFrame {
        ego2global: b2dr::scene::import::ego2global(&ego.rear_axle),
        lidar2ego: sv.scenario.rig.lidar2ego,
    };
    Ok((views, sv.map, about, lidar))
}

/// Masks, overlays and `projection.json` of the views (module docs).
fn write_views(
    args: &ProjectArgs,
    views: &[View],
    map: &MapLayer,
    cfg: &ProjectionConfig,
    (rw, rh): (u32, u32),
    about: serde_json::Value,
    lidar: &LidarFrame,
) -> Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let mut renderer = LayoutRenderer::new(rw as usize, rh as usize);
    let mut masks = LayoutMasks::new(rw as usize, rh as usize);
    let mut cams_json = serde_json::Map::new();
    let mut protocol = serde_json::Map::new();
    for View {
        cam,
        img,
        boxes,
        photo,
    } in views
    {
        // camera names come from the input: never let one leave --out
        let dir = args.out.join(b2dr::scene::safe_name(&cam.name));
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let render = CameraProjector::new(cam, &img.ego2global, rw, rh)?;
        renderer.render(&render, boxes, map, cfg, &mut masks);
        for c in 0..NUM_MASK_CHANNELS {
            let data: Vec<u8> = masks.channel(c).iter().map(|&v| v * 255).collect();
            let p = dir.join(format!("{}.png", channel_name(c)));
            image::GrayImage::from_raw(rw, rh, data)
                .context("mask buffer size")?
                .save(&p)
                .with_context(|| format!("writing {}", p.display()))?;
        }

        let native = CameraProjector::new(cam, &img.ego2global, cam.width, cam.height)?;
        let mut entries = Vec::new();
        let mut wires = Vec::new();
        for (i, b) in boxes.iter().enumerate() {
            let Some((center, depth)) = native.project(b.center) else {
                continue;
            };
            let corners: Vec<serde_json::Value> = b
                .corners()
                .iter()
                .map(|p| match native.project(*p) {
                    Some((q, _)) => json!([q.x, q.y]),
                    None => serde_json::Value::Null,
                })
                .collect();
            let wf = box_wireframe(&native, b, cfg);
            let in_view = wf
                .as_ref()
                .is_some_and(|segs| segs.iter().any(|s| segment_hits_image(&native, s)));
            if let Some(segs) = wf {
                wires.push((b.class.index(), segs));
            }
            entries.push(json!({
                "box": i, "class": b.class.name(), "center": b.center.to_array(),
                "center_px": [center.x, center.y], "depth": depth,
                "corners_px": corners, "in_view": in_view,
            }));
        }
        cams_json.insert(cam.name.clone(), serde_json::Value::Array(entries));
        // the camera as a protocol-v2 `plan` request describes it at the native size (lidar2img included)
        let frame = CameraFrame {
            camera: cam.name.clone(),
            width: cam.width,
            height: cam.height,
            rgb: std::sync::Arc::new(photo.as_raw().clone()),
            intrinsic: cam.intrinsic,
            cam2ego: cam.cam2ego,
            ego2global: img.ego2global,
        };
        protocol.insert(
            cam.name.clone(),
            camera_entry(&frame, &lidar.ego2global, &lidar.lidar2ego),
        );

        let mut photo = photo.clone();
        blend_masks(&mut photo, &masks);
        for (cls, segs) in &wires {
            for (a, b) in segs {
                draw_line(&mut photo, *a, *b, MASK_COLOURS[*cls]);
            }
        }
        let photo = match args.overlay_width {
            Some(w) if w > 0 && w != cam.width => {
                let h = ((cam.height as u64 * w as u64) / cam.width as u64).max(1) as u32;
                image::imageops::resize(&photo, w, h, image::imageops::FilterType::Triangle)
            }
            _ => photo,
        };
        if args.overlay_png {
            let p = dir.join("overlay.png");
            photo
                .save(&p)
                .with_context(|| format!("writing {}", p.display()))?;
        } else {
            let p = dir.join("overlay.jpg");
            let f =
                std::fs::File::create(&p).with_context(|| format!("creating {}", p.display()))?;
            image::codecs::jpeg::JpegEncoder::new_with_quality(std::io::BufWriter::new(f), 85)
                .encode_image(&photo)
                .with_context(|| format!("writing {}", p.display()))?;
        }
    }
    let p = args.out.join("projection.json");
    let mut doc = json!({
        "cameras": cams_json, "protocol_cameras": protocol,
        "ego2global": rows4(&lidar.ego2global), "lidar2ego": rows4(&lidar.lidar2ego),
    });
    if let (Some(o), serde_json::Value::Object(a)) = (doc.as_object_mut(), about) {
        o.extend(a);
    }
    let text = serde_json::to_string_pretty(&doc)?;
    std::fs::write(&p, text).with_context(|| format!("writing {}", p.display()))?;
    println!(
        "wrote masks, overlays and {} for {} cameras",
        p.display(),
        views.len()
    );
    Ok(())
}

fn segment_hits_image(p: &CameraProjector, (a, b): &(DVec2, DVec2)) -> bool {
    // sample along the segment: enough for a yes/no in-view flag
    (0..=32).any(|k| p.in_image(a.lerp(*b, k as f64 / 32.0)))
}

/// Blends the masks (render resolution) onto the native image; each native pixel takes the mask pixel whose
/// area it falls in (nearest under the align_corners=False mapping).
fn blend_masks(photo: &mut RgbImage, m: &LayoutMasks) {
    let (w, h) = photo.dimensions();
    let (sx, sy) = (m.width as f64 / w as f64, m.height as f64 / h as f64);
    for y in 0..h {
        let my = (((y as f64 + 0.5) * sy) as usize).min(m.height - 1);
        for x in 0..w {
            let mx = (((x as f64 + 0.5) * sx) as usize).min(m.width - 1);
            let px = photo.get_pixel_mut(x, y);
            // map channels first (under), boxes last (over)
            for c in (0..NUM_MASK_CHANNELS).rev() {
                if m.channel(c)[my * m.width + mx] != 0 {
                    let a = if c >= 10 { 0.3 } else { 0.4 };
                    for (v, col) in px.0.iter_mut().zip(MASK_COLOURS[c]) {
                        *v = (*v as f64 * (1.0 - a) + col as f64 * a) as u8;
                    }
                }
            }
        }
    }
}

/// A 3-pixel-wide line (pixel centres at integer coordinates), clipped to the image by skipping off-image samples.
fn draw_line(img: &mut RgbImage, a: DVec2, b: DVec2, c: [u8; 3]) {
    let (w, h) = (img.width() as i64, img.height() as i64);
    // Liang-Barsky against the image rectangle (plus the pen's margin): near-clipped edges can end ~1e5 px away
    let (lo, hi) = (
        DVec2::splat(-2.0),
        DVec2::new(w as f64 + 1.0, h as f64 + 1.0),
    );
    let d = b - a;
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-d.x, a.x - lo.x),
        (d.x, hi.x - a.x),
        (-d.y, a.y - lo.y),
        (d.y, hi.y - a.y),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return;
            }
        } else if p < 0.0 {
            t0 = t0.max(q / p);
        } else {
            t1 = t1.min(q / p);
        }
    }
    if t0 > t1 {
        return;
    }
    let (a, b) = (a + d * t0, a + d * t1);
    let n = ((b - a).abs().max_element().ceil() as i64).clamp(1, 20_000);
    for k in 0..=n {
        let p = a.lerp(b, k as f64 / n as f64);
        let (x, y) = (p.x.round() as i64, p.y.round() as i64);
        for dy in -1..=1 {
            for dx in -1..=1 {
                let (xx, yy) = (x + dx, y + dy);
                if xx >= 0 && yy >= 0 && xx < w && yy < h {
                    img.put_pixel(xx as u32, yy as u32, Rgb(c));
                }
            }
        }
    }
}

/// 4x4 rows (`m[r][c]`), as the protocol writes matrices.
fn rows4(m: &glam::DMat4) -> [[f64; 4]; 4] {
    [0, 1, 2, 3].map(|r| m.row(r).to_array())
}
