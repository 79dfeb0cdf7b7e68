//! Opening each format for region reads: where its samples lie (file, offset, compression, sample
//! type, byte order, rescale) is parsed here from the header alone; what the header means
//! (validation, channels, spacing, placement) is taken from the format's own decoder run on a
//! *stand-in*: the same header with every size set to one voxel (or two, where a size of 1 or 3
//! decides which axis holds the channels), the data attached, raw, and zero-filled. So
//! [`super::RegionReader`] reports exactly what [`crate::reader::read_volume`] would, without a
//! second copy of the geometry code, and the stand-in is a few bytes whatever the volume's size.
//! The sizes, the data location and encoding, which the stand-in replaces, are validated here
//! with the decoders' rules and messages.

mod metaimage;
mod nifti;
mod nrrd;
mod raw;

use std::fs::File;
use std::io::{self, BufReader, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use self::metaimage::open_metaimage;
use self::nifti::open_nifti;
use self::nrrd::open_nrrd;
use self::raw::open_raw;
use super::{Opened, Stored};
use crate::reader::text::TEXT_HEADER_WINDOW;
use crate::reader::{Endian, Format, RawSpec, ReadError, SampleType, SourceFiles};
use wavesplat_codec::volume::{Volume, VolumeError};

/// Opens `path` by format, as [`crate::reader::read_volume`] dispatches (of a Zarr array, the
/// channel `channel`, and of a TIFF storing channels as planes of their own; other formats
/// read every channel: `None` there).
pub(super) fn open(
    path: &Path,
    raw: Option<&RawSpec>,
    channel: Option<usize>,
) -> Result<Opened, ReadError> {
    let meta = std::fs::metadata(path).map_err(|e| ReadError::io(path, e))?;
    if meta.is_dir() {
        // A Zarr store, a DICOM series, else a stack of TIFF files.
        if crate::reader::zarr::is_store(path) {
            return open_zarr(path, channel);
        }
        if crate::reader::is_tiff_directory(path)? {
            return open_tiff(path, channel);
        }
        return open_series(path);
    }
    let by_name = Format::from_name(path);
    if let (None, Some(spec)) = (by_name, raw) {
        return open_raw(path, spec);
    }
    if by_name.is_none() {
        if let Some(header) = crate::reader::nifti::pair_header_of(path) {
            return Err(crate::reader::nifti::pair_data_read_alone(path, &header));
        }
    }
    let format = match by_name {
        Some(f) => Some(f),
        None => Format::sniff(&read_prefix(path, 512)?),
    };
    match format {
        Some(Format::Dicom) => open_series(path),
        Some(Format::Nrrd) => open_nrrd(path),
        Some(Format::MetaImage) => open_metaimage(path),
        Some(Format::Nifti) => open_nifti(path),
        Some(Format::Tiff) => open_tiff(path, channel),
        Some(Format::Zarr) => open_zarr(path, channel),
        None => Err(ReadError::MissingRawSpec {
            path: path.to_path_buf(),
        }),
    }
}

/// A DICOM series directory or file, read by slice ranges.
fn open_series(path: &Path) -> Result<Opened, ReadError> {
    let s = crate::reader::dicom::SeriesRegions::open(path)?;
    Ok(Opened {
        dims: s.dims(),
        channels: s.channels(),
        spacing: s.spacing(),
        placement: s.placement().copied(),
        source: super::Source::Series(s),
        time_points: 1,
        time_step: None,
    })
}

/// A TIFF stack (a multi-page file or a directory of files), read by slices and chunks (of
/// channels stored as planes of their own, the one chosen).
fn open_tiff(path: &Path, channel: Option<usize>) -> Result<Opened, ReadError> {
    let s = crate::reader::tiff_stack::TiffRegions::open(path, channel)?;
    Ok(Opened {
        dims: s.dims(),
        channels: s.channels(),
        spacing: s.spacing(),
        placement: None,
        time_points: s.time_points(),
        time_step: s.time_step(),
        source: super::Source::Tiff(s),
    })
}

/// A Zarr array, read by chunks (of its channels, the one chosen).
fn open_zarr(path: &Path, channel: Option<usize>) -> Result<Opened, ReadError> {
    let z = crate::reader::zarr::ZarrVolume::open(path, channel)?;
    Ok(Opened {
        dims: z.dims(),
        channels: 1,
        spacing: z.spacing(),
        placement: None,
        time_points: z.time_points(),
        time_step: z.time_step(),
        source: super::Source::Zarr(Box::new(z)),
    })
}

/// Up to `limit` bytes from the start of a file.
fn read_prefix(path: &Path, limit: u64) -> Result<Vec<u8>, ReadError> {
    let f = File::open(path).map_err(|e| ReadError::io(path, e))?;
    let mut out = Vec::new();
    f.take(limit)
        .read_to_end(&mut out)
        .map_err(|e| ReadError::io(path, e))?;
    Ok(out)
}

/// Bytes of one time point, `dims` × `channels` samples of `size` bytes, and of `points` of
/// them, checked (u128, then u64).
fn stored_bytes(
    path: &Path,
    dims: [usize; 3],
    channels: usize,
    size: usize,
    points: usize,
) -> Result<(u64, u64), ReadError> {
    if dims.contains(&0) {
        return Err(ReadError::volume(path, VolumeError::ZeroDimension(dims)));
    }
    let too_large = || ReadError::TooLarge {
        dims,
        channels,
        bytes_per_sample: size,
    };
    let frame = dims
        .iter()
        .chain([&channels, &size])
        .try_fold(1u128, |acc, d| acc.checked_mul(*d as u128))
        .and_then(|b| u64::try_from(b).ok())
        .filter(|b| *b <= i64::MAX as u64)
        .ok_or_else(too_large)?;
    let all = frame.checked_mul(points as u64).ok_or_else(too_large)?;
    Ok((frame, all))
}

/// Samples stored uncompressed in `data_path` from `offset` on; the file must hold all
/// `expected` bytes.
fn stored_at(
    data_path: &Path,
    offset: u64,
    expected: u64,
    sample: SampleType,
    endian: Endian,
) -> Result<Stored, ReadError> {
    let file = File::open(data_path).map_err(|e| ReadError::io(data_path, e))?;
    let len = file
        .metadata()
        .map_err(|e| ReadError::io(data_path, e))?
        .len();
    let actual = len.saturating_sub(offset);
    if actual < expected {
        return Err(ReadError::Truncated {
            path: data_path.to_path_buf(),
            offset,
            expected,
            actual,
        });
    }
    Ok(Stored::plain(
        file,
        data_path.to_path_buf(),
        offset,
        sample,
        endian,
        expected,
    ))
}

/// Inflates `stream` (`what` data: gzip, zlib) into a temporary file, which then holds the
/// `expected` bytes of samples; a stream that ends early is [`ReadError::Truncated`], a corrupt
/// one a bad header of `format`.
fn spool(
    stream: &mut dyn Read,
    expected: u64,
    data_path: &Path,
    format: &'static str,
    what: &str,
    sample: SampleType,
    endian: Endian,
) -> Result<Stored, ReadError> {
    let mut file = temp_file(data_path)?;
    spool_into(&mut file, stream, expected, data_path, format, what)?;
    Ok(Stored::plain(
        file,
        data_path.to_path_buf(),
        0,
        sample,
        endian,
        expected,
    ))
}

/// [`spool`] of a sample stream cut into pieces, one per data file (`(path, bytes)`): each
/// inflated by `inflate` from where `start_of` says its data starts, in turn into one
/// temporary file.
fn spool_pieces(
    pieces: &[(PathBuf, u64)],
    start_of: impl Fn(&Path, u64) -> Result<u64, ReadError>,
    inflate: impl Fn(BufReader<File>) -> Box<dyn Read>,
    format: &'static str,
    what: &str,
    sample: SampleType,
    endian: Endian,
) -> Result<Stored, ReadError> {
    let Some((first, _)) = pieces.first() else {
        return Err(ReadError::io(
            Path::new(""),
            io::Error::new(io::ErrorKind::NotFound, "no data file"),
        ));
    };
    let mut file = temp_file(first)?;
    for (path, bytes) in pieces {
        let mut stream = inflate(reader_at(path, start_of(path, *bytes)?)?);
        spool_into(&mut file, &mut stream, *bytes, path, format, what)?;
    }
    let frame = pieces.iter().map(|(_, b)| b).sum();
    let spooled = (pieces.len() > 1).then(|| {
        let files = pieces.iter().map(|(p, _)| p.clone()).collect();
        (pieces[0].1, files)
    });
    Ok(Stored {
        spooled,
        ..Stored::plain(file, first.clone(), 0, sample, endian, frame)
    })
}

/// The error of writing the inflated samples of `data_path` to a temporary file.
fn temp_error(data_path: &Path, e: io::Error) -> ReadError {
    ReadError::io(
        &std::env::temp_dir(),
        io::Error::new(
            e.kind(),
            format!(
                "writing the inflated samples of {} to a temporary file: {e}",
                data_path.display()
            ),
        ),
    )
}

/// An anonymous temporary file for the inflated samples of `data_path`.
fn temp_file(data_path: &Path) -> Result<File, ReadError> {
    tempfile::tempfile().map_err(|e| temp_error(data_path, e))
}

/// Appends the `expected` bytes `stream` inflates to `file`.
fn spool_into(
    file: &mut File,
    stream: &mut dyn Read,
    expected: u64,
    data_path: &Path,
    format: &'static str,
    what: &str,
) -> Result<(), ReadError> {
    let mut buf = vec![0u8; 1 << 20];
    let mut done = 0u64;
    while done < expected {
        let want = (expected - done).min(buf.len() as u64) as usize;
        let n = match stream.read(&mut buf[..want]) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::InvalidInput | io::ErrorKind::InvalidData
                ) =>
            {
                return Err(ReadError::bad_header(
                    data_path,
                    format,
                    format!("the {what} data is corrupt: {e}"),
                ))
            }
            Err(e) => return Err(ReadError::io(data_path, e)),
        };
        file.write_all(&buf[..n])
            .map_err(|e| temp_error(data_path, e))?;
        done += n as u64;
    }
    if done != expected {
        return Err(ReadError::Truncated {
            path: data_path.to_path_buf(),
            offset: 0,
            expected,
            actual: done,
        });
    }
    file.flush().map_err(|e| temp_error(data_path, e))
}

/// The samples of a stream cut into pieces, one per data file (`(path, bytes)`, all of one
/// length), each from where `start_of` says its data starts (one piece: [`stored_at`]); every
/// file is checked to hold its piece.
fn stored_pieces(
    pieces: &[(PathBuf, u64)],
    start_of: impl Fn(&Path, u64) -> Result<u64, ReadError>,
    sample: SampleType,
    endian: Endian,
) -> Result<Stored, ReadError> {
    let starts = pieces
        .iter()
        .map(|(p, bytes)| Ok((p.clone(), start_of(p, *bytes)?)))
        .collect::<Result<Vec<_>, ReadError>>()?;
    let (Some((first, first_start)), Some((_, piece))) = (starts.first(), pieces.first()) else {
        return Err(ReadError::io(
            Path::new(""),
            io::Error::new(io::ErrorKind::NotFound, "no data file"),
        ));
    };
    let piece = *piece;
    if starts.len() == 1 {
        return stored_at(first, *first_start, piece, sample, endian);
    }
    // Each file is checked to hold its piece, and closed again: a reader opens the files a
    // region needs, a few at a time.
    for (path, start) in &starts[1..] {
        stored_at(path, *start, piece, sample, endian)?;
    }
    let Stored { file, .. } = stored_at(first, *first_start, piece, sample, endian)?;
    let total = piece.saturating_mul(starts.len() as u64);
    let first = first.clone();
    Ok(Stored {
        pieces: Some(super::Pieces::new(piece, starts)),
        ..Stored::plain(file, first, 0, sample, endian, total)
    })
}

/// A file positioned at `offset`, buffered.
fn reader_at(path: &Path, offset: u64) -> Result<BufReader<File>, ReadError> {
    let mut f = File::open(path).map_err(|e| ReadError::io(path, e))?;
    f.seek(SeekFrom::Start(offset))
        .map_err(|e| ReadError::io(path, e))?;
    Ok(BufReader::new(f))
}

/// Runs a format's decoder on a stand-in file `name` (in `dir`) holding `bytes`.
fn stand_in(dir: &Path, name: String, format: Format, bytes: Vec<u8>) -> Result<Volume, ReadError> {
    let src = SourceFiles {
        origin: dir.join(&name),
        base: dir.to_path_buf(),
        format: Some(format),
        files: vec![(name, bytes)],
    };
    match format {
        Format::Nrrd => crate::reader::nrrd::decode(&src),
        Format::MetaImage => crate::reader::metaimage::decode(&src),
        _ => unreachable!("stand-ins are built for text headers only"),
    }
}

fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

fn parent(path: &Path) -> PathBuf {
    path.parent().map(Path::to_path_buf).unwrap_or_default()
}

/// The text header of `path`: the bytes up to where a header that the decoders accept can
/// end (each line within [`MAX_TEXT_HEADER`](crate::reader::text::MAX_TEXT_HEADER), starting within it), and the file's length.
fn text_header(path: &Path) -> Result<(Vec<u8>, u64), ReadError> {
    let len = std::fs::metadata(path)
        .map_err(|e| ReadError::io(path, e))?
        .len();
    Ok((read_prefix(path, TEXT_HEADER_WINDOW)?, len))
}
