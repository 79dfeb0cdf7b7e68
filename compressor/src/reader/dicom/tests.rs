//! DICOM reader tests: series and multi-frame files written here with dicom-rs read back equal
//! to their source arrays, spacing and placement; inconsistent series, missing or bad
//! attributes, truncated and hostile files are typed errors.

use super::pixels::{jpeg_colour_markers, jpeg_sample_precision, packbits, EXPLICIT_VR_BIG_ENDIAN};
use super::*;
use crate::reader::read_volume;
use dicom_core::{DataElement, PrimitiveValue, Tag, VR};
use dicom_object::{open_file, DefaultDicomObject, InMemDicomObject};
use std::path::{Path, PathBuf};
use wavesplat_codec::volume::{Placement, Volume};
use wavesplat_fixtures::{
    self as fixtures, write_dicom_multiframe, write_dicom_series, DicomEncoding, DicomOptions,
    Layout,
};

/// A placement that is neither axis-aligned nor at the origin (cosines exact in decimal).
fn oblique() -> Placement {
    Placement {
        origin: [-120.5, 30.25, 512.0],
        directions: [[0.6, 0.8, 0.0], [0.0, 0.0, -1.0], [-0.8, 0.6, 0.0]],
    }
}

/// A volume whose values, stored as `(v − intercept) / slope`, fit `layout` exactly.
fn volume(
    dims: [usize; 3],
    spacing: [f32; 3],
    layout: Layout,
    slope: f64,
    intercept: f64,
) -> Volume {
    let (lo, hi) = match layout {
        Layout::U8 => (0.0, 255.0),
        Layout::I8 => (-128.0, 127.0),
        Layout::U16 => (0.0, 65535.0),
        _ => (-32768.0, 32767.0),
    };
    let n = dims.iter().product::<usize>();
    let data = (0..n)
        .map(|i| {
            let t = (i * 7919 % 1009) as f64 / 1008.0;
            let stored = (lo + t * (hi - lo)).round();
            (stored * slope + intercept) as f32
        })
        .collect();
    Volume::new(dims, spacing, vec![data])
        .unwrap()
        .with_placement(oblique())
        .unwrap()
}

fn assert_same(back: &Volume, v: &Volume, what: &str) {
    assert_eq!(back.dims(), v.dims(), "{what}");
    assert_eq!(back.channels(), v.channels(), "{what}");
    for a in 0..3 {
        assert!(
            (back.spacing()[a] - v.spacing()[a]).abs() <= 1e-6 * v.spacing()[a],
            "{what}: spacing {:?} vs {:?}",
            back.spacing(),
            v.spacing()
        );
    }
    let (b, p) = (back.placement().unwrap(), v.placement().unwrap());
    for i in 0..3 {
        assert!(
            (b.origin[i] - p.origin[i]).abs() < 1e-6,
            "{what}: {b:?} vs {p:?}"
        );
        for j in 0..3 {
            assert!(
                (b.directions[i][j] - p.directions[i][j]).abs() < 1e-9,
                "{what}: {b:?}"
            );
        }
    }
}

#[test]
fn series_round_trip_every_layout_and_transfer_syntax() {
    let root = tempfile::tempdir().unwrap();
    let mut k = 0;
    for (layout, slope, intercept) in [
        (Layout::I16, 1.0, -1024.0),
        (Layout::U16, 0.5, -1000.0),
        (Layout::U8, 2.0, 0.0),
        (Layout::I8, 1.0, 10.0),
    ] {
        for encoding in [
            DicomEncoding::ExplicitLittle,
            DicomEncoding::ImplicitLittle,
            DicomEncoding::RleLossless,
        ] {
            k += 1;
            let dir = root.path().join(format!("s{k}"));
            let v = volume([7, 5, 6], [0.7, 0.8, 2.5], layout, slope, intercept);
            let o = DicomOptions {
                layout,
                slope,
                intercept,
                encoding,
                ..DicomOptions::default()
            };
            write_dicom_series(&dir, &v, &o);
            let back = read_volume(&dir, None).unwrap();
            assert_same(&back, &v, &format!("{layout:?} {encoding:?}"));
        }
    }
    // CT values in HU survive: the source had −1024 .. 31743.
    let v = volume([7, 5, 6], [0.7, 0.8, 2.5], Layout::I16, 1.0, -1024.0);
    let (lo, hi) = v.value_range();
    assert!(lo < -1000.0 && hi > 30000.0);
}

#[test]
fn multiframe_round_trip_native_and_rle_and_rgb() {
    let dir = tempfile::tempdir().unwrap();
    for (i, encoding) in [DicomEncoding::ExplicitLittle, DicomEncoding::RleLossless]
        .into_iter()
        .enumerate()
    {
        let v = volume([9, 4, 5], [0.5, 0.5, 1.25], Layout::I16, 1.0, -1024.0);
        let o = DicomOptions {
            encoding,
            intercept: -1024.0,
            ..DicomOptions::default()
        };
        let path = dir.path().join(format!("mf{i}.dcm"));
        write_dicom_multiframe(&path, &v, &o);
        let back = read_volume(&path, None).unwrap();
        assert_same(&back, &v, &format!("multi-frame {encoding:?}"));
    }
    // RGB, 8 bits.
    let n = 4 * 3 * 2;
    let rgb: Vec<Vec<f32>> = (0..3)
        .map(|c| (0..n).map(|i| ((i * 11 + 70 * c) % 256) as f32).collect())
        .collect();
    let v = Volume::new([4, 3, 2], [1.0, 1.0, 2.0], rgb)
        .unwrap()
        .with_placement(oblique())
        .unwrap();
    let o = DicomOptions {
        layout: Layout::U8,
        ..DicomOptions::default()
    };
    let path = dir.path().join("rgb.dcm");
    write_dicom_multiframe(&path, &v, &o);
    assert_same(&read_volume(&path, None).unwrap(), &v, "rgb");
}

#[test]
fn single_slice_uses_the_slice_thickness() {
    let dir = tempfile::tempdir().unwrap();
    let v = volume([3, 3, 1], [0.5, 0.6, 3.0], Layout::I16, 1.0, 0.0);
    write_dicom_series(dir.path(), &v, &DicomOptions::default());
    assert_same(&read_volume(dir.path(), None).unwrap(), &v, "one slice");
}

fn series(dir: &Path, dims: [usize; 3], o: &DicomOptions) -> (Volume, Vec<PathBuf>) {
    let v = volume(dims, [1.0, 1.0, 2.0], o.layout, o.slope, o.intercept);
    let files = write_dicom_series(dir, &v, o);
    (v, files)
}

fn expect_series_error(dir: &Path, needle: &str) {
    let e = read_volume(dir, None).unwrap_err();
    assert!(matches!(e, ReadError::Series { .. }), "{e}");
    assert!(e.to_string().contains(needle), "{e}");
}

#[test]
fn inconsistent_series_are_reported() {
    let root = tempfile::tempdir().unwrap();
    let o = DicomOptions::default();

    // Two series in one directory.
    let d = root.path().join("two");
    series(&d, [4, 4, 3], &o);
    let other = DicomOptions {
        series_uid: "1.2.3.4.5".into(),
        ..DicomOptions::default()
    };
    let tmp = root.path().join("tmp");
    let (_, files) = series(&tmp, [4, 4, 1], &other);
    std::fs::rename(&files[0], d.join("OTHER")).unwrap();
    expect_series_error(&d, "holds 2 series");

    // A gap: one slice removed from the middle.
    let d = root.path().join("gap");
    let (_, files) = series(&d, [4, 4, 5], &o);
    std::fs::remove_file(&files[2]).unwrap();
    expect_series_error(&d, "1 slice(s) missing");

    // Irregular spacing and a duplicate position: a slice of the same series moved.
    let d = root.path().join("irregular");
    let (_, files) = series(&d, [4, 4, 4], &o);
    let mut obj = open_file(&files[3]).unwrap();
    let p = oblique().position([1.0, 1.0, 2.0], [0.0, 0.0, 2.5]);
    set(
        &mut obj,
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        PrimitiveValue::from(format!("{}\\{}\\{}", p[0], p[1], p[2])),
    );
    obj.write_to_file(&files[3]).unwrap();
    expect_series_error(&d, "irregular slice spacing");
    let p = oblique().position([1.0, 1.0, 2.0], [0.0, 0.0, 1.0]);
    set(
        &mut obj,
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        PrimitiveValue::from(format!("{}\\{}\\{}", p[0], p[1], p[2])),
    );
    obj.write_to_file(&files[3]).unwrap();
    expect_series_error(&d, "same position");

    // Slices of different sizes.
    let d = root.path().join("rows");
    series(&d, [4, 4, 2], &o);
    let (_, files) = series(&root.path().join("tmp2"), [5, 4, 1], &o);
    std::fs::rename(&files[0], d.join("ZZZ")).unwrap();
    expect_series_error(&d, "(0028,0010) Rows differs");

    // One slice turned: the orientations are named as DICOM writes them, not as Rust's
    // `Some([…])`.
    let d = root.path().join("turned");
    let (_, files) = series(&d, [4, 4, 3], &o);
    let mut obj = open_file(&files[1]).unwrap();
    set(
        &mut obj,
        tags::IMAGE_ORIENTATION_PATIENT,
        VR::DS,
        PrimitiveValue::from("0\\1\\0\\1\\0\\0".to_string()),
    );
    obj.write_to_file(&files[1]).unwrap();
    expect_series_error(&d, "Image Orientation (Patient) differs");
    let e = read_volume(&d, None).unwrap_err().to_string();
    assert!(!e.contains("Some("), "{e}");
    assert!(e.contains("0\\1\\0\\1\\0\\0"), "{e}");

    // Gantry tilt: each slice shifted sideways.
    let d = root.path().join("tilt");
    let tilted = DicomOptions {
        shear: [0.0, 0.0, 0.5],
        ..DicomOptions::default()
    };
    series(&d, [4, 4, 4], &tilted);
    expect_series_error(&d, "gantry tilt");

    // An empty directory and ones without DICOM files: the error says what each holds and
    // what it could be read as.
    let d = root.path().join("empty");
    std::fs::create_dir(&d).unwrap();
    expect_series_error(&d, "holds no file");
    std::fs::write(d.join("notes.txt"), "hello").unwrap();
    expect_series_error(&d, "no DICOM files");
    expect_series_error(&d, "(`notes.txt`…) are not volume files");
    std::fs::write(d.join("step_0.raw"), [0u8; 64]).unwrap();
    expect_series_error(
        &d,
        "1 .raw file(s) are read as a time series of raw steps with --dims",
    );
}

/// An edit of a fixture's data set.
type Edit = Box<dyn Fn(&mut DefaultDicomObject)>;

/// Puts an element into a data set (replacing one with its tag).
fn set<V>(o: &mut InMemDicomObject, tag: Tag, vr: VR, value: V)
where
    V: Into<dicom_core::value::Value<InMemDicomObject, dicom_core::value::InMemFragment>>,
{
    o.put(DataElement::new(tag, vr, value));
}

/// Rewrites a fixture file with `edit` applied to its data set.
fn edit(path: &Path, edit: impl FnOnce(&mut DefaultDicomObject)) {
    let mut obj = open_file(path).unwrap();
    edit(&mut obj);
    obj.write_to_file(path).unwrap();
}

fn expect_tag_error(dir: &Path, file: &Path, tag: &str) {
    let e = read_volume(dir, None).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, ReadError::Dicom { .. }), "{msg}");
    assert!(msg.contains(tag), "{msg}");
    let name = file.file_name().unwrap().to_string_lossy().into_owned();
    assert!(msg.contains(&name), "{msg}");
}

#[test]
fn bad_attributes_name_the_file_and_the_tag() {
    let root = tempfile::tempdir().unwrap();
    let o = DicomOptions::default();
    let cases: Vec<(&str, Edit)> = vec![
        (
            "(0028,0100) Bits Allocated",
            Box::new(|o| {
                o.remove_element(tags::BITS_ALLOCATED);
            }),
        ),
        (
            "(0028,0100) Bits Allocated",
            Box::new(|o| {
                set(o, tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(12u16));
            }),
        ),
        (
            "(0028,0102) High Bit",
            Box::new(|o| {
                set(o, tags::HIGH_BIT, VR::US, PrimitiveValue::from(3u16));
            }),
        ),
        (
            "(0020,000E) Series Instance UID",
            Box::new(|o| {
                o.remove_element(tags::SERIES_INSTANCE_UID);
            }),
        ),
        (
            "(0020,0032) Image Position (Patient)",
            Box::new(|o| {
                o.remove_element(tags::IMAGE_POSITION_PATIENT);
            }),
        ),
        (
            "(0028,0030) Pixel Spacing",
            Box::new(|o| {
                set(o, tags::PIXEL_SPACING, VR::DS, PrimitiveValue::from("0\\1"));
            }),
        ),
        (
            "(0028,1053) Rescale Slope",
            Box::new(|o| {
                set(o, tags::RESCALE_SLOPE, VR::DS, PrimitiveValue::from("0"));
            }),
        ),
        (
            "(0028,1053) Rescale Slope",
            Box::new(|o| {
                set(o, tags::RESCALE_SLOPE, VR::DS, PrimitiveValue::from("NaN"));
            }),
        ),
        (
            "(0028,0004) Photometric Interpretation",
            Box::new(|o| {
                set(
                    o,
                    tags::PHOTOMETRIC_INTERPRETATION,
                    VR::CS,
                    PrimitiveValue::from("HSV"),
                );
            }),
        ),
        (
            "(7FE0,0010) Pixel Data",
            Box::new(|o| {
                o.remove_element(tags::PIXEL_DATA);
            }),
        ),
        // Hostile sizes: a header claiming a huge image on a small file.
        (
            "(0028,0008) Number of Frames",
            Box::new(|o| {
                set(o, tags::ROWS, VR::US, PrimitiveValue::from(65535u16));
                set(o, tags::COLUMNS, VR::US, PrimitiveValue::from(65535u16));
                set(
                    o,
                    tags::NUMBER_OF_FRAMES,
                    VR::IS,
                    PrimitiveValue::from("1000"),
                );
            }),
        ),
    ];
    for (i, (tag, f)) in cases.into_iter().enumerate() {
        let d = root.path().join(format!("c{i}"));
        let (_, files) = series(&d, [4, 4, 3], &o);
        let target = files.iter().max().unwrap().clone();
        edit(&target, f);
        expect_tag_error(&d, &target, tag);
    }
    // Type 2 attributes present but blank (an RT Dose's Slice Thickness, padded with a space;
    // the same bytes in an element of VR UN) are absent, not "not a list of numbers".
    for (name, vr) in [("blank-ds", VR::DS), ("blank-un", VR::UN)] {
        let d = root.path().join(name);
        let (_, files) = series(&d, [4, 4, 3], &o);
        for f in &files {
            edit(f, |o| {
                o.remove_element(tags::SPACING_BETWEEN_SLICES);
                let blank: PrimitiveValue = match vr {
                    VR::UN => PrimitiveValue::from(vec![b' ', b' ']),
                    _ => PrimitiveValue::from("  "),
                };
                set(o, tags::SLICE_THICKNESS, vr, blank);
                set(
                    o,
                    tags::RESCALE_INTERCEPT,
                    vr,
                    match vr {
                        VR::UN => PrimitiveValue::from(vec![b' ', b' ']),
                        _ => PrimitiveValue::from(" "),
                    },
                );
            });
        }
        let v = read_volume(&d, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(v.dims(), [4, 4, 3], "{name}");
    }

    // A single file without a Series Instance UID is its own series (other toolkits read it);
    // in a directory of several it is refused above.
    let d = root.path().join("lone");
    let (_, files) = series(&d, [4, 4, 1], &o);
    edit(&files[0], |o| {
        o.remove_element(tags::SERIES_INSTANCE_UID);
    });
    let lone = read_volume(&files[0], None).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(lone.dims(), [4, 4, 1]);
    let lone_dir = read_volume(&d, None).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(lone_dir.dims(), [4, 4, 1]);

    // A header claiming more native pixel data than the file holds.
    let d = root.path().join("short");
    let (_, files) = series(&d, [4, 4, 1], &o);
    edit(&files[0], |o| {
        set(o, tags::ROWS, VR::US, PrimitiveValue::from(4096u16));
        set(o, tags::COLUMNS, VR::US, PrimitiveValue::from(4096u16));
    });
    expect_tag_error(&d, &files[0], "(7FE0,0010) Pixel Data");

    // Encapsulated frames claiming more than the expansion limit.
    let d = root.path().join("rle");
    let rle = DicomOptions {
        encoding: DicomEncoding::RleLossless,
        ..DicomOptions::default()
    };
    let path = d.join("mf.dcm");
    std::fs::create_dir_all(&d).unwrap();
    let v = volume([4, 4, 2], [1.0; 3], Layout::I16, 1.0, 0.0);
    write_dicom_multiframe(&path, &v, &rle);
    edit(&path, |o| {
        set(o, tags::ROWS, VR::US, PrimitiveValue::from(30000u16));
        set(o, tags::COLUMNS, VR::US, PrimitiveValue::from(30000u16));
    });
    let e = read_volume(&path, None).unwrap_err().to_string();
    assert!(e.contains("expansion") || e.contains("Pixel Data"), "{e}");
}

#[test]
fn unsupported_transfer_syntax_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let v = volume([4, 4, 2], [1.0; 3], Layout::I16, 1.0, 0.0);
    let o = DicomOptions {
        encoding: DicomEncoding::RleLossless,
        ..DicomOptions::default()
    };
    let path = dir.path().join("jxl.dcm");
    write_dicom_multiframe(&path, &v, &o);
    // Relabel the encapsulated data as JPEG XL (no decoder in this build).
    edit(&path, |o| {
        o.update_meta(|m| m.transfer_syntax = "1.2.840.10008.1.2.4.110".into());
    });
    let e = read_volume(&path, None).unwrap_err().to_string();
    assert!(e.contains("1.2.840.10008.1.2.4.110"), "{e}");
    assert!(e.contains("(0002,0010)"), "{e}");
}

#[test]
fn truncated_and_garbage_files_are_errors_not_panics() {
    let dir = tempfile::tempdir().unwrap();
    let v = volume([6, 5, 1], [1.0; 3], Layout::I16, 1.0, 0.0);
    let files = write_dicom_series(&dir.path().join("src"), &v, &DicomOptions::default());
    let good = std::fs::read(&files[0]).unwrap();
    let target = dir.path().join("cut.dcm");
    for cut in (132..good.len()).step_by(7) {
        std::fs::write(&target, &good[..cut]).unwrap();
        assert!(read_volume(&target, None).is_err(), "cut at {cut}");
    }
    let mut seed = 99u64;
    for len in [0usize, 4, 16, 64, 300, 2000] {
        let mut b = vec![0u8; 128];
        b.extend_from_slice(b"DICM");
        for _ in 0..len {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            b.push((seed >> 56) as u8);
        }
        std::fs::write(&target, &b).unwrap();
        assert!(read_volume(&target, None).is_err());
        // A valid meta group followed by garbage.
        let mut c = good[..good.len().min(400)].to_vec();
        c.extend_from_slice(&b[132..]);
        std::fs::write(&target, &c).unwrap();
        assert!(read_volume(&target, None).is_err());
    }
    // Flipped bytes in a good file never panic (and most fail).
    for i in (132..good.len()).step_by(13) {
        let mut b = good.clone();
        b[i] ^= 0xa5;
        std::fs::write(&target, &b).unwrap();
        let _ = read_volume(&target, None);
    }
}

#[test]
fn fixtures_reject_unrepresentable_values() {
    let r = std::panic::catch_unwind(|| {
        let v = Volume::new([1, 1, 1], [1.0; 3], vec![vec![0.5]]).unwrap();
        let d = tempfile::tempdir().unwrap();
        fixtures::write_dicom_series(d.path(), &v, &DicomOptions::default());
    });
    assert!(r.is_err());
}

#[test]
fn hostile_element_lengths_allocate_nothing_large() {
    let dir = tempfile::tempdir().unwrap();
    let v = volume([4, 4, 1], [1.0; 3], Layout::I16, 1.0, 0.0);
    let files = write_dicom_series(&dir.path().join("src"), &v, &DicomOptions::default());
    edit(&files[0], |o| {
        set(o, Tag(0x0040, 0xA160), VR::UT, PrimitiveValue::from("ab"));
    });
    let mut bytes = std::fs::read(&files[0]).unwrap();
    let pat = [0x40, 0x00, 0x60, 0xA1, b'U', b'T', 0, 0, 2, 0, 0, 0];
    let at = bytes.windows(pat.len()).position(|w| w == pat).unwrap();
    bytes[at + 8..at + 12].copy_from_slice(&0xFFFF_FFF0u32.to_le_bytes());
    let target = dir.path().join("hostile.dcm");
    std::fs::write(&target, &bytes).unwrap();
    let e = read_volume(&target, None).unwrap_err();
    assert!(matches!(e, ReadError::Dicom { .. }), "{e}");

    // An unknown VR (found by the fuzzer): dicom-rs reads it with a 4-byte length, here the
    // Pixel Spacing's length and first value bytes (~0x2E30_0008 bytes) — the length walk must
    // not read it as a 2-byte one.
    let mut bytes = std::fs::read(&files[0]).unwrap();
    let pat = [0x28, 0x00, 0x30, 0x00, b'D', b'S'];
    let at = bytes.windows(pat.len()).position(|w| w == pat).unwrap();
    bytes[at + 4..at + 6].copy_from_slice(&[0x10, 0x00]);
    std::fs::write(&target, &bytes).unwrap();
    let e = read_volume(&target, None).unwrap_err();
    assert!(matches!(e, ReadError::Dicom { .. }), "{e}");
    assert!(
        e.to_string().contains("unknown value representation"),
        "{e}"
    );

    // A binary value whose length is not a whole number of values (found by the fuzzer: an AT
    // of 6 bytes): dicom-rs reads one tag, counts six bytes and goes on two bytes early, so
    // the walk must refuse what the parser would misalign on.
    for (vr, size) in [(VR::AT, 4u16), (VR::FD, 8), (VR::US, 2)] {
        edit(&files[0], |o| {
            let value = match vr {
                VR::AT => {
                    PrimitiveValue::Tags([Tag(0x0020, 0x0032), Tag(0x0020, 0x0037)][..].into())
                }
                VR::FD => PrimitiveValue::F64([1.5, 2.5][..].into()),
                _ => PrimitiveValue::U16([7, 9][..].into()),
            };
            set(o, Tag(0x0083, 0x0032), vr, value);
        });
        let mut bytes = std::fs::read(&files[0]).unwrap();
        let name = vr.to_string();
        let mut pat = vec![0x83, 0x00, 0x32, 0x00];
        pat.extend_from_slice(name.as_bytes());
        pat.extend_from_slice(&(2 * size).to_le_bytes());
        let at = bytes.windows(pat.len()).position(|w| w == pat).unwrap();
        // One byte short of two values, the byte moved into the next element's place.
        bytes[at + 6..at + 8].copy_from_slice(&(2 * size - 1).to_le_bytes());
        std::fs::write(&target, &bytes).unwrap();
        let e = read_volume(&target, None).unwrap_err();
        assert!(e.to_string().contains("not a whole number"), "{vr}: {e}");
    }
}

#[test]
fn the_length_walk_reads_the_meta_group_by_its_group_length() {
    // dicom-rs reads the meta group by its group length (0002,0000), whatever groups the
    // elements in it belong to; the walk must start the data set where the parser does.
    let dir = tempfile::tempdir().unwrap();
    let v = volume([4, 4, 1], [1.0; 3], Layout::I16, 1.0, 0.0);
    let files = write_dicom_series(&dir.path().join("src"), &v, &DicomOptions::default());
    let bytes = std::fs::read(&files[0]).unwrap();
    assert_eq!(
        &bytes[132..136],
        &[2, 0, 0, 0],
        "the group length comes first"
    );
    let target = dir.path().join("edited.dcm");
    // Without its group length, the meta group cannot be read as dicom-rs reads it.
    let mut no_length = bytes.clone();
    no_length[134] = 1;
    std::fs::write(&target, &no_length).unwrap();
    let e = read_volume(&target, None).unwrap_err();
    assert!(e.to_string().contains("group length"), "{e}");
    // A group length 8 bytes short ends the meta group inside its last element for the
    // parser; the walk must read on to the element's end as the parser does, and agree.
    let group = u32::from_le_bytes(bytes[140..144].try_into().unwrap());
    let mut short = bytes.clone();
    short[140..144].copy_from_slice(&(group - 8).to_le_bytes());
    std::fs::write(&target, &short).unwrap();
    let read = read_volume(&target, None);
    assert!(read.is_ok(), "{:?}", read.err());
}

#[test]
fn a_small_file_cannot_declare_a_large_volume() {
    // Both within MAX_VOXELS, on files of a few hundred bytes: two billion one-voxel frames
    // (per-frame loops), and one 46 340² frame (an 8 GiB voxel buffer). Refused from the
    // header, before either is touched.
    let root = tempfile::tempdir().unwrap();
    for (i, (rows, cols, frames)) in [(1u16, 1u16, "2000000000"), (46340, 46340, "1")]
        .into_iter()
        .enumerate()
    {
        let d = root.path().join(format!("c{i}"));
        let (_, files) = series(&d, [4, 4, 1], &DicomOptions::default());
        edit(&files[0], |o| {
            set(o, tags::ROWS, VR::US, PrimitiveValue::from(rows));
            set(o, tags::COLUMNS, VR::US, PrimitiveValue::from(cols));
            set(
                o,
                tags::NUMBER_OF_FRAMES,
                VR::IS,
                PrimitiveValue::from(frames),
            );
        });
        let e = read_volume(&d, None).unwrap_err();
        let msg = e.to_string();
        assert!(matches!(e, ReadError::Dicom { .. }), "{msg}");
        assert!(msg.contains("cannot come from a file of"), "{msg}");
        assert!(msg.contains("(7FE0,0010) Pixel Data"), "{msg}");
    }
}

#[test]
fn many_small_files_cannot_add_up_to_a_large_volume() {
    // Each 1200×1200 8-bit slice (1.44 MB) is within what one file allows (its bytes ×
    // MAX_FILE_EXPANSION + EXPANSION_SLACK); four of them are more than the series' bytes can
    // hold with one slack.
    let root = tempfile::tempdir().unwrap();
    let o = DicomOptions {
        layout: Layout::U8,
        ..DicomOptions::default()
    };
    let (_, files) = series(root.path(), [4, 4, 4], &o);
    for f in &files {
        edit(f, |o| {
            set(o, tags::ROWS, VR::US, PrimitiveValue::from(1200u16));
            set(o, tags::COLUMNS, VR::US, PrimitiveValue::from(1200u16));
        });
    }
    expect_series_error(root.path(), "bytes of files can hold");
}

/// An RT Dose grid as a treatment planning system writes one: a classic multi-frame object
/// whose frames are placed by Grid Frame Offset Vector, 32-bit unsigned samples scaled by Dose
/// Grid Scaling, saved in transfer syntax `ts`.
fn rt_dose(path: &Path, ts: &str, stored: &[u32], dims: [usize; 3], offsets: &[f64]) {
    use dicom_dictionary_std::uids;
    use dicom_object::FileMetaTableBuilder;
    let e = |tag, vr, v: PrimitiveValue| DataElement::new(tag, vr, v);
    let text = |s: &str| PrimitiveValue::from(s.to_string());
    let offsets: Vec<String> = offsets.iter().map(|x| x.to_string()).collect();
    let obj = InMemDicomObject::from_element_iter([
        e(tags::SOP_CLASS_UID, VR::UI, text(uids::RT_DOSE_STORAGE)),
        e(
            tags::SOP_INSTANCE_UID,
            VR::UI,
            text("1.2.826.0.1.3680043.9.7433.9.1"),
        ),
        e(tags::MODALITY, VR::CS, text("RTDOSE")),
        e(
            tags::SERIES_INSTANCE_UID,
            VR::UI,
            text("1.2.826.0.1.3680043.9.7433.9"),
        ),
        e(tags::SAMPLES_PER_PIXEL, VR::US, PrimitiveValue::from(1u16)),
        e(
            tags::PHOTOMETRIC_INTERPRETATION,
            VR::CS,
            text("MONOCHROME2"),
        ),
        e(tags::NUMBER_OF_FRAMES, VR::IS, text(&dims[2].to_string())),
        e(
            tags::FRAME_INCREMENT_POINTER,
            VR::AT,
            PrimitiveValue::Tags(vec![tags::GRID_FRAME_OFFSET_VECTOR].into()),
        ),
        e(tags::ROWS, VR::US, PrimitiveValue::from(dims[1] as u16)),
        e(tags::COLUMNS, VR::US, PrimitiveValue::from(dims[0] as u16)),
        e(tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(32u16)),
        e(tags::BITS_STORED, VR::US, PrimitiveValue::from(32u16)),
        e(tags::HIGH_BIT, VR::US, PrimitiveValue::from(31u16)),
        e(
            tags::PIXEL_REPRESENTATION,
            VR::US,
            PrimitiveValue::from(0u16),
        ),
        e(tags::PIXEL_SPACING, VR::DS, text("2.5\\2")),
        e(tags::IMAGE_POSITION_PATIENT, VR::DS, text("-10\\20.5\\30")),
        e(
            tags::IMAGE_ORIENTATION_PATIENT,
            VR::DS,
            text("1\\0\\0\\0\\1\\0"),
        ),
        e(
            tags::GRID_FRAME_OFFSET_VECTOR,
            VR::DS,
            PrimitiveValue::Strs(offsets.into()),
        ),
        e(tags::DOSE_UNITS, VR::CS, text("GY")),
        e(tags::DOSE_GRID_SCALING, VR::DS, text("1e-05")),
    ]);
    let mut obj = obj;
    if ts == "1.2.840.10008.1.2.5" {
        // RLE Lossless, a fragment a frame.
        let plane = dims[0] * dims[1];
        let fragments: Vec<Vec<u8>> = stored
            .chunks(plane)
            .map(|f| {
                let bytes: Vec<u8> = f.iter().flat_map(|v| v.to_le_bytes()).collect();
                fixtures::rle_frame(&bytes, 4, 1)
            })
            .collect();
        set(
            &mut obj,
            tags::PIXEL_DATA,
            VR::OB,
            dicom_core::DicomValue::from(dicom_core::value::PixelFragmentSequence::new(
                Vec::<u32>::new(),
                fragments,
            )),
        );
    } else {
        obj.put(e(
            tags::PIXEL_DATA,
            VR::OW,
            PrimitiveValue::U32(stored.to_vec().into()),
        ));
    }
    obj.with_meta(FileMetaTableBuilder::new().transfer_syntax(ts))
        .unwrap()
        .write_to_file(path)
        .unwrap();
}

/// 32-bit samples of a big-endian file were read without putting their 16-bit halves back in
/// order (795 000 came out as 561 512 460); RT Dose grids were refused for want of Spacing
/// Between Slices and their values not scaled to Gy; 32-bit RLE was refused ("Could not
/// decode pixel data").
#[test]
fn rt_dose_grids_read_in_gray_in_either_byte_order() {
    let dims = [4, 3, 5];
    let n: usize = dims.iter().product();
    let stored: Vec<u32> = (0..n as u32).map(|i| 795_000 + i * 7_919).collect();
    let dir = tempfile::tempdir().unwrap();
    for (name, ts, offsets) in [
        (
            "le-relative",
            "1.2.840.10008.1.2.1",
            vec![0.0, 3.0, 6.0, 9.0, 12.0],
        ),
        (
            "be-relative",
            "1.2.840.10008.1.2.2",
            vec![0.0, 3.0, 6.0, 9.0, 12.0],
        ),
        (
            "be-absolute",
            "1.2.840.10008.1.2.2",
            vec![30.0, 33.0, 36.0, 39.0, 42.0],
        ),
        ("rle", "1.2.840.10008.1.2.5", vec![0.0, 3.0, 6.0, 9.0, 12.0]),
    ] {
        let path = dir.path().join(format!("{name}.dcm"));
        rt_dose(&path, ts, &stored, dims, &offsets);
        let raw = std::fs::read(&path).unwrap();
        let want = if ts.ends_with(".2") {
            795_000u32.to_be_bytes()
        } else {
            795_000u32.to_le_bytes()
        };
        assert!(
            name == "rle" || raw.windows(4).any(|w| w == want),
            "{name}: the writer did not store the first sample in the file's byte order"
        );
        let v = read_volume(&path, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        if offsets[0] == 0.0 {
            check_against_pydicom(std::slice::from_ref(&path), &v, 1e-6, name);
        }
        assert_eq!(v.dims(), dims, "{name}");
        assert_eq!(v.spacing(), [2.0, 2.5, 3.0], "{name}");
        let p = v.placement().unwrap();
        assert_eq!(p.origin, [-10.0, 20.5, 30.0], "{name}");
        for (i, (&got, &s)) in v.channel(0).iter().zip(&stored).enumerate() {
            let gy = f64::from(s) * 1e-5;
            assert!(
                (f64::from(got) - gy).abs() <= 1e-6 * gy,
                "{name}: voxel {i} is {got} Gy, stored {s} × 1e-5 = {gy}"
            );
        }
    }
    // Offsets that do not match the frames are refused, naming the attribute.
    let path = dir.path().join("short.dcm");
    rt_dose(&path, "1.2.840.10008.1.2.1", &stored, dims, &[0.0, 3.0]);
    let e = read_volume(&path, None).unwrap_err().to_string();
    assert!(e.contains("(3004,000C)") && e.contains("5 frames"), "{e}");
}

/// An attribute written with VR UN by a toolkit that did not know it is read as the VR the
/// standard gives it: Image Orientation (Patient) was taken as the ASCII codes of its text.
#[test]
fn attributes_written_as_unknown_vr_are_read_as_their_standard_vr() {
    let v = volume([6, 5, 4], [0.8, 0.8, 2.0], Layout::I16, 1.0, -1024.0);
    let dir = tempfile::tempdir().unwrap();
    let o = DicomOptions {
        intercept: -1024.0,
        ..Default::default()
    };
    let files = write_dicom_series(dir.path(), &v, &o);
    for f in &files {
        let mut obj = open_file(f).unwrap();
        for tag in [tags::IMAGE_ORIENTATION_PATIENT, tags::ROWS] {
            let e = obj.element(tag).unwrap();
            let mut bytes = match tag {
                tags::ROWS => e.to_int::<u16>().unwrap().to_le_bytes().to_vec(),
                _ => e.to_str().unwrap().as_bytes().to_vec(),
            };
            if bytes.len() % 2 == 1 {
                bytes.push(b' ');
            }
            set(&mut obj, tag, VR::UN, PrimitiveValue::U8(bytes.into()));
        }
        obj.write_to_file(f).unwrap();
        let back = open_file(f).unwrap();
        assert_eq!(
            back.element(tags::IMAGE_ORIENTATION_PATIENT).unwrap().vr(),
            VR::UN,
            "the file must hold the attribute as UN for this test to mean anything"
        );
    }
    assert_same(&read_volume(dir.path(), None).unwrap(), &v, "UN attributes");
}

/// A multi-frame cine file (frames of one slice over time, no per-frame positions) at `path`,
/// made from the slices of `v`, its frames stepped by `pointer` (Frame Time or Frame Time
/// Vector, set to `value`).
fn write_cine(path: &Path, v: &Volume, pointer: Tag, value: &str) {
    let o = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    write_dicom_multiframe(path, v, &o);
    // Make it what an MR cine looks like: no per-frame positions, frames stepped by time.
    let mut obj = open_file(path).unwrap();
    obj.remove_element(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE);
    set(
        &mut obj,
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        PrimitiveValue::from("0\\0\\0".to_string()),
    );
    set(
        &mut obj,
        tags::FRAME_INCREMENT_POINTER,
        VR::AT,
        PrimitiveValue::Tags(vec![pointer].into()),
    );
    set(
        &mut obj,
        pointer,
        VR::DS,
        PrimitiveValue::from(value.to_string()),
    );
    obj.write_to_file(path).unwrap();
}

/// A cine (one slice over time) is not a volume: one volume's reader refuses it, saying what it
/// is and what reads it; the time series reader reads each frame as a time point of one slice
/// (the values the volume's slices had, the pixel spacing), at the times Frame Time or Frame
/// Time Vector give; a Frame Time Vector of the wrong length is refused by name.
#[test]
fn temporal_multiframe_files_are_time_series() {
    let v = volume([8, 7, 6], [0.5, 0.75, 5.0], Layout::U16, 1.0, 0.0);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cine.dcm");
    write_cine(&path, &v, tags::FRAME_TIME, "33.3");
    let e = read_volume(&path, None).unwrap_err().to_string();
    assert!(
        e.contains("time series") && e.contains("Frame Time") && e.contains("compress"),
        "{e}"
    );
    let (frames, times) = read_cine_file(&path).unwrap().expect("a cine");
    assert_eq!(frames.len(), 6);
    let times = times.expect("times from Frame Time");
    for (f, t) in times.iter().enumerate() {
        assert!((t - f as f64 * 0.0333).abs() < 1e-9, "frame {f} at {t}");
    }
    let plane = 8 * 7;
    for (f, frame) in frames.iter().enumerate() {
        assert_eq!(frame.dims(), [8, 7, 1]);
        assert_eq!(&frame.spacing()[..2], &[0.5, 0.75]);
        assert_eq!(
            frame.channel(0),
            &v.channel(0)[f * plane..(f + 1) * plane],
            "frame {f}"
        );
    }
    // A directory holding the one file reads the same.
    let (in_dir, _) = read_time_series(dir.path()).unwrap().expect("a cine");
    assert_eq!(in_dir.len(), 6);
    // Frame Time Vector: the increments since the previous frame.
    let p = dir.path().join("vector.dcm");
    write_cine(&p, &v, tags::FRAME_TIME_VECTOR, "0\\40\\40\\50\\40\\40");
    let (_, times) = read_cine_file(&p).unwrap().unwrap();
    assert_eq!(times.unwrap(), vec![0.0, 0.04, 0.08, 0.13, 0.17, 0.21]);
    write_cine(&p, &v, tags::FRAME_TIME_VECTOR, "0\\40\\40");
    let e = read_cine_file(&p).unwrap_err().to_string();
    assert!(e.contains("3 values for 6 frames"), "{e}");
    // A volume's multi-frame file is not a cine.
    let p = dir.path().join("volume.dcm");
    write_dicom_multiframe(
        &p,
        &v,
        &DicomOptions {
            layout: Layout::U16,
            ..Default::default()
        },
    );
    assert!(read_cine_file(&p).unwrap().is_none());
}

/// A 4D series (the same slices at several time points) is refused as a time series, not as
/// a pile of duplicate slices.
#[test]
fn series_of_several_time_points_are_refused_as_time_series() {
    let v = volume([6, 5, 3], [1.0, 1.0, 2.0], Layout::U16, 1.0, 0.0);
    let dir = tempfile::tempdir().unwrap();
    let o = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    let first = write_dicom_series(&dir.path().join("t1"), &v, &o);
    let second = write_dicom_series(&dir.path().join("t2"), &v, &o);
    let series = dir.path().join("4d");
    std::fs::create_dir_all(&series).unwrap();
    for (t, files) in [(1, &first), (2, &second)] {
        for (i, f) in files.iter().enumerate() {
            let mut obj = open_file(f).unwrap();
            set(
                &mut obj,
                tags::TEMPORAL_POSITION_IDENTIFIER,
                VR::IS,
                PrimitiveValue::from(t.to_string()),
            );
            set(
                &mut obj,
                tags::SOP_INSTANCE_UID,
                VR::UI,
                PrimitiveValue::from(format!("1.2.826.0.1.3680043.9.7433.4.{t}.{i}")),
            );
            obj.write_to_file(series.join(format!("t{t}-{i}.dcm")))
                .unwrap();
        }
    }
    let e = read_volume(&series, None).unwrap_err().to_string();
    assert!(
        e.contains("time series") && e.contains("2 time points") && e.contains("(0020,0100)"),
        "{e}"
    );
}

/// A baseline JPEG of `rgb` (w × h, interleaved) whose components are the RGB values
/// themselves (no colour transform), component ids 1, 2, 3, marked by an Adobe APP14 segment
/// with transform flag 0 and no JFIF segment: how some toolkits write lossy RGB.
fn adobe_rgb_jpeg(rgb: &[u8], w: u16, h: u16) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = jpeg_encoder::Encoder::new(&mut out, 100);
    enc.set_sampling_factor(jpeg_encoder::SamplingFactor::R_4_4_4);
    // "Adobe", version 100, flags 0 and 0, transform 0 (the components are RGB).
    let adobe = [b"Adobe".as_slice(), &[0, 100, 0, 0, 0, 0, 0]].concat();
    enc.add_app_segment(14, adobe).unwrap();
    // Ycbcr input is coded as given: the components are R, G and B.
    enc.encode(rgb, w, h, jpeg_encoder::ColorType::Ycbcr)
        .unwrap();
    // Drop the JFIF segment (APP0 right after SOI): with it, libjpeg too would read YCbCr.
    assert_eq!(&out[2..4], &[0xFF, 0xE0]);
    let len = usize::from(u16::from_be_bytes([out[4], out[5]]));
    out.drain(2..4 + len);
    // Component ids 1, 2, 3 (the encoder writes 0, 1, 2) in the frame and scan headers.
    let mut i = 2;
    while out[i] == 0xFF && out[i + 1] != 0xD9 {
        let marker = out[i + 1];
        let len = usize::from(u16::from_be_bytes([out[i + 2], out[i + 3]]));
        let (first, count, stride) = match marker {
            0xC0 => (i + 4 + 6, out[i + 4 + 5], 3),
            0xDA => (i + 4 + 1, out[i + 4], 2),
            _ => (0, 0, 0),
        };
        for k in 0..usize::from(count) {
            out[first + k * stride] += 1;
        }
        if marker == 0xDA {
            break;
        }
        i += 2 + len;
    }
    assert_eq!(jpeg_colour_markers(&out), (false, Some(0)));
    out
}

/// A baseline JPEG of `rgb` whose components are the RGB values themselves, with neither a
/// JFIF nor an Adobe segment and component ids 0, 1, 2 (what the encoder writes): libjpeg's
/// guess from the ids reads YCbCr, DICOM's Photometric Interpretation RGB says no transform.
fn unmarked_rgb_jpeg(rgb: &[u8], w: u16, h: u16) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = jpeg_encoder::Encoder::new(&mut out, 100);
    enc.set_sampling_factor(jpeg_encoder::SamplingFactor::R_4_4_4);
    enc.encode(rgb, w, h, jpeg_encoder::ColorType::Ycbcr)
        .unwrap();
    assert_eq!(&out[2..4], &[0xFF, 0xE0]);
    let len = usize::from(u16::from_be_bytes([out[4], out[5]]));
    out.drain(2..4 + len);
    assert_eq!(jpeg_colour_markers(&out), (false, None));
    out
}

#[test]
fn lossy_rgb_jpeg_with_an_adobe_marker_keeps_its_colours() {
    for marked in [true, false] {
        lossy_rgb_jpeg_keeps_its_colours(marked);
    }
}

/// A lossy RGB JPEG (Photometric Interpretation RGB) reads back its colours: marked by an
/// Adobe segment with ids 1, 2, 3, or unmarked with ids 0, 1, 2.
fn lossy_rgb_jpeg_keeps_its_colours(adobe_marked: bool) {
    use dicom_core::value::PixelFragmentSequence;
    use dicom_dictionary_std::uids;
    use dicom_object::FileMetaTableBuilder;
    let (w, h) = (16u16, 12u16);
    let rgb: Vec<u8> = (0..usize::from(w) * usize::from(h))
        .flat_map(|i| {
            let (x, y) = (i % usize::from(w), i / usize::from(w));
            [(40 + 12 * x) as u8, (200 - 10 * y) as u8, 90u8]
        })
        .collect();
    let mut jpeg = if adobe_marked {
        adobe_rgb_jpeg(&rgb, w, h)
    } else {
        unmarked_rgb_jpeg(&rgb, w, h)
    };
    if jpeg.len() % 2 == 1 {
        jpeg.push(0);
    }
    let e = |tag, vr, v: PrimitiveValue| DataElement::new(tag, vr, v);
    let text = |s: &str| PrimitiveValue::from(s.to_string());
    let mut obj = InMemDicomObject::from_element_iter([
        e(
            tags::SOP_CLASS_UID,
            VR::UI,
            text(uids::SECONDARY_CAPTURE_IMAGE_STORAGE),
        ),
        e(
            tags::SOP_INSTANCE_UID,
            VR::UI,
            text("1.2.826.0.1.3680043.9.7433.8.1"),
        ),
        e(
            tags::SERIES_INSTANCE_UID,
            VR::UI,
            text("1.2.826.0.1.3680043.9.7433.8"),
        ),
        e(tags::SAMPLES_PER_PIXEL, VR::US, PrimitiveValue::from(3u16)),
        e(tags::PHOTOMETRIC_INTERPRETATION, VR::CS, text("RGB")),
        e(
            tags::PLANAR_CONFIGURATION,
            VR::US,
            PrimitiveValue::from(0u16),
        ),
        e(tags::ROWS, VR::US, PrimitiveValue::from(h)),
        e(tags::COLUMNS, VR::US, PrimitiveValue::from(w)),
        e(tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(8u16)),
        e(tags::BITS_STORED, VR::US, PrimitiveValue::from(8u16)),
        e(tags::HIGH_BIT, VR::US, PrimitiveValue::from(7u16)),
        e(
            tags::PIXEL_REPRESENTATION,
            VR::US,
            PrimitiveValue::from(0u16),
        ),
    ]);
    set(
        &mut obj,
        tags::PIXEL_DATA,
        VR::OB,
        dicom_core::DicomValue::from(PixelFragmentSequence::new(Vec::<u32>::new(), vec![jpeg])),
    );
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("adobe-rgb.dcm");
    obj.with_meta(FileMetaTableBuilder::new().transfer_syntax(uids::JPEG_BASELINE8_BIT))
        .unwrap()
        .write_to_file(&path)
        .unwrap();
    let v = read_volume(&path, None).unwrap();
    assert_eq!(v.dims(), [usize::from(w), usize::from(h), 1]);
    let mut worst = 0.0f32;
    for (i, px) in rgb.chunks_exact(3).enumerate() {
        for c in 0..3 {
            worst = worst.max((v.channel(c)[i] - f32::from(px[c])).abs());
        }
    }
    // Quality 100 at 4:4:4: a few levels of rounding; read as YCbCr the colours are off by
    // tens to hundreds of levels.
    assert!(
        worst <= 4.0,
        "adobe marked {adobe_marked}: largest colour error {worst} levels"
    );
}

/// A build without CharLS refuses both JPEG-LS syntaxes naming the feature that reads them,
/// and nothing else; a build with it refuses neither. Runs in every build (CI's has the
/// feature), where the end-to-end refusal below runs only in a build without it.
#[test]
fn jpeg_ls_refusal_names_the_feature_only_where_it_is_left_out() {
    use dicom_dictionary_std::uids;
    let path = Path::new("series/1.dcm");
    for ts in [uids::JPEGLS_LOSSLESS, uids::JPEGLS_NEAR_LOSSLESS] {
        let err = super::pixels::jpeg_ls_refusal(path, ts, false)
            .expect("refused without the feature")
            .to_string();
        assert!(
            err.contains("JPEG-LS") && err.contains("--features jpeg-ls") && err.contains(ts),
            "{ts}: {err}"
        );
        assert!(super::pixels::jpeg_ls_refusal(path, ts, true).is_none());
    }
    for ts in [
        uids::EXPLICIT_VR_LITTLE_ENDIAN,
        uids::JPEG_LOSSLESS_SV1,
        uids::JPEG2000_LOSSLESS,
    ] {
        assert!(super::pixels::jpeg_ls_refusal(path, ts, false).is_none());
    }
}

/// Without the `jpeg-ls` feature a JPEG-LS file is refused before decoding, naming the
/// feature that reads it (not a panic, not a generic "cannot be decoded").
#[cfg(not(feature = "jpeg-ls"))]
#[test]
fn jpeg_ls_without_the_feature_is_refused_naming_it() {
    use dicom_core::value::PixelFragmentSequence;
    use dicom_dictionary_std::uids;
    use dicom_object::FileMetaTableBuilder;
    let e = |tag, vr, v: PrimitiveValue| DataElement::new(tag, vr, v);
    let text = |s: &str| PrimitiveValue::from(s.to_string());
    let mut obj = InMemDicomObject::from_element_iter([
        e(
            tags::SOP_CLASS_UID,
            VR::UI,
            text(uids::SECONDARY_CAPTURE_IMAGE_STORAGE),
        ),
        e(
            tags::SOP_INSTANCE_UID,
            VR::UI,
            text("1.2.826.0.1.3680043.9.7433.9.1"),
        ),
        e(
            tags::SERIES_INSTANCE_UID,
            VR::UI,
            text("1.2.826.0.1.3680043.9.7433.9"),
        ),
        e(tags::SAMPLES_PER_PIXEL, VR::US, PrimitiveValue::from(1u16)),
        e(
            tags::PHOTOMETRIC_INTERPRETATION,
            VR::CS,
            text("MONOCHROME2"),
        ),
        e(tags::ROWS, VR::US, PrimitiveValue::from(4u16)),
        e(tags::COLUMNS, VR::US, PrimitiveValue::from(4u16)),
        e(tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(16u16)),
        e(tags::BITS_STORED, VR::US, PrimitiveValue::from(12u16)),
        e(tags::HIGH_BIT, VR::US, PrimitiveValue::from(11u16)),
        e(
            tags::PIXEL_REPRESENTATION,
            VR::US,
            PrimitiveValue::from(0u16),
        ),
    ]);
    // A JPEG-LS start-of-image and end-of-image: never decoded, the syntax is refused first.
    let stream = vec![0xFF, 0xD8, 0xFF, 0xF7, 0xFF, 0xD9];
    set(
        &mut obj,
        tags::PIXEL_DATA,
        VR::OB,
        dicom_core::DicomValue::from(PixelFragmentSequence::new(Vec::<u32>::new(), vec![stream])),
    );
    let dir = tempfile::tempdir().unwrap();
    for ts in [uids::JPEGLS_LOSSLESS, uids::JPEGLS_NEAR_LOSSLESS] {
        let path = dir.path().join("jpeg-ls.dcm");
        obj.clone()
            .with_meta(FileMetaTableBuilder::new().transfer_syntax(ts))
            .unwrap()
            .write_to_file(&path)
            .unwrap();
        let err = read_volume(&path, None).unwrap_err().to_string();
        assert!(
            err.contains("JPEG-LS") && err.contains("--features jpeg-ls"),
            "{ts}: {err}"
        );
    }
}

/// JPEG-LS, the commonest lossless syntax of hospital archives after JPEG lossless: a series
/// transcoded by dicom-rs (CharLS) reads back exactly, and near-lossless within its NEAR.
#[cfg(feature = "jpeg-ls")]
#[test]
fn jpeg_ls_series_read_back_lossless_and_near_lossless() {
    use dicom_pixeldata::Transcode;
    use dicom_transfer_syntax_registry::entries::{
        JPEG_LS_LOSSLESS_IMAGE_COMPRESSION, JPEG_LS_LOSSY_IMAGE_COMPRESSION,
    };
    let v = volume([12, 10, 3], [0.7, 0.7, 2.0], Layout::U16, 1.0, 0.0);
    let o = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    // Quality 99 at 16 bits: NEAR = 2^12 × 1 / 100 = 40.
    let near = 40.0f32;
    for (name, ts, quality) in [
        (
            "lossless",
            JPEG_LS_LOSSLESS_IMAGE_COMPRESSION.erased(),
            None,
        ),
        (
            "near-lossless",
            JPEG_LS_LOSSY_IMAGE_COMPRESSION.erased(),
            Some(99),
        ),
    ] {
        let dir = tempfile::tempdir().unwrap();
        for f in write_dicom_series(dir.path(), &v, &o) {
            let mut obj = open_file(&f).unwrap();
            let mut options = dicom_encoding::adapters::EncodeOptions::default();
            options.quality = quality;
            obj.transcode_with_options(&ts, options).unwrap();
            assert_eq!(
                obj.meta().transfer_syntax().trim_end_matches('\0'),
                ts.uid(),
                "{name}"
            );
            obj.write_to_file(&f).unwrap();
        }
        let back = read_volume(dir.path(), None).unwrap_or_else(|e| panic!("{name}: {e}"));
        if quality.is_none() {
            assert_same(&back, &v, name);
        } else {
            let worst = back
                .channel(0)
                .iter()
                .zip(v.channel(0))
                .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                worst > 0.0 && worst <= near,
                "{name}: largest error {worst}"
            );
        }
    }
}

/// Which slice of `v` the series file `f` holds (the fixtures shuffle the file names): its
/// Image Position (Patient) along the slice normal, in slice steps.
fn slice_of(f: &Path, v: &Volume) -> usize {
    let obj = open_file(f).unwrap();
    let p = obj
        .element(tags::IMAGE_POSITION_PATIENT)
        .unwrap()
        .to_multi_float64()
        .unwrap();
    let pl = v.placement().unwrap();
    let d: f64 = (0..3)
        .map(|k| (p[k] - pl.origin[k]) * pl.directions[2][k])
        .sum();
    (d / f64::from(v.spacing()[2])).round() as usize
}

/// A reference coder's command `tool` (from the Debian package `package`), if installed.
/// Missing, the test says so and passes only when `WAVESPLAT_REQUIRE_REFERENCE_TOOLS` is unset
/// (CI sets it, with the package installed).
fn reference_tool(tool: &'static str, package: &str) -> Option<&'static str> {
    // Both coders print their usage and exit non-zero without arguments: being found is enough.
    let found = std::process::Command::new(tool).output().is_ok();
    if !found {
        assert!(
            std::env::var_os("WAVESPLAT_REQUIRE_REFERENCE_TOOLS").is_none(),
            "{tool} is missing (apt-get install {package})"
        );
        eprintln!("skipped: {tool} missing (apt-get install {package})");
        return None;
    }
    Some(tool)
}

/// `opj_compress` (OpenJPEG's command-line encoder, Debian's `libopenjp2-tools`): the test's
/// independent JPEG 2000 encoder.
fn opj_compress() -> Option<&'static str> {
    reference_tool("opj_compress", "libopenjp2-tools")
}

/// Runs a reference coder, failing the test with its error output.
fn run_tool(tool: &str, args: &[&str]) {
    let out = std::process::Command::new(tool)
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{tool} {args:?}: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The samples of a 16-bit binary PGM (big-endian), the last `n`.
fn pgm_samples(pgm: &[u8], n: usize) -> Vec<f32> {
    pgm[pgm.len() - 2 * n..]
        .chunks_exact(2)
        .map(|b| f32::from(u16::from_be_bytes([b[0], b[1]])))
        .collect()
}

/// Writes `v` (16-bit, one channel) as a DICOM series in `dir`/series, each slice coded by a
/// reference coder and wrapped as one fragment with transfer syntax `ts`: the slice goes to
/// the coder as a 16-bit PGM (`coder` plus `args`, its input after `-i`, its output, named
/// `*.ext`, after `-o`), and the coder's own decoder (`decoder -i CODED -o OUT.pgm`) gives
/// the reference samples. Returns the series directory and the reference samples.
fn series_coded_by(
    dir: &Path,
    v: &Volume,
    (coder, args, ext): (&str, &[&str], &str),
    decoder: &str,
    ts: &str,
) -> (PathBuf, Vec<f32>) {
    use dicom_core::value::PixelFragmentSequence;
    let dims = v.dims();
    let plane = dims[0] * dims[1];
    let o = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    let series = dir.join("series");
    let mut reference = vec![0f32; v.voxel_count()];
    for (z, f) in write_dicom_series(&series, v, &o).iter().enumerate() {
        let z_of = slice_of(f, v);
        let mut pgm = format!("P5\n{} {}\n65535\n", dims[0], dims[1]).into_bytes();
        for x in &v.channel(0)[z_of * plane..(z_of + 1) * plane] {
            pgm.extend_from_slice(&(*x as u16).to_be_bytes());
        }
        let (src, dst, decoded) = (
            dir.join(format!("{z}.pgm")),
            dir.join(format!("{z}.{ext}")),
            dir.join(format!("{z}-decoded.pgm")),
        );
        std::fs::write(&src, pgm).unwrap();
        let (src, dst, decoded) = (
            src.to_str().unwrap(),
            dst.to_str().unwrap(),
            decoded.to_str().unwrap(),
        );
        let mut coder_args = vec!["-i", src, "-o", dst];
        coder_args.extend(args);
        run_tool(coder, &coder_args);
        run_tool(decoder, &["-i", dst, "-o", decoded]);
        reference[z_of * plane..(z_of + 1) * plane]
            .copy_from_slice(&pgm_samples(&std::fs::read(decoded).unwrap(), plane));
        let mut coded = std::fs::read(dst).unwrap();
        if coded.len() % 2 == 1 {
            coded.push(0);
        }
        edit(f, |o| {
            set(
                o,
                tags::PIXEL_DATA,
                VR::OB,
                dicom_core::DicomValue::from(PixelFragmentSequence::new(
                    Vec::<u32>::new(),
                    vec![coded.clone()],
                )),
            );
            o.update_meta(|m| m.transfer_syntax = ts.into());
        });
    }
    (series, reference)
}

/// High-Throughput JPEG 2000 (lossless, lossless RPCL and lossy), coded by OpenJPH
/// (`ojph_compress`, Debian's `openjph-tools`, a coder independent of the OpenJPEG port that
/// decodes it here) from the slices' samples and wrapped into the series' files: read back
/// sample for sample as OpenJPH's own decoder (`ojph_expand`) reads them, and lossless equal
/// to the source.
#[test]
fn high_throughput_jpeg_2000_coded_by_openjph_reads_back() {
    let Some(tool) = reference_tool("ojph_compress", "openjph-tools") else {
        return;
    };
    // Not a power of two, and more than two decompositions' worth of samples.
    let v = volume([37, 29, 3], [0.7, 0.7, 2.0], Layout::U16, 1.0, 0.0);
    for (name, ts, args) in [
        (
            "lossless",
            "1.2.840.10008.1.2.4.201",
            vec!["-reversible", "true"],
        ),
        (
            "lossless RPCL",
            "1.2.840.10008.1.2.4.202",
            vec!["-reversible", "true", "-prog_order", "RPCL"],
        ),
        ("lossy", "1.2.840.10008.1.2.4.203", vec!["-qstep", "0.02"]),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let mut coder_args = vec!["-num_decomps", "2"];
        coder_args.extend(&args);
        let (series, reference) = series_coded_by(
            dir.path(),
            &v,
            (tool, &coder_args, "j2c"),
            "ojph_expand",
            ts,
        );
        let back = read_volume(&series, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        if args.contains(&"-reversible") {
            assert_same(&back, &v, name);
            assert_eq!(back.channel(0), &reference[..], "{name}");
        } else {
            assert_ne!(back.channel(0), v.channel(0), "{name} should be lossy");
            // The irreversible wavelet is floating point, and each decoder computes and rounds
            // it its own way (OpenJPH and the OpenJPEG port differ by up to 2 of 65 535 on
            // about half of the samples here): they must agree to 1 % of the coding error.
            let worst = back
                .channel(0)
                .iter()
                .zip(&reference)
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max);
            let coding = reference
                .iter()
                .zip(v.channel(0))
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max);
            assert!(
                coding > 100.0,
                "{name}: the coding error {coding} is too small to test"
            );
            assert!(
                worst <= 0.01 * coding,
                "{name}: differs from OpenJPH's decoder by {worst}, coding error {coding}"
            );
        }
    }
}

/// JPEG 2000, lossless and lossy, coded by OpenJPEG's own encoder from the slices' samples and
/// wrapped into the series' files: read back sample for sample as OpenJPEG's own decoder
/// (`opj_decompress`) reads them, and lossless equal to the source.
#[test]
fn jpeg_2000_series_coded_by_openjpeg_read_back() {
    let Some(tool) = opj_compress() else {
        return;
    };
    let v = volume([14, 11, 3], [0.7, 0.7, 2.0], Layout::U16, 1.0, 0.0);
    for (name, ts, args) in [
        ("lossless", "1.2.840.10008.1.2.4.90", vec![]),
        ("lossy", "1.2.840.10008.1.2.4.91", vec!["-r", "8"]),
    ] {
        let dir = tempfile::tempdir().unwrap();
        // Two resolution levels: the default six need images of at least 32².
        let mut coder_args = vec!["-n", "2"];
        coder_args.extend(&args);
        let (series, reference) = series_coded_by(
            dir.path(),
            &v,
            (tool, &coder_args, "j2k"),
            "opj_decompress",
            ts,
        );
        let back = read_volume(&series, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        // Every sample as OpenJPEG's decoder gives it; lossless, also the source's.
        assert_eq!(back.channel(0), &reference[..], "{name}");
        if args.is_empty() {
            assert_same(&back, &v, name);
        } else {
            assert_ne!(back.channel(0), v.channel(0), "{name} should be lossy");
        }
    }
}

/// Full-range Y, Cb, Cr of an RGB colour (PS3.3 C.7.6.3.1.2), rounded to 8 bits: the forward
/// transform, written out here independently of the reader's inverse.
fn ybr_full(rgb: [f64; 3]) -> [f32; 3] {
    let [r, g, b] = rgb;
    let q = |v: f64| v.round().clamp(0.0, 255.0) as f32;
    [
        q(0.299 * r + 0.587 * g + 0.114 * b),
        q(-0.168736 * r - 0.331264 * g + 0.5 * b + 128.0),
        q(0.5 * r - 0.418688 * g - 0.081312 * b + 128.0),
    ]
}

/// YBR_FULL in native and RLE files, and native YBR_FULL_422 (refused before), read as RGB:
/// the samples were stored as if Y, Cb and Cr were R, G and B.
#[test]
fn ybr_full_and_ybr_full_422_read_as_rgb() {
    let dims = [8, 6, 2];
    let n: usize = dims.iter().product();
    // Colours constant over each horizontal pair, so 4:2:2 loses nothing.
    let rgb: Vec<[f64; 3]> = (0..n)
        .map(|i| {
            let (x, y, z) = (
                i % dims[0] / 2,
                i / dims[0] % dims[1],
                i / (dims[0] * dims[1]),
            );
            [
                (30 + 50 * x) as f64,
                (220 - 30 * y) as f64,
                (60 + 100 * z) as f64,
            ]
        })
        .collect();
    let ybr: Vec<[f32; 3]> = rgb.iter().map(|c| ybr_full(*c)).collect();
    let channels: Vec<Vec<f32>> = (0..3).map(|c| ybr.iter().map(|p| p[c]).collect()).collect();
    let stored = Volume::new(dims, [1.0, 1.0, 2.0], channels)
        .unwrap()
        .with_placement(oblique())
        .unwrap();
    let check = |back: &Volume, what: &str| {
        let mut worst = 0f64;
        for (i, c) in rgb.iter().enumerate() {
            for k in 0..3 {
                worst = worst.max((f64::from(back.channel(k)[i]) - c[k]).abs());
            }
        }
        // 8-bit Y, Cb, Cr round each colour by up to ~1.5 levels.
        assert!(worst <= 2.0, "{what}: largest colour error {worst} levels");
    };
    for (what, encoding) in [
        ("native", DicomEncoding::ExplicitLittle),
        ("RLE", DicomEncoding::RleLossless),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let o = DicomOptions {
            layout: Layout::U8,
            encoding,
            ..DicomOptions::default()
        };
        let files = write_dicom_series(dir.path(), &stored, &o);
        for f in &files {
            edit(f, |o| {
                set(
                    o,
                    tags::PHOTOMETRIC_INTERPRETATION,
                    VR::CS,
                    PrimitiveValue::from("YBR_FULL".to_string()),
                );
            });
        }
        let back = read_volume(dir.path(), None).unwrap_or_else(|e| panic!("{what}: {e}"));
        check(&back, what);
        // pydicom converts in f32: a level either way at a rounding boundary.
        check_against_pydicom(&files, &back, 1.0, what);
    }
    // Native 4:2:2: Y1 Y2 Cb Cr for each pair of pixels along a row.
    let dir = tempfile::tempdir().unwrap();
    let o = DicomOptions {
        layout: Layout::U8,
        ..DicomOptions::default()
    };
    let files = write_dicom_series(dir.path(), &stored, &o);
    for f in &files {
        let z = slice_of(f, &stored);
        let plane = dims[0] * dims[1];
        let mut packed = Vec::new();
        for q in 0..plane / 2 {
            let (a, b) = (ybr[z * plane + 2 * q], ybr[z * plane + 2 * q + 1]);
            packed.extend_from_slice(&[a[0] as u8, b[0] as u8, a[1] as u8, a[2] as u8]);
        }
        edit(f, |o| {
            set(
                o,
                tags::PHOTOMETRIC_INTERPRETATION,
                VR::CS,
                PrimitiveValue::from("YBR_FULL_422".to_string()),
            );
            set(
                o,
                tags::PIXEL_DATA,
                VR::OB,
                PrimitiveValue::U8(packed.clone().into()),
            );
        });
    }
    let back = read_volume(dir.path(), None).unwrap();
    check(&back, "native YBR_FULL_422");
    check_against_pydicom(&files, &back, 1.0, "native YBR_FULL_422");
}

#[test]
fn packbits_decodes_literal_and_replicate_runs() {
    // PS3.5 G.3.1: n ≥ 0 copies n + 1 bytes, −127 ≤ n ≤ −1 repeats the next byte 1 − n
    // times, −128 does nothing.
    let coded = [2, 10, 11, 12, 0xFE, 7, 0x80, 0, 9];
    assert_eq!(packbits(&coded, 7).unwrap(), vec![10, 11, 12, 7, 7, 7, 9]);
    assert_eq!(packbits(&coded, 8), None);
    assert_eq!(packbits(&[5, 1, 2], 3), None);
}

/// The independent reader the DICOM tests check values against: pydicom (Debian's
/// `python3-pydicom`, with numpy), run on the same files. It decodes the pixel data with its own
/// handlers (native in either byte order, RLE), applies the rescale, Dose Grid Scaling and the
/// YBR_FULL → RGB conversion, and orders the frames along the slice normal.
const PYDICOM_READER: &str = r#"
import sys
import numpy as np
import pydicom
from pydicom.pixel_data_handlers.util import apply_color_lut, convert_color_space
out, paths = sys.argv[1], sys.argv[2:]
slices = []
for p in paths:
    ds = pydicom.dcmread(p)
    frames = int(getattr(ds, "NumberOfFrames", 1) or 1)
    spp = int(ds.SamplesPerPixel)
    a = ds.pixel_array
    pi = str(ds.PhotometricInterpretation)
    if spp == 3 and pi.startswith("YBR_FULL"):
        a = convert_color_space(a, pi, "RGB")
    if pi == "PALETTE COLOR":
        a, spp = apply_color_lut(a, ds), 3
    a = a.astype(np.float64)
    if "RescaleSlope" in ds and pi != "PALETTE COLOR":
        a = a * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
    if "DoseGridScaling" in ds:
        a = a * float(ds.DoseGridScaling)
    a = a.reshape((frames, int(ds.Rows), int(ds.Columns), spp))
    pos = np.array([float(x) for x in ds.ImagePositionPatient])
    iop = [float(x) for x in ds.ImageOrientationPatient]
    n = np.cross(iop[:3], iop[3:])
    offsets = [float(x) for x in getattr(ds, "GridFrameOffsetVector", [0.0] * frames)]
    for f in range(frames):
        slices.append((float(np.dot(pos, n)) + offsets[f], a[f]))
slices.sort(key=lambda s: s[0])
np.stack([s[1] for s in slices]).astype("<f8").tofile(out)
"#;

/// Checks `v`, read from `files` by wavesplat, value by value against pydicom's reading of the
/// same files (within `tolerance`, relative to 1 or the value's magnitude).
fn check_against_pydicom(files: &[PathBuf], v: &Volume, tolerance: f64, what: &str) {
    let Some(python) = wavesplat_fixtures::reference_python(
        "pydicom, numpy",
        "apt-get install python3-pydicom python3-numpy",
    ) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (script, out) = (dir.path().join("read.py"), dir.path().join("out.f64"));
    std::fs::write(&script, PYDICOM_READER).unwrap();
    let o = std::process::Command::new(python)
        .arg(&script)
        .arg(&out)
        .args(files)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{what}: pydicom failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let reference: Vec<f64> = std::fs::read(&out)
        .unwrap()
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
        .collect();
    let [nx, ny, nz] = v.dims();
    let nc = v.channel_count();
    assert_eq!(reference.len(), nx * ny * nz * nc, "{what}: sample count");
    for (k, r) in reference.iter().enumerate() {
        let (c, x, y, z) = (k % nc, k / nc % nx, k / nc / nx % ny, k / nc / nx / ny);
        let ours = f64::from(v.channel(c)[x + nx * (y + ny * z)]);
        assert!(
            (ours - r).abs() <= tolerance * r.abs().max(1.0),
            "{what}: sample ({x}, {y}, {z}) channel {c}: wavesplat {ours}, pydicom {r}"
        );
    }
}

/// Native (explicit and implicit little endian) and RLE series, signed and unsigned, with a
/// rescale, read as pydicom reads them.
#[test]
fn series_values_agree_with_pydicom() {
    for (what, layout, slope, intercept, encoding) in [
        (
            "i16 explicit, rescaled",
            Layout::I16,
            2.0,
            -1024.0,
            DicomEncoding::ExplicitLittle,
        ),
        (
            "u16 implicit",
            Layout::U16,
            1.0,
            0.0,
            DicomEncoding::ImplicitLittle,
        ),
        (
            "i16 RLE",
            Layout::I16,
            1.0,
            -1024.0,
            DicomEncoding::RleLossless,
        ),
        (
            "u8 RLE, fractional slope",
            Layout::U8,
            0.5,
            3.0,
            DicomEncoding::RleLossless,
        ),
    ] {
        let v = volume([9, 7, 4], [0.9, 0.8, 2.5], layout, slope, intercept);
        let dir = tempfile::tempdir().unwrap();
        let o = DicomOptions {
            layout,
            slope,
            intercept,
            encoding,
            ..Default::default()
        };
        let files = write_dicom_series(dir.path(), &v, &o);
        let back = read_volume(dir.path(), None).unwrap_or_else(|e| panic!("{what}: {e}"));
        assert_same(&back, &v, what);
        check_against_pydicom(&files, &back, 0.0, what);
    }
}

/// PALETTE COLOR images (refused before) read as the palette's RGB, as pydicom applies it.
#[test]
fn palette_colour_series_read_as_their_colours() {
    let dims = [7, 5, 3];
    let v = volume(dims, [1.0, 1.0, 2.0], Layout::U8, 1.0, 0.0);
    let dir = tempfile::tempdir().unwrap();
    let o = DicomOptions {
        layout: Layout::U8,
        ..Default::default()
    };
    let files = write_dicom_series(dir.path(), &v, &o);
    // 200 entries from stored value 20: values below take the first entry, above the last.
    let (entries, first) = (200usize, 20u16);
    let table = |c: usize| -> Vec<u16> {
        (0..entries)
            .map(|i| ((i * (97 + 31 * c) + 1000 * c) % 65536) as u16)
            .collect()
    };
    for f in &files {
        edit(f, |o| {
            set(
                o,
                tags::PHOTOMETRIC_INTERPRETATION,
                VR::CS,
                PrimitiveValue::from("PALETTE COLOR".to_string()),
            );
            o.remove_element(tags::RESCALE_SLOPE);
            o.remove_element(tags::RESCALE_INTERCEPT);
            for (c, (d, t)) in [
                (
                    tags::RED_PALETTE_COLOR_LOOKUP_TABLE_DESCRIPTOR,
                    tags::RED_PALETTE_COLOR_LOOKUP_TABLE_DATA,
                ),
                (
                    tags::GREEN_PALETTE_COLOR_LOOKUP_TABLE_DESCRIPTOR,
                    tags::GREEN_PALETTE_COLOR_LOOKUP_TABLE_DATA,
                ),
                (
                    tags::BLUE_PALETTE_COLOR_LOOKUP_TABLE_DESCRIPTOR,
                    tags::BLUE_PALETTE_COLOR_LOOKUP_TABLE_DATA,
                ),
            ]
            .into_iter()
            .enumerate()
            {
                set(
                    o,
                    d,
                    VR::US,
                    PrimitiveValue::U16(vec![entries as u16, first, 16].into()),
                );
                set(o, t, VR::OW, PrimitiveValue::U16(table(c).into()));
            }
        });
    }
    let back = read_volume(dir.path(), None).unwrap();
    assert_eq!(back.channel_count(), 3);
    for (i, stored) in v.channel(0).iter().enumerate() {
        let k = (*stored as i64 - i64::from(first)).clamp(0, entries as i64 - 1) as usize;
        for c in 0..3 {
            assert_eq!(
                back.channel(c)[i],
                f32::from(table(c)[k]),
                "voxel {i} colour {c}"
            );
        }
    }
    check_against_pydicom(&files, &back, 0.0, "PALETTE COLOR");
}

/// A 1-bit mask (5 × 3 pixels, 3 frames: 15 bits a frame, so frames 2 and 3 start inside a
/// byte) as a classic multi-frame Explicit VR Little Endian file at `path`; returns the mask
/// as a volume and its packed bits (least significant bit first, padded to an even length).
fn one_bit_mask_file(path: &Path) -> (Volume, Vec<u8>) {
    let dims = [5, 3, 3];
    let n: usize = dims.iter().product();
    let bits: Vec<u8> = (0..n).map(|i| u8::from((i * 7919) % 5 < 2)).collect();
    let v = Volume::new(
        dims,
        [1.0, 1.0, 2.0],
        vec![bits.iter().map(|b| f32::from(*b)).collect()],
    )
    .unwrap()
    .with_placement(oblique())
    .unwrap();
    let mut packed = vec![0u8; n.div_ceil(8)];
    for (k, b) in bits.iter().enumerate() {
        packed[k / 8] |= b << (k % 8);
    }
    if packed.len() % 2 == 1 {
        packed.push(0);
    }
    let o = DicomOptions {
        layout: Layout::U8,
        ..Default::default()
    };
    write_dicom_multiframe(path, &v, &o);
    // A classic multi-frame file (what pydicom's check places by Image Position and the
    // slice step), 1 bit a sample.
    let p = v.placement().unwrap();
    edit(path, |obj| {
        obj.remove_element(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE);
        obj.remove_element(tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE);
        obj.remove_element(tags::RESCALE_SLOPE);
        obj.remove_element(tags::RESCALE_INTERCEPT);
        let ds = |v: &[f64]| {
            PrimitiveValue::from(
                v.iter()
                    .map(|x| x.to_string())
                    .collect::<Vec<_>>()
                    .join("\\"),
            )
        };
        let d = p.directions;
        set(obj, tags::IMAGE_POSITION_PATIENT, VR::DS, ds(&p.origin));
        set(
            obj,
            tags::IMAGE_ORIENTATION_PATIENT,
            VR::DS,
            ds(&[d[0][0], d[0][1], d[0][2], d[1][0], d[1][1], d[1][2]]),
        );
        set(obj, tags::PIXEL_SPACING, VR::DS, ds(&[1.0, 1.0]));
        set(obj, tags::SPACING_BETWEEN_SLICES, VR::DS, ds(&[2.0]));
        for (tag, value) in [
            (tags::BITS_ALLOCATED, 1u16),
            (tags::BITS_STORED, 1),
            (tags::HIGH_BIT, 0),
        ] {
            set(obj, tag, VR::US, PrimitiveValue::from(value));
        }
        set(
            obj,
            tags::PIXEL_DATA,
            VR::OB,
            PrimitiveValue::U8(packed.clone().into()),
        );
    });
    (v, packed)
}

/// 1-bit masks (refused before) read as 0 and 1, their bits running on across frames without
/// padding, as pydicom reads them.
#[test]
fn one_bit_masks_read_as_zero_and_one() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mask.dcm");
    let (v, _) = one_bit_mask_file(&path);
    let back = read_volume(&path, None).unwrap();
    assert_eq!(back.channel(0), v.channel(0));
    check_against_pydicom(std::slice::from_ref(&path), &back, 0.0, "1-bit mask");
}

/// Rewrites the DICOM file `src` as Explicit VR Big Endian at `dst`, with `edit` applied to its
/// data set first.
fn rewrite_big_endian(src: &Path, dst: &Path, edit: impl FnOnce(&mut InMemDicomObject)) {
    use dicom_object::FileMetaTableBuilder;
    let mut obj = open_file(src).unwrap().into_inner();
    edit(&mut obj);
    obj.with_meta(FileMetaTableBuilder::new().transfer_syntax(EXPLICIT_VR_BIG_ENDIAN))
        .unwrap()
        .write_to_file(dst)
        .unwrap();
}

/// 1-bit masks in Explicit VR Big Endian (refused before): as OB their bytes are not swapped
/// in either byte order, so the bits read as in little endian, as pydicom reads them; as OW,
/// where toolkits disagree on the bit order, they are refused naming the layout.
#[test]
fn one_bit_masks_in_big_endian_read_as_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let le = dir.path().join("mask-le.dcm");
    let (v, packed) = one_bit_mask_file(&le);
    let be = dir.path().join("mask-be.dcm");
    rewrite_big_endian(&le, &be, |_| {});
    let raw = std::fs::read(&be).unwrap();
    assert!(
        raw.windows(packed.len()).any(|w| w == packed),
        "OB pixel data is written in file order"
    );
    let back = read_volume(&be, None).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(back.channel(0), v.channel(0));
    check_against_pydicom(
        std::slice::from_ref(&be),
        &back,
        0.0,
        "1-bit mask, big endian",
    );

    let ow = dir.path().join("mask-be-ow.dcm");
    rewrite_big_endian(&le, &ow, |o| {
        let words: Vec<u16> = packed
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect();
        set(
            o,
            tags::PIXEL_DATA,
            VR::OW,
            PrimitiveValue::U16(words.into()),
        );
    });
    let e = read_volume(&ow, None).unwrap_err().to_string();
    assert!(
        e.contains("1-bit samples in 16-bit words (OW) in an Explicit VR Big Endian file")
            && e.contains("(7FE0,0010) Pixel Data"),
        "{e}"
    );
}

/// Explicit VR Big Endian pixel data in 16-bit words (OW): 8-bit samples (refused before) read
/// as pydicom 3 reads them, each word's two bytes swapped back (the first sample is the low
/// byte of the first word), also where a frame starts inside a word; 8 bits stored in 16-bit
/// samples keep their low 8 bits whatever lies above them. Both read back as the little-endian
/// file they were made from.
#[test]
fn big_endian_samples_in_16_bit_words_read_in_order() {
    let dir = tempfile::tempdir().unwrap();
    // 5 × 3 pixels: 15 samples a frame, so frames 2 and 3 start inside a word.
    let v = volume([5, 3, 3], [1.0, 1.0, 2.0], Layout::U8, 1.0, 0.0);
    let le = dir.path().join("le.dcm");
    let o = DicomOptions {
        layout: Layout::U8,
        ..Default::default()
    };
    write_dicom_multiframe(&le, &v, &o);
    let want = read_volume(&le, None).unwrap();
    let mut samples = open_file(&le)
        .unwrap()
        .element(tags::PIXEL_DATA)
        .unwrap()
        .to_bytes()
        .unwrap()
        .to_vec();
    samples.truncate(5 * 3 * 3); // without the padding byte

    let eight = dir.path().join("be-8-in-ow.dcm");
    rewrite_big_endian(&le, &eight, |o| {
        let words: Vec<u16> = samples
            .chunks(2)
            .map(|c| u16::from(c[0]) | (u16::from(*c.get(1).unwrap_or(&0)) << 8))
            .collect();
        set(
            o,
            tags::PIXEL_DATA,
            VR::OW,
            PrimitiveValue::U16(words.into()),
        );
    });
    let raw = std::fs::read(&eight).unwrap();
    assert!(
        raw.windows(4)
            .any(|w| w == [samples[1], samples[0], samples[3], samples[2]]),
        "the writer did not store the words big-endian"
    );

    let sixteen = dir.path().join("be-16-bits-8-stored.dcm");
    rewrite_big_endian(&le, &sixteen, |o| {
        let words: Vec<u16> = samples.iter().map(|s| u16::from(*s) | 0xA500).collect();
        set(o, tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(16u16));
        set(o, tags::BITS_STORED, VR::US, PrimitiveValue::from(8u16));
        set(o, tags::HIGH_BIT, VR::US, PrimitiveValue::from(7u16));
        set(
            o,
            tags::PIXEL_DATA,
            VR::OW,
            PrimitiveValue::U16(words.into()),
        );
    });
    for (what, path) in [
        ("8 bits allocated in OW", &eight),
        ("8 of 16 bits stored", &sixteen),
    ] {
        let back = read_volume(path, None).unwrap_or_else(|e| panic!("{what}: {e}"));
        assert_eq!(back.dims(), want.dims(), "{what}");
        assert_eq!(back.channel(0), want.channel(0), "{what}");
    }
}

/// A greyscale JPEG of 12-bit precision in the extended process (SOF1), as a 12-bit lossy
/// DICOM file would hold: an 8-bit baseline stream from the encoder with its frame header
/// rewritten (the reader refuses from the frame header, before any decoding).
fn twelve_bit_jpeg(w: u16, h: u16) -> Vec<u8> {
    let grey: Vec<u8> = (0..usize::from(w) * usize::from(h))
        .map(|i| (i * 37 % 251) as u8)
        .collect();
    let mut out = Vec::new();
    jpeg_encoder::Encoder::new(&mut out, 90)
        .encode(&grey, w, h, jpeg_encoder::ColorType::Luma)
        .unwrap();
    let sof = out.windows(2).position(|m| m == [0xFF, 0xC0]).unwrap();
    out[sof + 1] = 0xC1;
    out[sof + 4] = 12;
    assert_eq!(jpeg_sample_precision(&out), Some(12));
    out
}

/// 12-bit lossy JPEG (the extended process, which jpeg-decoder does not decode) is refused
/// naming the feature, not with the decoder's generic error.
#[test]
fn twelve_bit_lossy_jpeg_is_refused_naming_it() {
    use dicom_core::value::PixelFragmentSequence;
    use dicom_dictionary_std::uids;
    use dicom_object::FileMetaTableBuilder;
    let (w, h) = (16u16, 8u16);
    let mut jpeg = twelve_bit_jpeg(w, h);
    if jpeg.len() % 2 == 1 {
        jpeg.push(0);
    }
    let e = |tag, vr, v: PrimitiveValue| DataElement::new(tag, vr, v);
    let text = |s: &str| PrimitiveValue::from(s.to_string());
    let mut obj = InMemDicomObject::from_element_iter([
        e(
            tags::SOP_CLASS_UID,
            VR::UI,
            text(uids::SECONDARY_CAPTURE_IMAGE_STORAGE),
        ),
        e(
            tags::SOP_INSTANCE_UID,
            VR::UI,
            text("1.2.826.0.1.3680043.9.7433.10.1"),
        ),
        e(tags::SAMPLES_PER_PIXEL, VR::US, PrimitiveValue::from(1u16)),
        e(
            tags::PHOTOMETRIC_INTERPRETATION,
            VR::CS,
            text("MONOCHROME2"),
        ),
        e(tags::ROWS, VR::US, PrimitiveValue::from(h)),
        e(tags::COLUMNS, VR::US, PrimitiveValue::from(w)),
        e(tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(16u16)),
        e(tags::BITS_STORED, VR::US, PrimitiveValue::from(12u16)),
        e(tags::HIGH_BIT, VR::US, PrimitiveValue::from(11u16)),
        e(
            tags::PIXEL_REPRESENTATION,
            VR::US,
            PrimitiveValue::from(0u16),
        ),
    ]);
    set(
        &mut obj,
        tags::PIXEL_DATA,
        VR::OB,
        dicom_core::DicomValue::from(PixelFragmentSequence::new(Vec::<u32>::new(), vec![jpeg])),
    );
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("jpeg12.dcm");
    obj.with_meta(FileMetaTableBuilder::new().transfer_syntax("1.2.840.10008.1.2.4.51"))
        .unwrap()
        .write_to_file(&path)
        .unwrap();
    let e = read_volume(&path, None).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, ReadError::Dicom { .. }), "{msg}");
    assert!(
        msg.contains("12-bit lossy JPEG (extended process) is not supported")
            && msg.contains("jpeg12.dcm"),
        "{msg}"
    );
}

/// Where `pat` starts in `bytes`.
fn find(bytes: &[u8], pat: &[u8]) -> usize {
    bytes
        .windows(pat.len())
        .position(|w| w == pat)
        .unwrap_or_else(|| panic!("{pat:?} not in the file"))
}

/// An element whose VR bytes are not a VR, in an Explicit VR Little Endian file, read as the
/// reference toolkits read it when wavesplat does not need the attribute (refused before):
/// `??` with a 2-byte length (dcmtk), letters that are no VR with a 2-byte length (pydicom),
/// letters with the 4-byte length of a VR newer than the dictionary (dcmtk, dicom-rs), and an
/// element written in implicit VR inside the explicit data set (pydicom). The file reads back
/// its volume, and as pydicom reads it where pydicom reads that layout. An attribute the
/// reader needs is refused, naming it.
#[test]
fn unknown_value_representations_are_read_as_other_toolkits_read_them() {
    let dir = tempfile::tempdir().unwrap();
    let v = volume([5, 4, 1], [0.8, 0.8, 2.0], Layout::I16, 1.0, 0.0);
    let files = write_dicom_series(&dir.path().join("src"), &v, &DicomOptions::default());
    let study = Tag(0x0008, 0x1030); // Study Description, LO: not read by wavesplat
    edit(&files[0], |o| {
        set(o, study, VR::LO, PrimitiveValue::from("HEAD CT "));
    });
    let bytes = std::fs::read(&files[0]).unwrap();
    let lo = find(&bytes, &[0x08, 0x00, 0x30, 0x10, b'L', b'O', 8, 0]);
    let with = |patch: &dyn Fn(&mut Vec<u8>)| {
        let mut b = bytes.clone();
        patch(&mut b);
        b
    };
    let mut cases: Vec<(&str, Vec<u8>, bool)> = vec![
        (
            "?? with a 2-byte length",
            with(&|b| b[lo + 4..lo + 6].copy_from_slice(b"??")),
            false,
        ),
        (
            "QX with a 2-byte length",
            with(&|b| b[lo + 4..lo + 6].copy_from_slice(b"QX")),
            true,
        ),
        (
            "implicit VR inside explicit",
            with(&|b| b[lo + 4..lo + 8].copy_from_slice(&8u32.to_le_bytes())),
            true,
        ),
    ];
    // A VR the dictionary does not know, with a 4-byte length (written as UN, renamed).
    edit(&files[0], |o| {
        set(o, study, VR::UN, PrimitiveValue::U8(b"HEAD CT "[..].into()));
    });
    let mut b = std::fs::read(&files[0]).unwrap();
    let un = find(&b, &[0x08, 0x00, 0x30, 0x10, b'U', b'N', 0, 0, 8, 0, 0, 0]);
    b[un + 4..un + 6].copy_from_slice(b"ZZ");
    cases.push(("ZZ with a 4-byte length", b, false));
    for (what, b, pydicom_reads_it) in cases {
        let path = dir.path().join("odd-vr.dcm");
        std::fs::write(&path, &b).unwrap();
        let back = read_volume(&path, None).unwrap_or_else(|e| panic!("{what}: {e}"));
        assert_same(&back, &v, what);
        assert_eq!(back.channel(0), v.channel(0), "{what}");
        if pydicom_reads_it {
            check_against_pydicom(std::slice::from_ref(&path), &back, 0.0, what);
        }
    }

    // Needed attributes are refused, naming them: Pixel Spacing with the VR bytes 10 00
    // (also in the hostile-lengths test), Rows as ?? with its 2-byte length.
    for (pat, what) in [
        (
            &[0x28, 0x00, 0x30, 0x00, b'D', b'S'][..],
            "(0028,0030) Pixel Spacing",
        ),
        (
            &[0x28, 0x00, 0x10, 0x00, b'U', b'S'][..],
            "(0028,0010) Rows",
        ),
    ] {
        let mut b = bytes.clone();
        let at = find(&b, pat);
        b[at + 4..at + 6].copy_from_slice(if what.contains("Rows") {
            b"??"
        } else {
            &[0x10, 0]
        });
        let path = dir.path().join("needed.dcm");
        std::fs::write(&path, &b).unwrap();
        let e = read_volume(&path, None).unwrap_err();
        let msg = e.to_string();
        assert!(matches!(e, ReadError::Dicom { .. }), "{msg}");
        assert!(
            msg.contains(what) && msg.contains("unknown value representation"),
            "{what}: {msg}"
        );
    }
}

/// Writes the 4D series of `volumes` (one per time point) into `dir/4d`: each time point's
/// slices with `attr` = `value(t)` and UIDs of their own; returns the directory.
fn write_4d(
    dir: &Path,
    volumes: &[Volume],
    attr: (Tag, VR),
    value: &dyn Fn(usize) -> String,
) -> PathBuf {
    let o = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    let series = dir.join("4d");
    std::fs::create_dir_all(&series).unwrap();
    for (t, v) in volumes.iter().enumerate() {
        let files = write_dicom_series(&dir.join(format!("t{t}")), v, &o);
        for (i, f) in files.iter().enumerate() {
            let mut obj = open_file(f).unwrap();
            set(&mut obj, attr.0, attr.1, PrimitiveValue::from(value(t)));
            set(
                &mut obj,
                tags::SOP_INSTANCE_UID,
                VR::UI,
                PrimitiveValue::from(format!("1.2.826.0.1.3680043.9.7433.5.{t}.{i}")),
            );
            obj.write_to_file(series.join(format!("img-{t}-{i}.dcm")))
                .unwrap();
        }
    }
    series
}

/// A 4D series read as a time series: each time point (grouped by Trigger Time, in the order
/// of its value, not of the text) decodes as that volume, with its time in seconds; by
/// Temporal Position Identifier, without times; by Acquisition Time only where slices repeat
/// positions (a volume whose slices each have their own is one volume). One volume's reader
/// still refuses it.
#[test]
fn a_4d_series_reads_as_time_points_in_time_order() {
    let vols: Vec<Volume> = (0..3)
        .map(|t| {
            let v = volume([6, 5, 3], [1.0, 1.0, 2.0], Layout::U16, 1.0, 0.0);
            let d = v
                .channel(0)
                .iter()
                .map(|x| (x + 1000.0 * t as f32).min(65535.0))
                .collect();
            Volume::new(v.dims(), v.spacing(), vec![d])
                .unwrap()
                .with_placement(oblique())
                .unwrap()
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    // Trigger times 0, 45.5 and 100 ms: "100" sorts before "45.5" as text.
    let ms = ["0", "45.5", "100"];
    let series = write_4d(dir.path(), &vols, (tags::TRIGGER_TIME, VR::DS), &|t| {
        ms[t].into()
    });
    let (back, times) = read_time_series(&series).unwrap().expect("a time series");
    assert_eq!(back.len(), 3);
    for (t, v) in back.iter().enumerate() {
        assert_same(v, &vols[t], &format!("time point {t}"));
    }
    assert_eq!(times, Some(vec![0.0, 0.0455, 0.1]));
    assert!(read_volume(&series, None)
        .unwrap_err()
        .to_string()
        .contains("time series"));

    let dir = tempfile::tempdir().unwrap();
    let series = write_4d(
        dir.path(),
        &vols,
        (tags::TEMPORAL_POSITION_IDENTIFIER, VR::IS),
        &|t| (t + 1).to_string(),
    );
    let (back, times) = read_time_series(&series).unwrap().unwrap();
    assert_eq!(times, None);
    assert_same(&back[2], &vols[2], "time point 2");
    // One volume is no time series.
    let one = tempfile::tempdir().unwrap();
    let o = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    write_dicom_series(one.path(), &vols[0], &o);
    assert!(read_time_series(one.path()).unwrap().is_none());

    // By Acquisition Time (TM), when slices repeat positions: times from the first.
    let dir = tempfile::tempdir().unwrap();
    let at = ["235958", "235958.5", "23:59:59.75"];
    let series = write_4d(dir.path(), &vols, (tags::ACQUISITION_TIME, VR::TM), &|t| {
        at[t].into()
    });
    let (back, times) = read_time_series(&series).unwrap().expect("a time series");
    assert_eq!(times, Some(vec![0.0, 0.5, 1.75]));
    assert_same(&back[1], &vols[1], "time point 1 by Acquisition Time");
    // A volume whose slices each say their own Acquisition Time (a helical CT) is one volume.
    for (z, f) in write_dicom_series(one.path(), &vols[0], &o)
        .iter()
        .enumerate()
    {
        let mut obj = open_file(f).unwrap();
        obj.put(DataElement::new(
            tags::ACQUISITION_TIME,
            VR::TM,
            PrimitiveValue::from(format!("1015{:02}.25", 10 + z)),
        ));
        obj.write_to_file(f).unwrap();
    }
    assert!(read_time_series(one.path()).unwrap().is_none());
    assert_same(
        &read_volume(one.path(), None).unwrap(),
        &vols[0],
        "a volume with per-slice times",
    );
}

/// A 4D series with a time point missing a slice, an image without its time or a time that is
/// not a number is refused, naming the time point or the file.
#[test]
fn broken_4d_series_are_refused_naming_the_problem() {
    let vols: Vec<Volume> = (0..2)
        .map(|_| volume([6, 5, 4], [1.0, 1.0, 2.0], Layout::U16, 1.0, 0.0))
        .collect();
    let attr = (tags::TRIGGER_TIME, VR::DS);
    let dir = tempfile::tempdir().unwrap();
    let series = write_4d(dir.path(), &vols, attr, &|t| (40 * t).to_string());
    std::fs::remove_file(series.join("img-1-1.dcm")).unwrap();
    let e = read_time_series(&series).unwrap_err().to_string();
    assert!(
        e.contains("time point 1 (Trigger Time (0018,1060) 40)") && e.contains("slice spacing"),
        "{e}"
    );

    let dir = tempfile::tempdir().unwrap();
    let series = write_4d(dir.path(), &vols, attr, &|t| (40 * t).to_string());
    let f = series.join("img-0-2.dcm");
    let mut obj = open_file(&f).unwrap();
    obj.remove_element(tags::TRIGGER_TIME);
    obj.write_to_file(&f).unwrap();
    let e = read_time_series(&series).unwrap_err().to_string();
    assert!(e.contains("img-0-2.dcm says no time"), "{e}");

    let dir = tempfile::tempdir().unwrap();
    let series = write_4d(dir.path(), &vols, attr, &|t| {
        if t == 0 {
            "0".into()
        } else {
            "late".into()
        }
    });
    let e = read_time_series(&series).unwrap_err().to_string();
    assert!(e.contains("not a number"), "{e}");
}
