//! Scanning a volume archive (a directory tree) for supported files and turning each into a
//! [`JobSpec`].
//!
//! Supported files:
//! - DICOM: a directory holding DICOM files (files with the `DICM` preamble, whatever their
//!   name) is one volume, a series or a multi-frame file, named by the directory's path;
//! - NRRD (`*.nrrd`, `*.nhdr` with its data file), MetaImage (`*.mha`, `*.mhd` with its data
//!   file), NIfTI-1 (`*.nii`, `*.nii.gz`, and `*.hdr` + `*.img` pairs, Analyze 7.5 too; either
//!   gzip-compressed): the header describes the data; a pair is one volume (its `.img` is not
//!   a file of its own), and a `.hdr` that is no NIfTI or Analyze header (ENVI's, say) is
//!   ignored;
//! - TIFF (`*.tif`, `*.tiff`): a directory of single-page TIFFs is one volume, a stack of
//!   slices in the natural order of their names (`z2` before `z10`), named by the directory's
//!   path; a multi-page TIFF is a volume of its own (of channels stored as planes of their
//!   own, an ImageJ hyperstack's or an OME-TIFF's, a volume per channel, `NAME/cC`);
//! - Zarr (a directory holding `zarr.json`, `.zarray` or `.zgroup`: an array, v2 or v3, or an
//!   OME-Zarr image): one volume, or a time series when the array has a time axis, named by
//!   the directory's path without `.zarr` / `.ome.zarr` (an array of several channels: a
//!   volume per channel, `NAME/c0`, `NAME/c1`, …); its chunks are not scanned;
//! - headerless raw, described by its name: `NAME_XxYxZ_DTYPE[_rgb][_be].raw`, e.g.
//!   `head_256x256x128_u16.raw`, `cells_64x64x64_u8_rgb.raw`, `ct_512x512x300_i16_be.raw`.
//!   DTYPE is `u8`, `i8`, `u16`, `i16`, `u32`, `i32`, `u64`, `i64`, `f32` or `f64`; `_rgb` means 3 channels interleaved per voxel;
//!   `_be` big-endian samples (little-endian otherwise); x varies fastest.
//!
//! With `time_steps` ([`scan_with`]), a directory whose volume files (NIfTI, NRRD, MetaImage)
//! are numbered time steps of one simulation or acquisition (`step_0000.nii.gz`,
//! `step_0010.nii.gz`, …: [`wavesplat_compressor::reader::steps`]) is one time series, named by
//! the directory's path; a directory whose files are not such steps (a step missing, repeated
//! or unnumbered, or of another size) is reported as skipped with the reason. Without it every
//! file is a volume of its own, as a directory of unrelated numbered volumes must be.
//!
//! The volume's name in the cache is its path relative to the archive root without the
//! extension and (for raw files) without the layout suffix: `ct/head_64x64x32_u8.raw` → `ct/head`,
//! `ct/series1/` (DICOM) → `ct/series1`. Data files named by `.nhdr` / `.mhd` headers are part
//! of their header's volume. Hidden files are ignored; `.raw` files whose name does not follow
//! the convention, and names used twice, are reported as skipped. Other files are ignored.

use std::collections::{BTreeSet, HashSet};
use std::path::{Path, PathBuf};
use wavesplat_compressor::reader::steps::{step_files, StepSeries};
use wavesplat_compressor::reader::{
    dicom::is_dicom_file, nifti, tiff_dataset, tiff_pages_and_channels, tiff_part_of_dataset, zarr,
    Format, ReadError, SourceListing, TiffDataset, MAX_SOURCE_FILES,
};
use wavesplat_orchestrator_client::model::{JobOptions, JobSpec, RawLayout, SampleType, Source};

/// A supported file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Found {
    /// The file.
    pub path: PathBuf,
    /// Its name in the cache.
    pub name: String,
    /// Raw layout (`None`: a format with a header, or a DICOM directory).
    pub raw: Option<RawLayout>,
    /// The one channel read, for each channel of a Zarr array of several (`None`: every
    /// channel).
    pub channel: Option<usize>,
}

/// What a scan found.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Scan {
    /// Supported files, sorted by path.
    pub found: Vec<Found>,
    /// Files that look like volumes but cannot be submitted, with the reason.
    pub skipped: Vec<(PathBuf, String)>,
}

/// Parses a raw file name following `NAME_XxYxZ_DTYPE[_rgb][_be].raw`; returns the name part
/// and the layout.
pub fn parse_raw_name(file_name: &str) -> Option<(String, RawLayout)> {
    let stem = file_name.strip_suffix(".raw")?;
    let mut parts: Vec<&str> = stem.split('_').collect();
    let mut big_endian = false;
    let mut channels = 1;
    if parts.last() == Some(&"be") {
        big_endian = true;
        parts.pop();
    } else if parts.last() == Some(&"le") {
        parts.pop();
    }
    if parts.last() == Some(&"rgb") {
        channels = 3;
        parts.pop();
    }
    let dtype = parts.pop()?;
    let dtype = SampleType::from_name(dtype)?;
    let dims_s = parts.pop()?;
    let dims: Vec<usize> = dims_s
        .split('x')
        .map(|d| d.parse().ok().filter(|&v: &usize| v > 0))
        .collect::<Option<_>>()?;
    let dims: [usize; 3] = dims.try_into().ok()?;
    let name = parts.join("_");
    if name.is_empty() {
        return None;
    }
    Some((
        name,
        RawLayout {
            dims,
            dtype,
            big_endian,
            channels,
        },
    ))
}

/// Most channels of one Zarr array submitted as volumes of their own (a spectral or
/// hyperspectral array of hundreds is rather compressed channel by channel, as chosen).
pub const MAX_CHANNEL_VOLUMES: usize = 64;

/// Every visible file under `dir`, in name order; a Zarr store found on the way goes to
/// `stores`, whole, its chunks not listed.
fn walk(dir: &Path, out: &mut Vec<PathBuf>, stores: &mut Vec<PathBuf>) -> std::io::Result<()> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)?.collect::<Result<_, _>>()?;
    entries.sort_by_key(|e| e.file_name());
    for e in entries {
        if e.file_name().to_string_lossy().starts_with('.') {
            continue;
        }
        let ty = e.file_type()?;
        if ty.is_dir() && zarr::is_store(&e.path()) {
            stores.push(e.path());
        } else if ty.is_dir() {
            walk(&e.path(), out, stores)?;
        } else {
            out.push(e.path());
        }
    }
    Ok(())
}

/// Scans `root` recursively (every file a volume of its own: [`scan_with`] without time steps).
pub fn scan(root: &Path) -> std::io::Result<Scan> {
    scan_with(root, false)
}

/// The name of a directory under `root` in the cache: its path relative to `root`, or `root`'s
/// own name for `root` itself (`fallback` when it has none).
fn dir_name(root: &Path, dir: &Path, fallback: &str) -> String {
    let rel = dir
        .strip_prefix(root)
        .map(|p| p.to_string_lossy().into_owned())
        .unwrap_or_default();
    if rel.is_empty() {
        root.file_name().map_or_else(
            || fallback.to_string(),
            |n| n.to_string_lossy().into_owned(),
        )
    } else {
        rel
    }
}

/// Scans `root` recursively; with `time_steps`, a directory of numbered time steps is one time
/// series (see the module documentation).
pub fn scan_with(root: &Path, time_steps: bool) -> std::io::Result<Scan> {
    let (mut files, mut stores) = (Vec::new(), Vec::new());
    if zarr::is_store(root) {
        stores.push(root.to_path_buf());
    } else {
        walk(root, &mut files, &mut stores)?;
    }
    let mut scan = Scan::default();
    let mut names = HashSet::new();
    // Zarr stores: each one volume (or series), named by its path without `.zarr`.
    for store in stores {
        let name = dir_name(root, &store, "zarr");
        let lower = name.to_ascii_lowercase();
        let name = [".ome.zarr", ".zarr"]
            .iter()
            .find_map(|ext| lower.strip_suffix(ext))
            .filter(|stem| !stem.is_empty() && !stem.ends_with('/'))
            .map_or(name.clone(), |stem| name[..stem.len()].to_string());
        // Its metadata only is read here (the array opened as the reader opens it), not its
        // chunks listed: a store may hold millions, and the submission lists them to hash
        // them (a store whose files cannot be listed is skipped then). Not an image or array
        // this reader takes (a plate, a group of other data): said here, as a bad file is.
        let channels = match zarr::channels(&store) {
            Ok(n) => n,
            Err(e) => {
                scan.skipped.push((store, e.to_string()));
                continue;
            }
        };
        push_channels(&mut scan, &mut names, store, name, None, channels);
    }
    // Directories of time steps: each one series, every file in it taken.
    let mut step_dirs: BTreeSet<PathBuf> = BTreeSet::new();
    if time_steps {
        let dirs: BTreeSet<PathBuf> = files
            .iter()
            .filter_map(|p| p.parent().map(Path::to_path_buf))
            .collect();
        for dir in dirs {
            let steps = match step_files(&dir, None) {
                Ok(s) if s.len() >= 2 => s,
                _ => continue,
            };
            let name = dir_name(root, &dir, "steps");
            match StepSeries::open(&dir, None) {
                Ok(_) if names.insert(name.clone()) => {
                    scan.found.push(Found {
                        path: dir.clone(),
                        name,
                        raw: None,
                        channel: None,
                    });
                    step_dirs.insert(dir);
                }
                // Skipped whole: its files are not submitted one by one either.
                Ok(_) => {
                    scan.skipped.push((
                        dir.clone(),
                        format!("another volume already uses the name {name:?}"),
                    ));
                    step_dirs.insert(dir);
                }
                Err(e) => {
                    scan.skipped.push((
                        dir.clone(),
                        format!("not one time series of {} steps: {e}", steps.len()),
                    ));
                    step_dirs.insert(dir);
                }
            }
        }
    }
    // DICOM files and single-page TIFFs make their directory a volume (a series, a stack of
    // slices); data files of detached headers belong to their header; a multi-page TIFF is a
    // volume of its own.
    let mut stack_dirs = BTreeSet::new();
    let mut taken = HashSet::new();
    // Single-page TIFFs by directory, and the directories that also hold a multi-page or an
    // unreadable TIFF (their single pages are no stack).
    let mut tiff_slices: std::collections::BTreeMap<PathBuf, Vec<PathBuf>> = Default::default();
    let mut mixed_tiff_dirs = HashSet::new();
    // Multi-page TIFFs storing several channels as planes of their own, and how many.
    let mut tiff_channel_counts: std::collections::HashMap<PathBuf, usize> = Default::default();
    // Each TIFF's place in a multi-file OME-TIFF, and the parts the files holding a dataset's
    // XML name.
    let datasets: std::collections::HashMap<PathBuf, Result<TiffDataset, ReadError>> = files
        .iter()
        .filter(|p| Format::from_name(p) == Some(Format::Tiff))
        .map(|p| (p.clone(), tiff_dataset(p)))
        .collect();
    let claimed: HashSet<&PathBuf> = datasets
        .values()
        .filter_map(|d| match d {
            Ok(TiffDataset::Holds(parts)) => Some(parts),
            _ => None,
        })
        .flatten()
        .collect();
    for path in &files {
        match Format::from_name(path) {
            Some(Format::Nrrd | Format::MetaImage) => {
                // Listed, not read: the data files may be many and large.
                if let Ok(listing) = SourceListing::list(path, None) {
                    for (_, data, _) in listing.files.iter().skip(1) {
                        taken.insert(data.clone());
                    }
                }
            }
            Some(Format::Nifti) if nifti::is_pair_header_path(path) => {
                // A `.hdr` and the `.img` beside it are one volume; a `.hdr` of another kind
                // is no volume.
                if !nifti::is_pair_header(path) {
                    taken.insert(path.clone());
                    continue;
                }
                match nifti::pair_data_file(path) {
                    Ok(data) => {
                        taken.insert(data);
                    }
                    Err(e) => {
                        scan.skipped.push((path.clone(), e.to_string()));
                        taken.insert(path.clone());
                    }
                }
            }
            Some(Format::Nifti | Format::Zarr) => {}
            Some(Format::Tiff) => {
                let dir = path.parent().unwrap_or(root).to_path_buf();
                // A file a multi-file OME-TIFF's XML names is a part of that volume, whatever
                // its own description says (a writer may give its parts none).
                if claimed.contains(path) {
                    taken.insert(path.clone());
                    mixed_tiff_dirs.insert(dir);
                    continue;
                }
                // A part of a multi-file OME-TIFF belongs to the file its dataset is read from,
                // when that file's XML names it; else it is skipped, saying why.
                match datasets.get(path) {
                    Some(Ok(TiffDataset::PartOf(holder))) => {
                        taken.insert(path.clone());
                        mixed_tiff_dirs.insert(dir);
                        let name = holder
                            .file_name()
                            .map(|n| n.to_string_lossy().into_owned())
                            .unwrap_or_default();
                        let why = if !holder.is_file() {
                            format!(
                                "a part of a multi-file OME-TIFF read from {}, which is not there",
                                holder.display()
                            )
                        } else if Format::from_name(holder) != Some(Format::Tiff) {
                            // Its XML in a file no reader takes.
                            tiff_part_of_dataset(&name)
                        } else {
                            format!(
                                "a part of a multi-file OME-TIFF read from {}, whose XML does not \
                                 name it",
                                holder.display()
                            )
                        };
                        scan.skipped.push((path.clone(), why));
                        continue;
                    }
                    Some(Err(e)) => {
                        scan.skipped.push((path.clone(), e.to_string()));
                        taken.insert(path.clone());
                        mixed_tiff_dirs.insert(dir);
                        continue;
                    }
                    _ => {}
                }
                // Its pages and channels stored as planes, read once (a file whose channel
                // planes do not add up is skipped, saying why).
                // A file holding a dataset (an OME companion file of one plane too) is a volume.
                let holds = matches!(datasets.get(path), Some(Ok(TiffDataset::Holds(_))));
                match tiff_pages_and_channels(path).map(|(pages, channels)| {
                    if channels > 1 {
                        tiff_channel_counts.insert(path.clone(), channels);
                    }
                    pages
                }) {
                    Ok(1) if !holds => {
                        tiff_slices.entry(dir).or_default().push(path.clone());
                        taken.insert(path.clone());
                    }
                    Ok(0) => {
                        let why = "no page holds an image at full resolution".to_string();
                        scan.skipped.push((path.clone(), why));
                        taken.insert(path.clone());
                        mixed_tiff_dirs.insert(dir);
                    }
                    Ok(_) => {
                        mixed_tiff_dirs.insert(dir);
                    }
                    Err(e) => {
                        scan.skipped.push((path.clone(), e.to_string()));
                        taken.insert(path.clone());
                        mixed_tiff_dirs.insert(dir);
                    }
                }
            }
            Some(Format::Dicom) | None => {
                if is_dicom_file(path)? {
                    stack_dirs.insert(path.parent().unwrap_or(root).to_path_buf());
                    taken.insert(path.clone());
                }
            }
        }
    }
    // A directory of single-page TIFFs is a stack, unless it is a DICOM series (the TIFFs are
    // previews beside it) or holds other TIFFs too.
    let mut tiff_dirs = HashSet::new();
    for (dir, slices) in tiff_slices {
        if stack_dirs.contains(&dir) {
            continue;
        }
        if mixed_tiff_dirs.contains(&dir) {
            for s in slices {
                let why = "a single-page TIFF beside multi-page or unreadable ones: a stack's \
                           directory holds its slices only";
                scan.skipped.push((s, why.into()));
            }
            continue;
        }
        tiff_dirs.insert(dir.clone());
        stack_dirs.insert(dir);
    }
    for dir in stack_dirs {
        let fallback = if tiff_dirs.contains(&dir) {
            "stack"
        } else {
            "dicom"
        };
        let name = dir_name(root, &dir, fallback);
        if !names.insert(name.clone()) {
            scan.skipped.push((
                dir,
                format!("another volume already uses the name {name:?}"),
            ));
            continue;
        }
        scan.found.push(Found {
            path: dir,
            name,
            raw: None,
            channel: None,
        });
    }
    for path in files {
        if taken.contains(&path) || path.parent().is_some_and(|d| step_dirs.contains(d)) {
            continue;
        }
        let file_name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let lower = file_name.to_ascii_lowercase();
        let rel_dir = path
            .parent()
            .and_then(|p| p.strip_prefix(root).ok())
            .map(|p| p.to_string_lossy().into_owned())
            .unwrap_or_default();
        let (base, raw) = if let Some(s) = [
            ".nii.gz",
            ".nii",
            ".hdr.gz",
            ".hdr",
            ".nrrd",
            ".nhdr",
            ".mha",
            ".mhd",
            ".dcm",
            ".dicom",
            ".tiff",
            ".tif",
            ".companion.ome",
        ]
        .iter()
        .find_map(|ext| lower.strip_suffix(ext))
        {
            (file_name[..s.len()].to_string(), None)
        } else if lower.ends_with(".raw") {
            match parse_raw_name(&file_name) {
                Some((n, layout)) => (n, Some(layout)),
                None => {
                    scan.skipped.push((
                        path,
                        "raw file name does not follow NAME_XxYxZ_DTYPE[_rgb][_be].raw".into(),
                    ));
                    continue;
                }
            }
        } else {
            continue;
        };
        let name = if rel_dir.is_empty() {
            base
        } else {
            format!("{rel_dir}/{base}")
        };
        // A TIFF storing channels as planes of their own (an ImageJ hyperstack, an OME-TIFF):
        // a volume per channel, as a Zarr array's.
        let channels = tiff_channel_counts.get(&path).copied().unwrap_or(1);
        push_channels(&mut scan, &mut names, path, name, raw, channels);
    }
    scan.found.sort_by(|a, b| a.path.cmp(&b.path));
    Ok(scan)
}

/// Adds the volume at `path` named `name`: one, or one per channel of `channels` (`NAME/cC`),
/// all of them or none (its names taken, or more channels than are submitted alone: skipped,
/// saying why).
fn push_channels(
    scan: &mut Scan,
    names: &mut HashSet<String>,
    path: PathBuf,
    name: String,
    raw: Option<RawLayout>,
    channels: usize,
) {
    let volumes: Vec<(String, Option<usize>)> = if channels <= 1 {
        vec![(name, None)]
    } else if channels > MAX_CHANNEL_VOLUMES {
        let why = format!(
            "{channels} channels, more than the {MAX_CHANNEL_VOLUMES} submitted as volumes of \
             their own: compress the ones wanted with `compress --channel C`"
        );
        scan.skipped.push((path, why));
        return;
    } else {
        (0..channels)
            .map(|c| (format!("{name}/c{c}"), Some(c)))
            .collect()
    };
    if let Some((name, _)) = volumes.iter().find(|(n, _)| names.contains(n)) {
        let why = format!("another volume already uses the name {name:?}");
        scan.skipped.push((path, why));
        return;
    }
    for (name, channel) in volumes {
        names.insert(name.clone());
        scan.found.push(Found {
            path: path.clone(),
            name,
            raw: raw.clone(),
            channel,
        });
    }
}

/// The files a job's hash covers and an upload carries, listed, not read: a raw file, the
/// visible files of a directory of time steps, or the volume's gathered files
/// ([`SourceListing::list`]: a single file, a DICOM directory's files, a detached header and
/// its data file).
pub fn source_listing(path: &Path, raw: bool) -> std::io::Result<SourceListing> {
    let name = |p: &Path| {
        p.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    if raw {
        let len = std::fs::metadata(path)?.len();
        return Ok(SourceListing {
            format: None,
            files: vec![(name(path), path.to_path_buf(), len)],
        });
    }
    let store = path.is_dir() && zarr::is_store(path);
    if !store && path.is_dir() && step_files(path, None).is_ok_and(|s| !s.is_empty()) {
        // Every visible file: the steps and their data files, in name order.
        let mut entries: Vec<_> = std::fs::read_dir(path)?.collect::<Result<_, _>>()?;
        entries.sort_by_key(|e| e.file_name());
        let mut files = Vec::new();
        for e in entries {
            let n = e.file_name().to_string_lossy().into_owned();
            if n.starts_with('.') || !e.file_type()?.is_file() {
                continue;
            }
            files.push((n, e.path(), e.metadata()?.len()));
        }
        return Ok(SourceListing {
            format: None,
            files,
        });
    }
    SourceListing::list(path, None).map_err(io_error)
}

/// A reader's error as an I/O error that keeps the path it names.
fn io_error(e: ReadError) -> std::io::Error {
    match &e {
        ReadError::Io { source, .. } => {
            std::io::Error::new(source.kind(), format!("{e}: {source}"))
        }
        _ => std::io::Error::other(e.to_string()),
    }
}

/// The bytes a job's hash covers and an upload carries ([`source_listing`]'s files, as
/// [`SourceFiles::to_bytes`] makes them: a single file's own bytes, or a bundle), in memory.
pub fn source_bytes(path: &Path, raw: bool) -> std::io::Result<Vec<u8>> {
    let listing = source_listing(path, raw)?;
    if listing.files.len() > MAX_SOURCE_FILES {
        // Refused here, before it is read, rather than by the worker after the upload.
        return Err(std::io::Error::other(format!(
            "{}: {} files, more than the {MAX_SOURCE_FILES} an upload carries; submit it by path \
             (on storage the workers read)",
            path.display(),
            listing.files.len()
        )));
    }
    let mut bytes = Vec::new();
    bytes
        .try_reserve_exact(usize::try_from(listing.byte_len()).unwrap_or(usize::MAX))
        .map_err(|_| {
            std::io::Error::new(
                std::io::ErrorKind::OutOfMemory,
                format!(
                    "{}: cannot hold {} bytes",
                    path.display(),
                    listing.byte_len()
                ),
            )
        })?;
    listing.write_to(&mut bytes).map_err(io_error)?;
    Ok(bytes)
}

/// The SHA-256 of [`source_bytes`], streamed one file at a time in pieces (a source larger
/// than memory is never held), and their length.
pub fn source_digest(path: &Path, raw: bool) -> std::io::Result<([u8; 32], u64)> {
    let listing = source_listing(path, raw)?;
    let digest = wavesplat_net::digest::sha256_stream(|w| listing.write_to(w).map_err(io_error))?;
    Ok((digest, listing.byte_len()))
}

/// Whether the source at `path` (raw layout `raw`) is a time series: a directory of time steps
/// (as `series::open_series_path` finds them) or a file of more than one time point (a 4D
/// NIfTI, a DICOM cine). What both the submission (a series is not bricked by size) and the
/// worker (a series is read in place) ask.
pub fn is_series_source(path: &Path, raw: Option<&wavesplat_compressor::reader::RawSpec>) -> bool {
    if path.is_dir() && zarr::is_store(path) {
        wavesplat_compressor::reader::time_points(path, raw).is_ok_and(|t| t > 1)
    } else if path.is_dir() {
        step_files(path, raw).is_ok_and(|s| !s.is_empty())
    } else {
        wavesplat_compressor::reader::time_points(path, raw).is_ok_and(|t| t > 1)
    }
}

/// Builds the job for a found volume: reads it to hash it; with `upload`, the bytes are
/// returned to be streamed with the submission, otherwise the job names the volume's absolute
/// path (which every worker must be able to read).
pub fn job_spec(
    found: &Found,
    options: &JobOptions,
    upload: bool,
) -> std::io::Result<(JobSpec, Option<Vec<u8>>)> {
    // A source that is not uploaded is hashed in pieces, file by file, as the bundle the
    // worker will gather (a single file's own bytes, or a DICOM series, a detached header and
    // its data, a directory of time steps), so that submitting a volume larger than memory
    // does not read it whole.
    let raw = found.raw.is_some();
    let (sha256, bytes) = if upload {
        let bytes = source_bytes(&found.path, raw)?;
        (wavesplat_net::digest::sha256(&bytes), Some(bytes))
    } else {
        (source_digest(&found.path, raw)?.0, None)
    };
    let source = match &bytes {
        Some(b) => Source::Upload {
            size: b.len() as u64,
        },
        None => Source::Path(std::fs::canonicalize(&found.path)?),
    };
    let spec = JobSpec {
        name: found.name.clone(),
        source,
        sha256,
        raw: found.raw.clone(),
        channel: found.channel.map(|c| c as u32),
        options: options.clone(),
        part: None,
    };
    Ok((spec, bytes))
}

#[cfg(test)]
mod tests {
    use super::*;
    use wavesplat_compressor::reader::SourceFiles;

    #[test]
    fn raw_names_follow_the_convention() {
        let (n, l) = parse_raw_name("my_head_64x32x16_u16_rgb_be.raw").unwrap();
        assert_eq!(n, "my_head");
        assert_eq!(l.dims, [64, 32, 16]);
        assert_eq!(l.dtype, SampleType::U16);
        assert_eq!(l.channels, 3);
        assert!(l.big_endian);
        let (n, l) = parse_raw_name("a_8x8x8_f32.raw").unwrap();
        assert_eq!((n.as_str(), l.channels, l.big_endian), ("a", 1, false));
        // Every sample type the raw reader takes, by its name and its aliases.
        for (name, dtype) in [
            ("i8", SampleType::I8),
            ("u32", SampleType::U32),
            ("int32", SampleType::I32),
            ("u64", SampleType::U64),
            ("i64", SampleType::I64),
            ("f64", SampleType::F64),
            ("double", SampleType::F64),
        ] {
            let (_, l) = parse_raw_name(&format!("scan_4x5x6_{name}_be.raw")).unwrap();
            assert_eq!(
                (l.dtype, l.dims, l.big_endian),
                (dtype, [4, 5, 6], true),
                "{name}"
            );
        }
        for bad in [
            "a.raw",
            "a_8x8_u8.raw",
            "a_8x8x0_u8.raw",
            "a_8x8x8_u9.raw",
            "8x8x8_u8.raw",
            "a_8x8x8_u8.bin",
        ] {
            assert!(parse_raw_name(bad).is_none(), "{bad}");
        }
    }

    #[test]
    fn scan_finds_supported_files_and_reports_the_rest() {
        let dir = tempfile::tempdir().unwrap();
        let r = dir.path();
        std::fs::create_dir(r.join("sub")).unwrap();
        for f in [
            "a.nii",
            "sub/b.nii.gz",
            "c_4x4x4_u8.raw",
            "bad.raw",
            "notes.txt",
            ".hidden.nii",
            "a_2x2x2_u8.raw",
            "ct.nrrd",
            "mr.mha",
        ] {
            std::fs::write(r.join(f), b"x").unwrap();
        }
        // A detached header's data file belongs to it, whatever its name.
        std::fs::write(r.join("vol.nhdr"), "NRRD0004\ndata file: v_4x4x4_u8.raw\n").unwrap();
        std::fs::write(r.join("v_4x4x4_u8.raw"), b"x").unwrap();
        std::fs::write(r.join("img.mhd"), "NDims = 3\nElementDataFile = img.data\n").unwrap();
        std::fs::write(r.join("img.data"), b"x").unwrap();
        // So do the files of a list or a pattern (here named as raw volumes would be).
        std::fs::write(
            r.join("list.nhdr"),
            "NRRD0004\nsizes: 2 2 2\ndata file: LIST\nl0_2x2x1_u8.raw\nl1_2x2x1_u8.raw\n",
        )
        .unwrap();
        std::fs::write(
            r.join("pat.mhd"),
            "NDims = 3\nDimSize = 2 2 2\nElementDataFile = q%d_2x2x1_u8.raw 0 1 1\n",
        )
        .unwrap();
        for f in ["l0", "l1", "q0", "q1"] {
            std::fs::write(r.join(format!("{f}_2x2x1_u8.raw")), b"xxxx").unwrap();
        }
        // DICOM files (by content) make their directory one volume.
        std::fs::create_dir_all(r.join("study/series1")).unwrap();
        let mut dcm = vec![0u8; 128];
        dcm.extend_from_slice(b"DICM");
        for f in ["IM1", "IM2", "x.dcm"] {
            std::fs::write(r.join("study/series1").join(f), &dcm).unwrap();
        }
        std::fs::write(r.join("study/series1/readme.txt"), b"x").unwrap();
        let s = scan(r).unwrap();
        let names: Vec<&str> = s.found.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(
            names,
            vec![
                "a",
                "c",
                "ct",
                "img",
                "list",
                "mr",
                "pat",
                "study/series1",
                "sub/b",
                "vol"
            ]
        );
        assert!(s.found.iter().any(|f| f.path == r.join("study/series1")));
        assert_eq!(s.skipped.len(), 2, "{:?}", s.skipped);
    }

    /// A NIfTI-1 (or Analyze) `.hdr` + `.img` pair is one volume named by its header (`.hdr`
    /// or `.hdr.gz`); its hash and upload cover the `.img` (the bundle decodes to the
    /// volume); a `.hdr` without its `.img` is skipped naming the file looked for; a `.hdr`
    /// that is no NIfTI header (ENVI's) and its `.img` are ignored, as before.
    #[test]
    fn a_nifti_pair_is_one_volume_with_its_img() {
        let dir = tempfile::tempdir().unwrap();
        let r = dir.path();
        let mut h = vec![0u8; 348];
        h[..4].copy_from_slice(&348i32.to_le_bytes());
        for (i, d) in [3u16, 2, 2, 2, 1, 1, 1, 1].iter().enumerate() {
            h[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
        }
        h[70..72].copy_from_slice(&2i16.to_le_bytes()); // uint8
        h[72..74].copy_from_slice(&8i16.to_le_bytes());
        h[344..348].copy_from_slice(b"ni1\0");
        let data: Vec<u8> = (1..=8).collect();
        std::fs::write(r.join("oasis.hdr"), &h).unwrap();
        std::fs::write(r.join("oasis.img"), &data).unwrap();
        std::fs::create_dir(r.join("fsl")).unwrap();
        // The readers tell gzip by content: these names are what the scan goes by.
        std::fs::write(r.join("fsl/pair.hdr.gz"), &h).unwrap();
        std::fs::write(r.join("fsl/pair.img.gz"), &data).unwrap();
        std::fs::write(r.join("lone.hdr"), &h).unwrap();
        std::fs::write(r.join("envi.hdr"), b"ENVI\nsamples = 2\n").unwrap();
        std::fs::write(r.join("envi.img"), &data).unwrap();
        let s = scan(r).unwrap();
        let names: Vec<&str> = s.found.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, vec!["fsl/pair", "oasis"]);
        assert!(s.found.iter().all(|f| f.raw.is_none()));
        assert_eq!(s.skipped.len(), 1, "{:?}", s.skipped);
        assert_eq!(s.skipped[0].0, r.join("lone.hdr"));
        assert!(s.skipped[0].1.contains("lone.img"), "{:?}", s.skipped);
        for f in &s.found {
            let listing = source_listing(&f.path, false).unwrap();
            assert_eq!(listing.files.len(), 2, "{}", f.name);
            let (spec, bytes) = job_spec(f, &JobOptions::default(), true).unwrap();
            let bytes = bytes.unwrap();
            assert_eq!(
                source_digest(&f.path, false).unwrap().0.to_vec(),
                spec.sha256
            );
            let src = SourceFiles::from_bytes(bytes, &f.path).unwrap();
            let v = wavesplat_compressor::reader::decode_source(&src, None).unwrap();
            assert_eq!(v.dims(), [2, 2, 2]);
            assert_eq!(v.channel(0), &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]);
        }
    }

    /// A directory of single-page TIFFs is one volume (a stack, its slices in natural name
    /// order), named by the directory; a multi-page TIFF is a volume of its own; a broken TIFF
    /// is skipped saying why, and so are single pages beside it (no stack); TIFFs beside a
    /// DICOM series are previews, not a volume. The stack's hash and upload cover its slices
    /// (the bundle decodes to the volume).
    #[test]
    fn tiff_stacks_are_volumes_by_directory_or_by_file() {
        use tiff::encoder::{colortype::Gray16, TiffEncoder};
        let dir = tempfile::tempdir().unwrap();
        let r = dir.path();
        std::fs::create_dir_all(r.join("scope/stack")).unwrap();
        // Slices 1..=10: slice10 is the last, not the second.
        for z in 1..=10u16 {
            let f = std::fs::File::create(r.join(format!("scope/stack/slice{z}.tif"))).unwrap();
            let mut e = TiffEncoder::new(f).unwrap();
            e.write_image::<Gray16>(3, 2, &[z; 6]).unwrap();
        }
        let f = std::fs::File::create(r.join("scope/vol.tif")).unwrap();
        let mut e = TiffEncoder::new(f).unwrap();
        for z in 0..4u16 {
            e.write_image::<Gray16>(2, 2, &[z; 4]).unwrap();
        }
        drop(e);
        std::fs::write(r.join("scope/broken.tif"), b"II*\0\x02\0\0\0").unwrap();
        let f = std::fs::File::create(r.join("scope/lonely.tif")).unwrap();
        TiffEncoder::new(f)
            .unwrap()
            .write_image::<Gray16>(2, 2, &[1; 4])
            .unwrap();
        // A DICOM series with a TIFF preview beside its slices.
        std::fs::create_dir_all(r.join("ct")).unwrap();
        let mut dcm = vec![0u8; 128];
        dcm.extend_from_slice(b"DICM");
        std::fs::write(r.join("ct/IM1"), &dcm).unwrap();
        let f = std::fs::File::create(r.join("ct/preview.tif")).unwrap();
        TiffEncoder::new(f)
            .unwrap()
            .write_image::<Gray16>(2, 2, &[1; 4])
            .unwrap();
        let s = scan(r).unwrap();
        let names: Vec<&str> = s.found.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, vec!["ct", "scope/stack", "scope/vol"]);
        let skipped: Vec<&Path> = s.skipped.iter().map(|(p, _)| p.as_path()).collect();
        assert_eq!(
            skipped,
            [r.join("scope/broken.tif"), r.join("scope/lonely.tif")],
            "{:?}",
            s.skipped
        );
        assert!(
            s.skipped[1].1.contains("single-page TIFF beside"),
            "{:?}",
            s.skipped
        );
        let stack = &s.found[1];
        assert_eq!(stack.path, r.join("scope/stack"));
        assert_eq!(source_listing(&stack.path, false).unwrap().files.len(), 10);
        let (spec, bytes) = job_spec(stack, &JobOptions::default(), true).unwrap();
        assert_eq!(
            source_digest(&stack.path, false).unwrap().0.to_vec(),
            spec.sha256
        );
        let src = SourceFiles::from_bytes(bytes.unwrap(), &stack.path).unwrap();
        let v = wavesplat_compressor::reader::decode_source(&src, None).unwrap();
        assert_eq!(v.dims(), [3, 2, 10]);
        let firsts: Vec<f32> = (0..10).map(|z| v.channel(0)[v.index(0, 0, z)]).collect();
        assert_eq!(firsts, (1..=10u16).map(f32::from).collect::<Vec<_>>());
        let v = wavesplat_compressor::reader::read_volume(&s.found[2].path, None).unwrap();
        assert_eq!(v.dims(), [2, 2, 4]);
    }

    /// A Zarr store is one volume named by its directory without `.zarr`, its chunks neither
    /// volumes nor skipped files; one with a time axis is a series; its listing is its
    /// metadata and chunks, and the bundle an upload carries decodes to the volume.
    #[test]
    fn zarr_stores_are_volumes_and_their_chunks_are_not() {
        let dir = tempfile::tempdir().unwrap();
        let r = dir.path();
        // A v2 array of 2 × 3 × 4 u8 samples (z, y, x) in two uncompressed chunks along z.
        let store = |path: &Path, shape: &str, chunks: &str, keys: &[&str]| {
            std::fs::create_dir_all(path).unwrap();
            let meta = format!(
                r#"{{"zarr_format": 2, "shape": [{shape}], "chunks": [{chunks}], "dtype": "|u1",
                    "compressor": null, "fill_value": 0, "order": "C", "filters": null}}"#
            );
            std::fs::write(path.join(".zarray"), meta).unwrap();
            for (k, key) in keys.iter().enumerate() {
                let samples: Vec<u8> = (0..12).map(|i| (12 * k + i) as u8).collect();
                let file = path.join(key);
                std::fs::create_dir_all(file.parent().unwrap()).unwrap();
                std::fs::write(file, samples).unwrap();
            }
        };
        store(
            &r.join("scope/cells.ome.zarr"),
            "2, 3, 4",
            "1, 3, 4",
            &["0.0.0", "1.0.0"],
        );
        store(
            &r.join("sim.zarr"),
            "2, 1, 3, 4",
            "1, 1, 3, 4",
            &["0.0.0.0", "1.0.0.0"],
        );
        std::fs::write(r.join("scope/notes.txt"), "not a volume").unwrap();
        // A group that is no image (a plate, say): skipped with the reason, not fatal.
        std::fs::create_dir_all(r.join("plate.zarr")).unwrap();
        std::fs::write(r.join("plate.zarr/.zgroup"), r#"{"zarr_format": 2}"#).unwrap();
        let s = scan(r).unwrap();
        let names: Vec<&str> = s.found.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, vec!["scope/cells", "sim"]);
        assert_eq!(s.skipped.len(), 1, "{:?}", s.skipped);
        assert_eq!(s.skipped[0].0, r.join("plate.zarr"));
        assert!(
            s.skipped[0].1.contains("no OME-Zarr image"),
            "{:?}",
            s.skipped
        );
        assert!(!is_series_source(&s.found[0].path, None));
        assert!(is_series_source(&s.found[1].path, None));
        let listing = source_listing(&s.found[0].path, false).unwrap();
        let files: Vec<&str> = listing.files.iter().map(|f| f.0.as_str()).collect();
        assert_eq!(files, [".zarray", "0.0.0", "1.0.0"]);
        let (spec, bytes) = job_spec(&s.found[0], &JobOptions::default(), true).unwrap();
        assert_eq!(
            source_digest(&s.found[0].path, false).unwrap().0.to_vec(),
            spec.sha256
        );
        let src = SourceFiles::from_bytes(bytes.unwrap(), Path::new("cells")).unwrap();
        let v = wavesplat_compressor::reader::decode_source(&src, None).unwrap();
        assert_eq!(v.dims(), [4, 3, 2]);
        assert_eq!(v.channel(0), (0..24u8).map(f32::from).collect::<Vec<_>>());
        // A store given as the archive's root is its one volume.
        let s = scan(&r.join("sim.zarr")).unwrap();
        assert_eq!(s.found.len(), 1, "{:?}", s.found);
        assert_eq!(s.found[0].name, "sim");
    }

    /// The names and channels a scan found, in order.
    fn names_and_channels(s: &Scan) -> Vec<(&str, Option<usize>)> {
        s.found
            .iter()
            .map(|f| (f.name.as_str(), f.channel))
            .collect()
    }

    /// The jobs of `found`, the channels of one source in order: job `c` carries channel `c`,
    /// and its upload decodes, with that channel, to `dims` voxels of `want(c)`.
    fn channel_jobs_read(found: &[Found], dims: [usize; 3], want: impl Fn(usize) -> Vec<f32>) {
        for (c, f) in found.iter().enumerate() {
            let (spec, bytes) = job_spec(f, &JobOptions::default(), true).unwrap();
            assert_eq!(spec.channel, Some(c as u32));
            let src = SourceFiles::from_bytes(bytes.unwrap(), &f.path).unwrap();
            let v =
                wavesplat_compressor::reader::decode_source_channel(&src, None, Some(c)).unwrap();
            assert_eq!(v.dims(), dims, "{}", f.name);
            assert_eq!(v.channel(0), want(c), "{}", f.name);
        }
    }

    /// A multi-file OME-TIFF is one volume, named by the file holding its XML, whose job
    /// carries every file, or by its OME companion file; its parts are no volumes (nor slices
    /// of a stack), and a part whose dataset's file is gone, does not name it or is neither a
    /// TIFF nor a companion file is skipped saying so.
    #[test]
    fn a_multi_file_ome_tiff_is_one_volume_of_all_its_files() {
        use tiff::encoder::{colortype::Gray16, TiffEncoder};
        use tiff::tags::Tag;
        let dir = tempfile::tempdir().unwrap();
        let r = dir.path();
        std::fs::create_dir_all(r.join("acq")).unwrap();
        std::fs::create_dir_all(r.join("lost")).unwrap();
        let uuid = |f: &str| format!(r#"<UUID FileName="{f}">urn:uuid:{f}</UUID>"#);
        let xml = format!(
            r#"<OME><Image ID="Image:0"><Pixels DimensionOrder="XYZCT" SizeX="2" SizeY="2" SizeZ="4" SizeC="1" SizeT="1"><TiffData IFD="0" PlaneCount="2">{}</TiffData><TiffData FirstZ="2" IFD="0">{}</TiffData><TiffData FirstZ="3" IFD="0">{}</TiffData></Pixels></Image></OME>"#,
            uuid("acq.ome.tif"),
            uuid("acq_1.ome.tif"),
            uuid("acq_2.ome.tif")
        );
        let part_of = |f: &str| format!(r#"<OME><BinaryOnly MetadataFile="{f}"/></OME>"#);
        let write = |path: &Path, slices: std::ops::Range<u16>, desc: &str| {
            let mut e = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
            for z in slices.clone() {
                let mut image = e.new_image::<Gray16>(2, 2).unwrap();
                if z == slices.start {
                    let tag = Tag::ImageDescription;
                    image.encoder().write_tag(tag, desc).unwrap();
                }
                image.write_data(&[10 * z; 4]).unwrap();
            }
        };
        write(&r.join("acq/acq.ome.tif"), 0..2, &xml);
        write(&r.join("acq/acq_1.ome.tif"), 2..3, &part_of("acq.ome.tif"));
        // A part with no OME description of its own: a part all the same.
        write(&r.join("acq/acq_2.ome.tif"), 3..4, "a plane");
        write(&r.join("lost/part.ome.tif"), 0..1, &part_of("gone.ome.tif"));
        // A part pointing at a file whose XML does not name it: skipped, saying so.
        write(&r.join("acq/acq_9.ome.tif"), 9..10, &part_of("acq.ome.tif"));
        // An OME companion file and the two files it places planes in: one volume named by it.
        std::fs::create_dir_all(r.join("companion")).unwrap();
        let companion_xml = format!(
            r#"<OME><Image ID="Image:0"><Pixels DimensionOrder="XYZCT" SizeX="2" SizeY="2" SizeZ="3" SizeC="1" SizeT="1"><TiffData IFD="0" PlaneCount="2">{}</TiffData><TiffData FirstZ="2" IFD="0">{}</TiffData></Pixels></Image></OME>"#,
            uuid("p.ome.tif"),
            uuid("q.ome.tif")
        );
        std::fs::write(r.join("companion/set.companion.ome"), companion_xml).unwrap();
        write(
            &r.join("companion/p.ome.tif"),
            0..2,
            &part_of("set.companion.ome"),
        );
        write(
            &r.join("companion/q.ome.tif"),
            2..3,
            &part_of("set.companion.ome"),
        );
        // A companion of one plane in one file: a volume too.
        std::fs::create_dir_all(r.join("single")).unwrap();
        let one_xml = format!(
            r#"<OME><Image ID="Image:0"><Pixels DimensionOrder="XYZCT" SizeX="2" SizeY="2" SizeZ="1" SizeC="1" SizeT="1"><TiffData IFD="0">{}</TiffData></Pixels></Image></OME>"#,
            uuid("x.ome.tif")
        );
        std::fs::write(r.join("single/one.companion.ome"), one_xml).unwrap();
        write(
            &r.join("single/x.ome.tif"),
            0..1,
            &part_of("one.companion.ome"),
        );
        // A part pointing at XML in a file that is neither: skipped, saying so.
        std::fs::create_dir_all(r.join("other")).unwrap();
        std::fs::write(r.join("other/set.xml"), "<OME/>").unwrap();
        write(&r.join("other/p.ome.tif"), 0..2, &part_of("set.xml"));
        let s = scan(r).unwrap();
        assert_eq!(
            names_and_channels(&s),
            [
                ("acq/acq.ome", None),
                ("companion/set", None),
                ("single/one", None)
            ]
        );
        assert_eq!(s.skipped.len(), 3, "{:?}", s.skipped);
        let (path, why) = &s.skipped[0];
        assert_eq!(path, &r.join("acq/acq_9.ome.tif"));
        assert!(why.contains("whose XML does not name it"), "{why}");
        let (path, why) = &s.skipped[2];
        assert_eq!(path, &r.join("other/p.ome.tif"));
        assert!(why.contains("neither a TIFF nor an OME companion"), "{why}");
        let (path, why) = &s.skipped[1];
        assert_eq!(path, &r.join("lost/part.ome.tif"));
        assert!(
            why.contains("gone.ome.tif") && why.contains("not there"),
            "{why}"
        );
        // The job's upload carries the three files, read as the four slices.
        let (_, bytes) = job_spec(&s.found[0], &JobOptions::default(), true).unwrap();
        let src = SourceFiles::from_bytes(bytes.unwrap(), &s.found[0].path).unwrap();
        assert_eq!(src.files.len(), 3);
        let v = wavesplat_compressor::reader::decode_source(&src, None).unwrap();
        assert_eq!(v.dims(), [2, 2, 4]);
        let want: Vec<f32> = (0..4).flat_map(|z| [10.0 * z as f32; 4]).collect();
        assert_eq!(v.channel(0), &want[..]);
        // The companion's job carries it and both files.
        let (_, bytes) = job_spec(&s.found[1], &JobOptions::default(), true).unwrap();
        let src = SourceFiles::from_bytes(bytes.unwrap(), &s.found[1].path).unwrap();
        assert_eq!(src.files.len(), 3);
        let v = wavesplat_compressor::reader::decode_source(&src, None).unwrap();
        assert_eq!(v.dims(), [2, 2, 3]);
        assert_eq!(v.channel(0), &want[..12]);
    }

    /// A Zarr array of several channels is a volume per channel, `NAME/cC`, each job reading
    /// its own; one of more channels than are submitted alone is skipped saying how to take
    /// them.
    #[test]
    fn a_zarr_array_of_several_channels_is_a_volume_per_channel() {
        let dir = tempfile::tempdir().unwrap();
        let r = dir.path();
        // c, z, y, x by xarray's names: u8 samples, each channel's 24 its own.
        let store = |name: &str, c: usize| {
            let path = r.join(name);
            std::fs::create_dir_all(&path).unwrap();
            let meta = format!(
                r#"{{"zarr_format": 2, "shape": [{c}, 2, 3, 4], "chunks": [1, 2, 3, 4],
                    "dtype": "|u1", "compressor": null, "fill_value": 0, "order": "C",
                    "filters": null}}"#
            );
            std::fs::write(path.join(".zarray"), meta).unwrap();
            let names = r#"{"_ARRAY_DIMENSIONS": ["c", "z", "y", "x"]}"#;
            std::fs::write(path.join(".zattrs"), names).unwrap();
            for k in 0..c.min(3) {
                let samples: Vec<u8> = (0..24).map(|i| (50 * k + i) as u8).collect();
                std::fs::write(path.join(format!("{k}.0.0.0")), samples).unwrap();
            }
        };
        store("multi.zarr", 3);
        store("spectral.zarr", MAX_CHANNEL_VOLUMES + 1);
        // Two stores named `dup`: the second's names `dup/c0`, `dup/c1` are taken by the
        // first's, so it is skipped, once, not submitted in part.
        store("dup.ome.zarr", 3);
        store("dup.zarr", 2);
        let s = scan(r).unwrap();
        let found = names_and_channels(&s);
        assert_eq!(
            found,
            [
                ("dup/c0", Some(0)),
                ("dup/c1", Some(1)),
                ("dup/c2", Some(2)),
                ("multi/c0", Some(0)),
                ("multi/c1", Some(1)),
                ("multi/c2", Some(2))
            ]
        );
        let skipped: Vec<&Path> = s.skipped.iter().map(|(p, _)| p.as_path()).collect();
        assert_eq!(
            skipped,
            [r.join("dup.zarr"), r.join("spectral.zarr")],
            "{:?}",
            s.skipped
        );
        assert!(s.skipped[0].1.contains("\"dup/c0\""), "{:?}", s.skipped);
        assert!(s.skipped[1].1.contains("--channel"), "{:?}", s.skipped);
        channel_jobs_read(&s.found[3..], [4, 3, 2], |c| {
            (0..24).map(|i| (50 * c + i) as f32).collect()
        });
        // The three jobs hash the same bytes; their keys differ by their names and channels.
        let keys: std::collections::HashSet<String> = s.found[3..]
            .iter()
            .map(|f| {
                job_spec(f, &JobOptions::default(), false)
                    .unwrap()
                    .0
                    .dedup_key()
            })
            .collect();
        assert_eq!(keys.len(), 3);
    }

    /// A multi-page TIFF storing channels as planes of their own (an ImageJ hyperstack) is a
    /// volume per channel, each job reading its own; a grey multi-page TIFF stays one volume.
    #[test]
    fn a_tiff_hyperstack_of_channels_is_a_volume_per_channel() {
        use tiff::encoder::{colortype::Gray16, TiffEncoder};
        use tiff::tags::Tag;
        let dir = tempfile::tempdir().unwrap();
        let r = dir.path();
        // Two channels of three slices of 2 × 2, ImageJ's order (channels fastest).
        let f = std::fs::File::create(r.join("cells.tif")).unwrap();
        let mut e = TiffEncoder::new(f).unwrap();
        for z in 0..3u16 {
            for c in 0..2u16 {
                let mut image = e.new_image::<Gray16>(2, 2).unwrap();
                if z == 0 && c == 0 {
                    let desc = "ImageJ=1.54f\nimages=6\nchannels=2\nslices=3\nhyperstack=true\n";
                    image
                        .encoder()
                        .write_tag(Tag::ImageDescription, desc)
                        .unwrap();
                }
                image.write_data(&[100 * c + z; 4]).unwrap();
            }
        }
        drop(e);
        let f = std::fs::File::create(r.join("grey.tif")).unwrap();
        let mut e = TiffEncoder::new(f).unwrap();
        for z in 0..2u16 {
            e.write_image::<Gray16>(2, 2, &[z; 4]).unwrap();
        }
        drop(e);
        // Single pages each describing two channels: no stack, skipped saying why.
        std::fs::create_dir_all(r.join("split")).unwrap();
        for z in 0..2u16 {
            let f = std::fs::File::create(r.join(format!("split/p{z}.tif"))).unwrap();
            let mut e = TiffEncoder::new(f).unwrap();
            let mut image = e.new_image::<Gray16>(2, 2).unwrap();
            let desc = "ImageJ=1.54f\nimages=1\nchannels=2\nslices=1\nhyperstack=true\n";
            image
                .encoder()
                .write_tag(Tag::ImageDescription, desc)
                .unwrap();
            image.write_data(&[z; 4]).unwrap();
        }
        let s = scan(r).unwrap();
        assert_eq!(s.skipped.len(), 2, "{:?}", s.skipped);
        assert!(
            s.skipped
                .iter()
                .all(|(p, why)| p.starts_with(r.join("split")) && why.contains("do not add up")),
            "{:?}",
            s.skipped
        );
        let found = names_and_channels(&s);
        assert_eq!(
            found,
            [("cells/c0", Some(0)), ("cells/c1", Some(1)), ("grey", None)],
            "{:?}",
            s.skipped
        );
        channel_jobs_read(&s.found[..2], [2, 2, 3], |c| {
            (0..3).flat_map(|z| [(100 * c + z) as f32; 4]).collect()
        });
    }

    /// A job names the same content whether its source is uploaded or named by path: files
    /// hashed in pieces (raw, NIfTI, MetaImage) and sources of several files streamed file by
    /// file (a detached header with its data, a DICOM series directory) alike.
    #[test]
    fn a_source_hashes_alike_by_path_and_by_upload() {
        let dir = tempfile::tempdir().unwrap();
        let r = dir.path();
        let data: Vec<u8> = (0..(5 << 20) + 3).map(|i| (i % 253) as u8).collect();
        std::fs::write(r.join("c_4x4x4_u8.raw"), &data).unwrap();
        std::fs::write(r.join("a.nii"), &data).unwrap();
        std::fs::write(r.join("vol.nhdr"), "NRRD0004\ndata file: v.raw\n").unwrap();
        std::fs::write(r.join("v.raw"), b"x").unwrap();
        std::fs::create_dir_all(r.join("series")).unwrap();
        for (i, f) in ["IM1", "IM2", "IM3"].iter().enumerate() {
            let mut dcm = vec![0u8; 128];
            dcm.extend_from_slice(b"DICM");
            dcm.extend(data.iter().skip(i).take(1 << 20));
            std::fs::write(r.join("series").join(f), &dcm).unwrap();
        }
        let s = scan(r).unwrap();
        assert_eq!(s.found.len(), 4, "{:?}", s.found);
        for f in &s.found {
            let (by_path, none) = job_spec(f, &JobOptions::default(), false).unwrap();
            let (by_upload, bytes) = job_spec(f, &JobOptions::default(), true).unwrap();
            assert!(none.is_none());
            let bytes = bytes.expect("an upload carries its bytes");
            assert_eq!(by_path.sha256, by_upload.sha256, "{}", f.name);
            assert_eq!(by_upload.sha256, wavesplat_net::digest::sha256(&bytes));
            assert!(matches!(by_path.source, Source::Path(_)));
            let streamed = source_digest(&f.path, f.raw.is_some()).unwrap();
            assert_eq!(streamed.0.to_vec(), by_path.sha256, "{}", f.name);
            assert_eq!(streamed.1, bytes.len() as u64, "{}", f.name);
        }
    }
}
