//! DICOM with dicom-rs (`dicom-object` parses, `dicom-pixeldata` decodes): a series directory
//! (one file per slice) or multi-frame files (classic, or enhanced with per-frame functional
//! groups). Files are grouped by Series Instance UID (a directory must hold one image series),
//! frames are sorted along the slice normal (the cross product of the Image Orientation
//! (Patient) row and column directions) by Image Position (Patient), and the steps between them
//! are checked: duplicates, gaps (missing slices), irregular spacing and a sheared grid (gantry
//! tilt) are errors that name the files and positions. Samples are 8, 16 or 32 bits, signed or
//! unsigned (Bits Stored / High Bit honoured, sign-extended), monochrome (one channel) or RGB
//! (three), with Rescale Slope / Intercept applied per frame, so CT values are in HU; 1-bit
//! masks read as 0 and 1.
//!
//! RT Dose grids place their frames by Grid Frame Offset Vector (relative to Image Position
//! (Patient), or absolute z for axial grids) and their values are scaled by Dose Grid Scaling
//! (so they are in Dose Units, Gy). Multi-frame files whose frames step through time (a
//! Frame Increment Pointer to Frame Time and the like) and series whose slices repeat at
//! several time points are refused as time series. Colour: RGB, YBR_FULL and YBR_FULL_422
//! (converted to RGB where the codec did not), and PALETTE COLOR (the palette applied, giving
//! RGB; segmented palettes are refused). Attributes written with VR UN are read as
//! the VR the standard dictionary gives them; 32-bit samples in big-endian files are put back
//! in order from the units dicom-rs reads them in, as are 8-bit samples in 16-bit words (OW);
//! 1-bit masks in big-endian files are read as OB (as OW, their bit order is ambiguous and
//! they are refused). An element whose VR bytes name no VR is read in the layout other
//! toolkits read it in (dcmtk's or pydicom's, whichever fits the bytes) when the reader does
//! not use it, and refused, naming it, when it does.
//!
//! Transfer syntaxes: Implicit VR Little Endian, Explicit VR Little and Big Endian, Deflated
//! Explicit VR Little Endian, Encapsulated Uncompressed, and the encapsulated ones
//! dicom-pixeldata decodes: RLE Lossless, JPEG Baseline (Process 1), JPEG Extended (Process 2 &
//! 4, 8-bit samples: 12-bit lossy JPEG is refused naming it), JPEG Lossless Non-Hierarchical (Process 14, and Selection Value 1) in pure Rust; JPEG-LS
//! (lossless and near-lossless) through CharLS (`charls`, built from source with cmake) when
//! the default-off `jpeg-ls` feature is on, refused naming the feature otherwise; JPEG
//! 2000 (lossless and lossy, and High-Throughput JPEG 2000) through OpenJPEG's Rust port
//! (`openjp2`). JPEG XL needs a codec this build does not enable; such files fail with an error
//! naming the transfer syntax.
//!
//! The volume's axes: x along the row direction (increasing column index), y along the column
//! direction (increasing row index), z along the slice normal; its placement is the position of
//! the first slice's first pixel and those three directions, in the patient frame (LPS).
//! Untrusted input: frame sizes are checked against [`MAX_VOXELS`], against the file's size
//! (at most [`MAX_FILE_EXPANSION`]× it) before any per-frame work, and against the pixel data
//! present before decoding, encapsulated frames may not expand beyond [`MAX_EXPANSION`] × their
//! compressed bytes, and a panic inside the DICOM crates is caught and reported as an error on
//! the file.

use std::collections::BTreeMap;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use dicom_object::file::ReadPreamble;
use dicom_object::{DefaultDicomObject, InMemDicomObject, OpenFileOptions};
use dicom_pixeldata::PixelDecoder;
use dicom_transfer_syntax_registry::{TransferSyntaxIndex, TransferSyntaxRegistry};
use wavesplat_codec::volume::{Placement, Volume, MAX_VOXELS};

use super::{voxel_count, ReadError, SourceFiles, MAX_SOURCE_FILES};

/// Largest ratio of decoded to encapsulated bytes accepted for a frame (plus 1 MiB): lossless
/// codecs on real images stay far below it; a forged header on a tiny file does not.
pub const MAX_EXPANSION: usize = 1024;

/// Largest ratio of decoded sample bytes to a file's bytes accepted before anything is
/// allocated for its frames (plus [`EXPANSION_SLACK`] per volume): deflate, which a Deflated
/// Explicit VR file applies to the whole data set, cannot expand beyond 1032×, and encapsulated
/// frames are held to [`MAX_EXPANSION`].
pub const MAX_FILE_EXPANSION: usize = 1032;

/// Decoded bytes allowed beyond the expansion ratios (tiny compressed frames of flat images).
pub const EXPANSION_SLACK: usize = 1 << 20;

/// A multi-valued decimal attribute as DICOM writes it (`1\0\0\0\1\0`), or "absent".
fn dicom_values<const N: usize>(v: &Option<[f64; N]>) -> String {
    match v {
        Some(values) => values
            .iter()
            .map(|x| x.to_string())
            .collect::<Vec<_>>()
            .join("\\"),
        None => "absent".to_string(),
    }
}

/// Transfer Syntax UID of RLE Lossless.
const RLE_LOSSLESS: &str = "1.2.840.10008.1.2.5";

/// SOP Class UID of a DICOMDIR (Media Storage Directory Storage): skipped in series directories.
const DICOMDIR_SOP_CLASS: &str = "1.2.840.10008.1.3.10";

/// Whether `head` has the DICOM file preamble (`DICM` at offset 128).
pub(crate) fn has_preamble(head: &[u8]) -> bool {
    head.len() >= 132 && &head[128..132] == b"DICM"
}

/// The name of an attribute in messages, e.g. `(0028,0030) Pixel Spacing`.
fn tag_name(tag: Tag) -> String {
    let name = match tag {
        tags::SERIES_INSTANCE_UID => "Series Instance UID",
        tags::ROWS => "Rows",
        tags::COLUMNS => "Columns",
        tags::PIXEL_SPACING => "Pixel Spacing",
        tags::IMAGER_PIXEL_SPACING => "Imager Pixel Spacing",
        tags::IMAGE_ORIENTATION_PATIENT => "Image Orientation (Patient)",
        tags::IMAGE_POSITION_PATIENT => "Image Position (Patient)",
        tags::SLICE_THICKNESS => "Slice Thickness",
        tags::SPACING_BETWEEN_SLICES => "Spacing Between Slices",
        tags::NUMBER_OF_FRAMES => "Number of Frames",
        tags::FRAME_INCREMENT_POINTER => "Frame Increment Pointer",
        tags::GRID_FRAME_OFFSET_VECTOR => "Grid Frame Offset Vector",
        tags::DOSE_GRID_SCALING => "Dose Grid Scaling",
        tags::SAMPLES_PER_PIXEL => "Samples per Pixel",
        tags::PHOTOMETRIC_INTERPRETATION => "Photometric Interpretation",
        tags::BITS_ALLOCATED => "Bits Allocated",
        tags::BITS_STORED => "Bits Stored",
        tags::HIGH_BIT => "High Bit",
        tags::PIXEL_REPRESENTATION => "Pixel Representation",
        tags::PLANAR_CONFIGURATION => "Planar Configuration",
        tags::RESCALE_SLOPE => "Rescale Slope",
        tags::RESCALE_INTERCEPT => "Rescale Intercept",
        tags::PIXEL_DATA => "Pixel Data",
        tags::TRANSFER_SYNTAX_UID => "Transfer Syntax UID",
        _ => "",
    };
    format!("({:04X},{:04X}) {name}", tag.group(), tag.element())
        .trim_end()
        .to_string()
}

fn dicom_err(path: &Path, tag: Option<Tag>, reason: impl Into<String>) -> ReadError {
    ReadError::Dicom {
        path: path.to_path_buf(),
        tag: tag.map(tag_name),
        reason: reason.into(),
    }
}

/// Gathers the DICOM files directly inside `dir` (regular, non-hidden files starting with the
/// DICOM preamble), sorted by name.
pub(crate) fn gather_series(dir: &Path) -> Result<SourceFiles, ReadError> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .map_err(|e| ReadError::io(dir, e))?
        .collect::<Result<_, _>>()
        .map_err(|e| ReadError::io(dir, e))?;
    entries.sort_by_key(|e| e.file_name());
    let mut files = Vec::new();
    for e in entries {
        let name = e.file_name().to_string_lossy().into_owned();
        let path = e.path();
        if name.starts_with('.')
            || !e
                .file_type()
                .map_err(|x| ReadError::io(&path, x))?
                .is_file()
        {
            continue;
        }
        if !is_dicom_file(&path).map_err(|x| ReadError::io(&path, x))? {
            continue;
        }
        if files.len() == MAX_SOURCE_FILES {
            return Err(ReadError::Series {
                path: dir.to_path_buf(),
                reason: format!("more than {MAX_SOURCE_FILES} DICOM files"),
            });
        }
        files.push((name, super::read_file(&path)?));
    }
    if files.is_empty() {
        return Err(ReadError::Series {
            path: dir.to_path_buf(),
            reason: "no DICOM files (files with the DICM preamble) in this directory".into(),
        });
    }
    Ok(SourceFiles {
        origin: dir.to_path_buf(),
        base: dir.to_path_buf(),
        format: Some(super::Format::Dicom),
        files,
    })
}

/// Whether the file at `path` starts with the DICOM preamble (reads 132 bytes).
pub fn is_dicom_file(path: &Path) -> std::io::Result<bool> {
    use std::io::Read;
    let mut head = [0u8; 132];
    let mut f = std::fs::File::open(path)?;
    let mut got = 0;
    while got < head.len() {
        match f.read(&mut head[got..])? {
            0 => break,
            n => got += n,
        }
    }
    Ok(has_preamble(&head[..got]))
}

/// Largest nesting of sequences accepted.
const MAX_DEPTH: usize = 32;

/// Walks the element headers of a file (meta group, then the data set in its transfer
/// syntax; into sequences, items and encapsulated fragments) and checks that every defined
/// length fits in the bytes that remain. dicom-rs sizes its buffers by the declared length
/// before reading, so without this walk a 1 KB file declaring a 4 GB text element allocates
/// 4 GB. Deflated data sets are inflated first (within [`MAX_EXPANSION`]).
///
/// Returns the elements with an unknown VR it read ([`Walker::odd_header`]), and the rewrites
/// of `bytes` that make dicom-rs read them as the walk did.
fn check_lengths(path: &Path, bytes: &[u8]) -> Result<Walked, ReadError> {
    let body = bytes.get(132..).unwrap_or(&[]);
    let mut w = Walker {
        explicit: true,
        big: false,
        patches: Vec::new(),
        odd: Vec::new(),
    };
    // The meta group: explicit VR little endian, read as dicom-rs reads it: a group length
    // (0002,0000) first, then whole elements (of any group) until that many bytes are read.
    // Where the data set starts must agree with the parser's, or the walk checks other
    // "elements" than the parser reads (a group length past a run of zeroed elements made
    // dicom-rs read a 1.3 GB value the walk never saw).
    let Header {
        tag,
        len,
        size: hdr,
        ..
    } = w.header(body, 0).map_err(|m| dicom_err(path, None, m))?;
    let group_length = match (tag, len) {
        (Tag(0x0002, 0x0000), Some(4)) => body
            .get(hdr..hdr + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
            .ok_or_else(|| dicom_err(path, Some(tag), "truncated group length"))?,
        _ => {
            return Err(dicom_err(
                path,
                Some(tag),
                "the file meta group does not start with its group length (0002,0000)",
            ))
        }
    };
    let meta_start = hdr + 4;
    let mut pos = meta_start;
    let mut ts = String::new();
    while pos - meta_start < group_length {
        let Header {
            tag,
            len,
            size: hdr,
            odd,
            ..
        } = w.header(body, pos).map_err(|m| dicom_err(path, None, m))?;
        if let Some(vr) = odd {
            return Err(dicom_err(
                path,
                Some(tag),
                format!(
                    "has an unknown value representation {} in the file meta group",
                    show_vr(vr.bytes)
                ),
            ));
        }
        let start = pos + hdr;
        let len = len.ok_or_else(|| dicom_err(path, None, "undefined length in the meta group"))?;
        let end = start
            .checked_add(len)
            .filter(|e| *e <= body.len())
            .ok_or_else(|| {
                dicom_err(
                    path,
                    Some(tag),
                    format!("declares {len} bytes, {} remain", body.len() - start),
                )
            })?;
        if tag == tags::TRANSFER_SYNTAX_UID {
            ts = String::from_utf8_lossy(&body[start..end])
                .trim_end_matches(['\0', ' '])
                .to_string();
        }
        pos = end;
    }
    let rest = &body[pos..];
    let data_start = 132 + pos;
    let mut deflated = false;
    let inflated;
    let data: &[u8] = match ts.as_str() {
        "1.2.840.10008.1.2" => {
            w.explicit = false;
            rest
        }
        "1.2.840.10008.1.2.2" => {
            w.big = true;
            rest
        }
        "1.2.840.10008.1.2.1.99" => {
            use std::io::Read;
            let limit = rest
                .len()
                .saturating_mul(MAX_EXPANSION)
                .saturating_add(1 << 20);
            let mut out = Vec::new();
            flate2::read::DeflateDecoder::new(rest)
                .take(limit as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| {
                    dicom_err(path, None, format!("the deflated data set is corrupt: {e}"))
                })?;
            if out.len() > limit {
                return Err(dicom_err(
                    path,
                    None,
                    "the deflated data set expands beyond the limit",
                ));
            }
            inflated = out;
            deflated = true;
            &inflated
        }
        _ => rest,
    };
    w.dataset(data, 0, data.len(), 0, false)
        .map_err(|(tag, m)| dicom_err(path, tag, m))?;
    if deflated {
        if let Some(p) = w.patches.first() {
            return Err(dicom_err(
                path,
                Some(p.tag),
                "has an unknown value representation with a 2-byte length (or in implicit VR) \
                 inside a deflated data set, which this reader cannot read",
            ));
        }
    }
    for p in &mut w.patches {
        p.at += data_start;
    }
    Ok(Walked {
        patches: w.patches,
        odd: w.odd,
    })
}

/// What [`check_lengths`] found beyond lengths that fit.
struct Walked {
    patches: Vec<Patch>,
    odd: Vec<(Tag, OddVr)>,
}

/// An element header as the walk reads it.
struct Header {
    tag: Tag,
    /// The VR as written (explicit syntaxes); `UN` for an unknown one, as dicom-rs takes it.
    vr: Option<[u8; 2]>,
    /// `None`: undefined.
    len: Option<usize>,
    /// Bytes of the header.
    size: usize,
    /// An unknown VR, and how its length was read.
    odd: Option<OddVr>,
}

/// VR bytes that name no VR (in an explicit VR data set), and the layout the walk read the
/// element in: the reference toolkits differ, so the walk takes the one under which the
/// element's value and the next element header fit ([`Walker::odd_header`]).
#[derive(Debug, Clone, Copy)]
struct OddVr {
    bytes: [u8; 2],
    layout: OddLayout,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum OddLayout {
    /// Two reserved bytes and a 4-byte length, as the VRs added to the standard lately (UC,
    /// UR, OL, OV, SV, UV) are written: how dcmtk reads unknown VRs of two capital letters,
    /// and dicom-rs every unknown VR.
    Extended,
    /// A 2-byte length: how dcmtk reads VR bytes that are not two capital letters ("??"),
    /// and pydicom unknown VRs of capital letters.
    Short,
    /// The element is in implicit VR (a 4-byte length where the VR would be): how pydicom
    /// reads VR bytes that are not capital letters (writers that switch to implicit VR
    /// inside sequences).
    Implicit,
}

/// VR bytes in messages: as text where printable, else as hexadecimal bytes.
fn show_vr(vr: [u8; 2]) -> String {
    if vr.iter().all(|b| b.is_ascii_graphic()) {
        format!("{:?}", String::from_utf8_lossy(&vr))
    } else {
        format!("(bytes {:02X} {:02X})", vr[0], vr[1])
    }
}

/// Whether `vr` is a VR written with a 4-byte length (`Some(true)`), a 2-byte one
/// (`Some(false)`), or none the reader knows.
fn vr_length_size(vr: [u8; 2]) -> Option<bool> {
    match &vr {
        b"OB" | b"OD" | b"OF" | b"OL" | b"OV" | b"OW" | b"SQ" | b"SV" | b"UC" | b"UN" | b"UR"
        | b"UT" | b"UV" => Some(true),
        b"AE" | b"AS" | b"AT" | b"CS" | b"DA" | b"DS" | b"DT" | b"FD" | b"FL" | b"IS" | b"LO"
        | b"LT" | b"PN" | b"SH" | b"SL" | b"SS" | b"ST" | b"TM" | b"UI" | b"UL" | b"US" => {
            Some(false)
        }
        _ => None,
    }
}

/// Attributes the reader (or dicom-pixeldata, decoding the pixel data) reads: one of these
/// with an unknown VR is refused rather than read by a guessed layout.
const NEEDED: [Tag; 47] = [
    tags::SERIES_INSTANCE_UID,
    tags::INSTANCE_NUMBER,
    tags::ROWS,
    tags::COLUMNS,
    tags::NUMBER_OF_FRAMES,
    tags::SAMPLES_PER_PIXEL,
    tags::PHOTOMETRIC_INTERPRETATION,
    tags::BITS_ALLOCATED,
    tags::BITS_STORED,
    tags::HIGH_BIT,
    tags::PIXEL_REPRESENTATION,
    tags::PLANAR_CONFIGURATION,
    tags::PIXEL_SPACING,
    tags::IMAGER_PIXEL_SPACING,
    tags::IMAGE_ORIENTATION_PATIENT,
    tags::IMAGE_POSITION_PATIENT,
    tags::SLICE_THICKNESS,
    tags::SPACING_BETWEEN_SLICES,
    tags::RESCALE_SLOPE,
    tags::RESCALE_INTERCEPT,
    tags::FRAME_INCREMENT_POINTER,
    tags::GRID_FRAME_OFFSET_VECTOR,
    tags::DOSE_GRID_SCALING,
    tags::TEMPORAL_POSITION_IDENTIFIER,
    tags::TRIGGER_TIME,
    tags::FRAME_TIME,
    tags::FRAME_TIME_VECTOR,
    tags::ACTUAL_FRAME_DURATION,
    tags::TIME_SLOT_VECTOR,
    tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE,
    tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE,
    tags::PIXEL_MEASURES_SEQUENCE,
    tags::PLANE_POSITION_SEQUENCE,
    tags::PLANE_ORIENTATION_SEQUENCE,
    tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
    tags::RED_PALETTE_COLOR_LOOKUP_TABLE_DESCRIPTOR,
    tags::GREEN_PALETTE_COLOR_LOOKUP_TABLE_DESCRIPTOR,
    tags::BLUE_PALETTE_COLOR_LOOKUP_TABLE_DESCRIPTOR,
    tags::RED_PALETTE_COLOR_LOOKUP_TABLE_DATA,
    tags::GREEN_PALETTE_COLOR_LOOKUP_TABLE_DATA,
    tags::BLUE_PALETTE_COLOR_LOOKUP_TABLE_DATA,
    tags::SEGMENTED_RED_PALETTE_COLOR_LOOKUP_TABLE_DATA,
    tags::SEGMENTED_GREEN_PALETTE_COLOR_LOOKUP_TABLE_DATA,
    tags::SEGMENTED_BLUE_PALETTE_COLOR_LOOKUP_TABLE_DATA,
    tags::WINDOW_CENTER,
    tags::WINDOW_WIDTH,
    tags::PIXEL_DATA,
];

/// A rewrite of the file's bytes: `bytes` replace those at `at` (same length).
#[derive(Debug, Clone)]
struct Patch {
    tag: Tag,
    at: usize,
    bytes: Vec<u8>,
}

/// dicom-rs reads every unknown VR with the [`OddLayout::Extended`] layout; an element the
/// walk read with an 8-byte header is rewritten so that dicom-rs reads the same bytes as one
/// element: as `LT` of spaces (its value is not used) where its length fits in 2 bytes, else
/// as `UN` whose 4-byte length covers the rest of the value.
fn odd_patch(tag: Tag, at: usize, len: usize, big: bool) -> Patch {
    let mut bytes = Vec::new();
    match u16::try_from(len) {
        Ok(short) => {
            bytes.extend_from_slice(b"LT");
            bytes.extend_from_slice(&if big {
                short.to_be_bytes()
            } else {
                short.to_le_bytes()
            });
            bytes.resize(4 + len, b' ');
        }
        Err(_) => {
            let rest = (len - 4) as u32;
            bytes.extend_from_slice(b"UN\0\0");
            bytes.extend_from_slice(&if big {
                rest.to_be_bytes()
            } else {
                rest.to_le_bytes()
            });
        }
    }
    Patch {
        tag,
        at: at + 4,
        bytes,
    }
}

struct Walker {
    explicit: bool,
    big: bool,
    /// Rewrites of elements with an unknown VR, at offsets in the data set.
    patches: Vec<Patch>,
    /// The elements with an unknown VR the walk read.
    odd: Vec<(Tag, OddVr)>,
}

type WalkError = (Option<Tag>, String);

impl Walker {
    fn u16(&self, b: &[u8]) -> u16 {
        if self.big {
            u16::from_be_bytes([b[0], b[1]])
        } else {
            u16::from_le_bytes([b[0], b[1]])
        }
    }

    fn u32(&self, b: &[u8]) -> u32 {
        if self.big {
            u32::from_be_bytes([b[0], b[1], b[2], b[3]])
        } else {
            u32::from_le_bytes([b[0], b[1], b[2], b[3]])
        }
    }

    /// The element header at `pos` in `b` (which ends where the data set does).
    fn header(&self, b: &[u8], pos: usize) -> Result<Header, String> {
        let h = b.get(pos..pos + 8).ok_or("truncated element header")?;
        let tag = Tag(self.u16(&h[0..2]), self.u16(&h[2..4]));
        let undefined = |l: u32| (l != 0xFFFF_FFFF).then_some(l as usize);
        let plain = |vr, len, size| Header {
            tag,
            vr,
            len,
            size,
            odd: None,
        };
        if tag.group() == 0xFFFE || !self.explicit {
            return Ok(plain(None, undefined(self.u32(&h[4..8])), 8));
        }
        let vr = [h[4], h[5]];
        match vr_length_size(vr) {
            Some(true) => {
                let l = b.get(pos + 8..pos + 12).ok_or("truncated element header")?;
                Ok(plain(Some(vr), undefined(self.u32(l)), 12))
            }
            Some(false) => Ok(plain(Some(vr), Some(usize::from(self.u16(&h[6..8]))), 8)),
            None => self.odd_header(b, pos, tag, vr),
        }
    }

    /// The header of an element whose VR bytes name no VR. The reference toolkits read such
    /// an element in one of three layouts ([`OddLayout`]); the walk takes, of the two a
    /// toolkit would use for these bytes (capital letters: extended, then short; others:
    /// short, then implicit), the first under which the value fits and is followed by the end
    /// of the data set or a plausible element header (a later tag with a known VR, or a
    /// delimiter). Reported with VR `UN`, as dicom-rs reads it.
    fn odd_header(&self, b: &[u8], pos: usize, tag: Tag, vr: [u8; 2]) -> Result<Header, String> {
        let h = &b[pos..pos + 8];
        let layouts = if vr.iter().all(u8::is_ascii_uppercase) {
            [OddLayout::Extended, OddLayout::Short]
        } else {
            [OddLayout::Short, OddLayout::Implicit]
        };
        for layout in layouts {
            let (len, size) = match layout {
                OddLayout::Extended => match b.get(pos + 8..pos + 12) {
                    Some(l) => (self.u32(l), 12),
                    None => continue,
                },
                OddLayout::Short => (u32::from(self.u16(&h[6..8])), 8),
                OddLayout::Implicit => (self.u32(&h[4..8]), 8),
            };
            let fits = if len == 0xFFFF_FFFF {
                // Undefined: a sequence as dicom-rs reads UN (the walk checks its items).
                layout == OddLayout::Extended
            } else {
                let next = (pos + size).saturating_add(len as usize);
                next == b.len() || self.plausible_header(b, next, tag)
            };
            if fits {
                return Ok(Header {
                    tag,
                    vr: Some(*b"UN"),
                    len: (len != 0xFFFF_FFFF).then_some(len as usize),
                    size,
                    odd: Some(OddVr { bytes: vr, layout }),
                });
            }
        }
        Err(format!(
            "element {tag} has an unknown value representation {}, and its value fits in none \
             of the layouts other toolkits read it in",
            show_vr(vr)
        ))
    }

    /// Whether an element header after `after` can start at `pos`: a delimiter, or a later
    /// tag with a VR the reader knows.
    fn plausible_header(&self, b: &[u8], pos: usize, after: Tag) -> bool {
        let Some(h) = b.get(pos..pos.saturating_add(8)) else {
            return false;
        };
        let tag = Tag(self.u16(&h[0..2]), self.u16(&h[2..4]));
        if tag == Tag(0xFFFE, 0xE00D) || tag == Tag(0xFFFE, 0xE0DD) {
            return true;
        }
        tag > after && (!self.explicit || vr_length_size([h[4], h[5]]).is_some())
    }

    /// The size of one value of a binary VR of fixed size (`None`: text, bytes, sequences).
    /// dicom-rs reads `length / size` values and then counts the whole length as read, so a
    /// length that is not a multiple (an AT of 6 bytes) leaves its stream misaligned and the
    /// next "element header" it reads is value bytes: a 1.7 KB file made it reserve 1.5 GB.
    fn value_size(&self, tag: Tag, vr: Option<[u8; 2]>) -> Option<usize> {
        use dicom_core::dictionary::{DataDictionary, DataDictionaryEntry};
        use dicom_core::VR;
        let vr = match vr {
            Some(v) => VR::from_binary(v)?,
            None => dicom_dictionary_std::StandardDataDictionary
                .by_tag(tag)
                .and_then(|e| e.vr().exact())?,
        };
        match vr {
            VR::SS | VR::US | VR::OW => Some(2),
            VR::AT | VR::FL | VR::SL | VR::UL | VR::OF | VR::OL => Some(4),
            VR::FD | VR::SV | VR::UV | VR::OD | VR::OV => Some(8),
            _ => None,
        }
    }

    fn is_sequence(&self, tag: Tag, vr: Option<[u8; 2]>) -> bool {
        use dicom_core::dictionary::{DataDictionary, DataDictionaryEntry};
        match vr {
            Some(v) => &v == b"SQ",
            None => dicom_dictionary_std::StandardDataDictionary
                .by_tag(tag)
                .is_some_and(|e| e.vr().exact() == Some(dicom_core::VR::SQ)),
        }
    }

    /// Walks a data set in `b[pos..end]`; with `end` unknown for undefined-length items, stops
    /// at an item delimiter. Returns the position after what it consumed.
    fn dataset(
        &mut self,
        b: &[u8],
        mut pos: usize,
        end: usize,
        depth: usize,
        delimited: bool,
    ) -> Result<usize, WalkError> {
        if depth > MAX_DEPTH {
            return Err((None, format!("sequences nested deeper than {MAX_DEPTH}")));
        }
        while pos < end {
            let Header {
                tag,
                vr,
                len,
                size: hdr,
                odd,
            } = self.header(&b[..end], pos).map_err(|m| (None, m))?;
            if let Some(odd) = odd {
                if NEEDED.contains(&tag) {
                    return Err((
                        Some(tag),
                        format!(
                            "has an unknown value representation {}; wavesplat needs this \
                             attribute, and does not guess how to read it",
                            show_vr(odd.bytes)
                        ),
                    ));
                }
                self.odd.push((tag, odd));
                if let (OddLayout::Short | OddLayout::Implicit, Some(len)) = (odd.layout, len) {
                    self.patches.push(odd_patch(tag, pos, len, self.big));
                }
            }
            pos += hdr;
            if tag == Tag(0xFFFE, 0xE00D) && delimited {
                return Ok(pos);
            }
            // Item and sequence delimiters end what the parser is in, whatever the walk thinks
            // it is in: one where the walk would read an ordinary element makes the two part.
            if tag.group() == 0xFFFE {
                return Err((
                    Some(tag),
                    "an item or sequence delimiter where an element belongs".into(),
                ));
            }
            match len {
                Some(len) => {
                    if let Some(size) = self.value_size(tag, vr).filter(|s| len % s != 0) {
                        return Err((
                            Some(tag),
                            format!("a value of {len} bytes is not a whole number of {size}-byte values"),
                        ));
                    }
                    let stop = pos.checked_add(len).filter(|e| *e <= end).ok_or_else(|| {
                        (
                            Some(tag),
                            format!("declares {len} bytes, {} remain", end - pos),
                        )
                    })?;
                    if self.is_sequence(tag, vr) {
                        let after = self.items(b, pos, stop, depth + 1, false)?;
                        if after != stop {
                            return Err((
                                Some(tag),
                                "a sequence delimiter inside a sequence of defined length".into(),
                            ));
                        }
                    }
                    pos = stop;
                }
                None => {
                    let fragments = tag == tags::PIXEL_DATA;
                    if !fragments && !self.is_sequence(tag, vr) && vr != Some(*b"UN") {
                        return Err((
                            Some(tag),
                            "undefined length on an element that is not a sequence".into(),
                        ));
                    }
                    pos = self.items(b, pos, end, depth + 1, fragments)?;
                }
            }
        }
        if delimited {
            return Err((None, "an item without its delimiter".into()));
        }
        Ok(pos)
    }

    /// Walks the items of a sequence (or the fragments of encapsulated pixel data) in
    /// `b[pos..end]`, up to the sequence delimiter when the sequence's length is undefined.
    fn items(
        &mut self,
        b: &[u8],
        mut pos: usize,
        end: usize,
        depth: usize,
        fragments: bool,
    ) -> Result<usize, WalkError> {
        let mut count = 0usize;
        while pos < end {
            let h = b
                .get(pos..pos + 8)
                .filter(|_| pos + 8 <= end)
                .ok_or((None, "truncated item header".to_string()))?;
            let tag = Tag(self.u16(&h[0..2]), self.u16(&h[2..4]));
            let len = self.u32(&h[4..8]);
            pos += 8;
            if tag == Tag(0xFFFE, 0xE0DD) {
                return Ok(pos);
            }
            if tag != Tag(0xFFFE, 0xE000) {
                return Err((Some(tag), "expected an item in a sequence".into()));
            }
            count += 1;
            if count > (1 << 24) {
                return Err((None, "too many items".into()));
            }
            if len == 0xFFFF_FFFF {
                if fragments {
                    return Err((
                        Some(tags::PIXEL_DATA),
                        "a fragment of undefined length".into(),
                    ));
                }
                pos = self.dataset(b, pos, end, depth, true)?;
            } else {
                let stop = pos
                    .checked_add(len as usize)
                    .filter(|e| *e <= end)
                    .ok_or_else(|| {
                        (
                            None,
                            format!("an item declares {len} bytes, {} remain", end - pos),
                        )
                    })?;
                if !fragments {
                    self.dataset(b, pos, stop, depth, false)?;
                }
                pos = stop;
            }
        }
        Ok(pos)
    }
}

/// Parses a file (the whole data set, or up to the pixel data), catching panics.
fn parse(path: &Path, bytes: &[u8], pixels: bool) -> Result<DefaultDicomObject, ReadError> {
    if !has_preamble(bytes) {
        return Err(dicom_err(
            path,
            None,
            "not a DICOM file (no DICM preamble at offset 128)",
        ));
    }
    let walked = check_lengths(path, bytes)?;
    if !pixels {
        for (tag, odd) in &walked.odd {
            tracing::warn!(
                file = %path.display(),
                element = %tag,
                vr = %show_vr(odd.bytes),
                layout = ?odd.layout,
                "an element with an unknown value representation, read as other toolkits read it; its value is not used"
            );
        }
    }
    let patched;
    let bytes = if walked.patches.is_empty() {
        bytes
    } else {
        let mut b = bytes.to_vec();
        for p in &walked.patches {
            b[p.at..p.at + p.bytes.len()].copy_from_slice(&p.bytes);
        }
        patched = b;
        &patched[..]
    };
    let body = &bytes[128..];
    let result = catch_unwind(AssertUnwindSafe(|| {
        let opts = OpenFileOptions::new().read_preamble(ReadPreamble::Never);
        if pixels {
            opts.from_reader(body)
        } else {
            opts.read_until(tags::PIXEL_DATA).from_reader(body)
        }
    }));
    match result {
        Ok(Ok(mut obj)) => {
            known_vrs(&mut obj);
            Ok(obj)
        }
        Ok(Err(e)) => Err(dicom_err(
            path,
            None,
            format!("cannot parse the data set: {e}"),
        )),
        Err(_) => Err(dicom_err(
            path,
            None,
            "the DICOM parser panicked on this file",
        )),
    }
}

/// Replaces the top-level elements written as `UN` whose attributes the standard dictionary
/// knows by their standard VR ([`value_element`]), so that the pixel data decoder, which reads
/// Rows, Columns, Bits Allocated and the rest itself, sees them too.
fn known_vrs(obj: &mut DefaultDicomObject) {
    let unknown: Vec<Tag> = obj
        .iter()
        .filter(|e| e.header().vr == dicom_core::VR::UN)
        .map(|e| e.header().tag)
        .collect();
    for tag in unknown {
        let fixed = match value_element(obj, tag) {
            Some(std::borrow::Cow::Owned(e)) => e,
            _ => continue,
        };
        obj.put(fixed);
    }
}

fn element(obj: &InMemDicomObject, tag: Tag) -> Option<&dicom_object::mem::InMemElement> {
    obj.element_opt(tag).ok().flatten()
}

/// The element `tag` of `obj` with the value representation its attribute has: an element
/// written as `UN` (unknown) by a toolkit that did not know it, but whose attribute the
/// standard dictionary knows as a text or binary number VR, is decoded again as that VR (its
/// bytes are the Implicit VR Little Endian encoding, PS3.5 §6.2.2). Read as `UN`, a decimal
/// string such as Image Orientation (Patient) `1.0\0.0\…` would give the ASCII codes of its
/// characters as numbers.
///
/// A value that is present but blank (no values, or only spaces and NULs: how a Type 2
/// attribute such as an RT Dose's Slice Thickness is written when unknown) is `None`, as if
/// absent: every reader of values goes through here, so none of them parses a blank as a
/// number.
fn value_element(
    obj: &InMemDicomObject,
    tag: Tag,
) -> Option<std::borrow::Cow<'_, dicom_object::mem::InMemElement>> {
    value_element_as_coded(obj, tag).filter(|e| !is_blank(e))
}

/// Whether an element's value is empty or only padding.
fn is_blank(e: &dicom_object::mem::InMemElement) -> bool {
    use dicom_core::PrimitiveValue;
    let blank = |s: &str| {
        s.trim_matches(|c: char| c == '\0' || c.is_whitespace())
            .is_empty()
    };
    match e.value().primitive() {
        Some(p) if p.multiplicity() == 0 => true,
        Some(PrimitiveValue::Str(s)) => blank(s),
        Some(PrimitiveValue::Strs(v)) => v.iter().all(|s| blank(s)),
        _ => false,
    }
}

/// [`value_element`] before the blank check.
fn value_element_as_coded(
    obj: &InMemDicomObject,
    tag: Tag,
) -> Option<std::borrow::Cow<'_, dicom_object::mem::InMemElement>> {
    use dicom_core::dictionary::{DataDictionary, VirtualVr};
    use dicom_core::VR;
    let e = element(obj, tag)?;
    if e.vr() != VR::UN {
        return Some(std::borrow::Cow::Borrowed(e));
    }
    let Some(entry) = dicom_dictionary_std::StandardDataDictionary.by_tag(tag) else {
        return Some(std::borrow::Cow::Borrowed(e));
    };
    let VirtualVr::Exact(vr) = entry.vr else {
        return Some(std::borrow::Cow::Borrowed(e));
    };
    let bytes = e.value().primitive()?.to_bytes();
    let value = reinterpret(&bytes, vr)?;
    Some(std::borrow::Cow::Owned(
        dicom_object::mem::InMemElement::new(tag, vr, value),
    ))
}

/// `bytes` (Implicit VR Little Endian) as a value of `vr`, for the text and number VRs the
/// reader uses; `None` for others.
fn reinterpret(bytes: &[u8], vr: dicom_core::VR) -> Option<dicom_core::PrimitiveValue> {
    use dicom_core::{PrimitiveValue, VR};
    let unit = match vr {
        VR::US | VR::SS => 2,
        VR::UL | VR::SL | VR::FL => 4,
        VR::FD => 8,
        _ => 1,
    };
    if !bytes.len().is_multiple_of(unit) {
        return None;
    }
    let words = |n: usize| bytes.chunks_exact(n);
    Some(match vr {
        VR::DS
        | VR::IS
        | VR::CS
        | VR::LO
        | VR::SH
        | VR::UI
        | VR::DA
        | VR::TM
        | VR::DT
        | VR::PN
        | VR::ST
        | VR::LT
        | VR::UT
        | VR::AS => {
            let text = std::str::from_utf8(bytes).ok()?;
            let text = text.trim_end_matches(['\0', ' ']);
            PrimitiveValue::Strs(text.split('\\').map(|p| p.trim().to_string()).collect())
        }
        VR::US => PrimitiveValue::U16(words(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect()),
        VR::SS => PrimitiveValue::I16(words(2).map(|c| i16::from_le_bytes([c[0], c[1]])).collect()),
        VR::UL => PrimitiveValue::U32(
            words(4)
                .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        ),
        VR::SL => PrimitiveValue::I32(
            words(4)
                .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        ),
        VR::FL => PrimitiveValue::F32(
            words(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        ),
        VR::FD => PrimitiveValue::F64(
            words(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
                .collect(),
        ),
        _ => return None,
    })
}

fn get_str(obj: &InMemDicomObject, tag: Tag) -> Option<String> {
    value_element(obj, tag)
        .and_then(|e| e.to_str().ok().map(|s| s.into_owned()))
        .map(|s| {
            s.trim_matches(|c: char| c == '\0' || c.is_whitespace())
                .to_string()
        })
        .filter(|s| !s.is_empty())
}

fn get_floats(
    path: &Path,
    obj: &InMemDicomObject,
    tag: Tag,
) -> Result<Option<Vec<f64>>, ReadError> {
    let Some(e) = value_element(obj, tag) else {
        return Ok(None);
    };
    let v = e
        .to_multi_float64()
        .map_err(|x| dicom_err(path, Some(tag), format!("not a list of numbers: {x}")))?;
    if v.iter().any(|x| !x.is_finite()) {
        return Err(dicom_err(path, Some(tag), format!("{v:?} is not finite")));
    }
    Ok(Some(v))
}

fn get_uint(path: &Path, obj: &InMemDicomObject, tag: Tag) -> Result<Option<u32>, ReadError> {
    let Some(e) = value_element(obj, tag) else {
        return Ok(None);
    };
    e.to_int::<u32>()
        .map(Some)
        .map_err(|x| dicom_err(path, Some(tag), format!("not a non-negative integer: {x}")))
}

fn require_uint(path: &Path, obj: &InMemDicomObject, tag: Tag) -> Result<u32, ReadError> {
    get_uint(path, obj, tag)?.ok_or_else(|| dicom_err(path, Some(tag), "missing"))
}

/// The first item of sequence `seq` in `obj`.
fn first_item(obj: &InMemDicomObject, seq: Tag) -> Option<&InMemDicomObject> {
    element(obj, seq)
        .and_then(|e| e.items())
        .and_then(|i| i.first())
}

/// An attribute of frame `f` from the functional groups (per-frame item, then shared), or the
/// top level.
fn frame_attr(obj: &InMemDicomObject, frame: usize, group_seq: Tag) -> Vec<&InMemDicomObject> {
    let mut out = Vec::new();
    if let Some(item) = element(obj, tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE)
        .and_then(|e| e.items())
        .and_then(|i| i.get(frame))
        .and_then(|i| first_item(i, group_seq))
    {
        out.push(item);
    }
    if let Some(item) = first_item(obj, tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE)
        .and_then(|s| first_item(s, group_seq))
    {
        out.push(item);
    }
    out.push(obj);
    out
}

fn floats_for_frame(
    path: &Path,
    obj: &InMemDicomObject,
    frame: usize,
    group_seq: Tag,
    tag: Tag,
) -> Result<Option<Vec<f64>>, ReadError> {
    for o in frame_attr(obj, frame, group_seq) {
        if let Some(v) = get_floats(path, o, tag)? {
            return Ok(Some(v));
        }
    }
    Ok(None)
}

/// What the reader needs of one image file (pixel data not yet decoded).
#[derive(Debug, Clone)]
struct Image {
    name: String,
    path: PathBuf,
    series: String,
    rows: usize,
    cols: usize,
    frames: usize,
    samples: usize,
    bits_allocated: u32,
    bits_stored: u32,
    signed: bool,
    /// (row spacing, column spacing), mm.
    pixel_spacing: Option<[f64; 2]>,
    /// Row direction, column direction.
    orientation: Option<[f64; 6]>,
    /// Per frame.
    positions: Vec<Option<[f64; 3]>>,
    /// Per frame (slope, intercept).
    rescale: Vec<(f64, f64)>,
    /// Spacing Between Slices, else Slice Thickness.
    slice_step: Option<f64>,
    instance: i64,
    /// When the image was taken in a time series: Temporal Position Identifier, else Trigger
    /// Time (named by `time_attribute`).
    time: Option<String>,
    time_attribute: &'static str,
    /// Photometric Interpretation as the file states it.
    photometric: String,
    /// The colour palette of a PALETTE COLOR image.
    palette: Option<std::sync::Arc<Palette>>,
}

impl Image {
    /// Channels of the volume: three for a palette image (its colours), else the samples.
    fn channels(&self) -> usize {
        if self.palette.is_some() {
            3
        } else {
            self.samples
        }
    }
}

/// A PALETTE COLOR image's lookup tables: per colour, the first stored value mapped and the
/// entries (PS3.3 C.7.6.3.1.5).
#[derive(Debug, Clone, PartialEq)]
struct Palette {
    tables: [(i64, Vec<f32>); 3],
}

impl Palette {
    /// The colour of stored value `v`: values below the first mapped one take the first entry,
    /// values past the last the last.
    fn colour(&self, c: usize, v: f64) -> f32 {
        let (first, t) = &self.tables[c];
        let i = (v as i64 - first).clamp(0, t.len() as i64 - 1);
        t[i as usize]
    }
}

/// Reads the red, green and blue palette tables (descriptor: entries (0 for 65536), first
/// mapped value, bits per entry; data: one 16-bit word an entry). Segmented palettes are
/// refused, naming them.
fn read_palette(path: &Path, o: &InMemDicomObject, signed: bool) -> Result<Palette, ReadError> {
    use dicom_core::PrimitiveValue;
    let colours = [
        (
            tags::RED_PALETTE_COLOR_LOOKUP_TABLE_DESCRIPTOR,
            tags::RED_PALETTE_COLOR_LOOKUP_TABLE_DATA,
            tags::SEGMENTED_RED_PALETTE_COLOR_LOOKUP_TABLE_DATA,
        ),
        (
            tags::GREEN_PALETTE_COLOR_LOOKUP_TABLE_DESCRIPTOR,
            tags::GREEN_PALETTE_COLOR_LOOKUP_TABLE_DATA,
            tags::SEGMENTED_GREEN_PALETTE_COLOR_LOOKUP_TABLE_DATA,
        ),
        (
            tags::BLUE_PALETTE_COLOR_LOOKUP_TABLE_DESCRIPTOR,
            tags::BLUE_PALETTE_COLOR_LOOKUP_TABLE_DATA,
            tags::SEGMENTED_BLUE_PALETTE_COLOR_LOOKUP_TABLE_DATA,
        ),
    ];
    let mut tables: Vec<(i64, Vec<f32>)> = Vec::with_capacity(3);
    for (descriptor, data, segmented) in colours {
        if element(o, segmented).is_some() {
            return Err(dicom_err(
                path,
                Some(segmented),
                "a segmented palette: not supported (only plain lookup tables are)",
            ));
        }
        let d = element(o, descriptor)
            .and_then(|e| e.to_multi_int::<i64>().ok())
            .filter(|d| d.len() == 3)
            .ok_or_else(|| dicom_err(path, Some(descriptor), "missing or not three numbers"))?;
        let entries = if d[0] == 0 { 65536 } else { d[0] as usize };
        // The first mapped value is US or SS as the pixels are: signed pixels' negative first
        // value read as US wraps.
        let first = if signed && d[1] > 32767 && d[1] <= 65535 {
            d[1] - 65536
        } else {
            d[1]
        };
        let words: Vec<f32> = match element(o, data).and_then(|e| e.value().primitive()) {
            Some(PrimitiveValue::U16(w)) => w.iter().map(|x| f32::from(*x)).collect(),
            Some(PrimitiveValue::U8(b)) if b.len() == entries => {
                b.iter().map(|x| f32::from(*x)).collect()
            }
            Some(PrimitiveValue::U8(b)) => b
                .chunks_exact(2)
                .map(|c| f32::from(u16::from_le_bytes([c[0], c[1]])))
                .collect(),
            _ => return Err(dicom_err(path, Some(data), "missing or not 16-bit words")),
        };
        if words.len() < entries {
            return Err(dicom_err(
                path,
                Some(data),
                format!("{} entries, the descriptor declares {entries}", words.len()),
            ));
        }
        tables.push((first, words[..entries].to_vec()));
    }
    let [r, g, b]: [(i64, Vec<f32>); 3] = tables.try_into().expect("three colours");
    Ok(Palette { tables: [r, g, b] })
}

/// Reads what the reader needs of an image's header; `file_len` (the file's size) bounds the
/// frames and sample bytes it may declare, so that a small file cannot make the per-frame
/// loops or the voxel buffer large.
fn read_image(
    name: &str,
    path: &Path,
    obj: &DefaultDicomObject,
    file_len: usize,
) -> Result<Option<Image>, ReadError> {
    let meta = obj.meta();
    if meta.media_storage_sop_class_uid().trim_end_matches('\0') == DICOMDIR_SOP_CLASS {
        return Ok(None);
    }
    let o: &InMemDicomObject = obj;
    let (Some(rows), Some(cols)) = (
        get_uint(path, o, tags::ROWS)?,
        get_uint(path, o, tags::COLUMNS)?,
    ) else {
        tracing::debug!(file = %path.display(), "no Rows/Columns: not an image, skipped");
        return Ok(None);
    };
    if rows == 0 || cols == 0 {
        return Err(dicom_err(
            path,
            Some(if rows == 0 { tags::ROWS } else { tags::COLUMNS }),
            "is 0",
        ));
    }
    // Empty when missing: a single file is its own series; files of a directory are grouped
    // by it, and there a missing one is refused (`read_series`).
    let series = get_str(o, tags::SERIES_INSTANCE_UID).unwrap_or_default();
    let frames = get_uint(path, o, tags::NUMBER_OF_FRAMES)?
        .unwrap_or(1)
        .max(1) as usize;
    let samples = get_uint(path, o, tags::SAMPLES_PER_PIXEL)?.unwrap_or(1) as usize;
    if samples != 1 && samples != 3 {
        return Err(dicom_err(
            path,
            Some(tags::SAMPLES_PER_PIXEL),
            format!("{samples}; 1 or 3 supported"),
        ));
    }
    let plane = (rows as usize) * (cols as usize);
    let total = plane
        .checked_mul(frames)
        .filter(|n| *n <= MAX_VOXELS)
        .ok_or_else(|| {
            dicom_err(
                path,
                Some(tags::NUMBER_OF_FRAMES),
                format!("{rows} rows × {cols} columns × {frames} frames exceed the {MAX_VOXELS}-voxel limit"),
            )
        })?;
    let bits_allocated = require_uint(path, o, tags::BITS_ALLOCATED)?;
    if !matches!(bits_allocated, 1 | 8 | 16 | 32) || bits_allocated == 1 && samples != 1 {
        return Err(dicom_err(
            path,
            Some(tags::BITS_ALLOCATED),
            format!(
                "{bits_allocated} with {samples} sample(s) per pixel; 8, 16 or 32 supported, \
                 and 1 (a bit mask) with one sample"
            ),
        ));
    }
    // Every frame needs at least one byte of the file (a native sample, or an encapsulated
    // fragment), and no transfer syntax expands the file beyond MAX_FILE_EXPANSION.
    let declared = total
        .saturating_mul(samples)
        .saturating_mul(bits_allocated as usize)
        .div_ceil(8);
    let most = file_len
        .saturating_mul(MAX_FILE_EXPANSION)
        .saturating_add(EXPANSION_SLACK);
    if frames > file_len || declared > most {
        return Err(dicom_err(
            path,
            Some(tags::PIXEL_DATA),
            format!(
                "{rows}×{cols} × {frames} frame(s) × {samples} sample(s) × {} byte(s) = {declared} bytes cannot come from a file of {file_len} bytes (at most {MAX_FILE_EXPANSION}× its size + {EXPANSION_SLACK} bytes)",
                bits_allocated / 8
            ),
        ));
    }
    let bits_stored = get_uint(path, o, tags::BITS_STORED)?.unwrap_or(bits_allocated);
    if bits_stored == 0 || bits_stored > bits_allocated {
        return Err(dicom_err(
            path,
            Some(tags::BITS_STORED),
            format!("{bits_stored} with {bits_allocated} bits allocated"),
        ));
    }
    let high_bit = get_uint(path, o, tags::HIGH_BIT)?.unwrap_or(bits_stored - 1);
    if high_bit != bits_stored - 1 {
        return Err(dicom_err(
            path,
            Some(tags::HIGH_BIT),
            format!("{high_bit} with {bits_stored} bits stored; only High Bit = Bits Stored − 1 is supported"),
        ));
    }
    let signed = match get_uint(path, o, tags::PIXEL_REPRESENTATION)?.unwrap_or(0) {
        0 => false,
        1 => true,
        r => {
            return Err(dicom_err(
                path,
                Some(tags::PIXEL_REPRESENTATION),
                format!("{r}; 0 or 1"),
            ))
        }
    };
    let photometric =
        get_str(o, tags::PHOTOMETRIC_INTERPRETATION).unwrap_or_else(|| "MONOCHROME2".into());
    let ok_photometric = match samples {
        1 => matches!(
            photometric.as_str(),
            "MONOCHROME1" | "MONOCHROME2" | "PALETTE COLOR"
        ),
        _ => matches!(
            photometric.as_str(),
            "RGB" | "YBR_FULL" | "YBR_FULL_422" | "YBR_ICT" | "YBR_RCT"
        ),
    };
    if !ok_photometric {
        return Err(dicom_err(
            path,
            Some(tags::PHOTOMETRIC_INTERPRETATION),
            format!("{photometric} with {samples} sample(s) per pixel; supported are MONOCHROME1/2 and PALETTE COLOR (one sample), RGB, YBR_FULL, YBR_FULL_422 and (JPEG 2000) YBR_ICT/YBR_RCT (three)"),
        ));
    }
    let palette = if photometric == "PALETTE COLOR" {
        Some(std::sync::Arc::new(read_palette(path, o, signed)?))
    } else {
        None
    };
    let pixel_spacing = match floats_for_frame(
        path,
        o,
        0,
        tags::PIXEL_MEASURES_SEQUENCE,
        tags::PIXEL_SPACING,
    )?
    .or(get_floats(path, o, tags::IMAGER_PIXEL_SPACING)?)
    {
        None => None,
        Some(v) if v.len() >= 2 && v[0] > 0.0 && v[1] > 0.0 => Some([v[0], v[1]]),
        Some(v) => {
            return Err(dicom_err(
                path,
                Some(tags::PIXEL_SPACING),
                format!("{v:?}: two positive numbers expected"),
            ))
        }
    };
    let orientation = match floats_for_frame(
        path,
        o,
        0,
        tags::PLANE_ORIENTATION_SEQUENCE,
        tags::IMAGE_ORIENTATION_PATIENT,
    )? {
        None => None,
        Some(v) if v.len() == 6 => Some([v[0], v[1], v[2], v[3], v[4], v[5]]),
        Some(v) => {
            return Err(dicom_err(
                path,
                Some(tags::IMAGE_ORIENTATION_PATIENT),
                format!("{v:?}: six numbers expected"),
            ))
        }
    };
    let slice_step = {
        let mut s = None;
        for tag in [tags::SPACING_BETWEEN_SLICES, tags::SLICE_THICKNESS] {
            if let Some(v) = floats_for_frame(path, o, 0, tags::PIXEL_MEASURES_SEQUENCE, tag)? {
                if let Some(x) = v.first().copied().filter(|x| *x > 0.0) {
                    s = Some(x);
                    break;
                }
            }
        }
        s
    };
    // Per-frame positions: the functional groups, or the top level for frame 0 (classic
    // multi-frame files then step along the normal by the slice step).
    let mut positions = Vec::with_capacity(frames.min(1 << 16));
    for f in 0..frames {
        let p = match floats_for_frame(
            path,
            o,
            f,
            tags::PLANE_POSITION_SEQUENCE,
            tags::IMAGE_POSITION_PATIENT,
        )? {
            None => None,
            Some(v) if v.len() == 3 => Some([v[0], v[1], v[2]]),
            Some(v) => {
                return Err(dicom_err(
                    path,
                    Some(tags::IMAGE_POSITION_PATIENT),
                    format!("{v:?}: three numbers expected"),
                ))
            }
        };
        positions.push(p);
    }
    let has_per_frame = element(o, tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE).is_some();
    let grid_offsets = get_floats(path, o, tags::GRID_FRAME_OFFSET_VECTOR)?;
    if frames > 1 && !has_per_frame && grid_offsets.is_none() {
        refuse_time_series(path, o, frames)?;
    }
    if frames > 1 && !has_per_frame {
        if let (Some(p0), Some(iop)) = (positions[0], orientation) {
            let n = normal(&iop);
            let offsets = match &grid_offsets {
                Some(g) => grid_frame_offsets(path, g, frames, p0, n)?,
                None => {
                    let step = slice_step.ok_or_else(|| {
                        dicom_err(
                            path,
                            Some(tags::SPACING_BETWEEN_SLICES),
                            "missing: a multi-frame file without per-frame positions needs the \
                             slice step (or, for RT Dose, Grid Frame Offset Vector (3004,000C))",
                        )
                    })?;
                    (0..frames).map(|f| f as f64 * step).collect()
                }
            };
            for (p, k) in positions.iter_mut().zip(offsets) {
                *p = Some([p0[0] + k * n[0], p0[1] + k * n[1], p0[2] + k * n[2]]);
            }
        }
    }
    // RT Dose: stored values × Dose Grid Scaling are the dose (in Dose Units, Gy or relative).
    let dose_scaling = match get_floats(path, o, tags::DOSE_GRID_SCALING)? {
        None => 1.0,
        Some(v) => match v.first().copied() {
            Some(x) if x > 0.0 => x,
            _ => {
                return Err(dicom_err(
                    path,
                    Some(tags::DOSE_GRID_SCALING),
                    format!("{v:?}: one positive number expected"),
                ))
            }
        },
    };
    let mut rescale = Vec::with_capacity(frames.min(1 << 16));
    for f in 0..frames {
        let slope = floats_for_frame(
            path,
            o,
            f,
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            tags::RESCALE_SLOPE,
        )?
        .and_then(|v| v.first().copied())
        .unwrap_or(1.0);
        let intercept = floats_for_frame(
            path,
            o,
            f,
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            tags::RESCALE_INTERCEPT,
        )?
        .and_then(|v| v.first().copied())
        .unwrap_or(0.0);
        if slope == 0.0 {
            return Err(dicom_err(path, Some(tags::RESCALE_SLOPE), "is 0"));
        }
        rescale.push(if samples == 3 {
            (1.0, 0.0)
        } else {
            (slope * dose_scaling, intercept * dose_scaling)
        });
    }
    let instance = get_str(o, tags::INSTANCE_NUMBER)
        .and_then(|s| s.parse::<i64>().ok())
        .unwrap_or(0);
    let (time, time_attribute) = [
        (
            tags::TEMPORAL_POSITION_IDENTIFIER,
            "Temporal Position Identifier (0020,0100)",
        ),
        (tags::TRIGGER_TIME, "Trigger Time (0018,1060)"),
    ]
    .into_iter()
    .find_map(|(t, name)| get_str(o, t).map(|v| (Some(v), name)))
    .unwrap_or((None, ""));
    Ok(Some(Image {
        name: name.to_string(),
        path: path.to_path_buf(),
        series,
        rows: rows as usize,
        cols: cols as usize,
        frames,
        samples,
        bits_allocated,
        bits_stored,
        signed,
        pixel_spacing,
        orientation,
        positions,
        rescale,
        slice_step,
        instance,
        time,
        time_attribute,
        photometric,
        palette,
    }))
}

/// The offsets along the slice normal of an RT Dose grid's frames from Grid Frame Offset
/// Vector (PS3.3 C.8.8.3.2): relative to Image Position (Patient) when its first value is 0,
/// otherwise the frames' z coordinates, which only an axial grid may use.
fn grid_frame_offsets(
    path: &Path,
    g: &[f64],
    frames: usize,
    p0: [f64; 3],
    n: [f64; 3],
) -> Result<Vec<f64>, ReadError> {
    let err = |reason: String| dicom_err(path, Some(tags::GRID_FRAME_OFFSET_VECTOR), reason);
    if g.len() != frames {
        return Err(err(format!("{} values for {frames} frames", g.len())));
    }
    if g[0] == 0.0 {
        return Ok(g.to_vec());
    }
    let axial = n[0].abs() < 1e-6 && n[1].abs() < 1e-6 && (n[2].abs() - 1.0).abs() < 1e-6;
    if !axial {
        return Err(err(format!(
            "absolute offsets (first value {}) need an axial grid; this one's normal is {n:?}",
            g[0]
        )));
    }
    if (g[0] - p0[2]).abs() > 1e-3 * g[0].abs().max(1.0) {
        return Err(err(format!(
            "absolute offsets start at z = {}, but Image Position (Patient) is at z = {}",
            g[0], p0[2]
        )));
    }
    Ok(g.iter().map(|z| (z - p0[2]) * n[2]).collect())
}

/// Attributes that make a multi-frame image's frames instants of one acquisition over time
/// (cine, gated) rather than slices of a volume.
const TEMPORAL_ATTRIBUTES: [(Tag, &str); 5] = [
    (tags::FRAME_TIME, "Frame Time"),
    (tags::FRAME_TIME_VECTOR, "Frame Time Vector"),
    (tags::TRIGGER_TIME, "Trigger Time"),
    (tags::ACTUAL_FRAME_DURATION, "Actual Frame Duration"),
    (tags::TIME_SLOT_VECTOR, "Time Slot Vector"),
];

/// Refuses a multi-frame file without per-frame positions whose frames step through time
/// (its Frame Increment Pointer names a time attribute, or it gives a frame time and nothing
/// that places the frames in space): stacking time as depth would draw a cine loop as a
/// volume.
fn refuse_time_series(path: &Path, o: &InMemDicomObject, frames: usize) -> Result<(), ReadError> {
    let pointers: Vec<Tag> =
        match element(o, tags::FRAME_INCREMENT_POINTER).and_then(|e| e.value().primitive()) {
            Some(dicom_core::PrimitiveValue::Tags(t)) => t.to_vec(),
            _ => Vec::new(),
        };
    let by_pointer = TEMPORAL_ATTRIBUTES
        .iter()
        .find(|(t, _)| pointers.contains(t));
    let present = TEMPORAL_ATTRIBUTES
        .iter()
        .find(|(t, _)| element(o, *t).is_some());
    let spatial_pointer = pointers
        .iter()
        .any(|t| !TEMPORAL_ATTRIBUTES.iter().any(|(x, _)| x == t));
    let (tag, name, how) = match (by_pointer, present) {
        (Some((t, n)), _) => (*t, *n, "its Frame Increment Pointer (0028,0009) names"),
        (None, Some((t, n))) if !spatial_pointer => (*t, *n, "it has"),
        _ => return Ok(()),
    };
    Err(dicom_err(
        path,
        Some(tags::FRAME_INCREMENT_POINTER),
        format!(
            "a time series, not a volume: {frames} frames of one slice over time ({how} {name} \
             ({:04X},{:04X}) and no frame has a position of its own). wavesplat reads volumes; \
             export one time point as its own series, or a volume's slices",
            tag.group(),
            tag.element()
        ),
    ))
}

fn normal(iop: &[f64; 6]) -> [f64; 3] {
    let (r, c) = ([iop[0], iop[1], iop[2]], [iop[3], iop[4], iop[5]]);
    [
        r[1] * c[2] - r[2] * c[1],
        r[2] * c[0] - r[0] * c[2],
        r[0] * c[1] - r[1] * c[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// One frame of the volume, in its final order.
#[derive(Debug, Clone, Copy)]
struct FrameRef {
    image: usize,
    frame: usize,
}

/// Decodes a DICOM volume (a series directory's files, or one multi-frame file).
pub(crate) fn decode(src: &SourceFiles) -> Result<Volume, ReadError> {
    // Pass 1: headers only.
    let mut images = Vec::new();
    for (name, bytes) in &src.files {
        let path = src.path_of(name);
        let obj = parse(&path, bytes, false)?;
        if let Some(img) = read_image(name, &path, &obj, bytes.len())? {
            images.push(img);
        }
    }
    let dir = &src.origin;
    if images.is_empty() {
        return Err(ReadError::Series {
            path: dir.clone(),
            reason: "no image (no file with Rows and Columns)".into(),
        });
    }
    if images.len() > 1 {
        if let Some(i) = images.iter().find(|i| i.series.is_empty()) {
            return Err(dicom_err(
                &i.path,
                Some(tags::SERIES_INSTANCE_UID),
                "missing (the files of a directory are grouped into one series by it)",
            ));
        }
    }
    let mut by_series: BTreeMap<&str, usize> = BTreeMap::new();
    for i in &images {
        *by_series.entry(i.series.as_str()).or_default() += 1;
    }
    if by_series.len() > 1 {
        let list: Vec<String> = by_series
            .iter()
            .map(|(s, n)| format!("{s} ({n} files)"))
            .collect();
        return Err(ReadError::Series {
            path: dir.clone(),
            reason: format!(
                "holds {} series, one volume needs one: {}; give each series its own directory",
                by_series.len(),
                list.join(", ")
            ),
        });
    }
    let first = images[0].clone();
    // Consistency of the in-plane geometry and sample format.
    for i in &images[1..] {
        let mismatch = |tag: Tag, what: String| {
            Err(ReadError::Series {
                path: dir.clone(),
                reason: format!(
                    "{} differs between {} and {}: {what}",
                    tag_name(tag),
                    first.name,
                    i.name
                ),
            })
        };
        if (i.rows, i.cols) != (first.rows, first.cols) {
            return mismatch(
                tags::ROWS,
                format!(
                    "{}×{} against {}×{}",
                    first.rows, first.cols, i.rows, i.cols
                ),
            );
        }
        if (i.samples, i.bits_allocated, i.bits_stored, i.signed)
            != (
                first.samples,
                first.bits_allocated,
                first.bits_stored,
                first.signed,
            )
        {
            return mismatch(tags::BITS_ALLOCATED, "sample format".into());
        }
        let close =
            |a: &[f64], b: &[f64], tol: f64| a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol);
        match (&first.pixel_spacing, &i.pixel_spacing) {
            (Some(a), Some(b)) if close(a, b, 1e-4 * a[0].max(a[1])) => {}
            (None, None) => {}
            (a, b) => {
                return mismatch(
                    tags::PIXEL_SPACING,
                    format!("{} against {}", dicom_values(a), dicom_values(b)),
                )
            }
        }
        match (&first.orientation, &i.orientation) {
            (Some(a), Some(b)) if close(a, b, 1e-4) => {}
            (None, None) => {}
            (a, b) => {
                return mismatch(
                    tags::IMAGE_ORIENTATION_PATIENT,
                    format!("{} against {}", dicom_values(a), dicom_values(b)),
                )
            }
        }
    }

    // Order the frames.
    let mut frames: Vec<(FrameRef, Option<[f64; 3]>)> = Vec::new();
    for (ii, img) in images.iter().enumerate() {
        for f in 0..img.frames {
            frames.push((
                FrameRef {
                    image: ii,
                    frame: f,
                },
                img.positions[f],
            ));
        }
    }
    let nz = frames.len();
    let plane = first.rows * first.cols;
    let dims = [first.cols, first.rows, nz];
    voxel_count(dims).map_err(|e| ReadError::Series {
        path: dir.clone(),
        reason: e.to_string(),
    })?;
    let with_pos = frames.iter().filter(|(_, p)| p.is_some()).count();
    if with_pos != 0 && with_pos != nz {
        let (missing, _) = frames
            .iter()
            .find(|(_, p)| p.is_none())
            .expect("some lack a position");
        let img = &images[missing.image];
        return Err(dicom_err(
            &img.path,
            Some(tags::IMAGE_POSITION_PATIENT),
            format!(
                "missing for frame {} while other frames have it",
                missing.frame
            ),
        ));
    }
    let [ps_row, ps_col] = first.pixel_spacing.unwrap_or_else(|| {
        tracing::warn!(series = %dir.display(), "no Pixel Spacing: assuming 1 mm");
        [1.0, 1.0]
    });
    let (z_step, placement) = match (first.orientation, with_pos == nz) {
        (Some(iop), true) => {
            let r = [iop[0], iop[1], iop[2]];
            let c = [iop[3], iop[4], iop[5]];
            let n = normal(&iop);
            let nn = dot(n, n).sqrt();
            if nn.is_nan() || nn <= 0.5 {
                return Err(dicom_err(
                    &first.path,
                    Some(tags::IMAGE_ORIENTATION_PATIENT),
                    format!("{iop:?}: row and column directions are not orthogonal unit vectors"),
                ));
            }
            let n = n.map(|x| x / nn);
            frames.sort_by(|a, b| {
                let (pa, pb) = (
                    a.1.expect("all have positions"),
                    b.1.expect("all have positions"),
                );
                dot(pa, n)
                    .total_cmp(&dot(pb, n))
                    .then(images[a.0.image].instance.cmp(&images[b.0.image].instance))
            });
            let pos: Vec<[f64; 3]> = frames
                .iter()
                .map(|(_, p)| p.expect("all have positions"))
                .collect();
            let step = if nz >= 2 {
                check_steps(dir, &images, &frames, &pos, n)?
            } else {
                first.slice_step.unwrap_or(1.0)
            };
            let p = Placement {
                origin: pos[0],
                directions: [r, c, n],
            };
            p.validate().map_err(|e| {
                dicom_err(
                    &first.path,
                    Some(tags::IMAGE_ORIENTATION_PATIENT),
                    e.to_string(),
                )
            })?;
            (step, Some(p))
        }
        _ => {
            // No geometry: order by Instance Number, then frame; no placement.
            frames.sort_by_key(|(f, _)| (images[f.image].instance, f.image, f.frame));
            (first.slice_step.unwrap_or(1.0), None)
        }
    };
    let spacing = [ps_col as f32, ps_row as f32, z_step as f32];
    if spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(ReadError::Series {
            path: dir.clone(),
            reason: format!("voxel spacing {spacing:?} is not finite and positive"),
        });
    }

    // The whole volume, too, must come from the files' bytes (one slack per volume, not per
    // file, so that many small files cannot add up to a large buffer).
    let file_bytes: usize = src.files.iter().map(|(_, b)| b.len()).sum();
    let declared: usize = images
        .iter()
        .map(|i| i.rows * i.cols * i.frames * i.samples * (i.bits_allocated as usize / 8))
        .fold(0usize, usize::saturating_add);
    let most = file_bytes
        .saturating_mul(MAX_FILE_EXPANSION)
        .saturating_add(EXPANSION_SLACK);
    if declared > most {
        return Err(ReadError::Series {
            path: dir.clone(),
            reason: format!(
                "the images declare {declared} bytes of samples, more than {file_bytes} bytes of files can hold (at most {MAX_FILE_EXPANSION}× + {EXPANSION_SLACK} bytes)"
            ),
        });
    }

    // Pass 2: decode each file's frames into their slots.
    let mut slot_of: Vec<Vec<usize>> = images.iter().map(|i| vec![0; i.frames]).collect();
    for (z, (f, _)) in frames.iter().enumerate() {
        slot_of[f.image][f.frame] = z;
    }
    let channels = first.channels();
    let n = plane * nz;
    let mut out: Vec<Vec<f32>> = Vec::with_capacity(channels);
    for _ in 0..channels {
        let mut c = Vec::new();
        c.try_reserve_exact(n).map_err(|_| ReadError::Series {
            path: dir.clone(),
            reason: format!("cannot allocate {n} voxels"),
        })?;
        c.resize(n, 0.0);
        out.push(c);
    }
    let by_name: BTreeMap<&str, &[u8]> = src
        .files
        .iter()
        .map(|(n, b)| (n.as_str(), b.as_slice()))
        .collect();
    for (ii, img) in images.iter().enumerate() {
        let obj = parse(&img.path, by_name[img.name.as_str()], true)?;
        check_pixel_data(img, &obj)?;
        for f in 0..img.frames {
            let z = slot_of[ii][f];
            decode_frame(img, &obj, f, z * plane, &mut out)?;
        }
    }
    let v = Volume::new(dims, spacing, out).map_err(|e| ReadError::volume(dir, e))?;
    match placement {
        Some(p) => v.with_placement(p).map_err(|e| ReadError::volume(dir, e)),
        None => Ok(v),
    }
}

/// Checks the sorted positions: distinct, evenly spaced along the normal (reporting gaps), and
/// stacked along it (no shear). Returns the slice step.
fn check_steps(
    dir: &Path,
    images: &[Image],
    frames: &[(FrameRef, Option<[f64; 3]>)],
    pos: &[[f64; 3]],
    n: [f64; 3],
) -> Result<f64, ReadError> {
    let label = |k: usize| {
        let f = frames[k].0;
        let img = &images[f.image];
        if img.frames > 1 {
            format!("{} frame {} at {:?}", img.name, f.frame + 1, pos[k])
        } else {
            format!("{} at {:?}", img.name, pos[k])
        }
    };
    let nz = pos.len();
    let d: Vec<f64> = (1..nz)
        .map(|k| dot(pos[k], n) - dot(pos[k - 1], n))
        .collect();
    let total = dot(pos[nz - 1], n) - dot(pos[0], n);
    for (k, dk) in d.iter().enumerate() {
        if *dk <= 1e-4 {
            let (a, b) = (&images[frames[k].0.image], &images[frames[k + 1].0.image]);
            let times: std::collections::BTreeSet<&str> =
                images.iter().filter_map(|i| i.time.as_deref()).collect();
            let reason = match (&a.time, &b.time) {
                (Some(ta), Some(tb)) if ta != tb => format!(
                    "a time series (4D), not a volume: the same slices at {} time points ({} \
                     {ta} and {tb} at one position: {} and {}). wavesplat reads volumes: give \
                     each time point its own directory",
                    times.len(),
                    a.time_attribute,
                    label(k),
                    label(k + 1)
                ),
                _ => format!(
                    "two slices at the same position along the normal: {} and {} (several \
                     acquisitions in one series?)",
                    label(k),
                    label(k + 1)
                ),
            };
            return Err(ReadError::Series {
                path: dir.to_path_buf(),
                reason,
            });
        }
    }
    let mut sorted = d.clone();
    sorted.sort_by(f64::total_cmp);
    let typical = sorted[sorted.len() / 2];
    let tol = (0.01 * typical).max(1e-3);
    for (k, dk) in d.iter().enumerate() {
        if (dk - typical).abs() > tol {
            let ratio = dk / typical;
            let reason = if ratio > 1.5 && (ratio - ratio.round()).abs() * typical <= tol {
                format!(
                    "a gap: {} slice(s) missing between {} and {} ({dk:.4} mm apart, slices are {typical:.4} mm apart elsewhere)",
                    ratio.round() as i64 - 1,
                    label(k),
                    label(k + 1)
                )
            } else {
                format!(
                    "irregular slice spacing: {} and {} are {dk:.4} mm apart, slices are {typical:.4} mm apart elsewhere",
                    label(k),
                    label(k + 1)
                )
            };
            return Err(ReadError::Series {
                path: dir.to_path_buf(),
                reason,
            });
        }
    }
    let step = total / (nz - 1) as f64;
    // Stacked along the normal: the mean step between neighbours has no in-plane part.
    let delta = [0, 1, 2].map(|c| (pos[nz - 1][c] - pos[0][c]) / (nz - 1) as f64);
    let along = dot(delta, n);
    let lateral = [0, 1, 2].map(|c| delta[c] - along * n[c]);
    let shear = dot(lateral, lateral).sqrt();
    if shear > (0.01 * step).max(1e-3) {
        return Err(ReadError::Series {
            path: dir.to_path_buf(),
            reason: format!(
                "the slices are not stacked along their normal (each is shifted {shear:.4} mm sideways per {step:.4} mm step, a tilt of {:.2}°: gantry tilt or a sheared acquisition is not supported)",
                shear.atan2(step).to_degrees()
            ),
        });
    }
    Ok(step)
}

/// Checks the transfer syntax and the pixel data's size before anything is decoded.
fn check_pixel_data(img: &Image, obj: &DefaultDicomObject) -> Result<(), ReadError> {
    let path = &img.path;
    let ts_uid = obj
        .meta()
        .transfer_syntax()
        .trim_end_matches('\0')
        .to_string();
    let jpeg_ls = ts_uid == dicom_dictionary_std::uids::JPEGLS_LOSSLESS
        || ts_uid == dicom_dictionary_std::uids::JPEGLS_NEAR_LOSSLESS;
    if jpeg_ls && !cfg!(feature = "jpeg-ls") {
        return Err(dicom_err(
            path,
            Some(tags::TRANSFER_SYNTAX_UID),
            format!(
                "JPEG-LS ({ts_uid}) needs CharLS, which this build leaves out: rebuild with `--features jpeg-ls` (needs cmake and a C++ compiler), or transcode the series to another syntax"
            ),
        ));
    }
    let ts = TransferSyntaxRegistry.get(&ts_uid).ok_or_else(|| {
        dicom_err(
            path,
            Some(tags::TRANSFER_SYNTAX_UID),
            format!("unknown transfer syntax {ts_uid}"),
        )
    })?;
    if !ts.can_decode_all() {
        return Err(dicom_err(
            path,
            Some(tags::TRANSFER_SYNTAX_UID),
            format!(
                "{} ({ts_uid}) cannot be decoded by this build; supported are the native syntaxes, deflate, RLE Lossless, JPEG baseline/extended/lossless, JPEG 2000 (with High-Throughput JPEG 2000) and, with the `jpeg-ls` feature, JPEG-LS",
                ts.name()
            ),
        ));
    }
    let e = element(obj, tags::PIXEL_DATA)
        .ok_or_else(|| dicom_err(path, Some(tags::PIXEL_DATA), "missing"))?;
    let bytes_per = (img.bits_allocated / 8) as usize;
    let frame_bytes = native_frame_bytes(img);
    match e.fragments() {
        Some(frags) => {
            // dicom-rs's RLE adapter allocates the segment count a fragment's header declares
            // (4 bytes each) before checking it; the standard allows at most 15 in a 64-byte
            // header.
            if ts_uid == RLE_LOSSLESS {
                for (i, f) in frags.iter().enumerate() {
                    let segments = f
                        .get(..4)
                        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]));
                    if f.len() < 64 || segments.is_none_or(|n| n > 15) {
                        return Err(dicom_err(
                            path,
                            Some(tags::PIXEL_DATA),
                            format!(
                                "RLE fragment {} of {} bytes declares {segments:?} segments; an RLE header is 64 bytes and holds at most 15",
                                i + 1,
                                f.len()
                            ),
                        ));
                    }
                }
            }
            // jpeg-decoder (and zune-jpeg) decode 8-bit lossy JPEG only; a 12-bit extended
            // process stream would fail with the decoder's generic "unsupported feature".
            if JPEG_LOSSY.contains(&ts_uid.as_str()) {
                let first = frags.iter().find(|f| !f.is_empty());
                if let Some(p) = first
                    .and_then(|f| jpeg_sample_precision(f))
                    .filter(|p| *p != 8)
                {
                    return Err(dicom_err(
                        path,
                        Some(tags::PIXEL_DATA),
                        format!(
                            "{p}-bit lossy JPEG (extended process) is not supported: this build's \
                             JPEG decoder reads 8-bit lossy JPEG only; transcode the series (to \
                             JPEG Lossless, JPEG 2000 or an uncompressed syntax)"
                        ),
                    ));
                }
            }
            let compressed: usize = frags.iter().map(|f| f.len()).sum();
            let limit = compressed
                .saturating_mul(MAX_EXPANSION)
                .saturating_add(1 << 20);
            if frame_bytes.saturating_mul(img.frames) > limit {
                return Err(dicom_err(
                    path,
                    Some(tags::PIXEL_DATA),
                    format!(
                        "{} frames of {frame_bytes} bytes from {compressed} encapsulated bytes: more than {MAX_EXPANSION}× expansion, the header does not match the data",
                        img.frames
                    ),
                ));
            }
        }
        None => {
            let have = e.value().primitive().map_or(0, |p| p.calculate_byte_len());
            let need = if img.bits_allocated == 1 {
                (img.rows * img.cols * img.frames).div_ceil(8)
            } else {
                frame_bytes * img.frames
            };
            if have < need {
                return Err(dicom_err(
                    path,
                    Some(tags::PIXEL_DATA),
                    format!("{have} bytes, but {} frames of {}×{} × {} sample(s) × {bytes_per} byte(s) need {need}", img.frames, img.cols, img.rows, img.samples),
                ));
            }
        }
    }
    Ok(())
}

/// The JPEG transfer syntaxes whose colour rule [`adobe_rgb_jpeg_frame`] corrects.
const JPEG_LOSSY: [&str; 2] = ["1.2.840.10008.1.2.4.50", "1.2.840.10008.1.2.4.51"];

/// What a JPEG stream's markers say about its colour: (a JFIF marker, the Adobe marker's
/// transform flag), read up to the first scan.
fn jpeg_colour_markers(jpeg: &[u8]) -> (bool, Option<u8>) {
    let (mut jfif, mut adobe) = (false, None);
    let mut i = 2; // after SOI
    while i + 4 <= jpeg.len() && jpeg[i] == 0xFF {
        let marker = jpeg[i + 1];
        if marker == 0xFF {
            i += 1; // fill byte
            continue;
        }
        if marker == 0xDA || marker == 0xD9 {
            break; // start of scan, end of image
        }
        let len = usize::from(u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]));
        let payload = jpeg.get(i + 4..i + 2 + len).unwrap_or(&[]);
        match marker {
            0xE0 if payload.starts_with(b"JFIF\0") => jfif = true,
            0xEE if payload.starts_with(b"Adobe") && payload.len() >= 12 => {
                adobe = Some(payload[11])
            }
            _ => {}
        }
        i += 2 + len;
    }
    (jfif, adobe)
}

/// The sample precision (bits) a JPEG stream's frame header (SOF) declares, read up to the
/// first scan; `None` without one.
fn jpeg_sample_precision(jpeg: &[u8]) -> Option<u8> {
    let mut i = 2; // after SOI
    while i + 4 <= jpeg.len() && jpeg[i] == 0xFF {
        let marker = jpeg[i + 1];
        if marker == 0xFF {
            i += 1; // fill byte
            continue;
        }
        // SOF0..SOF15 but DHT (C4), JPG (C8) and DAC (CC).
        if (0xC0..=0xCF).contains(&marker) && !matches!(marker, 0xC4 | 0xC8 | 0xCC) {
            return jpeg.get(i + 4).copied();
        }
        if marker == 0xDA || marker == 0xD9 {
            return None;
        }
        i += 2 + usize::from(u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]));
    }
    None
}

/// Frame `f` of a lossy JPEG colour image decoded with libjpeg's colour rule, when it differs
/// from the one dicom-pixeldata's decoder applies: without a JFIF marker, an Adobe marker's
/// transform flag says whether the components are RGB (0) or YCbCr (1), whatever their
/// component ids. jpeg-decoder looks at the ids first, so an RGB image with ids 1, 2, 3 and
/// the Adobe flag 0 came out as if it were YCbCr (other colours, silently). With neither
/// marker, Photometric Interpretation RGB means the components are RGB. `None`: the general
/// path decodes it.
fn adobe_rgb_jpeg_frame(
    img: &Image,
    obj: &DefaultDicomObject,
    f: usize,
) -> Result<Option<Vec<u8>>, ReadError> {
    let ts = obj.meta().transfer_syntax().trim_end_matches('\0');
    if img.samples != 3 || img.bits_allocated != 8 || !JPEG_LOSSY.contains(&ts) {
        return Ok(None);
    }
    let Some(fragments) = element(obj, tags::PIXEL_DATA).and_then(|e| e.fragments()) else {
        return Ok(None);
    };
    let frame: Vec<u8> = if img.frames == 1 {
        fragments.iter().flatten().copied().collect()
    } else if fragments.len() == img.frames {
        fragments[f].clone()
    } else {
        return Ok(None);
    };
    let transform = match jpeg_colour_markers(&frame) {
        (false, Some(0)) => jpeg_decoder::ColorTransform::RGB,
        (false, Some(_)) => jpeg_decoder::ColorTransform::YCbCr,
        // Neither marker: the decoders guess from the component ids (1, 2, 3 or 0, 1, 2 read
        // as YCbCr), where DICOM's Photometric Interpretation RGB says no transform was
        // applied; reference readers follow it.
        (false, None) if img.photometric == "RGB" => jpeg_decoder::ColorTransform::RGB,
        _ => return Ok(None),
    };
    let mut decoder = jpeg_decoder::Decoder::new(&frame[..]);
    decoder.set_color_transform(transform);
    let pixels = catch_unwind(AssertUnwindSafe(|| decoder.decode()))
        .map_err(|_| {
            dicom_err(
                &img.path,
                Some(tags::PIXEL_DATA),
                "the JPEG decoder panicked",
            )
        })?
        .map_err(|e| {
            dicom_err(
                &img.path,
                Some(tags::PIXEL_DATA),
                format!("frame {}: {e}", f + 1),
            )
        })?;
    let info = decoder.info();
    match info {
        Some(i) if usize::from(i.width) == img.cols && usize::from(i.height) == img.rows => {
            Ok(Some(pixels))
        }
        _ => Err(dicom_err(
            &img.path,
            Some(tags::PIXEL_DATA),
            format!(
                "frame {}: the JPEG stream is {:?}, Rows × Columns say {}×{}",
                f + 1,
                info.map(|i| (i.width, i.height)),
                img.cols,
                img.rows
            ),
        )),
    }
}

/// Transfer Syntax UID of Explicit VR Big Endian (retired, still written by some toolkits).
const EXPLICIT_VR_BIG_ENDIAN: &str = "1.2.840.10008.1.2.2";

/// Frame `f`'s native samples (`data`) as host-order integers of the sample size. dicom-rs
/// hands native pixel data over as the host-order bytes of the units the element was read in:
/// 16-bit words for OW, 32-bit for OL, bytes in file order for OB. In a little-endian file
/// that is the samples' order whatever the unit; in a big-endian one a 32-bit sample read as
/// two OW words has its high word first, and 16- or 32-bit samples read as OB bytes are
/// big-endian, so those are put back together here (they came out as other numbers, silently,
/// before). 8-bit samples in OW words of a big-endian file are each word's bytes swapped back
/// (PS3.5 8.1.1: the first sample is the low byte of the first word), as pydicom reads them;
/// a frame may start inside a word, so its samples are cut from the whole pixel data.
fn native_order<'a>(
    img: &Image,
    obj: &DefaultDicomObject,
    f: usize,
    data: &'a [u8],
) -> Result<std::borrow::Cow<'a, [u8]>, ReadError> {
    use dicom_core::PrimitiveValue;
    use std::borrow::Cow;
    let ts = obj.meta().transfer_syntax().trim_end_matches('\0');
    let bytes_per = (img.bits_allocated / 8) as usize;
    if ts != EXPLICIT_VR_BIG_ENDIAN {
        return Ok(Cow::Borrowed(data));
    }
    let Some(p) = element(obj, tags::PIXEL_DATA).and_then(|e| e.value().primitive()) else {
        return Ok(Cow::Borrowed(data));
    };
    let unit = match p {
        PrimitiveValue::U8(_) => 1,
        PrimitiveValue::U16(_) | PrimitiveValue::I16(_) => 2,
        PrimitiveValue::U32(_) | PrimitiveValue::I32(_) | PrimitiveValue::F32(_) => 4,
        _ => 0,
    };
    match (unit, bytes_per) {
        (a, b) if a == b => Ok(Cow::Borrowed(data)),
        (2, 1) => {
            let words = p.to_bytes(); // host order
            let n = img.rows * img.cols * img.samples;
            // Sample k is byte k % 2 of word k / 2, low byte first; a short frame is reported
            // by `store_samples`.
            Ok(Cow::Owned(
                (f * n..(f + 1) * n)
                    .map_while(|k| {
                        let w = words.get(k & !1..(k & !1) + 2)?;
                        Some(u16::from_ne_bytes([w[0], w[1]]).to_le_bytes()[k % 2])
                    })
                    .collect(),
            ))
        }
        (1, 2) => Ok(Cow::Owned(
            data.chunks_exact(2)
                .flat_map(|c| u16::from_be_bytes([c[0], c[1]]).to_ne_bytes())
                .collect(),
        )),
        (1, 4) => Ok(Cow::Owned(
            data.chunks_exact(4)
                .flat_map(|c| u32::from_be_bytes([c[0], c[1], c[2], c[3]]).to_ne_bytes())
                .collect(),
        )),
        (2, 4) => Ok(Cow::Owned(
            data.chunks_exact(4)
                .flat_map(|c| {
                    let high = u16::from_ne_bytes([c[0], c[1]]);
                    let low = u16::from_ne_bytes([c[2], c[3]]);
                    ((u32::from(high) << 16) | u32::from(low)).to_ne_bytes()
                })
                .collect(),
        )),
        _ => Err(dicom_err(
            &img.path,
            Some(tags::PIXEL_DATA),
            format!(
                "{}-bit samples stored in {}-bit units in an Explicit VR Big Endian file: this \
                 layout is not supported (its byte order is ambiguous)",
                img.bits_allocated,
                unit * 8
            ),
        )),
    }
}

/// Decodes frame `f` of `obj` into the planar channels at `offset`, with the modality rescale.
fn decode_frame(
    img: &Image,
    obj: &DefaultDicomObject,
    f: usize,
    offset: usize,
    out: &mut [Vec<f32>],
) -> Result<(), ReadError> {
    let path = &img.path;
    if img.bits_allocated == 1 {
        return decode_bit_frame(img, obj, f, offset, out);
    }
    if let Some(rgb) = adobe_rgb_jpeg_frame(img, obj, f)? {
        return store_samples(img, f, offset, out, &rgb, false);
    }
    if let Some(rgb) = native_ybr_422_frame(img, obj, f)? {
        return store_samples(img, f, offset, out, &rgb, false);
    }
    if let Some(samples) = rle_32_bit_frame(img, obj, f)? {
        return store_samples(img, f, offset, out, &samples, false);
    }
    let decoded = catch_unwind(AssertUnwindSafe(|| obj.decode_pixel_data_frame(f as u32)))
        .map_err(|_| {
            dicom_err(
                path,
                Some(tags::PIXEL_DATA),
                "the pixel data decoder panicked",
            )
        })?
        .map_err(|e| {
            // The decoders' own reasons are in the error's sources.
            let mut reason = e.to_string();
            let mut source = std::error::Error::source(&e);
            while let Some(s) = source {
                reason.push_str(&format!(": {s}"));
                source = s.source();
            }
            dicom_err(
                path,
                Some(tags::PIXEL_DATA),
                format!("frame {}: {reason}", f + 1),
            )
        })?;
    let data = decoded.data();
    let need = img.rows * img.cols * img.samples * (img.bits_allocated / 8) as usize;
    // A short frame is reported by `store_samples`.
    let data = native_order(img, obj, f, data.get(..need).unwrap_or(data))?;
    // Native RGB may be planar (R plane, G plane, B plane); decoders return interleaved.
    let planar = img.samples == 3
        && decoded.planar_configuration() == dicom_pixeldata::PlanarConfiguration::PixelFirst;
    match ybr_full_to_rgb(img, obj, &data, planar)? {
        Some(rgb) => store_samples(img, f, offset, out, &rgb, false),
        None => store_samples(img, f, offset, out, &data, planar),
    }
}

/// Frame `f` of RLE Lossless pixel data with 32-bit samples (an RT Dose grid, typically) as
/// host-order samples. dicom-rs's RLE decoder handles 8 and 16 bits only; RLE is PackBits per
/// byte plane (PS3.5 Annex G), decoded here. `None` for anything else.
fn rle_32_bit_frame(
    img: &Image,
    obj: &DefaultDicomObject,
    f: usize,
) -> Result<Option<Vec<u8>>, ReadError> {
    let ts = obj.meta().transfer_syntax().trim_end_matches('\0');
    if ts != RLE_LOSSLESS || img.bits_allocated != 32 {
        return Ok(None);
    }
    let err = |reason: String| {
        dicom_err(
            &img.path,
            Some(tags::PIXEL_DATA),
            format!("frame {}: {reason}", f + 1),
        )
    };
    let Some(fragments) = element(obj, tags::PIXEL_DATA).and_then(|e| e.fragments()) else {
        return Err(err("RLE Lossless without encapsulated fragments".into()));
    };
    let frame: Vec<u8> = if img.frames == 1 {
        fragments.iter().flatten().copied().collect()
    } else if fragments.len() == img.frames {
        fragments[f].clone()
    } else {
        return Err(err(format!(
            "{} fragments for {} frames: one fragment a frame expected",
            fragments.len(),
            img.frames
        )));
    };
    let n = img.rows * img.cols;
    let segments = img.samples * 4;
    let word = |i: usize| {
        frame
            .get(4 * i..4 * i + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
    };
    if frame.len() < 64 || word(0) != Some(segments) {
        return Err(err(format!(
            "the RLE header declares {:?} segments; {} samples of 4 bytes need {segments}",
            word(0),
            img.samples
        )));
    }
    let mut planes = Vec::with_capacity(segments);
    for s in 0..segments {
        let start = word(1 + s).unwrap_or(usize::MAX);
        let end = if s + 1 < segments {
            word(2 + s).unwrap_or(usize::MAX)
        } else {
            frame.len()
        };
        let Some(coded) = frame.get(start..end).filter(|_| start >= 64) else {
            return Err(err(format!(
                "RLE segment {} at bytes {start}..{end}",
                s + 1
            )));
        };
        planes.push(packbits(coded, n).ok_or_else(|| {
            err(format!(
                "RLE segment {} does not decode to {n} bytes",
                s + 1
            ))
        })?);
    }
    let mut out = Vec::with_capacity(n * segments);
    for i in 0..n {
        for c in 0..img.samples {
            // Segments run from each sample's most significant byte to its least.
            let p = &planes[4 * c..4 * c + 4];
            let v = u32::from_be_bytes([p[0][i], p[1][i], p[2][i], p[3][i]]);
            out.extend_from_slice(&v.to_ne_bytes());
        }
    }
    Ok(Some(out))
}

/// PackBits (the RLE of PS3.5 G.3.1): `n` bytes, or `None` if the data holds fewer.
fn packbits(coded: &[u8], n: usize) -> Option<Vec<u8>> {
    let mut out = Vec::with_capacity(n);
    let mut i = 0;
    while out.len() < n && i < coded.len() {
        let h = coded[i] as i8;
        i += 1;
        match h {
            0.. => {
                let len = h as usize + 1;
                out.extend_from_slice(coded.get(i..i + len)?);
                i += len;
            }
            -127..=-1 => {
                let b = *coded.get(i)?;
                i += 1;
                out.extend(std::iter::repeat_n(b, (1 - h as isize) as usize));
            }
            _ => {} // -128: no operation
        }
    }
    (out.len() >= n).then(|| {
        out.truncate(n);
        out
    })
}

/// Bytes of one frame of native pixel data: YBR_FULL_422 holds two luminance samples and one
/// pair of chrominance samples for every two pixels.
fn native_frame_bytes(img: &Image) -> usize {
    let bytes_per = (img.bits_allocated / 8) as usize;
    let samples = if img.photometric == "YBR_FULL_422" {
        2
    } else {
        img.samples
    };
    img.rows * img.cols * samples * bytes_per
}

/// Frame `f` of a 1-bit image (a mask) into channel 0 at `offset`, as 0 and 1 through the
/// rescale. The bits of all frames run on without padding, least significant bit first
/// (PS3.5 8.1.1); dicom-pixeldata cuts frames at byte boundaries, so they are read here. In
/// Explicit VR Big Endian only OB pixel data is read.
fn decode_bit_frame(
    img: &Image,
    obj: &DefaultDicomObject,
    f: usize,
    offset: usize,
    out: &mut [Vec<f32>],
) -> Result<(), ReadError> {
    let err = |reason: String| dicom_err(&img.path, Some(tags::PIXEL_DATA), reason);
    let ts = obj.meta().transfer_syntax().trim_end_matches('\0');
    let Some(p) = element(obj, tags::PIXEL_DATA).and_then(|e| e.value().primitive()) else {
        return Err(err("1-bit samples must be native (not encapsulated)".into()));
    };
    // OB bytes are never swapped, so in a big-endian file the bits read as in a little-endian
    // one (as pydicom reads them). OW words are byte-swapped there, and toolkits disagree on
    // where the bits go then (pydicom takes the bytes in file order, dcmtk the words').
    if ts == EXPLICIT_VR_BIG_ENDIAN && !matches!(p, dicom_core::PrimitiveValue::U8(_)) {
        return Err(err(
            "1-bit samples in 16-bit words (OW) in an Explicit VR Big Endian file are not \
             supported: their bit order is ambiguous (toolkits disagree); store them as OB"
                .into(),
        ));
    }
    let bytes = p.to_bytes();
    let plane = img.rows * img.cols;
    let (slope, intercept) = img.rescale[f];
    for (i, d) in out[0][offset..offset + plane].iter_mut().enumerate() {
        let k = f * plane + i;
        let byte = bytes.get(k / 8).ok_or_else(|| {
            err(format!(
                "{} bytes hold fewer than {} bits",
                bytes.len(),
                k + 1
            ))
        })?;
        let bit = f64::from((byte >> (k % 8)) & 1);
        *d = (bit * slope + intercept) as f32;
    }
    Ok(())
}

/// Whether `obj`'s pixel data is encapsulated and its codec leaves the colour space as it is
/// (RLE, JPEG-LS): then, as in native data, YBR_FULL samples are still Y, Cb, Cr.
fn colour_untouched_by_codec(obj: &DefaultDicomObject) -> bool {
    let ts = obj.meta().transfer_syntax().trim_end_matches('\0');
    let encapsulated = element(obj, tags::PIXEL_DATA).is_some_and(|e| e.fragments().is_some());
    !encapsulated
        || ts == RLE_LOSSLESS
        || ts == dicom_dictionary_std::uids::JPEGLS_LOSSLESS
        || ts == dicom_dictionary_std::uids::JPEGLS_NEAR_LOSSLESS
}

/// One full-range Y, Cb, Cr triple (PS3.3 C.7.6.3.1.2, the ITU-R BT.601 matrix without
/// head- and footroom) as R, G, B, rounded and clamped to the sample range as other readers
/// (pydicom, dicom-rs's image conversion) do; `half` is the chrominance zero (128 or 32768).
fn ybr_full_pixel(y: f64, cb: f64, cr: f64, half: f64) -> [f64; 3] {
    let (cb, cr) = (cb - half, cr - half);
    let max = 2.0 * half - 1.0;
    let c = |v: f64| (v + 0.5).floor().clamp(0.0, max);
    [
        c(y + 1.402 * cr),
        c(y - (0.114 * 1.772 / 0.587) * cb - (0.299 * 1.402 / 0.587) * cr),
        c(y + 1.772 * cb),
    ]
}

/// Interleaved RGB samples (host order) from 8- or 16-bit Y, Cb, Cr triples.
fn ybr_triples_to_rgb(bytes_per: usize, ybr: impl Iterator<Item = [f64; 3]>) -> Vec<u8> {
    let half = if bytes_per == 1 { 128.0 } else { 32768.0 };
    let mut out = Vec::new();
    for [y, cb, cr] in ybr {
        for v in ybr_full_pixel(y, cb, cr, half) {
            match bytes_per {
                1 => out.push(v as u8),
                _ => out.extend_from_slice(&(v as u16).to_ne_bytes()),
            }
        }
    }
    out
}

fn sample_at(data: &[u8], bytes_per: usize, k: usize) -> f64 {
    match bytes_per {
        1 => f64::from(data[k]),
        _ => f64::from(u16::from_ne_bytes([data[2 * k], data[2 * k + 1]])),
    }
}

/// A frame of YBR_FULL samples the codec did not convert (native, RLE, JPEG-LS) as RGB; `None`
/// for RGB, or where the decoder already converted (lossy JPEG, JPEG 2000). Before, such
/// frames were stored as if Y, Cb and Cr were R, G and B.
fn ybr_full_to_rgb(
    img: &Image,
    obj: &DefaultDicomObject,
    data: &[u8],
    planar: bool,
) -> Result<Option<Vec<u8>>, ReadError> {
    if img.samples != 3 || img.photometric != "YBR_FULL" || !colour_untouched_by_codec(obj) {
        return Ok(None);
    }
    let bytes_per = (img.bits_allocated / 8) as usize;
    if bytes_per > 2 || img.signed {
        return Err(dicom_err(
            &img.path,
            Some(tags::PHOTOMETRIC_INTERPRETATION),
            format!(
                "YBR_FULL with {} {}-bit samples: only unsigned 8- and 16-bit are supported",
                if img.signed { "signed" } else { "unsigned" },
                img.bits_allocated
            ),
        ));
    }
    let plane = img.rows * img.cols;
    if data.len() < 3 * plane * bytes_per {
        return Ok(None); // reported as a short frame
    }
    let at = |i: usize, c: usize| {
        let k = if planar { c * plane + i } else { 3 * i + c };
        sample_at(data, bytes_per, k)
    };
    Ok(Some(ybr_triples_to_rgb(
        bytes_per,
        (0..plane).map(|i| [at(i, 0), at(i, 1), at(i, 2)]),
    )))
}

/// Frame `f` of native YBR_FULL_422 pixel data (Y1 Y2 Cb Cr for each pair of pixels along a
/// row) as RGB. dicom-pixeldata sizes native frames as three samples a pixel, so these frames
/// are cut from the pixel data here. `None` for anything else.
fn native_ybr_422_frame(
    img: &Image,
    obj: &DefaultDicomObject,
    f: usize,
) -> Result<Option<Vec<u8>>, ReadError> {
    if img.samples != 3 || img.photometric != "YBR_FULL_422" {
        return Ok(None);
    }
    let Some(p) = element(obj, tags::PIXEL_DATA).and_then(|e| e.value().primitive()) else {
        return Ok(None); // encapsulated: the JPEG decoder converts
    };
    let bytes_per = (img.bits_allocated / 8) as usize;
    let err = |reason: String| dicom_err(&img.path, Some(tags::PHOTOMETRIC_INTERPRETATION), reason);
    if bytes_per > 2 || img.signed || img.cols % 2 == 1 {
        return Err(err(format!(
            "native YBR_FULL_422 with {} columns of {}-bit {} samples: only even widths of \
             unsigned 8- or 16-bit samples are supported",
            img.cols,
            img.bits_allocated,
            if img.signed { "signed" } else { "unsigned" }
        )));
    }
    let all = p.to_bytes();
    let size = native_frame_bytes(img);
    let Some(frame) = all.get(f * size..(f + 1) * size) else {
        return Err(err(format!(
            "frame {} lies beyond the {} bytes of pixel data",
            f + 1,
            all.len()
        )));
    };
    let pairs = img.rows * img.cols / 2;
    Ok(Some(ybr_triples_to_rgb(
        bytes_per,
        (0..pairs).flat_map(|q| {
            let s = |j: usize| sample_at(frame, bytes_per, 4 * q + j);
            let (cb, cr) = (s(2), s(3));
            [[s(0), cb, cr], [s(1), cb, cr]]
        }),
    )))
}

/// Stores frame `f`'s decoded samples (`data`, host order, interleaved or `planar`) into the
/// planar channels at `offset`, with the modality rescale.
fn store_samples(
    img: &Image,
    f: usize,
    offset: usize,
    out: &mut [Vec<f32>],
    data: &[u8],
    planar: bool,
) -> Result<(), ReadError> {
    let bytes_per = (img.bits_allocated / 8) as usize;
    let plane = img.rows * img.cols;
    let need = plane * img.samples * bytes_per;
    if data.len() < need {
        return Err(dicom_err(
            &img.path,
            Some(tags::PIXEL_DATA),
            format!(
                "frame {} decodes to {} bytes, {need} expected",
                f + 1,
                data.len()
            ),
        ));
    }
    let (slope, intercept) = img.rescale[f];
    let shift = 32 - img.bits_stored;
    let value = |s: &[u8]| -> f64 {
        let raw: u32 = match bytes_per {
            1 => u32::from(s[0]),
            2 => u32::from(u16::from_ne_bytes([s[0], s[1]])),
            _ => u32::from_ne_bytes([s[0], s[1], s[2], s[3]]),
        };
        // Keep the stored bits; sign-extend from Bits Stored.
        let v = raw << shift;
        if img.signed {
            f64::from((v as i32) >> shift)
        } else {
            f64::from(v >> shift)
        }
    };
    if let Some(palette) = &img.palette {
        for (c, ch) in out.iter_mut().enumerate() {
            let dst = &mut ch[offset..offset + plane];
            for (i, d) in dst.iter_mut().enumerate() {
                *d = palette.colour(c, value(&data[i * bytes_per..(i + 1) * bytes_per]));
            }
        }
        return Ok(());
    }
    for (c, ch) in out.iter_mut().enumerate() {
        let dst = &mut ch[offset..offset + plane];
        for (i, d) in dst.iter_mut().enumerate() {
            let k = if planar {
                c * plane + i
            } else {
                i * img.samples + c
            };
            let s = &data[k * bytes_per..(k + 1) * bytes_per];
            *d = (value(s) * slope + intercept) as f32;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests;
