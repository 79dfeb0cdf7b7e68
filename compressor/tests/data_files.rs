//! Volumes whose samples lie in several files: a detached NRRD or MetaImage header whose data
//! file is a `LIST` (the names on the header's lines after it) or a printf pattern, each file a
//! slice (or a row, with a file dimension) of the sample stream, with its own skipped lines and
//! bytes (`line skip`, `byte skip`, MetaImage `HeaderSize`) or its own gzip or zlib stream. Each
//! is read as the samples written through every path: decoding whole, region by region
//! (regions that cross files), the listing that hashes and uploads it, and a bundle decoded
//! elsewhere; and against SimpleITK (ITK's readers) where it is installed. Names that do not
//! match the sizes, a missing file and a short one are refused, naming what is wrong.

use std::io::Write;
use std::path::{Path, PathBuf};
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::reader::region::RegionReader;
use wavesplat_compressor::reader::{
    decode_source, read_volume, ReadError, SourceFiles, SourceListing,
};

const DIMS: [usize; 3] = [5, 4, 7];

/// The samples written: u16, x fastest, distinct and not monotone.
fn samples() -> Vec<u16> {
    let n = DIMS.iter().product::<usize>();
    (0..n).map(|i| ((i * 7919 + 13) % 65_521) as u16).collect()
}

fn le(values: &[u16]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// The bytes of slice `z` (or of row `(y, z)` when `rows`).
fn piece(values: &[u16], k: usize, rows: bool) -> Vec<u8> {
    let len = if rows { DIMS[0] } else { DIMS[0] * DIMS[1] };
    le(&values[k * len..(k + 1) * len])
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

fn zlib(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// One way of cutting the samples into files: how each file is written, the header's
/// data-file value and the names it lists.
struct Case {
    name: &'static str,
    header: PathBuf,
    /// The files, in the order their samples follow.
    files: Vec<String>,
}

/// Writes the data files of a case: `names[k]` holds piece `k` wrapped by `wrap`.
fn write_pieces(dir: &Path, names: &[String], rows: bool, wrap: impl Fn(Vec<u8>) -> Vec<u8>) {
    let values = samples();
    for (k, n) in names.iter().enumerate() {
        std::fs::write(dir.join(n), wrap(piece(&values, k, rows))).unwrap();
    }
}

fn nrrd_cases(dir: &Path) -> Vec<Case> {
    let nz = DIMS[2];
    let head = |fields: &str, data_file: &str| {
        format!(
            "NRRD0004\ntype: uint16\ndimension: 3\nsizes: {} {} {}\nendian: little\nspacings: 0.5 0.5 2\n{fields}data file: {data_file}\n",
            DIMS[0], DIMS[1], DIMS[2]
        )
    };
    let mut cases = Vec::new();
    let mut case = |name: &'static str, header: String, files: Vec<String>| {
        let p = dir.join(format!("{name}.nhdr"));
        std::fs::write(&p, header).unwrap();
        cases.push(Case {
            name,
            header: p,
            files,
        });
    };
    // A list of slices, names with spaces, each after two lines and three bytes of its own.
    let names: Vec<String> = (0..nz).map(|z| format!("list slice {z}.raw")).collect();
    write_pieces(dir, &names, false, |b| [b"a\nbb\nxyz".to_vec(), b].concat());
    case(
        "nrrd-list",
        head("encoding: raw\nline skip: 2\nbyte skip: 3\n", "LIST") + &names.join("\n") + "\n",
        names,
    );
    // A list of rows (each file of one dimension).
    let names: Vec<String> = (0..nz * DIMS[1]).map(|k| format!("row{k}.raw")).collect();
    write_pieces(dir, &names, true, |b| b);
    case(
        "nrrd-rows",
        head("encoding: raw\n", "LIST 1") + &names.join("\n") + "\n",
        names,
    );
    // A pattern counting down, each slice at the end of its file.
    let names: Vec<String> = (0..nz).map(|k| format!("down{:02}.raw", 9 - k)).collect();
    write_pieces(dir, &names, false, |b| [vec![7u8; 11], b].concat());
    case(
        "nrrd-pattern",
        head("encoding: raw\nbyte skip: -1\n", "down%02d.raw 9 3 -1"),
        names,
    );
    // A pattern of gzip files.
    let names: Vec<String> = (0..nz).map(|k| format!("g{}.raw.gz", 1 + 2 * k)).collect();
    write_pieces(dir, &names, false, |b| gzip(&b));
    case(
        "nrrd-gzip",
        head(
            "encoding: gzip\n",
            &format!("g%d.raw.gz 1 {} 2", 2 * nz - 1),
        ),
        names,
    );
    cases
}

fn metaimage_cases(dir: &Path) -> Vec<Case> {
    let nz = DIMS[2];
    let head = |fields: &str, data_file: &str| {
        format!(
            "ObjectType = Image\nNDims = 3\nDimSize = {} {} {}\nElementSpacing = 0.5 0.5 2\nElementType = MET_USHORT\n{fields}ElementDataFile = {data_file}\n",
            DIMS[0], DIMS[1], DIMS[2]
        )
    };
    let mut cases = Vec::new();
    let mut case = |name: &'static str, header: String, files: Vec<String>| {
        let p = dir.join(format!("{name}.mhd"));
        std::fs::write(&p, header).unwrap();
        cases.push(Case {
            name,
            header: p,
            files,
        });
    };
    // A list, each slice after a header of 6 bytes of its own.
    let names: Vec<String> = (0..nz).map(|z| format!("m slice {z}.raw")).collect();
    write_pieces(dir, &names, false, |b| [b"HEADER".to_vec(), b].concat());
    case(
        "mha-list",
        head("HeaderSize = 6\n", "LIST") + &names.join("\n") + "\n",
        names,
    );
    // A list of rows, each at the end of its file.
    let names: Vec<String> = (0..nz * DIMS[1]).map(|k| format!("mrow{k}.raw")).collect();
    write_pieces(dir, &names, true, |b| [vec![1u8; 3], b].concat());
    case(
        "mha-rows",
        head("HeaderSize = -1\n", "LIST 1D") + &names.join("\n") + "\n",
        names,
    );
    // A pattern.
    let names: Vec<String> = (0..nz).map(|k| format!("p{:03}.raw", k + 1)).collect();
    write_pieces(dir, &names, false, |b| b);
    case(
        "mha-pattern",
        head("", &format!("p%03d.raw 1 {nz} 1")),
        names,
    );
    // A list of zlib streams, one per file.
    let names: Vec<String> = (0..nz).map(|z| format!("z{z}.zraw")).collect();
    write_pieces(dir, &names, false, |b| zlib(&b));
    case(
        "mha-zlib",
        head("CompressedData = True\n", "LIST") + &names.join("\n") + "\n",
        names,
    );
    cases
}

/// The box `origin`, `size` of `v`'s one channel.
fn cut(v: &Volume, origin: [usize; 3], size: [usize; 3]) -> Vec<f32> {
    let mut out = Vec::new();
    for z in origin[2]..origin[2] + size[2] {
        for y in origin[1]..origin[1] + size[1] {
            let i = v.index(origin[0], y, z);
            out.extend_from_slice(&v.channel(0)[i..i + size[0]]);
        }
    }
    out
}

#[test]
fn samples_in_listed_or_patterned_files_read_as_written_through_every_path() {
    let dir = tempfile::tempdir().unwrap();
    let want: Vec<f32> = samples().iter().map(|v| f32::from(*v)).collect();
    let cases: Vec<Case> = nrrd_cases(dir.path())
        .into_iter()
        .chain(metaimage_cases(dir.path()))
        .collect();
    for c in &cases {
        let v = read_volume(&c.header, None).unwrap_or_else(|e| panic!("{}: {e}", c.name));
        assert_eq!(v.dims(), DIMS, "{}", c.name);
        assert_eq!(v.spacing(), [0.5, 0.5, 2.0], "{}", c.name);
        assert_eq!(v.channel(0), &want[..], "{}", c.name);

        // The listing names the header, then every data file in order.
        let listing = SourceListing::list(&c.header, None).unwrap();
        let names: Vec<&str> = listing.files.iter().map(|(n, _, _)| n.as_str()).collect();
        assert_eq!(names[1..], c.files, "{}", c.name);
        // Gathered and bundled, decoded elsewhere.
        let src = SourceFiles::gather(&c.header, None).unwrap();
        assert_eq!(src.files.len(), c.files.len() + 1, "{}", c.name);
        let back = SourceFiles::from_bytes(src.to_bytes(), Path::new("elsewhere/h")).unwrap();
        assert_eq!(decode_source(&back, None).unwrap(), v, "{}", c.name);

        // Regions: the whole, whole slabs, whole rows and a box, each crossing files.
        let r = RegionReader::open(&c.header, None).unwrap_or_else(|e| panic!("{}: {e}", c.name));
        assert_eq!(r.dims(), DIMS);
        assert_eq!(r.read_region([0; 3], DIMS).unwrap(), v, "{}", c.name);
        for (origin, size) in [
            ([0, 0, 2], [5, 4, 3]),
            ([0, 1, 1], [5, 2, 5]),
            ([1, 1, 0], [3, 3, 7]),
            ([4, 3, 6], [1, 1, 1]),
        ] {
            let region = r.read_region(origin, size).unwrap();
            assert_eq!(
                region.channel(0),
                &cut(&v, origin, size)[..],
                "{}: region {origin:?} {size:?}",
                c.name
            );
        }
    }
}

#[test]
fn data_files_that_do_not_match_the_header_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let cases: Vec<Case> = nrrd_cases(dir.path())
        .into_iter()
        .chain(metaimage_cases(dir.path()))
        .collect();
    let open_all = |h: &Path| {
        [
            read_volume(h, None).map(|_| ()),
            RegionReader::open(h, None).map(|_| ()),
        ]
    };
    for c in &cases {
        let text = std::fs::read_to_string(&c.header).unwrap();
        let ext = c.header.extension().unwrap().to_str().unwrap();
        // One name short (a list), or a pattern one file short.
        let short = if text.contains("LIST") {
            let last = c.files.last().unwrap();
            text.replace(&format!("{last}\n"), "")
        } else if c.name == "nrrd-pattern" {
            text.replace("9 3 -1", "9 4 -1")
        } else if c.name == "nrrd-gzip" {
            text.replace("1 13 2", "1 11 2")
        } else {
            text.replace("1 7 1", "1 6 1")
        };
        assert_ne!(short, text, "{}", c.name);
        let h = dir.path().join(format!("short-{}.{ext}", c.name));
        std::fs::write(&h, &short).unwrap();
        for e in open_all(&h) {
            let e = e.expect_err(c.name).to_string();
            assert!(e.contains("files named"), "{}: {e}", c.name);
        }
        // A data file missing.
        let gone = dir.path().join(&c.files[2]);
        let kept = std::fs::read(&gone).unwrap();
        std::fs::remove_file(&gone).unwrap();
        for e in open_all(&c.header) {
            let e = e.expect_err(c.name);
            assert!(matches!(e, ReadError::Io { .. }), "{}: {e}", c.name);
            assert!(e.to_string().contains(&c.files[2]), "{}: {e}", c.name);
        }
        assert!(SourceListing::list(&c.header, None).is_err(), "{}", c.name);
        // The same file cut short.
        std::fs::write(&gone, &kept[..3]).unwrap();
        for e in open_all(&c.header) {
            let e = e.expect_err(c.name);
            let message = e.to_string();
            assert!(message.contains(&c.files[2]), "{}: {message}", c.name);
        }
        std::fs::write(&gone, &kept).unwrap();
        assert!(read_volume(&c.header, None).is_ok(), "{}", c.name);
    }
}

/// SimpleITK (ITK's NRRD and MetaImage readers) reads each case to the same samples.
#[test]
fn simpleitk_reads_the_same_samples() {
    let Some(python) = wavesplat_fixtures::reference_python(
        "SimpleITK, numpy",
        "python3 -m pip install SimpleITK",
    ) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let want = le(&samples());
    for c in nrrd_cases(dir.path())
        .into_iter()
        .chain(metaimage_cases(dir.path()))
    {
        let out = dir.path().join(format!("{}.itk", c.name));
        let script = "import sys, SimpleITK as sitk, numpy as np\n\
                      a = sitk.GetArrayFromImage(sitk.ReadImage(sys.argv[1]))\n\
                      open(sys.argv[2], 'wb').write(a.astype('<u2').tobytes() + bytes(str(a.shape), 'ascii'))\n";
        let status = std::process::Command::new(python)
            .args(["-c", script])
            .arg(&c.header)
            .arg(&out)
            .status()
            .unwrap();
        assert!(status.success(), "{}: SimpleITK failed", c.name);
        let got = std::fs::read(&out).unwrap();
        let shape = format!("({}, {}, {})", DIMS[2], DIMS[1], DIMS[0]);
        assert_eq!(&got[want.len()..], shape.as_bytes(), "{}", c.name);
        assert_eq!(
            &got[..want.len()],
            &want[..],
            "{}: SimpleITK reads other samples",
            c.name
        );
        let ours = read_volume(&c.header, None).unwrap();
        let ours: Vec<u16> = ours.channel(0).iter().map(|v| *v as u16).collect();
        assert_eq!(le(&ours), want, "{}", c.name);
    }
}

/// A list of more files than a process may hold open (1 500 rows, each its own file) reads
/// region by region as written: the reader opens the files a region needs, a few at a time.
#[test]
fn a_list_of_thousands_of_files_reads_region_by_region() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [4usize, 300, 5];
    let n = dims.iter().product::<usize>();
    let values: Vec<u16> = (0..n).map(|i| (i * 31 % 60_001) as u16).collect();
    let rows = dims[1] * dims[2];
    let names: Vec<String> = (0..rows).map(|k| format!("r/{k:05}.raw")).collect();
    std::fs::create_dir(dir.path().join("r")).unwrap();
    for (k, name) in names.iter().enumerate() {
        let row = &values[k * dims[0]..(k + 1) * dims[0]];
        std::fs::write(dir.path().join(name), le(row)).unwrap();
    }
    let h = dir.path().join("rows.nhdr");
    std::fs::write(
        &h,
        format!(
            "NRRD0004\ntype: uint16\ndimension: 3\nsizes: {} {} {}\nendian: little\nencoding: raw\ndata file: LIST 1\n{}\n",
            dims[0],
            dims[1],
            dims[2],
            names.join("\n")
        ),
    )
    .unwrap();
    let want: Vec<f32> = values.iter().map(|v| f32::from(*v)).collect();
    let r = RegionReader::open(&h, None).unwrap();
    let whole = r.read_region([0; 3], dims).unwrap();
    assert_eq!(whole.channel(0), &want[..]);
    assert_eq!(read_volume(&h, None).unwrap(), whole);
    let part = r.read_region([1, 250, 3], [2, 50, 2]).unwrap();
    assert_eq!(part.channel(0), &cut(&whole, [1, 250, 3], [2, 50, 2])[..]);
}

/// A header that names itself as its data file (its `byte skip` counted from the file's start,
/// as for every other data file) is read alike whole and by region; a MetaImage list of names longer
/// than a header may be is refused alike by every path, not cut where one of them stops.
#[test]
fn every_path_reads_the_same_header() {
    let dir = tempfile::tempdir().unwrap();
    let values = samples();
    let h = dir.path().join("self.nhdr");
    // The samples just after the header: skipped to from the file's start.
    let header = |skip: usize| {
        format!(
            "NRRD0004\ntype: uint16\ndimension: 3\nsizes: {} {} {}\nendian: little\nencoding: raw\nbyte skip: {skip:06}\ndata file: self.nhdr\n\n",
            DIMS[0], DIMS[1], DIMS[2]
        )
    };
    let mut bytes = header(header(0).len()).into_bytes();
    bytes.extend(le(&values));
    std::fs::write(&h, bytes).unwrap();
    let v = read_volume(&h, None).unwrap();
    let want: Vec<f32> = values.iter().map(|v| f32::from(*v)).collect();
    assert_eq!(v.channel(0), &want[..]);
    let r = RegionReader::open(&h, None).unwrap();
    assert_eq!(r.read_region([0; 3], DIMS).unwrap(), v);

    // 40 000 names of 30 bytes: 1.2 MB after the header.
    let names: Vec<String> = (0..40_000)
        .map(|k| format!("slices/a-long-name-{k:07}.raw"))
        .collect();
    let h = dir.path().join("long.mhd");
    std::fs::write(
        &h,
        format!(
            "ObjectType = Image\nNDims = 3\nDimSize = 1 1 40000\nElementType = MET_UCHAR\nElementDataFile = LIST\n{}\n",
            names.join("\n")
        ),
    )
    .unwrap();
    let errors = [
        read_volume(&h, None).unwrap_err(),
        RegionReader::open(&h, None).unwrap_err(),
        SourceListing::list(&h, None).unwrap_err(),
    ];
    for e in errors {
        assert!(e.to_string().contains("longer than"), "{e}");
    }
}

/// A 4D NRRD time series cut into files: a volume per file (the time axis last), and a slice
/// per file holding every time point of each voxel (the time axis first); each time point
/// reads as written, region by region.
#[test]
fn a_time_series_cut_into_files_reads_by_time_point() {
    let dir = tempfile::tempdir().unwrap();
    let points = 3usize;
    // Time point t's samples: the volume's, plus 1000·t.
    let at = |t: usize| -> Vec<u16> {
        samples()
            .iter()
            .map(|v| v % 60_000 + 1000 * t as u16)
            .collect()
    };
    let head = |sizes: String, kinds: &str, list: &[String]| {
        format!(
            "NRRD0004\ntype: uint16\ndimension: 4\nsizes: {sizes}\nkinds: {kinds}\nendian: little\nencoding: raw\ndata file: LIST\n{}\n",
            list.join("\n")
        )
    };
    // Time last: one file per time point.
    let names: Vec<String> = (0..points).map(|t| format!("t{t}.raw")).collect();
    for (t, name) in names.iter().enumerate() {
        std::fs::write(dir.path().join(name), le(&at(t))).unwrap();
    }
    let last = dir.path().join("last.nhdr");
    let sizes = format!("{} {} {} {points}", DIMS[0], DIMS[1], DIMS[2]);
    std::fs::write(&last, head(sizes, "domain domain domain time", &names)).unwrap();
    // Time first: one file per slice, each voxel's time points together.
    let names: Vec<String> = (0..DIMS[2]).map(|z| format!("z{z}.raw")).collect();
    let slice = DIMS[0] * DIMS[1];
    for (z, name) in names.iter().enumerate() {
        let mut voxels = Vec::with_capacity(slice * points);
        for i in z * slice..(z + 1) * slice {
            voxels.extend((0..points).map(|t| at(t)[i]));
        }
        std::fs::write(dir.path().join(name), le(&voxels)).unwrap();
    }
    let first = dir.path().join("first.nhdr");
    let sizes = format!("{points} {} {} {}", DIMS[0], DIMS[1], DIMS[2]);
    std::fs::write(&first, head(sizes, "time domain domain domain", &names)).unwrap();
    for h in [&last, &first] {
        let r = RegionReader::open_series(h, None).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            (r.time_points(), r.dims()),
            (points, DIMS),
            "{}",
            h.display()
        );
        for t in 0..points {
            let want: Vec<f32> = at(t).iter().map(|v| f32::from(*v)).collect();
            let whole = r.read_region_at(t, [0; 3], DIMS).unwrap();
            assert_eq!(whole.channel(0), &want[..], "{} t {t}", h.display());
            let (origin, size) = ([1, 1, 2], [3, 2, 4]);
            let part = r.read_region_at(t, origin, size).unwrap();
            assert_eq!(
                part.channel(0),
                &cut(&whole, origin, size)[..],
                "{}",
                h.display()
            );
        }
    }
}

/// NRRD files of the volume's own dimension are slabs of the slowest axis, as teem reads them:
/// 3 files of 2 slices each read as the 6 slices written; 4 files for 6 slices are refused.
#[test]
fn nrrd_files_of_every_axis_are_slabs() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [5usize, 4, 6];
    let n = dims.iter().product::<usize>();
    let values: Vec<u16> = (0..n).map(|i| (i * 97 % 50_000) as u16).collect();
    let slab = n / 3;
    for k in 0..3 {
        std::fs::write(
            dir.path().join(format!("slab{k}.raw")),
            le(&values[k * slab..(k + 1) * slab]),
        )
        .unwrap();
    }
    let head =
        "NRRD0004\ntype: uint16\ndimension: 3\nsizes: 5 4 6\nendian: little\nencoding: raw\n";
    let h = dir.path().join("slabs.nhdr");
    std::fs::write(&h, format!("{head}data file: slab%d.raw 0 2 1 3\n")).unwrap();
    let want: Vec<f32> = values.iter().map(|v| f32::from(*v)).collect();
    let v = read_volume(&h, None).unwrap();
    assert_eq!(v.channel(0), &want[..]);
    let r = RegionReader::open(&h, None).unwrap();
    assert_eq!(r.read_region([0; 3], dims).unwrap(), v);
    let (origin, size) = ([1, 0, 1], [3, 4, 4]);
    assert_eq!(
        r.read_region(origin, size).unwrap().channel(0),
        &cut(&v, origin, size)[..]
    );
    std::fs::write(dir.path().join("slab3.raw"), b"").unwrap();
    std::fs::write(&h, format!("{head}data file: slab%d.raw 0 3 1 3\n")).unwrap();
    for e in [
        read_volume(&h, None).unwrap_err(),
        RegionReader::open(&h, None).unwrap_err(),
    ] {
        assert!(e.to_string().contains("do not divide"), "{e}");
    }
}

/// A NaN in the third of five slice files is refused naming that file, not the first, whole
/// and by region, for NRRD and MetaImage alike, raw or compressed.
#[test]
fn a_non_finite_sample_is_refused_naming_the_file_that_holds_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let [nx, ny, nz] = [4usize, 3, 5];
    let mut names = Vec::new();
    for z in 0..nz {
        let mut slice = vec![1.0f32; nx * ny];
        if z == 2 {
            slice[nx + 2] = f32::NAN; // voxel (2, 1, 2)
        }
        let name = format!("s{z}.raw");
        let bytes: Vec<u8> = slice.iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(d.join(format!("s{z}.raw.gz")), gzip(&bytes)).unwrap();
        std::fs::write(d.join(format!("s{z}.zraw")), zlib(&bytes)).unwrap();
        std::fs::write(d.join(&name), bytes).unwrap();
        names.push(name);
    }
    // The same slices compressed, each file on its own (inflated into one temporary file
    // for region reads).
    std::fs::write(
        d.join("gz.nhdr"),
        format!(
            "NRRD0004\ntype: float\ndimension: 3\nsizes: {nx} {ny} {nz}\nendian: little\n\
             encoding: gzip\ndata file: s%d.raw.gz 0 {} 1\n",
            nz - 1
        ),
    )
    .unwrap();
    std::fs::write(
        d.join("z.mhd"),
        format!(
            "ObjectType = Image\nNDims = 3\nDimSize = {nx} {ny} {nz}\nElementType = MET_FLOAT\n\
             CompressedData = True\nElementDataFile = s%d.zraw 0 {} 1\n",
            nz - 1
        ),
    )
    .unwrap();
    let list = names.join("\n");
    std::fs::write(
        d.join("v.nhdr"),
        format!(
            "NRRD0004\ntype: float\ndimension: 3\nsizes: {nx} {ny} {nz}\nendian: little\n\
             encoding: raw\ndata file: LIST\n{list}\n"
        ),
    )
    .unwrap();
    std::fs::write(
        d.join("v.mhd"),
        format!(
            "ObjectType = Image\nNDims = 3\nDimSize = {nx} {ny} {nz}\nElementType = MET_FLOAT\n\
             ElementDataFile = s%d.raw 0 {} 1\n",
            nz - 1
        ),
    )
    .unwrap();
    for header in ["v.nhdr", "v.mhd", "gz.nhdr", "z.mhd"] {
        let path = d.join(header);
        let whole = read_volume(&path, None).unwrap_err().to_string();
        let reader = RegionReader::open(&path, None).unwrap();
        let region = reader
            .read_region([0, 0, 1], [nx, ny, 3])
            .unwrap_err()
            .to_string();
        for e in [whole, region] {
            assert!(e.contains("s2."), "{header}: {e}");
            assert!(!e.contains("s0."), "{header}: {e}");
        }
    }
}
