//! Region reads (issue 55): for every format, a [`RegionReader`] gives for any box exactly the
//! voxels, spacing and placement (moved to the box's first voxel) that `read_volume` gives
//! for that box of the whole; a raw file and a NIfTI file of more than 2³¹ voxels (sparse
//! files, nothing large written or allocated) open and read small regions; truncated files,
//! hostile headers and boxes outside the volume are clean errors.

mod common;

use common::cut;
use std::fs::File;
use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::Path;

use wavesplat_codec::volume::{Placement, Volume, VolumeError, MAX_VOXELS};
use wavesplat_compressor::reader::region::RegionReader;
use wavesplat_compressor::reader::{read_volume, Endian, RawDtype, RawSpec, ReadError};
use wavesplat_fixtures::{self as fixtures, DicomOptions, Layout, NrrdEncoding};

/// Boxes of a volume of `d`: the whole, single voxels at both corners, unaligned interior
/// boxes, whole rows, whole slabs, and boxes on each far edge (those that fit in `d`).
fn regions(d: [usize; 3]) -> Vec<([usize; 3], [usize; 3])> {
    let fits = |(o, s): &([usize; 3], [usize; 3])| (0..3).all(|a| s[a] > 0 && o[a] + s[a] <= d[a]);
    let all = vec![
        ([0, 0, 0], d),
        ([0, 0, 0], [1, 1, 1]),
        ([d[0] - 1, d[1] - 1, d[2] - 1], [1, 1, 1]),
        ([1, 2, 1], [3, 2, 2]),
        ([1, 1, 0], [d[0] - 2, 1, d[2]]),
        ([0, 1, 1], [d[0], 3, 2]),
        ([0, 0, 1], [d[0], d[1], 2]),
        ([d[0] - 2, 0, 0], [2, d[1], d[2]]),
        ([0, d[1] - 1, 0], [d[0], 1, d[2]]),
        ([2, 0, d[2] - 1], [3, d[1], 1]),
    ];
    all.into_iter().filter(fits).collect()
}

/// Opens `path` both ways and compares every box of [`regions`].
fn check(path: &Path, raw: Option<&RawSpec>) {
    let name = path.display().to_string();
    let whole = read_volume(path, raw).unwrap_or_else(|e| panic!("{name}: {e}"));
    let r = RegionReader::open(path, raw).unwrap_or_else(|e| panic!("{name}: {e}"));
    // Only ASCII NRRD is decoded whole; everything else is read by region (DICOM by slices).
    assert_eq!(r.in_memory(), name.contains("Ascii"), "{name}");
    assert_eq!(r.dims(), whole.dims(), "{name}");
    assert_eq!(r.voxel_count(), whole.voxel_count() as u128, "{name}");
    assert_eq!(r.channels(), whole.channel_count(), "{name}");
    assert_eq!(r.spacing(), whole.spacing(), "{name}");
    assert_eq!(r.placement(), whole.placement(), "{name}");
    for (o, s) in regions(whole.dims()) {
        let got = r
            .read_region(o, s)
            .unwrap_or_else(|e| panic!("{name} at {o:?} size {s:?}: {e}"));
        assert_eq!(got, cut(&whole, o, s), "{name} at {o:?} size {s:?}");
    }
    // The whole box is the whole volume, placement and all.
    assert_eq!(
        r.read_region([0; 3], whole.dims()).unwrap(),
        whole,
        "{name}"
    );
}

const DIMS: [usize; 3] = [7, 5, 4];

fn placed(channels: usize, value: impl Fn(usize, usize) -> f32) -> Volume {
    let n = DIMS.iter().product::<usize>();
    let data = (0..channels)
        .map(|c| (0..n).map(|i| value(i, c)).collect())
        .collect();
    Volume::new(DIMS, [0.7, 1.25, 2.5], data)
        .unwrap()
        .with_placement(Placement {
            origin: [-120.5, 30.25, 512.0],
            directions: [[0.6, 0.8, 0.0], [0.0, 0.0, -1.0], [-0.8, 0.6, 0.0]],
        })
        .unwrap()
}

fn encode(v: f64, dtype: RawDtype, endian: Endian, out: &mut Vec<u8>) {
    macro_rules! put {
        ($x:expr) => {
            out.extend_from_slice(&match endian {
                Endian::Little => $x.to_le_bytes(),
                Endian::Big => $x.to_be_bytes(),
            })
        };
    }
    match dtype {
        RawDtype::U8 => out.push(v as u8),
        RawDtype::I8 => out.push(v as i8 as u8),
        RawDtype::U16 => put!(v as u16),
        RawDtype::I16 => put!(v as i16),
        RawDtype::U32 => put!(v as u32),
        RawDtype::I32 => put!(v as i32),
        RawDtype::U64 => put!(v as u64),
        RawDtype::I64 => put!(v as i64),
        RawDtype::F32 => put!(v as f32),
        RawDtype::F64 => put!(v),
    }
}

#[test]
fn raw_regions_match_the_whole_for_every_dtype_endian_and_channel_count() {
    let dir = tempfile::tempdir().unwrap();
    let n = DIMS.iter().product::<usize>();
    for dtype in RawDtype::ALL {
        for endian in [Endian::Little, Endian::Big] {
            for channels in [1, 3] {
                let value = |i: usize, c: usize| {
                    let v = ((i * 37 + c * 11) % 251) as f64;
                    match dtype {
                        RawDtype::U8 => v,
                        RawDtype::I8 => v - 125.0,
                        RawDtype::U16 => v * 250.0,
                        RawDtype::I16 => v * 100.0 - 12000.0,
                        RawDtype::U32 => v * 1000.0 + 70000.0,
                        RawDtype::I32 => 5.0 - v * 1000.0,
                        RawDtype::U64 => v * 3.0 + 1e6,
                        RawDtype::I64 => v * 7.0 - 1e6,
                        RawDtype::F32 => v * 0.125 - 3.0,
                        RawDtype::F64 => v * 0.25 - 7.5,
                    }
                };
                let mut bytes = Vec::new();
                for i in 0..n {
                    for c in 0..channels {
                        encode(value(i, c), dtype, endian, &mut bytes);
                    }
                }
                let path = dir
                    .path()
                    .join(format!("{dtype}_{endian:?}_{channels}.raw"));
                std::fs::write(&path, &bytes).unwrap();
                let spec = RawSpec {
                    dims: DIMS,
                    dtype,
                    endian,
                    channels,
                    spacing: [0.5, 1.0, 2.5],
                    time_points: 1,
                    header_bytes: 0,
                };
                check(&path, Some(&spec));
            }
        }
    }
}

/// A raw file with a 512-byte header before its samples (`header_bytes`) reads by region
/// exactly as whole, as a volume and as a time series; a wrong header size is refused at open
/// with the total the description needs.
#[test]
fn raw_regions_skip_a_header() {
    let dir = tempfile::tempdir().unwrap();
    let n = DIMS.iter().product::<usize>();
    let mut bytes: Vec<u8> = (0..512).map(|i| (i % 7) as u8).collect();
    for i in 0..2 * n {
        encode(
            i as f64 * 3.0 - 500.0,
            RawDtype::I16,
            Endian::Little,
            &mut bytes,
        );
    }
    let path = dir.path().join("with_header.dat");
    std::fs::write(&path, &bytes).unwrap();
    let mut spec = RawSpec::new(DIMS, RawDtype::I16);
    spec.header_bytes = 512;
    spec.time_points = 2;
    let r = RegionReader::open_series(&path, Some(&spec)).unwrap();
    assert_eq!(r.time_points(), 2);
    let second = r.read_region_at(1, [0; 3], DIMS).unwrap();
    assert_eq!(second.channel(0)[0], n as f32 * 3.0 - 500.0);
    // One volume of the first half of those samples, after the same header.
    let one = dir.path().join("one.dat");
    std::fs::write(&one, &bytes[..512 + 2 * n]).unwrap();
    spec.time_points = 1;
    check(&one, Some(&spec));
    assert_eq!(
        read_volume(&one, Some(&spec)).unwrap().channel(0)[1],
        -497.0
    );
    for wrong in [0u64, 511, 513] {
        spec.header_bytes = wrong;
        let e = RegionReader::open(&one, Some(&spec)).unwrap_err();
        let total = wrong + 2 * n as u64;
        assert!(
            matches!(e, ReadError::SizeMismatch { expected, .. } if expected == total),
            "{e}"
        );
        assert!(
            e.to_string().contains(&format!("exactly {total} bytes")),
            "{e}"
        );
    }
}

/// A NIfTI-1 single file: header (sform placement, scaling), `pad` bytes of extension space,
/// then `data`.
#[allow(clippy::too_many_arguments)]
fn nifti_bytes(
    dim: [u16; 8],
    datatype: i16,
    bitpix: i16,
    big: bool,
    slope: f32,
    inter: f32,
    pad: usize,
    data: &[u8],
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
    for (i, p) in [1.0f32, 0.8, 1.5, 3.0, 1.0, 1.0, 1.0, 1.0]
        .iter()
        .enumerate()
    {
        w!(76 + 4 * i, *p);
    }
    w!(108, (352 + pad) as f32);
    w!(112, slope);
    w!(116, inter);
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
    h[344..348].copy_from_slice(b"n+1\0");
    h.extend(vec![0u8; 4 + pad]);
    h.extend_from_slice(data);
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

#[test]
fn nifti_regions_match_the_whole_plain_and_gzip() {
    let dir = tempfile::tempdir().unwrap();
    let n = DIMS.iter().product::<usize>();
    let d = DIMS.map(|d| d as u16);
    for gz in [false, true] {
        for big in [false, true] {
            let name = |s: &str| {
                dir.path()
                    .join(format!("{s}_{big}.nii{}", if gz { ".gz" } else { "" }))
            };
            let end = if big { Endian::Big } else { Endian::Little };
            // int16 with scaling and extension space before the data.
            let mut data = Vec::new();
            for i in 0..n {
                encode(
                    (i * 97 % 2000) as f64 - 1000.0,
                    RawDtype::I16,
                    end,
                    &mut data,
                );
            }
            let b = nifti_bytes(
                [3, d[0], d[1], d[2], 1, 1, 1, 1],
                4,
                16,
                big,
                2.0,
                -1.0,
                20,
                &data,
            );
            write(&name("i16"), &b, gz);
            check(&name("i16"), None);
            // float32, 4D with one time point, slope 0 (no scaling).
            let mut data = Vec::new();
            for i in 0..n {
                encode(i as f64 * 0.25 - 7.0, RawDtype::F32, end, &mut data);
            }
            let b = nifti_bytes(
                [4, d[0], d[1], d[2], 1, 1, 1, 1],
                16,
                32,
                big,
                0.0,
                5.0,
                0,
                &data,
            );
            write(&name("f32"), &b, gz);
            check(&name("f32"), None);
            // uint16 and RGB24.
            let mut data = Vec::new();
            for i in 0..n {
                encode((i * 911 % 65536) as f64, RawDtype::U16, end, &mut data);
            }
            let b = nifti_bytes(
                [3, d[0], d[1], d[2], 1, 1, 1, 1],
                512,
                16,
                big,
                1.0,
                0.0,
                0,
                &data,
            );
            write(&name("u16"), &b, gz);
            check(&name("u16"), None);
            let data: Vec<u8> = (0..n * 3).map(|i| (i * 7 % 256) as u8).collect();
            let b = nifti_bytes(
                [3, d[0], d[1], d[2], 1, 1, 1, 1],
                128,
                24,
                big,
                1.0,
                0.0,
                0,
                &data,
            );
            write(&name("rgb"), &b, gz);
            check(&name("rgb"), None);
        }
    }
}

#[test]
fn nrrd_regions_match_the_whole_for_every_encoding_and_header_style() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (
            Layout::I16,
            placed(1, |i, _| ((i * 37) % 251) as f32 - 100.0),
        ),
        (Layout::F32, placed(1, |i, _| i as f32 * 0.5 - 30.0)),
        (
            Layout::U8,
            placed(3, |i, c| ((i * 5 + 80 * c) % 256) as f32),
        ),
    ];
    for (layout, v) in &cases {
        for encoding in [NrrdEncoding::Raw, NrrdEncoding::Gzip, NrrdEncoding::Ascii] {
            for detached in [false, true] {
                let name = format!("n_{layout:?}_{encoding:?}_{detached}");
                let p =
                    fixtures::write_nrrd(dir.path(), &name, v, *layout, encoding, detached, "RAS");
                check(&p, None);
            }
        }
    }
    // Big-endian, detached with line and byte skips; spacings only (no placement).
    let n = DIMS.iter().product::<usize>();
    let mut data = b"first line\nsecond\nXYZ".to_vec();
    for i in 0..n {
        encode(
            (i * 301 % 65536) as f64,
            RawDtype::U16,
            Endian::Big,
            &mut data,
        );
    }
    std::fs::write(dir.path().join("skip.raw"), &data).unwrap();
    let h = dir.path().join("skip.nhdr");
    std::fs::write(
        &h,
        "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 7 5 4\nspacings: 0.5 0.25 4\nendian: big\nencoding: raw\nline skip: 2\nbyte skip: 3\ndata file: skip.raw\n",
    )
    .unwrap();
    check(&h, None);
    // Attached, byte skip -1 (data at the end), 4D with a trailing axis of 1.
    let mut b = b"NRRD0005\ntype: int8\ndimension: 4\nsizes: 7 5 4 1\nencoding: raw\nbyte skip: -1\nkey:=value\n\nJUNK".to_vec();
    b.extend((0..n).map(|i| (i * 13 % 256) as u8));
    let p = dir.path().join("tail.nrrd");
    std::fs::write(&p, &b).unwrap();
    check(&p, None);
    // 2D.
    let mut b =
        b"NRRD0004\ntype: float\ndimension: 2\nsizes: 7 5\nendian: little\nencoding: raw\n\n"
            .to_vec();
    for i in 0..35 {
        b.extend_from_slice(&(i as f32 * 1.5).to_le_bytes());
    }
    let p = dir.path().join("flat.nrrd");
    std::fs::write(&p, &b).unwrap();
    check(&p, None);
}

#[test]
fn metaimage_regions_match_the_whole_raw_and_compressed() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (Layout::U8, placed(1, |i, _| (i % 256) as f32)),
        (Layout::I16, placed(1, |i, _| ((i * 13) % 97) as f32 * -7.0)),
        (Layout::F32, placed(1, |i, _| i as f32 * 0.125)),
        (Layout::U8, placed(3, |i, c| ((i + 40 * c) % 256) as f32)),
    ];
    for (k, (layout, v)) in cases.iter().enumerate() {
        for compressed in [false, true] {
            for detached in [false, true] {
                let name = format!("m{k}_{layout:?}_{compressed}_{detached}");
                let p =
                    fixtures::write_metaimage(dir.path(), &name, v, *layout, compressed, detached);
                check(&p, None);
            }
        }
    }
    // HeaderSize -1 (data at the end), big-endian shorts; HeaderSize 5 in a data file.
    let n = DIMS.iter().product::<usize>();
    let mut b = b"NDims = 3\nDimSize = 7 5 4\nElementType = MET_SHORT\nBinaryDataByteOrderMSB = True\nHeaderSize = -1\nElementDataFile = LOCAL\nxyz".to_vec();
    for i in 0..n {
        encode(i as f64 * 3.0 - 50.0, RawDtype::I16, Endian::Big, &mut b);
    }
    let p = dir.path().join("tail.mha");
    std::fs::write(&p, &b).unwrap();
    check(&p, None);
    let mut data = b"12345".to_vec();
    data.extend((0..n).map(|i| (i * 3 % 256) as u8));
    std::fs::write(dir.path().join("skip.raw"), &data).unwrap();
    let h = dir.path().join("skip.mhd");
    std::fs::write(
        &h,
        "ObjectType = Image\nNDims = 3\nDimSize = 7 5 4\nElementSpacing = 1 2 3\nElementType = MET_UCHAR\nHeaderSize = 5\nElementDataFile = skip.raw\n",
    )
    .unwrap();
    check(&h, None);
}

#[test]
fn dicom_series_regions_match_the_whole() {
    let dir = tempfile::tempdir().unwrap();
    let v = placed(1, |i, _| ((i * 37) % 251) as f32 - 100.0);
    let series = dir.path().join("series");
    fixtures::write_dicom_series(&series, &v, &DicomOptions::default());
    check(&series, None);
    // Slices whose file names run against their positions (the volume's order is the
    // positions'), rescaled, RLE-coded.
    let rle = dir.path().join("rle");
    let o = DicomOptions {
        slope: 0.5,
        intercept: -1024.0,
        encoding: fixtures::DicomEncoding::RleLossless,
        ..DicomOptions::default()
    };
    let files = fixtures::write_dicom_series(&rle, &v, &o);
    let n = files.len();
    for (i, f) in files.iter().enumerate() {
        std::fs::rename(f, rle.join(format!("tmp{i}"))).unwrap();
    }
    for i in 0..n {
        std::fs::rename(
            rle.join(format!("tmp{i}")),
            rle.join(format!("s{:02}.dcm", n - 1 - i)),
        )
        .unwrap();
    }
    check(&rle, None);
    // One multi-frame file.
    let multi = dir.path().join("multi.dcm");
    fixtures::write_dicom_multiframe(&multi, &v, &DicomOptions::default());
    check(&multi, None);
}

/// A series opens by its headers alone and a region decodes only the files of its slices: a
/// slice file damaged after opening fails the regions that cross it, naming it, and no other.
#[test]
fn dicom_regions_decode_only_the_slices_they_cross() {
    let dir = tempfile::tempdir().unwrap();
    let v = placed(1, |i, _| (i % 97) as f32);
    let series = dir.path().join("series");
    let files = fixtures::write_dicom_series(&series, &v, &DicomOptions::default());
    let r = RegionReader::open(&series, None).unwrap();
    let whole = read_volume(&series, None).unwrap();
    // The fixture returns the files in slice order (their names run in another).
    let keep = &files[..2];
    for f in files.iter().filter(|f| !keep.contains(f)) {
        let mut bytes = std::fs::read(f).unwrap();
        bytes.truncate(bytes.len() - 7);
        std::fs::write(f, bytes).unwrap();
    }
    let low = r.read_region([0, 0, 0], [DIMS[0], DIMS[1], 2]).unwrap();
    assert_eq!(low, cut(&whole, [0, 0, 0], [DIMS[0], DIMS[1], 2]));
    let e = r.read_region([0, 0, 1], [2, 2, 2]).unwrap_err().to_string();
    assert!(e.contains("IM"), "the damaged file is named: {e}");
}

/// Bytes on disk of a file (sparse files take few).
fn allocated(path: &Path) -> u64 {
    use std::os::unix::fs::MetadataExt;
    std::fs::metadata(path).unwrap().blocks() * 512
}

#[test]
fn more_than_two_to_the_31_voxels_open_and_read_small_regions() {
    let dir = tempfile::tempdir().unwrap();
    // 2048 × 2048 × 1024 u8 = 2³² voxels: a 4 GiB sparse file with a few bytes written.
    let dims = [2048, 2048, 1024];
    let path = dir.path().join("huge.raw");
    let f = File::create(&path).unwrap();
    f.set_len(1 << 32).unwrap();
    let at = |x: u64, y: u64, z: u64| x + 2048 * (y + 2048 * z);
    f.write_all_at(&[200], at(2047, 2047, 1023)).unwrap();
    f.write_all_at(&[1, 2, 3], at(2041, 2046, 1022)).unwrap();
    f.write_all_at(&[42], at(5, 7, 600)).unwrap();
    drop(f);
    assert!(allocated(&path) < 1 << 20, "the test file must stay sparse");
    let spec = RawSpec::new(dims, RawDtype::U8);
    let r = RegionReader::open(&path, Some(&spec)).unwrap();
    assert_eq!(r.dims(), dims);
    assert_eq!(r.voxel_count(), 1 << 32);
    assert!(r.voxel_count() > MAX_VOXELS as u128);
    let b = r.read_region([2040, 2044, 1020], [8, 4, 4]).unwrap();
    assert_eq!(b.dims(), [8, 4, 4]);
    let ch = b.channel(0);
    assert_eq!(ch[b.index(7, 3, 3)], 200.0);
    assert_eq!(&ch[b.index(1, 2, 2)..b.index(4, 2, 2)], &[1.0, 2.0, 3.0]);
    assert_eq!(ch.iter().filter(|v| **v != 0.0).count(), 4);
    let b = r.read_region([0, 0, 600], [8, 8, 1]).unwrap();
    assert_eq!(b.channel(0)[b.index(5, 7, 0)], 42.0);
    // Full-row and full-slab runs past 2³² bytes of offset arithmetic.
    let b = r.read_region([0, 2046, 1022], [2048, 2, 2]).unwrap();
    assert_eq!(b.channel(0)[b.index(2047, 1, 1)], 200.0);
    // A region of more than MAX_VOXELS is refused before allocating; so is the whole.
    for size in [dims, [2048, 2048, 513]] {
        assert!(matches!(
            r.read_region([0; 3], size),
            Err(ReadError::InvalidVolume {
                problem: VolumeError::TooLarge { .. },
                ..
            })
        ));
    }
    // read_volume refuses this volume outright.
    assert!(read_volume(&path, Some(&spec)).is_err());

    // A NIfTI header of 2048 × 2048 × 600 int16 (5 GiB of samples) on a sparse file.
    let path = dir.path().join("huge.nii");
    let head = nifti_bytes(
        [3, 2048, 2048, 600, 1, 1, 1, 1],
        4,
        16,
        false,
        0.5,
        10.0,
        0,
        &[],
    );
    let f = File::create(&path).unwrap();
    f.write_all_at(&head, 0).unwrap();
    f.set_len(352 + 2 * 2048 * 2048 * 600).unwrap();
    f.write_all_at(&(-300i16).to_le_bytes(), 352 + 2 * at(9, 1000, 599))
        .unwrap();
    drop(f);
    assert!(allocated(&path) < 1 << 20);
    let r = RegionReader::open(&path, None).unwrap();
    assert_eq!(r.dims(), [2048, 2048, 600]);
    assert!(r.placement().is_some());
    let b = r.read_region([8, 999, 598], [3, 3, 2]).unwrap();
    assert_eq!(b.channel(0)[b.index(1, 1, 1)], 0.5 * -300.0 + 10.0);
    assert_eq!(b.channel(0)[0], 10.0);
}

#[test]
fn truncated_files_and_boxes_outside_are_clean_errors() {
    let dir = tempfile::tempdir().unwrap();
    let n = DIMS.iter().product::<usize>();
    // A raw file shorter than its description.
    let path = dir.path().join("short.raw");
    std::fs::write(&path, vec![0u8; n - 1]).unwrap();
    let spec = RawSpec::new(DIMS, RawDtype::U8);
    assert!(matches!(
        RegionReader::open(&path, Some(&spec)),
        Err(ReadError::SizeMismatch { .. })
    ));
    // NIfTI and MetaImage files whose data stops early; a short gzip stream.
    let d = DIMS.map(|d| d as u16);
    let b = nifti_bytes(
        [3, d[0], d[1], d[2], 1, 1, 1, 1],
        2,
        8,
        false,
        1.0,
        0.0,
        0,
        &[7; 10],
    );
    for gz in [false, true] {
        let p = dir
            .path()
            .join(if gz { "short.nii.gz" } else { "short.nii" });
        write(&p, &b, gz);
        let e = RegionReader::open(&p, None).unwrap_err();
        assert!(matches!(e, ReadError::Truncated { actual: 10, .. }), "{e}");
    }
    let p = dir.path().join("short.mha");
    let mut b =
        b"NDims = 3\nDimSize = 7 5 4\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n".to_vec();
    b.extend(vec![0u8; 100]);
    std::fs::write(&p, &b).unwrap();
    assert!(matches!(
        RegionReader::open(&p, None),
        Err(ReadError::Truncated { .. })
    ));
    // A header announcing 10¹⁵ voxels on a tiny file: refused at open, nothing allocated.
    let p = dir.path().join("liar.nrrd");
    std::fs::write(
        &p,
        b"NRRD0004\ntype: double\ndimension: 3\nsizes: 100000 100000 100000\nendian: little\nencoding: raw\n\n12345678",
    )
    .unwrap();
    assert!(matches!(
        RegionReader::open(&p, None),
        Err(ReadError::Truncated { .. })
    ));
    let p = dir.path().join("liar.nii.gz");
    write(
        &p,
        &nifti_bytes(
            [3, 65535, 65535, 65535, 1, 1, 1, 1],
            64,
            64,
            false,
            1.0,
            0.0,
            0,
            &[0; 64],
        ),
        true,
    );
    assert!(matches!(
        RegionReader::open(&p, None),
        Err(ReadError::Truncated { actual: 64, .. })
    ));

    // A file cut short after opening: regions before the cut read, past it are errors.
    let v = placed(1, |i, _| (i % 200) as f32);
    let p = fixtures::write_nrrd(
        dir.path(),
        "cut",
        &v,
        Layout::U8,
        NrrdEncoding::Raw,
        false,
        "LPS",
    );
    let r = RegionReader::open(&p, None).unwrap();
    let len = std::fs::metadata(&p).unwrap().len();
    File::options()
        .write(true)
        .open(&p)
        .unwrap()
        .set_len(len - 20)
        .unwrap();
    assert_eq!(
        r.read_region([0, 0, 0], [7, 5, 2]).unwrap(),
        cut(&v, [0, 0, 0], [7, 5, 2])
    );
    let e = r.read_region([0, 0, 3], [7, 5, 1]).unwrap_err();
    assert!(matches!(e, ReadError::Truncated { .. }), "{e}");
    assert!(e.to_string().contains("cut.nrrd"), "{e}");

    // Boxes that are empty, outside, or overflow.
    for (o, s) in [
        ([0, 0, 0], [0, 1, 1]),
        ([0, 0, 0], [8, 5, 4]),
        ([6, 0, 0], [2, 1, 1]),
        ([0, 0, 4], [1, 1, 1]),
        ([usize::MAX, 0, 0], [1, 1, 1]),
        ([1, 0, 0], [usize::MAX, 1, 1]),
    ] {
        let e = r.read_region(o, s).unwrap_err();
        assert!(matches!(e, ReadError::Region { .. }), "{o:?} {s:?}: {e}");
        assert!(e.to_string().contains("cut.nrrd"), "{e}");
    }
}

#[test]
fn non_finite_samples_are_refused_in_the_regions_that_hold_them() {
    let dir = tempfile::tempdir().unwrap();
    let n = DIMS.iter().product::<usize>();
    let mut vals = vec![1.5f32; n];
    vals[3 + 7 * (2 + 5)] = f32::NAN; // voxel (3, 2, 1)
    let bytes: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
    let path = dir.path().join("nan.raw");
    std::fs::write(&path, bytes).unwrap();
    let spec = RawSpec::new(DIMS, RawDtype::F32);
    assert!(matches!(
        read_volume(&path, Some(&spec)),
        Err(ReadError::Volume(VolumeError::NonFinite {
            x: 3,
            y: 2,
            z: 1,
            ..
        }))
    ));
    let r = RegionReader::open(&path, Some(&spec)).unwrap();
    let e = r.read_region([2, 1, 1], [3, 3, 2]).unwrap_err();
    assert!(
        matches!(
            e,
            ReadError::InvalidVolume {
                problem: VolumeError::NonFinite {
                    x: 3,
                    y: 2,
                    z: 1,
                    ..
                },
                ..
            }
        ),
        "{e}"
    );
    assert_eq!(
        r.read_region([0, 0, 2], [7, 5, 2]).unwrap().channel(0),
        &[1.5; 70][..]
    );
}

#[test]
fn hostile_headers_never_panic() {
    let dir = tempfile::tempdir().unwrap();
    let mut seed = 12345u64;
    let mut next = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 56) as u8
    };
    for (name, magic) in [
        ("x.nrrd", &b"NRRD0004\ntype: uint8\ndimension: 3\n"[..]),
        ("x.mha", &b"NDims = 3\nDimSize = 2 2 2\n"[..]),
        ("x.nii", &[][..]),
    ] {
        let p = dir.path().join(name);
        for len in 0..150 {
            let mut b = magic.to_vec();
            b.extend((0..len * 3).map(|_| next()));
            std::fs::write(&p, &b).unwrap();
            if let Ok(r) = RegionReader::open(&p, None) {
                let _ = r.read_region([0; 3], r.dims());
            }
        }
    }
}
