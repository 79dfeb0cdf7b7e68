//! Single-precision synthesis, its transpose and the spline sampling FIR, for the compressor's
//! least-squares refinement (dozens of applications per compression) and for full decodes.
//!
//! Each 1D step is a periodic filter bank. Along y and z it is a list of (output row, input
//! row, weight) taps for one line length ([`Taps`]), applied to *panels*: all the x samples of
//! a row of the block move together, so the inner loop is an axpy over contiguous x (vectorized
//! by the compiler), and no copy of the whole array is ever made. Along x, where a line is one
//! contiguous row, the same banks run in polyphase form ([`LineBank`]): short convolutions of
//! each half of the line with the even and odd taps, over a halo holding the periodic wrap.
//! Along z, each panel (the z rows of one or two y rows, one plane apart) is gathered into a
//! per-thread buffer, filtered and written straight back. Memory traffic is about one read and one write of the
//! block per axis, less where consecutive in-plane steps share a sweep (a level's x and y
//! passes, the sampling after the finest level, and the caller's step between a synthesis and
//! its adjoint in [`FastTransform::normal_with`]); the extra memory is a few rows and one z
//! panel per thread.
//!
//! The f64 routines of [`super`] stay the reference: tests compare both. Results do not depend
//! on the thread count (each line is computed the same way whatever thread runs it).

use super::lanes::weighted_row_sum;
use super::{for_each_chunk, interpolation_taps};
use crate::family::Family;
use crate::layout::Geometry;
use multiversion::multiversion;
use std::collections::HashMap;

/// A periodic filter bank for one line length: `out[dst] += weight · in[src]` for every entry.
#[derive(Debug, Clone)]
struct Taps {
    /// (dst, src, weight), sorted by dst.
    list: Vec<(u32, u32, f32)>,
    /// Per output row: the row and the range of its taps in `list`.
    rows: Vec<(usize, std::ops::Range<usize>)>,
}

/// y rows that one z panel takes together where they are contiguous (a whole-row block).
const Z_ROWS: usize = 2;

/// Samples of an output row that [`Taps::apply_from`] sums over all its taps at once.
const LANES: usize = 16;

impl Taps {
    /// Synthesis c0[(2k + i) mod n] += c1[k] p[i] + d1[k] q[i].
    fn synthesis(p: &[f64], q: &[f64], n: usize) -> Taps {
        let h = n / 2;
        let mut list = Vec::with_capacity(h * (p.len() + q.len()));
        for k in 0..h {
            for (i, w) in p.iter().enumerate() {
                list.push((((2 * k + i) % n) as u32, k as u32, *w as f32));
            }
            for (i, w) in q.iter().enumerate() {
                list.push((((2 * k + i) % n) as u32, (h + k) as u32, *w as f32));
            }
        }
        Taps::sorted(list)
    }

    /// Transpose of the synthesis: c1[k] = Σ_i c0[(2k + i) mod n] p[i], d1[k] likewise with q.
    fn adjoint(p: &[f64], q: &[f64], n: usize) -> Taps {
        let h = n / 2;
        let mut list = Vec::with_capacity(h * (p.len() + q.len()));
        for k in 0..h {
            for (i, w) in p.iter().enumerate() {
                list.push((k as u32, ((2 * k + i) % n) as u32, *w as f32));
            }
            for (i, w) in q.iter().enumerate() {
                list.push(((h + k) as u32, ((2 * k + i) % n) as u32, *w as f32));
            }
        }
        Taps::sorted(list)
    }

    /// Circular convolution with centred `taps` (the spline sampling FIR; symmetric).
    fn sampling(taps: &[f64], n: usize) -> Taps {
        let r = (taps.len() / 2) as i64;
        let mut list = Vec::with_capacity(n * taps.len());
        for t in 0..n as i64 {
            for (j, w) in taps.iter().enumerate() {
                let src = (t + j as i64 - r).rem_euclid(n as i64);
                list.push((t as u32, src as u32, *w as f32));
            }
        }
        Taps::sorted(list)
    }

    fn sorted(mut list: Vec<(u32, u32, f32)>) -> Taps {
        list.sort_by_key(|(d, s, _)| (*d, *s));
        let mut rows: Vec<(usize, std::ops::Range<usize>)> = Vec::new();
        for (i, (d, _, _)) in list.iter().enumerate() {
            match rows.last_mut() {
                Some((row, range)) if *row == *d as usize => range.end = i + 1,
                _ => rows.push((*d as usize, i..i + 1)),
            }
        }
        Taps { list, rows }
    }

    /// Applies the bank to a panel: `n` rows of `width` samples, row t at `data[t·stride..]`;
    /// `out` is scratch.
    fn apply(&self, data: &mut [f32], n: usize, width: usize, stride: usize, out: &mut Vec<f32>) {
        // Every output row is written by its first tap, so stale contents need no clearing.
        out.resize(n * width, 0.0);
        self.apply_from(|t| &data[t * stride..], width, out);
        for t in 0..n {
            data[t * stride..t * stride + width].copy_from_slice(&out[t * width..(t + 1) * width]);
        }
    }

    /// The bank from a panel whose row t starts at `row(t)` (at least `width` samples) into
    /// the contiguous rows of `out` (`width` samples per output row). Each output row is
    /// summed over all its taps [`LANES`] samples at a time in registers, then stored once
    /// (every row has a tap). The taps are added in list order starting from zero, so the
    /// sums are the same as one axpy per tap.
    fn apply_from<'a>(&self, row: impl Fn(usize) -> &'a [f32], width: usize, out: &mut [f32]) {
        apply_taps(&self.rows, &self.list, row, width, out);
    }
}

/// [`Taps::apply_from`]'s loop, a free function so that it can be compiled per target (see
/// [`filter2`]).
#[multiversion(targets("x86_64+avx2"))]
fn apply_taps<'a>(
    rows: &[(usize, std::ops::Range<usize>)],
    list: &[(u32, u32, f32)],
    row: impl Fn(usize) -> &'a [f32],
    width: usize,
    out: &mut [f32],
) {
    for (dst_row, range) in rows {
        let taps = &list[range.clone()];
        let dst = &mut out[dst_row * width..(dst_row + 1) * width];
        weighted_row_sum::<_, _, LANES>(dst, || taps.iter().map(|&(_, s, w)| (row(s as usize), w)));
    }
}

/// The x-axis kernels: the same filter banks as [`Taps`] for one contiguous line, in polyphase
/// form. A synthesis output c0[2m + e] is a short convolution of c1 and of d1 with the phase
/// e of p and q (p[2t + e], q[2t + e]); an adjoint output c1[k] or d1[k] a short correlation
/// of the even and odd samples of c0 with those phases; the sampling FIR a plain circular
/// convolution. With the periodic wrap copied into a halo before the line, every inner loop
/// is an axpy over contiguous memory that the compiler vectorizes, where the per-output tap
/// list of [`Taps`] would gather one scalar at a time (the x pass was ~30 % of a refinement).
#[derive(Debug, Clone)]
struct LineBank {
    /// p[2t + e] for e = 0, 1.
    p: [Vec<f32>; 2],
    /// q[2t + e] for e = 0, 1.
    q: [Vec<f32>; 2],
    /// Halo of the two-scale banks: the longest phase minus one.
    halo: usize,
    /// The centred sampling FIR (one tap of 1 for Haar and linear).
    sampling: Vec<f32>,
}

/// Per-thread buffers of the line kernels.
#[derive(Debug, Default)]
struct LineBuffers {
    a: Vec<f32>,
    b: Vec<f32>,
    even: Vec<f32>,
    odd: Vec<f32>,
}

/// `ext` ← the periodic extension of `src` from index −`halo` to `src.len() + after` − 1.
fn periodic_extension(ext: &mut Vec<f32>, src: &[f32], halo: usize, after: usize) {
    let h = src.len();
    ext.clear();
    // (i − halo) mod h, kept non-negative by adding a multiple of h.
    ext.extend((0..halo).map(|i| src[(i + h * halo - halo) % h]));
    ext.extend_from_slice(src);
    ext.extend((0..after).map(|i| src[i % h]));
}

/// out[m] ← Σ_t wa[t] · a[base + m − t] + Σ_t wb[t] · b[base + m − t] for m < out.len() (two
/// convolutions summed; `base` ≥ either filter's length − 1), in that order from zero (see
/// [`filter2`]).
fn convolve2(out: &mut [f32], a: &[f32], wa: &[f32], b: &[f32], wb: &[f32], base: usize) {
    filter2(out, [(a, wa), (b, wb)], |m, t| base + m - t);
}

/// out[m] ← Σ_t wa[t] · a[m + t] + Σ_t wb[t] · b[m + t] for m < out.len() (two correlations
/// summed), in that order from zero (see [`filter2`]).
fn correlate2(out: &mut [f32], a: &[f32], wa: &[f32], b: &[f32], wb: &[f32]) {
    filter2(out, [(a, wa), (b, wb)], |m, t| m + t);
}

/// out[m] ← Σ over the two (source, weights) pairs in order, Σ_t w[t] · source[at(m, t)],
/// each output's terms added in that order from zero, [`LANES`] outputs at a time in
/// registers: the same sums as one axpy per tap into a zeroed `out`, with one store per output
/// instead of one per tap. `at(m, t) + i` must be `at(m + i, t)`.
///
/// Compiled twice, for baseline x86-64 (SSE2) and for AVX2, and the CPU's features pick one at
/// run time. Both do the same IEEE operations on every sample in the same order (Rust never
/// fuses a multiply and an add), so the results are the same bit for bit; AVX2 only does eight
/// lanes per instruction instead of four.
#[multiversion(targets("x86_64+avx2"))]
fn filter2(out: &mut [f32], pairs: [(&[f32], &[f32]); 2], at: impl Fn(usize, usize) -> usize) {
    let mut m = 0;
    while m + LANES <= out.len() {
        let mut acc = [0.0f32; LANES];
        for (src, w) in pairs {
            for (t, wt) in w.iter().enumerate() {
                let s: &[f32; LANES] = src[at(m, t)..at(m, t) + LANES]
                    .try_into()
                    .expect("a slice of LANES samples");
                for (x, v) in acc.iter_mut().zip(s) {
                    *x += wt * v;
                }
            }
        }
        out[m..m + LANES].copy_from_slice(&acc);
        m += LANES;
    }
    for (i, o) in out.iter_mut().enumerate().skip(m) {
        let mut x = 0.0f32;
        for (src, w) in pairs {
            for (t, wt) in w.iter().enumerate() {
                x += wt * src[at(i, t)];
            }
        }
        *o = x;
    }
}

impl LineBank {
    fn new(p: &[f64], q: &[f64], sampling: &[f64]) -> LineBank {
        let phase = |f: &[f64], e: usize| -> Vec<f32> {
            f.iter().skip(e).step_by(2).map(|v| *v as f32).collect()
        };
        let p = [phase(p, 0), phase(p, 1)];
        let q = [phase(q, 0), phase(q, 1)];
        let halo = p.iter().chain(&q).map(Vec::len).max().unwrap_or(1).max(1) - 1;
        LineBank {
            p,
            q,
            halo,
            sampling: sampling.iter().map(|v| *v as f32).collect(),
        }
    }

    /// Synthesis of one line in place: [c1 | d1] → c0[(2k + i) mod n] += c1[k] p[i] + d1[k] q[i].
    fn synthesize(&self, line: &mut [f32], s: &mut LineBuffers) {
        let h = line.len() / 2;
        periodic_extension(&mut s.a, &line[..h], self.halo, 0);
        periodic_extension(&mut s.b, &line[h..], self.halo, 0);
        for (e, out) in [&mut s.even, &mut s.odd].into_iter().enumerate() {
            out.resize(h, 0.0);
            convolve2(out, &s.a, &self.p[e], &s.b, &self.q[e], self.halo);
        }
        for (pair, (e, o)) in line.chunks_exact_mut(2).zip(s.even.iter().zip(&s.odd)) {
            pair[0] = *e;
            pair[1] = *o;
        }
    }

    /// Transpose of [`LineBank::synthesize`]: c1[k] = Σ_i c0[(2k + i) mod n] p[i], d1 likewise.
    fn adjoint(&self, line: &mut [f32], s: &mut LineBuffers) {
        let h = line.len() / 2;
        s.even.resize(h, 0.0);
        s.odd.resize(h, 0.0);
        for ((e, o), pair) in s
            .even
            .iter_mut()
            .zip(s.odd.iter_mut())
            .zip(line.chunks_exact(2))
        {
            *e = pair[0];
            *o = pair[1];
        }
        periodic_extension(&mut s.a, &s.even, 0, self.halo);
        periodic_extension(&mut s.b, &s.odd, 0, self.halo);
        let (c1, d1) = line.split_at_mut(h);
        correlate2(c1, &s.a, &self.p[0], &s.b, &self.p[1]);
        correlate2(d1, &s.a, &self.q[0], &s.b, &self.q[1]);
    }

    /// The centred sampling FIR along one line, circularly.
    fn sample(&self, line: &mut [f32], s: &mut LineBuffers) {
        let r = self.sampling.len() / 2;
        periodic_extension(&mut s.a, line, r, r);
        correlate2(line, &s.a, &self.sampling, &[], &[]);
    }

    fn apply(&self, kind: Kind, line: &mut [f32], s: &mut LineBuffers) {
        match kind {
            Kind::Synthesis => self.synthesize(line, s),
            Kind::Adjoint => self.adjoint(line, s),
            Kind::Sampling => self.sample(line, s),
        }
    }
}

/// One pass of a transform over a corner block of the padded grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pass {
    /// A bank along z.
    Z([usize; 3], Kind),
    /// A step within each z plane.
    Plane([usize; 3], PlaneStep),
}

/// A step within one z plane.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum PlaneStep {
    /// A bank along x (0) or y (1).
    Axis(usize, Kind),
    /// The caller's step between a synthesis and its adjoint ([`FastTransform::normal_with`]).
    Between,
}

/// Which filter bank.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Kind {
    Synthesis,
    Adjoint,
    Sampling,
}

/// Filter banks of one family for every line length a geometry needs (build once, reuse).
pub struct FastTransform {
    family: Family,
    geometry: Geometry,
    /// Panel banks for the y and z axes, by kind and line length.
    banks: HashMap<(Kind, usize), Taps>,
    /// Line kernels for the x axis (any length).
    lines: LineBank,
}

impl FastTransform {
    /// Plans the transforms of `geometry`.
    pub fn new(geometry: &Geometry) -> FastTransform {
        let family = geometry.family;
        let (p, q) = (family.scaling_filter(), family.wavelet_filter());
        let taps = interpolation_taps(family);
        let mut banks = HashMap::new();
        for level in 1..=geometry.levels {
            // The x axis runs on `LineBank`, which serves every length.
            for a in 1..3 {
                let n = geometry.padded[a] >> (level - 1);
                banks
                    .entry((Kind::Synthesis, n))
                    .or_insert_with(|| Taps::synthesis(&p, &q, n));
                banks
                    .entry((Kind::Adjoint, n))
                    .or_insert_with(|| Taps::adjoint(&p, &q, n));
            }
        }
        if taps.len() > 1 {
            for a in 1..3 {
                let n = geometry.padded[a];
                banks
                    .entry((Kind::Sampling, n))
                    .or_insert_with(|| Taps::sampling(&taps, n));
            }
        }
        FastTransform {
            family,
            geometry: *geometry,
            banks,
            lines: LineBank::new(&p, &q, &taps),
        }
    }

    /// The geometry this plan is for.
    pub fn geometry(&self) -> &Geometry {
        &self.geometry
    }

    /// Coefficients (Mallat layout) to the padded grid of spline coefficients, in place: the
    /// f32 twin of [`super::inverse_3d`].
    pub fn inverse(&self, data: &mut [f32]) {
        let mut passes = Vec::new();
        self.push_inverse(&mut passes);
        self.run(data, &passes, &|_, _| {});
    }

    /// Transpose of [`FastTransform::inverse`], in place: the f32 twin of
    /// [`super::inverse_3d_adjoint`].
    pub fn inverse_adjoint(&self, data: &mut [f32]) {
        let mut passes = Vec::new();
        self.push_inverse_adjoint(&mut passes);
        self.run(data, &passes, &|_, _| {});
    }

    /// Samples the spline at the voxel centres in place (symmetric, so also its own transpose):
    /// the f32 twin of [`super::coefficients_to_samples`]. No-op for Haar and linear.
    pub fn coefficients_to_samples(&self, data: &mut [f32]) {
        let mut passes = Vec::new();
        self.push_sampling(&mut passes);
        self.run(data, &passes, &|_, _| {});
    }

    /// Synthesis to voxel samples (inverse, then sampling): the operator R of refinement.
    pub fn synthesize(&self, data: &mut [f32]) {
        let mut passes = Vec::new();
        self.push_inverse(&mut passes);
        self.push_sampling(&mut passes);
        self.run(data, &passes, &|_, _| {});
    }

    /// Rᵀ: the transpose of [`FastTransform::synthesize`].
    pub fn synthesize_adjoint(&self, data: &mut [f32]) {
        let mut passes = Vec::new();
        self.push_sampling(&mut passes);
        self.push_inverse_adjoint(&mut passes);
        self.run(data, &passes, &|_, _| {});
    }

    /// Rᵀ h(R x) in place: [`FastTransform::synthesize`], then `between(z, plane)` on every z
    /// plane of the samples (`plane`: the padded grid's plane z, rows of x), then
    /// [`FastTransform::synthesize_adjoint`]. The result is the same, bit for bit, as the three
    /// run one after the other; but the synthesis's last in-plane passes, `between` and the
    /// adjoint's first in-plane passes take each plane in one sweep while it is in the core's
    /// cache, instead of one sweep over the whole array each.
    pub fn normal_with(&self, data: &mut [f32], between: &(dyn Fn(usize, &mut [f32]) + Sync)) {
        let mut passes = Vec::new();
        self.push_inverse(&mut passes);
        self.push_sampling(&mut passes);
        passes.push(Pass::Plane(self.geometry.padded, PlaneStep::Between));
        self.push_sampling(&mut passes);
        self.push_inverse_adjoint(&mut passes);
        self.run(data, &passes, between);
    }

    fn push_inverse(&self, passes: &mut Vec<Pass>) {
        for level in (1..=self.geometry.levels).rev() {
            let block = self.block(level);
            passes.push(Pass::Z(block, Kind::Synthesis));
            passes.push(Pass::Plane(block, PlaneStep::Axis(1, Kind::Synthesis)));
            passes.push(Pass::Plane(block, PlaneStep::Axis(0, Kind::Synthesis)));
        }
    }

    fn push_inverse_adjoint(&self, passes: &mut Vec<Pass>) {
        for level in 1..=self.geometry.levels {
            let block = self.block(level);
            passes.push(Pass::Plane(block, PlaneStep::Axis(0, Kind::Adjoint)));
            passes.push(Pass::Plane(block, PlaneStep::Axis(1, Kind::Adjoint)));
            passes.push(Pass::Z(block, Kind::Adjoint));
        }
    }

    fn push_sampling(&self, passes: &mut Vec<Pass>) {
        if interpolation_taps(self.family).len() == 1 {
            return;
        }
        let full = self.geometry.padded;
        passes.push(Pass::Plane(full, PlaneStep::Axis(0, Kind::Sampling)));
        passes.push(Pass::Plane(full, PlaneStep::Axis(1, Kind::Sampling)));
        passes.push(Pass::Z(full, Kind::Sampling));
    }

    /// Runs `passes` in order; consecutive in-plane steps on the same block share one sweep.
    fn run(&self, data: &mut [f32], passes: &[Pass], between: &(dyn Fn(usize, &mut [f32]) + Sync)) {
        assert_eq!(data.len(), self.geometry.coefficient_count());
        let mut i = 0;
        while i < passes.len() {
            match passes[i] {
                Pass::Z(block, kind) => {
                    self.z_pass(data, block, kind);
                    i += 1;
                }
                Pass::Plane(block, _) => {
                    let mut steps = Vec::new();
                    while let Some(Pass::Plane(b, step)) = passes.get(i) {
                        if *b != block {
                            break;
                        }
                        steps.push(*step);
                        i += 1;
                    }
                    self.slab_pass(data, block, &steps, between);
                }
            }
        }
    }

    fn block(&self, level: usize) -> [usize; 3] {
        let full = self.geometry.padded;
        [0, 1, 2].map(|a| full[a] >> (level - 1))
    }

    /// Applies the in-plane `steps` in order to the corner block `block`, one z slab at a time:
    /// every x and y line lies in one slab, so a slab takes all its steps while it is in the
    /// core's cache (one sweep over the array instead of one per step). Lines along x are
    /// contiguous rows (the line kernels); lines along y are a panel (the bank of their
    /// length); [`PlaneStep::Between`] hands the slab to `between`.
    fn slab_pass(
        &self,
        data: &mut [f32],
        block: [usize; 3],
        steps: &[PlaneStep],
        between: &(dyn Fn(usize, &mut [f32]) + Sync),
    ) {
        let full = self.geometry.padded;
        let plane = full[0] * full[1];
        let slab = |scratch: &mut (Vec<f32>, LineBuffers), z: usize, s: &mut [f32]| {
            for step in steps {
                match *step {
                    PlaneStep::Axis(1, kind) => self.banks[&(kind, block[1])].apply(
                        s,
                        block[1],
                        block[0],
                        full[0],
                        &mut scratch.0,
                    ),
                    PlaneStep::Axis(_, kind) => {
                        for y in 0..block[1] {
                            let line = &mut s[y * full[0]..y * full[0] + block[0]];
                            self.lines.apply(kind, line, &mut scratch.1);
                        }
                    }
                    PlaneStep::Between => between(z, s),
                }
            }
        };
        for_each_chunk(data, plane, block[2], Default::default, slab);
    }

    /// Applies bank `kind` along z to every line of the corner block `block`, in place: the
    /// lines of one y row form a panel (z rows of x samples, one plane apart) that depends on
    /// nothing else, so each panel is filtered from the array into a per-thread buffer (it
    /// stays in the core's cache) and written straight back to the rows it was read from.
    fn z_pass(&self, data: &mut [f32], block: [usize; 3], kind: Kind) {
        let full = self.geometry.padded;
        let n = block[2];
        let taps = &self.banks[&(kind, n)];
        // Where the block spans whole rows, Z_ROWS consecutive y rows are contiguous in every
        // plane and form one wider panel row (longer runs of memory per plane).
        let rows_per_panel = if block[0] == full[0] { Z_ROWS } else { 1 };
        let run = rows_per_panel * full[0];
        let panel_count = block[1].div_ceil(rows_per_panel);
        // Each panel as n disjoint row borrows, one per z plane.
        let mut panels: Vec<Vec<&mut [f32]>> =
            (0..panel_count).map(|_| Vec::with_capacity(n)).collect();
        for slab in data.chunks_mut(full[0] * full[1]).take(n) {
            let rows = slab[..block[1] * full[0]].chunks_mut(run);
            for (panel, row) in panels.iter_mut().zip(rows) {
                // A whole run of rows, or the block's part of one row.
                let width = if rows_per_panel == 1 {
                    block[0]
                } else {
                    row.len()
                };
                panel.push(&mut row[..width]);
            }
        }
        for_each_chunk(
            &mut panels,
            1,
            panel_count,
            <(Vec<f32>, Vec<f32>)>::default,
            |(input, out): &mut (Vec<f32>, Vec<f32>), _, panel| {
                let rows = &mut panel[0];
                let width = rows[0].len();
                // The panel gathered first: row copies stream from memory, where the bank's
                // reads of several rows at once stalled on each first touch.
                input.clear();
                for r in rows.iter() {
                    input.extend_from_slice(r);
                }
                out.resize(n * width, 0.0);
                taps.apply_from(|t| &input[t * width..], width, out);
                for (r, o) in rows.iter_mut().zip(out.chunks_exact(width)) {
                    r.copy_from_slice(o);
                }
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dwt::{coefficients_to_samples, inverse_3d, inverse_3d_adjoint, Dwt1d};
    use rand::{Rng, SeedableRng};

    fn rel_l2(a: &[f32], b: &[f64]) -> f64 {
        let num: f64 = a.iter().zip(b).map(|(x, y)| (*x as f64 - y).powi(2)).sum();
        let den: f64 = b.iter().map(|y| y * y).sum::<f64>().max(1e-300);
        (num / den).sqrt()
    }

    /// The f32 panels agree with the f64 line-by-line reference, on odd, thin and non-cubic
    /// grids and every depth, including lines of length 2 (taps wrapping several times).
    #[test]
    fn f32_transforms_match_the_f64_reference() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
        for fam in Family::ALL {
            for dims in [
                [1usize, 1, 9],
                [5, 6, 7],
                [16, 9, 12],
                [3, 17, 4],
                [20, 2, 33],
            ] {
                for levels in 0..=Geometry::max_levels(dims).min(3) {
                    let g = Geometry::new(dims, fam, levels, 1).unwrap();
                    let n = g.coefficient_count();
                    let c: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
                    let fast = FastTransform::new(&g);
                    let mut planner = Dwt1d::new(fam);

                    let mut want = c.clone();
                    inverse_3d(&mut want, &g, &mut planner);
                    coefficients_to_samples(&mut want, &g);
                    let mut got: Vec<f32> = c.iter().map(|v| *v as f32).collect();
                    fast.synthesize(&mut got);
                    let e = rel_l2(&got, &want);
                    assert!(e < 1e-6, "{fam} {dims:?} M={levels}: synthesis {e}");

                    let mut want = c.clone();
                    coefficients_to_samples(&mut want, &g);
                    inverse_3d_adjoint(&mut want, &g, &planner);
                    let mut got: Vec<f32> = c.iter().map(|v| *v as f32).collect();
                    fast.synthesize_adjoint(&mut got);
                    let e = rel_l2(&got, &want);
                    assert!(e < 1e-6, "{fam} {dims:?} M={levels}: adjoint {e}");
                }
            }
        }
    }

    /// The fused normal operator is the synthesis, the step between and the adjoint run one
    /// after the other, bit for bit, for every family, thin and odd grids and every depth
    /// (including none, where only the sampling or nothing surrounds the step).
    #[test]
    fn normal_with_equals_the_three_passes_bit_for_bit() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(29);
        for fam in Family::ALL {
            for dims in [[1usize, 1, 9], [5, 6, 7], [16, 9, 12], [20, 2, 33]] {
                for levels in 0..=Geometry::max_levels(dims).min(3) {
                    let g = Geometry::new(dims, fam, levels, 1).unwrap();
                    let n = g.coefficient_count();
                    let plane = g.padded[0] * g.padded[1];
                    let x: Vec<f32> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
                    let f: Vec<f32> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
                    let fast = FastTransform::new(&g);
                    // A step that depends on the plane and the position within it.
                    let step = |z: usize, r: &mut [f32]| {
                        for (i, v) in r.iter_mut().enumerate() {
                            *v = if (i + z).is_multiple_of(3) {
                                0.0
                            } else {
                                f[z * plane + i] - *v
                            };
                        }
                    };
                    let mut want = x.clone();
                    fast.synthesize(&mut want);
                    want.chunks_mut(plane)
                        .enumerate()
                        .for_each(|(z, r)| step(z, r));
                    fast.synthesize_adjoint(&mut want);
                    let mut got = x.clone();
                    fast.normal_with(&mut got, &step);
                    let same = got
                        .iter()
                        .zip(&want)
                        .all(|(a, b)| a.to_bits() == b.to_bits());
                    assert!(same, "{fam} {dims:?} M={levels}");
                }
            }
        }
    }

    /// The kernels (whichever clone the CPU picks, AVX2 on most machines) give the same bits
    /// as plain loops that add the same terms in the same order, one sample at a time.
    #[test]
    fn kernels_equal_plain_loops_bit_for_bit() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(41);
        let mut random =
            |n: usize| -> Vec<f32> { (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect() };
        for len in [1usize, 7, 16, 33, 112, 130] {
            let (wa, wb) = (random(5), random(3));
            let (a, b) = (random(len + 8), random(len + 8));
            let base = 4;
            let mut got = vec![0.0f32; len];
            convolve2(&mut got, &a, &wa, &b, &wb, base);
            let want: Vec<f32> = (0..len)
                .map(|m| {
                    let mut x = 0.0f32;
                    for (t, w) in wa.iter().enumerate() {
                        x += w * a[base + m - t];
                    }
                    for (t, w) in wb.iter().enumerate() {
                        x += w * b[base + m - t];
                    }
                    x
                })
                .collect();
            assert!(
                got.iter()
                    .zip(&want)
                    .all(|(g, w)| g.to_bits() == w.to_bits()),
                "convolve {len}"
            );
            correlate2(&mut got, &a, &wa, &b, &wb);
            let want: Vec<f32> = (0..len)
                .map(|m| {
                    let mut x = 0.0f32;
                    for (t, w) in wa.iter().enumerate() {
                        x += w * a[m + t];
                    }
                    for (t, w) in wb.iter().enumerate() {
                        x += w * b[m + t];
                    }
                    x
                })
                .collect();
            assert!(
                got.iter()
                    .zip(&want)
                    .all(|(g, w)| g.to_bits() == w.to_bits()),
                "correlate {len}"
            );
            // A panel bank: 6 rows of `len` samples at stride len + 3.
            let (p, q) = (random(3), random(5));
            let taps = Taps::synthesis(
                &p.iter().map(|v| *v as f64).collect::<Vec<_>>(),
                &q.iter().map(|v| *v as f64).collect::<Vec<_>>(),
                6,
            );
            let stride = len + 3;
            let src = random(6 * stride);
            let mut got = vec![0.0f32; 6 * len];
            taps.apply_from(|t| &src[t * stride..], len, &mut got);
            let mut want = vec![0.0f32; 6 * len];
            for (row, range) in &taps.rows {
                for x in 0..len {
                    let mut acc = 0.0f32;
                    for &(_, s, w) in &taps.list[range.clone()] {
                        acc += w * src[s as usize * stride + x];
                    }
                    want[row * len + x] = acc;
                }
            }
            assert!(
                got.iter()
                    .zip(&want)
                    .all(|(g, w)| g.to_bits() == w.to_bits()),
                "taps {len}"
            );
        }
    }
}
