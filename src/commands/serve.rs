//! `wavesplat serve …`: which service to run; each service's arguments and start-up live in its
//! own module (`cache`, `orchestrator`).

use anyhow::Result;
use clap::Subcommand;

/// `wavesplat serve …`: run a service.
#[derive(Subcommand, Debug)]
pub enum ServeCommand {
    /// The coefficient cache (gRPC): stores .wsp volumes, streams view-dependent refinement.
    Cache(super::cache::ServeCacheArgs),
    /// The batch job orchestrator (gRPC): a durable queue of compression jobs for workers.
    Orchestrator(super::orchestrator::ServeOrchestratorArgs),
}

/// Runs the service.
pub fn run(cmd: ServeCommand) -> Result<()> {
    match cmd {
        ServeCommand::Cache(a) => super::cache::run_serve(a),
        ServeCommand::Orchestrator(a) => super::orchestrator::run_serve(a),
    }
}
