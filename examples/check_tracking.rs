use b2dr::scene::import::scenarionet;
use b2dr::sim::{run, AgentMode, ExpertPlanner, SimConfig};
fn main() {
    let f = std::env::args().nth(1).unwrap();
    let sc = scenarionet::load_file(std::path::Path::new(&f)).unwrap();
    let r = run(&sc, &mut ExpertPlanner, &SimConfig { agents: AgentMode::None, ..Default::default() });
    for s in r.steps.iter().step_by(5) {
        let log = sc.ego[s.step].rear_axle;
        let rel = log.relative(&s.ego.rear_axle);
        let vlog = sc.ego[s.step].velocity.length();
        println!("{:3} lon {:+.3} lat {:+.3} dh {:+.4} v {:.2} vlog {:.2} steer {:+.3} acc {:+.2}", s.step, rel.x, rel.y, rel.heading, s.ego.vx, vlog, s.ego.steering, s.ego.ax);
    }
}
