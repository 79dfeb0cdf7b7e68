//! Coefficients to splat records: each validated, clipped to the box or split into cued pieces,
//! projected to its basis centre and its footprint placed at the nearest phase (with gradient
//! corrections), in parallel chunks; records wholly off the screen are counted and dropped.

use super::{RenderStats, TableKey, ViewPlan};
use crate::backend::{FootprintAtlas, Layout, SplatRecord, TableRef};
use crate::footprint::{AxisFactor, Footprint};
use crate::pieces::{self, check_coefficient, Clipped, Piece};
use crate::RenderError;
use rayon::prelude::*;
use rustc_hash::FxHashSet as HashSet;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::view::multiview_map;

/// Coefficients per parallel planning task.
const CHUNK: usize = 1024;

/// Places a footprint centred at screen (X, Y) with weight `value`: the record at the nearest
/// phase, and with gradient tables the two records correcting the residual (skipped when the
/// residual is exactly zero). Records wholly off the screen are not produced; returns whether
/// any part is on screen.
pub(super) fn place(
    t: &TableRef,
    atlas: &FootprintAtlas,
    scr: [f64; 2],
    value: f32,
    channel: u16,
    view: u16,
    size: (usize, usize),
    out: &mut Vec<SplatRecord>,
) -> bool {
    let (a, x0, dx) = Footprint::place_with_residual(t.s, t.cx, scr[0]);
    let (b, y0, dy) = Footprint::place_with_residual(t.s, t.cy, scr[1]);
    let idx = (b * t.s + a) as u32;
    let phase = (t.first_phase + idx) as usize;
    // The phase keeps a box of its samples (`footprint::TRIM`); its gradient phases the same.
    let [ox, oy] = atlas.origins.get(phase).copied().unwrap_or([0, 0]);
    let x0 = (x0 + ox as i64).clamp(i32::MIN as i64, i32::MAX as i64) as i32;
    let y0 = (y0 + oy as i64).clamp(i32::MIN as i64, i32::MAX as i64) as i32;
    let rect = &atlas.phases[phase];
    let (w, h) = (size.0 as i64, size.1 as i64);
    if rect.cols == 0
        || rect.rows == 0
        || (x0 as i64) >= w
        || (y0 as i64) >= h
        || x0 as i64 + rect.cols as i64 <= 0
        || y0 as i64 + rect.rows as i64 <= 0
    {
        return false;
    }
    let record = |phase: u32, value: f32| SplatRecord {
        x0,
        y0,
        phase,
        value,
        channel,
        view,
    };
    out.push(record(t.first_phase + idx, value));
    if let Some(g) = t.grad_first {
        let ss = (t.s * t.s) as u32;
        if dx != 0.0 {
            out.push(record(g + idx, (value as f64 * dx) as f32));
        }
        if dy != 0.0 {
            out.push(record(g + ss + idx, (value as f64 * dy) as f32));
        }
    }
    true
}

impl ViewPlan {
    /// The accumulation target of this view.
    pub fn layout(&self) -> Layout {
        Layout {
            width: self.spec.view.width,
            height: self.spec.view.height,
            channels: self.channels,
            views: self.cameras.len(),
        }
    }

    /// Appends the records of `coefficients` to `out` (each validated: an invalid coefficient
    /// is an error and nothing is appended); counts what was planned and skipped in `stats` (a
    /// coefficient counts as splatted in a view when any of its pieces reaches the screen).
    pub fn splats(
        &mut self,
        coefficients: &[Coefficient],
        out: &mut Vec<SplatRecord>,
        stats: &mut RenderStats,
    ) -> Result<(), RenderError> {
        for c in coefficients {
            check_coefficient(c, &self.geometry, self.channels)?;
        }
        // Clipped to the box, a coefficient is one splat where it lies wholly inside and pieces
        // elsewhere; unclipped, with a cue every coefficient is split into cued pieces and
        // without one each is one splat at its image nearest the volume centre.
        let (clipped, pieces): (Option<Vec<Clipped>>, Vec<(usize, Piece)>) =
            match (&self.clip, &self.cue, &self.expansions) {
                (Some(b), cue, _) => {
                    let (c, p) = b.clip(coefficients, cue.as_ref());
                    (Some(c), p)
                }
                (None, Some(cue), Some(e)) => {
                    (None, pieces::expand(coefficients, &self.geometry, cue, e))
                }
                _ => (None, Vec::new()),
            };
        let whole = self.cue.is_none();
        let odd = self.geometry.family.psi_is_odd();
        let size = (self.spec.view.width, self.spec.view.height);
        let views = self.cameras.len();
        // Tables of the factor triples that first occur (first-use order: deterministic).
        let triples: Vec<Vec<([AxisFactor; 3], f32)>> = (0..views)
            .map(|k| {
                let (_, permuted) = self.set_of(k);
                pieces
                    .iter()
                    .map(|(_, p)| {
                        if permuted {
                            view_triple(&p.factors, k, odd)
                        } else {
                            (p.factors, 1.0)
                        }
                    })
                    .collect()
            })
            .collect();
        self.deferred.clear();
        self.poll_tables();
        let mut waiting: HashSet<usize> = HashSet::default();
        for (k, view_triples) in triples.iter().enumerate() {
            let (set, _) = self.set_of(k);
            let mut missing: Vec<[AxisFactor; 3]> = Vec::new();
            for (t, _) in view_triples {
                if !self.factor_tables[set].contains_key(t) && !missing.contains(t) {
                    missing.push(*t);
                }
            }
            if missing.is_empty() {
                continue;
            }
            // Tables another plan of the view built are taken as they are.
            let missing = self.take_shared(set, missing);
            if self.builder.is_some() {
                for ((i, _), (t, _)) in pieces.iter().zip(view_triples) {
                    if !self.factor_tables[set].contains_key(t) {
                        waiting.insert(*i);
                    }
                }
            }
            if missing.is_empty() {
                continue;
            }
            match &mut self.builder {
                Some(b) => {
                    // A table another plan asked for first is waited for, not asked for again.
                    let new: Vec<TableKey> = missing
                        .into_iter()
                        .filter(|(t, first)| b.pending.insert((set, *t)) && *first)
                        .map(|(t, _)| (set, t))
                        .collect();
                    // A builder that died (it panicked) leaves its coefficients waiting;
                    // `tables_pending` stays true and the caller sees no progress.
                    if !new.is_empty() {
                        b.asked.extend(new.iter().copied());
                        let _ = b.requests.send(new);
                    }
                }
                None => {
                    let missing: Vec<[AxisFactor; 3]> =
                        missing.into_iter().map(|(t, _)| t).collect();
                    tracing::debug!(
                        set,
                        tables = missing.len(),
                        pieces = pieces.len(),
                        "building factor tables inline"
                    );
                    let built = self.sets[set].factor_footprints(&missing);
                    self.built_inline += missing.len();
                    for (key, f) in missing.iter().zip(built) {
                        self.install_table(set, *key, f);
                    }
                }
            }
        }
        if !waiting.is_empty() {
            self.deferred = waiting.iter().copied().collect();
            self.deferred.sort_unstable();
        }
        stats.coefficients += coefficients.len() - waiting.len();
        if self.builder.is_some() {
            self.stand_ins(coefficients, &waiting, out);
        }
        let atlas = self.atlas();
        let atlas: &FootprintAtlas = &atlas;
        for (k, camera) in self.cameras.iter().enumerate() {
            let (set, permuted) = self.set_of(k);
            let tables = &self.tables[set];
            let clipped = clipped.as_deref();
            let planned: Vec<(Vec<SplatRecord>, usize, usize)> = coefficients
                .par_chunks(CHUNK)
                .enumerate()
                .map(|(ci, chunk)| {
                    let mut out = Vec::with_capacity(chunk.len() * 3);
                    let (mut placed, mut vanished) = (0usize, 0usize);
                    for (j, c) in chunk.iter().enumerate() {
                        let centre = match clipped.map(|cl| cl[ci * CHUNK + j]) {
                            Some(Clipped::Whole(centre)) => centre,
                            Some(Clipped::Split) => continue,
                            None if whole => self.centres.of(c.band, c.pos),
                            None => continue,
                        };
                        let (kind, sign) = if permuted {
                            multiview_map(k, c.band.kind, odd)
                        } else {
                            (c.band.kind, 1.0)
                        };
                        // Every (level, kind) of a checked coefficient has a table unless
                        // its footprint vanishes in this view.
                        let Some(t) = tables[c.band.level as usize * 8 + kind as usize] else {
                            vanished += 1;
                            continue;
                        };
                        let scr = camera.to_screen(centre);
                        let value = c.value * sign;
                        let (channel, view) = (c.channel as u16, k as u16);
                        if place(&t, atlas, scr, value, channel, view, size, &mut out) {
                            placed += 1;
                        }
                    }
                    (out, placed, vanished)
                })
                .collect();
            let (mut placed_here, mut vanished_here) = (0, 0);
            for (records, placed, vanished) in planned {
                out.extend(records);
                placed_here += placed;
                vanished_here += vanished;
            }
            // Split coefficients: placed when any piece is. A coefficient's pieces are
            // consecutive; chunks of pieces are placed on the pool and their records appended
            // in order (the same records in the same order as one pass would make), each
            // chunk counting the coefficients it placed and the first and last of them, so a
            // coefficient whose pieces straddle two chunks counts once.
            let factor_tables = &self.factor_tables[set];
            let waiting = &waiting;
            let placed_pieces: Vec<PlacedPieces> = pieces
                .par_chunks(CHUNK)
                .zip(triples[k].par_chunks(CHUNK))
                .map(|(chunk, chunk_triples)| {
                    let mut records = Vec::with_capacity(chunk.len() * 3);
                    let mut placed = 0usize;
                    let mut ends: Option<(usize, usize)> = None;
                    for ((i, p), (triple, sign)) in chunk.iter().zip(chunk_triples) {
                        // A deferred coefficient is drawn whole later, when all its tables
                        // are here.
                        if waiting.contains(i) {
                            continue;
                        }
                        let t = factor_tables[triple];
                        let scr = camera.to_screen(p.centre);
                        let value = (p.value * *sign as f64) as f32;
                        let on = place(
                            &t,
                            atlas,
                            scr,
                            value,
                            p.channel as u16,
                            k as u16,
                            size,
                            &mut records,
                        );
                        if on && ends.is_none_or(|(_, last)| *i != last) {
                            placed += 1;
                            ends = Some((ends.map_or(*i, |(first, _)| first), *i));
                        }
                    }
                    (records, placed, ends)
                })
                .collect();
            let mut last = usize::MAX;
            for (records, placed, ends) in placed_pieces {
                out.extend(records);
                if let Some((first, end)) = ends {
                    placed_here += placed - usize::from(first == last);
                    last = end;
                }
            }
            stats.splatted += placed_here;
            stats.vanished += vanished_here;
            stats.skipped += coefficients.len() - waiting.len() - placed_here - vanished_here;
        }
        Ok(())
    }
}

/// The records of a chunk of cued pieces, how many coefficients they placed, and the first and
/// last of those (input indices).
type PlacedPieces = (Vec<SplatRecord>, usize, Option<(usize, usize)>);

/// A piece's factor triple as seen in multiview view `k` through the first view's tables (the
/// triple counterpart of `codec::view::multiview_map`): view 2 takes (y, reflected x, z), view 3
/// (reflected z, y, x); the sign is that of a reflected odd ψ.
fn view_triple(f: &[AxisFactor; 3], k: usize, psi_is_odd: bool) -> ([AxisFactor; 3], f32) {
    match k {
        1 => {
            let (rx, s) = f[0].reflected(psi_is_odd);
            ([f[1], rx, f[2]], s)
        }
        2 => {
            let (rz, s) = f[2].reflected(psi_is_odd);
            ([rz, f[1], f[0]], s)
        }
        _ => (*f, 1.0),
    }
}
