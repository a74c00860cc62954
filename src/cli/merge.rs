//! `b2dr merge`: shard folders of `b2dr sim` / `b2dr run` into one summary (see `b2dr::eval::batch::merge`).
use std::path::PathBuf;

use anyhow::Result;

#[derive(clap::Args, Debug)]
pub struct MergeArgs {
    /// The shard folders (the --out of each `--shard K/N` run; all N of them)
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// Folder for the merged metrics.json and config.json
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: MergeArgs) -> Result<()> {
    let s = b2dr::eval::batch::merge(&a.dirs, &a.out)?;
    eprintln!(
        "{} shard(s), {} scenario(s), {} {:.4} -> {}",
        a.dirs.len(),
        s["scenarios"].as_array().map(|v| v.len()).unwrap_or(0),
        s["cls_kind"].as_str().unwrap_or("CLS"),
        s["cls"].as_f64().unwrap_or(0.0),
        a.out.join("metrics.json").display()
    );
    Ok(())
}
