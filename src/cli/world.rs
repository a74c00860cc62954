//! `b2dr world`: the ground truth of one state of a scenario (the logged ego at a step, or displaced in the ego
//! frame), per-camera PNGs, a mosaic with the bird's-eye view, and overlays of b2dr's projected masks.
use anyhow::{ensure, Result};
use b2dr::scene::geometry::Pose2;
use b2dr::world::view::{parse_offset, parse_size, view, write_view, ViewRequest};
use b2dr::world::World;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct WorldArgs {
    /// Scenario: builtin:LAYOUT[:seed[:n_vehicles[:palette]]] or a ScenarioNet .json file (one scenario).
    #[arg(long, default_value = "builtin:town")]
    pub scenario: String,
    /// Log step (10 Hz) of the ego pose and the objects.
    #[arg(long, default_value_t = 0)]
    pub step: usize,
    /// Ego displacement in the ego frame: DX,DY,DYAW (metres forward, metres left, degrees counter-clockwise).
    #[arg(long, allow_hyphen_values = true)]
    pub offset: Option<String>,
    /// Render size HEIGHTxWIDTH.
    #[arg(long, default_value = "224x400")]
    pub size: String,
    /// Cameras (comma-separated rig names; default: all).
    #[arg(long, value_delimiter = ',')]
    pub cameras: Vec<String>,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: WorldArgs) -> Result<()> {
    let (height, width) = parse_size(&a.size)?;
    let offset = match &a.offset {
        Some(s) => parse_offset(s)?,
        None => Pose2::default(),
    };
    let mut scs = b2dr::world::load_all(&a.scenario)?;
    ensure!(
        scs.len() == 1,
        "--scenario {:?} names {} scenarios; b2dr world takes one",
        a.scenario,
        scs.len()
    );
    let sc = scs.remove(0);
    let world = World::new(&sc);
    let req = ViewRequest {
        step: a.step,
        offset,
        height,
        width,
        cameras: a.cameras,
    };
    let out = view(&sc, &world, &req)?;
    write_view(&out, &sc, a.step, &a.out)?;
    println!(
        "{}: step {} ego ({:.2}, {:.2}, {:.1} deg), {} cameras at {height}x{width} -> {}",
        sc.name,
        a.step,
        out.ego.x,
        out.ego.y,
        out.ego.heading.to_degrees(),
        out.frames.len(),
        a.out.display()
    );
    Ok(())
}
