//! The significance-map coder ([`super::CoderKind::Sigmap`]), our improvement over the paper's
//! position-delta syntax: instead of coding each coefficient's position as a delta from the
//! previous one, a packet codes, per substream (channel, band), *which* cells of the tile's band
//! region hold a coefficient, by octree set partitioning with adaptive binary contexts (as in
//! SPECK-style wavelet coders), and each coefficient's magnitude as a uniform quantization step
//! above the layer's lower magnitude bound. Everything resets per packet, so packets stay
//! self-contained; coefficients come out in octree order (order within a packet carries no
//! meaning: the packet is the unit of progression).
//!
//! Per packet: for each substream that has parameters in the header, one adaptive "present" bit;
//! for a present substream, the octree over its tile-local band region: the dyadic octree of the
//! region's power-of-two bounding cube with the parts outside the region left out (so boxes
//! stay aligned whatever the region's size), and every child gets an adaptive "occupied" bit
//! (context: band, log2 of the child's size, whether the same cells hold a coefficient in the
//! parent band (same type, one level coarser) and in the cousin bands (earlier types of the
//! same level), as coded earlier in this packet, and, for small boxes, how many coded cells of
//! the same band touch its lower faces, weighted by magnitude class for a single cell from
//! version 6), except a last child implied occupied by its empty
//! siblings. A leaf is a coefficient: sign (adaptive, context: band and the signs of its three
//! lower neighbours) then q (adaptive exp-Golomb, context: band and the magnitude classes of
//! its three lower neighbours, from format version 6; band only before), reconstructed as
//! min(lb + (q + ½)·Δ, ub), where lb and ub are the layer's magnitude bounds of the substream
//! and Δ its step (exact f32 bits when Δ = 0).
//!
//! Format version 3 added the dyadic split, the sign contexts and the face contexts; they cut
//! the file by ~12 % at equal coefficients on the 128³ MNI volume (1.25 % and 5.85 % points).
//! Version 6 added the magnitude contexts: magnitudes cluster as positions do, so a
//! coefficient whose coded lower neighbours are large tends to be large, and a cell beside
//! large coefficients is likelier to hold one: each magnitude is coded in the context of its
//! lower neighbours' magnitude classes, and a single cell's occupancy weighs its face
//! neighbours by them (−2.0 % and a further −0.75 % of the decode bench's file at equal
//! coefficients; magnitudes take half or more of a file).
//!
//! Its parts: `octree` (the boxes and their children), `contexts` (the adaptive models and the
//! context of every decision), `cells` (the coded cells of the substream being coded and their
//! lower-neighbour contexts), `grid` (the significance of earlier bands: dense grids, a sparse
//! grid, the pyramid of coarser levels), `neighbourhood` (the parent and cousin bands a box is
//! looked up in); this module holds the coder itself.

mod cells;
mod contexts;
mod grid;
mod neighbourhood;
mod octree;
pub mod priors;

use super::coefficient::PacketFraming;
use super::coefficient::{Coefficient, SizeBreakdown};
use super::quant::Quantizer;
use super::{invalid, morton, FormatError, Header};
use crate::entropy::range::{RangeDecoder, RangeEncoder};
use crate::layout::Band;
use cells::magnitude_class;
use contexts::{CellContexts, Models};
use neighbourhood::{Neighbourhood, Relatives};
use octree::{region, Box3};
/// The substreams a packet of `header` codes (those with parameters), in order, as (substream,
/// its band index, whether it is the first coded one of its channel: the neighbourhood
/// restarts there). The encoder and the decoder walk this one sequence.
fn coded_substreams(header: &Header) -> impl Iterator<Item = (usize, usize, bool)> + '_ {
    let nb = header.geometry.band_count();
    let mut last_channel = None;
    (0..header.substream_count())
        .filter(|&sub| header.substreams[sub].is_some())
        .map(move |sub| {
            let channel = sub / nb;
            let starts_channel = last_channel != Some(channel);
            last_channel = Some(channel);
            (sub, sub % nb, starts_channel)
        })
}

/// Encodes one packet's coefficients; returns payload, the decoder's reconstruction (in decode
/// order) and the bit breakdown (model-cost estimates scaled to the payload).
pub(crate) fn encode(
    header: &Header,
    tile: usize,
    layer: usize,
    coefficients: &[Coefficient],
) -> (Vec<u8>, Vec<Coefficient>, SizeBreakdown) {
    let mut enc = RangeEncoder::new();
    let mut m = Models::new(header);
    let bands = header.geometry.bands();
    let mut per_sub: Vec<Vec<&Coefficient>> = vec![Vec::new(); header.substream_count()];
    for c in coefficients {
        per_sub[header.substream_id(c.channel as usize, c.band)].push(c);
    }
    let mut recon = Vec::with_capacity(coefficients.len());
    let mut bd = SizeBreakdown::default();
    let mut hood = Neighbourhood::new(header, tile);
    for (sub, bi, starts_channel) in coded_substreams(header) {
        if starts_channel {
            hood.reset();
        }
        let list = &per_sub[sub];
        let b0 = enc.bits_spent();
        enc.encode_bit(&mut m.present[bi], !list.is_empty());
        bd.tag_bits += enc.bits_spent() - b0;
        if list.is_empty() {
            continue;
        }
        let band = bands[bi];
        let (origin, root) = region(header, tile, band.level, header.geometry.band_dims(band));
        let cells: Vec<[u32; 3]> = list
            .iter()
            .map(|c| [0, 1, 2].map(|a| c.pos[a] - origin[a]))
            .collect();
        let mut pts: Vec<Point> = cells.iter().zip(list).map(|(&p, c)| (p, c.value)).collect();
        morton::sort_by_cell(&mut pts, root.scale.trailing_zeros(), |p| p.0);
        let ctx = Ctx::new(header, layer, (sub, bi), band, origin, &hood);
        m.coded.reset(root.hi);
        encode_box(&mut enc, &mut m, &ctx, root, &pts, &mut recon, &mut bd);
        hood.record(band, origin, &cells);
    }
    priors::record(m.arrays(), &bands);
    let mut payload = enc.finish();
    // Keep the count within what the packet reader accepts for this payload size; the range
    // decoder reads missing bytes as zeros, so the padding decodes as if absent.
    let per_byte = super::coefficient::MAX_COEFFICIENTS_PER_PAYLOAD_BYTE;
    let min_len = coefficients.len().div_ceil(per_byte).saturating_sub(1);
    if payload.len() < min_len {
        payload.resize(min_len, 0);
    }
    (payload, recon, bd)
}

struct Ctx<'a> {
    bi: usize,
    quant: Quantizer,
    origin: [u32; 3],
    channel: u8,
    band: Band,
    relatives: Relatives<'a>,
}

impl<'a> Ctx<'a> {
    /// The context of substream `sub` (band index `bi`, of `band`) in `layer`, its band's
    /// region of the tile starting at `origin`, its relatives taken from `hood`.
    fn new(
        header: &Header,
        layer: usize,
        (sub, bi): (usize, usize),
        band: Band,
        origin: [u32; 3],
        hood: &'a Neighbourhood,
    ) -> Ctx<'a> {
        Ctx {
            bi,
            quant: Quantizer::of(header, sub, layer),
            origin,
            channel: (sub / header.geometry.band_count()) as u8,
            band,
            relatives: hood.relatives(bi, band),
        }
    }
}

/// A point to code: its cell and value.
type Point = ([u32; 3], f32);

/// Where each of box `children`' points lie in `pts` (Morton-sorted points of their parent):
/// child i's are `bounds[i]..bounds[i + 1]`. A split halves the dyadic cube, so a child's
/// lower corner has the split's bit set on each axis where it is the upper half, and so do
/// its points.
fn child_runs(children: &[Box3], pts: &[Point]) -> [usize; 9] {
    let half = children[0].scale;
    let code = |c: [u32; 3]| {
        (0..3)
            .map(|a| usize::from(c[a] & half != 0) << a)
            .sum::<usize>()
    };
    let mut bounds = [0usize; 9];
    for (i, child) in children.iter().enumerate() {
        let mine = code(child.lo);
        let start = bounds[i];
        bounds[i + 1] = start + pts[start..].partition_point(|p| code(p.0) <= mine);
    }
    bounds
}

/// Codes the points of box `b`, in Morton order ([`morton::sort_by_cell`]).
fn encode_box(
    enc: &mut RangeEncoder,
    m: &mut Models,
    ctx: &Ctx,
    b: Box3,
    pts: &[Point],
    recon: &mut Vec<Coefficient>,
    bd: &mut SizeBreakdown,
) {
    if b.cells() == 1 {
        let cell = m.cell_contexts(ctx.bi, b.lo);
        encode_leaf(enc, m, ctx, pts[0], cell, recon, bd);
        return;
    }
    let (children, n) = b.children();
    let children = &children[..n];
    let bounds = child_runs(children, pts);
    debug_assert_eq!(bounds[n], pts.len());
    debug_assert!((0..n).all(|i| pts[bounds[i]..bounds[i + 1]]
        .iter()
        .all(|p| children[i].contains(p.0))));
    let mut any_before = false;
    for (i, &child) in children.iter().enumerate() {
        let part = &pts[bounds[i]..bounds[i + 1]];
        let occupied = !part.is_empty();
        let cells = child.cells();
        let single = (cells == 1).then(|| m.cell_contexts(ctx.bi, child.lo));
        // The last child must be occupied if all its siblings are empty: not coded.
        if i + 1 < n || any_before {
            let b0 = enc.bits_spent();
            let states = ctx.relatives.states(ctx.origin, &child);
            let face = match single {
                Some(cell) => cell.face,
                None => m.face_state(&child, cells),
            };
            let oc = m.occupancy_context(ctx.bi, cells, states, face);
            enc.encode_bit(&mut m.occupied[oc], occupied);
            bd.position_bits += enc.bits_spent() - b0;
        }
        any_before |= occupied;
        if occupied {
            match single {
                Some(cell) => encode_leaf(enc, m, ctx, part[0], cell, recon, bd),
                None => encode_box(enc, m, ctx, child, part, recon, bd),
            }
        }
    }
}

/// Codes the coefficient `(p, v)` of a single cell whose contexts are `cell`: its sign, then
/// its quantized magnitude.
fn encode_leaf(
    enc: &mut RangeEncoder,
    m: &mut Models,
    ctx: &Ctx,
    (p, v): ([u32; 3], f32),
    cell: CellContexts,
    recon: &mut Vec<Coefficient>,
    bd: &mut SizeBreakdown,
) {
    let b0 = enc.bits_spent();
    let negative = v < 0.0;
    enc.encode_bit(&mut m.sign[cell.sign], negative);
    let b1 = enc.bits_spent();
    let (q, mag) = ctx.quant.quantize((v as f64).abs());
    m.value[cell.value].encode(enc, q);
    m.coded.insert(p, negative, magnitude_class(q));
    bd.sign_bits += b1 - b0;
    bd.value_bits += enc.bits_spent() - b1;
    let value = if v < 0.0 { -mag } else { mag } as f32;
    recon.push(Coefficient::in_region(
        ctx.channel,
        ctx.band,
        ctx.origin,
        p,
        value,
    ));
}

/// Payload bytes read per kind of syntax element while decoding.
#[derive(Default)]
struct Spent {
    tag: usize,
    position: usize,
    sign: usize,
    value: usize,
}

/// Decodes a sigmap payload of `packet.count` coefficients (a [`super::packet::PayloadDecoder`]).
pub(crate) fn decode(
    header: &Header,
    packet: &PacketFraming<'_>,
    bd: &mut SizeBreakdown,
) -> Result<Vec<Coefficient>, FormatError> {
    let (tile, layer, count) = (packet.tile, packet.layer, packet.count);
    let mut dec = RangeDecoder::new(packet.payload);
    let mut m = Models::new(header);
    let bands = header.geometry.bands();
    // The count is bounded but may still be large for a hostile packet: grow as decoded.
    let mut out = Vec::with_capacity(count.min(super::coefficient::INITIAL_CAPACITY));
    let mut hood = Neighbourhood::new(header, tile);
    let mut spent = Spent::default();
    for (sub, bi, starts_channel) in coded_substreams(header) {
        if starts_channel {
            hood.reset();
        }
        let b0 = dec.bytes_read();
        let present = dec.decode_bit(&mut m.present[bi]);
        spent.tag += dec.bytes_read() - b0;
        if !present {
            continue;
        }
        let band = bands[bi];
        let (origin, root) = region(header, tile, band.level, header.geometry.band_dims(band));
        if root.cells() == 0 {
            return Err(invalid(
                "packet",
                "substream present in an empty tile region",
            ));
        }
        let ctx = Ctx::new(header, layer, (sub, bi), band, origin, &hood);
        let first = out.len();
        m.coded.reset(root.hi);
        decode_box(&mut dec, &mut m, &ctx, root, count, &mut out, &mut spent)?;
        let cells: Vec<[u32; 3]> = out[first..]
            .iter()
            .map(|c| [0, 1, 2].map(|a| c.pos[a] - origin[a]))
            .collect();
        hood.record(band, origin, &cells);
    }
    // Sums of whole bytes, as the per-symbol sums were: the same f64 values.
    bd.tag_bits += 8.0 * spent.tag as f64;
    bd.position_bits += 8.0 * spent.position as f64;
    bd.sign_bits += 8.0 * spent.sign as f64;
    bd.value_bits += 8.0 * spent.value as f64;
    if out.len() != count {
        return Err(invalid(
            "packet",
            format!(
                "decoded {} coefficients, header of the packet says {count}",
                out.len()
            ),
        ));
    }
    Ok(out)
}

fn decode_box(
    dec: &mut RangeDecoder,
    m: &mut Models,
    ctx: &Ctx,
    b: Box3,
    count: usize,
    out: &mut Vec<Coefficient>,
    spent: &mut Spent,
) -> Result<(), FormatError> {
    check_room(dec, count, out)?;
    if b.cells() == 1 {
        let cell = m.cell_contexts(ctx.bi, b.lo);
        return decode_leaf(dec, m, ctx, b.lo, cell, out, spent);
    }
    let (children, n) = b.children();
    let mut any_before = false;
    for (i, &child) in children[..n].iter().enumerate() {
        let cells = child.cells();
        // A single cell's contexts serve its occupancy and its leaf (nothing is decoded
        // between the two); its leaf is decoded here, without a call of its own.
        let single = (cells == 1).then(|| m.cell_contexts(ctx.bi, child.lo));
        let occupied = if i + 1 < n || any_before {
            let b0 = dec.bytes_read();
            let states = ctx.relatives.states(ctx.origin, &child);
            let face = match single {
                Some(cell) => cell.face,
                None => m.face_state(&child, cells),
            };
            let oc = m.occupancy_context(ctx.bi, cells, states, face);
            let o = dec.decode_bit(&mut m.occupied[oc]);
            spent.position += dec.bytes_read() - b0;
            o
        } else {
            true
        };
        any_before |= occupied;
        if occupied {
            match single {
                Some(cell) => {
                    check_room(dec, count, out)?;
                    decode_leaf(dec, m, ctx, child.lo, cell, out, spent)?;
                }
                None => decode_box(dec, m, ctx, child, count, out, spent)?,
            }
        }
    }
    Ok(())
}

/// Stops a packet that decodes more coefficients than it declares, or reads on past its
/// payload, before it decodes another box.
#[inline(always)]
fn check_room(dec: &RangeDecoder, count: usize, out: &[Coefficient]) -> Result<(), FormatError> {
    if out.len() >= count {
        return Err(invalid(
            "packet",
            "more coefficients than the packet declares",
        ));
    }
    if dec.overrun() {
        return Err(invalid(
            "packet",
            format!(
                "the payload ends after {} of {count} declared coefficients",
                out.len()
            ),
        ));
    }
    Ok(())
}

/// Decodes the coefficient of the single cell `at` whose contexts are `cell`: its sign, then
/// its quantized magnitude.
#[inline(always)]
fn decode_leaf(
    dec: &mut RangeDecoder,
    m: &mut Models,
    ctx: &Ctx,
    at: [u32; 3],
    cell: CellContexts,
    out: &mut Vec<Coefficient>,
    spent: &mut Spent,
) -> Result<(), FormatError> {
    let b0 = dec.bytes_read();
    let negative = dec.decode_bit(&mut m.sign[cell.sign]);
    let b1 = dec.bytes_read();
    let q = m.value[cell.value].decode(dec)?;
    m.coded.insert(at, negative, magnitude_class(q));
    spent.sign += b1 - b0;
    spent.value += dec.bytes_read() - b1;
    let value = ctx.quant.signed_value(q, negative)?;
    out.push(Coefficient::in_region(
        ctx.channel,
        ctx.band,
        ctx.origin,
        at,
        value,
    ));
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::cells::{count_ones3, CodedCells, FACE_CONTEXT_MAX_CELLS, VALUE_CONTEXTS};
    use super::grid::{Pyramid, SignificanceGrid, MAX_GRID_CELLS};
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn huge_bounding_boxes_are_coarsened_never_missing_a_cell() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for _ in 0..10 {
            let side = rng.gen_range(200..5000u32);
            let cells: Vec<[u32; 3]> = (0..rng.gen_range(2..40))
                .map(|_| [0, 1, 2].map(|_| rng.gen_range(0..side)))
                .collect();
            let grid = SignificanceGrid::new([3, 5, 7], &cells);
            assert!(grid.sums.len() <= MAX_GRID_CELLS && grid.cells.len() <= MAX_GRID_CELLS);
            for c in &cells {
                let g = [0, 1, 2].map(|a| (c[a] + [3, 5, 7][a]) as u64);
                assert!(grid.any(g, g.map(|v| v + 1)), "cell {c:?} missed");
                assert!(grid.any(g.map(|v| v.saturating_sub(9)), g.map(|v| v + 3)));
            }
            // Far outside the cells' bounding box nothing is set.
            let far = [u64::from(side) + 100; 3];
            assert!(!grid.any(far, far.map(|v| v + 50)));
        }
    }

    #[test]
    fn significance_grid_counts_boxes_like_a_brute_force_scan() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for _ in 0..20 {
            let dims = [0, 1, 2].map(|_| rng.gen_range(1..9usize));
            let origin = [0, 1, 2].map(|_| rng.gen_range(0..5u32));
            let cells: Vec<[u32; 3]> = (0..rng.gen_range(0..12))
                .map(|_| [0, 1, 2].map(|a| rng.gen_range(0..dims[a] as u32)))
                .collect();
            let grid = SignificanceGrid::new(origin, &cells);
            for _ in 0..200 {
                // Boxes in band coordinates, partly or wholly outside the region.
                let lo = [0, 1, 2].map(|_| rng.gen_range(0..14u64));
                let hi = [0, 1, 2].map(|a| lo[a] + rng.gen_range(0..6u64));
                let brute = cells.iter().any(|c| {
                    (0..3).all(|a| {
                        let g = (c[a] + origin[a]) as u64;
                        g >= lo[a] && g < hi[a]
                    })
                });
                assert_eq!(
                    grid.any(lo, hi),
                    brute,
                    "{lo:?}..{hi:?} in {origin:?}+{dims:?}"
                );
            }
        }
    }

    /// Leaves of the octree over a region, in coding order.
    fn leaves(b: Box3, out: &mut Vec<[u32; 3]>) {
        if b.cells() == 1 {
            out.push(b.lo);
            return;
        }
        let (children, n) = b.children();
        assert!(n >= 2, "a box of {} cells must split", b.cells());
        for c in &children[..n] {
            assert!(c.cells() >= 1);
            assert!((0..3).all(|a| c.lo[a] >= b.lo[a] && c.hi[a] <= b.hi[a]));
            assert!((0..3).all(|a| c.hi[a] - c.lo[a] <= c.scale));
            leaves(*c, out);
        }
    }

    /// Points sorted by [`morton::sort_by_cell`] split into one run per octree child at every
    /// box, in the children's order, down to single cells: for regions whose key fits a `u64`
    /// and for longer axes than it holds.
    #[test]
    fn morton_order_puts_each_childs_points_in_one_run() {
        fn walk(b: Box3, pts: &[Point], leaves: &mut Vec<[u32; 3]>) {
            if b.cells() == 1 {
                assert_eq!(pts.len(), 1);
                assert_eq!(pts[0].0, b.lo);
                leaves.push(b.lo);
                return;
            }
            let (children, n) = b.children();
            let bounds = child_runs(&children[..n], pts);
            assert_eq!(bounds[n], pts.len(), "points outside every child");
            for (i, child) in children[..n].iter().enumerate() {
                let run = &pts[bounds[i]..bounds[i + 1]];
                assert!(run.iter().all(|p| child.contains(p.0)));
                if !run.is_empty() {
                    walk(*child, run, leaves);
                }
            }
        }
        let mut rng = ChaCha8Rng::seed_from_u64(31);
        for extent in [
            [1, 1, 1],
            [5, 7, 3],
            [64, 64, 64],
            [33, 1, 70],
            [1 << 21, 2, 3],
            [(1 << 23) + 5, 3, 2],
            [4, (1 << 22) + 1, 9],
            [3, 5, u32::MAX / 2],
        ] {
            let mut cells = std::collections::HashSet::new();
            let total: u64 = extent.iter().map(|&e| e as u64).product();
            while (cells.len() as u64) < total.min(300) {
                cells.insert([0, 1, 2].map(|a| rng.gen_range(0..extent[a])));
            }
            let mut pts: Vec<Point> = cells.iter().map(|&c| (c, 1.0)).collect();
            let root = Box3::root(extent);
            let log = root.scale.trailing_zeros();
            morton::sort_by_cell(&mut pts, log, |p| p.0);
            let mut leaves = Vec::new();
            walk(root, &pts, &mut leaves);
            assert_eq!(leaves.len(), pts.len(), "{extent:?}");
            assert!(
                leaves.iter().zip(&pts).all(|(l, p)| *l == p.0),
                "leaves out of order"
            );
        }
    }

    #[test]
    fn octree_visits_every_cell_once_after_its_lower_neighbours() {
        for extent in [
            [1, 1, 1],
            [1, 1, 9],
            [5, 7, 3],
            [13, 2, 6],
            [16, 16, 16],
            [17, 1, 33],
        ] {
            let mut order = Vec::new();
            leaves(Box3::root(extent), &mut order);
            let cells: usize = extent.iter().map(|&e| e as usize).product();
            assert_eq!(order.len(), cells, "{extent:?}");
            let mut rank = std::collections::HashMap::new();
            for (i, c) in order.iter().enumerate() {
                assert!((0..3).all(|a| c[a] < extent[a]), "{c:?} outside {extent:?}");
                assert!(rank.insert(*c, i).is_none(), "{c:?} visited twice");
            }
            for (c, &i) in &rank {
                for a in 0..3 {
                    if c[a] > 0 {
                        let mut below = *c;
                        below[a] -= 1;
                        assert!(rank[&below] < i, "{below:?} after {c:?} in {extent:?}");
                    }
                }
            }
        }
    }

    /// A dense and a sparse [`CodedCells`] that are fed the same cells, so that the two
    /// layouts can be checked to answer alike.
    #[derive(Default)]
    struct DenseAndSparse {
        dense: CodedCells,
        sparse: CodedCells,
    }

    impl DenseAndSparse {
        /// Resets both to one random extent, each side from 1 to `max_side - 1` cells, the
        /// one dense and the other sparse whatever the size.
        fn reset_random(&mut self, rng: &mut ChaCha8Rng, max_side: u32) -> [u32; 3] {
            let extent = [0, 1, 2].map(|_| rng.gen_range(1..max_side));
            self.dense.reset(extent);
            self.sparse.reset_with_limit(extent, 0);
            assert!(self.dense.use_dense && !self.sparse.use_dense);
            extent
        }

        fn insert(&mut self, c: [u32; 3], negative: bool, class: u8) {
            self.dense.insert(c, negative, class);
            self.sparse.insert(c, negative, class);
        }
    }

    #[test]
    fn coded_cells_dense_and_sparse_agree_with_a_brute_force_count() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut both = DenseAndSparse::default();
        for round in 0..20 {
            let extent = both.reset_random(&mut rng, 12);
            let mut inserted = std::collections::HashMap::new();
            for _ in 0..rng.gen_range(0..200) {
                let c = extent.map(|e| rng.gen_range(0..e));
                let negative = rng.gen_bool(0.5);
                let q = rng.gen_range(0..12u64);
                both.insert(c, negative, magnitude_class(q));
                inserted.insert(c, (negative, q));
            }
            let DenseAndSparse { dense, sparse } = &both;
            for _ in 0..200 {
                let lo = extent.map(|e| rng.gen_range(0..e));
                let hi = [0, 1, 2].map(|a| rng.gen_range(lo[a] + 1..=extent[a]));
                let b = Box3 { lo, hi, scale: 16 };
                let c = lo;
                assert_eq!(dense.get(c), sparse.get(c));
                let want = inserted.get(&c).map_or(0, |&(n, _)| 1 + n as u8);
                assert_eq!(dense.get(c), want, "round {round}");
                assert_eq!(dense.sign_context(3, c), sparse.sign_context(3, c));
                // Brute force: 1 + the class of each coded lower neighbour, bucketed.
                let sum: usize = (0..3)
                    .filter(|&a| c[a] > 0)
                    .filter_map(|a| {
                        let mut below = c;
                        below[a] -= 1;
                        inserted.get(&below)
                    })
                    .map(|&(_, q)| 1 + magnitude_class(q) as usize)
                    .sum();
                let bucket = [0, 1, 2, 3, 4, 5, 5, 6, 6, 6, 7, 7, 7][sum];
                assert_eq!(dense.value_context(3, c), 3 * VALUE_CONTEXTS + bucket);
                assert_eq!(sparse.value_context(3, c), 3 * VALUE_CONTEXTS + bucket);
                assert_eq!(
                    dense.face_state(&b, b.cells()),
                    sparse.face_state(&b, b.cells())
                );
                // Brute force: coded cells just below one of the box's lower faces.
                let touching = inserted
                    .keys()
                    .filter(|p| {
                        (0..3).any(|a| {
                            lo[a] > 0
                                && p[a] == lo[a] - 1
                                && (0..3).all(|o| o == a || (p[o] >= lo[o] && p[o] < hi[o]))
                        })
                    })
                    .count();
                let expected = if b.cells() > FACE_CONTEXT_MAX_CELLS {
                    0
                } else {
                    match touching {
                        0 => 0,
                        1 => 1,
                        2..=3 => 2,
                        _ => 3,
                    }
                };
                assert_eq!(
                    dense.face_state(&b, b.cells()),
                    expected,
                    "{b:?}",
                    b = (lo, hi)
                );
            }
        }
        // A reset forgets every cell.
        let dense = &mut both.dense;
        let extent = dense.extent;
        dense.reset(extent);
        for z in 0..extent[2] {
            for y in 0..extent[1] {
                for x in 0..extent[0] {
                    assert_eq!(dense.get([x, y, z]), 0);
                }
            }
        }
    }

    /// Every box of the octree over a region (the coders query their children), in order.
    fn boxes(b: Box3, out: &mut Vec<Box3>) {
        out.push(b);
        if b.cells() > 1 {
            let (children, n) = b.children();
            for c in &children[..n] {
                boxes(*c, out);
            }
        }
    }

    fn random_cells(rng: &mut ChaCha8Rng, extent: [u32; 3], n: usize) -> Vec<[u32; 3]> {
        (0..n)
            .map(|_| extent.map(|e| rng.gen_range(0..e)))
            .collect()
    }

    #[test]
    fn pyramids_answer_octree_boxes_as_the_grid_does() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        for round in 0..40 {
            let extent = [0, 1, 2].map(|_| rng.gen_range(1..40u32));
            let origin = [0, 1, 2].map(|_| rng.gen_range(0..9u32) * 2);
            let n = rng.gen_range(0..(round % 5) * 30 + 2);
            let cells = random_cells(&mut rng, extent, n);
            let grid = SignificanceGrid::new(origin, &cells);
            assert_eq!(grid.shift, 0);
            let mut pyramid = Pyramid::new(extent);
            cells.iter().for_each(|c| pyramid.insert(*c));
            let mut all = Vec::new();
            boxes(Box3::root(extent), &mut all);
            for b in &all {
                let glo = [0, 1, 2].map(|a| (origin[a] + b.lo[a]) as u64);
                let ghi = [0, 1, 2].map(|a| (origin[a] + b.hi[a]) as u64);
                let k = b.scale.trailing_zeros();
                assert_eq!(
                    pyramid.cube(k, b.lo),
                    grid.any(glo, ghi),
                    "{extent:?} {:?}",
                    b.lo
                );
            }
            // As a parent: the finer level's region is twice this one (plus up to a cell).
            let child_extent = [0, 1, 2].map(|a| 2 * extent[a] - rng.gen_range(0..2u32));
            let child_origin = origin.map(|o| 2 * o);
            let mut all = Vec::new();
            boxes(Box3::root(child_extent), &mut all);
            for b in &all {
                let plo = [0, 1, 2].map(|a| (child_origin[a] + b.lo[a]) as u64 / 2);
                let phi = [0, 1, 2].map(|a| ((child_origin[a] + b.hi[a]) as u64).div_ceil(2));
                let k = b.scale.trailing_zeros();
                let half = [b.lo[0] >> 1, b.lo[1] >> 1, b.lo[2] >> 1];
                assert_eq!(
                    pyramid.cube(k.saturating_sub(1), half),
                    grid.any(plo, phi),
                    "parent of {:?} in {child_extent:?}",
                    b.lo
                );
            }
        }
    }

    #[test]
    fn brick_face_counts_match_the_map_on_octree_boxes() {
        let mut rng = ChaCha8Rng::seed_from_u64(23);
        let mut both = DenseAndSparse::default();
        for _ in 0..30 {
            let extent = both.reset_random(&mut rng, 30);
            let cells: usize = extent.iter().map(|&e| e as usize).product();
            let n = rng.gen_range(0..=cells);
            for c in random_cells(&mut rng, extent, n) {
                let negative = rng.gen_bool(0.4);
                let class = rng.gen_range(0..4u8);
                both.insert(c, negative, class);
            }
            let DenseAndSparse { dense, sparse } = &both;
            let mut all = Vec::new();
            boxes(Box3::root(extent), &mut all);
            for b in &all {
                assert_eq!(
                    dense.face_state(b, b.cells()),
                    sparse.face_state(b, b.cells()),
                    "{:?}..{:?} in {extent:?}",
                    b.lo,
                    b.hi
                );
                if b.cells() == 1 {
                    assert_eq!(dense.sign_context(2, b.lo), sparse.sign_context(2, b.lo));
                    assert_eq!(dense.value_context(2, b.lo), sparse.value_context(2, b.lo));
                }
            }
        }
    }

    #[test]
    fn three_word_population_count() {
        let mut rng = ChaCha8Rng::seed_from_u64(29);
        for _ in 0..1000 {
            let w: [u64; 3] = [rng.gen(), rng.gen(), rng.gen()];
            let w = w.map(|v| v >> rng.gen_range(0..64));
            let want: u32 = w.iter().map(|v| v.count_ones()).sum();
            assert_eq!(count_ones3(w), want as usize);
        }
        assert_eq!(count_ones3([u64::MAX; 3]), 192);
    }
}
