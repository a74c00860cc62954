//! The synthetic ground-truth world (docs/world.md of the spec): scenarios whose cameras can be rendered
//! exactly from any pose, on the CPU. Never imports `ash` or `crate::vk`.
//!
//! - [`town`]: the built-in scenarios (`builtin:LAYOUT[...]`), generated with the simulator's IDM agents
//!   (hence this layer sits above `sim`).
//! - [`scenery`], [`objects`], [`shapes`], [`palette`]: what the world is made of.
//! - [`render`]: the deterministic CPU renderer (RGB, depth, class id, instance id per camera).
//! - [`images`]: the image store resolving a log's recorded images (`builtin://` paths are rendered on demand and
//!   cached in memory; files are read from disk).
//! - [`step_views`]: the projection inputs of one log step of any scenario (`b2dr project --scenario`).
//! - [`view`]: the `b2dr world` command's logic (ground truth of any state, mosaics, mask overlays).
//! - [`export`]: training samples (`b2dr export-training`, docs/training_data.md).
pub mod export;
pub mod images;
pub mod objects;
pub mod palette;
pub mod render;
pub mod scenery;
pub mod shapes;
pub mod step_views;
pub mod town;
pub mod view;

use crate::scene::camera::Camera;
use crate::scene::import::{nuplan, nuscenes, scenarionet, BuiltinSpec, DayPalette, Source};
use crate::scene::Scenario;
use anyhow::Result;
use glam::DMat4;

pub use objects::{objects_at, WorldObject};
pub use palette::{Palette, SemanticClass};
pub use render::{render_cameras, CameraFrame, RenderOptions};
pub use scenery::Scenery;

/// Loads one scenario source (built-in towns are generated, files imported).
pub fn load(src: &Source) -> Result<Scenario> {
    match src {
        Source::Builtin(spec) => Ok(town::generate(spec)),
        Source::File(p) => scenarionet::load_file(p),
        Source::Nuscenes(n) => nuscenes::load(n),
        Source::Nuplan(n) => nuplan::load(n),
    }
}

/// Resolves a `--scenario` argument and loads every scenario it names.
pub fn load_all(spec: &str) -> Result<Vec<Scenario>> {
    crate::scene::import::resolve(spec)?
        .iter()
        .map(load)
        .collect()
}

/// The day palette of a scenario: the one its `builtin:` spec names, else one drawn from the scenery seed.
pub fn palette_of(sc: &Scenario) -> DayPalette {
    let named = sc
        .source
        .strip_prefix("builtin:")
        .and_then(|r| BuiltinSpec::parse(r, &sc.source).ok())
        .and_then(|b| b.palette);
    named.unwrap_or_else(|| {
        // Noon is twice as likely as each other palette.
        let opts = [
            DayPalette::Noon,
            DayPalette::Noon,
            DayPalette::Morning,
            DayPalette::Evening,
            DayPalette::Overcast,
        ];
        opts[(palette::mix64(scenery::scenery_seed(sc)) % opts.len() as u64) as usize]
    })
}

/// A scenario's renderable world: its static scenery (built once) plus the scenario it belongs to.
pub struct World<'a> {
    pub scenario: &'a Scenario,
    pub scenery: Scenery,
}

impl<'a> World<'a> {
    pub fn new(scenario: &'a Scenario) -> World<'a> {
        let pal = Palette::of(palette_of(scenario));
        World {
            scenario,
            scenery: Scenery::build(scenario, pal),
        }
    }

    /// Ground truth of `cams` at `width x height` with the ego at `ego2global` and the objects of log step
    /// `step` (every camera sees the same instant).
    pub fn render_step(
        &self,
        cams: &[Camera],
        ego2global: &DMat4,
        step: usize,
        width: usize,
        height: usize,
        threads: usize,
    ) -> Result<Vec<CameraFrame>> {
        anyhow::ensure!(
            step < self.scenario.len(),
            "step {step} is out of range: the log of {} has {} steps (0..={})",
            self.scenario.name,
            self.scenario.len(),
            self.scenario.len().saturating_sub(1)
        );
        let objects = objects_at(self.scenario, step);
        render_cameras(
            &self.scenery,
            cams,
            ego2global,
            width,
            height,
            &objects,
            &RenderOptions::default(),
            threads,
        )
    }
}
