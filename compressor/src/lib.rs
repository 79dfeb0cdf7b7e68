//! The offline batch compressor (paper §4): reads a volume, decorrelates colour, runs the 3D
//! wavelet transform, selects coefficients with the energy oracle, orders them by significance
//! with spatial clustering, quantizes and entropy-codes them into tiles and packets of the
//! wavesplat format (`wavesplat-codec`). Work is parallel on the rayon pool; results do not
//! depend on the number of threads.

pub mod bricked;
pub mod checkpoint;
pub mod colorspace;
pub mod decode;
pub mod encode;
pub mod order;
pub mod phantom;
pub mod reader;
pub mod refine;
pub mod scratch;
mod select;
pub mod series;
pub mod visible;
