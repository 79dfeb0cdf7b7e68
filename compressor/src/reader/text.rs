//! Small helpers shared by the text-header readers (NRRD, MetaImage): bounded header scanning,
//! number lists and parenthesised vectors, sample type names, and the LPS conversion and
//! validation of a grid given by per-axis vectors.

use std::path::Path;

use super::{ReadError, SampleType};
use wavesplat_codec::volume::{Placement, PLACEMENT_TOLERANCE};

/// Largest text header accepted (bytes); real headers are a few hundred bytes.
pub(crate) const MAX_TEXT_HEADER: usize = 1 << 20;

/// How much of a file every reader of a text header reads to parse it (the listing, the
/// region reader): enough for a last line that starts within [`MAX_TEXT_HEADER`] and is that
/// long, and one byte more, so that a line cut by the window is seen to be too long.
pub(crate) const TEXT_HEADER_WINDOW: u64 = 2 * MAX_TEXT_HEADER as u64 + 2;

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

/// Most data files one detached header may name (a list or a pattern): a slice per file of
/// the largest volumes is tens of thousands; with the header, a volume's sources are at most
/// [`super::MAX_SOURCE_FILES`].
pub(crate) const MAX_DATA_FILES: usize = super::MAX_SOURCE_FILES - 1;

/// The files a detached header's data-file value (NRRD `data file`, MetaImage
/// `ElementDataFile`) names, in the order their samples follow one another.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct DataFileNames {
    /// The names, relative to the header's directory.
    pub names: Vec<String>,
    /// The dimension of each file's data, when the value gives it (`LIST 2`, `LIST 2D`, a
    /// pattern's fifth word); else each file of a list or a pattern holds one slice along the
    /// slowest axis.
    pub file_dim: Option<usize>,
    /// Whether the value is one name (the file holds all the samples), not a list or a
    /// pattern.
    pub single: bool,
}

/// Reads a data-file value: one name (spaces allowed, as teem and MetaIO read it); `LIST`
/// (optionally with each file's dimension) followed by one name per non-empty line of
/// `following` (the header's lines after it); or a printf pattern `FORMAT MIN MAX STEP
/// [DIM]`, whose format has one `%d` (`%i`, `%u`; a `0` flag and a width allowed; `%%` is a
/// percent sign), expanded from MIN to MAX by STEP (which may be negative) as teem and MetaIO
/// expand it. `Err` says what is wrong with the value.
pub(crate) fn data_file_names(value: &str, following: &[String]) -> Result<DataFileNames, String> {
    let dim_of = |d: &str| -> Result<usize, String> {
        d.strip_suffix(['D', 'd'])
            .unwrap_or(d)
            .parse::<usize>()
            .ok()
            .filter(|d| *d >= 1)
            .ok_or_else(|| format!("{d:?} is not a file dimension (1 or more)"))
    };
    if is_file_list(value) {
        let file_dim = value.split_whitespace().nth(1).map(dim_of).transpose()?;
        let names: Vec<String> = following
            .iter()
            .map(|l| l.trim_end().to_string())
            .filter(|l| !l.trim().is_empty())
            .collect();
        if names.is_empty() {
            return Err("LIST names no file on the lines after it".into());
        }
        if names.len() > MAX_DATA_FILES {
            return Err(format!("LIST names more than {MAX_DATA_FILES} files"));
        }
        return Ok(DataFileNames {
            names,
            file_dim,
            single: false,
        });
    }
    if value.contains('%') {
        let words: Vec<&str> = value.split_whitespace().collect();
        if !(4..=5).contains(&words.len()) {
            return Err(format!(
                "{value:?}: a file name pattern is FORMAT MIN MAX STEP [DIM]"
            ));
        }
        let number = |w: &str| {
            w.parse::<i64>()
                .map_err(|_| format!("{value:?}: {w:?} is not a whole number"))
        };
        let (min, max, step) = (number(words[1])?, number(words[2])?, number(words[3])?);
        let file_dim = words.get(4).map(|d| dim_of(d)).transpose()?;
        if step == 0 || (step > 0 && min > max) || (step < 0 && min < max) {
            return Err(format!(
                "{value:?}: from {min} by {step} never reaches {max}"
            ));
        }
        let count = (max.abs_diff(min) / step.unsigned_abs()).saturating_add(1);
        if count > MAX_DATA_FILES as u64 {
            return Err(format!(
                "{value:?} names {count} files, more than {MAX_DATA_FILES}"
            ));
        }
        let format = PrintfInteger::parse(words[0]).map_err(|e| format!("{value:?}: {e}"))?;
        // Each number lies between MIN and MAX; the steps to it are counted in i128, where
        // they cannot overflow.
        let names = (0..count)
            .map(|k| format.format(i128::from(min) + i128::from(k) * i128::from(step)))
            .collect();
        return Ok(DataFileNames {
            names,
            file_dim,
            single: false,
        });
    }
    if value.is_empty() {
        return Err("it names no file".into());
    }
    Ok(DataFileNames {
        names: vec![value.to_string()],
        file_dim: None,
        single: true,
    })
}

/// Bytes of each data file's piece when the files `named` hold a sample stream of `total`
/// bytes whose axes have `sizes` (fastest first): all of it for one named file; else each file
/// holds `file_dim` of the axes (by default all but the slowest), and there must be one file
/// per sample of the remaining axes. With `slabs` (NRRD, as teem reads it), files of every axis
/// are slabs: the slowest axis divides evenly among them. `Err` says what does not match.
pub(crate) fn piece_bytes(
    sizes: &[u64],
    named: &DataFileNames,
    total: u64,
    slabs: bool,
) -> Result<u64, String> {
    if named.single {
        return Ok(total);
    }
    let files = named.names.len();
    let dim = named
        .file_dim
        .unwrap_or(sizes.len().saturating_sub(1).max(1));
    if dim > sizes.len() {
        return Err(format!(
            "each file of {dim} dimensions, of a volume of {}",
            sizes.len()
        ));
    }
    if slabs && dim == sizes.len() && files > 1 {
        let slowest = sizes.last().copied().unwrap_or(1);
        if slowest % files as u64 != 0 {
            return Err(format!(
                "{files} files named, each a slab of the slowest axis, whose {slowest} samples \
                 do not divide among them"
            ));
        }
        return Ok(total / files as u64);
    }
    let wanted = sizes[dim..]
        .iter()
        .try_fold(1u64, |acc, s| acc.checked_mul(*s))
        .unwrap_or(u64::MAX);
    if wanted != files as u64 {
        return Err(format!(
            "{files} files named, where sizes {sizes:?} in files of {dim} dimensions make {wanted}"
        ));
    }
    Ok(total / wanted.max(1))
}

/// A printf format with one integer conversion (`%d`, `%i`, `%u`, with an optional `0` flag
/// and width), the only kind teem's and MetaIO's file name patterns use. Written here: a
/// format string from an untrusted header must not reach a C-style formatter, and no crate
/// formats one integer into a runtime printf pattern safely.
struct PrintfInteger {
    before: String,
    after: String,
    zero: bool,
    width: usize,
}

impl PrintfInteger {
    fn parse(format: &str) -> Result<PrintfInteger, String> {
        let mut parts = (String::new(), String::new());
        let mut conversion: Option<(bool, usize)> = None;
        let mut chars = format.chars().peekable();
        while let Some(c) = chars.next() {
            let out = if conversion.is_some() {
                &mut parts.1
            } else {
                &mut parts.0
            };
            if c != '%' {
                out.push(c);
                continue;
            }
            if chars.peek() == Some(&'%') {
                chars.next();
                out.push('%');
                continue;
            }
            if conversion.is_some() {
                return Err("more than one % conversion".into());
            }
            let zero = chars.next_if_eq(&'0').is_some();
            let mut width = 0usize;
            while let Some(d) = chars.next_if(char::is_ascii_digit) {
                width = width * 10 + d.to_digit(10).unwrap_or(0) as usize;
                if width > 32 {
                    return Err("a field width over 32".into());
                }
            }
            match chars.next() {
                Some('d' | 'i' | 'u') => conversion = Some((zero, width)),
                other => {
                    return Err(format!(
                        "the conversion %{} is not an integer's (%d)",
                        other.map(String::from).unwrap_or_default()
                    ))
                }
            }
        }
        let (zero, width) = conversion.ok_or("no %d in the format")?;
        Ok(PrintfInteger {
            before: parts.0,
            after: parts.1,
            zero,
            width,
        })
    }

    fn format(&self, n: i128) -> String {
        let digits = n.unsigned_abs().to_string();
        let sign = if n < 0 { "-" } else { "" };
        let pad = self.width.saturating_sub(sign.len() + digits.len());
        let number = if self.zero {
            format!("{sign}{}{digits}", "0".repeat(pad))
        } else {
            format!("{}{sign}{digits}", " ".repeat(pad))
        };
        format!("{}{number}{}", self.before, self.after)
    }
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

    /// Data-file values as teem and MetaIO read them: one name (spaces kept), a list with or
    /// without each file's dimension, and printf patterns counting up or down; bad ones say
    /// what is wrong.
    #[test]
    fn data_file_values_name_their_files_in_order() {
        let lines = |l: &[&str]| l.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let one = data_file_names("CT scan.raw", &[]).unwrap();
        assert_eq!(
            (one.names, one.file_dim),
            (vec!["CT scan.raw".to_string()], None)
        );
        assert!(one.single);
        let list = data_file_names("LIST", &lines(&["a.raw", "", "b c.raw  ", "c.raw"])).unwrap();
        assert_eq!(list.names, ["a.raw", "b c.raw", "c.raw"]);
        assert_eq!(list.file_dim, None);
        assert!(!list.single);
        assert_eq!(
            data_file_names("LIST 2D", &lines(&["a"])).unwrap().file_dim,
            Some(2)
        );
        assert_eq!(
            data_file_names("LIST 3", &lines(&["a"])).unwrap().file_dim,
            Some(3)
        );
        let up = data_file_names("s%03d.raw 1 10 4", &[]).unwrap();
        assert_eq!(up.names, ["s001.raw", "s005.raw", "s009.raw"]);
        let down = data_file_names("v%d_%%.raw 2 -1 -1 2", &[]).unwrap();
        assert_eq!(
            down.names,
            ["v2_%.raw", "v1_%.raw", "v0_%.raw", "v-1_%.raw"]
        );
        assert_eq!(down.file_dim, Some(2));
        assert_eq!(data_file_names("x%4i 7 7 1", &[]).unwrap().names, ["x   7"]);
        assert_eq!(
            data_file_names("x%03u -5 -5 1", &[]).unwrap().names,
            ["x-05"]
        );
        for bad in [
            "",
            "s%03d.raw 1 10",
            "s%03d.raw 1 10 0",
            "s%03d.raw 10 1 1",
            "s%03d.raw 1 10 -1",
            "s%s.raw 1 2 1",
            "s%d%d.raw 1 2 1",
            "s.raw% 1 2 1",
            "s%d.raw 1 2 1 0",
            "s%d.raw 0 99999999 1",
            "s%99d.raw 1 2 1",
            "s%d.raw a 2 1",
        ] {
            assert!(data_file_names(bad, &[]).is_err(), "{bad:?} accepted");
        }
        assert!(data_file_names("LIST", &lines(&["", "  "])).is_err());
        assert!(data_file_names("LIST 0", &lines(&["a"])).is_err());
    }

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
            let d = data_file_names(one, &["x.raw".to_string()]).unwrap();
            assert_eq!(d.names, [one], "{one}");
        }
        for several in [
            "LIST",
            "list",
            "LIST 2",
            "LIST 2D",
            "vol%03d.raw 1 10 1",
            "v%d.raw 0 4 1 2",
        ] {
            let d = data_file_names(several, &["x.raw".into(), "y.raw".into()]).unwrap();
            assert!(d.names.len() >= 2, "{several}");
        }
    }
}
