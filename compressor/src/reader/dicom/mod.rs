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
//! Untrusted input: frame sizes are checked against
//! [`MAX_VOXELS`](wavesplat_codec::volume::MAX_VOXELS), against the file's size (at most
//! [`MAX_FILE_EXPANSION`]× it) before any per-frame work, and against the pixel data
//! present before decoding, encapsulated frames may not expand beyond [`MAX_EXPANSION`] × their
//! compressed bytes, and a panic inside the DICOM crates is caught and reported as an error on
//! the file.

use std::path::{Path, PathBuf};

use dicom_core::Tag;
use dicom_dictionary_std::tags;

use super::ReadError;
use colour::Palette;

// One file a job: `series` finds the files and assembles the volume (the entry points),
// `walk` checks element lengths and parses, `attributes` reads values, `image` describes
// one file's image, `geometry` orders and places the frames, `pixels` decodes them, and
// `colour` converts palettes and YBR to RGB.
mod attributes;
mod colour;
mod geometry;
mod image;
mod pixels;
mod series;
mod walk;

pub(crate) use series::{decode, series_files, SeriesRegions};
pub use series::{is_dicom_file, read_cine_file, read_time_series, TimeSeries};
pub(crate) use walk::has_preamble;

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
    /// Time, else Acquisition Time (named by `time_attribute`).
    time: Option<String>,
    time_attribute: &'static str,
    /// Photometric Interpretation as the file states it.
    photometric: String,
    /// The colour palette of a PALETTE COLOR image.
    palette: Option<std::sync::Arc<Palette>>,
    /// Per frame, of an enhanced multi-frame file with a temporal dimension: its Temporal
    /// Position Index (`None` when frames do not have one each, or all share one).
    temporal_index: Option<Vec<u32>>,
    /// Per frame: Nominal Cardiac Trigger Delay Time, ms (when every frame has one).
    trigger_delay_ms: Option<Vec<f64>>,
    /// The frames of this file that belong to the volume being read (`None`: all): one time
    /// point of an enhanced multi-frame series.
    selected: Option<Vec<usize>>,
}

impl Image {
    /// The frames read into the volume, in file order.
    fn frame_list(&self) -> Vec<usize> {
        match &self.selected {
            Some(s) => s.clone(),
            None => (0..self.frames).collect(),
        }
    }

    /// Channels of the volume: three for a palette image (its colours), else the samples.
    fn channels(&self) -> usize {
        if self.palette.is_some() {
            3
        } else {
            self.samples
        }
    }
}

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

#[cfg(test)]
mod tests;
