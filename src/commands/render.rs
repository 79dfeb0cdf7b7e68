//! `wavesplat render`: X-ray images straight from the coefficients of a volume, from a local
//! `.wsp` file or from a cache, by wavelet splatting (the volume is never reconstructed). A
//! whole local file is drawn in one pass (`open::draw_whole_file`). Otherwise it drives the same
//! progressive render session and frame loop as the window, headless: packets arrive in the
//! order the cache ranks them for the view, and each frame splats what fits in its budget. Options: a byte budget, a time budget, a client memory bound, multiview, depth
//! cueing, a per-frame record (PNG + CSV) and the quality against the full-data image.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use wavesplat_codec::metrics::{q_i_paper_db, snr_db};
use wavesplat_codec::view::patient::PatientView;
use wavesplat_codec::view::{Cue, CueDirection};
use wavesplat_viewer::backend::{select, BackendChoice, Selected};
use wavesplat_viewer::open::{
    draw_whole_file, one_pass_backend, open, Opened, ViewRequest, VolumeLocation,
};
use wavesplat_viewer::remote::is_remote;
use wavesplat_viewer::session::{RenderSession, SessionOptions};
use wavesplat_viewer::{CpuBackend, FrameLoop, Image, RunToEnd};

/// Where the volume comes from and how to look at it (shared by `render` and `view`).
#[derive(Args, Debug, Clone)]
pub struct ViewArgs {
    /// The .wsp file (or use --cache and --volume), or the URL of a published volume
    /// (`https://HOST/PATH/vol.wspx` from any web server or CDN, `s3://BUCKET/KEY` with the
    /// AWS_* variables) to browse by range requests with no wavesplat server (`wavesplat
    /// publish` writes that layout; a plain .wsp URL works too, fetched whole in file order).
    #[arg(required_unless_present = "cache")]
    pub input: Option<PathBuf>,
    /// Cache URL (`https://HOST:PORT` for TLS, `http://HOST:PORT` or `HOST:PORT` for
    /// plaintext) to render from, with --volume; --ca and --token-file (or WAVESPLAT_CA and
    /// WAVESPLAT_TOKEN, a `read` token) say how to reach it. Several nodes over one store,
    /// comma-separated (`https://c1:50051,https://c2:50051`): the stream continues on the next
    /// node when one fails, and nothing is sent twice.
    #[arg(long, requires = "volume", conflicts_with = "input")]
    pub cache: Option<String>,
    /// Name of the volume in the cache.
    #[arg(long, requires = "cache")]
    pub volume: Option<String>,
    /// CA and token for --cache.
    #[command(flatten)]
    pub security: super::security::ClientSecurityArgs,
    /// Azimuth α of the view (radians, paper §3.1). At α = β = 0 the rays run along the
    /// volume's x axis and the image shows its y–z plane, y to the right, z up; α turns the
    /// view about z (α = π/2: along y, x to the left), β tilts it towards z (β = π/2: along z,
    /// seen from above). Default 0.66 with β 0.91, an oblique view; a volume one voxel thin
    /// (a single slice) is seen face-on instead.
    #[arg(long, allow_negative_numbers = true)]
    pub alpha: Option<f64>,
    /// View named from the side of the patient it is seen from: anterior, posterior, left,
    /// right, superior or inferior (radiological display: anterior shows the patient's left on
    /// the right). Needs a volume whose source gave its orientation (DICOM, NIfTI, NRRD,
    /// MetaImage); replaces --alpha/--beta.
    #[arg(long, value_name = "SIDE", conflicts_with_all = ["alpha", "beta"])]
    pub view: Option<String>,
    /// Elevation β of the view (radians; default 0.91, see --alpha).
    #[arg(long, allow_negative_numbers = true)]
    pub beta: Option<f64>,
    /// Image size WxH (per view with --multiview).
    #[arg(long, default_value = "256x256")]
    pub size: String,
    /// Pixels per unit of voxel spacing: per millimetre when the volume's spacing is in mm (as
    /// DICOM, NIfTI, NRRD and MetaImage give it), per voxel for unit spacing (default: fit the
    /// volume: the ellipsoid inscribed in its box fills the image, so an axis view shows the
    /// whole box and an oblique one what a head or body occupies). Anisotropic volumes are
    /// drawn in their physical shape.
    #[arg(long)]
    pub zoom: Option<f64>,
    /// Pan of the image centre from the volume centre, in units of spacing (mm) along the
    /// screen axes: X,Y.
    #[arg(long, allow_hyphen_values = true)]
    pub pan: Option<String>,
    /// Three views side by side from one set of footprints (paper §3.1).
    #[arg(long)]
    pub multiview: bool,
    /// Depth cueing (paper §3.2): a point d units of spacing (mm, or voxels for unit spacing)
    /// behind the light-facing side of the volume is weighted e^(−k·d), so k = 2 / depth
    /// leaves the far side of a volume `depth` units deep at 14 % (e^−2). `auto` takes 2 / the
    /// volume's diagonal (printed); 0 disables.
    #[arg(long, value_name = "K|auto", default_value = "0", value_parser = parse_cue_k)]
    pub cue_k: CueK,
    /// Depth-cue direction α,β (default: along the view direction).
    #[arg(long, allow_hyphen_values = true)]
    pub cue_dir: Option<String>,
    /// Largest memory for retained coefficients, in bytes (suffixes k, M, G); beyond it the
    /// least visible are dropped after splatting and asked for again after a view change.
    /// 0 keeps nothing but the footprint tables and the image (the paper's network computer).
    #[arg(long, value_parser = super::parse_bytes)]
    pub client_memory: Option<u64>,
    /// Plan each new view exactly before drawing it. By default a view without cached
    /// footprint tables is drawn at once with coarse preview tables while the exact ones are
    /// built in the background (tens to hundreds of ms), then redrawn with them.
    #[arg(long)]
    pub no_preview: bool,
    /// Of a time series, show time point N (counting from 0; default 0).
    #[arg(long, value_name = "N")]
    pub time_point: Option<usize>,
    /// Time points per second when a time series plays (the window's playback, space to
    /// play and pause; the animated PNG of `render --time-points`).
    #[arg(long, default_value_t = 10.0)]
    pub fps: f64,
    /// The most pixels drawn across the volume's finest voxel. A view magnified beyond it (a
    /// large --zoom, or a small volume in a large image) is drawn at this resolution and
    /// magnified to the size asked for by bilinear interpolation. The volume has no detail
    /// finer than a voxel: at 16 the image keeps to the splats' accuracy (≥ 50 dB against the
    /// exact line integrals), and the footprint tables and splats stop growing with the zoom
    /// (×10 on an MRI at 1024²: 1.7 GB and 9 s with every pixel drawn, 0.3 GB and 1.0 s
    /// bounded). Lower is faster and blurrier; 0 draws every pixel.
    #[arg(long, value_name = "N", default_value_t = wavesplat_viewer::magnify::DEFAULT_MAX_PIXELS_PER_VOXEL)]
    pub max_pixels_per_voxel: f64,
}

/// Arguments of `wavesplat render`.
#[derive(Args, Debug)]
pub struct RenderArgs {
    #[command(flatten)]
    pub view: ViewArgs,
    /// Use at most this many bytes of packets (the ones the cache ranks first for this view).
    /// From a local file the first packet is always used, even when it is larger, so that there
    /// is an image.
    #[arg(long, value_parser = super::parse_bytes)]
    pub bytes: Option<u64>,
    /// Stop after this much time in milliseconds (default: until every packet is splatted).
    #[arg(long)]
    pub budget_ms: Option<f64>,
    /// Time budget of one frame in milliseconds (the loop's granularity).
    #[arg(long, default_value_t = 16.6)]
    pub frame_ms: f64,
    /// Also render every coefficient of the volume and report the image's quality against it
    /// (Q_I in the paper's units and the conventional SNR), both at the size drawn (before a
    /// view magnified beyond --max-pixels-per-voxel is magnified back).
    #[arg(long)]
    pub reference: bool,
    /// Write per-frame figures (frames.csv) and frame PNGs (1, 2, 4, 8, … and the last) here.
    #[arg(long)]
    pub record: Option<PathBuf>,
    /// Draw a whole local file through the progressive frame loop, as the window does (frames,
    /// preview tables, batches timed to the frame). Without it, a local file rendered without
    /// --bytes, --budget-ms, --record or --client-memory is drawn in one pass: every packet
    /// decoded while the view is planned, then every coefficient splatted: the same image (up
    /// to the order of f32 additions) in about 70 % of the time.
    #[arg(long)]
    pub progressive: bool,
    /// Of a time series, draw time points A to B (both included; `all`: every one): one PNG
    /// each (t0000.png, …) in the directory -o names, all through one window so that they
    /// compare, and an animated PNG of them (animation.png, at --fps).
    #[arg(long, value_name = "A..B", conflicts_with = "time_point")]
    pub time_points: Option<String>,
    /// Output PNG (a directory with --time-points).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Also write the image as raw f32 (H rows of W little-endian floats; RGB interleaved).
    #[arg(long)]
    pub raw: Option<PathBuf>,
    #[command(flatten)]
    pub backend: super::BackendArgs,
}

/// The depth-cue extinction asked for on the command line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CueK {
    /// Per unit of spacing (0: no depth cueing).
    PerUnit(f64),
    /// The volume's [`Cue::default_extinction`].
    FromVolume,
}

fn parse_cue_k(s: &str) -> Result<CueK, String> {
    if s.trim().eq_ignore_ascii_case("auto") {
        return Ok(CueK::FromVolume);
    }
    match s.trim().parse::<f64>() {
        Ok(k) if k.is_finite() && k >= 0.0 => Ok(CueK::PerUnit(k)),
        _ => Err(format!(
            "{s:?} is not an extinction: give a finite number >= 0 per unit of spacing \
             (e.g. 0.01 per mm), or `auto`"
        )),
    }
}

fn pair(s: &str, what: &str) -> Result<[f64; 2]> {
    let p: Vec<&str> = s.split(',').collect();
    if p.len() != 2 {
        bail!("{what} must be two numbers A,B, got {s:?}");
    }
    let a: f64 = p[0]
        .trim()
        .parse()
        .with_context(|| format!("{what}: {s:?}"))?;
    let b: f64 = p[1]
        .trim()
        .parse()
        .with_context(|| format!("{what}: {s:?}"))?;
    if !a.is_finite() || !b.is_finite() {
        bail!("{what} must be finite, got {s:?}");
    }
    Ok([a, b])
}

impl ViewArgs {
    /// What the options ask to see, parsed and checked.
    pub fn request(&self) -> Result<ViewRequest> {
        let (width, height) = self
            .size
            .split_once(['x', ','])
            .and_then(|(w, h)| {
                Some((
                    w.trim().parse::<usize>().ok()?,
                    h.trim().parse::<usize>().ok()?,
                ))
            })
            .with_context(|| format!("--size must be WxH, got {:?}", self.size))?;
        let p = self.max_pixels_per_voxel;
        if !(p == 0.0 || (p.is_finite() && p >= 1.0)) {
            bail!("--max-pixels-per-voxel must be 0 (draw every pixel) or at least 1, got {p}");
        }
        let (k, cue_k_from_volume) = match self.cue_k {
            CueK::PerUnit(k) => (k, false),
            // A placeholder until the volume is known (`ViewRequest::spec_for`).
            CueK::FromVolume => (1.0, true),
        };
        if k <= 0.0 && self.cue_dir.is_some() {
            bail!("--cue-dir sets the direction of depth cueing, which is off: give --cue-k K (or auto) too");
        }
        let cue = if k > 0.0 {
            let direction = match &self.cue_dir {
                Some(s) => {
                    let [alpha, beta] = pair(s, "--cue-dir")?;
                    CueDirection::Angles { alpha, beta }
                }
                None => CueDirection::View,
            };
            Some(Cue { k, direction })
        } else {
            None
        };
        let side = match &self.view {
            Some(name) => Some(PatientView::from_name(name).context("--view")?),
            None => None,
        };
        let pan = match &self.pan {
            Some(p) => Some(pair(p, "--pan")?),
            None => None,
        };
        Ok(ViewRequest {
            alpha: self.alpha,
            beta: self.beta,
            side,
            width,
            height,
            zoom: self.zoom,
            pan,
            multiview: self.multiview,
            cue,
            cue_k_from_volume,
            time_point: self.time_point,
            max_pixels_per_voxel: (self.max_pixels_per_voxel > 0.0)
                .then_some(self.max_pixels_per_voxel),
        })
    }

    /// Where the volume is: a file (read here, with advice when it is not a `.wsp`), a
    /// published URL or a cache.
    pub fn location(&self) -> Result<VolumeLocation> {
        match (&self.input, &self.cache, &self.volume) {
            (Some(path), _, _) if path.to_str().is_some_and(is_remote) => {
                Ok(VolumeLocation::Published {
                    url: path.to_str().unwrap_or_default().to_string(),
                    ca: self.security.options()?.ca,
                })
            }
            (Some(path), _, _) => Ok(VolumeLocation::File {
                path: path.clone(),
                bytes: super::read_wsp(path)?,
            }),
            (None, Some(urls), Some(name)) => Ok(VolumeLocation::Cache {
                urls: urls.clone(),
                connect: self.security.options()?,
                name: name.clone(),
            }),
            _ => bail!("give a .wsp file, or --cache URL and --volume NAME"),
        }
    }

    /// Session settings from the options.
    pub fn session_options(&self) -> SessionOptions {
        SessionOptions {
            memory_bound: self
                .client_memory
                .map(|b| b.min(usize::MAX as u64) as usize),
            preview: (!self.no_preview).then(SessionOptions::default_preview),
            ..SessionOptions::default()
        }
    }
}

/// Per-frame record: a CSV row per frame and PNGs of frames 1, 2, 4, ….
struct Recorder {
    dir: PathBuf,
    csv: std::fs::File,
    next_png: u64,
}

impl Recorder {
    fn new(dir: &PathBuf, with_quality: bool) -> Result<Recorder> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let mut csv = std::fs::File::create(dir.join("frames.csv"))?;
        write!(
            csv,
            "frame,t_ms,frame_ms,packets,bytes,coefficients_held,splatted,pending,batches"
        )?;
        if with_quality {
            write!(csv, ",q_i_paper_db,snr_db")?;
        }
        writeln!(csv)?;
        Ok(Recorder {
            dir: dir.clone(),
            csv,
            next_png: 1,
        })
    }
}

/// Runs the subcommand.
pub fn run(a: RenderArgs) -> Result<()> {
    let view = a.view.request()?;
    view.spec()?;
    if a.time_points.is_none() {
        super::check_output(&a.output)?;
    }
    if let Some(r) = &a.raw {
        super::check_output(r)?;
        if a.time_points.is_some() {
            bail!(
                "--raw writes one image: it takes --time-point T, not --time-points (which \
                 writes a PNG per time point and an animation)"
            );
        }
        if *r == a.output {
            bail!(
                "--raw and -o both name {}: the raw floats would replace the PNG",
                r.display()
            );
        }
    }
    if let Some(input) = &a.view.input {
        for out in std::iter::once(&a.output).chain(&a.raw) {
            super::check_not_input(out, input)?;
        }
    }
    // Bounded (a day) so that a time in the future can be formed from them.
    const MAX_MS: f64 = 86_400_000.0;
    if !(a.frame_ms.is_finite() && a.frame_ms > 0.0 && a.frame_ms <= MAX_MS) {
        bail!(
            "--frame-ms must be a positive number of milliseconds up to {MAX_MS} (a day), got {}",
            a.frame_ms
        );
    }
    if let Some(b) = a.budget_ms {
        if !(b.is_finite() && (0.0..=MAX_MS).contains(&b)) {
            bail!(
                "--budget-ms must be a non-negative number of milliseconds up to {MAX_MS} (a \
                 day), got {b}"
            );
        }
    }
    // The times printed count from here (the request), session start-up included and the
    // reference rendering left out.
    let request = Instant::now();
    let location = a.view.location()?;
    let one_pass_asked = !a.progressive
        && a.bytes.is_none()
        && a.budget_ms.is_none()
        && a.record.is_none()
        && a.view.client_memory.is_none();
    let series = matches!(&location, VolumeLocation::File { bytes, .. }
        if wavesplat_codec::format::series::is_series(bytes));
    // A series in a cache or published: one time point, progressively (below). A time point
    // of a volume that is no series is refused before any way of drawing it (bricked too).
    let cached = matches!(
        location,
        VolumeLocation::Cache { .. } | VolumeLocation::Published { .. }
    );
    if cached && a.time_points.is_some() {
        bail!("--time-points draws a local time series file; from a cache or a URL, render one --time-point N at a time (or `view` it to play)");
    }
    if !series && !cached && (a.view.time_point.is_some() || a.time_points.is_some()) {
        bail!("--time-point and --time-points apply to a time series: a local file (one `compress` made from a 4D file, a directory of time steps or --phantom beating) or one in a cache or published");
    }
    if let VolumeLocation::File { path, bytes } = &location {
        if series {
            if a.reference {
                bail!(
                    "{}: --reference does not apply to a time series yet (compress the time \
                     point alone with `compress --time-point N` and render that)",
                    path.display()
                );
            }
            if one_pass_asked {
                note_cpu_only(&a, "a time series");
                return render_series(&a, &view, path, bytes, request);
            }
            if a.time_points.is_some() {
                bail!("--time-points draws each time point in one pass: leave out --progressive, --bytes, --budget-ms, --record and --client-memory");
            }
            // Drawn progressively below: the time point's components as one volume.
        }
        if wavesplat_codec::format::bricked::is_bricked(bytes) && one_pass_asked && !a.reference {
            note_cpu_only(&a, "a bricked volume");
            return render_bricked(&a, &view, path, bytes, request);
        }
    }
    let volume = location.describe();
    let (header, opened, spec) = open(location, &view, a.bytes)?;
    let opened_after = request.elapsed();
    say_cue_k(&view, &spec);
    let reference_started = Instant::now();
    let reference = if a.reference {
        Some(
            opened
                .reference_image(&header, &spec)
                .context("rendering the reference")?,
        )
    } else {
        None
    };
    let reference_took = reference_started.elapsed();
    let since_request = || request.elapsed().saturating_sub(reference_took);
    // A bricked file comes here only to be drawn progressively (or with a reference).
    let one_pass = one_pass_asked
        && matches!(opened, Opened::File { .. })
        && opened.bricked_volume().is_none();
    let (choice, why) = if one_pass {
        one_pass_backend(
            a.backend.choice(),
            &header,
            &spec,
            rayon::current_num_threads(),
        )
    } else {
        (a.backend.choice(), None)
    };
    // Opening a GPU device takes 100-300 ms (more on a software adapter, which then is not
    // even used): a progressive run draws on the CPU meanwhile and switches when a hardware
    // device is ready. Not with a client memory bound: a switch re-splats what is held, and
    // the bound may have dropped coefficients already drawn.
    let probe_aside =
        !one_pass && matches!(choice, BackendChoice::Auto) && a.view.client_memory.is_none();
    let (mut selected, mut probe) = if probe_aside {
        let probe = ProbeAside::spawn("gpu probe", || select(BackendChoice::Auto))
            .context("starting the GPU probe")?;
        (
            Selected {
                backend: Box::new(CpuBackend::new()),
                reason: "cpu backend while a GPU is looked for".into(),
            },
            Some(probe),
        )
    } else {
        let s = select(choice).context("choosing the accumulation backend")?;
        (s, None)
    };
    eprintln!("backend: {}", why.unwrap_or(selected.reason));
    if let (true, Opened::File { source }) = (one_pass, &opened) {
        let whole = draw_whole_file(source.file_bytes(), &spec, &mut selected.backend)
            .with_context(|| format!("rendering {volume}"))?;
        let done_after = since_request();
        let image = &whole.image;
        write_outputs(image, &a, &view)?;
        outln!(
            "wrote {} ({}) from {}: {} packets, {} bytes, {} coefficients splatted in one pass ({} backend){}",
            a.output.display(),
            output_size(image, &view),
            volume,
            whole.packets,
            whole.bytes,
            whole.coefficients,
            selected.backend.name(),
            left_out(whole.stats.vanished)
        );
        warn_if_nothing_seen(whole.coefficients == 0 || whole.stats.splatted > 0);
        outln!(
            "opened in {:.1} ms, done {:.1} ms after the request (start-up included; decoding and planning together {:.1} ms, splatting {:.1} ms: in the backend's accumulate {:.1} ms and read-back {:.1} ms, the rest making records)",
            opened_after.as_secs_f64() * 1e3,
            done_after.as_secs_f64() * 1e3,
            whole.decode_and_plan.as_secs_f64() * 1e3,
            whole.splat.as_secs_f64() * 1e3,
            whole.accumulate.as_secs_f64() * 1e3,
            whole.read.as_secs_f64() * 1e3
        );
        report_quality(reference.as_ref(), image);
        return Ok(());
    }
    let session = match opened.bricked_volume() {
        Some(bricked) => {
            RenderSession::new_bricked(bricked, spec, selected.backend, a.view.session_options())?
        }
        None => RenderSession::new(
            header.clone(),
            spec,
            selected.backend,
            a.view.session_options(),
        )?,
    };
    let mut frames = FrameLoop::new(session, opened.into_source());
    let mut recorder = match &a.record {
        Some(d) => Some(Recorder::new(d, reference.is_some())?),
        None => None,
    };
    let run = RunToEnd {
        frame: Duration::from_secs_f64(a.frame_ms / 1e3),
        deadline: a.budget_ms.map(|b| Duration::from_secs_f64(b / 1e3)),
        // A restarting cache takes seconds; the stream resumes with what the viewer holds.
        patience: Duration::from_secs(30),
    };
    let run_started = since_request();
    let outcome = frames.run_to_end(&run, |frames, n, report, at| -> Result<()> {
        if let Some(aside) = &probe {
            match aside.try_recv() {
                Ok(Ok(found)) => {
                    probe = None;
                    let mut backend = found.backend;
                    if backend.gpu().is_some() {
                        frames
                            .session
                            .replace_backend(backend)
                            .context("switching to the GPU backend")?;
                        eprintln!(
                            "backend: {} (from frame {n}; the CPU drew until then)",
                            found.reason
                        );
                    } else {
                        eprintln!("backend: {}", found.reason);
                    }
                }
                Ok(Err(e)) => {
                    probe = None;
                    eprintln!("backend: cpu backend (no GPU backend: {e})");
                }
                Err(std::sync::mpsc::TryRecvError::Disconnected) => probe = None,
                Err(std::sync::mpsc::TryRecvError::Empty) => {}
            }
        }
        let Some(rec) = &mut recorder else {
            return Ok(());
        };
        let image = frames.session.image()?;
        let (status, stats) = (frames.source_status(), frames.session.stats());
        write!(
            rec.csv,
            "{n},{:.3},{:.3},{},{},{},{},{},{}",
            at.as_secs_f64() * 1e3,
            report.elapsed.as_secs_f64() * 1e3,
            status.packets,
            status.bytes,
            stats.coefficients_held,
            stats.splatted_in_view,
            report.pending,
            report.batches
        )?;
        if let Some(r) = &reference {
            write!(
                rec.csv,
                ",{:.3},{:.3}",
                q_i_paper_db(&r.data, &image.data),
                snr_db(&r.data, &image.data)
            )?;
        }
        writeln!(rec.csv)?;
        if n == rec.next_png {
            view.shown(&image)
                .write_png(&rec.dir.join(format!("frame-{n:05}.png")), None)?;
            rec.next_png *= 2;
        }
        Ok(())
    })?;
    let (n, elapsed) = (outcome.frames, outcome.elapsed);
    let first_image = outcome.first_image.map(|t| run_started + t);
    let done_after = since_request();
    let image = frames.session.image()?;
    if let Some(rec) = &recorder {
        view.shown(&image)
            .write_png(&rec.dir.join(format!("frame-{n:05}.png")), None)?;
    }
    write_outputs(&image, &a, &view)?;
    let status = frames.source_status();
    let stats = frames.session.stats();
    outln!(
        "wrote {} ({}) from {}: {} packets, {} bytes received, {} coefficients held, {} splatted, {} frames in {:.1} ms ({} backend)",
        a.output.display(),
        output_size(&image, &view),
        volume,
        status.packets,
        status.bytes,
        stats.coefficients_held,
        stats.splatted_in_view,
        n,
        elapsed.as_secs_f64() * 1e3,
        frames.session.backend_name()
    );
    if status.object_bytes > 0 {
        outln!(
            "range requests: {} ({} before the first packet), {} of {} bytes fetched ({:.1} %)",
            status.requests,
            status.requests_before_first_packet,
            status.received_bytes,
            status.object_bytes,
            100.0 * status.received_bytes as f64 / status.object_bytes as f64
        );
    }
    if a.view.cache.is_some() {
        outln!(
            "cache stream: {} reconnections, {} packets sent again",
            status.reconnects,
            status.resent
        );
    }
    if let Some(t) = first_image {
        outln!(
            "opened in {:.1} ms, first image {:.1} ms and done {:.1} ms after the request (start-up included)",
            opened_after.as_secs_f64() * 1e3,
            t.as_secs_f64() * 1e3,
            done_after.as_secs_f64() * 1e3
        );
    }
    report_quality(reference.as_ref(), &image);
    Ok(())
}

/// Says which extinction `--cue-k auto` took from the volume.
fn say_cue_k(view: &ViewRequest, spec: &wavesplat_codec::view::ViewSpec) {
    if let (true, Some(cue)) = (view.cue_k_from_volume, spec.view.cue) {
        outln!(
            "depth cueing: k = {:.6} per unit of spacing (2 / the volume's diagonal)",
            cue.k
        );
    }
}

/// Writes the PNG and, when asked, the raw image.
fn write_outputs(drawn: &Image, a: &RenderArgs, view: &ViewRequest) -> Result<()> {
    let image = view.shown(drawn);
    image
        .write_png(&a.output, None)
        .with_context(|| format!("writing {}", a.output.display()))?;
    if let Some(r) = &a.raw {
        image
            .write_raw(r)
            .with_context(|| format!("writing {}", r.display()))?;
    }
    Ok(())
}

/// The size of the image written for `drawn`: the size asked for, and the size it was drawn at
/// when the view was magnified beyond --max-pixels-per-voxel.
fn output_size(drawn: &Image, view: &ViewRequest) -> String {
    let panels = view.panels();
    let asked = format!("{}x{}", view.width * panels, view.height);
    if drawn.width == view.width * panels && drawn.height == view.height {
        asked
    } else {
        format!(
            "{asked}, drawn at {}x{} and magnified: --max-pixels-per-voxel",
            drawn.width, drawn.height
        )
    }
}

/// Prints the image's quality against the reference, when one was drawn.
fn report_quality(reference: Option<&Image>, image: &Image) {
    if let Some(r) = reference {
        outln!(
            "quality against the full-data image: Q_I {:.2} dB (paper units), SNR {:.2} dB",
            q_i_paper_db(&r.data, &image.data),
            snr_db(&r.data, &image.data)
        );
    }
}

/// What a render summary says of the splats left out because their footprints vanish (a ψ along
/// the direction of a view along an axis integrates to zero), summed over the views: nothing
/// when there are none.
fn left_out(vanished: usize) -> String {
    if vanished == 0 {
        String::new()
    } else {
        format!("; {vanished} splats left out (seen along an axis, the wavelets along it project to zero)")
    }
}

/// Says that `--gpu` is not taken where the one-pass drawing of `what` runs on the CPU only.
fn note_cpu_only(a: &RenderArgs, what: &str) {
    if a.backend.choice() == BackendChoice::Gpu {
        eprintln!(
            "note: --gpu: {what} is drawn in one pass on the CPU (--progressive draws it with \
             the backend asked for)"
        );
    }
}

/// Warns where the view saw nothing of the volume: the image is black because nothing is in
/// it (a pan or zoom off the volume), not because the volume is empty.
fn warn_if_nothing_seen(seen: bool) {
    if !seen {
        eprintln!(
            "warning: the view sees none of the volume (nothing of it on screen): the image is \
             empty; check --pan and --zoom"
        );
    }
}

/// `render` of a local bricked file in one pass: every brick the view sees, drawn on the CPU
/// and added up ([`wavesplat_viewer::bricked`]). (Progressive runs go through the session, as
/// any file.)
fn render_bricked(
    a: &RenderArgs,
    view: &ViewRequest,
    path: &std::path::Path,
    bytes: &[u8],
    request: Instant,
) -> Result<()> {
    let (file, first) = wavesplat_viewer::bricked::parse_with_first(bytes)
        .with_context(|| format!("reading {}", path.display()))?;
    let whole = wavesplat_viewer::bricked::whole_geometry(&file.manifest, &first);
    let spec = view.spec_for_volume(&whole, file.manifest.placement.as_ref())?;
    say_cue_k(view, &spec);
    let drawn = wavesplat_viewer::bricked::draw_bricked_file(
        bytes,
        &spec,
        &mut wavesplat_viewer::CpuBackend::new(),
    )
    .with_context(|| format!("rendering {}", path.display()))?;
    write_outputs(&drawn.image, a, view)?;
    outln!(
        "wrote {} ({}) from {}: {} of {} bricks drawn, {} bytes, {} coefficients splatted \
         (cpu backend) in {:.1} ms",
        a.output.display(),
        output_size(&drawn.image, view),
        path.display(),
        drawn.drawn,
        drawn.bricks,
        drawn.bytes,
        drawn.coefficients,
        request.elapsed().as_secs_f64() * 1e3
    );
    warn_if_nothing_seen(drawn.drawn > 0);
    Ok(())
}

/// `render` of a local series file: one time point to -o, or a range of them as PNGs and an
/// animated PNG in the directory -o names. Drawn in one pass on the CPU, each time point from
/// its own group's components.
fn render_series(
    a: &RenderArgs,
    view: &wavesplat_viewer::open::ViewRequest,
    path: &std::path::Path,
    bytes: &[u8],
    request: std::time::Instant,
) -> Result<()> {
    use wavesplat_codec::format::series::parse_series;
    use wavesplat_viewer::series::{draw_series_point, series_header};
    use wavesplat_viewer::{CpuBackend, Image};
    let file = parse_series(bytes).with_context(|| format!("reading {}", path.display()))?;
    let m = &file.manifest;
    let points = m.points.len();
    let header = series_header(&file).with_context(|| format!("reading {}", path.display()))?;
    let spec = view.spec_for_volume(&header.geometry, m.space.placement.as_ref())?;
    say_cue_k(view, &spec);
    let when = |t: usize| {
        if m.times_known {
            format!(" at {:.3} s", m.points[t].time)
        } else {
            String::new()
        }
    };
    let draw = |t: usize| {
        draw_series_point(bytes, t, &spec, &mut CpuBackend::new())
            .with_context(|| format!("rendering time point {t} of {}", path.display()))
    };
    let Some(range) = &a.time_points else {
        let t = a.view.time_point.unwrap_or(0);
        if t >= points {
            bail!(
                "--time-point {t}: the series has {points} time points (0..={})",
                points - 1
            );
        }
        let d = draw(t)?;
        write_outputs(&d.image, a, view)?;
        outln!(
            "wrote {} ({}) from {}: time point {t} of {points}{}, {} components, {} bytes, {} \
             coefficients splatted (cpu backend) in {:.1} ms{}",
            a.output.display(),
            output_size(&d.image, view),
            path.display(),
            when(t),
            d.components,
            d.bytes,
            d.coefficients,
            request.elapsed().as_secs_f64() * 1e3,
            if a.view.time_point.is_none() && points > 1 {
                " (--time-point N or --time-points A..B for others)"
            } else {
                ""
            }
        );
        return Ok(());
    };
    if !(a.view.fps.is_finite() && a.view.fps > 0.0 && a.view.fps <= 1000.0) {
        bail!(
            "--fps {}: a rate in (0, 1000] frames per second",
            a.view.fps
        );
    }
    let range = super::series::parse_time_range(range, points)?;
    std::fs::create_dir_all(&a.output)
        .with_context(|| format!("creating {}", a.output.display()))?;
    let progress = wavesplat_harness::console::Progress::new("render");
    let mut frames: Vec<Image> = Vec::with_capacity(range.clone().count());
    let mut read = 0u64;
    for t in range.clone() {
        progress.stage(&format!("time point {t} of {points}"));
        let d = draw(t)?;
        read += d.bytes;
        frames.push(view.shown(&d.image));
    }
    progress.finish();
    // One window for all, so that the frames compare: the widest of theirs.
    let window = frames
        .iter()
        .map(Image::auto_window)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (l, h)| {
            (lo.min(l), hi.max(h))
        });
    let window = if window.1 > window.0 {
        window
    } else {
        (window.0, window.0 + 1.0)
    };
    for (t, f) in range.clone().zip(&frames) {
        let p = a.output.join(format!("t{t:04}.png"));
        f.write_png(&p, Some(window))
            .with_context(|| format!("writing {}", p.display()))?;
    }
    let anim = a.output.join("animation.png");
    let delay = (1000.0 / a.view.fps).round().clamp(1.0, 65535.0) as u16;
    Image::write_animated_png(&frames, &anim, window, delay)
        .with_context(|| format!("writing {}", anim.display()))?;
    outln!(
        "wrote {} time points ({}..={}) of {points} from {} to {}: t{:04}.png … t{:04}.png and \
         animation.png at {} frames/s; {read} bytes of components read in {:.1} ms",
        frames.len(),
        range.start(),
        range.end(),
        path.display(),
        a.output.display(),
        range.start(),
        range.end(),
        a.view.fps,
        request.elapsed().as_secs_f64() * 1e3
    );
    Ok(())
}

/// A question answered on a thread of its own (the GPU probe) while the caller goes on. Dropping
/// it waits for that thread: the probe loads the Vulkan driver (`dlopen` of lavapipe runs LLVM's
/// static constructors under the dynamic loader's lock), and a process that returns from `main`
/// meanwhile deadlocks in `exit`, whose `_dl_fini` waits for that same lock (seen once in about
/// 125 renders of a 32×32 image, which finishes before the probe does).
struct ProbeAside<T> {
    answer: std::sync::mpsc::Receiver<T>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl<T: Send + 'static> ProbeAside<T> {
    fn spawn(name: &str, ask: impl FnOnce() -> T + Send + 'static) -> std::io::Result<Self> {
        let (tx, answer) = std::sync::mpsc::channel();
        let thread = std::thread::Builder::new()
            .name(name.into())
            .spawn(move || {
                let _ = tx.send(ask());
            })?;
        Ok(ProbeAside {
            answer,
            thread: Some(thread),
        })
    }

    /// The answer if it has come.
    fn try_recv(&self) -> Result<T, std::sync::mpsc::TryRecvError> {
        self.answer.try_recv()
    }
}

impl<T> Drop for ProbeAside<T> {
    fn drop(&mut self) {
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::ProbeAside;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    use std::time::Duration;

    /// The caller goes on while the probe runs, and letting go of an unanswered probe waits
    /// until its thread has finished (so the process never exits in the middle of it).
    #[test]
    fn dropping_an_unanswered_probe_waits_for_its_thread() {
        let finished = Arc::new(AtomicBool::new(false));
        let f = finished.clone();
        let aside = ProbeAside::spawn("slow probe", move || {
            std::thread::sleep(Duration::from_millis(300));
            f.store(true, Ordering::SeqCst);
            7
        })
        .unwrap();
        assert!(aside.try_recv().is_err(), "answered before it could have");
        drop(aside);
        assert!(
            finished.load(Ordering::SeqCst),
            "the probe thread outlived its handle"
        );
    }

    /// A probe that answered gives the answer once.
    #[test]
    fn an_answered_probe_gives_its_answer() {
        let aside = ProbeAside::spawn("quick probe", || 7).unwrap();
        let mut got = None;
        for _ in 0..1000 {
            if let Ok(v) = aside.try_recv() {
                got = Some(v);
                break;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        assert_eq!(got, Some(7));
        assert!(aside.try_recv().is_err());
    }
}
