//! Pixel decoding: the checks on the transfer syntax and the pixel data's size before anything
//! is decoded, and each frame's samples into the volume's channels with the modality rescale.
//! Native data in either byte order (units put back in sample order; native YBR_FULL_422
//! frames cut from the pixel data here, then converted by [`super::colour`]), RLE (32-bit here, the
//! rest through dicom-pixeldata), 1-bit masks, and the JPEG family (lossy colour JPEG with
//! libjpeg's colour rule, 12-bit lossy JPEG refused naming it; the rest through
//! dicom-pixeldata).

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;

use dicom_dictionary_std::tags;
use dicom_object::DefaultDicomObject;
use dicom_pixeldata::PixelDecoder;
use dicom_transfer_syntax_registry::{TransferSyntaxIndex, TransferSyntaxRegistry};

use super::attributes::{element, transfer_syntax};
use super::colour::{sample_at, ybr_full_to_rgb, ybr_triples_to_rgb};
use super::Image;
use super::{dicom_err, MAX_EXPANSION};
use crate::reader::ReadError;

/// Transfer Syntax UID of RLE Lossless.
pub(super) const RLE_LOSSLESS: &str = "1.2.840.10008.1.2.5";

/// Frame `f` of encapsulated pixel data: every fragment joined for a single frame, else
/// fragment `f` when there is one fragment a frame. `None` when the pixel data is not
/// encapsulated; `Some(Err(n))` when its `n` fragments are neither.
fn encapsulated_frame(
    img: &Image,
    obj: &DefaultDicomObject,
    f: usize,
) -> Option<Result<Vec<u8>, usize>> {
    let fragments = element(obj, tags::PIXEL_DATA)?.fragments()?;
    Some(if img.frames == 1 {
        Ok(fragments.iter().flatten().copied().collect())
    } else if fragments.len() == img.frames {
        Ok(fragments[f].clone())
    } else {
        Err(fragments.len())
    })
}

/// The refusal of a JPEG-LS transfer syntax by a build that leaves CharLS out
/// (`reads_jpeg_ls` false: the default-off `jpeg-ls` feature), naming the feature that reads
/// it; `None` for any other syntax, or where the build reads JPEG-LS. A function of its own so
/// that a build with the feature tests the refusal too.
pub(super) fn jpeg_ls_refusal(path: &Path, ts_uid: &str, reads_jpeg_ls: bool) -> Option<ReadError> {
    let jpeg_ls = ts_uid == dicom_dictionary_std::uids::JPEGLS_LOSSLESS
        || ts_uid == dicom_dictionary_std::uids::JPEGLS_NEAR_LOSSLESS;
    (jpeg_ls && !reads_jpeg_ls).then(|| {
        dicom_err(
            path,
            Some(tags::TRANSFER_SYNTAX_UID),
            format!(
                "JPEG-LS ({ts_uid}) needs CharLS, which this build leaves out: rebuild with `--features jpeg-ls` (needs cmake and a C++ compiler), or transcode the series to another syntax"
            ),
        )
    })
}

/// Checks the transfer syntax and the pixel data's size before anything is decoded.
pub(super) fn check_pixel_data(img: &Image, obj: &DefaultDicomObject) -> Result<(), ReadError> {
    let path = &img.path;
    let ts_uid = transfer_syntax(obj).to_string();
    if let Some(refused) = jpeg_ls_refusal(path, &ts_uid, cfg!(feature = "jpeg-ls")) {
        return Err(refused);
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

/// The marker segments of a JPEG stream's header, from after SOI up to the first scan (SOS)
/// or the end of the image (EOI), each as (marker, offset of its 0xFF, its length field); fill
/// bytes are passed over, and the walk ends where the bytes stop looking like segments.
fn jpeg_header_segments(jpeg: &[u8]) -> impl Iterator<Item = (u8, usize, usize)> + '_ {
    let mut i = 2; // after SOI
    std::iter::from_fn(move || {
        while i + 4 <= jpeg.len() && jpeg[i] == 0xFF {
            let marker = jpeg[i + 1];
            if marker == 0xFF {
                i += 1; // fill byte
                continue;
            }
            if marker == 0xDA || marker == 0xD9 {
                return None; // start of scan, end of image
            }
            let at = i;
            let len = usize::from(u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]));
            i += 2 + len;
            return Some((marker, at, len));
        }
        None
    })
}

/// What a JPEG stream's markers say about its colour: (a JFIF marker, the Adobe marker's
/// transform flag), read up to the first scan.
pub(super) fn jpeg_colour_markers(jpeg: &[u8]) -> (bool, Option<u8>) {
    let (mut jfif, mut adobe) = (false, None);
    for (marker, at, len) in jpeg_header_segments(jpeg) {
        let payload = jpeg.get(at + 4..at + 2 + len).unwrap_or(&[]);
        match marker {
            0xE0 if payload.starts_with(b"JFIF\0") => jfif = true,
            0xEE if payload.starts_with(b"Adobe") && payload.len() >= 12 => {
                adobe = Some(payload[11])
            }
            _ => {}
        }
    }
    (jfif, adobe)
}

/// The sample precision (bits) a JPEG stream's frame header (SOF) declares, read up to the
/// first scan; `None` without one.
pub(super) fn jpeg_sample_precision(jpeg: &[u8]) -> Option<u8> {
    jpeg_header_segments(jpeg)
        // SOF0..SOF15 but DHT (C4), JPG (C8) and DAC (CC).
        .find(|&(marker, _, _)| {
            (0xC0..=0xCF).contains(&marker) && !matches!(marker, 0xC4 | 0xC8 | 0xCC)
        })
        .and_then(|(_, at, _)| jpeg.get(at + 4).copied())
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
    if img.samples != 3 || img.bits_allocated != 8 || !JPEG_LOSSY.contains(&transfer_syntax(obj)) {
        return Ok(None);
    }
    let Some(Ok(frame)) = encapsulated_frame(img, obj, f) else {
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
pub(super) const EXPLICIT_VR_BIG_ENDIAN: &str = "1.2.840.10008.1.2.2";

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
    let ts = transfer_syntax(obj);
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

/// A decoder of a case that the general path (dicom-pixeldata) gets wrong or lacks: frame `f`
/// as interleaved host-order samples, or `None` when the case is not this one.
type SpecialFrame = fn(&Image, &DefaultDicomObject, usize) -> Result<Option<Vec<u8>>, ReadError>;

/// Decodes frame `f` of `obj` into the planar channels at `offset`, with the modality rescale.
pub(super) fn decode_frame(
    img: &Image,
    obj: &DefaultDicomObject,
    f: usize,
    offset: usize,
    out: &mut [Vec<f32>],
) -> Result<(), ReadError> {
    let path = &img.path;
    if img.bits_allocated == 1 {
        let plane = img.rows * img.cols;
        return decode_bit_frame(img, obj, f, &mut out[0][offset..offset + plane]);
    }
    let special: [SpecialFrame; 3] = [adobe_rgb_jpeg_frame, native_ybr_422_frame, rle_32_bit_frame];
    for decode in special {
        if let Some(samples) = decode(img, obj, f)? {
            return store_samples(img, f, offset, out, &samples, false);
        }
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
    if transfer_syntax(obj) != RLE_LOSSLESS || img.bits_allocated != 32 {
        return Ok(None);
    }
    let err = |reason: String| {
        dicom_err(
            &img.path,
            Some(tags::PIXEL_DATA),
            format!("frame {}: {reason}", f + 1),
        )
    };
    let frame = match encapsulated_frame(img, obj, f) {
        Some(Ok(frame)) => frame,
        None => return Err(err("RLE Lossless without encapsulated fragments".into())),
        Some(Err(n)) => {
            return Err(err(format!(
                "{n} fragments for {} frames: one fragment a frame expected",
                img.frames
            )))
        }
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
pub(super) fn packbits(coded: &[u8], n: usize) -> Option<Vec<u8>> {
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
pub(super) fn native_frame_bytes(img: &Image) -> usize {
    let bytes_per = (img.bits_allocated / 8) as usize;
    let samples = if img.photometric == "YBR_FULL_422" {
        2
    } else {
        img.samples
    };
    img.rows * img.cols * samples * bytes_per
}

/// Frame `f` of a 1-bit image (a mask) into `frame` (its samples in channel 0), as 0 and 1
/// through the rescale. The bits of all frames run on without padding, least significant bit first
/// (PS3.5 8.1.1); dicom-pixeldata cuts frames at byte boundaries, so they are read here. In
/// Explicit VR Big Endian only OB pixel data is read.
fn decode_bit_frame(
    img: &Image,
    obj: &DefaultDicomObject,
    f: usize,
    frame: &mut [f32],
) -> Result<(), ReadError> {
    let err = |reason: String| dicom_err(&img.path, Some(tags::PIXEL_DATA), reason);
    let ts = transfer_syntax(obj);
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
    for (i, d) in frame.iter_mut().take(plane).enumerate() {
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
