//! Opening a volume for viewing, the one way `render`, `view` and the benches do it: a
//! `ViewRequest` (angles or a named patient side, image size, zoom or the fitting zoom, pan,
//! multiview, depth cue) becomes the `ViewSpec` for the volume once its header is known; a
//! `VolumeLocation` (a `.wsp` file's bytes, a published volume's URL, or a cache and a volume
//! name) becomes a packet source ranked for that view (`open` → `Opened`). It also owns getting
//! every coefficient of an opened volume and the image they draw (the reference of `render
//! --reference`), and decoding a file's packets in parallel (`load_coefficients`).

use crate::remote::{fetch_wsp, RangeSource, RangeSourceOptions};
use crate::source::{CacheSource, CacheSourceOptions, FileSource, PacketSource, SourceError};
use crate::{Image, RenderError, RenderOptions, Renderer};
use std::path::PathBuf;
use thiserror::Error;
use wavesplat_client::{ConnectOptions, VolumeKey};
use wavesplat_codec::format::packet::{decode_packets, Coefficient, PacketError};
use wavesplat_codec::format::{check_kept, parse_file, FormatError, Header};
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::patient::{PatientView, PatientViewError};
use wavesplat_codec::view::{Cue, Orientation, View, ViewError, ViewSpec};
use wavesplat_codec::volume::Placement;

/// Why a volume could not be opened, or its reference drawn.
#[derive(Debug, Error)]
pub enum OpenError {
    /// The volume's source failed (file, range requests or cache).
    #[error("opening {what}")]
    Source {
        /// The volume, in words.
        what: String,
        /// Why.
        #[source]
        source: SourceError,
    },
    /// The file is not a valid `.wsp` file.
    #[error("reading {what}")]
    Format {
        /// The volume, in words.
        what: String,
        /// Why.
        #[source]
        source: FormatError,
    },
    /// A packet could not be decoded.
    #[error("decoding a packet")]
    Packet(#[from] PacketError),
    /// The view is invalid.
    #[error("invalid view")]
    View(#[from] ViewError),
    /// A named patient view cannot be resolved for this volume.
    #[error("the {side} view")]
    Patient {
        /// The side asked for.
        side: String,
        /// Why.
        #[source]
        source: PatientViewError,
    },
    /// The cache failed while every coefficient was fetched.
    #[error("fetching every coefficient from the cache")]
    Client(#[from] wavesplat_client::ClientError),
    /// Drawing the reference image failed.
    #[error(transparent)]
    Render(#[from] RenderError),
    /// The async runtime for the cache could not be started.
    #[error("starting an async runtime: {0}")]
    Runtime(#[from] std::io::Error),
}

/// How to look at a volume, before the volume is known: what a user asks for.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewRequest {
    /// Azimuth α (radians); `None`: [`DEFAULT_ALPHA`], or face-on for a volume one voxel thin
    /// ([`face_on_angles`]).
    pub alpha: Option<f64>,
    /// Elevation β (radians); `None` as for α.
    pub beta: Option<f64>,
    /// A view named from the side of the patient; replaces α and β once the volume's placement
    /// is known.
    pub side: Option<PatientView>,
    /// Image width (per view with multiview).
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Pixels per unit of spacing; `None`: fit the volume ([`Camera::fitting_zoom`]).
    ///
    /// [`Camera::fitting_zoom`]: wavesplat_codec::view::Camera::fitting_zoom
    pub zoom: Option<f64>,
    /// Pan of the image centre in units of spacing along the screen axes.
    pub pan: Option<[f64; 2]>,
    /// Three views side by side.
    pub multiview: bool,
    /// Depth cueing.
    pub cue: Option<Cue>,
    /// Whether the cue's extinction is the volume's [`Cue::default_extinction`], set once the
    /// volume is known (`cue.k` is a placeholder until then).
    pub cue_k_from_volume: bool,
    /// Of a time series, the time point shown (`None`: the first).
    pub time_point: Option<usize>,
    /// The most pixels a view draws across the volume's finest voxel; a view magnified beyond
    /// it is drawn smaller and magnified back ([`crate::magnify`]). `None`: every pixel drawn.
    pub max_pixels_per_voxel: Option<f64>,
}

/// The azimuth α of a view when none is given: an oblique view that shows a volume's three
/// axes.
pub const DEFAULT_ALPHA: f64 = 0.66;
/// The elevation β of a view when none is given.
pub const DEFAULT_BETA: f64 = 0.91;

/// The angles (α, β) that look at a volume one voxel thin (a single image slice) face-on, with
/// its other two axes on the screen as an image viewer shows them; `None` for a volume with
/// depth along every axis. For a slice in x–y (the usual DICOM or PNG slice) x runs to the
/// right and y down, as the rows and columns of the image; the other two keep the
/// right-handed screen of [`wavesplat_codec::view::basis_from_angles`].
pub fn face_on_angles(dims: [usize; 3]) -> Option<(f64, f64)> {
    use std::f64::consts::FRAC_PI_2;
    if dims[2] == 1 {
        Some((-FRAC_PI_2, -FRAC_PI_2))
    } else if dims[1] == 1 {
        Some((-FRAC_PI_2, 0.0))
    } else if dims[0] == 1 {
        Some((0.0, 0.0))
    } else {
        None
    }
}

impl ViewRequest {
    /// The view spec the request describes, before the volume is known (validated).
    pub fn spec(&self) -> Result<ViewSpec, OpenError> {
        let mut view = View::new(
            self.alpha.unwrap_or(DEFAULT_ALPHA),
            self.beta.unwrap_or(DEFAULT_BETA),
            self.width,
            self.height,
        );
        if let Some(z) = self.zoom {
            view = view.with_zoom(z);
        }
        if let Some(p) = self.pan {
            view = view.with_pan(p);
        }
        if let Some(c) = self.cue {
            view = view.with_cue(c);
        }
        let spec = ViewSpec {
            view,
            multiview: self.multiview,
        };
        spec.validate()?;
        Ok(spec)
    }

    /// The view spec for the volume of `header`: [`ViewRequest::spec_for_volume`] with its
    /// geometry and placement.
    pub fn spec_for(&self, header: &Header) -> Result<ViewSpec, OpenError> {
        self.spec_for_volume(&header.geometry, header.placement.as_ref())
    }

    /// The view spec for a volume of `geometry` placed at `placement`: [`ViewRequest::spec`],
    /// turned to the named patient side through the placement (or, with no angle given,
    /// face-on to a volume one voxel thin), its cue's extinction the volume's when asked for,
    /// and without a zoom zoomed to fit the volume (for a multiview, the tightest of its
    /// panels). A bricked volume passes its whole's geometry.
    pub fn spec_for_volume(
        &self,
        geometry: &Geometry,
        placement: Option<&Placement>,
    ) -> Result<ViewSpec, OpenError> {
        let mut spec = self.spec()?;
        if let (None, None, None, Some((alpha, beta))) = (
            self.side,
            self.alpha,
            self.beta,
            face_on_angles(geometry.dims),
        ) {
            spec.view.orientation = Orientation::Angles { alpha, beta };
        }
        if let (true, Some(cue)) = (self.cue_k_from_volume, spec.view.cue.as_mut()) {
            cue.k = Cue::default_extinction(geometry);
        }
        if let Some(side) = self.side {
            spec.view.orientation =
                side.orientation(placement)
                    .map_err(|e| OpenError::Patient {
                        side: side.name().to_string(),
                        source: e,
                    })?;
        }
        if self.zoom.is_none() {
            let fit = spec
                .cameras(geometry)?
                .iter()
                .map(|c| c.fitting_zoom(geometry))
                .fold(f64::INFINITY, f64::min);
            spec.view = spec.view.with_zoom(fit);
        }
        spec.validate()?;
        if let Some(max) = self.max_pixels_per_voxel {
            if let Some(drawn) = crate::magnify::bounded(&spec, geometry, max)? {
                tracing::debug!(
                    asked = format!("{}x{}", spec.view.width, spec.view.height),
                    drawn = format!("{}x{}", drawn.view.width, drawn.view.height),
                    "a magnified view drawn smaller and magnified back"
                );
                spec = drawn;
            }
        }
        Ok(spec)
    }

    /// `image`, drawn for this request's [`ViewRequest::spec_for_volume`], at the size asked
    /// for: magnified back where the view was drawn smaller ([`crate::magnify::magnify`]).
    pub fn shown(&self, image: &Image) -> Image {
        crate::magnify::magnify(image, self.panels(), self.width, self.height)
    }

    /// Views side by side in the image: three for multiview, else one.
    pub fn panels(&self) -> usize {
        if self.multiview {
            3
        } else {
            1
        }
    }

    /// For a source opened with `first` before the volume was known (a cache stream, range
    /// requests): the view for the volume, handed to the source when it differs, before the
    /// first frame.
    fn respec(
        &self,
        header: &Header,
        first: ViewSpec,
        source: &mut dyn PacketSource,
    ) -> Result<ViewSpec, OpenError> {
        let spec = self.spec_for(header)?;
        if spec != first {
            source.set_view(&spec);
        }
        Ok(spec)
    }
}

/// Where a volume is.
#[derive(Debug, Clone)]
pub enum VolumeLocation {
    /// A `.wsp` file, already read (the caller reads it, with its own advice for files that
    /// are not `.wsp`).
    File {
        /// Its path, for messages.
        path: PathBuf,
        /// Its bytes.
        bytes: Vec<u8>,
    },
    /// A published volume read by range requests (`https://…`, `s3://…`).
    Published {
        /// Its URL.
        url: String,
        /// The PEM CA to trust for `https://` (else the system's roots).
        ca: Option<PathBuf>,
    },
    /// A volume in a cache.
    Cache {
        /// The cache's URL, or several nodes' comma-separated.
        urls: String,
        /// CA and token.
        connect: ConnectOptions,
        /// The volume's name.
        name: String,
    },
}

impl VolumeLocation {
    /// A short name of the volume for messages.
    pub fn describe(&self) -> String {
        match self {
            VolumeLocation::File { path, .. } => path.display().to_string(),
            VolumeLocation::Published { url, .. } => crate::remote::redacted(url),
            VolumeLocation::Cache { urls, name, .. } => format!("{name} at {urls}"),
        }
    }
}

/// An opened volume: a packet source and what is needed to get every coefficient.
pub enum Opened {
    /// A local file.
    File {
        /// Its packets in view order.
        source: Box<FileSource>,
    },
    /// A published volume read by range requests.
    Remote {
        /// Its URL.
        url: String,
        /// The PEM CA trusted for `https://`.
        ca: Option<PathBuf>,
        /// The fetching source.
        source: RangeSource,
    },
    /// A cached volume.
    Cache {
        /// The cache URL(s).
        url: String,
        /// CA and token.
        connect: ConnectOptions,
        /// The volume.
        key: VolumeKey,
        /// The pulling source.
        source: CacheSource,
    },
}

impl Opened {
    /// The packet source, for a frame loop.
    pub fn into_source(self) -> Box<dyn PacketSource> {
        match self {
            Opened::File { source } => source,
            Opened::Remote { source, .. } => Box::new(source),
            Opened::Cache { source, .. } => Box::new(source),
        }
    }

    /// Every coefficient of the volume: decoded from the file, or from one full stream of the
    /// cache.
    pub fn all_coefficients(&self, header: &Header) -> Result<Vec<Coefficient>, OpenError> {
        match self {
            Opened::File { source } => Ok(load_coefficients(source.file_bytes(), None, None)?.1),
            Opened::Remote { url, ca, .. } => {
                let bytes = fetch_wsp(url, ca.as_deref()).map_err(|source| OpenError::Source {
                    what: crate::remote::redacted(url),
                    source,
                })?;
                Ok(load_coefficients(&bytes, None, None)?.1)
            }
            Opened::Cache {
                url, connect, key, ..
            } => {
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()?;
                let packets = runtime.block_on(async {
                    let first = url.split(',').next().unwrap_or(url);
                    let mut c = wavesplat_client::CacheClient::connect_with(first, connect).await?;
                    let request = wavesplat_client::RefineRequest::new(
                        key.clone(),
                        ViewSpec::single(View::new(0.0, 0.0, 1, 1)),
                    );
                    c.refine_collect(request, None).await
                })?;
                let data: Vec<&[u8]> = packets.packets.iter().map(|p| p.data.as_slice()).collect();
                Ok(decode_packets(header, &data, 0)?.concat())
            }
        }
    }

    /// The image of every coefficient for `spec`, in display space (a bricked file's: every
    /// brick drawn in one pass, [`crate::bricked::draw_bricked_file`]).
    pub fn reference_image(&self, header: &Header, spec: &ViewSpec) -> Result<Image, OpenError> {
        let draw = |bytes: &[u8]| -> Result<Image, OpenError> {
            let drawn =
                crate::bricked::draw_bricked_file(bytes, spec, &mut crate::CpuBackend::new())?;
            Ok(drawn.image)
        };
        match self {
            Opened::File { source } if source.bricked_volume().is_some() => {
                return draw(source.file_bytes())
            }
            Opened::Remote { url, ca, source } if source.bricked_volume().is_some() => {
                let bytes = fetch_wsp(url, ca.as_deref()).map_err(|source| OpenError::Source {
                    what: crate::remote::redacted(url),
                    source,
                })?;
                return draw(&bytes);
            }
            Opened::Cache { source, key, .. } if source.bricked_volume().is_some() => {
                return Err(OpenError::Source {
                    what: key.to_string(),
                    source: SourceError::Unsupported(
                        "the reference image of a bricked volume is drawn from its file: \
                         compare against the local .wsp file or its published URL"
                            .into(),
                    ),
                });
            }
            _ => {}
        }
        display_image(header, &self.all_coefficients(header)?, spec)
    }

    /// The volume as a bricked session draws it, when it is a bricked file or published
    /// bricked volume (`None` otherwise): [`crate::session::RenderSession::new_bricked`] takes it.
    pub fn bricked_volume(&self) -> Option<crate::session::BrickedVolume> {
        match self {
            Opened::File { source } => source.bricked_volume(),
            Opened::Remote { source, .. } => source.bricked_volume(),
            Opened::Cache { source, .. } => source.bricked_volume(),
        }
    }
}

/// The one-shot image of `coefficients` (of the volume `header` describes) for `spec`, in
/// display space (colour basis undone, the offset added back).
pub fn display_image(
    header: &Header,
    coefficients: &[Coefficient],
    spec: &ViewSpec,
) -> Result<Image, OpenError> {
    let mut r = Renderer::new(RenderOptions {
        channels: header.channels,
        ..RenderOptions::default()
    });
    let (img, _) = r.render_spec(coefficients, &header.geometry, spec)?;
    Ok(crate::color::to_rgb_for_spec(&img, header, spec)?)
}

impl From<crate::bricked::BrickedError> for OpenError {
    fn from(e: crate::bricked::BrickedError) -> Self {
        use crate::bricked::BrickedError as B;
        match e {
            B::Format(source) => OpenError::Format {
                what: "the bricked file".into(),
                source,
            },
            B::Packet(p) => OpenError::Packet(p),
            B::View(v) => OpenError::View(v),
            B::Render(r) => OpenError::Render(r),
        }
    }
}

/// Opens the volume at `location`, ranked for the view `request` describes; returns its header,
/// the opened source and that view (a named patient side resolved through the volume's
/// placement, the fitting zoom). `byte_budget` caps the packets' bytes (file and cache). A
/// file's bytes move into its source.
pub fn open(
    location: VolumeLocation,
    request: &ViewRequest,
    byte_budget: Option<u64>,
) -> Result<(Header, Opened, ViewSpec), OpenError> {
    let what = location.describe();
    let failed = |source| OpenError::Source {
        what: what.clone(),
        source,
    };
    match location {
        VolumeLocation::Published { url, ca } => {
            let first = request.spec()?;
            let options = RangeSourceOptions {
                time_point: request.time_point.unwrap_or(0),
                ..RangeSourceOptions::default()
            };
            let (mut source, header) =
                RangeSource::open(&url, ca.as_deref(), first, options).map_err(failed)?;
            let spec = request.respec(&header, first, &mut source)?;
            Ok((header, Opened::Remote { url, ca, source }, spec))
        }
        VolumeLocation::File { path, bytes } => {
            // A named view and the fitting zoom need the volume before packets are ordered.
            if wavesplat_codec::format::series::is_series(&bytes) {
                let t = request.time_point.unwrap_or(0);
                let header = {
                    let file = wavesplat_codec::format::series::parse_series(&bytes).map_err(
                        |source| OpenError::Format {
                            what: path.display().to_string(),
                            source,
                        },
                    )?;
                    wavesplat_codec::view::bricked::series_header(&file).map_err(|source| {
                        OpenError::Format {
                            what: path.display().to_string(),
                            source,
                        }
                    })?
                };
                let spec = request.spec_for_volume(&header.geometry, header.placement.as_ref())?;
                let source = FileSource::open_series_point(bytes, t, &spec)
                    .map_err(failed)?
                    .with_byte_budget(byte_budget);
                return Ok((
                    source.header().clone(),
                    Opened::File {
                        source: Box::new(source),
                    },
                    spec,
                ));
            }
            let spec = if wavesplat_codec::format::bricked::is_bricked(&bytes) {
                let (file, first) = crate::bricked::parse_with_first(&bytes)?;
                let whole = crate::bricked::whole_geometry(&file.manifest, &first);
                request.spec_for_volume(&whole, file.manifest.placement.as_ref())?
            } else {
                let header = parse_file(&bytes)
                    .map_err(|source| OpenError::Format {
                        what: path.display().to_string(),
                        source,
                    })?
                    .header;
                request.spec_for(&header)?
            };
            let source = FileSource::open(bytes, &spec)
                .map_err(failed)?
                .with_byte_budget(byte_budget);
            Ok((
                source.header().clone(),
                Opened::File {
                    source: Box::new(source),
                },
                spec,
            ))
        }
        VolumeLocation::Cache {
            urls,
            connect,
            name,
        } => {
            let key = VolumeKey::Name(name);
            let options = CacheSourceOptions {
                byte_budget,
                time_point: request
                    .time_point
                    .map_or(0, |t| u32::try_from(t).unwrap_or(u32::MAX)),
                ..CacheSourceOptions::default()
            };
            let first = request.spec()?;
            let (mut source, header) =
                CacheSource::open_with(&urls, &connect, key.clone(), first, options)
                    .map_err(failed)?;
            let spec = request.respec(&header.header, first, &mut source)?;
            // A time point of a series is drawn with its own header (its components' offsets
            // weighted), as the file's is.
            let drawn = match (&header.series, source.bricked_volume()) {
                (Some(_), Some(volume)) => volume.whole,
                _ => header.header,
            };
            Ok((
                drawn,
                Opened::Cache {
                    url: urls,
                    connect,
                    key,
                    source,
                },
                spec,
            ))
        }
    }
}

/// Decodes the packets (or a prefix in file order) of a file. Packets decode on their own, so
/// they are decoded in parallel, in batches of a few per thread so that a coefficient cap stops
/// early.
pub fn load_coefficients(
    bytes: &[u8],
    max_coefficients: Option<usize>,
    max_bytes: Option<usize>,
) -> Result<(Header, Vec<Coefficient>), OpenError> {
    let file = parse_file(bytes).map_err(|source| OpenError::Format {
        what: "the file".into(),
        source,
    })?;
    let mut used = file.header_bytes + file.directory_bytes;
    let mut prefix = 0usize;
    for p in &file.packets {
        if max_bytes.is_some_and(|b| used + p.len() > b) {
            break;
        }
        used += p.len();
        prefix += 1;
    }
    let batch = 4 * rayon::current_num_threads();
    let mut coeffs = Vec::new();
    let mut start = 0usize;
    while start < prefix && max_coefficients.is_none_or(|n| coeffs.len() < n) {
        let end = if max_coefficients.is_some() {
            (start + batch).min(prefix)
        } else {
            prefix
        };
        let decoded = decode_packets(&file.header, &file.packets[start..end], start)?;
        for d in decoded {
            if max_coefficients.is_some_and(|n| coeffs.len() >= n) {
                break;
            }
            coeffs.extend(d);
        }
        start = end;
    }
    if let Some(n) = max_coefficients {
        coeffs.truncate(n);
    }
    Ok((file.header, coeffs))
}

/// What [`draw_whole_file`] drew, and where its time went.
#[derive(Debug, Clone)]
pub struct WholeFileImage {
    /// The image in display values (as [`crate::RenderSession::image`] gives it).
    pub image: Image,
    /// Packets decoded (all of the file's).
    pub packets: usize,
    /// Their bytes.
    pub bytes: u64,
    /// Coefficients decoded and splatted.
    pub coefficients: usize,
    /// Planning and accumulation counters.
    pub stats: crate::RenderStats,
    /// Wall time of decoding every packet and planning the view, which run together.
    pub decode_and_plan: std::time::Duration,
    /// Wall time of the splatting after them (records and accumulation, display values).
    pub splat: std::time::Duration,
    /// Of `splat`, the time inside the backend: its `begin` and `accumulate` calls (a GPU's
    /// uploads and dispatches, which may return before the device is done) ...
    pub accumulate: std::time::Duration,
    /// ... and reading the image back (for a GPU, waiting for the device too). The rest of
    /// `splat` is making the records on the host and the display values.
    pub read: std::time::Duration,
}

/// A backend whose calls are timed ([`WholeFileImage::accumulate`], [`WholeFileImage::read`]).
struct TimedBackend<'b> {
    inner: &'b mut dyn crate::AccumulationBackend,
    accumulate: std::time::Duration,
    read: std::time::Duration,
}

impl crate::AccumulationBackend for TimedBackend<'_> {
    fn name(&self) -> String {
        self.inner.name()
    }

    fn begin(&mut self, layout: crate::backend::Layout) -> Result<(), crate::BackendError> {
        let t = std::time::Instant::now();
        let r = self.inner.begin(layout);
        self.accumulate += t.elapsed();
        r
    }

    fn accumulate(
        &mut self,
        atlas: &crate::backend::FootprintAtlas,
        records: &[crate::backend::SplatRecord],
    ) -> Result<u64, crate::BackendError> {
        let t = std::time::Instant::now();
        let r = self.inner.accumulate(atlas, records);
        self.accumulate += t.elapsed();
        r
    }

    fn read(&mut self) -> Result<Image, crate::BackendError> {
        let t = std::time::Instant::now();
        let r = self.inner.read();
        self.read += t.elapsed();
        r
    }

    fn prepare(
        &mut self,
        atlas: &crate::backend::FootprintAtlas,
    ) -> Result<(), crate::BackendError> {
        let t = std::time::Instant::now();
        let r = self.inner.prepare(atlas);
        self.accumulate += t.elapsed();
        r
    }

    fn gpu(&mut self) -> Option<&mut crate::backend::gpu::GpuBackend> {
        self.inner.gpu()
    }
}

/// Work of a one-pass render, in coefficients times pixels over 256², per pool thread, up to
/// which [`one_pass_backend`] draws on the CPU whatever a GPU might do. Measured: opening an
/// H200 and building its pipelines took ~170 ms before the first splat, while the CPU backend
/// drew MNI at 1.25 % (165 k coefficients at 256²: 0.16 M) whole in 70 ms on 16 cores and 50 ms
/// on 2; MNI at 5 % at 512² (2.6 M) took ~270 ms on 2 cores, about half of it accumulation,
/// the only part a GPU takes over (decoding and planning stay on the CPU). So below ~1 M per
/// thread the CPU is done before a device would be open; far above it a GPU can win.
pub const ONE_PASS_CPU_WORK_PER_THREAD: f64 = 1.0e6;

/// The backend a one-pass render ([`draw_whole_file`]) of `header`'s file at `spec` should ask
/// for: `choice` itself, except that [`BackendChoice::Auto`] becomes [`BackendChoice::Cpu`]
/// when the work (kept coefficients × pixels / 256²) is at most
/// [`ONE_PASS_CPU_WORK_PER_THREAD`] per thread of `threads`, so that such a render neither
/// opens a device nor probes for one (probing Mesa's software adapter alone took 30–270 ms on
/// the 2-core machine, against 50 ms for the whole render of MNI at 1.25 %). Returns the
/// choice and, when it changed, why.
pub fn one_pass_backend(
    choice: crate::backend::BackendChoice,
    header: &Header,
    spec: &ViewSpec,
    threads: usize,
) -> (crate::backend::BackendChoice, Option<String>) {
    use crate::backend::BackendChoice;
    if choice != BackendChoice::Auto {
        return (choice, None);
    }
    let views = if spec.multiview { 3.0 } else { 1.0 };
    let pixels = spec.view.width as f64 * spec.view.height as f64 * views;
    let work = header.kept as f64 * pixels / 65536.0;
    if work <= ONE_PASS_CPU_WORK_PER_THREAD * threads.max(1) as f64 {
        let why = format!(
            "cpu backend: {} coefficients at {}x{}{} are drawn on the CPU before a GPU device \
             would be open (--gpu to use one)",
            header.kept,
            spec.view.width,
            spec.view.height,
            if spec.multiview { " (three views)" } else { "" }
        );
        (BackendChoice::Cpu, Some(why))
    } else {
        (choice, None)
    }
}

/// Draws every coefficient of a `.wsp` file's bytes for `spec` with `backend`, at once: the
/// packets are decoded on the rayon pool while the view's exact footprint tables are planned from
/// a thread of their own (neither needs the other), then everything is splatted in batches of up to
/// [`crate::plan::SPLAT_BATCH`] coefficients. This is what a one-shot render of a whole local file
/// needs: a frame loop ([`crate::FrameLoop`]) would decode on its own thread, plan before
/// drawing and splat in batches sized to a frame, leaving a core idle much of the time. The
/// image equals the frame loop's final one up to the order of f32 additions (a test compares
/// them).
pub fn draw_whole_file(
    bytes: &[u8],
    spec: &ViewSpec,
    backend: &mut dyn crate::AccumulationBackend,
) -> Result<WholeFileImage, OpenError> {
    draw_whole_file_in_batches(bytes, spec, backend, crate::plan::SPLAT_BATCH)
}

/// [`draw_whole_file`] with batches of up to `batch` coefficients (at least 1).
fn draw_whole_file_in_batches(
    bytes: &[u8],
    spec: &ViewSpec,
    backend: &mut dyn crate::AccumulationBackend,
    batch_size: usize,
) -> Result<WholeFileImage, OpenError> {
    let batch_size = batch_size.max(1);
    let start = std::time::Instant::now();
    let file = parse_file(bytes).map_err(|source| OpenError::Format {
        what: "the file".into(),
        source,
    })?;
    let header = &file.header;
    let plan_it = || {
        crate::Planner::new(crate::PlanOptions::default()).plan(
            &header.geometry,
            spec,
            header.channels,
        )
    };
    // The planner gets a thread of its own and uses the pool from there: under
    // `rayon::join` its parallel steps queued behind whole packets being decoded (the pair
    // took 16.8 ms against 13.4 one after the other on two cores; with a thread, 12.5).
    let (decoded, plan) = std::thread::scope(|s| {
        let planner = s.spawn(plan_it);
        let decoded = decode_packets(header, &file.packets, 0);
        let plan = planner
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        (decoded, plan)
    });
    let (decoded, mut plan) = (decoded?, plan?);
    // As a file source does: missing or cut packets would draw a partial image.
    let coefficients: usize = decoded.iter().map(Vec::len).sum();
    check_kept(header, coefficients as u64).map_err(|source| OpenError::Format {
        what: "the file".into(),
        source,
    })?;
    let decode_and_plan = start.elapsed();
    let splat_start = std::time::Instant::now();
    let mut timed = TimedBackend {
        inner: backend,
        accumulate: Default::default(),
        read: Default::default(),
    };
    let backend: &mut dyn crate::AccumulationBackend = &mut timed;
    backend.begin(plan.layout()).map_err(RenderError::Backend)?;
    let mut stats = crate::RenderStats::default();
    plan.splat_in_batches(
        decoded.iter().map(Vec::as_slice),
        backend,
        batch_size,
        &mut crate::plan::SplatBuffers::default(),
        &mut stats,
    )?;
    let raw = backend.read().map_err(RenderError::Backend)?;
    let image = crate::color::to_rgb(&raw, header, &plan.cameras, plan.cue.as_ref())?;
    Ok(WholeFileImage {
        image,
        packets: file.packets.len(),
        bytes: file.packets.iter().map(|p| p.len() as u64).sum(),
        coefficients,
        stats,
        decode_and_plan,
        splat: splat_start.elapsed(),
        accumulate: timed.accumulate,
        read: timed.read,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::CpuBackend;
    use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
    use wavesplat_compressor::phantom::Phantom;

    /// The `n`³ Shepp–Logan phantom at a tenth of its coefficients, tiles of `tile`.
    fn shepp_logan(n: usize, tile: usize) -> Vec<u8> {
        let options = CompressOptions {
            target: Target::Fraction(0.1),
            tile: TileChoice::Size(tile),
            refine: None,
            ..Default::default()
        };
        compress(&Phantom::SheppLogan.generate([n; 3]), &options, &|_, _| {})
            .expect("compress")
            .bytes
    }

    /// Auto becomes the CPU for a one-pass render whose work (kept coefficients × pixels /
    /// 256²) is within a million per thread, three views counting three times; beyond it, and
    /// for a backend asked for, the choice stands.
    #[test]
    fn a_small_one_pass_render_takes_the_cpu_without_probing() {
        use crate::backend::BackendChoice::{Auto, Cpu, Gpu};
        let mut header = parse_file(&shepp_logan(16, 8)).unwrap().header;
        let at = |size: usize, multiview: bool| ViewSpec {
            view: View::new(0.4, 0.3, size, size),
            multiview,
        };
        header.kept = 1_000_000;
        let (choice, why) = one_pass_backend(Auto, &header, &at(256, false), 1);
        assert_eq!(choice, Cpu);
        assert!(why.unwrap().contains("1000000 coefficients at 256x256"));
        // Just past a million on one thread; within it on two.
        assert_eq!(one_pass_backend(Auto, &header, &at(257, false), 1).0, Auto);
        assert_eq!(one_pass_backend(Auto, &header, &at(257, false), 2).0, Cpu);
        // Three views are three times the pixels.
        assert_eq!(one_pass_backend(Auto, &header, &at(256, true), 2).0, Auto);
        assert_eq!(one_pass_backend(Auto, &header, &at(256, true), 3).0, Cpu);
        // Asked for, a backend is kept whatever the size.
        assert_eq!(
            one_pass_backend(Gpu, &header, &at(16, false), 8),
            (Gpu, None)
        );
        header.kept = u64::MAX;
        assert_eq!(
            one_pass_backend(Cpu, &header, &at(4096, true), 1),
            (Cpu, None)
        );
        assert_eq!(one_pass_backend(Auto, &header, &at(4096, true), 64).0, Auto);
    }

    /// Batches of any size, cutting packets or gathering them, draw the same image (up to the
    /// order of f32 additions) from the same coefficients.
    #[test]
    fn the_batch_size_does_not_change_the_image() {
        let bytes = shepp_logan(24, 8);
        let spec = ViewSpec::single(View::new(0.4, 0.3, 40, 36));
        let draw = |batch| {
            draw_whole_file_in_batches(&bytes, &spec, &mut CpuBackend::new(), batch).unwrap()
        };
        let whole = draw(usize::MAX);
        let file = parse_file(&bytes).unwrap();
        assert_eq!(whole.packets, file.packets.len());
        // The backend's share of the splatting is measured inside it.
        assert!(whole.accumulate > std::time::Duration::ZERO);
        assert!(
            whole.accumulate + whole.read <= whole.splat,
            "{:?} + {:?} of {:?}",
            whole.accumulate,
            whole.read,
            whole.splat
        );
        assert!(whole.packets > 4, "the file should have several packets");
        let largest = file
            .packets
            .iter()
            .map(|p| decode_packets(&file.header, &[*p], 0).unwrap()[0].len())
            .max()
            .unwrap();
        // 1: every coefficient alone; 7: packets cut; largest + 1: small packets gathered.
        for batch in [0, 1, 7, largest + 1] {
            let got = draw(batch);
            assert_eq!(got.coefficients, whole.coefficients, "batch {batch}");
            assert_eq!(got.stats.pixel_updates, whole.stats.pixel_updates);
            let e = crate::image::max_relative_difference(&got.image.data, &whole.image.data);
            assert!(e <= 1e-5, "batch {batch}: {e:e}");
        }
    }

    /// Bytes that are not a `.wsp` file, a file cut short and one missing a packet are refused
    /// with the format error, not drawn.
    #[test]
    fn bytes_that_are_not_a_whole_file_are_refused() {
        let spec = ViewSpec::single(View::new(0.4, 0.3, 16, 16));
        let mut backend = CpuBackend::new();
        assert!(matches!(
            draw_whole_file(b"not a volume", &spec, &mut backend),
            Err(OpenError::Format { .. })
        ));
        let bytes = shepp_logan(16, 16);
        assert!(draw_whole_file(&bytes[..bytes.len() - 3], &spec, &mut backend).is_err());
        // A well-formed file whose last packet is gone holds fewer coefficients than its
        // header declares.
        let file = parse_file(&bytes).unwrap();
        let kept: Vec<Vec<u8>> = file.packets[..file.packets.len() - 1]
            .iter()
            .map(|p| p.to_vec())
            .collect();
        let short = wavesplat_codec::format::write_file(&file.header, &kept);
        match draw_whole_file(&short, &spec, &mut backend) {
            Err(OpenError::Format { source, .. }) => {
                assert!(
                    source.to_string().contains("packets are missing"),
                    "{source}"
                )
            }
            other => panic!("a file missing a packet was not refused: {other:?}"),
        }
    }

    /// Flipped bytes anywhere in a file (header, directory, packets) give an error or an image,
    /// never a panic, and never a non-finite image.
    #[test]
    fn corrupted_files_are_refused_or_drawn_never_a_panic() {
        let bytes = shepp_logan(16, 8);
        let spec = ViewSpec::single(View::new(0.4, 0.3, 24, 24));
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let (mut refused, mut drawn) = (0, 0);
        for _ in 0..120 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let mut bad = bytes.clone();
            let at = (state % bad.len() as u64) as usize;
            bad[at] ^= 1 << (state >> 61);
            match draw_whole_file(&bad, &spec, &mut CpuBackend::new()) {
                Ok(w) => {
                    assert!(w.image.data.iter().all(|v| v.is_finite()), "byte {at}");
                    drawn += 1;
                }
                Err(_) => refused += 1,
            }
        }
        // The file carries checksums: most flips are caught before anything is drawn.
        assert!(refused > 0, "{refused} refused, {drawn} drawn");
    }
}
