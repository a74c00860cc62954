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
