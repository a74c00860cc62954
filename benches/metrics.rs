//! Closed-loop score timing: `cargo bench --bench metrics`.
//! metrics_score_<steps>x<objects>: one whole `score_scenario` (all eight metrics) on the synthetic busy
//! scenario (straight 4-lane road, VecMap linear-scan map), single thread; prints the median of 20 runs.
//!
//! Recorded (release, shared 2-core dev box under load, 2026-11-23): 150x50 0.59 ms, 150x200 6.4 ms median
//! (2.2 ms min), 150x1000 37 ms median. Budget: well under 50 ms for 150 steps x ~200 objects.
use b2dr::metrics::synthetic::busy_scenario;
use b2dr::metrics::{score_scenario, ScoreParams};
use std::time::Instant;

fn main() {
    let p = ScoreParams::default();
    for (steps, objects) in [(150, 200), (150, 50), (150, 1000)] {
        let (map, trace) = busy_scenario(steps, objects, 7);
        let mut times = Vec::new();
        let mut score = 0.0;
        for _ in 0..20 {
            let t0 = Instant::now();
            score = score_scenario(&map, &trace, &p).expect("score").score;
            times.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(|a, b| a.total_cmp(b));
        println!(
            "metrics_score_{steps}x{objects}: median {:.2} ms, min {:.2} ms (score {score:.4})",
            times[times.len() / 2],
            times[0]
        );
    }
}
