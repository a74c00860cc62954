//! Closed-loop simulation speed: one 15 s scenario (150 steps at 10 Hz) with IDM agents and the expert
//! planner (LQR tracker + bicycle every step, planner at 2 Hz), single thread. Scenario loading is outside
//! the timed region. Prints steps/s. Names: sim_<agents>_<scene>_150steps.
use b2dr::scene::import::scenarionet;
use b2dr::scene::Scenario;
use b2dr::sim::{run, AgentMode, ExpertPlanner, SimConfig};
use b2dr::world::town as synthetic;
use criterion::{black_box, criterion_group, criterion_main, Criterion};
use std::path::PathBuf;
use std::time::Instant;

fn bench_one(c: &mut Criterion, name: &str, sc: &Scenario, agents: AgentMode) {
    let cfg = SimConfig {
        agents,
        ..SimConfig::default()
    };
    // One timed run outside criterion for a steps/s line.
    let t0 = Instant::now();
    let r = run(sc, &mut ExpertPlanner, &cfg);
    let dt = t0.elapsed().as_secs_f64();
    let steps = r.steps.len() - 1;
    println!(
        "{name}: {steps} steps, {} IDM agents, {:.2} ms, {:.0} steps/s",
        r.idm_agents,
        dt * 1e3,
        steps as f64 / dt
    );
    c.bench_function(name, |b| {
        b.iter(|| black_box(run(black_box(sc), &mut ExpertPlanner, &cfg)))
    });
    // The measure: the simulation plus the full nuPlan score of the run.
    let params = b2dr::metrics::ScoreParams::default();
    c.bench_function(&format!("{name}_with_score"), |b| {
        b.iter(|| {
            let r = run(black_box(sc), &mut ExpertPlanner, &cfg);
            black_box(b2dr::sim::score::score_run(sc, &r, &params).expect("score"))
        })
    });
}

fn benches(c: &mut Criterion) {
    let town = synthetic::town(1, Some(200));
    bench_one(c, "sim_idm_town200v_150steps", &town, AgentMode::Idm);
    let f = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/nuscenes-mini/scenes/scene-0061.json");
    if f.is_file() {
        let sc = scenarionet::load_file(&f).expect("scene-0061 loads");
        bench_one(c, "sim_idm_scene0061_150steps", &sc, AgentMode::Idm);
        bench_one(c, "sim_replay_scene0061_150steps", &sc, AgentMode::Replay);
    } else {
        println!("SKIP scene-0061 benches: {} absent", f.display());
    }
}

criterion_group! {
    name = sim;
    config = Criterion::default().sample_size(20);
    targets = benches
}
criterion_main!(sim);
