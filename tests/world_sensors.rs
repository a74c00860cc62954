//! The ground-truth renderer as the closed loop's observation engine: the frames of a run are the exact images
//! of the simulated state.
use b2dr::sim::closed_loop::run_with_sensors;
use b2dr::sim::{AgentMode, ExpertPlanner, SimConfig};
use b2dr::world::sensors::GroundTruthSensors;
use b2dr::world::{load_all, World};

#[test]
fn groundtruth_sensors_render_the_simulated_state() {
    let sc = load_all("builtin:straight:2").unwrap().remove(0);
    let cfg = SimConfig {
        agents: AgentMode::Replay,
        steps: 20,
        ..SimConfig::default()
    };
    let mut sensors = GroundTruthSensors::new(56, 100, 2).unwrap();
    let mut seen = Vec::new();
    let r = run_with_sensors(
        &sc,
        &mut ExpertPlanner,
        &cfg,
        &|_, _| vec![],
        Some(&mut sensors),
        &mut |step, frames| {
            seen.push((step, frames.to_vec()));
            Ok(())
        },
    );
    assert!(r.failure.is_none(), "{:?}", r.failure);
    assert!(seen.len() >= 2, "planner steps observed: {}", seen.len());
    let (step, frames) = &seen[1];
    assert_eq!(frames.len(), 6);
    assert_eq!((frames[0].width, frames[0].height), (100, 56));
    // With replayed agents the objects are the log's; the ego is the simulated one: rendering the world from
    // the frame's own ego pose at that step gives the same pixels.
    let world = World::new(&sc);
    let direct = world
        .render_step(&sc.rig.cameras, &frames[0].ego2global, *step, 100, 56, 1)
        .unwrap();
    for (f, d) in frames.iter().zip(&direct) {
        assert_eq!(f.camera, d.camera);
        assert_eq!(f.rgb.as_slice(), d.rgb.as_slice(), "{}", f.camera);
    }
    assert!(GroundTruthSensors::new(0, 100, 1).is_err());
}
