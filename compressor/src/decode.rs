//! Full decompression back to a volume, for checks and metrics (the viewer never does this: it
//! renders from the coefficients). Decodes every packet, places the coefficients in per-channel
//! coefficient arrays, runs the inverse 3D transform, crops the padding and undoes the colour
//! transform.

use crate::colorspace::{ColorSpaceKind, ColorTransform};
use wavesplat_codec::dwt::{coefficients_to_samples, crop_channel, inverse_3d, Dwt1d};
use wavesplat_codec::format::packet::{decode_packets, Coefficient, PacketError};
use wavesplat_codec::format::{parse_file, ColorKind, FormatError, Header};
use wavesplat_codec::volume::{Volume, VolumeError};

/// Errors of decompression.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DecodeError {
    /// The bitstream is malformed.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// A packet is malformed.
    #[error(transparent)]
    Packet(#[from] PacketError),
    /// The colour transform in the header could not be inverted.
    #[error("colour transform: {0}")]
    Color(#[from] crate::colorspace::ColorError),
    /// The result is not a valid volume (non-finite values from extreme coefficients).
    #[error("decoded volume is invalid: {0}")]
    Volume(#[from] VolumeError),
}

/// Decodes all packets of a file (in parallel: each packet decodes on its own): the header and
/// every coefficient (file order).
pub fn decode_coefficients(bytes: &[u8]) -> Result<(Header, Vec<Coefficient>), DecodeError> {
    let file = parse_file(bytes)?;
    let packets = decode_packets(&file.header, &file.packets, 0)?;
    Ok((file.header, packets.concat()))
}

/// Reconstructs the volume from a header and coefficients.
pub fn reconstruct(header: &Header, coefficients: &[Coefficient]) -> Result<Volume, DecodeError> {
    let g = &header.geometry;
    let mut planner = Dwt1d::new(g.family);
    let mut channels = Vec::with_capacity(header.channels);
    for c in 0..header.channels {
        let mut data = vec![0.0f64; g.coefficient_count()];
        for k in coefficients.iter().filter(|k| k.channel as usize == c) {
            let pos = [k.pos[0] as usize, k.pos[1] as usize, k.pos[2] as usize];
            data[g.linear_index(k.band, pos)] = k.value as f64;
        }
        inverse_3d(&mut data, g, &mut planner);
        coefficients_to_samples(&mut data, g);
        channels.push(crop_channel(&data, g));
    }
    let mut coded = Volume::new(g.dims, header.spacing, channels)?;
    if let Some(p) = header.placement {
        coded = coded.with_placement(p)?;
    }
    if header.channels == 1 {
        return Ok(coded);
    }
    let t = ColorTransform {
        kind: match header.color.kind {
            ColorKind::Yiq => ColorSpaceKind::Yiq,
            ColorKind::Pca => ColorSpaceKind::Pca,
            _ => ColorSpaceKind::Rgb,
        },
        basis: header.color.basis,
        mean: header.color.mean,
        importance: header.color.importance,
    };
    Ok(t.inverse(&coded)?)
}

/// Decodes a whole `.wsp` file to a volume.
pub fn decompress(bytes: &[u8]) -> Result<Volume, DecodeError> {
    let (header, coefficients) = decode_coefficients(bytes)?;
    reconstruct(&header, &coefficients)
}
