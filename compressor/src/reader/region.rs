//! Reading sub-boxes ("regions", e.g. 256³ bricks) of a volume file without loading it whole,
//! so that volumes larger than memory, or than [`MAX_VOXELS`](wavesplat_codec::volume::MAX_VOXELS), can be compressed brick by
//! brick. A [`RegionReader`] owns an opened volume: its dimensions (a `usize` triple whose
//! product may exceed [`MAX_VOXELS`](wavesplat_codec::volume::MAX_VOXELS); byte offsets use checked `u64` arithmetic), channels,
//! spacing and placement, and where its samples lie. Headerless raw files, NIfTI-1 `.nii`,
//! NRRD with `raw` encoding (attached or detached) and MetaImage with raw data (`.mha`,
//! `.mhd` + data file) are read with positioned reads of just the bytes of the region (one
//! read per row, per slab of full rows, or one for a run of full slabs; samples cut into many
//! data files, a slice or a row each, are read from the files the region's bytes lie in). gzip and zlib data
//! (`.nii.gz`, NRRD `gzip`, MetaImage `CompressedData`) cannot be seeked into, and inflating
//! the stream again from the start for every brick would cost time quadratic in the volume;
//! so it is inflated once, streaming, into an anonymous temporary file in the system
//! temporary directory (deleted when the reader is dropped) and regions are read from there:
//! memory stays bounded, at the cost of disk space equal to the decompressed samples. A DICOM
//! series (or multi-frame file) is read by slice ranges: opening reads every file's header
//! (and keeps no bytes), and a region decodes only the frames of its slices, with the series
//! decoder's own validation and ordering. A Zarr array decodes only the chunks a region
//! touches. ASCII NRRD is read whole through [`read_volume`] and
//! cut in memory: it opens only when the whole volume fits within
//! [`MAX_VOXELS`](wavesplat_codec::volume::MAX_VOXELS). The meaning of each header
//! (its validation, the spacing, the placement, the channel layout) comes from the format's
//! own decoder, run on a one-voxel stand-in of the header (see `formats/`), so a region gets
//! exactly the metadata and values [`read_volume`] gives those voxels.
//!
//! ```no_run
//! # fn main() -> Result<(), wavesplat_compressor::reader::ReadError> {
//! use wavesplat_compressor::reader::region::RegionReader;
//! let reader = RegionReader::open("ct.nii.gz".as_ref(), None)?;
//! let [nx, ny, nz] = reader.dims();
//! let brick = reader.read_region([0, 0, 0], [nx.min(256), ny.min(256), nz.min(256)])?;
//! assert_eq!(brick.channel_count(), reader.channels());
//! # Ok(()) }
//! ```

mod formats;

use std::fs::File;
use std::io;
use std::path::{Path, PathBuf};

use super::{deinterleave, read_volume, Endian, RawSpec, ReadError, SampleType};
use wavesplat_codec::volume::{checked_voxels, Placement, Volume, VolumeError};

/// A volume file opened to read sub-boxes ("regions") without loading it whole. Reads are
/// positioned (`&self`), so one reader can serve several threads at once.
#[derive(Debug)]
pub struct RegionReader {
    /// The path it was opened from (for messages).
    path: PathBuf,
    dims: [usize; 3],
    channels: usize,
    spacing: [f32; 3],
    placement: Option<Placement>,
    source: Source,
    /// Time points (a 4D file's; 1 for a volume).
    time_points: usize,
    /// Seconds between time points, when the file says.
    time_step: Option<f64>,
    /// The time point [`RegionReader::read_region`] reads.
    selected: usize,
    /// The one channel kept of a source of several read together (RGB), when one was chosen
    /// ([`RegionReader::open_channel`]); `channels` stays the source's, and regions hold this
    /// one. A Zarr array's channel, and one of a TIFF's channels stored as planes of their own,
    /// is chosen when it is opened, and only it is read.
    kept_channel: Option<usize>,
}

/// Where the samples of an opened volume are.
#[derive(Debug)]
enum Source {
    /// Uncompressed in a file (the volume's own, or a temporary one holding inflated data).
    Stored(Stored),
    /// Decoded whole in memory (the formats that cannot be read by region yet).
    Whole(Volume),
    /// A DICOM series (or file) read by slice ranges.
    Series(super::dicom::SeriesRegions),
    /// A TIFF stack read by slices, only the strips or tiles a region covers.
    Tiff(super::tiff_stack::TiffRegions),
    /// A Zarr array read by the chunks a region covers.
    Zarr(Box<super::zarr::ZarrVolume>),
}

/// Samples stored in a file from `offset` on (or in several files, [`Stored::pieces`]): x
/// fastest, then y, then z, the channels of a voxel interleaved; value = `slope · sample +
/// inter`.
#[derive(Debug)]
struct Stored {
    file: File,
    /// The file the samples come from (for messages: the compressed file when `file` is a
    /// temporary one).
    path: PathBuf,
    offset: u64,
    /// The sample stream cut into pieces of equal length, one per data file, in order (a
    /// detached header's `LIST` or file name pattern): then `file` is the first piece's,
    /// `offset` is 0, and byte `b` of the stream is byte `b % len` of piece `b / len`.
    pieces: Option<Pieces>,
    /// The data files whose pieces, inflated, follow one another in a temporary `file` (their
    /// length; the files in order): for messages only.
    spooled: Option<(u64, Vec<PathBuf>)>,
    sample: SampleType,
    endian: Endian,
    slope: f64,
    inter: f64,
    /// Bytes of one time point's samples (time points follow one another).
    frame: u64,
    /// Time points stored within each voxel, one after another (an NRRD whose first axis is
    /// time); 1 where each time point's volume follows the previous one (`frame` apart).
    interleaved: usize,
}

/// A sample stream cut into equal pieces, each in its own file ([`Stored::pieces`]).
#[derive(Debug)]
struct Pieces {
    /// Bytes of each piece.
    len: u64,
    /// Each piece's file and where in it the piece starts (each checked at open to hold its
    /// piece).
    files: Vec<(PathBuf, u64)>,
    /// The files opened last, the latest first, at most [`OPEN_PIECES`]: a list of thousands
    /// of slices is not held open at once (the process's limit on open files is often 1024),
    /// and a region's rows, read slice after slice, find theirs open.
    open: std::sync::Mutex<Vec<(usize, std::sync::Arc<File>)>>,
}

impl Stored {
    /// The data file holding the sample of `channel` of voxel `at` at time point `t`, where
    /// the samples are cut into files of a volume `dims` wide; `None` for one file, or time
    /// points interleaved within a voxel.
    fn piece_path(
        &self,
        t: usize,
        at: [usize; 3],
        channel: usize,
        dims: [usize; 3],
        channels: usize,
    ) -> Option<&Path> {
        let (len, files): (u64, Vec<&Path>) = match (&self.pieces, &self.spooled) {
            (Some(p), _) => (p.len, p.files.iter().map(|(f, _)| f.as_path()).collect()),
            (None, Some((len, files))) => (*len, files.iter().map(PathBuf::as_path).collect()),
            (None, None) => return None,
        };
        if self.interleaved != 1 {
            return None;
        }
        let within = super::sample_byte(
            at,
            channel,
            [dims[0], dims[1]],
            channels,
            self.sample.size(),
        );
        let byte = self.frame as u128 * t as u128 + within;
        let file = usize::try_from(byte / u128::from(len.max(1))).ok()?;
        files.get(file).copied()
    }
}

/// Most piece files a reader keeps open ([`Pieces::open`]).
const OPEN_PIECES: usize = 16;

impl Pieces {
    fn new(len: u64, files: Vec<(PathBuf, u64)>) -> Pieces {
        Pieces {
            len,
            files,
            open: std::sync::Mutex::new(Vec::new()),
        }
    }

    /// Piece `index`'s file, opened (or found open).
    fn file(&self, index: usize) -> io::Result<std::sync::Arc<File>> {
        // A poisoned lock holds only open files: still usable.
        let mut open = self.open.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(k) = open.iter().position(|(i, _)| *i == index) {
            let entry = open.remove(k);
            let file = entry.1.clone();
            open.insert(0, entry);
            return Ok(file);
        }
        let file = std::sync::Arc::new(File::open(&self.files[index].0)?);
        open.insert(0, (index, file.clone()));
        open.truncate(OPEN_PIECES);
        Ok(file)
    }
}

impl Stored {
    /// Samples of one time point (`frame` bytes) stored as they are in `file` from `offset` on,
    /// not rescaled.
    fn plain(
        file: File,
        path: PathBuf,
        offset: u64,
        sample: SampleType,
        endian: Endian,
        frame: u64,
    ) -> Stored {
        Stored {
            file,
            path,
            offset,
            pieces: None,
            spooled: None,
            sample,
            endian,
            slope: 1.0,
            inter: 0.0,
            frame,
            interleaved: 1,
        }
    }

    /// Fills `buf` from byte `offset` of the stored bytes (counted from the file's start; for
    /// pieces, from the first piece's start), reading across pieces as needed. An error names
    /// the file it came from and the offset in it.
    fn read_at(&self, buf: &mut [u8], offset: u64) -> Result<(), (io::Error, &Path, u64)> {
        let Some(pieces) = &self.pieces else {
            return read_at(&self.file, buf, offset).map_err(|e| (e, self.path.as_path(), offset));
        };
        let (mut buf, mut pos) = (buf, offset - self.offset);
        while !buf.is_empty() {
            let (index, within) = ((pos / pieces.len) as usize, pos % pieces.len);
            let n = (pieces.len - within).min(buf.len() as u64) as usize;
            let Some((path, start)) = pieces.files.get(index) else {
                let e = io::Error::new(io::ErrorKind::UnexpectedEof, "past the last data file");
                return Err((e, self.path.as_path(), pos));
            };
            let at = start + within;
            let (now, rest) = buf.split_at_mut(n);
            pieces
                .file(index)
                .and_then(|f| read_at(&f, now, at))
                .map_err(|e| (e, path.as_path(), at))?;
            buf = rest;
            pos += n as u64;
        }
        Ok(())
    }
}

/// What a format's opener found: the volume's metadata and its samples.
#[derive(Debug)]
struct Opened {
    dims: [usize; 3],
    channels: usize,
    spacing: [f32; 3],
    placement: Option<Placement>,
    source: Source,
    time_points: usize,
    time_step: Option<f64>,
}

impl Opened {
    /// A volume decoded whole: its own metadata.
    fn whole(v: Volume) -> Opened {
        Opened {
            dims: v.dims(),
            channels: v.channel_count(),
            spacing: v.spacing(),
            placement: v.placement().copied(),
            source: Source::Whole(v),
            time_points: 1,
            time_step: None,
        }
    }

    /// A volume whose samples are `stored` in a file and whose other metadata (channels,
    /// spacing, placement) is that of `meta`, the stand-in a format's decoder read; `dims` are
    /// the real ones.
    fn stored(meta: &Volume, dims: [usize; 3], stored: Stored) -> Opened {
        Opened {
            dims,
            channels: meta.channel_count(),
            spacing: meta.spacing(),
            placement: meta.placement().copied(),
            source: Source::Stored(stored),
            time_points: 1,
            time_step: None,
        }
    }
}

impl RegionReader {
    /// Opens the volume at `path` as [`read_volume`] would read it (a DICOM series directory,
    /// a DICOM, NRRD, MetaImage or NIfTI file by extension, else by content, or a headerless
    /// raw file described by `raw`), reading only its header, and checking that the file
    /// holds all the samples the header announces. Compressed samples are inflated to a
    /// temporary file here; DICOM and ASCII NRRD are decoded whole here.
    ///
    /// A time series (a 4D NIfTI, a raw spec of several time points) is refused here as
    /// [`ReadError::TimeSeries`]: [`RegionReader::open_series`] opens it.
    pub fn open(path: &Path, raw: Option<&RawSpec>) -> Result<RegionReader, ReadError> {
        let reader = RegionReader::open_series(path, raw)?;
        if reader.time_points > 1 {
            return Err(ReadError::TimeSeries {
                path: path.to_path_buf(),
                points: reader.time_points,
            });
        }
        Ok(reader)
    }

    /// Opens `path` as [`RegionReader::open`] does, and a time series too: a 4D NIfTI
    /// (`dim[4]` time points, `pixdim[4]` in the unit of `xyzt_units` between them), a 4D NRRD
    /// whose first or last axis is `time` or `list` (a first one is read with every voxel's
    /// time points, of which one is kept), a 4D MetaImage, or a raw file of `raw.time_points`
    /// volumes one after another. Regions of any time point are
    /// read with [`RegionReader::read_region_at`]; [`RegionReader::read_region`] reads the
    /// selected one (the first, or [`RegionReader::select_time_point`]'s).
    pub fn open_series(path: &Path, raw: Option<&RawSpec>) -> Result<RegionReader, ReadError> {
        RegionReader::open_series_channel(path, raw, None)
    }

    /// [`RegionReader::open`] with a channel chosen: of a Zarr array with a channel axis, or
    /// of a TIFF storing channels as planes of their own (an ImageJ hyperstack, an OME-TIFF),
    /// the one read (several are refused without a choice, as [`ReadError::Channels`]); of any
    /// other source, one of the channels it reads together (of RGB, 0 to 2), kept as a volume
    /// of one channel. `None` opens as [`RegionReader::open`] does.
    pub fn open_channel(
        path: &Path,
        raw: Option<&RawSpec>,
        channel: Option<usize>,
    ) -> Result<RegionReader, ReadError> {
        let reader = RegionReader::open_series_channel(path, raw, channel)?;
        if reader.time_points > 1 {
            return Err(ReadError::TimeSeries {
                path: path.to_path_buf(),
                points: reader.time_points,
            });
        }
        Ok(reader)
    }

    /// [`RegionReader::open_series`] with a channel chosen, as [`RegionReader::open_channel`]
    /// chooses it.
    pub fn open_series_channel(
        path: &Path,
        raw: Option<&RawSpec>,
        channel: Option<usize>,
    ) -> Result<RegionReader, ReadError> {
        let opened = formats::open(path, raw, channel)?;
        // Whether the format chose the channel when it opened (only its samples are read).
        let chosen = match &opened.source {
            Source::Zarr(_) => true,
            Source::Tiff(t) => t.channel_chosen(),
            _ => false,
        };
        let kept_channel = if chosen {
            None
        } else {
            super::channel_to_keep(path, opened.channels, channel)?
        };
        Ok(RegionReader {
            path: path.to_path_buf(),
            dims: opened.dims,
            channels: opened.channels,
            spacing: opened.spacing,
            placement: opened.placement,
            source: opened.source,
            time_points: opened.time_points,
            time_step: opened.time_step,
            selected: 0,
            kept_channel,
        })
    }

    /// Time points (1 for a volume).
    pub fn time_points(&self) -> usize {
        self.time_points
    }

    /// Seconds between time points, when the file says.
    pub fn time_step(&self) -> Option<f64> {
        self.time_step
    }

    /// This reader with time point `t` selected: [`RegionReader::read_region`] (and so the
    /// reader as a brick source) reads it, as one volume.
    pub fn select_time_point(mut self, t: usize) -> Result<RegionReader, ReadError> {
        if t >= self.time_points {
            return Err(ReadError::Region {
                path: self.path.clone(),
                reason: format!(
                    "time point {t}: it has {} (0..={})",
                    self.time_points,
                    self.time_points - 1
                ),
            });
        }
        self.selected = t;
        Ok(self)
    }

    /// Dimensions (x, y, z) of the whole volume; their product may exceed [`MAX_VOXELS`](wavesplat_codec::volume::MAX_VOXELS).
    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// Voxels in the whole volume (u128: three `usize` factors can overflow `u64`).
    pub fn voxel_count(&self) -> u128 {
        self.dims.iter().map(|d| *d as u128).product()
    }

    /// Number of channels a region holds (1 or 3; 1 where one was chosen).
    pub fn channels(&self) -> usize {
        if self.kept_channel.is_some() {
            1
        } else {
            self.channels
        }
    }

    /// Voxel spacing (x, y, z), as [`read_volume`] gives it.
    pub fn spacing(&self) -> [f32; 3] {
        self.spacing
    }

    /// Placement of the whole volume in patient space (LPS), as [`read_volume`] gives it.
    pub fn placement(&self) -> Option<&Placement> {
        self.placement.as_ref()
    }

    /// Whether the volume was decoded whole at open (ASCII NRRD) rather than read region by
    /// region from its files.
    pub fn in_memory(&self) -> bool {
        matches!(self.source, Source::Whole(_))
    }

    /// The path the reader was opened from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Reads the box of `size` voxels whose first voxel is `origin`: the same values (rescale,
    /// sign, byte order, channels) as [`read_volume`] gives those voxels, the volume's
    /// spacing, and its placement moved to where voxel `origin` lies, so the region is placed
    /// where it is in the whole. The box must be non-empty and within [`RegionReader::dims`]
    /// (else [`ReadError::Region`]) and hold at most [`MAX_VOXELS`](wavesplat_codec::volume::MAX_VOXELS) voxels. NaN or Inf
    /// samples are refused as [`read_volume`] refuses them, with the whole volume's
    /// coordinates, but only when they lie in the region.
    pub fn read_region(&self, origin: [usize; 3], size: [usize; 3]) -> Result<Volume, ReadError> {
        self.read_region_at(self.selected, origin, size)
    }

    /// Reads a region of time point `t` as [`RegionReader::read_region`] does.
    pub fn read_region_at(
        &self,
        t: usize,
        origin: [usize; 3],
        size: [usize; 3],
    ) -> Result<Volume, ReadError> {
        if t >= self.time_points {
            return Err(ReadError::Region {
                path: self.path.clone(),
                reason: format!("time point {t} of {}", self.time_points),
            });
        }
        let outside = || ReadError::Region {
            path: self.path.clone(),
            reason: format!(
                "the region of {size:?} voxels at {origin:?} is empty or outside the volume's {:?}",
                self.dims
            ),
        };
        for a in 0..3 {
            let end = origin[a].checked_add(size[a]).ok_or_else(outside)?;
            if size[a] == 0 || end > self.dims[a] {
                return Err(outside());
            }
        }
        let voxels = checked_voxels(size).map_err(|e| ReadError::volume(&self.path, e))?;
        let (planar, data_path) = match &self.source {
            Source::Whole(v) => (cut(v, origin, size), &self.path),
            Source::Series(s) => (s.read(origin, size)?, &self.path),
            Source::Tiff(s) => (s.read(t, origin, size)?, &self.path),
            Source::Zarr(s) => (vec![s.read(t, origin, size)?], &self.path),
            Source::Stored(s) => (self.read_stored(s, t, origin, size, voxels)?, &s.path),
        };
        let planar = match self.kept_channel {
            Some(c) => planar.into_iter().nth(c).into_iter().collect(),
            None => planar,
        };
        let volume = Volume::new(size, self.spacing, planar).map_err(|e| {
            let e = match e {
                VolumeError::NonFinite {
                    channel,
                    x,
                    y,
                    z,
                    value,
                } => VolumeError::NonFinite {
                    // The source's channel, where one of several was kept.
                    channel: self.kept_channel.unwrap_or(channel),
                    x: x + origin[0],
                    y: y + origin[1],
                    z: z + origin[2],
                    value,
                },
                e => e,
            };
            match (&self.source, &e) {
                // Samples cut into files: the file holding the sample.
                (
                    Source::Stored(s),
                    VolumeError::NonFinite {
                        channel, x, y, z, ..
                    },
                ) => {
                    let at = s.piece_path(t, [*x, *y, *z], *channel, self.dims, self.channels);
                    ReadError::volume(at.unwrap_or(data_path), e)
                }
                _ => ReadError::volume(data_path, e),
            }
        })?;
        match &self.placement {
            Some(p) => {
                let moved = Placement {
                    origin: p.position(self.spacing, origin.map(|o| o as f64)),
                    directions: p.directions,
                };
                volume
                    .with_placement(moved)
                    .map_err(|e| ReadError::volume(&self.path, e))
            }
            None => Ok(volume),
        }
    }

    /// Reads the samples of a region from a file: one positioned read per row, or per run of
    /// contiguous rows when the region spans whole rows (and whole slabs).
    fn read_stored(
        &self,
        s: &Stored,
        t: usize,
        origin: [usize; 3],
        size: [usize; 3],
        voxels: usize,
    ) -> Result<Vec<Vec<f32>>, ReadError> {
        // Bytes of a voxel of one time point, and as stored (with every time point of the
        // voxel when they are interleaved: then only time point `t`'s are kept).
        let voxel_bytes = self.channels * s.sample.size();
        let il = s.interleaved.max(1);
        let stored_voxel = voxel_bytes * il;
        let total = voxels.checked_mul(voxel_bytes).ok_or(ReadError::TooLarge {
            dims: size,
            channels: self.channels,
            bytes_per_sample: s.sample.size(),
        })?;
        let mut buf = Vec::new();
        buf.try_reserve_exact(total).map_err(|_| {
            ReadError::io(
                &s.path,
                io::Error::new(
                    io::ErrorKind::OutOfMemory,
                    format!("cannot allocate {total} bytes for a region"),
                ),
            )
        })?;
        buf.resize(total, 0);
        let [nx, ny, _] = self.dims.map(|d| d as u64);
        let first = if il == 1 { t as u64 * s.frame } else { 0 };
        // Byte offset of voxel (x, y, z); within the file size checked at open, so no overflow.
        let at = |x: usize, y: usize, z: usize| {
            s.offset + first + ((z as u64 * ny + y as u64) * nx + x as u64) * stored_voxel as u64
        };
        let full_rows = size[0] == self.dims[0];
        // Interleaved time points are read a slab at a time at most, the slab with all of them.
        let full_slabs = full_rows && size[1] == self.dims[1] && il == 1;
        let (run, runs): (usize, Vec<u64>) = if full_slabs {
            (total, vec![at(0, 0, origin[2])])
        } else if full_rows {
            let run = size[0] * size[1] * voxel_bytes;
            let starts = (origin[2]..origin[2] + size[2])
                .map(|z| at(0, origin[1], z))
                .collect();
            (run, starts)
        } else {
            let run = size[0] * voxel_bytes;
            let starts = (origin[2]..origin[2] + size[2])
                .flat_map(|z| (origin[1]..origin[1] + size[1]).map(move |y| (y, z)))
                .map(|(y, z)| at(origin[0], y, z))
                .collect();
            (run, starts)
        };
        let mut scratch = Vec::new();
        for (chunk, start) in buf.chunks_mut(run).zip(runs) {
            let into: &mut [u8] = if il == 1 {
                &mut *chunk
            } else {
                scratch.resize(chunk.len() * il, 0);
                &mut scratch[..]
            };
            let wanted = into.len() as u64;
            s.read_at(into, start).map_err(|(e, path, at)| {
                if e.kind() == io::ErrorKind::UnexpectedEof {
                    let len = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
                    ReadError::Truncated {
                        path: path.to_path_buf(),
                        offset: at,
                        expected: wanted,
                        actual: len.saturating_sub(at).min(wanted),
                    }
                } else {
                    ReadError::io(path, e)
                }
            })?;
            if il > 1 {
                let keep = t * voxel_bytes..(t + 1) * voxel_bytes;
                for (dst, src) in chunk
                    .chunks_exact_mut(voxel_bytes)
                    .zip(scratch.chunks_exact(stored_voxel))
                {
                    dst.copy_from_slice(&src[keep.clone()]);
                }
            }
        }
        let planar = deinterleave(&buf, s.sample, s.endian, self.channels, s.slope, s.inter);
        Ok(planar)
    }
}

/// The box `origin`, `size` (within `v`) of each channel of `v`.
fn cut(v: &Volume, origin: [usize; 3], size: [usize; 3]) -> Vec<Vec<f32>> {
    let n = size[0] * size[1] * size[2];
    v.channels()
        .iter()
        .map(|ch| {
            let mut out = Vec::with_capacity(n);
            for z in origin[2]..origin[2] + size[2] {
                for y in origin[1]..origin[1] + size[1] {
                    let i = v.index(origin[0], y, z);
                    out.extend_from_slice(&ch[i..i + size[0]]);
                }
            }
            out
        })
        .collect()
}

/// Fills `buf` from `file` at byte `offset`, without moving a shared cursor.
fn read_at(file: &File, buf: &mut [u8], offset: u64) -> io::Result<()> {
    #[cfg(unix)]
    {
        std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
    }
    #[cfg(windows)]
    {
        use std::os::windows::fs::FileExt;
        let (mut buf, mut offset) = (buf, offset);
        while !buf.is_empty() {
            match file.seek_read(buf, offset) {
                Ok(0) => return Err(io::ErrorKind::UnexpectedEof.into()),
                Ok(n) => {
                    buf = &mut buf[n..];
                    offset += n as u64;
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
}

/// Reads `path` whole through [`read_volume`] (the fallback for formats not read by region).
fn read_whole(path: &Path) -> Result<Opened, ReadError> {
    Ok(Opened::whole(read_volume(path, None)?))
}
