//! `demo`: the whole system in one process, on a fresh machine without a GPU. It
//! starts the cache, the orchestrator and a worker on loopback, submits an archive (an
//! intensity phantom, a classified RGB phantom and any volumes given with `--volume`), waits
//! for the compression jobs, then browses each volume from the cache with the headless viewer
//! under a frame budget along a short path (rest, a 90° turn, rest) in three scenes (single
//! view, multiview, depth cueing). Every frame is scored against the reference ray caster's
//! image of the original volume; it writes frame PNGs, a CSV per run and `report.html` with
//! charts of the error against time and bytes and a table of figures beside each.
//!
//! The final rest runs until the image converges (at most [`FINAL_REST_FACTOR`] times the
//! first rest's frames), so the final figures are the converged image's rather than whatever a
//! loaded machine reached in a fixed number of frames; a rest that ends at its limit is
//! reported as such, with what was still pending ([`RestEnd`]). Progress goes to stderr as
//! a spinner on a terminal and as plain lines otherwise.

use crate::browse::{browse, probe_backend, reference_options};
use crate::report::{Chart, Section, Series, Table};
use crate::scoring::{q_i_at, score_reporting, FrameQuality, GroundTruth};
use crate::LocalStack;
use anyhow::{bail, Context, Result};
use std::collections::{HashMap, HashSet};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use wavesplat_client::VolumeKey;
use wavesplat_codec::view::{Cue, CueDirection, View, ViewSpec};
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_orchestrator_client as client;
use wavesplat_orchestrator_client::model::{JobOptions, TargetSpec};
use wavesplat_viewer::backend::BackendChoice;
use wavesplat_viewer::walk::{percentile, turn, FrameSample, PathStep};
use wavesplat_worker::archive;

/// What the demo runs: its output directory, the user's volumes, the phantoms' edge, the image
/// side, the frame budget, the most frames to rest at a view and the worker's threads (the
/// meanings of `wavesplat demo --help`).
#[derive(Debug, Clone)]
pub struct Demo {
    /// Output directory; given, it also keeps the services' databases (DIR/db). `None`:
    /// `./wavesplat-demo`, databases in a temporary directory.
    pub out: Option<PathBuf>,
    /// Further volumes to compress and browse.
    pub volumes: Vec<PathBuf>,
    /// Edge of the built-in phantoms (8..=512).
    pub size: usize,
    /// Image side (16..=2048 pixels; per view for multiview).
    pub image: usize,
    /// Frame budget (ms).
    pub frame_ms: f64,
    /// Most frames to rest at a view.
    pub rest_frames: usize,
    /// Compression threads of the worker (0: one per core).
    pub threads: usize,
}

/// The final rest's frame limit as a multiple of the first rest's: generous, so that the final
/// rest ends when the image converges (it does so well within it on an idle machine, e.g. 216
/// frames of 240 for the RGB head's multiview) and the final figures do not depend on how far
/// refinement got on a loaded one.
pub const FINAL_REST_FACTOR: usize = 10;

/// How a rest ended.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RestEnd {
    /// The image converged: everything sent was drawn with exact tables and the source had
    /// nothing more; the time is from the walk's start (ms).
    Converged {
        /// When (ms from the walk's start).
        ms: f64,
    },
    /// The rest reached its frame limit first.
    LimitReached {
        /// Coefficients queued but not yet drawn at its last frame.
        pending: usize,
    },
}

impl RestEnd {
    /// How path step `step` of `samples` ended (its last frame); `None` if it has no frame.
    pub fn of(samples: &[FrameSample], step: usize) -> Option<RestEnd> {
        let last = samples.iter().rfind(|s| s.step == step)?;
        Some(if last.converged {
            RestEnd::Converged {
                ms: last.t.as_secs_f64() * 1e3,
            }
        } else {
            RestEnd::LimitReached {
                pending: last.pending,
            }
        })
    }

    /// Whether the image converged.
    pub fn converged(&self) -> bool {
        matches!(self, RestEnd::Converged { .. })
    }

    /// In words: "converged" or "rest limit reached, N pending" (with "packets still
    /// arriving" when nothing was pending but the source had not finished).
    pub fn label(&self) -> String {
        match *self {
            RestEnd::Converged { .. } => "converged".into(),
            RestEnd::LimitReached { pending: 0 } => {
                "rest limit reached, 0 pending, packets still arriving".into()
            }
            RestEnd::LimitReached { pending } => format!("rest limit reached, {pending} pending"),
        }
    }

    /// For the table: "converged at T ms" or the label.
    pub fn cell(&self) -> String {
        match *self {
            RestEnd::Converged { ms } => format!("converged at {ms:.0} ms"),
            RestEnd::LimitReached { .. } => self.label(),
        }
    }
}

/// Runs the demo, writing its outputs to `say` and its progress to stderr.
pub fn run(demo: &Demo, say: &mut (dyn Write + Send)) -> Result<()> {
    if !(demo.frame_ms.is_finite() && demo.frame_ms > 0.0) {
        bail!("--frame-ms must be positive, got {}", demo.frame_ms);
    }
    if demo.size < 8 || demo.size > 512 {
        bail!("--size must be 8..=512 voxels, got {}", demo.size);
    }
    if demo.image < 16 || demo.image > 2048 {
        bail!("--image must be 16..=2048 pixels, got {}", demo.image);
    }
    let started = Instant::now();
    let out = demo
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("wavesplat-demo"));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let temp_db;
    let db = match &demo.out {
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
    let n = demo.size;
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
    for p in &demo.volumes {
        for f in found_for(p)? {
            if !names.insert(f.name.clone()) {
                bail!("two volumes are called {:?}; rename one", f.name);
            }
            writeln!(say, "reading {} …", f.path.display())?;
            volumes.push(ArchiveVolume {
                name: f.name.clone(),
                original: read_original(&f)?,
            });
            found.push(f);
        }
    }

    // 2. Services on loopback, jobs submitted and watched.
    writeln!(
        say,
        "1/3 starting the cache, the orchestrator and a worker on loopback (databases in {}) …",
        db.display()
    )?;
    let stack = LocalStack::start(&db, true, demo.threads)?;
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
            writeln!(say, "    submitted {} as job {}", f.name, job.id)?;
            ids.insert(job.id);
        }
        crate::console::watch(&mut c, Some(&ids), say).await
    })?;
    writeln!(
        say,
        "    compressed {} volumes in {:.1} s",
        found.len(),
        t.elapsed().as_secs_f64()
    )?;

    // 3. Browse each volume from the cache along the path, in each scene.
    writeln!(
        say,
        "2/3 browsing each volume from the cache (frame budget {} ms) …",
        demo.frame_ms
    )?;
    let frame = Duration::from_secs_f64(demo.frame_ms / 1e3);
    let (backend, reason) = probe_backend(BackendChoice::Auto)?;
    writeln!(say, "    backend: {reason}")?;
    let mut runs = Vec::new();
    let progress = crate::console::Progress::with_lines("demo");
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
        let base = View::new(0.66, 0.91, demo.image, demo.image);
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
            let mut path = vec![PathStep::rest(spec, demo.rest_frames)];
            path.extend(turn(
                spec,
                [0.66, 0.91],
                [std::f64::consts::FRAC_PI_2, 0.0],
                6,
                3,
            ));
            let end = path.last().expect("a turn has steps").spec;
            path.push(PathStep::rest(
                end,
                demo.rest_frames.saturating_mul(FINAL_REST_FACTOR),
            ));
            progress.stage(&format!(
                "browsing {} ({scene}), walk {} of {total_runs}",
                v.name,
                runs.len() + 1
            ));
            let (header, backend, samples) =
                browse(&stack.cache_url, &v.name, spec, &path, frame, backend)
                    .with_context(|| format!("browsing {} ({scene})", v.name))?;
            let ends = [0, path.len() - 1].map(|step| {
                RestEnd::of(&samples, step).map_or_else(|| "no frame".into(), |e| e.label())
            });
            progress.stage(&format!(
                "browsed {} ({scene}): {} frames; first rest: {}; final rest: {}",
                v.name,
                samples.len(),
                ends[0],
                ends[1]
            ));
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
    writeln!(
        say,
        "3/3 scoring every frame against the reference ray caster and writing the report …"
    )?;
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
        sections.push(volume_section(&out, v, &runs, demo.frame_ms)?);
    }
    progress.finish();
    let intro = format!(
        "{} volumes compressed by the worker (linear B-spline wavelets, 5 % of the coefficients), \
         then browsed from the cache over loopback by the headless viewer with the {} backend at a \
         {} ms frame budget: rest at α = 0.66, β = 0.91 until converged (at most {} frames), a \
         90° turn in six steps of three frames, rest again until converged (at most {} frames, \
         so that the final figures are the converged image's; a rest that ends at its limit is \
         marked \"rest limit reached\" with the coefficients still pending). Q_I is the paper's \
         image quality (eq. 18) against the reference ray caster's image of the original volume \
         for the same view; SNR the conventional one. Times depend on the machine and its load; \
         converged figures do not. Machine: {} threads.",
        volumes.len(),
        runs.first().map_or("cpu".into(), |r| r.backend.clone()),
        demo.frame_ms,
        demo.rest_frames,
        demo.rest_frames.saturating_mul(FINAL_REST_FACTOR),
        rayon::current_num_threads()
    );
    crate::report::write_html(
        &out.join("report.html"),
        "wavesplat demo: browsing compressed volumes from the cache",
        &intro,
        &sections,
    )?;
    for r in &runs {
        let last = r.samples.last();
        let q = r.quality.iter().rev().flatten().next();
        let end = RestEnd::of(&r.samples, r.path.len() - 1);
        writeln!(
            say,
            "    {:12} {:10} {:4} frames, {:7} bytes of {:7}, final Q_I {:6.2} dB, SNR {:6.2} dB, {}",
            r.volume,
            r.scene,
            r.samples.len(),
            last.map_or(0, |s| s.bytes),
            r.file_bytes,
            q.map_or(f64::NAN, |q| q.q_i),
            q.map_or(f64::NAN, |q| q.snr),
            end.map_or_else(|| "no frame".into(), |e| e.label())
        )?;
    }
    writeln!(
        say,
        "done in {:.0} s: open {}",
        started.elapsed().as_secs_f64(),
        out.join("report.html").display()
    )?;
    if demo.out.is_some() {
        writeln!(
            say,
            "the cache database is kept: wavesplat serve cache --db {} --addr 127.0.0.1:50051",
            db.join("cache").display()
        )?;
    }
    Ok(())
}

/// One browsing run: a volume, a scene, its samples and their quality.
pub struct Run {
    /// The volume's name in the cache.
    pub volume: String,
    /// The scene: single, multiview or depth-cued.
    pub scene: &'static str,
    /// The volume's header.
    pub header: wavesplat_codec::format::Header,
    /// The accumulation backend's name.
    pub backend: String,
    /// The walk.
    pub path: Vec<PathStep>,
    /// Its frames.
    pub samples: Vec<FrameSample>,
    /// Their quality (after scoring).
    pub quality: Vec<Option<FrameQuality>>,
    /// The file's size in the cache.
    pub file_bytes: u64,
}

/// A volume of the demo archive: its name in the cache and its original samples.
pub struct ArchiveVolume {
    /// Its name in the cache.
    pub name: String,
    /// Its samples.
    pub original: Volume,
}

/// Writes `v` as raw little-endian f32 (channels interleaved) named by the raw convention.
pub fn write_raw(dir: &Path, name: &str, v: &Volume) -> Result<PathBuf> {
    let d = v.dims();
    let rgb = if v.channel_count() == 3 { "_rgb" } else { "" };
    let path = dir.join(format!("{name}_{}x{}x{}_f32{rgb}.raw", d[0], d[1], d[2]));
    let bytes: Vec<u8> = v
        .to_interleaved()
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// The found volumes of a `--volume` argument: the file itself, or what a directory holds.
pub fn found_for(path: &Path) -> Result<Vec<archive::Found>> {
    let meta = std::fs::metadata(path).with_context(|| format!("reading {}", path.display()))?;
    let scan_root = if meta.is_dir() {
        path.to_path_buf()
    } else {
        path.parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_path_buf()
    };
    let scan = archive::scan(&scan_root).with_context(|| format!("scanning {}", path.display()))?;
    if meta.is_dir() {
        if scan.found.is_empty() {
            bail!("no supported volume under {}", path.display());
        }
        return Ok(scan.found);
    }
    let want = std::fs::canonicalize(path)?;
    let hit: Vec<archive::Found> = scan
        .found
        .into_iter()
        .filter(|f| std::fs::canonicalize(&f.path).is_ok_and(|p| p == want))
        .collect();
    if hit.is_empty() {
        bail!(
            "{} is not a supported volume (NIfTI, NRRD, MetaImage, DICOM, or raw named NAME_XxYxZ_DTYPE[_rgb].raw)",
            path.display()
        );
    }
    Ok(hit)
}

/// The original samples of a found volume, read as the worker reads them.
pub fn read_original(f: &archive::Found) -> Result<Volume> {
    let raw = f.raw.as_ref().map(wavesplat_worker::options::raw_spec);
    wavesplat_compressor::reader::read_volume(&f.path, raw.as_ref())
        .with_context(|| format!("reading {}", f.path.display()))
}

fn q_at(r: &Run, step: usize, n: u64) -> Option<f64> {
    q_i_at(&r.samples, &r.quality, step, n)
}

fn fmt(x: Option<f64>, digits: usize) -> String {
    x.filter(|v| v.is_finite())
        .map_or("–".into(), |v| format!("{v:.digits$}"))
}

/// Writes the runs' CSVs, frame PNGs and charts of volume `v`; returns its report section.
pub fn volume_section(
    out: &Path,
    v: &ArchiveVolume,
    runs: &[Run],
    frame_ms: f64,
) -> Result<Section> {
    let mine: Vec<&Run> = runs.iter().filter(|r| r.volume == v.name).collect();
    let slug = v.name.replace(['/', ' '], "_");
    let mut table = Table {
        head: [
            "scene",
            "frames",
            "first image ms",
            "first rest",
            "Q_I 1 frame",
            "Q_I 10",
            "Q_I 60",
            "Q_I at rest",
            "final rest",
            "Q_I final",
            "SNR final",
            "bytes",
            "of file",
            "frame p50 ms",
            "p95 ms",
            "past budget",
        ]
        .map(String::from)
        .to_vec(),
        rows: Vec::new(),
    };
    let mut images = Vec::new();
    let mut by_time = Vec::new();
    let mut by_bytes = Vec::new();
    let mut by_frame = Vec::new();
    for r in &mine {
        let csv_path = out.join("runs").join(format!("{slug}-{}.csv", r.scene));
        write_csv(&csv_path, r)?;
        let turn_end = r.path.len() - 1;
        let first_image = r
            .samples
            .iter()
            .find(|s| s.splatted > 0)
            .map(|s| s.t.as_secs_f64() * 1e3);
        let rest_cell =
            |step: usize| RestEnd::of(&r.samples, step).map_or_else(|| "–".into(), |e| e.cell());
        let times: Vec<f64> = r
            .samples
            .iter()
            .map(|s| s.frame_time.as_secs_f64() * 1e3)
            .collect();
        let over = times.iter().filter(|t| **t > frame_ms).count();
        let last_q = r.quality.iter().rev().flatten().next();
        table.rows.push(vec![
            r.scene.to_string(),
            r.samples.len().to_string(),
            fmt(first_image, 0),
            rest_cell(0),
            fmt(q_at(r, 0, 1), 1),
            fmt(q_at(r, 0, 10), 1),
            fmt(q_at(r, 0, 60), 1),
            fmt(q_at(r, 0, u64::MAX), 1),
            rest_cell(turn_end),
            fmt(q_at(r, turn_end, u64::MAX), 1),
            fmt(last_q.map(|q| q.snr), 1),
            r.samples.last().map_or(0, |s| s.bytes).to_string(),
            r.file_bytes.to_string(),
            fmt(percentile(&times, 50.0), 1),
            fmt(percentile(&times, 95.0), 1),
            over.to_string(),
        ]);
        let pts = |x: &dyn Fn(&FrameSample) -> f64| -> Vec<(f64, f64)> {
            r.samples
                .iter()
                .zip(&r.quality)
                .filter_map(|(s, q)| q.map(|q| (x(s), q.q_i)))
                .collect()
        };
        by_time.push(Series::new(r.scene, pts(&|s| s.t.as_secs_f64() * 1e3)));
        by_bytes.push(Series::new(
            r.scene,
            pts(&|s| s.bytes as f64)
                .into_iter()
                .filter(|p| p.0 > 0.0)
                .collect(),
        ));
        by_frame.push(Series::new(r.scene, pts(&|s| s.frame as f64)));
        // Frames worth looking at: the first, the 10th, the end of the first rest, the turn's
        // end and the end of the final rest, each rest's end named by how it ended.
        let step0: Vec<&FrameSample> = r.samples.iter().filter(|s| s.step == 0).collect();
        let rest_caption =
            |step: usize, converged: &str, limit: &str| match RestEnd::of(&r.samples, step) {
                Some(e) if e.converged() => converged.to_string(),
                Some(e) => format!("{limit}: {}", e.label()),
                None => limit.to_string(),
            };
        let picks = [
            ("first frame".to_string(), r.samples.first()),
            ("frame 10".to_string(), step0.get(9).copied()),
            (
                rest_caption(0, "converged at rest", "first rest"),
                step0.last().copied(),
            ),
            (
                "first frame after the turn".to_string(),
                r.samples.iter().find(|s| s.step == turn_end),
            ),
            (
                rest_caption(turn_end, "converged after the turn", "rest after the turn"),
                r.samples.last(),
            ),
        ];
        for (caption, s) in picks {
            let Some(s) = s else { continue };
            let Some(img) = &s.image else { continue };
            let file = format!("frames/{slug}-{}-{:04}.png", r.scene, s.frame);
            img.write_png(&out.join(&file), None)?;
            let q = r.quality[(s.frame - 1) as usize];
            images.push((
                file,
                format!(
                    "{} {caption} (frame {}, {:.0} ms, Q_I {})",
                    r.scene,
                    s.frame,
                    s.t.as_secs_f64() * 1e3,
                    fmt(q.map(|q| q.q_i), 1)
                ),
            ));
        }
    }
    let chart_time = format!("charts/{slug}-qi-time.png");
    Chart {
        title: format!("{}: Q_I against time", v.name),
        x_label: "time since opening (ms)".into(),
        y_label: "Q_I (dB, paper units)".into(),
        log_x: true,
        series: by_time,
    }
    .write_png(&out.join(&chart_time), 560, 360)?;
    let chart_bytes = format!("charts/{slug}-qi-bytes.png");
    // Over a fast link every byte can arrive with the first frames: Q_I against bytes is then
    // a vertical line, and Q_I against frames says what the bytes cannot.
    let (title, x_label, series) = if bytes_tell_apart(&by_bytes) {
        (
            "Q_I against bytes received",
            "bytes received (after the last byte: a vertical line)",
            by_bytes,
        )
    } else {
        (
            "Q_I against frames (all bytes within the first frames)",
            "frame",
            by_frame,
        )
    };
    Chart {
        title: format!("{}: {title}", v.name),
        x_label: x_label.into(),
        y_label: "Q_I (dB, paper units)".into(),
        log_x: true,
        series,
    }
    .write_png(&out.join(&chart_bytes), 560, 360)?;
    let d = v.original.dims();
    Ok(Section {
        title: format!(
            "{} ({}×{}×{}, {} channel{})",
            v.name,
            d[0],
            d[1],
            d[2],
            v.original.channel_count(),
            if v.original.channel_count() == 1 {
                ""
            } else {
                "s"
            }
        ),
        text: format!(
            "Compressed file: {} bytes. Each line is one scene; the dips are the 90° turn \
             (a new view restarts accumulation from the most important coefficients held).",
            mine.first().map_or(0, |r| r.file_bytes)
        ),
        charts: vec![chart_time, chart_bytes],
        table,
        images,
    })
}

/// Whether Q_I against bytes received shows more than vertical lines: some run received its
/// bytes over at least four distinct frames' worth (counts per run, not across runs, whose
/// few values each would otherwise add up).
pub fn bytes_tell_apart(by_bytes: &[Series]) -> bool {
    by_bytes.iter().any(|s| {
        let distinct: HashSet<u64> = s.points.iter().map(|p| p.0.to_bits()).collect();
        distinct.len() >= 4
    })
}

/// One CSV row per frame.
fn write_csv(path: &Path, r: &Run) -> Result<()> {
    let mut f = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?,
    );
    writeln!(f, "{},q_i_paper_db,snr_db", FrameSample::CSV_COLUMNS)?;
    for (s, q) in r.samples.iter().zip(&r.quality) {
        writeln!(
            f,
            "{},{},{}",
            s.csv_row(),
            fmt(q.map(|q| q.q_i), 3),
            fmt(q.map(|q| q.snr), 3),
        )?;
    }
    f.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(frame: u64, step: usize, pending: usize, converged: bool) -> FrameSample {
        FrameSample {
            frame,
            step,
            frame_in_step: 1,
            t: Duration::from_millis(17 * frame),
            frame_time: Duration::from_millis(15),
            packets: 10,
            bytes: 78_346,
            coefficients_held: 94_789,
            splatted: 50_000,
            splatted_this_frame: 1_000,
            invisible: 0,
            batches: 1,
            batches_past_deadline: 0,
            pending,
            exact: true,
            converged,
            memory_full: false,
            image: None,
        }
    }

    #[test]
    fn a_rest_cut_at_its_limit_is_not_called_converged() {
        // The reported run: the last frame (431) still had 38 538 coefficients pending.
        let mut samples: Vec<FrameSample> = (1..=240).map(|f| sample(f, 0, 0, f == 240)).collect();
        samples.extend((241..=431).map(|f| sample(f, 7, 38_538 + (431 - f as usize), false)));
        let end = RestEnd::of(&samples, 7).unwrap();
        assert_eq!(end, RestEnd::LimitReached { pending: 38_538 });
        assert!(!end.converged());
        assert_eq!(end.label(), "rest limit reached, 38538 pending");
        assert!(!end.cell().contains("converged"), "{}", end.cell());
        // The first rest did converge, at its last frame.
        let first = RestEnd::of(&samples, 0).unwrap();
        assert!(first.converged());
        assert_eq!(first.label(), "converged");
        assert_eq!(first.cell(), "converged at 4080 ms");
        // A step without frames has no end, and a rest cut while packets still arrive says so.
        assert_eq!(RestEnd::of(&samples, 3), None);
        assert_eq!(
            RestEnd::LimitReached { pending: 0 }.label(),
            "rest limit reached, 0 pending, packets still arriving"
        );
    }

    #[test]
    fn bytes_arriving_at_once_choose_the_frame_chart() {
        // Three runs each with two byte counts: four distinct values across runs, but every
        // run a vertical line.
        let runs = [
            Series::new(
                "single",
                vec![(36_000.0, 20.0), (36_247.0, 50.0), (36_247.0, 72.0)],
            ),
            Series::new("multiview", vec![(30_000.0, 15.0), (36_247.0, 72.0)]),
            Series::new("depth-cued", vec![(33_000.0, 30.0), (36_247.0, 72.0)]),
        ];
        assert!(!bytes_tell_apart(&runs));
        let spread = Series::new(
            "single",
            [400.0, 4_000.0, 20_000.0, 36_247.0]
                .iter()
                .map(|b| (*b, 50.0))
                .collect(),
        );
        assert!(bytes_tell_apart(&[runs[0].clone(), spread]));
    }
}
