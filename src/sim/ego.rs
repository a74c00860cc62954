//! Ego state and nuPlan's kinematic bicycle motion model
//! [simulation/controller/motion_model/kinematic_bicycle.py]: first-order lag on acceleration (0.2 s) and
//! steering angle (0.05 s), forward Euler with the OLD speed and OLD steering angle, steering clipped to
//! +-pi/3, lateral velocity forced to 0.
use crate::scene::geometry::{wrap_angle, Pose2};
use crate::scene::{EgoLogState, VehicleParameters};

/// Ego state at one step (rear-axle reference, like nuPlan's EgoState).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct EgoState {
    pub time_s: f64,
    pub rear_axle: Pose2,
    /// Rear-axle velocity in the ego frame (x forward, y left).
    pub vx: f64,
    pub vy: f64,
    /// Rear-axle acceleration in the ego frame.
    pub ax: f64,
    pub ay: f64,
    pub steering: f64,
    pub steering_rate: f64,
    pub yaw_rate: f64,
    pub yaw_accel: f64,
}

impl EgoState {
    /// The logged state at step k of `log` (steering 0 like nuPlan's log-built ego states; yaw rate from
    /// heading differences).
    pub fn from_log(log: &[EgoLogState], k: usize, dt: f64) -> EgoState {
        let e = log[k];
        let (s, c) = e.rear_axle.heading.sin_cos();
        let vx = c * e.velocity.x + s * e.velocity.y;
        let vy = -s * e.velocity.x + c * e.velocity.y;
        let yaw_rate = if k + 1 < log.len() {
            wrap_angle(log[k + 1].rear_axle.heading - e.rear_axle.heading) / dt
        } else if k > 0 {
            wrap_angle(e.rear_axle.heading - log[k - 1].rear_axle.heading) / dt
        } else {
            0.0
        };
        EgoState {
            time_s: k as f64 * dt,
            rear_axle: e.rear_axle,
            vx: if vx.is_finite() { vx } else { 0.0 },
            vy: if vy.is_finite() { vy } else { 0.0 },
            ax: e.accel,
            ay: 0.0,
            steering: 0.0,
            steering_rate: 0.0,
            yaw_rate,
            yaw_accel: 0.0,
        }
    }
    pub fn speed(&self) -> f64 {
        self.vx.hypot(self.vy)
    }
}

/// Kinematic bicycle parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BicycleModel {
    pub wheel_base: f64,
    pub max_steering: f64,
    pub accel_time_constant: f64,
    pub steering_time_constant: f64,
}

impl BicycleModel {
    pub fn new(v: &VehicleParameters) -> Self {
        Self {
            wheel_base: v.wheel_base,
            max_steering: std::f64::consts::PI / 3.0,
            accel_time_constant: 0.2,
            steering_time_constant: 0.05,
        }
    }

    /// One step of `dt` seconds under the commanded acceleration and steering rate.
    pub fn propagate(
        &self,
        s: &EgoState,
        accel_cmd: f64,
        steering_rate_cmd: f64,
        dt: f64,
    ) -> EgoState {
        // _update_commands: low-pass filters.
        let a_f = dt / (dt + self.accel_time_constant) * (accel_cmd - s.ax) + s.ax;
        let delta_ideal = dt * steering_rate_cmd + s.steering;
        let delta_f =
            dt / (dt + self.steering_time_constant) * (delta_ideal - s.steering) + s.steering;
        let deltadot_f = (delta_f - s.steering) / dt;
        // get_state_dot + forward_integrate with the old speed and the old steering angle.
        let v = s.vx;
        let psi = s.rear_axle.heading;
        let x = s.rear_axle.x + v * psi.cos() * dt;
        let y = s.rear_axle.y + v * psi.sin() * dt;
        let heading = wrap_angle(psi + v * s.steering.tan() / self.wheel_base * dt);
        let vx = v + a_f * dt;
        let steering = (s.steering + deltadot_f * dt).clamp(-self.max_steering, self.max_steering);
        let yaw_rate = vx * steering.tan() / self.wheel_base;
        EgoState {
            time_s: s.time_s + dt,
            rear_axle: Pose2::new(x, y, heading),
            vx,
            vy: 0.0,
            ax: a_f,
            ay: 0.0,
            steering,
            steering_rate: deltadot_f,
            yaw_rate,
            yaw_accel: (yaw_rate - s.yaw_rate) / dt,
        }
    }
}
