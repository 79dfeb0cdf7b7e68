//! The compressor on volumes unlike the skull-stripped MNI brain that archives hold: one voxel
//! wide, thin slabs, non-zero faces, CT values (negative, air at −1000, a body through the
//! faces), a wide 16-bit range, anisotropic boxes and RGB. Round trips, perfect reconstruction,
//! bit-exact decoding, thread-count independence and byte targets on each; and the memory cap.

use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::decode_packet;
use wavesplat_codec::format::parse_file;
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::decode::decompress;
use wavesplat_compressor::encode::{
    compress, deepest_compared, default_levels, memory_estimate, worth_going_shallower,
    CompressError, CompressOptions, Compressed, Target, TileChoice,
};
use wavesplat_compressor::phantom::Phantom;

/// Shepp–Logan with `add` on every voxel (non-zero faces when `add` ≠ 0).
fn shepp(dims: [usize; 3], scale: f32, add: f32) -> Volume {
    let v = Phantom::SheppLogan.generate(dims);
    let ch: Vec<f32> = v.channel(0).iter().map(|x| x * scale + add).collect();
    Volume::new(dims, [1.0; 3], vec![ch]).unwrap()
}

/// The test set: (name, volume).
fn archive() -> Vec<(&'static str, Volume)> {
    let line: Vec<f32> = (0..40)
        .map(|i| ((i as f32) * 0.7).sin() * 50.0 + 60.0)
        .collect();
    let mut wide = shepp([28, 26, 24], 250.0, 0.0);
    {
        // A tiny very bright spot on top of the 0..63 750 range: 16-bit data, wide range.
        let mut ch = wide.channel(0).to_vec();
        let i = wide.index(14, 13, 12);
        ch[i] = 65_535.0;
        wide = Volume::new(wide.dims(), [1.0; 3], vec![ch]).unwrap();
    }
    vec![
        (
            "1x1x40",
            Volume::new([1, 1, 40], [1.0; 3], vec![line]).unwrap(),
        ),
        ("slab16", shepp([40, 36, 16], 1.0, 0.0)),
        ("slab32", shepp([36, 30, 32], 1.0, 0.0)),
        ("non-zero faces", shepp([30, 28, 26], 1.0, 100.0)),
        ("ct", Phantom::Ct.generate([36, 30, 20])),
        ("wide16", wide),
        ("aniso", shepp([48, 14, 26], 1.0, 0.0)),
        ("rgb", Phantom::RgbHead.generate([24, 22, 20])),
    ]
}

fn rel_l2(a: &[f32], b: &[f32]) -> f64 {
    let num: f64 = a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
    let den: f64 = b.iter().map(|y| (*y as f64).powi(2)).sum();
    (num / den.max(1e-300)).sqrt()
}

/// Every coefficient at a fine step: the decoded volume is the input (perfect reconstruction
/// through the whole pipeline), for every shape.
#[test]
fn all_coefficients_reproduce_every_archive_volume() {
    for (name, vol) in archive() {
        let o = CompressOptions {
            target: Target::All,
            step: 1e-4,
            ..Default::default()
        };
        let c = compress(&vol, &o, &|_, _| {}).unwrap();
        let back = decompress(&c.bytes).unwrap();
        assert_eq!(back.dims(), vol.dims(), "{name}");
        assert_eq!(back.channel_count(), vol.channel_count(), "{name}");
        let e = rel_l2(&back.to_interleaved(), &vol.to_interleaved());
        assert!(e < 1e-4, "{name}: rel L2 {e}");
    }
}

/// Lossy files decode to exactly the encoder's reconstruction, packet by packet, and the
/// decoded volume approximates the input.
#[test]
fn lossy_round_trips_are_bit_exact_on_every_archive_volume() {
    for (name, vol) in archive() {
        let o = CompressOptions {
            target: Target::Fraction(0.08),
            tile: TileChoice::Size(16),
            layers: Some(2),
            ..Default::default()
        };
        let c = compress(&vol, &o, &|_, _| {}).unwrap();
        let file = parse_file(&c.bytes).unwrap();
        assert_eq!(file.packets.len(), c.reconstruction.len(), "{name}");
        for (p, expect) in file.packets.iter().zip(&c.reconstruction) {
            let d = decode_packet(&file.header, p).unwrap();
            assert_eq!(&d.coefficients, expect, "{name}");
        }
        let back = decompress(&c.bytes).unwrap();
        let e = rel_l2(&back.to_interleaved(), &vol.to_interleaved());
        assert!(e < 0.5, "{name}: rel L2 {e}");
    }
}

#[test]
fn archive_volumes_compress_the_same_on_any_thread_count() {
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let three = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .unwrap();
    for (name, vol) in archive() {
        let o = CompressOptions {
            target: Target::Bytes(4000.min(vol.voxel_count() as u64)),
            ..Default::default()
        };
        let a = one.install(|| compress(&vol, &o, &|_, _| {}).map(|c| c.bytes));
        let b = three.install(|| compress(&vol, &o, &|_, _| {}).map(|c| c.bytes));
        match (a, b) {
            (Ok(a), Ok(b)) => assert_eq!(a, b, "{name}"),
            (Err(_), Err(_)) => {}
            (a, b) => panic!("{name}: {:?} vs {:?}", a.is_ok(), b.is_ok()),
        }
    }
}

/// A byte target is met from below within 2 % on every volume, at small and large sizes
/// (percentages of the 8-bit sample count, like the peers' tables, but at least 1 500 bytes:
/// below that the header and packet framing make the size jump by more than 2 %).
#[test]
fn byte_targets_are_met_within_two_percent_on_every_archive_volume() {
    for (name, vol) in archive() {
        let samples = (vol.voxel_count() * vol.channel_count()) as f64;
        for pct in [1.0, 4.0, 12.0] {
            let target = ((samples * pct / 100.0) as u64).max(1500);
            let o = CompressOptions {
                target: Target::Bytes(target),
                ..Default::default()
            };
            match compress(&vol, &o, &|_, _| {}) {
                Ok(c) => {
                    let size = c.bytes.len() as f64;
                    assert!(size <= target as f64, "{name} {pct} %: {size} > {target}");
                    // Unless every coefficient fits, the file fills the target.
                    let everything = c.stats.kept >= c.stats.nonzero_coefficients;
                    assert!(
                        everything || size >= 0.98 * target as f64,
                        "{name} {pct} %: {size} < 98 % of {target}"
                    );
                }
                // Only a target below the smallest possible file may fail.
                Err(CompressError::TargetTooSmall { minimum, .. }) => {
                    assert!(minimum > target, "{name} {pct} %")
                }
                Err(e) => panic!("{name} {pct} %: {e}"),
            }
        }
    }
}

/// The memory cap: a limit above the estimate compresses, one below it is refused before any
/// work with a typed error naming both figures; the estimate grows with the volume and the
/// channels.
#[test]
fn memory_cap_is_honoured_with_a_clear_error() {
    let vol = Phantom::Ct.generate([30, 26, 22]);
    let o = CompressOptions {
        target: Target::Bytes(3000),
        ..Default::default()
    };
    let (needed, _) = memory_estimate(vol.dims(), 1, &o).unwrap();
    let fits = CompressOptions {
        memory_limit: Some(needed),
        ..o.clone()
    };
    assert!(compress(&vol, &fits, &|_, _| {}).is_ok());
    let tight = CompressOptions {
        memory_limit: Some(needed / 2),
        ..o.clone()
    };
    match compress(&vol, &tight, &|_, _| panic!("no work may start")) {
        Err(e @ CompressError::MemoryLimit { .. }) => {
            let CompressError::MemoryLimit {
                needed: n, limit, ..
            } = &e
            else {
                unreachable!()
            };
            assert_eq!((*n, *limit), (needed, needed / 2));
            let msg = e.to_string();
            assert!(msg.contains(&needed.to_string()) && msg.contains(&(needed / 2).to_string()));
        }
        other => panic!(
            "expected a memory-limit error, got {:?}",
            other.map(|c| c.stats)
        ),
    }
    // A 512³ volume's estimate: within 10 GB for one channel (the grid of the deepest depth a
    // comparison may reach, 608³ at M = 5, where the default's is 536³), and RGB needs more.
    let big = memory_estimate(
        [512; 3],
        1,
        &CompressOptions {
            target: Target::Bytes(512 * 512 * 512 * 2 / 80),
            ..Default::default()
        },
    )
    .unwrap()
    .0;
    let rgb = memory_estimate(
        [512; 3],
        3,
        &CompressOptions {
            target: Target::Bytes(512 * 512 * 512 * 3 / 80),
            ..Default::default()
        },
    )
    .unwrap()
    .0;
    assert!(big > needed && big < 10 << 30, "512³: {big}");
    assert!(rgb > big, "RGB 512³: {rgb}");
}

/// The faces' median is subtracted before the transform and restored on decode, so adding a
/// constant to a volume changes neither which coefficients a byte target keeps nor how well
/// it decodes (the padded grid would otherwise see a step along every face): the same
/// Shepp–Logan head at 0, +100 and −1000 (air) costs the same bytes for the same error. The
/// header records the offset, and files keep decoding to the input plus that constant.
#[test]
fn a_constant_added_to_the_volume_costs_nothing() {
    let dims = [30, 28, 26];
    let mut errors = Vec::new();
    for add in [0.0f32, 100.0, -1000.0] {
        let vol = shepp(dims, 1.0, add);
        let o = CompressOptions {
            target: Target::Bytes(1500),
            ..Default::default()
        };
        let c = compress(&vol, &o, &|_, _| {}).unwrap();
        let header = parse_file(&c.bytes).unwrap().header;
        assert_eq!(header.color.mean[0], f64::from(add), "offset at {add}");
        let back = decompress(&c.bytes).unwrap();
        // Error against the volume without the constant, measured the same way for each.
        let a: Vec<f32> = back.channel(0).iter().map(|x| x - add).collect();
        let b: Vec<f32> = vol.channel(0).iter().map(|x| x - add).collect();
        errors.push((add, c.bytes.len(), rel_l2(&a, &b)));
    }
    let (_, bytes0, err0) = errors[0];
    assert!(err0 < 0.5, "{errors:?}");
    for &(add, bytes, err) in &errors[1..] {
        assert!(bytes.abs_diff(bytes0) <= bytes0 / 50, "{add}: {errors:?}");
        assert!(err <= err0 * 1.05 + 1e-6, "{add}: {errors:?}");
    }
}

/// The mean over the three axis X-ray views (sums along x, y and z, every channel) of the log
/// of the view's squared error, in f64 on the decoded volume: computed here independently of
/// the compressor's own scoring.
fn log_view_error(original: &Volume, decoded: &Volume) -> f64 {
    let [nx, ny, nz] = original.dims();
    let mut energy = [0.0f64; 3];
    for c in 0..original.channel_count() {
        let (a, b) = (original.channel(c), decoded.channel(c));
        let mut views = [
            vec![0.0f64; ny * nz],
            vec![0.0; nx * nz],
            vec![0.0; nx * ny],
        ];
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    let i = original.index(x, y, z);
                    let d = f64::from(a[i]) - f64::from(b[i]);
                    views[0][y + ny * z] += d;
                    views[1][x + nx * z] += d;
                    views[2][x + nx * y] += d;
                }
            }
        }
        for (e, v) in energy.iter_mut().zip(&views) {
            *e += v.iter().map(|p| p * p).sum::<f64>();
        }
    }
    energy
        .iter()
        .map(|e| (e + f64::MIN_POSITIVE).ln())
        .sum::<f64>()
        / 3.0
}

/// Without a given depth, a byte target codes at whichever of the family's default depth and
/// one level less brings the X-ray views closer to the volume's, and goes on to shallower
/// depths while the shallowest wins and its file affords the next coarse band
/// ([`worth_going_shallower`]): the file is the one forced to that depth, and no worse than
/// the one forced to any depth the rule compared (without refinement, so the compared files
/// are the files). A low rate (0.2 % of the samples' bytes, at least 200 bytes) and a high one
/// (15 %) on every archive volume; each of the first two depths wins somewhere, so the choice
/// follows the data rather than a constant, and somewhere a third depth is compared.
#[test]
fn a_byte_target_keeps_the_depth_whose_views_come_closer() {
    let mut wins = std::collections::BTreeMap::<usize, usize>::new();
    // Points where a depth below the first two was compared, and where one past the default.
    let mut descended = 0;
    let mut deeper = 0;
    for (name, vol) in archive() {
        let samples = (vol.voxel_count() * vol.channel_count()) as f64;
        for pct in [0.2, 15.0] {
            let target = ((samples * pct / 100.0) as u64).max(200);
            let opts = |levels| CompressOptions {
                target: Target::Bytes(target),
                levels,
                refine: None,
                ..Default::default()
            };
            let Ok(auto) = compress(&vol, &opts(None), &|_, _| {}) else {
                continue;
            };
            let depth = auto.header.geometry.levels;
            let deepest = default_levels(vol.dims(), Family::Linear);
            let cap = deepest_compared(vol.dims(), Family::Linear);
            if deepest < 2 {
                assert_eq!(depth, deepest, "{name} {pct} %");
                continue;
            }
            // Forced files from the deepest the rule may compare down, each the oracle's file
            // at that depth.
            let forced: Vec<(usize, Compressed)> = (1..=cap)
                .rev()
                .filter_map(|m| match compress(&vol, &opts(Some(m)), &|_, _| {}) {
                    Ok(c) => Some((m, c)),
                    Err(CompressError::TargetTooSmall { .. }) => None,
                    Err(e) => panic!("{name} {pct} % M = {m}: {e}"),
                })
                .collect();
            let error = |m: usize| {
                let (_, f) = forced.iter().find(|(fm, _)| *fm == m).unwrap();
                log_view_error(&vol, &decompress(&f.bytes).unwrap())
            };
            let (_, same) = forced
                .iter()
                .find(|(m, _)| *m == depth)
                .unwrap_or_else(|| panic!("{name} {pct} %: M = {depth} was not forced"));
            assert_eq!(same.bytes, auto.bytes, "{name} {pct} %: M = {depth}");
            // The depths the rule compared: the default and one less, every depth down to the
            // chosen one (each won while it was the shallowest), and one below the chosen one
            // when its file affords that depth's coarse band.
            let worth = |m: usize| {
                forced
                    .iter()
                    .find(|(fm, _)| *fm == m)
                    .is_some_and(|(_, f)| {
                        worth_going_shallower(f.stats.kept, vol.channel_count(), &f.header.geometry)
                    })
            };
            // Below the first two only through depths whose files opened the gate.
            for m in depth + 1..deepest {
                assert!(
                    worth(m),
                    "{name} {pct} %: went below M = {m} without its gate"
                );
            }
            let mut compared: Vec<usize> = (depth.min(deepest)..=depth.max(deepest)).collect();
            compared.push(deepest - 1);
            if depth < deepest && worth(depth) {
                compared.push(depth - 1);
            }
            // The default or a deeper depth won over one level less: one level deeper was
            // compared too, up to the cap.
            let fits = |m: usize| forced.iter().any(|(fm, _)| *fm == m);
            if depth >= deepest && depth < cap && fits(deepest - 1) {
                compared.push(depth + 1);
                deeper += 1;
            }
            if compared.iter().any(|m| *m + 1 < deepest) {
                descended += 1;
            }
            for m in compared
                .iter()
                .filter(|m| forced.iter().any(|(fm, _)| fm == *m))
            {
                assert!(
                    error(depth) <= error(*m) + 1e-3,
                    "{name} {pct} %: chose M = {depth} ({}), M = {m} has {}",
                    error(depth),
                    error(*m)
                );
            }
            *wins.entry(depth).or_default() += 1;
        }
    }
    assert!(
        wins.get(&3).is_some_and(|w| *w > 0) && wins.get(&2).is_some_and(|w| *w > 0),
        "wins by depth {wins:?}"
    );
    assert!(
        descended > 0 && deeper > 0,
        "no point compared a third depth below ({descended}) or past the default ({deeper}); \
         wins {wins:?}"
    );
}

/// A volume smooth at its finest scales (`Phantom::Blobs`, 96³) is drawn closer by a
/// deeper transform than the default: a byte target compares past the default while the
/// deepest compared wins, takes the depth whose X-ray views come closest (the file forced to
/// that depth, byte for byte), and stops at the first deeper depth that loses.
#[test]
fn a_byte_target_goes_deeper_on_a_volume_smooth_at_its_finest_scales() {
    let vol = Phantom::Blobs.generate([96; 3]);
    let deepest = default_levels(vol.dims(), Family::Linear);
    let cap = deepest_compared(vol.dims(), Family::Linear);
    assert!(cap > deepest + 1, "the grid allows {cap} levels");
    for target in [600u64, 3000] {
        let opts = |levels| CompressOptions {
            target: Target::Bytes(target),
            levels,
            refine: None,
            ..Default::default()
        };
        let auto = compress(&vol, &opts(None), &|_, _| {}).unwrap();
        let depth = auto.header.geometry.levels;
        assert!(depth > deepest, "{target} B: M = {depth}");
        let error = |m: usize| {
            let f = compress(&vol, &opts(Some(m)), &|_, _| {}).unwrap();
            (log_view_error(&vol, &decompress(&f.bytes).unwrap()), f)
        };
        let (chosen, same) = error(depth);
        assert_eq!(same.bytes, auto.bytes, "{target} B: M = {depth}");
        for m in deepest..=(depth + 1).min(cap) {
            if m != depth {
                let (e, _) = error(m);
                assert!(
                    chosen < e,
                    "{target} B: M = {depth} ({chosen}), M = {m} ({e})"
                );
            }
        }
    }
}

/// A byte target that only one of the compared depths can meet is met at that depth; one that
/// neither can meet is refused naming the smallest file of either.
#[test]
fn a_target_too_small_for_one_depth_is_met_at_the_other() {
    let vol = shepp([30, 28, 26], 1.0, 0.0);
    let minimum = |levels| {
        let o = CompressOptions {
            target: Target::Bytes(1),
            levels,
            ..Default::default()
        };
        match compress(&vol, &o, &|_, _| {}) {
            Err(CompressError::TargetTooSmall { minimum, .. }) => minimum,
            other => panic!("M = {levels:?}: {:?}", other.map(|c| c.bytes.len())),
        }
    };
    let (m3, m2) = (minimum(Some(3)), minimum(Some(2)));
    assert_ne!(m3, m2, "the depths' smallest files differ");
    assert_eq!(minimum(None), m3.min(m2));
    let o = CompressOptions {
        target: Target::Bytes(m3.min(m2)),
        ..Default::default()
    };
    let c = compress(&vol, &o, &|_, _| {}).unwrap();
    assert!(c.bytes.len() as u64 <= m3.min(m2));
    assert_eq!(c.header.geometry.levels, if m2 < m3 { 2 } else { 3 });
}
