//! Writes the seed corpora of the fuzz targets (`fuzz/corpus/TARGET/`) and the sample files the
//! packet targets decode against (`fuzz/corpus/headers/CODER.wsp`): small phantoms compressed
//! with each coder, their packets, raw and NIfTI volumes, DICOM, NRRD and MetaImage volumes (the
//! [`SourceFiles::to_bytes`] of each: one file, or a bundle of a header and its data file or of
//! a series' slices), Zarr stores (bundles of their files), and one message of every gRPC
//! request.
//! The corpora are kept in the repository; rerun this only to reseed.
//!
//! `cargo run --example fuzz_seeds`

use prost::Message;
use std::path::Path;
use wavesplat_codec::format::{parse_file, CoderKind};
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_compressor::reader::{Format, SourceFiles};
use wavesplat_fixtures::{self as fixtures, DicomEncoding, DicomOptions, Layout, NrrdEncoding};
use wavesplat_proto::pb;

fn put(dir: &Path, name: &str, bytes: &[u8]) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(dir.join(name), bytes).unwrap();
}

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus");
    for (coder, name) in [
        (CoderKind::Sigmap, "sigmap"),
        (CoderKind::Fast, "fast"),
        (CoderKind::Range, "range"),
        (CoderKind::Huffman, "huffman"),
    ] {
        let vol = Phantom::SheppLogan.generate([12, 10, 8]);
        let bytes = compress(
            &vol,
            &CompressOptions {
                coder,
                target: Target::Fraction(0.2),
                tile: TileChoice::Size(8),
                layers: Some(2),
                levels: Some(2),
                refine: None,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes;
        put(&root.join("headers"), &format!("{name}.wsp"), &bytes);
        put(&root.join("file"), &format!("{name}.wsp"), &bytes);
        let f = parse_file(&bytes).unwrap();
        for (i, p) in f.packets.iter().enumerate().take(4) {
            put(&root.join(format!("packet_{name}")), &format!("p{i}"), p);
        }
    }
    // The fast coder's packets of earlier versions for the file target: prefix-coded (format
    // version 13; version 14 codes them by rANS) and by rANS before the occupancy contexts
    // (version 14; version 15 has them).
    let vol = Phantom::SheppLogan.generate([12, 10, 8]);
    let fast_file = |format_version: u16| {
        compress(
            &vol,
            &CompressOptions {
                coder: CoderKind::Fast,
                target: Target::Fraction(0.2),
                tile: TileChoice::Size(8),
                layers: Some(2),
                levels: Some(2),
                refine: None,
                format_version,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes
    };
    use wavesplat_codec::format::{COMPACT_HEADER_VERSION, RANS_VERSION};
    put(
        &root.join("file"),
        "fast-prefix-coded.wsp",
        &fast_file(COMPACT_HEADER_VERSION),
    );
    put(
        &root.join("file"),
        "fast-rans-v14.wsp",
        &fast_file(RANS_VERSION),
    );
    // A bricked container and a time series (format versions 9 and 10) for the file target,
    // and published series.
    let small = CompressOptions {
        target: Target::Fraction(0.2),
        refine: None,
        ..Default::default()
    };
    let vol = Phantom::SheppLogan.generate([16, 12, 10]);
    let bricked =
        wavesplat_compressor::bricked::compress_bricked(&vol, &small, 8, &|_| {}).unwrap();
    put(&root.join("file"), "bricked.wsp", &bricked.bytes);
    // The same bricks in the explicit manifest (format version 9, each brick's box and bytes
    // listed), and both published (the indexed layout's versions 2 and, for a plain file, 1).
    let parsed = wavesplat_codec::format::bricked::parse_bricked(&bricked.bytes).unwrap();
    let bricks: Vec<&[u8]> = (0..parsed.manifest.bricks.len())
        .map(|i| parsed.brick_bytes(i).unwrap())
        .collect();
    let mut explicit = parsed.manifest.clone();
    explicit.version = wavesplat_codec::format::bricked::EXPLICIT_BRICKED_VERSION;
    let explicit = wavesplat_codec::format::bricked::write_bricked(&mut explicit, &bricks).unwrap();
    put(&root.join("file"), "bricked-explicit.wsp", &explicit);
    let index = wavesplat_codec::format::index::indexed_layout;
    put(
        &root.join("file"),
        "bricked.wspx",
        &index(&bricked.bytes).unwrap(),
    );
    put(&root.join("file"), "plain.wspx", &index(bricks[0]).unwrap());
    let points = (0..3)
        .map(|t| wavesplat_compressor::phantom::beating([10, 8, 6], t, 3).unwrap())
        .collect();
    let series = wavesplat_compressor::series::VolumeSeries::new(points, None).unwrap();
    let series =
        wavesplat_compressor::series::compress_series(&series, &small, 2, 256, &|_| {}).unwrap();
    put(&root.join("file"), "series.wsp", &series.bytes);
    // Published (the indexed layout's version 3): a series of plain and of bricked components.
    put(
        &root.join("file"),
        "plain-series.wspx",
        &index(&series.bytes).unwrap(),
    );
    let points = (0..2)
        .map(|t| wavesplat_compressor::phantom::beating([12, 10, 8], t, 2).unwrap())
        .collect();
    let series = wavesplat_compressor::series::VolumeSeries::new(points, None).unwrap();
    let series =
        wavesplat_compressor::series::compress_series(&series, &small, 2, 8, &|_| {}).unwrap();
    put(
        &root.join("file"),
        "series.wspx",
        &index(&series.bytes).unwrap(),
    );
    let mut raw = vec![7u8, 5, 3, 1, 0, 0, 0, 0];
    raw.extend((0..8 * 6 * 4 * 2).map(|i| (i * 37 % 251) as u8));
    put(&root.join("raw"), "u16", &raw);
    // A minimal NIfTI-1 file: 348-byte header, 4 bytes of extension flag, 2x2x2 u8 samples.
    let mut nii = vec![0u8; 352];
    nii[0..4].copy_from_slice(&348i32.to_le_bytes());
    for (i, d) in [3i16, 2, 2, 2, 1, 1, 1, 1].iter().enumerate() {
        nii[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
    }
    nii[70..72].copy_from_slice(&2i16.to_le_bytes()); // datatype: u8
    nii[72..74].copy_from_slice(&8i16.to_le_bytes()); // bitpix
    for (i, p) in [1f32, 1.0, 1.0, 1.0].iter().enumerate() {
        nii[76 + 4 * i..80 + 4 * i].copy_from_slice(&p.to_le_bytes());
    }
    nii[108..112].copy_from_slice(&352f32.to_le_bytes()); // vox_offset
    nii[344..348].copy_from_slice(b"n+1\0");
    nii.extend([1u8, 2, 3, 4, 5, 6, 7, 8]);
    put(&root.join("nifti"), "tiny.nii", &nii);
    let grpc = root.join("grpc");
    let view = pb::ViewSpec {
        alpha: 0.3,
        beta: 0.2,
        width: 64,
        height: 64,
        ..Default::default()
    };
    let volume = Some(pb::VolumeRef {
        key: Some(pb::volume_ref::Key::Name("head".into())),
    });
    put(
        &grpc,
        "refine_start",
        &pb::RefineRequest {
            msg: Some(pb::refine_request::Msg::Start(pb::RefineStart {
                volume: volume.clone(),
                view: Some(view),
                have: vec![1, 2, 3],
                have_header: true,
                credit_bytes: 1 << 16,
                visible_only: true,
            })),
        }
        .encode_to_vec(),
    );
    put(
        &grpc,
        "ingest_start",
        &pb::IngestRequest {
            msg: Some(pb::ingest_request::Msg::Start(pb::IngestStart {
                name: "head".into(),
                total_size: 1000,
                sha256: vec![1; 32],
            })),
        }
        .encode_to_vec(),
    );
    put(
        &grpc,
        "describe",
        &pb::DescribeRequest { volume }.encode_to_vec(),
    );
    put(
        &grpc,
        "submit_spec",
        &pb::SubmitRequest {
            msg: Some(pb::submit_request::Msg::Spec(pb::JobSpec {
                name: "ct/head".into(),
                source: Some(pb::job_spec::Source::Path("/data/ct/head.nii".into())),
                sha256: vec![2; 32],
                raw: Some(pb::RawLayout {
                    dims: vec![4, 4, 4],
                    dtype: "u16".into(),
                    big_endian: true,
                    channels: 1,
                }),
                options: Some(pb::CompressOptions {
                    family: "cubic".into(),
                    ..Default::default()
                }),
                part: None,
                channel: None,
            })),
        }
        .encode_to_vec(),
    );
    put(
        &grpc,
        "finish",
        &pb::FinishRequest {
            job_id: 3,
            attempt: 1,
            worker: "w".into(),
            outcome: Some(pb::finish_request::Outcome::Delivered(pb::Delivered {
                cache_volume_id: 9,
                output_bytes: 100,
                voxels: 64,
                existed: false,
                sha256: "ab".repeat(32),
            })),
        }
        .encode_to_vec(),
    );
    readers(&root);
    println!("seeds written under {}", root.display());
}

/// Small volumes in every layout and encoding the DICOM, NRRD and MetaImage readers take.
fn readers(root: &Path) {
    let tmp = tempfile::tempdir().unwrap();
    let vol = |dims: [usize; 3], scale: f32| {
        let n: usize = dims.iter().product();
        wavesplat_codec::volume::Volume::new(
            dims,
            [0.5, 0.75, 2.0],
            vec![(0..n).map(|i| ((i * 37) % 101) as f32 * scale).collect()],
        )
        .unwrap()
    };
    let v = vol([4, 3, 2], 1.0);
    let seed = |target: &str, name: &str, path: &Path, format: Format| {
        let src = SourceFiles::gather(path, Some(format)).unwrap();
        put(&root.join(target), name, &src.to_bytes());
    };
    for (name, layout, enc, detached) in [
        ("raw_u8", Layout::U8, NrrdEncoding::Raw, false),
        ("gzip_i16", Layout::I16, NrrdEncoding::Gzip, false),
        ("ascii_f32", Layout::F32, NrrdEncoding::Ascii, false),
        ("detached_u16", Layout::U16, NrrdEncoding::Raw, true),
        ("detached_gzip", Layout::I8, NrrdEncoding::Gzip, true),
    ] {
        let p = fixtures::write_nrrd(tmp.path(), name, &v, layout, enc, detached, "RAS");
        seed("nrrd", name, &p, Format::Nrrd);
    }
    // Samples cut into files: a list of slices (each after a skipped line and bytes), a
    // pattern of gzip slices, a MetaImage list of rows and a pattern of zlib slices.
    // Every reader seed is a volume of 4 × 3 × 2 samples.
    let slices: Vec<Vec<u8>> = (0..2u8)
        .map(|z| (0..12u8).map(|b| b ^ (z * 7)).collect())
        .collect();
    let gz = |b: &[u8]| {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        std::io::Write::write_all(&mut e, b).unwrap();
        e.finish().unwrap()
    };
    let zl = |b: &[u8]| {
        let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        std::io::Write::write_all(&mut e, b).unwrap();
        e.finish().unwrap()
    };
    for (z, s) in slices.iter().enumerate() {
        std::fs::write(
            tmp.path().join(format!("ls{z}.raw")),
            [b"#\nxy".to_vec(), s.clone()].concat(),
        )
        .unwrap();
        std::fs::write(tmp.path().join(format!("gs{z}.raw.gz")), gz(s)).unwrap();
        std::fs::write(tmp.path().join(format!("zs{z}.raw")), zl(s)).unwrap();
        for (y, row) in s.chunks(4).enumerate() {
            std::fs::write(tmp.path().join(format!("mr{z}_{y}.raw")), row).unwrap();
        }
    }
    let nrrd_head = "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 3 2\n";
    for (name, text) in [
        ("list_skips", format!("{nrrd_head}encoding: raw\nline skip: 1\nbyte skip: 2\ndata file: LIST\nls0.raw\nls1.raw\n")),
        ("pattern_gzip", format!("{nrrd_head}encoding: gzip\ndata file: gs%d.raw.gz 0 1 1\n")),
    ] {
        let p = tmp.path().join(format!("{name}.nhdr"));
        std::fs::write(&p, text).unwrap();
        seed("nrrd", name, &p, Format::Nrrd);
    }
    let mha_head = "ObjectType = Image\nNDims = 3\nDimSize = 4 3 2\nElementType = MET_UCHAR\n";
    let rows: Vec<String> = (0..2)
        .flat_map(|z| (0..3).map(move |y| format!("mr{z}_{y}.raw")))
        .collect();
    for (name, text) in [
        (
            "list_rows",
            format!("{mha_head}ElementDataFile = LIST 1D\n{}\n", rows.join("\n")),
        ),
        (
            "pattern_zlib",
            format!("{mha_head}CompressedData = True\nElementDataFile = zs%d.raw 0 1 1\n"),
        ),
    ] {
        let p = tmp.path().join(format!("{name}.mhd"));
        std::fs::write(&p, text).unwrap();
        seed("metaimage", name, &p, Format::MetaImage);
    }
    for (name, layout, lzw, per_slice) in [
        ("multipage_u16", Layout::U16, false, false),
        ("multipage_lzw_i16", Layout::I16, true, false),
        ("multipage_f32", Layout::F32, false, false),
        ("slices_lzw_u8", Layout::U8, true, true),
    ] {
        let p = fixtures::write_tiff_stack(tmp.path(), name, &v, layout, lzw, per_slice);
        seed("tiff", name, &p, Format::Tiff);
    }
    // An ImageJ hyperstack of two channels (planes channel fastest): a channel is read as
    // chosen.
    {
        use tiff::encoder::{colortype::Gray16, TiffEncoder};
        let [nx, ny, nz] = v.dims();
        let p = tmp.path().join("hyperstack_channels.tif");
        let mut e = TiffEncoder::new(std::fs::File::create(&p).unwrap()).unwrap();
        for z in 0..nz {
            for c in 0..2u16 {
                let mut image = e.new_image::<Gray16>(nx as u32, ny as u32).unwrap();
                if z == 0 && c == 0 {
                    let desc = format!(
                        "ImageJ=1.54f\nimages={}\nchannels=2\nslices={nz}\nhyperstack=true\n",
                        2 * nz
                    );
                    let tag = tiff::tags::Tag::ImageDescription;
                    image.encoder().write_tag(tag, desc.as_str()).unwrap();
                }
                let plane: Vec<u16> = v.channel(0)[z * nx * ny..(z + 1) * nx * ny]
                    .iter()
                    .map(|s| (s * 100.0) as u16 + 500 * c)
                    .collect();
                image.write_data(&plane).unwrap();
            }
        }
        drop(e);
        seed("tiff", "hyperstack_channels", &p, Format::Tiff);
    }
    // A multi-file OME-TIFF of two channels, a file each, the first's XML placing both (a
    // bundle of the two files).
    {
        use tiff::encoder::{colortype::Gray16, TiffEncoder};
        let [nx, ny, nz] = v.dims();
        let dir = tmp.path().join("ome_multi_file");
        std::fs::create_dir_all(&dir).unwrap();
        let xml = format!(
            r#"<OME><Image ID="Image:0"><Pixels DimensionOrder="XYZCT" SizeX="{nx}" SizeY="{ny}" SizeZ="{nz}" SizeC="2" SizeT="1"><TiffData IFD="0" PlaneCount="{nz}"><UUID FileName="a.ome.tif">urn:uuid:a</UUID></TiffData><TiffData FirstC="1" IFD="0" PlaneCount="{nz}"><UUID FileName="b.ome.tif">urn:uuid:b</UUID></TiffData></Pixels></Image></OME>"#
        );
        for (c, name) in [(0u16, "a.ome.tif"), (1, "b.ome.tif")] {
            let f = std::fs::File::create(dir.join(name)).unwrap();
            let mut e = TiffEncoder::new(f).unwrap();
            for z in 0..nz {
                let mut image = e.new_image::<Gray16>(nx as u32, ny as u32).unwrap();
                if z == 0 && c == 0 {
                    let tag = tiff::tags::Tag::ImageDescription;
                    image.encoder().write_tag(tag, xml.as_str()).unwrap();
                }
                let plane: Vec<u16> = v.channel(0)[z * nx * ny..(z + 1) * nx * ny]
                    .iter()
                    .map(|s| (s * 100.0) as u16 + 500 * c)
                    .collect();
                image.write_data(&plane).unwrap();
            }
        }
        seed(
            "tiff",
            "ome_multi_file",
            &dir.join("a.ome.tif"),
            Format::Tiff,
        );
        // The same planes placed by an OME companion file (a bundle of it and both files).
        let companion = dir.join("set.companion.ome");
        std::fs::write(
            &companion,
            xml.replace("<OME>", r#"<OME UUID="urn:uuid:c">"#),
        )
        .unwrap();
        seed("tiff", "ome_companion", &companion, Format::Tiff);
    }
    for (name, layout, compressed, detached) in [
        ("mha_u8", Layout::U8, false, false),
        ("mha_zlib_i16", Layout::I16, true, false),
        ("mhd_f32", Layout::F32, false, true),
        ("mhd_zlib_u16", Layout::U16, true, true),
    ] {
        let p = fixtures::write_metaimage(tmp.path(), name, &v, layout, compressed, detached);
        seed("metaimage", name, &p, Format::MetaImage);
    }
    for (name, layout, encoding, multiframe) in [
        (
            "series_i16",
            Layout::I16,
            DicomEncoding::ExplicitLittle,
            false,
        ),
        (
            "series_u8_implicit",
            Layout::U8,
            DicomEncoding::ImplicitLittle,
            false,
        ),
        ("series_rle", Layout::U16, DicomEncoding::RleLossless, false),
        (
            "multiframe_i16",
            Layout::I16,
            DicomEncoding::ExplicitLittle,
            true,
        ),
        (
            "multiframe_rle",
            Layout::I8,
            DicomEncoding::RleLossless,
            true,
        ),
    ] {
        let o = DicomOptions {
            layout,
            encoding,
            intercept: -10.0,
            ..DicomOptions::default()
        };
        let v = vol([4, 3, 2], 1.0);
        let dir = tmp.path().join(name);
        let p = if multiframe {
            std::fs::create_dir_all(&dir).unwrap();
            fixtures::write_dicom_multiframe(&dir.join("mf.dcm"), &v, &o)
        } else {
            fixtures::write_dicom_series(&dir, &v, &o);
            dir
        };
        seed("dicom", name, &p, Format::Dicom);
    }
    hostile(root, &tmp.path().join("series_i16"));
    zarr(root);
}

/// Zarr stores of the readers' 4 × 3 × 2 volume (u16 samples, written by hand from the
/// specifications): v2 uncompressed, gzip, zlib and Blosc (a copied buffer) chunks, v3 Zstd
/// chunks with a CRC-32C, a v3 shard of Zstd inner chunks, an OME-Zarr image; and the hostile
/// chunks of the reader's test (`oom_*`), which zarrs decoded past a chunk's size before the
/// reader checked them.
fn zarr(root: &Path) {
    use std::io::Write;
    let tmp = tempfile::tempdir().unwrap();
    // z, y, x = 2, 3, 4; the sample at (z, y, x) is i = (z·3 + y)·4 + x.
    let value = |i: usize| ((i * 37) % 101) as u16;
    let chunk_bytes = |shape: [usize; 3], at: [usize; 3]| -> Vec<u8> {
        let mut out = Vec::new();
        for z in 0..shape[0] {
            for y in 0..shape[1] {
                for x in 0..shape[2] {
                    let (z, y, x) = (at[0] + z, at[1] + y, at[2] + x);
                    // Past the array's edge a chunk still holds samples, never read.
                    let v = if z < 2 && y < 3 && x < 4 {
                        value((z * 3 + y) * 4 + x)
                    } else {
                        0
                    };
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        out
    };
    let gzip = |b: &[u8]| {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        e.write_all(b).unwrap();
        e.finish().unwrap()
    };
    let zlib = |b: &[u8]| {
        let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        e.write_all(b).unwrap();
        e.finish().unwrap()
    };
    // Blosc's header (version 2, codec version 1, flags: copied, type size 2; decoded, block
    // and compressed bytes), then the bytes themselves.
    let blosc = |b: &[u8]| {
        let mut out = vec![2u8, 1, 0x02, 2];
        for n in [b.len(), b.len(), b.len() + 16] {
            out.extend_from_slice(&(n as u32).to_le_bytes());
        }
        out.extend_from_slice(b);
        out
    };
    let with_crc = |b: Vec<u8>| {
        let c = crc32c::crc32c(&b);
        [b, c.to_le_bytes().to_vec()].concat()
    };
    let write = |dir: &Path, files: &[(&str, Vec<u8>)]| {
        for (name, bytes) in files {
            let p = dir.join(name);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, bytes).unwrap();
        }
    };
    let seed = |name: &str, files: &[(&str, Vec<u8>)]| {
        let dir = tmp.path().join(name);
        write(&dir, files);
        let src = SourceFiles::gather(&dir, Some(Format::Zarr)).unwrap();
        put(&root.join("zarr"), name, &src.to_bytes());
    };
    let v2 = |chunks: [usize; 3], compressor: &str| {
        format!(
            r#"{{"zarr_format": 2, "shape": [2, 3, 4], "chunks": {chunks:?}, "dtype": "<u2",
                "compressor": {compressor}, "fill_value": 0, "order": "C", "filters": null}}"#
        )
        .into_bytes()
    };
    let v2_chunks = |chunks: [usize; 3], code: &dyn Fn(&[u8]) -> Vec<u8>| {
        let mut files = Vec::new();
        for cz in 0..2usize.div_ceil(chunks[0]) {
            for cy in 0..3usize.div_ceil(chunks[1]) {
                for cx in 0..4usize.div_ceil(chunks[2]) {
                    let at = [cz * chunks[0], cy * chunks[1], cx * chunks[2]];
                    files.push((format!("{cz}.{cy}.{cx}"), code(&chunk_bytes(chunks, at))));
                }
            }
        }
        files
    };
    for (name, chunks, compressor, code) in [
        (
            "v2_raw",
            [2, 3, 4],
            "null",
            &(|b: &[u8]| b.to_vec()) as &dyn Fn(&[u8]) -> Vec<u8>,
        ),
        ("v2_gzip", [1, 2, 3], r#"{"id": "gzip", "level": 1}"#, &gzip),
        ("v2_zlib", [2, 2, 2], r#"{"id": "zlib", "level": 1}"#, &zlib),
        (
            "v2_blosc",
            [1, 3, 4],
            r#"{"id": "blosc", "cname": "lz4", "clevel": 5, "shuffle": 0, "blocksize": 0}"#,
            &blosc,
        ),
    ] {
        let chunk_files = v2_chunks(chunks, code);
        let mut files: Vec<(&str, Vec<u8>)> = vec![(".zarray", v2(chunks, compressor))];
        files.extend(chunk_files.iter().map(|(n, b)| (n.as_str(), b.clone())));
        seed(name, &files);
    }
    let v3 = |chunk: &str, codecs: &str| {
        format!(
            r#"{{"zarr_format": 3, "node_type": "array", "shape": [2, 3, 4], "data_type": "uint16",
                "chunk_grid": {{"name": "regular", "configuration": {{"chunk_shape": {chunk}}}}},
                "chunk_key_encoding": {{"name": "default", "configuration": {{"separator": "/"}}}},
                "fill_value": 0, "codecs": {codecs}, "dimension_names": ["z", "y", "x"]}}"#
        )
        .into_bytes()
    };
    let zstd_codecs = r#"[{"name": "bytes", "configuration": {"endian": "little"}},
        {"name": "zstd", "configuration": {"level": 1, "checksum": false}}]"#;
    let zstd = |b: &[u8]| zstd::encode_all(b, 1).unwrap();
    // Zstd chunks followed by their CRC-32C; `checksum`: Zstd's own checksum in each frame.
    let checked_zstd = |checksum: bool| {
        format!(
            r#"[{{"name": "bytes", "configuration": {{"endian": "little"}}}},
                        {{"name": "zstd", "configuration": {{"level": 1, "checksum": {checksum}}}}},
                        {{"name": "crc32c"}}]"#
        )
    };
    seed(
        "v3_zstd_crc32c",
        &[
            ("zarr.json", v3("[2, 3, 4]", &checked_zstd(true))),
            ("c/0/0/0", with_crc(zstd(&chunk_bytes([2, 3, 4], [0; 3])))),
        ],
    );
    let shard_codecs = format!(
        r#"[{{"name": "sharding_indexed", "configuration": {{"chunk_shape": [1, 3, 2],
            "codecs": {zstd_codecs},
            "index_codecs": [{{"name": "bytes", "configuration": {{"endian": "little"}}}},
                {{"name": "crc32c"}}], "index_location": "end"}}}}]"#
    );
    let (mut shard, mut index) = (Vec::new(), Vec::new());
    for cz in 0..2 {
        for cx in 0..2 {
            let frame = zstd(&chunk_bytes([1, 3, 2], [cz, 0, 2 * cx]));
            index.extend_from_slice(&(shard.len() as u64).to_le_bytes());
            index.extend_from_slice(&(frame.len() as u64).to_le_bytes());
            shard.extend_from_slice(&frame);
        }
    }
    shard.extend(with_crc(index));
    seed(
        "v3_sharded",
        &[
            ("zarr.json", v3("[2, 3, 4]", &shard_codecs)),
            ("c/0/0/0", shard),
        ],
    );
    // Three channels (c, z, y, x), a Zstd chunk each: a channel is read as chosen.
    let channels = format!(
        r#"{{"zarr_format": 3, "node_type": "array", "shape": [3, 2, 3, 4], "data_type": "uint16",
            "chunk_grid": {{"name": "regular", "configuration": {{"chunk_shape": [1, 2, 3, 4]}}}},
            "chunk_key_encoding": {{"name": "default", "configuration": {{"separator": "/"}}}},
            "fill_value": 0, "codecs": {zstd_codecs}, "dimension_names": ["c", "z", "y", "x"]}}"#
    );
    let channel_chunks: Vec<(String, Vec<u8>)> = (0..3)
        .map(|c| {
            let samples: Vec<u8> = chunk_bytes([2, 3, 4], [0; 3])
                .chunks_exact(2)
                .flat_map(|v| (u16::from_le_bytes([v[0], v[1]]) + 200 * c).to_le_bytes())
                .collect();
            (format!("c/{c}/0/0/0"), zstd(&samples))
        })
        .collect();
    let mut files: Vec<(&str, Vec<u8>)> = vec![("zarr.json", channels.into_bytes())];
    files.extend(channel_chunks.iter().map(|(n, b)| (n.as_str(), b.clone())));
    seed("v3_channels", &files);
    let attrs = r#"{"multiscales": [{"version": "0.4", "axes": [
        {"name": "z", "type": "space", "unit": "millimeter"},
        {"name": "y", "type": "space", "unit": "micrometer"},
        {"name": "x", "type": "space"}],
        "datasets": [{"path": "0", "coordinateTransformations":
            [{"type": "scale", "scale": [2.0, 750.0, 0.5]}]}]}]}"#;
    seed(
        "ome_image",
        &[
            (".zgroup", br#"{"zarr_format": 2}"#.to_vec()),
            (".zattrs", attrs.as_bytes().to_vec()),
            ("0/.zarray", v2([2, 3, 4], "null")),
            ("0/0.0.0", chunk_bytes([2, 3, 4], [0; 3])),
        ],
    );
    // Hostile chunks: a Zstd frame declaring 1 TiB behind its CRC-32C, 4 MiB of zeros as gzip.
    let mut declared = vec![0x28, 0xb5, 0x2f, 0xfd, 0xe0];
    declared.extend_from_slice(&(1u64 << 40).to_le_bytes());
    declared.extend_from_slice(&[0x01, 0x00, 0x00]);
    seed(
        "oom_zstd_behind_crc32c",
        &[
            ("zarr.json", v3("[2, 3, 4]", &checked_zstd(false))),
            ("c/0/0/0", with_crc(declared)),
        ],
    );
    seed(
        "oom_gzip_bomb",
        &[
            (".zarray", v2([2, 3, 4], r#"{"id": "gzip", "level": 9}"#)),
            ("0.0.0", {
                let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
                e.write_all(&vec![0u8; 4 << 20]).unwrap();
                e.finish().unwrap()
            }),
        ],
    );
}

/// Small inputs whose headers declare far more than their bytes hold (`oom_*`: each made a
/// reader allocate hundreds of MiB or more before it was fixed); the stable replay checks
/// their heap against the targets' bound.
fn hostile(root: &Path, series: &Path) {
    use flate2::write::{GzEncoder, ZlibEncoder};
    use flate2::Compression;
    use std::io::Write;
    let deflate = |gzip: bool, n: usize| {
        let zeros = vec![0u8; n];
        if gzip {
            let mut e = GzEncoder::new(Vec::new(), Compression::best());
            e.write_all(&zeros).unwrap();
            e.finish().unwrap()
        } else {
            let mut e = ZlibEncoder::new(Vec::new(), Compression::best());
            e.write_all(&zeros).unwrap();
            e.finish().unwrap()
        }
    };
    // 1 GiB of u8 samples declared, 64 bytes of gzip present: the buffer reserved up front was
    // min(declared, 64 MiB).
    let mut nrrd =
        b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 1024 1024 1024\nencoding: gzip\n\n".to_vec();
    nrrd.extend(deflate(true, 64));
    put(&root.join("nrrd"), "oom_gzip_reserve", &nrrd);
    let mut mha = b"ObjectType = Image\nNDims = 3\nDimSize = 1024 1024 1024\nElementType = MET_UCHAR\nCompressedData = True\nElementDataFile = LOCAL\n"
        .to_vec();
    mha.extend(deflate(false, 64));
    put(&root.join("metaimage"), "oom_zlib_reserve", &mha);
    let mut nii = std::fs::read(root.join("nifti/tiny.nii")).unwrap();
    for d in 1..=3 {
        nii[40 + 2 * d..42 + 2 * d].copy_from_slice(&1024i16.to_le_bytes());
    }
    put(
        &root.join("nifti"),
        "oom_gzip_reserve",
        &deflate_gz_of(&nii),
    );
    // One slice re-declared as 46 340² 16-bit pixels (within the voxel limit): the series'
    // voxel buffer (8 GiB of f32) was allocated before the pixel data was checked.
    let first = std::fs::read_dir(series)
        .unwrap()
        .map(|e| e.unwrap().path())
        .min()
        .unwrap();
    let mut dcm = std::fs::read(first).unwrap();
    for element in [0x10u8, 0x11] {
        let tag = [0x28, 0x00, element, 0x00, b'U', b'S', 2, 0];
        let at = dcm.windows(8).position(|w| w == tag).unwrap() + 8;
        dcm[at..at + 2].copy_from_slice(&46340u16.to_le_bytes());
    }
    put(&root.join("dicom"), "oom_rows_columns", &dcm);
}

fn deflate_gz_of(bytes: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}
