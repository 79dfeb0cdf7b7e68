//! The prepared encoder: from a `Prepared` volume and a number of coefficients to a file — the
//! oracle's top set (or a refined one), layers and tiles, clustering order, quantization and
//! coding — and the error of the X-ray views by which depths are compared; `finish` fills in
//! Q_E of the chosen file.

use super::options::{CompressOptions, CompressStats, Compressed, TileChoice};
use super::prepare::{
    axis_views, choose_tiling, Located, Prepared, PreparedScores, Ranked, Scored,
    COARSE_LAYER_MIN_LEVELS,
};
use crate::order::{cluster_order, Item};
use crate::refine::{refine_with, KeptValue, Output, RefineOptions, Refined};
use crate::select::{pick_order, top_k};
use crate::visible::Visible;
use rayon::prelude::*;
use wavesplat_codec::dwt::fast::FastTransform;
use wavesplat_codec::format::packet::{encode_packets, Coefficient, PacketInput};
use wavesplat_codec::format::{
    magnitude_threshold, write_file, Header, SubstreamParams, COMPACT_HEADER_VERSION, MAX_LAYERS,
};
use wavesplat_codec::metrics::{q_e_percent, q_v_percent};

impl Prepared {
    /// The oracle's score S = E·I of coefficient `i` of channel `c` (−1 for a zero coefficient,
    /// which is never kept).
    pub(super) fn score(&self, c: usize, i: usize) -> f64 {
        let w = self.coefficients[c][i];
        if w == 0.0 {
            return -1.0;
        }
        self.score_in_band(c, i, w, self.band_of[i])
    }

    /// [`Prepared::score`] of a non-zero coefficient `i` of channel `c` whose value `w` and
    /// band index `band` are known.
    #[inline]
    pub(super) fn score_in_band(&self, c: usize, i: usize, w: f32, band: u8) -> f64 {
        self.score_seen(c, w, band, Visible::share(self.visible.as_ref(), i, band))
    }

    /// [`Prepared::score_in_band`] of a coefficient whose seen fraction `seen` is known.
    #[inline]
    pub(super) fn score_seen(&self, c: usize, w: f32, band: u8, seen: f64) -> f64 {
        if seen == 0.0 {
            // Wholly outside the box: never drawn, never decoded.
            return -1.0;
        }
        (w as f64).powi(2) * self.norms[band as usize] * self.color.importance[c] * seen
    }

    /// The band index of coefficient `i`: from the band map, or from the geometry where the
    /// map was dropped ([`super::top::KeptTop`]).
    pub(super) fn band_at(&self, i: usize) -> u8 {
        match self.band_of.get(i) {
            Some(b) => *b,
            None => {
                let g = &self.geometry;
                g.band_index(g.locate(i).0)
                    .expect("a coefficient of the grid") as u8
            }
        }
    }

    /// The energy E = w²·‖b‖² (eq. 14, without importance).
    pub(super) fn energy(&self, c: usize, i: usize) -> f64 {
        (self.coefficients[c][i] as f64).powi(2) * self.norms[self.band_of[i] as usize]
    }

    /// How far a file's three axis X-ray views lie from the volume's: the mean over the views
    /// of ln Σ_c I_c·‖P_v f_c − P_v R ĉ_c‖², with f_c the channel's samples (after the colour
    /// transform or offset; their views are [`Prepared::views`]), ĉ_c the file's decoded
    /// coefficients, R the synthesis to samples, P_v the sum along axis v over the volume's box
    /// and I_c the channel's importance. The log-mean follows Q_I, which averages the views in
    /// dB.
    pub(super) fn view_error(&self, file: &Compressed) -> f64 {
        let g = &self.geometry;
        let fast = FastTransform::new(g);
        let [px, py, _] = g.padded;
        let [ox, oy, oz] = g.origin;
        let mut energy = [0.0f64; 3];
        for (c, target) in self.views.iter().enumerate() {
            // The grid goes back to the depth's scratch, for the next channel and this depth's
            // refinement (a fresh one of the MNI volume, 51 MB, costs ~10 ms of page faults).
            let mut r = self.scratch.floats(g.coefficient_count(), 0.0f32);
            for k in file.reconstruction.iter().flatten() {
                if k.channel as usize == c {
                    let pos = [k.pos[0] as usize, k.pos[1] as usize, k.pos[2] as usize];
                    r[g.linear_index(k.band, pos)] = k.value;
                }
            }
            fast.synthesize(&mut r);
            let at = |x: usize, y: usize, z: usize| {
                f64::from(r[(ox + x) + px * ((oy + y) + py * (oz + z))])
            };
            let decoded = axis_views(g.dims, &at);
            let w = self.color.importance[c];
            for ((e, t), d) in energy.iter_mut().zip(target).zip(&decoded) {
                *e += w * t.iter().zip(d).map(|(t, d)| (t - d).powi(2)).sum::<f64>();
            }
            self.scratch.keep_floats([r]);
        }
        energy
            .iter()
            .map(|e| (e + f64::MIN_POSITIVE).ln())
            .sum::<f64>()
            / 3.0
    }

    /// The oracle's top `cap` coefficients (all non-zero ones when `cap` reaches them).
    pub(super) fn ranked(&self, cap: usize) -> Ranked {
        let n = self.geometry.coefficient_count();
        let picks = top_k(
            &self.histogram,
            self.channels,
            n,
            cap,
            &PreparedScores(self),
        );
        let sorted: Vec<Scored> = picks
            .into_par_iter()
            .map(|(score, channel, index)| Scored {
                score,
                channel,
                index,
                value: self.coefficients[channel as usize][index as usize],
            })
            .collect();
        let complete = sorted.len() as u64 >= self.nonzero;
        Ranked::new(sorted, complete, 0)
    }

    /// `ranked` with its top `k` replaced by their least-squares refinement (at most `k`
    /// coefficients, all scoring at least the k-th), followed by up to `extension`
    /// coefficients that would join the refined set next (their values one gradient step from
    /// its fit, see [`Refined::extension`]), then by the rest of `ranked` that scores below
    /// them.
    pub(super) fn refined(
        &self,
        ranked: &Ranked,
        k: usize,
        opts: &RefineOptions,
        extension: usize,
    ) -> Ranked {
        let importance = &self.color.importance[..self.channels];
        let Refined {
            kept, extension, ..
        } = self.refine_top(ranked, k, opts, Output::Set { extension });
        let count = kept.len();
        let scored = |r: &KeptValue| {
            let band = self.band_of[r.index as usize];
            let seen = Visible::share(self.visible.as_ref(), r.index as usize, band);
            Scored {
                score: (r.value as f64).powi(2)
                    * self.norms[band as usize]
                    * importance[r.channel as usize]
                    * seen,
                channel: r.channel,
                index: r.index,
                value: r.value,
            }
        };
        let mut sorted: Vec<Scored> = kept.par_iter().chain(&extension).map(scored).collect();
        // The rest of the oracle's order, without what the refinement picked up (iterative
        // hard thresholding moves coefficients from beyond rank k into the set) and below the
        // last score so far (the order must stay decreasing).
        // A bit per coefficient of every channel: the rest can be most of the grid's
        // non-zero coefficients, and a search per entry in a sorted list of the picks cost
        // 0.5 s on the MNI grid at 5.85 %.
        let n = self.geometry.coefficient_count();
        let mut picked = vec![0u64; (self.channels * n).div_ceil(64)];
        let bit = |channel: u8, index: u32| channel as usize * n + index as usize;
        for r in &sorted {
            let b = bit(r.channel, r.index);
            picked[b / 64] |= 1 << (b % 64);
        }
        let floor = sorted.last().map_or(f64::INFINITY, |s| s.score);
        sorted.extend(ranked.sorted[k..].iter().filter(|s| {
            let b = bit(s.channel, s.index);
            s.score <= floor && picked[b / 64] & (1 << (b % 64)) == 0
        }));
        Ranked::new(sorted, ranked.complete, count)
    }

    /// How many of the top `k` of `ranked` reach the k-th score after one refit
    /// ([`Output::Pilot`]).
    pub(super) fn pilot(&self, ranked: &Ranked, k: usize, opts: &RefineOptions) -> usize {
        self.refine_top(ranked, k, opts, Output::Pilot)
            .first_survivors
    }

    /// [`refine_with`] on the top `k` of `ranked`, against this volume's padded targets.
    fn refine_top(
        &self,
        ranked: &Ranked,
        k: usize,
        opts: &RefineOptions,
        output: Output,
    ) -> Refined {
        refine_with(
            &self.geometry,
            &self.band_of,
            self.visible.as_ref(),
            &self.targets,
            &self.color.importance[..self.channels],
            &ranked.top_values(k),
            opts,
            output,
            &self.scratch,
        )
    }

    /// Encodes the top `k` coefficients of `ranked`. Q_E is left at NaN unless `q_e` is set
    /// (it pairs every kept value with its decoded one, which a rate-search trial skips).
    pub(super) fn encode(
        &self,
        ranked: &Ranked,
        k: usize,
        opts: &CompressOptions,
        expected_bytes: u64,
        q_e: bool,
    ) -> Compressed {
        let g = &self.geometry;
        // The kept set is chosen by what is seen (where `visible` applies), but the coder's
        // layers and magnitude chains need the plain score order w²·‖b‖²·I, in which a
        // substream's magnitudes never grow: re-score and re-sort the set for coding.
        let plain: Vec<Scored>;
        let kept = match &self.visible {
            None => &ranked.sorted[..k],
            Some(_) => {
                let importance = &self.color.importance;
                let mut v: Vec<Scored> = ranked.sorted[..k]
                    .par_iter()
                    .map(|s| Scored {
                        score: (s.value as f64).powi(2)
                            * self.norms[self.band_at(s.index as usize) as usize]
                            * importance[s.channel as usize],
                        ..*s
                    })
                    .collect();
                v.par_sort_unstable_by(|a, b| {
                    pick_order(
                        &(a.score, a.channel, a.index),
                        &(b.score, b.channel, b.index),
                    )
                });
                plain = v;
                &plain[..]
            }
        };
        let (tile, nl) = choose_tiling(g, opts.tile, opts.layers, expected_bytes);
        let tiles: usize = g.padded.iter().map(|p| p.div_ceil(tile)).product();
        let coarse_layer = opts.coarse_layer
            && g.levels >= COARSE_LAYER_MIN_LEVELS
            && tiles >= 2
            && !matches!(opts.tile, TileChoice::Single);
        // The score layers (after the coarse layer, when there is one).
        let nl = nl.clamp(1, MAX_LAYERS - usize::from(coarse_layer));
        let first_score_layer = usize::from(coarse_layer);
        // Band and position of every kept coefficient: kept with the ranking, whose prefixes
        // a rate search codes many times, unless the set was re-sorted above.
        let resorted: Vec<Located>;
        let cached;
        let located: &[Located] = match &self.visible {
            None => {
                cached = ranked.located(g, k);
                &cached[..k]
            }
            Some(_) => {
                resorted = kept
                    .par_iter()
                    .map(|s| {
                        let (band, pos) = g.locate(s.index as usize);
                        (band, pos.map(|p| p as u32))
                    })
                    .collect();
                &resorted
            }
        };
        let in_coarse_layer = |i: usize| coarse_layer && located[i].0.kind == 0;
        // What the score layers split: the kept coefficients outside the coarse layer, in
        // significance order.
        let ranked_rest: Vec<&Scored> = kept
            .iter()
            .enumerate()
            .filter(|(i, _)| !in_coarse_layer(*i))
            .map(|(_, s)| s)
            .collect();
        let kr = ranked_rest.len();
        // Score layer l ends at rank k·G^(l−(L−1)) with G the layer growth: layer 0 holds the
        // top k/G^(L−1).
        let mut ends = Vec::with_capacity(nl);
        for l in 0..nl {
            let frac = opts.layer_growth.powi(l as i32 - (nl as i32 - 1));
            ends.push(((kr as f64 * frac).ceil() as usize).clamp(1.min(kr), kr));
        }
        let mut layer_bounds = vec![f64::INFINITY; first_score_layer];
        let mut start = 0usize;
        for (l, end) in ends.iter().enumerate() {
            let bound = if l == 0 || start >= kr {
                f64::INFINITY
            } else {
                ranked_rest[start].score
            };
            layer_bounds.push(bound.min(layer_bounds.last().copied().unwrap_or(f64::INFINITY)));
            start = (*end).max(start);
        }
        let nb = g.band_count();
        let nsub = self.channels * nb;
        // Substream parameters: w0 = largest magnitude (a substream's first: its magnitudes
        // never grow in score order), Δ from the threshold or from the sorted magnitudes (eq.
        // 15); a threshold coder needs no more than the first of each.
        let mut mags: Vec<Vec<f64>> = vec![Vec::new(); nsub];
        let first_only = opts.coder.quantizes_by_threshold();
        for (s, &(band, _)) in kept.iter().zip(located) {
            let sub = s.channel as usize * nb + g.band_index(band).expect("band");
            if !first_only || mags[sub].is_empty() {
                mags[sub].push((s.value as f64).abs());
            }
        }
        // Smallest kept score: every kept coefficient's magnitude is at least the threshold.
        let score_threshold = kept.last().map_or(0.0, |s| s.score);
        // A selection of every coefficient (no target to fill) has no rate to spare a coarse
        // step for: there the step is also at most 2^−P of the substream's largest magnitude,
        // so that values far above their band's smallest one (a slice's voxels, whose smallest
        // may be a fifth of the largest) keep P bits instead of an error of half the smallest.
        let every = matches!(opts.target, crate::encode::Target::All);
        let substreams: Vec<Option<SubstreamParams>> = mags
            .iter()
            .enumerate()
            .map(|(sub, m)| {
                SubstreamParams::of_magnitudes(m, opts.coder, opts.bits, || {
                    let step =
                        opts.step * magnitude_threshold(g, &self.color, score_threshold, sub);
                    match m.first() {
                        Some(w0) if every => step.min(w0 * 2f64.powi(-i32::from(opts.bits))),
                        _ => step,
                    }
                })
            })
            .collect();
        let mut header = Header {
            geometry: *g,
            margin: self.margin,
            placement: self.placement,
            channels: self.channels,
            color: self.color,
            value_range: self.value_range,
            coder: opts.coder,
            bits: opts.bits,
            tile,
            layer_bounds,
            coarse_layer,
            score_threshold,
            substreams,
            tables: None,
            fast_tables: None,
            total_energy: self.total_energy,
            kept: k as u64,
            version: opts.format_version,
        };
        // From the compact header on, a threshold coder's cap on reconstructions goes in
        // sixteenths of Δ (one byte), or not at all where it changed little.
        if opts.format_version >= COMPACT_HEADER_VERSION && opts.coder.quantizes_by_threshold() {
            for sub in 0..header.substreams.len() {
                let threshold = header.magnitude_threshold(sub);
                if let Some(params) = header.substreams[sub].as_mut() {
                    *params = params.with_coarse_cap(threshold);
                }
            }
        }
        // Group by (layer, tile), keeping significance order inside each group: each kept
        // coefficient's group (layer-major, the packets' order), then a stable counting sort
        // of the ranks by group. A rate search's trials group a million coefficients or more
        // each; pushing them into a map of growing lists took a third of a trial.
        let counts = header.tile_counts();
        let mut group_of: Vec<u32> = located
            .par_iter()
            .map(|&(band, pos)| {
                let l = band.level;
                let t = pos.map(|p| ((p as usize) << l) / tile);
                (t[0] + counts[0] * (t[1] + counts[1] * t[2])) as u32
            })
            .collect();
        let mut members = vec![0usize; (first_score_layer + nl) * tiles + 1];
        let mut score_layer = 0usize;
        let mut rank = 0usize;
        for (i, group) in group_of.iter_mut().enumerate() {
            let layer = if in_coarse_layer(i) {
                0
            } else {
                while rank >= ends[score_layer] {
                    score_layer += 1;
                }
                rank += 1;
                first_score_layer + score_layer
            };
            *group += (layer * tiles) as u32;
            members[*group as usize + 1] += 1;
        }
        for g in 1..members.len() {
            members[g] += members[g - 1];
        }
        // `members[g]..members[g + 1]` of `by_group` are group g's ranks, in order.
        let mut by_group = vec![0usize; kept.len()];
        let mut next = members.clone();
        for (i, &group) in group_of.iter().enumerate() {
            by_group[next[group as usize]] = i;
            next[group as usize] += 1;
        }
        // The sigmap and fast coders code positions as octree maps, so the order inside a
        // packet carries no cost and clustering is skipped.
        let clustering = opts
            .clustering
            .filter(|_| !opts.coder.quantizes_by_threshold());
        let coefficient = |i: usize| {
            let (band, pos) = located[i];
            Coefficient {
                channel: kept[i].channel,
                band,
                pos,
                value: kept[i].value,
            }
        };
        let inputs: Vec<PacketInput> = (0..members.len() - 1)
            .into_par_iter()
            .filter(|&g| members[g + 1] > members[g])
            .map(|g| {
                let ranks = &by_group[members[g]..members[g + 1]];
                let coefficients = match clustering {
                    None => ranks.iter().map(|&i| coefficient(i)).collect(),
                    Some(_) => {
                        let items: Vec<Item> = ranks
                            .iter()
                            .map(|&i| {
                                let (band, pos) = located[i];
                                let l = band.level as u32;
                                Item {
                                    score: kept[i].score,
                                    voxel: pos.map(|p| p << l),
                                }
                            })
                            .collect();
                        cluster_order(&items, clustering)
                            .into_iter()
                            .map(|j| coefficient(ranks[j]))
                            .collect()
                    }
                };
                PacketInput {
                    tile: g % tiles,
                    layer: g / tiles,
                    coefficients,
                }
            })
            .collect();
        let encoded = encode_packets(&mut header, &inputs);
        let bytes = write_file(&header, &encoded.packets);
        let header_bytes = wavesplat_codec::format::write_header_section(&header).len() as u64;
        // Q_E over the kept coefficients (importance-free energies, eq. 20–21). The sigmap coder
        // reorders coefficients within a packet, so pair exact and decoded values by address.
        let key = |c: &Coefficient| {
            let p = [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize];
            (c.channel, g.linear_index(c.band, p))
        };
        let q_e = if q_e {
            let mut exact: Vec<&Coefficient> =
                inputs.iter().flat_map(|i| &i.coefficients).collect();
            let mut decoded: Vec<&Coefficient> = encoded.reconstruction.iter().flatten().collect();
            exact.par_sort_unstable_by_key(|c| key(c));
            decoded.par_sort_unstable_by_key(|c| key(c));
            q_e_percent(
                exact
                    .iter()
                    .zip(&decoded)
                    .map(|(a, b)| (a.value as f64, b.value as f64, g.basis_norm2(a.band))),
            )
        } else {
            f64::NAN
        };
        let kept_energy: f64 = kept
            .iter()
            .map(|s| (s.value as f64).powi(2) * self.norms[self.band_at(s.index as usize) as usize])
            .sum();
        let stats = CompressStats {
            total_coefficients: self.total_coefficients,
            nonzero_coefficients: self.nonzero,
            kept: k as u64,
            q_v: q_v_percent(kept_energy, self.selectable_energy),
            q_e,
            bytes: bytes.len() as u64,
            breakdown: encoded.breakdown,
            header_bytes,
            packets: inputs.len() as u64,
            tile,
            layers: nl + first_score_layer,
            coarse_layer,
            refined: ranked.refined > 0 && k > 0,
        };
        Compressed {
            bytes,
            header,
            stats,
            reconstruction: encoded.reconstruction,
        }
    }
}

/// Fills in Q_E of the chosen file (the rate search skips it).
pub(super) fn finish(prepared: &Prepared, ranked: &Ranked, mut c: Compressed) -> Compressed {
    let k = c.stats.kept as usize;
    let g = &prepared.geometry;
    let key = |channel: u8, band: wavesplat_codec::layout::Band, pos: [u32; 3]| {
        let p = [pos[0] as usize, pos[1] as usize, pos[2] as usize];
        (channel, g.linear_index(band, p) as u32)
    };
    let mut exact: Vec<(u8, u32, f32)> = ranked.sorted[..k]
        .iter()
        .map(|s| (s.channel, s.index, s.value))
        .collect();
    let mut decoded: Vec<((u8, u32), f32)> = c
        .reconstruction
        .iter()
        .flatten()
        .map(|d| (key(d.channel, d.band, d.pos), d.value))
        .collect();
    exact.par_sort_unstable_by_key(|e| (e.0, e.1));
    decoded.par_sort_unstable_by_key(|d| d.0);
    c.stats.q_e = q_e_percent(exact.iter().zip(&decoded).map(|(a, b)| {
        let norm = prepared.norms[prepared.band_of[a.1 as usize] as usize];
        (a.2 as f64, b.1 as f64, norm)
    }));
    c
}

#[cfg(test)]
mod tests {
    use crate::encode::prepare::{code, prepare, PreparedScores};
    use crate::encode::{CompressOptions, Stage};
    use crate::phantom::Phantom;
    use crate::select::Scores;

    /// A run of scores walked over a clipped grid (a brick's smooth padding) is every
    /// coefficient's score by its index, to the bit: from chunk starts inside rows and across
    /// planes, with clipped coefficients among them.
    #[test]
    fn walked_scores_are_the_scores_by_index() {
        let v = Phantom::SheppLogan.generate([21, 14, 9]);
        let opts = CompressOptions {
            levels: Some(2),
            margin: Some(1),
            smooth_padding: true,
            ..CompressOptions::default()
        };
        let none = |_: Stage, _: f64| {};
        let coded = code(&v, &opts, false, &none).unwrap();
        let p = prepare(&v, &opts, &coded, false, &none).unwrap();
        let visible = p.visible.as_ref().expect("the grid is not clipped");
        let n = p.geometry.coefficient_count();
        let row = p.geometry.padded[0];
        let mut clipped = 0;
        for (start, end) in [
            (0, n),
            (row - 3, 5 * row + 2),
            (n / 3, n / 3 + 700),
            (n - 1, n),
        ] {
            let mut next = start;
            PreparedScores(&p).for_each(0, start..end, |i, s| {
                assert_eq!(i, next);
                next += 1;
                let want = p.score(0, i);
                assert_eq!(s.to_bits(), want.to_bits(), "index {i} from {start}");
                clipped += usize::from(visible.fraction(i, p.band_of[i]) < 1.0);
            });
            assert_eq!(next, end);
        }
        assert!(clipped > 0, "nothing clipped");
    }
}
