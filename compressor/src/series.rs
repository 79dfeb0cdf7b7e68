//! Time-varying volumes compressed together: the time points of a series go through an
//! orthonormal Haar wavelet along time in groups of G ([`TemporalHaar`]), so a group's common
//! content becomes one low-pass *component* and its changes a few detail components that cost
//! little where nothing moves. Each component is a volume of its own ([`ComponentSource`]: a
//! weighted sum of time points, read brick by brick) compressed as bricks are
//! ([`BrickPlan`]), with the whole series' rate allocated by one score threshold across every
//! component and brick ([`allocate_units`]): the transform is orthonormal, so the squared error
//! summed over time points is the one summed over components. The result is a series container
//! ([`wavesplat_codec::format::series`]) whose time points name their group's components and
//! weights: a reader wants no byte of another group. Groups of 1 compress each time point
//! alone.
//!
//! Time points come from a [`SeriesSource`]: volumes in memory ([`VolumeSeries`]), a 4D file
//! read by region ([`crate::reader::region::RegionReader`]), or one file per time step
//! ([`crate::reader::steps::StepSeries`]).

use thiserror::Error;
use wavesplat_codec::format::bricked::Space;
use wavesplat_codec::format::series::{
    manifest_section, parse_series, place_components, write_series, ComponentEntry, SeriesManifest,
    TimePoint, MAX_TERMS,
};
use wavesplat_codec::format::FormatError;
use wavesplat_codec::volume::{Placement, Volume, VolumeError};

use crate::bricked::{
    allocate_units, in_grid_order, BrickError, BrickPlan, BrickSource, BrickStage, CodedBrick,
    KeptTops, SharedChoices, Spill, SpilledBrick,
};
use crate::encode::{compress, CompressOptions, ScoreSummary, Target};
use crate::reader::ReadError;

/// Largest temporal group.
pub const MAX_GROUP: usize = 1 << (MAX_TERMS - 1);

/// A time-varying volume: time points of one space, read box by box.
pub trait SeriesSource: Sync {
    /// Every time point's dimensions.
    fn dims(&self) -> [u64; 3];
    /// Channels.
    fn channels(&self) -> usize;
    /// Voxel spacing.
    fn spacing(&self) -> [f32; 3];
    /// Placement in patient space (of voxel (0, 0, 0)).
    fn placement(&self) -> Option<Placement>;
    /// How many time points.
    fn time_points(&self) -> usize;
    /// Each time point's time in seconds, when the source says (else `None`).
    fn times(&self) -> Option<Vec<f64>>;
    /// The box at `origin` of `dims` of time point `t` (spacing as the whole's).
    fn read_at(&self, t: usize, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError>;
}

/// Why a series cannot be made or compressed.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum SeriesError {
    /// Time points that are not one space.
    #[error("time point {t} does not match time point 0: {what}")]
    Mismatch {
        /// The time point.
        t: usize,
        /// What differs.
        what: String,
    },
    /// Options that do not suit a series.
    #[error("invalid option for a time series: {0}")]
    InvalidOption(String),
    /// Compressing a component failed (boxed: it is large, and small results travel well).
    #[error(transparent)]
    Brick(Box<BrickError>),
    /// The container could not be written or read.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// A component could not be decoded.
    #[error("decoding component {component}")]
    Decode {
        /// The component.
        component: usize,
        /// Why.
        #[source]
        source: Box<crate::decode::DecodeError>,
    },
    /// Decoded components could not be summed.
    #[error(transparent)]
    Volume(#[from] VolumeError),
    /// The series could not be read (boxed: it is large).
    #[error(transparent)]
    Read(Box<ReadError>),
}

impl From<ReadError> for SeriesError {
    fn from(e: ReadError) -> SeriesError {
        SeriesError::Read(Box::new(e))
    }
}

/// A time series as read from where it is kept.
#[derive(Debug)]
pub enum SeriesInput {
    /// Held in memory (a DICOM cine, decoded; a generated phantom).
    Memory(VolumeSeries),
    /// A 4D file read by region.
    File(Box<crate::reader::region::RegionReader>),
    /// A directory of one volume file per time step.
    Steps(crate::reader::steps::StepSeries),
}

impl SeriesInput {
    /// The series as a source of time points.
    pub fn source(&self) -> &dyn SeriesSource {
        match self {
            SeriesInput::Memory(s) => s,
            SeriesInput::File(r) => r.as_ref(),
            SeriesInput::Steps(s) => s,
        }
    }
}

/// The time series at `path`, when it is one (read from headers where the format allows;
/// `None` for one volume): a directory of time steps, a DICOM series whose slices repeat at
/// several times or a multi-frame DICOM cine (decoded here), a 4D NIfTI or NRRD, a Zarr array
/// with a time axis, or a raw file
/// whose spec has several time points.
pub fn open_series_path(
    path: &std::path::Path,
    raw: Option<&crate::reader::RawSpec>,
) -> Result<Option<SeriesInput>, SeriesError> {
    open_series_path_channel(path, raw, None)
}

/// [`open_series_path`] with a channel chosen
/// ([`crate::reader::region::RegionReader::open_channel`]): of a Zarr array, of a file of
/// several channels, of each time point of a DICOM series or cine; a directory of time steps
/// is read with every channel, so only channel 0 of grey steps is taken there.
pub fn open_series_path_channel(
    path: &std::path::Path,
    raw: Option<&crate::reader::RawSpec>,
    channel: Option<usize>,
) -> Result<Option<SeriesInput>, SeriesError> {
    use crate::reader::dicom::read_time_series;
    use crate::reader::region::RegionReader;
    use crate::reader::steps::{step_files, StepSeries};
    if path.is_dir() && crate::reader::zarr::is_store(path) {
        // A Zarr array: a series when it has a time axis of several points.
        if crate::reader::time_points(path, raw)? <= 1 {
            return Ok(None);
        }
        let reader = RegionReader::open_series_channel(path, raw, channel)?;
        return Ok(Some(SeriesInput::File(Box::new(reader))));
    }
    // Time points read whole (a DICOM series or cine): the channel chosen kept of each.
    let keep = |volumes: Vec<wavesplat_codec::volume::Volume>| {
        volumes
            .into_iter()
            .map(|v| crate::reader::keep_channel(v, channel, path))
            .collect::<Result<Vec<_>, _>>()
    };
    if path.is_dir() {
        let files = step_files(path, raw)?;
        // A directory of TIFF slices (and no DICOM file): one volume, a stack.
        if files.is_empty() && crate::reader::is_tiff_directory(path)? {
            return Ok(None);
        }
        if files.is_empty() {
            // A DICOM series: a time series when its slices repeat at several times.
            let Some((volumes, times)) = read_time_series(path)? else {
                return Ok(None);
            };
            return Ok(Some(SeriesInput::Memory(VolumeSeries::new(
                keep(volumes)?,
                times,
            )?)));
        }
        let steps = StepSeries::open(path, raw)?;
        // Steps are read with all their channels: a channel is chosen of grey steps only (0).
        if let Some(c) = channel.filter(|&c| c > 0 || steps.channels() > 1) {
            return Err(SeriesError::InvalidOption(format!(
                "channel {c} chosen of a directory of time steps of {} channel(s), which are \
                 read with all their channels",
                steps.channels()
            )));
        }
        return Ok(Some(SeriesInput::Steps(steps)));
    }
    if raw.is_none() && crate::reader::dicom::is_dicom_file(path).unwrap_or(false) {
        // A multi-frame cine: its frames are the time points.
        let Some((volumes, times)) = crate::reader::dicom::read_cine_file(path)? else {
            return Ok(None);
        };
        return Ok(Some(SeriesInput::Memory(VolumeSeries::new(
            keep(volumes)?,
            times,
        )?)));
    }
    if crate::reader::time_points(path, raw)? <= 1 {
        return Ok(None);
    }
    let reader = RegionReader::open_series_channel(path, raw, channel)?;
    Ok(Some(SeriesInput::File(Box::new(reader))))
}

impl From<BrickError> for SeriesError {
    fn from(e: BrickError) -> SeriesError {
        match e {
            // Said of the series (a target too small for its parts), not of a bricked volume.
            BrickError::InvalidOption(m) => SeriesError::InvalidOption(m),
            e => SeriesError::Brick(Box::new(e)),
        }
    }
}

/// A series held in memory: one volume per time point.
#[derive(Debug, Clone)]
pub struct VolumeSeries {
    volumes: Vec<Volume>,
    times: Option<Vec<f64>>,
}

impl VolumeSeries {
    /// The time points `volumes` (at least one; all of one size, channel count and spacing),
    /// taken at `times` seconds when known (as many, finite, increasing).
    pub fn new(volumes: Vec<Volume>, times: Option<Vec<f64>>) -> Result<VolumeSeries, SeriesError> {
        let first = volumes
            .first()
            .ok_or_else(|| SeriesError::InvalidOption("a series of no time points".into()))?;
        for (t, v) in volumes.iter().enumerate().skip(1) {
            check_same(t, first, v)?;
        }
        if let Some(times) = &times {
            check_times(times, volumes.len())?;
        }
        Ok(VolumeSeries { volumes, times })
    }

    /// The time points.
    pub fn volumes(&self) -> &[Volume] {
        &self.volumes
    }
}

/// Refuses a time point `v` that is not of `first`'s space.
pub fn check_same(t: usize, first: &Volume, v: &Volume) -> Result<(), SeriesError> {
    let what = if v.dims() != first.dims() {
        format!("dimensions {:?} against {:?}", v.dims(), first.dims())
    } else if v.channel_count() != first.channel_count() {
        format!(
            "{} channel(s) against {}",
            v.channel_count(),
            first.channel_count()
        )
    } else if v.spacing() != first.spacing() {
        format!("spacing {:?} against {:?}", v.spacing(), first.spacing())
    } else {
        return Ok(());
    };
    Err(SeriesError::Mismatch { t, what })
}

/// Refuses times that are not one finite, strictly increasing time per time point.
pub fn check_times(times: &[f64], points: usize) -> Result<(), SeriesError> {
    if times.len() != points {
        return Err(SeriesError::InvalidOption(format!(
            "{} times for {points} time points",
            times.len()
        )));
    }
    if let Some(t) =
        (0..points).find(|&t| !times[t].is_finite() || t > 0 && times[t] <= times[t - 1])
    {
        return Err(SeriesError::InvalidOption(format!(
            "time point {t} at {} s: times must be finite and increasing",
            times[t]
        )));
    }
    Ok(())
}

impl SeriesSource for VolumeSeries {
    fn dims(&self) -> [u64; 3] {
        self.volumes[0].dims().map(|d| d as u64)
    }

    fn channels(&self) -> usize {
        self.volumes[0].channel_count()
    }

    fn spacing(&self) -> [f32; 3] {
        self.volumes[0].spacing()
    }

    fn placement(&self) -> Option<Placement> {
        self.volumes[0].placement().copied()
    }

    fn time_points(&self) -> usize {
        self.volumes.len()
    }

    fn times(&self) -> Option<Vec<f64>> {
        self.times.clone()
    }

    fn read_at(&self, t: usize, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError> {
        let v = self.volumes.get(t).ok_or_else(|| ReadError::Region {
            path: "(series in memory)".into(),
            reason: format!("no time point {t} of {}", self.volumes.len()),
        })?;
        Ok(crate::bricked::crop(v, origin, dims)?)
    }
}

impl SeriesSource for crate::reader::region::RegionReader {
    fn dims(&self) -> [u64; 3] {
        crate::reader::region::RegionReader::dims(self).map(|d| d as u64)
    }
    fn channels(&self) -> usize {
        crate::reader::region::RegionReader::channels(self)
    }
    fn spacing(&self) -> [f32; 3] {
        crate::reader::region::RegionReader::spacing(self)
    }
    fn placement(&self) -> Option<Placement> {
        crate::reader::region::RegionReader::placement(self).copied()
    }
    fn time_points(&self) -> usize {
        crate::reader::region::RegionReader::time_points(self)
    }
    fn times(&self) -> Option<Vec<f64>> {
        let step = self.time_step()?;
        Some((0..self.time_points()).map(|t| t as f64 * step).collect())
    }
    fn read_at(&self, t: usize, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError> {
        self.read_region_at(t, origin.map(|o| o as usize), dims)
    }
}

impl SeriesSource for crate::reader::steps::StepSeries {
    fn dims(&self) -> [u64; 3] {
        self.steps()[0].dims().map(|d| d as u64)
    }
    fn channels(&self) -> usize {
        self.steps()[0].channels()
    }
    fn spacing(&self) -> [f32; 3] {
        self.steps()[0].spacing()
    }
    fn placement(&self) -> Option<Placement> {
        self.steps()[0].placement().copied()
    }
    fn time_points(&self) -> usize {
        self.steps().len()
    }
    fn times(&self) -> Option<Vec<f64>> {
        None
    }
    fn read_at(&self, t: usize, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError> {
        let step = self.steps().get(t).ok_or_else(|| ReadError::Region {
            path: self.dir().to_path_buf(),
            reason: format!("no time step {t} of {}", self.steps().len()),
        })?;
        step.read_region(origin.map(|o| o as usize), dims)
    }
}

/// One time point of a series, as a volume to read bricks from.
pub struct TimePointSource<'a> {
    /// The series.
    pub series: &'a dyn SeriesSource,
    /// The time point.
    pub t: usize,
}

impl BrickSource for TimePointSource<'_> {
    fn dims(&self) -> [u64; 3] {
        self.series.dims()
    }
    fn channels(&self) -> usize {
        self.series.channels()
    }
    fn spacing(&self) -> [f32; 3] {
        self.series.spacing()
    }
    fn placement(&self) -> Option<Placement> {
        self.series.placement()
    }
    fn read(&self, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError> {
        self.series.read_at(self.t, origin, dims)
    }
    fn reads_rows_whole(&self) -> bool {
        true
    }
}

/// One component of a series' temporal transform as a volume: Σ weight · time point, read
/// box by box (one box of each time point it sums at a time). It has no placement: the
/// series manifest places the whole.
pub struct ComponentSource<'a> {
    /// The series.
    pub series: &'a dyn SeriesSource,
    /// (time point, weight).
    pub terms: &'a [(usize, f64)],
}

impl BrickSource for ComponentSource<'_> {
    fn dims(&self) -> [u64; 3] {
        self.series.dims()
    }
    fn channels(&self) -> usize {
        self.series.channels()
    }
    fn spacing(&self) -> [f32; 3] {
        self.series.spacing()
    }
    fn placement(&self) -> Option<Placement> {
        None
    }
    fn read(&self, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError> {
        let channels = self.series.channels();
        let n: usize = dims.iter().product();
        // Summed in f64: a group's detail components are small differences of large values.
        let mut acc = vec![vec![0f64; n]; channels];
        for &(t, w) in self.terms {
            let v = self.series.read_at(t, origin, dims)?;
            for (a, c) in acc.iter_mut().zip(v.channels()) {
                a.iter_mut()
                    .zip(c)
                    .for_each(|(a, x)| *a += w * f64::from(*x));
            }
        }
        let data = acc
            .into_iter()
            .map(|c| c.into_iter().map(|v| v as f32).collect())
            .collect();
        Ok(Volume::new(dims, self.series.spacing(), data)?)
    }
    fn reads_rows_whole(&self) -> bool {
        true
    }
}

/// The orthonormal Haar transform along time over groups of G consecutive time points (the
/// last group may be shorter): in a group, time points are paired, each pair's normalised sum
/// goes on to the next level and its difference is a detail component; an odd one out goes on
/// unchanged; the last sum left is the group's low-pass component. Its matrix is orthogonal, so
/// each time point is its group's components weighted by the transposed matrix.
#[derive(Debug, Clone, PartialEq)]
pub struct TemporalHaar {
    /// The group size G.
    pub group: usize,
    /// Each component as (time point, weight): the analysis. A group's components are
    /// consecutive, its low-pass one first, then details from coarse to fine.
    pub components: Vec<Vec<(usize, f64)>>,
    /// Each time point as (component, weight): the synthesis.
    pub points: Vec<Vec<(usize, f64)>>,
}

impl TemporalHaar {
    /// The transform of `points` time points in groups of `group` (a power of two, at most
    /// [`MAX_GROUP`]).
    pub fn new(points: usize, group: usize) -> Result<TemporalHaar, SeriesError> {
        if !group.is_power_of_two() || group > MAX_GROUP {
            return Err(SeriesError::InvalidOption(format!(
                "temporal group {group}; a power of two up to {MAX_GROUP}"
            )));
        }
        if points == 0 {
            return Err(SeriesError::InvalidOption(
                "a series of no time points".into(),
            ));
        }
        let mut components: Vec<Vec<(usize, f64)>> = Vec::new();
        let mut synthesis: Vec<Vec<(usize, f64)>> = vec![Vec::new(); points];
        let h = std::f64::consts::FRAC_1_SQRT_2;
        for start in (0..points).step_by(group) {
            let end = (start + group).min(points);
            // Each signal as its weights over the group's time points.
            let mut level: Vec<Vec<(usize, f64)>> = (start..end).map(|t| vec![(t, 1.0)]).collect();
            let mut details: Vec<Vec<Vec<(usize, f64)>>> = Vec::new();
            while level.len() > 1 {
                let mut next = Vec::with_capacity(level.len().div_ceil(2));
                let mut found = Vec::new();
                for pair in level.chunks(2) {
                    match pair {
                        [a, b] => {
                            let combine = |sign: f64| -> Vec<(usize, f64)> {
                                a.iter()
                                    .map(|(t, w)| (*t, w * h))
                                    .chain(b.iter().map(|(t, w)| (*t, sign * w * h)))
                                    .collect()
                            };
                            next.push(combine(1.0));
                            found.push(combine(-1.0));
                        }
                        [a] => next.push(a.clone()),
                        _ => unreachable!("chunks of two"),
                    }
                }
                details.push(found);
                level = next;
            }
            let first = components.len();
            components.push(level.pop().expect("one signal left"));
            for d in details.into_iter().rev().flatten() {
                components.push(d);
            }
            for (c, comp) in components.iter().enumerate().skip(first) {
                for &(t, w) in comp {
                    synthesis[t].push((c, w));
                }
            }
        }
        Ok(TemporalHaar {
            group,
            components,
            points: synthesis,
        })
    }
}

/// What a series compression made.
#[derive(Debug)]
pub struct SeriesCompressed {
    /// The container's bytes.
    pub bytes: Vec<u8>,
    /// Its manifest.
    pub manifest: SeriesManifest,
    /// The depth every component was transformed with.
    pub levels: usize,
    /// Coefficients of all components' padded grids, all channels.
    pub total_coefficients: u64,
}

/// A series' compression planned: its temporal transform, one [`BrickPlan`] per component
/// and the *units* the rate is allocated over (every component's bricks, component after
/// component). A unit is scored or coded alone ([`SeriesPlan::score_into`],
/// [`SeriesPlan::encode_from`]), in this process ([`compress_series`]) or on any worker that can
/// read the series, and the units' files make the container ([`SeriesPlan::assemble`]).
#[derive(Debug, Clone)]
pub struct SeriesPlan {
    /// The temporal transform.
    pub haar: TemporalHaar,
    /// Each component's bricks.
    pub plans: Vec<BrickPlan>,
    /// (component, brick) of each unit.
    pub units: Vec<(usize, usize)>,
    /// What one time point's bricks share (a component's offset is scaled by its weights' sum).
    pub choices: SharedChoices,
    /// The whole series' target.
    pub target: Target,
    /// Bytes of the container beside the units' files (manifests), for a byte target's search.
    pub overhead: u64,
}

impl SeriesPlan {
    /// Plans `series` in temporal groups of `group`, every component as bricks of edge `brick`
    /// (one brick, a plain volume file, when a time point fits one), under the target of
    /// `opts`, whose depth, when not given, is the one a time point alone would take at its
    /// share of a byte target (the middle time point is read and compressed for it).
    /// Intensity series only.
    pub fn new(
        series: &dyn SeriesSource,
        opts: &CompressOptions,
        group: usize,
        brick: usize,
    ) -> Result<SeriesPlan, SeriesError> {
        check_intensity(series)?;
        let points = series.time_points();
        TemporalHaar::new(points, group)?;
        let mid = TimePointSource {
            series,
            t: points / 2,
        };
        // The depth and offset come from one time point at its share of the target.
        let share = CompressOptions {
            target: match opts.target {
                Target::Bytes(total) => Target::Bytes((total / points as u64).max(1024)),
                t => t,
            },
            ..opts.clone()
        };
        wavesplat_codec::format::bricked::check_bricking(series.dims(), brick)
            .map_err(BrickError::InvalidOption)?;
        let single = wavesplat_codec::format::bricked::brick_grid(series.dims(), brick).len() == 1;
        let levels = match (opts.levels, opts.target) {
            (None, Target::Bytes(_)) if single => {
                let v = mid
                    .read([0; 3], series.dims().map(|d| d as usize))
                    .map_err(|source| BrickError::Read {
                        origin: [0; 3],
                        source,
                    })?;
                // The depth is chosen before any refinement, which this probe leaves out.
                let depth_only = CompressOptions {
                    refine: None,
                    ..share.clone()
                };
                let c = compress(&v, &depth_only, &|_, _| {}).map_err(|source| {
                    BrickError::Compress {
                        origin: [0; 3],
                        source: Box::new(source),
                    }
                })?;
                Some(c.header.geometry.levels)
            }
            (m, _) => m,
        };
        let probe = BrickPlan::new(
            &mid,
            &CompressOptions {
                levels,
                ..share.clone()
            },
            brick,
        )?;
        SeriesPlan::with_choices(series, opts, group, brick, probe.choices)
    }

    /// The plan of `series` with what its time points share already chosen (as
    /// [`SeriesPlan::new`] chose it, elsewhere): nothing is read.
    pub fn with_choices(
        series: &dyn SeriesSource,
        opts: &CompressOptions,
        group: usize,
        brick: usize,
        choices: SharedChoices,
    ) -> Result<SeriesPlan, SeriesError> {
        check_intensity(series)?;
        let haar = TemporalHaar::new(series.time_points(), group)?;
        let plans: Vec<BrickPlan> = haar
            .components
            .iter()
            .map(|terms| {
                let s = ComponentSource { series, terms };
                let gain: f64 = terms.iter().map(|(_, w)| w).sum();
                BrickPlan::with_choices(
                    &s,
                    opts,
                    brick,
                    SharedChoices {
                        // A component's mean is its weights' sum times a time point's.
                        offset: choices.offset.map(|o| o * gain),
                        ..choices.clone()
                    },
                )
            })
            .collect::<Result<_, _>>()?;
        let units: Vec<(usize, usize)> = plans
            .iter()
            .enumerate()
            .flat_map(|(c, p)| (0..p.grid.len()).map(move |i| (c, i)))
            .collect();
        // The series manifest's section, exactly (its fields are of fixed sizes), and each
        // bricked component's manifest.
        let placeholders = (0..plans.len())
            .map(|_| ComponentEntry {
                offset: 0,
                length: 0,
                crc: 0,
                kept: 0,
            })
            .collect();
        let section = manifest_section(&series_manifest(&haar, series, placeholders)).len();
        let overhead = section as u64
            + plans
                .iter()
                .filter(|p| p.grid.len() > 1)
                .map(BrickPlan::manifest_len)
                .sum::<u64>();
        Ok(SeriesPlan {
            haar,
            plans,
            units,
            choices,
            target: opts.target,
            overhead,
        })
    }

    /// The component of unit `u` as a volume to read bricks from.
    fn component<'a>(&'a self, series: &'a dyn SeriesSource, c: usize) -> ComponentSource<'a> {
        ComponentSource {
            series,
            terms: &self.haar.components[c],
        }
    }

    fn unit(&self, u: usize) -> Result<(usize, usize), BrickError> {
        self.units.get(u).copied().ok_or_else(|| {
            BrickError::InvalidOption(format!("unit {u} of a series of {}", self.units.len()))
        })
    }

    /// Unit `u`'s score summary, its top coefficients kept in `tops` where the units do not
    /// refine ([`BrickPlan::top_cap`], the target spread over every component), so that
    /// [`SeriesPlan::encode_from`] codes it without summing its time points and transforming
    /// them again.
    pub fn score_into(
        &self,
        series: &dyn SeriesSource,
        u: usize,
        tops: &KeptTops,
    ) -> Result<ScoreSummary, BrickError> {
        let (c, i) = self.unit(u)?;
        let cap = self.top_cap(c, i);
        self.plans[c].score_into(&self.component(series, c), i, tops, c, cap)
    }

    /// How many top coefficients unit `u` keeps for the second pass (`None`: none, as
    /// [`BrickPlan::top_cap`]; also for a unit this plan does not have): what a worker coding
    /// it without a top held keeps on the way.
    pub fn unit_top_cap(&self, u: usize) -> Option<u64> {
        let (c, i) = self.unit(u).ok()?;
        self.top_cap(c, i)
    }

    /// How many top coefficients brick `i` of component `c` keeps for the second pass
    /// ([`BrickPlan::top_cap`]). A group's low-pass component holds most of a slowly changing
    /// series and takes most of the kept coefficients: its top is sized as if the low-pass
    /// components shared the whole target; a detail component's as if every component did.
    fn top_cap(&self, c: usize, i: usize) -> Option<u64> {
        let low_pass = |terms: &[(usize, f64)]| terms.iter().all(|(_, w)| *w > 0.0);
        let parts = match low_pass(&self.haar.components[c]) {
            true => self.haar.components.iter().filter(|t| low_pass(t)).count(),
            false => self.plans.len(),
        };
        self.plans[c].top_cap_within(i, parts)
    }

    /// Unit `u` compressed as a `.wsp` of its own keeping its top `count` coefficients
    /// (`None`: all), and the count it kept: from its top kept in `tops` where that covers
    /// `count`, else read and transformed again ([`BrickPlan::encode_from`], keeping its top
    /// in `tops` on the way).
    pub fn encode_from(
        &self,
        series: &dyn SeriesSource,
        u: usize,
        count: Option<u64>,
        tops: &KeptTops,
    ) -> Result<(Vec<u8>, u64), BrickError> {
        let (c, i) = self.unit(u)?;
        let cap = self.top_cap(c, i);
        self.plans[c].encode_from(&self.component(series, c), i, count, tops, c, cap)
    }

    /// The budget of the units' kept tops ([`KeptTops::for_plan`] of the first component).
    pub fn kept_tops(&self) -> KeptTops {
        self.plans
            .first()
            .map_or(KeptTops::new(0), KeptTops::for_plan)
    }

    /// The series container of every unit's file and kept count, in unit order.
    pub fn assemble(
        &self,
        series: &dyn SeriesSource,
        units: Vec<(Vec<u8>, u64)>,
        total_coefficients: u64,
    ) -> Result<SeriesCompressed, SeriesError> {
        if units.len() != self.units.len() {
            return Err(SeriesError::InvalidOption(format!(
                "{} coded units for a series of {}",
                units.len(),
                self.units.len()
            )));
        }
        // Each component's bricks, in order: one brick is its plain file, more a container.
        let mut coded = units.into_iter();
        let mut files: Vec<Vec<u8>> = Vec::with_capacity(self.plans.len());
        let mut entries = Vec::with_capacity(self.plans.len());
        for plan in &self.plans {
            let bricks: Vec<(Vec<u8>, u64)> = coded.by_ref().take(plan.grid.len()).collect();
            let kept = bricks.iter().map(|b| b.1).sum();
            let file = if bricks.len() == 1 {
                bricks.into_iter().next().expect("one brick").0
            } else {
                plan.assemble(&bricks)?.0
            };
            entries.push(ComponentEntry {
                offset: 0,
                length: 0,
                crc: 0,
                kept,
            });
            files.push(file);
        }
        let mut manifest = self.manifest(series, entries);
        let slices: Vec<&[u8]> = files.iter().map(Vec::as_slice).collect();
        let bytes = write_series(&mut manifest, &slices)?;
        Ok(SeriesCompressed {
            bytes,
            manifest,
            levels: self.choices.levels,
            total_coefficients,
        })
    }

    /// The series manifest of components `entries` (offsets to be filled in).
    fn manifest(&self, series: &dyn SeriesSource, entries: Vec<ComponentEntry>) -> SeriesManifest {
        series_manifest(&self.haar, series, entries)
    }

    /// Writes the series container of the units coded in `units` (unit order) to `out`: the
    /// series manifest section, then each component (its plain file, or its bricked
    /// container's manifest section and bricks), the units' bytes copied from where they
    /// wait. Returns the manifest and the bytes written.
    pub fn write_container(
        &self,
        series: &dyn SeriesSource,
        units: &[CodedBrick<SpilledBrick>],
        out: &mut dyn std::io::Write,
    ) -> Result<(SeriesManifest, u64), SeriesError> {
        if units.len() != self.units.len() {
            return Err(SeriesError::InvalidOption(format!(
                "{} coded units for a series of {}",
                units.len(),
                self.units.len()
            )));
        }
        /// One component as written: its bricked manifest section (none for one brick), its
        /// units, and its length, CRC-32 (combined from its units' without reading them again)
        /// and count.
        struct Component<'u> {
            section: Vec<u8>,
            units: &'u [CodedBrick<SpilledBrick>],
            len: u64,
            crc: u32,
            kept: u64,
        }
        let mut components = Vec::with_capacity(self.plans.len());
        let mut start = 0;
        for plan in &self.plans {
            let mine = &units[start..start + plan.grid.len()];
            start += plan.grid.len();
            let section = if mine.len() == 1 {
                Vec::new()
            } else {
                let placed: Vec<(u64, u32, u64)> =
                    mine.iter().map(|u| (u.len, u.file.crc, u.kept)).collect();
                plan.manifest_section_for(&placed)?.0
            };
            let mut crc = crc32fast::Hasher::new();
            crc.update(&section);
            for u in mine {
                crc.combine(&crc32fast::Hasher::new_with_initial_len(u.file.crc, u.len));
            }
            let len = section.len() as u64 + mine.iter().map(|u| u.len).sum::<u64>();
            let kept = mine.iter().map(|u| u.kept).sum();
            components.push(Component {
                section,
                units: mine,
                len,
                crc: crc.finalize(),
                kept,
            });
        }
        let entries = components
            .iter()
            .map(|c| ComponentEntry {
                offset: 0,
                length: 0,
                crc: 0,
                kept: c.kept,
            })
            .collect();
        let mut manifest = self.manifest(series, entries);
        let placed: Vec<(u64, u32)> = components.iter().map(|c| (c.len, c.crc)).collect();
        let section = place_components(&mut manifest, &placed)?;
        let output = |e| SeriesError::Brick(Box::new(BrickError::Output(e)));
        out.write_all(&section).map_err(output)?;
        let mut written = section.len() as u64;
        for c in &components {
            out.write_all(&c.section).map_err(output)?;
            for u in c.units {
                u.file.copy_to(u.len, out).map_err(output)?;
            }
            written += c.len;
        }
        out.flush().map_err(output)?;
        Ok((manifest, written))
    }
}

/// Refuses a colour series.
fn check_intensity(series: &dyn SeriesSource) -> Result<(), SeriesError> {
    if series.channels() != 1 {
        return Err(SeriesError::InvalidOption(
            "colour time series are not supported yet; compress one time point (--time-point)"
                .into(),
        ));
    }
    Ok(())
}

/// Compresses `series` as one series container in this process: planned by
/// [`SeriesPlan::new`] (groups of `group`, bricks of edge `brick`), with the target of `opts`
/// allocated over every unit by [`allocate_units`] on the rayon pool.
pub fn compress_series(
    series: &dyn SeriesSource,
    opts: &CompressOptions,
    group: usize,
    brick: usize,
    progress: &(dyn Fn(BrickStage) + Sync),
) -> Result<SeriesCompressed, SeriesError> {
    let mut bytes = Vec::new();
    let w = compress_series_to(series, opts, group, brick, progress, None, &mut bytes)?;
    Ok(SeriesCompressed {
        bytes,
        manifest: w.manifest,
        levels: w.levels,
        total_coefficients: w.total_coefficients,
    })
}

/// What [`compress_series_to`] wrote.
#[derive(Debug)]
pub struct SeriesWritten {
    /// The container's manifest.
    pub manifest: SeriesManifest,
    /// Bytes written.
    pub bytes: u64,
    /// The depth every component was transformed with.
    pub levels: usize,
    /// Coefficients of all components' padded grids, all channels.
    pub total_coefficients: u64,
}

/// Compresses as [`compress_series`] does, writing the container to `out` as it is
/// assembled: the coded units of each trial wait in a temporary file in `spill_dir` (`None`:
/// the temporary directory), as a bricked volume's bricks do
/// ([`crate::bricked::compress_bricked_to`]), so memory does not grow with the file.
pub fn compress_series_to(
    series: &dyn SeriesSource,
    opts: &CompressOptions,
    group: usize,
    brick: usize,
    progress: &(dyn Fn(BrickStage) + Sync),
    spill_dir: Option<&std::path::Path>,
    out: &mut dyn std::io::Write,
) -> Result<SeriesWritten, SeriesError> {
    let plan = SeriesPlan::new(series, opts, group, brick)?;
    let of = plan.units.len();
    let counter = std::sync::atomic::AtomicUsize::new(0);
    let tick = |stage: &dyn Fn(usize) -> BrickStage| {
        let done = counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        progress(stage(done));
    };
    let tops = plan.kept_tops().spilling_in(spill_dir);
    let allocated = allocate_units(
        plan.target,
        of,
        plan.overhead,
        None,
        || {
            counter.store(0, std::sync::atomic::Ordering::Relaxed);
            in_grid_order(of, |u| {
                let s = plan.score_into(series, u, &tops)?;
                tick(&|done| BrickStage::Scored { done, of });
                Ok(s)
            })
        },
        |counts, trial| {
            counter.store(0, std::sync::atomic::Ordering::Relaxed);
            let spill = std::sync::Arc::new(Spill::new(spill_dir)?);
            in_grid_order(of, |u| {
                let (file, kept) = plan.encode_from(series, u, counts.map(|k| k[u]), &tops)?;
                let len = file.len() as u64;
                let file = spill.push(&file)?;
                tick(&|done| BrickStage::Compressed { done, of, trial });
                Ok(CodedBrick { len, file, kept })
            })
        },
    )?;
    let (from_kept_top, transformed_again) = tops.counts();
    let spilled = tops.spilled();
    tracing::debug!(
        from_kept_top,
        transformed_again,
        spilled,
        "series units coded"
    );
    let (manifest, bytes) = plan.write_container(series, &allocated.bricks, out)?;
    Ok(SeriesWritten {
        manifest,
        bytes,
        levels: plan.choices.levels,
        total_coefficients: allocated.total_coefficients,
    })
}

/// Decodes time point `t` of a series container: its components decoded (plain files or
/// bricked containers) and summed with their weights, in f64.
pub fn decode_time_point(bytes: &[u8], t: usize) -> Result<Volume, SeriesError> {
    let file = parse_series(bytes)?;
    let m = &file.manifest;
    let point = m.points.get(t).ok_or_else(|| {
        SeriesError::InvalidOption(format!("time point {t}; the series has {}", m.points.len()))
    })?;
    let dims = m.space.dims.map(|d| d as usize);
    let n = wavesplat_codec::volume::checked_voxels(dims)?;
    let mut acc = vec![vec![0f64; n]; m.space.channels];
    for &(c, w) in &point.terms {
        let data = file.component_bytes(c)?;
        let v = decode_component(data).map_err(|source| SeriesError::Decode {
            component: c,
            source: Box::new(source),
        })?;
        if v.dims() != dims || v.channel_count() != m.space.channels {
            return Err(SeriesError::Format(FormatError::Invalid {
                what: "series manifest",
                detail: format!(
                    "component {c} decodes to {:?} with {} channel(s); the series is {:?} with {}",
                    v.dims(),
                    v.channel_count(),
                    dims,
                    m.space.channels
                ),
            }));
        }
        for (a, ch) in acc.iter_mut().zip(v.channels()) {
            a.iter_mut()
                .zip(ch)
                .for_each(|(a, x)| *a += f64::from(w) * f64::from(*x));
        }
    }
    let data = acc
        .into_iter()
        .map(|c| c.into_iter().map(|v| v as f32).collect())
        .collect();
    let v = Volume::new(dims, m.space.spacing, data)?;
    Ok(match m.space.placement {
        Some(p) => v.with_placement(p)?,
        None => v,
    })
}

/// A component's file decoded whole: a plain file, or a bricked container's bricks pasted
/// into the whole (series held whole are small; a large one is drawn, not decoded).
fn decode_component(data: &[u8]) -> Result<Volume, crate::decode::DecodeError> {
    use crate::decode::DecodeError;
    use wavesplat_codec::format::bricked::{is_bricked, parse_bricked};
    let budget = wavesplat_codec::format::packet::DecodeBudget::default();
    if !is_bricked(data) {
        return crate::decode::decompress_within(data, &budget);
    }
    let m = parse_bricked(data).map_err(DecodeError::Format)?.manifest;
    let dims = m.dims.map(|d| d as usize);
    let n = wavesplat_codec::volume::checked_voxels(dims).map_err(|e| {
        DecodeError::Format(FormatError::Invalid {
            what: "bricked component",
            detail: e.to_string(),
        })
    })?;
    let whole = std::sync::Mutex::new(vec![vec![0f32; n]; m.channels]);
    crate::bricked::decode_bricks(data, &budget, &|e, v| {
        let mut whole = whole.lock().expect("not poisoned");
        let [bx, by, bz] = e.dims;
        let o = e.origin.map(|v| v as usize);
        for (w, c) in whole.iter_mut().zip(v.channels()) {
            for z in 0..bz {
                for y in 0..by {
                    let src = &c[(z * by + y) * bx..][..bx];
                    let at = ((o[2] + z) * dims[1] + o[1] + y) * dims[0] + o[0];
                    w[at..at + bx].copy_from_slice(src);
                }
            }
        }
        Ok(())
    })
    .map_err(|e| {
        DecodeError::Format(FormatError::Invalid {
            what: "bricked component",
            detail: e.to_string(),
        })
    })?;
    let data = whole.into_inner().expect("not poisoned");
    Volume::new(dims, m.spacing, data).map_err(|e| {
        DecodeError::Format(FormatError::Invalid {
            what: "bricked component",
            detail: e.to_string(),
        })
    })
}

/// The series manifest of `haar`'s components `entries` over `series` (offsets to be filled
/// in).
fn series_manifest(
    haar: &TemporalHaar,
    series: &dyn SeriesSource,
    entries: Vec<ComponentEntry>,
) -> SeriesManifest {
    let points = series.time_points();
    let (times_known, times) = match series.times() {
        Some(t) if check_times(&t, points).is_ok() => (true, t),
        _ => (false, (0..points).map(|t| t as f64).collect()),
    };
    SeriesManifest {
        space: Space {
            dims: series.dims(),
            channels: series.channels(),
            spacing: series.spacing(),
            placement: series.placement(),
        },
        times_known,
        group: haar.group,
        components: entries,
        points: haar
            .points
            .iter()
            .zip(&times)
            .map(|(terms, time)| TimePoint {
                time: *time,
                terms: terms.iter().map(|(c, w)| (*c, *w as f32)).collect(),
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::phantom::{beating, beating_scale};
    use wavesplat_codec::metrics::psnr_db;

    fn cine(dims: [usize; 3], points: usize) -> VolumeSeries {
        let v = (0..points)
            .map(|t| beating(dims, t, points).unwrap())
            .collect();
        VolumeSeries::new(v, Some((0..points).map(|t| 0.04 * t as f64).collect())).unwrap()
    }

    /// Mean PSNR (peak 400) of every decoded time point against the original.
    fn mean_psnr(series: &VolumeSeries, bytes: &[u8]) -> f64 {
        let n = series.time_points();
        (0..n)
            .map(|t| {
                let d = decode_time_point(bytes, t).unwrap();
                psnr_db(series.volumes()[t].channel(0), d.channel(0), 400.0)
            })
            .sum::<f64>()
            / n as f64
    }

    #[test]
    fn the_temporal_haar_is_orthonormal_and_inverts_in_f64() {
        for points in 1..=19 {
            for group in [1, 2, 4, 8, 16] {
                let h = TemporalHaar::new(points, group).unwrap();
                assert_eq!(h.components.len(), points, "{points}/{group}");
                // A A^T = I over the components' analysis rows.
                for (a, ca) in h.components.iter().enumerate() {
                    for (b, cb) in h.components.iter().enumerate() {
                        let dot: f64 = ca
                            .iter()
                            .map(|(t, w)| {
                                cb.iter().find(|(u, _)| u == t).map_or(0.0, |(_, v)| w * v)
                            })
                            .sum();
                        let want = if a == b { 1.0 } else { 0.0 };
                        assert!(
                            (dot - want).abs() < 1e-12,
                            "{points}/{group}: {a},{b} {dot}"
                        );
                    }
                }
                // Synthesis of a random signal's analysis gives it back.
                let x: Vec<f64> = (0..points)
                    .map(|t| ((t * 7919) % 101) as f64 - 50.0)
                    .collect();
                let coef: Vec<f64> = h
                    .components
                    .iter()
                    .map(|c| c.iter().map(|(t, w)| w * x[*t]).sum())
                    .collect();
                for (t, terms) in h.points.iter().enumerate() {
                    let back: f64 = terms.iter().map(|(c, w)| w * coef[*c]).sum();
                    assert!((back - x[t]).abs() < 1e-9, "{points}/{group} t={t}");
                    // A time point needs its group's components only, at most log2(G) + 1.
                    assert!(terms.len() <= group.trailing_zeros() as usize + 1);
                    assert!(terms
                        .iter()
                        .all(|(c, _)| c / group == t / group || group == 1));
                }
            }
        }
        assert!(TemporalHaar::new(4, 3).is_err());
        assert!(TemporalHaar::new(0, 2).is_err());
    }

    #[test]
    fn every_coefficient_gives_every_time_point_back() {
        let s = cine([20, 18, 9], 5);
        let opts = CompressOptions {
            target: Target::All,
            refine: None,
            ..CompressOptions::default()
        };
        for group in [1, 4] {
            let c = compress_series(&s, &opts, group, 256, &|_| {}).unwrap();
            assert_eq!(c.manifest.points.len(), 5);
            assert!(c.manifest.times_known);
            assert!((c.manifest.points[3].time - 0.12).abs() < 1e-12);
            // Quantization only: far above the noise's 4.
            assert!(mean_psnr(&s, &c.bytes) > 50.0, "group {group}");
        }
    }

    #[test]
    fn a_group_shares_what_does_not_move_and_beats_time_points_alone_at_equal_bytes() {
        let s = cine([32, 32, 16], 8);
        let target = 24_000;
        let opts = CompressOptions {
            target: Target::Bytes(target),
            ..CompressOptions::default()
        };
        let alone = compress_series(&s, &opts, 1, 256, &|_| {}).unwrap();
        let grouped = compress_series(&s, &opts, 8, 256, &|_| {}).unwrap();
        for c in [&alone, &grouped] {
            let n = c.bytes.len() as u64;
            assert!(n <= target && n as f64 >= 0.98 * target as f64, "{n}");
        }
        let (a, g) = (mean_psnr(&s, &alone.bytes), mean_psnr(&s, &grouped.bytes));
        assert!(g > a + 1.0, "grouped {g:.2} dB, alone {a:.2} dB");
        // The known motion survives: the blood pool (> 325) grows and shrinks with s(t)³.
        let pool = |t: usize| {
            let d = decode_time_point(&grouped.bytes, t).unwrap();
            d.channel(0).iter().filter(|v| **v > 325.0).count() as f64
        };
        let (p0, p2, p6) = (pool(0), pool(2), pool(6));
        let ratio = |t: usize| (beating_scale(t, 8) / beating_scale(0, 8)).powi(3);
        assert!((p2 / p0 / ratio(2) - 1.0).abs() < 0.2, "{p0} {p2}");
        assert!((p6 / p0 / ratio(6) - 1.0).abs() < 0.2, "{p0} {p6}");
    }

    /// A bricked series lands within 2 % of a byte target: its components' manifests are set
    /// aside at their exact length (an allowance per brick left the files a fixed ~4 kB short,
    /// 5.7 % at 80 kB and 38 % at 11 kB, with 72 bricks).
    #[test]
    fn a_bricked_series_lands_within_two_percent_of_a_byte_target() {
        let s = cine([20, 21, 13], 4);
        for target in [12_000u64, 40_000] {
            let opts = CompressOptions {
                target: Target::Bytes(target),
                ..CompressOptions::default()
            };
            let c = compress_series(&s, &opts, 1, 8, &|_| {}).unwrap();
            let n = c.bytes.len() as u64;
            assert!(
                n <= target && n as f64 >= 0.98 * target as f64,
                "{n} for {target}"
            );
        }
    }

    /// A byte target near the smallest file a series makes (every component's header and
    /// the manifests, with or without a placement in patient space): the refusal names the
    /// smallest file's size, that size is then met, and no file is larger than its target.
    /// (The series manifest was once set aside at an estimate 1 byte short without a placement
    /// and 97 with one, and the search crept down a tenth at a time and gave up at 74
    /// coefficients where 1 fits.)
    #[test]
    fn byte_targets_near_the_smallest_series_file_are_met_or_refused_with_its_size() {
        let placed = |v: Volume| {
            v.with_placement(Placement {
                origin: [-90.0, 126.0, -72.0],
                directions: [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]],
            })
            .unwrap()
        };
        let points = 8;
        for placement in [false, true] {
            let volumes = (0..points)
                .map(|t| {
                    let v = beating([24, 20, 12], t, points).unwrap();
                    if placement {
                        placed(v)
                    } else {
                        v
                    }
                })
                .collect();
            let s = VolumeSeries::new(volumes, None).unwrap();
            let at = |target: u64| {
                let opts = CompressOptions {
                    target: Target::Bytes(target),
                    ..CompressOptions::default()
                };
                compress_series(&s, &opts, 4, 256, &|_| {})
            };
            let refused = at(0).unwrap_err().to_string();
            assert!(
                refused.starts_with("invalid option for a time series")
                    && refused.contains("keeping 1 coefficient(s)"),
                "{refused}"
            );
            let smallest: u64 = refused
                .split(" takes ")
                .nth(1)
                .and_then(|t| t.split_whitespace().next()?.parse().ok())
                .unwrap_or_else(|| panic!("{refused}"));
            for target in [smallest, smallest + 40, smallest + 400] {
                let c = at(target).unwrap_or_else(|e| panic!("{target}: {e}"));
                let n = c.bytes.len() as u64;
                assert!(
                    n <= target,
                    "{n} bytes for {target} (placement {placement})"
                );
            }
            let c = at(smallest + 400).unwrap();
            assert!(c.manifest.kept() > points as u64, "{}", c.manifest.kept());
        }
    }

    /// A Q_V target keeps a small part of a series, not all of it (the components' bridge
    /// energy outside their boxes was once counted in the goal).
    #[test]
    fn a_qv_target_keeps_what_the_energy_needs() {
        let s = cine([24, 20, 12], 4);
        let at = |target| {
            let opts = CompressOptions {
                target,
                refine: None,
                ..CompressOptions::default()
            };
            compress_series(&s, &opts, 4, 256, &|_| {})
                .unwrap()
                .bytes
                .len()
        };
        let (qv, all) = (at(Target::QvPercent(90.0)), at(Target::All));
        assert!(qv * 10 < all, "Q_V 90 %: {qv} bytes, everything {all}");
    }

    /// `plan`'s units allocated one after another in this thread, scored and coded through
    /// `tops` (a budget of nothing: each unit read and transformed in both passes).
    fn allocated_in_order(
        plan: &SeriesPlan,
        s: &dyn SeriesSource,
        tops: &KeptTops,
    ) -> crate::bricked::Allocated<Vec<u8>> {
        let of = plan.units.len();
        allocate_units(
            plan.target,
            of,
            plan.overhead,
            None,
            || (0..of).map(|u| plan.score_into(s, u, tops)).collect(),
            |counts, _| {
                (0..of)
                    .map(|u| {
                        let count = counts.map(|k| k[u]);
                        let (file, kept) = plan.encode_from(s, u, count, tops)?;
                        let len = file.len() as u64;
                        Ok(CodedBrick { len, file, kept })
                    })
                    .collect()
            },
        )
        .unwrap()
    }

    /// A series streamed from its coded units on disk (bricked components: their manifest
    /// sections made there, their CRCs combined from the bricks') is byte for byte the one
    /// assembled in memory, as workers assemble it, at a fraction and over a byte target's
    /// trials; every component's CRC checks.
    #[test]
    fn a_series_streamed_from_its_spill_is_the_one_assembled_in_memory() {
        let s = cine([24, 20, 18], 6);
        for target in [Target::Fraction(0.2), Target::Bytes(30_000)] {
            let opts = CompressOptions {
                target,
                ..CompressOptions::default()
            };
            let plan = SeriesPlan::new(&s, &opts, 2, 12).unwrap();
            let a = allocated_in_order(&plan, &s, &KeptTops::new(0));
            let units = a.bricks.into_iter().map(|b| (b.file, b.kept)).collect();
            let in_memory = plan.assemble(&s, units, a.total_coefficients).unwrap();
            let spill = tempfile::tempdir().unwrap();
            let mut out = Vec::new();
            let w = compress_series_to(&s, &opts, 2, 12, &|_| {}, Some(spill.path()), &mut out)
                .unwrap();
            assert_eq!(out, in_memory.bytes, "{target:?}");
            assert_eq!(w.bytes, out.len() as u64);
            assert_eq!(w.manifest, in_memory.manifest);
            let f = parse_series(&out).unwrap();
            for c in 0..f.manifest.components.len() {
                f.component_bytes(c).unwrap();
            }
        }
    }

    /// Without refinement, the units coded from the tops their score pass kept are the files
    /// coded by summing their time points and transforming them again, byte for byte, at a
    /// fraction and over a byte target's trials; most units are coded from their tops, and
    /// the whole series written so is the one written without them.
    #[test]
    fn series_units_coded_from_kept_tops_are_the_files_a_second_transform_writes() {
        let s = cine([24, 20, 18], 6);
        for target in [Target::Fraction(0.05), Target::Bytes(12_000)] {
            let opts = CompressOptions {
                target,
                ..crate::encode::Effort::Fast.options()
            };
            let plan = SeriesPlan::new(&s, &opts, 2, 12).unwrap();
            let of = plan.units.len();
            let allocated = |tops: &KeptTops| allocated_in_order(&plan, &s, tops);
            let files = |a: crate::bricked::Allocated<Vec<u8>>| -> Vec<(Vec<u8>, u64)> {
                a.bricks.into_iter().map(|b| (b.file, b.kept)).collect()
            };
            let none = KeptTops::new(0);
            let without = allocated(&none);
            let total = without.total_coefficients;
            let again = files(without);
            assert_eq!(none.counts().0, 0);
            let tops = plan.kept_tops();
            let kept = files(allocated(&tops));
            assert_eq!(kept, again, "{target:?}");
            let (reused, transformed) = tops.counts();
            assert!(reused + transformed >= of);
            assert!(
                4 * reused >= 3 * (reused + transformed),
                "{target:?}: {reused} {transformed}"
            );
            let mut out = Vec::new();
            compress_series_to(&s, &opts, 2, 12, &|_| {}, None, &mut out).unwrap();
            let in_memory = plan.assemble(&s, again, total).unwrap();
            assert_eq!(out, in_memory.bytes, "{target:?}");
        }
    }

    #[test]
    fn bricked_components_decode_and_stay_apart_by_group() {
        let s = cine([24, 20, 18], 6);
        let opts = CompressOptions {
            target: Target::Fraction(0.2),
            ..CompressOptions::default()
        };
        let c = compress_series(&s, &opts, 2, 12, &|_| {}).unwrap();
        let f = parse_series(&c.bytes).unwrap();
        assert_eq!(f.manifest.components.len(), 6);
        for c in 0..6 {
            assert!(wavesplat_codec::format::bricked::is_bricked(
                f.component_bytes(c).unwrap()
            ));
        }
        // Time point 3 needs the second group's two components only.
        let terms: Vec<usize> = f.manifest.points[3].terms.iter().map(|t| t.0).collect();
        assert_eq!(terms.len(), 2);
        assert!(terms.iter().all(|c| (2..4).contains(c)), "{terms:?}");
        assert!(mean_psnr(&s, &c.bytes) > 35.0);
    }

    #[test]
    fn series_that_are_not_one_space_or_not_intensity_are_refused() {
        let a = beating([8, 8, 8], 0, 2).unwrap();
        let b = beating([8, 8, 9], 1, 2).unwrap();
        let e = VolumeSeries::new(vec![a.clone(), b], None).unwrap_err();
        assert!(e.to_string().contains("time point 1"), "{e}");
        let e = VolumeSeries::new(vec![a.clone(), a.clone()], Some(vec![0.0, 0.0])).unwrap_err();
        assert!(e.to_string().contains("increasing"), "{e}");
        assert!(VolumeSeries::new(Vec::new(), None).is_err());
        let rgb = crate::phantom::Phantom::RgbHead.generate([8, 8, 8]);
        let s = VolumeSeries::new(vec![rgb.clone(), rgb], None).unwrap();
        let e = compress_series(&s, &CompressOptions::default(), 2, 256, &|_| {}).unwrap_err();
        assert!(e.to_string().contains("colour"), "{e}");
    }
}
