//! NIfTI-1: the header is read from the start of the file (gzip-compressed or not) and its
//! meaning taken from the NIfTI decoder on a stand-in; the samples lie from `vox_offset` on,
//! in the file itself (`.nii`) or in the `.img` beside a `.hdr` (a NIfTI-1 or Analyze 7.5
//! pair), read in place or inflated into a temporary file.

use std::io::Read;
use std::path::Path;

use super::super::Opened;
use super::{read_prefix, reader_at, spool, stored_at, stored_bytes};
use crate::reader::nifti::{self, Flavour};
use crate::reader::{ReadError, SampleType};

/// A stream of `path`'s bytes, inflated when they are gzip-compressed (by content).
fn stream_of(path: &Path) -> Result<Box<dyn Read>, ReadError> {
    let gz = read_prefix(path, 2)?.starts_with(&[0x1f, 0x8b]);
    let file = reader_at(path, 0)?;
    Ok(if gz {
        Box::new(flate2::bufread::MultiGzDecoder::new(file))
    } else {
        Box::new(file)
    })
}

pub(super) fn open_nifti(path: &Path) -> Result<Opened, ReadError> {
    // A `.hdr`'s samples are in the `.img` beside it.
    let data_path = if nifti::is_pair_header_path(path) {
        Some(nifti::pair_data_file(path)?)
    } else {
        None
    };
    let mut stream = stream_of(path)?;
    let bad = |reason: String| ReadError::bad_header(path, "NIfTI", reason);
    let head = nifti::read_header_bytes(&mut stream, path)?;
    // The stand-in: this header with dim[1..=7] = 1 and one voxel of zeros (at most 8 bytes,
    // 32 given), right after it in a single file (vox_offset 352), at the start of a pair's
    // data (vox_offset 0).
    let big = head[..4] == 348i32.to_be_bytes();
    let mut probe = head.clone();
    for i in 1..8 {
        let one = if big {
            1u16.to_be_bytes()
        } else {
            1u16.to_le_bytes()
        };
        probe[40 + 2 * i..42 + 2 * i].copy_from_slice(&one);
    }
    let offset = if data_path.is_some() { 0f32 } else { 352f32 };
    let offset = if big {
        offset.to_be_bytes()
    } else {
        offset.to_le_bytes()
    };
    probe[108..112].copy_from_slice(&offset);
    let meta = match &data_path {
        None => {
            probe.extend_from_slice(&[0u8; 4 + 32]);
            nifti::decode_nifti(path, &probe)?
        }
        Some(data) => nifti::decode_nifti_pair(path, &probe, data, &[0u8; 32])?,
    };

    let header = nifti::parse_header(path, &head)?;
    // The decoder accepted the stand-in: the header has a flavour.
    let flavour = nifti::flavour(&head).unwrap_or(Flavour::Pair);
    // The stand-in had every size 1: check the real ones as the decoder does.
    let (dims, time_points) = nifti::series_dims(path, &header)?;
    let sample = match header.datatype {
        2 | 128 => SampleType::U8,
        4 => SampleType::I16,
        8 => SampleType::I32,
        16 => SampleType::F32,
        64 => SampleType::F64,
        256 => SampleType::I8,
        512 => SampleType::U16,
        768 => SampleType::U32,
        1024 => SampleType::I64,
        1280 => SampleType::U64,
        t => {
            return Err(bad(format!(
                "datatype {t} passed the decoder but is unknown here"
            )))
        }
    };
    let channels = meta.channel_count();
    let (frame, expected) = stored_bytes(path, dims, channels, sample.size(), time_points)?;
    let vox_offset = nifti::data_offset(path, &header, flavour)?;
    let endian = nifti::endian(&header);
    // Where the samples are: this file after its header, or the pair's data file from its
    // start; inflated to a temporary file when compressed.
    let (data, mut stream, at) = match &data_path {
        None => (path, stream, nifti::NIFTI1_HEADER_BYTES),
        Some(d) => (d.as_path(), stream_of(d)?, 0),
    };
    let gz = read_prefix(data, 2)?.starts_with(&[0x1f, 0x8b]);
    let mut stored = if gz {
        nifti::skip_to_data(&mut stream, data, at, vox_offset, expected)?;
        spool(&mut stream, expected, data, "NIfTI", "gzip", sample, endian)?
    } else {
        stored_at(data, vox_offset, expected, sample, endian)?
    };
    if let Some((slope, inter)) = nifti::scaling(&header, channels) {
        stored.slope = slope;
        stored.inter = inter;
    }
    stored.frame = frame;
    Ok(Opened {
        time_points,
        time_step: nifti::time_step(&header, flavour),
        ..Opened::stored(&meta, dims, stored)
    })
}
