//! nuPlan logs read from the log DB (SQLite): `--scenario nuplan:DB[:SCENARIO_TOKEN]` (docs/nuplan.md).
//!
//! - DB: one nuPlan log file (`<log>.db`); tables of motional/nuplan-devkit docs/nuplan_schema.md, tokens are
//!   BLOBs written as lower-case hex. Map: found as the devkit's GPKGMapsDB finds it ([`maps_db`]):
//!   `MAPS_ROOT/<log.map_version>/<version>/map.gpkg`, the version from the manifest
//!   `MAPS_ROOT/<$NUPLAN_MAP_VERSION or nuplan-maps-v1.0>.json` (read with [`gpkg`]); images:
//!   `SENSOR_ROOT/<image.filename_jpg>`. MAPS_ROOT is `$NUPLAN_MAPS_ROOT`, else the first `maps` folder holding
//!   the manifest found in the DB's folder or one of its ancestors; SENSOR_ROOT is `$NUPLAN_SENSOR_ROOT`, else
//!   the first `sensor_blobs` folder found the same way.
//! - Window: with SCENARIO_TOKEN (a `lidar_pc` token, as the `scenario_tag` rows and the devkit's scenario tokens
//!   are), [`WINDOW_S`] seconds starting [`OFFSET_S`] from that lidar_pc (clamped to the log); without, the whole
//!   log. Steps: every second lidar_pc of the window (20 Hz -> 10 Hz), dt = 0.1 s.
//! - Ego: the lidar_pc's `ego_pose` (x, y: the rear axle; yaw of the quaternion; velocity vx, vy rotated from the
//!   ego frame to the global frame). Objects: `lidar_box` rows of the step's lidar_pc (global centre, yaw, vx, vy)
//!   grouped by `track_token`; size and category from `track` / `category`.
//! - Traffic lights: `traffic_light_status` of the step's lidar_pc, `lane_connector_id` = connector fid.
//! - Cameras: `camera` rows of the log (pickled translation, rotation w,x,y,z camera->ego, intrinsic 3x3;
//!   distortion (k1, k2, p1, p2, k3) kept on the camera: the image store undistorts its images); `image` rows
//!   within the window become recorded images (own timestamp and ego pose), grouped into one frame per step
//!   (the image of each camera nearest the step time, within [`FRAME_TOLERANCE_US`]). Without cameras the rig is the default generated one.
//! - Lidar: the rig's `lidar2ego` is the log's `lidar` row (pickled translation, rotation w,x,y,z lidar->ego;
//!   channel `MergedPointCloud` when several), the nominal nuScenes mounting without one.
//! - Route: the `roadblock_ids` of the scenario's `scene` rows, as the devkit's `get_route_roadblock_ids`
//!   ([`scene_route`]; lane ids: the lanes the logged ego drives); the lane groups the logged ego drives
//!   through when no scene gives roadblocks. Mission goal: `scene.goal_ego_pose_token` (`Route::mission_goal`).
use crate::scene::camera::{Camera, CameraImage, CameraRig, RecordedFrame};
use crate::scene::geometry::{Aabb, Pose2};
use crate::scene::{
    EgoLogState, ObjectClass, ObjectState, Scenario, Track, TrafficLightStatus, VehicleParameters,
};
use anyhow::{anyhow, bail, Context, Result};
use glam::{DMat3, DMat4, DQuat, DVec2, DVec3};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use super::bounds;

pub mod db;
pub mod gpkg;
pub mod maps_db;
pub mod pickle;
pub mod utm;
pub mod wkb;

use db::{unhex, Db, Rec};

/// Log step (s): every second lidar_pc.
pub const DT: f64 = 0.1;
/// Scenario window length (s) and start relative to the tagged lidar_pc (s): the devkit's
/// `nuplan_scenario_mapping.yaml` gives `[15.0, -3.0]` to every scenario type (subsample ratio 0.5).
pub const WINDOW_S: f64 = 15.0;
pub const OFFSET_S: f64 = -3.0;
/// Map elements are kept within this distance of the ego path's bounding box.
pub const MAP_MARGIN_M: f64 = 200.0;
/// An image joins the frame of a step when it is within this time of the step.
pub const FRAME_TOLERANCE_US: i64 = 60_000;
/// nuPlan camera channels in rig order.
pub const CAMERAS: [&str; 8] = [
    "CAM_F0", "CAM_L0", "CAM_R0", "CAM_L1", "CAM_R1", "CAM_L2", "CAM_R2", "CAM_B0",
];

/// `nuplan:DB[:SCENARIO_TOKEN]` with the resolved map and sensor roots.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NuplanSpec {
    pub db: PathBuf,
    /// A lidar_pc token (hex) starting a scenario window; None: the whole log.
    pub token: Option<String>,
    /// `$NUPLAN_MAPS_ROOT` when set (else searched from the DB's folder at load).
    pub maps_root: Option<PathBuf>,
    /// The maps manifest's name (`MAPS_ROOT/<map_version>.json`): `$NUPLAN_MAP_VERSION`, else
    /// [`maps_db::DEFAULT_MAP_VERSION`].
    pub map_version: String,
    /// `$NUPLAN_SENSOR_ROOT` when set (else searched from the DB's folder at load).
    pub sensor_root: Option<PathBuf>,
}

impl NuplanSpec {
    /// Parses the part after `nuplan:`: the DB path, then an optional `:TOKEN` of hex digits (split from the
    /// right, so a path may hold a colon).
    pub fn parse(rest: &str, spec: &str) -> Result<NuplanSpec> {
        let (db, token) = match rest.rsplit_once(':') {
            Some((d, t))
                if !t.is_empty()
                    && t.len() % 2 == 0
                    && t.chars().all(|c| c.is_ascii_hexdigit())
                    && !d.is_empty() =>
            {
                (d.to_string(), Some(t.to_ascii_lowercase()))
            }
            _ => (rest.to_string(), None),
        };
        if db.is_empty() {
            bail!("scenario {spec:?}: expected nuplan:DB[:SCENARIO_TOKEN]");
        }
        let env = |k: &str| {
            std::env::var_os(k)
                .filter(|v| !v.is_empty())
                .map(PathBuf::from)
        };
        Ok(NuplanSpec {
            db: PathBuf::from(db),
            token,
            maps_root: env("NUPLAN_MAPS_ROOT"),
            map_version: std::env::var("NUPLAN_MAP_VERSION")
                .ok()
                .filter(|v| !v.is_empty())
                .unwrap_or_else(|| maps_db::DEFAULT_MAP_VERSION.to_string()),
            sensor_root: env("NUPLAN_SENSOR_ROOT"),
        })
    }

    pub fn spec(&self) -> String {
        match &self.token {
            Some(t) => format!("nuplan:{}:{t}", self.db.display()),
            None => format!("nuplan:{}", self.db.display()),
        }
    }

    /// MAPS_ROOT: `$NUPLAN_MAPS_ROOT`, else the first `maps` folder holding the manifest
    /// `<map_version>.json` next to the DB or above it.
    fn maps_root(&self) -> Result<PathBuf> {
        let manifest = format!("{}.json", self.map_version);
        match &self.maps_root {
            Some(m) => Ok(m.clone()),
            None => search_up(&self.db, "maps", |p| p.join(&manifest).is_file()).ok_or_else(|| {
                anyhow!(
                    "no `maps` folder holding the maps manifest {manifest} found in the DB's folder or its 5 \
                     ancestors (set NUPLAN_MAPS_ROOT to the maps folder, NUPLAN_MAP_VERSION to another manifest)"
                )
            }),
        }
    }

    /// The manifest and GeoPackage of the log whose `map_version` column is `log_map_version` ([`maps_db`]).
    fn map_files(&self, log_map_version: &str) -> Result<(PathBuf, PathBuf)> {
        let root = self.maps_root()?;
        let gpkg = maps_db::locate(&root, &self.map_version, log_map_version)?;
        Ok((maps_db::manifest_path(&root, &self.map_version), gpkg))
    }

    /// The files an import of this spec reads whole (for `--resume`'s fingerprints): the log DB, the maps
    /// manifest and the map.
    pub fn input_files(&self) -> Result<Vec<PathBuf>> {
        let db = Db::open(&self.db, "nuPlan log DB")?;
        let log = db
            .select("log", &["token", "map_version"], "LIMIT 1", &[])?
            .into_iter()
            .next()
            .ok_or_else(|| anyhow!("{}: table `log` is empty", db.what))?;
        let (manifest, map) = self
            .map_files(log.plain_text("map_version")?)
            .with_context(|| format!("{}: column `map_version`", log.at()))?;
        Ok([self.db.clone(), manifest, map]
            .into_iter()
            .filter(|p| p.is_file())
            .collect())
    }

    /// Output name: the log file stem, plus the token when one is given.
    pub fn name(&self) -> String {
        let stem = self
            .db
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        match &self.token {
            Some(t) => format!("{stem}_{t}"),
            None => stem,
        }
    }
}

/// The first `<ancestor>/<sub>` folder (of the DB's folder and its ancestors, at most 6 up) for which `ok`
/// holds, also trying `<ancestor>/*/<sub>` one level down.
fn search_up(db: &Path, sub: &str, ok: impl Fn(&Path) -> bool) -> Option<PathBuf> {
    let start = db
        .canonicalize()
        .ok()
        .and_then(|p| p.parent().map(Path::to_path_buf))?;
    for dir in start.ancestors().take(6) {
        let c = dir.join(sub);
        if c.is_dir() && ok(&c) {
            return Some(c);
        }
    }
    None
}

/// The object class of a nuPlan category name.
pub fn class_of_category(name: &str) -> ObjectClass {
    match name {
        "vehicle" => ObjectClass::Vehicle,
        "bicycle" => ObjectClass::Bicycle,
        "pedestrian" => ObjectClass::Pedestrian,
        "traffic_cone" => ObjectClass::TrafficCone,
        "barrier" => ObjectClass::Barrier,
        "czone_sign" => ObjectClass::CzoneSign,
        _ => ObjectClass::GenericObject,
    }
}

fn light_of(r: &Rec) -> Result<TrafficLightStatus> {
    Ok(match r.text("status")? {
        "green" => TrafficLightStatus::Green,
        "yellow" => TrafficLightStatus::Yellow,
        "red" => TrafficLightStatus::Red,
        "unknown" => TrafficLightStatus::Unknown,
        other => bail!(
            "{}: column `status`: {other:?} is not green, yellow, red or unknown",
            r.at()
        ),
    })
}

fn quat(r: &Rec) -> Result<DQuat> {
    let q = DQuat::from_xyzw(r.f64("qx")?, r.f64("qy")?, r.f64("qz")?, r.f64("qw")?);
    rotation(q).map_err(|why| anyhow!("{}: columns qw, qx, qy, qz: {why}", r.at()))
}

/// The unit quaternion of `q`; `Err(why)` when `q` is not a rotation (zero, non-finite or huge: its length is
/// not within 1e-6..1e6).
fn rotation(q: DQuat) -> std::result::Result<DQuat, String> {
    let n = q.length();
    if !(n.is_finite() && (1e-6..=1e6).contains(&n)) {
        return Err(format!(
            "({}, {}, {}, {}) is not a rotation (length {n})",
            q.w, q.x, q.y, q.z
        ));
    }
    Ok(q.normalize())
}

fn yaw_of(q: DQuat) -> f64 {
    let v = q * DVec3::X;
    v.y.atan2(v.x)
}

/// `?, ?, ...` for `n` parameters.
fn marks(n: usize) -> String {
    vec!["?"; n].join(",")
}

/// Rows of `table` whose `token` is one of `tokens` (hex), by token; in chunks (SQLite's parameter limit).
fn by_token(
    db: &Db,
    table: &str,
    cols: &[&str],
    tokens: &[String],
) -> Result<HashMap<String, Rec>> {
    let mut out = HashMap::new();
    let mut uniq: Vec<&String> = tokens.iter().collect();
    uniq.sort();
    uniq.dedup();
    for chunk in uniq.chunks(900) {
        let blobs: Vec<Vec<u8>> = chunk.iter().filter_map(|t| unhex(t)).collect();
        let params: Vec<&dyn rusqlite::ToSql> =
            blobs.iter().map(|b| b as &dyn rusqlite::ToSql).collect();
        let tail = format!("WHERE token IN ({})", marks(blobs.len()));
        for r in db.select(table, cols, &tail, &params)? {
            out.insert(r.token("token")?, r);
        }
    }
    Ok(out)
}

/// Follows `from`'s column `col` into `rows` (a dangling token is an error naming both tables).
fn follow<'a>(
    from: &Rec,
    col: &str,
    table: &str,
    rows: &'a HashMap<String, Rec>,
) -> Result<&'a Rec> {
    let t = from.token(col)?;
    rows.get(&t).ok_or_else(|| {
        anyhow!(
            "{}: column `{col}`: no row of table `{table}` has token {t} (dangling token)",
            from.at()
        )
    })
}

/// A loaded nuPlan scenario with the log facts the scenario model does not hold.
#[derive(Clone, Debug)]
pub struct NuplanLog {
    pub scenario: Scenario,
    pub log_name: String,
    /// Unix time (us) of the first step; every time in the scenario is relative to it.
    pub t0_us: i64,
    /// lidar_pc tokens of the steps.
    pub lidar_pc: Vec<String>,
    /// scenario_tag rows in the window: (lidar_pc token, type).
    pub tags: Vec<(String, String)>,
    pub map_path: PathBuf,
}

/// Loads one scenario.
pub fn load(spec: &NuplanSpec) -> Result<Scenario> {
    Ok(load_log(spec)?.scenario)
}

/// Loads one scenario with its log facts.
pub fn load_log(spec: &NuplanSpec) -> Result<NuplanLog> {
    let db = Db::open(&spec.db, "nuPlan log DB")?;
    let what = db.what.clone();
    let log = db
        .select(
            "log",
            &["token", "logfile", "location", "map_version"],
            "LIMIT 1",
            &[],
        )?
        .into_iter()
        .next()
        .ok_or_else(|| anyhow!("{what}: table `log` is empty"))?;
    // `map_version` is the map's name (its folder under MAPS_ROOT); `location` (e.g. las_vegas) names no file.
    let location = log.opt_text("location")?.unwrap_or("").to_string();
    let map_version = log.plain_text("map_version")?.to_string();
    let log_name = log.opt_text("logfile")?.unwrap_or("").to_string();

    // lidar_pc of the whole log, in time order.
    let pcs = db.select(
        "lidar_pc",
        &["token", "ego_pose_token", "timestamp"],
        "ORDER BY timestamp",
        &[],
    )?;
    if pcs.is_empty() {
        bail!("{what}: table `lidar_pc` is empty");
    }
    let ts: Vec<i64> = pcs
        .iter()
        .map(|r| r.timestamp("timestamp"))
        .collect::<Result<_>>()?;
    // Time order (issue #36): sorted by the query, so only duplicates can remain; two sweeps at one instant
    // would make a zero time step (as the nuScenes importer, increasing strictly).
    if let Some(w) = ts.windows(2).position(|w| w[1] <= w[0]) {
        bail!(
            "{}: column `timestamp`: {} us, the same instant as {}: lidar_pc timestamps must increase strictly",
            pcs[w + 1].at(),
            ts[w + 1],
            pcs[w].at()
        );
    }
    let (a, b) = match &spec.token {
        None => (0, pcs.len()),
        Some(t) => {
            let i = pcs
                .iter()
                .position(|r| r.token("token").ok().as_deref() == Some(t.as_str()))
                .ok_or_else(|| {
                    let tags: Vec<String> = db
                        .select("scenario_tag", &["token", "lidar_pc_token"], "", &[])
                        .map(|v| {
                            v.iter()
                                .filter_map(|r| r.token("lidar_pc_token").ok())
                                .take(10)
                                .collect()
                        })
                        .unwrap_or_default();
                    anyhow!(
                        "{what}: table `lidar_pc`: no lidar_pc has token {t} (scenario tokens are lidar_pc tokens; tagged ones: {})",
                        tags.join(", ")
                    )
                })?;
            let start = ts[i] + (OFFSET_S * 1e6) as i64;
            let end = start + (WINDOW_S * 1e6) as i64;
            (
                ts.partition_point(|&x| x < start),
                ts.partition_point(|&x| x < end),
            )
        }
    };
    let sel: Vec<&Rec> = pcs[a..b].iter().step_by(2).collect();
    if sel.len() < 2 {
        bail!("{what}: table `lidar_pc`: the scenario window holds fewer than 2 steps");
    }
    let t0 = ts[a];
    let t_last = sel[sel.len() - 1].timestamp("timestamp")?;
    let n = sel.len();
    let pc_tokens: Vec<String> = sel
        .iter()
        .map(|r| r.token("token"))
        .collect::<Result<_>>()?;
    let step_of: HashMap<&str, usize> = pc_tokens
        .iter()
        .enumerate()
        .map(|(k, t)| (t.as_str(), k))
        .collect();

    // Ego.
    let ego_cols = [
        "token",
        "x",
        "y",
        "qw",
        "qx",
        "qy",
        "qz",
        "vx",
        "vy",
        "timestamp",
    ];
    let ep_tokens: Vec<String> = sel
        .iter()
        .map(|r| r.token("ego_pose_token"))
        .collect::<Result<_>>()?;
    let eps = by_token(&db, "ego_pose", &ego_cols, &ep_tokens)?;
    let mut ego = Vec::with_capacity(n);
    let mut prev_pose: Option<(&Rec, i64)> = None;
    for r in &sel {
        let e = follow(r, "ego_pose_token", "ego_pose", &eps)?;
        // the steps' ego poses in the steps' order: strictly increasing time too (a reversed or shared pose
        // would make the ego jump back or stand still for a step)
        let te = e.timestamp("timestamp")?;
        if let Some((p, tp)) = prev_pose {
            if te <= tp {
                bail!(
                    "{}: column `timestamp`: {te} us is {} {tp} us of {}, the previous step's ego pose \
                     (the ego pose of {}): ego pose timestamps must increase strictly with the lidar_pc's",
                    e.at(),
                    if te == tp { "the same instant as" } else { "before" },
                    p.at(),
                    r.at()
                );
            }
        }
        prev_pose = Some((e, te));
        let yaw = yaw_of(quat(e)?);
        let v_local = DVec2::new(e.speed("vx")?, e.speed("vy")?);
        let (s, c) = yaw.sin_cos();
        ego.push(EgoLogState {
            rear_axle: Pose2::new(e.coord("x")?, e.coord("y")?, yaw),
            velocity: DVec2::new(c * v_local.x - s * v_local.y, s * v_local.x + c * v_local.y),
            accel: 0.0,
        });
    }
    super::scenarionet::fill_ego_accel(&mut ego, DT);

    // Window filter for per-lidar_pc tables.
    let win = format!(
        "WHERE lidar_pc_token IN (SELECT token FROM lidar_pc WHERE timestamp BETWEEN {t0} AND {t_last})"
    );
    // Objects.
    let boxes = db.select(
        "lidar_box",
        &[
            "token",
            "lidar_pc_token",
            "track_token",
            "x",
            "y",
            "yaw",
            "vx",
            "vy",
        ],
        &win,
        &[],
    )?;
    let track_tokens: Vec<String> = boxes
        .iter()
        .map(|r| r.token("track_token"))
        .collect::<Result<_>>()?;
    let tracks_t = by_token(
        &db,
        "track",
        &["token", "category_token", "width", "length", "height"],
        &track_tokens,
    )?;
    let cats = db.select("category", &["token", "name"], "", &[])?;
    let cat_name: HashMap<String, Rec> = cats
        .into_iter()
        .map(|r| Ok((r.token("token")?, r)))
        .collect::<Result<_>>()?;
    let mut tracks: Vec<Track> = Vec::new();
    let mut track_idx: HashMap<String, usize> = HashMap::new();
    for bx in &boxes {
        let Some(&k) = step_of.get(bx.token("lidar_pc_token")?.as_str()) else {
            continue; // an odd lidar_pc (20 Hz) between steps
        };
        let tr = follow(bx, "track_token", "track", &tracks_t)?;
        let tid = tr.token("token")?;
        let i = match track_idx.get(&tid) {
            Some(&i) => i,
            None => {
                let cat = follow(tr, "category_token", "category", &cat_name)?;
                let (l, w, h) = (tr.f64("length")?, tr.f64("width")?, tr.f64("height")?);
                if !(l > 0.0 && w > 0.0 && h >= 0.0 && [l, w, h].into_iter().all(bounds::size_ok)) {
                    bail!(
                        "{}: columns length, width, height must be positive and at most {} m, found {l}, {w}, {h}",
                        tr.at(),
                        bounds::MAX_SIZE_M
                    );
                }
                tracks.push(Track {
                    id: tid.clone(),
                    class: class_of_category(cat.text("name")?),
                    length: l,
                    width: w,
                    height: h,
                    states: vec![None; n],
                });
                track_idx.insert(tid, tracks.len() - 1);
                tracks.len() - 1
            }
        };
        tracks[i].states[k] = Some(ObjectState {
            pose: Pose2::new(
                bx.coord("x")?,
                bx.coord("y")?,
                bx.f64_within("yaw", bounds::MAX_ANGLE_RAD, "rad")?,
            ),
            velocity: DVec2::new(bx.speed("vx")?, bx.speed("vy")?),
        });
    }
    tracks.sort_by(|a, b| a.id.cmp(&b.id));

    // Map around the ego path.
    // Errors about the map name the log row that chose it.
    let log_at = format!("{}: column `map_version`", log.at());
    let (_, map_path) = spec.map_files(&map_version).with_context(|| {
        format!("{log_at}: finding the map {map_version:?} (location {location:?})")
    })?;
    let region = Aabb::from_points(&ego.iter().map(|e| e.rear_axle.pos()).collect::<Vec<_>>())
        .expand(MAP_MARGIN_M);
    let map = gpkg::load(&map_path, &maps_db::map_name(&map_version), &region)
        .with_context(|| format!("{log_at}: loading the map {map_version:?}"))?;

    // Traffic lights.
    let mut traffic_lights: Vec<Vec<(usize, TrafficLightStatus)>> = vec![vec![]; n];
    for r in db.select(
        "traffic_light_status",
        &["token", "lidar_pc_token", "lane_connector_id", "status"],
        &win,
        &[],
    )? {
        let Some(&k) = step_of.get(r.token("lidar_pc_token")?.as_str()) else {
            continue;
        };
        let id = r.i64("lane_connector_id")?.to_string();
        let st = light_of(&r)?;
        if let Some(li) = map.lane_index(&id) {
            traffic_lights[k].push((li, st));
        }
    }
    for v in &mut traffic_lights {
        v.sort_by_key(|x| x.0);
    }

    // Scenario tags in the window.
    let mut tags = Vec::new();
    for r in db.select(
        "scenario_tag",
        &["token", "lidar_pc_token", "type"],
        &win,
        &[],
    )? {
        tags.push((
            r.token("lidar_pc_token")?,
            r.opt_text("type")?.unwrap_or("").to_string(),
        ));
    }

    let ego_params = VehicleParameters::PACIFICA;
    let driven = super::scenarionet::route_from_ego(&map, &ego, &ego_params);
    let (mut route, goal) = scene_route(&db, spec, t0, t_last, driven)?;
    route.mission_goal = goal;
    let name = spec.name();
    let mut rig = camera_rig(&db, spec, &log, &sel, &eps, t0, t_last)?
        .unwrap_or_else(|| super::default_rig(&name, &ego, DT));
    if let Some(m) = lidar2ego(&db, &log)? {
        rig.lidar2ego = m;
    }
    let scenario = Scenario {
        name,
        source: spec.spec(),
        dt: DT,
        map,
        ego,
        ego_params,
        tracks,
        route,
        traffic_lights,
        rig,
        ego_past: vec![],
    };
    Ok(NuplanLog {
        scenario,
        log_name,
        t0_us: t0,
        lidar_pc: pc_tokens,
        tags,
        map_path,
    })
}

/// Most route roadblock ids accepted from the `scene` rows of one scenario, and the longest id.
pub const MAX_ROUTE_ROADBLOCKS: usize = 10_000;
pub const MAX_ROADBLOCK_ID_CHARS: usize = 64;

/// The route and mission goal as the devkit reads them (`get_roadblock_ids_for_lidarpc_token_from_db`,
/// `get_mission_goal_for_sensor_data_token_from_db`): the `scene` of a lidar_pc (`lidar_pc.scene_token`) gives
/// the route roadblock ids (`roadblock_ids`, space separated) and the goal (`goal_ego_pose_token`). With a
/// scenario token, the scene of that lidar_pc; for the whole log, the scenes of its steps in time order
/// (their routes concatenated, a repeated id kept once where two meet; the goal of the last). Lane ids stay those
/// the logged ego drives (`driven`), as do the roadblocks when no scene gives any (no `scene` table, NULL or
/// empty `roadblock_ids`).
fn scene_route(
    db: &Db,
    spec: &NuplanSpec,
    t0: i64,
    t_last: i64,
    driven: crate::scene::Route,
) -> Result<(crate::scene::Route, Option<Pose2>)> {
    if !db.has_table("scene")? {
        return Ok((driven, None));
    }
    let pcs = db.select(
        "lidar_pc",
        &["token", "scene_token"],
        "WHERE timestamp BETWEEN ?1 AND ?2 ORDER BY timestamp",
        &[&t0 as &dyn rusqlite::ToSql, &t_last],
    )?;
    let mut scene_of: Vec<(String, &Rec)> = Vec::new();
    for r in &pcs {
        if spec
            .token
            .as_deref()
            .is_some_and(|t| r.token("token").ok().as_deref() != Some(t))
        {
            continue;
        }
        let s = r.token("scene_token")?;
        if scene_of.last().map(|x| &x.0) != Some(&s) {
            scene_of.push((s, r));
        }
    }
    let toks: Vec<String> = scene_of.iter().map(|x| x.0.clone()).collect();
    let scenes = by_token(
        db,
        "scene",
        &["token", "roadblock_ids", "goal_ego_pose_token"],
        &toks,
    )?;
    let mut ids: Vec<String> = Vec::new();
    let mut goal_tok = None;
    for (_, pc) in &scene_of {
        let sc = follow(pc, "scene_token", "scene", &scenes)?;
        for id in sc.opt_text("roadblock_ids")?.unwrap_or("").split(' ') {
            let id = id.trim();
            if id.is_empty() || ids.last().is_some_and(|l| l == id) {
                continue;
            }
            if ids.len() >= MAX_ROUTE_ROADBLOCKS || id.chars().count() > MAX_ROADBLOCK_ID_CHARS {
                bail!(
                    "{}: column `roadblock_ids`: more than {MAX_ROUTE_ROADBLOCKS} roadblock ids in the scenario, or \
                     one longer than {MAX_ROADBLOCK_ID_CHARS} characters",
                    sc.at()
                );
            }
            ids.push(id.to_string());
        }
        goal_tok = sc.opt_token("goal_ego_pose_token")?.map(|t| (t, sc));
    }
    let goal = match goal_tok {
        None => None,
        Some((t, sc)) => {
            let eps = by_token(
                db,
                "ego_pose",
                &["token", "x", "y", "qw", "qx", "qy", "qz"],
                std::slice::from_ref(&t),
            )?;
            let e = follow(sc, "goal_ego_pose_token", "ego_pose", &eps)?;
            Some(Pose2::new(e.coord("x")?, e.coord("y")?, yaw_of(quat(e)?)))
        }
    };
    let route = if ids.is_empty() {
        driven
    } else {
        crate::scene::Route {
            roadblock_ids: ids,
            lane_ids: driven.lane_ids,
            mission_goal: None,
        }
    };
    Ok((route, goal))
}

fn ego2global_of(e: &Rec) -> Result<DMat4> {
    Ok(DMat4::from_rotation_translation(
        quat(e)?,
        DVec3::new(e.f64("x")?, e.f64("y")?, 0.0),
    ))
}

/// The lidar mounting of the log (module docs): the `lidar` row of channel `MergedPointCloud` (the point cloud
/// nuPlan's `lidar_pc` rows hold), else the log's first `lidar` row; None without a `lidar` table or row.
fn lidar2ego(db: &Db, log: &Rec) -> Result<Option<DMat4>> {
    if !db.has_table("lidar")? {
        return Ok(None);
    }
    let log_tok = unhex(&log.token("token")?).unwrap_or_default();
    let rows = db.select(
        "lidar",
        &["token", "channel", "translation", "rotation"],
        "WHERE log_token = ?1",
        &[&log_tok as &dyn rusqlite::ToSql],
    )?;
    let Some(r) = rows
        .iter()
        .find(|r| r.opt_text("channel").ok().flatten() == Some("MergedPointCloud"))
        .or(rows.first())
    else {
        return Ok(None);
    };
    let t = r.pickled("translation", 3)?;
    let q = r.pickled("rotation", 4)?;
    let rot = rotation(DQuat::from_xyzw(q[1], q[2], q[3], q[0]))
        .map_err(|why| anyhow!("{}: column `rotation`: {why}", r.at()))?;
    if !t.iter().all(|x| x.abs() <= bounds::MAX_SIZE_M) {
        bail!(
            "{}: column `translation`: {t:?} lies beyond {} m of the ego",
            r.at(),
            bounds::MAX_SIZE_M
        );
    }
    Ok(Some(DMat4::from_rotation_translation(
        rot,
        DVec3::new(t[0], t[1], t[2]),
    )))
}

/// Cameras and recorded frames (module docs); None when the log has no camera rows.
fn camera_rig(
    db: &Db,
    spec: &NuplanSpec,
    log: &Rec,
    sel: &[&Rec],
    eps: &HashMap<String, Rec>,
    t0: i64,
    t_last: i64,
) -> Result<Option<CameraRig>> {
    if !db.has_table("camera")? || !db.has_table("image")? {
        return Ok(None);
    }
    let log_tok = unhex(&log.token("token")?).unwrap_or_default();
    let cam_rows = db.select(
        "camera",
        &[
            "token",
            "channel",
            "translation",
            "rotation",
            "intrinsic",
            "distortion",
            "width",
            "height",
        ],
        "WHERE log_token = ?1",
        &[&log_tok as &dyn rusqlite::ToSql],
    )?;
    if cam_rows.is_empty() {
        return Ok(None);
    }
    let mut cameras = Vec::new();
    let mut cam_by_tok: HashMap<String, String> = HashMap::new();
    for r in &cam_rows {
        let t = r.pickled("translation", 3)?;
        let q = r.pickled("rotation", 4)?;
        let k = r.pickled("intrinsic", 9)?;
        let d = r.blob("distortion")?;
        let (_, dv) = pickle::decode(d)
            .and_then(|o| pickle::to_array(&o))
            .map_err(|e| anyhow!("{}: column `distortion`: pickled array: {e}", r.at()))?;
        let distortion = distortion_coefficients(&dv)
            .map_err(|why| anyhow!("{}: column `distortion`: {why}", r.at()))?;
        let rot = rotation(DQuat::from_xyzw(q[1], q[2], q[3], q[0]))
            .map_err(|why| anyhow!("{}: column `rotation`: {why}", r.at()))?;
        if !t.iter().all(|x| x.abs() <= bounds::MAX_SIZE_M) {
            bail!(
                "{}: column `translation`: {t:?} lies beyond {} m of the ego",
                r.at(),
                bounds::MAX_SIZE_M
            );
        }
        let m = bounds::MAX_INTRINSIC_PX;
        if !(k.iter().all(|x| x.abs() <= m) && k[0] > 0.0 && k[4] > 0.0) {
            bail!(
                "{}: column `intrinsic`: {k:?} is not [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 and \
                 every value within {m:e} px",
                r.at()
            );
        }
        let (w, h) = (r.i64("width")?, r.i64("height")?);
        let side = 1..=i64::from(bounds::MAX_IMAGE_SIDE_PX);
        if !(side.contains(&w) && side.contains(&h)) {
            bail!(
                "{}: columns width, height: image size {w}x{h} (each side must be 1..={} px)",
                r.at(),
                bounds::MAX_IMAGE_SIDE_PX
            );
        }
        // Camera names become output file names (frames/<step>_<CAM>.png).
        let name = r.plain_text("channel")?.to_string();
        cam_by_tok.insert(r.token("token")?, name.clone());
        cameras.push(Camera {
            name,
            // Row-major 3x3 -> columns.
            intrinsic: DMat3::from_cols_array(&[
                k[0], k[3], k[6], k[1], k[4], k[7], k[2], k[5], k[8],
            ]),
            cam2ego: DMat4::from_rotation_translation(rot, DVec3::new(t[0], t[1], t[2])),
            width: w as u32,
            height: h as u32,
            distortion,
        });
    }
    let order = |n: &str| CAMERAS.iter().position(|c| *c == n).unwrap_or(usize::MAX);
    cameras.sort_by(|a, b| {
        order(&a.name)
            .cmp(&order(&b.name))
            .then(a.name.cmp(&b.name))
    });

    let sensor_root = match &spec.sensor_root {
        Some(s) => s.clone(),
        None => search_up(&spec.db, "sensor_blobs", |_| true)
            .or_else(|| search_up(&spec.db, "nuplan-v1.1/sensor_blobs", |_| true))
            .unwrap_or_else(|| PathBuf::from("sensor_blobs")),
    };
    let imgs = db.select(
        "image",
        &[
            "token",
            "ego_pose_token",
            "camera_token",
            "filename_jpg",
            "timestamp",
        ],
        "WHERE timestamp BETWEEN ?1 AND ?2 ORDER BY timestamp",
        &[
            &(t0 - FRAME_TOLERANCE_US) as &dyn rusqlite::ToSql,
            &(t_last + FRAME_TOLERANCE_US),
        ],
    )?;
    let ep_tokens: Vec<String> = imgs
        .iter()
        .map(|r| r.token("ego_pose_token"))
        .collect::<Result<_>>()?;
    let img_eps = by_token(
        db,
        "ego_pose",
        &["token", "x", "y", "qw", "qx", "qy", "qz", "vx", "vy"],
        &ep_tokens,
    )?;
    let step_ts: Vec<i64> = sel
        .iter()
        .map(|r| r.timestamp("timestamp"))
        .collect::<Result<_>>()?;
    // Per step and camera: (|dt|, image).
    let mut best: Vec<HashMap<String, (i64, CameraImage)>> = vec![HashMap::new(); sel.len()];
    for r in &imgs {
        let tok = r.token("camera_token")?;
        let cam = cam_by_tok.get(&tok).ok_or_else(|| {
            anyhow!(
                "{}: column `camera_token`: no row of table `camera` of this log has token {tok} (dangling token)",
                r.at()
            )
        })?;
        let e = follow(r, "ego_pose_token", "ego_pose", &img_eps)?;
        let t = r.timestamp("timestamp")?;
        let k = step_ts.partition_point(|&s| s < t);
        let k = [k.saturating_sub(1), k.min(step_ts.len() - 1)]
            .into_iter()
            .min_by_key(|&j| (step_ts[j] - t).abs())
            .unwrap_or(0);
        let d = (step_ts[k] - t).abs();
        if d > FRAME_TOLERANCE_US {
            continue;
        }
        if best[k].get(cam).is_some_and(|(bd, _)| *bd <= d) {
            continue;
        }
        let file = r.text("filename_jpg")?;
        bounds::inside_relative(file)
            .map_err(|why| anyhow!("{}: column `filename_jpg`: {why}", r.at()))?;
        best[k].insert(
            cam.clone(),
            (
                d,
                CameraImage {
                    camera: cam.clone(),
                    path: sensor_root.join(file).display().to_string(),
                    timestamp_us: t - t0,
                    ego2global: ego2global_of(e)?,
                },
            ),
        );
    }
    let mut frames = Vec::new();
    for (k, m) in best.into_iter().enumerate() {
        if m.is_empty() {
            continue;
        }
        let mut images: Vec<CameraImage> = m.into_values().map(|x| x.1).collect();
        images.sort_by(|a, b| {
            order(&a.camera)
                .cmp(&order(&b.camera))
                .then(a.camera.cmp(&b.camera))
        });
        let e = follow(sel[k], "ego_pose_token", "ego_pose", eps)?;
        frames.push(RecordedFrame {
            timestamp_us: (k as f64 * DT * 1e6).round() as i64,
            ego2global: ego2global_of(e)?,
            images,
        });
    }
    Ok(Some(CameraRig {
        cameras,
        // the log's `lidar` row replaces it where there is one (`load_log`)
        lidar2ego: crate::scene::camera::nuscenes_lidar2ego(),
        frames,
    }))
}

/// The (k1, k2, p1, p2, k3) of a `camera.distortion` array (nuplan-devkit: "the Caltech model (k1, k2, p1, p2,
/// k3)"); four values are (k1, k2, p1, p2) with k3 = 0. Every coefficient finite and within +-1e3 (a real
/// lens's are O(1); larger ones fold the image onto itself).
fn distortion_coefficients(v: &[f64]) -> std::result::Result<[f64; 5], String> {
    let mut k = [0.0; 5];
    match v.len() {
        4 | 5 => k[..v.len()].copy_from_slice(v),
        n => {
            return Err(format!(
                "{n} coefficients; expected 5 (k1, k2, p1, p2, k3) or 4 (k1, k2, p1, p2)"
            ))
        }
    }
    if !k.iter().all(|x| x.is_finite() && x.abs() <= 1e3) {
        return Err(format!(
            "{k:?}: each coefficient must be finite and within 1e3"
        ));
    }
    Ok(k)
}
