//! `b2dr export-training`: training samples (target, previous frame, two hierarchical references, 15 masks,
//! camera matrices) as safetensors shards + index.json; format in docs/training_data.md.
use anyhow::Result;
use b2dr::world::export::{export_training, ExportOptions};
use b2dr::world::view::{parse_offset, parse_size};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    /// Scenario(s), repeatable: builtin:LAYOUT[:seed[:n_vehicles[:palette]]], a ScenarioNet .json, a folder.
    #[arg(long, required = true, num_args = 1..)]
    pub scenario: Vec<String>,
    /// Output directory (index.json + shard_NNNNN.safetensors).
    #[arg(long)]
    pub out: PathBuf,
    /// Render size HEIGHTxWIDTH.
    #[arg(long, default_value = "112x200")]
    pub size: String,
    /// Target frames per scenario (each exported once per offset).
    #[arg(long, default_value_t = 16)]
    pub samples_per_scenario: usize,
    /// Ego offsets DX,DY,DYAW (m, m, degrees) in the ego frame, separated by ';' (e.g. "0,0,0;0,1.5,0;0,-1.5,5");
    /// every target is exported once per offset; 0,0,0 = the logged pose.
    #[arg(long, default_value = "0,0,0", allow_hyphen_values = true)]
    pub offsets: String,
    /// Seed of the sample and reference choice.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Cameras (comma-separated; default: the rig's six).
    #[arg(long, value_delimiter = ',')]
    pub cameras: Vec<String>,
    /// Samples per shard.
    #[arg(long, default_value_t = 64)]
    pub shard_samples: usize,
    /// Only targets whose previous frame has a previous frame, with that frame's image (`prev2`) and pose
    /// (`prev2_ego2global`) and the previous frame's own layout (`prev_masks_packed`): for
    /// `train --self-prev-pose chain`.
    #[arg(long)]
    pub prev_chain: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

pub fn run(a: ExportArgs) -> Result<()> {
    let (height, width) = parse_size(&a.size)?;
    let offsets = a
        .offsets
        .split(';')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(parse_offset)
        .collect::<Result<Vec<_>>>()?;
    let s = export_training(&ExportOptions {
        scenarios: a.scenario,
        out: a.out,
        height,
        width,
        samples_per_scenario: a.samples_per_scenario,
        offsets,
        seed: a.seed,
        cameras: a.cameras,
        shard_samples: a.shard_samples,
        progress: !a.quiet,
        prev_chain: a.prev_chain,
    })?;
    println!(
        "{} samples in {} shards ({} skipped: off the map) -> {}",
        s.samples,
        s.shards,
        s.skipped_off_map,
        s.index.display()
    );
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct ExportPlannerArgs {
    /// Synthetic scenario(s), repeatable: builtin:LAYOUT[:seed[:n_vehicles[:palette]]] (comma lists allowed).
    #[arg(long, required = true, num_args = 1..)]
    pub scenario: Vec<String>,
    /// Output directory (index.json + one safetensors file per scenario).
    #[arg(long)]
    pub out: PathBuf,
    /// Image size HEIGHTxWIDTH (the renderer's size the planner will see in closed loop).
    #[arg(long, default_value = "112x200")]
    pub size: String,
    /// Cameras (comma-separated; default CAM_FRONT).
    #[arg(long, value_delimiter = ',')]
    pub cameras: Vec<String>,
    /// Ego displacements LATERAL_M,YAW_DEG separated by ';'; each planner step is exported once per entry.
    #[arg(
        long,
        default_value = "0,0;1,0;-1,0;0,6;0,-6",
        allow_hyphen_values = true
    )]
    pub offsets: String,
    /// Planner period in log steps (5 = 2 Hz).
    #[arg(long, default_value_t = 5)]
    pub every: usize,
    #[arg(long)]
    pub quiet: bool,
}

pub fn run_planner(a: ExportPlannerArgs) -> Result<()> {
    use b2dr::eval::planner_data::{export, PlannerDataOptions};
    let size = parse_size(&a.size).map_err(|e| e.context("--size"))?;
    let offsets = a
        .offsets
        .split(';')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            let v: Vec<f64> = s
                .split(',')
                .map(|x| x.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|e| anyhow::anyhow!("--offsets {s:?}: {e}"))?;
            anyhow::ensure!(
                v.len() == 2 && v.iter().all(|x| x.is_finite()),
                "--offsets {s:?}: expected LATERAL_M,YAW_DEG"
            );
            Ok((v[0], v[1].to_radians()))
        })
        .collect::<Result<Vec<_>>>()?;
    let s = export(&PlannerDataOptions {
        scenarios: a.scenario,
        out: a.out.clone(),
        size,
        cameras: a.cameras,
        offsets,
        every: a.every,
        progress: !a.quiet,
    })?;
    println!(
        "{} samples in {} files ({} skipped: off the map) -> {}",
        s.samples,
        s.files,
        s.skipped_off_map,
        a.out.join("index.json").display()
    );
    Ok(())
}
