//! The depth-cue expansion of coefficients into splat pieces (paper §3.2), a planning step of its
//! own. The medium is the data: the cue is cut at the data's light-facing faces (per axis −j/2
//! or n − 1 + j/2, where the order-j spline of the voxels ends), so the cue weight of a basis
//! function is a product of per-axis factors. Along each axis a basis factor lies behind its
//! face (exponential, cued from its support end nearest the light), in front of it (weight 0:
//! no piece) or across it. A coefficient with no factor across a face is one piece with the
//! matching table; one whose support crosses a face along some axes is split there into level-0
//! B-splines (its exact refinement): those wholly behind are ordinary cued factors, those in
//! front are dropped, and the few across the face (one for linear, three for cubic, none for
//! Haar) are cut there ([`AxisFactor::Cut`]). Each piece carries the weight e^(−k·dist) of its
//! support's corner nearest the light (the face itself for a cut factor), so no exponent is
//! positive.

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
    let near_of = |a: usize, lo: f64, hi: f64| if cue.l[a] >= 0.0 { lo } else { hi };
    let weight_of = |near: [f64; 3]| (-cue.k * cue.dist(near).max(0.0)).exp();
    let per: Vec<Vec<(usize, Piece)>> = coefficients
        .par_iter()
        .enumerate()
        .map(|(i, c)| {
            let level = c.band.level as usize;
            let centre = geometry.basis_center(
                c.band,
                [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize],
            );
            let mut choices: [Vec<AxisChoice>; 3] = Default::default();
            for a in 0..3 {
                let wavelet = c.band.is_wavelet_along(a);
                let half = geometry.half_support_1d(level, wavelet);
                let (lo, hi) = (centre[a] - half, centre[a] + half);
                match cue.side(a, lo, hi) {
                    CueSide::Front => return Vec::new(),
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
            let mut out = Vec::with_capacity(choices.iter().map(Vec::len).product());
            for x in &choices[0] {
                for y in &choices[1] {
                    for z in &choices[2] {
                        let value = c.value as f64 * x.2 * y.2 * z.2 * weight_of([x.3, y.3, z.3]);
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
            out
        })
        .collect();
    per.into_iter().flatten().collect()
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
