//! Smooth padding: filling the padding of a grid whose images are clipped to the volume's box
//! ([`Geometry::clips_to_box`]) with a bridge from each line's last voxel round to its first,
//! instead of zeros. The transform is periodic on the padded grid, so zero padding (or none)
//! puts a step wherever structure reaches a face, and a step costs coefficients at every level
//! and leaves its quantization error along the face. The renderer draws only the level-0
//! B-splines centred in the box and the decoder crops to it, so what the padding holds is free
//! to choose: a smooth periodic continuation makes the faces as cheap as the interior. This is
//! what a brick of a bricked volume needs, where every inner face cuts the content.
//!
//! The bridge along one line is the cubic Hermite curve from the last voxel to the first
//! (wrapping), matching both values and both end slopes (each the mean of the last two
//! differences), so the periodic signal is continuous with a continuous first derivative.
//! Axes are bridged one after another: x on the rows inside the box, y on every column of the
//! x-bridged planes inside the box, z on every line, so the whole padding is filled.

use crate::layout::Geometry;

/// Fills the padding of `data` (the padded grid of `geometry`, x fastest) with smooth periodic
/// bridges, axis by axis. Samples inside the box are unchanged. A no-op on an axis without
/// padding.
pub fn bridge_padding(data: &mut [f64], geometry: &Geometry) {
    debug_assert_eq!(data.len(), geometry.padded.iter().product::<usize>());
    for axis in 0..3 {
        let (n, p, o) = (
            geometry.dims[axis],
            geometry.padded[axis],
            geometry.origin[axis],
        );
        if p == n {
            continue;
        }
        let step = axis_stride(geometry, axis);
        let hermite = Hermite::new(p - n);
        // Where the bridge's samples go along the axis: after the box, wrapping round.
        let gap_at: Vec<usize> = (0..p - n).map(|k| ((o + n + k) % p) * step).collect();
        for base in line_starts(geometry, axis) {
            // Only the line's first and last three samples shape its bridge.
            let ends = end_samples(n, |k| data[base + (o + k) * step]);
            for (at, v) in gap_at.iter().zip(hermite.bridge(&ends)) {
                data[base + at] = v;
            }
        }
    }
}

/// The distance in the padded grid (x fastest) between neighbours along `axis`.
fn axis_stride(geometry: &Geometry, axis: usize) -> usize {
    geometry.padded[..axis].iter().product()
}

/// The index of sample 0 along `axis` of every line that axis's bridging fills: over the other
/// two axes, every position of an axis already bridged and the box of one not yet bridged.
fn line_starts(geometry: &Geometry, axis: usize) -> impl Iterator<Item = usize> + '_ {
    let range = move |a: usize| {
        if a < axis {
            0..geometry.padded[a]
        } else {
            geometry.origin[a]..geometry.origin[a] + geometry.dims[a]
        }
    };
    let [b, c] = match axis {
        0 => [1, 2],
        1 => [0, 2],
        _ => [0, 1],
    };
    let (stride_b, stride_c) = (axis_stride(geometry, b), axis_stride(geometry, c));
    range(c).flat_map(move |j| range(b).map(move |i| i * stride_b + j * stride_c))
}

/// A line's first and last samples as [`Hermite::bridge`] reads them: `first[..held]` the
/// first three (fewer when the line is shorter), `last[..held]` the last three, in order.
struct EndSamples {
    first: [f64; 3],
    last: [f64; 3],
    held: usize,
}

/// The end samples of a line of `n ≥ 1` samples read by `at`.
fn end_samples(n: usize, at: impl Fn(usize) -> f64) -> EndSamples {
    let held = n.min(3);
    let mut first = [0.0; 3];
    let mut last = [0.0; 3];
    for k in 0..held {
        first[k] = at(k);
        last[k] = at(n - held + k);
    }
    EndSamples { first, last, held }
}

/// The cubic Hermite weights of a bridge across `gap` samples, computed once per axis: the
/// bridge of every line across that gap is a weighted sum of its two end values and slopes.
struct Hermite {
    span: f64,
    /// Per bridge sample: the weights of the last value, the end slope, the first value and
    /// the start slope.
    weights: Vec<[f64; 4]>,
}

impl Hermite {
    fn new(gap: usize) -> Hermite {
        let span = (gap + 1) as f64;
        let weights = (1..=gap)
            .map(|k| {
                let t = k as f64 / span;
                let (t2, t3) = (t * t, t * t * t);
                [
                    2.0 * t3 - 3.0 * t2 + 1.0,
                    t3 - 2.0 * t2 + t,
                    3.0 * t2 - 2.0 * t3,
                    t3 - t2,
                ]
            })
            .collect();
        Hermite { span, weights }
    }

    /// The bridge from the line's last sample round to its first.
    fn bridge<'a>(&'a self, ends: &EndSamples) -> impl Iterator<Item = f64> + 'a {
        let (tail, head) = (&ends.last[..ends.held], &ends.first[..ends.held]);
        let (last, first) = (tail[ends.held - 1], head[0]);
        // End slopes per voxel: the mean of up to two differences at each end.
        let m0 = mean_difference(tail) * self.span;
        let m1 = mean_difference(head) * self.span;
        self.weights
            .iter()
            .map(move |w| w[0] * last + w[1] * m0 + w[2] * first + w[3] * m1)
    }
}

/// The mean of the successive differences of `samples` (0 for one sample).
fn mean_difference(samples: &[f64]) -> f64 {
    let d = samples.len().saturating_sub(1);
    if d == 0 {
        return 0.0;
    }
    let mut differences = [0.0; 2];
    for k in 0..d {
        differences[k] = samples[k + 1] - samples[k];
    }
    differences[..d].iter().sum::<f64>() / d as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dwt::pad_channel;
    use crate::family::Family;

    /// The `gap` values that follow `line` periodically, from its last sample round to its
    /// first, from the whole line: the formula `bridge_padding` is checked against.
    fn reference_bridge(line: &[f64], gap: usize) -> Vec<f64> {
        let n = line.len();
        let (last, first) = (line[n - 1], line[0]);
        // End slopes per voxel: the mean of up to two differences at each end.
        let slope = |d: &[f64]| {
            if d.is_empty() {
                0.0
            } else {
                d.iter().sum::<f64>() / d.len() as f64
            }
        };
        let tail: Vec<f64> = (n.saturating_sub(3)..n.saturating_sub(1))
            .map(|k| line[k + 1] - line[k])
            .collect();
        let head: Vec<f64> = (0..2.min(n - 1)).map(|k| line[k + 1] - line[k]).collect();
        let span = (gap + 1) as f64;
        let (m0, m1) = (slope(&tail) * span, slope(&head) * span);
        (1..=gap)
            .map(|k| {
                let t = k as f64 / span;
                let (t2, t3) = (t * t, t * t * t);
                (2.0 * t3 - 3.0 * t2 + 1.0) * last
                    + (t3 - 2.0 * t2 + t) * m0
                    + (3.0 * t2 - 2.0 * t3) * first
                    + (t3 - t2) * m1
            })
            .collect()
    }

    /// The bridge of [`Hermite`] from a line's end samples, as `bridge_padding` computes it.
    fn bridge(line: &[f64], gap: usize) -> Vec<f64> {
        let ends = end_samples(line.len(), |k| line[k]);
        Hermite::new(gap).bridge(&ends).collect()
    }

    /// The per-axis weights and end samples give the very bits of the whole-line formula, for
    /// every line length up to beyond the three end samples.
    #[test]
    fn the_bridge_from_end_samples_is_the_line_formula() {
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 * 200.0 - 100.0
        };
        for n in 1..9 {
            for gap in [1, 2, 5, 13] {
                let line: Vec<f64> = (0..n).map(|_| next()).collect();
                let expected = reference_bridge(&line, gap);
                let got = bridge(&line, gap);
                assert_eq!(
                    got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    expected.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    "n {n} gap {gap}"
                );
            }
        }
    }

    /// The padding filled axis by axis as the whole-line formula fills it, each line copied
    /// whole (over the same lines, [`line_starts`]): the reference `bridge_padding` is checked
    /// against bit for bit.
    fn reference_padding(data: &mut [f64], geometry: &Geometry) {
        for axis in 0..3 {
            let (n, p, o) = (
                geometry.dims[axis],
                geometry.padded[axis],
                geometry.origin[axis],
            );
            if p == n {
                continue;
            }
            let step = axis_stride(geometry, axis);
            let starts: Vec<usize> = line_starts(geometry, axis).collect();
            for base in starts {
                let line: Vec<f64> = (0..n).map(|k| data[base + (o + k) * step]).collect();
                for (k, v) in reference_bridge(&line, p - n).into_iter().enumerate() {
                    data[base + ((o + n + k) % p) * step] = v;
                }
            }
        }
    }

    /// On a grid of random samples, odd sizes and a margin, every padded sample is the
    /// reference's, bit for bit.
    #[test]
    fn padding_is_the_line_by_line_reference() {
        for dims in [[7, 5, 6], [4, 6, 3], [2, 2, 9]] {
            let g = Geometry::new(dims, Family::Linear, 1, 3).unwrap();
            let n: usize = dims.iter().product();
            let samples: Vec<f32> = (0..n)
                .map(|i| ((i * 37 % 23) as f32).sin() * 50.0)
                .collect();
            let mut got = pad_channel(&samples, &g);
            let mut expected = got.clone();
            bridge_padding(&mut got, &g);
            reference_padding(&mut expected, &g);
            assert!(
                got.iter()
                    .zip(&expected)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "{dims:?}"
            );
        }
    }

    /// A line's bridge joins its last sample to its first with matching values and slopes,
    /// and a constant line is bridged by the constant.
    #[test]
    fn a_bridge_continues_the_line_smoothly() {
        let line = [3.0, 4.0, 5.0, 6.0, 7.0];
        let b = bridge(&line, 9);
        assert_eq!(b.len(), 9);
        // Value and slope continuous at both ends (within the discretisation).
        assert!((b[0] - 8.0).abs() < 0.5, "{b:?}");
        assert!((b[8] - 2.0).abs() < 0.5, "{b:?}");
        assert!(bridge(&[2.5; 6], 4).iter().all(|v| (v - 2.5).abs() < 1e-12));
        // One voxel: the constant.
        assert!(bridge(&[7.0], 3).iter().all(|v| (v - 7.0).abs() < 1e-12));
    }

    /// The padding is filled everywhere, the box is untouched, and a volume that is constant
    /// stays constant over the whole periodic grid (no step at any face).
    #[test]
    fn padding_is_filled_and_the_box_kept() {
        let dims = [5, 3, 4];
        let g = Geometry::new(dims, Family::Linear, 2, 1).unwrap();
        assert!(g.padded.iter().zip(dims).all(|(p, d)| *p > d));
        let n: usize = dims.iter().product();
        let constant = vec![1.5f32; n];
        let mut data = pad_channel(&constant, &g);
        bridge_padding(&mut data, &g);
        assert!(data.iter().all(|v| (v - 1.5).abs() < 1e-12), "{data:?}");
        let ramp: Vec<f32> = (0..n).map(|i| i as f32).collect();
        let before = pad_channel(&ramp, &g);
        let mut data = before.clone();
        bridge_padding(&mut data, &g);
        assert_eq!(crate::dwt::crop_channel(&data, &g), ramp);
        let zeros = data.iter().filter(|v| **v == 0.0).count();
        assert_eq!(zeros, 1, "only the ramp's first sample is zero");
    }
}
