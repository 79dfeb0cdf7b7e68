//! A time series stored as one volume file per time step in a directory (`step_0000.nii.gz`,
//! `step_0001.nii.gz` …, as simulation codes and many exports write them): the files whose
//! names end in a volume format's extension (NIfTI, NRRD, MetaImage; raw `.raw` files with a
//! raw spec), ordered by the last number in their names, each opened for region reads.
//! Every step must be of the first's dimensions, channels and spacing, and the numbers must
//! go up by one stride: a repeated, missing or unnumbered step is an error naming it, not a
//! series silently missing a time point. A directory of DICOM files is not a series of steps
//! (it is read as a DICOM series).

use std::path::{Path, PathBuf};

use super::region::RegionReader;
use super::{Format, RawSpec, ReadError};

/// The time steps of a directory, opened.
#[derive(Debug)]
pub struct StepSeries {
    dir: PathBuf,
    steps: Vec<RegionReader>,
    numbers: Vec<u64>,
}

/// The volume files of `dir` a series of steps is made of: those named as NIfTI, NRRD or
/// MetaImage (their detached data files, `.raw` and the like, are not steps), else, with a raw
/// spec, the `.raw` files. Empty when the directory holds none (e.g. a DICOM series).
pub fn step_files(dir: &Path, raw: Option<&RawSpec>) -> Result<Vec<PathBuf>, ReadError> {
    let mut headers = Vec::new();
    let mut raws = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| ReadError::io(dir, e))? {
        let entry = entry.map_err(|e| ReadError::io(dir, e))?;
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().to_ascii_lowercase();
        if name.starts_with('.') || !path.is_file() {
            continue;
        }
        match Format::from_name(&path) {
            Some(Format::Nifti | Format::Nrrd | Format::MetaImage) => headers.push(path),
            _ if name.ends_with(".raw") => raws.push(path),
            _ => {}
        }
    }
    Ok(match (headers.is_empty(), raw) {
        (false, _) => headers,
        (true, Some(_)) => raws,
        (true, None) => Vec::new(),
    })
}

/// The last run of digits in a file's name (without its extensions), as a number.
fn step_number(path: &Path) -> Option<u64> {
    let name = path.file_name()?.to_string_lossy().into_owned();
    let stem = name.split('.').next().unwrap_or(&name);
    let digits: String = stem
        .chars()
        .rev()
        .skip_while(|c| !c.is_ascii_digit())
        .take_while(char::is_ascii_digit)
        .collect::<Vec<_>>()
        .into_iter()
        .rev()
        .collect();
    digits.parse().ok()
}

impl StepSeries {
    /// Opens the steps of `dir` (see [`step_files`]); at least two.
    pub fn open(dir: &Path, raw: Option<&RawSpec>) -> Result<StepSeries, ReadError> {
        let bad = |reason: String| ReadError::Region {
            path: dir.to_path_buf(),
            reason,
        };
        let files = step_files(dir, raw)?;
        if files.len() < 2 {
            return Err(bad(format!(
                "{} volume file(s); a series of time steps needs at least two, named with \
                 their step numbers (step_0000.nii.gz, step_0001.nii.gz, …)",
                files.len()
            )));
        }
        let mut numbered = Vec::with_capacity(files.len());
        for f in files {
            let n = step_number(&f).ok_or_else(|| {
                bad(format!(
                    "{} has no step number in its name",
                    f.file_name().unwrap_or_default().to_string_lossy()
                ))
            })?;
            numbered.push((n, f));
        }
        numbered.sort();
        let name = |p: &Path| {
            p.file_name()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned()
        };
        if let Some(w) = numbered.windows(2).find(|w| w[0].0 == w[1].0) {
            return Err(bad(format!(
                "step {} is repeated: {} and {}",
                w[0].0,
                name(&w[0].1),
                name(&w[1].1)
            )));
        }
        let stride = numbered[1].0 - numbered[0].0;
        if let Some(w) = numbered.windows(2).find(|w| w[1].0 - w[0].0 != stride) {
            return Err(bad(format!(
                "step {} is missing: the steps go by {stride} from {}, and {} comes after {}",
                w[0].0 + stride,
                numbered[0].0,
                name(&w[1].1),
                name(&w[0].1)
            )));
        }
        let mut steps: Vec<RegionReader> = Vec::with_capacity(numbered.len());
        for (_, path) in &numbered {
            let r = RegionReader::open(path, raw)?;
            if let Some(first) = steps.first() {
                let differs = if r.dims() != first.dims() {
                    Some(format!(
                        "dimensions {:?} against {:?}",
                        r.dims(),
                        first.dims()
                    ))
                } else if r.channels() != first.channels() {
                    Some(format!(
                        "{} channel(s) against {}",
                        r.channels(),
                        first.channels()
                    ))
                } else if r.spacing() != first.spacing() {
                    Some(format!(
                        "spacing {:?} against {:?}",
                        r.spacing(),
                        first.spacing()
                    ))
                } else {
                    None
                };
                if let Some(d) = differs {
                    return Err(bad(format!(
                        "{} does not match {}: {d}",
                        name(path),
                        name(first.path())
                    )));
                }
            }
            steps.push(r);
        }
        Ok(StepSeries {
            dir: dir.to_path_buf(),
            numbers: numbered.into_iter().map(|(n, _)| n).collect(),
            steps,
        })
    }

    /// The steps, in order.
    pub fn steps(&self) -> &[RegionReader] {
        &self.steps
    }

    /// Each step's number (from its file's name).
    pub fn numbers(&self) -> &[u64] {
        &self.numbers
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn step_numbers_are_the_last_digits_of_the_name() {
        let n = |s: &str| step_number(Path::new(s));
        assert_eq!(n("step_0012.nii.gz"), Some(12));
        assert_eq!(n("run3_t007.nrrd"), Some(7));
        assert_eq!(n("t10x.mha"), Some(10));
        assert_eq!(n("final.nii"), None);
    }
}
