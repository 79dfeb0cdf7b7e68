//! Zarr stores read as volumes: arrays written by zarr-python (the format's reference
//! implementation; v2 and v3, Blosc, Zstd, zlib, sharding, Fortran order, big-endian samples,
//! OME-Zarr 0.4 and 0.5 images and a time series) read to the samples it wrote, whole, region by
//! region and through a bundle; stores written here by hand from the specification (uncompressed
//! v2 chunks) check the axes, missing chunks and what is refused, with no Python.

use std::path::{Path, PathBuf};
use wavesplat_compressor::reader::region::RegionReader;
use wavesplat_compressor::reader::{
    decode_source, read_volume, time_points, unpack_bundle, Format, ReadError, SourceFiles,
    SourceListing,
};

/// zarr-python's version the CI installs.
const INSTALL: &str = "python3 -m pip install zarr==3.1.6";

/// The stores zarr-python writes (name, what it is), every one holding the same 28 × 24 × 20
/// u16-valued samples (`reference.f64`, x fastest) but the series, whose time point t is the
/// same samples plus 1000 t.
const WRITTEN: [&str; 9] = [
    "v3_zstd.zarr",
    "v3_sharded.zarr",
    "v2_blosc.zarr",
    "v2_zlib_nested_fortran.zarr",
    "v2_big_endian_i2.zarr",
    "v3_float64.zarr",
    "ome04.zarr",
    "ome05.ome.zarr",
    "xarray_xyz.zarr",
];

const SCRIPT: &str = r#"
import sys, numpy as np, zarr, numcodecs
from zarr.codecs import BloscCodec, ZstdCodec
out = sys.argv[1]
z, y, x = 20, 24, 28
g = np.mgrid[0:z, 0:y, 0:x]
a = (1000 + 37 * g[0] + 3 * g[1] * g[1] + 11 * g[2] + (g[0] * g[1] * g[2]) % 17).astype(np.uint16)
a[:8, :8, :8] = 0   # a chunk of the fill value: zarr-python leaves it unwritten
a.astype('<f8').tofile(out + '/reference.f64')
def v3(name, **kw):
    zarr.create_array(out + '/' + name, shape=a.shape, chunks=(8, 8, 8), dtype=kw.pop('dtype', a.dtype), **kw)[:] = a
v3('v3_zstd.zarr')
v3('v3_sharded.zarr', shards=(16, 16, 16), compressors=BloscCodec(cname='zstd', shuffle='bitshuffle'))
v3('v3_float64.zarr', dtype='f8', compressors=ZstdCodec(level=3, checksum=True))
zarr.create_array(out + '/v2_blosc.zarr', shape=a.shape, chunks=(8, 8, 8), dtype=a.dtype, zarr_format=2,
                  compressors=numcodecs.Blosc(cname='lz4', shuffle=numcodecs.Blosc.SHUFFLE))[:] = a
zarr.create_array(out + '/v2_zlib_nested_fortran.zarr', shape=a.shape, chunks=(8, 8, 8), dtype=a.dtype, zarr_format=2,
                  compressors=numcodecs.Zlib(level=6), chunk_key_encoding={'name': 'v2', 'separator': '/'}, order='F')[:] = a
zarr.create_array(out + '/v2_big_endian_i2.zarr', shape=a.shape, chunks=(8, 8, 8), dtype='>i2', zarr_format=2)[:] = a.astype('>i2')
# xarray's layout: dimension names in _ARRAY_DIMENSIONS, here x slowest.
t = zarr.create_array(out + '/xarray_xyz.zarr', shape=(x, y, z), chunks=(8, 8, 8), dtype=a.dtype, zarr_format=2)
t[:] = a.transpose(2, 1, 0)
t.attrs['_ARRAY_DIMENSIONS'] = ['x', 'y', 'z']
axes = [{'name': 'z', 'type': 'space', 'unit': 'micrometer'}, {'name': 'y', 'type': 'space', 'unit': 'micrometer'},
        {'name': 'x', 'type': 'space', 'unit': 'micrometer'}]
datasets = [{'path': '0', 'coordinateTransformations': [{'type': 'scale', 'scale': [2.0, 0.5, 0.25]}]},
            {'path': '1', 'coordinateTransformations': [{'type': 'scale', 'scale': [4.0, 1.0, 0.5]}]}]
for name, fmt in [('ome04.zarr', 2), ('ome05.ome.zarr', 3)]:
    g0 = zarr.open_group(out + '/' + name, mode='w', zarr_format=fmt)
    g0.create_array('0', shape=a.shape, chunks=(8, 8, 8), dtype=a.dtype)[:] = a
    g0.create_array('1', shape=(10, 12, 14), chunks=(8, 8, 8), dtype=a.dtype)[:] = a[::2, ::2, ::2]
    ms = [{'version': '0.4', 'axes': axes, 'datasets': datasets}]
    if fmt == 2:
        g0.attrs['multiscales'] = ms
    else:
        ms[0].pop('version')
        g0.attrs['ome'] = {'version': '0.5', 'multiscales': ms}
# A series: t, z, y, x, 3 time points 1.5 s apart (a time scale in milliseconds).
s = zarr.open_group(out + '/series.zarr', mode='w', zarr_format=2)
s.create_array('0', shape=(3,) + a.shape, chunks=(1, 8, 8, 8), dtype=a.dtype)[:] = np.stack([a + 1000 * k for k in range(3)])
s.attrs['multiscales'] = [{'version': '0.4', 'axes': [{'name': 't', 'type': 'time', 'unit': 'millisecond'}] + axes,
                           'datasets': [{'path': '0', 'coordinateTransformations': [{'type': 'scale', 'scale': [1500.0, 2.0, 0.5, 0.25]}]}]}]
"#;

const DIMS: [usize; 3] = [28, 24, 20];

/// The Python that has zarr-python: `WAVESPLAT_ZARR_PYTHON` (the venv `.ci/run` makes), else
/// `python3`'s where it has it.
fn zarr_python() -> Option<String> {
    if let Some(p) = std::env::var_os("WAVESPLAT_ZARR_PYTHON") {
        return Some(p.to_string_lossy().into_owned());
    }
    wavesplat_fixtures::reference_python("zarr, numcodecs, numpy", INSTALL).map(str::to_string)
}

/// Writes the stores with zarr-python into `dir`; `None` where it is not installed.
fn written(dir: &Path) -> Option<Vec<f32>> {
    let python = zarr_python()?;
    let status = std::process::Command::new(&python)
        .args(["-c", SCRIPT])
        .arg(dir)
        .status()
        .unwrap();
    assert!(status.success(), "zarr-python failed");
    let bytes = std::fs::read(dir.join("reference.f64")).unwrap();
    Some(
        bytes
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().unwrap()) as f32)
            .collect(),
    )
}

/// The reference's samples of the box at `o` of size `s`.
fn cut(all: &[f32], o: [usize; 3], s: [usize; 3]) -> Vec<f32> {
    let mut out = Vec::new();
    for z in o[2]..o[2] + s[2] {
        for y in o[1]..o[1] + s[1] {
            let row = (z * DIMS[1] + y) * DIMS[0];
            out.extend_from_slice(&all[row + o[0]..row + o[0] + s[0]]);
        }
    }
    out
}

/// Regions that cross chunk faces, touch the far faces, and one voxel.
const REGIONS: [([usize; 3], [usize; 3]); 4] = [
    ([0, 0, 0], [28, 24, 20]),
    ([5, 7, 3], [13, 11, 9]),
    ([20, 16, 12], [8, 8, 8]),
    ([27, 0, 19], [1, 1, 1]),
];

#[test]
fn stores_written_by_zarr_python_read_as_written() {
    let dir = tempfile::tempdir().unwrap();
    let Some(want) = written(dir.path()) else {
        return;
    };
    for name in WRITTEN {
        let path = dir.path().join(name);
        assert_eq!(Format::from_name(&path), Some(Format::Zarr), "{name}");
        let whole = read_volume(&path, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(whole.dims(), DIMS, "{name}");
        assert_eq!(whole.channel(0), &want[..], "{name}: other samples");
        let ome = name.starts_with("ome");
        let spacing = if ome {
            [0.00025, 0.0005, 0.002]
        } else {
            [1.0; 3]
        };
        assert_eq!(whole.spacing(), spacing, "{name}");
        let reader = RegionReader::open(&path, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(!reader.in_memory(), "{name}: read whole, not by region");
        assert_eq!((reader.dims(), reader.spacing()), (DIMS, spacing), "{name}");
        for (o, s) in REGIONS {
            let region = reader.read_region(o, s).unwrap();
            assert_eq!(
                region.channel(0),
                &cut(&want, o, s)[..],
                "{name} {o:?} {s:?}"
            );
        }
        // The listing that hashes and uploads it, as a bundle decoded elsewhere and unpacked
        // to files.
        let listing = SourceListing::list(&path, None).unwrap();
        assert_eq!(listing.format, Some(Format::Zarr));
        if ome {
            // The full resolution's chunks, not the lower level's.
            assert!(
                listing.files.iter().all(|f| !f.0.starts_with("1/")),
                "{name}"
            );
        }
        let mut streamed = Vec::new();
        listing.write_to(&mut streamed).unwrap();
        let gathered = SourceFiles::gather(&path, None).unwrap();
        assert_eq!(gathered.to_bytes(), streamed, "{name}");
        let elsewhere = SourceFiles::from_bytes(streamed.clone(), Path::new("upload")).unwrap();
        let decoded = decode_source(&elsewhere, None).unwrap();
        assert_eq!(decoded.channel(0), &want[..], "{name}: from the bundle");
        let unpacked = tempfile::tempdir().unwrap();
        let u = unpack_bundle(&mut streamed.as_slice(), unpacked.path()).unwrap();
        assert_eq!(u.primary, unpacked.path(), "{name}");
        let r = RegionReader::open(&u.primary, None).unwrap();
        let (o, s) = REGIONS[1];
        assert_eq!(
            r.read_region(o, s).unwrap().channel(0),
            &cut(&want, o, s)[..]
        );
    }
}

#[test]
fn an_ome_zarr_time_axis_is_a_series() {
    let dir = tempfile::tempdir().unwrap();
    let Some(want) = written(dir.path()) else {
        return;
    };
    let path = dir.path().join("series.zarr");
    assert_eq!(time_points(&path, None).unwrap(), 3);
    match read_volume(&path, None) {
        Err(ReadError::TimeSeries { points: 3, .. }) => {}
        other => panic!("one volume read of a series: {other:?}"),
    }
    let reader = RegionReader::open_series(&path, None).unwrap();
    assert_eq!(reader.time_points(), 3);
    assert_eq!(reader.time_step(), Some(1.5));
    assert_eq!(reader.spacing(), [0.00025, 0.0005, 0.002]);
    for t in 0..3 {
        let (o, s) = REGIONS[1];
        let got = reader.read_region_at(t, o, s).unwrap();
        let shifted: Vec<f32> = cut(&want, o, s)
            .iter()
            .map(|v| v + 1000.0 * t as f32)
            .collect();
        assert_eq!(got.channel(0), &shifted[..], "time point {t}");
    }
}

/// A v2 array written by hand from the specification: `.zarray` with no compressor, each
/// chunk its samples in C order (little-endian u16), a chunk left out where `skip` says.
fn hand_written(
    dir: &Path,
    name: &str,
    shape: &[usize],
    chunks: &[usize],
    attrs: Option<&str>,
    value: impl Fn(&[usize]) -> u16,
    skip: impl Fn(&[usize]) -> bool,
) -> PathBuf {
    let path = dir.join(name);
    std::fs::create_dir_all(&path).unwrap();
    let list = |v: &[usize]| {
        v.iter()
            .map(|d| d.to_string())
            .collect::<Vec<_>>()
            .join(", ")
    };
    let meta = format!(
        r#"{{"zarr_format": 2, "shape": [{}], "chunks": [{}], "dtype": "<u2", "compressor": null,
            "fill_value": 7, "order": "C", "filters": null}}"#,
        list(shape),
        list(chunks)
    );
    std::fs::write(path.join(".zarray"), meta).unwrap();
    if let Some(a) = attrs {
        std::fs::write(path.join(".zattrs"), a).unwrap();
    }
    let grid: Vec<usize> = shape
        .iter()
        .zip(chunks)
        .map(|(s, c)| s.div_ceil(*c))
        .collect();
    let count: usize = grid.iter().product();
    for k in 0..count {
        // The chunk's index, the last axis fastest.
        let mut idx = vec![0; grid.len()];
        let mut r = k;
        for a in (0..grid.len()).rev() {
            idx[a] = r % grid[a];
            r /= grid[a];
        }
        if skip(&idx) {
            continue;
        }
        let n: usize = chunks.iter().product();
        let mut bytes = Vec::with_capacity(2 * n);
        for e in 0..n {
            let mut pos = vec![0; chunks.len()];
            let mut r = e;
            for a in (0..chunks.len()).rev() {
                pos[a] = idx[a] * chunks[a] + r % chunks[a];
                r /= chunks[a];
            }
            // Samples past the array's edge in a chunk are stored too (and never read).
            bytes.extend_from_slice(&value(&pos).to_le_bytes());
        }
        let key = list(&idx).replace(", ", ".");
        std::fs::write(path.join(key), bytes).unwrap();
    }
    path
}

#[test]
fn axes_come_from_names_and_missing_chunks_are_the_fill_value() {
    let dir = tempfile::tempdir().unwrap();
    // z, y, x by count; x, y, z by xarray's names; and a fifth axis of one channel.
    let zyx = |p: &[usize]| (p[2] + 10 * p[1] + 100 * p[0]) as u16;
    let missing = |i: &[usize]| i.iter().all(|c| *c == 1);
    let plain = hand_written(
        dir.path(),
        "zyx",
        &[5, 6, 7],
        &[3, 4, 5],
        None,
        zyx,
        missing,
    );
    let names = Some(r#"{"_ARRAY_DIMENSIONS": ["x", "y", "z"]}"#);
    let xyz = |p: &[usize]| (p[0] + 10 * p[1] + 100 * p[2]) as u16;
    let named = hand_written(
        dir.path(),
        "xyz",
        &[7, 6, 5],
        &[5, 4, 3],
        names,
        xyz,
        |_| false,
    );
    let tczyx = |p: &[usize]| zyx(&p[2..]);
    let five = hand_written(
        dir.path(),
        "tczyx",
        &[1, 1, 5, 6, 7],
        &[1, 1, 3, 4, 5],
        None,
        tczyx,
        |_| false,
    );
    for (path, gap) in [(&plain, true), (&named, false), (&five, false)] {
        let v = read_volume(path, None).unwrap();
        assert_eq!(v.dims(), [7, 6, 5], "{}", path.display());
        for z in 0..5 {
            for y in 0..6 {
                for x in 0..7 {
                    // The left-out chunk (1, 1, 1) holds z 3..5, y 4..6, x 5..7.
                    let filled = gap && z >= 3 && y >= 4 && x >= 5;
                    let want = if filled { 7 } else { x + 10 * y + 100 * z };
                    let got = v.channel(0)[(z * 6 + y) * 7 + x];
                    assert_eq!(got, want as f32, "{} at {x},{y},{z}", path.display());
                }
            }
        }
    }
}

#[test]
fn what_is_no_volume_is_refused_saying_why() {
    let dir = tempfile::tempdir().unwrap();
    let flat = hand_written(dir.path(), "flat", &[6, 7], &[3, 3], None, |_| 1, |_| false);
    let channels = hand_written(
        dir.path(),
        "channels",
        &[1, 2, 3, 4, 5],
        &[1, 1, 3, 4, 5],
        None,
        |_| 1,
        |_| false,
    );
    // A chunk of 2 000³ u16 samples (16 GB) is refused from its metadata alone.
    let huge = dir.path().join("huge");
    std::fs::create_dir_all(&huge).unwrap();
    std::fs::write(
        huge.join(".zarray"),
        r#"{"zarr_format": 2, "shape": [2000, 2000, 2000], "chunks": [2000, 2000, 2000],
            "dtype": "<u2", "compressor": null, "fill_value": 0, "order": "C", "filters": null}"#,
    )
    .unwrap();
    let complex = dir.path().join("complex");
    std::fs::create_dir_all(&complex).unwrap();
    std::fs::write(
        complex.join(".zarray"),
        r#"{"zarr_format": 2, "shape": [2, 2, 2], "chunks": [2, 2, 2], "dtype": "<f2",
            "compressor": null, "fill_value": 0, "order": "C", "filters": null}"#,
    )
    .unwrap();
    let group = dir.path().join("group");
    std::fs::create_dir_all(&group).unwrap();
    std::fs::write(group.join(".zgroup"), r#"{"zarr_format": 2}"#).unwrap();
    let garbled = dir.path().join("garbled");
    std::fs::create_dir_all(&garbled).unwrap();
    std::fs::write(garbled.join("zarr.json"), "{ not json").unwrap();
    // A chunk cut short.
    let short = hand_written(
        dir.path(),
        "short",
        &[4, 4, 4],
        &[2, 2, 2],
        None,
        |_| 3,
        |_| false,
    );
    std::fs::write(short.join("1.1.1"), [0u8; 5]).unwrap();
    let cases: [(&Path, &str); 7] = [
        (&flat, "three spatial axes"),
        (&channels, "2 channels"),
        (&huge, "bytes a chunk"),
        (&complex, "samples of type"),
        (&group, "no OME-Zarr image"),
        (&garbled, "not JSON"),
        (&short, "reading"),
    ];
    for (path, why) in cases {
        let e = read_volume(path, None).expect_err(why).to_string();
        assert!(e.contains(why), "{}: {e}", path.display());
        assert!(e.contains(&path.display().to_string()), "{e}");
        if why != "reading" {
            let e = RegionReader::open(path, None).expect_err(why).to_string();
            assert!(e.contains(why), "{}: {e}", path.display());
        }
    }
    let r = RegionReader::open(&short, None).unwrap();
    assert!(r.read_region([0, 0, 0], [2, 2, 2]).is_ok());
    let e = r.read_region([1, 1, 1], [3, 3, 3]).unwrap_err().to_string();
    assert!(e.contains("reading"), "{e}");
}

/// A float array's NaN fill value where chunks are missing is refused as NaN samples are.
#[test]
fn a_nan_fill_value_in_a_region_read_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("nan");
    std::fs::create_dir_all(&path).unwrap();
    std::fs::write(
        path.join(".zarray"),
        r#"{"zarr_format": 2, "shape": [2, 2, 4], "chunks": [2, 2, 2], "dtype": "<f4",
            "compressor": null, "fill_value": "NaN", "order": "C", "filters": null}"#,
    )
    .unwrap();
    let chunk: Vec<u8> = [1.5f32; 8].iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(path.join("0.0.0"), chunk).unwrap();
    let r = RegionReader::open(&path, None).unwrap();
    let v = r.read_region([0, 0, 0], [2, 2, 2]).unwrap();
    assert!(v.channel(0).iter().all(|s| *s == 1.5));
    let e = r.read_region([0, 0, 0], [4, 2, 2]).unwrap_err().to_string();
    assert!(e.to_lowercase().contains("nan"), "{e}");
    assert!(read_volume(&path, None).is_err());
}

/// Stores whose metadata and chunks are corrupted byte by byte (zarr-python's stores, and one
/// written here) are read to a volume or refused with an error, never a panic: the store is
/// untrusted input.
#[test]
fn corrupted_stores_are_refused_or_read_never_a_panic() {
    use rand::{Rng, SeedableRng};
    let dir = tempfile::tempdir().unwrap();
    let mut stores = vec![hand_written(
        dir.path(),
        "hand",
        &[5, 6, 7],
        &[3, 4, 5],
        Some(r#"{"_ARRAY_DIMENSIONS": ["z", "y", "x"]}"#),
        |p| p.iter().sum::<usize>() as u16,
        |i| i[0] == 1,
    )];
    if written(dir.path()).is_some() {
        stores.extend(WRITTEN.iter().map(|n| dir.path().join(n)));
        stores.push(dir.path().join("series.zarr"));
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(57);
    for store in &stores {
        let files: Vec<PathBuf> = SourceListing::list(store, None)
            .unwrap()
            .files
            .into_iter()
            .map(|f| f.1)
            .collect();
        for round in 0..24 {
            let victim = &files[rng.gen_range(0..files.len())];
            let kept = std::fs::read(victim).unwrap();
            let mut bytes = kept.clone();
            match round % 3 {
                // A few bytes changed.
                0 | 1 if !bytes.is_empty() => {
                    for _ in 0..rng.gen_range(1..4) {
                        let i = rng.gen_range(0..bytes.len());
                        bytes[i] = rng.gen();
                    }
                }
                // Cut short.
                _ => bytes.truncate(rng.gen_range(0..=bytes.len())),
            }
            std::fs::write(victim, &bytes).unwrap();
            let outcome = std::panic::catch_unwind(|| {
                let _ = read_volume(store, None);
                if let Ok(r) = RegionReader::open_series(store, None) {
                    let [nx, ny, nz] = r.dims();
                    let _ = r.read_region([0, 0, 0], [nx.min(9), ny.min(9), nz.min(9)]);
                }
            });
            assert!(
                outcome.is_ok(),
                "{} with {} corrupted (round {round})",
                store.display(),
                victim.display()
            );
            std::fs::write(victim, &kept).unwrap();
        }
    }
    if stores.len() > 1 {
        // A shard cut shorter than its index (zarrs 0.23 overflows on it, and would panic).
        let store = dir.path().join("v3_sharded.zarr");
        std::fs::write(store.join("c/1/1/1"), [0u8; 5]).unwrap();
        let e = read_volume(&store, None).unwrap_err().to_string();
        assert!(e.contains("v3_sharded.zarr"), "{e}");
    }
}

/// Writes an OME-Zarr 0.4 group's metadata at `group` naming the array `0` with `axes` and
/// `scale` (JSON text).
fn ome_group(group: &Path, axes: &str, scale: &str) {
    std::fs::write(group.join(".zgroup"), r#"{"zarr_format": 2}"#).unwrap();
    let attrs = format!(
        r#"{{"multiscales": [{{"version": "0.4", "axes": {axes}, "datasets": [{{"path": "0",
            "coordinateTransformations": [{{"type": "scale", "scale": {scale}}}]}}]}}]}}"#
    );
    std::fs::write(group.join(".zattrs"), attrs).unwrap();
}

#[test]
fn layouts_met_in_the_wild_and_the_limits_on_them() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let zyx = |p: &[usize]| (p[2] + 10 * p[1] + 100 * p[0]) as u16;
    let check = |path: &Path, what: &str| {
        let v = read_volume(path, None).unwrap_or_else(|e| panic!("{what}: {e}"));
        assert_eq!(v.dims(), [7, 6, 5], "{what}");
        assert_eq!(v.channel(0)[(4 * 6 + 5) * 7 + 6], 456.0, "{what}");
        let mut bundle = Vec::new();
        SourceListing::list(path, None)
            .unwrap()
            .write_to(&mut bundle)
            .unwrap();
        let src = SourceFiles::from_bytes(bundle, Path::new("elsewhere")).unwrap();
        let again = decode_source(&src, None).unwrap_or_else(|e| panic!("{what}: {e}"));
        assert_eq!(again.channel(0), v.channel(0), "{what}: from its bundle");
    };
    // xarray's default names say nothing: read as z, y, x.
    let dims = Some(r#"{"_ARRAY_DIMENSIONS": ["dim_0", "dim_1", "dim_2"]}"#);
    let p = hand_written(d, "xr", &[5, 6, 7], &[3, 4, 5], dims, zyx, |_| false);
    check(&p, "xarray's default names");
    // bioformats2raw's layout: the image is group 0 of the root.
    let root = d.join("b2r.zarr");
    std::fs::create_dir_all(root.join("0")).unwrap();
    std::fs::write(root.join(".zgroup"), r#"{"zarr_format": 2}"#).unwrap();
    std::fs::write(root.join(".zattrs"), r#"{"bioformats2raw.layout": 3}"#).unwrap();
    let axes = r#"[{"name": "z", "type": "space"}, {"name": "y", "type": "space"},
                   {"name": "x", "type": "space"}]"#;
    ome_group(&root.join("0"), axes, "[1, 1, 1]");
    hand_written(
        &root.join("0"),
        "0",
        &[5, 6, 7],
        &[3, 4, 5],
        None,
        zyx,
        |_| false,
    );
    check(&root, "bioformats2raw");
    let names: Vec<String> = SourceListing::list(&root, None)
        .unwrap()
        .files
        .into_iter()
        .map(|f| f.0)
        .collect();
    assert!(names.contains(&"0/.zattrs".to_string()), "{names:?}");
    // Every chunk a symbolic link (a DataLad or git-annex checkout).
    let linked = hand_written(d, "linked", &[5, 6, 7], &[3, 4, 5], None, zyx, |_| false);
    let annex = d.join("annex");
    std::fs::create_dir_all(&annex).unwrap();
    for e in std::fs::read_dir(&linked).unwrap() {
        let e = e.unwrap();
        let name = e.file_name();
        if name.to_string_lossy().contains('.') && !name.to_string_lossy().starts_with('.') {
            std::fs::rename(e.path(), annex.join(&name)).unwrap();
            std::os::unix::fs::symlink(annex.join(&name), e.path()).unwrap();
        }
    }
    check(&linked, "linked chunks");
    // Every chunk the fill value, none written: the metadata alone is the store.
    let empty = hand_written(d, "empty", &[5, 6, 7], &[3, 4, 5], None, zyx, |_| true);
    let listing = SourceListing::list(&empty, None).unwrap();
    assert_eq!(listing.files.len(), 1);
    let mut bundle = Vec::new();
    listing.write_to(&mut bundle).unwrap();
    assert_eq!(bundle.len() as u64, listing.byte_len());
    let src = SourceFiles::from_bytes(bundle, Path::new("elsewhere")).unwrap();
    let v = decode_source(&src, None).unwrap();
    assert!(v.channel(0).iter().all(|s| *s == 7.0));
    // Refused: too many time points, a scale of the wrong length, a unit of no length.
    let many = d.join("many");
    std::fs::create_dir_all(&many).unwrap();
    std::fs::write(
        many.join(".zarray"),
        r#"{"zarr_format": 2, "shape": [1099511627776, 1, 1, 1], "chunks": [1, 1, 1, 1],
            "dtype": "|u1", "compressor": null, "fill_value": 0, "order": "C", "filters": null}"#,
    )
    .unwrap();
    let short_scale = d.join("short_scale");
    std::fs::create_dir_all(&short_scale).unwrap();
    ome_group(&short_scale, axes, "[1, 1]");
    hand_written(&short_scale, "0", &[5, 6, 7], &[3, 4, 5], None, zyx, |_| {
        false
    });
    let parsec = d.join("parsec");
    std::fs::create_dir_all(&parsec).unwrap();
    let far = r#"[{"name": "z", "type": "space", "unit": "parsec"}, {"name": "y", "type": "space"},
                  {"name": "x", "type": "space"}]"#;
    ome_group(&parsec, far, "[1, 1, 1]");
    hand_written(&parsec, "0", &[5, 6, 7], &[3, 4, 5], None, zyx, |_| false);
    // Two links to their own directory: a walk following them visits 2^depth directories.
    let looped = hand_written(d, "looped", &[5, 6, 7], &[3, 4, 5], None, zyx, |_| false);
    std::os::unix::fs::symlink(&looped, looped.join("again")).unwrap();
    std::os::unix::fs::symlink(&looped, looped.join("also")).unwrap();
    let e = SourceListing::list(&looped, None).unwrap_err().to_string();
    assert!(e.contains("reached twice"), "{e}");
    assert!(read_volume(&looped, None).is_err());
    for (path, why) in [
        (&many, "time points"),
        (&short_scale, "a scale of 2 values for 3 axes"),
        (&parsec, "\"parsec\""),
    ] {
        let e = RegionReader::open_series(path, None)
            .expect_err(why)
            .to_string();
        assert!(e.contains(why), "{e}");
    }
}

/// A chunk whose codec header claims far more bytes than a chunk holds (a Zstd frame declaring
/// 1 TiB in 17 bytes, a Blosc header declaring 4 GiB) is refused before anything that large is
/// allocated.
#[test]
fn a_chunk_claiming_more_than_a_chunk_holds_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let zstd = dir.path().join("zstd");
    std::fs::create_dir_all(zstd.join("c/0/0")).unwrap();
    std::fs::write(
        zstd.join("zarr.json"),
        r#"{"zarr_format": 3, "node_type": "array", "shape": [4, 4, 4], "data_type": "uint16",
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [4, 4, 4]}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": 0, "codecs": [{"name": "bytes", "configuration": {"endian": "little"}},
            {"name": "zstd", "configuration": {"level": 0, "checksum": false}}]}"#,
    )
    .unwrap();
    // Magic; a single segment with an 8-byte content size of 2^40; one empty last raw block.
    let mut frame = vec![0x28, 0xb5, 0x2f, 0xfd, 0xe0];
    frame.extend_from_slice(&(1u64 << 40).to_le_bytes());
    frame.extend_from_slice(&[0x01, 0x00, 0x00]);
    std::fs::write(zstd.join("c/0/0/0"), &frame).unwrap();
    let blosc = dir.path().join("blosc");
    std::fs::create_dir_all(&blosc).unwrap();
    std::fs::write(
        blosc.join(".zarray"),
        r#"{"zarr_format": 2, "shape": [4, 4, 4], "chunks": [4, 4, 4], "dtype": "<u2",
            "compressor": {"id": "blosc", "cname": "lz4", "clevel": 5, "shuffle": 1,
            "blocksize": 0}, "fill_value": 0, "order": "C", "filters": null}"#,
    )
    .unwrap();
    let header = [
        2u8, 1, 1, 2, 0xff, 0xff, 0xff, 0xff, 0, 0, 1, 0, 16, 0, 0, 0,
    ];
    std::fs::write(blosc.join("0.0.0"), header).unwrap();
    for store in [&zstd, &blosc] {
        let e = read_volume(store, None).unwrap_err().to_string();
        assert!(e.contains("declares"), "{}: {e}", store.display());
        let r = RegionReader::open(store, None).unwrap();
        let e = r.read_region([0, 0, 0], [2, 2, 2]).unwrap_err().to_string();
        assert!(e.contains("declares"), "{}: {e}", store.display());
    }
}

/// A shard's index at its end: each inner chunk's (offset, length) as little-endian u64s
/// (`u64::MAX` twice for a missing chunk), then their CRC-32C.
fn shard_index(entries: &[(u64, u64)]) -> Vec<u8> {
    let mut index: Vec<u8> = entries
        .iter()
        .flat_map(|(o, l)| [o.to_le_bytes(), l.to_le_bytes()])
        .flatten()
        .collect();
    let crc = crc32c::crc32c(&index);
    index.extend_from_slice(&crc.to_le_bytes());
    index
}

/// A v3 array of 4×4×4 u16 samples in one chunk (or one shard) with these codecs, its chunk
/// (or shard) file holding `chunk`.
fn v3_store(dir: &Path, name: &str, codecs: &str, chunk: &[u8]) -> PathBuf {
    let path = dir.join(name);
    std::fs::create_dir_all(path.join("c/0/0")).unwrap();
    let meta = format!(
        r#"{{"zarr_format": 3, "node_type": "array", "shape": [4, 4, 4], "data_type": "uint16",
            "chunk_grid": {{"name": "regular", "configuration": {{"chunk_shape": [4, 4, 4]}}}},
            "chunk_key_encoding": {{"name": "default", "configuration": {{"separator": "/"}}}},
            "fill_value": 0, "codecs": {codecs}}}"#
    );
    std::fs::write(path.join("zarr.json"), meta).unwrap();
    std::fs::write(path.join("c/0/0/0"), chunk).unwrap();
    path
}

/// A v2 array of 4×4×4 u16 samples in one chunk compressed by `compressor`, holding `chunk`.
fn v2_store(dir: &Path, name: &str, compressor: &str, chunk: &[u8]) -> PathBuf {
    let path = dir.join(name);
    std::fs::create_dir_all(&path).unwrap();
    let meta = format!(
        r#"{{"zarr_format": 2, "shape": [4, 4, 4], "chunks": [4, 4, 4], "dtype": "<u2",
            "compressor": {compressor}, "fill_value": 0, "order": "C", "filters": null}}"#
    );
    std::fs::write(path.join(".zarray"), meta).unwrap();
    std::fs::write(path.join("0.0.0"), chunk).unwrap();
    path
}

/// Chunks that decode to far more than a chunk holds without declaring it in a header zarrs
/// trusts are refused before zarrs decodes them: a Zstd frame of 32 MiB (RLE blocks, no
/// declared size) with a byte after it (no whole frames, so zarrs decodes by streaming), a
/// frame declaring 1 TiB followed by its CRC-32C (zarrs strips the checksum and allocates the
/// declared size: the process aborts), gzip and zlib streams of 32 MiB of zeros (zarrs
/// inflates them whole), and a shard read whole whose first inner chunk declares 1 TiB.
#[test]
fn chunks_that_decode_past_a_chunk_are_refused_before_they_are_decoded() {
    let dir = tempfile::tempdir().unwrap();
    // Magic; no declared size, not a single segment, a window of 128 KiB; 256 RLE blocks of
    // 128 KiB of one byte, the last one marked last.
    let mut streamed = vec![0x28, 0xb5, 0x2f, 0xfd, 0x00, 0x38];
    for k in 0..256u32 {
        let header = (131_072 << 3) | (1 << 1) | u32::from(k == 255);
        streamed.extend_from_slice(&header.to_le_bytes()[..3]);
        streamed.push(7);
    }
    let whole = zstd::decode_all(&streamed[..]).unwrap();
    assert_eq!(whole.len(), 32 << 20, "the frame inflates to 32 MiB");
    streamed.push(0);
    let mut declared = vec![0x28, 0xb5, 0x2f, 0xfd, 0xe0];
    declared.extend_from_slice(&(1u64 << 40).to_le_bytes());
    declared.extend_from_slice(&[0x01, 0x00, 0x00]);
    let mut checked = declared.clone();
    checked.extend_from_slice(&crc32c::crc32c(&declared).to_le_bytes());
    let zeros = vec![0u8; 32 << 20];
    let gzip = {
        use std::io::Write;
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
        e.write_all(&zeros).unwrap();
        e.finish().unwrap()
    };
    let zlib = {
        use std::io::Write;
        let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
        e.write_all(&zeros).unwrap();
        e.finish().unwrap()
    };
    // A shard of 2×2×2 inner chunks: the first the 1 TiB frame, the others missing; its index
    // (offset, length) pairs at the end with their CRC-32C.
    let first_of_eight = |offset: u64, length: u64| {
        let mut entries = vec![(u64::MAX, u64::MAX); 8];
        entries[0] = (offset, length);
        shard_index(&entries)
    };
    let shard = [declared.clone(), first_of_eight(0, declared.len() as u64)].concat();
    let zstd_codecs = r#"[{"name": "bytes", "configuration": {"endian": "little"}},
        {"name": "zstd", "configuration": {"level": 0, "checksum": false}}]"#;
    let checked_codecs = r#"[{"name": "bytes", "configuration": {"endian": "little"}},
        {"name": "zstd", "configuration": {"level": 0, "checksum": false}},
        {"name": "crc32c"}]"#;
    let shard_codecs = format!(
        r#"[{{"name": "sharding_indexed", "configuration": {{"chunk_shape": [2, 2, 2],
            "codecs": {zstd_codecs},
            "index_codecs": [{{"name": "bytes", "configuration": {{"endian": "little"}}}},
                {{"name": "crc32c"}}], "index_location": "end"}}}}]"#
    );
    // A shard whose first entry reaches one byte into its index (zarrs only checks that an
    // entry ends within the shard): a byte, then the 32 MiB frame, then the index.
    let overlapping = [
        vec![0u8],
        streamed[..streamed.len() - 1].to_vec(),
        first_of_eight(1, streamed.len() as u64),
    ]
    .concat();
    let v3_zlib = r#"[{"name": "bytes", "configuration": {"endian": "little"}},
        {"name": "numcodecs.zlib", "configuration": {"level": 9}}]"#;
    let stores = [
        v3_store(dir.path(), "streamed", zstd_codecs, &streamed),
        v3_store(dir.path(), "checked", checked_codecs, &checked),
        v2_store(dir.path(), "gzip", r#"{"id": "gzip", "level": 9}"#, &gzip),
        v2_store(dir.path(), "zlib", r#"{"id": "zlib", "level": 9}"#, &zlib),
        v3_store(dir.path(), "v3-zlib", v3_zlib, &zlib),
        v3_store(dir.path(), "shard", &shard_codecs, &shard),
        v3_store(dir.path(), "overlapping-shard", &shard_codecs, &overlapping),
        // The 1 TiB shard with a CRC-32C of the whole shard after it.
        v3_store(
            dir.path(),
            "checksummed-shard",
            &shard_codecs.replace(
                r#""index_location": "end"}}]"#,
                r#""index_location": "end"}}, {"name": "crc32c"}]"#,
            ),
            &[shard.clone(), crc32c::crc32c(&shard).to_le_bytes().to_vec()].concat(),
        ),
    ];
    for store in &stores {
        let e = read_volume(store, None).unwrap_err().to_string();
        assert!(e.contains("declares"), "{}: {e}", store.display());
        let r = RegionReader::open(store, None).unwrap();
        let e = r.read_region([0, 0, 0], [4, 4, 4]).unwrap_err().to_string();
        assert!(e.contains("declares"), "{}: {e}", store.display());
        // A box inside the first chunk (of a shard: its first inner chunk alone, read by its
        // range in the shard).
        let e = r.read_region([0, 0, 0], [2, 2, 2]).unwrap_err().to_string();
        assert!(e.contains("declares"), "{}: {e}", store.display());
    }
    // The same codecs on honest chunks still read: the checks refuse only what overflows.
    let samples: Vec<u8> = (0..64u16).flat_map(|v| (v * 3).to_le_bytes()).collect();
    let framed = zstd::encode_all(&samples[..], 3).unwrap();
    let mut framed_checked = framed.clone();
    framed_checked.extend_from_slice(&crc32c::crc32c(&framed).to_le_bytes());
    let deflated = {
        use std::io::Write;
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
        e.write_all(&samples).unwrap();
        e.finish().unwrap()
    };
    let honest = [
        v3_store(
            dir.path(),
            "honest-checked",
            checked_codecs,
            &framed_checked,
        ),
        v2_store(
            dir.path(),
            "honest-gzip",
            r#"{"id": "gzip", "level": 9}"#,
            &deflated,
        ),
    ];
    let want: Vec<f32> = (0..64u16).map(|v| f32::from(v * 3)).collect();
    for store in &honest {
        let v = read_volume(store, None).unwrap();
        assert_eq!(v.channel(0), &want[..], "{}", store.display());
    }
    // A whole shard that decodes to far more than one of its inner chunks (2 MiB of 32 inner
    // chunks of 64 KiB) is checked chunk by chunk, not as one.
    let (shape, inner) = ([64usize, 128, 128], [32usize, 32, 32]);
    let value = |z: usize, y: usize, x: usize| ((z * 7 + y * 3 + x * 5) % 4099) as u16;
    let (mut frames, mut entries) = (Vec::new(), Vec::new());
    for cz in 0..shape[0] / inner[0] {
        for cy in 0..shape[1] / inner[1] {
            for cx in 0..shape[2] / inner[2] {
                let mut samples = Vec::new();
                for z in 0..inner[0] {
                    for y in 0..inner[1] {
                        for x in 0..inner[2] {
                            let v = value(cz * inner[0] + z, cy * inner[1] + y, cx * inner[2] + x);
                            samples.extend_from_slice(&v.to_le_bytes());
                        }
                    }
                }
                let frame = zstd::encode_all(&samples[..], 1).unwrap();
                entries.push((frames.len() as u64, frame.len() as u64));
                frames.extend_from_slice(&frame);
            }
        }
    }
    let data = [frames.clone(), shard_index(&entries)].concat();
    let path = dir.path().join("honest-shard");
    std::fs::create_dir_all(path.join("c/0/0")).unwrap();
    let meta = format!(
        r#"{{"zarr_format": 3, "node_type": "array", "shape": {shape:?}, "data_type": "uint16",
            "chunk_grid": {{"name": "regular", "configuration": {{"chunk_shape": {shape:?}}}}},
            "chunk_key_encoding": {{"name": "default", "configuration": {{"separator": "/"}}}},
            "fill_value": 0, "codecs": [{{"name": "sharding_indexed", "configuration": {{
            "chunk_shape": {inner:?}, "codecs": {zstd_codecs},
            "index_codecs": [{{"name": "bytes", "configuration": {{"endian": "little"}}}},
                {{"name": "crc32c"}}], "index_location": "end"}}}}]}}"#
    );
    std::fs::write(path.join("zarr.json"), &meta).unwrap();
    std::fs::write(path.join("c/0/0/0"), &data).unwrap();
    // The same shard with its index first: the offsets move by the index's length.
    let first = dir.path().join("honest-shard-index-first");
    std::fs::create_dir_all(first.join("c/0/0")).unwrap();
    let index_len = 16 * entries.len() as u64 + 4;
    let moved: Vec<(u64, u64)> = entries.iter().map(|(o, l)| (o + index_len, *l)).collect();
    let shard_first = [shard_index(&moved), frames].concat();
    std::fs::write(
        first.join("zarr.json"),
        meta.replace(r#""index_location": "end""#, r#""index_location": "start""#),
    )
    .unwrap();
    std::fs::write(first.join("c/0/0/0"), &shard_first).unwrap();
    // The same shard followed by a CRC-32C of it (`[sharding_indexed, crc32c]`).
    let checksummed = dir.path().join("honest-shard-checksummed");
    std::fs::create_dir_all(checksummed.join("c/0/0")).unwrap();
    std::fs::write(
        checksummed.join("zarr.json"),
        meta.replace(
            r#""index_location": "end"}}]"#,
            r#""index_location": "end"}}, {"name": "crc32c"}]"#,
        ),
    )
    .unwrap();
    let crc = crc32c::crc32c(&data);
    std::fs::write(
        checksummed.join("c/0/0/0"),
        [data.clone(), crc.to_le_bytes().to_vec()].concat(),
    )
    .unwrap();
    for store in [&path, &first, &checksummed] {
        let v = read_volume(store, None).unwrap();
        assert_eq!(v.dims(), [128, 128, 64]);
        for (i, got) in v.channel(0).iter().enumerate() {
            let (x, y, z) = (i % 128, (i / 128) % 128, i / (128 * 128));
            assert_eq!(
                *got,
                f32::from(value(z, y, x)),
                "{}: sample {i}",
                store.display()
            );
        }
        let r = RegionReader::open(store, None).unwrap();
        let part = r.read_region([40, 10, 20], [30, 50, 20]).unwrap();
        assert_eq!(
            part.channel(0)[0],
            f32::from(value(20, 10, 40)),
            "{}",
            store.display()
        );
    }
}

/// Chains of codecs whose chunks' decoded sizes the reader cannot check before zarrs decodes
/// them are refused when the array is opened, saying which: two compressors in a row (the
/// inner one's input is never seen by the store), a compressor after a shard's codec (the
/// inner chunks are decoded in memory), a shard inside a shard, a v2 compressor used as a
/// filter; a v2 CRC-32C in the compressor's place (its checksum before the data) is refused
/// by zarrs itself.
#[test]
fn codec_chains_the_reader_cannot_see_through_are_refused_saying_which() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = r#"{"name": "bytes", "configuration": {"endian": "little"}}"#;
    let zstd = r#"{"name": "zstd", "configuration": {"level": 1, "checksum": false}}"#;
    let gzip = r#"{"name": "gzip", "configuration": {"level": 1}}"#;
    let index = format!(r#""index_codecs": [{bytes}], "index_location": "end""#);
    let sharding = |codecs: &str| {
        format!(
            r#"{{"name": "sharding_indexed", "configuration": {{"chunk_shape": [2, 2, 2],
                "codecs": {codecs}, {index}}}}}"#
        )
    };
    let cases = [
        (
            v3_store(
                dir.path(),
                "two",
                &format!("[{bytes}, {zstd}, {gzip}]"),
                &[],
            ),
            "two compressors",
        ),
        (
            v3_store(
                dir.path(),
                "after-shard",
                &format!("[{}, {zstd}]", sharding(&format!("[{bytes}]"))),
                &[],
            ),
            "after sharding_indexed",
        ),
        (
            v3_store(
                dir.path(),
                "nested",
                &format!(
                    "[{}]",
                    sharding(&format!("[{}]", sharding(&format!("[{bytes}]"))))
                ),
                &[],
            ),
            "a shard inside a shard",
        ),
        (
            v2_store(dir.path(), "filter", r#"null"#, &[]),
            "the filter \"zstd\"",
        ),
        (
            v2_store(
                dir.path(),
                "crc-first",
                r#"{"id": "crc32c", "location": "start"}"#,
                &[],
            ),
            "crc32c",
        ),
    ];
    // The filter case: a v2 array whose filters hold a compressor.
    let zarray = dir.path().join("filter/.zarray");
    let meta = std::fs::read_to_string(&zarray).unwrap();
    std::fs::write(
        &zarray,
        meta.replace(
            r#""filters": null"#,
            r#""filters": [{"id": "zstd", "level": 1}]"#,
        ),
    )
    .unwrap();
    for (store, why) in &cases {
        let e = read_volume(store, None).unwrap_err().to_string();
        assert!(e.contains(why), "{}: {e}", store.display());
        let e = RegionReader::open(store, None).err().map(|e| e.to_string());
        assert!(
            e.as_ref().is_some_and(|e| e.contains(why)),
            "{}: {e:?}",
            store.display()
        );
    }
}

/// The sample of the hand-written channel arrays at time `t`, channel `c`, voxel `x, y, z`.
fn channel_sample(t: usize, c: usize, x: usize, y: usize, z: usize) -> f32 {
    (x + 10 * y + 100 * z + 1000 * c + 5000 * t) as f32
}

/// Of an array of several channels one is read, the one chosen, by every way in (a path, a
/// region reader, a bundle, a time series); none chosen, or one it lacks, is refused naming
/// the count; a source read with all its channels together (raw RGB) keeps the one chosen.
#[test]
fn a_channel_of_several_is_read_as_chosen_and_none_chosen_is_refused() {
    use wavesplat_compressor::reader::zarr::channels;
    use wavesplat_compressor::reader::{decode_source_channel, read_volume_channel};
    use wavesplat_compressor::series::{open_series_path, open_series_path_channel};
    let dir = tempfile::tempdir().unwrap();
    // t, c, z, y, x by count: one time point of three channels, and two of three.
    let value = |p: &[usize]| channel_sample(p[0], p[1], p[4], p[3], p[2]) as u16;
    let one = hand_written(
        dir.path(),
        "three",
        &[1, 3, 5, 6, 7],
        &[1, 1, 3, 4, 5],
        None,
        value,
        |_| false,
    );
    let series = hand_written(
        dir.path(),
        "series",
        &[2, 3, 5, 6, 7],
        &[1, 2, 3, 4, 5],
        None,
        value,
        |_| false,
    );
    let want = |t: usize, c: usize, o: [usize; 3], s: [usize; 3]| {
        let mut out = Vec::new();
        for z in o[2]..o[2] + s[2] {
            for y in o[1]..o[1] + s[1] {
                for x in o[0]..o[0] + s[0] {
                    out.push(channel_sample(t, c, x, y, z));
                }
            }
        }
        out
    };
    assert_eq!(channels(&one).unwrap(), 3);
    assert_eq!(channels(&series).unwrap(), 3);
    let refused = |e: ReadError, what: &str| {
        assert!(
            matches!(e, ReadError::Channels { channels: 3, .. }),
            "{e:?}"
        );
        let e = e.to_string();
        assert!(e.contains("3 channels") && e.contains(what), "{e}");
        assert!(e.contains("from 0 to 2") && e.contains("--channel"), "{e}");
    };
    refused(read_volume(&one, None).unwrap_err(), "axis 1");
    refused(RegionReader::open(&one, None).unwrap_err(), "axis 1");
    let bundle = SourceFiles::gather(&one, None).unwrap();
    refused(decode_source(&bundle, None).unwrap_err(), "axis 1");
    for (c, none) in [(3, "channel 3"), (17, "channel 17")] {
        refused(read_volume_channel(&one, None, Some(c)).unwrap_err(), none);
        let e = RegionReader::open_channel(&one, None, Some(c)).unwrap_err();
        refused(e, none);
    }
    let (o, s) = ([2, 1, 1], [5, 4, 3]);
    for c in 0..3 {
        let whole = read_volume_channel(&one, None, Some(c)).unwrap();
        assert_eq!(whole.dims(), [7, 6, 5]);
        assert_eq!(whole.channel_count(), 1);
        assert_eq!(
            whole.channel(0),
            &want(0, c, [0; 3], [7, 6, 5])[..],
            "channel {c}"
        );
        let bundled = decode_source_channel(&bundle, None, Some(c)).unwrap();
        assert_eq!(bundled, whole, "channel {c} from a bundle");
        let r = RegionReader::open_channel(&one, None, Some(c)).unwrap();
        assert_eq!(r.channels(), 1);
        assert_eq!(
            r.read_region(o, s).unwrap().channel(0),
            &want(0, c, o, s)[..]
        );
    }
    // A time series of channels: each time point's region of the channel chosen.
    match open_series_path(&series, None) {
        Err(wavesplat_compressor::series::SeriesError::Read(e)) => refused(*e, "axis 1"),
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("a series of three channels read without a choice"),
    }
    let input = open_series_path_channel(&series, None, Some(2))
        .unwrap()
        .expect("a series");
    let source = input.source();
    assert_eq!(source.time_points(), 2);
    for t in 0..2 {
        let got = source.read_at(t, o.map(|v| v as u64), s).unwrap();
        assert_eq!(got.channel(0), &want(t, 2, o, s)[..], "time point {t}");
    }

    // Raw RGB, read with its channels together: the one chosen kept, as one channel.
    use wavesplat_compressor::reader::{RawDtype, RawSpec};
    let dims = [4, 3, 2];
    let rgb: Vec<u8> = (0..24 * 3).map(|i| (i * 7 % 251) as u8).collect();
    let raw_path = dir.path().join("rgb.bin");
    std::fs::write(&raw_path, &rgb).unwrap();
    let mut spec = RawSpec::new(dims, RawDtype::from_name("u8").unwrap());
    spec.channels = 3;
    let all = read_volume(&raw_path, Some(&spec)).unwrap();
    assert_eq!(all.channel_count(), 3);
    for c in 0..3 {
        let kept = read_volume_channel(&raw_path, Some(&spec), Some(c)).unwrap();
        assert_eq!(kept.channel_count(), 1);
        assert_eq!(kept.channel(0), all.channel(c), "RGB channel {c}");
        let r = RegionReader::open_channel(&raw_path, Some(&spec), Some(c)).unwrap();
        assert_eq!(r.channels(), 1);
        let region = r.read_region([1, 1, 0], [2, 2, 2]).unwrap();
        let whole = r.read_region([0, 0, 0], dims).unwrap();
        assert_eq!(whole.channel(0), all.channel(c));
        assert_eq!(region.channel(0)[0], all.channel(c)[all.index(1, 1, 0)]);
    }
    let e = read_volume_channel(&raw_path, Some(&spec), Some(3)).unwrap_err();
    assert!(matches!(e, ReadError::Channels { channels: 3, .. }), "{e}");
    let e = RegionReader::open_channel(&raw_path, Some(&spec), Some(3)).unwrap_err();
    assert!(matches!(e, ReadError::Channels { channels: 3, .. }), "{e}");
    // One channel: 0 is it, 1 is refused.
    spec.channels = 1;
    std::fs::write(&raw_path, &rgb[..24]).unwrap();
    let single = read_volume_channel(&raw_path, Some(&spec), Some(0)).unwrap();
    assert_eq!(single, read_volume(&raw_path, Some(&spec)).unwrap());
    let e = read_volume_channel(&raw_path, Some(&spec), Some(1)).unwrap_err();
    assert!(e.to_string().contains("1 channel,"), "{e}");
}
