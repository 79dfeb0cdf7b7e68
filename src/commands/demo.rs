//! `wavesplat demo`: the whole system in one process, on a fresh machine without a GPU. It
//! starts the cache, the orchestrator and a worker on loopback, submits an archive (an
//! intensity phantom, a classified RGB phantom and any volumes given with `--volume`), waits
//! for the compression jobs, then browses each volume from the cache with the headless viewer
//! under a frame budget along a short path (rest, a 90° turn, rest) in three scenes (single
//! view, multiview, depth cueing). Every frame is scored against the reference ray caster's
//! image of the original volume; it writes frame PNGs, a CSV per run and `report.html` with
//! charts of the error against time and bytes and a table of figures beside each.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use wavesplat_client::VolumeKey;
use wavesplat_codec::view::{Cue, CueDirection, View, ViewSpec};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_harness::browse::{browse, probe_backend, reference_options};
use wavesplat_harness::demo::{
    found_for, read_original, volume_section, write_raw, ArchiveVolume, Run,
};
use wavesplat_harness::report;
use wavesplat_harness::scoring::{score_reporting, GroundTruth};
use wavesplat_harness::LocalStack;
use wavesplat_orchestrator::client;
use wavesplat_orchestrator::model::{JobOptions, TargetSpec};
use wavesplat_viewer::walk::{turn, PathStep};
use wavesplat_worker::archive;

/// Arguments of `wavesplat demo`.
#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Output directory (frames, CSVs, charts, report.html). Given explicitly, it also keeps
    /// the services' databases (DIR/db) so the cache can be served again afterwards; by default
    /// they live in a temporary directory and outputs go to ./wavesplat-demo.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Also compress and browse this volume (NIfTI, NRRD, MetaImage, a DICOM directory, or
    /// raw named NAME_XxYxZ_DTYPE[_rgb].raw); repeatable.
    #[arg(long = "volume")]
    pub volumes: Vec<PathBuf>,
    /// Edge of the built-in phantoms in voxels (the intensity phantom is X×X×(3X/4), so it is
    /// not a cube).
    #[arg(long, default_value_t = 80)]
    pub size: usize,
    /// Image side in pixels (per view for multiview).
    #[arg(long, default_value_t = 192)]
    pub image: usize,
    /// Frame budget in milliseconds.
    #[arg(long, default_value_t = 16.6)]
    pub frame_ms: f64,
    /// Most frames to rest at a view waiting for convergence.
    #[arg(long, default_value_t = 240)]
    pub rest_frames: usize,
    /// Compression threads of the worker (0: one per core).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

/// Runs the subcommand.
pub fn run(a: DemoArgs) -> Result<()> {
    if !(a.frame_ms.is_finite() && a.frame_ms > 0.0) {
        bail!("--frame-ms must be positive, got {}", a.frame_ms);
    }
    if a.size < 8 || a.size > 512 {
        bail!("--size must be 8..=512 voxels, got {}", a.size);
    }
    if a.image < 16 || a.image > 2048 {
        bail!("--image must be 16..=2048 pixels, got {}", a.image);
    }
    let started = Instant::now();
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("wavesplat-demo"));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let temp_db;
    let db = match &a.out {
        Some(o) => o.join("db"),
        None => {
            temp_db = tempfile::tempdir().context("creating a temporary directory")?;
            temp_db.path().to_path_buf()
        }
    };
    let archive_dir = out.join("archive");
    for sub in ["archive", "frames", "runs", "charts"] {
        std::fs::create_dir_all(out.join(sub))?;
    }

    // 1. The archive: two phantoms written as raw files, plus the user's volumes.
    let n = a.size;
    let mut volumes = vec![
        ArchiveVolume {
            name: "shepp-logan".into(),
            original: Phantom::SheppLogan.generate([n, n, (3 * n / 4).max(1)]),
        },
        ArchiveVolume {
            name: "rgb-head".into(),
            original: Phantom::RgbHead.generate([(3 * n / 4).max(1); 3]),
        },
    ];
    let mut found = Vec::new();
    for v in &volumes {
        let p = write_raw(&archive_dir, &v.name, &v.original)?;
        found.extend(found_for(&p)?);
    }
    let mut names: HashSet<String> = volumes.iter().map(|v| v.name.clone()).collect();
    for p in &a.volumes {
        for f in found_for(p)? {
            if !names.insert(f.name.clone()) {
                bail!("two volumes are called {:?}; rename one", f.name);
            }
            outln!("reading {} …", f.path.display());
            volumes.push(ArchiveVolume {
                name: f.name.clone(),
                original: read_original(&f)?,
            });
            found.push(f);
        }
    }

    // 2. Services on loopback, jobs submitted and watched.
    outln!(
        "1/3 starting the cache, the orchestrator and a worker on loopback (databases in {}) …",
        db.display()
    );
    let stack = LocalStack::start(&db, true, a.threads)?;
    let orchestrator = stack
        .orchestrator_url
        .clone()
        .context("the orchestrator did not start")?;
    let options = JobOptions {
        target: TargetSpec::Fraction(0.05),
        // Smaller tiles and a few quality layers: more, smaller packets, so the view-dependent
        // order and the progressive refinement have something to order (+5 % bytes).
        tile: Some(32),
        layers: Some(4),
        ..JobOptions::default()
    };
    let options = options.validate()?;
    let t = Instant::now();
    stack.block_on(async {
        let mut c = client::connect(&orchestrator)
            .await
            .context("connecting to the local orchestrator")?;
        let mut ids = HashSet::new();
        for f in &found {
            let (spec, bytes) = archive::job_spec(f, &options, false)
                .with_context(|| format!("reading {}", f.path.display()))?;
            let r = client::submit(&mut c, &spec, bytes.as_deref())
                .await
                .with_context(|| format!("submitting {}", f.path.display()))?;
            let job = r.job.context("the orchestrator returned no job")?;
            outln!("    submitted {} as job {}", f.name, job.id);
            ids.insert(job.id);
        }
        super::orchestrator::watch(&mut c, Some(&ids)).await
    })?;
    outln!(
        "    compressed {} volumes in {:.1} s",
        found.len(),
        t.elapsed().as_secs_f64()
    );

    // 3. Browse each volume from the cache along the path, in each scene.
    outln!(
        "2/3 browsing each volume from the cache (frame budget {} ms) …",
        a.frame_ms
    );
    let frame = Duration::from_secs_f64(a.frame_ms / 1e3);
    let (backend, reason) = probe_backend()?;
    outln!("    backend: {reason}");
    let mut runs = Vec::new();
    let progress = crate::progress::Progress::new("demo");
    let total_runs = volumes.len() * 3;
    for v in &volumes {
        let file_bytes = stack
            .block_on(async {
                let mut c = wavesplat_client::CacheClient::connect(&stack.cache_url).await?;
                c.describe(&VolumeKey::Name(v.name.clone())).await
            })
            .with_context(|| format!("describing {}", v.name))?
            .file_bytes;
        let diagonal = {
            let d = v.original.dims();
            ((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) as f64).sqrt()
        };
        let base = View::new(0.66, 0.91, a.image, a.image);
        let scenes: [(&'static str, ViewSpec); 3] = [
            ("single", ViewSpec::single(base)),
            (
                "multiview",
                ViewSpec {
                    view: base,
                    multiview: true,
                },
            ),
            (
                "depth-cued",
                ViewSpec::single(base.with_cue(Cue {
                    // Light falls to e^-3 across the volume's diagonal.
                    k: 3.0 / diagonal,
                    direction: CueDirection::View,
                })),
            ),
        ];
        for (scene, spec) in scenes {
            let mut path = vec![PathStep::rest(spec, a.rest_frames)];
            path.extend(turn(
                spec,
                [0.66, 0.91],
                [std::f64::consts::FRAC_PI_2, 0.0],
                6,
                3,
            ));
            let end = path.last().expect("a turn has steps").spec;
            path.push(PathStep::rest(end, a.rest_frames));
            progress.stage(&format!(
                "browsing {} ({scene}), walk {} of {total_runs}",
                v.name,
                runs.len() + 1
            ));
            let (header, backend, samples) =
                browse(&stack.cache_url, &v.name, spec, &path, frame, backend)
                    .with_context(|| format!("browsing {} ({scene})", v.name))?;
            runs.push(Run {
                volume: v.name.clone(),
                scene,
                header,
                backend,
                path,
                samples,
                quality: Vec::new(),
                file_bytes,
            });
        }
    }
    stack.shutdown()?;

    // 4. Score, write frames, CSVs, charts and the report.
    outln!("3/3 scoring every frame against the reference ray caster and writing the report …");
    let mut sections = Vec::new();
    for v in &volumes {
        let Some(first) = runs.iter().find(|r| r.volume == v.name) else {
            continue;
        };
        let truth = GroundTruth::new(&v.original, &first.header.geometry, reference_options());
        for r in runs.iter_mut().filter(|r| r.volume == v.name) {
            let what = format!("scoring {} ({})", r.volume, r.scene);
            progress.stage(&format!("{what}: ray casting the references"));
            r.quality = score_reporting(
                &truth,
                &r.path,
                &r.samples,
                &mut HashMap::new(),
                &mut |done, needed| {
                    progress.stage(&format!("{what}: reference image {done} of {needed}"))
                },
            )?;
        }
        sections.push(volume_section(&out, v, &runs, a.frame_ms)?);
    }
    progress.finish();
    let intro = format!(
        "{} volumes compressed by the worker (linear B-spline wavelets, 5 % of the coefficients), \
         then browsed from the cache over loopback by the headless viewer with the {} backend at a \
         {} ms frame budget: rest at α = 0.66, β = 0.91 until converged, a 90° turn in six steps \
         of three frames, rest again. Q_I is the paper's image quality (eq. 18) against the \
         reference ray caster's image of the original volume for the same view; SNR the \
         conventional one. Machine: {} threads.",
        volumes.len(),
        runs.first().map_or("cpu".into(), |r| r.backend.clone()),
        a.frame_ms,
        rayon::current_num_threads()
    );
    report::write_html(
        &out.join("report.html"),
        "wavesplat demo: browsing compressed volumes from the cache",
        &intro,
        &sections,
    )?;
    for r in &runs {
        let last = r.samples.last();
        let q = r.quality.iter().rev().flatten().next();
        outln!(
            "    {:12} {:10} {:4} frames, {:7} bytes of {:7}, final Q_I {:6.2} dB, SNR {:6.2} dB",
            r.volume,
            r.scene,
            r.samples.len(),
            last.map_or(0, |s| s.bytes),
            r.file_bytes,
            q.map_or(f64::NAN, |q| q.q_i),
            q.map_or(f64::NAN, |q| q.snr)
        );
    }
    outln!(
        "done in {:.0} s: open {}",
        started.elapsed().as_secs_f64(),
        out.join("report.html").display()
    );
    if a.out.is_some() {
        outln!(
            "the cache database is kept: wavesplat serve cache --db {} --addr 127.0.0.1:50051",
            db.join("cache").display()
        );
    }
    Ok(())
}
