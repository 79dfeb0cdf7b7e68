//! Time series read from files the tests write: a 4D NIfTI (plain and gzip), a 4D NRRD (a time
//! or Slicer `list` axis), a 4D MetaImage, a 4D raw file and a directory of one volume per time
//! step. Each time point reads back exactly as written, a
//! series read from a file compresses to the same bytes as the same time points held in
//! memory, and bad series (a header lying about its size, missing, repeated or mismatched
//! steps) are clear errors naming the problem.

use std::path::Path;

use wavesplat_codec::volume::Volume;
use wavesplat_compressor::encode::{CompressOptions, Target};
use wavesplat_compressor::phantom::beating;
use wavesplat_compressor::reader::region::RegionReader;
use wavesplat_compressor::reader::steps::StepSeries;
use wavesplat_compressor::reader::{RawDtype, RawSpec, ReadError};
use wavesplat_compressor::series::{compress_series, SeriesSource, VolumeSeries};
use wavesplat_fixtures::{write_nifti, write_nifti_series};

const DIMS: [usize; 3] = [14, 12, 7];

fn points(n: usize) -> Vec<Volume> {
    (0..n).map(|t| beating(DIMS, t, n).unwrap()).collect()
}

fn opts() -> CompressOptions {
    CompressOptions {
        target: Target::Fraction(0.1),
        ..CompressOptions::default()
    }
}

/// Every time point of `s` reads back as `want` (exactly), and `s` compresses to the bytes the
/// same time points held in memory compress to.
fn reads_as(s: &dyn SeriesSource, want: &[Volume], times: Option<Vec<f64>>) {
    assert_eq!(s.time_points(), want.len());
    assert_eq!(s.dims(), DIMS.map(|d| d as u64));
    for (t, v) in want.iter().enumerate() {
        let got = s.read_at(t, [0; 3], DIMS).unwrap();
        assert_eq!(got.channel(0), v.channel(0), "time point {t}");
    }
    let mem = VolumeSeries::new(want.to_vec(), times).unwrap();
    let a = compress_series(s, &opts(), 4, 256, &|_| {}).unwrap();
    let b = compress_series(&mem, &opts(), 4, 256, &|_| {}).unwrap();
    assert_eq!(a.bytes, b.bytes);
}

#[test]
fn a_4d_nifti_is_read_time_point_by_time_point_plain_and_gzip() {
    let dir = tempfile::tempdir().unwrap();
    let vols = points(6);
    let samples: Vec<Vec<f32>> = vols.iter().map(|v| v.channel(0).to_vec()).collect();
    for gz in [false, true] {
        let path = dir.path().join(if gz { "cine.nii.gz" } else { "cine.nii" });
        write_nifti_series(&path, DIMS, &samples, Some(40.0), gz);
        // One volume's readers refuse it by name.
        let e = RegionReader::open(&path, None).unwrap_err();
        assert!(matches!(e, ReadError::TimeSeries { points: 6, .. }), "{e}");
        let e = wavesplat_compressor::reader::read_volume(&path, None).unwrap_err();
        assert!(e.to_string().contains("6 time points"), "{e}");
        let r = RegionReader::open_series(&path, None).unwrap();
        assert_eq!(r.time_step(), Some(0.04));
        let times: Vec<f64> = (0..6).map(|t| t as f64 * 0.04).collect();
        assert_eq!(r.times(), Some(times.clone()));
        reads_as(&r, &vols, Some(times));
        // One time point taken out reads as that volume.
        let one = r.select_time_point(4).unwrap();
        assert_eq!(
            one.read_region([0; 3], DIMS).unwrap().channel(0),
            vols[4].channel(0)
        );
        let e = RegionReader::open_series(&path, None)
            .unwrap()
            .select_time_point(6)
            .unwrap_err();
        assert!(e.to_string().contains("time point 6"), "{e}");
    }
}

#[test]
fn a_4d_nifti_whose_header_lies_about_its_size_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("short.nii");
    let samples: Vec<Vec<f32>> = points(4).iter().map(|v| v.channel(0).to_vec()).collect();
    write_nifti_series(&path, DIMS, &samples, None, false);
    // Say 9 time points where 4 are stored.
    let mut b = std::fs::read(&path).unwrap();
    b[48..50].copy_from_slice(&9i16.to_le_bytes());
    std::fs::write(&path, &b).unwrap();
    let e = RegionReader::open_series(&path, None).unwrap_err();
    assert!(matches!(e, ReadError::Truncated { .. }), "{e}");
}

#[test]
fn a_4d_raw_file_is_read_with_its_time_points() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cine.raw");
    let vols = points(4);
    let bytes: Vec<u8> = vols
        .iter()
        .flat_map(|v| {
            v.channel(0)
                .iter()
                .flat_map(|x| (x.max(0.0) as u16).to_le_bytes())
        })
        .collect();
    std::fs::write(&path, &bytes).unwrap();
    let mut spec = RawSpec::new(DIMS, RawDtype::U16);
    spec.time_points = 4;
    let e = RegionReader::open(&path, Some(&spec)).unwrap_err();
    assert!(matches!(e, ReadError::TimeSeries { points: 4, .. }), "{e}");
    let e = wavesplat_compressor::reader::read_volume(&path, Some(&spec)).unwrap_err();
    assert!(matches!(e, ReadError::TimeSeries { .. }), "{e}");
    let r = RegionReader::open_series(&path, Some(&spec)).unwrap();
    assert_eq!(r.times(), None);
    let want: Vec<Volume> = vols
        .iter()
        .map(|v| {
            let d = v
                .channel(0)
                .iter()
                .map(|x| x.max(0.0) as u16 as f32)
                .collect();
            Volume::new(DIMS, [1.0; 3], vec![d]).unwrap()
        })
        .collect();
    reads_as(&r, &want, None);
    // One time point too few in the file.
    spec.time_points = 5;
    let e = RegionReader::open_series(&path, Some(&spec)).unwrap_err();
    assert!(matches!(e, ReadError::SizeMismatch { .. }), "{e}");
}

fn write_steps(dir: &Path, names: &[&str], vols: &[Volume]) {
    for (n, v) in names.iter().zip(vols) {
        write_nifti(&dir.join(n), v.dims(), v.channel(0));
    }
}

#[test]
fn a_directory_of_time_steps_is_one_series_in_step_order() {
    let dir = tempfile::tempdir().unwrap();
    let vols = points(5);
    // Written out of order, numbered by tens, with a data file and a hidden one beside them.
    let names = [
        "sim_t0040.nii",
        "sim_t0000.nii",
        "sim_t0020.nii",
        "sim_t0010.nii",
        "sim_t0030.nii",
    ];
    let order = [4, 0, 2, 1, 3];
    let shuffled: Vec<Volume> = order.iter().map(|&t| vols[t].clone()).collect();
    write_steps(dir.path(), &names, &shuffled);
    std::fs::write(dir.path().join(".notes.nii"), b"x").unwrap();
    std::fs::write(dir.path().join("README.txt"), b"steps").unwrap();
    let s = StepSeries::open(dir.path(), None).unwrap();
    assert_eq!(s.numbers(), &[0, 10, 20, 30, 40]);
    reads_as(&s, &vols, None);
}

#[test]
fn missing_repeated_unnumbered_or_mismatched_steps_are_named() {
    let vols = points(4);
    let open = |names: &[&str], vols: &[Volume]| {
        let dir = tempfile::tempdir().unwrap();
        write_steps(dir.path(), names, vols);
        StepSeries::open(dir.path(), None).unwrap_err().to_string()
    };
    let e = open(&["s0.nii", "s1.nii", "s3.nii"], &vols);
    assert!(e.contains("step 2 is missing"), "{e}");
    let e = open(&["s0.nii", "s1.nii", "s01.nii"], &vols);
    assert!(e.contains("step 1 is repeated"), "{e}");
    let e = open(&["s0.nii", "final.nii"], &vols);
    assert!(e.contains("final.nii has no step number"), "{e}");
    let e = open(&["s0.nii"], &vols);
    assert!(e.contains("at least two"), "{e}");
    let other = beating([14, 12, 8], 1, 4).unwrap();
    let e = open(&["s0.nii", "s1.nii"], &[vols[0].clone(), other]);
    assert!(
        e.contains("s1.nii does not match s0.nii") && e.contains("dimensions"),
        "{e}"
    );
}

/// A 4D NRRD whose last axis is time (`kinds: domain domain domain time`, as Slicer writes a
/// sequence), raw and gzip, attached and detached: every time point reads back exactly, the
/// time step comes from the axis' spacing and unit, one volume's readers refuse it by name,
/// and a file shorter than its time points is refused at open.
#[test]
fn a_4d_nrrd_with_a_time_axis_is_read_time_point_by_time_point() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let vols = points(5);
    let data: Vec<u8> = vols
        .iter()
        .flat_map(|v| v.channel(0).iter().flat_map(|x| x.to_le_bytes()))
        .collect();
    let header = |encoding: &str, data_file: Option<&str>| {
        let mut h = format!(
            "NRRD0004\ntype: float\ndimension: 4\nsizes: {} {} {} 5\nendian: little\n\
             encoding: {encoding}\nkinds: domain domain domain time\nspacings: 1 1 1 40\n\
             units: mm mm mm ms\n",
            DIMS[0], DIMS[1], DIMS[2]
        );
        if let Some(f) = data_file {
            h += &format!("data file: {f}\n");
        }
        h + "\n"
    };
    let gz = {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        e.write_all(&data).unwrap();
        e.finish().unwrap()
    };
    let raw_path = dir.path().join("cine.nrrd");
    std::fs::write(
        &raw_path,
        [header("raw", None).into_bytes(), data.clone()].concat(),
    )
    .unwrap();
    let gz_path = dir.path().join("cine_gz.nrrd");
    std::fs::write(&gz_path, [header("gzip", None).into_bytes(), gz].concat()).unwrap();
    let nhdr = dir.path().join("detached.nhdr");
    std::fs::write(&nhdr, header("raw", Some("detached.data"))).unwrap();
    std::fs::write(dir.path().join("detached.data"), &data).unwrap();
    for path in [&raw_path, &gz_path, &nhdr] {
        assert_eq!(
            wavesplat_compressor::reader::time_points(path, None).unwrap(),
            5,
            "{path:?}"
        );
        let e = RegionReader::open(path, None).unwrap_err();
        assert!(matches!(e, ReadError::TimeSeries { points: 5, .. }), "{e}");
        let e = wavesplat_compressor::reader::read_volume(path, None).unwrap_err();
        assert!(e.to_string().contains("5 time points"), "{e}");
        let r = RegionReader::open_series(path, None).unwrap();
        assert_eq!(r.time_points(), 5);
        assert_eq!(r.time_step(), Some(0.04));
        assert_eq!(r.dims(), DIMS);
        reads_as(&r, &vols, Some((0..5).map(|t| t as f64 * 0.04).collect()));
    }
    // Without units the times are unknown; a file one time point short is refused.
    let no_units = header("raw", None).replace("units: mm mm mm ms\n", "");
    let p = dir.path().join("no_units.nrrd");
    std::fs::write(&p, [no_units.into_bytes(), data.clone()].concat()).unwrap();
    assert_eq!(
        RegionReader::open_series(&p, None).unwrap().time_step(),
        None
    );
    let frame = data.len() / 5;
    let p = dir.path().join("short.nrrd");
    std::fs::write(
        &p,
        [header("raw", None).into_bytes(), data[..4 * frame].to_vec()].concat(),
    )
    .unwrap();
    let e = RegionReader::open_series(&p, None).unwrap_err();
    assert!(e.to_string().contains("short.nrrd"), "{e}");
}

/// `vols` placed at the origin along the LPS axes (as the headers below place them).
fn placed(vols: &[Volume]) -> Vec<Volume> {
    let p = wavesplat_codec::volume::Placement {
        origin: [0.0; 3],
        directions: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    vols.iter()
        .map(|v| v.clone().with_placement(p).unwrap())
        .collect()
}

/// A 3D Slicer sequence NRRD: `kinds: domain domain domain list` (each time point's volume
/// after the previous one) or, as older Slicer writes it, `list domain domain domain` (a
/// voxel's time points after each other; raw and gzip), with `none` for the list axis' space
/// direction: the list axis is time, every time point reads back exactly and compresses as the
/// same time points held in memory do.
#[test]
fn a_slicer_sequence_nrrd_is_read_time_point_by_time_point() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let vols = points(4);
    let [x, y, z] = DIMS;
    let trailing: Vec<u8> = vols
        .iter()
        .flat_map(|v| v.channel(0).iter().flat_map(|s| s.to_le_bytes()))
        .collect();
    let n = DIMS.iter().product::<usize>();
    let leading: Vec<u8> = (0..n)
        .flat_map(|i| vols.iter().flat_map(move |v| v.channel(0)[i].to_le_bytes()))
        .collect();
    let header = |encoding: &str, sizes: &str, kinds: &str, dirs: &str| {
        format!(
            "NRRD0004\ntype: float\ndimension: 4\nspace: left-posterior-superior\n\
             sizes: {sizes}\nspace directions: {dirs}\nkinds: {kinds}\nendian: little\n\
             encoding: {encoding}\nspace origin: (0,0,0)\n\n"
        )
    };
    let gzip = |data: &[u8]| {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        e.write_all(data).unwrap();
        e.finish().unwrap()
    };
    let spatial = "(1,0,0) (0,1,0) (0,0,1)";
    let last = (
        format!("{x} {y} {z} 4"),
        "domain domain domain list",
        format!("{spatial} none"),
    );
    let first = (
        format!("4 {x} {y} {z}"),
        "list domain domain domain",
        format!("none {spatial}"),
    );
    let files = [
        ("last.seq.nrrd", "raw", &last, trailing.clone()),
        ("first.seq.nrrd", "raw", &first, leading.clone()),
        ("first_gz.seq.nrrd", "gzip", &first, gzip(&leading)),
    ];
    for (name, encoding, (sizes, kinds, dirs), data) in files {
        let path = dir.path().join(name);
        let h = header(encoding, sizes, kinds, dirs);
        std::fs::write(&path, [h.into_bytes(), data].concat()).unwrap();
        assert_eq!(
            wavesplat_compressor::reader::time_points(&path, None).unwrap(),
            4,
            "{name}"
        );
        let e = wavesplat_compressor::reader::read_volume(&path, None).unwrap_err();
        assert!(
            matches!(e, ReadError::TimeSeries { points: 4, .. }),
            "{name}: {e}"
        );
        let r = RegionReader::open_series(&path, None).unwrap();
        assert_eq!((r.dims(), r.channels(), r.time_step()), (DIMS, 1, None));
        assert!(r.placement().is_some(), "{name}");
        reads_as(&r, &placed(&vols), None);
        // A box of one time point, away from the origin.
        let b = r.read_region_at(2, [1, 2, 3], [4, 3, 2]).unwrap();
        for (i, s) in b.channel(0).iter().enumerate() {
            let (bx, by, bz) = (i % 4 + 1, i / 4 % 3 + 2, i / 12 + 3);
            assert_eq!(*s, vols[2].channel(0)[vols[2].index(bx, by, bz)], "{name}");
        }
    }
}

/// A 4D MetaImage (`NDims = 4`, the last size the time points, each volume after the previous
/// one, as ITK writes a series): attached raw, zlib-compressed and detached (a data file whose
/// name holds a space) read time point by time point; one volume's readers name it a series.
#[test]
fn a_4d_metaimage_is_read_time_point_by_time_point() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let vols = points(3);
    let data: Vec<u8> = vols
        .iter()
        .flat_map(|v| v.channel(0).iter().flat_map(|s| s.to_le_bytes()))
        .collect();
    let zlib = {
        let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        e.write_all(&data).unwrap();
        e.finish().unwrap()
    };
    let header = |extra: &str, file: &str| {
        format!(
            "ObjectType = Image\nNDims = 4\nDimSize = {} {} {} 3\nElementType = MET_FLOAT\n\
             ElementSpacing = 1 1 1 1\nOffset = 0 0 0 0\n\
             TransformMatrix = 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n{extra}ElementDataFile = {file}\n",
            DIMS[0], DIMS[1], DIMS[2]
        )
    };
    let attached = dir.path().join("cine.mha");
    std::fs::write(
        &attached,
        [header("", "LOCAL").into_bytes(), data.clone()].concat(),
    )
    .unwrap();
    let compressed = dir.path().join("cine_z.mha");
    std::fs::write(
        &compressed,
        [
            header("CompressedData = True\n", "LOCAL").into_bytes(),
            zlib,
        ]
        .concat(),
    )
    .unwrap();
    let detached = dir.path().join("cine.mhd");
    std::fs::write(&detached, header("", "cine series.raw")).unwrap();
    std::fs::write(dir.path().join("cine series.raw"), &data).unwrap();
    for path in [&attached, &compressed, &detached] {
        assert_eq!(
            wavesplat_compressor::reader::time_points(path, None).unwrap(),
            3,
            "{path:?}"
        );
        let e = RegionReader::open(path, None).unwrap_err();
        assert!(matches!(e, ReadError::TimeSeries { points: 3, .. }), "{e}");
        let e = wavesplat_compressor::reader::read_volume(path, None).unwrap_err();
        assert!(e.to_string().contains("3 time points"), "{e}");
        let r = RegionReader::open_series(path, None).unwrap();
        assert_eq!((r.dims(), r.time_step()), (DIMS, None));
        assert!(r.placement().is_some());
        reads_as(&r, &placed(&vols), None);
    }
    // One time point short of its header.
    let short = dir.path().join("short.mha");
    std::fs::write(
        &short,
        [
            header("", "LOCAL").into_bytes(),
            data[..data.len() * 2 / 3].to_vec(),
        ]
        .concat(),
    )
    .unwrap();
    let e = RegionReader::open_series(&short, None).unwrap_err();
    assert!(matches!(e, ReadError::Truncated { .. }), "{e}");
}

/// An enhanced multi-frame DICOM whose frames carry a temporal dimension (each frame's Frame
/// Content gives its Temporal Position Index; frames stored slice-major, as an enhanced MR
/// cine stack is) reads as a series: each index's frames one volume, exactly as written, its
/// time from the frames' Nominal Cardiac Trigger Delay Time. One volume's reader refuses it,
/// naming the series; a frame moved to another time point is an error naming the time point.
#[test]
fn an_enhanced_multiframe_dicom_with_a_temporal_dimension_is_a_series() {
    use dicom_core::value::DataSetSequence;
    use dicom_core::{DataElement, Length, PrimitiveValue, VR};
    use dicom_dictionary_std::tags;
    use dicom_object::InMemDicomObject;
    use wavesplat_compressor::series::open_series_path;
    use wavesplat_fixtures::{write_dicom_enhanced_series, DicomOptions, Layout};
    let dir = tempfile::tempdir().unwrap();
    // Integer samples: the file stores 16-bit values.
    let vols: Vec<Volume> = points(5)
        .iter()
        .map(|v| {
            let data = v.channel(0).iter().map(|x| x.max(0.0).round()).collect();
            Volume::new(DIMS, [1.0, 1.0, 1.0], vec![data]).unwrap()
        })
        .collect();
    let ms = [0.0, 45.0, 90.0, 135.0, 180.0];
    let path = dir.path().join("enhanced.dcm");
    let o = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    write_dicom_enhanced_series(&path, &vols, &ms, &o);
    let e = wavesplat_compressor::reader::read_volume(&path, None).unwrap_err();
    let said = e.to_string();
    assert!(
        said.contains("5 time points") && said.contains("Temporal Position Index"),
        "{said}"
    );
    let input = open_series_path(&path, None).unwrap().expect("a series");
    let times: Vec<f64> = ms.iter().map(|m| m / 1000.0).collect();
    assert_eq!(input.source().times(), Some(times.clone()));
    // Placed as the file says (the fixture's identity orientation, slice 0 at the origin).
    let placement = input.source().placement().expect("placed");
    assert_eq!(placement.origin, [0.0; 3]);
    let placed: Vec<Volume> = vols
        .iter()
        .map(|v| v.clone().with_placement(placement).unwrap())
        .collect();
    reads_as(input.source(), &placed, Some(times));

    // Frame 1 (slice 0 of time point 1) says it belongs to time point 3.
    let mut obj = dicom_object::open_file(&path).unwrap();
    let mut items: Vec<InMemDicomObject> = obj
        .element(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE)
        .unwrap()
        .items()
        .unwrap()
        .to_vec();
    let content = InMemDicomObject::from_element_iter([DataElement::new(
        tags::TEMPORAL_POSITION_INDEX,
        VR::UL,
        PrimitiveValue::from(4u32),
    )]);
    let sq = |tag, items: Vec<InMemDicomObject>| {
        DataElement::new(tag, VR::SQ, DataSetSequence::new(items, Length::UNDEFINED))
    };
    items[1].put(sq(tags::FRAME_CONTENT_SEQUENCE, vec![content]));
    obj.put(sq(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE, items));
    obj.write_to_file(&path).unwrap();
    let e = open_series_path(&path, None).unwrap_err().to_string();
    assert!(e.contains("Temporal Position Index 2"), "{e}");
}

/// A channel chosen of a series read with all its channels: of grey time steps only channel
/// 0 is there (1 is refused, saying so); of a DICOM series read whole, each time point keeps
/// the channel chosen (0 of grey frames: the same series), and one it lacks is refused.
#[test]
fn a_channel_chosen_of_steps_and_of_a_dicom_cine_is_taken_or_refused() {
    use wavesplat_compressor::series::{open_series_path, open_series_path_channel, SeriesError};
    use wavesplat_fixtures::{write_dicom_enhanced_series, DicomOptions, Layout};
    let dir = tempfile::tempdir().unwrap();
    let vols = points(3);
    write_steps(dir.path(), &["s_0.nii", "s_1.nii", "s_2.nii"], &vols);
    let taken = open_series_path_channel(dir.path(), None, Some(0))
        .unwrap()
        .expect("a series");
    reads_as(taken.source(), &vols, None);
    match open_series_path_channel(dir.path(), None, Some(1)) {
        Err(SeriesError::InvalidOption(why)) => {
            assert!(
                why.contains("channel 1") && why.contains("1 channel(s)"),
                "{why}"
            )
        }
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("channel 1 of grey steps taken"),
    }
    let cine_dir = tempfile::tempdir().unwrap();
    let grey: Vec<Volume> = vols
        .iter()
        .map(|v| {
            let data = v.channel(0).iter().map(|x| x.max(0.0).round()).collect();
            Volume::new(DIMS, [1.0, 1.0, 1.0], vec![data]).unwrap()
        })
        .collect();
    let path = cine_dir.path().join("cine.dcm");
    let o = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    write_dicom_enhanced_series(&path, &grey, &[0.0, 40.0, 80.0], &o);
    let all = open_series_path(&path, None).unwrap().expect("a series");
    let zero = open_series_path_channel(&path, None, Some(0))
        .unwrap()
        .expect("a series");
    for t in 0..3 {
        let whole = |s: &wavesplat_compressor::series::SeriesInput| {
            s.source().read_at(t, [0; 3], DIMS).unwrap()
        };
        assert_eq!(whole(&zero), whole(&all), "time point {t}");
    }
    match open_series_path_channel(&path, None, Some(2)) {
        Err(SeriesError::Read(e)) => {
            assert!(matches!(*e, ReadError::Channels { channels: 1, .. }), "{e}")
        }
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("channel 2 of grey frames taken"),
    }
}
