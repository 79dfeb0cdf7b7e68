//! The one place where wire types (`pb`) become domain types and back. Everything arriving from
//! the network is checked here (missing fields, sizes, enum values) and reported as
//! [`ClientError::InvalidRequest`]; nothing panics on bad input.

use crate::error::ClientError;
use crate::model::{
    parse_coder, parse_colorspace, parse_effort, parse_family, Delivery, Effort, Failure,
    FailureKind, Job, JobOptions, JobSpec, JobState, Outcome, PartColor, PartSpec, PartStep,
    RawLayout, SampleType, Source, TargetSpec,
};
use wavesplat_proto::pb;

fn invalid(msg: impl Into<String>) -> ClientError {
    ClientError::InvalidRequest(msg.into())
}

fn to_usize(v: u32) -> usize {
    v as usize
}

/// `pb::JobSpec` → [`JobSpec`] (shape and names; [`JobSpec::validate`] checks values).
pub fn spec_from_pb(p: pb::JobSpec) -> Result<JobSpec, ClientError> {
    let source = match p.source {
        Some(pb::job_spec::Source::Path(path)) => Source::Path(path.into()),
        Some(pb::job_spec::Source::UploadSize(size)) => Source::Upload { size },
        None => return Err(invalid("job spec without a source (path or upload_size)")),
    };
    let sha256: [u8; 32] = p.sha256.as_slice().try_into().map_err(|_| {
        invalid(format!(
            "sha256 of {} bytes; must be 32 bytes",
            p.sha256.len()
        ))
    })?;
    let raw = match p.raw {
        None => None,
        Some(r) => {
            let dims: [u32; 3] =
                r.dims.as_slice().try_into().map_err(|_| {
                    invalid(format!("raw dims {:?}; need exactly 3 values", r.dims))
                })?;
            let dtype = SampleType::from_name(&r.dtype).ok_or_else(|| {
                invalid(format!(
                    "raw dtype {:?}; allowed {:?}",
                    r.dtype,
                    SampleType::names()
                ))
            })?;
            Some(RawLayout {
                dims: dims.map(to_usize),
                dtype,
                big_endian: r.big_endian,
                channels: if r.channels == 0 {
                    1
                } else {
                    to_usize(r.channels)
                },
            })
        }
    };
    let options = options_from_pb(p.options.unwrap_or_default())?;
    let part = p.part.map(part_from_pb).transpose()?;
    Ok(JobSpec {
        name: p.name,
        source,
        sha256,
        raw,
        channel: p.channel,
        options,
        part,
    })
}

/// `pb::PartSpec` → [`PartSpec`] (shape; [`PartSpec::validate`] checks values).
pub fn part_from_pb(p: pb::PartSpec) -> Result<PartSpec, ClientError> {
    let step = match p.step {
        Some(pb::part_spec::Step::Score(s)) => PartStep::Score {
            energies: s.energies,
        },
        Some(pb::part_spec::Step::Encode(e)) => PartStep::Encode {
            count: e.count,
            trial: e.trial,
        },
        None => return Err(invalid("part without a step (score or encode)")),
    };
    let color = match p.color {
        None => None,
        Some(c) => {
            let three = |v: &[f64], what: &str| -> Result<[f64; 3], ClientError> {
                v.try_into()
                    .map_err(|_| invalid(format!("part colour {what}: {} values, need 3", v.len())))
            };
            if c.basis.len() != 9 {
                return Err(invalid(format!(
                    "part colour basis: {} values, need 9",
                    c.basis.len()
                )));
            }
            Some(PartColor {
                basis: [
                    three(&c.basis[0..3], "basis")?,
                    three(&c.basis[3..6], "basis")?,
                    three(&c.basis[6..9], "basis")?,
                ],
                mean: three(&c.mean, "mean")?,
                importance: three(&c.importance, "importance")?,
            })
        }
    };
    Ok(PartSpec {
        parent: p.parent,
        index: p.index,
        of: p.of,
        step,
        levels: p.levels,
        offset: p.offset,
        color,
        source_bytes: (p.source_bytes > 0).then_some(p.source_bytes),
        time_points: (p.time_points > 0).then_some(p.time_points),
        prefer_worker: (!p.prefer_worker.is_empty()).then_some(p.prefer_worker),
    })
}

fn part_to_pb(p: &PartSpec) -> pb::PartSpec {
    pb::PartSpec {
        parent: p.parent,
        index: p.index,
        of: p.of,
        step: Some(match p.step {
            PartStep::Score { energies } => pb::part_spec::Step::Score(pb::ScoreStep { energies }),
            PartStep::Encode { count, trial } => {
                pb::part_spec::Step::Encode(pb::EncodeStep { count, trial })
            }
        }),
        levels: p.levels,
        offset: p.offset,
        color: p.color.map(|c| pb::PartColor {
            basis: c.basis.iter().flatten().copied().collect(),
            mean: c.mean.to_vec(),
            importance: c.importance.to_vec(),
        }),
        source_bytes: p.source_bytes.unwrap_or(0),
        time_points: p.time_points.unwrap_or(0),
        prefer_worker: p.prefer_worker.clone().unwrap_or_default(),
    }
}

fn options_from_pb(o: pb::CompressOptions) -> Result<JobOptions, ClientError> {
    let d = JobOptions::default();
    let target = match o.target.and_then(|t| t.kind) {
        None => d.target,
        Some(pb::target::Kind::Fraction(f)) => TargetSpec::Fraction(f),
        Some(pb::target::Kind::Bytes(b)) => TargetSpec::Bytes(b),
        Some(pb::target::Kind::Coefficients(c)) => TargetSpec::Coefficients(c),
        Some(pb::target::Kind::QvPercent(q)) => TargetSpec::QvPercent(q),
        Some(pb::target::Kind::All(_)) => TargetSpec::All,
    };
    Ok(JobOptions {
        family: if o.family.is_empty() {
            d.family
        } else {
            parse_family(&o.family)?
        },
        levels: o.levels.map(to_usize),
        colorspace: if o.colorspace.is_empty() {
            d.colorspace
        } else {
            parse_colorspace(&o.colorspace)?
        },
        bits: match o.bits {
            0 => d.bits,
            b => u8::try_from(b).map_err(|_| invalid(format!("bits {b}; allowed 1..=16")))?,
        },
        step: if o.step == 0.0 { d.step } else { o.step },
        coder: if o.coder.is_empty() {
            d.coder
        } else {
            parse_coder(&o.coder)?
        },
        target,
        tile: o.tile.map(to_usize),
        layers: o.layers.map(to_usize),
        refine_rounds: o.refine_rounds.map(to_usize),
        no_refine: o.no_refine,
        layer_growth: o.layer_growth,
        brick: o.brick.map(to_usize),
        time_group: o.time_group.map(to_usize),
        effort: if o.effort.is_empty() {
            d.effort
        } else {
            parse_effort(&o.effort)?
        },
        memory_limit: o.memory_limit,
    })
}

fn u32_of(v: usize) -> u32 {
    u32::try_from(v).unwrap_or(u32::MAX)
}

/// [`JobSpec`] → `pb::JobSpec`.
pub fn spec_to_pb(s: &JobSpec) -> pb::JobSpec {
    let o = &s.options;
    let kind = match o.target {
        TargetSpec::Fraction(f) => pb::target::Kind::Fraction(f),
        TargetSpec::Bytes(b) => pb::target::Kind::Bytes(b),
        TargetSpec::Coefficients(c) => pb::target::Kind::Coefficients(c),
        TargetSpec::QvPercent(q) => pb::target::Kind::QvPercent(q),
        TargetSpec::All => pb::target::Kind::All(true),
    };
    pb::JobSpec {
        name: s.name.clone(),
        source: Some(match &s.source {
            Source::Path(p) => pb::job_spec::Source::Path(p.to_string_lossy().into_owned()),
            Source::Upload { size } => pb::job_spec::Source::UploadSize(*size),
        }),
        sha256: s.sha256.to_vec(),
        raw: s.raw.as_ref().map(|r| pb::RawLayout {
            dims: r.dims.iter().map(|&d| u32_of(d)).collect(),
            dtype: r.dtype.name().into(),
            big_endian: r.big_endian,
            channels: u32_of(r.channels),
        }),
        channel: s.channel,
        options: Some(pb::CompressOptions {
            family: o.family.name().into(),
            levels: o.levels.map(u32_of),
            colorspace: o.colorspace.name().into(),
            bits: u32::from(o.bits),
            step: o.step,
            coder: o.coder.name().into(),
            target: Some(pb::Target { kind: Some(kind) }),
            tile: o.tile.map(u32_of),
            layers: o.layers.map(u32_of),
            refine_rounds: o.refine_rounds.map(u32_of),
            no_refine: o.no_refine,
            layer_growth: o.layer_growth,
            brick: o.brick.map(u32_of),
            time_group: o.time_group.map(u32_of),
            effort: match o.effort {
                Effort::Default => String::new(),
                e => e.name().into(),
            },
            memory_limit: o.memory_limit,
        }),
        part: s.part.as_ref().map(part_to_pb),
    }
}

/// [`FailureKind`] → wire enum.
pub fn failure_kind_to_pb(k: FailureKind) -> pb::FailureKind {
    match k {
        FailureKind::InvalidInput => pb::FailureKind::InvalidInput,
        FailureKind::Compress => pb::FailureKind::Compress,
        FailureKind::SourceUnavailable => pb::FailureKind::SourceUnavailable,
        FailureKind::CacheUnavailable => pb::FailureKind::CacheUnavailable,
        FailureKind::CacheRejected => pb::FailureKind::CacheRejected,
        FailureKind::LeaseExpired => pb::FailureKind::LeaseExpired,
        FailureKind::Worker => pb::FailureKind::Worker,
    }
}

/// Wire enum value → [`FailureKind`].
pub fn failure_kind_from_pb(v: i32) -> Result<FailureKind, ClientError> {
    Ok(match pb::FailureKind::try_from(v) {
        Ok(pb::FailureKind::InvalidInput) => FailureKind::InvalidInput,
        Ok(pb::FailureKind::Compress) => FailureKind::Compress,
        Ok(pb::FailureKind::SourceUnavailable) => FailureKind::SourceUnavailable,
        Ok(pb::FailureKind::CacheUnavailable) => FailureKind::CacheUnavailable,
        Ok(pb::FailureKind::CacheRejected) => FailureKind::CacheRejected,
        Ok(pb::FailureKind::LeaseExpired) => FailureKind::LeaseExpired,
        Ok(pb::FailureKind::Worker) => FailureKind::Worker,
        _ => return Err(invalid(format!("failure kind {v}; allowed 1..=7"))),
    })
}

/// A worker's `FinishRequest` outcome → [`Outcome`].
pub fn outcome_from_pb(o: Option<pb::finish_request::Outcome>) -> Result<Outcome, ClientError> {
    match o {
        Some(pb::finish_request::Outcome::Delivered(d)) => {
            if !(d.sha256.len() == 64 && d.sha256.bytes().all(|b| b.is_ascii_hexdigit())) {
                return Err(invalid(format!(
                    "delivered SHA-256 {:?}; expected 64 hex digits",
                    d.sha256.chars().take(80).collect::<String>()
                )));
            }
            Ok(Outcome::Delivered(Delivery {
                cache_volume_id: d.cache_volume_id,
                output_bytes: d.output_bytes,
                voxels: d.voxels,
                existed: d.existed,
                sha256: d.sha256.to_ascii_lowercase(),
            }))
        }
        Some(pb::finish_request::Outcome::Failure(f)) => Ok(Outcome::Failed(Failure {
            kind: failure_kind_from_pb(f.kind)?,
            message: f.message.chars().take(4000).collect(),
        })),
        None => Err(invalid("finish request without an outcome")),
    }
}

/// [`Job`] → `pb::Job`.
pub fn job_to_pb(j: &Job, max_attempts: u32) -> pb::Job {
    let mut p = pb::Job {
        id: j.id,
        spec: Some(spec_to_pb(&j.spec)),
        attempts: j.attempts.saturating_sub(j.retried_at),
        max_attempts,
        created_unix_ms: j.created_ms,
        updated_unix_ms: j.updated_ms,
        ..Default::default()
    };
    if let Some(f) = &j.last_failure {
        p.failure = failure_kind_to_pb(f.kind) as i32;
        p.error = f.message.clone();
    }
    let state = match &j.state {
        JobState::Queued { not_before_ms } => {
            p.not_before_unix_ms = *not_before_ms;
            pb::JobState::Queued
        }
        JobState::Running {
            worker,
            lease_expires_ms,
            progress,
            stage,
            ..
        } => {
            p.worker = worker.clone();
            p.lease_expires_unix_ms = *lease_expires_ms;
            p.progress = *progress;
            p.stage = stage.clone();
            pb::JobState::Running
        }
        JobState::Done {
            delivery,
            run_ms,
            worker,
        } => {
            p.worker = worker.clone();
            p.progress = 1.0;
            p.cache_volume_id = delivery.cache_volume_id;
            p.output_bytes = delivery.output_bytes;
            p.voxels = delivery.voxels;
            p.run_ms = *run_ms;
            pb::JobState::Done
        }
        JobState::Failed(f) => {
            p.failure = failure_kind_to_pb(f.kind) as i32;
            p.error = f.message.clone();
            pb::JobState::Failed
        }
        JobState::Cancelled => pb::JobState::Cancelled,
    };
    p.state = state as i32;
    p
}

/// The short name of a wire job state.
pub fn state_name(v: i32) -> &'static str {
    match pb::JobState::try_from(v) {
        Ok(pb::JobState::Queued) => "queued",
        Ok(pb::JobState::Running) => "running",
        Ok(pb::JobState::Done) => "done",
        Ok(pb::JobState::Failed) => "failed",
        Ok(pb::JobState::Cancelled) => "cancelled",
        _ => "unknown",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_round_trips_and_bad_shapes_are_refused() {
        let spec = JobSpec {
            name: "head".into(),
            source: Source::Path("/a/head_8x8x8_u8.raw".into()),
            sha256: [7; 32],
            raw: Some(RawLayout {
                dims: [8, 8, 8],
                dtype: SampleType::U8,
                big_endian: false,
                channels: 3,
            }),
            channel: None,
            options: JobOptions {
                levels: Some(2),
                target: TargetSpec::All,
                refine_rounds: Some(2),
                no_refine: true,
                layer_growth: Some(4.0),
                brick: Some(64),
                effort: Effort::Fast,
                ..JobOptions::default()
            },
            part: None,
        };
        assert_eq!(spec_from_pb(spec_to_pb(&spec)).unwrap(), spec);
        // Every effort round-trips; the default one travels as nothing and is stored as before.
        for effort in [Effort::Fast, Effort::Default, Effort::Best] {
            let mut s = spec.clone();
            s.options.effort = effort;
            assert_eq!(spec_from_pb(spec_to_pb(&s)).unwrap(), s);
        }
        let default = JobOptions::default();
        assert!(!serde_json::to_string(&default).unwrap().contains("effort"));
        // A memory limit round-trips and is part of the job's identity; none is stored as
        // before limits; a limit of nothing is refused.
        let mut limited = spec.clone();
        limited.options.memory_limit = Some(3 << 30);
        assert_eq!(spec_from_pb(spec_to_pb(&limited)).unwrap(), limited);
        assert_ne!(limited.dedup_key(), spec.dedup_key());
        assert!(!serde_json::to_string(&default).unwrap().contains("memory"));
        // A channel chosen round-trips and is part of the job's identity; none is stored and
        // keyed as before channels.
        let mut one_channel = spec.clone();
        one_channel.channel = Some(2);
        assert_eq!(spec_from_pb(spec_to_pb(&one_channel)).unwrap(), one_channel);
        assert_ne!(one_channel.dedup_key(), spec.dedup_key());
        assert!(!spec.dedup_key().contains("|channel:"));
        assert!(!serde_json::to_string(&spec)
            .unwrap()
            .contains("\"channel\""));
        assert!(serde_json::to_string(&one_channel)
            .unwrap()
            .contains("\"channel\":2"));
        limited.options.memory_limit = Some(0);
        assert!(spec_from_pb(spec_to_pb(&limited))
            .and_then(|s| s.validate())
            .is_err());
        let mut pb_spec = spec_to_pb(&spec);
        pb_spec.options.as_mut().unwrap().effort = "slow".into();
        assert!(spec_from_pb(pb_spec).is_err());
        // A part, with its colour transform, round-trips and validates; a broken one does not.
        let part = JobSpec {
            part: Some(PartSpec {
                parent: 9,
                index: 3,
                of: 8,
                step: PartStep::Encode {
                    count: Some(1234),
                    trial: 2,
                },
                levels: 2,
                offset: None,
                color: Some(PartColor {
                    basis: [[0.6, 0.5, 0.1], [0.2, -0.7, 0.3], [0.1, 0.2, -0.9]],
                    mean: [0.25, 0.5, 0.125],
                    importance: [1.0, 1.0, 0.0],
                }),
                source_bytes: Some(1 << 33),
                time_points: Some(16),
                prefer_worker: Some("w1-4242".into()),
            }),
            ..spec.clone()
        };
        let back = spec_from_pb(spec_to_pb(&part)).unwrap();
        assert_eq!(back, part);
        assert!(spec.is_parent_of(&back.clone().validate().unwrap()));
        // A part of another channel is no part of it.
        let mut other_channel = back.clone();
        other_channel.channel = Some(1);
        assert!(!spec.is_parent_of(&other_channel));
        assert_ne!(part.dedup_key(), spec.dedup_key());
        let mut p = spec_to_pb(&part);
        p.part.as_mut().unwrap().color.as_mut().unwrap().basis.pop();
        assert!(spec_from_pb(p).is_err());
        let mut p = spec_to_pb(&part);
        p.part.as_mut().unwrap().index = 8;
        assert!(spec_from_pb(p).unwrap().validate().is_err());
        // The preferred worker: not part of the identity; bounded, no control characters.
        let mut elsewhere = part.clone();
        elsewhere.part.as_mut().unwrap().prefer_worker = None;
        assert_eq!(elsewhere.dedup_key(), part.dedup_key());
        assert!(spec_from_pb(spec_to_pb(&elsewhere))
            .unwrap()
            .validate()
            .is_ok());
        for bad in ["w\n1".to_string(), "w".repeat(256)] {
            let mut p = spec_to_pb(&part);
            p.part.as_mut().unwrap().prefer_worker = bad;
            assert!(spec_from_pb(p).unwrap().validate().is_err());
        }
        let mut p = spec_to_pb(&part);
        p.part.as_mut().unwrap().step = None;
        assert!(spec_from_pb(p).is_err());
        let mut p = spec_to_pb(&spec);
        p.sha256 = vec![1, 2];
        assert!(spec_from_pb(p).is_err());
        let mut p = spec_to_pb(&spec);
        p.raw.as_mut().unwrap().dims = vec![1, 2];
        assert!(spec_from_pb(p).is_err());
        let mut p = spec_to_pb(&spec);
        p.source = None;
        assert!(spec_from_pb(p).is_err());
        let mut p = spec_to_pb(&spec);
        p.options.as_mut().unwrap().layer_growth = Some(0.5);
        // The wire form carries it; validation (on submit) refuses it.
        let e = spec_from_pb(p).unwrap().validate().unwrap_err();
        assert!(e.to_string().contains("layer growth"), "{e}");
        for brick in [3, 4096] {
            let mut p = spec_to_pb(&spec);
            p.options.as_mut().unwrap().brick = Some(brick);
            let e = spec_from_pb(p).unwrap().validate().unwrap_err();
            assert!(e.to_string().contains(&format!("brick {brick}")), "{e}");
        }
        let mut p = spec_to_pb(&spec);
        p.options.as_mut().unwrap().family = "sinc".into();
        let e = spec_from_pb(p).unwrap_err();
        assert!(e.to_string().contains("sinc"), "{e}");
        let mut p = spec_to_pb(&spec);
        p.raw.as_mut().unwrap().dtype = "u9".into();
        assert!(spec_from_pb(p).is_err());
        assert!(failure_kind_from_pb(99).is_err());
    }
}
