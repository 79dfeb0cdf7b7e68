//! NIfTI-1: the header is read from the start of the file (gzip-compressed or not) and its
//! meaning taken from the NIfTI decoder on a stand-in; the samples lie from `vox_offset` on,
//! read in place or inflated into a temporary file.

use std::io::Read;
use std::path::Path;

use super::super::Opened;
use super::{read_prefix, reader_at, spool, stored_at, stored_bytes};
use crate::reader::{nifti, ReadError, SampleType};

pub(super) fn open_nifti(path: &Path) -> Result<Opened, ReadError> {
    let gz = read_prefix(path, 2)?.starts_with(&[0x1f, 0x8b]);
    let file = reader_at(path, 0)?;
    let mut stream: Box<dyn Read> = if gz {
        Box::new(flate2::bufread::MultiGzDecoder::new(file))
    } else {
        Box::new(file)
    };
    let bad = |reason: String| ReadError::bad_header(path, "NIfTI", reason);
    let head = nifti::read_header_bytes(&mut stream, path)?;
    // The stand-in: this header with dim[1..=7] = 1, the data right after it (one voxel of
    // zeros; at most 8 bytes, 32 given).
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
    let at352 = if big {
        352f32.to_be_bytes()
    } else {
        352f32.to_le_bytes()
    };
    probe[108..112].copy_from_slice(&at352);
    probe.extend_from_slice(&[0u8; 4 + 32]);
    let meta = nifti::decode_nifti(path, &probe)?;

    let header = nifti::parse_header(path, &head)?;
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
    let frame = stored_bytes(path, dims, channels, sample.size())?;
    let expected = frame
        .checked_mul(time_points as u64)
        .ok_or(ReadError::TooLarge {
            dims,
            channels,
            bytes_per_sample: sample.size(),
        })?;
    let vox_offset = nifti::data_offset(path, &header)?;
    let endian = nifti::endian(&header);
    let mut stored = if gz {
        nifti::skip_to_data(&mut stream, path, vox_offset, expected)?;
        spool(&mut stream, expected, path, "NIfTI", "gzip", sample, endian)?
    } else {
        stored_at(path, vox_offset, expected, sample, endian)?
    };
    if let Some((slope, inter)) = nifti::scaling(&header, channels) {
        stored.slope = slope;
        stored.inter = inter;
    }
    stored.frame = frame;
    Ok(Opened {
        time_points,
        time_step: nifti::time_step(&header),
        ..Opened::stored(&meta, dims, stored)
    })
}
