//! NRRD: the text header is parsed for the sizes, sample type, encoding, byte order and data
//! location (attached, detached, or after skipped lines or bytes), and its meaning taken from
//! the NRRD decoder on a stand-in with each size cut to one or two voxels.

use std::fs::File;
use std::io::{self, BufRead, BufReader, Seek, SeekFrom};
use std::path::Path;

use super::super::{read_whole, Opened};
use super::{file_name, parent, spool_pieces, stand_in, stored_bytes, stored_pieces, text_header};
use crate::reader::text::{self, header_lines};
use crate::reader::{Endian, Format, ReadError};

/// A NRRD stand-in size: 1 and 3 kept (they decide which axis of a 4D volume holds the
/// channels), 0 kept (refused), any other size 2.
fn nrrd_stand_in_size(s: u64) -> u64 {
    match s {
        0 | 1 | 3 => s,
        _ => 2,
    }
}

pub(super) fn open_nrrd(path: &Path) -> Result<Opened, ReadError> {
    const FORMAT: &str = "NRRD";
    let bad = |reason: String| ReadError::bad_header(path, FORMAT, reason);
    let (prefix, len) = text_header(path)?;
    if !prefix.starts_with(b"NRRD000") {
        return Err(bad("the file does not start with the magic NRRD000N".into()));
    }
    let (lines, end, found) = header_lines(&prefix, |l| l.is_empty(), false)
        .ok_or_else(|| bad("the header is not UTF-8 text or is longer than 1 MiB".into()))?;

    // The fields that say where the samples are; every other line goes to the stand-in.
    let mut probe = format!("{}\n", lines[0]);
    let mut sizes: Option<Vec<u64>> = None;
    let mut encoding: Option<String> = None;
    let mut sample = None;
    let mut endian = None;
    let (mut byte_skip, mut line_skip) = (0i64, 0u64);
    for line in lines.iter().skip(1) {
        let keep = match line.split_once(": ") {
            Some(_) if line.starts_with('#') || line.contains(":=") => true,
            None => true, // the decoder names the malformed line
            Some((field, value)) => {
                let value = value.trim();
                match field.trim().to_ascii_lowercase().as_str() {
                    "sizes" => match text::sizes(value) {
                        Some(s) => {
                            sizes = Some(s);
                            false
                        }
                        None => true,
                    },
                    "encoding" => {
                        encoding = Some(value.to_ascii_lowercase());
                        false
                    }
                    "type" => {
                        sample = text::nrrd_type(value);
                        true
                    }
                    "endian" => {
                        endian = match value {
                            "little" => Some(Endian::Little),
                            "big" => Some(Endian::Big),
                            _ => None,
                        };
                        true
                    }
                    "byte skip" => match value.parse() {
                        Ok(v) => {
                            byte_skip = v;
                            false
                        }
                        Err(_) => true,
                    },
                    "line skip" => match value.parse() {
                        Ok(v) => {
                            line_skip = v;
                            false
                        }
                        Err(_) => true,
                    },
                    "data file" | "datafile" => {
                        // Where the data is comes from the header's parser (`data_pieces`).
                        if text::is_file_list(value) {
                            break;
                        }
                        false
                    }
                    _ => true,
                }
            }
        };
        if keep {
            probe += line;
            probe.push('\n');
        }
    }
    // A time axis (`kinds` `time` or `list`): last, the time points follow each other, each a
    // volume; first, a voxel's time points follow each other. The stand-in has one.
    let series = crate::reader::nrrd::series_info(path, &prefix)?;
    if let Some(e) = &encoding {
        if matches!(e.as_str(), "ascii" | "text" | "txt") {
            if let Some(crate::reader::nrrd::SeriesAxis { points, .. }) = series {
                return Err(ReadError::unsupported(
                    path,
                    format!("a time series of {points} time points in ASCII encoding; raw or gzip are read by time point"),
                ));
            }
            return read_whole(path); // decimal text: no fixed place per voxel
        }
    }
    if let Some(s) = &sizes {
        let s: Vec<String> = s
            .iter()
            .enumerate()
            .map(|(a, s)| match series {
                Some(t) if a == t.axis => "1".to_string(),
                _ => nrrd_stand_in_size(*s).to_string(),
            })
            .collect();
        probe += &format!("sizes: {}\n", s.join(" "));
    }
    probe += "encoding: raw\n\n";
    let mut probe = probe.into_bytes();
    probe.resize(probe.len() + 3 * 3 * 3 * 3 * 8, 0);
    let meta = stand_in(&parent(path), file_name(path), Format::Nrrd, probe)?;

    // The stand-in's decoder checked dimension (1..=4), one size per axis, the type, the
    // endian for multi-byte samples, and the 4D channel layout.
    let (Some(sizes), Some(sample)) = (sizes, sample) else {
        return Err(bad(
            "the stand-in header was accepted without sizes or type".into(),
        ));
    };
    let channels = meta.channel_count();
    // The axes as the decoder takes them (the stand-in's layout is checked against them).
    let spatial = crate::reader::nrrd::spatial_axes(path, &prefix)?;
    let mut dims = [1usize; 3];
    for (d, a) in dims.iter_mut().zip(&spatial) {
        *d = usize::try_from(sizes[*a]).unwrap_or(usize::MAX);
    }
    let stand_in_dims = dims.map(|d| nrrd_stand_in_size(d as u64) as usize);
    if meta.dims() != stand_in_dims {
        return Err(bad(format!(
            "sizes {sizes:?}: the decoder laid out the axes as {:?}, this reader as {stand_in_dims:?}",
            meta.dims()
        )));
    }
    let points = series.map_or(1, |s| s.points);
    let (frame, expected) = stored_bytes(path, dims, channels, sample.size(), points)?;
    let endian = endian.unwrap_or(Endian::Little);

    // Where the data is: the data file(s), each with its piece of the samples, or just past
    // the blank line.
    let (pieces, attached): (Vec<(std::path::PathBuf, u64)>, bool) =
        match crate::reader::nrrd::data_pieces(path, &prefix, expected)? {
            Some((names, piece)) => (
                names
                    .into_iter()
                    .map(|f| (parent(path).join(f), piece))
                    .collect(),
                false,
            ),
            None if found => (vec![(path.to_path_buf(), expected)], true),
            None => {
                return Err(bad(
                    "no blank line ends the header and no `data file` is named".into(),
                ))
            }
        };
    let encoding = encoding.as_deref().unwrap_or("");
    // Where a file's piece starts: past the header (attached data), then the skipped lines,
    // then the skipped bytes (-1: the piece ends the file).
    let start_of =
        |data_path: &Path, piece: u64| -> Result<u64, ReadError> {
            let mut offset = if attached { end as u64 } else { 0 };
            let data_len = if attached {
                len
            } else {
                std::fs::metadata(data_path)
                    .map_err(|e| ReadError::io(data_path, e))?
                    .len()
            };
            if line_skip > 0 {
                offset = skip_lines(data_path, offset, line_skip).map_err(|e| match e {
                    Some(e) => ReadError::io(data_path, e),
                    None => ReadError::bad_header(
                        data_path,
                        FORMAT,
                        format!("line skip {line_skip} passes the end of the data"),
                    ),
                })?;
            }
            match (encoding, byte_skip) {
                ("raw", -1) => data_len.checked_sub(piece).filter(|s| *s >= offset).ok_or(
                    ReadError::Truncated {
                        path: data_path.to_path_buf(),
                        offset,
                        expected: piece,
                        actual: data_len.saturating_sub(offset),
                    },
                ),
                ("raw", s) if s >= 0 => Ok(offset.saturating_add(s as u64)),
                ("raw", s) => Err(bad(format!("byte skip {s}; -1 or ≥ 0 allowed"))),
                (_, 0) => Ok(offset),
                _ => Err(ReadError::unsupported(path, "byte skip with gzip encoding")),
            }
        };
    let stored = match encoding {
        "raw" => stored_pieces(&pieces, start_of, sample, endian)?,
        "gzip" | "gz" => spool_pieces(
            &pieces,
            start_of,
            |r| Box::new(flate2::bufread::MultiGzDecoder::new(r)),
            FORMAT,
            "gzip",
            sample,
            endian,
        )?,
        "" => return Err(bad("no `encoding` field".into())),
        e => {
            return Err(ReadError::unsupported(
                path,
                format!("encoding {e:?}; supported are raw, gzip and ascii"),
            ))
        }
    };
    let mut stored = stored;
    stored.frame = frame;
    if series.is_some_and(|s| s.axis == 0) {
        stored.interleaved = points;
    }
    Ok(Opened {
        time_points: points,
        time_step: series.and_then(|s| s.step),
        ..Opened::stored(&meta, dims, stored)
    })
}

/// The offset just past `lines` newlines from `offset` in `path`; `Err(None)` when the file
/// ends first. Scans without holding a line.
fn skip_lines(path: &Path, offset: u64, lines: u64) -> Result<u64, Option<io::Error>> {
    let mut f = File::open(path).map_err(Some)?;
    f.seek(SeekFrom::Start(offset)).map_err(Some)?;
    let mut r = BufReader::new(f);
    let (mut pos, mut left) = (offset, lines);
    while left > 0 {
        let buf = r.fill_buf().map_err(Some)?;
        if buf.is_empty() {
            return Err(None);
        }
        let mut used = buf.len();
        for (i, b) in buf.iter().enumerate() {
            if *b == b'\n' {
                left -= 1;
                if left == 0 {
                    used = i + 1;
                    break;
                }
            }
        }
        r.consume(used);
        pos += used as u64;
    }
    Ok(pos)
}
