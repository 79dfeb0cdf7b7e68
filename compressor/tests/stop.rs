//! A compression asked to stop (its options' `StopFlag` raised from another thread, as a worker
//! does when its lease is lost) ends at its next stage with `CompressError::Stopped`: at every
//! stage of a count target's and a byte target's run (the depth comparison, the transforms,
//! the rate search's trials, the refinements), and between the bricks of a bricked volume. A
//! flag never raised changes nothing in the file.

use std::sync::Mutex;
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::bricked::{compress_bricked, BrickError, BrickStage};
use wavesplat_compressor::encode::{
    compress, CompressError, CompressOptions, Effort, Stage, StopFlag, Target,
};
use wavesplat_compressor::phantom::Phantom;

fn volume(dims: [usize; 3]) -> Volume {
    Phantom::SheppLogan.generate(dims)
}

/// The options of `effort` with `target`, holding `stop`.
fn options(effort: Effort, target: Target, stop: &StopFlag) -> CompressOptions {
    let mut o = CompressOptions {
        target,
        depth_search: effort.depth_search(),
        refine: effort.refine_with(false, None, None),
        ..Default::default()
    };
    o.stop = stop.clone();
    o
}

/// Every stage a whole run reports, in order.
fn stages(v: &Volume, o: &CompressOptions) -> Vec<Stage> {
    let seen = Mutex::new(Vec::new());
    compress(v, o, &|s, _| seen.lock().unwrap().push(s)).unwrap();
    seen.into_inner().unwrap()
}

#[test]
fn a_compression_stops_at_the_stage_after_the_flag_is_raised() {
    let v = volume([40, 36, 28]);
    for (effort, target) in [
        (Effort::Default, Target::Fraction(0.02)),
        (Effort::Default, Target::Bytes(6_000)),
        (Effort::Fast, Target::Bytes(6_000)),
        (Effort::Best, Target::Coefficients(3_000)),
    ] {
        let all = stages(&v, &options(effort, target, &StopFlag::default()));
        assert!(all.len() >= 4, "{effort:?} {target:?}: {all:?}");
        // Raised at the k-th report (the work of that stage may finish): no later stage of
        // another kind starts, and the run ends stopped.
        for k in 0..all.len() {
            let stop = StopFlag::new();
            let o = options(effort, target, &stop);
            let seen = Mutex::new(0usize);
            let r = compress(&v, &o, &|_, _| {
                let mut n = seen.lock().unwrap();
                if *n == k {
                    stop.stop();
                }
                *n += 1;
            });
            assert!(
                matches!(r, Err(CompressError::Stopped)),
                "{effort:?} {target:?}, raised at report {k} of {}: {:?}",
                all.len(),
                r.map(|c| c.stats.bytes)
            );
            let reports = seen.into_inner().unwrap();
            assert!(
                reports <= k + 1,
                "{effort:?} {target:?}: raised at report {k}, {reports} reports"
            );
        }
    }
}

#[test]
fn a_flag_never_raised_changes_nothing() {
    let v = volume([33, 40, 17]);
    for target in [Target::Fraction(0.03), Target::Bytes(5_000)] {
        let plain = compress(
            &v,
            &options(Effort::Default, target, &StopFlag::default()),
            &|_, _| {},
        )
        .unwrap();
        let held = compress(
            &v,
            &options(Effort::Default, target, &StopFlag::new()),
            &|_, _| {},
        )
        .unwrap();
        assert_eq!(plain.bytes, held.bytes, "{target:?}");
    }
}

#[test]
fn a_bricked_compression_stops_between_its_bricks() {
    let v = volume([48, 40, 32]);
    for target in [Target::Fraction(0.02), Target::Bytes(12_000)] {
        // Raised when the first brick is scored: no brick is compressed after that.
        let stop = StopFlag::new();
        let o = options(Effort::Default, target, &stop);
        let compressed = Mutex::new(0usize);
        let r = compress_bricked(&v, &o, 16, &|s| match s {
            BrickStage::Scored { .. } => stop.stop(),
            BrickStage::Compressed { .. } => *compressed.lock().unwrap() += 1,
        });
        match r {
            Err(BrickError::Compress { source, .. }) => {
                assert!(matches!(*source, CompressError::Stopped), "{source}")
            }
            Err(e) => panic!("{target:?}: {e}"),
            Ok(c) => panic!("{target:?}: finished, {} bytes", c.bytes.len()),
        }
        assert_eq!(*compressed.lock().unwrap(), 0, "{target:?}");
        // Not raised, the same options compress.
        let o = options(Effort::Default, target, &StopFlag::new());
        assert!(compress_bricked(&v, &o, 16, &|_| {}).is_ok(), "{target:?}");
    }
}
