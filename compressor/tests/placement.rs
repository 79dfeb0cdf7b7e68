//! The volume's placement in patient space travels through the `.wsp` header: written by the
//! encoder, validated on read, returned by the decoder; version 3 files (before placement)
//! still read, older versions are refused with a message saying what to do.

use wavesplat_codec::format::{
    parse_file, read_header_section, write_file_version, FormatError, MAGIC,
    OLDEST_READABLE_VERSION, VERSION,
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

fn file(v: &Volume) -> Vec<u8> {
    let opts = CompressOptions {
        target: Target::Fraction(0.3),
        refine: None,
        ..CompressOptions::default()
    };
    compress(v, &opts, &|_, _| {}).unwrap().bytes
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

/// Rewrites the header's `i`-th f64 of the placement (0..3 origin, 3..12 directions) and fixes
/// the header CRC.
fn patch_placement(bytes: &[u8], i: usize, value: f64) -> Vec<u8> {
    let mut b = bytes.to_vec();
    let len = u32::from_le_bytes(b[6..10].try_into().unwrap()) as usize;
    let hb = 10;
    // The header starts with three varint dims and three f32 spacings, then the flag byte.
    let mut p = hb;
    for _ in 0..3 {
        while b[p] & 0x80 != 0 {
            p += 1;
        }
        p += 1;
    }
    p += 12;
    assert_eq!(b[p], 1, "placement flag");
    let at = p + 1 + 8 * i;
    b[at..at + 8].copy_from_slice(&value.to_le_bytes());
    let crc = crc32fast::hash(&b[hb..hb + len]);
    b[hb + len..hb + len + 4].copy_from_slice(&crc.to_le_bytes());
    b
}

#[test]
fn hostile_placements_and_old_versions_are_refused() {
    let bytes = file(&placed());
    assert!(read_header_section(&patch_placement(&bytes, 0, 0.0)).is_ok());
    for (i, v) in [
        (1, f64::NAN),
        (2, f64::INFINITY),
        (0, 1e300),
        (3, 0.0),
        (4, 0.5),
        (11, 2.0),
    ] {
        let e = read_header_section(&patch_placement(&bytes, i, v)).unwrap_err();
        assert!(matches!(e, FormatError::Invalid { .. }), "{i} {v}: {e}");
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
    let v3 = write_file_version(&parsed.header, &packets, 3).unwrap();
    assert_eq!(u16::from_le_bytes([v3[4], v3[5]]), 3);
    assert_ne!(v3, bytes);
    let back = parse_file(&v3).unwrap();
    assert_eq!(back.header, parsed.header);
    assert_eq!(back.packets, parsed.packets);
    assert_eq!(
        decompress(&v3).unwrap().channels(),
        decompress(&bytes).unwrap().channels()
    );
    let placed_header = parse_file(&file(&placed())).unwrap().header;
    assert!(write_file_version(&placed_header, &packets, 3).is_err());
    assert!(write_file_version(&parsed.header, &packets, VERSION + 1).is_err());
}
