//! Zarr arrays, the chunked format of large microscopy (OME-Zarr), synchrotron and simulation
//! volumes: a directory holding an array (Zarr v3 `zarr.json`, or v2 `.zarray`) or an OME-Zarr
//! image group (`multiscales`, of which the first dataset, the full resolution, is read).
//! Decoding (the chunk grid, chunk keys, codecs such as Blosc, Zstd, gzip, zlib, sharding and
//! transposition, fill values of missing chunks) is the `zarrs` crate's; this module finds the
//! array, decides which of its axes are x, y, z, time and channel, reads a region's samples and
//! converts them to f32.
//!
//! Axes come from OME-Zarr's `axes` (their `type`, else their name), else from the array's
//! dimension names (v3 `dimension_names`, xarray's `_ARRAY_DIMENSIONS`: `x`, `y`, `z`, `t` or
//! `time`, `c` or `channel`), else from the count: `z, y, x` for three, `t, z, y, x` for four and
//! OME's `t, c, z, y, x` for five. The spatial axes may come in any order; of a channel axis
//! of several channels one is read, the one chosen (an array of several channels opened
//! without a choice is refused, saying how many it holds); any other axis must
//! be of size 1. Spacing, in mm: OME's `scale`
//! transformations of the first dataset (and of the whole multiscale) in each axis's `unit`
//! (a scale without a unit is taken as mm), else 1; the seconds between time points from the
//! time axis's scale and unit. Samples: unsigned and signed integers of 8 to 64 bits, 32- and
//! 64-bit floats and booleans; others are refused naming the type. A chunk larger than
//! [`MAX_CHUNK_BYTES`] is refused (a region decodes every chunk it touches whole; a chunk that
//! reaches outside the region, such as a chunk of one whole plane under bricks side by side,
//! is decoded into a temporary file once regions share it: [`super::spool`]). The store
//! is untrusted: every chunk's decoded size is checked before zarrs decodes it (`Bounded`),
//! and codec chains that check cannot see through (two compressors, a compressor after a
//! shard, a shard in a shard) are refused; metadata that does not parse, chunks that do not
//! decode and non-finite samples (a float array's NaN fill value where chunks are missing,
//! too) are typed errors naming it.

use std::io::Read;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use serde_json::Value;
use zarrs::array::{data_type, Array, ArrayShardedExt, ArraySubset};
use zarrs::storage::byte_range::{ByteRange, ByteRangeIterator, InvalidByteRangeError};
use zarrs::storage::{
    MaybeBytesIterator, ReadableStorage, ReadableStorageTraits, StorageError, StoreKey,
    WritableStorageTraits,
};

use super::spool::{ChunkSpool, NativeBytes};
use super::{ReadError, SampleType, SourceFiles};
use wavesplat_codec::format::series::MAX_TIME_POINTS;
use wavesplat_codec::volume::{checked_voxels, Volume};

const FORMAT: &str = "Zarr";

/// Largest decoded chunk, in bytes.
pub const MAX_CHUNK_BYTES: u64 = 1 << 30;

/// The metadata files that make a directory a Zarr store (an array or a group).
const METADATA_FILES: [&str; 3] = ["zarr.json", ".zarray", ".zgroup"];

/// Whether `path` is a directory holding Zarr metadata at its top.
pub fn is_store(path: &Path) -> bool {
    path.is_dir() && METADATA_FILES.iter().any(|m| path.join(m).is_file())
}

/// What an axis of the array is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    /// x, y or z (0, 1, 2).
    Space(usize),
    /// Spatial, its letter not said (taken in `z, y, x` order among the unnamed).
    SpaceUnnamed,
    Time,
    Channel,
    /// Anything else: must be of size 1.
    Other,
}

/// An OME-Zarr axis, or an array's dimension name.
#[derive(Debug, Clone, Default)]
struct Axis {
    name: String,
    kind: Option<String>,
    unit: Option<String>,
}

/// Where the array is inside the store, and what its image metadata says.
#[derive(Debug, Clone)]
struct Target {
    /// The array's node path (`/`, or `/0` for an OME-Zarr image's first dataset).
    array: String,
    /// OME-Zarr's axes, when an image group names them.
    axes: Option<Vec<Axis>>,
    /// The product of OME-Zarr's scale transformations, per axis.
    scale: Option<Vec<f64>>,
}

/// A Zarr array opened as a volume (or a time series of volumes), read by region.
pub(crate) struct ZarrVolume {
    /// The store (for messages).
    path: PathBuf,
    array: Array<dyn ReadableStorageTraits>,
    /// The sample type, as the other readers name it; `None` for booleans.
    sample: Option<SampleType>,
    /// For x, y, z: the array axis holding it.
    space_axes: [usize; 3],
    /// The array axis of time, if any.
    time_axis: Option<usize>,
    /// The array axis of channels, if any, and the channel read along it.
    channel_axis: Option<(usize, u64)>,
    /// Channels along the channel axis (1 without one).
    channels: usize,
    dims: [usize; 3],
    time_points: usize,
    spacing: [f32; 3],
    time_step: Option<f64>,
    /// A decoded chunk's bytes (an inner chunk's, of an array sharded and nothing else).
    chunk_bytes: u64,
    /// Whether the chunks are compressed (else a region reads only its own bytes of them,
    /// and nothing is spooled).
    compressed: bool,
    /// Chunks that several regions share (a chunk of one whole plane under bricks side by
    /// side), decoded once they share them, by their grid indices.
    spool: ChunkSpool<Vec<u64>, ()>,
}

impl std::fmt::Debug for ZarrVolume {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZarrVolume")
            .field("path", &self.path)
            .field("dims", &self.dims)
            .field("time_points", &self.time_points)
            .finish_non_exhaustive()
    }
}

fn bad(path: &Path, reason: impl Into<String>) -> ReadError {
    ReadError::bad_header(path, FORMAT, reason)
}

impl ZarrVolume {
    /// Opens the store at `path` (a directory) as a volume, the channel `channel` of it
    /// (`None`: the only one; an array of several channels is refused).
    pub(crate) fn open(path: &Path, channel: Option<usize>) -> Result<ZarrVolume, ReadError> {
        let store = zarrs::filesystem::FilesystemStore::new(path)
            .map_err(|e| ReadError::io(path, std::io::Error::other(e.to_string())))?;
        ZarrVolume::of_store(path, Arc::new(store), channel)
    }

    /// Opens a store's gathered files (names relative to the store, `/`-separated).
    fn of_files(src: &SourceFiles, channel: Option<usize>) -> Result<ZarrVolume, ReadError> {
        let store = zarrs::storage::store::MemoryStore::new();
        for (name, bytes) in &src.files {
            let key = StoreKey::new(name.as_str())
                .map_err(|e| bad(&src.path_of(name), format!("not a store key: {e}")))?;
            store
                .set(&key, bytes.clone().into())
                .map_err(|e| bad(&src.path_of(name), e.to_string()))?;
        }
        ZarrVolume::of_store(&src.origin, Arc::new(store), channel)
    }

    fn of_store(
        path: &Path,
        store: ReadableStorage,
        channel: Option<usize>,
    ) -> Result<ZarrVolume, ReadError> {
        let target = locate(path, &store)?;
        let bounded = Arc::new(Bounded::new(store));
        let store: ReadableStorage = bounded.clone();
        let array = guarded(path, || Array::open(store, &target.array))?
            .map_err(|e| bad(path, format!("array {}: {e}", target.array)))?;
        let dt = array.data_type();
        let sample = [
            (data_type::bool(), None),
            (data_type::uint8(), Some(SampleType::U8)),
            (data_type::int8(), Some(SampleType::I8)),
            (data_type::uint16(), Some(SampleType::U16)),
            (data_type::int16(), Some(SampleType::I16)),
            (data_type::uint32(), Some(SampleType::U32)),
            (data_type::int32(), Some(SampleType::I32)),
            (data_type::uint64(), Some(SampleType::U64)),
            (data_type::int64(), Some(SampleType::I64)),
            (data_type::float32(), Some(SampleType::F32)),
            (data_type::float64(), Some(SampleType::F64)),
        ]
        .into_iter()
        .find(|(d, _)| d == dt)
        .map(|(_, s)| s)
        .ok_or_else(|| {
            ReadError::unsupported(
                path,
                format!(
                    "samples of type {}: Zarr arrays of booleans, integers of 8 to 64 bits \
                     and 32- or 64-bit floats are read",
                    serde_json::to_value(array.metadata())
                        .ok()
                        .and_then(|m| m.get("data_type").or(m.get("dtype")).cloned())
                        .unwrap_or(Value::Null)
                ),
            )
        })?;
        let shape = array.shape().to_vec();
        let axes = match &target.axes {
            Some(axes) => axes.clone(),
            None => dimension_names(&array),
        };
        let roles = roles(path, &shape, &axes)?;
        let mut space_axes = [usize::MAX; 3];
        let mut unnamed = Vec::new();
        let (mut time_axis, mut channel_axis) = (None, None);
        for (i, role) in roles.iter().enumerate() {
            match *role {
                Role::Space(k) if space_axes[k] == usize::MAX => space_axes[k] = i,
                Role::Space(k) => {
                    return Err(bad(path, format!("two axes are {}", ["x", "y", "z"][k])));
                }
                Role::SpaceUnnamed => unnamed.push(i),
                Role::Time if time_axis.is_none() => time_axis = Some(i),
                Role::Channel if channel_axis.is_none() => channel_axis = Some(i),
                Role::Time | Role::Channel => {
                    return Err(bad(path, format!("two {role:?} axes").to_lowercase()));
                }
                Role::Other => {}
            }
        }
        // The unnamed spatial axes fill the letters left, slowest first: z, y, x.
        let free: Vec<usize> = (0..3)
            .rev()
            .filter(|k| space_axes[*k] == usize::MAX)
            .collect();
        let mut roles = roles;
        for (n, i) in unnamed.into_iter().enumerate() {
            match free.get(n) {
                Some(&k) => space_axes[k] = i,
                // A spatial axis beyond three: of size 1, or refused below.
                None => roles[i] = Role::Other,
            }
        }
        if space_axes.contains(&usize::MAX) {
            return Err(ReadError::unsupported(
                path,
                format!(
                    "an array of shape {shape:?} with axes {:?}: a volume has three spatial \
                     axes (x, y, z)",
                    axes.iter().map(|a| a.name.as_str()).collect::<Vec<_>>()
                ),
            ));
        }
        for (i, role) in roles.iter().enumerate() {
            if *role == Role::Other && shape[i] != 1 {
                let name = axes.get(i).map_or("", |a| a.name.as_str());
                let why = format!(
                    "{} entries along axis {i} ({name:?}) of shape {shape:?}, which is no \
                     spatial, time or channel axis: such an axis must be of size 1",
                    shape[i]
                );
                return Err(ReadError::unsupported(path, why));
            }
        }
        let channels = channel_axis.map_or(1, |i| shape[i]);
        if channels == 0 {
            return Err(ReadError::unsupported(
                path,
                format!("a channel axis of no channel (shape {shape:?})"),
            ));
        }
        let channel_axis = match (channel_axis, channel) {
            (None, None | Some(0)) => None,
            (Some(i), None) if channels == 1 => Some((i, 0)),
            (Some(i), Some(c)) if (c as u64) < channels => Some((i, c as u64)),
            (Some(i), None) => {
                return Err(ReadError::Channels {
                    path: path.to_path_buf(),
                    channels,
                    why: format!(
                        "axis {i} of shape {shape:?} holds them; one is read (`archive \
                         submit` makes each a volume of its own)"
                    ),
                });
            }
            (_, Some(c)) => return Err(ReadError::channel_not_held(path, channels, c)),
        };
        let channels = usize::try_from(channels).unwrap_or(usize::MAX);
        let size = |i: usize| {
            usize::try_from(shape[i]).map_err(|_| bad(path, format!("size {} too large", shape[i])))
        };
        let dims = [
            size(space_axes[0])?,
            size(space_axes[1])?,
            size(space_axes[2])?,
        ];
        let time_points = time_axis.map(size).transpose()?.unwrap_or(1);
        if time_points > MAX_TIME_POINTS {
            return Err(ReadError::unsupported(
                path,
                format!("{time_points} time points: at most {MAX_TIME_POINTS} are read"),
            ));
        }
        if dims.contains(&0) || time_points == 0 {
            return Err(ReadError::volume(
                path,
                wavesplat_codec::volume::VolumeError::ZeroDimension(dims),
            ));
        }
        // A region decodes each chunk it touches whole (of a sharded array with no other codec,
        // each inner chunk): bound a chunk's bytes. Only regular grids: every chunk is the
        // first's shape.
        let grid = serde_json::to_value(array.metadata())
            .ok()
            .and_then(|m| m.get("chunk_grid").cloned())
            .and_then(|g| g.get("name").and_then(Value::as_str).map(str::to_string));
        if let Some(name) = grid.filter(|n| n != "regular") {
            return Err(ReadError::unsupported(
                path,
                format!("a {name:?} chunk grid: regular grids are read"),
            ));
        }
        let origin = vec![0u64; shape.len()];
        let chunk = match array.effective_subchunk_shape() {
            Some(inner) if array.is_exclusively_sharded() => inner,
            _ => array
                .chunk_shape(&origin)
                .map_err(|e| bad(path, format!("chunk grid: {e}")))?,
        };
        let chunk_bytes = chunk
            .iter()
            .try_fold(sample.map_or(1, SampleType::size) as u128, |acc, d| {
                acc.checked_mul(u128::from(d.get()))
            })
            .unwrap_or(u128::MAX);
        if chunk_bytes > u128::from(MAX_CHUNK_BYTES) {
            return Err(ReadError::unsupported(
                path,
                format!(
                    "chunks of {:?} samples ({chunk_bytes} bytes): at most {MAX_CHUNK_BYTES} \
                     bytes a chunk are decoded",
                    chunk.iter().map(|d| d.get()).collect::<Vec<_>>()
                ),
            ));
        }
        if let Some(s) = target.scale.as_ref().filter(|s| s.len() != shape.len()) {
            let why = format!("a scale of {} values for {} axes", s.len(), shape.len());
            return Err(bad(path, why));
        }
        let metadata = serde_json::to_value(array.metadata()).unwrap_or_default();
        let codecs = Codecs::of(&metadata).map_err(|why| ReadError::unsupported(path, why))?;
        let compressed = codecs.chain.compressor != Compressor::None;
        bounded.arm(chunk_bytes as u64, codecs);
        let scale_of = |i: usize| target.scale.as_ref().and_then(|s| s.get(i)).copied();
        let mut spacing = [1.0f32; 3];
        for (k, &i) in space_axes.iter().enumerate() {
            if let Some(s) = scale_of(i) {
                let unit = axes.get(i).and_then(|a| a.unit.as_deref());
                let mm = match unit.map(|u| (u, super::tiff_stack::unit_mm(u))) {
                    None => 1.0,
                    Some((_, Some(mm))) => mm,
                    Some((u, None)) => {
                        return Err(bad(
                            path,
                            format!("axis {i}'s unit {u:?} is no length this reader knows"),
                        ))
                    }
                };
                let v = (s * mm) as f32;
                if !(v.is_finite() && v > 0.0) {
                    return Err(bad(
                        path,
                        format!("scale {s} of axis {i} is no positive spacing"),
                    ));
                }
                spacing[k] = v;
            }
        }
        let time_step = time_axis.and_then(|i| {
            let s = scale_of(i)?;
            let unit = axes
                .get(i)
                .and_then(|a| a.unit.as_deref())
                .unwrap_or("second");
            let step = s * super::tiff_stack::time_unit_s(unit)?;
            (step.is_finite() && step > 0.0).then_some(step)
        });
        Ok(ZarrVolume {
            path: path.to_path_buf(),
            array,
            sample,
            space_axes,
            time_axis,
            channel_axis,
            channels,
            dims,
            time_points,
            spacing,
            time_step,
            chunk_bytes: chunk_bytes as u64,
            compressed,
            spool: ChunkSpool::default(),
        })
    }

    pub(crate) fn dims(&self) -> [usize; 3] {
        self.dims
    }

    pub(crate) fn time_points(&self) -> usize {
        self.time_points
    }

    /// Channels along the array's channel axis (1 without one), of which one is read.
    pub(crate) fn channels(&self) -> usize {
        self.channels
    }

    pub(crate) fn time_step(&self) -> Option<f64> {
        self.time_step
    }

    pub(crate) fn spacing(&self) -> [f32; 3] {
        self.spacing
    }

    /// The samples of the box at `origin` of `size` at time point `t`, x fastest (one channel).
    pub(crate) fn read(
        &self,
        t: usize,
        origin: [usize; 3],
        size: [usize; 3],
    ) -> Result<Vec<f32>, ReadError> {
        let n = checked_voxels(size).map_err(|e| ReadError::volume(&self.path, e))?;
        let rank = self.array.dimensionality();
        let mut ranges: Vec<Range<u64>> = vec![0..1; rank];
        for k in 0..3 {
            let (o, s) = (origin[k] as u64, size[k] as u64);
            ranges[self.space_axes[k]] = o..o + s;
        }
        if let Some(i) = self.time_axis {
            ranges[i] = t as u64..t as u64 + 1;
        }
        if let Some((i, c)) = self.channel_axis {
            ranges[i] = c..c + 1;
        }
        // Strides of the box's array axes (C order), for x, y and z.
        let extent: Vec<usize> = ranges.iter().map(|r| (r.end - r.start) as usize).collect();
        let mut stride = vec![1usize; rank];
        for i in (0..rank.saturating_sub(1)).rev() {
            stride[i] = stride[i + 1] * extent[i + 1];
        }
        let s = self.space_axes.map(|i| stride[i]);
        let failed = |e: zarrs::array::ArrayError| ReadError::Data {
            path: self.path.clone(),
            format: FORMAT,
            reason: format!("reading the box {ranges:?} of the array: {e}"),
        };
        let mut out = Vec::new();
        out.try_reserve_exact(n).map_err(|_| {
            ReadError::io(
                &self.path,
                std::io::Error::new(
                    std::io::ErrorKind::OutOfMemory,
                    format!("cannot allocate {n} samples"),
                ),
            )
        })?;
        let shared = self.shared_chunks(&ranges)?;
        // The box in one call to zarrs.
        macro_rules! whole {
            ($t:ty, $conv:expr) => {{
                let v: Vec<$t> = guarded(&self.path, || self.array.retrieve_array_subset(&ranges))?
                    .map_err(failed)?;
                let conv = $conv;
                for z in 0..size[2] {
                    for y in 0..size[1] {
                        let row = z * s[2] + y * s[1];
                        out.extend((0..size[0]).map(|x| conv(v[row + x * s[0]])));
                    }
                }
            }};
        }
        // Chunk by chunk where the box's chunks are shared with other regions, else whole.
        macro_rules! gather {
            ($t:ty, $conv:expr) => {{
                if let Some(chunks) = &shared {
                    out.resize(n, 0.0);
                    for (chunk, shared) in chunks {
                        let at = (chunk.as_slice(), *shared);
                        self.read_chunk::<$t>(at, &ranges, origin, size, &mut out, $conv)?;
                    }
                    return Ok(out);
                }
                whole!($t, $conv)
            }};
        }
        match self.sample {
            None => whole!(bool, |v: bool| f32::from(u8::from(v))),
            Some(SampleType::U8) => gather!(u8, f32::from),
            Some(SampleType::I8) => gather!(i8, f32::from),
            Some(SampleType::U16) => gather!(u16, f32::from),
            Some(SampleType::I16) => gather!(i16, f32::from),
            Some(SampleType::U32) => gather!(u32, |v: u32| v as f32),
            Some(SampleType::I32) => gather!(i32, |v: i32| v as f32),
            Some(SampleType::U64) => gather!(u64, |v: u64| v as f32),
            Some(SampleType::I64) => gather!(i64, |v: i64| v as f32),
            Some(SampleType::F32) => gather!(f32, |v: f32| v),
            Some(SampleType::F64) => gather!(f64, |v: f64| v as f32),
        }
        Ok(out)
    }
}

impl ZarrVolume {
    /// The chunks the box `ranges` meets, each with its samples within the array
    /// ([`ZarrVolume::samples_read`]) where it reaches outside the box (other regions will
    /// decode it too), where some of them do (`None`: the box is read in one call, as `zarrs`
    /// reads it).
    /// Arrays of booleans, uncompressed and sharded arrays (whose regions read only their own
    /// bytes, or a shard's inner chunks) and boxes of more than [`MAX_CHUNKS_ONE_BY_ONE`]
    /// chunks are read in one call.
    #[allow(clippy::type_complexity)]
    fn shared_chunks(
        &self,
        ranges: &[Range<u64>],
    ) -> Result<Option<Vec<(Vec<u64>, Option<u64>)>>, ReadError> {
        if self.sample.is_none() || !self.compressed || self.array.is_sharded() {
            return Ok(None);
        }
        let grid = |e: &dyn std::fmt::Display| ReadError::Data {
            path: self.path.clone(),
            format: FORMAT,
            reason: format!("the chunks of the box {ranges:?}: {e}"),
        };
        let subset = ArraySubset::new_with_ranges(ranges);
        let Some(within) = self
            .array
            .chunks_in_array_subset(&subset)
            .map_err(|e| grid(&e))?
        else {
            return Ok(None);
        };
        if within.num_elements() > MAX_CHUNKS_ONE_BY_ONE {
            return Ok(None);
        }
        let mut chunks = Vec::new();
        for c in &within.indices() {
            let chunk = self.array.chunk_subset_bounded(&c).map_err(|e| grid(&e))?;
            let chunk = chunk.to_ranges();
            let shared = self
                .reaches_out(&chunk, ranges)
                .then(|| self.samples_read(&chunk));
            chunks.push((c.to_vec(), shared));
        }
        Ok(chunks.iter().any(|(_, s)| s.is_some()).then_some(chunks))
    }

    /// The samples of `block` a region reads: along space and time, not channels (of which
    /// one is read).
    fn samples_read(&self, block: &[Range<u64>]) -> u64 {
        let channel = self.channel_axis.map(|(a, _)| a);
        (0..block.len())
            .filter(|d| Some(*d) != channel)
            .map(|d| block[d].end - block[d].start)
            .product()
    }

    /// Whether the chunk over `chunk` (within the array) reaches outside the box `ranges` along
    /// an axis other regions read along: space or time (not channels, of which one is read).
    fn reaches_out(&self, chunk: &[Range<u64>], ranges: &[Range<u64>]) -> bool {
        let channel = self.channel_axis.map(|(a, _)| a);
        (0..ranges.len()).any(|d| {
            Some(d) != channel && (chunk[d].start < ranges[d].start || chunk[d].end > ranges[d].end)
        })
    }

    /// Adds the samples of chunk `chunk` inside the box `ranges` (a region at `origin` of
    /// `size`) to `out` (x fastest): from the spool where the chunk reaches outside the box
    /// (`shared`: its samples within the array, [`ZarrVolume::shared_chunks`]) and another
    /// region has needed it, else decoded by `zarrs`, only the part inside the box.
    fn read_chunk<T: NativeBytes + zarrs::array::ElementOwned>(
        &self,
        (chunk, shared): (&[u64], Option<u64>),
        ranges: &[Range<u64>],
        origin: [usize; 3],
        size: [usize; 3],
        out: &mut [f32],
        conv: impl Fn(T) -> f32,
    ) -> Result<(), ReadError> {
        let failed = |e: &dyn std::fmt::Display| ReadError::Data {
            path: self.path.clone(),
            format: FORMAT,
            reason: format!("reading chunk {chunk:?} of the array: {e}"),
        };
        // The chunk's own grid (beyond the array's end at its edge, as zarrs decodes it).
        let whole = self
            .array
            .chunk_subset(chunk)
            .map_err(|e| failed(&e))?
            .to_ranges();
        let inside: Vec<Range<u64>> = whole
            .iter()
            .zip(ranges)
            .map(|(c, r)| c.start.max(r.start)..c.end.min(r.end))
            .collect();
        if inside.iter().any(|r| r.start >= r.end) {
            return Ok(());
        }
        let place = Placing {
            space_axes: self.space_axes,
            origin,
            size,
        };
        if let Some(total) = shared {
            // The chunk's samples this box reads, of its `total`: it is released once the
            // regions have read them all.
            let samples = (self.samples_read(&inside), total);
            let spooled = self.spool.get_or_spool(chunk.to_vec(), samples.0, || {
                self.spool.count_decoded();
                let v: Vec<T> = guarded(&self.path, || self.array.retrieve_chunk(chunk))
                    .ok()?
                    .ok()?;
                Some(((), T::to_bytes(&v)))
            });
            if let Some(s) = spooled {
                // The bytes from the box's first sample in the chunk to its last.
                let strides = c_strides(&whole);
                let at = |corner: &dyn Fn(&Range<u64>) -> u64| -> usize {
                    (0..whole.len())
                        .map(|d| (corner(&inside[d]) - whole[d].start) as usize * strides[d])
                        .sum()
                };
                let (first, last) = (at(&|r| r.start), at(&|r| r.end - 1));
                let span = (last + 1 - first) * T::SIZE;
                let at = ((first * T::SIZE) as u64, span);
                if let Some(bytes) = self.spool.read(chunk, &s, at, samples) {
                    let v = T::from_bytes(&bytes);
                    place.copy(&v, first, &whole, &inside, out, &conv);
                    return Ok(());
                }
            }
        }
        self.spool.count_decoded();
        let v: Vec<T> = guarded(&self.path, || self.array.retrieve_array_subset(&inside))?
            .map_err(|e| failed(&e))?;
        place.copy(&v, 0, &inside, &inside, out, &conv);
        Ok(())
    }
}

/// Chunks a box may meet and still be read one chunk at a time (beyond it, one call to
/// `zarrs`, which decodes its chunks in parallel).
const MAX_CHUNKS_ONE_BY_ONE: u64 = 4096;

/// Strides of a C-order block over `block`.
fn c_strides(block: &[Range<u64>]) -> Vec<usize> {
    let mut strides = vec![1usize; block.len()];
    for d in (0..block.len().saturating_sub(1)).rev() {
        strides[d] = strides[d + 1] * (block[d + 1].end - block[d + 1].start) as usize;
    }
    strides
}

/// Where the array's samples go in a region (x fastest).
struct Placing {
    /// For x, y, z: the array axis holding it.
    space_axes: [usize; 3],
    origin: [usize; 3],
    size: [usize; 3],
}

impl Placing {
    /// Copies the samples of the box `inside` from `src`, a C-order block over `block` whose
    /// first `skip` samples are left out, into `out`.
    fn copy<T: Copy>(
        &self,
        src: &[T],
        skip: usize,
        block: &[Range<u64>],
        inside: &[Range<u64>],
        out: &mut [f32],
        conv: &impl Fn(T) -> f32,
    ) {
        let rank = block.len();
        let strides = c_strides(block);
        let mut out_stride = vec![0usize; rank];
        let mut out_origin = vec![0u64; rank];
        let region = [1, self.size[0], self.size[0] * self.size[1]];
        for k in 0..3 {
            out_stride[self.space_axes[k]] = region[k];
            out_origin[self.space_axes[k]] = self.origin[k] as u64;
        }
        let last = rank - 1;
        let run = (inside[last].end - inside[last].start) as usize;
        let mut at: Vec<u64> = inside.iter().map(|r| r.start).collect();
        loop {
            let (mut s, mut o) = (0usize, 0usize);
            for d in 0..rank {
                s += (at[d] - block[d].start) as usize * strides[d];
                o += at[d].saturating_sub(out_origin[d]) as usize * out_stride[d];
            }
            let s = s - skip;
            for (j, v) in src[s..s + run].iter().enumerate() {
                out[o + j * out_stride[last]] = conv(*v);
            }
            // The next row of the box: the axes before the last, the last of them fastest.
            let mut d = last;
            loop {
                if d == 0 {
                    return;
                }
                d -= 1;
                at[d] += 1;
                if at[d] < inside[d].end {
                    break;
                }
                at[d] = inside[d].start;
            }
        }
    }
}

/// A store whose chunks are checked before `zarrs` decodes them, so that a few hostile bytes
/// cannot make the process allocate far more than a chunk (an allocation failure aborts; no
/// `catch_unwind` catches it; zarrs has no limit of its own). A chunk may decode to at most
/// twice a chunk's bytes and a MiB, by its one compressor ([`Chain`]; chains this cannot see
/// through are refused when the array is opened):
/// - Zstd: the bound of its frames (each frame's declared content size, which zarrs allocates
///   at once, or its blocks' most); where the bytes are not whole frames (zarrs then decodes
///   by streaming, as far as they go), they are decoded here first into nothing, up to the
///   limit;
/// - Blosc: its header's decoded size;
/// - gzip and zlib: inflated here first into nothing, up to the limit, where the chunk is long
///   enough to inflate past it (Deflate's most is 1 032 times its input). zarrs inflates with
///   no bound; a codec of our own in its place is not possible (zarrs picks a codec by name),
///   so such chunks are inflated twice;
/// - a shard read whole (a region covering it): every inner chunk its index places inside it,
///   as above; a part of a shard (an inner chunk, its index) as one inner chunk.
///
/// A byte range past a value's end is refused too: zarrs' stores compute a reversed range
/// from it and panic (seen in the in-memory store by the fuzz target).
struct Bounded {
    inner: ReadableStorage,
    /// The most decoded bytes a chunk may claim and the array's codecs, once its metadata is
    /// read; until then nothing is checked.
    armed: OnceLock<(u64, Codecs)>,
}

/// The one compressor of a chain of bytes-to-bytes codecs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Compressor {
    None,
    Zstd,
    Blosc,
    Gzip,
    Zlib,
}

/// What a chain of codecs does to a chunk's bytes, as far as its size goes.
#[derive(Clone, Copy, Debug)]
struct Chain {
    compressor: Compressor,
    /// A CRC-32C follows the compressed bytes (zarrs checks and strips it first).
    crc32c_after: bool,
}

/// The array's codecs: its chunks' chain, or its shards' index and their inner chunks' chain.
struct Codecs {
    chain: Chain,
    shard: Option<ShardIndex>,
}

/// Where a shard's inner chunks lie: its index of (offset, length) pairs, little-endian u64s.
struct ShardIndex {
    chunks: usize,
    at_end: bool,
    crc32c: bool,
    /// A CRC-32C of the whole shard follows it (zarrs checks and strips it first).
    checksummed: bool,
    inner: Chain,
}

/// A codec's name in a v3 list (`{"name": …}`, or the name alone) or a v2 entry (`{"id": …}`),
/// without numcodecs' `numcodecs.` prefix.
fn codec_name(codec: &Value) -> &str {
    let name = codec
        .as_str()
        .or_else(|| codec.get("name").and_then(Value::as_str))
        .or_else(|| codec.get("id").and_then(Value::as_str))
        .unwrap_or("");
    name.strip_prefix("numcodecs.").unwrap_or(name)
}

/// Where a v3 list of codecs (array-to-array ones such as transposition, one array-to-bytes
/// codec, then bytes-to-bytes ones) has its array-to-bytes codec.
fn array_to_bytes(codecs: &[Value]) -> Option<usize> {
    codecs
        .iter()
        .position(|c| matches!(codec_name(c), "bytes" | "sharding_indexed"))
}

/// `bytes` without the CRC-32C that ends them where `checksum` says one does; `None` when
/// they are shorter than one.
fn before_checksum(bytes: &[u8], checksum: bool) -> Option<&[u8]> {
    bytes.get(..bytes.len().checked_sub(if checksum { 4 } else { 0 })?)
}

fn compressor_named(name: &str) -> Option<Compressor> {
    Some(match name {
        "zstd" => Compressor::Zstd,
        "blosc" => Compressor::Blosc,
        "gzip" => Compressor::Gzip,
        "zlib" => Compressor::Zlib,
        _ => return None,
    })
}

impl Chain {
    /// The bytes-to-bytes codecs after a chunk's array-to-bytes codec: at most one compressor
    /// and at most one CRC-32C. A second compressor (whose input the first's output is, never
    /// seen by the store) is refused.
    fn of(codecs: &[Value]) -> Result<Chain, String> {
        let mut chain = Chain {
            compressor: Compressor::None,
            crc32c_after: false,
        };
        let mut crc32c = false;
        for c in codecs {
            let name = codec_name(c);
            if let Some(k) = compressor_named(name) {
                if chain.compressor != Compressor::None {
                    return Err(format!(
                        "two compressors in a chunk's codecs ({:?}, then {name:?}): one is read",
                        chain.compressor
                    ));
                }
                chain.compressor = k;
            } else if name == "crc32c" && !crc32c {
                crc32c = true;
                chain.crc32c_after = chain.compressor != Compressor::None;
            } else if name == "sharding_indexed" {
                return Err("a shard inside a shard, or codecs after a shard's: not read".into());
            } else {
                return Err(format!("the bytes codec {name:?} is not read"));
            }
        }
        Ok(chain)
    }
}

impl Codecs {
    /// The codecs of an array's metadata (v3 `codecs`; v2 `compressor` and `filters`), or why
    /// the chunks' sizes could not be checked before zarrs decodes them.
    fn of(metadata: &Value) -> Result<Codecs, String> {
        if let Some(list) = metadata.get("codecs").and_then(Value::as_array) {
            let at = array_to_bytes(list)
                .ok_or("no array-to-bytes codec (bytes or sharding_indexed)")?;
            let chain = Chain::of(&list[at + 1..])?;
            if codec_name(&list[at]) != "sharding_indexed" {
                return Ok(Codecs { chain, shard: None });
            }
            // After a shard's codec only a CRC-32C of the whole shard is read: a compressor
            // there would decode the inner chunks in memory, out of the store's sight.
            if chain.compressor != Compressor::None {
                return Err("a compressor after sharding_indexed is not read".into());
            }
            let mut shard = ShardIndex::of(metadata, &list[at])?;
            shard.checksummed = !list[at + 1..].is_empty();
            return Ok(Codecs {
                chain,
                shard: Some(shard),
            });
        }
        let compressor = metadata.get("compressor").filter(|c| !c.is_null());
        if let Some(c) = compressor {
            let name = codec_name(c);
            if compressor_named(name).is_none() {
                return Err(format!(
                    "the compressor {name:?}: Blosc, Zstd, gzip and zlib are read"
                ));
            }
        }
        let filters = metadata.get("filters").and_then(Value::as_array);
        for f in filters.into_iter().flatten() {
            let name = codec_name(f);
            if compressor_named(name).is_some() || name == "crc32c" {
                return Err(format!(
                    "the filter {name:?}: a compressor is read as the compressor only"
                ));
            }
        }
        Ok(Codecs {
            chain: Chain::of(compressor.map(std::slice::from_ref).unwrap_or_default())?,
            shard: None,
        })
    }
}

impl ShardIndex {
    fn of(metadata: &Value, sharding: &Value) -> Result<ShardIndex, String> {
        let config = sharding
            .get("configuration")
            .ok_or("sharding without configuration")?;
        let shape = |v: Option<&Value>| -> Option<Vec<u64>> {
            v?.as_array()?.iter().map(Value::as_u64).collect()
        };
        let shard = shape(
            metadata
                .get("chunk_grid")
                .and_then(|g| g.get("configuration"))
                .and_then(|c| c.get("chunk_shape")),
        )
        .ok_or("a shard's shape")?;
        let inner = shape(config.get("chunk_shape")).ok_or("a shard's inner chunk shape")?;
        if shard.len() != inner.len() || inner.contains(&0) {
            return Err(format!("inner chunks of {inner:?} in shards of {shard:?}"));
        }
        let chunks = shard
            .iter()
            .zip(&inner)
            .try_fold(1usize, |n, (s, i)| {
                n.checked_mul(usize::try_from(s.div_ceil(*i)).ok()?)
            })
            .ok_or("too many inner chunks in a shard")?;
        // Only an index of plain little-endian words, perhaps with a CRC-32C, is read.
        let mut crc32c = false;
        let index = config.get("index_codecs").and_then(Value::as_array);
        for c in index.into_iter().flatten() {
            match codec_name(c) {
                "bytes" => {
                    let endian = c
                        .get("configuration")
                        .and_then(|c| c.get("endian"))
                        .and_then(Value::as_str);
                    if !matches!(endian, None | Some("little")) {
                        return Err("a big-endian shard index is not read".into());
                    }
                }
                "crc32c" => crc32c = true,
                other => return Err(format!("the shard index codec {other:?} is not read")),
            }
        }
        let codecs = config.get("codecs").and_then(Value::as_array);
        let codecs = codecs.map(Vec::as_slice).unwrap_or_default();
        let at = array_to_bytes(codecs).ok_or("inner chunks without an array-to-bytes codec")?;
        if codec_name(&codecs[at]) == "sharding_indexed" {
            return Err("a shard inside a shard is not read".into());
        }
        Ok(ShardIndex {
            chunks,
            at_end: config.get("index_location").and_then(Value::as_str) != Some("start"),
            crc32c,
            checksummed: false,
            inner: Chain::of(&codecs[at + 1..])?,
        })
    }

    /// The inner chunks zarrs decodes of a whole shard: each entry of its index that lies
    /// within the shard's bytes (zarrs' own test; it may overlap the index); `None` if the
    /// bytes are shorter than the index.
    fn inner_chunks<'a>(&self, bytes: &'a [u8]) -> Option<Vec<&'a [u8]>> {
        let bytes = before_checksum(bytes, self.checksummed)?;
        let len = self.chunks.checked_mul(16)? + if self.crc32c { 4 } else { 0 };
        let index = if self.at_end {
            bytes.get(bytes.len().checked_sub(len)?..)?
        } else {
            bytes.get(..len)?
        };
        let word = |i: usize| u64::from_le_bytes(index[8 * i..8 * i + 8].try_into().unwrap());
        let inner = (0..self.chunks)
            .filter_map(|k| {
                let (offset, length) = (word(2 * k), word(2 * k + 1));
                let end = offset.checked_add(length)?;
                (end <= bytes.len() as u64).then(|| &bytes[offset as usize..end as usize])
            })
            .collect();
        Some(inner)
    }
}

impl Bounded {
    fn new(inner: ReadableStorage) -> Bounded {
        Bounded {
            inner,
            armed: OnceLock::new(),
        }
    }

    /// Checks chunks from now on: `chunk_bytes` a chunk (an inner chunk of a shard), with the
    /// array's `codecs`.
    fn arm(&self, chunk_bytes: u64, codecs: Codecs) {
        let limit = chunk_bytes.saturating_mul(2).saturating_add(1 << 20);
        let _ = self.armed.set((limit, codecs));
    }

    /// Checks the `bytes` of a chunk `key` read at `range`.
    fn check(&self, key: &StoreKey, range: &ByteRange, bytes: &[u8]) -> Result<(), StorageError> {
        let Some((limit, codecs)) = self.armed.get() else {
            return Ok(());
        };
        let limit = *limit;
        let name = key.as_str().rsplit('/').next().unwrap_or("");
        if METADATA_FILES.contains(&name) || matches!(name, ".zattrs" | ".zmetadata") {
            return Ok(());
        }
        let refuse = |d: u64| {
            StorageError::Other(format!(
                "chunk {key} declares {d} bytes decoded (or inflates past them), more than a \
                 chunk of this array holds"
            ))
        };
        let (chain, chunks) = match &codecs.shard {
            Some(shard) if *range == ByteRange::FromStart(0, None) => {
                let chunks = shard.inner_chunks(bytes).ok_or_else(|| {
                    StorageError::Other(format!(
                        "shard {key}: {} bytes, shorter than its index",
                        bytes.len()
                    ))
                })?;
                (shard.inner, chunks)
            }
            // A part of a shard: an inner chunk, or the index.
            Some(shard) => (shard.inner, vec![bytes]),
            None => (codecs.chain, vec![bytes]),
        };
        for chunk in chunks {
            if let Some(d) = decoded_bound(chain, chunk, limit).filter(|d| *d > limit) {
                return Err(refuse(d));
            }
        }
        Ok(())
    }
}

/// The most bytes `bytes` may decode to through `chain`, where it matters against `limit`
/// (a bound at or below it may be given as `None`).
fn decoded_bound(chain: Chain, bytes: &[u8], limit: u64) -> Option<u64> {
    let bytes = before_checksum(bytes, chain.crc32c_after)?;
    match chain.compressor {
        Compressor::None => None,
        Compressor::Zstd => zstd::zstd_safe::decompress_bound(bytes).ok().or_else(|| {
            // Not whole frames: zarrs streams them, as far as they decode.
            let decoder = zstd::stream::read::Decoder::with_buffer(bytes).ok()?;
            Some(inflated(decoder, limit))
        }),
        Compressor::Blosc => {
            // Blosc's header: version, codec version, flags, type size, then the decoded,
            // block and compressed bytes (u32, little-endian); Blosc refuses a buffer whose
            // compressed size is not its length.
            let word = |i: usize| Some(u32::from_le_bytes(bytes.get(i..i + 4)?.try_into().ok()?));
            (word(12)? as usize == bytes.len()).then(|| word(4).map(u64::from))?
        }
        // Deflate decodes at most 1 032 bytes a byte of input (a 258-byte match in 2 bits).
        Compressor::Gzip | Compressor::Zlib
            if (bytes.len() as u64).saturating_mul(1032) <= limit =>
        {
            None
        }
        Compressor::Gzip => Some(inflated(flate2::read::GzDecoder::new(bytes), limit)),
        Compressor::Zlib => Some(inflated(flate2::read::ZlibDecoder::new(bytes), limit)),
    }
}

/// How many bytes `decoder` gives before its end or its first error, counted up to one past
/// `limit` (written nowhere).
fn inflated(decoder: impl std::io::Read, limit: u64) -> u64 {
    let mut counted = 0u64;
    let mut reader = decoder.take(limit.saturating_add(1));
    let mut buf = vec![0u8; 64 << 10];
    loop {
        match reader.read(&mut buf) {
            Ok(0) | Err(_) => return counted,
            Ok(n) => counted += n as u64,
        }
    }
}

impl ReadableStorageTraits for Bounded {
    fn get_partial_many<'a>(
        &'a self,
        key: &StoreKey,
        byte_ranges: ByteRangeIterator<'a>,
    ) -> Result<MaybeBytesIterator<'a>, StorageError> {
        let key = key.clone();
        let ranges: Vec<ByteRange> = byte_ranges.collect();
        if let Some(size) = self.inner.size_key(&key)? {
            // zarrs_storage's own test of a range is private (and its sum overflows).
            let fits = |r: &ByteRange| match *r {
                ByteRange::FromStart(offset, None) => offset <= size,
                ByteRange::FromStart(offset, Some(length)) => {
                    offset.checked_add(length).is_some_and(|end| end <= size)
                }
                ByteRange::Suffix(length) => length <= size,
            };
            if let Some(r) = ranges.iter().find(|r| !fits(r)) {
                return Err(InvalidByteRangeError::new(*r, size).into());
            }
        }
        let parts = self
            .inner
            .get_partial_many(&key, Box::new(ranges.clone().into_iter()))?;
        Ok(parts.map(|parts| {
            Box::new(parts.zip(ranges).map(move |(part, range)| {
                let bytes = part?;
                self.check(&key, &range, &bytes)?;
                Ok(bytes)
            })) as _
        }))
    }

    fn size_key(&self, key: &StoreKey) -> Result<Option<u64>, StorageError> {
        self.inner.size_key(key)
    }

    fn supports_get_partial(&self) -> bool {
        self.inner.supports_get_partial()
    }
}

/// Runs a call into `zarrs` on the store's bytes, a panic in it (an arithmetic overflow on a
/// corrupt shard index, say) becoming an error: the bytes are untrusted, and one hostile store
/// must not bring down a worker serving others.
fn guarded<T>(path: &Path, f: impl FnOnce() -> T) -> Result<T, ReadError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).map_err(|panic| {
        let what = panic
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| panic.downcast_ref::<String>().cloned())
            .unwrap_or_default();
        ReadError::Data {
            path: path.to_path_buf(),
            format: FORMAT,
            reason: format!("the Zarr decoder failed on the store ({what})"),
        }
    })
}

/// The axes an array's own metadata names (v3 `dimension_names`, xarray's
/// `_ARRAY_DIMENSIONS`), or none.
fn dimension_names(array: &Array<dyn ReadableStorageTraits>) -> Vec<Axis> {
    let named = |names: Vec<String>| {
        names
            .into_iter()
            .map(|name| Axis {
                name,
                ..Axis::default()
            })
            .collect()
    };
    if let Some(names) = array.dimension_names() {
        if names.iter().all(Option::is_some) {
            return named(names.iter().flatten().cloned().collect());
        }
    }
    if let Some(Value::Array(names)) = array.attributes().get("_ARRAY_DIMENSIONS") {
        let names: Option<Vec<String>> = names
            .iter()
            .map(|n| n.as_str().map(str::to_string))
            .collect();
        if let Some(names) = names {
            return named(names);
        }
    }
    Vec::new()
}

/// Each array axis's role, from its axis (`axes`, as many as the shape, or none).
fn roles(path: &Path, shape: &[u64], axes: &[Axis]) -> Result<Vec<Role>, ReadError> {
    // Names none of which says an axis (xarray's `dim_0`, …), and no types: as if unnamed.
    let known = |a: &Axis| {
        a.kind.is_some()
            || matches!(
                a.name.to_ascii_lowercase().as_str(),
                "x" | "y" | "z" | "t" | "time" | "c" | "channel" | "channels"
            )
    };
    let axes = if axes.iter().any(known) { axes } else { &[] };
    if axes.is_empty() {
        return match shape.len() {
            3 => Ok(vec![Role::Space(2), Role::Space(1), Role::Space(0)]),
            4 => Ok(vec![
                Role::Time,
                Role::Space(2),
                Role::Space(1),
                Role::Space(0),
            ]),
            5 => Ok(vec![
                Role::Time,
                Role::Channel,
                Role::Space(2),
                Role::Space(1),
                Role::Space(0),
            ]),
            n => Err(ReadError::unsupported(
                path,
                format!(
                    "an array of {n} dimensions (shape {shape:?}) naming none: a volume has \
                     three spatial axes, in z, y, x; t, z, y, x; or t, c, z, y, x"
                ),
            )),
        };
    }
    if axes.len() != shape.len() {
        return Err(bad(
            path,
            format!(
                "{} axes for an array of {} dimensions",
                axes.len(),
                shape.len()
            ),
        ));
    }
    Ok(axes
        .iter()
        .map(|a| {
            let name = a.name.to_ascii_lowercase();
            let by_name = match name.as_str() {
                "x" => Some(Role::Space(0)),
                "y" => Some(Role::Space(1)),
                "z" => Some(Role::Space(2)),
                "t" | "time" => Some(Role::Time),
                "c" | "channel" | "channels" => Some(Role::Channel),
                _ => None,
            };
            match a.kind.as_deref() {
                Some("space") => match by_name {
                    Some(Role::Space(k)) => Role::Space(k),
                    _ => Role::SpaceUnnamed,
                },
                Some("time") => Role::Time,
                Some("channel") => Role::Channel,
                Some(_) => Role::Other,
                None => by_name.unwrap_or(Role::Other),
            }
        })
        .collect())
}

/// Reads a metadata document of the store, if present.
fn json(path: &Path, store: &ReadableStorage, key: &str) -> Result<Option<Value>, ReadError> {
    let k = StoreKey::new(key).expect("a valid key");
    let Some(bytes) = store
        .get(&k)
        .map_err(|e| ReadError::io(&path.join(key), std::io::Error::other(e.to_string())))?
    else {
        return Ok(None);
    };
    serde_json::from_slice(&bytes)
        .map(Some)
        .map_err(|e| bad(&path.join(key), format!("not JSON: {e}")))
}

/// The array to read in the store at `path`: the store's own array, or the first (full
/// resolution) dataset of an OME-Zarr image group.
fn locate(path: &Path, store: &ReadableStorage) -> Result<Target, ReadError> {
    locate_in(path, store, "")
}

/// [`locate`] in the group at `prefix` (`""`: the store's root; else `0/`, as
/// bioformats2raw's layout puts its first image).
fn locate_in(path: &Path, store: &ReadableStorage, prefix: &str) -> Result<Target, ReadError> {
    let plain = || Target {
        array: "/".to_string(),
        axes: None,
        scale: None,
    };
    let key = |name: &str| format!("{prefix}{name}");
    let attributes = if let Some(root) = json(path, store, &key("zarr.json"))? {
        match root.get("node_type").and_then(Value::as_str) {
            Some("array") if prefix.is_empty() => return Ok(plain()),
            Some("group") => root.get("attributes").cloned().unwrap_or(Value::Null),
            other => {
                return Err(bad(
                    &path.join(key("zarr.json")),
                    format!("node_type {other:?}: an OME-Zarr image or an array was expected"),
                ))
            }
        }
    } else if prefix.is_empty() && json(path, store, ".zarray")?.is_some() {
        return Ok(plain());
    } else if json(path, store, &key(".zgroup"))?.is_some() {
        json(path, store, &key(".zattrs"))?.unwrap_or(Value::Null)
    } else if prefix.is_empty() {
        return Err(bad(
            path,
            "no zarr.json, .zarray or .zgroup: not a Zarr store".to_string(),
        ));
    } else {
        return Err(bad(path, format!("no group at {prefix}")));
    };
    // OME-Zarr 0.5 nests its metadata under `ome`; earlier versions do not.
    let ome = attributes.get("ome").unwrap_or(&attributes);
    let Some(multiscale) = ome
        .get("multiscales")
        .and_then(Value::as_array)
        .and_then(|m| m.first())
    else {
        // bioformats2raw's layout: the images are groups 0, 1, …; the first is read.
        if prefix.is_empty() && ome.get("bioformats2raw.layout").is_some() {
            return locate_in(path, store, "0/");
        }
        return Err(ReadError::unsupported(
            path,
            "a Zarr group that is no OME-Zarr image (no `multiscales`): give the directory of \
             an OME-Zarr image, or of an array",
        ));
    };
    let dataset = multiscale
        .get("datasets")
        .and_then(Value::as_array)
        .and_then(|d| d.first())
        .ok_or_else(|| bad(path, "an OME-Zarr multiscale with no datasets"))?;
    let array_path = dataset
        .get("path")
        .and_then(Value::as_str)
        .filter(|p| !p.is_empty() && !p.split('/').any(|c| c.is_empty() || c == "." || c == ".."))
        .ok_or_else(|| bad(path, "an OME-Zarr dataset without a plain relative path"))?;
    let axes = multiscale
        .get("axes")
        .and_then(Value::as_array)
        .map(|axes| {
            axes.iter()
                .map(|a| match a {
                    // OME-Zarr 0.3 lists names only.
                    Value::String(name) => Axis {
                        name: name.clone(),
                        ..Axis::default()
                    },
                    a => Axis {
                        name: a
                            .get("name")
                            .and_then(Value::as_str)
                            .unwrap_or("")
                            .to_string(),
                        kind: a.get("type").and_then(Value::as_str).map(str::to_string),
                        unit: a.get("unit").and_then(Value::as_str).map(str::to_string),
                    },
                })
                .collect()
        });
    let mut scale: Option<Vec<f64>> = None;
    for transforms in [
        dataset.get("coordinateTransformations"),
        multiscale.get("coordinateTransformations"),
    ]
    .into_iter()
    .flatten()
    .filter_map(Value::as_array)
    {
        for t in transforms {
            if t.get("type").and_then(Value::as_str) != Some("scale") {
                continue;
            }
            let Some(s) = t.get("scale").and_then(Value::as_array) else {
                return Err(bad(
                    path,
                    "a scale transformation given by path is not read",
                ));
            };
            let s: Vec<f64> = s
                .iter()
                .map(|v| v.as_f64())
                .collect::<Option<_>>()
                .ok_or_else(|| bad(path, "a scale that is not numbers"))?;
            scale = Some(match scale {
                None => s,
                Some(prev) if prev.len() == s.len() => {
                    prev.iter().zip(&s).map(|(a, b)| a * b).collect()
                }
                Some(_) => return Err(bad(path, "scales of different lengths")),
            });
        }
    }
    Ok(Target {
        array: format!("/{prefix}{array_path}"),
        axes,
        scale,
    })
}

/// The files of the store at `path` that its volume is read from, as (name relative to the
/// store, `/`-separated; path), sorted by name: the store's top metadata and every file under
/// the array read (an OME-Zarr image's lower resolutions are left out).
pub(crate) fn store_files(path: &Path) -> Result<Vec<(String, PathBuf)>, ReadError> {
    let store: ReadableStorage = Arc::new(
        zarrs::filesystem::FilesystemStore::new(path)
            .map_err(|e| ReadError::io(path, std::io::Error::other(e.to_string())))?,
    );
    let target = locate(path, &store)?;
    let rel = target.array.trim_start_matches('/');
    // The metadata of every group from the root down to the array, then the array's files.
    let mut files = Vec::new();
    let mut group = String::new();
    for part in rel.split('/').filter(|p| !p.is_empty()) {
        for m in METADATA_FILES.iter().chain([&".zattrs"]) {
            let name = format!("{group}{m}");
            if path.join(&name).is_file() {
                files.push((name.clone(), path.join(&name)));
            }
        }
        group = format!("{group}{part}/");
    }
    walk(&path.join(rel), rel, 0, &mut files)?;
    files.sort_by(|a, b| a.0.cmp(&b.0));
    files.dedup_by(|a, b| a.0 == b.0);
    Ok(files)
}

/// Most directories below an array's (a chunk key's parts, a sharded array's too).
const MAX_DEPTH: usize = 32;

/// Every file under `dir`, named `prefix/…`, symbolic links followed (a DataLad or git-annex
/// checkout links every file: a chunk left out would read as the fill value). A directory
/// reached twice (a link to itself or to a parent) is refused: the walk would not end.
fn walk(
    dir: &Path,
    prefix: &str,
    depth: usize,
    out: &mut Vec<(String, PathBuf)>,
) -> Result<(), ReadError> {
    walk_once(
        dir,
        prefix,
        depth,
        out,
        &mut std::collections::HashSet::new(),
    )
}

fn walk_once(
    dir: &Path,
    prefix: &str,
    depth: usize,
    out: &mut Vec<(String, PathBuf)>,
    seen: &mut std::collections::HashSet<PathBuf>,
) -> Result<(), ReadError> {
    if depth > MAX_DEPTH {
        return Err(ReadError::unsupported(
            dir,
            format!("directories nested more than {MAX_DEPTH} deep"),
        ));
    }
    let real = std::fs::canonicalize(dir).map_err(|e| ReadError::io(dir, e))?;
    if !seen.insert(real) {
        return Err(ReadError::unsupported(
            dir,
            "a directory reached twice through symbolic links (a link loop)",
        ));
    }
    let entries = std::fs::read_dir(dir).map_err(|e| ReadError::io(dir, e))?;
    for e in entries {
        let e = e.map_err(|e| ReadError::io(dir, e))?;
        let name = e.file_name().to_string_lossy().into_owned();
        let rel = if prefix.is_empty() {
            name
        } else {
            format!("{prefix}/{name}")
        };
        let meta = std::fs::metadata(e.path()).map_err(|err| ReadError::io(&e.path(), err))?;
        if meta.is_dir() {
            walk_once(&e.path(), &rel, depth + 1, out, seen)?;
        } else if meta.is_file() {
            out.push((rel, e.path()));
        }
    }
    Ok(())
}

/// How many time points the store at `path` holds (1 for a volume).
pub(crate) fn time_points(path: &Path) -> Result<usize, ReadError> {
    Ok(ZarrVolume::open(path, Some(0))?.time_points())
}

/// How many channels the array of the store at `path` holds along its channel axis (1
/// without one), each a volume ([`ChannelChoice`]); its metadata only is read.
pub fn channels(path: &Path) -> Result<usize, ReadError> {
    Ok(ZarrVolume::open(path, Some(0))?.channels())
}

/// What decoding a gathered store whole ([`decode`]) may hold at once by what its metadata
/// declares, in bytes: one time point's samples as stored and as f32, and a chunk decoded.
/// A store may declare far more than its bytes hold (a missing chunk is its fill value), so
/// this, not the store's size, is what reading it costs; the fuzz target bounds the reader's
/// heap by it.
pub fn declared_bytes(src: &SourceFiles) -> Result<u64, ReadError> {
    let z = ZarrVolume::of_files(src, Some(0))?;
    let voxels = checked_voxels(z.dims).map_err(|e| ReadError::volume(&src.origin, e))? as u64;
    let sample = z.sample.map_or(1, SampleType::size) as u64;
    Ok(voxels
        .saturating_mul(4 + sample)
        .saturating_add(z.chunk_bytes))
}

/// Decodes a gathered store whole, the channel `channel` of it (one time point; a series is
/// refused as [`ReadError::TimeSeries`]).
pub(crate) fn decode(src: &SourceFiles, channel: Option<usize>) -> Result<Volume, ReadError> {
    let z = ZarrVolume::of_files(src, channel)?;
    if z.time_points > 1 {
        return Err(ReadError::TimeSeries {
            path: src.origin.clone(),
            points: z.time_points,
        });
    }
    let samples = z.read(0, [0; 3], z.dims)?;
    Volume::new(z.dims, z.spacing, vec![samples]).map_err(|e| ReadError::volume(&src.origin, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A Zarr v2 array of u16 samples `value(position)` (array axes, C order), its chunks
    /// zlib-compressed (`compressed`) or not, with `attrs` as its `.zattrs`.
    fn store(
        dir: &Path,
        shape: &[u64],
        chunks: &[u64],
        attrs: &str,
        value: fn(&[u64]) -> u16,
        compressed: bool,
    ) {
        let list = |v: &[u64]| v.iter().map(u64::to_string).collect::<Vec<_>>().join(", ");
        let meta = format!(
            r#"{{"zarr_format": 2, "shape": [{}], "chunks": [{}], "dtype": "<u2",
                "compressor": {}, "fill_value": 0, "order": "C", "filters": null}}"#,
            list(shape),
            list(chunks),
            if compressed {
                r#"{"id": "zlib", "level": 1}"#
            } else {
                "null"
            }
        );
        std::fs::create_dir_all(dir).unwrap();
        std::fs::write(dir.join(".zarray"), meta).unwrap();
        std::fs::write(dir.join(".zattrs"), attrs).unwrap();
        let grid: Vec<u64> = shape
            .iter()
            .zip(chunks)
            .map(|(s, c)| s.div_ceil(*c))
            .collect();
        for c in &ArraySubset::new_with_shape(grid).indices() {
            let start: Vec<u64> = c.iter().zip(chunks).map(|(i, n)| i * n).collect();
            let ranges: Vec<Range<u64>> =
                start.iter().zip(chunks).map(|(s, n)| *s..s + n).collect();
            let mut bytes = Vec::new();
            for p in &ArraySubset::new_with_ranges(&ranges).indices() {
                bytes.extend_from_slice(&value(&p).to_le_bytes());
            }
            if compressed {
                use std::io::Write;
                let mut z =
                    flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
                z.write_all(&bytes).unwrap();
                bytes = z.finish().unwrap();
            }
            let key = c.iter().map(u64::to_string).collect::<Vec<_>>().join(".");
            std::fs::write(dir.join(key), bytes).unwrap();
        }
    }

    /// Chunks that reach outside the regions read (whole planes, chunks across the bricks'
    /// faces, chunks past the array's edge) are decoded twice for all the regions that share
    /// them, the second time into the spool, from threads at once too; each region reads what
    /// the samples are, in every axis order; a region that holds its chunks whole reads them
    /// as before, and one region alone spools nothing.
    #[test]
    fn chunks_shared_by_regions_are_decoded_twice_for_all() {
        use crate::reader::spool::read_bricks_from_two_threads;
        let dir = tempfile::tempdir().unwrap();
        let zyx = |p: &[u64]| (p[0] * 1000 + p[1] * 40 + p[2]) as u16;
        let xyz = |p: &[u64]| (p[2] * 1000 + p[1] * 40 + p[0]) as u16;
        let tzyx = |p: &[u64]| (p[0] * 20000 + p[1] * 1000 + p[2] * 40 + p[3]) as u16;
        let czyx = |p: &[u64]| (p[0] * 10000 + p[1] * 1000 + p[2] * 40 + p[3]) as u16;
        let names = |n: &str| format!(r#"{{"_ARRAY_DIMENSIONS": [{n}]}}"#);
        // (name, shape, chunks, axis names, value, time point read, chunks in the grid)
        #[allow(clippy::type_complexity)]
        let cases: [(
            &str,
            Vec<u64>,
            Vec<u64>,
            String,
            fn(&[u64]) -> u16,
            usize,
            usize,
        ); 8] = [
            (
                "planes",
                vec![5, 11, 13],
                vec![1, 11, 13],
                names(r#""z", "y", "x""#),
                zyx,
                0,
                5,
            ),
            (
                "x_slowest",
                vec![13, 11, 5],
                vec![13, 11, 1],
                names(r#""x", "y", "z""#),
                xyz,
                0,
                5,
            ),
            (
                "ragged",
                vec![5, 11, 13],
                vec![2, 6, 8],
                names(r#""z", "y", "x""#),
                zyx,
                0,
                12,
            ),
            (
                "time",
                vec![2, 5, 11, 13],
                vec![1, 1, 11, 13],
                names(r#""t", "z", "y", "x""#),
                tzyx,
                1,
                5,
            ),
            // Chunks holding both time points: the second one's samples lie past the first's.
            (
                "time_chunks",
                vec![2, 5, 11, 13],
                vec![2, 1, 11, 13],
                names(r#""t", "z", "y", "x""#),
                tzyx,
                1,
                5,
            ),
            // Channels, channel 1 chosen: in chunks holding all three (the others' samples
            // lie beside it in every chunk) and in chunks of one channel.
            (
                "channel_chunks",
                vec![3, 5, 11, 13],
                vec![3, 1, 11, 13],
                names(r#""c", "z", "y", "x""#),
                czyx,
                0,
                5,
            ),
            (
                "channel_planes",
                vec![3, 5, 11, 13],
                vec![1, 1, 11, 13],
                names(r#""c", "z", "y", "x""#),
                czyx,
                0,
                5,
            ),
            // Uncompressed chunks: a region reads its own bytes of them, nothing is spooled.
            (
                "uncompressed",
                vec![5, 11, 13],
                vec![1, 11, 13],
                names(r#""z", "y", "x""#),
                zyx,
                0,
                0,
            ),
        ];
        for (name, shape, chunks, attrs, value, t, count) in cases {
            let path = dir.path().join(name);
            let compressed = name != "uncompressed";
            store(&path, &shape, &chunks, &attrs, value, compressed);
            let channel = name.starts_with("channel").then_some(1);
            let z = ZarrVolume::open(&path, channel).unwrap();
            assert_eq!(z.dims(), [13, 11, 5], "{name}");
            let sample = |x: usize, y: usize, zz: usize| -> f32 {
                let p: Vec<u64> = match name {
                    "x_slowest" => vec![x as u64, y as u64, zz as u64],
                    "time" | "time_chunks" => vec![t as u64, zz as u64, y as u64, x as u64],
                    "channel_chunks" | "channel_planes" => vec![1, zz as u64, y as u64, x as u64],
                    _ => vec![zz as u64, y as u64, x as u64],
                };
                f32::from(value(&p))
            };
            let check = |origin: [usize; 3], size: [usize; 3], got: &[f32]| {
                for (j, v) in got.iter().enumerate() {
                    let (x, y, zz) = (j % size[0], j / size[0] % size[1], j / size[0] / size[1]);
                    let want = sample(origin[0] + x, origin[1] + y, origin[2] + zz);
                    assert_eq!(*v, want, "{name}: {origin:?} {size:?} at {j}");
                }
            };
            let whole = z.read(t, [0; 3], [13, 11, 5]).unwrap();
            check([0; 3], [13, 11, 5], &whole);
            assert!(!z.spool.has_file(), "{name}: the whole holds its chunks");
            // Bricks of 5 × 4 × 3 voxels, read by two threads at once.
            let bricks = ZarrVolume::open(&path, channel).unwrap();
            read_bricks_from_two_threads([13, 11, 5], [5, 4, 3], |origin, size| {
                check(origin, size, &bricks.read(t, origin, size).unwrap());
            });
            assert_eq!(bricks.spool.has_file(), compressed, "{name}");
            // Every chunk of this time point lies under several bricks.
            assert_eq!(
                bricks.spool.decoded(),
                2 * count,
                "{name}: each chunk twice"
            );
            // Read whole by the bricks, each chunk is released; the chunks of two time points
            // are half read (one time point is) and stay.
            let halves = name == "time_chunks";
            assert_eq!(bricks.spool.held().0 == 0, !halves, "{name}: released");
            // A second pass spools the released chunks again, once each.
            read_bricks_from_two_threads([13, 11, 5], [5, 4, 3], |origin, size| {
                check(origin, size, &bricks.read(t, origin, size).unwrap());
            });
            let again = if halves { 2 } else { 3 };
            assert_eq!(
                bricks.spool.decoded(),
                again * count,
                "{name}: a second pass"
            );
            // One brick of a reader of its own spools nothing.
            let one = ZarrVolume::open(&path, channel).unwrap();
            check(
                [5, 4, 0],
                [5, 4, 5],
                &one.read(t, [5, 4, 0], [5, 4, 5]).unwrap(),
            );
            assert!(!one.spool.has_file(), "{name}: one region, no spool");
        }
    }
}
