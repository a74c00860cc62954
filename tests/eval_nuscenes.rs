//! The generative renderer's closed loop on a nuScenes scene (the fixture of `tests/nuscenes_fixture`): the first
//! previous frame is the recorded camera images at t = 0 (the real JPEGs) and the references are recorded images
//! retrieved at the simulated pose. Skips without the shared data, Python or a Vulkan device.
#[path = "golden/b2dr_package.rs"]
mod b2dr_package;
mod common;
#[path = "common/fixture_dirs.rs"]
mod fixture_dirs;
#[path = "golden/common.rs"]
mod golden;
mod nuscenes_fixture;

use b2dr::eval::sensors::{nearest_recorded, planar, B2dr, B2drEngine};
use b2dr::projection::retrieve;
use b2dr::scene::import::nuscenes;
use b2dr::sim::closed_loop::run_with_sensors;
use b2dr::sim::AgentMode;
use b2dr::world::images::ImageStore;

#[test]
fn b2dr_renderer_starts_from_the_recorded_frame_and_retrieves_recorded_references() {
    let Some(root) = nuscenes_fixture::dataroot() else {
        return;
    };
    let Some(ctx) = common::ctx() else { return };
    let sc = nuscenes::load(&nuscenes_fixture::spec(root)).unwrap();
    let store = ImageStore::new(&sc, None);
    let cams = ["CAM_FRONT", "CAM_BACK"];
    let mut engine = B2drEngine::new(
        &ctx,
        b2dr_package::small_package(),
        b2dr::tensor::DType::F32,
        cams.iter().map(|c| c.to_string()).collect(),
        true,
        None,
        None,
        3,
    )
    .unwrap();
    let size = engine.size();
    let mut sensors = B2dr::new(&mut engine, &store).unwrap();
    sensors.record = Some(vec![]);
    let cfg = b2dr::sim::SimConfig {
        agents: AgentMode::Idm,
        steps: 10,
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
    assert_eq!(frames.len(), 2);
    let pixels = |img: &b2dr::scene::CameraImage| {
        planar(&store.image(img, size.1, size.0).unwrap().data, size)
    };
    // The first previous frame: the first keyframe's images.
    let mut want = vec![];
    for cam in cams {
        let img = nearest_recorded(&sc, cam, 0.0).unwrap();
        assert_eq!(img, sc.rig.frames[0].image(cam).unwrap());
        want.extend(pixels(img));
    }
    assert_eq!(frames[0].prev.as_ref(), Some(&want));
    assert!(
        frames[1].prev.is_none(),
        "later frames carry the previous one"
    );
    // References at the step-0 pose (the logged ego): the recorded images the linear scan finds.
    let e2g = b2dr::scene::import::ego2global(&sc.ego[0].rear_axle);
    let mut want = vec![];
    for cam in cams {
        let rf = retrieve(&sc.rig.frames, cam, &e2g);
        let pick = |x: &Option<b2dr::projection::Reference>| {
            x.as_ref().map(|r| &sc.rig.frames[r.frame].images[r.image])
        };
        let (a, b) = match (pick(&rf.front), pick(&rf.rear)) {
            (Some(a), Some(b)) => (a, b),
            (Some(a), None) | (None, Some(a)) => (a, a),
            (None, None) => panic!("no reference for {cam}"),
        };
        want.extend(pixels(a));
        want.extend(pixels(b));
    }
    assert_eq!(frames[0].ref_images, want);
    assert!(frames.iter().all(|f| f.image.iter().all(|v| v.is_finite())));
    common::assert_no_validation_errors();
}
