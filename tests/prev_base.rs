//! The previous-frame base of a model that starts from its references (eval::prev_base): the reference's logged
//! agents against the world's own ground truth of that image, and the "composite" base's pixels against a
//! plain warp of its two sources. Host side only (no device).
use b2dr::eval::prev_base::{reference_agents, reference_base, AgentPixels};
use b2dr::eval::sensors::references;
use b2dr::nn::b2dr_config::B2drConfig;
use b2dr::ops::reference::image::warp_bilinear;
use b2dr::ops::warp::NO_SOURCE;
use b2dr::projection::scene::{boxes_at, map_layer};
use b2dr::projection::{BoxClass, ProjectionConfig};
use b2dr::render::inputs;
use b2dr::render::warp::{ground_warp_grid, reference_base_choice};
use b2dr::world::export::plan::frame_step;
use b2dr::world::images::ImageStore;
use b2dr::world::palette::SemanticClass;
use glam::DVec3;

const SIZE: (usize, usize) = (112, 200);
const DEPTH: f64 = 30.0;

fn config() -> B2drConfig {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("models/b2dr-res-z16-warp/controlnet/config.json");
    B2drConfig::from_file(&p).unwrap()
}

/// Every vehicle pixel the world draws in a retrieved reference image (its pose, its log step) lies inside
/// that reference's agent mask: the mask is the log's boxes at the image's own step, from its own pose (a
/// wrong step or pose would leave moving vehicles outside it).
#[test]
fn reference_agents_hold_the_vehicles_the_reference_shows() {
    let sc = b2dr::world::load_all("builtin:town:0:60")
        .unwrap()
        .remove(0);
    let store = ImageStore::new(&sc, None);
    let cams = sc.select_cameras(&["CAM_FRONT".to_string()]).unwrap();
    let (hw, mut vehicles, mut inside) = (SIZE.0 * SIZE.1, 0usize, 0usize);
    for fi in [10, 25, 40] {
        let e2g = sc.rig.frames[fi].ego2global;
        let r = references(&store, &config(), &cams, SIZE, &e2g).unwrap();
        let agents = reference_agents(&sc, &cams, &r, SIZE).unwrap();
        for (j, m) in agents[0].iter().enumerate() {
            let f = r.frames[0][j];
            let truth = store
                .world()
                .render_step(
                    &cams,
                    &r.poses[0][j],
                    frame_step(&sc, &sc.rig.frames[f]),
                    SIZE.1,
                    SIZE.0,
                    1,
                )
                .unwrap();
            assert_eq!(m.len(), hw);
            for (p, &c) in truth[0].class.iter().enumerate() {
                if c == SemanticClass::Vehicle as u8 {
                    vehicles += 1;
                    inside += m[p] as usize;
                }
            }
        }
    }
    assert!(
        vehicles > 200,
        "only {vehicles} vehicle pixels in the references: pick busier frames"
    );
    assert!(
        inside as f64 >= 0.97 * vehicles as f64,
        "{inside} of {vehicles} vehicle pixels inside the reference agent masks"
    );
}

/// "composite": where CAM_FRONT takes its reference, the base is that reference warped to the current pose,
/// except on the agents (the current layout's boxes and the reference's own logged agents, warped, grown by a
/// pixel), which hold the warped frame before; its grid keeps every pixel (the base is already warped). Without
/// agents ("reference") the base is the reference itself with its grid.
#[test]
fn composite_base_takes_the_agents_from_the_frame_before() {
    let sc = b2dr::world::load_all("builtin:town:0:60")
        .unwrap()
        .remove(0);
    let store = ImageStore::new(&sc, None);
    let cams = sc.select_cameras(&["CAM_FRONT".to_string()]).unwrap();
    let map = map_layer(&sc.map);
    let (h, w) = SIZE;
    let hw = h * w;
    let nb = BoxClass::ALL.len();
    let mut checked = 0;
    for fi in [10, 25, 40] {
        // the ego half a metre to the left of the log, so that nothing warps by the identity
        let e2g =
            sc.rig.frames[fi].ego2global * glam::DMat4::from_translation(DVec3::new(0.0, 0.5, 0.0));
        let r = references(&store, &config(), &cams, SIZE, &e2g).unwrap();
        let agents = reference_agents(&sc, &cams, &r, SIZE).unwrap();
        let bx: Vec<_> = boxes_at(&sc, frame_step(&sc, &sc.rig.frames[fi]))
            .into_iter()
            .map(|(_, b)| b)
            .collect();
        let masks =
            inputs::masks(&cams, &[e2g], &bx, &map, SIZE, &ProjectionConfig::default()).unwrap();
        // the frame before: a flat colour no 8-bit reference holds, 1 m behind
        let fallback = vec![0.123_456_f32; 3 * hw];
        let fpose = sc.rig.frames[fi].ego2global
            * glam::DMat4::from_translation(DVec3::new(-1.0, 0.0, 0.0));
        let a = AgentPixels {
            masks: &masks,
            refs: &agents,
        };
        let (img, grid, took) =
            reference_base(&cams, &e2g, &r, SIZE, DEPTH, &fallback, &[fpose], Some(&a)).unwrap();
        let (plain, pgrid, ptook) =
            reference_base(&cams, &e2g, &r, SIZE, DEPTH, &fallback, &[fpose], None).unwrap();
        assert_eq!(took, ptook);
        if !took[0] {
            assert_eq!(
                img, plain,
                "frame {fi}: a fallback camera is the same in both"
            );
            continue;
        }
        checked += 1;
        let j = reference_base_choice(&cams[0], &e2g, [&r.poses[0][0], &r.poses[0][1]]);
        let g = ground_warp_grid(&cams[0], &e2g, &r.poses[0][j], SIZE, DEPTH).unwrap();
        let reference = &r.images[j * 3 * hw..(j + 1) * 3 * hw];
        assert_eq!(
            &plain[..],
            reference,
            "frame {fi}: \"reference\" is the reference itself"
        );
        assert_eq!(pgrid, g);
        assert!(
            grid.iter().all(|&v| v == NO_SOURCE),
            "frame {fi}: the composite is given unwarped"
        );
        let f64s = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<_>>();
        let warped = warp_bilinear(&f64s(reference), &f64s(&g), 1, 3, h, w);
        let logged: Vec<f64> = agents[0][j].iter().map(|&b| b as u8 as f64).collect();
        let logged = warp_bilinear(&logged, &f64s(&g), 1, 1, h, w);
        let agent = |p: usize| logged[p] > 0.0 || (0..nb).any(|c| masks[c * hw + p] > 0.5);
        let (mut from_before, mut must) = (0, 0);
        for p in 0..hw {
            let before = (0..3).all(|c| img[c * hw + p] == 0.123_456);
            let near = |p: usize| {
                let (y, x) = ((p / w) as i64, (p % w) as i64);
                (-1..=1).any(|dy| {
                    (-1..=1).any(|dx| {
                        let (yy, xx) = (y + dy, x + dx);
                        (0..h as i64).contains(&yy)
                            && (0..w as i64).contains(&xx)
                            && agent((yy * w as i64 + xx) as usize)
                    })
                })
            };
            if agent(p) {
                must += 1;
                assert!(
                    before,
                    "frame {fi} pixel {p}: an agent pixel not from the frame before"
                );
            }
            if before {
                from_before += 1;
                assert!(
                    near(p),
                    "frame {fi} pixel {p}: from the frame before, but no agent within a pixel"
                );
            } else {
                for c in 0..3 {
                    let (got, want) = (img[c * hw + p] as f64, warped[c * hw + p]);
                    assert!(
                        (got - want).abs() < 1e-6,
                        "frame {fi} pixel {p}: {got} vs the warp's {want}"
                    );
                }
            }
        }
        assert!(
            must > 50,
            "frame {fi}: only {must} agent pixels: pick a busier frame"
        );
        // the rest is the reference's warp: a base taken wholly from the frame before fails here
        assert!(
            from_before < hw / 2,
            "frame {fi}: {from_before} of {hw} pixels from the frame before"
        );
    }
    assert!(
        checked >= 2,
        "CAM_FRONT took its reference on {checked} of 3 frames"
    );
}
