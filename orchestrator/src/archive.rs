//! Scanning a volume archive (a directory tree) for supported files and turning each into a
//! [`JobSpec`].
//!
//! Supported files:
//! - NIfTI-1: `*.nii`, `*.nii.gz` (scalar or RGB24; the header describes the data);
//! - headerless raw, described by its name: `NAME_XxYxZ_DTYPE[_rgb][_be].raw`, e.g.
//!   `head_256x256x128_u16.raw`, `cells_64x64x64_u8_rgb.raw`, `ct_512x512x300_i16_be.raw`.
//!   DTYPE is `u8`, `u16`, `i16` or `f32`; `_rgb` means 3 channels interleaved per voxel;
//!   `_be` big-endian samples (little-endian otherwise); x varies fastest.
//!
//! The volume's name in the cache is its path relative to the archive root without the
//! extension and (for raw files) without the layout suffix: `ct/head_64x64x32_u8.raw` → `ct/head`.
//! Hidden files are ignored; `.raw` files whose name does not follow the convention, and names
//! used twice, are reported as skipped. Other files are ignored.

use crate::model::{JobOptions, JobSpec, RawLayout, SampleType, Source};
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// A supported file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Found {
    /// The file.
    pub path: PathBuf,
    /// Its name in the cache.
    pub name: String,
    /// Raw layout (`None`: NIfTI).
    pub raw: Option<RawLayout>,
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

fn walk(dir: &Path, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)?.collect::<Result<_, _>>()?;
    entries.sort_by_key(|e| e.file_name());
    for e in entries {
        if e.file_name().to_string_lossy().starts_with('.') {
            continue;
        }
        let ty = e.file_type()?;
        if ty.is_dir() {
            walk(&e.path(), out)?;
        } else {
            out.push(e.path());
        }
    }
    Ok(())
}

/// Scans `root` recursively.
pub fn scan(root: &Path) -> std::io::Result<Scan> {
    let mut files = Vec::new();
    walk(root, &mut files)?;
    let mut scan = Scan::default();
    let mut names = HashSet::new();
    for path in files {
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
        let (base, raw) = if let Some(s) = lower
            .strip_suffix(".nii.gz")
            .or_else(|| lower.strip_suffix(".nii"))
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
        if !names.insert(name.clone()) {
            scan.skipped
                .push((path, format!("another file already uses the name {name:?}")));
            continue;
        }
        scan.found.push(Found { path, name, raw });
    }
    Ok(scan)
}

/// Builds the job for a found file: reads it to hash it; with `upload`, the bytes are returned
/// to be streamed with the submission, otherwise the job names the file's absolute path
/// (which every worker must be able to read).
pub fn job_spec(
    found: &Found,
    options: &JobOptions,
    upload: bool,
) -> std::io::Result<(JobSpec, Option<Vec<u8>>)> {
    let bytes = std::fs::read(&found.path)?;
    let sha256 = crate::sha256(&bytes);
    let source = if upload {
        Source::Upload {
            size: bytes.len() as u64,
        }
    } else {
        Source::Path(std::fs::canonicalize(&found.path)?)
    };
    let spec = JobSpec {
        name: found.name.clone(),
        source,
        sha256,
        raw: found.raw.clone(),
        options: options.clone(),
    };
    Ok((spec, upload.then_some(bytes)))
}

#[cfg(test)]
mod tests {
    use super::*;

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
        ] {
            std::fs::write(r.join(f), b"x").unwrap();
        }
        let s = scan(r).unwrap();
        let names: Vec<&str> = s.found.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, vec!["a", "c", "sub/b"]);
        assert_eq!(s.skipped.len(), 2, "{:?}", s.skipped);
    }
}
