//! Rendering one time point of a series container ([`wavesplat_codec::format::series`]): a time
//! point is a weighted sum of components that each span the whole volume, and an X-ray image
//! (depth cued or not) is linear in the data, so its image is the same weighted sum of the
//! components' images, each drawn by the ordinary path for its file (a plain file whole, a
//! bricked container brick by brick, [`crate::bricked`]). Only the components the time point
//! names are checked, decoded and drawn.

use crate::backend::AccumulationBackend;
use crate::bricked::{draw_bricked_file, parse_with_first, whole_header, BrickedError};
use crate::open::{draw_whole_file, OpenError};
use crate::Image;
use wavesplat_codec::format::bricked::is_bricked;
use wavesplat_codec::format::series::{parse_series, SeriesFile};
use wavesplat_codec::format::{parse_file, FormatError, Header};
use wavesplat_codec::view::ViewSpec;

pub use wavesplat_codec::view::bricked::series_header;

/// What drawing a time point made.
#[derive(Debug)]
pub struct SeriesImage {
    /// The image in display space.
    pub image: Image,
    /// Components drawn.
    pub components: usize,
    /// Their bytes.
    pub bytes: u64,
    /// Coefficients splatted over them.
    pub coefficients: usize,
}

/// Why a time point cannot be drawn.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SeriesDrawError {
    /// The container is not valid.
    #[error("reading the series")]
    Format(#[from] FormatError),
    /// The series has no such time point.
    #[error("time point {asked}: the series has {points} (0..={})", points - 1)]
    NoTimePoint {
        /// The time point asked for.
        asked: usize,
        /// Time points in the series.
        points: usize,
    },
    /// A bricked component could not be drawn.
    #[error("drawing component {component}")]
    Bricked {
        /// The component.
        component: usize,
        /// Why.
        #[source]
        source: Box<BrickedError>,
    },
    /// A plain component could not be drawn.
    #[error("drawing component {component}")]
    Plain {
        /// The component.
        component: usize,
        /// Why.
        #[source]
        source: Box<OpenError>,
    },
    /// A component is not of the series' dimensions or channels.
    #[error("component {component} is {found}; the series is {expected}")]
    Mismatch {
        /// The component.
        component: usize,
        /// What it is.
        found: String,
        /// What the series is.
        expected: String,
    },
}

/// Refuses component `c` whose (whole) header is not the series' space.
fn check_component(
    file: &SeriesFile<'_>,
    c: usize,
    header: &Header,
) -> Result<(), SeriesDrawError> {
    let s = &file.manifest.space;
    let dims = s.dims.map(|d| d as usize);
    if header.geometry.dims != dims || header.channels != s.channels {
        return Err(SeriesDrawError::Mismatch {
            component: c,
            found: format!(
                "{:?} with {} channel(s)",
                header.geometry.dims, header.channels
            ),
            expected: format!("{dims:?} with {}", s.channels),
        });
    }
    Ok(())
}

/// Draws time point `t` of a series container's `bytes` for `spec` with `backend`.
pub fn draw_series_point(
    bytes: &[u8],
    t: usize,
    spec: &ViewSpec,
    backend: &mut dyn AccumulationBackend,
) -> Result<SeriesImage, SeriesDrawError> {
    let file = parse_series(bytes)?;
    let points = file.manifest.points.len();
    let point = file
        .manifest
        .points
        .get(t)
        .ok_or(SeriesDrawError::NoTimePoint { asked: t, points })?;
    let mut total: Option<Image> = None;
    let (mut drawn_bytes, mut coefficients) = (0u64, 0usize);
    for &(c, weight) in &point.terms {
        let data = file.component_bytes(c)?;
        drawn_bytes += data.len() as u64;
        let image = if is_bricked(data) {
            let (f, first) = parse_with_first(data).map_err(|e| SeriesDrawError::Bricked {
                component: c,
                source: Box::new(e),
            })?;
            check_component(&file, c, &whole_header(&f.manifest, &first))?;
            let d =
                draw_bricked_file(data, spec, backend).map_err(|e| SeriesDrawError::Bricked {
                    component: c,
                    source: Box::new(e),
                })?;
            coefficients += d.coefficients;
            d.image
        } else {
            check_component(&file, c, &parse_file(data)?.header)?;
            let d = draw_whole_file(data, spec, backend).map_err(|e| SeriesDrawError::Plain {
                component: c,
                source: Box::new(e),
            })?;
            coefficients += d.coefficients;
            d.image
        };
        match &mut total {
            None => {
                let mut image = image;
                image.data.iter_mut().for_each(|v| *v *= weight);
                total = Some(image);
            }
            Some(sum) => sum
                .data
                .iter_mut()
                .zip(&image.data)
                .for_each(|(s, v)| *s += weight * v),
        }
    }
    Ok(SeriesImage {
        image: total.expect("a time point names at least one component"),
        components: point.terms.len(),
        bytes: drawn_bytes,
        coefficients,
    })
}
