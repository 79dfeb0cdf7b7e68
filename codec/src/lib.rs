//! The wavesplat format shared by the compressor (writer), the cache and the viewer (readers).
//!
//! It owns what both sides must agree on bit for bit: the [`volume::Volume`] type, the
//! Chui–Wang semi-orthogonal B-spline wavelet families with their filters and closed-form
//! Fourier transforms ([`family`]), the periodic 3D non-standard wavelet transform and the
//! coefficient addressing ([`dwt`], [`layout`]), the entropy coders ([`entropy`]), the versioned
//! bitstream of header, tiles and self-contained packets with their decoder ([`format`]), the view
//! geometry that renderer, cache and client share ([`view`]: views, cameras, depth cue,
//! multiview, visibility weights) and the quality metrics of the paper ([`metrics`]). It has no dependency on async runtimes, GPUs or RPC code; rayon is an
//! optional feature that only changes how independent lines of the transform are scheduled.
//!
//! ```
//! use wavesplat_codec::family::Family;
//! // The linear Chui–Wang wavelet is built from 5 fine-scale hats (eq. 6 of the paper).
//! assert_eq!(Family::Linear.wavelet_filter().len(), 5);
//! ```

#[cfg(feature = "transform")]
pub mod dwt;
pub mod entropy;
pub mod family;
pub mod format;
pub mod layout;
pub mod metrics;
pub mod view;
pub mod volume;
