//! `wavesplat bench`: measurements written as CSV (and plots where people would rather look):
//! `throughput` of the pipeline stages, `refine` (framerate-constrained refinement against a
//! cache on loopback), `queue` (the job queue's own speed, embedded and PostgreSQL) and `stability` (stiff and extreme numerical cases). Nothing here is
//! asserted; the tests assert the pass/fail parts.

pub mod queue;
pub mod refine;
pub mod stability;
pub mod throughput;

use anyhow::Result;
use clap::{Args, Subcommand};

/// Arguments of `wavesplat bench`.
#[derive(Args, Debug)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub which: BenchCommand,
}

/// The benchmarks.
#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Throughput of compression, packet decoding and splatting per family (CSV + table).
    Throughput(throughput::ThroughputArgs),
    /// Frame-budgeted refinement from a cache on loopback: budgets × link speeds along a view
    /// path, Q_I against time and bytes, frame-time distribution, the paper's Table 4.
    Refine(refine::RefineArgs),
    /// The job queue's speed without compression: submitting an archive, leases per second
    /// and a tiny job's latency, for the embedded store and PostgreSQL with one and two
    /// orchestrators (starts a throwaway PostgreSQL server; CSV + table).
    Queue(queue::QueueBenchArgs),
    /// Stiff and extreme numerical cases against the reference renderer (table + CSV; exits
    /// non-zero when a case fails).
    Stability(stability::StabilityArgs),
}

/// Runs the subcommand.
pub fn run(a: BenchArgs) -> Result<()> {
    match a.which {
        BenchCommand::Throughput(t) => throughput::run(t),
        BenchCommand::Refine(r) => refine::run(r),
        BenchCommand::Stability(s) => stability::run(s),
        BenchCommand::Queue(q) => queue::run(q),
    }
}
