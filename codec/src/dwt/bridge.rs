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
    let padded = geometry.padded;
    debug_assert_eq!(data.len(), padded.iter().product::<usize>());
    let stride = [1, padded[0], padded[0] * padded[1]];
    let mut line = Vec::new();
    for axis in 0..3 {
        let (n, p, o) = (geometry.dims[axis], padded[axis], geometry.origin[axis]);
        if p == n {
            continue;
        }
        // The other two axes: every position of an axis already bridged, the box of one not
        // yet bridged.
        let range = |a: usize| {
            if a < axis {
                0..padded[a]
            } else {
                geometry.origin[a]..geometry.origin[a] + geometry.dims[a]
            }
        };
        let [b, c] = match axis {
            0 => [1, 2],
            1 => [0, 2],
            _ => [0, 1],
        };
        for j in range(c) {
            for i in range(b) {
                let base = i * stride[b] + j * stride[c];
                line.clear();
                line.extend((0..n).map(|k| data[base + (o + k) * stride[axis]]));
                for (k, v) in bridge(&line, p - n).into_iter().enumerate() {
                    let at = (o + n + k) % p;
                    data[base + at * stride[axis]] = v;
                }
            }
        }
    }
}

/// The `gap` values that follow `line` periodically, from its last sample round to its first.
fn bridge(line: &[f64], gap: usize) -> Vec<f64> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dwt::pad_channel;
    use crate::family::Family;

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
