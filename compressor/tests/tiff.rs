//! TIFF stacks: a multi-page file and a directory of single-page files (natural name order)
//! read as the volume written, for every sample type and compression the writer here makes,
//! whole and region by region (chunk by chunk, regions that cut strips); the spacing an ImageJ
//! or OME description gives; one channel of a hyperstack as chosen (files written here and by
//! tifffile); and the refusals (pages that disagree, hyperstacks, alpha, an ImageJ stack whose
//! images outnumber its pages), each naming the file.

use std::io::{Seek, Write};
use std::path::Path;
use tiff::encoder::colortype::{self, ColorType};
use tiff::encoder::{Compression, DeflateLevel, Rational, TiffEncoder, TiffValue};
use tiff::tags::Tag;
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_compressor::reader::region::RegionReader;
use wavesplat_compressor::reader::{read_volume, Format, ReadError, SourceListing};

const DIMS: [usize; 3] = [37, 29, 11];

/// Values of a phantom as samples of `T` (scaled to `scale`).
fn samples<T>(dims: [usize; 3], scale: f32, to: impl Fn(f32) -> T) -> Vec<T> {
    Phantom::SheppLogan
        .generate(dims)
        .to_interleaved()
        .iter()
        .map(|v| to(v * scale))
        .collect()
}

/// Writes `slices` (each `w·h` samples, channels interleaved) as pages of one TIFF, strips of
/// `rows` rows, with `description` on the first page.
fn write_pages<C: ColorType, W: Write + Seek>(
    out: W,
    compression: Compression,
    (w, h): (usize, usize),
    slices: &[&[C::Inner]],
    rows: u32,
    description: Option<&str>,
) where
    [C::Inner]: TiffValue,
{
    let mut enc = TiffEncoder::new(out).unwrap().with_compression(compression);
    for (i, s) in slices.iter().enumerate() {
        let mut image = enc.new_image::<C>(w as u32, h as u32).unwrap();
        image.rows_per_strip(rows).unwrap();
        if let (0, Some(d)) = (i, description) {
            image.encoder().write_tag(Tag::ImageDescription, d).unwrap();
        }
        image.write_data(s).unwrap();
    }
}

fn multipage<C: ColorType>(
    path: &Path,
    compression: Compression,
    data: &[C::Inner],
    channels: usize,
    description: Option<&str>,
) where
    [C::Inner]: TiffValue,
{
    let slice = DIMS[0] * DIMS[1] * channels;
    let slices: Vec<&[C::Inner]> = data.chunks(slice).collect();
    let f = std::fs::File::create(path).unwrap();
    write_pages::<C, _>(f, compression, (DIMS[0], DIMS[1]), &slices, 4, description);
}

/// The phantom as the reader should give it from samples `data`.
fn expected(data: &[f32], channels: usize, spacing: [f32; 3]) -> Volume {
    let n = DIMS[0] * DIMS[1] * DIMS[2];
    let planar = (0..channels)
        .map(|c| (0..n).map(|i| data[i * channels + c]).collect())
        .collect();
    Volume::new(DIMS, spacing, planar).unwrap()
}

fn same(got: &Volume, want: &Volume, what: &str) {
    assert_eq!(got.dims(), want.dims(), "{what}");
    assert_eq!(got.spacing(), want.spacing(), "{what}");
    assert_eq!(got.channel_count(), want.channel_count(), "{what}");
    for (a, b) in got.channels().iter().zip(want.channels()) {
        assert!(a == b, "{what}: samples differ");
    }
}

/// Regions that cut strips, rows and slices, read from `path` against the whole.
fn regions_match(path: &Path, whole: &Volume) {
    let r = RegionReader::open(path, None).unwrap();
    assert_eq!(r.dims(), DIMS);
    assert_eq!(r.channels(), whole.channel_count());
    for (origin, size) in [
        ([0, 0, 0], DIMS),
        ([3, 5, 2], [10, 7, 4]),
        ([36, 28, 10], [1, 1, 1]),
        ([0, 3, 0], [37, 1, 11]),
        ([11, 0, 5], [26, 29, 6]),
    ] {
        let got = r.read_region(origin, size).unwrap();
        for c in 0..whole.channel_count() {
            for z in 0..size[2] {
                for y in 0..size[1] {
                    for x in 0..size[0] {
                        let g = got.channels()[c][got.index(x, y, z)];
                        let w = whole.channels()[c]
                            [whole.index(x + origin[0], y + origin[1], z + origin[2])];
                        assert_eq!(g, w, "{} at {origin:?}+{:?}", path.display(), [x, y, z]);
                    }
                }
            }
        }
    }
}

#[test]
fn a_multipage_tiff_reads_as_the_volume_written_for_every_sample_type_and_compression() {
    let dir = tempfile::tempdir().unwrap();
    let compressions = [
        ("none", Compression::Uncompressed),
        ("lzw", Compression::Lzw),
        ("deflate", Compression::Deflate(DeflateLevel::Fast)),
        ("packbits", Compression::Packbits),
    ];
    for (name, compression) in compressions {
        let path = dir.path().join(format!("u16_{name}.tif"));
        let data = samples(DIMS, 4000.0, |v| v.round() as u16);
        multipage::<colortype::Gray16>(&path, compression, &data, 1, None);
        let f: Vec<f32> = data.iter().map(|v| *v as f32).collect();
        let want = expected(&f, 1, [1.0; 3]);
        same(&read_volume(&path, None).unwrap(), &want, name);
        regions_match(&path, &want);
    }
    let path = dir.path().join("u8.tiff");
    let data = samples(DIMS, 250.0, |v| v.round() as u8);
    multipage::<colortype::Gray8>(&path, Compression::Lzw, &data, 1, None);
    let f: Vec<f32> = data.iter().map(|v| *v as f32).collect();
    same(
        &read_volume(&path, None).unwrap(),
        &expected(&f, 1, [1.0; 3]),
        "u8",
    );

    let path = dir.path().join("i16.tif");
    let data = samples(DIMS, 3000.0, |v| (v * 2.0 - 1000.0).round() as i16);
    multipage::<colortype::GrayI16>(&path, Compression::Uncompressed, &data, 1, None);
    let f: Vec<f32> = data.iter().map(|v| *v as f32).collect();
    same(
        &read_volume(&path, None).unwrap(),
        &expected(&f, 1, [1.0; 3]),
        "i16",
    );

    let path = dir.path().join("f32.tif");
    let data = samples(DIMS, 1.0, |v| v * 1e-3 - 7.5);
    multipage::<colortype::Gray32Float>(
        &path,
        Compression::Deflate(DeflateLevel::Fast),
        &data,
        1,
        None,
    );
    let want = expected(&data, 1, [1.0; 3]);
    same(&read_volume(&path, None).unwrap(), &want, "f32");
    regions_match(&path, &want);

    // RGB, 8 bits a channel.
    let rgb: Vec<u8> = Phantom::RgbHead
        .generate(DIMS)
        .to_interleaved()
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let path = dir.path().join("rgb.tif");
    multipage::<colortype::RGB8>(&path, Compression::Lzw, &rgb, 3, None);
    let f: Vec<f32> = rgb.iter().map(|v| *v as f32).collect();
    let want = expected(&f, 3, [1.0; 3]);
    same(&read_volume(&path, None).unwrap(), &want, "rgb");
    regions_match(&path, &want);
}

#[test]
fn a_directory_of_tiffs_is_one_stack_in_natural_name_order() {
    let dir = tempfile::tempdir().unwrap();
    let stack = dir.path().join("stack");
    std::fs::create_dir(&stack).unwrap();
    let data = samples(DIMS, 4000.0, |v| v.round() as u16);
    let slice = DIMS[0] * DIMS[1];
    // slice1.tif … slice11.tif: in byte order slice10 and slice11 would come before slice2.
    for (z, s) in data.chunks(slice).enumerate() {
        let f = std::fs::File::create(stack.join(format!("slice{}.tif", z + 1))).unwrap();
        write_pages::<colortype::Gray16, _>(f, Compression::Lzw, (DIMS[0], DIMS[1]), &[s], 7, None);
    }
    std::fs::write(stack.join(".hidden.tif"), b"not a tiff").unwrap();
    std::fs::write(stack.join("notes.txt"), b"acquisition notes").unwrap();
    let f: Vec<f32> = data.iter().map(|v| *v as f32).collect();
    let want = expected(&f, 1, [1.0; 3]);
    same(&read_volume(&stack, None).unwrap(), &want, "stack");
    regions_match(&stack, &want);
    let listing = SourceListing::list(&stack, None).unwrap();
    assert_eq!(listing.format, Some(Format::Tiff));
    let names: Vec<&str> = listing.files.iter().map(|(n, _, _)| n.as_str()).collect();
    let numbered: Vec<String> = (1..=DIMS[2]).map(|z| format!("slice{z}.tif")).collect();
    assert_eq!(names, numbered);
}

#[test]
fn imagej_and_ome_descriptions_give_the_spacing_in_mm() {
    let dir = tempfile::tempdir().unwrap();
    let data = samples(DIMS, 4000.0, |v| v.round() as u16);
    let f: Vec<f32> = data.iter().map(|v| *v as f32).collect();
    let slice = DIMS[0] * DIMS[1];
    let slices: Vec<&[u16]> = data.chunks(slice).collect();

    // ImageJ: 4 pixels a micron across (0.25 µm), 2 µm between slices.
    let path = dir.path().join("imagej.tif");
    let mut enc = TiffEncoder::new(std::fs::File::create(&path).unwrap()).unwrap();
    for (i, s) in slices.iter().enumerate() {
        let mut image = enc
            .new_image::<colortype::Gray16>(DIMS[0] as u32, DIMS[1] as u32)
            .unwrap();
        image.x_resolution(Rational { n: 4, d: 1 });
        image.y_resolution(Rational { n: 5, d: 1 });
        if i == 0 {
            let d = format!(
                "ImageJ=1.54f\nimages={}\nslices={}\nunit=micron\nspacing=2.0\n",
                DIMS[2], DIMS[2]
            );
            image
                .encoder()
                .write_tag(Tag::ImageDescription, d.as_str())
                .unwrap();
        }
        image.write_data(s).unwrap();
    }
    drop(enc);
    let got = read_volume(&path, None).unwrap();
    let want = [0.25e-3, 0.2e-3, 2e-3];
    for a in 0..3 {
        assert!(
            (got.spacing()[a] - want[a]).abs() < 1e-9,
            "{:?}",
            got.spacing()
        );
    }
    assert_eq!(
        RegionReader::open(&path, None).unwrap().spacing(),
        got.spacing()
    );
    same(&got, &expected(&f, 1, got.spacing()), "imagej");

    // OME-XML: nanometres across, micrometres (the unit OME assumes) between slices.
    let path = dir.path().join("stack.ome.tif");
    let ome = r#"<?xml version="1.0"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06"><Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYZCT" Type="uint16" SizeX="37" SizeY="29" SizeZ="11" SizeC="1" SizeT="1" PhysicalSizeX="500" PhysicalSizeXUnit="nm" PhysicalSizeY="500" PhysicalSizeYUnit="nm" PhysicalSizeZ="1.5"/></Image></OME>"#;
    let file = std::fs::File::create(&path).unwrap();
    write_pages::<colortype::Gray16, _>(
        file,
        Compression::Uncompressed,
        (DIMS[0], DIMS[1]),
        &slices,
        29,
        Some(ome),
    );
    let got = read_volume(&path, None).unwrap();
    let want = [0.5e-3, 0.5e-3, 1.5e-3];
    for a in 0..3 {
        assert!(
            (got.spacing()[a] - want[a]).abs() < 1e-9,
            "{:?}",
            got.spacing()
        );
    }

    // The same XML in a file of 5 of the 11 slices (the first file of a multi-file OME-TIFF,
    // or a truncated one) is refused, not read as a volume of 5 slices.
    let part = dir.path().join("part.ome.tif");
    write_pages::<colortype::Gray16, _>(
        std::fs::File::create(&part).unwrap(),
        Compression::Uncompressed,
        (DIMS[0], DIMS[1]),
        &slices[..5],
        29,
        Some(ome),
    );
    let e = read_volume(&part, None).unwrap_err().to_string();
    assert!(e.contains("counts 11 slices but it holds 5"), "{e}");
    let e = RegionReader::open(&part, None).err().map(|e| e.to_string());
    assert!(e.is_some_and(|e| e.contains("counts 11 slices")));
}

/// An ImageJ hyperstack of time frames, and an OME-TIFF of several time points (one channel),
/// are time series: read whole they say so, and each time point reads as written, region by
/// region, from uncompressed pages (read as bytes) and Deflate ones (decoded), in the planes'
/// order the description gives (a time point's slices together, or each slice's time points).
#[test]
fn hyperstacks_of_time_points_are_time_series() {
    let dir = tempfile::tempdir().unwrap();
    let frames: Vec<Vec<u16>> = (0..2u16)
        .map(|t| samples(DIMS, 1000.0, |v| (v as u16).saturating_add(1000 * t)))
        .collect();
    let slice = DIMS[0] * DIMS[1];
    let time_major: Vec<&[u16]> = frames.iter().flat_map(|f| f.chunks(slice)).collect();
    let slice_major: Vec<&[u16]> = (0..DIMS[2])
        .flat_map(|z| frames.iter().map(move |f| &f[z * slice..(z + 1) * slice]))
        .collect();
    let imagej = format!(
        "ImageJ=1.54f\nimages={}\nslices={}\nframes=2\nhyperstack=true\nfinterval=1.5\ntunit=min\n",
        time_major.len(),
        DIMS[2]
    );
    let ome = |order: &str| {
        format!(
            r#"<?xml version="1.0"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06"><Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="{order}" Type="uint16" SizeX="37" SizeY="29" SizeZ="11" SizeC="1" SizeT="2" TimeIncrement="250" TimeIncrementUnit="ms"/></Image></OME>"#
        )
    };
    let cases = [
        ("imagej", imagej, &time_major, Some(90.0)),
        ("ome_zt", ome("XYZCT"), &time_major, Some(0.25)),
        ("ome_tz", ome("XYTZC"), &slice_major, Some(0.25)),
    ];
    for (name, desc, pages, step) in cases {
        for (how, compression) in [
            ("raw", Compression::Uncompressed),
            ("deflate", Compression::Deflate(DeflateLevel::Fast)),
        ] {
            let what = format!("{name} {how}");
            let path = dir.path().join(format!("{name}_{how}.tif"));
            let file = std::fs::File::create(&path).unwrap();
            write_pages::<colortype::Gray16, _>(
                file,
                compression,
                (DIMS[0], DIMS[1]),
                pages,
                5,
                Some(&desc),
            );
            assert!(
                matches!(
                    read_volume(&path, None),
                    Err(ReadError::TimeSeries { points: 2, .. })
                ),
                "{what}"
            );
            assert!(matches!(
                RegionReader::open(&path, None),
                Err(ReadError::TimeSeries { points: 2, .. })
            ));
            assert_eq!(
                wavesplat_compressor::reader::time_points(&path, None).unwrap(),
                2
            );
            let r = RegionReader::open_series(&path, None).unwrap();
            assert_eq!((r.time_points(), r.dims()), (2, DIMS), "{what}");
            assert_eq!(r.time_step(), step, "{what}");
            for (t, frame) in frames.iter().enumerate() {
                let whole = Volume::new(
                    DIMS,
                    [1.0; 3],
                    vec![frame.iter().map(|v| f32::from(*v)).collect()],
                )
                .unwrap();
                for (origin, size) in [([0, 0, 0], DIMS), ([3, 5, 2], [10, 7, 4])] {
                    let got = r.read_region_at(t, origin, size).unwrap();
                    for z in 0..size[2] {
                        for y in 0..size[1] {
                            for x in 0..size[0] {
                                let w = whole.channel(0)
                                    [whole.index(x + origin[0], y + origin[1], z + origin[2])];
                                assert_eq!(got.channel(0)[got.index(x, y, z)], w, "{what} t {t}");
                            }
                        }
                    }
                }
            }
        }
    }
}

/// The message of a read that must fail.
fn refusal(path: &Path) -> String {
    let e: ReadError = read_volume(path, None).unwrap_err();
    let r = RegionReader::open(path, None).unwrap_err().to_string();
    let e = e.to_string();
    assert_eq!(e, r, "the whole and the region reader refuse alike");
    e
}

#[test]
fn stacks_that_are_not_one_volume_are_refused_saying_why() {
    let dir = tempfile::tempdir().unwrap();
    let data = samples(DIMS, 4000.0, |v| v.round() as u16);
    let slice = DIMS[0] * DIMS[1];
    let slices: Vec<&[u16]> = data.chunks(slice).collect();

    // A page of another size among the files of a directory.
    let mixed = dir.path().join("mixed");
    std::fs::create_dir(&mixed).unwrap();
    for (z, s) in slices.iter().take(3).enumerate() {
        let f = std::fs::File::create(mixed.join(format!("z{z}.tif"))).unwrap();
        write_pages::<colortype::Gray16, _>(
            f,
            Compression::Uncompressed,
            (DIMS[0], DIMS[1]),
            &[s],
            8,
            None,
        );
    }
    let f = std::fs::File::create(mixed.join("z3.tif")).unwrap();
    write_pages::<colortype::Gray16, _>(
        f,
        Compression::Uncompressed,
        (DIMS[1], DIMS[0]),
        &[slices[3]],
        8,
        None,
    );
    let e = refusal(&mixed);
    assert!(
        e.contains("z3.tif") && e.contains("29x37") && e.contains("37x29"),
        "{e}"
    );

    // Slice files numbered with a gap (z5.tif missing among z0 to z6): read, the volume would
    // close the gap without a word.
    let gap = dir.path().join("gap");
    std::fs::create_dir(&gap).unwrap();
    for (z, s) in slices.iter().enumerate().take(7).filter(|(z, _)| *z != 5) {
        let f = std::fs::File::create(gap.join(format!("z{z}.tif"))).unwrap();
        write_pages::<colortype::Gray16, _>(
            f,
            Compression::Uncompressed,
            (DIMS[0], DIMS[1]),
            &[s],
            8,
            None,
        );
    }
    let e = refusal(&gap);
    assert!(
        e.contains("between \"z4.tif\" and \"z6.tif\" are missing"),
        "{e}"
    );
    assert!(RegionReader::open(&gap, None).is_err());
    std::fs::rename(gap.join("z6.tif"), gap.join("z5.tif")).unwrap();
    assert_eq!(read_volume(&gap, None).unwrap().dims()[2], 6);

    // A page of 8 bits after pages of 16.
    let path = dir.path().join("depths.tif");
    {
        let mut enc = TiffEncoder::new(std::fs::File::create(&path).unwrap()).unwrap();
        enc.write_image::<colortype::Gray16>(DIMS[0] as u32, DIMS[1] as u32, slices[0])
            .unwrap();
        let bytes: Vec<u8> = slices[1].iter().map(|v| (*v >> 8) as u8).collect();
        enc.write_image::<colortype::Gray8>(DIMS[0] as u32, DIMS[1] as u32, &bytes)
            .unwrap();
    }
    let e = refusal(&path);
    assert!(e.contains("8-bit") && e.contains("16-bit"), "{e}");

    // An ImageJ hyperstack of two channels, one whose 9 images are not 2 frames' slices, and
    // one whose 9 images are 3 frames' but not of the 4 slices it counts.
    for (d, word) in [
        ("channels=2\nslices=5\n", "channels"),
        ("slices=4\nframes=2\n", "in 9 images"),
        ("slices=4\nframes=3\n", "3 time points of 4 slices in 9"),
    ] {
        let path = dir.path().join(format!("hyper_{}.tif", word.len()));
        let desc = format!("ImageJ=1.54f\nimages=9\n{d}hyperstack=true\n");
        let file = std::fs::File::create(&path).unwrap();
        write_pages::<colortype::Gray16, _>(
            file,
            Compression::Uncompressed,
            (DIMS[0], DIMS[1]),
            &slices[..9],
            29,
            Some(&desc),
        );
        let e = RegionReader::open_series(&path, None)
            .unwrap_err()
            .to_string();
        assert!(e.contains(word), "{e}");
    }

    // An ImageJ stack over 4 GB whose images are not all there: its description counts 400
    // images after the first page's samples, the file holds one.
    let path = dir.path().join("big_imagej.tif");
    let desc = "ImageJ=1.54f\nimages=400\nslices=400\n";
    for (compression, name) in [
        (Compression::Uncompressed, "raw"),
        (Compression::Lzw, "lzw"),
    ] {
        let path = path.with_extension(format!("{name}.tif"));
        let file = std::fs::File::create(&path).unwrap();
        write_pages::<colortype::Gray16, _>(
            file,
            compression,
            (DIMS[0], DIMS[1]),
            &slices[..1],
            29,
            Some(desc),
        );
        let e = refusal(&path);
        if name == "raw" {
            assert!(
                e.contains("truncated") && e.contains(&(400 * slice * 2).to_string()),
                "{e}"
            );
        } else {
            // Compressed, its images cannot be found without their pages.
            assert!(
                e.contains("400 images") && e.contains("Image Sequence"),
                "{e}"
            );
        }
    }

    // RGBA: an alpha channel.
    let path = dir.path().join("rgba.tif");
    {
        let mut enc = TiffEncoder::new(std::fs::File::create(&path).unwrap()).unwrap();
        enc.write_image::<colortype::RGBA8>(4, 3, &[7u8; 4 * 3 * 4])
            .unwrap();
    }
    let e = refusal(&path);
    assert!(
        e.contains("RGBA") && e.contains("supported are grey and RGB"),
        "{e}"
    );

    // Not a TIFF after its magic: refused, never a panic.
    let path = dir.path().join("broken.tif");
    std::fs::write(&path, b"II*\0\xff\xff\xff\x7f and nothing after").unwrap();
    assert!(read_volume(&path, None).is_err());
    assert!(RegionReader::open(&path, None).is_err());
}

/// Writes TIFFs with tifffile (an independent writer: tiles, BigTIFF, zlib, ImageJ metadata)
/// and each volume as little-endian f64 samples (x fastest, channels interleaved), and the
/// spacing it wrote in mm, for the Rust side to compare.
const TIFFFILE_WRITER: &str = r#"
import sys, json
import numpy as np
import tifffile
out = sys.argv[1]
rng = np.random.default_rng(7)
z, y, x = 9, 45, 53
cases = {}
def case(name, data, ref=None, **kw):
    path = f"{out}/{name}.tif"
    tifffile.imwrite(path, data, **kw)
    (data if ref is None else ref).astype("<f8").tofile(f"{out}/{name}.f64")
    cases[name] = list(data.shape)
case("tiled_u16_zlib", rng.integers(0, 65535, (z, y, x), dtype=np.uint16),
     tile=(16, 32), compression="zlib")
case("bigtiff_f32", rng.normal(3.0, 40.0, (z, y, x)).astype(np.float32), bigtiff=True)
case("big_endian_i16", rng.integers(-30000, 30000, (z, y, x), dtype=np.int16), byteorder=">",
     rowsperstrip=7)
case("i16_strips", rng.integers(-30000, 30000, (z, y, x), dtype=np.int16),
     rowsperstrip=5, compression="zlib")
case("u32_tiled", rng.integers(0, 2**31, (z, y, x), dtype=np.uint32), tile=(16, 16))
case("f64", rng.normal(0.0, 1e5, (z, y, x)), compression="zlib")
case("rgb_tiled", rng.integers(0, 255, (z, y, x, 3), dtype=np.uint8),
     photometric="rgb", tile=(32, 16), compression="zlib")
# RGB and a fourth sample that is not alpha: read as RGB (uncompressed: as bytes).
rgbx = rng.integers(0, 255, (z, y, x, 4), dtype=np.uint8)
# Pages in one compressed strip each, grey and colour: every brick across a page shares it.
case("u16_one_strip", rng.integers(0, 65535, (z, y, x), dtype=np.uint16),
     rowsperstrip=y, compression="zlib")
case("rgb_one_strip", rng.integers(0, 255, (z, y, x, 3), dtype=np.uint8),
     photometric="rgb", rowsperstrip=y, compression="zlib")
case("rgb_extra", rgbx, ref=rgbx[..., :3], photometric="rgb", extrasamples=["unspecified"],
     rowsperstrip=8)
case("imagej", rng.integers(0, 4000, (z, y, x), dtype=np.uint16), imagej=True,
     resolution=(1 / 0.4, 1 / 0.5), metadata={"spacing": 1.25, "unit": "um", "axes": "ZYX"})
# A hyperstack of 3 time frames of 3 slices: a time series.
case("imagej_frames", rng.integers(0, 4000, (3, 3, y, x), dtype=np.uint16), imagej=True,
     metadata={"axes": "TZYX"})
case("ome_frames", rng.integers(0, 4000, (3, 3, y, x), dtype=np.uint16), ome=True,
     metadata={"axes": "TZYX"})
json.dump(cases, open(f"{out}/cases.json", "w"))
"#;

/// Runs the tifffile `script` in `dir` with `args` by the reference Python (asserting it
/// succeeded); `None`, the check skipped saying why, where tifffile is not installed.
fn run_tifffile(dir: &Path, script: &str, args: &[&Path]) -> Option<()> {
    let python = wavesplat_fixtures::reference_python(
        "tifffile, numpy",
        "apt-get install python3-tifffile python3-numpy",
    )?;
    let path = dir.join("tifffile_script.py");
    std::fs::write(&path, script).unwrap();
    let o = std::process::Command::new(python)
        .arg(&path)
        .args(args)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "tifffile: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    Some(())
}

/// Little-endian f64 samples a tifffile script wrote.
fn read_f64(path: &Path) -> Vec<f64> {
    std::fs::read(path)
        .unwrap()
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
        .collect()
}

#[test]
fn tiffs_written_by_tifffile_read_as_it_wrote_them() {
    let dir = tempfile::tempdir().unwrap();
    if run_tifffile(dir.path(), TIFFFILE_WRITER, &[dir.path()]).is_none() {
        return;
    }
    for name in [
        "tiled_u16_zlib",
        "bigtiff_f32",
        "big_endian_i16",
        "i16_strips",
        "u32_tiled",
        "f64",
        "rgb_tiled",
        "rgb_extra",
        "u16_one_strip",
        "rgb_one_strip",
        "imagej",
    ] {
        let path = dir.path().join(format!("{name}.tif"));
        let reference = read_f64(&dir.path().join(format!("{name}.f64")));
        let v = read_volume(&path, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(v.dims(), [53, 45, 9], "{name}");
        let nc = v.channel_count();
        assert_eq!(nc, if name.starts_with("rgb") { 3 } else { 1 }, "{name}");
        for (k, r) in reference.iter().enumerate() {
            let (c, i) = (k % nc, k / nc);
            let ours = f64::from(v.channels()[c][i]);
            // Samples are f32 in a volume: equal to the reference rounded to f32.
            assert_eq!(ours, f64::from(*r as f32), "{name}: sample {i} channel {c}");
        }
        // Region reads give the same samples.
        let r = RegionReader::open(&path, None).unwrap();
        let part = r.read_region([17, 20, 3], [30, 19, 5]).unwrap();
        for z in 0..5 {
            for y in 0..19 {
                for x in 0..30 {
                    for c in 0..nc {
                        assert_eq!(
                            part.channels()[c][part.index(x, y, z)],
                            v.channels()[c][v.index(x + 17, y + 20, z + 3)],
                            "{name}: region"
                        );
                    }
                }
            }
        }
        // Bricks over the whole from one reader: strips and tiles under several of them are
        // decoded into the reader's spool and read back from it.
        let bricks = RegionReader::open(&path, None).unwrap();
        let brick = [17, 16, 4];
        for z0 in (0..9).step_by(brick[2]) {
            for y0 in (0..45).step_by(brick[1]) {
                for x0 in (0..53).step_by(brick[0]) {
                    let o = [x0, y0, z0];
                    let s = [0, 1, 2].map(|a| brick[a].min([53, 45, 9][a] - o[a]));
                    let got = bricks.read_region(o, s).unwrap();
                    for c in 0..nc {
                        for (j, g) in got.channels()[c].iter().enumerate() {
                            let (x, y, z) = (j % s[0], j / s[0] % s[1], j / s[0] / s[1]);
                            let w = v.channels()[c][v.index(x + x0, y + y0, z + z0)];
                            assert_eq!(*g, w, "{name}: brick {o:?} channel {c} at {j}");
                        }
                    }
                }
            }
        }
        let spacing = if name == "imagej" {
            [0.4e-3, 0.5e-3, 1.25e-3]
        } else {
            [1.0; 3]
        };
        for a in 0..3 {
            assert!(
                (f64::from(v.spacing()[a]) - spacing[a]).abs() < 1e-9,
                "{name}: spacing {:?}",
                v.spacing()
            );
        }
    }
    // The ImageJ hyperstack and the OME-TIFF of time frames: series of 3 time points of 3
    // slices, each as written.
    for name in ["imagej_frames", "ome_frames"] {
        let path = dir.path().join(format!("{name}.tif"));
        let reference = read_f64(&dir.path().join(format!("{name}.f64")));
        let points = wavesplat_compressor::reader::time_points(&path, None).unwrap();
        assert_eq!(points, 3, "{name}");
        let r = RegionReader::open_series(&path, None).unwrap();
        assert_eq!((r.time_points(), r.dims()), (3, [53, 45, 3]), "{name}");
        for t in 0..3 {
            let frame = r.read_region_at(t, [0; 3], [53, 45, 3]).unwrap();
            let want = &reference[t * 53 * 45 * 3..(t + 1) * 53 * 45 * 3];
            let got: Vec<f64> = frame.channel(0).iter().map(|v| f64::from(*v)).collect();
            assert_eq!(got, want, "{name}: time point {t}");
        }
    }
}

/// A few bytes that declare a huge image are refused before it is allocated, saying so.
#[test]
fn a_header_declaring_more_samples_than_its_bytes_hold_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("claims.tif");
    // A 60000 × 60000 16-bit page (7.2 GB) in one strip of 4 bytes.
    let mut b: Vec<u8> = b"II*\0".to_vec();
    b.extend_from_slice(&8u32.to_le_bytes());
    let entries: [(u16, u16, u32, u32); 8] = [
        (256, 4, 1, 60000), // ImageWidth
        (257, 4, 1, 60000), // ImageLength
        (258, 3, 1, 16),    // BitsPerSample
        (259, 3, 1, 1),     // Compression: none
        (262, 3, 1, 1),     // BlackIsZero
        (273, 4, 1, 200),   // StripOffsets
        (278, 4, 1, 60000), // RowsPerStrip
        (279, 4, 1, 4),     // StripByteCounts
    ];
    b.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    for (tag, ty, count, value) in entries {
        b.extend_from_slice(&tag.to_le_bytes());
        b.extend_from_slice(&ty.to_le_bytes());
        b.extend_from_slice(&count.to_le_bytes());
        match ty {
            3 => {
                b.extend_from_slice(&(value as u16).to_le_bytes());
                b.extend_from_slice(&[0, 0]);
            }
            _ => b.extend_from_slice(&value.to_le_bytes()),
        }
    }
    b.extend_from_slice(&0u32.to_le_bytes());
    b.resize(204, 7);
    std::fs::write(&path, &b).unwrap();
    let e = refusal(&path);
    assert!(e.contains("7200000000 bytes of samples"), "{e}");
}

/// A DICOM series beside a stray TIFF preview stays a DICOM series (whole and by regions).
#[test]
fn a_dicom_series_beside_a_tiff_preview_stays_a_series() {
    use wavesplat_fixtures::{write_dicom_series, DicomOptions, Layout};
    let dir = tempfile::tempdir().unwrap();
    let series = dir.path().join("ct");
    std::fs::create_dir(&series).unwrap();
    let dims = [12, 10, 6];
    let samples: Vec<f32> = Phantom::SheppLogan
        .generate(dims)
        .to_interleaved()
        .iter()
        .map(|v| v.round())
        .collect();
    let v = Volume::new(dims, [1.0; 3], vec![samples]).unwrap();
    let options = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    write_dicom_series(&series, &v, &options);
    let f = std::fs::File::create(series.join("preview.tif")).unwrap();
    write_pages::<colortype::Gray8, _>(f, Compression::Uncompressed, (4, 4), &[&[9; 16]], 4, None);
    assert_eq!(
        SourceListing::list(&series, None).unwrap().format,
        Some(Format::Dicom)
    );
    assert_eq!(read_volume(&series, None).unwrap().dims(), dims);
    assert_eq!(RegionReader::open(&series, None).unwrap().dims(), dims);
}

/// OME-TIFF: RGB pages count their samples in `SizeC` (3) and read; grey pages of several
/// channels are refused without a channel chosen, and several images in one file are refused,
/// saying so.
#[test]
fn ome_channels_and_images_are_told_apart() {
    let dir = tempfile::tempdir().unwrap();
    let ome = |size_c: usize, images: usize| {
        let image = format!(
            r#"<Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYZCT" Type="uint8" SizeX="4" SizeY="3" SizeZ="2" SizeC="{size_c}" SizeT="1"/></Image>"#
        );
        format!("<?xml version=\"1.0\"?><OME>{}</OME>", image.repeat(images))
    };
    let rgb = dir.path().join("rgb.ome.tif");
    let f = std::fs::File::create(&rgb).unwrap();
    let page = [50u8; 4 * 3 * 3];
    write_pages::<colortype::RGB8, _>(
        f,
        Compression::Uncompressed,
        (4, 3),
        &[&page, &page],
        3,
        Some(&ome(3, 1)),
    );
    let v = read_volume(&rgb, None).unwrap();
    assert_eq!((v.dims(), v.channel_count()), ([4, 3, 2], 3));
    let grey = dir.path().join("two.ome.tif");
    let f = std::fs::File::create(&grey).unwrap();
    let page = [50u8; 4 * 3];
    write_pages::<colortype::Gray8, _>(
        f,
        Compression::Uncompressed,
        (4, 3),
        &[&page, &page],
        3,
        Some(&ome(2, 1)),
    );
    // Grey pages of two channels (of two slices each, in two pages: a part of a dataset).
    let e = refusal(&grey);
    assert!(
        e.contains("2 channels") && e.contains("do not add up"),
        "{e}"
    );
    let many = dir.path().join("positions.ome.tif");
    let f = std::fs::File::create(&many).unwrap();
    write_pages::<colortype::Gray8, _>(
        f,
        Compression::Uncompressed,
        (4, 3),
        &[&page, &page],
        3,
        Some(&ome(1, 2)),
    );
    let e = refusal(&many);
    assert!(e.contains("2 images"), "{e}");
}

/// `RowsPerStrip` of 2^32 − 1 (the spec's default, "the whole image in one strip", written out
/// by some writers) reads, compressed and not.
#[test]
fn rows_per_strip_of_the_default_reads() {
    let dir = tempfile::tempdir().unwrap();
    let data = samples(DIMS, 4000.0, |v| v.round() as u16);
    let slice = DIMS[0] * DIMS[1];
    let slices: Vec<&[u16]> = data.chunks(slice).collect();
    let f: Vec<f32> = data.iter().map(|v| *v as f32).collect();
    let want = expected(&f, 1, [1.0; 3]);
    for (name, compression) in [
        ("raw", Compression::Uncompressed),
        ("lzw", Compression::Lzw),
    ] {
        let path = dir.path().join(format!("rps_{name}.tif"));
        let file = std::fs::File::create(&path).unwrap();
        let rows = DIMS[1] as u32;
        write_pages::<colortype::Gray16, _>(
            file,
            compression,
            (DIMS[0], DIMS[1]),
            &slices,
            rows,
            None,
        );
        // Every RowsPerStrip entry (tag 278, LONG, 1 value: `rows`) set to 2^32 − 1.
        let mut bytes = std::fs::read(&path).unwrap();
        let mut entry = Vec::new();
        entry.extend_from_slice(&278u16.to_le_bytes());
        entry.extend_from_slice(&4u16.to_le_bytes());
        entry.extend_from_slice(&1u32.to_le_bytes());
        entry.extend_from_slice(&rows.to_le_bytes());
        let mut patched = 0;
        for i in 0..bytes.len() - 12 {
            if bytes[i..i + 12] == entry[..] {
                bytes[i + 8..i + 12].copy_from_slice(&u32::MAX.to_le_bytes());
                patched += 1;
            }
        }
        assert_eq!(patched, DIMS[2], "{name}");
        std::fs::write(&path, &bytes).unwrap();
        same(&read_volume(&path, None).unwrap(), &want, name);
        regions_match(&path, &want);
    }
}

/// Channels stored as planes of their own (an ImageJ hyperstack of channels, and of channels
/// and time frames; OME-TIFFs of `SizeC` 2 in two plane orders): none chosen is refused
/// naming the count; each channel chosen reads as written, whole, by region, from a bundle
/// and as a time series; a channel the file lacks is refused.
#[test]
fn channels_stored_as_planes_are_read_one_at_a_time_as_chosen() {
    use wavesplat_compressor::reader::{
        decode_source_channel, read_volume_channel, tiff_pages_and_channels, SourceFiles,
    };
    use wavesplat_compressor::series::open_series_path_channel;
    let dir = tempfile::tempdir().unwrap();
    // volume[t][c]: each its own values.
    let volume = |t: usize, c: usize| -> Vec<u16> {
        samples(DIMS, 1000.0, |v| (v as u16).min(1000))
            .iter()
            .map(|v| v + 2000 * c as u16 + 7000 * t as u16)
            .collect()
    };
    let slice = DIMS[0] * DIMS[1];
    let vols: Vec<Vec<Vec<u16>>> = (0..2)
        .map(|t| (0..2).map(|c| volume(t, c)).collect())
        .collect();
    let plane = |t: usize, c: usize, z: usize| &vols[t][c][z * slice..(z + 1) * slice];
    // The planes in an order, fastest axis first, of `frames` time points.
    let ordered = |order: &[u8; 3], frames: usize| -> Vec<&[u16]> {
        let size = |a: u8| match a {
            b'Z' => DIMS[2],
            b'C' => 2,
            _ => frames,
        };
        let n = DIMS[2] * 2 * frames;
        (0..n)
            .map(|i| {
                let (mut rest, mut at) = (i, [0usize; 3]);
                for &a in order {
                    let k = b"ZCT".iter().position(|b| *b == a).unwrap();
                    at[k] = rest % size(a);
                    rest /= size(a);
                }
                plane(at[2], at[1], at[0])
            })
            .collect()
    };
    let imagej = |frames: usize| {
        format!(
            "ImageJ=1.54f\nimages={}\nchannels=2\nslices={}\nframes={frames}\nhyperstack=true\n",
            2 * DIMS[2] * frames,
            DIMS[2]
        )
    };
    let ome = |order: &str| {
        format!(
            r#"<?xml version="1.0"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06"><Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="{order}" Type="uint16" SizeX="37" SizeY="29" SizeZ="11" SizeC="2" SizeT="1"/></Image></OME>"#
        )
    };
    let cases = [
        ("imagej", imagej(1), ordered(b"CZT", 1)),
        ("ome_zct", ome("XYZCT"), ordered(b"ZCT", 1)),
        ("ome_czt", ome("XYCZT"), ordered(b"CZT", 1)),
    ];
    for (name, desc, pages) in &cases {
        let path = dir.path().join(format!("{name}.tif"));
        let file = std::fs::File::create(&path).unwrap();
        write_pages::<colortype::Gray16, _>(
            file,
            Compression::Deflate(DeflateLevel::Fast),
            (DIMS[0], DIMS[1]),
            pages,
            5,
            Some(desc),
        );
        let planes = (2 * DIMS[2], 2);
        assert_eq!(tiff_pages_and_channels(&path).unwrap(), planes, "{name}");
        let e = read_volume(&path, None).unwrap_err();
        assert!(
            matches!(e, ReadError::Channels { channels: 2, .. }),
            "{name}: {e}"
        );
        assert!(e.to_string().contains("--channel"), "{e}");
        let e = RegionReader::open(&path, None).unwrap_err();
        assert!(matches!(e, ReadError::Channels { channels: 2, .. }), "{e}");
        let e = RegionReader::open_channel(&path, None, Some(2)).unwrap_err();
        assert!(e.to_string().contains("channel 2 was chosen"), "{e}");
        let bundle = SourceFiles::gather(&path, None).unwrap();
        for c in 0..2 {
            let want: Vec<f32> = vols[0][c].iter().map(|v| f32::from(*v)).collect();
            let whole = read_volume_channel(&path, None, Some(c)).unwrap();
            assert_eq!(whole.dims(), DIMS, "{name}");
            assert_eq!(whole.channel(0), &want[..], "{name} channel {c}");
            let bundled = decode_source_channel(&bundle, None, Some(c)).unwrap();
            assert_eq!(bundled, whole, "{name} channel {c} from a bundle");
            let r = RegionReader::open_channel(&path, None, Some(c)).unwrap();
            assert_eq!(r.channels(), 1);
            let (o, s) = ([3, 5, 2], [10, 7, 4]);
            let got = r.read_region(o, s).unwrap();
            let at = |x: usize, y: usize, z: usize| want[whole.index(x, y, z)];
            assert_eq!(got.channel(0)[got.index(0, 0, 0)], at(3, 5, 2), "{name}");
            assert_eq!(got.channel(0)[got.index(9, 6, 3)], at(12, 11, 5), "{name}");
        }
    }
    // Channels and time frames: each time point of the channel chosen.
    let path = dir.path().join("imagej_ct.tif");
    let file = std::fs::File::create(&path).unwrap();
    write_pages::<colortype::Gray16, _>(
        file,
        Compression::Uncompressed,
        (DIMS[0], DIMS[1]),
        &ordered(b"CZT", 2),
        5,
        Some(&imagej(2)),
    );
    let input = open_series_path_channel(&path, None, Some(1))
        .unwrap()
        .expect("a series");
    assert_eq!(input.source().time_points(), 2);
    for t in 0..2 {
        let got = input.source().read_at(t, [0; 3], DIMS).unwrap();
        let want: Vec<f32> = vols[t][1].iter().map(|v| f32::from(*v)).collect();
        assert_eq!(got.channel(0), &want[..], "time point {t}");
    }
}

/// Writes hyperstacks of channels with tifffile (ImageJ's plane order, and OME-TIFFs whose
/// DimensionOrder puts Z or C first), and each channel as little-endian f64 samples (x fastest,
/// then y, z and time), for the Rust side to compare.
const TIFFFILE_CHANNELS_WRITER: &str = r#"
import sys, json
import numpy as np
import tifffile
out = sys.argv[1]
rng = np.random.default_rng(11)
z, y, x = 5, 21, 19
cases = {}
def case(name, data, channel_axis, time_axis=None, **kw):
    tifffile.imwrite(f"{out}/{name}.tif", data, photometric="minisblack", **kw)
    channels = data.shape[channel_axis]
    for c in range(channels):
        np.take(data, c, axis=channel_axis).astype("<f8").tofile(f"{out}/{name}_c{c}.f64")
    cases[name] = [channels, 1 if time_axis is None else data.shape[time_axis]]
def values(shape):
    return rng.integers(0, 4000, shape, dtype=np.uint16)
case("imagej_zc", values((z, 2, y, x)), 1, imagej=True, metadata={"axes": "ZCYX"})
case("imagej_tzc", values((2, z, 3, y, x)), 2, 0, imagej=True, metadata={"axes": "TZCYX"})
case("ome_cz", values((3, z, y, x)), 0, ome=True, metadata={"axes": "CZYX"})
case("ome_zc", values((z, 2, y, x)), 1, ome=True, metadata={"axes": "ZCYX"})
case("ome_cz_f32_tiled", rng.normal(0, 100, (2, z, y, x)).astype(np.float32), 0, ome=True,
     metadata={"axes": "CZYX"}, compression="zlib", tile=(16, 16))
json.dump(cases, open(f"{out}/cases.json", "w"))
"#;

/// Hyperstacks of channels written by tifffile, an independent writer: each channel read as
/// it wrote it (whole, by regions, and each time point of a series), none chosen refused.
#[test]
fn channels_written_by_tifffile_read_as_it_wrote_them() {
    use wavesplat_compressor::reader::{read_volume_channel, tiff_pages_and_channels};
    use wavesplat_compressor::series::open_series_path_channel;
    let dir = tempfile::tempdir().unwrap();
    if run_tifffile(dir.path(), TIFFFILE_CHANNELS_WRITER, &[dir.path()]).is_none() {
        return;
    }
    let dims = [19, 21, 5];
    let cases = [
        ("imagej_zc", 2, 1),
        ("imagej_tzc", 3, 2),
        ("ome_cz", 3, 1),
        ("ome_zc", 2, 1),
        ("ome_cz_f32_tiled", 2, 1),
    ];
    let written = std::fs::read_to_string(dir.path().join("cases.json")).unwrap();
    for (name, channels, frames) in cases {
        assert!(
            written.contains(&format!("\"{name}\": [{channels}, {frames}]")),
            "{name}: {written}"
        );
        let path = dir.path().join(format!("{name}.tif"));
        assert_eq!(
            tiff_pages_and_channels(&path).unwrap(),
            (channels * frames * dims[2], channels),
            "{name}"
        );
        let e = read_volume(&path, None).unwrap_err();
        assert!(
            matches!(e, ReadError::Channels { channels: n, .. } if n == channels as u64),
            "{name}: {e}"
        );
        for c in 0..channels {
            let reference: Vec<f32> = read_f64(&dir.path().join(format!("{name}_c{c}.f64")))
                .into_iter()
                .map(|v| v as f32)
                .collect();
            let voxels = dims.iter().product::<usize>();
            assert_eq!(reference.len(), voxels * frames, "{name}");
            if frames == 1 {
                let v = read_volume_channel(&path, None, Some(c))
                    .unwrap_or_else(|e| panic!("{name} channel {c}: {e}"));
                assert_eq!(v.dims(), dims, "{name}");
                assert_eq!(v.channel(0), &reference[..], "{name} channel {c}");
                let r = RegionReader::open_channel(&path, None, Some(c)).unwrap();
                let part = r.read_region([4, 7, 1], [11, 9, 3]).unwrap();
                for (z, y, x) in [(0, 0, 0), (2, 8, 10), (1, 3, 5)] {
                    assert_eq!(
                        part.channel(0)[part.index(x, y, z)],
                        reference[v.index(x + 4, y + 7, z + 1)],
                        "{name} channel {c}: region"
                    );
                }
            } else {
                let input = open_series_path_channel(&path, None, Some(c))
                    .unwrap()
                    .expect("a series");
                assert_eq!(input.source().time_points(), frames, "{name}");
                for t in 0..frames {
                    let got = input.source().read_at(t, [0; 3], dims).unwrap();
                    assert_eq!(
                        got.channel(0),
                        &reference[t * voxels..(t + 1) * voxels],
                        "{name} channel {c} time point {t}"
                    );
                }
            }
        }
    }
}

/// Channel descriptions that do not fit their pages are refused, never read in part or as
/// something else: ImageJ channels over RGB pages (unless they are the pages' three samples),
/// counts that do not multiply to the pages (or overflow), an unknown OME plane order.
#[test]
fn channel_descriptions_that_do_not_fit_their_pages_are_refused() {
    use wavesplat_compressor::reader::{read_volume_channel, tiff_pages_and_channels};
    let dir = tempfile::tempdir().unwrap();
    let rgb_page = [40u8; 4 * 3 * 3];
    let grey_page = [40u8; 4 * 3];
    let write = |name: &str, rgb: bool, pages: usize, desc: &str| {
        let path = dir.path().join(name);
        let f = std::fs::File::create(&path).unwrap();
        if rgb {
            let all: Vec<&[u8]> = (0..pages).map(|_| &rgb_page[..]).collect();
            write_pages::<colortype::RGB8, _>(
                f,
                Compression::Uncompressed,
                (4, 3),
                &all,
                3,
                Some(desc),
            );
        } else {
            let all: Vec<&[u8]> = (0..pages).map(|_| &grey_page[..]).collect();
            write_pages::<colortype::Gray8, _>(
                f,
                Compression::Uncompressed,
                (4, 3),
                &all,
                3,
                Some(desc),
            );
        }
        path
    };
    let ij = |d: &str| format!("ImageJ=1.54f\n{d}hyperstack=true\n");
    // The three channels of RGB pages are their samples: one RGB volume.
    let rgb3 = write("rgb3.tif", true, 2, &ij("images=2\nchannels=3\nslices=2\n"));
    assert_eq!(tiff_pages_and_channels(&rgb3).unwrap(), (2, 1));
    let v = read_volume(&rgb3, None).unwrap();
    assert_eq!((v.dims(), v.channel_count()), ([4, 3, 2], 3));
    let cases = [
        ("rgb2.tif", true, 4, ij("images=4\nchannels=2\nslices=2\n"), "pages of 3 samples"),
        ("short.tif", false, 4, ij("images=4\nchannels=2\nslices=3\n"), "do not add up"),
        (
            "huge.tif",
            false,
            4,
            ij("images=4\nchannels=4294967297\nframes=4294967297\n"),
            "do not add up",
        ),
        (
            "order.tif",
            false,
            2,
            r#"<?xml version="1.0"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06"><Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYQRS" Type="uint8" SizeX="4" SizeY="3" SizeZ="1" SizeC="2" SizeT="1"/></Image></OME>"#.to_string(),
            "DimensionOrder",
        ),
    ];
    for (name, rgb, pages, desc, why) in cases {
        let path = write(name, rgb, pages, &desc);
        let e = tiff_pages_and_channels(&path).unwrap_err().to_string();
        assert!(e.contains(why), "{name}: {e}");
        for c in [None, Some(0)] {
            let e = read_volume_channel(&path, None, c).unwrap_err().to_string();
            assert!(e.contains(why), "{name} {c:?}: {e}");
            let e = RegionReader::open_channel(&path, None, c)
                .unwrap_err()
                .to_string();
            assert!(e.contains(why), "{name} {c:?}: {e}");
        }
    }
}

/// The OME-XML of a multi-file OME-TIFF of `DIMS` in two channels (`DimensionOrder` XYZCT:
/// channel 0's slices, then channel 1's), placing its 22 planes in three files: nine in
/// `acq.ome.tif` and nine in `acq_1.ome.tif` by one `TiffData` each, the last four in
/// `acq_2.ome.tif` one `TiffData` a plane (as Micro-Manager writes them), each file's `UUID`
/// ending in its number (1 to 3), the XML's own that of file `own`. `extra` is added among the
/// `TiffData` elements.
fn multi_file_ome_xml(extra: &str, own: u32) -> String {
    let uuid = |file: &str, n: u32| {
        format!(r#"<UUID FileName="{file}">urn:uuid:00000000-0000-0000-0000-00000000000{n}</UUID>"#)
    };
    let mut tiff_data = format!(
        r#"<TiffData FirstZ="0" FirstC="0" FirstT="0" IFD="0" PlaneCount="9">{}</TiffData><TiffData FirstZ="9" FirstC="0" IFD="0" PlaneCount="9">{}</TiffData>"#,
        uuid("acq.ome.tif", 1),
        uuid("acq_1.ome.tif", 2)
    );
    for k in 0..4 {
        tiff_data += &format!(
            r#"<TiffData FirstZ="{}" FirstC="1" IFD="{k}">{}</TiffData>"#,
            7 + k,
            uuid("acq_2.ome.tif", 3)
        );
    }
    tiff_data += extra;
    format!(
        r#"<?xml version="1.0" encoding="UTF-8"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06" UUID="urn:uuid:00000000-0000-0000-0000-00000000000{own}"><Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYZCT" Type="uint16" SizeX="37" SizeY="29" SizeZ="11" SizeC="2" SizeT="1" PhysicalSizeX="0.5" PhysicalSizeY="0.5" PhysicalSizeZ="2"><Channel ID="Channel:0:0" SamplesPerPixel="1"/><Channel ID="Channel:0:1" SamplesPerPixel="1"/>{tiff_data}</Pixels></Image></OME>"#
    )
}

/// Writes the multi-file OME-TIFF of [`multi_file_ome_xml`] into `dir`, its XML in the first
/// file and the others' descriptions `part(n)` (a `BinaryOnly` pointer, or the XML again as
/// file `n` holds it); returns each channel's samples.
fn write_multi_file_ome(dir: &Path, xml: &str, part: &dyn Fn(u32) -> String) -> Vec<Vec<u16>> {
    let channel = |c: u16| -> Vec<u16> {
        samples(DIMS, 1000.0, |v| (v as u16).min(1000))
            .iter()
            .map(|v| v + 3000 * c)
            .collect()
    };
    let volumes = vec![channel(0), channel(1)];
    let slice = DIMS[0] * DIMS[1];
    // Planes in the DimensionOrder: channel 0's slices, then channel 1's.
    let planes: Vec<&[u16]> = volumes.iter().flat_map(|v| v.chunks(slice)).collect();
    for (name, range, description) in [
        ("acq.ome.tif", 0..9, xml.to_string()),
        ("acq_1.ome.tif", 9..18, part(2)),
        ("acq_2.ome.tif", 18..22, part(3)),
    ] {
        let file = std::fs::File::create(dir.join(name)).unwrap();
        write_pages::<colortype::Gray16, _>(
            file,
            Compression::Deflate(DeflateLevel::Fast),
            (DIMS[0], DIMS[1]),
            &planes[range],
            8,
            Some(&description),
        );
    }
    volumes
}

/// Reads a multi-file OME-TIFF with tifffile (an independent reader), each channel's samples as
/// little-endian f64 into `out`_cC.f64 (x fastest).
const TIFFFILE_MULTI_FILE_READER: &str = r#"
import sys
import numpy as np
import tifffile
with tifffile.TiffFile(sys.argv[1]) as t:
    series = t.series[0]
    data = series.asarray()
    axes = series.axes
data = np.transpose(data, [axes.index(a) for a in "CZYX"])
for c in range(data.shape[0]):
    data[c].astype("<f8").tofile(f"{sys.argv[2]}_c{c}.f64")
print(axes, data.shape)
"#;

/// A multi-file OME-TIFF (one acquisition over several files, its XML in the first placing
/// every plane by `TiffData` elements) is read from its first file as one volume, each channel
/// as tifffile reads it, whole, by regions and from a bundle of its files; a part alone is
/// refused naming the file to read; XML that places planes twice, nowhere, past the files'
/// pages, outside the directory or in a file that is no TIFF is refused; the same dataset's XML
/// in an OME companion file is read from it; a one-file OME-TIFF renamed is still one file.
#[test]
fn a_multi_file_ome_tiff_is_read_as_one_volume_from_the_file_holding_its_xml() {
    use wavesplat_compressor::reader::{
        decode_source_channel, read_volume_channel, tiff_dataset, tiff_pages_and_channels,
        SourceFiles, TiffDataset,
    };
    let xml = multi_file_ome_xml("", 1);
    let binary_only = |_: u32| {
        r#"<?xml version="1.0" encoding="UTF-8"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06"><BinaryOnly MetadataFile="acq.ome.tif" UUID="urn:uuid:00000000-0000-0000-0000-000000000001"/></OME>"#.to_string()
    };
    let xml_again = |n: u32| multi_file_ome_xml("", n);
    // Parts pointing at the XML (Micro-Manager), and parts holding the XML too (Bio-Formats).
    let styles: [(&str, &dyn Fn(u32) -> String); 2] = [
        ("binary-only parts", &binary_only),
        ("XML in every part", &xml_again),
    ];
    for (style, part) in styles {
        let dir = tempfile::tempdir().unwrap();
        let volumes = write_multi_file_ome(dir.path(), &xml, part);
        let holder = dir.path().join("acq.ome.tif");
        assert_eq!(
            tiff_pages_and_channels(&holder).unwrap(),
            (22, 2),
            "{style}"
        );
        let e = read_volume(&holder, None).unwrap_err();
        assert!(
            matches!(e, ReadError::Channels { channels: 2, .. }),
            "{style}: {e}"
        );
        let listing = SourceListing::list(&holder, None).unwrap();
        let names: Vec<&str> = listing.files.iter().map(|(n, _, _)| n.as_str()).collect();
        assert_eq!(
            names,
            ["acq.ome.tif", "acq_1.ome.tif", "acq_2.ome.tif"],
            "{style}"
        );
        let bundle = SourceFiles::gather(&holder, None).unwrap();
        let prefix = dir.path().join("tifffile");
        let tifffile_read =
            run_tifffile(dir.path(), TIFFFILE_MULTI_FILE_READER, &[&holder, &prefix]).map(|()| {
                (0..2)
                    .map(|c| {
                        read_f64(&dir.path().join(format!("tifffile_c{c}.f64")))
                            .into_iter()
                            .map(|v| v as f32)
                            .collect::<Vec<f32>>()
                    })
                    .collect::<Vec<_>>()
            });
        for (c, volume) in volumes.iter().enumerate() {
            let want: Vec<f32> = volume.iter().map(|v| f32::from(*v)).collect();
            if let Some(read) = &tifffile_read {
                assert_eq!(read[c], want, "{style}: tifffile's channel {c}");
            }
            let whole = read_volume_channel(&holder, None, Some(c))
                .unwrap_or_else(|e| panic!("{style}: {e}"));
            assert_eq!(whole.dims(), DIMS, "{style}");
            assert_eq!(whole.channel(0), &want[..], "{style}: channel {c}");
            assert_eq!(whole.spacing(), [0.5e-3, 0.5e-3, 2e-3], "{style}");
            let bundled = decode_source_channel(&bundle, None, Some(c)).unwrap();
            assert_eq!(bundled, whole, "{style}: channel {c} from a bundle");
            let r = RegionReader::open_channel(&holder, None, Some(c)).unwrap();
            assert_eq!(r.dims(), DIMS, "{style}");
            // Slices 6 to 9 of channel 1 lie in all three files.
            let (o, size) = ([3, 5, 6], [20, 9, 4]);
            let part = r.read_region(o, size).unwrap();
            for (x, y, z) in [(0, 0, 0), (19, 8, 3), (7, 2, 1), (11, 4, 2)] {
                assert_eq!(
                    part.channel(0)[part.index(x, y, z)],
                    want[whole.index(x + o[0], y + o[1], z + o[2])],
                    "{style}: channel {c} region"
                );
            }
        }
        // A part alone: refused, naming the file the dataset is read from.
        for name in ["acq_1.ome.tif", "acq_2.ome.tif"] {
            let path = dir.path().join(name);
            assert_eq!(
                tiff_dataset(&path).unwrap(),
                TiffDataset::PartOf(holder.clone())
            );
            let e = read_volume_channel(&path, None, Some(0))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("part of a multi-file OME-TIFF") && e.contains("acq.ome.tif"),
                "{style}: {e}"
            );
            assert!(RegionReader::open_channel(&path, None, Some(0)).is_err());
        }
        let parts = ["acq_1.ome.tif", "acq_2.ome.tif"].map(|n| dir.path().join(n));
        assert_eq!(
            tiff_dataset(&holder).unwrap(),
            TiffDataset::Holds(parts.to_vec())
        );
        // The directory of the dataset's files is the dataset, read from its holder.
        let v = read_volume_channel(dir.path(), None, Some(1)).unwrap();
        let want: Vec<f32> = volumes[1].iter().map(|v| f32::from(*v)).collect();
        assert_eq!(v.channel(0), &want[..], "{style}: the directory");
        // A part missing: refused, naming it.
        std::fs::remove_file(dir.path().join("acq_2.ome.tif")).unwrap();
        let e = read_volume_channel(&holder, None, Some(0))
            .unwrap_err()
            .to_string();
        assert!(e.contains("acq_2.ome.tif"), "{style}: {e}");
    }
    // XML that does not place every plane once, in a page a file of the directory holds.
    for (extra, says) in [
        (
            r#"<TiffData FirstZ="3" FirstC="0" IFD="0"><UUID FileName="acq_2.ome.tif">u</UUID></TiffData>"#,
            "places plane 3 twice",
        ),
        (
            r#"<TiffData FirstZ="0" FirstC="2" IFD="0"><UUID FileName="acq_1.ome.tif">u</UUID></TiffData>"#,
            "places a plane at C 2 of 2",
        ),
        (
            r#"<TiffData FirstZ="0" FirstC="0" IFD="0" PlaneCount="18446744073709551615"><UUID FileName="acq_1.ome.tif">u</UUID></TiffData>"#,
            "twice",
        ),
        (
            r#"<TiffData FirstZ="0" FirstC="0" IFD="0"><UUID FileName="../acq_1.ome.tif">u</UUID></TiffData>"#,
            "supported are TIFF files beside it",
        ),
        (
            r#"<TiffData FirstZ="0" FirstC="1" IFD="0"><UUID FileName=".env">u</UUID></TiffData>"#,
            "supported are TIFF files beside it",
        ),
        // Placements not read (a count that is no number): the file read alone, whose planes
        // do not add up to its description's.
        (
            r#"<TiffData FirstZ="0" FirstC="0" IFD="x"><UUID FileName="acq_1.ome.tif">u</UUID></TiffData>"#,
            "do not add up",
        ),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let xml = multi_file_ome_xml(extra, 1);
        write_multi_file_ome(dir.path(), &xml, &binary_only);
        let holder = dir.path().join("acq.ome.tif");
        let e = read_volume_channel(&holder, None, Some(0))
            .unwrap_err()
            .to_string();
        assert!(e.contains(says), "{says}: {e}");
        assert!(tiff_pages_and_channels(&holder).is_err(), "{says}");
        // Nothing the XML names beyond what it may is listed (or uploaded).
        let listed = SourceListing::list(&holder, None).unwrap().files.len();
        assert!(
            listed == 3 || (listed == 1 && !says.contains("twice")),
            "{says}"
        );
    }
    // A page a file does not hold, planes past the count, and planes placed nowhere.
    let dir = tempfile::tempdir().unwrap();
    let xml = multi_file_ome_xml("", 1).replace(r#"IFD="3">"#, r#"IFD="4">"#);
    write_multi_file_ome(dir.path(), &xml, &binary_only);
    let e = read_volume_channel(&dir.path().join("acq.ome.tif"), None, Some(1))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("places plane 21 in page 4 of acq_2.ome.tif"),
        "{e}"
    );
    let xml = multi_file_ome_xml("", 1).replace(r#"IFD="3">"#, r#"IFD="3" PlaneCount="2">"#);
    write_multi_file_ome(dir.path(), &xml, &binary_only);
    let e = read_volume_channel(&dir.path().join("acq.ome.tif"), None, Some(1))
        .unwrap_err()
        .to_string();
    assert!(e.contains("places planes past the 22"), "{e}");
    let xml = multi_file_ome_xml("", 1).replace(r#"PlaneCount="9">"#, r#"PlaneCount="8">"#);
    write_multi_file_ome(dir.path(), &xml, &binary_only);
    let e = read_volume_channel(&dir.path().join("acq.ome.tif"), None, Some(1))
        .unwrap_err()
        .to_string();
    assert!(e.contains("places plane 8 of 22 nowhere"), "{e}");
    // The XML in an OME companion file beside the TIFFs, each a `BinaryOnly` pointer to it.
    let dir = tempfile::tempdir().unwrap();
    let pointer = |_: u32| {
        r#"<OME><BinaryOnly MetadataFile="set.companion.ome" UUID="urn:uuid:0"/></OME>"#.to_string()
    };
    // The last part's own pointer is one no reader takes alone (a path): it is not read here.
    let part_pointer = |n: u32| match n {
        3 => r#"<OME><BinaryOnly MetadataFile="./set.companion.ome"/></OME>"#.to_string(),
        _ => pointer(n),
    };
    let volumes = write_multi_file_ome(dir.path(), &pointer(1), &part_pointer);
    let companion = dir.path().join("set.companion.ome");
    std::fs::write(&companion, multi_file_ome_xml("", 0)).unwrap();
    assert_eq!(tiff_pages_and_channels(&companion).unwrap(), (22, 2));
    let files = ["acq.ome.tif", "acq_1.ome.tif", "acq_2.ome.tif"].map(|n| dir.path().join(n));
    assert_eq!(
        tiff_dataset(&companion).unwrap(),
        TiffDataset::Holds(files.to_vec())
    );
    let listing = SourceListing::list(&companion, None).unwrap();
    assert_eq!(listing.files.len(), 4);
    assert_eq!(listing.format, Some(Format::Tiff));
    let bundle = SourceFiles::gather(&companion, None).unwrap();
    for (c, volume) in volumes.iter().enumerate() {
        let want: Vec<f32> = volume.iter().map(|v| f32::from(*v)).collect();
        let whole = read_volume_channel(&companion, None, Some(c)).unwrap();
        assert_eq!(whole.channel(0), &want[..], "companion: channel {c}");
        assert_eq!(whole.spacing(), [0.5e-3, 0.5e-3, 2e-3]);
        let bundled = decode_source_channel(&bundle, None, Some(c)).unwrap();
        assert_eq!(bundled, whole, "companion: channel {c} from a bundle");
        let r = RegionReader::open_channel(&companion, None, Some(c)).unwrap();
        let part = r.read_region([3, 5, 6], [20, 9, 4]).unwrap();
        assert_eq!(
            part.channel(0)[part.index(19, 8, 3)],
            want[whole.index(22, 13, 9)],
            "companion: channel {c} region"
        );
    }
    // Uploaded as a bundle and unpacked (as a worker reads a bricked job's upload): read from
    // the companion file, by regions.
    let unpacked = tempfile::tempdir().unwrap();
    let bytes = bundle.to_bytes();
    let u = wavesplat_compressor::reader::unpack_bundle(&mut bytes.as_slice(), unpacked.path())
        .unwrap();
    assert_eq!(u.primary, unpacked.path().join("set.companion.ome"));
    let r = RegionReader::open_channel(&u.primary, None, Some(1)).unwrap();
    let whole = read_volume_channel(&companion, None, Some(1)).unwrap();
    assert_eq!(r.read_region([0; 3], DIMS).unwrap(), whole);
    assert_eq!(
        tiff_dataset(&files[0]).unwrap(),
        TiffDataset::PartOf(companion.clone())
    );
    let e = read_volume_channel(&files[2], None, Some(0))
        .unwrap_err()
        .to_string();
    assert!(e.contains("supported are files beside it"), "{e}");
    let e = read_volume_channel(&files[0], None, Some(0))
        .unwrap_err()
        .to_string();
    assert!(e.contains("read from set.companion.ome"), "{e}");
    // A one-file OME-TIFF renamed since it was written: its XML names the file by its old name
    // and its UUID, which is the file's own: it is read.
    let data = samples(DIMS, 1000.0, |v| (v as u16).min(1000));
    let renamed = |root_uuid: &str| {
        let xml = format!(
            r#"<OME{root_uuid}><Image ID="Image:0"><Pixels DimensionOrder="XYZCT" SizeX="37" SizeY="29" SizeZ="11" SizeC="1" SizeT="1"><TiffData IFD="0" PlaneCount="11"><UUID FileName="old.ome.tif">urn:uuid:7</UUID></TiffData></Pixels></Image></OME>"#
        );
        let path = dir.path().join("renamed.ome.tif");
        multipage::<colortype::Gray16>(&path, Compression::Uncompressed, &data, 1, Some(&xml));
        path
    };
    let path = renamed(r#" UUID="urn:uuid:7""#);
    let v = read_volume(&path, None).unwrap();
    let want: Vec<f32> = data.iter().map(|v| f32::from(*v)).collect();
    assert_eq!(v.channel(0), &want[..]);
    assert_eq!(SourceListing::list(&path, None).unwrap().files.len(), 1);
    // Without its own UUID too: the XML names one file for all its planes, this one.
    let v = read_volume(&renamed(""), None).unwrap();
    assert_eq!(v.channel(0), &want[..]);
}
