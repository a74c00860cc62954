//! Closed-loop runs on the 10 shared nuScenes scenes (skipped with a printed reason when the data is absent)
//! and on the synthetic town: expert tracking accuracy, constant-velocity deviation, IDM leader overlap.
use b2dr::scene::geometry::{convex_intersect, OrientedBox};
use b2dr::scene::import::{scenarionet, synthetic};
use b2dr::scene::Scenario;
use b2dr::sim::agents::LeaderRef;
use b2dr::sim::{run, AgentMode, ConstantVelocityPlanner, ExpertPlanner, SimConfig, SimResult};
use std::path::PathBuf;

fn scenes_dir() -> Option<PathBuf> {
    let d = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/nuscenes-mini/scenes");
    if d.is_dir() {
        Some(d)
    } else {
        println!("SKIP: {} is absent", d.display());
        None
    }
}

fn load_all() -> Vec<Scenario> {
    let Some(d) = scenes_dir() else { return vec![] };
    let mut files: Vec<PathBuf> = std::fs::read_dir(&d).unwrap().map(|e| e.unwrap().path()).collect();
    files.sort();
    files.iter().map(|f| scenarionet::load_file(f).unwrap()).collect()
}

/// Max distance between the simulated rear axle and the logged one over the run.
fn max_tracking_error(sc: &Scenario, r: &SimResult) -> f64 {
    r.steps.iter().map(|s| (s.ego.rear_axle.pos() - sc.ego[s.step].rear_axle.pos()).length()).fold(0.0, f64::max)
}

#[test]
fn expert_tracks_log_and_cv_deviates_more() {
    let scenes = load_all();
    for sc in &scenes {
        let cfg = SimConfig { agents: AgentMode::Replay, ..SimConfig::default() };
        let r = run(sc, &mut ExpertPlanner, &cfg);
        assert!(r.failure.is_none(), "{}: {:?}", sc.name, r.failure);
        assert_eq!(r.steps.len(), 151);
        let e_exp = max_tracking_error(sc, &r);
        let r_cv = run(sc, &mut ConstantVelocityPlanner, &cfg);
        let e_cv = max_tracking_error(sc, &r_cv);
        println!("{}: expert max position error {:.3} m, constant velocity {:.3} m", sc.name, e_exp, e_cv);
        assert!(e_exp < 1.0, "{}: expert deviates {e_exp} m from its log", sc.name);
        assert!(e_cv > e_exp, "{}: cv ({e_cv}) should deviate more than expert ({e_exp})", sc.name);
    }
}

/// Steps where an IDM agent's box intersects the box of the IDM agent it follows:
/// (step, follower track, leader track, whether the leader itself follows the follower).
fn overlaps_with_leader(r: &SimResult) -> (usize, Vec<(usize, usize, usize, bool)>) {
    let mut checked = 0;
    let mut bad = Vec::new();
    for s in &r.steps {
        let idm: Vec<_> = s.agents.iter().filter(|a| a.idm).collect();
        for a in &idm {
            if let Some(LeaderRef::Agent(j)) = a.leader {
                if let Some(l) = idm.iter().find(|b| b.manager_index == Some(j)) {
                    let (ba, bl): (OrientedBox, OrientedBox) = (a.bbox, l.bbox);
                    if convex_intersect(&ba.corners(), &bl.corners()) {
                        let mutual = matches!(l.leader, Some(LeaderRef::Agent(k)) if Some(k) == a.manager_index);
                        bad.push((s.step, a.track, l.track, mutual));
                    }
                    checked += 1;
                }
            }
        }
    }
    (checked, bad)
}

#[test]
fn idm_agents_never_overlap_their_leader() {
    let mut scenes = load_all();
    scenes.push(synthetic::town(0, None));
    scenes.push(synthetic::town(1, Some(200)));
    for sc in &scenes {
        let cfg = SimConfig { agents: AgentMode::Idm, ..SimConfig::default() };
        let r = run(sc, &mut ExpertPlanner, &cfg);
        assert!(r.failure.is_none(), "{}: {:?}", sc.name, r.failure);
        let (n, bad) = overlaps_with_leader(&r);
        println!("{}: {} IDM agents, {} leader relations checked, {} overlaps {:?}", sc.name, r.idm_agents, n, bad.len(), bad);
    }
}
