//! `b2dr run`: with `--renderer none` the scores equal `b2dr sim`'s; groundtruth frames equal the world's
//! ground truth of the simulated state bit for bit; log replay gives the recorded frame nearest in time; the
//! b2dr renderer reruns bit-identically; `--resume` refuses another configuration.
#[path = "golden/b2dr_package.rs"]
mod b2dr_package;
mod common;
#[path = "golden/common.rs"]
mod golden;

use std::path::{Path, PathBuf};

use b2dr::eval::run::{run, RendererMode, RunConfig};
use b2dr::sim::AgentMode;
use b2dr::world::images::ImageStore;
use b2dr::world::World;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("b2dr-run-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn cfg(renderer: RendererMode, agents: AgentMode, controller: &str, steps: usize) -> RunConfig {
    RunConfig {
        scenario: "builtin:town:2".into(),
        renderer,
        model: None,
        planner: "expert".parse().unwrap(),
        agents,
        controller: controller.parse().unwrap(),
        steps,
        planner_timeout_s: 30.0,
        planner_start_timeout_s: 300.0,
        cameras: vec![],
        size: (56, 104),
        seed: 0,
        dtype: b2dr::tensor::DType::F32,
        gif: false,
        shard: None,
        requests: Default::default(),
    }
}

fn png(p: &Path) -> Vec<u8> {
    image::open(p).unwrap().to_rgb8().into_raw()
}

#[test]
fn renderer_none_scores_equal_sim() {
    let out = tmp("none");
    let s = run(
        None,
        &cfg(RendererMode::None, AgentMode::Idm, "lqr", 150),
        &out,
        false,
    )
    .unwrap();
    let sc = b2dr::world::load_all("builtin:town:2").unwrap().remove(0);
    let r = b2dr::sim::run(
        &sc,
        &mut b2dr::sim::ExpertPlanner,
        &b2dr::sim::SimConfig::default(),
    );
    let want = b2dr::sim::score::score_run(&sc, &r, &Default::default())
        .unwrap()
        .score;
    assert_eq!(s["scenarios"][0]["score"].as_f64().unwrap(), want);
    // the trace is the sim's, line for line
    let trace = std::fs::read_to_string(out.join("town-2/trace.jsonl")).unwrap();
    let want_trace: Vec<String> = r
        .steps
        .iter()
        .map(|s| serde_json::to_string(s).unwrap())
        .collect();
    assert_eq!(trace.lines().collect::<Vec<_>>(), want_trace);
}

#[test]
fn groundtruth_frames_equal_the_world_and_log_replay_the_log() {
    let sc = b2dr::world::load_all("builtin:town:2").unwrap().remove(0);
    let world = World::new(&sc);
    // replayed agents + the expert + perfect tracking: the simulated state is the log's
    let out = tmp("gt");
    run(
        None,
        &cfg(RendererMode::Groundtruth, AgentMode::Replay, "perfect", 20),
        &out,
        false,
    )
    .unwrap();
    for k in [0usize, 5, 10, 15] {
        let e2g = b2dr::scene::import::ego2global(&sc.ego[k].rear_axle);
        let want = world
            .render_step(&sc.rig.cameras, &e2g, k, 104, 56, 1)
            .unwrap();
        for f in &want {
            let got = png(&out.join(format!("town-2/frames/{k:04}_{}.png", f.camera)));
            assert_eq!(
                got, f.rgb,
                "step {k} {}: groundtruth frame differs from the world's",
                f.camera
            );
        }
    }
    // log replay: the recorded image nearest in time, whatever the ego does (IDM agents, LQR)
    let out = tmp("lr");
    run(
        None,
        &cfg(RendererMode::LogReplay, AgentMode::Idm, "lqr", 20),
        &out,
        false,
    )
    .unwrap();
    let store = ImageStore::new(&sc, None);
    for k in [0usize, 5, 10, 15] {
        for c in &sc.rig.cameras {
            let img =
                b2dr::eval::sensors::nearest_recorded(&sc, &c.name, k as f64 * sc.dt).unwrap();
            assert_eq!(
                img.timestamp_us,
                (k as f64 * sc.dt * 1e6).round() as i64,
                "a frame at each planner step"
            );
            let want = store.image(img, 104, 56).unwrap();
            let got = png(&out.join(format!("town-2/frames/{k:04}_{}.png", c.name)));
            assert_eq!(got, want.data, "step {k} {}", c.name);
        }
    }
}

#[test]
fn b2dr_renderer_reruns_bit_identically_and_resume_checks_the_config() {
    let Some(ctx) = common::ctx() else { return };
    let dir = tmp("pkg");
    b2dr_package::small_package()
        .save(&dir, b2dr::nn::weights::FileDType::F32)
        .unwrap();
    let mut c = cfg(RendererMode::B2dr, AgentMode::Idm, "lqr", 10);
    c.model = Some(dir.clone());
    c.cameras = vec!["CAM_FRONT".into(), "CAM_BACK".into()];
    let (o1, o2) = (tmp("b1"), tmp("b2"));
    let s = run(Some(&ctx), &c, &o1, false).unwrap();
    run(Some(&ctx), &c, &o2, false).unwrap();
    assert!(
        s["scenarios"][0]["failure"].is_null(),
        "{}",
        s["scenarios"][0]["failure"]
    );
    assert_eq!(s["scenarios"][0]["frames"], 2);
    for k in [0, 5] {
        for cam in ["CAM_FRONT", "CAM_BACK"] {
            let f = format!("town-2/frames/{k:04}_{cam}.png");
            assert_eq!(png(&o1.join(&f)), png(&o2.join(&f)), "{f}: reruns differ");
        }
    }
    assert_ne!(
        png(&o1.join("town-2/frames/0000_CAM_FRONT.png")),
        png(&o1.join("town-2/frames/0005_CAM_FRONT.png")),
        "frames differ over time"
    );
    let t = &s["scenarios"][0]["timing_ms"];
    for k in [
        "projection",
        "retrieval",
        "encode",
        "denoise",
        "decode",
        "planner",
        "sim",
    ] {
        assert!(t[k].as_f64().is_some(), "timing {k} missing: {t}");
    }
    // resume: same configuration skips, another is refused
    let again = run(Some(&ctx), &c, &o1, true).unwrap();
    assert_eq!(again["scenarios"][0]["score"], s["scenarios"][0]["score"]);
    let mut other = c.clone();
    other.seed = 1;
    let e = format!("{:#}", run(Some(&ctx), &other, &o1, true).unwrap_err());
    assert!(
        e.contains("--resume") && e.contains("another configuration"),
        "{e}"
    );
    // the model's weights changed under the same path: refused, naming the file (issue #18)
    let cfg_json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(o1.join("config.json")).unwrap()).unwrap();
    let weights = dir.join("controlnet/diffusion_pytorch_model.safetensors");
    let key = weights.display().to_string();
    assert_eq!(cfg_json["input_files"][&key]["role"], "model", "{cfg_json}");
    let mut bytes = std::fs::read(&weights).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&weights, &bytes).unwrap();
    let e = format!("{:#}", run(Some(&ctx), &c, &o1, true).unwrap_err());
    assert!(
        e.contains("--resume") && e.contains(&format!("the model {key} changed")),
        "{e}"
    );
    bytes[last] ^= 1;
    std::fs::write(&weights, &bytes).unwrap();
    // the masks-only baseline runs too, and differs
    let mut nr = c.clone();
    nr.renderer = RendererMode::B2drNorefNoprev;
    let o3 = tmp("b3");
    run(Some(&ctx), &nr, &o3, false).unwrap();
    assert_ne!(
        png(&o1.join("town-2/frames/0005_CAM_FRONT.png")),
        png(&o3.join("town-2/frames/0005_CAM_FRONT.png"))
    );
    common::assert_no_validation_errors();
}

/// Each frame of `b2dr run --renderer b2dr` equals a standalone render (a separately planned renderer) of the
/// same inputs, bit for bit: the loop adds no state of its own beyond the carried previous frame.
#[test]
fn b2dr_loop_frames_equal_standalone_renders() {
    let Some(ctx) = common::ctx() else { return };
    let frames = loop_frames_vs_standalone(&ctx, 0.0);
    assert!(frames.iter().all(|f| f.prev_warp.is_none()));
    common::assert_no_validation_errors();
}

/// The same with a model that warps its previous frame (b2dr.json prev_warp_max_depth): every frame gets a
/// grid, and the ego's motion between frames moves it (the pose the loop warps from is the last frame's).
#[test]
fn b2dr_loop_frames_with_a_warping_model_equal_standalone_renders() {
    use b2dr::ops::warp::NO_SOURCE;
    let Some(ctx) = common::ctx() else { return };
    let frames = loop_frames_vs_standalone(&ctx, 30.0);
    for (k, f) in frames.iter().enumerate() {
        let g = f.prev_warp.as_ref().expect("a grid for every frame");
        assert_eq!(g.len(), 2 * 56 * 104 * 2, "two cameras' (H, W, 2)");
        let moved = g
            .chunks(2)
            .enumerate()
            .filter(|(i, v)| {
                let (x, y) = ((i % (56 * 104)) % 104, (i % (56 * 104)) / 104);
                v[0] != NO_SOURCE
                    && ((v[0] - x as f32).abs() > 0.5 || (v[1] - y as f32).abs() > 0.5)
            })
            .count();
        if k > 0 {
            assert!(
                moved > 1000,
                "frame {k}: the ego drove 0.5 s, yet {moved} pixels moved"
            );
        }
    }
    common::assert_no_validation_errors();
}

/// A model that takes its previous frame from its references (b2dr.json prev_source "reference"): every frame,
/// the first one included, is given its previous frame as an image: per camera the retrieved reference behind it
/// along its axis (CAM_FRONT: the rear one, which it must take at least once; CAM_BACK_LEFT, which looks
/// backwards: the front one when it takes one, which at this reach it may never do: tests/render_warp.rs checks
/// the backward choice), warped from that reference's pose, where that warp reaches `MIN_REFERENCE_COVERAGE` of
/// the frame, else the frame rendered before (8-bit); each frame still equals a standalone render of its inputs.
#[test]
fn b2dr_loop_frames_with_a_reference_base_equal_standalone_renders() {
    use b2dr::eval::sensors::as_8bit;
    use b2dr::nn::b2dr_config::PrevSource;
    let Some(ctx) = common::ctx() else { return };
    let frames = loop_frames_vs_standalone_with(&ctx, 30.0, PrevSource::Reference);
    let per = 3 * 56 * 104;
    let mut front_took = 0;
    for (k, f) in frames.iter().enumerate() {
        let prev = f
            .prev
            .as_ref()
            .expect("every frame gets its previous frame as an image");
        assert_eq!(prev.len(), 2 * per);
        assert_eq!(f.took_reference.len(), 2);
        // camera c's reference j sits at ref_images[(2 c + j) per..]
        for (c, j) in [(0, 1), (1, 0)] {
            let mine = &prev[c * per..(c + 1) * per];
            if f.took_reference[c] {
                assert!(
                    mine == &f.ref_images[(2 * c + j) * per..(2 * c + j + 1) * per],
                    "frame {k} camera {c}"
                );
            } else if k > 0 {
                let last = as_8bit(&frames[k - 1].image);
                assert!(
                    mine == &last[c * per..(c + 1) * per],
                    "frame {k} camera {c}: the frame before"
                );
            }
        }
        // at the log's start there is nothing behind: both references are the one ahead
        if !f.took_reference[0] || f.ref_images[..per] == f.ref_images[per..2 * per] {
            continue;
        }
        front_took += 1;
        // the grid warps the rear reference from its pose, metres behind the ego: most CAM_FRONT pixels find
        // their source nearer the image centre than themselves
        let g = f.prev_warp.as_ref().expect("a grid for every frame");
        let (mut inward, mut with_source) = (0, 0);
        for (i, v) in g[..2 * 56 * 104].chunks(2).enumerate() {
            if v[0] == b2dr::ops::warp::NO_SOURCE {
                continue;
            }
            with_source += 1;
            let (x, y) = ((i % 104) as f32, (i / 104) as f32);
            if (v[0] - 51.5).abs() + (v[1] - 27.5).abs() < (x - 51.5).abs() + (y - 27.5).abs() - 0.5
            {
                inward += 1;
            }
        }
        assert!(
            inward * 2 > with_source,
            "frame {k}: {inward} of {with_source} CAM_FRONT pixels sample nearer the centre"
        );
    }
    assert!(
        front_took > 0,
        "CAM_FRONT never started from a rear reference"
    );
    common::assert_no_validation_errors();
}

/// A "composite" model (b2dr.json prev_source): a camera that takes its reference is given the composite
/// already warped (a grid that keeps every pixel: tests/prev_base.rs checks its pixels), one that falls back
/// the frame before with its warp; each frame still equals a standalone render of its inputs.
#[test]
fn b2dr_loop_frames_with_a_composite_base_equal_standalone_renders() {
    use b2dr::nn::b2dr_config::PrevSource;
    use b2dr::ops::warp::NO_SOURCE;
    let Some(ctx) = common::ctx() else { return };
    let frames = loop_frames_vs_standalone_with(&ctx, 30.0, PrevSource::Composite);
    let hw = 56 * 104;
    let mut took = 0;
    for (k, f) in frames.iter().enumerate() {
        assert!(
            f.prev.is_some(),
            "frame {k}: the previous frame as an image"
        );
        let g = f.prev_warp.as_ref().expect("a grid for every frame");
        for (c, &t) in f.took_reference.iter().enumerate() {
            let unwarped = g[c * 2 * hw..(c + 1) * 2 * hw]
                .iter()
                .all(|&v| v == NO_SOURCE);
            assert_eq!(unwarped, t, "frame {k} camera {c}: took its reference {t}");
            took += t as usize;
        }
    }
    assert!(took > 0, "no camera ever took its reference");
    common::assert_no_validation_errors();
}

/// Runs 15 steps of builtin:town:2 with the small package (its prev_warp_max_depth set to `warp`), then replays
/// every recorded frame's inputs through a standalone renderer and asserts the same image bit for bit.
fn loop_frames_vs_standalone(
    ctx: &b2dr::vk::Context,
    warp: f64,
) -> Vec<b2dr::eval::sensors::FrameRecord> {
    loop_frames_vs_standalone_with(ctx, warp, b2dr::nn::b2dr_config::PrevSource::Previous)
}

fn loop_frames_vs_standalone_with(
    ctx: &b2dr::vk::Context,
    warp: f64,
    source: b2dr::nn::b2dr_config::PrevSource,
) -> Vec<b2dr::eval::sensors::FrameRecord> {
    use b2dr::eval::sensors::{B2dr, B2drEngine};
    use b2dr::render::frame::{FrameInputs, Prev, RefInputs};
    use b2dr::sim::closed_loop::run_with_sensors;
    let sc = b2dr::world::load_all("builtin:town:2").unwrap().remove(0);
    let store = ImageStore::new(&sc, None);
    let mut pkg = b2dr_package::small_package();
    pkg.control_cfg.prev_warp_max_depth = warp;
    pkg.control_cfg.prev_source = source;
    let mut engine = B2drEngine::new(
        ctx,
        pkg,
        b2dr::tensor::DType::F32,
        vec!["CAM_FRONT".into(), "CAM_BACK_LEFT".into()],
        true,
        None,
        None,
        7,
    )
    .unwrap();
    let standalone = engine.standalone().unwrap();
    let mut sensors = B2dr::new(&mut engine, &store).unwrap();
    sensors.record = Some(vec![]);
    let cfg = b2dr::sim::SimConfig {
        agents: AgentMode::Idm,
        steps: 15,
        ..Default::default()
    };
    let r = run_with_sensors(
        &sc,
        &mut b2dr::sim::ExpertPlanner,
        &cfg,
        &|_, _| vec![],
        Some(&mut sensors),
        &mut |_, _| Ok(()),
    );
    assert!(r.failure.is_none(), "{:?}", r.failure);
    let frames = sensors.record.take().unwrap();
    assert_eq!(frames.len(), 3);
    for (k, f) in frames.iter().enumerate() {
        standalone
            .render(&FrameInputs {
                masks: &f.masks,
                prev: match &f.prev {
                    Some(p) => Prev::Image(p),
                    None => Prev::Carried,
                },
                refs: Some(RefInputs {
                    images: &f.ref_images,
                    pe_cur: f.pe_cur.iter().map(|v| &v[..]).collect(),
                    pe_ref: f.pe_ref.iter().map(|v| &v[..]).collect(),
                }),
                x_t: &f.x_t,
                eps_prev: &f.eps_prev,
                prev_warp: f.prev_warp.as_deref(),
            })
            .unwrap();
        assert_eq!(
            standalone.image().unwrap(),
            f.image,
            "frame {k} differs from the standalone render"
        );
    }
    frames
}
