//! nuPlan's LQR trajectory tracker [simulation/controller/tracker/lqr.py, tracker_utils.py]: a one-step
//! longitudinal LQR on speed and a one-step lateral LQR on (lateral error, heading error, steering angle)
//! over a 10-step horizon, fed by speed and curvature profiles fitted to the reference poses by regularised
//! least squares.
use super::ego::EgoState;
use super::trajectory::Trajectory;
use crate::scene::geometry::{angle_diff, wrap_angle, Pose2};

/// Tracker parameters (nuPlan's defaults, config/simulation/ego_controller/tracker/lqr_tracker.yaml).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LqrParams {
    pub q_longitudinal: f64,
    pub r_longitudinal: f64,
    pub q_lateral: [f64; 3],
    pub r_lateral: f64,
    pub dt: f64,
    pub horizon: usize,
    pub jerk_penalty: f64,
    pub curvature_rate_penalty: f64,
    pub stopping_gain: f64,
    pub stopping_velocity: f64,
    pub wheel_base: f64,
}

impl LqrParams {
    pub fn nuplan(wheel_base: f64) -> Self {
        Self {
            q_longitudinal: 10.0,
            r_longitudinal: 1.0,
            q_lateral: [1.0, 10.0, 0.0],
            r_lateral: 1.0,
            dt: 0.1,
            horizon: 10,
            jerk_penalty: 1e-4,
            curvature_rate_penalty: 1e-2,
            stopping_gain: 0.5,
            stopping_velocity: 0.2,
            wheel_base,
        }
    }
}

/// Initial curvature regulariser (tracker_utils.INITIAL_CURVATURE_PENALTY).
const INITIAL_CURVATURE_PENALTY: f64 = 1e-10;

/// Solves the symmetric system M x = b (Gaussian elimination with partial pivoting). `np.linalg.pinv`
/// equals the inverse for the non-singular systems the fits produce (both regularisers make them definite).
pub fn solve(mut m: Vec<f64>, mut b: Vec<f64>) -> Vec<f64> {
    let n = b.len();
    for col in 0..n {
        let piv = (col..n)
            .max_by(|&i, &j| m[i * n + col].abs().total_cmp(&m[j * n + col].abs()))
            .unwrap_or(col);
        if piv != col {
            for k in 0..n {
                m.swap(col * n + k, piv * n + k);
            }
            b.swap(col, piv);
        }
        let d = m[col * n + col];
        if d.abs() < 1e-300 {
            continue;
        }
        for r in col + 1..n {
            let f = m[r * n + col] / d;
            if f != 0.0 {
                for k in col..n {
                    m[r * n + k] -= f * m[col * n + k];
                }
                b[r] -= f * b[col];
            }
        }
    }
    let mut x = vec![0.0; n];
    for r in (0..n).rev() {
        let mut s = b[r];
        for k in r + 1..n {
            s -= m[r * n + k] * x[k];
        }
        let d = m[r * n + r];
        x[r] = if d.abs() < 1e-300 { 0.0 } else { s / d };
    }
    x
}

/// Solves M x = b for a symmetric positive definite M by Cholesky; falls back to [`solve`] when a pivot is
/// not positive.
pub fn solve_spd(m: &[f64], b: &[f64]) -> Vec<f64> {
    let n = b.len();
    let mut l = vec![0.0; n * n];
    for j in 0..n {
        let mut d = m[j * n + j];
        for k in 0..j {
            d -= l[j * n + k] * l[j * n + k];
        }
        // Not positive (or NaN): not SPD, use the general solver.
        if d.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return solve(m.to_vec(), b.to_vec());
        }
        let d = d.sqrt();
        l[j * n + j] = d;
        for i in j + 1..n {
            let mut s = m[i * n + j];
            for k in 0..j {
                s -= l[i * n + k] * l[j * n + k];
            }
            l[i * n + j] = s / d;
        }
    }
    let mut y = vec![0.0; n];
    for i in 0..n {
        let mut s = b[i];
        for k in 0..i {
            s -= l[i * n + k] * y[k];
        }
        y[i] = s / l[i * n + i];
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        let mut s = y[i];
        for k in i + 1..n {
            s -= l[k * n + i] * x[k];
        }
        x[i] = s / l[i * n + i];
    }
    x
}

/// Normal equations of the lower-triangular design both fits share: row k = w_k [c0, c1, c1, ..., c1 (k
/// times), 0, ...] (one row per displacement). Then (A'A)[i][j] = c c' sum_{k >= max(i, j)} w_k^2 and
/// (A'y)[j] = c sum_{k >= j} w_k y_k, built in O(M^2) from suffix sums instead of forming A.
fn normal_equations(w2: &[f64], wy: &[f64], c0: f64, c1: f64) -> (Vec<f64>, Vec<f64>) {
    let m = w2.len();
    let mut suf_w2 = vec![0.0; m + 1];
    let mut suf_wy = vec![0.0; m + 1];
    for k in (0..m).rev() {
        suf_w2[k] = suf_w2[k + 1] + w2[k];
        suf_wy[k] = suf_wy[k + 1] + wy[k];
    }
    let mut ata = vec![0.0; m * m];
    let mut aty = vec![0.0; m];
    for i in 0..m {
        let ci = if i == 0 { c0 } else { c1 };
        aty[i] = ci * suf_wy[i];
        for j in 0..m {
            let cj = if j == 0 { c0 } else { c1 };
            ata[i * m + j] = ci * cj * suf_w2[i.max(j)];
        }
    }
    (ata, aty)
}

/// Fits (v0, a_0..a_{M-2}) to M displacements: displacement_k = [cos psi_k, sin psi_k](v0 dt + dt^2
/// sum_{j<k} a_j), jerk penalty on first differences of a (`_fit_initial_velocity_and_acceleration_profile`).
/// The x and y rows of a step share the unit heading vector, so their weights add to 1 and the data enter
/// through the displacement projected on the heading.
pub fn fit_velocity(
    xy: &[[f64; 2]],
    headings: &[f64],
    dt: f64,
    jerk_penalty: f64,
) -> (f64, Vec<f64>) {
    let m = xy.len();
    let w2 = vec![1.0; m];
    let proj: Vec<f64> = (0..m)
        .map(|k| headings[k].cos() * xy[k][0] + headings[k].sin() * xy[k][1])
        .collect();
    let (mut ata, aty) = normal_equations(&w2, &proj, dt, dt * dt);
    // R = [0 | D] with D the (M-2) x (M-1) banded difference matrix: R'R adds the second-difference
    // stencil on the acceleration block.
    if m >= 3 {
        for r in 0..m - 2 {
            let (i, j) = (1 + r, 2 + r);
            ata[i * m + i] += jerk_penalty;
            ata[j * m + j] += jerk_penalty;
            ata[i * m + j] -= jerk_penalty;
            ata[j * m + i] -= jerk_penalty;
        }
    }
    let x = solve_spd(&ata, &aty);
    (x[0], x[1..].to_vec())
}

/// Fits (kappa0, kappadot_0..) to M heading displacements: dpsi_k = v_k dt kappa0 + v_k dt^2 sum_{j<k}
/// kappadot_j; penalties curvature_rate_penalty on kappadot and 1e-10 on kappa0
/// (`_fit_initial_curvature_and_curvature_rate_profile`).
pub fn fit_curvature(dpsi: &[f64], v: &[f64], dt: f64, penalty: f64) -> (f64, Vec<f64>) {
    let m = dpsi.len();
    let w2: Vec<f64> = v.iter().take(m).map(|x| x * x).collect();
    let wy: Vec<f64> = (0..m).map(|k| v[k] * dpsi[k]).collect();
    let (mut ata, aty) = normal_equations(&w2, &wy, dt, dt * dt);
    for i in 0..m {
        ata[i * m + i] += if i == 0 {
            INITIAL_CURVATURE_PENALTY
        } else {
            penalty
        };
    }
    let x = solve_spd(&ata, &aty);
    (x[0], x[1..].to_vec())
}

/// Profile from an initial value and derivatives: [x0, x0 + d0 dt, x0 + (d0 + d1) dt, ...].
pub fn integrate_profile(x0: f64, d: &[f64], dt: f64) -> Vec<f64> {
    let mut out = Vec::with_capacity(d.len() + 1);
    let mut acc = 0.0;
    out.push(x0);
    for v in d {
        acc += v * dt;
        out.push(x0 + acc);
    }
    out
}

/// np.interp: linear interpolation clamped to the end values.
pub fn interp(x: f64, xs: &[f64], ys: &[f64]) -> f64 {
    let n = xs.len();
    if n == 0 {
        return 0.0;
    }
    if x <= xs[0] {
        return ys[0];
    }
    if x >= xs[n - 1] {
        return ys[n - 1];
    }
    let i = xs.partition_point(|&v| v <= x) - 1;
    let a = (x - xs[i]) / (xs[i + 1] - xs[i]);
    ys[i] + a * (ys[i + 1] - ys[i])
}

/// `get_interpolated_reference_trajectory_poses`: times (s) and poses every dt from the trajectory's start
/// to its end, plus the end itself when it falls on the grid.
pub fn resample(traj: &Trajectory, dt: f64) -> (Vec<f64>, Vec<Pose2>) {
    let step = (dt * 1e6) as i64;
    let (t0, t1) = (traj.start_us(), traj.end_us());
    let mut times = Vec::new();
    let mut t = t0;
    while t < t1 {
        times.push(t);
        t += step;
    }
    if let Some(&last) = times.last() {
        if last + step <= t1 {
            times.push(last + step);
        }
    }
    let poses = times.iter().map(|&t| traj.pose_at_us(t)).collect();
    (times.iter().map(|&t| t as f64 / 1e6).collect(), poses)
}

/// Longest span of a trajectory the tracker fits its profiles to (s); the tracker looks 1 s ahead.
pub const MAX_FIT_S: f64 = 10.0;

/// Output of one tracker call (for traces and tests).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct TrackerCommand {
    pub accel: f64,
    pub steering_rate: f64,
    pub reference_velocity: f64,
    pub stopping: bool,
}

#[derive(Clone, Debug)]
pub struct LqrTracker {
    pub p: LqrParams,
}

impl LqrTracker {
    pub fn new(p: LqrParams) -> Self {
        Self { p }
    }

    /// Reference speed at t + N dt and curvatures at t + k dt, k < N. The profiles are fitted to the first
    /// [`MAX_FIT_S`] seconds of the trajectory (all of nuPlan's 8 s ones): the fit is a dense solve, cubic in
    /// the samples, and a 1000-pose (500 s) reply made every 10 Hz step take minutes.
    pub fn reference_profiles(&self, t_now: f64, traj: &Trajectory) -> (f64, Vec<f64>) {
        let p = &self.p;
        let (mut times, mut poses) = resample(traj, p.dt);
        let t_end = times.first().copied().unwrap_or(0.0) + MAX_FIT_S + 1e-9;
        let keep = times.partition_point(|&t| t <= t_end);
        times.truncate(keep);
        poses.truncate(keep);
        if poses.len() < 3 {
            // Too short to fit (fewer than 2 displacements): hold the average speed, no curvature.
            let d = traj.poses[traj.poses.len() - 1].pos() - traj.poses[0].pos();
            let span = (traj.end_us() - traj.start_us()) as f64 / 1e6;
            return (d.length() / span.max(1e-6), vec![0.0; p.horizon]);
        }
        let m = poses.len() - 1;
        let mut xy = Vec::with_capacity(m);
        let mut dpsi = Vec::with_capacity(m);
        for k in 0..m {
            xy.push([poses[k + 1].x - poses[k].x, poses[k + 1].y - poses[k].y]);
            dpsi.push(wrap_angle(poses[k + 1].heading - poses[k].heading));
        }
        let headings: Vec<f64> = poses[..m].iter().map(|q| q.heading).collect();
        let (v0, acc) = fit_velocity(&xy, &headings, p.dt, p.jerk_penalty);
        let vel = integrate_profile(v0, &acc, p.dt);
        let (k0, kdot) = fit_curvature(&dpsi, &vel, p.dt, p.curvature_rate_penalty);
        let curv = integrate_profile(k0, &kdot, p.dt);
        let ts = &times[..m];
        let v_ref = interp(t_now + p.horizon as f64 * p.dt, ts, &vel);
        let kappa = (0..p.horizon)
            .map(|k| interp(t_now + k as f64 * p.dt, ts, &curv))
            .collect();
        (v_ref, kappa)
    }

    /// The commanded rear-axle acceleration and steering rate for ego state `s` at time `t_now`.
    pub fn track(&self, t_now: f64, s: &EgoState, traj: &Trajectory) -> TrackerCommand {
        let p = &self.p;
        let r = traj.pose_at_us((t_now * 1e6).round() as i64);
        let (dx, dy) = (s.rear_axle.x - r.x, s.rear_axle.y - r.y);
        let e_lat = -dx * r.heading.sin() + dy * r.heading.cos();
        let e_psi = angle_diff(s.rear_axle.heading, r.heading);
        let x0 = [e_lat, e_psi, s.steering];
        let v0 = s.vx;
        let (v_ref, kappa) = self.reference_profiles(t_now, traj);
        if v_ref <= p.stopping_velocity && v0 <= p.stopping_velocity {
            return TrackerCommand {
                accel: -p.stopping_gain * (v0 - v_ref),
                steering_rate: 0.0,
                reference_velocity: v_ref,
                stopping: true,
            };
        }
        let accel = self.longitudinal(v0, v_ref);
        let vel: Vec<f64> = (0..p.horizon)
            .map(|k| v0 + k as f64 * accel * p.dt)
            .collect();
        let steering_rate = self.lateral(x0, &vel, &kappa);
        TrackerCommand {
            accel,
            steering_rate,
            reference_velocity: v_ref,
            stopping: false,
        }
    }

    /// One-step LQR with A = 1, B = N dt: u = -(B Q B + R)^-1 B Q (v0 - v_ref).
    pub fn longitudinal(&self, v0: f64, v_ref: f64) -> f64 {
        let b = self.p.horizon as f64 * self.p.dt;
        let q = self.p.q_longitudinal;
        -(b * q * (v0 - v_ref)) / (b * q * b + self.p.r_longitudinal)
    }

    /// Lateral LQR over the horizon's linear time-varying dynamics.
    pub fn lateral(&self, x0: [f64; 3], vel: &[f64], kappa: &[f64]) -> f64 {
        let (dt, l) = (self.p.dt, self.p.wheel_base);
        let mut a = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let mut b = [0.0; 3];
        let mut g = [0.0; 3];
        for (&v, &k) in vel.iter().zip(kappa) {
            let mut ak = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
            ak[0][1] = v * dt;
            ak[1][2] = v * dt / l;
            let mul = |m: &[[f64; 3]; 3], x: &[f64; 3]| {
                [
                    m[0][0] * x[0] + m[0][1] * x[1] + m[0][2] * x[2],
                    m[1][0] * x[0] + m[1][1] * x[1] + m[1][2] * x[2],
                    m[2][0] * x[0] + m[2][1] * x[1] + m[2][2] * x[2],
                ]
            };
            let mut na = [[0.0; 3]; 3];
            for i in 0..3 {
                for j in 0..3 {
                    na[i][j] = (0..3).map(|q| ak[i][q] * a[q][j]).sum();
                }
            }
            a = na;
            let nb = mul(&ak, &b);
            b = [nb[0], nb[1], nb[2] + dt];
            let ng = mul(&ak, &g);
            g = [ng[0], ng[1] - v * k * dt, ng[2]];
        }
        let mut e = [0.0; 3];
        for i in 0..3 {
            e[i] = a[i][0] * x0[0] + a[i][1] * x0[1] + a[i][2] * x0[2] + g[i];
        }
        // angle_diff_indices = [heading error, steering angle].
        e[1] = wrap_angle(e[1]);
        e[2] = wrap_angle(e[2]);
        let q = self.p.q_lateral;
        let btqb: f64 = (0..3).map(|i| b[i] * q[i] * b[i]).sum();
        let btqe: f64 = (0..3).map(|i| b[i] * q[i] * e[i]).sum();
        -btqe / (btqb + self.p.r_lateral)
    }
}
