//! MetaImage: the text header is parsed for the sizes, element type, byte order, compression
//! and data file (local or detached, with a header size to skip), and its meaning taken from
//! the MetaImage decoder on a stand-in. A 4D file (`NDims = 4`) is a time series of its last
//! size's time points, each volume after the previous one.

use std::path::Path;

use super::super::Opened;
use super::{file_name, parent, spool_pieces, stand_in, stored_bytes, stored_pieces, text_header};
use crate::reader::text::{self, header_lines};
use crate::reader::{Endian, Format, ReadError, SampleType};

pub(super) fn open_metaimage(path: &Path) -> Result<Opened, ReadError> {
    const FORMAT: &str = "MetaImage";
    let bad = |reason: String| ReadError::bad_header(path, FORMAT, reason);
    let (prefix, len) = text_header(path)?;
    let (lines, end, found) = header_lines(
        &prefix,
        |l| {
            l.split_once('=')
                .is_some_and(|(k, _)| k.trim().eq_ignore_ascii_case("ElementDataFile"))
        },
        true,
    )
    .ok_or_else(|| bad("the header is not UTF-8 text or is longer than 1 MiB".into()))?;
    if !found {
        return Err(bad("no ElementDataFile line ends the header".into()));
    }
    let mut fields: Vec<(String, String)> = Vec::new();
    let mut probe = String::new();
    const REPLACED: &[&str] = &[
        "DimSize",
        "CompressedData",
        "CompressedDataSize",
        "HeaderSize",
        "ElementDataFile",
    ];
    for line in &lines {
        if let Some((k, v)) = line.split_once('=') {
            let k = k.trim();
            fields.push((k.to_string(), v.trim().to_string()));
            if REPLACED.iter().any(|r| r.eq_ignore_ascii_case(k)) {
                continue;
            }
        }
        probe += line;
        probe.push('\n');
    }
    let get = |keys: &[&str]| -> Option<(String, String)> {
        keys.iter().find_map(|k| {
            fields
                .iter()
                .find(|(f, _)| f.eq_ignore_ascii_case(k))
                .cloned()
        })
    };
    let ndims = get(&["NDims"])
        .and_then(|(_, v)| v.parse::<usize>().ok())
        .filter(|n| (1..=4).contains(n));
    let sizes = match (get(&["DimSize"]), ndims) {
        (Some((_, v)), Some(n)) => match text::sizes(&v).filter(|s| s.len() == n) {
            Some(s) => {
                probe += &format!("DimSize = {}\n", vec!["1"; n].join(" "));
                Some(s)
            }
            None => {
                probe += &format!("DimSize = {v}\n"); // refused by the decoder
                None
            }
        },
        (Some((_, v)), None) => {
            probe += &format!("DimSize = {v}\n");
            None
        }
        (None, _) => None,
    };
    probe += "ElementDataFile = LOCAL\n";
    let mut probe = probe.into_bytes();
    probe.resize(probe.len() + 3 * 8, 0);
    let meta = stand_in(&parent(path), file_name(path), Format::MetaImage, probe)?;

    // The stand-in's decoder checked NDims, the DimSize count, the element type and channels,
    // BinaryData and the byte order.
    let Some(sizes) = sizes else {
        return Err(bad(
            "the stand-in header was accepted without DimSize".into()
        ));
    };
    let mut dims = [1usize; 3];
    for (d, s) in dims.iter_mut().zip(&sizes) {
        *d = usize::try_from(*s).unwrap_or(usize::MAX);
    }
    // A fourth size is the time points (0 refused as the decoder refuses it).
    let points = match sizes.get(3) {
        None => 1,
        Some(0) => return Err(bad(format!("DimSize = {sizes:?}: a size of 0"))),
        Some(t) => usize::try_from(*t).unwrap_or(usize::MAX),
    };
    let channels = meta.channel_count();
    let ty = get(&["ElementType"]).map(|(_, t)| t.to_ascii_uppercase());
    let sample = match ty.as_deref() {
        Some("MET_CHAR") => SampleType::I8,
        Some("MET_UCHAR") => SampleType::U8,
        Some("MET_SHORT") => SampleType::I16,
        Some("MET_USHORT") => SampleType::U16,
        Some("MET_INT" | "MET_LONG") => SampleType::I32,
        Some("MET_UINT" | "MET_ULONG") => SampleType::U32,
        Some("MET_LONG_LONG") => SampleType::I64,
        Some("MET_ULONG_LONG") => SampleType::U64,
        Some("MET_FLOAT") => SampleType::F32,
        Some("MET_DOUBLE") => SampleType::F64,
        t => {
            return Err(bad(format!(
                "ElementType {t:?} passed the decoder but is unknown here"
            )))
        }
    };
    let bool_field = |keys: &[&str]| -> Result<Option<bool>, ReadError> {
        match get(keys) {
            None => Ok(None),
            Some((k, v)) => match v.to_ascii_lowercase().as_str() {
                "true" | "1" => Ok(Some(true)),
                "false" | "0" => Ok(Some(false)),
                _ => Err(bad(format!("{k} = {v:?} is not True or False"))),
            },
        }
    };
    let endian = match bool_field(&["BinaryDataByteOrderMSB", "ElementByteOrderMSB"])? {
        Some(true) => Endian::Big,
        _ => Endian::Little,
    };
    let compressed = bool_field(&["CompressedData"])?.unwrap_or(false);
    let header_size = match get(&["HeaderSize"]) {
        None => 0i64,
        Some((_, v)) => v
            .parse::<i64>()
            .ok()
            .filter(|s| *s >= -1)
            .ok_or_else(|| bad(format!("HeaderSize = {v:?}; -1 or ≥ 0 expected")))?,
    };
    let (frame, expected) = stored_bytes(path, dims, channels, sample.size(), points)?;
    // The data: after the header (`LOCAL`), or in the data files, each with its piece.
    let (pieces, local): (Vec<(std::path::PathBuf, u64)>, bool) =
        match crate::reader::metaimage::data_pieces(path, &prefix, expected)? {
            None => (vec![(path.to_path_buf(), expected)], true),
            Some((names, piece)) => (
                names
                    .into_iter()
                    .map(|f| (parent(path).join(f), piece))
                    .collect(),
                false,
            ),
        };
    if compressed && header_size != 0 {
        return Err(ReadError::unsupported(
            path,
            "HeaderSize with CompressedData",
        ));
    }
    // Where a file's piece starts: past the header (local data), then HeaderSize (-1: the
    // piece ends the file).
    let start_of = |data_path: &Path, piece: u64| -> Result<u64, ReadError> {
        let (base, data_len) = if local {
            (end as u64, len)
        } else {
            let l = std::fs::metadata(data_path)
                .map_err(|e| ReadError::io(data_path, e))?
                .len();
            (0, l)
        };
        if header_size == -1 {
            data_len
                .checked_sub(piece)
                .filter(|s| *s >= base)
                .ok_or(ReadError::Truncated {
                    path: data_path.to_path_buf(),
                    offset: 0,
                    expected: piece,
                    actual: data_len.saturating_sub(base),
                })
        } else {
            Ok(base.saturating_add(header_size as u64))
        }
    };
    let stored = if compressed {
        let inflate =
            |r| -> Box<dyn std::io::Read> { Box::new(flate2::bufread::ZlibDecoder::new(r)) };
        spool_pieces(&pieces, start_of, inflate, FORMAT, "zlib", sample, endian)?
    } else {
        stored_pieces(&pieces, start_of, sample, endian)?
    };
    let mut stored = stored;
    stored.frame = frame;
    Ok(Opened {
        time_points: points,
        ..Opened::stored(&meta, dims, stored)
    })
}
