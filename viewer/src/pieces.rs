//! The expansions of coefficients into splat pieces, a planning step of its own: clipping to the
//! volume's box ([`BoxClip`]), and the depth-cue expansion (paper §3.2, [`expand`]).
//!
//! **Clipping.** The decomposition is periodic on the padded grid. A basis function across a
//! face of the volume's box draws, outside it, what the transform put in the margin; where the
//! padded grid leaves less room around the volume than the coarsest support (a small or zero
//! margin) it reaches the volume with more than one periodic image, and wherever its support
//! leaves the padded grid its tail there stands for a wrapped part on the far side: drawn as
//! one image per coefficient, such functions put errors of about 40 dB into oblique views
//! whatever the margin ([`Geometry::splats_clip_to_box`]). The volume is drawn as what it is:
//! the spline of the level-0 coefficients of the periodic reconstruction that lie in the box.
//! Along each axis every image of a basis function that reaches the box is kept whole when all
//! its level-0 B-splines lie in the box, dropped when none does, and otherwise split by the
//! two-scale relation into φ one level finer, each tested again (coincident pieces merged). Every piece is then a whole φ or ψ at some level: no cut
//! factor is needed, and every piece lies behind the depth cue's planes.
//!
//! **Depth cue (no clipping).** The medium is the data: the cue is cut at the data's light-facing
//! faces (per axis −j/2 or n − 1 + j/2, where the order-j spline of the voxels ends), so the cue
//! weight of a basis function is a product of per-axis factors. Along each axis a basis factor lies
//! behind its face (exponential, cued from its support end nearest the light), in front of it
//! (weight 0: no piece) or across it. A coefficient with no factor across a face is one piece with
//! the matching table; one whose support crosses a face along some axes is split there into level-0
//! B-splines (its exact refinement): those wholly behind are ordinary cued factors, those in front
//! are dropped, and the few across the face (one for linear, three for cubic, none for Haar) are
//! cut there ([`AxisFactor::Cut`]). Each piece carries the weight e^(−k·dist) of its support's
//! corner nearest the light (the face itself for a cut factor), so no exponent is positive.

use crate::footprint::AxisFactor;
use crate::RenderError;
use rayon::prelude::*;
use wavesplat_codec::dwt::unit_basis_line;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::{CueSide, ResolvedCue};

/// One splat piece before placement: factor triple, centre in volume coordinates, weighted
/// value, channel.
#[derive(Debug, Clone, PartialEq)]
pub struct Piece {
    /// The three axis factors (select the footprint table).
    pub factors: [AxisFactor; 3],
    /// Centre in volume coordinates.
    pub centre: [f64; 3],
    /// Coefficient times expansion weights times the cue weight of the near corner.
    pub value: f64,
    /// Channel.
    pub channel: u8,
}

/// The level-0 expansions of every level's φ and ψ for a geometry (what splitting needs).
#[derive(Debug, Clone)]
pub struct Expansions {
    /// Per level: [φ, ψ] as (offset of φ₀'s centre from the basis centre, weight).
    levels: Vec<[Vec<(f64, f64)>; 2]>,
}

impl Expansions {
    /// Expansions for every level of `geometry`.
    pub fn new(geometry: &Geometry) -> Expansions {
        Expansions {
            levels: (0..=geometry.levels)
                .map(|l| {
                    [
                        level0_expansion(geometry, l, false),
                        level0_expansion(geometry, l, true),
                    ]
                })
                .collect(),
        }
    }
}

/// Level-0 expansion of the level-`level` φ (or ψ) with index 0: the B-spline coefficients
/// a_l with b = Σ a_l φ₀(· − l), as (offset of φ₀'s centre from b's centre, a_l) — the
/// synthesis filters applied `level` times to a unit coefficient (no wrap: the line is longer
/// than the support).
fn level0_expansion(geometry: &Geometry, level: usize, wavelet: bool) -> Vec<(f64, f64)> {
    if level == 0 {
        return vec![(0.0, 1.0)];
    }
    let len = (4 * geometry.family.order()) << level;
    let line = unit_basis_line(geometry.family, len, level, wavelet, false);
    let centre = geometry.raw_center_1d(level, 0, wavelet);
    line.iter()
        .enumerate()
        .filter(|(_, v)| **v != 0.0)
        .map(|(i, v)| (i as f64 - centre, *v))
        .collect()
}

/// One choice along one axis: factor, centre, expansion weight, near-light end.
type AxisChoice = (AxisFactor, f64, f64, f64);

/// Expands `coefficients` (already validated) into cued pieces (input order; a coefficient
/// wholly in front of the data gives none).
pub fn expand(
    coefficients: &[Coefficient],
    geometry: &Geometry,
    cue: &ResolvedCue,
    expansions: &Expansions,
) -> Vec<(usize, Piece)> {
    let half0 = 0.5 * geometry.family.phi_support();
    let h0 = half0.round() as i8;
    let near_of = |a: usize, lo: f64, hi: f64| near_end(cue, a, lo, hi);
    let weight_of = |near: [f64; 3]| near_weight(cue, near);
    // In chunks on the pool, each with one output vector and one set of choice vectors
    // (a vector per coefficient and axis made allocation most of the expansion).
    let per: Vec<Vec<(usize, Piece)>> = coefficients
        .par_chunks(EXPAND_CHUNK)
        .enumerate()
        .map(|(chunk_index, chunk)| {
            let mut out = Vec::with_capacity(2 * chunk.len());
            let mut choices: [Vec<AxisChoice>; 3] = Default::default();
            'coefficients: for (j, c) in chunk.iter().enumerate() {
                let i = chunk_index * EXPAND_CHUNK + j;
                let level = c.band.level as usize;
                let centre = geometry.basis_center(
                    c.band,
                    [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize],
                );
                choices.iter_mut().for_each(Vec::clear);
                for a in 0..3 {
                    let wavelet = c.band.is_wavelet_along(a);
                    let half = geometry.half_support_1d(level, wavelet);
                    let (lo, hi) = (centre[a] - half, centre[a] + half);
                    match cue.side(a, lo, hi) {
                        CueSide::Front => continue 'coefficients,
                        CueSide::Behind => {
                            let f = AxisFactor::Basis {
                                level: level as u8,
                                wavelet,
                            };
                            choices[a].push((f, centre[a], 1.0, near_of(a, lo, hi)));
                            continue;
                        }
                        CueSide::Straddle => {}
                    }
                    for (offset, coef) in &expansions.levels[level][wavelet as usize] {
                        let c0 = centre[a] + offset;
                        let (lo0, hi0) = (c0 - half0, c0 + half0);
                        match cue.side(a, lo0, hi0) {
                            CueSide::Front => {}
                            CueSide::Behind => choices[a].push((
                                AxisFactor::Basis {
                                    level: 0,
                                    wavelet: false,
                                },
                                c0,
                                *coef,
                                near_of(a, lo0, hi0),
                            )),
                            CueSide::Straddle => {
                                // The face relative to the φ₀'s centre (an integer: faces sit at
                                // −j/2 and n − 1 + j/2, centres at integers for the splines).
                                let f = (cue.planes[a] - c0).round() as i8;
                                let cut = if cue.l[a] >= 0.0 {
                                    AxisFactor::Cut { a: f, b: h0 }
                                } else {
                                    AxisFactor::Cut { a: -h0, b: f }
                                };
                                choices[a].push((cut, c0, *coef, cue.planes[a]));
                            }
                        }
                    }
                }
                for x in &choices[0] {
                    for y in &choices[1] {
                        for z in &choices[2] {
                            let value =
                                c.value as f64 * x.2 * y.2 * z.2 * weight_of([x.3, y.3, z.3]);
                            if value != 0.0 {
                                out.push((
                                    i,
                                    Piece {
                                        factors: [x.0, y.0, z.0],
                                        centre: [x.1, y.1, z.1],
                                        value,
                                        channel: c.channel,
                                    },
                                ));
                            }
                        }
                    }
                }
            }
            out
        })
        .collect();
    per.concat()
}

/// Coefficients expanded into pieces per task of [`expand`].
const EXPAND_CHUNK: usize = 1024;

/// The end of the support [lo, hi] along axis `a` nearest the light.
fn near_end(cue: &ResolvedCue, a: usize, lo: f64, hi: f64) -> f64 {
    if cue.l[a] >= 0.0 {
        lo
    } else {
        hi
    }
}

/// The cue weight e^(−k·dist) at a piece's corner nearest the light (never above 1).
fn near_weight(cue: &ResolvedCue, near: [f64; 3]) -> f64 {
    (-cue.k * cue.dist(near).max(0.0)).exp()
}

/// How one coefficient is drawn after clipping.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Clipped {
    /// Whole, with its band's table, at this centre (volume coordinates): one image wholly in
    /// the box along every axis, and no cue.
    Whole([f64; 3]),
    /// As pieces (listed separately), or not at all when none reaches the box.
    Split,
}

/// Slack on the box's faces for a level-0 B-spline centre that lies on one (rounding).
const EDGE_EPS: f64 = 1e-9;

/// Whether a function centred at `c` whose level-0 B-spline centres reach `r` either side
/// lies wholly in a box of `n` voxels along an axis (those centres in [0, n − 1]).
fn wholly_inside(c: f64, r: f64, n: f64) -> bool {
    c - r >= -EDGE_EPS && c + r <= n - 1.0 + EDGE_EPS
}

/// One axis entry of a clipped coefficient: φ (or ψ at the coefficient's own level) at a level,
/// centre, weight.
type AxisPiece = (u8, bool, f64, f64);

/// The two-scale relations and supports that clipping to the box needs, for one geometry.
#[derive(Debug, Clone)]
pub struct BoxClip {
    geometry: Geometry,
    /// Per level l ≥ 1 (index l): [φ_l, ψ_l] as (offset of a φ_(l−1) centre from the level-l
    /// centre, weight).
    relations: Vec<[Vec<(f64, f64)>; 2]>,
    /// Per level: [φ, ψ] distance from the centre to the farthest level-0 B-spline of its
    /// expansion.
    reach: Vec<[f64; 2]>,
}

impl BoxClip {
    /// The relations for `geometry`.
    pub fn new(geometry: &Geometry) -> BoxClip {
        let family = geometry.family;
        // The level-1 relation, in level-0 units; level l scales its offsets by 2^(l−1).
        let len = 8 * family.order() + 8;
        let one: [Vec<(f64, f64)>; 2] = [false, true].map(|wavelet| {
            let line = unit_basis_line(family, len, 1, wavelet, false);
            let centre = geometry.raw_center_1d(1, 0, wavelet);
            line.iter()
                .enumerate()
                .filter(|(_, v)| **v != 0.0)
                .map(|(i, v)| (i as f64 - centre, *v))
                .collect()
        });
        let mut relations = vec![[Vec::new(), Vec::new()]];
        let mut reach = vec![[0.0, 0.0]];
        for l in 1..=geometry.levels {
            let s = (1u64 << (l - 1)) as f64;
            let rel = one.clone().map(|taps| {
                taps.into_iter()
                    .map(|(o, w)| (o * s, w))
                    .collect::<Vec<_>>()
            });
            let r = rel
                .clone()
                .map(|taps| taps.iter().fold(0.0f64, |m, (o, _)| m.max(o.abs())) + reach[l - 1][0]);
            relations.push(rel);
            reach.push(r);
        }
        BoxClip {
            geometry: *geometry,
            relations,
            reach,
        }
    }

    /// The pieces along axis `a` of the level-`level` φ or ψ whose raw (unwrapped, padded-grid)
    /// centre is `raw`: every periodic image reaching the box, clipped (merged, non-zero).
    fn axis(&self, a: usize, level: usize, wavelet: bool, raw: f64) -> Vec<AxisPiece> {
        let g = &self.geometry;
        let n = g.dims[a] as f64;
        let period = g.padded[a] as f64;
        let centre = raw - g.origin[a] as f64;
        let r = self.reach[level][wavelet as usize];
        let first = ((-r - centre) / period).floor() as i64;
        let last = ((n - 1.0 + r - centre) / period).ceil() as i64;
        let mut out = Vec::new();
        for m in first..=last {
            self.split(level, wavelet, centre + m as f64 * period, 1.0, n, &mut out);
        }
        out.sort_by(|x, y| (x.0, x.1).cmp(&(y.0, y.1)).then(x.2.total_cmp(&y.2)));
        let mut merged: Vec<AxisPiece> = Vec::with_capacity(out.len());
        for p in out {
            match merged.last_mut() {
                Some(q) if q.0 == p.0 && q.1 == p.1 && (q.2 - p.2).abs() < 1e-9 => q.3 += p.3,
                _ => merged.push(p),
            }
        }
        merged.retain(|p| p.3 != 0.0);
        merged
    }

    /// The centre (volume coordinates) of coefficient `c` when its basis function lies wholly
    /// in the box: its image on the padded grid has every level-0 B-spline of its refinement
    /// in the box along every axis. Then no other image reaches the box (they lie a period,
    /// at least the box's side, away) and it is one whole piece: what [`BoxClip::axes`] finds
    /// for it, without the splitting's lists (most coefficients of a volume lie inside).
    fn inside(&self, c: &Coefficient) -> Option<[f64; 3]> {
        let g = &self.geometry;
        let level = c.band.level as usize;
        let mut centre = [0.0; 3];
        for (a, out) in centre.iter_mut().enumerate() {
            let wavelet = c.band.is_wavelet_along(a);
            let x = g.raw_center_1d(level, c.pos[a] as usize, wavelet) - g.origin[a] as f64;
            if !wholly_inside(x, self.reach[level][wavelet as usize], g.dims[a] as f64) {
                return None;
            }
            *out = x;
        }
        Some(centre)
    }

    /// The pieces of coefficient `c` along each axis.
    fn axes(&self, c: &Coefficient) -> [Vec<AxisPiece>; 3] {
        let level = c.band.level as usize;
        [0, 1, 2].map(|a| {
            let wavelet = c.band.is_wavelet_along(a);
            let raw = self
                .geometry
                .raw_center_1d(level, c.pos[a] as usize, wavelet);
            self.axis(a, level, wavelet, raw)
        })
    }

    fn split(&self, level: usize, wavelet: bool, c: f64, w: f64, n: f64, out: &mut Vec<AxisPiece>) {
        let r = self.reach[level][wavelet as usize];
        if c + r < -EDGE_EPS || c - r > n - 1.0 + EDGE_EPS {
            return;
        }
        if wholly_inside(c, r, n) {
            out.push((level as u8, wavelet, c, w));
            return;
        }
        // Straddles a face (level ≥ 1: a level-0 B-spline is either in or out).
        for (offset, weight) in &self.relations[level][wavelet as usize] {
            self.split(level - 1, false, c + offset, w * weight, n, out);
        }
    }

    /// The summed `weight` of the levels of a coefficient's pieces (each piece weighs as its
    /// coarsest factor, which sets its footprint's size; a coefficient wholly inside the box
    /// weighs `weight(level)`, one wholly outside nothing): what drawing it costs.
    pub fn weigh(&self, c: &Coefficient, weight: impl Fn(u8) -> f64) -> f64 {
        if self.inside(c).is_some() {
            return weight(c.band.level);
        }
        let axes = self.axes(c);
        let mut total = 0.0;
        for x in &axes[0] {
            for y in &axes[1] {
                for z in &axes[2] {
                    total += weight(x.0.max(y.0).max(z.0));
                }
            }
        }
        total
    }

    /// Clips `coefficients` (already validated) to the box: per coefficient whether it is drawn
    /// whole (and where) or as pieces, and the pieces (input order). With a cue every
    /// coefficient becomes pieces, each weighted by the cue at its support's corner nearest the
    /// light (see [`expand`]); all of them lie behind the cue's planes.
    pub fn clip(
        &self,
        coefficients: &[Coefficient],
        cue: Option<&ResolvedCue>,
    ) -> (Vec<Clipped>, Vec<(usize, Piece)>) {
        let g = &self.geometry;
        let per: Vec<(Clipped, Vec<(usize, Piece)>)> = coefficients
            .par_iter()
            .enumerate()
            .map(|(i, c)| {
                if cue.is_none() {
                    if let Some(centre) = self.inside(c) {
                        return (Clipped::Whole(centre), Vec::new());
                    }
                }
                let level = c.band.level as usize;
                let axes = self.axes(c);
                if axes.iter().any(Vec::is_empty) {
                    return (Clipped::Split, Vec::new());
                }
                let whole = |p: &Vec<AxisPiece>, a: usize| {
                    p.len() == 1
                        && p[0].0 as usize == level
                        && p[0].1 == c.band.is_wavelet_along(a)
                        && p[0].3 == 1.0
                };
                if cue.is_none() && (0..3).all(|a| whole(&axes[a], a)) {
                    return (
                        Clipped::Whole([axes[0][0].2, axes[1][0].2, axes[2][0].2]),
                        Vec::new(),
                    );
                }
                let support = |p: &AxisPiece| g.half_support_1d(p.0 as usize, p.1);
                let mut out = Vec::with_capacity(axes.iter().map(Vec::len).product());
                for x in &axes[0] {
                    for y in &axes[1] {
                        for z in &axes[2] {
                            let centre = [x.2, y.2, z.2];
                            let weight = match cue {
                                None => 1.0,
                                Some(cue) => {
                                    let mut near = [0.0; 3];
                                    for (a, p) in [x, y, z].into_iter().enumerate() {
                                        let h = support(p);
                                        near[a] = near_end(cue, a, p.2 - h, p.2 + h);
                                    }
                                    near_weight(cue, near)
                                }
                            };
                            let value = c.value as f64 * x.3 * y.3 * z.3 * weight;
                            if value != 0.0 {
                                out.push((
                                    i,
                                    Piece {
                                        factors: [x, y, z].map(|p| AxisFactor::Basis {
                                            level: p.0,
                                            wavelet: p.1,
                                        }),
                                        centre,
                                        value,
                                        channel: c.channel,
                                    },
                                ));
                            }
                        }
                    }
                }
                (Clipped::Split, out)
            })
            .collect();
        let mut clipped = Vec::with_capacity(per.len());
        let mut pieces = Vec::new();
        for (c, p) in per {
            clipped.push(c);
            pieces.extend(p);
        }
        (clipped, pieces)
    }
}

/// Checks a coefficient addresses an existing band position and channel and is finite.
pub(crate) fn check_coefficient(
    c: &Coefficient,
    geometry: &Geometry,
    channels: usize,
) -> Result<(), RenderError> {
    if c.channel as usize >= channels {
        return Err(RenderError::Channel {
            channel: c.channel,
            channels,
        });
    }
    if geometry.band_index(c.band).is_none() {
        return Err(RenderError::Band(c.band));
    }
    let bd = geometry.band_dims(c.band);
    if (0..3).any(|a| c.pos[a] as usize >= bd[a]) {
        return Err(RenderError::Position {
            band: c.band,
            pos: c.pos,
        });
    }
    if !c.value.is_finite() {
        return Err(RenderError::NotFinite);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use wavesplat_codec::family::Family;

    /// Along one axis, the clipped pieces of every basis function sum to its periodic level-0
    /// expansion (the codec's synthesis, shifted: the transform is shift-invariant) restricted
    /// to the box, and draw nothing outside it: for a box with no margin, one narrower than its
    /// period and one much narrower than the coarsest support.
    #[test]
    fn clipped_pieces_sum_to_the_periodic_expansion_inside_the_box() {
        for family in [Family::Linear, Family::Cubic] {
            for (n, levels) in [(16usize, 3usize), (13, 3), (5, 3), (16, 4)] {
                let g = Geometry::new([n, 16, 16], family, levels, 0).unwrap();
                let clip = BoxClip::new(&g);
                let period = g.padded[0];
                for level in 1..=g.levels {
                    for wavelet in [false, true] {
                        let base = unit_basis_line(family, period, level, wavelet, false);
                        for k in 0..period >> level {
                            let mut want = vec![0.0f64; n];
                            for (i, w) in want.iter_mut().enumerate() {
                                let p = i + g.origin[0];
                                *w = base[(p + period - (k << level) % period) % period];
                            }
                            let mut got = vec![0.0f64; n];
                            let raw = g.raw_center_1d(level, k, wavelet);
                            for (l, wv, c, weight) in clip.axis(0, level, wavelet, raw) {
                                let (l, long) = (l as usize, (64 * family.order()) << level);
                                let line = unit_basis_line(family, long, l, wv, false);
                                let c0 = g.raw_center_1d(l, 0, wv);
                                for (t, v) in line.iter().enumerate().filter(|(_, v)| **v != 0.0) {
                                    let at = c + (t as f64 - c0);
                                    let i = at.round() as i64;
                                    assert!((at - i as f64).abs() < 1e-9);
                                    assert!(
                                        (0..n as i64).contains(&i),
                                        "{family} n={n} l={level} ψ={wavelet} k={k}: tap at {i}"
                                    );
                                    got[i as usize] += weight * v;
                                }
                            }
                            for i in 0..n {
                                assert!(
                                    (got[i] - want[i]).abs() < 1e-12,
                                    "{family} n={n} l={level} ψ={wavelet} k={k} i={i}: {} vs {}",
                                    got[i],
                                    want[i]
                                );
                            }
                        }
                    }
                }
            }
        }
    }
}
