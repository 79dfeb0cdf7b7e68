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

use anyhow::{bail, Context, Result};

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
