//! `wavesplat info`: header, tiles, packets and where the bytes went (paper Fig. 16).

use anyhow::{Context, Result};
use clap::Args;
use rayon::prelude::*;
use std::path::PathBuf;
use wavesplat_codec::format::packet::{decode_packet, SizeBreakdown};
use wavesplat_codec::format::{parse_file, Header, WspFile};

/// Arguments of `wavesplat info`.
#[derive(Args, Debug)]
pub struct InfoArgs {
    /// The .wsp file (or a time series source: a 4D NIfTI, a DICOM cine, a directory of time
    /// steps, whose time points are listed).
    pub input: PathBuf,
    /// Also list every packet (of a bricked file: of each brick listed, under its line).
    #[arg(long)]
    pub packets: bool,
    /// For a bricked file, list every brick (otherwise the first 16); for a time series, every
    /// time point (otherwise the first 32).
    #[arg(long)]
    pub bricks: bool,
    /// For a bricked file over 64 MB, still split its bytes into headers, positions, signs
    /// and values (and count the coefficients in the bricks' padding), which decodes every
    /// brick; smaller files always show it.
    #[arg(long)]
    pub breakdown: bool,
}

/// Bricked files up to this size show their size breakdown without `--breakdown`.
const BREAKDOWN_BYTES: u64 = 64 << 20;

/// Bricks a bricked file's listing shows without `--bricks`.
const BRICKS_LISTED: usize = 16;

/// Runs the subcommand.
pub fn run(a: InfoArgs) -> Result<()> {
    // A time series source (a 4D file, a DICOM cine, a directory of steps): its time points.
    let head = std::fs::File::open(&a.input).and_then(|mut f| {
        let mut head = [0u8; 4];
        std::io::Read::read_exact(&mut f, &mut head).map(|_| head)
    });
    if !matches!(&head, Ok(h) if h == wavesplat_codec::format::MAGIC) {
        if let Some(series) = super::series::open_path(&a.input, None, None)? {
            outln!(
                "{}",
                super::series::describe_source(&a.input, series.source())
            );
            return Ok(());
        }
    }
    let bytes = super::read_wsp(&a.input)?;
    if wavesplat_codec::format::series::is_series(&bytes) {
        return series_info(&a, &bytes);
    }
    if wavesplat_codec::format::bricked::is_bricked(&bytes) {
        let f = wavesplat_codec::format::bricked::parse_bricked(&bytes)
            .with_context(|| format!("parsing {}", a.input.display()))?;
        let m = &f.manifest;
        outln!("file        {} ({} bytes)", a.input.display(), bytes.len());
        outln!("format      bricked container (version {})", m.version);
        outln!(
            "dims        {}x{}x{}, spacing {} x {} x {}",
            m.dims[0],
            m.dims[1],
            m.dims[2],
            m.spacing[0],
            m.spacing[1],
            m.spacing[2]
        );
        outln!("channels    {}", m.channels);
        outln!(
            "bricks      {} (at most {} a side), {} coefficients kept",
            m.bricks.len(),
            m.brick,
            m.kept()
        );
        // Every brick's family, depth and coder (one line when they share them, as the
        // compressor writes them; a file put together otherwise lists each set).
        let brick_headers = f
            .brick_headers()
            .with_context(|| format!("reading the bricks of {}", a.input.display()))?;
        let mut codings: std::collections::BTreeMap<String, usize> = Default::default();
        for (h, _) in &brick_headers {
            let g = &h.geometry;
            let coding = format!(
                "{} (order {}), levels M = {}, coder {} (format version {})",
                g.family,
                g.family.order(),
                g.levels,
                h.coder.name(),
                h.version
            );
            *codings.entry(coding).or_default() += 1;
        }
        for (coding, n) in &codings {
            if codings.len() == 1 {
                outln!("coding      {coding}, every brick");
            } else {
                outln!("coding      {coding}, {n} bricks");
            }
        }
        let mut lengths: Vec<u64> = m.bricks.iter().map(|b| b.length).collect();
        lengths.sort_unstable();
        let headers = f.overhead_bytes(&brick_headers);
        outln!(
            "brick bytes min {} / median {} / max {}; the manifest and their headers {} bytes ({:.1} % of the file)",
            lengths[0],
            lengths[lengths.len() / 2],
            lengths[lengths.len() - 1],
            headers,
            100.0 * headers as f64 / bytes.len() as f64
        );
        let listed = if a.bricks {
            m.bricks.len()
        } else {
            BRICKS_LISTED.min(m.bricks.len())
        };
        for (i, b) in m.bricks.iter().enumerate().take(listed) {
            outln!(
                "  brick {i}: at {},{},{} size {}x{}x{}, {} bytes, {} coefficients",
                b.origin[0],
                b.origin[1],
                b.origin[2],
                b.dims[0],
                b.dims[1],
                b.dims[2],
                b.length,
                b.kept
            );
            if a.packets {
                let brick = f
                    .brick_bytes(i)
                    .and_then(parse_file)
                    .with_context(|| format!("reading brick {i} of {}", a.input.display()))?;
                packets_breakdown(&brick, &mut SizeBreakdown::default(), Some("    "))
                    .with_context(|| format!("decoding brick {i}"))?;
            }
        }
        if listed < m.bricks.len() {
            outln!(
                "  … and {} more (--bricks lists every one)",
                m.bricks.len() - listed
            );
        }
        // Where the bytes went, over every brick: the manifest with the bricks' header
        // sections (as above), their packet directories, and their packets' payload. It
        // decodes every brick (on every core), so a large file does it when asked.
        if bytes.len() as u64 > BREAKDOWN_BYTES && !a.breakdown {
            outln!(
                "size breakdown: --breakdown decodes every brick to split their bytes (this file \
                 is over {} MB)",
                BREAKDOWN_BYTES >> 20
            );
            return Ok(());
        }
        let per_brick = (0..m.bricks.len())
            .into_par_iter()
            .map(|i| {
                let brick = f
                    .brick_bytes(i)
                    .and_then(parse_file)
                    .with_context(|| format!("reading brick {i} of {}", a.input.display()))?;
                let mut part = SizeBreakdown::default();
                let counted = packets_breakdown(&brick, &mut part, None)
                    .with_context(|| format!("decoding brick {i}"))?;
                Ok((part, brick.directory_bytes, counted.outside))
            })
            .collect::<Result<Vec<_>>>()?;
        let mut total = SizeBreakdown::default();
        let (mut directories, mut outside) = (0usize, 0usize);
        for (part, directory, out) in per_brick {
            add_breakdown(&mut total, &part);
            directories += directory;
            outside += out;
        }
        // Coefficients in a brick's padding draw only near its faces: the share bricking costs
        // in coefficients (an unbricked file keeps almost none there).
        outln!(
            "padding     {} of the kept coefficients ({:.1} %) sit in the bricks' padding, for their faces",
            outside,
            100.0 * outside as f64 / m.kept().max(1) as f64
        );
        print_breakdown(bytes.len(), headers as usize, directories, &total);
        return Ok(());
    }
    let file = parse_file(&bytes).with_context(|| format!("parsing {}", a.input.display()))?;
    let h = &file.header;
    outln!("file        {} ({} bytes)", a.input.display(), bytes.len());
    print_header(h);
    let mut total = SizeBreakdown::default();
    let coefficients = packets_breakdown(&file, &mut total, a.packets.then_some(""))?.coefficients;
    outln!(
        "packets     {} holding {} coefficients (header says {})",
        file.packets.len(),
        coefficients,
        h.kept
    );
    print_breakdown(bytes.len(), file.header_bytes, file.directory_bytes, &total);
    Ok(())
}

/// How many coefficients a file's packets hold, and how many of them sit in the padding
/// ([`wavesplat_codec::layout::Geometry::cell_outside_box`]).
struct Counted {
    coefficients: usize,
    outside: usize,
}

/// Decodes `file`'s packets, adds where their bits went to `total` and counts their
/// coefficients; `list` prints a line per packet, after this indent.
fn packets_breakdown(
    file: &WspFile<'_>,
    total: &mut SizeBreakdown,
    list: Option<&str>,
) -> Result<Counted> {
    let mut counted = Counted {
        coefficients: 0,
        outside: 0,
    };
    let g = &file.header.geometry;
    for (i, p) in file.packets.iter().enumerate() {
        let d = decode_packet(&file.header, p).with_context(|| format!("decoding packet {i}"))?;
        counted.coefficients += d.coefficients.len();
        counted.outside += d
            .coefficients
            .iter()
            .filter(|c| g.cell_outside_box(c.band, c.pos))
            .count();
        add_breakdown(total, &d.breakdown);
        if let Some(indent) = list {
            let energy: f64 = d.summary.iter().map(|(_, e)| e).sum();
            outln!(
                "{indent}packet {i:5}  tile {:5}  layer {:2}  {:7} coefficients  {:8} bytes  energy {:.3e}",
                d.tile,
                d.layer,
                d.coefficients.len(),
                p.len(),
                energy
            );
        }
    }
    Ok(counted)
}

/// Adds `part` to `total`.
fn add_breakdown(total: &mut SizeBreakdown, part: &SizeBreakdown) {
    total.tag_bits += part.tag_bits;
    total.position_bits += part.position_bits;
    total.sign_bits += part.sign_bits;
    total.value_bits += part.value_bits;
    total.framing_bytes += part.framing_bytes;
}

/// Prints a size breakdown: header sections, packet directories, then the packets' framing
/// and payload, each in bytes and as a share of a file of `file_bytes`.
fn print_breakdown(
    file_bytes: usize,
    header_bytes: usize,
    directory_bytes: usize,
    total: &SizeBreakdown,
) {
    let pct = |x: f64| 100.0 * x / file_bytes as f64;
    outln!("size breakdown (bytes, % of file):");
    outln!(
        "  header + tables        {:9} {:6.2} %",
        header_bytes,
        pct(header_bytes as f64)
    );
    outln!(
        "  packet directory       {:9} {:6.2} %",
        directory_bytes,
        pct(directory_bytes as f64)
    );
    outln!(
        "  packet framing/summary {:9} {:6.2} %",
        total.framing_bytes,
        pct(total.framing_bytes as f64)
    );
    for (name, bits) in [
        ("type/depth/channel", total.tag_bits),
        ("positions", total.position_bits),
        ("signs", total.sign_bits),
        ("values", total.value_bits),
    ] {
        outln!("  {name:22} {:9.0} {:6.2} %", bits / 8.0, pct(bits / 8.0));
    }
}

/// Prints a header's facts, one per line (shared by `info` and `cache show`).
pub fn print_header(h: &Header) {
    let g = &h.geometry;
    outln!(
        "dims        {}x{}x{}, spacing {} x {} x {}",
        g.dims[0],
        g.dims[1],
        g.dims[2],
        h.spacing()[0],
        h.spacing()[1],
        h.spacing()[2]
    );
    match &h.placement {
        Some(p) => {
            let labels = p.axis_labels();
            outln!(
                "origin      ({:.3}, {:.3}, {:.3}) mm, LPS (patient position of voxel 0,0,0)",
                nz(p.origin[0]),
                nz(p.origin[1]),
                nz(p.origin[2])
            );
            for (a, d) in p.directions.iter().enumerate() {
                outln!(
                    "axis {}      ({:+.6}, {:+.6}, {:+.6}) LPS, towards {}",
                    ["x", "y", "z"][a],
                    nz(d[0]),
                    nz(d[1]),
                    nz(d[2]),
                    labels[a]
                );
            }
        }
        None => outln!("orientation unknown (the source gave no placement in patient space)"),
    }
    outln!(
        "padded      {}x{}x{} (margin {}, origin {:?}; periodic boundary on the zero-padded grid)",
        g.padded[0],
        g.padded[1],
        g.padded[2],
        h.margin,
        g.origin
    );
    outln!("channels    {} ({})", h.channels, h.color.kind.name());
    if h.channels == 3 {
        outln!("importance  {:?}", h.color.importance);
        outln!(
            "origin      {:?} (colour subtracted before the projection: the faces' median)",
            h.color.mean
        );
    } else if h.color.mean[0] != 0.0 {
        outln!(
            "offset      {} (subtracted from every voxel before the transform: the faces' median)",
            h.color.mean[0]
        );
    }
    outln!(
        "family      {} (order {}), levels M = {}",
        g.family,
        g.family.order(),
        g.levels
    );
    // The fast coder's tables named built-in rather than described in the header.
    let builtin = h
        .fast_tables
        .as_ref()
        .map(|t| t.builtin_count())
        .filter(|&n| n > 0)
        .map_or(String::new(), |n| format!(", {n} of its tables built in"));
    outln!(
        "coder       {}, P = {} bits (format version {}){builtin}",
        h.coder.name(),
        h.bits,
        h.version
    );
    outln!("values      {} .. {}", h.value_range[0], h.value_range[1]);
    outln!(
        "tiles       {} of {} voxels ({:?}), {} layers{}",
        h.tile_count(),
        h.tile,
        h.tile_counts(),
        h.layer_bounds.len(),
        if h.coarse_layer {
            " (the first the coarse layer: each tile's scaling band)"
        } else {
            ""
        }
    );
    outln!(
        "substreams  {} used of {}",
        h.substreams.iter().filter(|s| s.is_some()).count(),
        h.substream_count()
    );
}

/// `x` without the sign of zero (so `-0.000000` prints as `0.000000`).
fn nz(x: f64) -> f64 {
    if x == 0.0 {
        0.0
    } else {
        x
    }
}

/// Time points `info` lists for a series without `--bricks`.
const TIME_POINTS_LISTED: usize = 32;

/// `info` of a series file: its space, time points and their times, the components each
/// names and the bytes a viewer of each reads.
fn series_info(a: &InfoArgs, bytes: &[u8]) -> Result<()> {
    use wavesplat_codec::format::series::{parse_series, SERIES_VERSION};
    let f = parse_series(bytes).with_context(|| format!("parsing {}", a.input.display()))?;
    let m = &f.manifest;
    let s = &m.space;
    outln!("file        {} ({} bytes)", a.input.display(), bytes.len());
    outln!("format      time series (version {SERIES_VERSION})");
    outln!(
        "dims        {}x{}x{}, spacing {} x {} x {}",
        s.dims[0],
        s.dims[1],
        s.dims[2],
        s.spacing[0],
        s.spacing[1],
        s.spacing[2]
    );
    outln!("channels    {}", s.channels);
    let n = m.points.len();
    let times = if m.times_known {
        let step = if n > 1 {
            format!(
                ", {:.4} s apart",
                (m.points[n - 1].time - m.points[0].time) / (n - 1) as f64
            )
        } else {
            String::new()
        };
        format!(
            "from {:.4} s to {:.4} s{step}",
            m.points[0].time,
            m.points[n - 1].time
        )
    } else {
        "no times in the source (numbered in order)".to_string()
    };
    outln!("time points {n}, {times}");
    let bricked = (0..m.components.len())
        .filter(|&c| {
            f.component_bytes(c)
                .is_ok_and(wavesplat_codec::format::bricked::is_bricked)
        })
        .count();
    outln!(
        "components  {} (a Haar wavelet along time in groups of {}; {} bricked), {} coefficients \
         kept",
        m.components.len(),
        m.group,
        bricked,
        m.kept()
    );
    let listed = if a.bricks {
        n
    } else {
        TIME_POINTS_LISTED.min(n)
    };
    for (t, p) in m.points.iter().enumerate().take(listed) {
        let terms: Vec<String> = p
            .terms
            .iter()
            .map(|(c, w)| format!("{w:+.4}·c{c}"))
            .collect();
        outln!(
            "  time point {t}{}: {} bytes = {}",
            if m.times_known {
                format!(" at {:.4} s", p.time)
            } else {
                String::new()
            },
            m.point_bytes(t),
            terms.join(" ")
        );
    }
    if listed < n {
        outln!("  … and {} more (--bricks lists every one)", n - listed);
    }
    if a.packets {
        for c in 0..m.components.len() {
            let part = f
                .component_bytes(c)
                .with_context(|| format!("reading component {c} of {}", a.input.display()))?;
            outln!("  component c{c}: {} bytes", part.len());
            list_packets(part, "    ").with_context(|| format!("decoding component c{c}"))?;
        }
    }
    Ok(())
}

/// Lists the packets of one volume's bytes (a series' component) after `indent`: a plain
/// file's, or each brick's of a bricked one under a line naming the brick.
fn list_packets(bytes: &[u8], indent: &str) -> Result<()> {
    use wavesplat_codec::format::bricked::{is_bricked, parse_bricked};
    let mut ignored = SizeBreakdown::default();
    if !is_bricked(bytes) {
        packets_breakdown(&parse_file(bytes)?, &mut ignored, Some(indent))?;
        return Ok(());
    }
    let f = parse_bricked(bytes)?;
    for (i, b) in f.manifest.bricks.iter().enumerate() {
        outln!(
            "{indent}brick {i}: at {},{},{}, {} coefficients",
            b.origin[0],
            b.origin[1],
            b.origin[2],
            b.kept
        );
        let brick = f.brick_bytes(i).and_then(parse_file)?;
        packets_breakdown(&brick, &mut ignored, Some(&format!("{indent}  ")))
            .with_context(|| format!("decoding brick {i}"))?;
    }
    Ok(())
}
