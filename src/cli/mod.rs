//! clap definitions and dispatch. One file per subcommand.
use clap::{Parser, Subcommand};

mod sim;

#[derive(Parser, Debug)]
#[command(name = "b2dr", version, about = "Reactive closed-loop driving evaluation with a generative renderer")]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Closed-loop simulation of a planner over scenarios, with the nuPlan closed-loop score.
    Sim(sim::SimArgs),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Sim(a) => sim::run(a),
    }
}
