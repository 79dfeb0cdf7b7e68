//! TIFF stacks, the format of microscopy, micro-CT and synchrotron volumes: a multi-page TIFF
//! (BigTIFF included; ImageJ and OME-TIFF stacks) holds one slice per page, and a directory of
//! TIFF files is one stack, its files in the natural order of their names (`z2` before `z10`),
//! each file's pages in order. Grey samples of 8 to 64 bits (unsigned, signed or float, half
//! floats too) and RGB, in every compression the `tiff` crate decodes (none, LZW, Deflate,
//! PackBits, JPEG), in strips or tiles. Pages marked as reduced-resolution copies (thumbnails,
//! pyramid levels) are skipped. An ImageJ stack over 4 GB (one page directory, its description
//! counting the images that follow the first's samples) is read as ImageJ reads it.
//!
//! Spacing, in mm: an ImageJ description's `spacing=` (z) and the resolution tags (x, y, pixels
//! per unit) in its `unit=`, or OME-XML's `PhysicalSizeX/Y/Z` in their units; else 1 on every
//! axis (the stack says nothing physical). An ImageJ hyperstack of several time frames, or an
//! OME-TIFF of several time points (`SizeT`, its planes in its `DimensionOrder`, seconds between
//! them from `TimeIncrement`), is a time series. Channels stored as planes of their own (an
//! ImageJ hyperstack's `channels`, OME's `SizeC` over grey pages, in ImageJ's or the
//! `DimensionOrder`'s plane order) are read one at a time, the one chosen; none chosen is
//! refused, naming the count. A multi-file OME-TIFF (one acquisition over several files, as
//! Micro-Manager and Bio-Formats write one over 4 GB or a file a plane) is read from the file
//! holding its first plane and an XML whose `TiffData` elements place every plane in a page of
//! a file beside it, each plane once, or from its OME companion file (`NAME.companion.ome`, the
//! XML alone, as Bio-Formats writes one); a part given alone (its XML placing the first plane
//! elsewhere, or a `BinaryOnly` pointer to the XML) is refused naming the file to read. Refused,
//! saying why: palette, CMYK, YCbCr, alpha,
//! inverted grey (`WhiteIsZero`), bilevel and planar colour pages, pages of different sizes or
//! sample types, several OME images in one file, and a file whose ImageJ description counts
//! more images than it has pages where they cannot follow the first (compressed), or do not
//! (truncated).
//!
//! Decoding is the `tiff` crate's (image-rs): this module picks the pages, checks that they form
//! one volume, and reads a region's slices chunk by chunk (a strip or a tile), decoding only the
//! chunks the region covers, and uncompressed strips as bytes, only the region's rows
//! ([`TiffRegions`]), so that a stack larger than memory is read brick by brick. A compressed
//! chunk that several regions share (a page in one strip under all the bricks of a plane) is
//! decoded into a temporary file once they share it, not again for each, and its bytes released
//! once they have all read it (`crate::reader::spool`).

use std::fs::File;
use std::io::{BufReader, Cursor, Read, Seek};
use std::path::{Path, PathBuf};

use ::tiff::decoder::{ChunkType, Decoder, DecodingResult, Limits};
use ::tiff::tags::Tag;
use ::tiff::ColorType;

mod spooled;

use self::spooled::TiffSpool;
use super::{deinterleave, Endian, ReadError, SampleType, SourceFiles};
use wavesplat_codec::volume::{checked_voxels, Volume};

const FORMAT: &str = "TIFF";

/// Largest decoded chunk (a strip or a tile), and of a tag's values (an OME-XML description of
/// a large acquisition exceeds the crate's default MiB).
const CHUNK_LIMIT: usize = 1 << 30;

/// Most sample bytes a file may declare per byte of its own (beyond [`DECLARED_SLACK`]): what
/// TIFF's LZW reaches on constant data (about 1365: a blank slice; Deflate's limit is 1032,
/// PackBits' 64), with room. A header declaring more is refused before anything that large is
/// allocated (a few bytes must not claim a gigabyte image); only a JPEG-compressed blank page
/// goes further.
const MAX_EXPANSION: u64 = 1400;
const DECLARED_SLACK: u64 = 1 << 20;

fn bad(path: &Path, reason: impl Into<String>) -> ReadError {
    ReadError::bad_header(path, FORMAT, reason)
}

/// A decoding failure of the `tiff` crate, as a read error of `path`.
fn failed(path: &Path, e: ::tiff::TiffError) -> ReadError {
    match e {
        ::tiff::TiffError::IoError(e) => ReadError::io(path, e),
        ::tiff::TiffError::UnsupportedError(e) => ReadError::unsupported(path, e.to_string()),
        ::tiff::TiffError::LimitsExceeded => ReadError::unsupported(
            path,
            format!("a strip or tile larger than {CHUNK_LIMIT} bytes"),
        ),
        e => bad(path, e.to_string()),
    }
}

/// Whether a file name says TIFF (`.tif`, `.tiff`, any case).
pub(crate) fn is_tiff_name(name: &str) -> bool {
    let n = name.to_ascii_lowercase();
    n.ends_with(".tif") || n.ends_with(".tiff")
}

/// Whether the first bytes are a TIFF's or a BigTIFF's (either byte order).
pub(crate) fn looks_like_tiff(head: &[u8]) -> bool {
    [b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"]
        .iter()
        .any(|m| head.starts_with(*m))
}

/// The TIFF files directly inside `dir` (not hidden, regular), in the natural order of their
/// names; empty when there are none.
pub(crate) fn stack_files(dir: &Path) -> Result<Vec<(String, PathBuf)>, ReadError> {
    let entries = std::fs::read_dir(dir).map_err(|e| ReadError::io(dir, e))?;
    let mut files = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| ReadError::io(dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') || !is_tiff_name(&name) {
            continue;
        }
        let path = entry.path();
        if std::fs::metadata(&path).is_ok_and(|m| m.is_file()) {
            files.push((name, path));
        }
    }
    files.sort_by(|a, b| natural_order(&a.0, &b.0));
    Ok(files)
}

/// Why the numbers of a stack's slice files, in their order, leave a slice out, if they do:
/// files named alike but for one number (`slice_0049.tif`, `slice_0051.tif`; other numbers the
/// same in every name) whose values do not go up in one step (a file missing, which would
/// close the gap in the volume without a word) or repeat (`z1.tif` beside `z01.tif`). Names
/// numbered otherwise are not judged.
fn numbering_gap(names: &[PathBuf]) -> Option<String> {
    if names.len() < 3 {
        return None;
    }
    let files: Vec<String> = names
        .iter()
        .map(|p| Some(p.file_name()?.to_string_lossy().into_owned()))
        .collect::<Option<_>>()?;
    let all: Vec<Vec<(bool, &str)>> = files.iter().map(|f| digit_runs(f)).collect();
    let first = &all[0];
    if all.iter().any(|r| r.len() != first.len()) {
        return None;
    }
    // The one run that differs between names must be a number; every other run the same.
    let differing: Vec<usize> = (0..first.len())
        .filter(|&k| all.iter().any(|r| r[k] != first[k]))
        .collect();
    let [k] = differing[..] else {
        return None;
    };
    let numbers: Vec<u128> = all
        .iter()
        .map(|r| r[k].1.parse().ok())
        .collect::<Option<_>>()?;
    // Files listed out of order (a bundle names its files in its own order) are not judged.
    if numbers.windows(2).any(|w| w[1] < w[0]) {
        return None;
    }
    let step = numbers.windows(2).map(|w| w[1] - w[0]).min()?;
    if step == 0 {
        let i = numbers.windows(2).position(|w| w[0] == w[1])?;
        return Some(format!(
            "the slice files {:?} and {:?} have the same number",
            files[i],
            files[i + 1]
        ));
    }
    let i = numbers.windows(2).position(|w| w[1] - w[0] != step)?;
    let missing = (numbers[i + 1] - numbers[i]) / step - 1;
    Some(format!(
        "the slice files are numbered in steps of {step}, but {} slice(s) between {:?} and {:?} \
         are missing (there are {} files, numbered {} to {}): the stack would close the gap \
         without a word; add the missing files, or number the files without the gap if none is \
         meant",
        missing.max(1),
        files[i],
        files[i + 1],
        names.len(),
        numbers[0],
        numbers[numbers.len() - 1]
    ))
}

/// A name as its runs of digits and of other characters, each with whether it is digits.
fn digit_runs(s: &str) -> Vec<(bool, &str)> {
    let mut out = Vec::new();
    let mut start = 0;
    let bytes = s.as_bytes();
    for i in 1..=bytes.len() {
        if i == bytes.len() || bytes[i].is_ascii_digit() != bytes[start].is_ascii_digit() {
            out.push((bytes[start].is_ascii_digit(), &s[start..i]));
            start = i;
        }
    }
    out
}

/// Natural order of names: runs of digits compare as numbers (`z2` < `z10`), the rest as text.
fn natural_order(a: &str, b: &str) -> std::cmp::Ordering {
    let (ra, rb) = (digit_runs(a), digit_runs(b));
    for ((da, sa), (db, sb)) in ra.iter().zip(&rb) {
        let o = if *da && *db {
            let (ta, tb) = (sa.trim_start_matches('0'), sb.trim_start_matches('0'));
            ta.len().cmp(&tb.len()).then_with(|| ta.cmp(tb))
        } else {
            sa.cmp(sb)
        };
        if o.is_ne() {
            return o;
        }
    }
    ra.len().cmp(&rb.len()).then_with(|| a.cmp(b))
}

/// What a page holds: its size, channels and sample kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct PageShape {
    width: usize,
    height: usize,
    channels: usize,
    /// Bits per sample.
    bits: u8,
    /// `SampleFormat`: 1 unsigned, 2 signed, 3 float.
    format: u16,
}

impl PageShape {
    /// Bytes of the page's samples, uncompressed.
    fn bytes(&self) -> u64 {
        (self.width * self.height * self.channels * usize::from(self.bits) / 8) as u64
    }

    fn describe(&self) -> String {
        let kind = match self.format {
            2 => "signed",
            3 => "float",
            _ => "unsigned",
        };
        format!(
            "{}x{}, {} channel(s) of {}-bit {kind}",
            self.width, self.height, self.channels, self.bits
        )
    }
}

/// What the first page's description and tags say of the whole stack.
#[derive(Debug, Default, Clone)]
struct StackMeta {
    spacing: [Option<f64>; 3],
    /// The images an ImageJ description counts.
    imagej_images: Option<usize>,
    /// The time points of an ImageJ hyperstack or an OME-TIFF (`SizeT`), when more than 1.
    frames: Option<usize>,
    /// Whether a time point's slices follow one another (ImageJ; OME's `DimensionOrder` with
    /// Z before T), else each slice's time points do.
    time_major: bool,
    /// Seconds between time points (OME's `TimeIncrement`, ImageJ's `finterval`), when given.
    time_step: Option<f64>,
    /// The slices of one time point the description gives (ImageJ's `slices`, OME's `SizeZ`).
    slices: Option<usize>,
    /// OME's `SizeC`: samples a pixel (3 for RGB pages), not only separate channels.
    ome_size_c: Option<usize>,
    /// Channels stored as planes of their own (an ImageJ hyperstack's `channels`, an
    /// OME-TIFF's `SizeC` over pages of one sample), when more than 1: one is read.
    channels: Option<usize>,
    /// The planes' order, fastest first: a permutation of `b"ZCT"` (ImageJ's is C, Z, T; OME's
    /// its `DimensionOrder` after X and Y).
    plane_order: [u8; 3],
    /// An ImageJ stack over 4 GB: one page directory, every image's samples one after another.
    contiguous: Option<Contiguous>,
    /// The file's place in a multi-file OME-TIFF, when it is one's.
    ome: Option<std::sync::Arc<OmeRole>>,
    /// Why its XML's placing of planes is refused (said where its place matters: not for a
    /// part of a dataset an OME companion file places).
    ome_refusal: Option<std::sync::Arc<str>>,
}

/// One `TiffData` element of OME-XML: the planes from (`FirstZ`, `FirstC`, `FirstT`) on, in
/// the `DimensionOrder`, lie in the pages from `IFD` on of the file its `UUID` child names
/// (none: the file holding the XML), `PlaneCount` of them.
#[derive(Debug, Clone, PartialEq)]
struct TiffData {
    /// The `UUID` child's `FileName` and its text (the file's UUID).
    file: Option<String>,
    uuid: Option<String>,
    /// `IFD`, when the element gives it (default 0).
    ifd: Option<usize>,
    /// `FirstZ`, `FirstC`, `FirstT` (default 0).
    first: [usize; 3],
    /// `PlaneCount`, when given (default: 1 with an `IFD`, else every page of the file).
    count: Option<usize>,
}

/// A multi-file OME-TIFF (one acquisition written over several TIFF files, as Micro-Manager
/// and Bio-Formats write one over 4 GB or per plane): its files, the one holding the XML (and
/// the dataset's first plane) first, then the others in the order the XML names them, and
/// where the planes lie, each `TiffData` with its file's index.
#[derive(Debug, Clone, PartialEq)]
struct OmeDataset {
    files: Vec<String>,
    tiff_data: Vec<(usize, TiffData)>,
}

/// A TIFF file's place in a multi-file OME-TIFF.
#[derive(Debug, Clone, PartialEq)]
enum OmeRole {
    /// It holds the dataset's first plane (and an XML placing every plane): the dataset is
    /// read from it.
    Holds(OmeDataset),
    /// A part: the dataset is read from the named file (the one holding its first plane, or
    /// its XML: `BinaryOnly`'s `MetadataFile`).
    PartOf(String),
}

/// The value of attribute `key` of an XML element (namespace prefixes aside).
fn xml_element_attr(
    e: &quick_xml::events::BytesStart<'_>,
    key: &[u8],
) -> Result<Option<String>, String> {
    for a in e.attributes() {
        let a = a.map_err(|err| format!("OME-XML: {err}"))?;
        if a.key.local_name().as_ref() == key {
            let v = a
                .normalized_value(quick_xml::XmlVersion::Implicit1_0)
                .map_err(|err| format!("OME-XML: {err}"))?;
            return Ok(Some(v.into_owned()));
        }
    }
    Ok(None)
}

/// A count attribute of a `TiffData` element.
fn tiff_data_count(
    e: &quick_xml::events::BytesStart<'_>,
    key: &str,
) -> Result<Option<usize>, String> {
    xml_element_attr(e, key.as_bytes())?
        .map(|v| {
            v.trim()
                .parse::<usize>()
                .map_err(|_| format!("a TiffData element's {key} is not a count: {v:?}"))
        })
        .transpose()
}

/// Where an OME-XML text's planes lie: its `TiffData` elements, and its `BinaryOnly`
/// element's metadata file (the XML lies there).
struct OmePlacement {
    tiff_data: Vec<TiffData>,
    metadata_file: Option<String>,
    /// The `OME` element's `UUID`: the file's own, whatever its name now.
    own_uuid: Option<String>,
}

/// The [`OmePlacement`] of an OME-XML text; `None` for a text that is not well-formed XML or
/// whose placing elements are not read (an attribute malformed, a count that is no number):
/// nothing is placed then, and the stack is read as its pages come, as before placements were
/// read (its counts still checked against its pages).
fn ome_placement(xml: &str) -> Option<OmePlacement> {
    read_ome_placement(xml).ok().flatten()
}

/// [`ome_placement`], saying why not.
fn read_ome_placement(xml: &str) -> Result<Option<OmePlacement>, String> {
    use quick_xml::events::Event;
    let mut reader = quick_xml::Reader::from_str(xml);
    let (mut placed, mut metadata_file, mut own_uuid) = (Vec::new(), None, None);
    // A `TiffData` element whose children (its `UUID`) are being read, and whether its
    // `UUID`'s text is.
    let mut open: Option<TiffData> = None;
    let mut in_uuid = false;
    loop {
        let event = match reader.read_event() {
            Ok(e) => e,
            Err(_) => return Ok(None),
        };
        match &event {
            Event::Start(e) | Event::Empty(e) => match e.local_name().as_ref() {
                b"TiffData" => {
                    let first = ["FirstZ", "FirstC", "FirstT"]
                        .map(|k| tiff_data_count(e, k).map(|v| v.unwrap_or(0)));
                    let [z, c, t] = first;
                    let data = TiffData {
                        file: None,
                        uuid: None,
                        ifd: tiff_data_count(e, "IFD")?,
                        first: [z?, c?, t?],
                        count: tiff_data_count(e, "PlaneCount")?,
                    };
                    if placed.len() == MAX_TIFF_DATA {
                        return Err(format!(
                            "its OME-XML has more than {MAX_TIFF_DATA} TiffData elements"
                        ));
                    }
                    if matches!(event, Event::Empty(_)) {
                        placed.push(data);
                    } else {
                        open = Some(data);
                    }
                }
                b"UUID" => {
                    if let Some(data) = open.as_mut() {
                        data.file = xml_element_attr(e, b"FileName")?;
                        in_uuid = matches!(event, Event::Start(_));
                    }
                }
                b"BinaryOnly" => metadata_file = xml_element_attr(e, b"MetadataFile")?,
                b"OME" => own_uuid = xml_element_attr(e, b"UUID")?,
                _ => {}
            },
            Event::Text(t) if in_uuid => {
                if let (Some(data), Ok(text)) = (open.as_mut(), t.decode()) {
                    data.uuid = Some(text.trim().to_string());
                }
            }
            Event::End(e) => match e.local_name().as_ref() {
                b"TiffData" => placed.extend(open.take()),
                b"UUID" => in_uuid = false,
                _ => {}
            },
            Event::Eof => break,
            _ => {}
        }
    }
    Ok(Some(OmePlacement {
        tiff_data: placed,
        metadata_file,
        own_uuid,
    }))
}

/// A file name an OME-XML gives, checked to name a file beside the one holding the XML (a
/// path elsewhere is refused: a worker reads the files of a volume from one directory), and,
/// where the file is to be read (`tiff`), a visible TIFF file: an XML naming `.env` or a
/// socket must not have it listed, hashed and uploaded.
fn sibling_name(name: &str, tiff: bool) -> Result<&str, String> {
    let plain =
        !name.is_empty() && name != "." && name != ".." && !name.contains(['/', '\\', '\0']);
    if plain && (!tiff || (!name.starts_with('.') && is_tiff_name(name))) {
        Ok(name)
    } else {
        Err(format!(
            "its OME-XML names the file {name:?}; supported are {} beside it",
            if tiff { "TIFF files" } else { "files" }
        ))
    }
}

/// The file a `TiffData` element places its planes in.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
enum PlaneFile {
    /// The file holding the XML.
    Own,
    Named(String),
    /// A file named by its UUID only.
    Uuid(String),
}

/// The place of the file named `own` in a multi-file OME-TIFF, from its OME-XML `xml`: none
/// for a file whose planes all lie in itself.
fn ome_role(xml: &str, own: &str) -> Result<Option<OmeRole>, String> {
    let Some(OmePlacement {
        tiff_data: placed,
        metadata_file,
        own_uuid,
    }) = ome_placement(xml)
    else {
        return Ok(None);
    };
    if let Some(m) = metadata_file.filter(|m| m != own) {
        return Ok(Some(OmeRole::PartOf(sibling_name(&m, false)?.to_string())));
    }
    let keys = plane_files(&placed, Some(own), own_uuid.as_deref());
    // Planes all in one file, whatever the XML calls it (this file renamed, or read under
    // another name, as an upload is): this file's own.
    let distinct: std::collections::HashSet<&PlaneFile> = keys.iter().collect();
    if distinct.len() <= 1 {
        return Ok(None);
    }
    if distinct.len() > super::MAX_SOURCE_FILES {
        return Err(format!(
            "its OME-XML places planes in {} files, more than the {} of a volume",
            distinct.len(),
            super::MAX_SOURCE_FILES
        ));
    }
    let holder = placed
        .iter()
        .position(|d| d.first == [0; 3])
        .map(|i| &keys[i])
        .ok_or("its OME-XML places planes in other files but none at the first plane")?;
    match holder {
        PlaneFile::Own => {}
        PlaneFile::Named(h) => return Ok(Some(OmeRole::PartOf(sibling_name(h, true)?.into()))),
        PlaneFile::Uuid(u) => return Err(by_uuid_only(u)),
    }
    Ok(Some(OmeRole::Holds(dataset_of(placed, keys, Some(own))?)))
}

/// Why a `TiffData` naming a file by its UUID alone is refused.
fn by_uuid_only(uuid: &str) -> String {
    format!("its OME-XML names a file by its UUID only ({uuid}); supported are files named")
}

/// Each `TiffData`'s file, as the XML of the file named `own` (none: an OME companion file,
/// which holds no plane) says: this one when its UUID is the file's own (`own_uuid`: a file
/// renamed since it was written keeps its UUID), when it names this one, or when it names none.
fn plane_files(placed: &[TiffData], own: Option<&str>, own_uuid: Option<&str>) -> Vec<PlaneFile> {
    placed
        .iter()
        .map(|d| match (&d.file, &d.uuid) {
            (_, Some(u)) if Some(u.as_str()) == own_uuid => PlaneFile::Own,
            (Some(f), _) if Some(f.as_str()) == own => PlaneFile::Own,
            (Some(f), _) => PlaneFile::Named(f.clone()),
            (None, None) => PlaneFile::Own,
            (None, Some(u)) => PlaneFile::Uuid(u.clone()),
        })
        .collect()
}

/// The dataset of the `TiffData` elements `placed`, each in the file `keys` says: the file
/// holding the XML first where it holds planes (`own`), then the others in the order the XML
/// names them, each a TIFF file beside it, at most [`super::MAX_SOURCE_FILES`] of them.
fn dataset_of(
    placed: Vec<TiffData>,
    keys: Vec<PlaneFile>,
    own: Option<&str>,
) -> Result<OmeDataset, String> {
    let mut files: Vec<String> = own.map(str::to_string).into_iter().collect();
    let mut index: std::collections::HashMap<PlaneFile, usize> =
        own.map(|_| (PlaneFile::Own, 0)).into_iter().collect();
    let mut tiff_data = Vec::with_capacity(placed.len());
    for (d, key) in placed.into_iter().zip(keys) {
        let f = match index.get(&key) {
            Some(f) => *f,
            None => {
                match &key {
                    PlaneFile::Named(n) => {
                        sibling_name(n, true)?;
                        if files.len() == super::MAX_SOURCE_FILES {
                            return Err(format!(
                                "its OME-XML places planes in more than the {} files of a volume",
                                super::MAX_SOURCE_FILES
                            ));
                        }
                        files.push(n.clone());
                    }
                    PlaneFile::Uuid(u) => return Err(by_uuid_only(u)),
                    PlaneFile::Own => {
                        return Err("a TiffData element of its XML names no file".into())
                    }
                }
                index.insert(key, files.len() - 1);
                files.len() - 1
            }
        };
        tiff_data.push((f, d));
    }
    if files.is_empty() {
        return Err("its XML places no plane in a TIFF file".into());
    }
    Ok(OmeDataset { files, tiff_data })
}

/// Where the images of an ImageJ stack over 4 GB lie: ImageJ writes one page directory (32-bit
/// offsets cannot reach further) and every image's uncompressed samples after the first's, as
/// its description's `images=` counts them.
#[derive(Debug, Clone, Copy)]
struct Contiguous {
    /// The first image's first byte.
    offset: u64,
    /// Bytes of one image.
    page_bytes: u64,
    endian: Endian,
}

impl Contiguous {
    /// Where image `p` of the file lies.
    fn strips(&self, p: usize, shape: &PageShape) -> RawStrips {
        RawStrips {
            offsets: vec![self.offset + p as u64 * self.page_bytes],
            rows_per_strip: shape.height,
            endian: self.endian,
        }
    }
}

/// A decoder of `reader`, whose buffers (a decoded chunk, a tag's value) are bounded by what
/// the file's length can hold ([`MAX_EXPANSION`]), so that a few bytes cannot make it
/// allocate a gigabyte.
fn decoder<R: Read + Seek>(mut reader: R, path: &Path) -> Result<Decoder<R>, ReadError> {
    let len = reader
        .seek(std::io::SeekFrom::End(0))
        .and_then(|n| reader.rewind().map(|()| n))
        .map_err(|e| ReadError::io(path, e))?;
    directories_fit(&mut reader, len, path)?;
    reader.rewind().map_err(|e| ReadError::io(path, e))?;
    let bound = len
        .saturating_mul(MAX_EXPANSION)
        .saturating_add(DECLARED_SLACK);
    let bound = usize::try_from(bound).unwrap_or(usize::MAX);
    let mut limits = Limits::default();
    limits.decoding_buffer_size = CHUNK_LIMIT.min(bound);
    limits.intermediate_buffer_size = CHUNK_LIMIT.min(bound);
    Ok(Decoder::new(reader)
        .map_err(|e| failed(path, e))?
        .with_limits(limits))
}

/// Checks that no entry of any page directory declares more values than the file's `len`
/// bytes hold. The `tiff` crate reserves about 32 bytes a declared value before reading them,
/// bounded only by its decoding buffer limit, and reads the first directory when the decoder is
/// made, before limits can be set: a 307-byte file declaring a million strip byte counts took
/// 30 MB, four billion would abort. (Written here because the crate has no constructor taking
/// limits and no limit of its own on a tag's values.)
fn directories_fit<R: Read + Seek>(r: &mut R, len: u64, path: &Path) -> Result<(), ReadError> {
    let mut head = Vec::with_capacity(16);
    r.take(16)
        .read_to_end(&mut head)
        .map_err(|e| ReadError::io(path, e))?;
    let little = match head.get(..2) {
        Some(b"II") => true,
        Some(b"MM") => false,
        _ => return Ok(()), // the crate refuses it
    };
    let int = |b: &[u8]| {
        let mut v = 0u64;
        for k in 0..b.len() {
            let byte = if little { b[b.len() - 1 - k] } else { b[k] };
            v = (v << 8) | u64::from(byte);
        }
        v
    };
    if head.len() < 8 {
        return Ok(());
    }
    let big = int(&head[2..4]) == 43;
    // (first directory, bytes of the entry count, of an entry, of the count field, of an offset)
    let (mut at, count_bytes, entry_bytes, count_field, offset_bytes) = match big {
        false => (int(&head[4..8]), 2, 12, 4, 4),
        true if head.len() >= 16 => (int(&head[8..16]), 8, 20, 8, 8),
        true => return Ok(()),
    };
    let mut seen = std::collections::HashSet::new();
    let mut buf = [0u8; 20];
    while at != 0 && at < len && seen.insert(at) {
        if r.seek(std::io::SeekFrom::Start(at)).is_err()
            || r.read_exact(&mut buf[..count_bytes]).is_err()
        {
            return Ok(()); // the crate reports it
        }
        let entries = int(&buf[..count_bytes]);
        if entries.saturating_mul(entry_bytes as u64) > len {
            return Err(bad(
                path,
                format!("a page directory at byte {at} declares {entries} entries, more than the file's {len} bytes hold"),
            ));
        }
        for _ in 0..entries {
            if r.read_exact(&mut buf[..entry_bytes]).is_err() {
                return Ok(());
            }
            let (tag, kind) = (int(&buf[0..2]), int(&buf[2..4]));
            let values = int(&buf[4..4 + count_field]);
            let size: u64 = match kind {
                1 | 2 | 6 | 7 => 1,
                3 | 8 => 2,
                4 | 9 | 11 | 13 => 4,
                5 | 10 | 12 | 16 | 17 | 18 => 8,
                // The crate skips an entry of unknown type by a classic entry's 8 bytes, not
                // a BigTIFF entry's 16, and reads the rest of the directory out of step.
                _ if big => {
                    return Err(bad(
                        path,
                        format!("the page directory at byte {at} has an entry (tag {tag}) of unknown type {kind}"),
                    ))
                }
                _ => 0,
            };
            if values.saturating_mul(size) > len {
                return Err(bad(
                    path,
                    format!("tag {tag} in the page directory at byte {at} declares {values} values, more than the file's {len} bytes hold"),
                ));
            }
        }
        if r.read_exact(&mut buf[..offset_bytes]).is_err() {
            return Ok(());
        }
        at = int(&buf[..offset_bytes]);
    }
    Ok(())
}

fn tag_u64<R: Read + Seek>(
    d: &mut Decoder<R>,
    tag: Tag,
    path: &Path,
) -> Result<Option<u64>, ReadError> {
    match d.find_tag(tag).map_err(|e| failed(path, e))? {
        None => Ok(None),
        Some(v) => v
            .into_u64()
            .map(Some)
            .map_err(|_| bad(path, format!("tag {tag:?} is not a number"))),
    }
}

/// The shape of the current page, or `None` for a reduced-resolution copy (skipped).
fn page_shape<R: Read + Seek>(
    d: &mut Decoder<R>,
    path: &Path,
    page: usize,
) -> Result<Option<PageShape>, ReadError> {
    let at = |reason: String| bad(path, format!("page {page}: {reason}"));
    let subfile = tag_u64(d, Tag::NewSubfileType, path)?.unwrap_or(0);
    if subfile & 1 != 0 {
        return Ok(None);
    }
    if subfile & 4 != 0 {
        return Err(ReadError::unsupported(
            path,
            format!("page {page} is a transparency mask"),
        ));
    }
    let (width, height) = d.dimensions().map_err(|e| failed(path, e))?;
    let colour = d.colortype().map_err(|e| failed(path, e))?;
    let photometric = tag_u64(d, Tag::PhotometricInterpretation, path)?;
    let (channels, bits) = match colour {
        ColorType::Gray(b) if photometric == Some(0) => {
            return Err(ReadError::unsupported(
                path,
                format!("page {page} is inverted grey ({b}-bit WhiteIsZero); supported are BlackIsZero grey and RGB"),
            ))
        }
        ColorType::Gray(b) => (1, b),
        ColorType::RGB(b) => (3, b),
        other => {
            return Err(ReadError::unsupported(
                path,
                format!("page {page} is {other:?}; supported are grey and RGB samples (no palette, alpha, CMYK or YCbCr)"),
            ))
        }
    };
    if !matches!(bits, 8 | 16 | 32 | 64) {
        return Err(ReadError::unsupported(
            path,
            format!("page {page} has {bits}-bit samples; supported are 8, 16, 32 and 64 bits"),
        ));
    }
    let format = match d.find_tag(Tag::SampleFormat).map_err(|e| failed(path, e))? {
        None => 1,
        Some(v) => {
            let all = v
                .into_u16_vec()
                .map_err(|_| at("SampleFormat is not a list of numbers".into()))?;
            match all.first() {
                Some(&f) if all.iter().all(|g| *g == f) && (1..=3).contains(&f) => f,
                _ => return Err(ReadError::unsupported(
                    path,
                    format!("page {page} has SampleFormat {all:?}; supported are unsigned, signed and float samples, one kind for all channels"),
                )),
            }
        }
    };
    if format == 3 && bits == 8 {
        return Err(at("8-bit float samples".into()));
    }
    if channels > 1 && tag_u64(d, Tag::PlanarConfiguration, path)? == Some(2) {
        return Err(ReadError::unsupported(
            path,
            format!("page {page} stores its colour channels in separate planes (PlanarConfiguration 2); supported are interleaved channels"),
        ));
    }
    if width == 0 || height == 0 {
        return Err(at(format!("an empty page ({width}x{height})")));
    }
    Ok(Some(PageShape {
        width: width as usize,
        height: height as usize,
        channels,
        bits,
        format,
    }))
}

/// A length in `unit` (ImageJ's, OME-XML's or OME-Zarr's spelling) in mm; `None` for no
/// physical unit.
pub(crate) fn unit_mm(unit: &str) -> Option<f64> {
    Some(match unit.trim().trim_matches('"') {
        // ImageJ writes the micro sign as the escape `\u00B5` in some versions.
        "micron" | "microns" | "um" | "µm" | "\u{3bc}m" | "\\u00B5m" | "\\u00b5m"
        | "micrometer" | "micrometre" => 1e-3,
        "nm" | "nanometer" | "nanometre" => 1e-6,
        "pm" | "picometer" | "picometre" => 1e-9,
        "fm" | "femtometer" | "femtometre" => 1e-12,
        "Å" | "angstrom" => 1e-7,
        "dm" | "decimeter" | "decimetre" => 100.0,
        "km" | "kilometer" | "kilometre" => 1e6,
        "foot" | "ft" => 304.8,
        "yard" | "yd" => 914.4,
        "mile" => 1_609_344.0,
        "mm" | "millimeter" | "millimetre" => 1.0,
        "cm" | "centimeter" | "centimetre" => 10.0,
        "m" | "meter" | "metre" => 1e3,
        "inch" | "in" => 25.4,
        _ => return None,
    })
}

/// Seconds in an OME (XML or Zarr) or ImageJ time unit.
pub(crate) fn time_unit_s(unit: &str) -> Option<f64> {
    Some(match unit {
        "s" | "sec" | "second" => 1.0,
        "ms" | "millisecond" => 1e-3,
        "µs" | "us" | "microsecond" => 1e-6,
        "ns" | "nanosecond" => 1e-9,
        "min" | "minute" => 60.0,
        "h" | "hr" | "hour" => 3600.0,
        "day" => 86400.0,
        _ => return None,
    })
}

/// The value of `key="…"` in an XML text.
fn xml_attr<'a>(xml: &'a str, key: &str) -> Option<&'a str> {
    let pat = format!(" {key}=\"");
    let start = xml.find(&pat)? + pat.len();
    let len = xml[start..].find('"')?;
    Some(&xml[start..start + len])
}

/// Pixels per unit of a resolution tag, as a number.
fn resolution<R: Read + Seek>(d: &mut Decoder<R>, tag: Tag) -> Option<f64> {
    use ::tiff::decoder::ifd::Value;
    let v = match d.find_tag(tag).ok()?? {
        Value::Rational(n, q) => f64::from(n) / f64::from(q),
        Value::Float(v) => f64::from(v),
        Value::Double(v) => v,
        other => other.into_u64().ok()? as f64,
    };
    (v.is_finite() && v > 0.0).then_some(v)
}

/// What the first page's description (ImageJ's or OME-XML) says of the stack: its spacing,
/// and a refusal for several channels or time points.
fn stack_meta<R: Read + Seek>(d: &mut Decoder<R>, path: &Path) -> Result<StackMeta, ReadError> {
    let mut meta = StackMeta::default();
    let description = match d.find_tag(Tag::ImageDescription) {
        Ok(Some(v)) => v.into_string().unwrap_or_default(),
        _ => String::new(),
    };
    if description.starts_with("ImageJ=") {
        imagej_meta(d, &description, &mut meta);
    } else if description.contains("<OME") {
        ome_meta(&description, path, &mut meta)?;
        let own = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        match ome_role(&description, &own) {
            Ok(role) => meta.ome = role.map(std::sync::Arc::new),
            Err(reason) => meta.ome_refusal = Some(reason.into()),
        }
    }
    physical_spacing(&mut meta);
    Ok(meta)
}

/// Keeps a spacing where it is a positive f32 (what a volume's spacing is): else 1.
fn physical_spacing(meta: &mut StackMeta) {
    for s in meta.spacing.iter_mut() {
        if s.is_some_and(|v| !((v as f32).is_finite() && v as f32 > 0.0)) {
            *s = None;
        }
    }
}

/// Largest OME companion file read (its XML alone: kilobytes to tens of megabytes for a file a
/// plane of a long acquisition).
const COMPANION_LIMIT: u64 = 64 << 20;

/// Most `TiffData` elements read of one OME-XML (a million planes placed one by one; each
/// element costs about 200 bytes once parsed).
const MAX_TIFF_DATA: usize = 1 << 20;

/// Whether a file name is an OME companion file's (`NAME.companion.ome`, any case).
pub(crate) fn is_companion_name(name: &str) -> bool {
    name.to_ascii_lowercase().ends_with(".companion.ome")
}

/// An OME companion file: an OME-XML file of its own (as Bio-Formats writes one beside a
/// multi-file OME-TIFF whose TIFFs hold `BinaryOnly` pointers to it): what it says of the
/// stack, and where it places the planes, every one in a TIFF file beside it.
#[derive(Debug, Clone)]
struct Companion {
    meta: StackMeta,
    dataset: OmeDataset,
}

impl Companion {
    /// The companion file at `path` whose bytes are `bytes`.
    fn of(bytes: &[u8], path: &Path) -> Result<Companion, ReadError> {
        if bytes.len() as u64 > COMPANION_LIMIT {
            return Err(bad(
                path,
                format!("an OME companion file of more than {COMPANION_LIMIT} bytes"),
            ));
        }
        let xml = std::str::from_utf8(bytes)
            .map_err(|_| bad(path, "an OME companion file that is not UTF-8 text"))?;
        if !xml.contains("<OME") {
            return Err(bad(path, "an OME companion file without an OME element"));
        }
        let mut meta = StackMeta::default();
        ome_meta(xml, path, &mut meta)?;
        physical_spacing(&mut meta);
        let dataset = companion_dataset(xml).map_err(|reason| bad(path, reason))?;
        Ok(Companion { meta, dataset })
    }

    /// Reads the companion file at `path` (at most [`COMPANION_LIMIT`] bytes).
    fn read(path: &Path) -> Result<Companion, ReadError> {
        let file = File::open(path).map_err(|e| ReadError::io(path, e))?;
        let mut bytes = Vec::new();
        file.take(COMPANION_LIMIT + 1)
            .read_to_end(&mut bytes)
            .map_err(|e| ReadError::io(path, e))?;
        if bytes.len() as u64 > COMPANION_LIMIT {
            return Err(bad(
                path,
                format!("an OME companion file of more than {COMPANION_LIMIT} bytes"),
            ));
        }
        Companion::of(&bytes, path)
    }
}

/// Where an OME companion file's XML places its planes: every `TiffData` in a TIFF file beside
/// it, named (the files in the order the XML names them).
fn companion_dataset(xml: &str) -> Result<OmeDataset, String> {
    let placement = read_ome_placement(xml)?.ok_or("its XML is not well-formed")?;
    let keys = plane_files(&placement.tiff_data, None, None);
    dataset_of(placement.tiff_data, keys, None)
}

/// What an ImageJ description says of the stack (its spacing from the page's resolution tags
/// in its `unit`).
fn imagej_meta<R: Read + Seek>(d: &mut Decoder<R>, description: &str, meta: &mut StackMeta) {
    let field = |key: &str| {
        description.lines().find_map(|l| {
            let (k, v) = l.split_once('=')?;
            (k.trim() == key).then(|| v.trim().to_string())
        })
    };
    let count = |key: &str| field(key).and_then(|v| v.parse::<usize>().ok());
    meta.channels = count("channels").filter(|c| *c > 1);
    meta.plane_order = *b"CZT";
    meta.frames = count("frames").filter(|t| *t > 1);
    meta.slices = count("slices");
    meta.time_major = true;
    // The frame interval, in `tunit` (ImageJ's default: seconds).
    let tunit = field("tunit").unwrap_or_else(|| "sec".into());
    meta.time_step = field("finterval")
        .and_then(|v| v.parse::<f64>().ok())
        .zip(time_unit_s(&tunit))
        .map(|(v, s)| v * s)
        .filter(|v| v.is_finite() && *v > 0.0);
    meta.imagej_images = count("images");
    if let Some(mm) = field("unit").as_deref().and_then(unit_mm) {
        let x = resolution(d, Tag::XResolution).map(|r| mm / r);
        let y = resolution(d, Tag::YResolution).map(|r| mm / r);
        let z = field("spacing")
            .and_then(|v| v.parse::<f64>().ok())
            .map(|s| s.abs() * mm);
        meta.spacing = [x, y, z];
    }
}

/// What an OME-XML description (of the file at `path`) says of the stack.
fn ome_meta(description: &str, path: &Path, meta: &mut StackMeta) -> Result<(), ReadError> {
    let images = description.matches("<Image ").count();
    if images > 1 {
        return Err(ReadError::unsupported(
            path,
            format!("an OME-TIFF of {images} images (series or positions); supported is one"),
        ));
    }
    let size = |key: &str| xml_attr(description, key).and_then(|v| v.parse::<usize>().ok());
    meta.frames = size("SizeT").filter(|t| *t > 1);
    meta.slices = size("SizeZ");
    // The planes' order, fastest first after X and Y: Z before T keeps a time point's
    // slices together (of channels stored as planes, one is kept: `Stack::of`).
    let order = xml_attr(description, "DimensionOrder").unwrap_or("XYZCT");
    meta.time_major = order.find('Z') < order.find('T');
    if let Some(o) = order.as_bytes().strip_prefix(b"XY").filter(|o| {
        let mut sorted = o.to_vec();
        sorted.sort_unstable();
        sorted == b"CTZ"
    }) {
        meta.plane_order.copy_from_slice(o);
    }
    // Left all zeros for an order that is none of OME's: channels stored as planes are
    // then refused (`channel_layout`).
    meta.time_step = xml_attr(description, "TimeIncrement")
        .and_then(|v| v.parse::<f64>().ok())
        .zip(time_unit_s(
            xml_attr(description, "TimeIncrementUnit").unwrap_or("s"),
        ))
        .map(|(v, s)| v * s)
        .filter(|v| v.is_finite() && *v > 0.0);
    meta.ome_size_c = size("SizeC");
    for (axis, key) in ["PhysicalSizeX", "PhysicalSizeY", "PhysicalSizeZ"]
        .iter()
        .enumerate()
    {
        let unit = xml_attr(description, &format!("{key}Unit")).unwrap_or("µm");
        let size = xml_attr(description, key).and_then(|v| v.parse::<f64>().ok());
        meta.spacing[axis] = size.zip(unit_mm(unit)).map(|(s, mm)| s * mm);
    }
    Ok(())
}

/// The channels a description says (OME's `SizeC`, ImageJ's `channels`) against the first
/// page's samples: channels stored as planes of their own over grey pages, or the samples of
/// RGB pages (then none stored as planes); else refused.
fn settle_channels(
    meta: &mut StackMeta,
    first: Option<&PageShape>,
    path: &Path,
) -> Result<(), ReadError> {
    if let (Some(c), Some(first)) = (meta.ome_size_c, first) {
        if c > 1 && first.channels == 1 {
            // Channels as planes of their own.
            meta.channels = Some(c);
        } else if c > 1 && c != first.channels {
            return Err(ReadError::unsupported(
                path,
                format!(
                    "an OME-TIFF of {c} channels (SizeC) in pages of {}; supported is one \
                     channel (or RGB pages)",
                    first.channels
                ),
            ));
        }
    }
    if let (Some(c), Some(first)) = (meta.channels, first) {
        if first.channels == c {
            // An RGB hyperstack: its channels are each page's samples, read together.
            meta.channels = None;
        } else if first.channels != 1 {
            return Err(ReadError::unsupported(
                path,
                format!(
                    "an ImageJ hyperstack of {c} channels in pages of {} samples each; \
                     supported are grey pages (a channel a plane) or RGB pages",
                    first.channels
                ),
            ));
        }
    }
    Ok(())
}

/// The pages of one file: their index among the file's pages and their shape, and what its
/// first page says of the stack.
fn file_pages<R: Read + Seek>(
    mut reader: R,
    path: &Path,
) -> Result<(Vec<(usize, PageShape)>, StackMeta), ReadError> {
    let len = reader
        .seek(std::io::SeekFrom::End(0))
        .map_err(|e| ReadError::io(path, e))?;
    let mut d = decoder(reader, path)?;
    let mut meta = stack_meta(&mut d, path)?;
    let mut pages = Vec::new();
    let mut index = 0;
    loop {
        if let Some(shape) = page_shape(&mut d, path, index)? {
            pages.push((index, shape));
        }
        if !d.more_images() {
            break;
        }
        d.next_image().map_err(|e| failed(path, e))?;
        index += 1;
    }
    let declared = pages.iter().try_fold(0u64, |sum, (_, s)| {
        let page = (s.width as u64)
            .checked_mul(s.height as u64)?
            .checked_mul(s.channels as u64 * u64::from(s.bits) / 8)?;
        sum.checked_add(page)
    });
    let most = len
        .saturating_mul(MAX_EXPANSION)
        .saturating_add(DECLARED_SLACK);
    if declared.is_none_or(|d| d > most) {
        return Err(bad(
            path,
            format!(
                "its {} pages declare {} bytes of samples, more than its {len} bytes can hold",
                pages.len(),
                declared.map_or("more than 2^64".into(), |d| d.to_string())
            ),
        ));
    }
    settle_channels(&mut meta, pages.first().map(|(_, shape)| shape), path)?;
    if let Some(n) = meta.imagej_images.filter(|n| *n > pages.len()) {
        // One page directory: the images follow one another after the first's samples.
        let first = match pages.as_slice() {
            [(0, shape)] if d.seek_to_image(0).is_ok() => raw_strips(&mut d, shape, path)
                .filter(|r| r.contiguous(shape) && raw_sample(shape).is_some())
                .map(|r| (*shape, r)),
            _ => None,
        };
        let Some((shape, strips)) = first else {
            return Err(ReadError::unsupported(
                path,
                format!(
                    "ImageJ counts {n} images but the file has {} pages, and its first image is \
                     not stored uncompressed in one run as ImageJ stores a stack over 4 GB; save \
                     it as a sequence of TIFF files (File > Save As > Image Sequence) or as OME-TIFF",
                    pages.len()
                ),
            ));
        };
        let page_bytes = shape.bytes();
        let end = (n as u64)
            .checked_mul(page_bytes)
            .and_then(|b| b.checked_add(strips.offsets[0]));
        if end.is_none_or(|e| e > len) {
            return Err(ReadError::Truncated {
                path: path.to_path_buf(),
                offset: strips.offsets[0],
                expected: (n as u64).saturating_mul(page_bytes),
                actual: len.saturating_sub(strips.offsets[0]),
            });
        }
        meta.contiguous = Some(Contiguous {
            offset: strips.offsets[0],
            page_bytes,
            endian: strips.endian,
        });
        pages.extend((1..n).map(|p| (p, shape)));
    }
    Ok((pages, meta))
}

/// The time points of the TIFF file at `path`: an ImageJ hyperstack's frames or an OME-TIFF's
/// `SizeT` (its first page's description read), else 1.
pub(crate) fn time_points(path: &Path) -> Result<usize, ReadError> {
    if is_companion_path(path) {
        return Ok(Companion::read(path)?.meta.frames.unwrap_or(1));
    }
    let file = File::open(path).map_err(|e| ReadError::io(path, e))?;
    let mut d = decoder(BufReader::new(file), path)?;
    Ok(stack_meta(&mut d, path)?.frames.unwrap_or(1))
}

/// The full-resolution pages of the TIFF file at `path` and the channels it stores as planes of
/// their own (1: none), its page directories read once; a file whose channel planes do not add
/// up is refused here, as the reader refuses it.
pub(crate) fn pages_and_channels(path: &Path) -> Result<(usize, usize), ReadError> {
    // A multi-file OME-TIFF's planes: every file's, placed (a part alone is refused).
    let of_dataset = || {
        let (_, stack) = open_stack(path, Some(0))?;
        let count = stack.planes_per_slice;
        Ok((stack.slices.len() * count, count))
    };
    if is_companion_path(path) {
        return of_dataset();
    }
    let (pages, meta) = open_file_pages(path)?;
    if meta.ome.is_some() || meta.ome_refusal.is_some() {
        return of_dataset();
    }
    let channels = match meta.channels {
        Some(c) => {
            channel_layout(path, 1, pages.len(), &meta, c)?;
            c
        }
        None => 1,
    };
    Ok((pages.len(), channels))
}

/// [`file_pages`] of the file at `path`.
fn open_file_pages(path: &Path) -> Result<(Vec<(usize, PageShape)>, StackMeta), ReadError> {
    let file = File::open(path).map_err(|e| ReadError::io(path, e))?;
    file_pages(BufReader::new(file), path)
}

/// The place of the TIFF file at `path` in a multi-file OME-TIFF (its first page's
/// description read), if it has one.
fn ome_role_of(path: &Path) -> Result<Option<std::sync::Arc<OmeRole>>, ReadError> {
    let file = File::open(path).map_err(|e| ReadError::io(path, e))?;
    let mut d = decoder(BufReader::new(file), path)?;
    let meta = stack_meta(&mut d, path)?;
    match meta.ome_refusal {
        Some(reason) => Err(bad(path, reason.to_string())),
        None => Ok(meta.ome),
    }
}

/// Why a part of a multi-file OME-TIFF whose dataset is read from `holder` is not read alone.
pub(crate) fn part_of_dataset(holder: &str) -> String {
    if is_tiff_name(&holder.to_ascii_lowercase()) || is_companion_name(holder) {
        format!(
            "a part of a multi-file OME-TIFF: the dataset is read from {holder} beside it (the \
             file holding its first plane or its XML)"
        )
    } else {
        format!(
            "a part of a multi-file OME-TIFF whose XML is in {holder}, which is neither a TIFF \
             nor an OME companion file (`.companion.ome`); convert the dataset to one OME-TIFF \
             or a Zarr store (e.g. with Bio-Formats' bfconvert)"
        )
    }
}

/// The place of the TIFF file at `path` in a multi-file OME-TIFF: the other files of the
/// dataset whose XML and first plane it holds (beside it, in the order its XML names them; of
/// an OME companion file, all of them), or the file the dataset it is a part of is read from
/// (the one holding its first plane or its XML).
pub(crate) fn dataset(path: &Path) -> Result<super::TiffDataset, ReadError> {
    if is_companion_path(path) {
        let files = Companion::read(path)?.dataset.files;
        let files = files.iter().map(|n| path.with_file_name(n)).collect();
        return Ok(super::TiffDataset::Holds(files));
    }
    Ok(match ome_role_of(path)?.as_deref() {
        Some(OmeRole::Holds(dataset)) => super::TiffDataset::Holds(
            dataset.files[1..]
                .iter()
                .map(|n| path.with_file_name(n))
                .collect(),
        ),
        Some(OmeRole::PartOf(holder)) => super::TiffDataset::PartOf(path.with_file_name(holder)),
        None => super::TiffDataset::Alone,
    })
}

/// The stack at `path` (a TIFF file, a directory of them, or an OME companion file) and its
/// files, read from disk.
fn open_stack(path: &Path, channel: Option<usize>) -> Result<(Vec<PathBuf>, Stack), ReadError> {
    let companion = is_companion_path(path)
        .then(|| Companion::read(path))
        .transpose()?;
    let files = match &companion {
        Some(c) => c
            .dataset
            .files
            .iter()
            .map(|n| path.with_file_name(n))
            .collect(),
        None => stack_paths(path)?,
    };
    if files.is_empty() {
        return Err(bad(path, "the directory holds no .tif or .tiff file"));
    }
    let stack = Stack::of(
        &files,
        |f| open_file_pages(&files[f]),
        channel,
        companion.as_ref(),
    )?;
    Ok((files, stack))
}

/// Whether `path` names an OME companion file (not a directory).
fn is_companion_path(path: &Path) -> bool {
    path.file_name()
        .is_some_and(|n| is_companion_name(&n.to_string_lossy()))
        && !path.is_dir()
}

/// The files of the stack at `path`: a directory's TIFF files in order; a file, then the other
/// files of the multi-file OME-TIFF whose XML it holds ([`dataset`]).
fn stack_paths(path: &Path) -> Result<Vec<PathBuf>, ReadError> {
    if path.is_dir() {
        return Ok(stack_files(path)?.into_iter().map(|(_, p)| p).collect());
    }
    let mut files = vec![path.to_path_buf()];
    if let super::TiffDataset::Holds(parts) = dataset(path)? {
        files.extend(parts);
    }
    Ok(files)
}

/// A stack's slices: the file and page of each, in order, their common shape, and the spacing.
#[derive(Debug, Clone)]
struct Stack {
    /// (file index, page index within the file) of each slice.
    slices: Vec<(usize, usize)>,
    shape: PageShape,
    spacing: [f32; 3],
    /// For each file, where its images lie when it is an ImageJ stack over 4 GB (one page
    /// directory for them all).
    contiguous: Vec<Option<Contiguous>>,
    /// Time points: an ImageJ hyperstack's frames or an OME-TIFF's `SizeT`, else 1.
    time_points: usize,
    /// Whether a time point's slices follow one another in `slices` (else each slice's time
    /// points do).
    time_major: bool,
    /// Seconds between time points, when the description says.
    time_step: Option<f64>,
    /// The channels stored as planes of their own (1: none), of which `slices` holds the one
    /// chosen.
    planes_per_slice: usize,
}

impl Stack {
    /// The stack of `files` (each file's pages listed by `pages_of`), checking that every page
    /// has the first's shape; of channels stored as planes of their own, the planes of
    /// `channel` (none chosen: refused as [`ReadError::Channels`]). With a `companion`, the
    /// files are its dataset's, placed as its XML says.
    fn of(
        names: &[PathBuf],
        mut pages_of: impl FnMut(usize) -> Result<(Vec<(usize, PageShape)>, StackMeta), ReadError>,
        channel: Option<usize>,
        companion: Option<&Companion>,
    ) -> Result<Stack, ReadError> {
        let mut slices = Vec::new();
        let mut first: Option<(PageShape, usize, usize)> = None;
        // The full-resolution pages of each file, and what its first page says.
        let mut held: Vec<Vec<usize>> = Vec::with_capacity(names.len());
        let mut metas: Vec<StackMeta> = Vec::with_capacity(names.len());
        for (f, path) in names.iter().enumerate() {
            let (pages, meta) = pages_of(f)?;
            metas.push(meta);
            held.push(pages.iter().map(|(p, _)| *p).collect());
            for (p, shape) in pages {
                match &first {
                    None => first = Some((shape, f, p)),
                    Some((s, f0, p0)) if *s != shape => {
                        return Err(ReadError::Series {
                            path: path.clone(),
                            reason: format!(
                                "page {p} is {}, but page {p0} of {} is {}: the slices of a stack must agree",
                                shape.describe(),
                                names[*f0].display(),
                                s.describe()
                            ),
                        });
                    }
                    Some(_) => {}
                }
                slices.push((f, p));
            }
        }
        let Some((shape, f0, _)) = first else {
            return Err(bad(
                names.first().map_or(Path::new("."), PathBuf::as_path),
                "no page holds an image at full resolution",
            ));
        };
        let mut meta = metas[f0].clone();
        // A file whose XML places planes as no reader may (unless an OME companion file places
        // them: its own XML is not read then).
        let refusal = metas
            .iter()
            .enumerate()
            .find_map(|(f, m)| m.ome_refusal.as_ref().map(|r| (f, r)));
        if let (None, Some((f, reason))) = (companion, refusal) {
            return Err(bad(&names[f], reason.to_string()));
        }
        // The files of a multi-file OME-TIFF hold its planes as one file of them all would,
        // read from the file holding its XML and first plane (in a directory of its files,
        // wherever that sorts); a part without it is refused.
        let role = |f: usize| metas[f].ome.as_deref();
        let holder = (0..names.len()).find(|&f| matches!(role(f), Some(OmeRole::Holds(_))));
        let part = (0..names.len()).find_map(|f| match role(f) {
            Some(OmeRole::PartOf(h)) => Some((f, h)),
            _ => None,
        });
        let files = match (holder, part) {
            // The files of an OME companion file, whatever their own descriptions say.
            _ if companion.is_some() => {
                let companion = companion.expect("matched");
                meta = companion.meta.clone();
                settle_channels(&mut meta, Some(&shape), &names[0])?;
                slices = dataset_planes(names, &held, &meta, &companion.dataset)?;
                1
            }
            (None, Some((f, h))) => {
                return Err(ReadError::unsupported(&names[f], part_of_dataset(h)));
            }
            (Some(h), _) => {
                let Some(OmeRole::Holds(dataset)) = role(h) else {
                    unreachable!("found holding above")
                };
                // The holder's description counts the dataset (a part's may say nothing).
                meta = metas[h].clone();
                slices = dataset_planes(names, &held, &meta, dataset)?;
                1
            }
            (None, None) => {
                if let Some(reason) = numbering_gap(names) {
                    let dir = names[0].parent().unwrap_or(Path::new("."));
                    return Err(ReadError::Series {
                        path: dir.to_path_buf(),
                        reason,
                    });
                }
                names.len()
            }
        };
        let spacing = meta.spacing.map(|s| s.unwrap_or(1.0) as f32);
        let time_points = meta.frames.unwrap_or(1);
        if let Some(count) = meta.channels {
            slices = planes_of_channel(names, files, slices, &meta, count, channel)?;
        }
        // A file whose description counts more slices than it holds is a part (a multi-file
        // OME-TIFF, whose XML in the first file describes all of them) or a truncated file:
        // read as a volume of its own slices, the rest would be lost without a word.
        if let (1, Some(z)) = (files, meta.slices) {
            if time_points == 1 && z > slices.len() {
                return Err(ReadError::unsupported(
                    &names[0],
                    format!(
                        "its description counts {z} slices but it holds {}: a part of a \
                         dataset of several files (a multi-file OME-TIFF, whose XML names the \
                         others), or a truncated file; write the dataset as one file or a Zarr \
                         store (e.g. with Bio-Formats' bfconvert)",
                        slices.len()
                    ),
                ));
            }
        }
        // Each time point's slices as the description counts them, else as the pages divide.
        let per_point = meta.slices.unwrap_or(slices.len() / time_points.max(1));
        if time_points > 1
            && (files > 1 || per_point.checked_mul(time_points) != Some(slices.len()))
        {
            let path = names.first().map_or(Path::new("."), PathBuf::as_path);
            return Err(ReadError::unsupported(
                path,
                if files > 1 {
                    format!(
                        "a stack of {time_points} time points among {} files; one file of them \
                         all, or a stack per time point, is read",
                        names.len()
                    )
                } else {
                    format!(
                        "a stack of {time_points} time points of {per_point} slices in {} \
                         images (a part of a dataset of several files?)",
                        slices.len()
                    )
                },
            ));
        }
        Ok(Stack {
            slices,
            shape,
            spacing,
            contiguous: metas.iter().map(|m| m.contiguous).collect(),
            time_points,
            time_major: meta.time_major,
            time_step: meta.time_step.filter(|_| time_points > 1),
            planes_per_slice: meta.channels.unwrap_or(1),
        })
    }

    /// Whether the file stores channels as planes of their own, of which `slices` holds the
    /// one chosen.
    fn channel_planes(&self) -> bool {
        self.planes_per_slice > 1
    }

    /// The dimensions of one time point.
    fn dims(&self) -> [usize; 3] {
        [
            self.shape.width,
            self.shape.height,
            self.slices.len() / self.time_points,
        ]
    }

    /// Index in [`Stack::slices`] of slice `z` of time point `t`.
    fn slice_index(&self, t: usize, z: usize) -> usize {
        if self.time_major {
            t * (self.slices.len() / self.time_points) + z
        } else {
            z * self.time_points + t
        }
    }
}

/// The slices a time point and the time points of a stack of `planes` planes in `files` files
/// storing `count` channels as planes of their own: one file, in a known plane order, whose
/// counts multiply to its planes (else refused: a part of a multi-file dataset, a truncated
/// file, a description that lies).
fn channel_layout(
    path: &Path,
    files: usize,
    planes: usize,
    meta: &StackMeta,
    count: usize,
) -> Result<(usize, usize), ReadError> {
    if files > 1 {
        return Err(ReadError::unsupported(
            path,
            format!(
                "{count} channels stored as planes among {files} files: one file of them all \
                 is read"
            ),
        ));
    }
    if meta.plane_order == [0; 3] {
        return Err(ReadError::unsupported(
            path,
            format!("{count} channels in planes whose DimensionOrder is not one of OME's"),
        ));
    }
    let frames = meta.frames.unwrap_or(1);
    let per_slice = count.checked_mul(frames);
    let z = meta
        .slices
        .unwrap_or(planes / per_slice.unwrap_or(usize::MAX).max(1));
    if per_slice.and_then(|n| n.checked_mul(z)) != Some(planes) || z == 0 {
        return Err(ReadError::unsupported(
            path,
            format!(
                "{count} channels of {z} slices and {frames} time point(s) in {planes} images: \
                 they do not add up (a part of a dataset of several files, or a truncated file)"
            ),
        ));
    }
    Ok((z, frames))
}

/// The planes of a multi-file OME-TIFF in its `DimensionOrder` (as one file of them all would
/// hold them in turn): each plane's file (its index in `names`, found by name) and page, as
/// the `TiffData` elements place them, `held` being each file's full-resolution pages. Every
/// plane is placed once, in a page its file holds; else refused, saying which.
fn dataset_planes(
    names: &[PathBuf],
    held: &[Vec<usize>],
    meta: &StackMeta,
    dataset: &OmeDataset,
) -> Result<Vec<(usize, usize)>, ReadError> {
    let path = &names[0];
    let refuse = |reason: String| {
        ReadError::unsupported(path, format!("a multi-file OME-TIFF whose XML {reason}"))
    };
    let by_name: std::collections::HashMap<String, usize> = names
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let name = p.file_name().map(|n| n.to_string_lossy().into_owned());
            (name.unwrap_or_default(), i)
        })
        .collect();
    let mut index = Vec::with_capacity(dataset.files.len());
    for file in &dataset.files {
        match by_name.get(file) {
            Some(i) => index.push(*i),
            None => {
                let why = "a file of the multi-file OME-TIFF is missing";
                return Err(ReadError::io(
                    &path.with_file_name(file),
                    std::io::Error::new(std::io::ErrorKind::NotFound, why),
                ));
            }
        }
    }
    if names.len() != dataset.files.len() {
        return Err(refuse(format!(
            "names {} files, read among {}",
            dataset.files.len(),
            names.len()
        )));
    }
    if meta.plane_order == [0; 3] {
        return Err(refuse(
            "gives a DimensionOrder that is none of OME's".into(),
        ));
    }
    let Some(z) = meta.slices else {
        return Err(refuse("gives no SizeZ".into()));
    };
    let size = |axis: u8| match axis {
        b'Z' => z,
        b'C' => meta.channels.unwrap_or(1),
        _ => meta.frames.unwrap_or(1),
    };
    let pages: usize = held.iter().map(Vec::len).sum();
    let total = b"ZCT"
        .iter()
        .try_fold(1usize, |n, &a| n.checked_mul(size(a)))
        .filter(|n| (1..=pages).contains(n))
        .ok_or_else(|| {
            refuse(format!(
                "counts {z} slices, {} channels and {} time points, and its files hold {pages} \
                 pages",
                size(b'C'),
                size(b'T')
            ))
        })?;
    let mut slots: Vec<Option<(usize, usize)>> = vec![None; total];
    for (f, data) in &dataset.tiff_data {
        let file = index[*f];
        let pages = &held[file];
        let ifd = data.ifd.unwrap_or(0);
        // Without an IFD, every page of the file; with one, one page.
        let count = data.count.unwrap_or(match data.ifd {
            Some(_) => 1,
            None => pages.len(),
        });
        // The element's first plane, in the DimensionOrder (fastest axis first).
        let mut start = 0usize;
        for &axis in meta.plane_order.iter().rev() {
            let at = data.first[b"ZCT".iter().position(|a| *a == axis).unwrap_or(0)];
            if at >= size(axis) {
                return Err(refuse(format!(
                    "places a plane at {} {at} of {}",
                    axis as char,
                    size(axis)
                )));
            }
            start = start * size(axis) + at;
        }
        for k in 0..count {
            let plane = (start + k < total)
                .then_some(start + k)
                .ok_or_else(|| refuse(format!("places planes past the {total} it counts")))?;
            let page = ifd
                .checked_add(k)
                .filter(|p| pages.binary_search(p).is_ok())
                .ok_or_else(|| {
                    refuse(format!(
                        "places plane {plane} in page {} of {}, which holds no such page at \
                         full resolution",
                        ifd.saturating_add(k),
                        dataset.files[*f]
                    ))
                })?;
            if slots[plane].replace((file, page)).is_some() {
                return Err(refuse(format!("places plane {plane} twice")));
            }
        }
    }
    slots
        .into_iter()
        .enumerate()
        .map(|(i, s)| s.ok_or_else(|| refuse(format!("places plane {i} of {total} nowhere"))))
        .collect()
}

/// Of the planes `slices` of a file storing `count` channels as planes of their own (in
/// `meta.plane_order`), those of channel `channel`, in their order.
fn planes_of_channel(
    names: &[PathBuf],
    files: usize,
    slices: Vec<(usize, usize)>,
    meta: &StackMeta,
    count: usize,
    channel: Option<usize>,
) -> Result<Vec<(usize, usize)>, ReadError> {
    let path = names.first().map_or(Path::new("."), PathBuf::as_path);
    let (z, frames) = channel_layout(path, files, slices.len(), meta, count)?;
    let c = match channel {
        None => {
            return Err(ReadError::Channels {
                path: path.to_path_buf(),
                channels: count as u64,
                why: "stored as planes of their own; one is read (`archive submit` makes each \
                      a volume of its own)"
                    .into(),
            })
        }
        Some(c) if c >= count => return Err(ReadError::channel_not_held(path, count as u64, c)),
        Some(c) => c,
    };
    let order = meta.plane_order;
    Ok(slices
        .into_iter()
        .enumerate()
        .filter(|&(i, _)| {
            // Plane i's index along each axis, fastest first.
            let mut rest = i;
            order.iter().any(|&axis| {
                let size = match axis {
                    b'Z' => z,
                    b'C' => count,
                    _ => frames,
                };
                let at = rest % size;
                rest /= size;
                axis == b'C' && at == c
            })
        })
        .map(|(_, s)| s)
        .collect())
}

/// Adds the samples of `data` (a chunk of `cw` × `ch` pixels at `(cx, cy)` of the page, channels
/// interleaved) that fall in columns `x0..x1` and rows `y0..y1` to `out` (one plane per channel,
/// rows of `x1 − x0` values, the slice starting at `base`).
#[allow(clippy::too_many_arguments)]
fn place(
    data: &DecodingResult,
    (cx, cy, cw, ch): (usize, usize, usize, usize),
    (x0, x1, y0, y1): (usize, usize, usize, usize),
    channels: usize,
    out: &mut [Vec<f32>],
    base: usize,
) {
    fn copy<T: Copy>(
        v: &[T],
        f: impl Fn(T) -> f32,
        (cx, cy, cw, ch): (usize, usize, usize, usize),
        (x0, x1, y0, y1): (usize, usize, usize, usize),
        channels: usize,
        out: &mut [Vec<f32>],
        base: usize,
    ) {
        let (xa, xb) = (x0.max(cx), x1.min(cx + cw));
        let (ya, yb) = (y0.max(cy), y1.min(cy + ch));
        if xa >= xb || ya >= yb {
            return;
        }
        let row = x1 - x0;
        for y in ya..yb {
            let src = ((y - cy) * cw + (xa - cx)) * channels;
            let dst = base + (y - y0) * row + (xa - x0);
            for (i, px) in v[src..src + (xb - xa) * channels]
                .chunks_exact(channels)
                .enumerate()
            {
                for (c, s) in px.iter().enumerate() {
                    out[c][dst + i] = f(*s);
                }
            }
        }
    }
    let (c, r) = ((cx, cy, cw, ch), (x0, x1, y0, y1));
    match data {
        DecodingResult::U8(v) => copy(v, f32::from, c, r, channels, out, base),
        DecodingResult::U16(v) => copy(v, f32::from, c, r, channels, out, base),
        DecodingResult::U32(v) => copy(v, |s| s as f32, c, r, channels, out, base),
        DecodingResult::U64(v) => copy(v, |s| s as f32, c, r, channels, out, base),
        DecodingResult::F16(v) => copy(v, |s| s.to_f32(), c, r, channels, out, base),
        DecodingResult::F32(v) => copy(v, |s| s, c, r, channels, out, base),
        DecodingResult::F64(v) => copy(v, |s| s as f32, c, r, channels, out, base),
        DecodingResult::I8(v) => copy(v, f32::from, c, r, channels, out, base),
        DecodingResult::I16(v) => copy(v, f32::from, c, r, channels, out, base),
        DecodingResult::I32(v) => copy(v, |s| s as f32, c, r, channels, out, base),
        DecodingResult::I64(v) => copy(v, |s| s as f32, c, r, channels, out, base),
    }
}

fn samples(data: &DecodingResult) -> usize {
    match data {
        DecodingResult::U8(v) => v.len(),
        DecodingResult::U16(v) => v.len(),
        DecodingResult::U32(v) => v.len(),
        DecodingResult::U64(v) => v.len(),
        DecodingResult::F16(v) => v.len(),
        DecodingResult::F32(v) => v.len(),
        DecodingResult::F64(v) => v.len(),
        DecodingResult::I8(v) => v.len(),
        DecodingResult::I16(v) => v.len(),
        DecodingResult::I32(v) => v.len(),
        DecodingResult::I64(v) => v.len(),
    }
}

/// Decodes the chunks of the current page that meet columns `x0..x1` and rows `y0..y1` into
/// `out` (see [`place`]). With a spool (and the page's slice), a chunk reaching outside those
/// columns or rows is decoded once for all the regions that share it ([`spooled`]).
#[allow(clippy::too_many_arguments)]
fn read_page<R: Read + Seek>(
    d: &mut Decoder<R>,
    path: &Path,
    page: usize,
    shape: &PageShape,
    (x0, x1, y0, y1): (usize, usize, usize, usize),
    out: &mut [Vec<f32>],
    base: usize,
    spool: Option<(&TiffSpool, usize)>,
) -> Result<(), ReadError> {
    let (cw, ch) = d.chunk_dimensions();
    let (cw, ch) = (cw.max(1) as usize, ch.max(1) as usize);
    let across = match d.get_chunk_type() {
        ChunkType::Strip => 1,
        ChunkType::Tile => shape.width.div_ceil(cw),
    };
    // Strips counted here: the crate's count overflows on RowsPerStrip 2^32 − 1 (the spec's
    // default, written out by some writers).
    let chunks = match d.get_chunk_type() {
        ChunkType::Strip => shape.height.div_ceil(ch),
        ChunkType::Tile => d.tile_count().map_err(|e| failed(path, e))? as usize,
    };
    let (col0, col1) = (x0 / cw, (x1 - 1) / cw);
    let (row0, row1) = (y0 / ch, (y1 - 1) / ch);
    for row in row0..=row1 {
        for col in col0..=col1.min(across - 1) {
            let i = row * across + col;
            if i >= chunks {
                return Err(bad(
                    path,
                    format!("page {page} has {chunks} strips or tiles; its size needs more"),
                ));
            }
            let (dw, dh) = d.chunk_data_dimensions(i as u32);
            let (dw, dh) = (dw as usize, dh as usize);
            let (cx, cy) = (col * cw, row * ch);
            let mut decode = || -> Result<DecodingResult, ReadError> {
                if let Some((spool, _)) = spool {
                    spool.count_decoded();
                }
                let data = d.read_chunk(i as u32).map_err(|e| failed(path, e))?;
                if samples(&data) < dw * dh * shape.channels {
                    return Err(bad(
                        path,
                        format!("page {page}: a strip or tile holds fewer samples than its size"),
                    ));
                }
                Ok(data)
            };
            let shared = cx < x0 || cx + dw > x1 || cy < y0 || cy + dh > y1;
            if let (Some((spool, slice)), true) = (spool, shared) {
                let key = (slice, i as u32);
                let (ya, yb) = (y0.max(cy), y1.min(cy + dh));
                // The chunk's pixels this region reads (it is released once all are read).
                let pixels = (x1.min(cx + dw) - x0.max(cx)) * (yb - ya);
                let spooled = spool.get_or_spool(key, pixels as u64, || {
                    spooled::to_spool(&decode().ok()?, dw * shape.channels, dh)
                });
                let rows = spooled.and_then(|s| {
                    spooled::rows(spool, (&key, &s), (ya - cy, yb - cy), (pixels, dw * dh))
                });
                if let Some(rows) = rows {
                    let at = (cx, ya, dw, yb - ya);
                    place(&rows, at, (x0, x1, y0, y1), shape.channels, out, base);
                    continue;
                }
            }
            let data = decode()?;
            place(
                &data,
                (cx, cy, dw, dh),
                (x0, x1, y0, y1),
                shape.channels,
                out,
                base,
            );
        }
    }
    Ok(())
}

/// Planes of `channels` × `n` zeros, refusing what cannot be allocated.
fn planes(path: &Path, channels: usize, n: usize) -> Result<Vec<Vec<f32>>, ReadError> {
    (0..channels)
        .map(|_| {
            let mut v = Vec::new();
            v.try_reserve_exact(n).map_err(|_| {
                ReadError::io(
                    path,
                    std::io::Error::new(
                        std::io::ErrorKind::OutOfMemory,
                        format!("cannot allocate {n} samples"),
                    ),
                )
            })?;
            v.resize(n, 0.0);
            Ok(v)
        })
        .collect()
}

/// Decodes a TIFF stack from its gathered files (one multi-page file, or the files of a stack
/// directory in order).
pub(crate) fn decode(src: &SourceFiles) -> Result<Volume, ReadError> {
    Ok(decode_channel(src, None)?.0)
}

/// [`decode`] with a channel chosen of channels stored as planes of their own; says whether
/// the file stored them so (else every channel of its pages is read: RGB's three).
pub(crate) fn decode_channel(
    src: &SourceFiles,
    channel: Option<usize>,
) -> Result<(Volume, bool), ReadError> {
    // An OME companion file first: its XML places the planes of the TIFF files after it.
    let companion = match src.files.first() {
        Some((name, bytes)) if is_companion_name(name) => {
            Some(Companion::of(bytes, &src.path_of(name))?)
        }
        _ => None,
    };
    let files = &src.files[usize::from(companion.is_some())..];
    let paths: Vec<PathBuf> = files.iter().map(|(n, _)| src.path_of(n)).collect();
    let stack = Stack::of(
        &paths,
        |f| file_pages(Cursor::new(files[f].1.as_slice()), &paths[f]),
        channel,
        companion.as_ref(),
    )?;
    if stack.time_points > 1 {
        return Err(ReadError::TimeSeries {
            path: src.origin.clone(),
            points: stack.time_points,
        });
    }
    let dims = stack.dims();
    let voxels = checked_voxels(dims).map_err(|e| ReadError::volume(&src.origin, e))?;
    let mut out = planes(&src.origin, stack.shape.channels, voxels)?;
    let slice = dims[0] * dims[1];
    let mut open: Option<(usize, Decoder<Cursor<&[u8]>>)> = None;
    for (z, &(f, p)) in stack.slices.iter().enumerate() {
        if let (Some(c), Some(sample)) = (stack.contiguous[f], raw_sample(&stack.shape)) {
            // An ImageJ stack over 4 GB: image `p`'s bytes (within the file: checked when its
            // pages were listed).
            let start = (c.offset + p as u64 * c.page_bytes) as usize;
            let bytes = &files[f].1[start..start + c.page_bytes as usize];
            let planes = deinterleave(bytes, sample, c.endian, stack.shape.channels, 1.0, 0.0);
            for (o, plane) in out.iter_mut().zip(planes) {
                o[z * slice..z * slice + plane.len()].copy_from_slice(&plane);
            }
            continue;
        }
        if open.as_ref().is_none_or(|(g, _)| *g != f) {
            open = Some((f, decoder(Cursor::new(files[f].1.as_slice()), &paths[f])?));
        }
        let (_, d) = open.as_mut().expect("opened above");
        d.seek_to_image(p).map_err(|e| failed(&paths[f], e))?;
        let whole = (0, dims[0], 0, dims[1]);
        read_page(
            d,
            &paths[f],
            p,
            &stack.shape,
            whole,
            &mut out,
            z * slice,
            None,
        )?;
    }
    Volume::new(dims, stack.spacing, out)
        .map(|v| (v, stack.channel_planes()))
        .map_err(|e| ReadError::volume(&src.origin, e))
}

/// A TIFF stack opened for region reads: the pages of each slice, read from disk when a region
/// needs them, only the strips or tiles the region covers.
#[derive(Debug)]
pub(crate) struct TiffRegions {
    files: Vec<PathBuf>,
    stack: Stack,
    /// Where each slice's rows lie when its page is stored uncompressed in strips (read as
    /// bytes, only the region's; `None`: decoded chunk by chunk).
    raw: Vec<Option<RawStrips>>,
    /// The samples' type, for the pages read as bytes.
    sample: Option<SampleType>,
    /// Chunks shared by regions (a page in one compressed strip, under bricks side by side),
    /// decoded once.
    spool: TiffSpool,
}

/// An uncompressed page in strips: where each strip starts, how many rows it holds, and the
/// file's byte order.
#[derive(Debug, Clone)]
struct RawStrips {
    offsets: Vec<u64>,
    rows_per_strip: usize,
    endian: Endian,
}

impl RawStrips {
    /// Whether the strips follow one another without a gap: the page is one run of bytes.
    fn contiguous(&self, shape: &PageShape) -> bool {
        let row = shape.bytes() / shape.height as u64;
        self.offsets.windows(2).enumerate().all(|(s, w)| {
            let rows = self
                .rows_per_strip
                .min(shape.height - s * self.rows_per_strip);
            w[0].checked_add(rows as u64 * row) == Some(w[1])
        })
    }
}

/// The sample type of `shape` as the raw reader converts it (`None`: half floats, decoded).
fn raw_sample(shape: &PageShape) -> Option<SampleType> {
    Some(match (shape.bits, shape.format) {
        (8, 1) => SampleType::U8,
        (8, 2) => SampleType::I8,
        (16, 1) => SampleType::U16,
        (16, 2) => SampleType::I16,
        (32, 1) => SampleType::U32,
        (32, 2) => SampleType::I32,
        (32, 3) => SampleType::F32,
        (64, 1) => SampleType::U64,
        (64, 2) => SampleType::I64,
        (64, 3) => SampleType::F64,
        _ => return None,
    })
}

/// Where the current page's rows lie, when it is stored uncompressed in strips that hold
/// them all (else `None`: the page is decoded chunk by chunk).
fn raw_strips<R: Read + Seek>(
    d: &mut Decoder<R>,
    shape: &PageShape,
    path: &Path,
) -> Option<RawStrips> {
    if !matches!(d.get_chunk_type(), ChunkType::Strip) {
        return None;
    }
    let tag = |d: &mut Decoder<R>, t: Tag| tag_u64(d, t, path).ok();
    if tag(d, Tag::Compression)?.unwrap_or(1) != 1 || tag(d, Tag::Predictor)?.unwrap_or(1) != 1 {
        return None;
    }
    // Extra samples a pixel (not alpha: RGB and one more) are dropped by the decoder; as bytes
    // they would shift every pixel.
    if tag(d, Tag::SamplesPerPixel)?.unwrap_or(1) != shape.channels as u64 {
        return None;
    }
    let mut offsets = d.get_tag_u64_vec(Tag::StripOffsets).ok()?;
    let counts = d.get_tag_u64_vec(Tag::StripByteCounts).ok()?;
    let rows = (tag(d, Tag::RowsPerStrip)?.unwrap_or(u64::MAX) as usize).clamp(1, shape.height);
    let row_bytes = (shape.width * shape.channels * usize::from(shape.bits) / 8) as u64;
    let strips = shape.height.div_ceil(rows);
    if offsets.len() < strips || counts.len() < strips {
        return None;
    }
    offsets.truncate(strips);
    for s in 0..strips {
        let held = rows.min(shape.height - s * rows) as u64;
        if counts[s] < held * row_bytes || offsets[s].checked_add(counts[s]).is_none() {
            return None;
        }
    }
    let endian = match d.byte_order() {
        ::tiff::tags::ByteOrder::LittleEndian => Endian::Little,
        ::tiff::tags::ByteOrder::BigEndian => Endian::Big,
    };
    Some(RawStrips {
        offsets,
        rows_per_strip: rows,
        endian,
    })
}

impl TiffRegions {
    /// Opens a multi-page TIFF file, or the TIFF files of a directory, reading every page's
    /// directory (not its samples).
    pub(crate) fn open(path: &Path, channel: Option<usize>) -> Result<TiffRegions, ReadError> {
        let (files, stack) = open_stack(path, channel)?;
        // Uncompressed pages in strips are read as bytes, only the region's: decoding a whole
        // strip (often the whole page) for every brick across it would read each slice once
        // per brick in the plane.
        let sample = raw_sample(&stack.shape);
        let mut raw = Vec::with_capacity(stack.slices.len());
        let mut open: Option<(usize, Decoder<BufReader<File>>)> = None;
        for &(f, p) in &stack.slices {
            if let Some(c) = stack.contiguous[f] {
                raw.push(Some(c.strips(p, &stack.shape)));
                continue;
            }
            if sample.is_none() {
                raw.push(None);
                continue;
            }
            if open.as_ref().is_none_or(|(g, _)| *g != f) {
                let file = File::open(&files[f]).map_err(|e| ReadError::io(&files[f], e))?;
                open = Some((f, decoder(BufReader::new(file), &files[f])?));
            }
            let (_, d) = open.as_mut().expect("opened above");
            d.seek_to_image(p).map_err(|e| failed(&files[f], e))?;
            raw.push(raw_strips(d, &stack.shape, &files[f]));
        }
        Ok(TiffRegions {
            files,
            stack,
            raw,
            sample,
            spool: TiffSpool::default(),
        })
    }

    pub(crate) fn dims(&self) -> [usize; 3] {
        self.stack.dims()
    }

    /// Time points: an ImageJ hyperstack's frames or an OME-TIFF's `SizeT`, else 1.
    pub(crate) fn time_points(&self) -> usize {
        self.stack.time_points
    }

    /// Seconds between time points, when an OME description says.
    pub(crate) fn time_step(&self) -> Option<f64> {
        self.stack.time_step
    }

    pub(crate) fn channels(&self) -> usize {
        self.stack.shape.channels
    }

    /// Whether the file stores channels as planes of their own, one of them chosen at open.
    pub(crate) fn channel_chosen(&self) -> bool {
        self.stack.channel_planes()
    }

    pub(crate) fn spacing(&self) -> [f32; 3] {
        self.stack.spacing
    }

    /// The samples of the box at `origin` of `size` of time point `t` (within the volume: the
    /// caller checks), one plane per channel.
    pub(crate) fn read(
        &self,
        t: usize,
        origin: [usize; 3],
        size: [usize; 3],
    ) -> Result<Vec<Vec<f32>>, ReadError> {
        let n = checked_voxels(size).map_err(|e| ReadError::volume(&self.files[0], e))?;
        let mut out = planes(&self.files[0], self.channels(), n)?;
        let window = (
            origin[0],
            origin[0] + size[0],
            origin[1],
            origin[1] + size[1],
        );
        let mut open: Option<(usize, Decoder<BufReader<File>>)> = None;
        let mut bytes: Option<(usize, File)> = None;
        let mut buf = Vec::new();
        for z in 0..size[2] {
            let slice = self.stack.slice_index(t, origin[2] + z);
            let (f, p) = self.stack.slices[slice];
            let path = &self.files[f];
            let base = z * size[0] * size[1];
            if let (Some(raw), Some(sample)) = (&self.raw[slice], self.sample) {
                if bytes.as_ref().is_none_or(|(g, _)| *g != f) {
                    let file = File::open(path).map_err(|e| ReadError::io(path, e))?;
                    bytes = Some((f, file));
                }
                let (_, file) = bytes.as_mut().expect("opened above");
                let shape = &self.stack.shape;
                let pixel = shape.channels * usize::from(shape.bits) / 8;
                let row = size[0] * pixel;
                buf.resize(row * size[1], 0);
                let (mut j, mut y) = (0, window.2);
                while y < window.3 {
                    let s = y / raw.rows_per_strip;
                    let first = y - s * raw.rows_per_strip;
                    // Whole rows follow one another within a strip: read together.
                    let run = if size[0] == shape.width {
                        (raw.rows_per_strip - first).min(window.3 - y)
                    } else {
                        1
                    };
                    let at = raw.offsets[s] + ((first * shape.width + window.0) * pixel) as u64;
                    let into = &mut buf[j * row..(j + run) * row];
                    let want = into.len() as u64;
                    (j, y) = (j + run, y + run);
                    file.seek(std::io::SeekFrom::Start(at))
                        .and_then(|_| file.read_exact(into))
                        .map_err(|e| match e.kind() {
                            std::io::ErrorKind::UnexpectedEof => ReadError::Truncated {
                                path: path.clone(),
                                offset: at,
                                expected: want,
                                actual: 0,
                            },
                            _ => ReadError::io(path, e),
                        })?;
                }
                let planes = deinterleave(&buf, sample, raw.endian, shape.channels, 1.0, 0.0);
                for (o, plane) in out.iter_mut().zip(planes) {
                    o[base..base + plane.len()].copy_from_slice(&plane);
                }
                continue;
            }
            if open.as_ref().is_none_or(|(g, _)| *g != f) {
                let file = File::open(path).map_err(|e| ReadError::io(path, e))?;
                open = Some((f, decoder(BufReader::new(file), path)?));
            }
            let (_, d) = open.as_mut().expect("opened above");
            d.seek_to_image(p).map_err(|e| failed(path, e))?;
            // The page read at open may have changed since: its shape is checked again.
            if page_shape(d, path, p)? != Some(self.stack.shape) {
                return Err(ReadError::Series {
                    path: path.clone(),
                    reason: format!("page {p} changed since the stack was opened"),
                });
            }
            let spool = Some((&self.spool, slice));
            read_page(d, path, p, &self.stack.shape, window, &mut out, base, spool)?;
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_gap_in_the_slice_files_numbers_is_found_and_other_names_are_not_judged() {
        let paths = |names: &[&str]| -> Vec<PathBuf> {
            names.iter().map(|n| Path::new("/d").join(n)).collect()
        };
        let gap = numbering_gap(&paths(&[
            "s_0001.tif",
            "s_0002.tif",
            "s_0004.tif",
            "s_0005.tif",
        ]));
        let gap = gap.expect("a missing file");
        assert!(
            gap.contains("1 slice(s) between \"s_0002.tif\" and \"s_0004.tif\""),
            "{gap}"
        );
        let twice = numbering_gap(&paths(&["z1.tif", "z01.tif", "z2.tif"])).expect("a repeat");
        assert!(twice.contains("the same number"), "{twice}");
        for fine in [
            &["s_0001.tif", "s_0002.tif", "s_0003.tif"][..],
            // Every other slice kept: one step all along.
            &["s_000.tif", "s_002.tif", "s_004.tif", "s_006.tif"],
            // A number that is the same in every name (a date) beside the slice's.
            &["scan_2024_z7.tif", "scan_2024_z8.tif", "scan_2024_z9.tif"],
            // Names numbered otherwise are not judged.
            &["a.tif", "b.tif", "c.tif"],
            &["t1_z1.tif", "t1_z2.tif", "t2_z1.tif"],
            &["s_1.tif", "s_3.tif"],
            &["s_3.tif", "s_1.tif", "s_2.tif"],
        ] {
            assert_eq!(numbering_gap(&paths(fine)), None, "{fine:?}");
        }
    }

    #[test]
    fn names_sort_naturally() {
        let mut names = vec![
            "z10.tif",
            "z2.tif",
            "z1.tif",
            "z002b.tif",
            "a.tif",
            "z02.tif",
        ];
        names.sort_by(|a, b| natural_order(a, b));
        assert_eq!(
            names,
            [
                "a.tif",
                "z1.tif",
                "z02.tif",
                "z2.tif",
                "z002b.tif",
                "z10.tif"
            ]
        );
    }

    /// An uncompressed page in strips is read as bytes, only the region's rows, and gives what
    /// decoding its strips gives.
    #[test]
    fn uncompressed_strips_are_read_as_bytes_alike() {
        use ::tiff::encoder::{colortype::Gray16, TiffEncoder};
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("raw.tif");
        let (w, h) = (13usize, 11usize);
        {
            let mut e = TiffEncoder::new(File::create(&path).unwrap()).unwrap();
            for z in 0..3u16 {
                let data: Vec<u16> = (0..(w * h) as u16).map(|i| i * 7 + z * 1000).collect();
                let mut image = e.new_image::<Gray16>(w as u32, h as u32).unwrap();
                image.rows_per_strip(2).unwrap();
                image.write_data(&data).unwrap();
            }
        }
        let by_bytes = TiffRegions::open(&path, None).unwrap();
        assert!(by_bytes.raw.iter().all(Option::is_some), "read as bytes");
        let mut decoded = TiffRegions::open(&path, None).unwrap();
        decoded.raw.iter_mut().for_each(|r| *r = None);
        for (origin, size) in [
            ([0, 0, 0], [13, 11, 3]),
            ([4, 3, 1], [6, 5, 2]),
            ([12, 10, 2], [1, 1, 1]),
        ] {
            let a = by_bytes.read(0, origin, size).unwrap();
            assert_eq!(a, decoded.read(0, origin, size).unwrap(), "{origin:?}");
            let first = (origin[2] * 1000 + (origin[1] * w + origin[0]) * 7) as f32;
            assert_eq!(a[0][0], first);
        }
    }

    /// A compressed strip under several regions (a page in one Deflate strip, or strips of
    /// full rows under bricks side by side) is decoded twice for all of them (the second time
    /// into the spool), from threads at once too, and the regions read what decoding the whole
    /// gives; a reader of one region spools nothing.
    #[test]
    fn a_compressed_strip_shared_by_regions_is_decoded_twice_for_all() {
        use crate::reader::spool::read_bricks_from_two_threads;
        use ::tiff::encoder::{colortype::Gray16, Compression, DeflateLevel, TiffEncoder};
        let dir = tempfile::tempdir().unwrap();
        let (w, h, pages) = (13usize, 11usize, 4usize);
        for rows in [h, 4] {
            let path = dir.path().join(format!("deflate_{rows}.tif"));
            {
                let file = File::create(&path).unwrap();
                let mut e = TiffEncoder::new(file)
                    .unwrap()
                    .with_compression(Compression::Deflate(DeflateLevel::Fast));
                for z in 0..pages as u16 {
                    let data: Vec<u16> = (0..(w * h) as u16).map(|i| i * 7 + z * 1000).collect();
                    let mut image = e.new_image::<Gray16>(w as u32, h as u32).unwrap();
                    image.rows_per_strip(rows as u32).unwrap();
                    image.write_data(&data).unwrap();
                }
            }
            let whole = TiffRegions::open(&path, None).unwrap();
            assert!(whole.raw.iter().all(Option::is_none), "compressed: decoded");
            let all = whole.read(0, [0, 0, 0], [w, h, pages]).unwrap().remove(0);
            let strips = pages * h.div_ceil(rows);
            assert_eq!(whole.spool.decoded(), strips, "the whole: each strip once");
            assert!(!whole.spool.has_file(), "nothing shared, nothing spooled");
            // Bricks of 5 × 4 × 3 voxels over the volume, read by two threads at once.
            let bricks = TiffRegions::open(&path, None).unwrap();
            read_bricks_from_two_threads([w, h, pages], [5, 4, 3], |origin, size| {
                let got = bricks.read(0, origin, size).unwrap().remove(0);
                for (j, v) in got.iter().enumerate() {
                    let (x, y, z) = (j % size[0], j / size[0] % size[1], j / size[0] / size[1]);
                    let at = ((origin[2] + z) * h + origin[1] + y) * w + origin[0] + x;
                    assert_eq!(*v, all[at], "{rows} rows a strip, {origin:?} {size:?}");
                }
            });
            assert_eq!(
                bricks.spool.decoded(),
                2 * strips,
                "{rows} rows a strip: each strip twice"
            );
            assert!(bricks.spool.has_file());
            assert_eq!(bricks.spool.held().0, 0, "every strip read whole: released");
            // A spool of two strips' room, from two threads: the oldest strips are released
            // to make room, and every brick still reads what the whole gives.
            let mut tight = TiffRegions::open(&path, None).unwrap();
            tight.spool = TiffSpool::with_budget((2 * w * rows * 2) as u64);
            read_bricks_from_two_threads([w, h, pages], [5, 4, 3], |origin, size| {
                let got = tight.read(0, origin, size).unwrap().remove(0);
                for (j, v) in got.iter().enumerate() {
                    let (x, y, z) = (j % size[0], j / size[0] % size[1], j / size[0] / size[1]);
                    let at = ((origin[2] + z) * h + origin[1] + y) * w + origin[0] + x;
                    assert_eq!(
                        *v, all[at],
                        "{rows} rows a strip, tight, {origin:?} {size:?}"
                    );
                }
            });
            assert!(tight.spool.held().1 <= (2 * w * rows * 2) as u64);
            // Two passes of bricks in order on one thread: a strip is released once the
            // bricks across it have read it, so the spool holds one layer of bricks' strips
            // at most; the second pass spools each strip again, once.
            let passes = TiffRegions::open(&path, None).unwrap();
            for _ in 0..2 {
                for z in (0..pages).step_by(3) {
                    for y in (0..h).step_by(4) {
                        for x in (0..w).step_by(5) {
                            let size = [5.min(w - x), 4.min(h - y), 3.min(pages - z)];
                            let got = passes.read(0, [x, y, z], size).unwrap().remove(0);
                            let at = (z * h + y) * w + x;
                            assert_eq!(got[0], all[at], "{rows} rows a strip, {x} {y} {z}");
                        }
                    }
                }
            }
            assert_eq!(
                passes.spool.decoded(),
                3 * strips,
                "{rows} rows a strip: passes"
            );
            let strip_bytes = w * rows * 2;
            assert_eq!(
                passes.spool.held(),
                (0, 3 * strip_bytes as u64),
                "{rows} rows a strip: three pages' strips of a band at most"
            );
            // One brick of a reader of its own (a worker's brick job) spools nothing.
            let one = TiffRegions::open(&path, None).unwrap();
            let brick = one.read(0, [5, 4, 0], [5, 4, pages]).unwrap().remove(0);
            assert_eq!(brick[0], all[4 * w + 5]);
            // Rows 4..8 lie in one strip of a page at either strip height.
            assert_eq!(one.spool.decoded(), pages);
            assert!(
                !one.spool.has_file(),
                "{rows} rows a strip: one region, no spool"
            );
        }
    }

    #[test]
    fn magic_and_names_say_tiff() {
        assert!(looks_like_tiff(b"II*\0\x08\0\0\0"));
        assert!(looks_like_tiff(b"MM\0*"));
        assert!(looks_like_tiff(b"II+\0\x08\0"));
        assert!(!looks_like_tiff(b"NRRD0004"));
        assert!(is_tiff_name("Stack.TIF") && is_tiff_name("a.tiff") && !is_tiff_name("a.tif.gz"));
    }

    #[test]
    fn units_convert_to_mm() {
        assert_eq!(unit_mm("micron"), Some(1e-3));
        assert_eq!(unit_mm("\\u00B5m"), Some(1e-3));
        assert_eq!(unit_mm("µm"), Some(1e-3));
        assert_eq!(unit_mm("cm"), Some(10.0));
        assert_eq!(unit_mm("pixel"), None);
        let xml = r#"<Pixels SizeC="1" PhysicalSizeX="0.5" PhysicalSizeXUnit="nm">"#;
        assert_eq!(xml_attr(xml, "PhysicalSizeX"), Some("0.5"));
        assert_eq!(xml_attr(xml, "PhysicalSizeXUnit"), Some("nm"));
        assert_eq!(xml_attr(xml, "SizeT"), None);
    }
}
