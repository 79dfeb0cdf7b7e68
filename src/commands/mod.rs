//! One module per subcommand: argument parsing (clap) into the libraries' option types, and
//! human-readable output.

pub mod bench;
pub mod cache;
pub mod compress;
pub mod decompress;
pub mod demo;
pub mod info;
pub mod orchestrator;
pub mod phantom;
pub mod render;
pub mod security;
pub mod view;

use anyhow::{bail, Context, Result};
use clap::Args;
use wavesplat_compressor::encode::Target;

/// How much of a volume to keep, shared by `compress` and `archive submit`.
#[derive(Args, Debug, Clone)]
pub struct TargetArgs {
    /// Keep as many coefficients as fit in this many bytes (whole file).
    #[arg(long, group = "target")]
    pub target_bytes: Option<u64>,
    /// Keep this fraction (0..1] of all coefficients (default 0.05).
    #[arg(long, group = "target")]
    pub target_fraction: Option<f64>,
    /// Keep this many coefficients.
    #[arg(long, group = "target")]
    pub target_coefficients: Option<u64>,
    /// Keep the fewest coefficients whose energy is at least this percentage (Q_V, eq. 19).
    #[arg(long, group = "target")]
    pub target_qv: Option<f64>,
    /// Keep every non-zero coefficient.
    #[arg(long, group = "target")]
    pub lossless_selection: bool,
}

impl TargetArgs {
    /// The chosen target (default: 5 % of the coefficients).
    pub fn target(&self) -> Target {
        if let Some(b) = self.target_bytes {
            Target::Bytes(b)
        } else if let Some(f) = self.target_fraction {
            Target::Fraction(f)
        } else if let Some(c) = self.target_coefficients {
            Target::Coefficients(c)
        } else if let Some(q) = self.target_qv {
            Target::QvPercent(q)
        } else if self.lossless_selection {
            Target::All
        } else {
            Target::Fraction(0.05)
        }
    }
}

/// Binds a server's listener and prints `listening on ADDR` (scripts and tests read the bound
/// address, e.g. for port 0, from that line). The exposure rule is checked on every address
/// `addr` resolves to before anything is bound or printed, and what the operator should know
/// about the server's protection is said once on stderr.
pub async fn bind_announced(
    addr: &str,
    security: &wavesplat_net::Security,
) -> Result<tokio::net::TcpListener> {
    let candidates: Vec<std::net::SocketAddr> = tokio::net::lookup_host(addr)
        .await
        .with_context(|| format!("resolving the listen address {addr:?} (HOST:PORT)"))?
        .collect();
    for a in &candidates {
        security.check(*a)?;
    }
    let listener = tokio::net::TcpListener::bind(&candidates[..])
        .await
        .with_context(|| format!("binding {addr}"))?;
    let bound = listener.local_addr()?;
    security.check(bound)?;
    for w in security.warnings(bound) {
        eprintln!("{w}");
    }
    outln!("listening on {bound}");
    use std::io::Write;
    std::io::stdout().flush()?;
    Ok(listener)
}

/// Resolves on Ctrl-C: the graceful-shutdown signal of the servers.
pub async fn ctrl_c() {
    let _ = tokio::signal::ctrl_c().await;
    tracing::info!("shutting down");
}

/// Parses `X,Y,Z` into three positive integers.
pub fn parse_dims(s: &str) -> Result<[usize; 3]> {
    let parts: Vec<&str> = s.split([',', 'x']).collect();
    if parts.len() != 3 {
        bail!("dimensions must be X,Y,Z (three integers), got {s:?}");
    }
    let mut d = [0usize; 3];
    for (i, p) in parts.iter().enumerate() {
        d[i] = p
            .trim()
            .parse()
            .with_context(|| format!("dimension {:?} in {s:?} is not an integer", p))?;
        if d[i] == 0 {
            bail!("dimensions must be at least 1, got {s:?}");
        }
    }
    Ok(d)
}
