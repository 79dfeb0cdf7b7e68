//! NIfTI-1 `.hdr` + `.img` pairs (magic `ni1`, as SPM, FSL's `NIFTI_PAIR` and the OASIS data
//! set write them) and Analyze 7.5 (no NIfTI magic): a pair reads exactly as the same volume
//! in one `.nii` does (scaling, byte order, datatypes, placement), whole and region by region,
//! plain and gzip-compressed on either side, as a time series when 4D; its source listing and
//! bundle carry the `.img`; Analyze reads with no placement; a missing `.img`, a `.img` given
//! alone and a header of the wrong kind are clear errors naming the files.

mod common;

use common::cut;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use wavesplat_codec::volume::Volume;
use wavesplat_compressor::reader::region::RegionReader;
use wavesplat_compressor::reader::{
    decode_source, read_volume, time_points, unpack_bundle, Format, ReadError, SourceFiles,
    SourceListing,
};

const DIMS: [usize; 3] = [7, 5, 4];

/// A NIfTI-1 header (`magic` `n+1` or `ni1`; anything else makes an Analyze 7.5 header, whose
/// orientation bytes are filled with what Analyze keeps there) with an sform placement,
/// scaling and `vox_offset`.
#[allow(clippy::too_many_arguments)]
fn header(
    dim: [u16; 8],
    datatype: i16,
    bitpix: i16,
    big: bool,
    slope: f32,
    inter: f32,
    vox_offset: f32,
    magic: &[u8; 4],
) -> Vec<u8> {
    let mut h = vec![0u8; 348];
    macro_rules! w {
        ($off:expr, $v:expr) => {{
            let b = if big {
                $v.to_be_bytes()
            } else {
                $v.to_le_bytes()
            };
            h[$off..$off + b.len()].copy_from_slice(&b);
        }};
    }
    w!(0, 348i32);
    for (i, d) in dim.iter().enumerate() {
        w!(40 + 2 * i, *d);
    }
    w!(70, datatype);
    w!(72, bitpix);
    for (i, p) in [1.0f32, 0.8, 1.5, 3.0, 2.5, 1.0, 1.0, 1.0]
        .iter()
        .enumerate()
    {
        w!(76 + 4 * i, *p);
    }
    w!(108, vox_offset);
    w!(112, slope);
    w!(116, inter);
    h[123] = 2 | 8; // xyzt_units: mm, s
    w!(254, 1i16); // sform_code: scanner
    let rows = [
        [0.0f32, -1.5, 0.0, 90.0],
        [0.8, 0.0, 0.0, -126.0],
        [0.0, 0.0, 3.0, -72.0],
    ];
    for (r, row) in rows.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            w!(280 + 16 * r + 4 * c, *v);
        }
    }
    if magic == b"n+1\0" || magic == b"ni1\0" {
        h[344..348].copy_from_slice(magic);
    } else {
        // Analyze 7.5: `orient` and `originator` where NIfTI has qform_code (and so on), and
        // `smin` where NIfTI has its magic.
        h[252] = 1;
        h[253..263].copy_from_slice(&[0, 45, 0, 63, 0, 36, 0, 0, 0, 0]);
        h[344..348].copy_from_slice(magic);
    }
    h
}

fn write(path: &Path, bytes: &[u8], gz: bool) {
    let f = File::create(path).unwrap();
    if gz {
        let mut e = flate2::write::GzEncoder::new(f, flate2::Compression::fast());
        e.write_all(bytes).unwrap();
        e.finish().unwrap();
    } else {
        let mut f = f;
        f.write_all(bytes).unwrap();
    }
}

/// Int16 samples (x fastest) of `points` volumes of [`DIMS`], in the byte order asked.
fn i16_samples(points: usize, big: bool) -> Vec<u8> {
    let n = DIMS.iter().product::<usize>() * points;
    (0..n)
        .flat_map(|i| {
            let v = (i * 97 % 2000) as i16 - 1000;
            if big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        })
        .collect()
}

fn dims_u16(points: u16) -> [u16; 8] {
    let d = DIMS.map(|d| d as u16);
    let ndim = if points > 1 { 4 } else { 3 };
    [ndim, d[0], d[1], d[2], points, 1, 1, 1]
}

/// Writes `stem.hdr` (`.hdr.gz`) and `stem.img` (`.img.gz`) in `dir`; returns the header.
fn write_pair(
    dir: &Path,
    stem: &str,
    head: &[u8],
    data: &[u8],
    hdr_gz: bool,
    img_gz: bool,
) -> PathBuf {
    let hdr = dir.join(format!("{stem}.hdr{}", if hdr_gz { ".gz" } else { "" }));
    let img = dir.join(format!("{stem}.img{}", if img_gz { ".gz" } else { "" }));
    write(&hdr, head, hdr_gz);
    write(&img, data, img_gz);
    hdr
}

/// The region reader of `path` gives `want` whole and box by box, read from the files (not
/// decoded whole).
fn regions_match(path: &Path, want: &Volume) {
    let name = path.display().to_string();
    let r = RegionReader::open(path, None).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert!(!r.in_memory(), "{name}");
    assert_eq!(r.dims(), want.dims(), "{name}");
    assert_eq!(r.spacing(), want.spacing(), "{name}");
    assert_eq!(r.placement(), want.placement(), "{name}");
    for (o, s) in [
        ([0, 0, 0], DIMS),
        ([0, 0, 0], [1, 1, 1]),
        ([6, 4, 3], [1, 1, 1]),
        ([1, 2, 1], [3, 2, 2]),
        ([0, 1, 1], [7, 3, 2]),
        ([0, 0, 1], [7, 5, 2]),
    ] {
        let got = r
            .read_region(o, s)
            .unwrap_or_else(|e| panic!("{name} at {o:?} size {s:?}: {e}"));
        assert_eq!(got, cut(want, o, s), "{name} at {o:?} size {s:?}");
    }
}

#[test]
fn a_pair_reads_as_the_same_volume_in_one_file_whole_and_by_region() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for big in [false, true] {
        let data = i16_samples(1, big);
        // The same volume as a single file: the reference.
        let mut single = header(dims_u16(1), 4, 16, big, 2.0, -1.0, 352.0, b"n+1\0");
        single.extend_from_slice(&[0; 4]);
        single.extend_from_slice(&data);
        let nii = d.join(format!("ref_{big}.nii"));
        write(&nii, &single, false);
        let want = read_volume(&nii, None).unwrap();
        assert!(want.placement().is_some());
        assert_eq!(want.channel(0)[1], 2.0 * (97.0 - 1000.0) - 1.0);
        for hdr_gz in [false, true] {
            for img_gz in [false, true] {
                // Data at byte 0 of the .img, as pairs usually have it, and after 16 bytes.
                for offset in [0usize, 16] {
                    let head = header(dims_u16(1), 4, 16, big, 2.0, -1.0, offset as f32, b"ni1\0");
                    let img = [vec![0xAB; offset], data.clone()].concat();
                    let stem = format!("p_{big}_{hdr_gz}_{img_gz}_{offset}");
                    let hdr = write_pair(d, &stem, &head, &img, hdr_gz, img_gz);
                    assert_eq!(Format::from_name(&hdr), Some(Format::Nifti));
                    let got = read_volume(&hdr, None).unwrap_or_else(|e| panic!("{stem}: {e}"));
                    assert_eq!(got, want, "{stem}");
                    regions_match(&hdr, &want);
                    assert_eq!(time_points(&hdr, None).unwrap(), 1, "{stem}");
                }
            }
        }
    }
    // Upper-case names find their upper-case data file; other datatypes read too.
    let n = DIMS.iter().product::<usize>();
    let f32s: Vec<u8> = (0..n)
        .flat_map(|i| (i as f32 * 0.25 - 7.0).to_le_bytes())
        .collect();
    let head = header(dims_u16(1), 16, 32, false, 0.0, 5.0, 0.0, b"ni1\0");
    std::fs::write(d.join("UP.HDR"), &head).unwrap();
    std::fs::write(d.join("UP.IMG"), &f32s).unwrap();
    let v = read_volume(&d.join("UP.HDR"), None).unwrap();
    assert_eq!(v.channel(0)[3], 3.0 * 0.25 - 7.0, "slope 0: no scaling");
    regions_match(&d.join("UP.HDR"), &v);
    let rgb: Vec<u8> = (0..n * 3).map(|i| (i * 7 % 256) as u8).collect();
    let head = header(dims_u16(1), 128, 24, false, 1.0, 0.0, 0.0, b"ni1\0");
    let hdr = write_pair(d, "rgb", &head, &rgb, false, true);
    let v = read_volume(&hdr, None).unwrap();
    assert_eq!(v.channel_count(), 3);
    assert_eq!(v.channel(2)[1], 5.0 * 7.0);
    regions_match(&hdr, &v);
}

#[test]
fn a_4d_pair_is_a_time_series() {
    let dir = tempfile::tempdir().unwrap();
    let data = i16_samples(3, false);
    let head = header(dims_u16(3), 4, 16, false, 1.0, 0.0, 0.0, b"ni1\0");
    let mut single = header(dims_u16(3), 4, 16, false, 1.0, 0.0, 352.0, b"n+1\0");
    single.extend_from_slice(&[0; 4]);
    single.extend_from_slice(&data);
    let nii = dir.path().join("ref.nii");
    write(&nii, &single, false);
    let want = RegionReader::open_series(&nii, None).unwrap();
    for img_gz in [false, true] {
        let hdr = write_pair(
            dir.path(),
            &format!("fmri_{img_gz}"),
            &head,
            &data,
            false,
            img_gz,
        );
        assert_eq!(time_points(&hdr, None).unwrap(), 3);
        let e = read_volume(&hdr, None).unwrap_err();
        assert!(matches!(e, ReadError::TimeSeries { points: 3, .. }), "{e}");
        let e = RegionReader::open(&hdr, None).unwrap_err();
        assert!(matches!(e, ReadError::TimeSeries { points: 3, .. }), "{e}");
        let r = RegionReader::open_series(&hdr, None).unwrap();
        assert_eq!(r.time_points(), 3);
        assert_eq!(r.time_step(), Some(2.5));
        for t in 0..3 {
            for (o, s) in [([0, 0, 0], DIMS), ([1, 2, 1], [3, 2, 2])] {
                assert_eq!(
                    r.read_region_at(t, o, s).unwrap(),
                    want.read_region_at(t, o, s).unwrap(),
                    "time point {t}"
                );
            }
        }
        // `compress` takes it as a series, read in place.
        let series = wavesplat_compressor::series::open_series_path(&hdr, None).unwrap();
        assert!(series.is_some());
    }
}

#[test]
fn a_pairs_listing_and_bundle_carry_its_img() {
    let dir = tempfile::tempdir().unwrap();
    let data = i16_samples(1, false);
    let head = header(dims_u16(1), 4, 16, false, 1.0, 0.0, 0.0, b"ni1\0");
    for (hdr_gz, img_gz) in [(false, false), (true, true), (false, true)] {
        let stem = format!("l_{hdr_gz}_{img_gz}");
        let hdr = write_pair(dir.path(), &stem, &head, &data, hdr_gz, img_gz);
        let img = format!("{stem}.img{}", if img_gz { ".gz" } else { "" });
        let listing = SourceListing::list(&hdr, None).unwrap();
        assert_eq!(listing.format, Some(Format::Nifti));
        let names: Vec<&str> = listing.files.iter().map(|(n, _, _)| n.as_str()).collect();
        assert_eq!(names[1], img, "{stem}");
        assert_eq!(names.len(), 2);
        // The bytes hashed and uploaded are the gathered ones, and decode to the volume.
        let gathered = SourceFiles::gather(&hdr, None).unwrap();
        let mut streamed = Vec::new();
        listing.write_to(&mut streamed).unwrap();
        assert!(streamed == gathered.to_bytes(), "{stem}");
        assert_eq!(listing.byte_len(), streamed.len() as u64);
        let want = read_volume(&hdr, None).unwrap();
        let back = SourceFiles::from_bytes(streamed.clone(), &hdr).unwrap();
        assert_eq!(decode_source(&back, None).unwrap(), want, "{stem}");
        // A worker unpacks the upload and reads it by region from the files.
        let up = tempfile::tempdir().unwrap();
        let unpacked = unpack_bundle(&mut streamed.as_slice(), up.path()).unwrap();
        assert_eq!(unpacked.files, 2);
        let r = RegionReader::open(&unpacked.primary, None).unwrap();
        assert_eq!(r.read_region([0; 3], DIMS).unwrap(), want, "{stem}");
    }
}

#[test]
fn a_missing_or_lone_img_and_a_wrong_magic_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let head = header(dims_u16(1), 4, 16, false, 1.0, 0.0, 0.0, b"ni1\0");
    // No .img: every way in says which file it looked for.
    for (name, first, second) in [
        ("lone.hdr", "lone.img", "lone.img.gz"),
        ("lone_gz.hdr.gz", "lone_gz.img.gz", "lone_gz.img"),
    ] {
        let p = d.join(name);
        write(&p, &head, name.ends_with(".gz"));
        let errors = [
            read_volume(&p, None).unwrap_err(),
            RegionReader::open(&p, None).unwrap_err(),
            SourceListing::list(&p, None).unwrap_err(),
            time_points(&p, None)
                .ok()
                .and_then(|_| RegionReader::open_series(&p, None).err())
                .unwrap(),
        ];
        for e in errors {
            assert!(matches!(e, ReadError::MissingPairData { .. }), "{e}");
            let msg = e.to_string();
            let looked = format!(
                "no {} nor {}",
                d.join(first).display(),
                d.join(second).display()
            );
            assert!(msg.contains(&looked), "{msg}");
            assert!(msg.contains(name), "{msg}");
        }
    }
    // The .img given alone names its header (with a raw layout it is read as raw samples).
    let data = i16_samples(1, false);
    let hdr = write_pair(d, "half", &head, &data, false, false);
    let img = d.join("half.img");
    for e in [
        read_volume(&img, None).unwrap_err(),
        RegionReader::open(&img, None).unwrap_err(),
    ] {
        assert!(matches!(e, ReadError::Unsupported { .. }), "{e}");
        assert!(e.to_string().contains(&hdr.display().to_string()), "{e}");
    }
    let spec = wavesplat_compressor::reader::RawSpec::new(
        DIMS,
        wavesplat_compressor::reader::RawDtype::I16,
    );
    assert_eq!(
        read_volume(&img, Some(&spec)).unwrap().channel(0),
        read_volume(&hdr, None).unwrap().channel(0)
    );
    // A single file's magic in a .hdr, and a pair's in a .nii, say what to do.
    let p = write_pair(
        d,
        "single",
        &header(dims_u16(1), 4, 16, false, 1.0, 0.0, 0.0, b"n+1\0"),
        &data,
        false,
        false,
    );
    let e = read_volume(&p, None).unwrap_err();
    assert!(
        e.to_string().contains("n+1") && e.to_string().contains(".nii"),
        "{e}"
    );
    assert!(RegionReader::open(&p, None).is_err());
    let nii = d.join("pair.nii");
    write(&nii, &[head.clone(), data.clone()].concat(), false);
    for e in [
        read_volume(&nii, None).unwrap_err(),
        RegionReader::open(&nii, None).unwrap_err(),
    ] {
        assert!(e.to_string().contains(".hdr"), "{e}");
    }
    // A .hdr of another kind (ENVI's text header) is no readable header.
    std::fs::write(d.join("envi.hdr"), b"ENVI\nsamples = 7\nlines = 5\n").unwrap();
    std::fs::write(d.join("envi.img"), &data).unwrap();
    assert!(read_volume(&d.join("envi.hdr"), None).is_err());
    // A short .img is truncated, naming it.
    let p = write_pair(d, "short", &head, &data[..20], false, false);
    for e in [
        read_volume(&p, None).unwrap_err(),
        RegionReader::open(&p, None).unwrap_err(),
    ] {
        assert!(matches!(e, ReadError::Truncated { .. }), "{e}");
        assert!(e.to_string().contains("short.img"), "{e}");
    }
}

#[test]
fn analyze_reads_with_no_placement() {
    let dir = tempfile::tempdir().unwrap();
    for (big, hdr_gz, img_gz) in [(false, false, false), (true, true, true)] {
        let data = i16_samples(1, big);
        // SPM's scale factor in funused1; `smin` where NIfTI's magic would be.
        let head = header(dims_u16(1), 4, 16, big, 0.5, 0.0, 0.0, &[0, 0, 0, 0]);
        let stem = format!("oasis_{big}");
        let hdr = write_pair(dir.path(), &stem, &head, &data, hdr_gz, img_gz);
        let v = read_volume(&hdr, None).unwrap_or_else(|e| panic!("{stem}: {e}"));
        assert_eq!(v.dims(), DIMS);
        assert_eq!(v.spacing(), [0.8, 1.5, 3.0]);
        assert_eq!(v.placement(), None, "Analyze's orientation is unknown");
        assert_eq!(v.channel(0)[1], 0.5 * (97.0 - 1000.0));
        regions_match(&hdr, &v);
        assert_eq!(time_points(&hdr, None).unwrap(), 1);
        // Its listing carries the .img too.
        assert_eq!(SourceListing::list(&hdr, None).unwrap().files.len(), 2);
    }
    // A 4D Analyze file is a series, with no time unit.
    let head = header(dims_u16(2), 4, 16, false, 1.0, 0.0, 0.0, &[7, 0, 0, 0]);
    let hdr = write_pair(
        dir.path(),
        "a4d",
        &head,
        &i16_samples(2, false),
        false,
        false,
    );
    let r = RegionReader::open_series(&hdr, None).unwrap();
    assert_eq!(
        (r.time_points(), r.time_step(), r.placement()),
        (2, None, None)
    );
    // An Analyze header is not a single file's.
    let nii = dir.path().join("analyze.nii");
    write(&nii, &[head, vec![0; 4]].concat(), false);
    let e = read_volume(&nii, None).unwrap_err();
    assert!(e.to_string().contains("Analyze"), "{e}");
}
