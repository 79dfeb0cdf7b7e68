//! `wavesplat bench throughput`: arguments and wiring; the benchmark is
//! `wavesplat_harness::throughput`.

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_compressor::reader::read_volume;
use wavesplat_harness::throughput::{run as bench, ThroughputBench};

/// Arguments of `wavesplat bench throughput`.
#[derive(Args, Debug)]
pub struct ThroughputArgs {
    /// Volume file (NIfTI, NRRD, MetaImage, DICOM directory or file); default: the Shepp–Logan
    /// phantom of --size³.
    pub input: Option<PathBuf>,
    /// Phantom edge length when no input is given.
    #[arg(long, default_value_t = 128)]
    pub size: usize,
    /// Fraction of coefficients kept.
    #[arg(long, default_value_t = 0.05)]
    pub fraction: f64,
    /// Repetitions per measurement (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    /// CSV output.
    #[arg(short, long, default_value = "bench.csv")]
    pub output: PathBuf,
}

/// Runs the subcommand.
pub fn run(a: ThroughputArgs) -> Result<()> {
    let volume = match &a.input {
        Some(p) => read_volume(p, None).with_context(|| format!("reading {}", p.display()))?,
        None => Phantom::SheppLogan
            .try_generate([a.size; 3])
            .with_context(|| format!("--size {}", a.size))?,
    };
    let settings = ThroughputBench {
        volume,
        fraction: a.fraction,
        repeat: a.repeat,
        output: a.output,
    };
    bench(&settings, &mut crate::Stdout)
}
