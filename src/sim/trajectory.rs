//! Timed rear-axle pose trajectories (what a planner returns, in the global frame) with nuPlan's
//! `InterpolatedTrajectory` semantics: linear in x, y and in the unwrapped heading; times in microseconds.
use crate::scene::geometry::{wrap_angle, Pose2};

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Trajectory {
    /// Strictly increasing times (microseconds).
    pub times_us: Vec<i64>,
    /// Rear-axle poses, headings unwrapped along the trajectory.
    pub poses: Vec<Pose2>,
}

impl Trajectory {
    /// Builds a trajectory; headings are unwrapped so interpolation never takes the long way round.
    pub fn new(times_us: Vec<i64>, mut poses: Vec<Pose2>) -> anyhow::Result<Self> {
        anyhow::ensure!(
            times_us.len() == poses.len(),
            "trajectory: {} times but {} poses",
            times_us.len(),
            poses.len()
        );
        anyhow::ensure!(
            poses.len() >= 2,
            "trajectory needs at least 2 poses, got {}",
            poses.len()
        );
        for w in times_us.windows(2) {
            anyhow::ensure!(w[1] > w[0], "trajectory times must increase strictly");
        }
        for p in &poses {
            anyhow::ensure!(
                p.x.is_finite() && p.y.is_finite() && p.heading.is_finite(),
                "trajectory contains a non-finite pose"
            );
        }
        for i in 1..poses.len() {
            let prev = poses[i - 1].heading;
            poses[i].heading = prev + wrap_angle(poses[i].heading - prev);
        }
        Ok(Self { times_us, poses })
    }
    pub fn start_us(&self) -> i64 {
        self.times_us[0]
    }
    pub fn end_us(&self) -> i64 {
        *self.times_us.last().unwrap_or(&0)
    }
    /// Pose at time t (clamped to the trajectory's span); heading wrapped to [-pi, pi).
    pub fn pose_at_us(&self, t: i64) -> Pose2 {
        let n = self.times_us.len();
        if t <= self.times_us[0] {
            let p = self.poses[0];
            return Pose2::new(p.x, p.y, wrap_angle(p.heading));
        }
        if t >= self.times_us[n - 1] {
            let p = self.poses[n - 1];
            return Pose2::new(p.x, p.y, wrap_angle(p.heading));
        }
        let i = self.times_us.partition_point(|&x| x <= t) - 1;
        let (t0, t1) = (self.times_us[i] as f64, self.times_us[i + 1] as f64);
        let a = (t as f64 - t0) / (t1 - t0);
        let (p, q) = (self.poses[i], self.poses[i + 1]);
        Pose2::new(
            p.x + a * (q.x - p.x),
            p.y + a * (q.y - p.y),
            wrap_angle(p.heading + a * (q.heading - p.heading)),
        )
    }
}
