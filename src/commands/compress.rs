//! `wavesplat compress`: volume file or phantom in, `.wsp` out, with a summary of what was kept
//! and where the bytes went.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use wavesplat_codec::family::Family;
use wavesplat_codec::format::CoderKind;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::volume::{Volume, MAX_VOXELS};
use wavesplat_compressor::bricked::{
    compress_bricked_to, AutoBrick, BrickReason, BrickSource, BrickStage,
};
use wavesplat_compressor::checkpoint::{Checkpoint, Resumed};
use wavesplat_compressor::colorspace::ColorSpaceKind;
use wavesplat_compressor::encode::{
    compress, CompressOptions, Compressed, Effort, Stage, Target, TileChoice,
};
use wavesplat_compressor::order::Clustering;
use wavesplat_compressor::phantom::{beating, Phantom, PhantomVolume};
use wavesplat_compressor::reader::region::RegionReader;
use wavesplat_compressor::reader::{read_volume_channel, Endian, RawDtype, RawSpec};
use wavesplat_compressor::series::{TimePointSource, VolumeSeries};
use wavesplat_harness::console::Progress;

/// Arguments of `wavesplat compress`.
#[derive(Args, Debug)]
pub struct CompressArgs {
    /// Input volume: a DICOM series directory or DICOM file, a TIFF stack (a multi-page .tif,
    /// or a directory of .tif slices in the natural order of their names), .nrrd / .nhdr, .mha / .mhd
    /// (a detached header's samples in one file, or in many: a LIST or a slice%03d.raw pattern),
    /// .nii / .nii.gz, a .hdr (+ the .img beside it: a NIfTI-1 pair or Analyze 7.5; .hdr.gz,
    /// .img.gz too), a Zarr store (a directory: a v2 or v3 array, or an OME-Zarr image), or raw
    /// samples: named `NAME_XxYxZ_DTYPE[_rgb][_be].raw` as `archive
    /// submit` reads them (e.g. `head_256x256x128_u16.raw`), or any name with --dims and
    /// --dtype. Omit it to use --phantom.
    pub input: Option<PathBuf>,
    /// Output .wsp file.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Use a built-in phantom instead of a file: shepp-logan, spheres, rgb-head, constant,
    /// zero, ct, blobs, noise; or beating, a time series (a heart whose size follows one beat
    /// over the series, in a static torso, with noise).
    #[arg(long, conflicts_with = "input")]
    pub phantom: Option<String>,
    /// Raw input dimensions X,Y,Z (x fastest), or X,Y,Z,T for a raw time series of T time
    /// points one after another; phantom size with --phantom (default 64,64,64; the beating
    /// phantom takes X,Y,Z,T, default 64,64,16,16).
    #[arg(long, value_parser = super::parse_series_dims)]
    pub dims: Option<super::SeriesDims>,
    /// From a time series (a 4D NIfTI, a raw file with --dims X,Y,Z,T, a directory of one
    /// volume per time step), compress only time point N (counting from 0) as one volume.
    #[arg(long, value_name = "N")]
    pub time_point: Option<usize>,
    /// Compress only channel C (counting from 0) as a volume of one channel: of a Zarr array
    /// with a channel axis (OME-Zarr's `c`: fluorescence channels, say) or a TIFF storing
    /// channels as planes of their own (an ImageJ hyperstack, an OME-TIFF), which are refused
    /// without it when they hold several; of an RGB volume, its red, green or blue samples.
    #[arg(long, value_name = "C", conflicts_with = "phantom")]
    pub channel: Option<usize>,
    /// A time series is compressed whole into one file: its time points go through a Haar
    /// wavelet along time in groups of G (a power of two), so what a group's time points share
    /// is stored once; a viewer of one time point reads its group's bytes only. 1 compresses
    /// each time point alone.
    #[arg(long, value_name = "G", default_value_t = 8)]
    pub time_group: usize,
    /// Raw sample type: u8, i8, u16, i16, u32, i32, u64, i64, f32, f64 (read as f32 values).
    #[arg(long)]
    pub dtype: Option<String>,
    /// Raw byte order: little or big.
    #[arg(long, default_value = "little")]
    pub endian: String,
    /// Raw channels: 1 (intensity) or 3 (RGB, interleaved per voxel).
    #[arg(long, default_value_t = 1)]
    pub channels: usize,
    /// Raw voxel spacing X,Y,Z in mm (default 1,1,1); formats with a header give their own.
    #[arg(long, value_parser = parse_spacing)]
    pub spacing: Option<[f32; 3]>,
    /// Raw input with a fixed-size header of another program's before the samples: skip its N
    /// bytes (the file must then be N bytes longer than the samples).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub header_bytes: u64,
    /// Wavelet family: haar, linear, cubic.
    #[arg(long, default_value = "linear")]
    pub family: String,
    /// Decomposition depth M (default: min(6, max) for Haar, 3 for linear, 2 for cubic;
    /// max = ceil(log2(smallest dimension))). With --target-bytes and no depth given, that
    /// default and one level less are both tried and the one whose X-ray views of the volume
    /// come out closer is kept (the shallower one usually wins at higher rates); one level
    /// less again is tried while the shallowest wins and the file nearly affords its coarse
    /// band (M = 1 at ~1 bit per voxel); while the default or a deeper depth wins, one level
    /// more is tried, up to 5 for linear, 3 for cubic (large volumes smooth at their finest
    /// scales: the MRI resampled to 512³ takes M = 5, +5.5 dB).
    #[arg(long)]
    pub levels: Option<usize>,
    /// Zero margin (voxels) around the volume before the periodic transform. Default: none when
    /// the data's faces cut through its content (zeros against them cost coefficients), else
    /// half the coarsest wavelet support, ceil((2j-1)·2^M/2). Every margin renders exactly
    /// (the viewer clips the basis functions across a face to the volume's box).
    #[arg(long)]
    pub margin: Option<usize>,
    /// Colour space for RGB volumes: rgb, yiq, pca.
    #[arg(long, default_value = "pca")]
    pub colorspace: String,
    /// Quantization bits P (1..=16) of the delta coder (paper eq. 15); for the sigmap and fast
    /// coders keeping every coefficient, the finest step is 2^-P of a band's largest magnitude.
    #[arg(long, default_value_t = 8)]
    pub bits: u8,
    /// Entropy coder: sigmap (octree significance maps, arithmetic coded; smallest files),
    /// fast (the same maps and contexts with static rANS tables: packets decode ~3.8× faster,
    /// for 4–10 % more bytes at the same coefficients, 0.2–1 dB less Q_I at the same bytes),
    /// range (the paper's syntax, arithmetic coded) or huffman (the paper's syntax and
    /// static tables).
    #[arg(long, default_value = "sigmap")]
    pub coder: String,
    /// Quantizer step of the sigmap and fast coders relative to each band's smallest kept
    /// magnitude; keeping every coefficient (--lossless-selection, a slice's default), the step
    /// is also at most 2^-P (--bits) of the band's largest.
    #[arg(long, default_value_t = 1.0)]
    pub step: f64,
    /// Plain format version to write: 15 (the fast coder's occupancy contexts and steps in
    /// half octaves); 14, which readers built before version 15 read too (the same file for
    /// every coder but --coder fast: 1–3 % more bytes); 13, which readers built before version
    /// 14 read too (--coder fast with prefix codes instead of rANS: a few per cent more bytes
    /// again); 12, which
    /// readers built before version 13 read too (the same packet syntax, a header larger by 100–250 bytes:
    /// it matters for small files and small bricks); or 8, which readers built before version
    /// 12 read too (its sigmap packets start their models at ½: 2–5 % more bytes at the same
    /// coefficients)
    #[arg(long, default_value_t = wavesplat_codec::format::VERSION)]
    pub format_version: u16,
    /// Compression effort: fast (the depth predicted from the rate instead of compared, one
    /// refit of the kept set by one conjugate-gradient step; the bricks of a bricked volume
    /// are not refined), default (depths compared, three refinement rounds) or best
    /// (more refinement rounds and iterations). --levels, --refine-rounds,
    /// --refine-iterations and --no-refine given too override it. What each costs and buys:
    /// BENCHMARKS.md, "Compression effort".
    #[arg(long, default_value = "default", value_parser = parse_effort)]
    pub effort: Effort,
    /// Rounds of least-squares refinement of the kept set (iterative hard thresholding with
    /// conjugate-gradient refits; splines only). 0 refits the oracle's selection only;
    /// --no-refine sends the oracle's exact coefficients, as the paper does (default 3).
    #[arg(long)]
    pub refine_rounds: Option<usize>,
    /// Conjugate-gradient iterations per refit of the refinement (default 2).
    #[arg(long)]
    pub refine_iterations: Option<usize>,
    /// Send the oracle's coefficients unchanged (no least-squares refinement): several times
    /// faster to compress, for less X-ray quality (MNI at 1.25 %: 0.86 instead of 1.7 s,
    /// 0.46 s with --levels 2; 89.5 instead of 92.3 dB Q_I). --refine-rounds 0 keeps most of
    /// the refinement's gain (92.1 dB) in 1.4 s.
    #[arg(long)]
    pub no_refine: bool,
    /// Keep compression within this working memory (bytes, or with a K, M or G suffix: `8G`);
    /// default: the memory available now. A volume file that does not fit whole is compressed
    /// as bricks that do (see --brick), one per thread, and so is a phantom (generated brick by
    /// brick); if none fits, it is refused with a clear error instead of running out of
    /// memory.
    #[arg(long, value_parser = super::parse_bytes)]
    pub memory_limit: Option<u64>,
    /// What to keep.
    #[command(flatten)]
    pub keep: super::TargetArgs,
    /// Split the volume into bricks of at most N voxels a side (each axis in near-equal
    /// parts), each compressed on its own and read from the file brick by brick (raw, NIfTI,
    /// NRRD, MetaImage, TIFF stacks, Zarr arrays and DICOM series without loading the whole; a
    /// phantom generated a
    /// brick at a time), written as one bricked file (format version 11); the coded bricks wait
    /// in a temporary file beside the output (about the output's size, twice that during a
    /// byte target's search), so memory stays about one brick per thread whatever the file's
    /// size; without refinement (--effort fast) each brick's top coefficients, kept from its
    /// first pass so that it is not transformed again, go there too beyond 512 MB of memory
    /// (8 bytes a coefficient, 8 times the brick's share; at most a quarter of the free
    /// space). The target is the whole's: one score threshold across all bricks. For
    /// volumes larger than memory or than one transform (2^31 voxels); `render` and `info`
    /// read the result (linear and haar families). Default: whole, unless the volume does not
    /// fit --memory-limit or has more than 2^31 voxels: then bricks of 256, 128, 64 or 32, the
    /// largest that fit.
    #[arg(long, value_name = "N")]
    pub brick: Option<usize>,
    /// Start a bricked compression over, discarding the checkpoint of an interrupted run. By
    /// default a bricked compression keeps its plan and each brick as it finishes in
    /// OUTPUT.checkpoint/ beside the output (about the output's size, once per trial of a byte
    /// target's search; without refinement also each brick's kept top, 8 bytes a coefficient
    /// within a quarter of the free disk, so that a run again codes the bricks scored before
    /// the interruption without transforming them) and removes it once the file is written;
    /// the same command run again
    /// after an interruption (a kill, a reboot, a full disk) goes on from there and writes the
    /// same file. A checkpoint of another input or other options is never used: a run again
    /// first reads the whole input and compares its digest with the one the interrupted run
    /// took (a run stopped before its digest was kept starts over).
    #[arg(long)]
    pub no_resume: bool,
    /// Tile edge in voxels (rounded up to a multiple of 2^M); default: chosen from the size.
    #[arg(long, conflicts_with = "single_sequence")]
    pub tile: Option<usize>,
    /// One tile and one layer: the paper's single global significance-ordered sequence.
    #[arg(long)]
    pub single_sequence: bool,
    /// Number of score layers (packets per tile, after the coarse layer); default: chosen from
    /// the size.
    #[arg(long)]
    pub layers: Option<usize>,
    /// Each quality layer holds G times the coefficients of all layers before it (G > 1). The
    /// default 16 makes the smallest files; 4 streams a finer coarse-to-fine progression in file
    /// order for ~8–11 % more bytes.
    #[arg(long, value_name = "G", default_value_t = wavesplat_compressor::encode::LAYER_GROWTH)]
    pub layer_growth: f64,
    /// Leave out the coarse layer. By default each tile's coarsest band (the scaling band) is a
    /// layer of its own, sent first, so that a stream's first packets draw a coarse picture of
    /// the whole volume; this writes the score layers alone, as format version 7 did.
    #[arg(long)]
    pub no_coarse_layer: bool,
    /// Spatial clustering radius in voxels (0 disables clustering; paper Fig. 11).
    #[arg(long, default_value_t = 4)]
    pub cluster_radius: u32,
    /// A neighbour is taken next if its score is at least this fraction of the best remaining.
    #[arg(long, default_value_t = 0.5)]
    pub cluster_threshold: f64,
}

/// What `compress` reads: a generated phantom, or a file (with its raw layout when it is raw).
enum Input {
    /// A phantom and its dimensions (generated whole by [`load`], brick by brick when bricked).
    Phantom(PhantomVolume),
    File {
        path: PathBuf,
        raw: Option<RawSpec>,
        /// The one channel read (`--channel`).
        channel: Option<usize>,
    },
}

fn load(a: &CompressArgs) -> Result<Volume> {
    match input(a)? {
        Input::Phantom(p) => p.phantom.try_generate(p.dims.map(|d| d as usize)).context(
            "generating the phantom (give --brick N for a phantom larger than one volume)",
        ),
        Input::File { path, raw, channel } => read_volume_channel(&path, raw.as_ref(), channel)
            .map_err(|e| super::read_error(&path, e)),
    }
}

fn input(a: &CompressArgs) -> Result<Input> {
    if let Some(name) = &a.phantom {
        let p = Phantom::from_name(name).with_context(|| {
            format!(
                "unknown phantom {name:?}; choose one of {:?}",
                Phantom::names()
            )
        })?;
        return Ok(Input::Phantom(PhantomVolume {
            phantom: p,
            dims: a.dims.map_or([64, 64, 64], |d| d.xyz).map(|d| d as u64),
        }));
    }
    let Some(input) = &a.input else {
        bail!("give an input file or --phantom NAME");
    };
    let mut head = [0u8; 4];
    if std::fs::File::open(input)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
        .is_ok()
        && &head == wavesplat_codec::format::MAGIC
    {
        bail!(
            "{} is already a compressed wavesplat volume: render, view, info or decompress it \
             (compress reads DICOM, NIfTI, NRRD, MetaImage, TIFF, Zarr and raw volumes)",
            input.display()
        );
    }
    let raw = match (&a.dims, &a.dtype) {
        (Some(d), Some(t)) => {
            let mut spec = RawSpec::new(d.xyz, RawDtype::from_name(t)?);
            spec.time_points = d.t.unwrap_or(1);
            spec.endian = Endian::from_name(&a.endian)?;
            spec.channels = a.channels;
            spec.header_bytes = a.header_bytes;
            if let Some(s) = a.spacing {
                spec.spacing = s;
            }
            Some(spec)
        }
        (None, None) => {
            // A raw file named by the archive's convention (`NAME_XxYxZ_DTYPE[_rgb][_be].raw`)
            // is read as `archive submit` reads it.
            let named = input
                .file_name()
                .and_then(|n| n.to_str())
                .and_then(wavesplat_worker::archive::parse_raw_name);
            match named {
                Some((_, layout)) => {
                    let mut spec = wavesplat_worker::options::raw_spec(&layout);
                    spec.header_bytes = a.header_bytes;
                    if let Some(s) = a.spacing {
                        spec.spacing = s;
                    }
                    Some(spec)
                }
                None => {
                    if a.spacing.is_some() {
                        bail!("--spacing applies to raw input (with --dims and --dtype); this file's header gives its spacing");
                    }
                    if a.header_bytes > 0 {
                        bail!("--header-bytes applies to raw input (with --dims and --dtype)");
                    }
                    None
                }
            }
        }
        _ => bail!("raw input needs both --dims and --dtype"),
    };
    Ok(Input::File {
        path: input.clone(),
        raw,
        channel: a.channel,
    })
}

/// The time series `compress` reads, when its input is one: the beating phantom, a 4D file
/// (from its header alone: nothing is read here but the header) or a directory of time steps.
fn open_series(a: &CompressArgs) -> Result<Option<super::series::SeriesInput>> {
    use super::series::SeriesInput;
    if a.phantom.as_deref() == Some("beating") {
        let d = a.dims.map_or([64, 64, 16], |d| d.xyz);
        let t = a.dims.and_then(|d| d.t).unwrap_or(16);
        let volumes = (0..t)
            .map(|i| beating(d, i, t))
            .collect::<Result<Vec<_>, _>>()
            .context("generating the beating phantom")?;
        return Ok(Some(SeriesInput::Memory(VolumeSeries::new(volumes, None)?)));
    }
    if a.phantom.is_some() {
        return Ok(None);
    }
    let Input::File { path, raw, channel } = input(a)? else {
        return Ok(None);
    };
    super::series::open_path(&path, raw.as_ref(), channel)
}

/// Without `--memory-limit`, files smaller than this fraction of the memory available are not
/// probed for bricking: even inflated from gzip and at one byte a sample, their volume's
/// working memory (~23× its f32 samples) fits.
const PROBE_FRACTION: u64 = 64;

/// Whether `compress` without `--brick` should brick the input file, and at which side: when
/// compressing it whole would need more memory than the limit (`--memory-limit`, else the
/// memory available now) or it has more voxels than one transform takes. The side is the
/// largest of `AUTO_BRICK_SIDES` below the volume's whose bricks, one per thread, fit the
/// limit (none fitting: compressed whole, which reports the limit). Only phantoms and files read
/// by region are probed (ASCII NRRD is read whole anyway); volumes that fit are compressed
/// whole, as before.
fn auto_brick(a: &CompressArgs, opts: &CompressOptions) -> Result<Option<(usize, String)>> {
    let threads = rayon::current_num_threads().max(1) as u64;
    match (&a.input, &a.phantom) {
        // A phantom's size is known without reading anything: always checked.
        (_, Some(_)) => {
            let Input::Phantom(p) = input(a)? else {
                return Ok(None);
            };
            let limit = opts.memory_limit.or_else(available_memory);
            let dims = p.dims.map(|v| v as usize);
            brick_side(dims, p.phantom.channel_count(), opts, limit, threads)
        }
        (Some(_), None) => {
            let Input::File { path, raw, channel } = input(a)? else {
                return Ok(None);
            };
            probe_file_for_bricks(&path, raw.as_ref(), channel, opts, threads)
        }
        (None, None) => Ok(None),
    }
}

/// Whether the volume file (or DICOM series directory) at `path` should be compressed as
/// bricks, `threads` of them at a time, within `opts.memory_limit` (else the memory available
/// now), and at which side, with the reason ([`wavesplat_compressor::bricked::auto_brick`]).
/// Without a limit given only files large enough are probed ([`PROBE_FRACTION`]); a file its
/// reader holds in memory anyway is not bricked.
pub(crate) fn probe_file_for_bricks(
    path: &std::path::Path,
    raw: Option<&RawSpec>,
    channel: Option<usize>,
    opts: &CompressOptions,
    threads: u64,
) -> Result<Option<(usize, String)>> {
    let limit = opts.memory_limit.or_else(available_memory);
    // A Zarr store is always probed (below): its files are not counted.
    let zarr = path.is_dir() && wavesplat_compressor::reader::zarr::is_store(path);
    // A DICOM series directory: the bytes of its files.
    let on_disk = if zarr {
        0
    } else if path.is_dir() {
        std::fs::read_dir(path)
            .map(|entries| {
                entries
                    .filter_map(|e| e.ok()?.metadata().ok())
                    .map(|m| m.len())
                    .sum()
            })
            .unwrap_or(0)
    } else {
        // Every file the volume is made of: a detached header's data files, a `.hdr`'s `.img`
        // (the header alone is a few hundred bytes).
        wavesplat_compressor::reader::SourceListing::list(path, None)
            .map(|l| l.files.iter().map(|f| f.2).sum())
            .or_else(|_| std::fs::metadata(path).map(|m| m.len()))
            .unwrap_or(0)
    };
    // A limit given is always checked; the memory available only for files large enough, and
    // for Zarr stores, whose chunks may be far smaller than their samples (chunks of the fill
    // value are not stored; their dimensions are in their metadata, read at once).
    let large = zarr
        || match (opts.memory_limit, limit) {
            (Some(_), _) => true,
            (None, Some(l)) => on_disk.saturating_mul(PROBE_FRACTION) >= l,
            (None, None) => on_disk >= 1 << 30,
        };
    if !large {
        return Ok(None);
    }
    let reader =
        RegionReader::open_channel(path, raw, channel).map_err(|e| super::read_error(path, e))?;
    if reader.in_memory() {
        return Ok(None);
    }
    brick_side(reader.dims(), reader.channels(), opts, limit, threads)
}

/// [`wavesplat_compressor::bricked::auto_brick`] with its reason said; refuses the cubic
/// family, which bricks do not support.
fn brick_side(
    dims: [usize; 3],
    channels: usize,
    opts: &CompressOptions,
    limit: Option<u64>,
    threads: u64,
) -> Result<Option<(usize, String)>> {
    let Some(AutoBrick { side, reason }) =
        wavesplat_compressor::bricked::auto_brick(dims, channels, opts, limit, threads)?
    else {
        return refuse_without_bricks(dims, channels, opts, threads).map(|()| None);
    };
    let why = brick_reason(dims, reason, opts.memory_limit.is_some());
    if opts.family == Family::Cubic {
        bail!("{why}, and bricked volumes do not support the cubic family yet: use --family linear (the default) or haar");
    }
    Ok(Some((side, why)))
}

/// Where `--memory-limit` is below what compressing the volume whole needs and no brick fits
/// either: an error that says what the smallest bricks need, on this many threads and on one,
/// instead of the whole's estimate alone.
fn refuse_without_bricks(
    dims: [usize; 3],
    channels: usize,
    opts: &CompressOptions,
    threads: u64,
) -> Result<()> {
    use wavesplat_compressor::bricked::{bricks_memory, AUTO_BRICK_SIDES};
    let Some(limit) = opts.memory_limit else {
        return Ok(());
    };
    let (whole, _) = wavesplat_compressor::encode::memory_estimate(dims, channels, opts)?;
    if whole <= limit {
        return Ok(());
    }
    let side = AUTO_BRICK_SIDES[AUTO_BRICK_SIDES.len() - 1];
    let human = wavesplat_viewer::window::human_bytes;
    let (Some(all), Some(one)) = (
        bricks_memory(dims, channels, opts, side, threads),
        bricks_memory(dims, channels, opts, side, 1),
    ) else {
        return Ok(());
    };
    let fewer = if threads > 1 && one <= limit {
        format!(", or one thread (RAYON_NUM_THREADS=1 needs {})", human(one))
    } else {
        String::new()
    };
    bail!(
        "compressing {}x{}x{} needs more memory than the {} of --memory-limit: about {} whole, \
         and {} in the smallest bricks ({side}³, {threads} at a time on {threads} thread(s); \
         {} of it the process's own); give --memory-limit {} or more{fewer}",
        dims[0],
        dims[1],
        dims[2],
        human(limit),
        human(whole),
        human(all),
        human(wavesplat_compressor::encode::PROCESS_MEMORY),
        human(all.min(whole)),
    )
}

/// Says why a volume of `dims` is bricked ([`BrickReason`]); `limit_given`: the limit is
/// `--memory-limit`'s (else the memory available now).
fn brick_reason(dims: [usize; 3], reason: BrickReason, limit_given: bool) -> String {
    match reason {
        BrickReason::TooManyVoxels(voxels) => format!(
            "{}x{}x{} is {voxels} voxels, more than one transform takes ({MAX_VOXELS})",
            dims[0], dims[1], dims[2]
        ),
        BrickReason::OverMemory { needed, limit } => format!(
            "compressing {}x{}x{} whole needs about {} of memory, more than the {} {}",
            dims[0],
            dims[1],
            dims[2],
            wavesplat_viewer::window::human_bytes(needed),
            wavesplat_viewer::window::human_bytes(limit),
            if limit_given {
                "of --memory-limit"
            } else {
                "available now (--memory-limit sets the limit)"
            }
        ),
    }
}

/// Memory available to a new process now (Linux: `MemAvailable` in `/proc/meminfo`); `None`
/// elsewhere. Read by hand: one line of a kernel file, no crate needed.
fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// The options given that a bricked volume does not apply (its bricks are coded without them).
fn ignored_for_bricks(a: &CompressArgs) -> Vec<&'static str> {
    [
        (a.margin.is_some(), "--margin"),
        (a.single_sequence, "--single-sequence"),
        (a.layers.is_some(), "--layers"),
        (a.no_coarse_layer, "--no-coarse-layer"),
    ]
    .into_iter()
    .filter_map(|(given, name)| given.then_some(name))
    .collect()
}

/// `compress --brick N`: the volume read brick by brick and written as one bricked file.
fn run_bricked(a: &CompressArgs, opts: &CompressOptions, brick: usize) -> Result<()> {
    let input = input(a)?;
    let reader;
    let source: &dyn BrickSource = match &input {
        Input::Phantom(p) => p,
        Input::File { path, raw, channel } => {
            reader = RegionReader::open_channel(path, raw.as_ref(), *channel)
                .map_err(|e| super::read_error(path, e))?;
            &reader
        }
    };
    compress_bricks_of(a, opts, brick, source)
}

/// Compresses `source` as bricks of `brick` into `a.output`, with a summary.
fn compress_bricks_of(
    a: &CompressArgs,
    opts: &CompressOptions,
    brick: usize,
    source: &dyn BrickSource,
) -> Result<()> {
    let d = source.dims();
    // A slice has no transform level, in bricks as whole: every non-zero voxel is kept
    // unless a target is given (see `compress_volume`).
    let thin;
    let opts = if !a.keep.is_given() && Geometry::max_levels(d.map(|v| v as usize)) == 0 {
        eprintln!(
            "note: {}x{}x{} is one voxel thin: the 3D transform has no level (M = 0) and its \
             coefficients are the voxels, so every non-zero one is kept (lossless selection); \
             give --target-fraction or --target-bytes to keep fewer",
            d[0], d[1], d[2]
        );
        thin = CompressOptions {
            target: Target::All,
            ..opts.clone()
        };
        &thin
    } else {
        opts
    };
    let ignored = ignored_for_bricks(a);
    if !ignored.is_empty() {
        tracing::warn!(
            "{} not applied to a bricked volume: its bricks are coded without them (each \
             brick's margin follows from its own faces)",
            ignored.join(", ")
        );
    }
    let progress = Progress::new("compress");
    let report = |stage: BrickStage| progress.stage(&stage.to_string());
    let checkpoint_dir = checkpoint_dir(&a.output);
    let c = super::write_output(&a.output, |spill, out| {
        // Only where the output is a file (a checkpoint beside a pipe or a device would
        // outlive what it served).
        // Whether the checkpoint holds nothing of an earlier run (only then may a refusal
        // remove it).
        let mut fresh_checkpoint = false;
        let checkpoint = match spill {
            Some(dir) => {
                // Read before --no-resume discards the checkpoint.
                let left = Checkpoint::unfinished_output_in(&checkpoint_dir);
                let (cp, fresh) = open_checkpoint(a, opts, brick, &checkpoint_dir)?;
                fresh_checkpoint = fresh;
                // The unfinished output of a run killed before it could remove it (SIGKILL),
                // replaced by this run's.
                let current = super::interrupt::unfinished()
                    .into_iter()
                    .rev()
                    .find(|p| p.parent() == Some(dir));
                if let Some(left) = left {
                    if Some(&left) != current.as_ref()
                        && left.parent() == Some(dir)
                        && std::fs::remove_file(&left).is_ok()
                    {
                        outln!("removed {}, left by the interrupted run", left.display());
                    }
                }
                if let Some(current) = &current {
                    cp.keep_unfinished_output(current);
                }
                Some(cp)
            }
            None => None,
        };
        let _kept = checkpoint.as_ref().map(|cp| {
            super::interrupt::Kept::note(format!(
                "the bricks finished so far are kept in {}: run the same command again to go \
                 on from there",
                cp.dir().display()
            ))
        });
        let written =
            compress_bricked_to(source, opts, brick, &report, spill, checkpoint.as_ref(), out);
        match (written, checkpoint) {
            (Ok(w), cp) => Ok((w, cp)),
            // Refused before any brick was scored: running again would not help, and there is
            // nothing to keep (a resumed checkpoint stays: a larger limit goes on from it).
            (Err(e), Some(cp)) if e.is_memory_refusal() && fresh_checkpoint => {
                if let Err(r) = cp.remove() {
                    tracing::debug!("removing the checkpoint: {r}");
                }
                Err(anyhow::Error::new(e).context(
                    "compressing: one brick needs more memory than --memory-limit gives; give \
                     more, or a smaller --brick",
                ))
            }
            // Options or samples refused: the same command cannot succeed, and a checkpoint made
            // for it holds nothing of use.
            (Err(e), Some(cp)) if e.is_refusal() => {
                if fresh_checkpoint {
                    if let Err(r) = cp.remove() {
                        tracing::debug!("removing the checkpoint: {r}");
                    }
                }
                Err(anyhow::Error::new(e).context("compressing"))
            }
            (Err(e), Some(_)) => Err(anyhow::Error::new(e).context(format!(
                "compressing (the bricks finished so far are kept in {}: run the same command \
                 again to go on from there, or with --no-resume to start over)",
                checkpoint_dir.display()
            ))),
            (Err(e), None) => Err(anyhow::Error::new(e).context("compressing")),
        }
    })
    .map(|(c, checkpoint)| {
        // The file is in place: what it was made from is no longer needed.
        if let Some(cp) = checkpoint {
            if let Err(e) = cp.remove() {
                tracing::warn!(dir = %checkpoint_dir.display(), error = %e, "could not remove the checkpoint");
            }
        }
        c
    })?;
    progress.finish();
    let voxels = d.iter().map(|v| *v as f64).product::<f64>() * source.channels() as f64;
    outln!(
        "{}: {} bytes ({:.4} % of {} samples at one byte each), bricked: {} bricks of at most \
         {brick} a side",
        a.output.display(),
        c.bytes,
        100.0 * c.bytes as f64 / voxels,
        voxels,
        c.manifest.bricks.len()
    );
    outln!(
        "volume {}x{}x{} x{} | {} M={} | kept {}",
        d[0],
        d[1],
        d[2],
        source.channels(),
        opts.family.name(),
        c.levels,
        super::kept_of(c.manifest.kept(), c.total_coefficients, Some(c.nonzero))
    );
    if let Some(note) = overhead_note(c.overhead, c.bytes, opts.coder) {
        outln!("{note}");
    }
    Ok(())
}

/// Where a bricked compression to `output` keeps its checkpoint: `OUTPUT.checkpoint` beside it.
fn checkpoint_dir(output: &std::path::Path) -> PathBuf {
    let mut name = output.file_name().unwrap_or_default().to_os_string();
    name.push(".checkpoint");
    output.with_file_name(name)
}

/// Opens the checkpoint of this compression in `dir` (emptied first with --no-resume), saying
/// what it holds when it resumes one; and whether it holds nothing of an earlier run.
fn open_checkpoint(
    a: &CompressArgs,
    opts: &CompressOptions,
    brick: usize,
    dir: &std::path::Path,
) -> Result<(Checkpoint, bool)> {
    if a.no_resume && dir.exists() {
        std::fs::remove_dir_all(dir)
            .with_context(|| format!("removing the checkpoint {}", dir.display()))?;
    }
    let key = checkpoint_key(a, opts, brick)?;
    let open = || {
        Checkpoint::open(dir, &key)
            .with_context(|| format!("opening the checkpoint {}", dir.display()))
    };
    let (mut cp, mut resumed) = open()?;
    if resumed.replaced {
        tracing::warn!(
            dir = %dir.display(),
            "the checkpoint was of another input or other options: starting over"
        );
    }
    let holds_work = |r: &Resumed| r.planned || r.scored + r.coded > 0;
    // A file or directory input: the checkpoint is resumed from only where the run that made
    // it recorded a digest of every byte of the input and the input still gives it.
    let input = a.input.clone().filter(|_| a.phantom.is_none());
    if let Some(path) = &input {
        // The digest this run took before it starts over, kept instead of read again.
        let mut taken = None;
        if !resumed.replaced && holds_work(&resumed) {
            let progress = Progress::new("checking the input against the checkpoint");
            let now = input_digest(path, &AtomicBool::new(false));
            progress.finish();
            let recorded = cp.content();
            if now.is_none() || recorded != now {
                tracing::warn!(
                    dir = %dir.display(),
                    "{}: starting over",
                    if recorded.is_none() {
                        "the checkpoint has no digest of the input (its run was stopped before \
                         it read the whole input)"
                    } else {
                        "the input's contents changed since the checkpoint was made"
                    }
                );
                drop(cp);
                std::fs::remove_dir_all(dir)
                    .with_context(|| format!("removing the checkpoint {}", dir.display()))?;
                (cp, resumed) = open()?;
                resumed.replaced = true;
                taken = now;
            }
        }
        if cp.content().is_none() {
            let path = path.clone();
            cp.record_content(move |stop| taken.or_else(|| input_digest(&path, stop)));
        }
    }
    let fresh = resumed.replaced || !holds_work(&resumed);
    if !fresh {
        outln!(
            "resuming from {}: {}{} bricks scored{} and {} coded already",
            dir.display(),
            if resumed.planned { "the plan, " } else { "" },
            resumed.scored,
            match resumed.tops {
                0 => String::new(),
                t => format!(" ({t} with their kept tops: coded without being read again)"),
            },
            resumed.coded
        );
    }
    Ok((cp, fresh))
}

/// What a checkpoint is tied to: this build, the input's identity (a file's canonical path,
/// length, modification time and a sample of its contents; a directory's entries' count, total
/// length and latest modification; a phantom's name and size), the brick edge and every option
/// that shapes the file.
fn checkpoint_key(a: &CompressArgs, opts: &CompressOptions, brick: usize) -> Result<String> {
    let input = match (&a.input, &a.phantom) {
        (Some(path), _) => {
            let canonical = std::fs::canonicalize(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let stamp = |m: &std::fs::Metadata| {
                let modified = m
                    .modified()
                    .ok()
                    .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                    .map_or(0, |d| d.as_nanos());
                (m.len(), modified)
            };
            let meta = std::fs::metadata(&canonical)
                .with_context(|| format!("reading {}", path.display()))?;
            if meta.is_dir() {
                let (mut count, mut bytes, mut latest) = (0u64, 0u64, 0u128);
                for entry in std::fs::read_dir(&canonical)
                    .with_context(|| format!("reading {}", path.display()))?
                {
                    let m = entry
                        .and_then(|e| e.metadata())
                        .with_context(|| format!("reading {}", path.display()))?;
                    let (len, modified) = stamp(&m);
                    count += 1;
                    bytes += len;
                    latest = latest.max(modified);
                }
                format!("dir {} {count} {bytes} {latest}", canonical.display())
            } else {
                let (len, modified) = stamp(&meta);
                let sample = content_sample(&canonical, len)
                    .with_context(|| format!("reading {}", path.display()))?;
                format!("file {} {len} {modified} {sample:08x}", canonical.display())
            }
        }
        (None, phantom) => format!("phantom {phantom:?} {:?}", a.dims),
    };
    // The memory limit shapes how the work is done, not the file: a run resumed under
    // another limit still uses the checkpoint.
    let shaping = CompressOptions {
        memory_limit: None,
        ..opts.clone()
    };
    Ok(format!(
        "wavesplat {}\ninput {input}\nraw {:?} {:?}\nbrick {brick}\noptions {shaping:?}\n",
        env!("CARGO_PKG_VERSION"),
        a.dims,
        a.dtype
    ))
}

/// Blocks of a file's contents read into its checkpoint key, and their length: a file
/// rewritten in place with the same length and modification time (a copy that keeps times, a
/// restore) is told apart wherever it differs in them, for 64 kB read whatever its size.
const SAMPLE_BLOCKS: u64 = 16;
const SAMPLE_BLOCK_BYTES: u64 = 4096;

/// The CRC-32 of [`SAMPLE_BLOCKS`] blocks spread evenly over the file's `len` bytes (the first
/// and the last among them; the whole of a smaller file).
fn content_sample(path: &std::path::Path, len: u64) -> std::io::Result<u32> {
    use std::io::{Read, Seek, SeekFrom};
    let mut file = std::fs::File::open(path)?;
    let mut crc = crc32fast::Hasher::new();
    let mut block = vec![0u8; SAMPLE_BLOCK_BYTES as usize];
    let last_start = len.saturating_sub(SAMPLE_BLOCK_BYTES);
    let mut next = 0u64;
    for k in 0..SAMPLE_BLOCKS {
        let start = (last_start * k / (SAMPLE_BLOCKS - 1)).max(next);
        if start >= len {
            break;
        }
        let take = SAMPLE_BLOCK_BYTES.min(len - start) as usize;
        file.seek(SeekFrom::Start(start))?;
        file.read_exact(&mut block[..take])?;
        crc.update(&block[..take]);
        next = start + take as u64;
    }
    Ok(crc.finalize())
}

/// A digest of every byte of the input at `path` (its files as `archive submit` uploads them:
/// a DICOM series' files, a detached header's data files) and their length: the CRC-32 of the
/// bytes, then their length, 12 bytes. `None` where they cannot be listed or read, or once
/// `stop` is set. Streamed through, a piece at a time.
fn input_digest(path: &std::path::Path, stop: &AtomicBool) -> Option<Vec<u8>> {
    /// A writer that hashes what it is given, until it is told to stop.
    struct Digest<'a> {
        crc: crc32fast::Hasher,
        len: u64,
        stop: &'a AtomicBool,
    }
    impl std::io::Write for Digest<'_> {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            if self.stop.load(Ordering::Relaxed) {
                return Err(std::io::Error::other("stopped"));
            }
            self.crc.update(bytes);
            self.len += bytes.len() as u64;
            Ok(bytes.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    let listing = wavesplat_compressor::reader::SourceListing::list(path, None).ok()?;
    let mut digest = Digest {
        crc: crc32fast::Hasher::new(),
        len: 0,
        stop,
    };
    listing.write_to(&mut digest).ok()?;
    let mut bytes = digest.crc.finalize().to_le_bytes().to_vec();
    bytes.extend_from_slice(&digest.len.to_le_bytes());
    Some(bytes)
}

/// A bricked file whose manifest and brick headers take more than a fifth of it leaves little
/// of a byte target to coefficients: say so, and what leaves more.
fn overhead_note(overhead: u64, total: u64, coder: CoderKind) -> Option<String> {
    if overhead * 5 <= total {
        return None;
    }
    let tables = if coder == CoderKind::Fast {
        " (each brick's header carries the fast coder's tables: the default coder's carry none)"
    } else {
        ""
    };
    Some(format!(
        "note: the manifest and the bricks' headers take {overhead} of the {total} bytes \
         ({:.0} %){tables}; larger bricks (--brick) leave more of the file to coefficients",
        100.0 * overhead as f64 / total.max(1) as f64
    ))
}

/// Parses `X,Y,Z` voxel spacing (finite, positive).
fn parse_spacing(s: &str) -> Result<[f32; 3], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|t| t.trim().parse::<f32>().map_err(|e| format!("{t:?}: {e}")))
        .collect::<Result<_, _>>()?;
    match v.as_slice() {
        [x, y, z] if v.iter().all(|s| s.is_finite() && *s > 0.0) => Ok([*x, *y, *z]),
        _ => Err(format!(
            "spacing {s:?} must be three finite positive numbers X,Y,Z"
        )),
    }
}

/// Builds compressor options from the arguments.
pub fn options(a: &CompressArgs) -> Result<CompressOptions> {
    let family = Family::from_name(&a.family).with_context(|| {
        format!(
            "unknown family {:?}; choose haar, linear or cubic",
            a.family
        )
    })?;
    let colorspace = ColorSpaceKind::from_name(&a.colorspace).with_context(|| {
        format!(
            "unknown colour space {:?}; choose rgb, yiq or pca",
            a.colorspace
        )
    })?;
    let coder = CoderKind::from_name(&a.coder).with_context(|| {
        format!(
            "unknown coder {:?}; choose sigmap, fast, range or huffman",
            a.coder
        )
    })?;
    if !(1..=16).contains(&a.bits) {
        bail!("--bits {}: quantization bits must be 1..=16", a.bits);
    }
    if !(0.0..=1.0).contains(&a.cluster_threshold) {
        bail!(
            "--cluster-threshold {} must be within 0..=1",
            a.cluster_threshold
        );
    }
    let target = a.keep.target();
    let tile = if a.single_sequence {
        TileChoice::Single
    } else {
        a.tile.map_or(TileChoice::Auto, TileChoice::Size)
    };
    Ok(CompressOptions {
        family,
        levels: a.levels,
        margin: a.margin,
        smooth_padding: false,
        offset: None,
        colorspace,
        color_transform: None,
        bits: a.bits,
        coder,
        target,
        tile,
        layers: a.layers,
        layer_growth: a.layer_growth,
        coarse_layer: !a.no_coarse_layer,
        clustering: (a.cluster_radius > 0).then_some(Clustering {
            radius: a.cluster_radius,
            threshold: a.cluster_threshold,
        }),
        step: a.step,
        depth_search: a.effort.depth_search(),
        refine: a
            .effort
            .refine_with(a.no_refine, a.refine_rounds, a.refine_iterations),
        memory_limit: a.memory_limit,
        format_version: a.format_version,
        stop: Default::default(),
    })
}

fn parse_effort(s: &str) -> Result<Effort, String> {
    Effort::from_name(s)
        .ok_or_else(|| format!("unknown effort {s:?}; one of {}", Effort::NAMES.join(", ")))
}

/// Runs the subcommand.
pub fn run(a: CompressArgs) -> Result<()> {
    let opts = options(&a)?;
    super::check_output(&a.output)?;
    if let Some(input) = &a.input {
        super::check_not_input(&a.output, input)?;
    }
    let series = open_series(&a)?;
    let taken;
    let volume = match (&series, a.time_point) {
        (Some(s), None) => {
            return super::series::compress(&a.output, a.time_group, a.brick, &opts, s.source())
        }
        (Some(s), Some(t)) => {
            let source = s.source();
            if t >= source.time_points() {
                bail!(
                    "--time-point {t}: the series has {} time points (0..={})",
                    source.time_points(),
                    source.time_points() - 1
                );
            }
            let one = TimePointSource { series: source, t };
            if let Some(brick) = a.brick {
                return compress_bricks_of(&a, &opts, brick, &one);
            }
            taken = one
                .read([0; 3], source.dims().map(|d| d as usize))
                .with_context(|| format!("reading time point {t}"))?;
            Some(taken)
        }
        (None, Some(_)) => bail!(
            "--time-point applies to a time series (a 4D NIfTI, raw --dims X,Y,Z,T, a \
             directory of time steps, --phantom beating); this input is one volume"
        ),
        (None, None) => None,
    };
    if let Some(volume) = volume {
        return compress_volume(&a, opts, volume);
    }
    if let Some(brick) = a.brick {
        return run_bricked(&a, &opts, brick);
    }
    if let Some((brick, why)) = auto_brick(&a, &opts)? {
        eprintln!(
            "note: {why}: compressing it as bricks of at most {brick} voxels a side, read from \
             the file brick by brick, into one bricked file (--brick N chooses the side)"
        );
        return run_bricked(&a, &opts, brick);
    }
    let volume = load(&a)?;
    compress_volume(&a, opts, volume)
}

/// Compresses one volume whole into `a.output`, with a summary.
fn compress_volume(a: &CompressArgs, mut opts: CompressOptions, volume: Volume) -> Result<()> {
    if !a.keep.is_given() && Geometry::max_levels(volume.dims()) == 0 {
        // The transform is one depth M on all three axes, limited by the thinnest: a slice
        // (one voxel along an axis) has M = 0, its coefficients are its voxels, and keeping
        // the default 5 % of them would keep the brightest pixels and nothing else.
        opts.target = Target::All;
        let d = volume.dims();
        eprintln!(
            "note: {}x{}x{} is one voxel thin: the 3D transform has no level (M = 0) and its \
             coefficients are the voxels, so every non-zero one is kept (lossless selection); \
             give --target-fraction or --target-bytes to keep fewer",
            d[0], d[1], d[2]
        );
    }
    let progress = Progress::new("compress");
    let report = |stage: Stage, _f: f64| {
        progress.stage(&match stage {
            Stage::Color => "colour transform".to_string(),
            Stage::Transform(c) => format!("wavelet transform, channel {c}"),
            Stage::Sort => "scoring and sorting coefficients".to_string(),
            Stage::Refine => "least-squares refinement of the kept set".to_string(),
            Stage::Encode(t) => format!("entropy coding (trial {t})"),
            Stage::Depth(m) => format!("trying decomposition depth M = {m}"),
        })
    };
    let c = compress(&volume, &opts, &report).context("compressing")?;
    progress.finish();
    super::write_output(&a.output, |_, w| {
        w.write_all(&c.bytes)
            .with_context(|| format!("writing {}", a.output.display()))
    })?;
    print_summary(&volume, &c, &a.output);
    Ok(())
}

fn print_summary(volume: &Volume, c: &Compressed, out: &std::path::Path) {
    let s = &c.stats;
    let d = volume.dims();
    // The source's sample width is gone after reading (samples are f32), so the ratio is to
    // one byte per sample: a 16-bit volume's own ratio is half of it.
    let samples = (volume.voxel_count() * volume.channel_count()) as f64;
    outln!(
        "{}: {} bytes ({:.4} % of {} samples at one byte each, {:.4} bits/voxel)",
        out.display(),
        s.bytes,
        100.0 * s.bytes as f64 / samples,
        samples,
        8.0 * s.bytes as f64 / volume.voxel_count() as f64
    );
    outln!(
        "volume {}x{}x{} x{} | {} M={} | kept {} of {} coefficients ({:.3} %; {} non-zero)",
        d[0],
        d[1],
        d[2],
        volume.channel_count(),
        c.header.geometry.family,
        c.header.geometry.levels,
        s.kept,
        s.total_coefficients,
        100.0 * s.kept as f64 / (s.total_coefficients as f64).max(1.0),
        s.nonzero_coefficients
    );
    let over = match (s.refined, s.q_v > 100.0) {
        // Eq. 19 over refitted values is no share of the original energy: the refit moves the
        // left-out coefficients' energy into the kept ones, and can pass 100 %.
        (true, true) => {
            ", over the least-squares refined values: above 100 % because the refit puts the \
             left-out coefficients' energy into the kept ones"
        }
        (true, false) => ", over the least-squares refined values",
        _ => "",
    };
    let coarse = if s.coarse_layer {
        " (the first the coarse layer)"
    } else {
        ""
    };
    outln!(
        "Q_V {:.4} % (eq. 19{over}) | Q_E {:.4} % (eq. 20) | tile {} | {} layers{coarse} | {} packets",
        s.q_v,
        s.q_e,
        s.tile,
        s.layers,
        s.packets
    );
    let b = &s.breakdown;
    // The coders' estimates, in bytes; a part of a tiny stream can come out a hair below zero
    // (the f32 logarithm of the range coder's estimate), which would print as "-0".
    let bytes = |bits: f64| (bits / 8.0).max(0.0);
    outln!(
        "bytes: header {} | types/depth/channel {:.0} | positions {:.0} | signs {:.0} | values {:.0} | packet framing {}",
        s.header_bytes,
        bytes(b.tag_bits),
        bytes(b.position_bits),
        bytes(b.sign_bits),
        bytes(b.value_bits),
        b.framing_bytes
    );
}
