//! Reader of the shared keyframe format (`b2dr-shared-keyframe/v1`, e.g.
//! `nuscenes-mini/keyframe-scene-0061/frame.json`): cameras with intrinsics, extrinsics and their own ego pose at
//! exposure, plus annotated 3D boxes in the global frame. Matrices are row-major in the file.
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use glam::{DMat4, DVec3};
use serde::Deserialize;

use super::geometry::{mat3_from_rows, mat4_from_rows, Box3d, BoxClass};
use crate::scene::camera::{Camera, CameraImage};

/// Top-level fields, kept as JSON values so each is decoded with its own name in the error.
#[derive(Deserialize)]
struct RawFrame {
    ego2global: serde_json::Value,
    cameras: serde_json::Map<String, serde_json::Value>,
    boxes: Vec<serde_json::Value>,
}

#[derive(Deserialize)]
struct RawCamera {
    image: String,
    width: u32,
    height: u32,
    #[serde(default)]
    timestamp_us: i64,
    intrinsic: [[f64; 3]; 3],
    cam2ego: [[f64; 4]; 4],
    ego2global: [[f64; 4]; 4],
}

#[derive(Deserialize)]
struct RawBox {
    category: String,
    center: [f64; 3],
    size_lwh: [f64; 3],
    yaw: f64,
}

/// One loaded keyframe.
#[derive(Clone, Debug)]
pub struct KeyFrame {
    /// Directory of `frame.json` (image paths are relative to it).
    pub dir: PathBuf,
    /// Ego pose at the keyframe (lidar) time.
    pub ego2global: DMat4,
    /// Cameras sorted by name, each with its image (own ego pose at exposure).
    pub cameras: Vec<(Camera, CameraImage)>,
    /// Boxes in file order (indices match `boxes[]` in the file).
    pub boxes: Vec<Box3d>,
}

fn check_pose(m: &DMat4, what: &str) -> Result<()> {
    ensure!(
        m.to_cols_array().iter().all(|v| v.is_finite()),
        "{what}: non-finite value"
    );
    let r = glam::DMat3::from_mat4(*m);
    ensure!(
        (r.determinant() - 1.0).abs() < 1e-3,
        "{what}: rotation part is not a rotation (det {})",
        r.determinant()
    );
    ensure!(
        m.row(3) == glam::DVec4::new(0.0, 0.0, 0.0, 1.0),
        "{what}: last row must be [0, 0, 0, 1]"
    );
    Ok(())
}

impl KeyFrame {
    /// Reads and validates `frame.json`; errors name the file and the field.
    pub fn load(path: &Path) -> Result<KeyFrame> {
        let text =
            crate::files::read_regular_string(path, "keyframe file", crate::files::JSON_LIMIT)?;
        let text = nan_to_null(&text);
        let raw: RawFrame =
            serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        let ctx = |field: String| format!("{}: {field}", path.display());
        let e2g_rows: [[f64; 4]; 4] =
            serde_json::from_value(raw.ego2global).with_context(|| ctx("ego2global".into()))?;
        let ego2global = mat4_from_rows(&e2g_rows);
        check_pose(&ego2global, &ctx("ego2global".into()))?;
        let mut cameras = Vec::new();
        for (name, v) in &raw.cameras {
            let c: RawCamera = serde_json::from_value(v.clone())
                .with_context(|| ctx(format!("cameras.{name}")))?;
            let cam = Camera {
                name: name.clone(),
                intrinsic: mat3_from_rows(&c.intrinsic),
                cam2ego: mat4_from_rows(&c.cam2ego),
                width: c.width,
                height: c.height,
                distortion: [0.0; 5],
            };
            ensure!(
                c.width > 0 && c.height > 0 && c.width <= 16384 && c.height <= 16384,
                "{}: size {}x{} (each side in 1..=16384)",
                ctx(format!("cameras.{name}.width/height")),
                c.width,
                c.height
            );
            let k = &c.intrinsic;
            ensure!(
                k[0][0] > 0.0 && k[1][1] > 0.0 && k[1][0] == 0.0 && k[2] == [0.0, 0.0, 1.0],
                "{}: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {k:?}",
                ctx(format!("cameras.{name}.intrinsic"))
            );
            check_pose(&cam.cam2ego, &ctx(format!("cameras.{name}.cam2ego")))?;
            let e2g = mat4_from_rows(&c.ego2global);
            check_pose(&e2g, &ctx(format!("cameras.{name}.ego2global")))?;
            let image = CameraImage {
                camera: name.clone(),
                path: c.image,
                timestamp_us: c.timestamp_us,
                ego2global: e2g,
            };
            cameras.push((cam, image));
        }
        ensure!(!cameras.is_empty(), "{}: no cameras", ctx("cameras".into()));
        cameras.sort_by(|a, b| a.0.name.cmp(&b.0.name));
        let mut boxes = Vec::with_capacity(raw.boxes.len());
        for (i, b) in raw.boxes.into_iter().enumerate() {
            let b: RawBox =
                serde_json::from_value(b).with_context(|| ctx(format!("boxes[{i}]")))?;
            let Some(class) = BoxClass::parse(&b.category) else {
                bail!(
                    "{}: unknown category {:?}",
                    ctx(format!("boxes[{i}].category")),
                    b.category
                );
            };
            ensure!(
                b.size_lwh.iter().all(|s| s.is_finite() && *s > 0.0),
                "{}: sizes must be positive, got {:?}",
                ctx(format!("boxes[{i}].size_lwh")),
                b.size_lwh
            );
            ensure!(
                b.center.iter().all(|s| s.is_finite()) && b.yaw.is_finite(),
                "{}: non-finite centre or yaw",
                ctx(format!("boxes[{i}]"))
            );
            boxes.push(Box3d {
                class,
                center: DVec3::from(b.center),
                size: DVec3::from(b.size_lwh),
                yaw: b.yaw,
            });
        }
        let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        Ok(KeyFrame {
            dir,
            ego2global,
            cameras,
            boxes,
        })
    }

    /// Reinterprets each box's `center.z` as the height of its top face (moves boxes down by half their
    /// height). The shared `keyframe-scene-0061/frame.json` (b2dr-shared-keyframe/v1, as of 2026-11-23) stores
    /// `z = nuScenes translation z + h/2` although its README calls it the gravity centre: nuScenes'
    /// translation already is the box centre (the same objects in `scenes/scene-0061.json` have z 0.8 / 0.741 /
    /// 1.623 where frame.json has 1.6204 / 1.5559 / 3.4192). See docs/projection.md.
    pub fn boxes_z_from_top(&mut self) {
        for b in &mut self.boxes {
            b.center.z -= 0.5 * b.size.z;
        }
    }

    /// Decides how `center.z` is stored from the data: vehicles stand on the road, so under the right reading
    /// the median height of vehicle-box bottoms above the ego's ground (`ego2global` z) is near 0. Returns
    /// true ("top face") when reading z as the top puts the bottoms closer to the ground than reading it as
    /// the centre, by more than 0.3 m; false with fewer than 3 vehicle boxes (the documented reading).
    pub fn z_looks_like_top(&self) -> bool {
        use super::geometry::BoxClass as C;
        let ground = self.ego2global.w_axis.z;
        let mut as_center = vec![];
        let mut as_top = vec![];
        for b in &self.boxes {
            if matches!(
                b.class,
                C::Car | C::Truck | C::Bus | C::Trailer | C::ConstructionVehicle
            ) {
                as_center.push(b.center.z - 0.5 * b.size.z - ground);
                as_top.push(b.center.z - b.size.z - ground);
            }
        }
        if as_center.len() < 3 {
            return false;
        }
        let median = |v: &mut Vec<f64>| {
            v.sort_by(|a, b| a.total_cmp(b));
            v[v.len() / 2]
        };
        median(&mut as_top).abs() + 0.3 < median(&mut as_center).abs()
    }

    /// Path of a camera's image file.
    pub fn image_path(&self, img: &CameraImage) -> PathBuf {
        self.dir.join(&img.path)
    }
}

/// Python's `json.dump` writes non-finite floats as bare `NaN` / `Infinity` / `-Infinity` (nuScenes has NaN
/// velocities); JSON has no such tokens. They are turned into `null` outside strings, so an optional field we do
/// not read parses and a required one fails with serde's "invalid type: null" at its line and column.
pub fn nan_to_null(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = String::with_capacity(text.len());
    let (mut i, mut start, mut in_str) = (0, 0, false);
    while i < b.len() {
        let c = b[i];
        if in_str {
            if c == b'\\' {
                i += 2;
                continue;
            }
            if c == b'"' {
                in_str = false;
            }
            i += 1;
            continue;
        }
        if c == b'"' {
            in_str = true;
            i += 1;
            continue;
        }
        let rest = &b[i..];
        let tok = [&b"-Infinity"[..], b"Infinity", b"NaN"]
            .into_iter()
            .find(|t| rest.starts_with(t));
        if let Some(t) = tok {
            out.push_str(&text[start..i]);
            out.push_str("null");
            i += t.len();
            start = i;
            continue;
        }
        i += 1;
    }
    out.push_str(&text[start..]);
    out
}

/// Drivable-area polygons from a GeoJSON `MultiPolygon` or `Polygon` (global frame, metres; e.g.
/// `nuscenes-mini/maps/<map>.drivable_area.geojson`), at ground height `z`. Each polygon's first ring is its
/// exterior, the others holes.
pub fn drivable_area_from_geojson(path: &Path, z: f64) -> Result<Vec<super::geometry::MapElement>> {
    use super::geometry::{MapClass, MapElement, MapGeometry};
    #[derive(Deserialize)]
    struct Geo {
        #[serde(rename = "type")]
        kind: String,
        coordinates: serde_json::Value,
    }
    let text = crate::files::read_regular_string(path, "map file", crate::files::JSON_LIMIT)?;
    let geo: Geo =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    let polys: Vec<Vec<Vec<[f64; 2]>>> = match geo.kind.as_str() {
        "MultiPolygon" => serde_json::from_value(geo.coordinates),
        "Polygon" => serde_json::from_value(geo.coordinates).map(|p| vec![p]),
        k => bail!(
            "{}: type: expected MultiPolygon or Polygon, got {k:?}",
            path.display()
        ),
    }
    .with_context(|| format!("{}: coordinates", path.display()))?;
    let ring = |r: &Vec<[f64; 2]>| {
        r.iter()
            .map(|p| DVec3::new(p[0], p[1], z))
            .collect::<Vec<_>>()
    };
    Ok(polys
        .iter()
        .filter(|p| !p.is_empty())
        .map(|p| MapElement {
            class: MapClass::DrivableArea,
            geometry: MapGeometry::Polygon {
                exterior: ring(&p[0]),
                holes: p[1..].iter().map(ring).collect(),
            },
        })
        .collect())
}
