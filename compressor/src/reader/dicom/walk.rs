//! The `DICM` preamble check, the length-checking element walker and the parse it guards: before dicom-rs reads a file,
//! [`check_lengths`] walks its element headers (meta group, data set, sequences, items,
//! fragments) and checks that every declared length fits in the bytes that remain, so that a
//! forged length cannot make the parser allocate; it also decides how to read an element whose
//! VR bytes name no VR, and [`parse`] rewrites such elements so that dicom-rs reads what the
//! walk read, then parses the file with panics caught.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use dicom_object::file::ReadPreamble;
use dicom_object::{DefaultDicomObject, OpenFileOptions};

use super::attributes::known_vrs;
use super::{dicom_err, MAX_EXPANSION};
use crate::reader::ReadError;

/// Whether `head` has the DICOM file preamble (`DICM` at offset 128).
pub(crate) fn has_preamble(head: &[u8]) -> bool {
    head.len() >= 132 && &head[128..132] == b"DICM"
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
pub(super) fn parse(
    path: &Path,
    bytes: &[u8],
    pixels: bool,
) -> Result<DefaultDicomObject, ReadError> {
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
