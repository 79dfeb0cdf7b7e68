//! The volume's placement in patient space travels through the `.wsp` header: written by the
//! encoder, validated on read, returned by the decoder; version 3 files (before placement) and
//! version 5 sigmap packets (before the magnitude contexts) still read, older versions are
//! refused with a message saying what to do.

use wavesplat_codec::format::packet::{decode_packet, encode_packets, Coefficient, PacketInput};
use wavesplat_codec::format::{
    parse_file, read_header_section, write_file, write_file_version, FormatError,
    COARSE_LAYER_VERSION, COMPACT_HEADER_VERSION, FAST_CODER_VERSION, MAGIC,
    MAGNITUDE_CONTEXTS_VERSION, OLDEST_READABLE_VERSION, PRIORS_VERSION, VERSION,
};
use wavesplat_codec::volume::{Placement, Volume};
use wavesplat_compressor::decode::decompress;
use wavesplat_compressor::encode::{compress, CompressOptions, Target};
use wavesplat_compressor::phantom::Phantom;

fn placed() -> Volume {
    let v = Phantom::SheppLogan.generate([12, 10, 8]);
    let (dims, channels) = (v.dims(), v.into_channels());
    Volume::new(dims, [0.7, 0.7, 2.5], channels)
        .unwrap()
        .with_placement(Placement {
            origin: [-120.5, 30.25, 512.0],
            directions: [[0.6, 0.8, 0.0], [0.0, 0.0, -1.0], [-0.8, 0.6, 0.0]],
        })
        .unwrap()
}

/// `v` compressed without the coarse layer (version 8), and in version 12 (every substream's
/// largest magnitude sent), so that it can be written in the versions before them.
fn file(v: &Volume) -> Vec<u8> {
    let opts = CompressOptions {
        target: Target::Fraction(0.3),
        refine: None,
        coarse_layer: false,
        format_version: PRIORS_VERSION,
        ..CompressOptions::default()
    };
    compress(v, &opts, &|_, _| {}).unwrap().bytes
}

/// Every packet's decoded coefficients, in file order.
fn decoded(bytes: &[u8]) -> Vec<(usize, usize, Vec<Coefficient>)> {
    let f = parse_file(bytes).unwrap();
    f.packets
        .iter()
        .map(|p| {
            let d = decode_packet(&f.header, p).unwrap();
            (d.tile, d.layer, d.coefficients)
        })
        .collect()
}

/// The file `bytes` written as format `version`, its packets coded again in that version's
/// syntax from their decoded coefficients (which quantize back to the same values).
fn rewritten(bytes: &[u8], version: u16) -> Vec<u8> {
    let mut header = parse_file(bytes).unwrap().header;
    header.version = version;
    let inputs: Vec<PacketInput> = decoded(bytes)
        .into_iter()
        .map(|(tile, layer, coefficients)| PacketInput {
            tile,
            layer,
            coefficients,
        })
        .collect();
    let packets = encode_packets(&mut header, &inputs).packets;
    write_file_version(&header, &packets, version).unwrap()
}

#[test]
fn placement_and_spacing_round_trip() {
    let v = placed();
    let bytes = file(&v);
    let h = parse_file(&bytes).unwrap().header;
    assert_eq!(h.placement.as_ref(), v.placement());
    assert_eq!(h.spacing(), v.spacing());
    let back = decompress(&bytes).unwrap();
    assert_eq!(back.placement(), v.placement());
    assert_eq!(back.spacing(), v.spacing());
    // Without a placement the header says so.
    let plain = Phantom::Spheres.generate([8, 8, 8]);
    assert!(parse_file(&file(&plain))
        .unwrap()
        .header
        .placement
        .is_none());
}

/// The file `bytes` written as format `version` (12: f64 fields as they are; 13: the compact
/// header's tagged numbers) with the placement's `i`-th value (0..3 origin, 3..12 directions)
/// set to `value`: what a hostile writer puts on the wire, through the writer, which checks
/// nothing of the placement, so the reader's checks are what the test sees.
fn with_placement_value(bytes: &[u8], i: usize, value: f64, version: u16) -> Vec<u8> {
    let f = parse_file(bytes).unwrap();
    let mut header = f.header.clone();
    let p = header.placement.as_mut().expect("a placed volume");
    if i < 3 {
        p.origin[i] = value;
    } else {
        p.directions[(i - 3) / 3][(i - 3) % 3] = value;
    }
    let packets: Vec<Vec<u8>> = f.packets.iter().map(|p| p.to_vec()).collect();
    write_file_version(&header, &packets, version).unwrap()
}

#[test]
fn hostile_placements_and_old_versions_are_refused() {
    let bytes = file(&placed());
    for version in [PRIORS_VERSION, COMPACT_HEADER_VERSION] {
        let fine = read_header_section(&with_placement_value(&bytes, 0, 0.0, version));
        assert_eq!(fine.unwrap().0.placement.unwrap().origin[0], 0.0);
        for (i, v) in [
            (1, f64::NAN),
            (2, f64::INFINITY),
            (0, 1e300),
            (3, 0.0),
            (4, 0.5),
            (11, 2.0),
            (5, -1.0),
        ] {
            let e = read_header_section(&with_placement_value(&bytes, i, v, version)).unwrap_err();
            assert!(
                matches!(e, FormatError::Invalid { .. }),
                "{version} {i} {v}: {e}"
            );
        }
    }
    let mut old = bytes.clone();
    old[4..6].copy_from_slice(&(OLDEST_READABLE_VERSION - 1).to_le_bytes());
    assert_eq!(&old[..4], MAGIC);
    let e = read_header_section(&old).unwrap_err();
    assert!(matches!(e, FormatError::UnsupportedVersion { .. }));
    assert!(
        e.to_string().contains("compress the source volume again"),
        "{e}"
    );
    // Versions 9 and 11 are the bricked containers and 10 the series container, which the
    // plain reader names as such (plain files went from 8 to 12 and 13); the first version
    // this build knows nothing of is newer.
    for v in [
        wavesplat_codec::format::bricked::EXPLICIT_BRICKED_VERSION,
        wavesplat_codec::format::bricked::BRICKED_VERSION,
    ] {
        let mut bricked = bytes.clone();
        bricked[4..6].copy_from_slice(&v.to_le_bytes());
        assert!(matches!(
            read_header_section(&bricked).unwrap_err(),
            FormatError::Bricked
        ));
    }
    let mut series = bytes.clone();
    series[4..6].copy_from_slice(&wavesplat_codec::format::series::SERIES_VERSION.to_le_bytes());
    assert!(matches!(
        read_header_section(&series).unwrap_err(),
        FormatError::Series
    ));
    let mut newer = bytes;
    newer[4..6].copy_from_slice(&(VERSION + 1).to_le_bytes());
    assert!(read_header_section(&newer)
        .unwrap_err()
        .to_string()
        .contains("newer"));
}

/// A file without placement written as version 3 (what caches and archives hold from before
/// placement existed) reads back as the same header and packets; a placed volume cannot be
/// written as version 3 without losing its placement, so that is refused.
#[test]
fn version_3_files_still_read() {
    let unplaced = Phantom::SheppLogan.generate([12, 10, 8]);
    let bytes = file(&unplaced);
    let parsed = parse_file(&bytes).unwrap();
    assert!(parsed.header.placement.is_none());
    let packets: Vec<Vec<u8>> = parsed.packets.iter().map(|p| p.to_vec()).collect();
    let v3 = rewritten(&bytes, 3);
    assert_eq!(u16::from_le_bytes([v3[4], v3[5]]), 3);
    let back = parse_file(&v3).unwrap();
    assert_eq!(back.header.version, 3);
    assert_eq!(
        back.header,
        wavesplat_codec::format::Header {
            version: 3,
            ..parsed.header.clone()
        }
    );
    assert_eq!(decoded(&v3), decoded(&bytes));
    assert_eq!(
        decompress(&v3).unwrap().channels(),
        decompress(&bytes).unwrap().channels()
    );
    let mut placed_header = parse_file(&file(&placed())).unwrap().header;
    placed_header.version = 3;
    assert!(write_file_version(&placed_header, &packets, 3).is_err());
    assert!(write_file_version(&parsed.header, &packets, VERSION + 1).is_err());
}

/// Sigmap packets of version 5 (each magnitude coded in its band's context only) still decode,
/// to the same coefficients as this version's packets of the same file, on an intensity head,
/// a CT-like body and a colour volume; packets coded with the magnitude contexts cannot be
/// written under a version whose readers do not know them.
#[test]
fn version_5_sigmap_packets_still_decode() {
    for v in [
        Phantom::SheppLogan.generate([20, 18, 16]),
        Phantom::Ct.generate([24, 20, 12]),
        Phantom::RgbHead.generate([16, 16, 16]),
    ] {
        let bytes = file(&v);
        let parsed = parse_file(&bytes).unwrap();
        assert_eq!(parsed.header.version, PRIORS_VERSION);
        const { assert!(PRIORS_VERSION >= MAGNITUDE_CONTEXTS_VERSION) };
        let v5 = rewritten(&bytes, 5);
        assert_eq!(parse_file(&v5).unwrap().header.version, 5);
        assert_ne!(parse_file(&v5).unwrap().packets, parsed.packets);
        assert_eq!(decoded(&v5), decoded(&bytes));
        assert_eq!(
            decompress(&v5).unwrap().channels(),
            decompress(&bytes).unwrap().channels()
        );
        let packets: Vec<Vec<u8>> = parsed.packets.iter().map(|p| p.to_vec()).collect();
        let e = write_file_version(&parsed.header, &packets, 5).unwrap_err();
        assert!(e.to_string().contains("magnitude contexts"), "{e}");
    }
}

#[test]
fn fast_coder_files_are_not_written_in_versions_before_it() {
    let v = Phantom::SheppLogan.generate([20, 18, 16]);
    let bytes = compress(
        &v,
        &CompressOptions {
            coder: wavesplat_codec::format::CoderKind::Fast,
            target: Target::Fraction(0.1),
            ..Default::default()
        },
        &|_, _| {},
    )
    .unwrap()
    .bytes;
    let parsed = parse_file(&bytes).unwrap();
    assert_eq!(
        parsed.header.coder,
        wavesplat_codec::format::CoderKind::Fast
    );
    let packets: Vec<Vec<u8>> = parsed.packets.iter().map(|p| p.to_vec()).collect();
    let e = write_file_version(&parsed.header, &packets, FAST_CODER_VERSION - 1).unwrap_err();
    assert!(e.to_string().contains("no fast coder"), "{e}");
    let same = write_file_version(&parsed.header, &packets, VERSION).unwrap();
    assert_eq!(parse_file(&same).unwrap().header, parsed.header);
}

/// From version 14 the fast coder codes its masks and step symbols by rANS. The same
/// coefficients, quantized the same way, decode to the same volume in fewer payload bytes than
/// version 13's prefix codes; packets coded for one version are not written as the other.
#[test]
fn fast_coder_rans_packets_decode_like_prefix_coded_ones_in_fewer_bytes() {
    use wavesplat_codec::format::{CoderKind, RANS_VERSION};
    let cases = [
        ("ct", Phantom::Ct.generate([48, 40, 36]), 0.05),
        (
            "shepp-logan",
            Phantom::SheppLogan.generate([40, 40, 40]),
            0.2,
        ),
        ("ct, all", Phantom::Ct.generate([24, 20, 17]), 1.0),
        ("one voxel", Phantom::Ct.generate([1, 1, 1]), 1.0),
    ];
    for (name, v, fraction) in cases {
        let coded = |coder: CoderKind, version: u16| {
            let opts = CompressOptions {
                coder,
                target: Target::Fraction(fraction),
                refine: None,
                format_version: version,
                ..Default::default()
            };
            compress(&v, &opts, &|_, _| {}).unwrap().bytes
        };
        let prefix = coded(CoderKind::Fast, COMPACT_HEADER_VERSION);
        let rans = coded(CoderKind::Fast, RANS_VERSION);
        let (p, r) = (parse_file(&prefix).unwrap(), parse_file(&rans).unwrap());
        assert_eq!(r.header.version, RANS_VERSION, "{name}");
        assert!(r.header.fast_tables.as_ref().unwrap().is_rans(), "{name}");
        assert!(!p.header.fast_tables.as_ref().unwrap().is_rans(), "{name}");
        assert_eq!(
            decompress(&rans).unwrap().channels(),
            decompress(&prefix).unwrap().channels(),
            "{name}"
        );
        let payload = |f: &wavesplat_codec::format::WspFile| -> usize {
            f.packets.iter().map(|p| p.len()).sum()
        };
        let kept: usize = p
            .packets
            .iter()
            .map(|q| decode_packet(&p.header, q).unwrap().coefficients.len())
            .sum();
        if kept > 1000 {
            assert!(
                payload(&r) < payload(&p),
                "{name}: rANS packets {} bytes, prefix-coded {}",
                payload(&r),
                payload(&p)
            );
        }
        let rp: Vec<Vec<u8>> = r.packets.iter().map(|q| q.to_vec()).collect();
        let e = write_file_version(&r.header, &rp, COMPACT_HEADER_VERSION).unwrap_err();
        assert!(e.to_string().contains("rANS"), "{name}: {e}");
        let pp: Vec<Vec<u8>> = p.packets.iter().map(|q| q.to_vec()).collect();
        let e = write_file_version(&p.header, &pp, RANS_VERSION).unwrap_err();
        assert!(e.to_string().contains("rANS"), "{name}: {e}");
        // The other coders' files are the same in both versions but for the version number.
        let a = coded(CoderKind::Sigmap, COMPACT_HEADER_VERSION);
        let b = coded(CoderKind::Sigmap, RANS_VERSION);
        let (a, b) = (parse_file(&a).unwrap(), parse_file(&b).unwrap());
        let mut h = a.header.clone();
        h.version = RANS_VERSION;
        assert_eq!(h, b.header, "{name}");
        assert_eq!(a.packets, b.packets, "{name}");
    }
}

/// From version 15 the fast coder codes the masks of nodes of 4×4×4 cells bit by bit in the
/// context of their faces, and large steps in half octaves. The same coefficients decode to
/// the same volume in fewer bytes than version 14's, every coefficient kept or a few, at a
/// volume's faces (a 1-voxel volume, odd sizes); packets coded for one version are not written
/// as the other.
#[test]
fn fast_coder_occupancy_contexts_decode_like_version_14_in_fewer_bytes() {
    use wavesplat_codec::format::{CoderKind, FAST_CONTEXTS_VERSION, RANS_VERSION};
    let cases = [
        ("ct", Phantom::Ct.generate([48, 40, 36]), 0.05),
        ("blobs", Phantom::Blobs.generate([33, 29, 40]), 0.1),
        ("ct, all", Phantom::Ct.generate([24, 20, 17]), 1.0),
        ("one voxel", Phantom::Ct.generate([1, 1, 1]), 1.0),
    ];
    for (name, v, fraction) in cases {
        let coded = |version: u16| {
            let opts = CompressOptions {
                coder: CoderKind::Fast,
                target: Target::Fraction(fraction),
                refine: None,
                format_version: version,
                ..Default::default()
            };
            compress(&v, &opts, &|_, _| {}).unwrap().bytes
        };
        let (old, new) = (coded(RANS_VERSION), coded(FAST_CONTEXTS_VERSION));
        let (o, n) = (parse_file(&old).unwrap(), parse_file(&new).unwrap());
        assert_eq!(n.header.version, FAST_CONTEXTS_VERSION, "{name}");
        assert!(n
            .header
            .fast_tables
            .as_ref()
            .unwrap()
            .has_occupancy_tables());
        assert!(!o
            .header
            .fast_tables
            .as_ref()
            .unwrap()
            .has_occupancy_tables());
        assert_eq!(
            decompress(&new).unwrap().channels(),
            decompress(&old).unwrap().channels(),
            "{name}"
        );
        let kept: usize = o
            .packets
            .iter()
            .map(|q| decode_packet(&o.header, q).unwrap().coefficients.len())
            .sum();
        if kept > 1000 {
            assert!(
                new.len() < old.len(),
                "{name}: version 15 {} bytes, version 14 {}",
                new.len(),
                old.len()
            );
        }
        let np: Vec<Vec<u8>> = n.packets.iter().map(|q| q.to_vec()).collect();
        let e = write_file_version(&n.header, &np, RANS_VERSION).unwrap_err();
        assert!(e.to_string().contains("face"), "{name}: {e}");
        let op: Vec<Vec<u8>> = o.packets.iter().map(|q| q.to_vec()).collect();
        let e = write_file_version(&o.header, &op, FAST_CONTEXTS_VERSION).unwrap_err();
        assert!(e.to_string().contains("face"), "{name}: {e}");
    }
}

/// A header that names no plain version (a container's, or none) is written as the current
/// version, and its packets are coded for that version too, so the file reads back.
#[test]
fn packets_of_a_header_without_a_plain_version_are_coded_for_the_current_one() {
    use wavesplat_codec::format::CoderKind;
    let v = Phantom::Ct.generate([24, 19, 13]);
    for coder in [CoderKind::Fast, CoderKind::Sigmap] {
        let opts = CompressOptions {
            coder,
            target: Target::Fraction(0.3),
            refine: None,
            ..Default::default()
        };
        let bytes = compress(&v, &opts, &|_, _| {}).unwrap().bytes;
        let f = parse_file(&bytes).unwrap();
        let inputs: Vec<PacketInput> = f
            .packets
            .iter()
            .map(|p| {
                let d = decode_packet(&f.header, p).unwrap();
                PacketInput {
                    tile: d.tile,
                    layer: d.layer,
                    coefficients: d.coefficients,
                }
            })
            .collect();
        for version in [0u16, 10, 11] {
            let mut h = f.header.clone();
            h.version = version;
            let packets = encode_packets(&mut h, &inputs).packets;
            let written = write_file(&h, &packets);
            let back = parse_file(&written)
                .unwrap_or_else(|e| panic!("{coder:?}, version {version}: {e}"));
            assert_eq!(back.header.version, VERSION);
            let kept: usize = back
                .packets
                .iter()
                .map(|p| decode_packet(&back.header, p).unwrap().coefficients.len())
                .sum();
            assert_eq!(kept as u64, f.header.kept, "{coder:?}, version {version}");
        }
    }
}

/// A file with the coarse layer reads back with it; it is not written in a version before the
/// coarse layer (whose readers would take layer 0 for a score layer and quantize it wrongly),
/// and a header that claims a coarse layer with one layer only is refused on read.
#[test]
fn coarse_layer_files_are_not_written_in_versions_before_it() {
    let v = Phantom::SheppLogan.generate([20, 18, 16]);
    let bytes = compress(
        &v,
        &CompressOptions {
            target: Target::Fraction(0.1),
            tile: wavesplat_compressor::encode::TileChoice::Size(8),
            ..Default::default()
        },
        &|_, _| {},
    )
    .unwrap()
    .bytes;
    let parsed = parse_file(&bytes).unwrap();
    assert!(parsed.header.coarse_layer);
    assert!(parsed.header.layer_bounds.len() >= 2);
    let packets: Vec<Vec<u8>> = parsed.packets.iter().map(|p| p.to_vec()).collect();
    let e = write_file_version(&parsed.header, &packets, COARSE_LAYER_VERSION - 1).unwrap_err();
    assert!(e.to_string().contains("no coarse layer"), "{e}");
    let same = write_file_version(&parsed.header, &packets, VERSION).unwrap();
    assert_eq!(parse_file(&same).unwrap().header, parsed.header);
    let mut one_layer = parsed.header.clone();
    one_layer.layer_bounds.truncate(1);
    let e = parse_file(&write_file(&one_layer, &[])).unwrap_err();
    assert!(
        e.to_string().contains("coarse layer needs two layers"),
        "{e}"
    );
}

/// Sigmap packets of version 8 (models starting at ½) still decode, to the same coefficients
/// as the same file's version 12 packets (models starting from the trained priors), on volumes
/// the priors were not trained on (a CT-like body, noise) and on ones they were; version 12's
/// are smaller in all; packets coded with the priors cannot be written under version 8, and
/// `compress` writes version 8 when asked.
#[test]
fn version_8_sigmap_packets_still_decode_and_the_priors_save_bytes() {
    use wavesplat_codec::format::LAST_UNPRIMED_VERSION;
    let (mut primed, mut unprimed) = (0usize, 0usize);
    for (v, fraction) in [
        (Phantom::Ct.generate([40, 36, 24]), 0.02),
        (Phantom::Ct.generate([40, 36, 24]), 0.002),
        (Phantom::Noise { seed: 3 }.generate([16, 16, 16]), 0.2),
        (Phantom::SheppLogan.generate([32, 30, 28]), 0.01),
        (Phantom::RgbHead.generate([20, 20, 20]), 0.05),
    ] {
        let bytes = compress(
            &v,
            &CompressOptions {
                target: Target::Fraction(fraction),
                format_version: PRIORS_VERSION,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes;
        let parsed = parse_file(&bytes).unwrap();
        assert_eq!(parsed.header.version, PRIORS_VERSION);
        let v8 = rewritten(&bytes, LAST_UNPRIMED_VERSION);
        let parsed8 = parse_file(&v8).unwrap();
        assert_eq!(parsed8.header.version, LAST_UNPRIMED_VERSION);
        assert_eq!(decoded(&v8), decoded(&bytes));
        assert_eq!(
            decompress(&v8).unwrap().channels(),
            decompress(&bytes).unwrap().channels()
        );
        primed += parsed.packets.iter().map(|p| p.len()).sum::<usize>();
        unprimed += parsed8.packets.iter().map(|p| p.len()).sum::<usize>();
        let packets: Vec<Vec<u8>> = parsed.packets.iter().map(|p| p.to_vec()).collect();
        let e = write_file_version(&parsed.header, &packets, LAST_UNPRIMED_VERSION).unwrap_err();
        assert!(e.to_string().contains("trained priors"), "{e}");
        // Asked for, compress writes version 8 itself: the same coefficients.
        let asked = compress(
            &v,
            &CompressOptions {
                target: Target::Fraction(fraction),
                format_version: LAST_UNPRIMED_VERSION,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes;
        assert_eq!(
            parse_file(&asked).unwrap().header.version,
            LAST_UNPRIMED_VERSION
        );
        assert_eq!(decoded(&asked), decoded(&bytes));
    }
    assert!(
        primed < unprimed,
        "payloads: {primed} bytes with the priors, {unprimed} without"
    );
    let e = compress(
        &Phantom::SheppLogan.generate([8, 8, 8]),
        &CompressOptions {
            format_version: 9,
            ..Default::default()
        },
        &|_, _| {},
    )
    .unwrap_err();
    assert!(e.to_string().contains("format version 9"), "{e}");
}

/// The compact header (version 13) holds exactly what version 12's holds: files of every coder,
/// spacing, placement, colour space, layer count and quantizer step, and of degenerate volumes,
/// compressed in version 12 and written as 13, read back to the same header and packets, in a
/// smaller header. Compressed in version 13, a threshold coder's caps on reconstruction (w₀)
/// are rounded up to sixteenths of Δ or dropped (+∞, which version 12 cannot say: writing such
/// a file as version 12 is refused), and the header is smaller still. Δs and caps that no
/// step predicts (what another writer may send) round-trip exactly too.
#[test]
fn the_compact_header_holds_what_version_12_holds_in_fewer_bytes() {
    use wavesplat_codec::format::CoderKind;
    let rgb = Phantom::RgbHead.generate([10, 9, 8]);
    let zero = Volume::new([5, 4, 3], [1.0; 3], vec![vec![0.0; 60]]).unwrap();
    let constant = Volume::new([6, 6, 6], [2.0; 3], vec![vec![7.25; 216]]).unwrap();
    let one = Volume::new([1, 1, 1], [1.0; 3], vec![vec![3.0]]).unwrap();
    let cases: Vec<(&str, Volume, CompressOptions)> = vec![
        ("placed sigmap", placed(), CompressOptions::default()),
        (
            "placed fast",
            placed(),
            CompressOptions {
                coder: CoderKind::Fast,
                ..Default::default()
            },
        ),
        (
            "huffman",
            placed(),
            CompressOptions {
                coder: CoderKind::Huffman,
                ..Default::default()
            },
        ),
        (
            "range, 4 layers",
            Phantom::SheppLogan.generate([16, 12, 10]),
            CompressOptions {
                coder: CoderKind::Range,
                layers: Some(4),
                ..Default::default()
            },
        ),
        (
            "step 0.37, 3 layers",
            Phantom::Ct.generate([20, 18, 12]),
            CompressOptions {
                step: 0.37,
                layers: Some(3),
                ..Default::default()
            },
        ),
        ("rgb", rgb, CompressOptions::default()),
        ("zero", zero, CompressOptions::default()),
        ("constant", constant, CompressOptions::default()),
        ("one voxel", one, CompressOptions::default()),
    ];
    let mut capless = 0;
    for (name, v, opts) in cases {
        let opts = CompressOptions {
            target: Target::Fraction(0.3),
            refine: None,
            format_version: COMPACT_HEADER_VERSION,
            ..opts
        };
        let old_opts = CompressOptions {
            format_version: PRIORS_VERSION,
            ..opts.clone()
        };
        let old = compress(&v, &old_opts, &|_, _| {}).unwrap().bytes;
        let g = parse_file(&old).unwrap();
        assert_eq!(g.header.version, PRIORS_VERSION, "{name}");
        let packets: Vec<Vec<u8>> = g.packets.iter().map(|p| p.to_vec()).collect();
        let compact = write_file_version(&g.header, &packets, COMPACT_HEADER_VERSION).unwrap();
        let f = parse_file(&compact).unwrap();
        assert_eq!(f.header.version, COMPACT_HEADER_VERSION, "{name}");
        let mut same = f.header.clone();
        same.version = PRIORS_VERSION;
        assert_eq!(same, g.header, "{name}");
        assert_eq!(f.packets, g.packets, "{name}");
        assert_eq!(
            decompress(&compact).unwrap().channels(),
            decompress(&old).unwrap().channels(),
            "{name}"
        );
        assert!(
            f.header_bytes < g.header_bytes,
            "{name}: compact header {} bytes, version 12's {}",
            f.header_bytes,
            g.header_bytes
        );
        // Compressed in version 13 itself.
        let new = compress(&v, &opts, &|_, _| {}).unwrap().bytes;
        let n = parse_file(&new).unwrap();
        assert_eq!(n.header.version, COMPACT_HEADER_VERSION, "{name}");
        assert!(n.header_bytes <= f.header_bytes, "{name}");
        let new_packets: Vec<Vec<u8>> = n.packets.iter().map(|p| p.to_vec()).collect();
        let without = n
            .header
            .substreams
            .iter()
            .flatten()
            .filter(|s| s.w0.is_infinite());
        if without.count() > 0 {
            assert!(opts.coder.quantizes_by_threshold(), "{name}");
            capless += 1;
            let e = write_file_version(&n.header, &new_packets, PRIORS_VERSION).unwrap_err();
            assert!(e.to_string().contains("largest magnitude"), "{name}: {e}");
        }
        // Δs off the step's prediction: zero, subnormal, the largest f32, a factor off; caps
        // off the sixteenths, none, and zero.
        let oddities = [0.0f32, -0.0, f32::from_bits(1), f32::MAX, 1.37e-3, 3.0e7];
        let caps = [0.1f32, f32::INFINITY, 0.0, 1.0e30, 7.0];
        for (header, packets) in [(&f.header, &packets), (&n.header, &new_packets)] {
            let mut odd = header.clone();
            for (k, s) in odd.substreams.iter_mut().flatten().enumerate() {
                s.delta = oddities[k % oddities.len()];
                if k % 3 == 1 && header.coder.quantizes_by_threshold() {
                    s.w0 = caps[k % caps.len()];
                }
            }
            let written = write_file_version(&odd, packets, COMPACT_HEADER_VERSION).unwrap();
            let back = parse_file(&written).unwrap().header;
            assert_eq!(back, odd, "{name}: odd Δs");
            let signs = |h: &wavesplat_codec::format::Header| -> Vec<u32> {
                h.substreams
                    .iter()
                    .flatten()
                    .map(|s| s.delta.to_bits())
                    .collect()
            };
            assert_eq!(signs(&back), signs(&odd), "{name}: Δ bits");
            // An importance so small that every threshold magnitude overflows to +∞.
            let mut tiny = header.clone();
            tiny.color.importance[0] = 5e-324;
            let written = write_file_version(&tiny, packets, COMPACT_HEADER_VERSION).unwrap();
            assert_eq!(
                parse_file(&written).unwrap().header,
                tiny,
                "{name}: tiny importance"
            );
        }
    }
    assert!(capless >= 3, "{capless} files went without a w0");
}

/// With its cap on reconstruction rounded up to a sixteenth of Δ, or dropped where the largest
/// magnitude lies far above the rest, a version 13 file decodes as accurately as version 12's
/// exact caps at fewer bytes (a single coefficient's exactness is
/// `roundtrip::lossless_selection_of_a_single_coefficient_is_exact`).
#[test]
fn the_coarse_cap_costs_no_accuracy() {
    let v = Phantom::SheppLogan.generate([24, 20, 16]);
    for fraction in [0.01, 0.05, 0.3] {
        let err = |version: u16| {
            let o = CompressOptions {
                target: Target::Fraction(fraction),
                format_version: version,
                ..Default::default()
            };
            let bytes = compress(&v, &o, &|_, _| {}).unwrap().bytes;
            let back = decompress(&bytes).unwrap();
            let e: f64 = back.channels()[0]
                .iter()
                .zip(&v.channels()[0])
                .map(|(a, b)| (*a as f64 - *b as f64).powi(2))
                .sum();
            (e, bytes.len())
        };
        let (e12, b12) = err(PRIORS_VERSION);
        let (e13, b13) = err(COMPACT_HEADER_VERSION);
        assert!(b13 < b12, "{fraction}: {b13} bytes against {b12}");
        assert!(
            e13 <= e12 * 1.02,
            "{fraction}: squared error {e13} against version 12's {e12}"
        );
    }
}

/// A compact header's tagged numbers and spacing are checked like the rest: a tag no writer
/// uses is refused, as are a negative or non-finite step scale (the CRC fixed, so the checks
/// after it are what refuses).
#[test]
fn compact_header_tags_no_writer_uses_are_refused() {
    let bytes = compress(
        &Phantom::SheppLogan.generate([12, 10, 8]),
        &CompressOptions {
            target: Target::Fraction(0.3),
            refine: None,
            ..Default::default()
        },
        &|_, _| {},
    )
    .unwrap()
    .bytes;
    let len = u32::from_le_bytes(bytes[6..10].try_into().unwrap()) as usize;
    // The header: three one-byte dims, then the spacing tag.
    let spacing_at = 10 + 3;
    assert_eq!(bytes[spacing_at], 0, "unit spacing");
    let patched = |at: usize, byte: u8| {
        let mut b = bytes.clone();
        b[at] = byte;
        let crc = crc32fast::hash(&b[10..10 + len]);
        b[10 + len..14 + len].copy_from_slice(&crc.to_le_bytes());
        b
    };
    let e = read_header_section(&patched(spacing_at, 3)).unwrap_err();
    assert!(e.to_string().contains("spacing tag 3"), "{e}");
    // After the spacing tag: placement flag, channels, family, levels, margin, colour kind,
    // then the intensity offset's number tag.
    let offset_at = spacing_at + 7;
    let e = read_header_section(&patched(offset_at, 6)).unwrap_err();
    assert!(e.to_string().contains("number tag 6"), "{e}");
    for tag in 7..=255u8 {
        assert!(read_header_section(&patched(offset_at, tag)).is_err());
    }
}

/// Empty layers have +∞ bounds, and a layer above one takes its lower bound from the next
/// layer's chain start, which a substream without a cap (w₀ = +∞) left infinite: every value of
/// that layer came back +∞ and the file was refused. A 16³ volume kept to its 64 scaling
/// coefficients (the coarse layer) and one more, in three layers, so the last two are empty:
/// it decodes, to what version 12 decodes within the quantizer's step.
#[test]
fn a_layer_above_empty_ones_decodes_without_its_cap() {
    use wavesplat_codec::family::Family;
    use wavesplat_compressor::encode::TileChoice;
    let n = 16usize;
    let data: Vec<f32> = (0..n * n * n)
        .map(|i| {
            let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
            let block = 1.0 + (x / 4 + 4 * (y / 4) + 16 * (z / 4)) as f32;
            let cell = (4..6).contains(&x) && (4..6).contains(&y) && (4..6).contains(&z);
            block
                + if !cell {
                    0.0
                } else if x % 2 == 0 {
                    50.0
                } else {
                    -50.0
                }
        })
        .collect();
    let vol = Volume::new([n; 3], [1.0; 3], vec![data]).unwrap();
    let decoded_with = |version: u16| {
        let o = CompressOptions {
            family: Family::Haar,
            levels: Some(2),
            margin: Some(0),
            offset: Some(0.0),
            tile: TileChoice::Size(8),
            layers: Some(3),
            refine: None,
            target: Target::Coefficients(65),
            format_version: version,
            ..Default::default()
        };
        let bytes = compress(&vol, &o, &|_, _| {}).unwrap().bytes;
        let h = parse_file(&bytes).unwrap().header;
        (h, decompress(&bytes).unwrap())
    };
    let (h13, v13) = decoded_with(COMPACT_HEADER_VERSION);
    assert!(
        h13.layer_bounds.iter().skip(1).all(|b| b.is_infinite()),
        "the score layers' bounds: {:?}",
        h13.layer_bounds
    );
    assert!(h13.substreams.iter().flatten().any(|s| s.w0.is_infinite()));
    let (_, v12) = decoded_with(PRIORS_VERSION);
    let worst = v13.channels()[0]
        .iter()
        .zip(&v12.channels()[0])
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(
        worst.is_finite() && worst < 5.0,
        "largest difference {worst}"
    );
}
