//! Replays the fuzz targets' kept corpora (`fuzz/corpus/TARGET/`, seeds and anything the fuzzer
//! found worth keeping) through the same target bodies, on the stable toolchain: every input
//! must be handled without a panic. The coverage-guided runs themselves use `cargo +nightly
//! fuzz run TARGET` (see BENCHMARKS.md for executions and findings).

#[path = "../fuzz/targets.rs"]
mod targets;

/// What the reader targets' heap bound is checked with here: a counting global allocator. It
/// counts the whole process, so the tests of this file run one at a time (`serial`): a test
/// freeing memory while another measures would lower that measure (seen: a 1000-byte
/// allocation measured as 588 bytes).
mod meter {
    use peak_alloc::PeakAlloc;
    use std::sync::Mutex;

    #[global_allocator]
    static PEAK: PeakAlloc = PeakAlloc;
    static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());
    static SERIAL: Mutex<()> = Mutex::new(());

    /// Held for the whole of each test of this file.
    pub fn serial() -> std::sync::MutexGuard<'static, ()> {
        SERIAL.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Runs `f`; returns the peak of the live heap during it, above where it began.
    pub fn peak_during(f: impl FnOnce()) -> usize {
        let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
        let start = PEAK.current_usage();
        PEAK.reset_peak_usage();
        f();
        PEAK.peak_usage().saturating_sub(start)
    }
}

use std::path::{Path, PathBuf};
use wavesplat_codec::format::parse_file;

fn corpus(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fuzz/corpus")
        .join(target);
    let mut out: Vec<(PathBuf, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| {
            let p = e.unwrap().path();
            let b = std::fs::read(&p).unwrap();
            (p, b)
        })
        .collect();
    out.sort();
    assert!(!out.is_empty(), "empty corpus {}", dir.display());
    out
}

#[test]
fn every_kept_input_of_every_target_is_handled() {
    let _serial = meter::serial();
    let mut total = 0;
    for (target, run) in [
        ("file", targets::file as fn(&[u8])),
        ("raw", targets::raw),
        ("nifti", targets::nifti),
        ("dicom", targets::dicom),
        ("nrrd", targets::nrrd),
        ("metaimage", targets::metaimage),
        ("tiff", targets::tiff),
        ("zarr", targets::zarr),
        ("grpc", targets::grpc),
    ] {
        for (_, data) in corpus(target) {
            run(&data);
            total += 1;
        }
    }
    for coder in ["sigmap", "fast", "range", "huffman"] {
        let bytes = std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("fuzz/corpus/headers/{coder}.wsp")),
        )
        .unwrap();
        let header = parse_file(&bytes).unwrap().header;
        for (_, data) in corpus(&format!("packet_{coder}")) {
            targets::packet(&header, &data);
            total += 1;
        }
    }
    assert!(total >= 20, "{total} inputs");
}

#[test]
fn the_packet_seeds_are_valid_packets_of_their_headers() {
    let _serial = meter::serial();
    // So the fuzzer starts from inputs that reach the decoders' depths.
    for coder in ["sigmap", "fast", "range", "huffman"] {
        let bytes = std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("fuzz/corpus/headers/{coder}.wsp")),
        )
        .unwrap();
        let header = parse_file(&bytes).unwrap().header;
        for (p, data) in corpus(&format!("packet_{coder}")) {
            if p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with('p'))
            {
                wavesplat_codec::format::packet::decode_packet(&header, &data)
                    .unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            }
        }
    }
}

#[test]
fn the_reader_seeds_decode_to_volumes() {
    let _serial = meter::serial();
    // So the reader targets start from inputs that reach the decoders' depths.
    use wavesplat_compressor::reader::{
        decode_source, decode_source_channel, Format, ReadError, SourceFiles,
    };
    for (target, origin, format) in [
        ("dicom", "series", Format::Dicom),
        ("nrrd", "fuzz.nhdr", Format::Nrrd),
        ("metaimage", "fuzz.mhd", Format::MetaImage),
        ("tiff", "fuzz.tif", Format::Tiff),
        ("zarr", "fuzz.zarr", Format::Zarr),
    ] {
        let mut seeds = 0;
        for (p, data) in corpus(target) {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            // Findings (`oom_*`, `caught_*`) and the units the fuzzer kept (named by their
            // SHA-1) are replayed above, not decoded here.
            let unit = name.len() == 40 && name.bytes().all(|b| b.is_ascii_hexdigit());
            if unit
                || ["crash", "oom", "slow", "caught"]
                    .iter()
                    .any(|p| name.starts_with(p))
            {
                continue;
            }
            let mut src = SourceFiles::from_bytes(data, Path::new(origin)).unwrap();
            src.format = Some(format);
            // A seed of several channels: its last, as a job reads it.
            let v = match decode_source(&src, None) {
                Err(ReadError::Channels { channels, .. }) => {
                    decode_source_channel(&src, None, Some(channels as usize - 1))
                }
                read => read,
            }
            .unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            assert_eq!(v.dims(), [4, 3, 2], "{}", p.display());
            seeds += 1;
        }
        assert!(seeds >= 4, "{target}: {seeds} seeds");
    }
}

#[test]
fn the_meter_sees_a_large_allocation() {
    let _serial = meter::serial();
    // The bound the reader targets check is only as good as the count behind it. The count is
    // the whole process's, and the test harness's own thread allocates and frees (the results
    // of the tests before) while a test of this file measures: a measure can come out a little
    // lower than what was allocated (seen: 48 MiB measured as 24 bytes less), so the checks
    // allow that much.
    const HARNESS_SLACK: usize = 64 << 10;
    let peak = meter::peak_during(|| {
        let v = vec![1u8; 48 << 20];
        std::hint::black_box(&v);
    });
    assert!(peak + HARNESS_SLACK >= 48 << 20, "{peak}");
    assert!(peak > targets::alloc_bound(1024), "{peak}");
    let small = meter::peak_during(|| {
        std::hint::black_box(vec![0u8; 256 << 10]);
    });
    assert!(
        ((256 << 10) - HARNESS_SLACK..1 << 20).contains(&small),
        "{small}"
    );
}
