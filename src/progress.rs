//! Progress reporting: an indicatif bar on a terminal, structured `tracing` events otherwise.

use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;

/// A progress reporter for one long task.
pub struct Progress {
    bar: Option<ProgressBar>,
    task: &'static str,
}

impl Progress {
    /// Starts reporting `task`.
    pub fn new(task: &'static str) -> Progress {
        let bar = std::io::stderr().is_terminal().then(|| {
            let b = ProgressBar::new_spinner();
            b.set_style(
                ProgressStyle::with_template("{spinner} {elapsed:>4} {prefix}: {msg}")
                    .expect("valid template"),
            );
            b.set_prefix(task);
            b.enable_steady_tick(std::time::Duration::from_millis(120));
            b
        });
        Progress { bar, task }
    }

    /// Reports a new stage.
    pub fn stage(&self, msg: &str) {
        match &self.bar {
            Some(b) => b.set_message(msg.to_string()),
            None => tracing::info!(task = self.task, stage = msg, "progress"),
        }
    }

    /// Ends the report.
    pub fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}
