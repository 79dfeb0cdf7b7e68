//! What a small hostile (or merely unusual) file can cost its decoder: a tiny valid file
//! declaring a huge volume, a packet whose payload cannot hold what it declares, and a valid file
//! of many coefficients against a caller's budget. Each is refused with an error, early, instead
//! of an allocation that aborts the process or minutes of decoding.

use rand::{Rng, SeedableRng};
use wavesplat_codec::format::bytes::ByteWriter;
use wavesplat_codec::format::packet::{
    declared_count, decode_packet, decode_packet_within, decode_packets_within, read_framing,
    DecodeBudget,
};
use wavesplat_codec::format::{parse_file, write_file, CoderKind, FormatError, Header};
use wavesplat_codec::layout::Geometry;
use wavesplat_compressor::decode::{decompress, decompress_within, reconstruction_bytes};
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;

fn sigmap_file(dims: [usize; 3], target: Target) -> Vec<u8> {
    coded_file(CoderKind::Sigmap, dims, target)
}

/// A Shepp–Logan phantom of `dims` coded with `coder`: 16-voxel tiles, two layers.
fn coded_file(coder: CoderKind, dims: [usize; 3], target: Target) -> Vec<u8> {
    coded_file_version(coder, dims, target, wavesplat_codec::format::VERSION)
}

/// [`coded_file`] in format version `version`.
fn coded_file_version(coder: CoderKind, dims: [usize; 3], target: Target, version: u16) -> Vec<u8> {
    let vol = Phantom::SheppLogan.generate(dims);
    compress(
        &vol,
        &CompressOptions {
            coder,
            target,
            tile: TileChoice::Size(16),
            layers: Some(2),
            refine: None,
            format_version: version,
            ..Default::default()
        },
        &|_, _| {},
    )
    .unwrap()
    .bytes
}

/// `header` with its geometry grown to `dims` (no margin) and tiles of `tile` (same family and
/// depth, so the substreams still match).
fn grown(header: &Header, dims: [usize; 3], tile: usize) -> Header {
    let g = &header.geometry;
    let mut h = header.clone();
    h.geometry = Geometry::new(dims, g.family, g.levels, 0).unwrap();
    h.margin = 0;
    h.tile = tile;
    h
}

#[test]
fn a_tiny_valid_file_declaring_a_huge_volume_is_refused_not_allocated() {
    let file = sigmap_file([16, 16, 16], Target::Fraction(0.1));
    let header = parse_file(&file).unwrap().header;
    let huge = grown(&header, [1024, 1024, 2048], 16);
    let tiny = write_file(&huge, &[]);
    assert!(tiny.len() < 4096, "{} bytes", tiny.len());
    let parsed = parse_file(&tiny).unwrap();
    assert!(reconstruction_bytes(&parsed.header) > 16 << 30);
    let e = decompress(&tiny).unwrap_err();
    assert!(e.to_string().contains("over the budget"), "{e}");
    // A caller may allow less, and the original still decodes within a small budget.
    let small = DecodeBudget {
        max_coefficients: 1 << 20,
        max_bytes: 64 << 20,
    };
    assert!(decompress_within(&file, &small).is_ok());
    let need = reconstruction_bytes(&parse_file(&file).unwrap().header);
    let tight = DecodeBudget {
        max_bytes: need - 1,
        ..small
    };
    assert!(decompress_within(&file, &tight).is_err());
}

/// A packet of `header`'s tile 0, layer 0 declaring `count` coefficients with `payload`.
fn forged_packet(header: &Header, count: u64, payload: &[u8]) -> Vec<u8> {
    let mut w = ByteWriter::new();
    w.varint(0);
    w.u8(0);
    w.varint(count);
    for _ in 0..header.geometry.band_count().div_ceil(8) {
        w.u8(0);
    }
    w.varint(payload.len() as u64);
    w.bytes(payload);
    let mut p = w.into_bytes();
    p.extend_from_slice(&crc32fast::hash(&p).to_le_bytes());
    p
}

#[test]
fn a_payload_that_cannot_hold_its_declared_count_stops_where_it_ends() {
    let file = sigmap_file([16, 16, 16], Target::Fraction(0.1));
    let header = parse_file(&file).unwrap().header;
    // One 1024³ tile: the declared count is bounded only by the payload (64 per byte).
    let h = grown(&header, [1024, 1024, 1024], 1024);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(16);
    for len in [1usize, 100, 131 << 10] {
        for seed in 0..3u8 {
            let payload: Vec<u8> = (0..len).map(|_| rng.gen::<u8>() ^ seed).collect();
            let count = 64 * (len as u64 + 1);
            let p = forged_packet(&h, count, &payload);
            assert_eq!(declared_count(&h, &p).unwrap(), count);
            let e = decode_packet(&h, &p).unwrap_err();
            let msg = e.to_string();
            // Refused where the payload runs out (or, for a tiny one, within the few zeros a
            // valid stream may leave implicit), not after decoding the declared count from the
            // zeros past its end.
            assert!(
                msg.contains("payload ends")
                    || msg.contains("more coefficients than")
                    || msg.contains("header of the packet says"),
                "{len} bytes: {msg}"
            );
        }
    }
    // Payloads that keep the octree walk going: before the guard they went on decoding the
    // zeros past the end up to the declared 8.5 M coefficients (seconds and hundreds of MiB);
    // now they stop at the payload's end, or, where the garbage happens to close every octree
    // first, at the end of the walk with fewer coefficients than declared (or at a magnitude
    // no encoder writes).
    let mut at_the_end = 0;
    for b in [0x55u8, 0x80, 0x7f, 0xff, 0xaa, 0xfe, 0x01] {
        let payload = vec![b; 131 << 10];
        let p = forged_packet(&h, 64 * (payload.len() as u64 + 1), &payload);
        let msg = decode_packet(&h, &p).unwrap_err().to_string();
        if msg.contains("payload ends") {
            at_the_end += 1;
        } else {
            assert!(
                msg.contains("header of the packet says") || msg.contains("entropy-coded data"),
                "{b:#x}: {msg}"
            );
        }
    }
    assert!(at_the_end >= 1, "no payload reached the guard");
}

#[test]
fn a_caller_budget_refuses_a_valid_file_before_decoding_it() {
    // Dense, regular data: many coefficients from few bytes.
    let file = sigmap_file([32, 32, 32], Target::All);
    let parsed = parse_file(&file).unwrap();
    let h = &parsed.header;
    let total: u64 = parsed
        .packets
        .iter()
        .map(|p| declared_count(h, p).unwrap())
        .sum();
    assert!(total > 1000);
    let exact = DecodeBudget {
        max_coefficients: total,
        max_bytes: u64::MAX,
    };
    let all = decode_packets_within(h, &parsed.packets, 0, &exact).unwrap();
    assert_eq!(all.iter().map(Vec::len).sum::<usize>() as u64, total);
    let short = DecodeBudget {
        max_coefficients: total - 1,
        ..exact
    };
    let e = decode_packets_within(h, &parsed.packets, 0, &short).unwrap_err();
    assert!(
        matches!(e.source, FormatError::OverBudget { need, .. } if need == total),
        "{e}"
    );
    // Per packet, and by bytes of memory.
    let p = parsed.packets[0];
    let n = declared_count(h, p).unwrap();
    let bytes_budget = DecodeBudget {
        max_coefficients: u64::MAX,
        max_bytes: n * 8,
    };
    assert!(matches!(
        decode_packet_within(h, p, &bytes_budget),
        Err(FormatError::OverBudget { .. })
    ));
}

#[test]
fn fast_coder_packets_of_garbage_or_flipped_bits_are_refused_or_decode_whole() {
    // Prefix-coded (version 13), rANS-coded (version 14) and packets with the occupancy
    // contexts (version 15 on).
    for version in [
        wavesplat_codec::format::COMPACT_HEADER_VERSION,
        wavesplat_codec::format::RANS_VERSION,
        wavesplat_codec::format::FAST_CONTEXTS_VERSION,
    ] {
        fast_packets_of_garbage_or_flipped_bits(version);
    }
}

fn fast_packets_of_garbage_or_flipped_bits(version: u16) {
    let file = coded_file_version(
        CoderKind::Fast,
        [24, 20, 16],
        Target::Fraction(0.2),
        version,
    );
    let parsed = parse_file(&file).unwrap();
    let h = &parsed.header;
    assert_eq!(h.version, version);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
    let mut refused = 0;
    for packet in &parsed.packets {
        let declared = declared_count(h, packet).unwrap() as usize;
        for _ in 0..60 {
            // Flip one bit of the body and fix the checksum, so the decoder sees it.
            let mut p = packet.to_vec();
            let body = p.len() - 4;
            let bit = rng.gen_range(0..8 * body);
            p[bit / 8] ^= 1 << (bit % 8);
            let crc = crc32fast::hash(&p[..body]).to_le_bytes();
            p[body..].copy_from_slice(&crc);
            match decode_packet(h, &p) {
                Ok(d) => assert_eq!(
                    d.coefficients.len(),
                    declared_count(h, &p).unwrap() as usize
                ),
                Err(_) => refused += 1,
            }
        }
        assert!(declared > 0);
    }
    assert!(refused > 0, "no flipped packet was refused");
    // Garbage in one 1024³ tile: the count is bounded by 8 per payload byte.
    let big = grown(h, [1024, 1024, 1024], 1024);
    for len in [1usize, 7, 100, 64 << 10] {
        for seed in 0..3u8 {
            let payload: Vec<u8> = (0..len).map(|_| rng.gen::<u8>() ^ seed).collect();
            let p = forged_packet(&big, 8 * (len as u64 + 1), &payload);
            assert!(decode_packet(&big, &p).is_err(), "{len} bytes decoded");
        }
    }
}

/// A decoding thread hands its coded cells and pyramid buffers from one packet to the next
/// (they are region-sized, and fresh ones cost page faults). What one packet leaves in them
/// must not reach the next: each packet of a file, decoded on one thread after the others in
/// either order, and after a cut copy of a packet that failed halfway, equals the same packet
/// decoded alone on a fresh thread.
#[test]
fn packets_decode_the_same_after_any_other_on_the_same_thread() {
    let bytes = sigmap_file([40, 33, 29], Target::Fraction(0.2));
    let file = parse_file(&bytes).unwrap();
    let h = &file.header;
    assert!(file.packets.len() >= 8, "{} packets", file.packets.len());
    let alone: Vec<_> = file
        .packets
        .iter()
        .map(|p| {
            std::thread::scope(|s| {
                s.spawn(|| decode_packet(h, p).unwrap().coefficients)
                    .join()
                    .unwrap()
            })
        })
        .collect();
    let mut orders: Vec<Vec<usize>> = vec![(0..file.packets.len()).collect()];
    orders.push(orders[0].iter().rev().copied().collect());
    std::thread::scope(|s| {
        s.spawn(|| {
            for order in &orders {
                for &i in order {
                    let p = file.packets[i];
                    // A packet cut in the middle of its payload: decoding fails partway
                    // (or, for a tiny one, decodes what is left), leaving cells behind.
                    let payload = read_framing(h, p).unwrap().payload;
                    let cut = forged_packet(
                        h,
                        declared_count(h, p).unwrap(),
                        &payload[..payload.len() / 2],
                    );
                    let _ = decode_packet(h, &cut);
                    let got = decode_packet(h, p).unwrap().coefficients;
                    assert_eq!(got, alone[i], "packet {i}");
                }
            }
        })
        .join()
        .unwrap()
    });
}
