//! The one place where a job's options (the orchestrator's domain types, validated at
//! submission) become the compressor's: [`compress_options`] and [`raw_spec`].

use wavesplat_compressor::colorspace::ColorSpaceKind;
use wavesplat_compressor::encode::{CompressOptions, Target, TileChoice};
use wavesplat_compressor::reader::{Endian, RawDtype, RawSpec};
use wavesplat_compressor::refine::RefineOptions;
use wavesplat_orchestrator_client::model::{
    ColorSpace, JobOptions, RawLayout, SampleType, TargetSpec,
};

/// The compressor's options for a job.
pub fn compress_options(o: &JobOptions) -> CompressOptions {
    let d = CompressOptions::default();
    CompressOptions {
        family: o.family,
        levels: o.levels,
        colorspace: match o.colorspace {
            ColorSpace::Rgb => ColorSpaceKind::Rgb,
            ColorSpace::Yiq => ColorSpaceKind::Yiq,
            ColorSpace::Pca => ColorSpaceKind::Pca,
        },
        bits: o.bits,
        coder: o.coder,
        target: match o.target {
            TargetSpec::Fraction(f) => Target::Fraction(f),
            TargetSpec::Bytes(b) => Target::Bytes(b),
            TargetSpec::Coefficients(c) => Target::Coefficients(c),
            TargetSpec::QvPercent(q) => Target::QvPercent(q),
            TargetSpec::All => Target::All,
        },
        tile: o.tile.map_or(TileChoice::Auto, TileChoice::Size),
        layers: o.layers,
        layer_growth: o.layer_growth.unwrap_or(d.layer_growth),
        step: o.step,
        refine: (!o.no_refine).then(|| RefineOptions {
            rounds: o.refine_rounds.unwrap_or(RefineOptions::default().rounds),
            ..RefineOptions::default()
        }),
        ..d
    }
}

/// The raw reader's spec for a job's layout.
pub fn raw_spec(l: &RawLayout) -> RawSpec {
    let dtype = match l.dtype {
        SampleType::U8 => RawDtype::U8,
        SampleType::U16 => RawDtype::U16,
        SampleType::I16 => RawDtype::I16,
        SampleType::F32 => RawDtype::F32,
    };
    let mut spec = RawSpec::new(l.dims, dtype);
    spec.endian = if l.big_endian {
        Endian::Big
    } else {
        Endian::Little
    };
    spec.channels = l.channels;
    spec
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_job_options_are_the_compressors_defaults() {
        let got = compress_options(&JobOptions::default());
        let want = CompressOptions::default();
        assert_eq!(got, want);
    }

    #[test]
    fn every_name_maps_to_the_compressor_and_reader() {
        for name in ["rgb", "yiq", "pca"] {
            let o = JobOptions {
                colorspace: ColorSpace::from_name(name).unwrap(),
                ..JobOptions::default()
            };
            assert_eq!(compress_options(&o).colorspace.name(), name);
        }
        for name in SampleType::names() {
            let l = RawLayout {
                dims: [2, 3, 4],
                dtype: SampleType::from_name(name).unwrap(),
                big_endian: true,
                channels: 3,
            };
            let s = raw_spec(&l);
            assert_eq!(s.dtype.name(), *name);
            assert_eq!(s.dtype.size(), l.dtype.size());
            assert_eq!((s.dims, s.channels, s.endian), ([2, 3, 4], 3, Endian::Big));
        }
        let o = JobOptions {
            no_refine: true,
            target: TargetSpec::Bytes(1000),
            tile: Some(8),
            ..JobOptions::default()
        };
        let c = compress_options(&o);
        assert!(c.refine.is_none());
        assert!(matches!(c.target, Target::Bytes(1000)));
        assert!(matches!(c.tile, TileChoice::Size(8)));
    }
}
