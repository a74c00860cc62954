//! no_ego_at_fault_collisions and time_to_collision_within_bound, ports of nuPlan's
//! [evaluation_metrics/common/no_ego_at_fault_collisions.py], [.../time_to_collision_within_bound.py],
//! [metrics/utils/collision_utils.py] and the angle helpers of [simulation/observation/idm/utils.py].
//!
//! Spatial pruning: an axis-aligned bounds test runs before every exact (separating-axis) box test; it never
//! changes a result, it only skips pairs that cannot touch.
use super::geometry::{boxes_intersect, segment_intersects_convex};
use super::input::{EgoDims, EgoStep, MapQuery, ObjectClass, ObjectState};
use crate::scene::geometry::{Aabb, OrientedBox, Pose2};
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;

/// nuPlan `CollisionType`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CollisionType {
    StoppedEgo,
    StoppedTrack,
    ActiveFront,
    ActiveRear,
    ActiveLateral,
}

/// One new collision (a track is counted once per scenario).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Collision {
    pub step: usize,
    pub track_id: u64,
    pub class: ObjectClass,
    pub kind: CollisionType,
    /// nuPlan `ego_delta_v_collision` (equal masses).
    pub ego_delta_v: f64,
    pub at_fault: bool,
}

/// Result of no_ego_at_fault_collisions.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CollisionResult {
    pub collisions: Vec<Collision>,
    pub at_fault_vru: usize,
    pub at_fault_vehicles: usize,
    pub at_fault_objects: usize,
    pub score: f64,
}

/// Thresholds of the collision score (nuPlan defaults: VRU 0, vehicle 0, object 1).
pub const MAX_VIOLATION_VRU: usize = 0;
pub const MAX_VIOLATION_VEHICLE: usize = 0;
pub const MAX_VIOLATION_OBJECT: usize = 1;
/// `stopped_speed_threshold` of the collision classification.
pub const COLLISION_STOPPED_SPEED: f64 = 5e-2;

/// idm/utils.py `get_agent_relative_angle` (no clipping: NaN when the centres coincide, so neither ahead nor
/// behind, like nuPlan).
pub fn relative_angle(ego: &EgoStep, p: glam::DVec2) -> f64 {
    let v = p - ego.position;
    let n = v.length();
    let (s, c) = ego.heading.sin_cos();
    (c * (v.x / n) + s * (v.y / n)).acos()
}

/// `is_agent_ahead` (30 deg).
pub fn is_ahead(ego: &EgoStep, p: glam::DVec2) -> bool {
    relative_angle(ego, p) < 30f64.to_radians()
}

/// `is_agent_behind` (150 deg).
pub fn is_behind(ego: &EgoStep, p: glam::DVec2) -> bool {
    relative_angle(ego, p) > 150f64.to_radians()
}

fn aabb_overlap(a: Aabb, b: Aabb) -> bool {
    // Slightly inflated so the exact test decides every touching case.
    let eps = 1e-9 * (1.0 + a.max.abs().max_element().max(b.max.abs().max_element()));
    a.min.x <= b.max.x + eps
        && b.min.x <= a.max.x + eps
        && a.min.y <= b.max.y + eps
        && b.min.y <= a.max.y + eps
}

/// `in_collision` with an AABB pre-test.
pub fn in_collision(a: &OrientedBox, b: &OrientedBox) -> bool {
    aabb_overlap(a.aabb(), b.aabb()) && boxes_intersect(a, b)
}

/// `_get_collision_type`.
pub fn collision_type(ego: &EgoStep, ego_box: &OrientedBox, obj: &ObjectState) -> CollisionType {
    if ego.speed() <= COLLISION_STOPPED_SPEED {
        CollisionType::StoppedEgo
    } else if !obj.is_agent || obj.velocity.length() <= COLLISION_STOPPED_SPEED {
        CollisionType::StoppedTrack
    } else if is_behind(ego, obj.center) {
        CollisionType::ActiveRear
    } else {
        let c = ego_box.corners();
        // exterior.coords[0] and [3]: front-left and front-right, the front bumper.
        if segment_intersects_convex(c[0], c[3], &obj.footprint().corners()) {
            CollisionType::ActiveFront
        } else {
            CollisionType::ActiveLateral
        }
    }
}

/// `ego_delta_v_collision` with equal masses.
fn ego_delta_v(ego: &EgoStep, obj: &ObjectState) -> f64 {
    let v_e = ego.speed();
    let v_o = obj.speed();
    let sum_sq = v_e * v_e + v_o * v_o;
    let cos_term = 2.0 * v_e * v_o * (ego.heading - obj.heading).cos();
    0.5 * (sum_sq - cos_term).sqrt()
}

/// `max(0, 1 - n / (threshold + 1))`.
pub fn collision_score(n: usize, threshold: usize) -> f64 {
    (1.0 - n as f64 / (threshold as f64 + 1.0)).max(0.0)
}

/// no_ego_at_fault_collisions. `in_common_or_connected[i]`: ego corners in a common / connected lane set.
pub fn at_fault_collisions(
    ego: &[EgoStep],
    dims: &EgoDims,
    objects: &[Vec<ObjectState>],
    in_common_or_connected: &[bool],
) -> CollisionResult {
    let mut collided: BTreeSet<u64> = BTreeSet::new();
    let mut res = CollisionResult::default();
    for (step, (e, objs)) in ego.iter().zip(objects).enumerate() {
        let ego_box = e.footprint(dims);
        for o in objs {
            if collided.contains(&o.track_id) || !in_collision(&ego_box, &o.footprint()) {
                continue;
            }
            collided.insert(o.track_id);
            let kind = collision_type(e, &ego_box, o);
            let lateral_fault = kind == CollisionType::ActiveLateral
                && !in_common_or_connected.get(step).copied().unwrap_or(false);
            let at_fault = matches!(
                kind,
                CollisionType::ActiveFront | CollisionType::StoppedTrack
            ) || lateral_fault;
            if at_fault {
                if o.class.is_vru() {
                    res.at_fault_vru += 1;
                } else if o.class == ObjectClass::Vehicle {
                    res.at_fault_vehicles += 1;
                } else {
                    res.at_fault_objects += 1;
                }
            }
            res.collisions.push(Collision {
                step,
                track_id: o.track_id,
                class: o.class,
                kind,
                ego_delta_v: ego_delta_v(e, o),
                at_fault,
            });
        }
    }
    let n = res.at_fault_vru + res.at_fault_vehicles + res.at_fault_objects;
    res.score = if n == 0 {
        1.0
    } else {
        collision_score(res.at_fault_vru, MAX_VIOLATION_VRU)
            * collision_score(res.at_fault_vehicles, MAX_VIOLATION_VEHICLE)
            * collision_score(res.at_fault_objects, MAX_VIOLATION_OBJECT)
    };
    res
}

/// TTC parameters (nuPlan config: step 0.1 s, horizon 3 s, least_min_ttc 0.95 s; ego stopped <= 5e-3 m/s).
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct TtcParams {
    pub time_step_size: f64,
    pub time_horizon: f64,
    pub least_min_ttc: f64,
    pub stopped_speed_threshold: f64,
}

impl Default for TtcParams {
    fn default() -> Self {
        TtcParams {
            time_step_size: 0.1,
            time_horizon: 3.0,
            least_min_ttc: 0.95,
            stopped_speed_threshold: 5e-3,
        }
    }
}

/// Result of time_to_collision_within_bound.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TtcResult {
    /// TTC per step (`f64::INFINITY` when none within the horizon; serialised as null).
    #[serde(with = "inf_as_null_vec")]
    pub ttc: Vec<f64>,
    #[serde(with = "inf_as_null")]
    pub min_ttc: f64,
    pub score: f64,
}

/// JSON has no infinity: serialise it as null and read null back as infinity.
mod inf_as_null {
    use serde::{Deserialize, Deserializer, Serializer};
    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() {
            s.serialize_some(v)
        } else {
            s.serialize_none()
        }
    }
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::INFINITY))
    }
}

mod inf_as_null_vec {
    use serde::{Deserialize, Deserializer, Serializer};
    pub fn serialize<S: Serializer>(v: &[f64], s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(v.iter().map(|x| x.is_finite().then_some(*x)))
    }
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
        Ok(Vec::<Option<f64>>::deserialize(d)?
            .into_iter()
            .map(|x| x.unwrap_or(f64::INFINITY))
            .collect())
    }
}

/// `_get_elongated_box_length`.
fn elongated_length(length: f64, dx: f64, dy: f64, p: &TtcParams) -> f64 {
    length + (dx * p.time_horizon / p.time_step_size).hypot(dy * p.time_horizon / p.time_step_size)
}

/// `np.arange(step, horizon, step)` values.
fn arange(start: f64, stop: f64, step: f64) -> Vec<f64> {
    let n = ((stop - start) / step).ceil();
    if !(n.is_finite() && n > 0.0) {
        return Vec::new();
    }
    (0..n as usize).map(|i| start + i as f64 * step).collect()
}

/// time_to_collision_within_bound.
#[allow(clippy::too_many_arguments)]
pub fn time_to_collision(
    map: &dyn MapQuery,
    ego: &[EgoStep],
    dims: &EgoDims,
    objects: &[Vec<ObjectState>],
    in_common_or_connected: &[bool],
    collisions: &[Collision],
    p: &TtcParams,
) -> TtcResult {
    let times = arange(p.time_step_size, p.time_horizon, p.time_step_size);
    let mut collided: BTreeSet<u64> = BTreeSet::new();
    let mut ttc = vec![f64::INFINITY; ego.len()];
    // Scratch buffers reused over steps.
    let mut poses: Vec<(glam::DVec2, f64)> = Vec::new();
    let mut dxy: Vec<glam::DVec2> = Vec::new();
    let mut boxes: Vec<OrientedBox> = Vec::new();
    for (step, (e, objs)) in ego.iter().zip(objects).enumerate() {
        collided.extend(
            collisions
                .iter()
                .filter(|c| c.step == step)
                .map(|c| c.track_id),
        );
        if collisions.iter().any(|c| c.step == step && c.at_fault) {
            ttc[step] = 0.0;
            continue;
        }
        let speed = e.speed();
        if speed <= p.stopped_speed_threshold {
            continue;
        }
        let not_in_common = !in_common_or_connected.get(step).copied().unwrap_or(false);
        let lateral_ok = not_in_common || map.in_intersection(e.position);
        poses.clear();
        dxy.clear();
        boxes.clear();
        for o in objs {
            if collided.contains(&o.track_id) {
                continue;
            }
            if !(is_ahead(e, o.center) || (lateral_ok && !is_behind(e, o.center))) {
                continue;
            }
            let s = o.speed();
            poses.push((o.center, o.heading));
            dxy.push(glam::DVec2::new(
                o.heading.cos() * s * p.time_step_size,
                o.heading.sin() * s * p.time_step_size,
            ));
            boxes.push(o.footprint());
        }
        if poses.is_empty() {
            continue;
        }
        let ego_box = e.footprint(dims);
        let mut ego_pose = ego_box.center.pos();
        let ego_d = glam::DVec2::new(
            e.heading.cos() * speed * p.time_step_size,
            e.heading.sin() * speed * p.time_step_size,
        );
        // Broad phase (_get_relevant_tracks): boxes stretched over the horizon must overlap.
        let half = p.time_horizon / p.time_step_size / 2.0;
        let ego_long = OrientedBox::at(
            glam::DVec2::new(half * ego_d.x + ego_pose.x, half * ego_d.y + ego_pose.y),
            e.heading,
            elongated_length(ego_box.length, ego_d.x, ego_d.y, p),
            ego_box.width,
        );
        let relevant: Vec<usize> = (0..poses.len())
            .filter(|&i| {
                let d = dxy[i];
                let long = OrientedBox::at(
                    glam::DVec2::new(half * d.x + poses[i].0.x, half * d.y + poses[i].0.y),
                    poses[i].1,
                    elongated_length(boxes[i].length, d.x, d.y, p),
                    boxes[i].width,
                );
                in_collision(&ego_long, &long)
            })
            .collect();
        if relevant.is_empty() {
            continue;
        }
        'outer: for &t in &times {
            ego_pose += ego_d;
            let ego_proj = OrientedBox {
                center: Pose2::new(ego_pose.x, ego_pose.y, ego_box.center.heading),
                ..ego_box
            };
            for (i, pose) in poses.iter_mut().enumerate() {
                pose.0 += dxy[i];
            }
            for &i in &relevant {
                let tb = OrientedBox {
                    center: Pose2::new(poses[i].0.x, poses[i].0.y, boxes[i].center.heading),
                    ..boxes[i]
                };
                if in_collision(&ego_proj, &tb) {
                    ttc[step] = t;
                    break 'outer;
                }
            }
        }
    }
    let min_ttc = ttc.iter().copied().fold(f64::INFINITY, f64::min);
    let within = ttc.iter().all(|&t| p.least_min_ttc < t);
    TtcResult {
        ttc,
        min_ttc,
        score: if within { 1.0 } else { 0.0 },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec2;

    fn ego_at(x: f64, y: f64, h: f64, v: f64) -> EgoStep {
        EgoStep {
            time_s: 0.0,
            position: DVec2::new(x, y),
            heading: h,
            velocity: DVec2::new(v, 0.0),
            acceleration: DVec2::ZERO,
            yaw_rate: 0.0,
            yaw_acceleration: 0.0,
        }
    }

    fn car(id: u64, x: f64, y: f64, h: f64, v: f64) -> ObjectState {
        ObjectState {
            track_id: id,
            class: ObjectClass::Vehicle,
            center: DVec2::new(x, y),
            heading: h,
            length: 4.0,
            width: 2.0,
            velocity: DVec2::new(h.cos() * v, h.sin() * v),
            is_agent: true,
        }
    }

    #[test]
    fn classification_cases() {
        let d = EgoDims::PACIFICA;
        // Ego rear axle at 0, box x in [-1.127, 4.049], y in [-1.1485, 1.1485].
        let e = ego_at(0.0, 0.0, 0.0, 5.0);
        let b = e.footprint(&d);
        // Object straddling the front bumper -> active front.
        assert_eq!(
            collision_type(&e, &b, &car(1, 5.5, 0.0, 0.0, 3.0)),
            CollisionType::ActiveFront
        );
        // Object beside the ego (not reaching the bumper) -> active lateral.
        assert_eq!(
            collision_type(&e, &b, &car(1, 1.0, 2.0, 0.0, 3.0)),
            CollisionType::ActiveLateral
        );
        // Object behind the rear axle (> 150 deg) -> active rear.
        assert_eq!(
            collision_type(&e, &b, &car(1, -2.5, 0.0, 0.0, 6.0)),
            CollisionType::ActiveRear
        );
        // Stopped object / static object -> stopped track.
        assert_eq!(
            collision_type(&e, &b, &car(1, 5.5, 0.0, 0.0, 0.05)),
            CollisionType::StoppedTrack
        );
        let mut cone = car(1, 1.0, 2.0, 0.0, 3.0);
        cone.is_agent = false;
        cone.class = ObjectClass::TrafficCone;
        assert_eq!(collision_type(&e, &b, &cone), CollisionType::StoppedTrack);
        // Ego stopped wins over everything.
        let s = ego_at(0.0, 0.0, 0.0, 0.05);
        assert_eq!(
            collision_type(&s, &b, &car(1, 5.5, 0.0, 0.0, 3.0)),
            CollisionType::StoppedEgo
        );
    }

    #[test]
    fn at_fault_rules_and_score() {
        let d = EgoDims::PACIFICA;
        let ego = vec![ego_at(0.0, 0.0, 0.0, 5.0); 3];
        let mut cone = car(7, 1.0, 2.0, 0.0, 0.0);
        cone.is_agent = false;
        cone.class = ObjectClass::Barrier;
        let objects = vec![
            vec![car(1, 1.0, 2.0, 0.0, 3.0)], // lateral: at fault only when not in a common lane
            vec![car(1, 1.0, 2.0, 0.0, 3.0), cone], // track 1 counted once; static object at fault
            vec![car(2, -2.5, 0.0, 0.0, 6.0)], // rear: never at fault
        ];
        let r = at_fault_collisions(&ego, &d, &objects, &[true, true, true]);
        assert_eq!(r.collisions.len(), 3);
        assert_eq!(
            (r.at_fault_vru, r.at_fault_vehicles, r.at_fault_objects),
            (0, 0, 1)
        );
        assert_eq!(r.score, 0.5);
        let r = at_fault_collisions(&ego, &d, &objects, &[false, true, true]);
        assert_eq!((r.at_fault_vehicles, r.at_fault_objects), (1, 1));
        assert_eq!(r.score, 0.0);
        assert_eq!(collision_score(2, 1), 0.0);
        assert_eq!(collision_score(0, 0), 1.0);
    }

    #[test]
    fn ttc_constant_velocity() {
        use crate::metrics::vecmap::VecMap;
        let d = EgoDims::PACIFICA;
        let map = VecMap::default();
        // Ego at 10 m/s, stopped car whose rear is 9.5 m ahead of the front bumper: the gap closes by 1 m per
        // 0.1 s, so the first projected overlap is at t = 1.0 s.
        let e = ego_at(0.0, 0.0, 0.0, 10.0);
        let front = d.front_length;
        let obj = car(1, front + 9.5 + 2.0, 0.0, 0.0, 0.0);
        let r = time_to_collision(
            &map,
            &[e],
            &d,
            &[vec![obj]],
            &[true],
            &[],
            &TtcParams::default(),
        );
        assert!((r.ttc[0] - 1.0).abs() < 1e-9, "{:?}", r.ttc);
        assert_eq!(r.score, 1.0);
        // 7.5 m gap -> 0.8 s -> below 0.95.
        let obj = car(1, front + 7.5 + 2.0, 0.0, 0.0, 0.0);
        let r = time_to_collision(
            &map,
            &[e],
            &d,
            &[vec![obj]],
            &[true],
            &[],
            &TtcParams::default(),
        );
        assert!((r.ttc[0] - 0.8).abs() < 1e-9, "{:?}", r.ttc);
        assert_eq!(r.score, 0.0);
        // Object to the side (not ahead) is ignored while in a common lane, considered otherwise.
        let side = car(1, 8.0, 6.0, -std::f64::consts::FRAC_PI_2, 6.0); // 36.9 deg off the heading
        let r = time_to_collision(
            &map,
            &[e],
            &d,
            &[vec![side]],
            &[true],
            &[],
            &TtcParams::default(),
        );
        assert!(r.ttc[0].is_infinite());
        let r = time_to_collision(
            &map,
            &[e],
            &d,
            &[vec![side]],
            &[false],
            &[],
            &TtcParams::default(),
        );
        assert!(r.ttc[0].is_finite(), "{:?}", r.ttc);
        // Ego stopped -> infinite.
        let s = ego_at(0.0, 0.0, 0.0, 0.0);
        let obj = car(1, front + 1.0 + 2.0, 0.0, 0.0, 0.0);
        let r = time_to_collision(
            &map,
            &[s],
            &d,
            &[vec![obj]],
            &[true],
            &[],
            &TtcParams::default(),
        );
        assert!(r.ttc[0].is_infinite());
        assert_eq!(arange(0.1, 3.0, 0.1).len(), 29);
    }
}
