//! Full decompression back to a volume, for checks and metrics (the viewer never does this: it
//! renders from the coefficients). Decodes every packet, places the coefficients in per-channel
//! coefficient arrays, runs the inverse 3D transform, crops the padding and undoes the colour
//! transform (or adds an intensity volume's offset back). Every entry point has a `_within` form taking a [`DecodeBudget`]: what the file
//! declares (coefficients, the reconstruction's memory) is checked against it before anything is
//! allocated, so a tiny file declaring a huge volume is an error, not an abort.

use crate::colorspace::{ColorSpaceKind, ColorTransform};
use wavesplat_codec::dwt::{coefficients_to_samples, crop_channel, inverse_3d, Dwt1d};
use wavesplat_codec::format::packet::{
    decode_packets_within, Coefficient, DecodeBudget, PacketError,
};
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
/// every coefficient (file order), within the default budget.
pub fn decode_coefficients(bytes: &[u8]) -> Result<(Header, Vec<Coefficient>), DecodeError> {
    decode_coefficients_within(bytes, &DecodeBudget::default())
}

/// [`decode_coefficients`] within `budget` (all packets together).
pub fn decode_coefficients_within(
    bytes: &[u8],
    budget: &DecodeBudget,
) -> Result<(Header, Vec<Coefficient>), DecodeError> {
    let file = parse_file(bytes)?;
    let packets = decode_packets_within(&file.header, &file.packets, 0, budget)?.concat();
    wavesplat_codec::format::check_kept(&file.header, packets.len() as u64)?;
    Ok((file.header, packets))
}

/// Bytes of memory [`reconstruct`] allocates for the volume of `header`: one channel's
/// coefficient grid in f64 at a time, and the decoded and colour-transformed samples in f32.
pub fn reconstruction_bytes(header: &Header) -> u64 {
    let g = &header.geometry;
    let grid = (g.coefficient_count() as u64).saturating_mul(8);
    let voxels = g
        .dims
        .iter()
        .map(|&d| d as u64)
        .fold(1u64, u64::saturating_mul);
    let samples = voxels
        .saturating_mul(header.channels as u64)
        .saturating_mul(4);
    grid.saturating_add(samples.saturating_mul(2))
}

/// Reconstructs the volume from a header and coefficients, within the default budget.
pub fn reconstruct(header: &Header, coefficients: &[Coefficient]) -> Result<Volume, DecodeError> {
    reconstruct_within(header, coefficients, &DecodeBudget::default())
}

/// [`reconstruct`], refusing a volume whose reconstruction needs more memory than `budget`.
pub fn reconstruct_within(
    header: &Header,
    coefficients: &[Coefficient],
    budget: &DecodeBudget,
) -> Result<Volume, DecodeError> {
    budget.check_bytes(reconstruction_bytes(header))?;
    let g = &header.geometry;
    let mut planner = Dwt1d::new(g.family);
    // An intensity volume was coded less its offset (zero for files without one).
    let offset = if header.channels == 1 {
        header.color.mean[0]
    } else {
        0.0
    };
    let mut channels = Vec::with_capacity(header.channels);
    for c in 0..header.channels {
        let mut data = vec![0.0f64; g.coefficient_count()];
        for k in coefficients.iter().filter(|k| k.channel as usize == c) {
            let pos = [k.pos[0] as usize, k.pos[1] as usize, k.pos[2] as usize];
            data[g.linear_index(k.band, pos)] = k.value as f64;
        }
        inverse_3d(&mut data, g, &mut planner);
        coefficients_to_samples(&mut data, g);
        let mut samples = crop_channel(&data, g);
        if offset != 0.0 {
            samples
                .iter_mut()
                .for_each(|v| *v = (f64::from(*v) + offset) as f32);
        }
        channels.push(samples);
    }
    let mut coded = Volume::new(g.dims, header.spacing(), channels)?;
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

/// Decodes a whole `.wsp` file to a volume, within the default budget.
pub fn decompress(bytes: &[u8]) -> Result<Volume, DecodeError> {
    decompress_within(bytes, &DecodeBudget::default())
}

/// Decodes a whole `.wsp` file to a volume within `budget`: the reconstruction's memory is
/// checked from the header before any packet is decoded.
pub fn decompress_within(bytes: &[u8], budget: &DecodeBudget) -> Result<Volume, DecodeError> {
    let file = parse_file(bytes)?;
    budget.check_bytes(reconstruction_bytes(&file.header))?;
    let (header, coefficients) = decode_coefficients_within(bytes, budget)?;
    reconstruct_within(&header, &coefficients, budget)
}
