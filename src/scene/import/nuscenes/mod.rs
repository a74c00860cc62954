//! nuScenes logs read from the official tables: `--scenario nuscenes:DATAROOT[:VERSION]:SCENE` (docs/nuscenes.md).
//!
//! - Tables: `DATAROOT/VERSION/*.json` ([`tables`]; VERSION defaults to `v1.0-mini`); SCENE is a scene name
//!   (`scene-0061`) or token. Map: `DATAROOT/maps/expansion/<log.location>.json` ([`expansion`]); without
//!   it (a separate download) a map without lanes that names the missing file (`Map::without_lanes`).
//! - Time: the log starts at the scene's first sample; steps are 0.1 s up to the last sample. Keyframes
//!   (samples) come at about 2 Hz.
//! - Ego: the ego poses of the scene's LIDAR_TOP sample_data (all sample_data when there is no LIDAR_TOP),
//!   interpolated to each step (linear position, shortest-angle yaw). The ego pose is the rear axle.
//! - Objects: per step, the devkit's `NuScenes.get_boxes` rule: at time t in (t_{j-1}, t_j] the annotations of
//!   sample j, each interpolated from the same instance's annotation in sample j-1 (linear centre, quaternion
//!   slerp) when it has one, else taken as is. Velocities: the devkit's `box_velocity` of each annotation,
//!   interpolated the same way (0 when it cannot be estimated). Size: the instance's first annotation.
//! - Cameras: every camera sample_data becomes a recorded image with its own ego pose and timestamp; the
//!   keyframe images of a sample form one [`RecordedFrame`] at the log step nearest the sample time; non-key
//!   images (sweeps) are grouped into frames by time (one image per camera, within 60 ms). The rig's cameras
//!   take the calibration of each channel's first image; the rig's `lidar2ego` is the calibration of the scene's
//!   first LIDAR_TOP sample_data (the nominal nuScenes mounting without one). Image paths are
//!   `DATAROOT/<filename>` (absolute when DATAROOT is, else relative to the working directory, like the DATAROOT
//!   itself).
use super::bounds;
use crate::scene::camera::{Camera, CameraImage, CameraRig, RecordedFrame};
use crate::scene::geometry::{wrap_angle, Aabb, Pose2};
use crate::scene::map::Map;
use crate::scene::{
    EgoLogState, ObjectClass, ObjectState, Scenario, Track, TrafficLightStatus, VehicleParameters,
};
use anyhow::{anyhow, bail, Context, Result};
use glam::{DMat4, DQuat, DVec2, DVec3};
use std::collections::HashMap;
use std::path::PathBuf;

pub mod expansion;
pub mod tables;

use tables::{Row, Tables};

/// Version folder used when the spec names none.
pub const DEFAULT_VERSION: &str = "v1.0-mini";
/// Log step (s): annotations are interpolated to 10 Hz.
pub const DT: f64 = 0.1;
/// Map elements are kept within this distance of the ego path's bounding box.
pub const MAP_MARGIN_M: f64 = 200.0;
/// Camera sweeps closer than this in time (and of different cameras) form one frame.
pub const SWEEP_GROUP_US: i64 = 60_000;
/// The devkit's `box_velocity` max_time_diff (s), doubled for centred differences.
pub const BOX_VELOCITY_MAX_DT: f64 = 1.5;
/// Longest scene accepted (s; nuScenes scenes last about 20 s): the log is sampled every [`DT`] over it.
pub const MAX_SCENE_S: f64 = 600.0;
pub use super::bounds::MAX_TIMESTAMP_US;

/// `nuscenes:DATAROOT[:VERSION]:SCENE`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NuscenesSpec {
    pub dataroot: PathBuf,
    pub version: String,
    /// Scene name or token.
    pub scene: String,
}

impl NuscenesSpec {
    /// The files an import of this spec reads whole (for `--resume`'s fingerprints): the tables
    /// ([`tables::TABLES`]) and every map expansion file (which one is used depends on the scene's log). Files
    /// that do not exist are left out (the import names them).
    pub fn input_files(&self) -> Vec<PathBuf> {
        let dir = self.dataroot.join(&self.version);
        let mut out: Vec<PathBuf> = tables::TABLES
            .iter()
            .map(|t| dir.join(format!("{t}.json")))
            .filter(|p| p.is_file())
            .collect();
        let mut maps: Vec<PathBuf> = std::fs::read_dir(self.dataroot.join("maps/expansion"))
            .map(|d| {
                d.flatten()
                    .map(|e| e.path())
                    .filter(|p| p.extension().is_some_and(|x| x == "json") && p.is_file())
                    .collect()
            })
            .unwrap_or_default();
        maps.sort();
        out.extend(maps);
        out
    }

    /// Parses the part after `nuscenes:` (`spec` is the whole argument, for errors). Split from the right, so
    /// a DATAROOT may hold a colon; the middle field is a VERSION when it starts with `v` and a digit.
    pub fn parse(rest: &str, spec: &str) -> Result<NuscenesSpec> {
        let mut it = rest.rsplitn(3, ':');
        let scene = it.next().unwrap_or_default();
        let (a, b) = (it.next(), it.next());
        let is_version = |s: &str| {
            let c: Vec<char> = s.chars().take(2).collect();
            c.len() == 2 && c[0] == 'v' && c[1].is_ascii_digit()
        };
        let (root, version) = match (a, b) {
            (Some(v), Some(r)) if is_version(v) => (r.to_string(), v.to_string()),
            (Some(v), Some(r)) => (format!("{r}:{v}"), DEFAULT_VERSION.to_string()),
            (Some(r), None) => (r.to_string(), DEFAULT_VERSION.to_string()),
            _ => bail!("scenario {spec:?}: expected nuscenes:DATAROOT[:VERSION]:SCENE"),
        };
        if root.is_empty() || scene.is_empty() || version.is_empty() {
            bail!("scenario {spec:?}: expected nuscenes:DATAROOT[:VERSION]:SCENE with none of them empty");
        }
        Ok(NuscenesSpec {
            dataroot: PathBuf::from(root),
            version,
            scene: scene.to_string(),
        })
    }

    /// The spec string.
    pub fn spec(&self) -> String {
        format!(
            "nuscenes:{}:{}:{}",
            self.dataroot.display(),
            self.version,
            self.scene
        )
    }
}

/// One annotated box of a keyframe, as stored (global frame).
#[derive(Clone, Debug, PartialEq)]
pub struct Annotation {
    pub token: String,
    pub instance: String,
    pub category: String,
    /// Box centre.
    pub center: DVec3,
    /// (length, width, height): nuScenes' `size` is [width, length, height].
    pub size_lwh: DVec3,
    pub rotation: DQuat,
    /// Yaw of the box's x axis about +z.
    pub yaw: f64,
}

/// One sample (keyframe) of the log.
#[derive(Clone, Debug)]
pub struct Keyframe {
    pub token: String,
    /// Microseconds since the log start (the first sample).
    pub time_us: i64,
    pub annotations: Vec<Annotation>,
}

/// A loaded nuScenes scene: the scenario plus what the scenario model does not hold (3D annotations).
#[derive(Clone, Debug)]
pub struct NuscenesLog {
    pub scenario: Scenario,
    pub scene_token: String,
    /// Unix time of the first sample (us); every time in the scenario is relative to it.
    pub t0_us: i64,
    pub keyframes: Vec<Keyframe>,
    /// Per recorded frame of `scenario.rig.frames`: the index of its sample in `keyframes` when it is a keyframe
    /// frame (its images are keyframe sample_data), None for a frame of sweeps.
    pub frame_sample: Vec<Option<usize>>,
}

/// The annotated boxes the devkit's `NuScenes.get_boxes(sample_data_token)` gives for an image taken at `t_us`
/// (relative to the log start): for a keyframe image (`sample` = its sample index) the sample's annotations as
/// stored; for a sweep, the annotations of the first sample at or after `t_us`, each interpolated from the same
/// instance's annotation in the sample before (linear centre, quaternion slerp, fraction
/// `(t - t_prev) / (t_next - t_prev)`), or taken as is without one.
pub fn boxes_at_image(keyframes: &[Keyframe], sample: Option<usize>, t_us: i64) -> Vec<Annotation> {
    if let Some(j) = sample {
        return keyframes
            .get(j)
            .map(|k| k.annotations.clone())
            .unwrap_or_default();
    }
    let Some(j) = keyframes
        .iter()
        .position(|k| k.time_us >= t_us)
        .or(keyframes.len().checked_sub(1))
    else {
        return vec![];
    };
    let cur = &keyframes[j];
    if j == 0 {
        return cur.annotations.clone();
    }
    let prev = &keyframes[j - 1];
    let span = (cur.time_us - prev.time_us).max(1) as f64;
    let f = ((t_us - prev.time_us) as f64 / span).clamp(0.0, 1.0);
    cur.annotations
        .iter()
        .map(
            |a| match prev.annotations.iter().find(|p| p.instance == a.instance) {
                Some(p) => {
                    let rotation = p.rotation.slerp(a.rotation, f);
                    Annotation {
                        center: p.center.lerp(a.center, f),
                        rotation,
                        yaw: yaw_of(rotation),
                        ..a.clone()
                    }
                }
                None => a.clone(),
            },
        )
        .collect()
}

/// The object class of a nuScenes category (ScenarioNet's mapping: bicycles and motorcycles are cyclists).
pub fn class_of_category(name: &str) -> ObjectClass {
    match name {
        "vehicle.bicycle" | "vehicle.motorcycle" => ObjectClass::Bicycle,
        n if n.starts_with("vehicle.") => ObjectClass::Vehicle,
        n if n.starts_with("human.pedestrian") => ObjectClass::Pedestrian,
        "movable_object.trafficcone" => ObjectClass::TrafficCone,
        "movable_object.barrier" => ObjectClass::Barrier,
        _ => ObjectClass::GenericObject,
    }
}

/// Yaw of a rotation: the heading of its x axis projected on the ground plane (the devkit's `quaternion_yaw`).
pub fn yaw_of(q: DQuat) -> f64 {
    let v = q * DVec3::X;
    v.y.atan2(v.x)
}

/// Loads one scene.
pub fn load(spec: &NuscenesSpec) -> Result<Scenario> {
    Ok(load_log(spec)?.scenario)
}

/// A sample_data row of the scene with what the importer needs.
struct Sd {
    /// "table `sample_data` row i (token ...)" for errors.
    at: String,
    /// The row's ego_pose, for errors.
    ego_pose_at: String,
    channel: String,
    modality: String,
    sample: usize,
    key: bool,
    t: i64,
    e2g: DMat4,
    filename: String,
    calib: String,
    size: (u32, u32),
}

/// Loads one scene with its keyframe annotations.
pub fn load_log(spec: &NuscenesSpec) -> Result<NuscenesLog> {
    let dir = spec.dataroot.join(&spec.version);
    let t = Tables::read(&dir)?;
    let scene = t
        .scene
        .iter()
        .find(|r| {
            r.as_ref().is_ok_and(|r| {
                r.str("name").ok() == Some(spec.scene.as_str())
                    || r.str("token").ok() == Some(spec.scene.as_str())
            })
        })
        .transpose()?
        .ok_or_else(|| {
            let names: Vec<&str> = t
                .scene
                .iter()
                .filter_map(|r| r.ok().and_then(|r| r.str("name").ok()))
                .collect();
            anyhow!(
                "nuScenes table `scene` ({}): no scene named {:?} (scenes: {})",
                t.scene.file,
                spec.scene,
                names.join(", ")
            )
        })?;
    let name = scene.str("name")?.to_string();
    if let Err(why) = bounds::plain_name(&name) {
        bail!("{}: column `name`: {why}", scene.at());
    }
    let scene_token = scene.str("token")?.to_string();
    let log = scene.follow("log_token", &t.log)?;
    let location = log.str("location")?.to_string();
    // the location names the map file (`maps/expansion/<location>.json`)
    if let Err(why) = bounds::plain_name(&location) {
        bail!("{}: column `location`: {why}", log.at());
    }
    let ctx = || format!("nuScenes scene {name} ({})", dir.display());

    // Samples, first to last along `next`.
    let mut samples: Vec<Row> = vec![scene.follow("first_sample_token", &t.sample)?];
    loop {
        let last = samples[samples.len() - 1];
        if last.str("next")?.is_empty() {
            break;
        }
        if samples.len() > t.sample.len() {
            bail!(
                "{}: the `next` chain of the scene's samples loops",
                last.at()
            );
        }
        samples.push(last.follow("next", &t.sample)?);
    }
    let sample_ts: Vec<i64> = samples
        .iter()
        .map(|s| timestamp(s))
        .collect::<Result<_>>()?;
    if let Some(w) = sample_ts.windows(2).position(|w| w[1] <= w[0]) {
        bail!(
            "{}: column `timestamp`: samples must be in increasing time",
            samples[w + 1].at()
        );
    }
    let t0 = sample_ts[0];
    let last = sample_ts[sample_ts.len() - 1];
    if (last - t0) as f64 * 1e-6 > MAX_SCENE_S {
        bail!(
            "{}: column `timestamp`: the scene's samples span {} s, more than {MAX_SCENE_S} s",
            samples[samples.len() - 1].at(),
            (last - t0) as f64 * 1e-6
        );
    }
    let sample_idx: HashMap<&str, usize> = samples
        .iter()
        .enumerate()
        .map(|(i, s)| Ok((s.str("token")?, i)))
        .collect::<Result<_>>()?;

    // The scene's sample_data.
    let mut sds = Vec::new();
    for r in t.sample_data.iter() {
        let r = r?;
        let Some(&j) = sample_idx.get(r.str("sample_token")?) else {
            continue;
        };
        let cs = r.follow("calibrated_sensor_token", &t.calibrated_sensor)?;
        let sensor = cs.follow("sensor_token", &t.sensor)?;
        let ep = r.follow("ego_pose_token", &t.ego_pose)?;
        let channel = sensor.str("channel")?.to_string();
        if let Err(why) = bounds::plain_name(&channel) {
            bail!("{}: column `channel`: {why}", sensor.at());
        }
        // joined to the DATAROOT: it must stay inside
        let filename = r.str("filename")?.to_string();
        if let Err(why) = bounds::inside_relative(&filename) {
            bail!("{}: column `filename`: {why}", r.at());
        }
        // Symbolic links in the DATAROOT are followed (samples/ and sweeps/ often live on another disk); an
        // image that exists must be a regular file: a FIFO or device would block the run that reads it.
        let image = spec.dataroot.join(&filename);
        if sensor.str("modality")? == "camera" && image.symlink_metadata().is_ok() {
            if let Err(why) = bounds::regular_file(&image) {
                bail!("{}: column `filename`: {why}", r.at());
            }
        }
        sds.push(Sd {
            at: r.at(),
            ego_pose_at: ep.at(),
            channel,
            modality: sensor.str("modality")?.to_string(),
            sample: j,
            key: r.get("is_key_frame")?,
            t: timestamp(&r)?,
            e2g: ep.transform(bounds::MAX_COORD_M)?,
            filename,
            calib: cs.str("token")?.to_string(),
            size: (r.get("width")?, r.get("height")?),
        });
    }
    sds.sort_by(|a, b| a.t.cmp(&b.t).then_with(|| a.channel.cmp(&b.channel)));

    // Ego.
    let lidar: Vec<&Sd> = sds.iter().filter(|s| s.channel == "LIDAR_TOP").collect();
    let pose_src: Vec<&Sd> = if lidar.is_empty() {
        sds.iter().collect()
    } else {
        lidar
    };
    let mut poses: Vec<(i64, DVec2, f64)> = Vec::new();
    let mut last_at: Option<&str> = None;
    for s in pose_src {
        let p = (
            s.t,
            s.e2g.w_axis.truncate().truncate(),
            yaw_of(DQuat::from_mat4(&s.e2g)),
        );
        if let Some(l) = poses.last() {
            if l.0 == p.0 {
                continue;
            }
            let v = (p.1 - l.1).length() / ((p.0 - l.0) as f64 * 1e-6);
            if v > bounds::MAX_SPEED_MPS {
                bail!(
                    "{}: column `translation`: the ego moves at {v:.3e} m/s from {} (beyond {} m/s; sample_data {})",
                    s.ego_pose_at,
                    last_at.unwrap_or("the previous pose"),
                    bounds::MAX_SPEED_MPS,
                    s.at
                );
            }
        }
        last_at = Some(&s.ego_pose_at);
        poses.push(p);
    }
    if poses.is_empty() {
        bail!("{}: no sample_data (hence no ego pose) in the scene", ctx());
    }
    let span = (sample_ts[sample_ts.len() - 1] - t0) as f64 * 1e-6;
    let n_steps = ((span / DT).round() as usize + 1).max(2);
    let step_t = |k: usize| t0 + (k as f64 * DT * 1e6).round() as i64;
    let ego_pose: Vec<Pose2> = (0..n_steps)
        .map(|k| interp_pose(&poses, step_t(k)))
        .collect();
    let mut ego: Vec<EgoLogState> = (0..n_steps)
        .map(|k| {
            let (a, b) = (k.saturating_sub(1), (k + 1).min(n_steps - 1));
            let v = (ego_pose[b].pos() - ego_pose[a].pos()) / ((b - a).max(1) as f64 * DT);
            EgoLogState {
                rear_axle: ego_pose[k],
                velocity: v,
                accel: 0.0,
            }
        })
        .collect();
    super::scenarionet::fill_ego_accel(&mut ego, DT);

    // Annotations per sample.
    let mut keyframes = Vec::with_capacity(samples.len());
    let mut categories: HashMap<String, String> = HashMap::new();
    let mut ann_by_sample: Vec<Vec<Row>> = vec![vec![]; samples.len()];
    for r in t.sample_annotation.iter() {
        let r = r?;
        if let Some(&j) = sample_idx.get(r.str("sample_token")?) {
            ann_by_sample[j].push(r);
        }
    }
    for (j, anns) in ann_by_sample.iter().enumerate() {
        let mut out = Vec::with_capacity(anns.len());
        for r in anns {
            let inst = r.follow("instance_token", &t.instance)?;
            let inst_tok = inst.str("token")?.to_string();
            let category = match categories.get(&inst_tok) {
                Some(c) => c.clone(),
                None => {
                    let c = inst
                        .follow("category_token", &t.category)?
                        .str("name")?
                        .to_string();
                    categories.insert(inst_tok.clone(), c.clone());
                    c
                }
            };
            let [w, l, h] = r.vec::<3>("size")?;
            if !(w > 0.0 && l > 0.0 && h >= 0.0 && [w, l, h].into_iter().all(bounds::size_ok)) {
                bail!(
                    "{}: column `size`: [width, length, height] must be positive and at most {} m, found {:?}",
                    r.at(),
                    bounds::MAX_SIZE_M,
                    [w, l, h]
                );
            }
            let rotation = r.quat("rotation")?;
            out.push(Annotation {
                token: r.str("token")?.to_string(),
                instance: inst_tok,
                category,
                center: DVec3::from(r.position("translation")?),
                size_lwh: DVec3::new(l, w, h),
                rotation,
                yaw: yaw_of(rotation),
            });
        }
        keyframes.push(Keyframe {
            token: samples[j].str("token")?.to_string(),
            time_us: sample_ts[j] - t0,
            annotations: out,
        });
    }
    let velocities = box_velocities(&t, &ann_by_sample, &sample_idx, &sample_ts)?;
    let tracks = interpolate_tracks(&keyframes, &velocities, &sample_ts, n_steps, t0);

    // Map around the ego path.
    let mut region = Aabb::from_points(&ego_pose.iter().map(|p| p.pos()).collect::<Vec<_>>());
    region = region.expand(MAP_MARGIN_M);
    // The map expansion pack is a separate download that images, boxes and calibration do not need: without
    // it the scene loads with a map of no lanes, and what needs lanes says so (`Map::require_lanes`).
    let exp = expansion::path(&spec.dataroot, &location);
    let map = if exp.symlink_metadata().is_ok() {
        expansion::load(&spec.dataroot, &location, &region).with_context(ctx)?
    } else {
        Map::without_lanes(
            &location,
            format!(
                "the nuScenes map expansion pack's {} is not there (lanes, connectors and the drivable area come \
                 from it: a separate download, nuScenes-map-expansion-v1.3, unpacked into DATAROOT/maps)",
                exp.display()
            ),
        )
    };

    let ego_params = VehicleParameters {
        width: 1.73,
        length: 4.08,
        height: 1.56,
        ..VehicleParameters::PACIFICA
    };
    let route = super::scenarionet::route_from_ego(&map, &ego, &ego_params);
    let (rig, frame_sample) = camera_rig(&t, &sds, &sample_ts, t0, &spec.dataroot)?;
    let scenario = Scenario {
        name,
        source: spec.spec(),
        dt: DT,
        map,
        ego,
        ego_params,
        tracks,
        route,
        traffic_lights: vec![Vec::<(usize, TrafficLightStatus)>::new(); n_steps],
        rig,
        ego_past: vec![],
    };
    Ok(NuscenesLog {
        scenario,
        scene_token,
        t0_us: t0,
        keyframes,
        frame_sample,
    })
}

/// Column `timestamp` (us) within [`MAX_TIMESTAMP_US`] of 0.
fn timestamp(r: &Row) -> Result<i64> {
    let t: i64 = r.get("timestamp")?;
    if !(-MAX_TIMESTAMP_US..=MAX_TIMESTAMP_US).contains(&t) {
        bail!(
            "{}: column `timestamp`: {t} us is beyond {MAX_TIMESTAMP_US} us",
            r.at()
        );
    }
    Ok(t)
}

/// Pose at time `t` from time-sorted (t, position, yaw) samples: linear position, shortest-angle yaw; clamped
/// to the first / last sample outside their span.
fn interp_pose(poses: &[(i64, DVec2, f64)], t: i64) -> Pose2 {
    let i = poses.partition_point(|p| p.0 < t);
    if i == 0 {
        let p = poses[0];
        return Pose2::new(p.1.x, p.1.y, p.2);
    }
    if i == poses.len() {
        let p = poses[i - 1];
        return Pose2::new(p.1.x, p.1.y, p.2);
    }
    let (a, b) = (poses[i - 1], poses[i]);
    let f = (t - a.0) as f64 / (b.0 - a.0) as f64;
    let p = a.1 + (b.1 - a.1) * f;
    Pose2::new(p.x, p.y, wrap_angle(a.2 + f * wrap_angle(b.2 - a.2)))
}

/// The devkit's `box_velocity` (x, y) of every annotation, per sample: centred difference of the previous and
/// next annotation of the instance (one-sided at the ends), none when the time gap is too long or the instance
/// has a single annotation (then 0).
fn box_velocities(
    t: &Tables,
    anns: &[Vec<Row>],
    sample_idx: &HashMap<&str, usize>,
    sample_ts: &[i64],
) -> Result<Vec<Vec<DVec2>>> {
    let time_of = |r: &Row| -> Result<Option<i64>> {
        Ok(sample_idx
            .get(r.str("sample_token")?)
            .map(|&j| sample_ts[j]))
    };
    let mut out = Vec::with_capacity(anns.len());
    for (j, rows) in anns.iter().enumerate() {
        let mut v = Vec::with_capacity(rows.len());
        for r in rows {
            let link = |col: &str| -> Result<Option<Row>> {
                if r.str(col)?.is_empty() {
                    Ok(None)
                } else {
                    r.follow(col, &t.sample_annotation).map(Some)
                }
            };
            let (prev, next) = (link("prev")?, link("next")?);
            let mut max_dt = BOX_VELOCITY_MAX_DT;
            if prev.is_some() && next.is_some() {
                max_dt *= 2.0;
            }
            let ends = |x: Option<Row>| -> Result<Option<(i64, DVec2)>> {
                match x {
                    None => Ok(Some((
                        sample_ts[j],
                        DVec2::from_slice(&r.position("translation")?),
                    ))),
                    Some(x) => Ok(time_of(&x)?
                        .map(|tt| {
                            Ok::<_, anyhow::Error>((
                                tt,
                                DVec2::from_slice(&x.position("translation")?),
                            ))
                        })
                        .transpose()?),
                }
            };
            let vel = if prev.is_none() && next.is_none() {
                DVec2::ZERO
            } else {
                match (ends(prev)?, ends(next)?) {
                    (Some((ta, pa)), Some((tb, pb))) => {
                        let dt = (tb - ta) as f64 * 1e-6;
                        if dt > 0.0 && dt <= max_dt {
                            (pb - pa) / dt
                        } else {
                            DVec2::ZERO
                        }
                    }
                    _ => DVec2::ZERO,
                }
            };
            if !(vel.x.abs() <= bounds::MAX_SPEED_MPS && vel.y.abs() <= bounds::MAX_SPEED_MPS) {
                bail!(
                    "{}: column `translation`: the box velocity from its prev/next annotations is ({}, {}) m/s, beyond {} m/s",
                    r.at(),
                    vel.x,
                    vel.y,
                    bounds::MAX_SPEED_MPS
                );
            }
            v.push(vel);
        }
        out.push(v);
    }
    Ok(out)
}

/// Tracks at 10 Hz by the devkit's `get_boxes` rule (module docs), sorted by instance token.
fn interpolate_tracks(
    keyframes: &[Keyframe],
    velocities: &[Vec<DVec2>],
    sample_ts: &[i64],
    n_steps: usize,
    t0: i64,
) -> Vec<Track> {
    let mut insts: Vec<&str> = keyframes
        .iter()
        .flat_map(|k| k.annotations.iter().map(|a| a.instance.as_str()))
        .collect();
    insts.sort_unstable();
    insts.dedup();
    let idx: HashMap<&str, usize> = insts.iter().enumerate().map(|(i, s)| (*s, i)).collect();
    let mut tracks: Vec<Track> = insts
        .iter()
        .map(|id| Track {
            id: id.to_string(),
            class: ObjectClass::GenericObject,
            length: 0.0,
            width: 0.0,
            height: 0.0,
            states: vec![None; n_steps],
        })
        .collect();
    for kf in keyframes {
        for a in &kf.annotations {
            let tr = &mut tracks[idx[a.instance.as_str()]];
            if tr.length == 0.0 {
                tr.class = class_of_category(&a.category);
                (tr.length, tr.width, tr.height) = (a.size_lwh.x, a.size_lwh.y, a.size_lwh.z);
            }
        }
    }
    // Per sample: instance -> annotation index.
    let by_inst: Vec<HashMap<&str, usize>> = keyframes
        .iter()
        .map(|k| {
            k.annotations
                .iter()
                .enumerate()
                .map(|(i, a)| (a.instance.as_str(), i))
                .collect()
        })
        .collect();
    let n = sample_ts.len();
    for k in 0..n_steps {
        let tk = t0 + (k as f64 * DT * 1e6).round() as i64;
        let j = sample_ts.partition_point(|&s| s < tk).min(n - 1);
        for (i, a) in keyframes[j].annotations.iter().enumerate() {
            let prev = (j > 0)
                .then(|| by_inst[j - 1].get(a.instance.as_str()))
                .flatten()
                .map(|&pi| (&keyframes[j - 1].annotations[pi], velocities[j - 1][pi]));
            let (center, rot, vel) = match prev {
                Some((p, pv)) => {
                    let (ta, tb) = (sample_ts[j - 1], sample_ts[j]);
                    let f = ((tk.clamp(ta, tb) - ta) as f64 / (tb - ta) as f64).clamp(0.0, 1.0);
                    (
                        p.center.lerp(a.center, f),
                        p.rotation.slerp(a.rotation, f),
                        pv.lerp(velocities[j][i], f),
                    )
                }
                None => (a.center, a.rotation, velocities[j][i]),
            };
            tracks[idx[a.instance.as_str()]].states[k] = Some(ObjectState {
                pose: Pose2::new(center.x, center.y, yaw_of(rot)),
                velocity: vel,
            });
        }
    }
    tracks
}

/// Cameras (calibration of each channel's first image) and recorded frames (module docs).
fn camera_rig(
    t: &Tables,
    sds: &[Sd],
    sample_ts: &[i64],
    t0: i64,
    dataroot: &std::path::Path,
) -> Result<(CameraRig, Vec<Option<usize>>)> {
    let mut cameras: Vec<Camera> = Vec::new();
    let max_px = bounds::MAX_IMAGE_SIDE_PX;
    for s in sds.iter().filter(|s| s.modality == "camera") {
        if s.size.0 == 0 || s.size.1 == 0 || s.size.0 > max_px || s.size.1 > max_px {
            bail!(
                "{}: columns `width`, `height`: image {} of {} has size {}x{} (each side in 1..={max_px})",
                s.at,
                s.filename,
                s.channel,
                s.size.0,
                s.size.1
            );
        }
        if cameras.iter().any(|c| c.name == s.channel) {
            continue;
        }
        let cs = t
            .calibrated_sensor
            .find(&s.calib)
            .ok_or_else(|| anyhow!("calibrated_sensor {:?} vanished", s.calib))?;
        let intrinsic = cs.intrinsic("camera_intrinsic")?.ok_or_else(|| {
            anyhow!(
                "{}: column `camera_intrinsic`: empty for camera {}",
                cs.at(),
                s.channel
            )
        })?;
        cameras.push(Camera {
            name: s.channel.clone(),
            intrinsic,
            cam2ego: cs.transform(bounds::MAX_SIZE_M)?,
            width: s.size.0,
            height: s.size.1,
            distortion: [0.0; 5],
        });
    }
    let order = |n: &str| {
        super::CAMERAS
            .iter()
            .position(|c| *c == n)
            .unwrap_or(usize::MAX)
    };
    cameras.sort_by(|a, b| {
        order(&a.name)
            .cmp(&order(&b.name))
            .then(a.name.cmp(&b.name))
    });
    let image = |s: &Sd| CameraImage {
        camera: s.channel.clone(),
        path: dataroot.join(&s.filename).display().to_string(),
        timestamp_us: s.t - t0,
        ego2global: s.e2g,
    };
    let sort_images = |v: &mut Vec<CameraImage>| {
        v.sort_by(|a, b| {
            order(&a.camera)
                .cmp(&order(&b.camera))
                .then(a.camera.cmp(&b.camera))
        })
    };
    let mut frames = Vec::new();
    for (j, &ts) in sample_ts.iter().enumerate() {
        let mut images: Vec<CameraImage> = sds
            .iter()
            .filter(|s| s.sample == j && s.key && s.modality == "camera")
            .map(image)
            .collect();
        if images.is_empty() {
            continue;
        }
        sort_images(&mut images);
        let lidar = sds
            .iter()
            .find(|s| s.sample == j && s.key && s.channel == "LIDAR_TOP");
        let e2g = lidar.map(|s| s.e2g).unwrap_or(images[0].ego2global);
        let step = ((ts - t0) as f64 * 1e-6 / DT).round();
        frames.push((
            RecordedFrame {
                timestamp_us: (step * DT * 1e6).round() as i64,
                ego2global: e2g,
                images,
            },
            Some(j),
        ));
    }
    // Sweeps: greedy groups in time order.
    let mut group: Vec<CameraImage> = Vec::new();
    let flush = |g: &mut Vec<CameraImage>, frames: &mut Vec<(RecordedFrame, Option<usize>)>| {
        if g.is_empty() {
            return;
        }
        sort_images(g);
        frames.push((
            RecordedFrame {
                timestamp_us: g.iter().map(|i| i.timestamp_us).min().unwrap_or(0),
                ego2global: g[0].ego2global,
                images: std::mem::take(g),
            },
            None,
        ));
    };
    for s in sds.iter().filter(|s| !s.key && s.modality == "camera") {
        let img = image(s);
        let start = group.iter().map(|i| i.timestamp_us).min();
        if group.iter().any(|i| i.camera == img.camera)
            || start.is_some_and(|t| img.timestamp_us - t > SWEEP_GROUP_US)
        {
            flush(&mut group, &mut frames);
        }
        group.push(img);
    }
    flush(&mut group, &mut frames);
    frames.sort_by_key(|f| f.0.timestamp_us);
    let (frames, samples) = frames.into_iter().unzip();
    Ok((
        CameraRig {
            cameras,
            lidar2ego: lidar2ego(t, sds)?,
            frames,
        },
        samples,
    ))
}

/// The LIDAR_TOP mounting: the calibrated_sensor of the scene's first LIDAR_TOP sample_data (the devkit's
/// lidar2ego); the nominal nuScenes mounting when the scene has no LIDAR_TOP.
fn lidar2ego(t: &Tables, sds: &[Sd]) -> Result<DMat4> {
    let Some(s) = sds.iter().find(|s| s.channel == "LIDAR_TOP") else {
        return Ok(crate::scene::camera::nuscenes_lidar2ego());
    };
    let cs = t
        .calibrated_sensor
        .find(&s.calib)
        .ok_or_else(|| anyhow!("calibrated_sensor {:?} vanished", s.calib))?;
    cs.transform(bounds::MAX_SIZE_M)
}
