//! Projection benchmark: 1,000 boxes and a synthetic map into a 6-camera nuScenes-like rig at 400x224, masks
//! included, on one thread. `cargo bench --bench projection`.
//! - `project_6cam_1000box_map_400x224`: per-class masks (boxes + map) for all six cameras (the figure to keep
//!   under 20 ms).
//! - `project_6cam_1000box_400x224`: boxes only.
use b2dr::projection::geometry::{MapClass, MapElement, MapGeometry};
use b2dr::projection::{
    Box3d, BoxClass, CameraProjector, LayoutMasks, LayoutRenderer, MapLayer, ProjectionConfig,
};
use b2dr::scene::camera::Camera;
use criterion::{criterion_group, criterion_main, Criterion};
use glam::{DMat3, DMat4, DQuat, DVec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn rig() -> Vec<Camera> {
    // (name, yaw about ego z in degrees, focal length at 1600x900)
    let cams = [
        ("CAM_FRONT", 0.0, 1266.0),
        ("CAM_FRONT_LEFT", 55.0, 1260.0),
        ("CAM_FRONT_RIGHT", -55.0, 1260.0),
        ("CAM_BACK", 180.0, 800.0),
        ("CAM_BACK_LEFT", 110.0, 1260.0),
        ("CAM_BACK_RIGHT", -110.0, 1260.0),
    ];
    cams.iter()
        .map(|&(name, yaw, f)| {
            // optical axes: camera z along the yawed ego x, camera x to its right, camera y down
            let r = DQuat::from_rotation_z(f64::to_radians(yaw));
            let (z, x, y) = (r * DVec3::X, r * -DVec3::Y, -DVec3::Z);
            Camera {
                name: name.into(),
                intrinsic: DMat3::from_cols(
                    DVec3::new(f, 0.0, 0.0),
                    DVec3::new(0.0, f, 0.0),
                    DVec3::new(800.0, 450.0, 1.0),
                ),
                cam2ego: DMat4::from_cols(
                    x.extend(0.0),
                    y.extend(0.0),
                    z.extend(0.0),
                    (r * DVec3::new(1.0, 0.0, 0.0) + DVec3::new(0.5, 0.0, 1.5)).extend(1.0),
                ),
                width: 1600,
                height: 900,
                distortion: [0.0; 5],
            }
        })
        .collect()
}

fn scene() -> (Vec<Box3d>, MapLayer) {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let boxes = (0..1000)
        .map(|i| {
            let class = BoxClass::ALL[i % BoxClass::ALL.len()];
            let (x, y) = (rng.gen_range(-70.0..70.0), rng.gen_range(-70.0..70.0));
            let size = match class {
                BoxClass::Car => DVec3::new(4.5, 1.9, 1.6),
                BoxClass::Truck | BoxClass::Bus | BoxClass::Trailer => DVec3::new(10.0, 2.8, 3.5),
                BoxClass::Pedestrian | BoxClass::TrafficCone => DVec3::new(0.7, 0.7, 1.7),
                _ => DVec3::new(2.0, 1.0, 1.2),
            };
            Box3d {
                class,
                center: DVec3::new(x, y, size.z / 2.0),
                size,
                yaw: rng.gen_range(-std::f64::consts::PI..std::f64::consts::PI),
            }
        })
        .collect();
    // a 200 m road grid: 11 roads each way, each with a drivable polygon, 2 lane polygons, 3 polylines of 41
    // vertices, plus crosswalks at the crossings
    let mut map = Vec::new();
    let pt = |a: f64, b: f64, along_x: bool| {
        if along_x {
            DVec3::new(a, b, 0.0)
        } else {
            DVec3::new(b, a, 0.0)
        }
    };
    for k in -5..=5 {
        let c = k as f64 * 20.0;
        for along_x in [true, false] {
            let rect = |lo: f64, hi: f64| {
                vec![
                    pt(-100.0, c + lo, along_x),
                    pt(100.0, c + lo, along_x),
                    pt(100.0, c + hi, along_x),
                    pt(-100.0, c + hi, along_x),
                ]
            };
            map.push(MapElement {
                class: MapClass::DrivableArea,
                geometry: MapGeometry::Polygon {
                    exterior: rect(-4.0, 4.0),
                    holes: vec![],
                },
            });
            for (lo, hi) in [(-4.0, 0.0), (0.0, 4.0)] {
                map.push(MapElement {
                    class: MapClass::Lane,
                    geometry: MapGeometry::Polygon {
                        exterior: rect(lo, hi),
                        holes: vec![],
                    },
                });
            }
            for (off, class) in [
                (-4.0, MapClass::RoadBoundary),
                (0.0, MapClass::LaneDivider),
                (4.0, MapClass::RoadBoundary),
            ] {
                let line = (0..=40)
                    .map(|i| pt(-100.0 + 5.0 * i as f64, c + off, along_x))
                    .collect();
                map.push(MapElement {
                    class,
                    geometry: MapGeometry::Polyline(line),
                });
            }
            for j in -5..=5 {
                let d = j as f64 * 20.0 + 5.0;
                let cw = vec![
                    pt(d, c - 4.0, along_x),
                    pt(d + 3.0, c - 4.0, along_x),
                    pt(d + 3.0, c + 4.0, along_x),
                    pt(d, c + 4.0, along_x),
                ];
                map.push(MapElement {
                    class: MapClass::Crosswalk,
                    geometry: MapGeometry::Polygon {
                        exterior: cw,
                        holes: vec![],
                    },
                });
            }
        }
    }
    (boxes, MapLayer::new(map))
}

fn bench(c: &mut Criterion) {
    let cams = rig();
    let (boxes, map) = scene();
    let ego =
        DMat4::from_rotation_translation(DQuat::from_rotation_z(0.3), DVec3::new(3.0, 1.0, 0.0));
    let cfg = ProjectionConfig::default();
    let mut renderer = LayoutRenderer::new(400, 224);
    let mut masks: Vec<LayoutMasks> = (0..6).map(|_| LayoutMasks::new(400, 224)).collect();
    let empty = MapLayer::default();
    let mut run = |map: &MapLayer| {
        let mut drawn = 0;
        for (cam, m) in cams.iter().zip(masks.iter_mut()) {
            let p = CameraProjector::new(cam, &ego, 400, 224).unwrap();
            drawn += renderer.render(&p, &boxes, map, &cfg, m);
        }
        drawn
    };
    eprintln!(
        "boxes drawn over 6 cameras: {}, map elements: {}",
        run(&map),
        map.len()
    );
    c.bench_function("project_6cam_1000box_map_400x224", |b| {
        b.iter(|| run(std::hint::black_box(&map)))
    });
    c.bench_function("project_6cam_1000box_400x224", |b| {
        b.iter(|| run(std::hint::black_box(&empty)))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
