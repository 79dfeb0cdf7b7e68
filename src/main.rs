//! `wavesplat`: the front door. Parses the command line and wires the libraries together; all
//! the work lives in the crates (`wavesplat-codec`, `wavesplat-compressor`, `wavesplat-viewer`).

/// `println!` for the commands' output that ends the process quietly (status 141, as SIGPIPE
/// would) when stdout is closed early (`wavesplat info f.wsp | head`), where `println!` panics.
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        if let Err(e) = writeln!(std::io::stdout(), $($arg)*) {
            $crate::stdout_failed(e);
        }
    }};
}

mod commands;

use anyhow::Result;
use clap::{Parser, Subcommand};

/// The log filter when neither `--log` nor RUST_LOG says otherwise.
const DEFAULT_LOG: &str = "warn,winit=error";

/// Compression-domain volume rendering by wavelet splatting (Lippert, Gross & Kurmann, EG'97).
///
/// Volumes are compressed into B-spline wavelet coefficients (`compress`), inspected (`info`),
/// decoded for checks (`decompress`) and rendered as X-ray images directly from the coefficients
/// without expanding the volume (`render`), or in a window (`view`).
#[derive(Parser, Debug)]
#[command(name = "wavesplat", version, about, long_about = None)]
struct Cli {
    /// Log filter (e.g. `info`, `debug`, `wavesplat=trace`); also read from RUST_LOG. The
    /// default shows warnings, but of the windowing library (winit) only errors: its warnings
    /// are about the display server, not about anything a user can act on.
    #[arg(long, global = true, default_value = DEFAULT_LOG)]
    log: String,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the main job: the cache, the orchestrator and a worker on loopback in one process;
    /// an archive of built-in phantoms (and any --volume) queued and compressed; every volume
    /// browsed from the cache at a frame budget (single view, multiview, depth-cued), scored
    /// against a ray-cast reference, written up in report.html (under a minute on 2 cores).
    Demo(commands::demo::DemoArgs),
    /// Compress a volume (DICOM series or multi-frame file, NIfTI, NRRD, MetaImage, a TIFF
    /// stack (multi-page file or directory of slices), a Zarr store, raw, or a built-in phantom)
    /// into a .wsp
    /// file.
    Compress(Box<commands::compress::CompressArgs>),
    /// Show a .wsp file's header, tiles, packets and size breakdown.
    Info(commands::info::InfoArgs),
    /// Decode a .wsp file to raw little-endian f32 (x fastest, channels interleaved).
    Decompress(commands::decompress::DecompressArgs),
    /// Write a .wsp file in the indexed layout for a web server, CDN or bucket: `render` and
    /// `view` then browse it by range requests (`render https://HOST/vol.wspx`).
    Publish(commands::publish::PublishArgs),
    /// Render X-ray images directly from a .wsp file's or a cache's coefficients (wavelet
    /// splatting).
    Render(Box<commands::render::RenderArgs>),
    /// Open a window on a volume (file or cache): drag to turn it, watch it sharpen within a
    /// frame-time budget (H for the keys).
    View(Box<commands::view::ViewWindowArgs>),
    /// Benchmarks: `throughput` (compress, decode, splat), `refine` (frame-budgeted refinement
    /// from a cache on loopback), `stability` (stiff and extreme numerical cases).
    Bench(commands::bench::BenchArgs),
    /// Write a built-in phantom as raw f32 or u8 (for trying the other commands).
    Phantom(commands::phantom::PhantomArgs),
    /// Run a server (`serve cache`: the gRPC coefficient cache; `serve orchestrator`: the
    /// batch job queue).
    #[command(subcommand)]
    Serve(commands::serve::ServeCommand),
    /// Talk to a coefficient cache: `ingest`, `list`, `show`, `rm`.
    #[command(subcommand)]
    Cache(commands::cache::CacheCommand),
    /// Run a compression worker: lease jobs from an orchestrator, deliver to a cache.
    Worker(commands::orchestrator::WorkerArgs),
    /// Submit a directory of volumes to an orchestrator: `archive submit`.
    #[command(subcommand)]
    Archive(commands::orchestrator::ArchiveCommand),
    /// Inspect and steer orchestrator jobs: `list`, `watch`, `cancel`, `retry`.
    #[command(subcommand)]
    Jobs(commands::orchestrator::JobsCommand),
}

fn main() {
    quiet_vulkan_device_select();
    let cli = Cli::parse();
    let mut filter = std::env::var("RUST_LOG").unwrap_or_else(|_| cli.log.clone());
    if filter == DEFAULT_LOG && matches!(cli.command, Command::Worker(_)) {
        // A worker's log is its record of work: each job's outcome (running, delivered,
        // failed) at info, which the default filter would hide.
        filter = format!("{DEFAULT_LOG},wavesplat_worker=info");
    }
    // Colour only on a terminal, and never where NO_COLOR asks for none (no-color.org): logs
    // going to files and pipes (a worker's) stay plain text.
    let colour = std::io::IsTerminal::is_terminal(&std::io::stderr())
        && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::new(filter))
        .with_writer(std::io::stderr)
        .with_ansi(colour)
        .init();
    if let Err(e) = run(cli.command) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// Mesa's Vulkan device-select layer (an implicit layer every Vulkan program loads on Linux)
/// tries a Wayland connection while wgpu looks for an adapter, and libwayland prints "error:
/// XDG_RUNTIME_DIR is invalid or not set in the environment" twice where there is no session
/// directory (a server, a container, a CI runner): it reads as our failure. Without such a
/// directory there is no compositor whose GPU the layer could prefer, so it is turned off
/// (`NODEVICE_SELECT`), unless the user chose a device through it (`MESA_VK_DEVICE_SELECT`) or
/// set the switch themselves. Runs first in `main`, before any thread exists.
fn quiet_vulkan_device_select() {
    let runtime_dir_ok = std::env::var_os("XDG_RUNTIME_DIR")
        .is_some_and(|d| !d.is_empty() && std::path::Path::new(&d).is_dir());
    if !runtime_dir_ok
        && std::env::var_os("NODEVICE_SELECT").is_none()
        && std::env::var_os("MESA_VK_DEVICE_SELECT").is_none()
    {
        std::env::set_var("NODEVICE_SELECT", "1");
    }
}

fn run(command: Command) -> Result<()> {
    match command {
        Command::Demo(a) => commands::demo::run(a),
        Command::Compress(a) => commands::compress::run(*a),
        Command::Info(a) => commands::info::run(a),
        Command::Decompress(a) => commands::decompress::run(a),
        Command::Publish(a) => commands::publish::run(a),
        Command::Phantom(a) => commands::phantom::run(a),
        Command::Bench(a) => commands::bench::run(a),
        Command::Render(a) => commands::render::run(*a),
        Command::View(a) => commands::view::run(*a),
        Command::Serve(c) => commands::serve::run(c),
        Command::Cache(c) => commands::cache::run(c),
        Command::Worker(a) => commands::orchestrator::run_worker(a),
        Command::Archive(c) => commands::orchestrator::run_archive(c),
        Command::Jobs(c) => commands::orchestrator::run_jobs(c),
    }
}

/// Ends the process after a failed write to stdout. When the reader went away (`| head`), it
/// ends silently with status 141, what a shell reports for a program killed by SIGPIPE: the
/// command did not finish its work (an `archive submit` stops submitting, a `jobs watch` never
/// reports its failures), so it must not claim success. Any other failure is an error.
/// Standard output for the libraries' reports: a closed pipe or a failed write ends the
/// process as [`outln!`] does.
pub(crate) struct Stdout;

impl std::io::Write for Stdout {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        std::io::stdout().write(buf).or_else(|e| stdout_failed(e))
    }

    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stdout().flush().or_else(|e| stdout_failed(e))
    }
}

pub(crate) fn stdout_failed(e: std::io::Error) -> ! {
    if e.kind() == std::io::ErrorKind::BrokenPipe {
        std::process::exit(141);
    }
    eprintln!("error: writing to stdout: {e}");
    std::process::exit(1);
}
