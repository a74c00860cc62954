//! Hand-computed cases pinning the controller and IDM formulas (behaviour spec sections 1 and 2). Golden
//! numbers come from the spec's formulas evaluated by hand (python, plain floats), not from this code.
use b2dr::scene::geometry::Pose2;
use b2dr::scene::VehicleParameters;
use b2dr::sim::ego::{BicycleModel, EgoState};
use b2dr::sim::idm::{idm_accel, idm_step, IdmParams, IdmPath, Lead};
use b2dr::sim::lqr::{
    fit_curvature, fit_velocity, integrate_profile, interp, LqrParams, LqrTracker,
};
use b2dr::sim::trajectory::Trajectory;

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

#[test]
fn idm_acceleration_hand_case() {
    // v = 5, v0 = 10, x_lead = 20, v_lead = 3, l_r = 0: s* = 1 + 7.5 + 5*2/(2 sqrt 2) = 12.0355,
    // vdot = 1 - 0.5^4 - (12.0355/20)^2.
    let p = IdmParams::default();
    let a = idm_accel(
        &p,
        10.0,
        5.0,
        &Lead {
            progress: 20.0,
            velocity: 3.0,
            length_rear: 0.0,
        },
    );
    assert!(close(a, 0.5753648089978587, 1e-12), "{a}");
    // s_alpha is clamped to s0 = 1 (x_lead - l_r = 0.5 < 1).
    let a2 = idm_accel(
        &p,
        10.0,
        0.0,
        &Lead {
            progress: 2.0,
            velocity: 0.0,
            length_rear: 1.5,
        },
    );
    assert!(close(a2, 1.0 - 0.0 - 1.0, 1e-12), "{a2}");
}

#[test]
fn idm_step_clips_and_floors() {
    let p = IdmParams::default();
    // Hard braking is clipped to -2: v 1 -> 0.8; progress uses the OLD speed.
    let (dp, v) = idm_step(
        &p,
        10.0,
        1.0,
        &Lead {
            progress: 0.0,
            velocity: 0.0,
            length_rear: 0.0,
        },
        0.1,
    );
    assert!(close(dp, 0.1, 1e-15) && close(v, 0.8, 1e-12), "{dp} {v}");
    // Free road far away: accel close to a_max (clipped at +1): 0 -> 0.1.
    let (_, v) = idm_step(
        &p,
        10.0,
        0.0,
        &Lead {
            progress: 1e6,
            velocity: 0.0,
            length_rear: 0.0,
        },
        0.1,
    );
    assert!(close(v, 0.1, 1e-9), "{v}");
    // Speed never goes negative: v 0.1, s* = 1 + 0.15 + 0.1 * 50.1 / (2 sqrt 2) = 2.92 -> vdot = -7.5,
    // clipped to -2: 0.1 - 0.2 < 0 -> 0.
    let (_, v) = idm_step(
        &p,
        10.0,
        0.1,
        &Lead {
            progress: 0.0,
            velocity: -50.0,
            length_rear: 0.0,
        },
        0.1,
    );
    assert_eq!(v, 0.0);
}

#[test]
fn lqr_longitudinal_gain_is_10_over_11() {
    let t = LqrTracker::new(LqrParams::nuplan(3.089));
    assert!(close(t.longitudinal(5.0, 7.0), 10.0 / 11.0 * 2.0, 1e-12));
    assert!(close(t.longitudinal(7.0, 5.0), -10.0 / 11.0 * 2.0, 1e-12));
}

#[test]
fn lqr_lateral_hand_case() {
    // x0 = [0.5, -0.05, 0.03], v_k = 5 + 0.05 k, kappa = 0.02: composed 10-step system, one-step LQR.
    let t = LqrTracker::new(LqrParams::nuplan(3.089));
    let vel: Vec<f64> = (0..10).map(|k| 5.0 + k as f64 * 0.5 * 0.1).collect();
    let u = t.lateral([0.5, -0.05, 0.03], &vel, &[0.02; 10]);
    assert!(close(u, 0.08324490107317557, 1e-12), "{u}");
    // Symmetry: mirrored errors and curvature give the mirrored command.
    let u2 = t.lateral([-0.5, 0.05, -0.03], &vel, &[-0.02; 10]);
    assert!(close(u2, -u, 1e-12));
}

#[test]
fn lqr_stopping_controller() {
    // Reference standing still and ego at 0.1 m/s: accel = -0.5 (0.1 - v_ref), steering rate 0.
    let poses: Vec<Pose2> = (0..=8)
        .map(|k| Pose2::new(1e-4 * k as f64, 0.0, 0.0))
        .collect();
    let traj = Trajectory::new((0..=8).map(|k| k * 500_000).collect(), poses).unwrap();
    let mut s = EgoState::from_log(
        &[b2dr::scene::EgoLogState {
            rear_axle: Pose2::default(),
            velocity: glam::DVec2::new(0.1, 0.0),
            accel: 0.0,
        }],
        0,
        0.1,
    );
    s.vx = 0.1;
    let t = LqrTracker::new(LqrParams::nuplan(3.089));
    let c = t.track(0.0, &s, &traj);
    assert!(c.stopping);
    assert!(close(c.accel, -0.5 * (0.1 - c.reference_velocity), 1e-12));
    assert_eq!(c.steering_rate, 0.0);
}

#[test]
fn profile_fits_recover_constant_speed_and_circle() {
    // Straight line at 8 m/s: v0 = 8, accelerations 0.
    let dt = 0.1;
    let xy: Vec<[f64; 2]> = (0..20).map(|_| [0.8, 0.0]).collect();
    let (v0, a) = fit_velocity(&xy, &[0.0; 20], dt, 1e-4);
    assert!(close(v0, 8.0, 1e-9), "{v0}");
    assert!(a.iter().all(|x| x.abs() < 1e-6));
    // Circle of radius 20 at 5 m/s: heading increments v dt / R, curvature 1/R.
    let v = vec![5.0; 20];
    let dpsi = vec![5.0 * dt / 20.0; 20];
    let (k0, kd) = fit_curvature(&dpsi, &v, dt, 1e-2);
    let k = integrate_profile(k0, &kd, dt);
    assert!(k.iter().all(|x| close(*x, 0.05, 1e-6)), "{k:?}");
    assert_eq!(interp(-1.0, &[0.0, 1.0], &[3.0, 5.0]), 3.0);
    assert_eq!(interp(0.25, &[0.0, 1.0], &[3.0, 5.0]), 3.5);
    assert_eq!(interp(9.0, &[0.0, 1.0], &[3.0, 5.0]), 5.0);
}

#[test]
fn bicycle_step_with_filters() {
    // v 5, a 0, delta 0.1, yaw rate 0.2; command a 1, deltadot 0.2, dt 0.1.
    let m = BicycleModel::new(&VehicleParameters::PACIFICA);
    let s = EgoState {
        time_s: 0.0,
        rear_axle: Pose2::new(0.0, 0.0, 0.0),
        vx: 5.0,
        vy: 0.0,
        ax: 0.0,
        ay: 0.0,
        steering: 0.1,
        steering_rate: 0.0,
        yaw_rate: 0.2,
        yaw_accel: 0.0,
    };
    let n = m.propagate(&s, 1.0, 0.2, 0.1);
    assert!(close(n.ax, 0.3333333333333333, 1e-12));
    assert!(close(n.rear_axle.x, 0.5, 1e-12) && n.rear_axle.y == 0.0);
    assert!(
        close(n.rear_axle.heading, 0.01624063970305124, 1e-12),
        "{}",
        n.rear_axle.heading
    );
    assert!(close(n.vx, 5.033333333333333, 1e-12));
    assert!(close(n.steering, 0.11333333333333334, 1e-12));
    assert!(close(n.steering_rate, 0.13333333333333336, 1e-12));
    assert!(close(n.yaw_rate, 0.18546435920564983, 1e-12));
    assert!(close(n.yaw_accel, -0.14535640794350185, 1e-12));
    // Steering is clipped at pi/3.
    let s2 = EgoState {
        steering: 1.04,
        ..s
    };
    assert!(m.propagate(&s2, 0.0, 10.0, 0.1).steering <= std::f64::consts::PI / 3.0);
}

#[test]
fn interpolated_path_drops_last_state_quirk() {
    // nuPlan's create_path_from_se2 zips states with an (n-1)-long mask: the last state is dropped.
    let states: Vec<Pose2> = (0..5).map(|k| Pose2::new(k as f64, 0.0, 0.0)).collect();
    let p = IdmPath::from_states(&states).unwrap();
    assert_eq!(p.pts.len(), 4);
    assert_eq!(p.end(), 3.0);
    // Repeated states are removed (the first of a repeated pair).
    let mut st = states.clone();
    st.insert(2, st[2]);
    assert_eq!(IdmPath::from_states(&st).unwrap().pts.len(), 4);
    // trim_up_to at the very end returns the last two sampled states.
    let mut out = vec![];
    p.trim_up_to(3.0, &mut out);
    assert_eq!(out.len(), 2);
    assert_eq!((out[0].x, out[1].x), (2.0, 3.0));
    p.trim_up_to(1.5, &mut out);
    assert_eq!(
        out.iter().map(|q| q.x).collect::<Vec<_>>(),
        vec![1.5, 2.0, 3.0]
    );
}

/// The O(M^2) normal equations of `fit_velocity` / `fit_curvature` against a plain dense construction of
/// A'A + lambda R'R and A'y (the tracker_utils formulation), solved by Gaussian elimination.
#[test]
fn profile_fits_match_dense_reference() {
    use b2dr::sim::lqr::solve;
    let dt = 0.1;
    let m = 40;
    // Deterministic pseudo-random data.
    let mut seed = 12345u64;
    let mut rnd = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
    };
    let headings: Vec<f64> = (0..m)
        .map(|k| 0.3 + 0.02 * k as f64 + 0.01 * rnd())
        .collect();
    let xy: Vec<[f64; 2]> = (0..m)
        .map(|k| {
            [
                0.8 * headings[k].cos() + 0.05 * rnd(),
                0.8 * headings[k].sin() + 0.05 * rnd(),
            ]
        })
        .collect();
    // Dense velocity fit.
    let mut a = vec![vec![0.0; m]; 2 * m];
    let mut y = vec![0.0; 2 * m];
    for k in 0..m {
        for c in 0..2 {
            let dir = if c == 0 {
                headings[k].cos()
            } else {
                headings[k].sin()
            };
            a[2 * k + c][0] = dir * dt;
            for v in a[2 * k + c].iter_mut().take(k + 1).skip(1) {
                *v = dir * dt * dt;
            }
            y[2 * k + c] = xy[k][c];
        }
    }
    let mut ata = vec![0.0; m * m];
    let mut aty = vec![0.0; m];
    for i in 0..m {
        for j in 0..m {
            ata[i * m + j] = (0..2 * m).map(|r| a[r][i] * a[r][j]).sum();
        }
        aty[i] = (0..2 * m).map(|r| a[r][i] * y[r]).sum();
    }
    for r in 0..m - 2 {
        let (i, j) = (1 + r, 2 + r);
        ata[i * m + i] += 1e-4;
        ata[j * m + j] += 1e-4;
        ata[i * m + j] -= 1e-4;
        ata[j * m + i] -= 1e-4;
    }
    let x = solve(ata, aty);
    let (v0, acc) = fit_velocity(&xy, &headings, dt, 1e-4);
    assert!((v0 - x[0]).abs() < 1e-9, "{v0} vs {}", x[0]);
    for (p, q) in acc.iter().zip(&x[1..]) {
        assert!((p - q).abs() < 1e-6 * (1.0 + q.abs()), "{p} vs {q}");
    }
    // Dense curvature fit.
    let vel = integrate_profile(v0, &acc, dt);
    let dpsi: Vec<f64> = (0..m)
        .map(|k| 0.01 + 0.002 * rnd() + 0.0001 * k as f64)
        .collect();
    let mut ata = vec![0.0; m * m];
    let mut aty = vec![0.0; m];
    let row = |k: usize, j: usize| {
        if j == 0 {
            vel[k] * dt
        } else if j <= k {
            vel[k] * dt * dt
        } else {
            0.0
        }
    };
    for i in 0..m {
        for j in 0..m {
            ata[i * m + j] = (0..m).map(|k| row(k, i) * row(k, j)).sum();
        }
        aty[i] = (0..m).map(|k| row(k, i) * dpsi[k]).sum();
        ata[i * m + i] += if i == 0 { 1e-10 } else { 1e-2 };
    }
    let x = solve(ata, aty);
    let (k0, kd) = fit_curvature(&dpsi, &vel, dt, 1e-2);
    assert!(
        (k0 - x[0]).abs() < 1e-9 * (1.0 + x[0].abs()),
        "{k0} vs {}",
        x[0]
    );
    for (p, q) in kd.iter().zip(&x[1..]) {
        assert!((p - q).abs() < 1e-7 * (1.0 + q.abs()), "{p} vs {q}");
    }
}

/// nuPlan test_kinematic_motion_model: without time constants the commands pass unfiltered; with them the
/// applied commands are smaller; steering saturates exactly at pi/3.
#[test]
fn bicycle_filters_and_steering_limit_like_nuplan_tests() {
    let s = EgoState {
        time_s: 0.0,
        rear_axle: Pose2::new(0.0, 0.0, 0.0),
        vx: 0.0,
        vy: 0.0,
        ax: 0.0,
        ay: 0.0,
        steering: std::f64::consts::PI / 3.0 - 1e-4,
        steering_rate: 0.0,
        yaw_rate: 0.0,
        yaw_accel: 0.0,
    };
    let base = BicycleModel::new(&VehicleParameters::PACIFICA);
    let no_delay = BicycleModel {
        accel_time_constant: 0.0,
        steering_time_constant: 0.0,
        ..base
    };
    let n = no_delay.propagate(&s, 1.0, 0.5, 1.0);
    assert!((n.ax - 1.0).abs() < 1e-10 && (n.steering_rate - 0.5).abs() < 1e-10);
    let f = base.propagate(&s, 1.0, 0.5, 1.0);
    assert!(f.ax < 1.0 && f.steering_rate < 0.5);
    let sat = base.propagate(&s, 0.0, 10.0, 1.0);
    assert_eq!(sat.steering, std::f64::consts::PI / 3.0);
}
