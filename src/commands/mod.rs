//! One module per subcommand: argument parsing (clap) into the libraries' option types, and
//! human-readable output.

pub mod bench;
pub mod cache;
pub mod compress;
pub mod decompress;
pub mod demo;
pub mod info;
pub mod interrupt;
pub mod orchestrator;
pub mod phantom;
pub mod publish;
pub mod render;
pub mod security;
pub mod series;
pub mod serve;
pub mod view;

use anyhow::{bail, Context, Result};
use clap::Args;
use wavesplat_compressor::encode::Target;
use wavesplat_viewer::backend::BackendChoice;

/// The cache's default address.
pub const DEFAULT_CACHE_URL: &str = "http://127.0.0.1:50051";

/// The orchestrator's default address.
pub const DEFAULT_ORCHESTRATOR_URL: &str = "http://127.0.0.1:50052";

/// How much of a volume to keep, shared by `compress` and `archive submit`.
#[derive(Args, Debug, Clone)]
pub struct TargetArgs {
    /// Keep as many coefficients as fit in this many bytes (whole file); when every non-zero
    /// coefficient fits, the bytes left refine the quantizer (sigmap and fast coders).
    #[arg(long, group = "target")]
    pub target_bytes: Option<u64>,
    /// Keep this fraction (0..1] of all coefficients: every wavelet coefficient of the padded
    /// grid, all channels (default 0.05; `compress` keeps every non-zero coefficient of a
    /// volume one voxel thin, whose transform has no level). Least-squares refinement prunes the
    /// values its refit moves below the set's smallest score, so it refines a set grown by what
    /// a first refit keeps and cuts it to the count: the count kept is the target's.
    #[arg(long, group = "target", allow_negative_numbers = true)]
    pub target_fraction: Option<f64>,
    /// Keep this many coefficients (all of them where the volume has fewer non-zero ones).
    #[arg(long, group = "target")]
    pub target_coefficients: Option<u64>,
    /// Keep the fewest coefficients whose energy is at least this percentage (Q_V, eq. 19).
    #[arg(long, group = "target", allow_negative_numbers = true)]
    pub target_qv: Option<f64>,
    /// Keep every non-zero coefficient.
    #[arg(long, group = "target")]
    pub lossless_selection: bool,
}

impl TargetArgs {
    /// Whether any target option was given (else [`TargetArgs::target`] is the default).
    pub fn is_given(&self) -> bool {
        self.target_bytes.is_some()
            || self.target_fraction.is_some()
            || self.target_coefficients.is_some()
            || self.target_qv.is_some()
            || self.lossless_selection
    }

    /// The chosen target (default: 5 % of the coefficients).
    pub fn target(&self) -> Target {
        if let Some(b) = self.target_bytes {
            Target::Bytes(b)
        } else if let Some(f) = self.target_fraction {
            Target::Fraction(f)
        } else if let Some(c) = self.target_coefficients {
            Target::Coefficients(c)
        } else if let Some(q) = self.target_qv {
            Target::QvPercent(q)
        } else if self.lossless_selection {
            Target::All
        } else {
            Target::Fraction(0.05)
        }
    }
}

/// The error of opening a server's database at `path`: sled's lock held by another process
/// (its raw `WouldBlock`) said in words.
pub fn database_error(
    e: impl std::error::Error + Send + Sync + 'static,
    path: &std::path::Path,
    what: &str,
) -> anyhow::Error {
    let text = format!("{e:?} {e}");
    if text.contains("WouldBlock") || text.contains("temporarily unavailable") {
        anyhow::anyhow!(
            "the {what} database {} is in use by another process (is a {what} already running \
             on it?)",
            path.display()
        )
    } else {
        anyhow::Error::new(e).context(format!("opening the {what} database {}", path.display()))
    }
}

/// Checks, before any work, that the file `path` can be created: it is not a directory and
/// its directory exists.
pub fn check_output(path: &std::path::Path) -> Result<()> {
    if path.is_dir() {
        bail!(
            "cannot write {}: it is a directory (name a file in it)",
            path.display()
        );
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => return Ok(()),
    };
    if !dir.is_dir() {
        bail!(
            "cannot write {}: the directory {} does not exist",
            path.display(),
            dir.display()
        );
    }
    Ok(())
}

/// Checks, before any work, that the output `path` is not the input `input` (the same file by
/// another name or through a link included): writing it would replace what is being read.
pub fn check_not_input(path: &std::path::Path, input: &std::path::Path) -> Result<()> {
    use std::os::unix::fs::MetadataExt;
    let (Ok(o), Ok(i)) = (std::fs::metadata(path), std::fs::metadata(input)) else {
        return Ok(());
    };
    if o.is_file() && o.dev() == i.dev() && o.ino() == i.ino() {
        bail!(
            "the output {} is the input {}: writing it would destroy what is being read; give \
             another output path",
            path.display(),
            input.display()
        );
    }
    Ok(())
}

/// Writes the file `path` by `write`, which streams it to the writer it is given and may keep
/// temporary files in the directory it is given (where the file goes): under a temporary name
/// beside it, renamed over `path` when complete, so a failure leaves no partial file and
/// readers never see one. The file keeps what a plainly written one would: an existing file's
/// permissions (a new one's: 0o666 less the umask, not a temporary file's owner-only ones), and
/// a symbolic link stays a link (its target is replaced). A device or pipe (`-o /dev/null`) is
/// written in place.
pub fn write_output<T>(
    path: &std::path::Path,
    write: impl FnOnce(Option<&std::path::Path>, &mut dyn std::io::Write) -> Result<T>,
) -> Result<T> {
    use std::io::Write;
    let written =
        |e: std::io::Error| anyhow::Error::new(e).context(format!("writing {}", path.display()));
    let target = output_target(path).map_err(written)?;
    let existing = std::fs::metadata(&target).ok();
    if existing.as_ref().is_some_and(|m| !m.is_file()) {
        let mut out = std::io::BufWriter::new(std::fs::File::create(&target).map_err(written)?);
        let t = write(None, &mut out)?;
        out.flush().map_err(written)?;
        return Ok(t);
    }
    let dir = match target.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };
    remove_stale_partials(&dir);
    let mut builder = tempfile::Builder::new();
    builder.prefix(PARTIAL_PREFIX).suffix(PARTIAL_SUFFIX);
    // Each name tried is registered before the file is made, so that an interrupt at any
    // moment removes it ([`interrupt`]).
    let partial = builder
        .make_in(&dir, |name| {
            let mut open = std::fs::File::options();
            open.write(true).create_new(true);
            #[cfg(unix)]
            std::os::unix::fs::OpenOptionsExt::mode(&mut open, 0o666);
            interrupt::Unfinished::register(name, || open.open(name))
        })
        .with_context(|| format!("creating a file in {}", dir.display()))?;
    let _unfinished = interrupt::Unfinished::guard(partial.path());
    // Locked while this process lives (the lock goes with it, SIGKILL included), so that a
    // later run tells a live run's file from one a killed run left.
    if let Err(e) = partial.as_file().lock() {
        tracing::debug!(file = %partial.path().display(), error = %e, "locking the unfinished output");
    }
    if let Some(m) = &existing {
        partial
            .as_file()
            .set_permissions(m.permissions())
            .map_err(written)?;
    }
    let mut out = std::io::BufWriter::new(partial);
    let t = write(Some(&dir), &mut out)?;
    let partial = out.into_inner().map_err(|e| written(e.into_error()))?;
    partial.persist(&target).map_err(|e| written(e.error))?;
    Ok(t)
}

/// Names of [`write_output`]'s unfinished files: `.wavesplat-XXXXXX.partial`.
const PARTIAL_PREFIX: &str = ".wavesplat-";
const PARTIAL_SUFFIX: &str = ".partial";

/// How old an unlocked unfinished file must be to be taken for a killed run's: a live run
/// locks its file right after making it, so only that instant is unlocked.
const STALE_PARTIAL_AGE: std::time::Duration = std::time::Duration::from_secs(10);

/// Removes the unfinished output files that killed runs (SIGKILL, a power cut) left in `dir`:
/// those [`write_output`] names that no live process holds locked and that are older than
/// [`STALE_PARTIAL_AGE`]. Each is said; failures are only logged (the output is still written).
fn remove_stale_partials(dir: &std::path::Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        if !(name.starts_with(PARTIAL_PREFIX) && name.ends_with(PARTIAL_SUFFIX)) {
            continue;
        }
        let path = entry.path();
        let old = entry
            .metadata()
            .ok()
            .filter(|m| m.is_file())
            .and_then(|m| m.modified().ok())
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|age| age >= STALE_PARTIAL_AGE);
        if !old {
            continue;
        }
        let Ok(file) = std::fs::File::open(&path) else {
            continue;
        };
        // Held by a live run: leave it.
        if file.try_lock().is_err() {
            continue;
        }
        match std::fs::remove_file(&path) {
            Ok(()) => outln!("removed {}, left by an interrupted run", path.display()),
            Err(e) => {
                tracing::debug!(file = %path.display(), error = %e, "removing a stale unfinished output")
            }
        }
    }
}

/// "N of T coefficients (P %; Z non-zero)" of a bricked volume or series; a selection of
/// every coefficient scores nothing, so it knows no totals: "N coefficients (every non-zero
/// one)".
pub fn kept_of(kept: u64, total: u64, nonzero: Option<u64>) -> String {
    if total == 0 {
        return format!("{kept} coefficients (every non-zero one)");
    }
    let share = 100.0 * kept as f64 / total as f64;
    match nonzero {
        Some(z) => format!("{kept} of {total} coefficients ({share:.3} %; {z} non-zero)"),
        None => format!("{kept} of {total} coefficients ({share:.3} %)"),
    }
}

/// Where writing the output `path` goes: through a link to its target (a dangling link is
/// written as a new file at its target), so the link stays a link.
pub fn output_target(path: &std::path::Path) -> std::io::Result<std::path::PathBuf> {
    Ok(match std::fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_symlink() => match std::fs::canonicalize(path) {
            Ok(t) => t,
            Err(_) => std::fs::read_link(path)?,
        },
        _ => path.to_path_buf(),
    })
}

/// Reads a compressed volume: a `.wsp`, or the indexed layout `publish` writes (`.wspx`: its
/// index checked, the unchanged `.wsp` behind it returned). A file that is neither is refused
/// saying what it is: a volume in a format `compress` reads is a volume to compress first.
pub fn read_wsp(path: &std::path::Path) -> Result<Vec<u8>> {
    let bytes = read_wsp_or_indexed(path)?;
    if !bytes.starts_with(wavesplat_codec::format::index::INDEXED_MAGIC) {
        return Ok(bytes);
    }
    let wsp = wavesplat_codec::format::index::wsp_of_indexed(&bytes).with_context(|| {
        format!(
            "{} is not a whole indexed layout (cut short or damaged)",
            path.display()
        )
    })?;
    Ok(wsp.to_vec())
}

fn read_wsp_or_indexed(path: &std::path::Path) -> Result<Vec<u8>> {
    if path.is_dir() {
        bail!(
            "{} is a directory; a .wsp file was expected (a DICOM series directory is a \
             volume to compress first: wavesplat compress {} -o volume.wsp)",
            path.display(),
            path.display()
        );
    }
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    if !bytes.starts_with(wavesplat_codec::format::MAGIC)
        && !bytes.starts_with(wavesplat_codec::format::index::INDEXED_MAGIC)
    {
        let format = wavesplat_compressor::reader::Format::sniff(&bytes)
            .or_else(|| wavesplat_compressor::reader::Format::from_name(path));
        if let Some(f) = format {
            bail!(
                "{} is a {} volume, not a compressed one: compress it first \
                 (wavesplat compress {} -o volume.wsp)",
                path.display(),
                match f {
                    wavesplat_compressor::reader::Format::Dicom => "DICOM",
                    wavesplat_compressor::reader::Format::Nrrd => "NRRD",
                    wavesplat_compressor::reader::Format::MetaImage => "MetaImage",
                    wavesplat_compressor::reader::Format::Nifti => "NIfTI",
                    wavesplat_compressor::reader::Format::Tiff => "TIFF",
                    wavesplat_compressor::reader::Format::Zarr => "Zarr",
                },
                path.display()
            );
        }
        bail!(
            "{} is not a wavesplat file (.wsp starts with \"WSPL\", .wspx with \"WSPX\"); raw \
             samples and other volumes are compressed first (wavesplat compress FILE -o \
             volume.wsp)",
            path.display()
        );
    }
    Ok(bytes)
}

/// Binds a server's listener and prints `listening on ADDR` (scripts and tests read the bound
/// address, e.g. for port 0, from that line). The exposure rule is checked on every address
/// `addr` resolves to before anything is bound or printed, and what the operator should know
/// about the server's protection is said once on stderr.
pub async fn bind_announced(
    addr: &str,
    security: &wavesplat_net::Security,
) -> Result<tokio::net::TcpListener> {
    let candidates: Vec<std::net::SocketAddr> = tokio::net::lookup_host(addr)
        .await
        .with_context(|| format!("resolving the listen address {addr:?} (HOST:PORT)"))?
        .collect();
    for a in &candidates {
        security.check(*a)?;
    }
    let listener = tokio::net::TcpListener::bind(&candidates[..])
        .await
        .with_context(|| format!("binding {addr}"))?;
    let bound = listener.local_addr()?;
    for w in security.warnings(bound) {
        eprintln!("{w}");
    }
    outln!("listening on {bound}");
    use std::io::Write;
    std::io::stdout().flush()?;
    Ok(listener)
}

/// Resolves on Ctrl-C: the graceful-shutdown signal of the servers.
pub async fn ctrl_c() {
    let _ = tokio::signal::ctrl_c().await;
    tracing::info!("shutting down");
}

/// Parses `X,Y,Z` into three positive integers.
pub fn parse_dims(s: &str) -> Result<[usize; 3]> {
    let parts: Vec<&str> = s.split([',', 'x']).collect();
    if parts.len() != 3 {
        bail!("dimensions must be X,Y,Z (three integers), got {s:?}");
    }
    let mut d = [0usize; 3];
    for (i, p) in parts.iter().enumerate() {
        d[i] = p
            .trim()
            .parse()
            .with_context(|| format!("dimension {:?} in {s:?} is not an integer", p))?;
        if d[i] == 0 {
            bail!("dimensions must be at least 1, got {s:?}");
        }
    }
    Ok(d)
}

/// A reader's error, naming the file once (the readers' messages mostly name it already).
pub fn read_error(
    path: &std::path::Path,
    e: wavesplat_compressor::reader::ReadError,
) -> anyhow::Error {
    let shown = path.display().to_string();
    if e.to_string().contains(&shown) {
        anyhow::Error::new(e)
    } else {
        anyhow::Error::new(e).context(format!("reading {shown}"))
    }
}

/// Dimensions X,Y,Z of a volume, or X,Y,Z,T of a time series (T time points).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SeriesDims {
    /// X, Y, Z.
    pub xyz: [usize; 3],
    /// T, when given.
    pub t: Option<usize>,
}

/// Parses `X,Y,Z` or `X,Y,Z,T` (each at least 1).
pub fn parse_series_dims(s: &str) -> Result<SeriesDims> {
    let parts: Vec<&str> = s.split([',', 'x']).collect();
    match parts.len() {
        3 => Ok(SeriesDims {
            xyz: parse_dims(s)?,
            t: None,
        }),
        4 => {
            let xyz = parse_dims(&parts[..3].join(",")).with_context(|| format!("in {s:?}"))?;
            let t: usize = parts[3].trim().parse().with_context(|| {
                format!("time points {:?} in {s:?} is not an integer", parts[3])
            })?;
            if t == 0 {
                bail!("time points must be at least 1, got {s:?}");
            }
            Ok(SeriesDims { xyz, t: Some(t) })
        }
        _ => bail!("dimensions must be X,Y,Z or X,Y,Z,T (time points), got {s:?}"),
    }
}

/// Parses a byte count with an optional k/M/G suffix (powers of 1024).
pub fn parse_bytes(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let (num, mult) = match t.chars().last() {
        Some('k' | 'K') => (&t[..t.len() - 1], 1u64 << 10),
        Some('m' | 'M') => (&t[..t.len() - 1], 1 << 20),
        Some('g' | 'G') => (&t[..t.len() - 1], 1 << 30),
        _ => (t, 1),
    };
    let n: u64 = num
        .trim()
        .parse()
        .map_err(|_| format!("{s:?} is not a byte count (e.g. 65536, 64k, 512M, 8G)"))?;
    n.checked_mul(mult)
        .ok_or_else(|| format!("{s:?} is too large"))
}

/// The accumulation backend flags of `render` and `bench refine`.
#[derive(Args, Debug, Clone, Copy)]
pub struct BackendArgs {
    /// Accumulate on the GPU (wgpu; WGPU_BACKEND / WGPU_ADAPTER_NAME choose the adapter).
    #[arg(long, conflicts_with = "cpu")]
    pub gpu: bool,
    /// Accumulate on the CPU. Default: the GPU on a hardware adapter, else the CPU; `render`
    /// of a whole local file small enough to be drawn before a GPU device would be open (kept
    /// coefficients × pixels / 256² up to a million per core) uses the CPU without probing.
    #[arg(long)]
    pub cpu: bool,
}

impl BackendArgs {
    /// The backend the flags ask for.
    pub fn choice(self) -> BackendChoice {
        backend_choice(self.gpu, self.cpu)
    }
}

/// `--gpu`, `--cpu` or neither (the default: the GPU on a hardware adapter).
pub fn backend_choice(gpu: bool, cpu: bool) -> BackendChoice {
    match (gpu, cpu) {
        (true, _) => BackendChoice::Gpu,
        (_, true) => BackendChoice::Cpu,
        _ => BackendChoice::Auto,
    }
}
