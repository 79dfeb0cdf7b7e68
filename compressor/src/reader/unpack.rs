//! Unpacking a source bundle (the multi-file layout of [`SourceFiles::to_bytes`]) from a
//! stream into a directory, one file at a time, so that an uploaded bundle larger than memory
//! (a DICOM series of thousands of slices, a detached header and its data) becomes files that
//! a [`RegionReader`](super::region::RegionReader) reads by region, as it reads the same
//! source on shared storage. The bundle is untrusted: its counts are bounded, every length is
//! checked against what the stream holds, and every name must be a relative path that stays
//! inside the directory.
//!
//! [`SourceFiles::to_bytes`]: super::SourceFiles::to_bytes

use std::collections::HashSet;
use std::io::{self, Read};
use std::path::{Component, Path, PathBuf};

use super::{bundle_format, Format, ReadError, BUNDLE_MAGIC, MAX_SOURCE_FILES};

/// What [`unpack_bundle`] wrote.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnpackedBundle {
    /// The format the bundle names (`None`: to be found from the files). A reader of the
    /// files finds it again from their names and contents, as for a source on disk.
    pub format: Option<Format>,
    /// What to open: the directory for a DICOM series, else the primary (first) file.
    pub primary: PathBuf,
    /// Files written.
    pub files: usize,
    /// Bytes of file content written.
    pub bytes: u64,
}

/// Reads a bundle from `r` (its magic first) and writes its files under `dir`, which must
/// exist; a name with directories creates them inside `dir`. Refused as
/// [`ReadError::Bundle`]: a wrong magic, an unknown format name, a file count of 0 or above
/// [`MAX_SOURCE_FILES`], a name that is empty, not UTF-8, absolute or leads out of `dir`
/// (`..`), a name given twice, a stream that ends inside a file, and bytes after the last
/// file. What was written before a refusal stays in `dir` (its owner removes it).
pub fn unpack_bundle(r: &mut dyn Read, dir: &Path) -> Result<UnpackedBundle, ReadError> {
    let bad = |m: String| ReadError::Bundle(m);
    let mut magic = [0u8; BUNDLE_MAGIC.len()];
    read_exact(r, &mut magic, "magic")?;
    if &magic != BUNDLE_MAGIC {
        return Err(bad("not a source bundle (wrong magic)".into()));
    }
    let mut flen = [0u8; 1];
    read_exact(r, &mut flen, "format name")?;
    let mut fname = vec![0u8; flen[0] as usize];
    read_exact(r, &mut fname, "format name")?;
    let format = bundle_format(&fname)?;
    let mut count = [0u8; 4];
    read_exact(r, &mut count, "file count")?;
    let count = u32::from_le_bytes(count) as usize;
    if count == 0 || count > MAX_SOURCE_FILES {
        return Err(bad(format!(
            "file count {count} is not within 1..={MAX_SOURCE_FILES}"
        )));
    }
    let (mut seen, mut dirs) = (HashSet::new(), HashSet::new());
    let (mut primary, mut bytes) = (None, 0u64);
    for i in 0..count {
        let mut nl = [0u8; 2];
        read_exact(r, &mut nl, "name length")?;
        let mut name = vec![0u8; u16::from_le_bytes(nl) as usize];
        read_exact(r, &mut name, "name")?;
        let name =
            String::from_utf8(name).map_err(|_| bad(format!("file {i}: name is not UTF-8")))?;
        let relative = inside(&name)?;
        // A name given twice, or a file where another name needs a directory (`a` and
        // `a/b`, either way round).
        let clash = seen.contains(&relative)
            || dirs.contains(&relative)
            || relative.ancestors().skip(1).any(|a| seen.contains(a));
        if clash {
            return Err(bad(format!(
                "file {name:?} appears twice or clashes with another file's directory"
            )));
        }
        seen.insert(relative.clone());
        dirs.extend(relative.ancestors().skip(1).map(Path::to_path_buf));
        let mut len = [0u8; 8];
        read_exact(r, &mut len, "file length")?;
        let len = u64::from_le_bytes(len);
        let path = dir.join(&relative);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|e| ReadError::io(parent, e))?;
        }
        let mut out = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(|e| ReadError::io(&path, e))?;
        let copied = io::copy(&mut r.take(len), &mut out).map_err(|e| ReadError::io(&path, e))?;
        if copied != len {
            return Err(bad(format!(
                "file {name:?} claims {len} bytes, the bundle ends after {copied}"
            )));
        }
        bytes += len;
        primary.get_or_insert(path);
    }
    let mut one = [0u8; 1];
    if read_some(r, &mut one)? > 0 {
        return Err(bad("trailing bytes after the last file".into()));
    }
    let primary = match (format, primary) {
        // An OME companion file first: the dataset is read from it (its TIFFs are parts).
        (Some(Format::Tiff), Some(p))
            if p.file_name()
                .is_some_and(|n| super::tiff_stack::is_companion_name(&n.to_string_lossy())) =>
        {
            p
        }
        (Some(Format::Dicom | Format::Tiff | Format::Zarr), _) => dir.to_path_buf(),
        (_, p) => p.expect("count ≥ 1"),
    };
    Ok(UnpackedBundle {
        format,
        primary,
        files: count,
        bytes,
    })
}

/// Most directories a bundle's file name may descend (a DICOM series' names have none, a
/// header's data file one or two): deep names would make many directories for few bytes.
pub const MAX_NAME_DEPTH: usize = 8;

/// Longest file name in a bundle (bytes).
pub const MAX_NAME_BYTES: usize = 1024;

/// `name` as a path inside the unpacking directory: relative, made of plain components, at
/// most [`MAX_NAME_DEPTH`] directories deep and [`MAX_NAME_BYTES`] long.
fn inside(name: &str) -> Result<PathBuf, ReadError> {
    if name.len() > MAX_NAME_BYTES {
        return Err(ReadError::Bundle(format!(
            "a file name of {} bytes; at most {MAX_NAME_BYTES}",
            name.len()
        )));
    }
    let mut out = PathBuf::new();
    for c in Path::new(name).components() {
        match c {
            Component::Normal(part) => out.push(part),
            Component::CurDir => {}
            _ => {
                return Err(ReadError::Bundle(format!(
                    "file {name:?}: a name must stay inside the source's directory (no \
                     absolute path, no `..`); a header naming its data file so cannot be \
                     unpacked: submit the volume from shared storage instead"
                )))
            }
        }
    }
    if out.as_os_str().is_empty() {
        return Err(ReadError::Bundle(format!("file name {name:?} is empty")));
    }
    if out.components().count() > MAX_NAME_DEPTH + 1 {
        return Err(ReadError::Bundle(format!(
            "file {name:?} lies more than {MAX_NAME_DEPTH} directories deep"
        )));
    }
    Ok(out)
}

fn read_exact(r: &mut dyn Read, buf: &mut [u8], what: &str) -> Result<(), ReadError> {
    let mut got = 0;
    while got < buf.len() {
        match read_some(r, &mut buf[got..])? {
            0 => return Err(ReadError::Bundle(format!("truncated {what}"))),
            n => got += n,
        }
    }
    Ok(())
}

fn read_some(r: &mut dyn Read, buf: &mut [u8]) -> Result<usize, ReadError> {
    loop {
        match r.read(buf) {
            Ok(n) => return Ok(n),
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(ReadError::io(Path::new("(source bundle)"), e)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reader::{SourceFiles, SourceListing};

    fn bundle(format: Option<Format>, files: &[(&str, &[u8])]) -> Vec<u8> {
        SourceFiles {
            origin: PathBuf::from("x"),
            base: PathBuf::new(),
            format,
            files: files
                .iter()
                .map(|(n, b)| (n.to_string(), b.to_vec()))
                .collect(),
        }
        .to_bytes()
    }

    #[test]
    fn a_listed_source_unpacks_into_the_same_files() {
        // A detached header and its data in a subdirectory, streamed as an upload streams it.
        let src = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(src.path().join("data")).unwrap();
        let header = b"ObjectType = Image\nNDims = 3\nDimSize = 2 2 1\nElementType = MET_UCHAR\nElementDataFile = data/v.raw\n";
        std::fs::write(src.path().join("v.mhd"), header).unwrap();
        std::fs::write(src.path().join("data/v.raw"), [1u8, 2, 3, 4]).unwrap();
        let listing = SourceListing::list(&src.path().join("v.mhd"), None).unwrap();
        assert_eq!(listing.files.len(), 2, "{listing:?}");
        let mut streamed = Vec::new();
        listing.write_to(&mut streamed).unwrap();
        let out = tempfile::tempdir().unwrap();
        let got = unpack_bundle(&mut streamed.as_slice(), out.path()).unwrap();
        assert_eq!(got.format, Some(Format::MetaImage));
        assert_eq!(got.primary, out.path().join("v.mhd"));
        assert_eq!((got.files, got.bytes), (2, header.len() as u64 + 4));
        assert_eq!(std::fs::read(out.path().join("v.mhd")).unwrap(), header);
        assert_eq!(
            std::fs::read(out.path().join("data/v.raw")).unwrap(),
            [1, 2, 3, 4]
        );
        // A DICOM series opens as its directory.
        let b = bundle(Some(Format::Dicom), &[("a.dcm", b"x"), ("b.dcm", b"yz")]);
        let out = tempfile::tempdir().unwrap();
        let got = unpack_bundle(&mut b.as_slice(), out.path()).unwrap();
        assert_eq!(got.primary, out.path());
        assert_eq!(std::fs::read(out.path().join("b.dcm")).unwrap(), b"yz");
    }

    #[test]
    fn a_hostile_bundle_is_refused_and_writes_nothing_outside() {
        let refused = |bytes: &[u8], needle: &str| {
            let root = tempfile::tempdir().unwrap();
            let dir = root.path().join("in");
            std::fs::create_dir(&dir).unwrap();
            match unpack_bundle(&mut &bytes[..], &dir) {
                Err(ReadError::Bundle(m)) => assert!(m.contains(needle), "{m:?} ≠ {needle:?}"),
                other => panic!("{needle}: {other:?}"),
            }
            // Nothing beside the unpacking directory.
            let beside: Vec<_> = std::fs::read_dir(root.path()).unwrap().collect();
            assert_eq!(beside.len(), 1, "{needle}: {beside:?}");
        };
        for name in ["../evil", "/etc/evil", "a/../../evil", "", "."] {
            let b = bundle(None, &[("ok", b"1"), (name, b"2")]);
            refused(
                &b,
                if name.is_empty() || name == "." {
                    "empty"
                } else {
                    "inside"
                },
            );
        }
        refused(&bundle(None, &[("a", b"1"), ("./a", b"2")]), "twice");
        refused(&bundle(None, &[("a", b"1"), ("a/b", b"2")]), "clashes");
        refused(&bundle(None, &[("a/b", b"1"), ("a", b"2")]), "clashes");
        let deep = "d/".repeat(MAX_NAME_DEPTH + 1) + "f";
        refused(&bundle(None, &[("a", b"1"), (deep.as_str(), b"2")]), "deep");
        let long = "n".repeat(MAX_NAME_BYTES + 1);
        refused(
            &bundle(None, &[("a", b"1"), (long.as_str(), b"2")]),
            "at most",
        );
        // As deep as allowed is taken.
        let ok = "d/".repeat(MAX_NAME_DEPTH) + "f";
        let root = tempfile::tempdir().unwrap();
        unpack_bundle(
            &mut &bundle(None, &[("a", b"1"), (ok.as_str(), b"2")])[..],
            root.path(),
        )
        .unwrap();
        let good = bundle(Some(Format::Nrrd), &[("v.nhdr", b"h"), ("v.raw", b"1234")]);
        refused(&good[..good.len() - 1], "claims 4 bytes");
        for cut in 1..good.len() - 4 {
            let root = tempfile::tempdir().unwrap();
            assert!(
                unpack_bundle(&mut &good[..cut], root.path()).is_err(),
                "cut {cut}"
            );
        }
        let mut trailing = good.clone();
        trailing.push(0);
        refused(&trailing, "trailing");
        let mut wrong = good.clone();
        wrong[0] = b'X';
        refused(&wrong, "magic");
        let mut format = good.clone();
        format[BUNDLE_MAGIC.len() + 1] = b'x';
        refused(&format, "format");
        let mut huge = good[..BUNDLE_MAGIC.len() + 1 + 4].to_vec();
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        refused(&huge, "file count");
        let mut zero = good[..BUNDLE_MAGIC.len() + 1 + 4].to_vec();
        zero.extend_from_slice(&0u32.to_le_bytes());
        refused(&zero, "file count");
        let mut not_utf8 = bundle(None, &[("a", b"1"), ("bb", b"2")]);
        let at = not_utf8.windows(2).position(|w| w == b"bb").unwrap();
        not_utf8[at] = 0xff;
        refused(&not_utf8, "UTF-8");
    }
}
