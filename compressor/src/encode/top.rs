//! A volume's score pass that keeps the oracle's top coefficients ([`KeptTop`]), so that a
//! later pass codes the volume from them without reading or transforming it again: a bricked
//! volume's rate allocation scores every brick once to choose the global threshold, then codes
//! each brick with its share, and without this every brick went through the colour transform,
//! padding, prefilter, 3D transform and two passes of scores a second time (and once more per
//! trial of a byte target's search).
//!
//! Only compressions that do not refine keep their top: the least-squares refinement fits the
//! kept set to the voxels, which needs the dense transform and the samples. What is kept is
//! what [`Prepared::encode`] reads: the volume's small metadata (geometry, band norms, colour
//! information, value range, totals, the seen-share tables of a bridged grid) and the top
//! `cap` coefficients in the oracle's order, 8 bytes each (9 with more than one channel), in
//! memory or moved to a [`ScratchFile`] ([`KeptTop::spill`]), from which a coding reads only
//! the prefix it keeps. A file coded from them is the file [`super::compress`] writes for the
//! same count, byte for byte.

use super::options::{CompressError, CompressOptions, Compressed, Stage, Target};
use super::prepare::{band_norms, Prepared, Ranked, Scored};
use super::rate::expected_bytes;
use super::summary::ScoreSummary;
use super::{check_layer_growth, scored};
use crate::scratch::ScratchFile;
use crate::select::Histogram;
use crate::visible::Visible;
use std::borrow::Cow;
use std::sync::Arc;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::{ColorInfo, ColorKind};
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::volume::{Placement, Volume};

/// The share of the free disk space that kept tops may take where they are written: spilled
/// beyond their memory budget (a bricked compression's temporary file, measured when the first
/// top is spilled) and, separately, kept in a checkpoint ([`crate::checkpoint`], measured when
/// the first is kept). The rest is left to the output, the checkpoint's other entries and the
/// trials' coded bricks.
pub const TOP_DISK_SHARE: f64 = 0.25;

/// A volume's oracle's top coefficients and what coding them needs, kept from its score pass
/// ([`score_keeping_top`]).
pub struct KeptTop {
    /// The prepared volume without its dense arrays (coefficients, band map, histogram).
    prepared: Prepared,
    /// The top coefficients in the oracle's order.
    values: TopValues,
    /// The top holds every selectable coefficient.
    complete: bool,
    /// The options it was scored with.
    opts: CompressOptions,
}

/// Where a [`KeptTop`]'s coefficients are.
enum TopValues {
    /// In memory: index and value (8 bytes; their scores, which the ranking's 24-byte entries
    /// also hold, are computed again for the ones coded), and each one's channel (empty for
    /// one channel).
    Held {
        top: Vec<(u32, f32)>,
        channels: Vec<u8>,
    },
    /// In a scratch file from `offset`: `len` little-endian (index u32, value f32) pairs, then
    /// `len` channel bytes where `channels`.
    Spilled {
        file: Arc<ScratchFile>,
        offset: u64,
        len: usize,
        channels: bool,
    },
}

/// The score summary of `volume` under `opts` ([`super::score_summary`]) and, when `opts` do
/// not refine, its oracle's top `cap` coefficients kept for coding ([`KeptTop::compress`]).
pub fn score_keeping_top(
    volume: &Volume,
    opts: &CompressOptions,
    cap: u64,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<(ScoreSummary, Option<KeptTop>), CompressError> {
    let (mut prepared, summary) = scored(volume, opts, progress)?;
    if opts.refine.is_some() {
        return Ok((summary, None));
    }
    let cap = usize::try_from(cap.min(prepared.nonzero)).unwrap_or(usize::MAX);
    let ranked = prepared.ranked(cap);
    let top = ranked.sorted.iter().map(|s| (s.index, s.value)).collect();
    let channels = match prepared.channels {
        1 => Vec::new(),
        _ => ranked.sorted.iter().map(|s| s.channel).collect(),
    };
    let complete = ranked.complete;
    drop(ranked);
    prepared.coefficients = Vec::new();
    prepared.band_of = Vec::new();
    prepared.histogram = Histogram::none();
    prepared.targets = Vec::new();
    prepared.views = Vec::new();
    prepared.scratch = Default::default();
    let kept = KeptTop {
        prepared,
        values: TopValues::Held { top, channels },
        complete,
        opts: opts.clone(),
    };
    Ok((summary, Some(kept)))
}

impl KeptTop {
    /// Whether keeping `count` coefficients (as [`Target::Coefficients`]) can be coded from
    /// what is kept: the count is within the top kept, or the top holds every selectable
    /// coefficient.
    pub fn covers(&self, count: u64) -> bool {
        self.complete || count <= self.len() as u64
    }

    /// Whether it was scored with `opts`, up to the target (what a second pass may change).
    pub fn scored_with(&self, opts: &CompressOptions) -> bool {
        let same = CompressOptions {
            target: opts.target,
            ..self.opts.clone()
        };
        same == *opts
    }

    /// Coefficients kept.
    pub fn len(&self) -> usize {
        match &self.values {
            TopValues::Held { top, .. } => top.len(),
            TopValues::Spilled { len, .. } => *len,
        }
    }

    /// Whether no coefficient is kept.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes it holds on the heap (about).
    pub fn heap_bytes(&self) -> usize {
        let values = match &self.values {
            TopValues::Held { top, channels } => {
                top.capacity() * std::mem::size_of::<(u32, f32)>() + channels.capacity()
            }
            TopValues::Spilled { .. } => 0,
        };
        values
            + self.prepared.norms.capacity() * std::mem::size_of::<f64>()
            + self.prepared.visible.as_ref().map_or(0, |v| v.heap_bytes())
    }

    /// Whether its coefficients are in a scratch file.
    pub fn is_spilled(&self) -> bool {
        matches!(self.values, TopValues::Spilled { .. })
    }

    /// Bytes its coefficients take in a scratch file ([`KeptTop::spill`]).
    pub fn spilled_size(&self) -> u64 {
        let per = match &self.values {
            TopValues::Held { channels, .. } => 8 + u64::from(!channels.is_empty()),
            TopValues::Spilled { channels, .. } => 8 + u64::from(*channels),
        };
        self.len() as u64 * per
    }

    /// Moves its coefficients to the end of `file`, leaving in memory only what coding needs
    /// beside them (a few kB). On an error it keeps them in memory. Spilled already: nothing.
    pub fn spill(&mut self, file: &Arc<ScratchFile>) -> std::io::Result<()> {
        let TopValues::Held { top, channels } = &self.values else {
            return Ok(());
        };
        let mut bytes = Vec::with_capacity(self.spilled_size() as usize);
        push_pairs(&mut bytes, top);
        bytes.extend_from_slice(channels);
        let offset = file.append(&bytes)?;
        self.values = TopValues::Spilled {
            file: file.clone(),
            offset,
            len: top.len(),
            channels: !channels.is_empty(),
        };
        Ok(())
    }

    /// Its first `k` (at most its length) coefficients and their channels (empty for one
    /// channel), from memory or read back from its scratch file.
    #[allow(clippy::type_complexity)]
    fn prefix(&self, k: usize) -> Result<(Cow<'_, [(u32, f32)]>, Cow<'_, [u8]>), CompressError> {
        match &self.values {
            TopValues::Held { top, channels } => Ok((
                Cow::Borrowed(&top[..k]),
                Cow::Borrowed(&channels[..k.min(channels.len())]),
            )),
            TopValues::Spilled {
                file,
                offset,
                len,
                channels,
            } => {
                let read = |at: u64, n: usize| file.read(at, n).map_err(CompressError::KeptTopRead);
                let pairs = read(*offset, k * 8)?.chunks_exact(8).map(pair_of).collect();
                let channel_bytes = match channels {
                    true => read(offset + *len as u64 * 8, k)?,
                    false => Vec::new(),
                };
                Ok((Cow::Owned(pairs), Cow::Owned(channel_bytes)))
            }
        }
    }

    /// The volume compressed keeping its top `count` coefficients: the file
    /// [`super::compress`] writes with the options it was scored with and
    /// [`Target::Coefficients`]`(count)`. A count beyond what is kept ([`KeptTop::covers`]) is
    /// refused.
    pub fn compress(&self, count: u64) -> Result<Compressed, CompressError> {
        if !self.covers(count) {
            return Err(CompressError::InvalidOption(format!(
                "{count} coefficients asked of a kept top of {}",
                self.len()
            )));
        }
        let opts = CompressOptions {
            target: Target::Coefficients(count),
            ..self.opts.clone()
        };
        check_layer_growth(&opts)?;
        let k = usize::try_from(count.min(self.prepared.nonzero))
            .unwrap_or(usize::MAX)
            .min(self.len());
        let p = &self.prepared;
        let (top, channels) = self.prefix(k)?;
        let sorted = top
            .iter()
            .enumerate()
            .map(|(j, &(index, value))| {
                let channel = channels.get(j).copied().unwrap_or(0);
                let band = p.band_at(index as usize);
                Scored {
                    score: p.score_in_band(channel as usize, index as usize, value, band),
                    channel,
                    index,
                    value,
                }
            })
            .collect();
        let ranked = Ranked::new(sorted, self.complete && k == self.len(), 0);
        Ok(p.encode(&ranked, k, &opts, expected_bytes(k, opts.coder), true))
    }
}

/// The start of [`KeptTop::to_bytes`]: a tag and its version.
const TOP_MAGIC: &[u8; 8] = b"WSTOP\x00\x00\x01";

/// Bytes [`KeptTop::to_bytes`] writes before the coefficients: the tag, the geometry (nine
/// sizes, depth, margin, channels, family, spacing), the value range, the colour (kind, basis,
/// mean, importances), the placement (flag, origin, directions), energies, totals, two flags,
/// the length and the channel flag.
const TOP_HEADER_BYTES: u64 =
    8 + 12 * 8 + 1 + 3 * 4 + 2 * 4 + 1 + 15 * 8 + 1 + 12 * 8 + 2 * 8 + 2 * 8 + 1 + 1 + 8 + 1;

/// Appends `pairs` as [`KeptTop`] writes its coefficients (a scratch file, a checkpoint):
/// each index then value, little-endian, 8 bytes.
fn push_pairs(out: &mut Vec<u8>, pairs: &[(u32, f32)]) {
    let start = out.len();
    out.resize(start + pairs.len() * 8, 0);
    for (b, &(index, value)) in out[start..].chunks_exact_mut(8).zip(pairs) {
        b[..4].copy_from_slice(&index.to_le_bytes());
        b[4..].copy_from_slice(&value.to_bits().to_le_bytes());
    }
}

/// One coefficient of [`push_pairs`]' 8 bytes.
fn pair_of(b: &[u8]) -> (u32, f32) {
    let index = u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    let value = f32::from_bits(u32::from_le_bytes([b[4], b[5], b[6], b[7]]));
    (index, value)
}

/// Why bytes are not a [`KeptTop`] for the options they are read with.
#[derive(Debug, thiserror::Error)]
#[error("not a kept top: {0}")]
pub struct TopBytesError(String);

/// Bounds-checked little-endian reads of [`KeptTop::to_bytes`]'s output.
struct TopReader<'a>(&'a [u8]);

impl TopReader<'_> {
    fn take<const N: usize>(&mut self) -> Result<[u8; N], TopBytesError> {
        let (head, rest) = self
            .0
            .split_at_checked(N)
            .ok_or_else(|| TopBytesError("cut short".into()))?;
        self.0 = rest;
        Ok(head.try_into().unwrap_or([0; N]))
    }
    fn u8(&mut self) -> Result<u8, TopBytesError> {
        Ok(self.take::<1>()?[0])
    }
    fn u64(&mut self) -> Result<u64, TopBytesError> {
        Ok(u64::from_le_bytes(self.take()?))
    }
    fn usize(&mut self) -> Result<usize, TopBytesError> {
        usize::try_from(self.u64()?).map_err(|_| TopBytesError("a size beyond memory".into()))
    }
    fn f32(&mut self) -> Result<f32, TopBytesError> {
        Ok(f32::from_le_bytes(self.take()?))
    }
    fn f64(&mut self) -> Result<f64, TopBytesError> {
        Ok(f64::from_le_bytes(self.take()?))
    }
    fn flag(&mut self) -> Result<bool, TopBytesError> {
        match self.u8()? {
            0 => Ok(false),
            1 => Ok(true),
            _ => Err(TopBytesError("a flag neither 0 nor 1".into())),
        }
    }
}

impl KeptTop {
    /// The top written down, so that a compression run again after a kill codes the brick
    /// from it instead of reading and transforming it again ([`crate::checkpoint`]): the
    /// metadata coding needs (geometry, margin, colour information, value range, placement,
    /// totals) and the coefficients, 8 bytes each and a channel byte each with colour. The
    /// band norms and the seen-share tables are not written: they follow from the geometry.
    /// The options are not either: [`KeptTop::from_bytes`] takes them from its caller.
    pub fn to_bytes(&self) -> Result<Vec<u8>, CompressError> {
        let p = &self.prepared;
        let g = &p.geometry;
        let mut out = Vec::with_capacity(self.written_size() as usize);
        out.extend_from_slice(TOP_MAGIC);
        let u64s = |out: &mut Vec<u8>, v: &[usize]| {
            for x in v {
                out.extend_from_slice(&(*x as u64).to_le_bytes());
            }
        };
        let f64s = |out: &mut Vec<u8>, v: &[f64]| {
            for x in v {
                out.extend_from_slice(&x.to_le_bytes());
            }
        };
        u64s(&mut out, &g.dims);
        u64s(&mut out, &g.padded);
        u64s(&mut out, &g.origin);
        u64s(&mut out, &[g.levels, p.margin, p.channels]);
        out.push(g.family.code());
        for v in g.spacing.iter().chain(&p.value_range) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.push(p.color.kind.code());
        f64s(&mut out, p.color.basis.as_flattened());
        f64s(&mut out, &p.color.mean);
        f64s(&mut out, &p.color.importance);
        out.push(u8::from(p.placement.is_some()));
        let placement = p.placement.unwrap_or_else(Placement::identity);
        f64s(&mut out, &placement.origin);
        f64s(&mut out, placement.directions.as_flattened());
        f64s(&mut out, &[p.total_energy, p.selectable_energy]);
        out.extend_from_slice(&p.total_coefficients.to_le_bytes());
        out.extend_from_slice(&p.nonzero.to_le_bytes());
        out.push(u8::from(p.visible.is_some()));
        out.push(u8::from(self.complete));
        let (top, channels) = self.prefix(self.len())?;
        out.extend_from_slice(&(top.len() as u64).to_le_bytes());
        out.push(u8::from(!channels.is_empty()));
        push_pairs(&mut out, &top);
        out.extend_from_slice(&channels);
        debug_assert_eq!(out.len() as u64, self.written_size());
        Ok(out)
    }

    /// Bytes [`KeptTop::to_bytes`] writes.
    pub fn written_size(&self) -> u64 {
        TOP_HEADER_BYTES + self.spilled_size()
    }

    /// Reads [`KeptTop::to_bytes`]'s output back as a top of a volume of `dims` scored with
    /// `opts`. Everything is checked against what `dims`, `opts` and the geometry imply (the
    /// dimensions the caller's, so that no entry makes it allocate for another size; the
    /// geometry rebuilt from its dimensions, depth and margin; the seen-share tables present
    /// exactly where `opts` pad smoothly and the grid clips; indices within the grid, channels
    /// within the volume's, finite values, totals that agree), so that a damaged or foreign
    /// entry is refused rather than coded.
    pub fn from_bytes(
        bytes: &[u8],
        dims: [usize; 3],
        opts: &CompressOptions,
    ) -> Result<KeptTop, TopBytesError> {
        let bad = |what: &str| TopBytesError(what.to_string());
        let mut r = TopReader(bytes);
        if r.take::<8>()? != *TOP_MAGIC {
            return Err(bad("wrong tag or version"));
        }
        let mut three =
            || -> Result<[usize; 3], TopBytesError> { Ok([r.usize()?, r.usize()?, r.usize()?]) };
        let (stored_dims, padded, origin) = (three()?, three()?, three()?);
        if stored_dims != dims {
            return Err(bad("a top of a volume of another size"));
        }
        let (levels, margin, channels) = (r.usize()?, r.usize()?, r.usize()?);
        let family = Family::from_code(r.u8()?).ok_or_else(|| bad("no such family"))?;
        if family != opts.family {
            return Err(bad("another family than the options'"));
        }
        let spacing = [r.f32()?, r.f32()?, r.f32()?];
        let value_range = [r.f32()?, r.f32()?];
        let geometry = Geometry::new(dims, family, levels, margin)
            .and_then(|g| g.with_spacing(spacing))
            .map_err(|e| TopBytesError(format!("geometry: {e}")))?;
        if geometry.padded != padded || geometry.origin != origin {
            return Err(bad("a grid its dimensions, depth and margin do not give"));
        }
        if !(1..=3).contains(&channels) {
            return Err(bad("channels outside 1..=3"));
        }
        let kind = ColorKind::from_code(r.u8()?).ok_or_else(|| bad("no such colour kind"))?;
        let mut nine = || -> Result<[[f64; 3]; 3], TopBytesError> {
            let mut m = [[0.0; 3]; 3];
            for v in m.as_flattened_mut() {
                *v = r.f64()?;
            }
            Ok(m)
        };
        let basis = nine()?;
        let mut three_f64 =
            || -> Result<[f64; 3], TopBytesError> { Ok([r.f64()?, r.f64()?, r.f64()?]) };
        let (mean, importance) = (three_f64()?, three_f64()?);
        let color = ColorInfo {
            kind,
            basis,
            mean,
            importance,
        };
        let placed = r.flag()?;
        let place_origin = [r.f64()?, r.f64()?, r.f64()?];
        let mut directions = [[0.0; 3]; 3];
        for v in directions.as_flattened_mut() {
            *v = r.f64()?;
        }
        let placement = placed.then_some(Placement {
            origin: place_origin,
            directions,
        });
        let (total_energy, selectable_energy) = (r.f64()?, r.f64()?);
        let (total_coefficients, nonzero) = (r.u64()?, r.u64()?);
        let grid = geometry.coefficient_count();
        if total_coefficients != grid as u64 * channels as u64 || nonzero > total_coefficients {
            return Err(bad("totals that disagree with the grid"));
        }
        let energies_ok = [total_energy, selectable_energy]
            .iter()
            .all(|e| e.is_finite() && *e >= 0.0);
        if !energies_ok {
            return Err(bad("an energy negative or not finite"));
        }
        let visible = r.flag()?;
        if visible != (opts.smooth_padding && geometry.clips_to_box()) {
            return Err(bad(
                "seen shares where the options have none, or none where they do",
            ));
        }
        let complete = r.flag()?;
        let len = r.usize()?;
        let with_channels = r.flag()?;
        if with_channels != (channels > 1) || len as u64 > nonzero {
            return Err(bad("a top of another size or channel count"));
        }
        let per = 8 + usize::from(with_channels);
        if len.checked_mul(per) != Some(r.0.len()) {
            return Err(bad("a length that disagrees with the coefficients"));
        }
        let (pairs, channel_bytes) = r.0.split_at(len * 8);
        let mut top = Vec::with_capacity(len);
        for (index, value) in pairs.chunks_exact(8).map(pair_of) {
            if index as usize >= grid || !value.is_finite() {
                return Err(bad("an index outside the grid or a value not finite"));
            }
            top.push((index, value));
        }
        if channel_bytes.iter().any(|c| usize::from(*c) >= channels) {
            return Err(bad("a channel beyond the volume's"));
        }
        let norms = band_norms(&geometry);
        let prepared = Prepared {
            visible: if visible {
                Visible::new(&geometry)
            } else {
                None
            },
            geometry,
            margin,
            color,
            channels,
            value_range,
            placement,
            band_of: Vec::new(),
            norms,
            coefficients: Vec::new(),
            histogram: Histogram::none(),
            total_energy,
            selectable_energy,
            total_coefficients,
            targets: Vec::new(),
            views: Vec::new(),
            nonzero,
            scratch: Default::default(),
        };
        Ok(KeptTop {
            prepared,
            values: TopValues::Held {
                top,
                channels: channel_bytes.to_vec(),
            },
            complete,
            opts: opts.clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encode::{compress, score_summary, Effort};
    use crate::phantom::Phantom;

    /// Options without refinement: plain, and with the smooth padding and margin of a brick
    /// (a bridged grid, whose scores take the seen share).
    fn fast(v: &Volume, bridged: bool) -> CompressOptions {
        CompressOptions {
            smooth_padding: bridged,
            margin: bridged.then_some(4),
            levels: (v.dims().iter().min() >= Some(&8)).then_some(2),
            refine: None,
            ..Effort::Fast.options()
        }
    }

    /// Every count within the kept top gives the file `compress` writes for it, byte for byte,
    /// on scalar and colour volumes, flat and bridged grids, odd sizes and empty volumes; the
    /// summary is the one the plain score pass gives.
    #[test]
    fn a_kept_top_codes_the_file_compress_writes() {
        let slab = {
            let head = Phantom::Ct.generate([33, 29, 21]);
            let d = head.dims();
            Volume::new(d, [1.0, 1.0, 2.5], head.into_channels()).unwrap()
        };
        let volumes = [
            Phantom::SheppLogan.generate([40, 36, 30]),
            slab,
            Phantom::RgbHead.generate([24, 20, 17]),
            Phantom::Zero.generate([9, 8, 7]),
            Phantom::Constant(-1000.0).generate([16, 8, 4]),
            Phantom::SheppLogan.generate([1, 1, 1]),
        ];
        for v in &volumes {
            for bridged in [false, true] {
                let opts = fast(v, bridged);
                let cap = 700;
                let (summary, top) = score_keeping_top(v, &opts, cap, &|_, _| {}).unwrap();
                assert_eq!(summary, score_summary(v, &opts, &|_, _| {}).unwrap());
                let top = top.expect("no refinement: a top is kept");
                assert!(top.scored_with(&opts));
                let nonzero = summary.nonzero;
                assert_eq!(top.len() as u64, cap.min(nonzero), "{:?}", v.dims());
                for count in [0, 1, 37, 350, cap, nonzero, nonzero + 5] {
                    if count > cap && nonzero > cap {
                        assert!(!top.covers(count));
                        assert!(top.compress(count).is_err());
                        continue;
                    }
                    let want = compress(
                        v,
                        &CompressOptions {
                            target: Target::Coefficients(count),
                            ..opts.clone()
                        },
                        &|_, _| {},
                    )
                    .unwrap();
                    let got = top.compress(count).unwrap();
                    assert_eq!(got.bytes, want.bytes, "{:?} {bridged} {count}", v.dims());
                    assert_eq!(got.stats.kept, want.stats.kept);
                    assert_eq!(got.stats.q_v.to_bits(), want.stats.q_v.to_bits());
                    assert_eq!(got.stats.q_e.to_bits(), want.stats.q_e.to_bits());
                }
            }
        }
    }

    /// A top moved to a scratch file codes the files it coded in memory, holds only its
    /// metadata in memory, and takes 8 bytes a coefficient on disk (9 with colour); spilling
    /// it again changes nothing.
    #[test]
    fn a_spilled_top_codes_the_files_it_coded_in_memory() {
        let file = Arc::new(ScratchFile::new(None).unwrap());
        for v in [
            Phantom::SheppLogan.generate([40, 36, 30]),
            Phantom::RgbHead.generate([24, 20, 17]),
            Phantom::Zero.generate([9, 8, 7]),
            Phantom::SheppLogan.generate([1, 1, 1]),
        ] {
            let opts = fast(&v, true);
            let (_, top) = score_keeping_top(&v, &opts, 900, &|_, _| {}).unwrap();
            let mut top = top.unwrap();
            let counts = [0, 1, 100, 899, 900].map(|c: u64| c.min(top.len() as u64));
            let held: Vec<Vec<u8>> = counts
                .iter()
                .map(|&c| top.compress(c).unwrap().bytes)
                .collect();
            let (heap, len) = (top.heap_bytes(), top.len());
            let per = if v.channel_count() > 1 { 9 } else { 8 };
            assert_eq!(top.spilled_size(), len as u64 * per);
            let before = file.len();
            top.spill(&file).unwrap();
            assert!(top.is_spilled());
            assert_eq!(file.len() - before, len as u64 * per);
            assert!(
                top.heap_bytes() + len * 8 <= heap,
                "{} of {heap}",
                top.heap_bytes()
            );
            top.spill(&file).unwrap();
            assert_eq!(file.len() - before, len as u64 * per);
            assert_eq!(top.len(), len);
            for (&c, want) in counts.iter().zip(&held) {
                assert_eq!(&top.compress(c).unwrap().bytes, want, "{:?} {c}", v.dims());
            }
            if top.len() == 900 {
                assert!(top.compress(901).is_err());
            }
        }
    }

    /// A top written down and read back codes the files the original codes, byte for byte
    /// (scalar and colour volumes, flat and bridged grids, anisotropic spacing, an empty
    /// volume, one voxel), whether it was held or spilled when written; bytes cut short,
    /// lengthened, with an index outside the grid, or read with other options are refused.
    #[test]
    fn a_top_written_down_reads_back_as_the_same_top() {
        let file = Arc::new(ScratchFile::new(None).unwrap());
        let slab = {
            let head = Phantom::Ct.generate([33, 29, 21]);
            let d = head.dims();
            Volume::new(d, [1.0, 1.0, 2.5], head.into_channels()).unwrap()
        };
        for v in [
            Phantom::SheppLogan.generate([40, 36, 30]),
            slab,
            Phantom::RgbHead.generate([24, 20, 17]),
            Phantom::Zero.generate([9, 8, 7]),
            Phantom::SheppLogan.generate([1, 1, 1]),
        ] {
            for bridged in [false, true] {
                let opts = fast(&v, bridged);
                let (_, top) = score_keeping_top(&v, &opts, 600, &|_, _| {}).unwrap();
                let mut top = top.unwrap();
                let bytes = top.to_bytes().unwrap();
                assert_eq!(bytes.len() as u64, top.written_size());
                let back = KeptTop::from_bytes(&bytes, v.dims(), &opts).unwrap();
                assert_eq!(back.len(), top.len());
                assert_eq!(back.covers(601), top.covers(601));
                assert!(back.scored_with(&opts));
                for c in [0u64, 1, 50, 599, 600, 700] {
                    if !top.covers(c) {
                        assert!(!back.covers(c));
                        continue;
                    }
                    let want = top.compress(c).unwrap();
                    let got = back.compress(c).unwrap();
                    assert_eq!(got.bytes, want.bytes, "{:?} {bridged} {c}", v.dims());
                    assert_eq!(got.stats.q_v.to_bits(), want.stats.q_v.to_bits());
                }
                top.spill(&file).unwrap();
                assert_eq!(top.to_bytes().unwrap(), bytes, "spilled, written the same");

                let refused =
                    |b: &[u8], o: &CompressOptions| KeptTop::from_bytes(b, v.dims(), o).is_err();
                let d = v.dims();
                assert!(KeptTop::from_bytes(&bytes, [d[0] + 1, d[1], d[2]], &opts).is_err());
                let step = (bytes.len() / 97).max(1);
                for cut in (0..bytes.len()).step_by(step) {
                    assert!(refused(&bytes[..cut], &opts), "cut at {cut}");
                }
                let mut longer = bytes.clone();
                longer.push(0);
                assert!(refused(&longer, &opts));
                let other = CompressOptions {
                    smooth_padding: !bridged,
                    ..opts.clone()
                };
                let clips = back.prepared.geometry.clips_to_box();
                assert_eq!(refused(&bytes, &other), clips, "{:?} {bridged}", v.dims());
                let other_family = CompressOptions {
                    family: wavesplat_codec::family::Family::ALL
                        .into_iter()
                        .find(|f| *f != opts.family)
                        .unwrap(),
                    ..opts.clone()
                };
                assert!(refused(&bytes, &other_family));
                if !top.is_empty() {
                    let per = 8 + usize::from(v.channel_count() > 1);
                    let first = bytes.len() - top.len() * per;
                    let mut outside = bytes.clone();
                    outside[first..first + 4].copy_from_slice(&u32::MAX.to_le_bytes());
                    assert!(refused(&outside, &opts));
                    let mut nan = bytes.clone();
                    nan[first + 4..first + 8].copy_from_slice(&f32::NAN.to_bits().to_le_bytes());
                    assert!(refused(&nan, &opts));
                }
                let mut tag = bytes.clone();
                tag[7] = 2;
                assert!(refused(&tag, &opts));
            }
        }
    }

    /// A refining compression keeps nothing (its second pass needs the dense transform), and a
    /// top is not taken for other options.
    #[test]
    fn refinement_keeps_no_top_and_other_options_are_not_served() {
        let v = Phantom::SheppLogan.generate([24, 24, 24]);
        let refining = Effort::Default.options();
        let (_, top) = score_keeping_top(&v, &refining, 100, &|_, _| {}).unwrap();
        assert!(top.is_none());
        let opts = fast(&v, false);
        let (_, top) = score_keeping_top(&v, &opts, 100, &|_, _| {}).unwrap();
        let top = top.unwrap();
        let other_step = CompressOptions {
            step: opts.step * 2.0,
            ..opts.clone()
        };
        assert!(!top.scored_with(&other_step));
        let other_target = CompressOptions {
            target: Target::Bytes(999),
            ..opts.clone()
        };
        assert!(top.scored_with(&other_target));
    }
}
