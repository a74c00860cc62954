//! The ground-truth renderer as an observation engine of the closed loop (`groundtruth`, the perfect-sensor
//! baseline of spec world.md section 1): at each planner step it renders the SIMULATED state (the ego where
//! the controller put it, IDM agents where they drove, replayed objects from the log) with every camera of
//! the scenario's rig at a fixed size.
use super::objects::WorldObject;
use super::palette::hash_bytes;
use super::render::{render_cameras, RenderOptions};
use super::{palette_of, Palette, Scenery};
use crate::projection::scene::track_geometry;
use crate::scene::{ObjectState, Scenario};
use crate::sim::sensors::{CameraFrame, SensorState, Sensors};
use anyhow::{ensure, Context, Result};
use std::sync::Arc;
use std::time::Instant;

/// The `groundtruth` sensors: exact images of the simulated state.
pub struct GroundTruthSensors {
    pub width: usize,
    pub height: usize,
    pub threads: usize,
    scenery: Option<Scenery>,
    last_ms: f64,
}

impl GroundTruthSensors {
    /// Images of `height x width` (the rig's intrinsics rescaled to it), rendered on up to `threads` threads.
    pub fn new(height: usize, width: usize, threads: usize) -> Result<Self> {
        ensure!(
            (8..=4096).contains(&height) && (8..=4096).contains(&width),
            "groundtruth sensors: size {height}x{width} must be in 8..=4096 per side"
        );
        Ok(GroundTruthSensors {
            width,
            height,
            threads: threads.max(1),
            scenery: None,
            last_ms: 0.0,
        })
    }
}

/// The world objects of a simulated state: each agent's simulated footprint with its track's height.
pub fn objects_of(state: &SensorState) -> Vec<WorldObject> {
    let sc = state.scenario;
    state
        .agents
        .iter()
        .filter_map(|a| {
            let t = sc.tracks.get(a.track)?;
            let s = ObjectState {
                pose: a.bbox.center,
                velocity: a.velocity,
            };
            let (center, mut size) = track_geometry(t, &s);
            size.x = a.bbox.length;
            size.y = a.bbox.width;
            Some(WorldObject {
                track: a.track,
                class: a.class,
                center,
                size,
                yaw: a.bbox.center.heading,
                look: hash_bytes(t.id.as_bytes()),
            })
        })
        .collect()
}

impl Sensors for GroundTruthSensors {
    fn name(&self) -> String {
        format!("groundtruth {}x{}", self.height, self.width)
    }

    fn reset(&mut self, scenario: &Scenario) -> Result<()> {
        self.scenery = Some(Scenery::build(scenario, Palette::of(palette_of(scenario))));
        Ok(())
    }

    fn observe(&mut self, state: &SensorState) -> Result<Vec<CameraFrame>> {
        let t0 = Instant::now();
        let scenery = self
            .scenery
            .as_ref()
            .context("groundtruth sensors: observe before reset")?;
        let sc = state.scenario;
        let e2g = state.ego2global();
        let objects = objects_of(state);
        let frames = render_cameras(
            scenery,
            &sc.rig.cameras,
            &e2g,
            self.width,
            self.height,
            &objects,
            &RenderOptions::default(),
            self.threads,
        )?;
        let out = frames
            .into_iter()
            .zip(&sc.rig.cameras)
            .map(|(f, cam)| CameraFrame {
                camera: f.camera,
                width: self.width as u32,
                height: self.height as u32,
                rgb: Arc::new(f.rgb),
                intrinsic: cam.intrinsic_scaled(self.width as u32, self.height as u32),
                cam2ego: cam.cam2ego,
                ego2global: e2g,
            })
            .collect();
        self.last_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(out)
    }

    fn last_times(&self) -> Vec<(&'static str, f64)> {
        vec![("groundtruth_render", self.last_ms)]
    }
}
