//! `wavesplat publish`: a `.wsp` file in the indexed layout, for a web server, CDN or bucket, so
//! that `render`/`view https://…` fetch the header and index in one or two requests and then only
//! the packets a view needs (the layout is the codec's `format::index`).

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;

/// Arguments of `wavesplat publish`.
#[derive(Args, Debug)]
pub struct PublishArgs {
    /// The .wsp file.
    pub input: PathBuf,
    /// Output (conventionally `.wspx`): the packet index, then the .wsp unchanged. Serve it as
    /// a plain file; any server that answers `Range` requests will do.
    #[arg(short, long)]
    pub output: PathBuf,
}

/// Runs the subcommand.
pub fn run(a: PublishArgs) -> Result<()> {
    super::check_output(&a.output)?;
    super::check_not_input(&a.output, &a.input)?;
    let bytes = super::read_wsp(&a.input)?;
    let out = wavesplat_codec::format::index::indexed_layout(&bytes)
        .with_context(|| format!("indexing {}", a.input.display()))?;
    super::write_output(&a.output, |_, w| {
        w.write_all(&out)
            .with_context(|| format!("writing {}", a.output.display()))
    })?;
    outln!(
        "wrote {} ({} bytes: an index of {} bytes in front of the {}-byte .wsp)",
        a.output.display(),
        out.len(),
        out.len() - bytes.len(),
        bytes.len()
    );
    Ok(())
}
