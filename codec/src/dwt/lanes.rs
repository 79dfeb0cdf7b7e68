//! The register-lane weighted row sum the panel kernels share ([`super::fast`]'s filter banks
//! along y and z, [`super::recursive`]'s adjugate FIR): an output row as the sum of a few
//! weighted input rows, a fixed number of samples at a time held in registers and stored once.
//! Hand-written because it is the inner loop of every transform: the fixed-width array
//! accumulators are what lets the compiler keep the sums in vector registers, where one axpy
//! per tap would store and reload the row once per tap.

use std::ops::{AddAssign, Mul};

/// A sample type the kernel sums (f32 or f64).
pub(crate) trait Sample: Copy + Default + Mul<Output = Self> + AddAssign {}
impl Sample for f32 {}
impl Sample for f64 {}

/// dst[i] ← Σ over `terms()` of weight · row[i], for i < dst.len(), each row at least as long
/// as `dst`. The terms are added in the order `terms()` yields them, starting from zero,
/// whatever `dst`'s length: a row gives the same bits in any panel width. `LANES` samples are
/// summed at a time, then the tail one by one. Inlined into each caller, so it is compiled for
/// the caller's target features (the callers are `multiversion`ed).
#[inline(always)]
pub(crate) fn weighted_row_sum<'a, T, I, const LANES: usize>(dst: &mut [T], terms: impl Fn() -> I)
where
    T: Sample + 'a,
    I: Iterator<Item = (&'a [T], T)>,
{
    let width = dst.len();
    let mut x = 0;
    while x + LANES <= width {
        let mut acc = [T::default(); LANES];
        for (row, weight) in terms() {
            let from: &[T; LANES] = row[x..x + LANES]
                .try_into()
                .expect("a slice of LANES samples");
            for (a, v) in acc.iter_mut().zip(from) {
                *a += weight * *v;
            }
        }
        dst[x..x + LANES].copy_from_slice(&acc);
        x += LANES;
    }
    for (i, d) in dst.iter_mut().enumerate().skip(x) {
        let mut a = T::default();
        for (row, weight) in terms() {
            a += weight * row[i];
        }
        *d = a;
    }
}
