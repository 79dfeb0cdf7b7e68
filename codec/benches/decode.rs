//! Packet decoding throughput, single thread, in coefficients per second (criterion).
//!
//! The file is made here, without the compressor: a smooth phantom with structure at several
//! scales (a head-like shell, inner ellipsoids, a folded cortex-like texture, blobs) on a
//! 200×230×190 grid, the linear family at the compressor's default depth (3) and margin, the
//! top ~150 k coefficients by the oracle's score (w²·‖basis‖²), three quality layers (growth
//! 16) and 128-voxel tiles, as the compressor's automatic tiling picks for a ~100 KB file. The
//! sigmap coder uses the compressor's default step (the threshold magnitude); the paper's
//! syntaxes use Δ of eq. 15 and the coefficients in Morton order within a packet (a stand-in
//! for the compressor's clustering). Every packet is decoded with `decode_packet`, one after
//! the other. Time is the decoding thread's CPU time, not wall time, so that the figure is
//! per core even on a machine other jobs share.
use criterion::{black_box, criterion_group, criterion_main, Criterion, Throughput};
use rustix::time::{clock_gettime, ClockId};
use std::time::Duration;
use wavesplat_codec::dwt::decompose_channel;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::{decode_packet, encode_packets, Coefficient, PacketInput};
use wavesplat_codec::format::{CoderKind, ColorInfo, Header, SubstreamParams};
use wavesplat_codec::layout::Geometry;

const DIMS: [usize; 3] = [200, 230, 190];
const KEEP: usize = 150_000;
const TILE: usize = 128;
const LAYERS: usize = 3;
const GROWTH: f64 = 16.0;

/// A smooth phantom with non-trivial structure, values in about 0..255.
fn phantom() -> Vec<f32> {
    let [nx, ny, nz] = DIMS;
    let blobs = [
        ([0.3, 0.4, 0.5], 0.08, 60.0),
        ([0.65, 0.55, 0.4], 0.12, -40.0),
        ([0.5, 0.3, 0.7], 0.05, 80.0),
        ([0.45, 0.7, 0.35], 0.1, 30.0),
    ];
    let mut out = Vec::with_capacity(nx * ny * nz);
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let p = [
                    x as f64 / nx as f64,
                    y as f64 / ny as f64,
                    z as f64 / nz as f64,
                ];
                let d = [p[0] - 0.5, p[1] - 0.5, p[2] - 0.5];
                let r =
                    ((d[0] / 0.42).powi(2) + (d[1] / 0.46).powi(2) + (d[2] / 0.4).powi(2)).sqrt();
                // Skull-like shell, brain inside with smooth edges (a few voxels wide).
                let edge = |r: f64, at: f64| 0.5 - 0.5 * ((r - at) * 60.0).tanh();
                let head = edge(r, 1.0);
                let brain = edge(r, 0.88);
                let shell = (head - brain).max(0.0);
                // Folded texture inside: grey/white matter-like alternation.
                let fold = (p[0] * 37.0 + 3.0 * (p[1] * 11.0).sin()).sin()
                    * (p[1] * 29.0 + 2.0 * (p[2] * 13.0).cos()).cos()
                    * (p[2] * 23.0 + 2.5 * (p[0] * 7.0).sin()).sin();
                let mut v = 180.0 * shell + brain * (90.0 + 35.0 * fold);
                // Ventricle-like inner ellipsoid.
                let rv =
                    ((d[0] / 0.08).powi(2) + (d[1] / 0.16).powi(2) + (d[2] / 0.06).powi(2)).sqrt();
                v -= 70.0 * edge(rv, 1.0) * brain;
                for (c, s, a) in blobs {
                    let q: f64 = (0..3).map(|i| (p[i] - c[i]).powi(2)).sum();
                    v += a * (-q / (2.0 * s * s)).exp() * brain;
                }
                out.push(v as f32);
            }
        }
    }
    out
}

/// Interleaves the low 10 bits of each coordinate (x fastest).
fn morton(p: [u32; 3]) -> u64 {
    let mut m = 0u64;
    for bit in 0..10 {
        for (a, v) in p.iter().enumerate() {
            m |= (((v >> bit) & 1) as u64) << (3 * bit + a);
        }
    }
    m
}

/// CPU time of the calling thread.
fn thread_cpu_time() -> Duration {
    let t = clock_gettime(ClockId::ThreadCPUTime);
    Duration::new(t.tv_sec as u64, t.tv_nsec as u32)
}

struct Scored {
    score: f64,
    c: Coefficient,
}

/// Header and packets of the phantom's top coefficients with `coder`.
fn make_file(coder: CoderKind, g: &Geometry, kept: &[Scored]) -> (Header, Vec<Vec<u8>>) {
    let k = kept.len();
    let ends: Vec<usize> = (0..LAYERS)
        .map(|l| {
            let frac = GROWTH.powi(l as i32 - (LAYERS as i32 - 1));
            ((k as f64 * frac).ceil() as usize).clamp(1, k)
        })
        .collect();
    let mut layer_bounds = Vec::new();
    let mut start = 0;
    for (l, end) in ends.iter().enumerate() {
        let bound = if l == 0 {
            f64::INFINITY
        } else {
            kept[start].score
        };
        layer_bounds.push(bound.min(layer_bounds.last().copied().unwrap_or(f64::INFINITY)));
        start = *end;
    }
    let nb = g.band_count();
    let mut mags: Vec<Vec<f64>> = vec![Vec::new(); nb];
    for s in kept {
        mags[g.band_index(s.c.band).unwrap()].push((s.c.value as f64).abs());
    }
    let score_threshold = kept[k - 1].score;
    let substreams = mags
        .iter()
        .enumerate()
        .map(|(b, m)| {
            SubstreamParams::of_magnitudes(m, coder, 8, || {
                (score_threshold / g.basis_norm2(g.bands()[b])).sqrt()
            })
        })
        .collect();
    let mut header = Header {
        geometry: *g,
        margin: Geometry::separating_margin(g.family, g.levels),
        placement: None,
        channels: 1,
        color: ColorInfo::intensity(),
        value_range: [0.0, 255.0],
        coder,
        bits: 8,
        tile: TILE,
        layer_bounds,
        coarse_layer: false,
        score_threshold,
        substreams,
        tables: None,
        fast_tables: None,
        total_energy: 1.0,
        kept: k as u64,
        version: wavesplat_codec::format::VERSION,
    };
    let mut groups: std::collections::BTreeMap<(usize, usize), Vec<Coefficient>> =
        Default::default();
    let mut layer = 0;
    for (rank, s) in kept.iter().enumerate() {
        while rank >= ends[layer] {
            layer += 1;
        }
        let pos = s.c.pos.map(|p| p as usize);
        groups
            .entry((layer, header.tile_of(s.c.band, pos)))
            .or_default()
            .push(s.c);
    }
    let inputs: Vec<PacketInput> = groups
        .into_iter()
        .map(|((layer, tile), mut coefficients)| {
            if !coder.quantizes_by_threshold() {
                coefficients.sort_by_key(|c| morton(c.pos.map(|p| p << c.band.level)));
            }
            PacketInput {
                tile,
                layer,
                coefficients,
            }
        })
        .collect();
    let encoded = encode_packets(&mut header, &inputs);
    (header, encoded.packets)
}

fn bench(c: &mut Criterion) {
    let family = Family::Linear;
    let levels = 3;
    let g = Geometry::new(
        DIMS,
        family,
        levels,
        Geometry::separating_margin(family, levels),
    )
    .unwrap();
    let w = decompose_channel(&phantom(), &g);
    let norms: Vec<f64> = g.bands().iter().map(|b| g.basis_norm2(*b)).collect();
    let mut all: Vec<(f64, usize)> = w
        .iter()
        .enumerate()
        .filter(|(_, v)| **v != 0.0)
        .map(|(i, v)| {
            let (band, _) = g.locate(i);
            (v * v * norms[g.band_index(band).unwrap()], i)
        })
        .collect();
    let keep = KEEP.min(all.len());
    all.select_nth_unstable_by(keep - 1, |a, b| b.0.total_cmp(&a.0));
    all.truncate(keep);
    all.sort_by(|a, b| b.0.total_cmp(&a.0));
    let kept: Vec<Scored> = all
        .iter()
        .map(|&(score, i)| {
            let (band, pos) = g.locate(i);
            Scored {
                score,
                c: Coefficient {
                    channel: 0,
                    band,
                    pos: pos.map(|p| p as u32),
                    value: w[i] as f32,
                },
            }
        })
        .collect();
    for coder in [
        CoderKind::Sigmap,
        CoderKind::Fast,
        CoderKind::Range,
        CoderKind::Huffman,
    ] {
        let (header, packets) = make_file(coder, &g, &kept);
        let bytes: usize = packets.iter().map(Vec::len).sum();
        let mut decoded = 0;
        let mut spent = [0.0f64; 4];
        for p in &packets {
            let d = decode_packet(&header, p).unwrap();
            decoded += d.coefficients.len();
            let b = d.breakdown;
            for (s, v) in
                spent
                    .iter_mut()
                    .zip([b.tag_bits, b.position_bits, b.sign_bits, b.value_bits])
            {
                *s += v;
            }
        }
        assert_eq!(decoded, kept.len());
        let per = spent.map(|s| s / decoded as f64);
        eprintln!(
            "{}: {} coefficients in {} packets, {} bytes (header {} bytes); bits per \
             coefficient: tags {:.3}, positions {:.3}, signs {:.3}, values {:.3}",
            coder.name(),
            decoded,
            packets.len(),
            bytes,
            wavesplat_codec::format::write_header_section(&header).len(),
            per[0],
            per[1],
            per[2],
            per[3]
        );
        let mut group = c.benchmark_group("decode");
        group.throughput(Throughput::Elements(decoded as u64));
        group.sample_size(20);
        group.bench_function(coder.name(), |b| {
            b.iter_custom(|iters| {
                let start = thread_cpu_time();
                for _ in 0..iters {
                    for p in &packets {
                        black_box(decode_packet(&header, black_box(p)).unwrap());
                    }
                }
                thread_cpu_time() - start
            })
        });
        group.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
