//! NIfTI-1: the header is read from the start of the file (gzip-compressed or not) and its
//! meaning taken from the NIfTI decoder on a stand-in; the samples lie from `vox_offset` on,
//! read in place or inflated into a temporary file.

use std::io::{self, Read};
use std::path::Path;

use super::super::{Opened, Source};
use super::{read_prefix, reader_at, spool, stored_at, stored_bytes};
use crate::reader::{nifti, Endian, ReadError, SampleType};

/// Size of a NIfTI-1 header in bytes.
const NIFTI1_HEADER_BYTES: u64 = 348;
/// Largest `vox_offset` accepted (as the NIfTI reader).
const MAX_VOX_OFFSET: u64 = 1 << 30;

pub(super) fn open_nifti(path: &Path) -> Result<Opened, ReadError> {
    let gz = read_prefix(path, 2)?.starts_with(&[0x1f, 0x8b]);
    let file = reader_at(path, 0)?;
    let mut stream: Box<dyn Read> = if gz {
        Box::new(flate2::bufread::MultiGzDecoder::new(file))
    } else {
        Box::new(file)
    };
    let bad = |reason: String| ReadError::bad_header(path, "NIfTI", reason);
    let mut head = Vec::with_capacity(NIFTI1_HEADER_BYTES as usize);
    (&mut stream)
        .take(NIFTI1_HEADER_BYTES)
        .read_to_end(&mut head)
        .map_err(|e| ReadError::io(path, e))?;
    if head.len() as u64 != NIFTI1_HEADER_BYTES {
        return Err(bad(format!(
            "file holds {} bytes, a NIfTI-1 header needs {NIFTI1_HEADER_BYTES}",
            head.len()
        )));
    }
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

    let header =
        ::nifti::NiftiHeader::from_reader(&head[..]).map_err(|source| ReadError::Nifti {
            path: path.to_path_buf(),
            source,
        })?;
    // The stand-in had every size 1: check the real ones as the decoder does.
    let ndim = usize::from(header.dim[0]);
    let mut dims = [1usize; 3];
    for i in 1..=ndim {
        let d = usize::from(header.dim[i]);
        if d == 0 {
            return Err(bad(format!("dim[{i}] is 0, expected at least 1")));
        }
        if i <= 3 {
            dims[i - 1] = d;
        } else if d != 1 {
            return Err(ReadError::unsupported(
                path,
                format!(
                    "dim[{i}] is {d}: only 3D volumes are supported (dim[0] = {ndim}, extra dimensions must be 1); dim = {:?}",
                    &header.dim[1..=ndim]
                ),
            ));
        }
    }
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
    let expected = stored_bytes(path, dims, channels, sample.size())?;
    let vox_offset = header.vox_offset;
    if !vox_offset.is_finite()
        || vox_offset < NIFTI1_HEADER_BYTES as f32
        || vox_offset.fract() != 0.0
        || vox_offset > MAX_VOX_OFFSET as f32
    {
        return Err(bad(format!(
            "vox_offset is {vox_offset}, expected a whole number of bytes in 348..={MAX_VOX_OFFSET} (at least 352 for a single file)"
        )));
    }
    let vox_offset = vox_offset as u64;
    let endian = match header.endianness {
        ::nifti::Endianness::Little => Endian::Little,
        ::nifti::Endianness::Big => Endian::Big,
    };
    let mut stored = if gz {
        let skip = vox_offset - NIFTI1_HEADER_BYTES;
        let skipped = io::copy(&mut (&mut stream).take(skip), &mut io::sink())
            .map_err(|e| ReadError::io(path, e))?;
        if skipped != skip {
            return Err(ReadError::Truncated {
                path: path.to_path_buf(),
                offset: vox_offset,
                expected,
                actual: 0,
            });
        }
        spool(&mut stream, expected, path, "NIfTI", "gzip", sample, endian)?
    } else {
        stored_at(path, vox_offset, expected, sample, endian)?
    };
    if channels == 1
        && header.scl_slope.is_finite()
        && header.scl_slope != 0.0
        && header.scl_inter.is_finite()
    {
        stored.slope = f64::from(header.scl_slope);
        stored.inter = f64::from(header.scl_inter);
    }
    Ok(Opened {
        dims,
        channels,
        spacing: meta.spacing(),
        placement: meta.placement().copied(),
        source: Source::Stored(stored),
    })
}
