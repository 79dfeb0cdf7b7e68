//! `wavesplat demo`: the whole system in one process, on a fresh machine without a GPU. It
//! starts the cache, the orchestrator and a worker on loopback, submits an archive (an
//! intensity phantom, a classified RGB phantom and any volumes given with `--volume`), waits
//! for the compression jobs, then browses each volume from the cache with the headless viewer
//! under a frame budget along a short path (rest, a 90° turn, rest) in three scenes (single
//! view, multiview, depth cueing). Every frame is scored against the reference ray caster's
//! image of the original volume; it writes frame PNGs, a CSV per run and `report.html` with
//! charts of the error against time and bytes and a table of figures beside each.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;
use wavesplat_harness::demo::{run as demo, Demo};

/// Arguments of `wavesplat demo`.
#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Output directory (frames, CSVs, charts, report.html). Given explicitly, it also keeps
    /// the services' databases (DIR/db) so the cache can be served again afterwards; by default
    /// they live in a temporary directory and outputs go to ./wavesplat-demo.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Also compress and browse this volume (NIfTI, NRRD, MetaImage, a DICOM directory, or
    /// raw named NAME_XxYxZ_DTYPE[_rgb].raw); repeatable.
    #[arg(long = "volume")]
    pub volumes: Vec<PathBuf>,
    /// Edge of the built-in phantoms in voxels (the intensity phantom is X×X×(3X/4), so it is
    /// not a cube).
    #[arg(long, default_value_t = 80)]
    pub size: usize,
    /// Image side in pixels (per view for multiview).
    #[arg(long, default_value_t = 192)]
    pub image: usize,
    /// Frame budget in milliseconds.
    #[arg(long, default_value_t = 16.6)]
    pub frame_ms: f64,
    /// Most frames of the first rest at a view waiting for convergence (the report says "rest
    /// limit reached, N pending" when it ends there); the final rest after the turn runs until
    /// converged, at most ten times this.
    #[arg(long, default_value_t = 240)]
    pub rest_frames: usize,
    /// Compression threads of the worker (0: one per core).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

/// Runs the subcommand.
pub fn run(a: DemoArgs) -> Result<()> {
    let settings = Demo {
        out: a.out,
        volumes: a.volumes,
        size: a.size,
        image: a.image,
        frame_ms: a.frame_ms,
        rest_frames: a.rest_frames,
        threads: a.threads,
    };
    demo(&settings, &mut crate::Stdout)
}
