//! clap definitions and dispatch. One file per subcommand.
use clap::{Parser, Subcommand};

mod project;

#[derive(Parser, Debug)]
#[command(
    name = "b2dr",
    version,
    about = "Reactive closed-loop driving evaluation with a generative renderer"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Project a keyframe's boxes (and a map) into its cameras: masks, overlays, projection.json.
    Project(project::ProjectArgs),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Project(a) => project::run(a),
    }
}
