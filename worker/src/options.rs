//! The one place where a job's options (the orchestrator's domain types, validated at
//! submission) become the compressor's: [`compress_options`] and [`raw_spec`].

use wavesplat_compressor::colorspace::ColorSpaceKind;
use wavesplat_compressor::encode::{CompressOptions, Effort, Target, TileChoice};
use wavesplat_compressor::reader::{Endian, RawDtype, RawSpec};
use wavesplat_orchestrator_client::model::{
    self, ColorSpace, JobOptions, RawLayout, SampleType, TargetSpec,
};

/// The compressor's options for a job.
pub fn compress_options(o: &JobOptions) -> CompressOptions {
    let d = CompressOptions::default();
    let effort = effort(o.effort);
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
        depth_search: effort.depth_search(),
        refine: effort.refine_with(o.no_refine, o.refine_rounds, None),
        memory_limit: o.memory_limit,
        ..d
    }
}

/// The compressor's effort of a job's.
pub fn effort(e: model::Effort) -> Effort {
    match e {
        model::Effort::Fast => Effort::Fast,
        model::Effort::Default => Effort::Default,
        model::Effort::Best => Effort::Best,
    }
}

/// The raw reader's spec for a job's layout.
pub fn raw_spec(l: &RawLayout) -> RawSpec {
    let dtype = match l.dtype {
        SampleType::U8 => RawDtype::U8,
        SampleType::I8 => RawDtype::I8,
        SampleType::U16 => RawDtype::U16,
        SampleType::I16 => RawDtype::I16,
        SampleType::U32 => RawDtype::U32,
        SampleType::I32 => RawDtype::I32,
        SampleType::U64 => RawDtype::U64,
        SampleType::I64 => RawDtype::I64,
        SampleType::F32 => RawDtype::F32,
        SampleType::F64 => RawDtype::F64,
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
    fn every_sample_type_of_a_job_is_the_raw_readers_of_its_name_and_size() {
        for name in SampleType::names() {
            let t = SampleType::from_name(name).unwrap();
            let layout = RawLayout {
                dims: [2, 3, 4],
                dtype: t,
                big_endian: false,
                channels: 1,
            };
            let spec = raw_spec(&layout);
            assert_eq!(spec.dtype.name(), *name);
            assert_eq!(spec.dtype.size(), t.size(), "{name}");
            assert_eq!(RawDtype::from_name(name).unwrap(), spec.dtype);
        }
        assert_eq!(SampleType::names().len(), RawDtype::names().len());
    }

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

    /// A job's effort gives the compressor's options of that effort, and the job's refinement
    /// flags still override it.
    #[test]
    fn a_jobs_effort_is_the_compressors() {
        for e in [
            model::Effort::Fast,
            model::Effort::Default,
            model::Effort::Best,
        ] {
            let o = JobOptions {
                effort: e,
                ..JobOptions::default()
            };
            let want = effort(e).options();
            let got = compress_options(&o);
            assert_eq!(
                (got.depth_search, got.refine),
                (want.depth_search, want.refine)
            );
            assert_eq!(effort(e).name(), e.name());
        }
        let fast_refined = JobOptions {
            effort: model::Effort::Fast,
            refine_rounds: Some(1),
            ..JobOptions::default()
        };
        assert_eq!(
            compress_options(&fast_refined).refine.map(|r| r.rounds),
            Some(1)
        );
        let best_plain = JobOptions {
            effort: model::Effort::Best,
            no_refine: true,
            ..JobOptions::default()
        };
        assert!(compress_options(&best_plain).refine.is_none());
    }
}
