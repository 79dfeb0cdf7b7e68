//! The workstation window: the progressive render session of a volume shown in a window and
//! turned with the mouse, each displayed frame draining the packets that arrived and splatting
//! what fits in the frame budget. `controls` (the state the user controls and how input changes
//! it) and `script` (synthetic input for tests and demos) know no windowing library; `shell`,
//! behind the `window` feature, is the winit 0.30 front-end: the window and its wgpu surface on
//! the adapter it chose, surface upkeep, a lost device recreated on the same window, the title
//! showing the session's state; `soft`, behind the same feature, shows host images on a software
//! device by writing the window's buffer instead of drawing through wgpu.

pub mod controls;
pub mod script;
#[cfg(feature = "window")]
mod shell;
#[cfg(feature = "window")]
mod soft;

pub use controls::{
    human_bytes, Controls, Input, KeyPress, Reaction, TimeState, TitleFacts, ViewState, WindowSize,
    HELP,
};
pub use script::{Command, Script};
#[cfg(feature = "window")]
pub use shell::{
    run, Convergence, PlaybackFacts, SeriesPlayback, WindowOptions, WindowOutcome,
    DEFAULT_INTERACTIVE_MAX_IMAGE,
};

use thiserror::Error;

/// Why the window could not do what was asked.
#[derive(Debug, Error)]
pub enum WindowError {
    /// Invalid input: a script, an option, a view the window cannot turn.
    #[error("{0}")]
    Invalid(String),
    /// The window gave up (a surface that failed for good, a device lost too often).
    #[error("{0}")]
    Stopped(String),
    /// A step failed (opening the display, the device, the session, a frame, writing a file).
    #[error("{what}")]
    Failed {
        /// The step, in words.
        what: String,
        /// Why.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

/// The window's results.
pub type Result<T, E = WindowError> = std::result::Result<T, E>;

/// Names the step that failed: `.context("what")` on a result whose error is any error.
trait Context<T> {
    fn context(self, what: &str) -> Result<T>;
    fn with_context(self, what: impl FnOnce() -> String) -> Result<T>;
}

impl<T, E: std::error::Error + Send + Sync + 'static> Context<T> for std::result::Result<T, E> {
    fn context(self, what: &str) -> Result<T> {
        self.with_context(|| what.to_string())
    }

    fn with_context(self, what: impl FnOnce() -> String) -> Result<T> {
        self.map_err(|e| WindowError::Failed {
            what: what(),
            source: Box::new(e),
        })
    }
}
