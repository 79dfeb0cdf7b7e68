//! Attribute access: the getters every reader of values goes through. An attribute written as
//! `UN` is decoded again as the VR the standard dictionary gives it, a blank value reads as
//! absent, numbers are checked finite, and an enhanced multi-frame file's attributes are found
//! per frame in its functional groups (per-frame item, then shared, then the top level).

use std::path::Path;

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use dicom_object::{DefaultDicomObject, InMemDicomObject};

use super::dicom_err;
use crate::reader::ReadError;

/// The transfer syntax UID of `obj`, without the NUL that pads it to an even length.
pub(super) fn transfer_syntax(obj: &DefaultDicomObject) -> &str {
    obj.meta().transfer_syntax().trim_end_matches('\0')
}

/// Replaces the top-level elements written as `UN` whose attributes the standard dictionary
/// knows by their standard VR ([`value_element`]), so that the pixel data decoder, which reads
/// Rows, Columns, Bits Allocated and the rest itself, sees them too.
pub(super) fn known_vrs(obj: &mut DefaultDicomObject) {
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

pub(super) fn element(
    obj: &InMemDicomObject,
    tag: Tag,
) -> Option<&dicom_object::mem::InMemElement> {
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

pub(super) fn get_str(obj: &InMemDicomObject, tag: Tag) -> Option<String> {
    value_element(obj, tag)
        .and_then(|e| e.to_str().ok().map(|s| s.into_owned()))
        .map(|s| {
            s.trim_matches(|c: char| c == '\0' || c.is_whitespace())
                .to_string()
        })
        .filter(|s| !s.is_empty())
}

pub(super) fn get_floats(
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

pub(super) fn get_uint(
    path: &Path,
    obj: &InMemDicomObject,
    tag: Tag,
) -> Result<Option<u32>, ReadError> {
    let Some(e) = value_element(obj, tag) else {
        return Ok(None);
    };
    e.to_int::<u32>()
        .map(Some)
        .map_err(|x| dicom_err(path, Some(tag), format!("not a non-negative integer: {x}")))
}

pub(super) fn require_uint(
    path: &Path,
    obj: &InMemDicomObject,
    tag: Tag,
) -> Result<u32, ReadError> {
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

pub(super) fn floats_for_frame(
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
