//! Writers of small volumes in every format the readers understand (DICOM series and
//! multi-frame files through dicom-rs, NRRD, MetaImage), so that tests here and end to end can
//! generate their data and check the readers against the arrays, spacing and placement they
//! wrote. They are test fixtures, not exporters: they write what the tests need (integer
//! samples must be exactly representable in the chosen layout after the inverse rescale) and
//! panic on I/O errors.

use std::io::Write;
use std::path::{Path, PathBuf};

use dicom_core::value::{DataSetSequence, PixelFragmentSequence};
use dicom_core::{DataElement, DicomValue, Length, PrimitiveValue, VR};
use dicom_dictionary_std::{tags, uids};
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
use wavesplat_codec::volume::{Placement, Volume};

/// Sample type a fixture is written with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// Unsigned 8-bit.
    U8,
    /// Signed 8-bit.
    I8,
    /// Unsigned 16-bit.
    U16,
    /// Signed 16-bit.
    I16,
    /// 32-bit float (NRRD and MetaImage only).
    F32,
}

impl Layout {
    fn bytes(self) -> usize {
        match self {
            Layout::U8 | Layout::I8 => 1,
            Layout::U16 | Layout::I16 => 2,
            Layout::F32 => 4,
        }
    }

    fn signed(self) -> bool {
        matches!(self, Layout::I8 | Layout::I16 | Layout::F32)
    }

    /// Little-endian bytes of one stored value (checked to be representable).
    fn encode(self, v: f64, out: &mut Vec<u8>) {
        let int = |lo: f64, hi: f64| {
            assert!(
                v.fract() == 0.0 && (lo..=hi).contains(&v),
                "fixture value {v} is not representable as {self:?}"
            );
            v as i64
        };
        match self {
            Layout::U8 => out.push(int(0.0, 255.0) as u8),
            Layout::I8 => out.push(int(-128.0, 127.0) as i8 as u8),
            Layout::U16 => out.extend_from_slice(&(int(0.0, 65535.0) as u16).to_le_bytes()),
            Layout::I16 => out.extend_from_slice(&(int(-32768.0, 32767.0) as i16).to_le_bytes()),
            Layout::F32 => out.extend_from_slice(&(v as f32).to_le_bytes()),
        }
    }
}

/// Interleaved little-endian samples of `v`, each stored as `(value − intercept) / slope`.
fn samples(v: &Volume, layout: Layout, slope: f64, intercept: f64) -> Vec<u8> {
    let c = v.channel_count();
    let mut out = Vec::with_capacity(v.voxel_count() * c * layout.bytes());
    for i in 0..v.voxel_count() {
        for ch in 0..c {
            layout.encode((f64::from(v.channel(ch)[i]) - intercept) / slope, &mut out);
        }
    }
    out
}

fn placement_or_identity(v: &Volume) -> Placement {
    v.placement().copied().unwrap_or_else(Placement::identity)
}

/// NRRD data encodings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NrrdEncoding {
    /// Raw bytes.
    Raw,
    /// gzip-compressed bytes.
    Gzip,
    /// Decimal text.
    Ascii,
}

/// Writes `v` as NRRD (`NAME.nrrd`, or `NAME.nhdr` + `NAME.raw`/`.raw.gz`/`.txt` when
/// `detached`) with `space directions` and `space origin` in `space` (`LPS`, `RAS`, `LAS` or
/// their long names); returns the header's path.
pub fn write_nrrd(
    dir: &Path,
    name: &str,
    v: &Volume,
    layout: Layout,
    encoding: NrrdEncoding,
    detached: bool,
    space: &str,
) -> PathBuf {
    let p = placement_or_identity(v);
    let sign = match space.to_ascii_lowercase().as_str() {
        "lps" | "left-posterior-superior" => [1.0, 1.0, 1.0],
        "ras" | "right-anterior-superior" => [-1.0, -1.0, 1.0],
        "las" | "left-anterior-superior" => [1.0, -1.0, 1.0],
        s => panic!("fixture space {s}"),
    };
    let s = v.spacing();
    let vec = |a: usize| {
        let d = p.directions[a];
        let k = f64::from(s[a]);
        format!(
            "({},{},{})",
            d[0] * k * sign[0],
            d[1] * k * sign[1],
            d[2] * k * sign[2]
        )
    };
    let o = p.origin;
    let dims = v.dims();
    let rgb = v.channel_count() == 3;
    let ty = match layout {
        Layout::U8 => "uint8",
        Layout::I8 => "int8",
        Layout::U16 => "uint16",
        Layout::I16 => "short",
        Layout::F32 => "float",
    };
    let enc = match encoding {
        NrrdEncoding::Raw => "raw",
        NrrdEncoding::Gzip => "gzip",
        NrrdEncoding::Ascii => "ascii",
    };
    let mut h = String::from("NRRD0004\n# written by a wavesplat test\n");
    h += &format!("type: {ty}\n");
    if rgb {
        h += &format!(
            "dimension: 4\nsizes: 3 {} {} {}\nkinds: RGB-color domain domain domain\n",
            dims[0], dims[1], dims[2]
        );
    } else {
        h += &format!("dimension: 3\nsizes: {} {} {}\n", dims[0], dims[1], dims[2]);
    }
    h += &format!("space: {space}\n");
    h += &format!(
        "space directions: {}{} {} {}\n",
        if rgb { "none " } else { "" },
        vec(0),
        vec(1),
        vec(2)
    );
    h += &format!(
        "space origin: ({},{},{})\n",
        o[0] * sign[0],
        o[1] * sign[1],
        o[2] * sign[2]
    );
    h += &format!("endian: little\nencoding: {enc}\n");
    let data = match encoding {
        NrrdEncoding::Raw => samples(v, layout, 1.0, 0.0),
        NrrdEncoding::Gzip => {
            let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
            gz.write_all(&samples(v, layout, 1.0, 0.0)).unwrap();
            gz.finish().unwrap()
        }
        NrrdEncoding::Ascii => {
            let mut t = String::new();
            for i in 0..v.voxel_count() {
                for c in 0..v.channel_count() {
                    t += &format!("{} ", v.channel(c)[i]);
                }
                t.push('\n');
            }
            t.into_bytes()
        }
    };
    if detached {
        let data_name = format!(
            "{name}.{}",
            match encoding {
                NrrdEncoding::Raw => "raw",
                NrrdEncoding::Gzip => "raw.gz",
                NrrdEncoding::Ascii => "txt",
            }
        );
        h += &format!("data file: {data_name}\n");
        std::fs::write(dir.join(&data_name), data).unwrap();
        let path = dir.join(format!("{name}.nhdr"));
        std::fs::write(&path, h).unwrap();
        path
    } else {
        h.push('\n');
        let mut bytes = h.into_bytes();
        bytes.extend_from_slice(&data);
        let path = dir.join(format!("{name}.nrrd"));
        std::fs::write(&path, bytes).unwrap();
        path
    }
}

/// Writes `v` as MetaImage (`NAME.mha`, or `NAME.mhd` + `NAME.raw` when `detached`),
/// zlib-compressed when `compressed`; returns the header's path.
pub fn write_metaimage(
    dir: &Path,
    name: &str,
    v: &Volume,
    layout: Layout,
    compressed: bool,
    detached: bool,
) -> PathBuf {
    let p = placement_or_identity(v);
    let s = v.spacing();
    let d = v.dims();
    let ty = match layout {
        Layout::U8 => "MET_UCHAR",
        Layout::I8 => "MET_CHAR",
        Layout::U16 => "MET_USHORT",
        Layout::I16 => "MET_SHORT",
        Layout::F32 => "MET_FLOAT",
    };
    let m = p.directions;
    let mut data = samples(v, layout, 1.0, 0.0);
    if compressed {
        let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        z.write_all(&data).unwrap();
        data = z.finish().unwrap();
    }
    let mut h = String::from("ObjectType = Image\nNDims = 3\nBinaryData = True\n");
    h += "BinaryDataByteOrderMSB = False\n";
    h += &format!(
        "CompressedData = {}\n",
        if compressed { "True" } else { "False" }
    );
    if compressed {
        h += &format!("CompressedDataSize = {}\n", data.len());
    }
    h += &format!(
        "TransformMatrix = {} {} {} {} {} {} {} {} {}\n",
        m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2]
    );
    h += &format!("Offset = {} {} {}\n", p.origin[0], p.origin[1], p.origin[2]);
    h += "CenterOfRotation = 0 0 0\nAnatomicalOrientation = RAI\n";
    h += &format!("ElementSpacing = {} {} {}\n", s[0], s[1], s[2]);
    h += &format!("DimSize = {} {} {}\n", d[0], d[1], d[2]);
    if v.channel_count() == 3 {
        h += "ElementNumberOfChannels = 3\n";
    }
    h += &format!("ElementType = {ty}\n");
    if detached {
        let data_name = format!("{name}.raw");
        h += &format!("ElementDataFile = {data_name}\n");
        std::fs::write(dir.join(&data_name), data).unwrap();
        let path = dir.join(format!("{name}.mhd"));
        std::fs::write(&path, h).unwrap();
        path
    } else {
        h += "ElementDataFile = LOCAL\n";
        let mut bytes = h.into_bytes();
        bytes.extend_from_slice(&data);
        let path = dir.join(format!("{name}.mha"));
        std::fs::write(&path, bytes).unwrap();
        path
    }
}

/// How a DICOM fixture is encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DicomEncoding {
    /// Explicit VR Little Endian, native pixel data.
    ExplicitLittle,
    /// Implicit VR Little Endian, native pixel data.
    ImplicitLittle,
    /// RLE Lossless (encapsulated; one fragment per frame).
    RleLossless,
}

/// Options of the DICOM fixtures.
#[derive(Debug, Clone)]
pub struct DicomOptions {
    /// Stored sample type (8 or 16 bits, signed or not).
    pub layout: Layout,
    /// Rescale Slope.
    pub slope: f64,
    /// Rescale Intercept.
    pub intercept: f64,
    /// Series Instance UID.
    pub series_uid: String,
    /// Transfer syntax.
    pub encoding: DicomEncoding,
    /// In-plane shift (mm, LPS) added per slice to Image Position (Patient), to forge a
    /// sheared (gantry-tilted) series.
    pub shear: [f64; 3],
}

impl Default for DicomOptions {
    fn default() -> Self {
        DicomOptions {
            layout: Layout::I16,
            slope: 1.0,
            intercept: 0.0,
            series_uid: "1.2.826.0.1.3680043.9.7433.1.1".into(),
            encoding: DicomEncoding::ExplicitLittle,
            shear: [0.0; 3],
        }
    }
}

fn ds(v: f64) -> String {
    // Decimal strings are at most 16 characters; values that are f32 print as f32 (shortest).
    let f = v as f32;
    let s = if f64::from(f) == v {
        format!("{f}")
    } else {
        format!("{v}")
    };
    if s.len() <= 16 {
        s
    } else {
        format!("{v:.10e}")
    }
}

fn ds_list(v: &[f64]) -> String {
    v.iter().map(|x| ds(*x)).collect::<Vec<_>>().join("\\")
}

fn elem(
    tag: dicom_core::Tag,
    vr: VR,
    v: impl Into<PrimitiveValue>,
) -> DataElement<InMemDicomObject> {
    DataElement::new(tag, vr, DicomValue::from(v.into()))
}

/// The attributes shared by every fixture image; `frames` > 1 makes a multi-frame object.
fn image_base(v: &Volume, o: &DicomOptions, sop_uid: &str, frames: usize) -> InMemDicomObject {
    let d = v.dims();
    let s = v.spacing();
    let bits = (o.layout.bytes() * 8) as u16;
    assert!(matches!(
        o.layout,
        Layout::U8 | Layout::I8 | Layout::U16 | Layout::I16
    ));
    let mut obj = InMemDicomObject::from_element_iter([
        elem(tags::SOP_CLASS_UID, VR::UI, uids::CT_IMAGE_STORAGE),
        elem(tags::SOP_INSTANCE_UID, VR::UI, sop_uid),
        elem(tags::MODALITY, VR::CS, "CT"),
        elem(
            tags::STUDY_INSTANCE_UID,
            VR::UI,
            "1.2.826.0.1.3680043.9.7433.2",
        ),
        elem(tags::SERIES_INSTANCE_UID, VR::UI, o.series_uid.as_str()),
        elem(
            tags::SAMPLES_PER_PIXEL,
            VR::US,
            PrimitiveValue::from(v.channel_count() as u16),
        ),
        elem(
            tags::PHOTOMETRIC_INTERPRETATION,
            VR::CS,
            if v.channel_count() == 3 {
                "RGB"
            } else {
                "MONOCHROME2"
            },
        ),
        elem(tags::ROWS, VR::US, PrimitiveValue::from(d[1] as u16)),
        elem(tags::COLUMNS, VR::US, PrimitiveValue::from(d[0] as u16)),
        elem(tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(bits)),
        elem(tags::BITS_STORED, VR::US, PrimitiveValue::from(bits)),
        elem(tags::HIGH_BIT, VR::US, PrimitiveValue::from(bits - 1)),
        elem(
            tags::PIXEL_REPRESENTATION,
            VR::US,
            PrimitiveValue::from(u16::from(o.layout.signed())),
        ),
        elem(
            tags::PIXEL_SPACING,
            VR::DS,
            ds_list(&[f64::from(s[1]), f64::from(s[0])]),
        ),
        elem(tags::SLICE_THICKNESS, VR::DS, ds(f64::from(s[2]))),
    ]);
    if v.channel_count() == 3 {
        obj.put(elem(
            tags::PLANAR_CONFIGURATION,
            VR::US,
            PrimitiveValue::from(0u16),
        ));
    } else {
        obj.put(elem(tags::RESCALE_SLOPE, VR::DS, ds(o.slope)));
        obj.put(elem(tags::RESCALE_INTERCEPT, VR::DS, ds(o.intercept)));
    }
    if frames > 1 {
        obj.put(elem(tags::NUMBER_OF_FRAMES, VR::IS, frames.to_string()));
    }
    obj
}

fn pixel_element(
    frames: Vec<Vec<u8>>,
    o: &DicomOptions,
    samples: usize,
) -> DataElement<InMemDicomObject> {
    match o.encoding {
        DicomEncoding::RleLossless => {
            let fragments: Vec<Vec<u8>> = frames
                .iter()
                .map(|f| rle_frame(f, o.layout.bytes(), samples))
                .collect();
            DataElement::new(
                tags::PIXEL_DATA,
                VR::OB,
                DicomValue::from(PixelFragmentSequence::new(Vec::<u32>::new(), fragments)),
            )
        }
        _ => {
            let mut all: Vec<u8> = frames.concat();
            if o.layout.bytes() == 2 {
                let words: Vec<u16> = all
                    .chunks_exact(2)
                    .map(|c| u16::from_le_bytes([c[0], c[1]]))
                    .collect();
                DataElement::new(tags::PIXEL_DATA, VR::OW, PrimitiveValue::U16(words.into()))
            } else {
                if all.len() % 2 == 1 {
                    all.push(0);
                }
                DataElement::new(tags::PIXEL_DATA, VR::OB, PrimitiveValue::U8(all.into()))
            }
        }
    }
}

/// One RLE Lossless frame (PS3.5 Annex G) of interleaved samples: a segment per sample and
/// byte plane (each sample's most significant first), each PackBits-coded as literal runs of
/// at most 128 bytes.
pub fn rle_frame(frame: &[u8], bytes_per_sample: usize, samples: usize) -> Vec<u8> {
    let n = frame.len() / (bytes_per_sample * samples);
    let mut segments = Vec::new();
    for (c, plane) in (0..samples).flat_map(|c| (0..bytes_per_sample).rev().map(move |p| (c, p))) {
        let data: Vec<u8> = (0..n)
            .map(|i| frame[(i * samples + c) * bytes_per_sample + plane])
            .collect();
        let mut seg = Vec::new();
        for chunk in data.chunks(128) {
            seg.push((chunk.len() - 1) as u8);
            seg.extend_from_slice(chunk);
        }
        if seg.len() % 2 == 1 {
            seg.push(0);
        }
        segments.push(seg);
    }
    let mut out = vec![0u8; 64];
    out[0..4].copy_from_slice(&(segments.len() as u32).to_le_bytes());
    let mut offset = 64u32;
    for (i, s) in segments.iter().enumerate() {
        out[4 + 4 * i..8 + 4 * i].copy_from_slice(&offset.to_le_bytes());
        offset += s.len() as u32;
    }
    for s in segments {
        out.extend_from_slice(&s);
    }
    out
}

fn save(obj: InMemDicomObject, o: &DicomOptions, path: &Path) {
    let ts = match o.encoding {
        DicomEncoding::ExplicitLittle => uids::EXPLICIT_VR_LITTLE_ENDIAN,
        DicomEncoding::ImplicitLittle => uids::IMPLICIT_VR_LITTLE_ENDIAN,
        DicomEncoding::RleLossless => uids::RLE_LOSSLESS,
    };
    let file = obj
        .with_meta(FileMetaTableBuilder::new().transfer_syntax(ts))
        .unwrap();
    file.write_to_file(path).unwrap();
}

fn frame_bytes(v: &Volume, o: &DicomOptions, z: usize) -> Vec<u8> {
    let d = v.dims();
    let per = d[0] * d[1];
    let c = v.channel_count();
    let (slope, intercept) = if c == 3 {
        (1.0, 0.0)
    } else {
        (o.slope, o.intercept)
    };
    let mut out = Vec::with_capacity(per * c * o.layout.bytes());
    for i in z * per..(z + 1) * per {
        for ch in 0..c {
            o.layout
                .encode((f64::from(v.channel(ch)[i]) - intercept) / slope, &mut out);
        }
    }
    out
}

/// Writes `v` as a DICOM series, one file per z slice, into `dir` (file names in a shuffled
/// order, so readers must sort by position, not by name); returns the files.
pub fn write_dicom_series(dir: &Path, v: &Volume, o: &DicomOptions) -> Vec<PathBuf> {
    std::fs::create_dir_all(dir).unwrap();
    let p = placement_or_identity(v);
    let s = v.spacing();
    let nz = v.dims()[2];
    let mut out = Vec::new();
    for z in 0..nz {
        let mut pos = p.position(s, [0.0, 0.0, z as f64]);
        for c in 0..3 {
            pos[c] += o.shear[c] * z as f64;
        }
        let mut obj = image_base(v, o, &format!("{}.{}", o.series_uid, z + 1), 1);
        obj.put(elem(tags::INSTANCE_NUMBER, VR::IS, (z + 1).to_string()));
        obj.put(elem(tags::IMAGE_POSITION_PATIENT, VR::DS, ds_list(&pos)));
        let r = p.directions;
        obj.put(elem(
            tags::IMAGE_ORIENTATION_PATIENT,
            VR::DS,
            ds_list(&[r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2]]),
        ));
        obj.put(pixel_element(
            vec![frame_bytes(v, o, z)],
            o,
            v.channel_count(),
        ));
        // Names that do not sort by position.
        let path = dir.join(format!("IM{:04}", (z * 7919) % 10007));
        save(obj, o, &path);
        out.push(path);
    }
    out
}

/// Writes `v` as one multi-frame DICOM file (one frame per z slice) with the geometry in the
/// enhanced functional groups (shared pixel measures and orientation, a plane position per
/// frame); returns the path.
pub fn write_dicom_multiframe(path: &Path, v: &Volume, o: &DicomOptions) -> PathBuf {
    let p = placement_or_identity(v);
    let s = v.spacing();
    let nz = v.dims()[2];
    let mut obj = image_base(v, o, &format!("{}.1", o.series_uid), nz);
    let r = p.directions;
    let item = |e: Vec<DataElement<InMemDicomObject>>| InMemDicomObject::from_element_iter(e);
    let seq = |tag, items: Vec<InMemDicomObject>| {
        DataElement::new(tag, VR::SQ, DataSetSequence::new(items, Length::UNDEFINED))
    };
    let shared = item(vec![
        seq(
            tags::PIXEL_MEASURES_SEQUENCE,
            vec![item(vec![
                elem(
                    tags::PIXEL_SPACING,
                    VR::DS,
                    ds_list(&[f64::from(s[1]), f64::from(s[0])]),
                ),
                elem(tags::SLICE_THICKNESS, VR::DS, ds(f64::from(s[2]))),
            ])],
        ),
        seq(
            tags::PLANE_ORIENTATION_SEQUENCE,
            vec![item(vec![elem(
                tags::IMAGE_ORIENTATION_PATIENT,
                VR::DS,
                ds_list(&[r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2]]),
            )])],
        ),
    ]);
    obj.put(seq(tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE, vec![shared]));
    let per_frame: Vec<InMemDicomObject> = (0..nz)
        .map(|z| {
            let pos = p.position(s, [0.0, 0.0, z as f64]);
            item(vec![seq(
                tags::PLANE_POSITION_SEQUENCE,
                vec![item(vec![elem(
                    tags::IMAGE_POSITION_PATIENT,
                    VR::DS,
                    ds_list(&pos),
                )])],
            )])
        })
        .collect();
    obj.put(seq(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE, per_frame));
    let frames: Vec<Vec<u8>> = (0..nz).map(|z| frame_bytes(v, o, z)).collect();
    obj.put(pixel_element(frames, o, v.channel_count()));
    save(obj, o, path);
    path.to_path_buf()
}
