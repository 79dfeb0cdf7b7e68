//! Colour: PALETTE COLOR lookup tables (read, and applied to stored values), and YBR_FULL /
//! YBR_FULL_422 samples the codec left as they were (native, RLE, JPEG-LS) converted to RGB
//! with the full-range BT.601 matrix, as other readers convert them.

use std::path::Path;

use dicom_dictionary_std::tags;
use dicom_object::{DefaultDicomObject, InMemDicomObject};

use super::attributes::element;
use super::attributes::transfer_syntax;
use super::dicom_err;
use super::Image;
use crate::reader::ReadError;

/// A PALETTE COLOR image's lookup tables: per colour, the first stored value mapped and the
/// entries (PS3.3 C.7.6.3.1.5).
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Palette {
    tables: [(i64, Vec<f32>); 3],
}

impl Palette {
    /// The colour of stored value `v`: values below the first mapped one take the first entry,
    /// values past the last the last.
    pub(super) fn colour(&self, c: usize, v: f64) -> f32 {
        let (first, t) = &self.tables[c];
        let i = (v as i64 - first).clamp(0, t.len() as i64 - 1);
        t[i as usize]
    }
}

/// Reads the red, green and blue palette tables (descriptor: entries (0 for 65536), first
/// mapped value, bits per entry; data: one 16-bit word an entry). Segmented palettes are
/// refused, naming them.
pub(super) fn read_palette(
    path: &Path,
    o: &InMemDicomObject,
    signed: bool,
) -> Result<Palette, ReadError> {
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

/// Whether `obj`'s pixel data is encapsulated and its codec leaves the colour space as it is
/// (RLE, JPEG-LS): then, as in native data, YBR_FULL samples are still Y, Cb, Cr.
fn colour_untouched_by_codec(obj: &DefaultDicomObject) -> bool {
    let ts = transfer_syntax(obj);
    let encapsulated = element(obj, tags::PIXEL_DATA).is_some_and(|e| e.fragments().is_some());
    !encapsulated
        || ts == dicom_dictionary_std::uids::RLE_LOSSLESS
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
pub(super) fn ybr_triples_to_rgb(bytes_per: usize, ybr: impl Iterator<Item = [f64; 3]>) -> Vec<u8> {
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

pub(super) fn sample_at(data: &[u8], bytes_per: usize, k: usize) -> f64 {
    match bytes_per {
        1 => f64::from(data[k]),
        _ => f64::from(u16::from_ne_bytes([data[2 * k], data[2 * k + 1]])),
    }
}

/// A frame of YBR_FULL samples the codec did not convert (native, RLE, JPEG-LS) as RGB; `None`
/// for RGB, or where the decoder already converted (lossy JPEG, JPEG 2000). Before, such
/// frames were stored as if Y, Cb and Cr were R, G and B.
pub(super) fn ybr_full_to_rgb(
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
