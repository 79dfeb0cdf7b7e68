//! `wavesplat bench refine`: arguments and wiring; the benchmark (what it walks, measures and
//! writes) is `wavesplat_harness::refine`.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_harness::refine::{run as bench, RefineBench};
/// Arguments of `wavesplat bench refine`.
#[derive(Args, Debug)]
pub struct RefineArgs {
    /// Volume file (NIfTI, NRRD, MetaImage, DICOM directory); default: a Shepp–Logan phantom.
    #[arg(long)]
    pub volume: Option<PathBuf>,
    /// Phantom edge when no volume is given (X×X×3X/4).
    #[arg(long, default_value_t = 96)]
    pub size: usize,
    /// Image side in pixels.
    #[arg(long, default_value_t = 256)]
    pub image: usize,
    /// Frame budgets in milliseconds, comma-separated.
    #[arg(long, default_value = "8,16.6,33,100")]
    pub budgets: String,
    /// Link speeds in Mbit/s, comma-separated (`unlimited` or 0 for no limit).
    #[arg(long, default_value = "unlimited,100,10,1")]
    pub links: String,
    /// Most frames to rest at a view waiting for convergence.
    #[arg(long, default_value_t = 300)]
    pub rest_frames: usize,
    /// Skip the paper's Table 4 (twelve compressions of a 128³ RGB phantom).
    #[arg(long)]
    pub no_table4: bool,
    /// Output directory.
    #[arg(long, default_value = "bench-refine")]
    pub out: PathBuf,
    #[command(flatten)]
    pub backend: super::super::BackendArgs,
}

fn parse_list(s: &str, what: &str) -> Result<Vec<f64>> {
    s.split(',')
        .map(|t| {
            let t = t.trim();
            if t.eq_ignore_ascii_case("unlimited") || t.eq_ignore_ascii_case("inf") {
                return Ok(0.0);
            }
            let v: f64 = t
                .parse()
                .with_context(|| format!("{what}: {t:?} is not a number"))?;
            if !(v.is_finite() && v >= 0.0) {
                bail!("{what}: {t:?} must be a non-negative number");
            }
            Ok(v)
        })
        .collect()
}

/// Runs the subcommand.
pub fn run(a: RefineArgs) -> Result<()> {
    let budgets = parse_list(&a.budgets, "--budgets")?;
    if budgets.iter().any(|b| *b <= 0.0) {
        bail!("--budgets must be positive milliseconds");
    }
    let links = parse_list(&a.links, "--links")?;
    let volume: Volume = match &a.volume {
        Some(p) => wavesplat_compressor::reader::read_volume(p, None)
            .with_context(|| format!("reading {}", p.display()))?,
        None => Phantom::SheppLogan
            .try_generate([a.size, a.size, (3 * a.size / 4).max(1)])
            .with_context(|| format!("--size {}", a.size))?,
    };
    let settings = RefineBench {
        volume,
        budgets,
        links,
        image: a.image,
        rest_frames: a.rest_frames,
        table4: !a.no_table4,
        out: a.out,
        backend: a.backend.choice(),
    };
    bench(&settings, &mut crate::Stdout)
}
