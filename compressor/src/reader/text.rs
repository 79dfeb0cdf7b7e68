//! Small helpers shared by the text-header readers (NRRD, MetaImage): bounded header scanning,
//! number lists and parenthesised vectors, sample type names, and the LPS conversion and
//! validation of a grid given by per-axis vectors.

use std::path::Path;

use super::{ReadError, SampleType};
use wavesplat_codec::volume::{Placement, PLACEMENT_TOLERANCE};

/// Largest text header accepted (bytes); real headers are a few hundred bytes.
pub(crate) const MAX_TEXT_HEADER: usize = 1 << 20;

/// Splits `bytes` into header lines up to (not including) the line for which `is_end` holds
/// (that line is consumed) or the end of the input; returns the lines (without `\r\n` / `\n`)
/// and the offset just past the last consumed line. `None` if the header is not valid UTF-8
/// or exceeds [`MAX_TEXT_HEADER`] before it ends.
pub(crate) fn header_lines(
    bytes: &[u8],
    mut is_end: impl FnMut(&str) -> bool,
    inclusive: bool,
) -> Option<(Vec<String>, usize, bool)> {
    let mut lines = Vec::new();
    let mut pos = 0;
    while pos < bytes.len() {
        if pos > MAX_TEXT_HEADER {
            return None;
        }
        let rest = &bytes[pos..];
        let (line, next) = match rest.iter().position(|b| *b == b'\n') {
            Some(i) => (&rest[..i], pos + i + 1),
            None => (rest, bytes.len()),
        };
        if next - pos > MAX_TEXT_HEADER {
            return None;
        }
        let line = std::str::from_utf8(line).ok()?;
        let line = line.strip_suffix('\r').unwrap_or(line);
        if is_end(line) {
            if inclusive {
                lines.push(line.to_string());
            }
            return Some((lines, next, true));
        }
        lines.push(line.to_string());
        pos = next;
    }
    Some((lines, bytes.len(), false))
}

/// Whitespace-separated numbers (`nan` and `inf` parse too, and are caught by the callers'
/// range checks).
pub(crate) fn numbers(s: &str) -> Option<Vec<f64>> {
    s.split_whitespace()
        .map(|t| t.parse::<f64>().ok())
        .collect()
}

/// Whitespace-separated non-negative integers.
pub(crate) fn sizes(s: &str) -> Option<Vec<u64>> {
    s.split_whitespace()
        .map(|t| t.parse::<u64>().ok())
        .collect()
}

/// A parenthesised vector `(x, y, z)`.
pub(crate) fn vector(s: &str) -> Option<Vec<f64>> {
    let inner = s.trim().strip_prefix('(')?.strip_suffix(')')?;
    inner
        .split(',')
        .map(|t| t.trim().parse::<f64>().ok())
        .collect()
}

/// The items of a list of parenthesised vectors and `none`s, e.g.
/// `none (1,0,0) (0, 1, 0) (0,0,1)`.
pub(crate) fn vector_items(s: &str) -> Option<Vec<Option<Vec<f64>>>> {
    let mut out = Vec::new();
    let mut rest = s.trim();
    while !rest.is_empty() {
        if let Some(r) = rest.strip_prefix("none") {
            out.push(None);
            rest = r.trim_start();
        } else if rest.starts_with('(') {
            let end = rest.find(')')?;
            out.push(Some(vector(&rest[..=end])?));
            rest = rest[end + 1..].trim_start();
        } else {
            return None;
        }
    }
    Some(out)
}

/// Per-axis vectors (voxel steps, in the file's world frame) to spacing and, when `to_lps` is
/// given (the frame is anatomical), a validated placement. Zero, non-finite or sheared vectors
/// are header errors naming `field`.
pub(crate) fn grid_from_vectors(
    path: &Path,
    format: &'static str,
    field: &str,
    vectors: [[f64; 3]; 3],
    origin: Option<[f64; 3]>,
    to_lps: Option<[f64; 3]>,
) -> Result<([f32; 3], Option<Placement>), ReadError> {
    let mut spacing = [1.0f32; 3];
    let mut directions = [[0.0; 3]; 3];
    for (a, v) in vectors.iter().enumerate() {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let s = n as f32;
        if !(n.is_finite() && s.is_finite() && s > 0.0) {
            return Err(ReadError::bad_header(
                path,
                format,
                format!("{field}: the vector of axis {a} {v:?} gives spacing {n}; it must be finite and positive"),
            ));
        }
        spacing[a] = s;
        directions[a] = v.map(|c| c / n);
    }
    let Some(sign) = to_lps else {
        return Ok((spacing, None));
    };
    let flip = |v: [f64; 3]| [v[0] * sign[0], v[1] * sign[1], v[2] * sign[2]];
    let p = Placement {
        origin: flip(origin.unwrap_or([0.0; 3])),
        directions: directions.map(flip),
    };
    p.validate().map_err(|e| {
        ReadError::bad_header(
            path,
            format,
            format!("{field}: {e} (tolerance {PLACEMENT_TOLERANCE})"),
        )
    })?;
    Ok((spacing, Some(p)))
}

/// A finite origin, or a header error naming `field`.
pub(crate) fn origin3(
    path: &Path,
    format: &'static str,
    field: &str,
    v: &[f64],
) -> Result<[f64; 3], ReadError> {
    match v {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok([*x, *y, *z]),
        _ => Err(ReadError::bad_header(
            path,
            format,
            format!("{field} {v:?} must be three finite numbers"),
        )),
    }
}

/// Whether a detached header's data-file value (NRRD `data file`, MetaImage
/// `ElementDataFile`) is a list of files: `LIST`, optionally followed by the dimension of each
/// file (NRRD `LIST 2`, MetaIO `LIST 2D`; the file names follow the header's last line).
pub(crate) fn is_file_list(value: &str) -> bool {
    let mut t = value.split_whitespace();
    t.next().is_some_and(|f| f.eq_ignore_ascii_case("LIST"))
        && t.next().is_none_or(|d| {
            let d = d.strip_suffix(['D', 'd']).unwrap_or(d);
            d.parse::<u64>().is_ok()
        })
        && t.next().is_none()
}

/// Whether a detached header's data-file value names several files: a list
/// ([`is_file_list`]) or a printf pattern (`vol%03d.raw 1 10 1`). Any other value is one file
/// name, spaces included (`CT scan.raw`), as teem and ITK's MetaIO read it.
pub(crate) fn names_several_files(value: &str) -> bool {
    is_file_list(value) || value.contains('%')
}

/// NRRD type names (all the spellings of the NRRD spec).
pub(crate) fn nrrd_type(name: &str) -> Option<SampleType> {
    Some(match name.trim() {
        "signed char" | "int8" | "int8_t" => SampleType::I8,
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => SampleType::U8,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => {
            SampleType::I16
        }
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => {
            SampleType::U16
        }
        "int" | "signed int" | "int32" | "int32_t" => SampleType::I32,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => SampleType::U32,
        "longlong"
        | "long long"
        | "long long int"
        | "signed long long"
        | "signed long long int"
        | "int64"
        | "int64_t" => SampleType::I64,
        "ulonglong" | "unsigned long long" | "unsigned long long int" | "uint64" | "uint64_t" => {
            SampleType::U64
        }
        "float" => SampleType::F32,
        "double" => SampleType::F64,
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_lists_and_vectors() {
        assert_eq!(numbers(" 1 2.5\t-3 "), Some(vec![1.0, 2.5, -3.0]));
        assert_eq!(numbers("1 x"), None);
        assert_eq!(sizes("4 5 6"), Some(vec![4, 5, 6]));
        assert_eq!(sizes("4 -5"), None);
        assert_eq!(vector("(1, 2,3)"), Some(vec![1.0, 2.0, 3.0]));
        assert_eq!(vector("1,2,3"), None);
        assert_eq!(
            vector_items("none (1,0,0) (0, 2, 0)"),
            Some(vec![
                None,
                Some(vec![1.0, 0.0, 0.0]),
                Some(vec![0.0, 2.0, 0.0])
            ])
        );
        assert_eq!(vector_items("(1,0,0"), None);
        assert_eq!(vector_items("bogus"), None);
        let (lines, end, found) = header_lines(b"a\r\nb\n\ndata", |l| l.is_empty(), false).unwrap();
        assert_eq!((lines, end, found), (vec!["a".into(), "b".into()], 6, true));
        assert!(header_lines(&[0xff, b'\n'], |_| false, false).is_none());
    }

    #[test]
    fn one_data_file_name_may_hold_spaces() {
        for one in [
            "CT scan.raw",
            "Patient 1.raw.gz",
            "LIST of scans.raw",
            "a.raw",
            "LISTING",
        ] {
            assert!(!names_several_files(one), "{one}");
        }
        for several in [
            "LIST",
            "list",
            "LIST 2",
            "LIST 2D",
            "vol%03d.raw 1 10 1",
            "v%d.raw 0 4 1 2",
        ] {
            assert!(names_several_files(several), "{several}");
        }
    }
}
