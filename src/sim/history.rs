//! The ego history of a protocol-v2 `plan` message (docs/planner_protocol.md, "History"): the last K ego
//! states at the planner's spacing (0.5 s) before the request time, in the CURRENT ego rear-axle frame.
//!
//! Slot k (k = 1..K, newest first) is the state at `time_s - 0.5 k`:
//! - `sim`: that time is at or after the scenario start (step 0): the simulated state of that step (step 0 is
//!   the logged state the run starts from; later steps are what the simulation did);
//! - `log`: before the start, where the scenario has logged ego states before step 0 ([`Scenario::ego_past`]);
//! - `pad`: before the start where the log has no such step (every importer today starts its log at step
//!   0): a copy of the oldest state available (the oldest logged past state, else step 0), with the slot's
//!   own `time_s`, so a model sees a car that stood there.
//!
//! [`Scenario::ego_past`]: crate::scene::Scenario::ego_past
use super::ego::EgoState;
use crate::scene::geometry::{wrap_angle, Pose2};
use crate::scene::EgoLogState;

/// Default number of history slots (`--history`).
pub const HISTORY_DEFAULT: usize = 4;
/// Most history slots accepted (60 s at 0.5 s).
pub const HISTORY_MAX: usize = 120;
/// Spacing of the slots (the planner's step).
pub const HISTORY_DT_S: f64 = 0.5;

/// Where a history slot's state comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum HistorySource {
    Sim,
    Log,
    Pad,
}

/// One past ego state, all in the CURRENT ego rear-axle frame (x forward, y left): the pose, and the past
/// state's rear-axle velocity and acceleration vectors rotated into it (a state with the current heading has
/// the `vx`, `vy`, `ax`, `ay` the request's `ego` would give it).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct HistoryEntry {
    /// Relative to the request time (negative).
    pub time_s: f64,
    pub x: f64,
    pub y: f64,
    pub heading: f64,
    pub vx: f64,
    pub vy: f64,
    pub ax: f64,
    pub ay: f64,
    pub from: HistorySource,
}

/// A logged ego state as (pose, ego-frame velocity, ego-frame acceleration).
fn log_state(e: &EgoLogState) -> (Pose2, f64, f64, f64, f64) {
    let (s, c) = e.rear_axle.heading.sin_cos();
    let fin = |v: f64| if v.is_finite() { v } else { 0.0 };
    let vx = c * e.velocity.x + s * e.velocity.y;
    let vy = -s * e.velocity.x + c * e.velocity.y;
    (e.rear_axle, fin(vx), fin(vy), fin(e.accel), 0.0)
}

fn sim_state(e: &EgoState) -> (Pose2, f64, f64, f64, f64) {
    (e.rear_axle, e.vx, e.vy, e.ax, e.ay)
}

/// The history of the request at `now` (step `step`). `sim(j)` is the simulated state of step j (j <= step;
/// j = step is `now`), `past` the logged ego before step 0 (oldest first, `dt` apart), `count` the slots.
pub fn ego_history(
    now: &EgoState,
    step: usize,
    dt: f64,
    sim: &dyn Fn(usize) -> EgoState,
    past: &[EgoLogState],
    count: usize,
) -> Vec<HistoryEntry> {
    let per_slot = (HISTORY_DT_S / dt).round().max(1.0) as i64;
    let oldest = match past.first() {
        Some(p) => log_state(p),
        None => sim_state(&sim(0)),
    };
    (1..=count as i64)
        .map(|k| {
            let j = step as i64 - k * per_slot;
            let (state, from) = if j >= 0 {
                (sim_state(&sim(j as usize)), HistorySource::Sim)
            } else {
                // past[len - 1] is step -1
                let i = past.len() as i64 + j;
                if i >= 0 {
                    (log_state(&past[i as usize]), HistorySource::Log)
                } else {
                    (oldest, HistorySource::Pad)
                }
            };
            let (pose, vx, vy, ax, ay) = state;
            let local = now.rear_axle.relative(&pose);
            let (s, c) = local.heading.sin_cos();
            let rot = |x: f64, y: f64| (c * x - s * y, s * x + c * y);
            let ((vx, vy), (ax, ay)) = (rot(vx, vy), rot(ax, ay));
            HistoryEntry {
                time_s: -(k as f64) * per_slot as f64 * dt,
                x: local.x,
                y: local.y,
                heading: wrap_angle(local.heading),
                vx,
                vy,
                ax,
                ay,
                from,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec2;

    fn state(x: f64, v: f64, t: f64) -> EgoState {
        EgoState {
            time_s: t,
            rear_axle: Pose2::new(x, 0.0, 0.0),
            vx: v,
            vy: 0.0,
            ax: 0.0,
            ay: 0.0,
            steering: 0.0,
            steering_rate: 0.0,
            yaw_rate: 0.0,
            yaw_accel: 0.0,
        }
    }

    #[test]
    fn slots_come_from_sim_then_log_then_pad() {
        // 10 m/s along +x; two logged steps before the start (x = -1, -2), the run at step 6 (x = 6)
        let past: Vec<EgoLogState> = [-2.0, -1.0]
            .iter()
            .map(|&x| EgoLogState {
                rear_axle: Pose2::new(x, 0.0, 0.0),
                velocity: DVec2::new(10.0, 0.0),
                accel: 0.0,
            })
            .collect();
        let sim = |j: usize| state(j as f64, 10.0, j as f64 * 0.1);
        let h = ego_history(&sim(6), 6, 0.1, &sim, &past, 3);
        // slot 1: step 1 (sim); slot 2: step -4 (not logged: pad with the oldest, x = -2); slot 3 likewise
        assert_eq!(h[0].from, HistorySource::Sim);
        assert!((h[0].x - (1.0 - 6.0)).abs() < 1e-12);
        assert_eq!(h[1].from, HistorySource::Pad);
        assert!((h[1].x - (-2.0 - 6.0)).abs() < 1e-12);
        assert!((h[2].time_s + 1.5).abs() < 1e-12);
        // at step 5 with 10 past steps at 0.1 s: slot 1 = step 0 (sim), slot 2 = step -5 (log)
        let past10: Vec<EgoLogState> = (1..=10)
            .rev()
            .map(|i| EgoLogState {
                rear_axle: Pose2::new(-(i as f64), 0.0, 0.0),
                velocity: DVec2::new(10.0, 0.0),
                accel: 0.0,
            })
            .collect();
        let h = ego_history(&sim(5), 5, 0.1, &sim, &past10, 3);
        let from: Vec<_> = h.iter().map(|e| e.from).collect();
        assert_eq!(
            from,
            [HistorySource::Sim, HistorySource::Log, HistorySource::Log]
        );
        assert!((h[1].x - (-5.0 - 5.0)).abs() < 1e-12, "{:?}", h[1]);
        assert!((h[2].x - (-10.0 - 5.0)).abs() < 1e-12, "{:?}", h[2]);
    }

    #[test]
    fn a_turned_straight_drive_is_behind_the_ego_on_its_x_axis() {
        // 8 m/s along heading 0.7 rad from (100, -50), sampled every 0.1 s: in the current frame slot k is at
        // x = -v 0.5 k, y = 0, heading 0, with vx = v, vy = 0 (the velocity rotated into the current frame)
        let (v, h0) = (8.0, 0.7);
        let at = |j: usize| {
            let t = j as f64 * 0.1;
            let p = Pose2::new(100.0, -50.0, h0).forward(v * t);
            EgoState {
                rear_axle: p,
                ..state(0.0, v, t)
            }
        };
        let h = ego_history(&at(20), 20, 0.1, &at, &[], 4);
        for (i, e) in h.iter().enumerate() {
            let k = (i + 1) as f64;
            assert_eq!(e.from, HistorySource::Sim);
            assert!((e.x + v * 0.5 * k).abs() < 1e-9, "{e:?}");
            assert!(e.y.abs() < 1e-9 && e.heading.abs() < 1e-12, "{e:?}");
            assert!((e.vx - v).abs() < 1e-12 && e.vy.abs() < 1e-12, "{e:?}");
        }
        // a past state turned by +0.3 rad relative to now, moving along its own x: its velocity appears
        // rotated by +0.3 in the current frame
        let now = state(0.0, v, 1.0);
        let past = |_: usize| EgoState {
            rear_axle: Pose2::new(-4.0, 0.0, 0.3),
            ..state(-4.0, v, 0.5)
        };
        let h = ego_history(&now, 10, 0.1, &past, &[], 1);
        assert!((h[0].heading - 0.3).abs() < 1e-12);
        assert!(
            (h[0].vx - v * 0.3f64.cos()).abs() < 1e-12
                && (h[0].vy - v * 0.3f64.sin()).abs() < 1e-12
        );
    }
}
