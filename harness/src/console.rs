//! What long commands show while they work: a spinner per task ([`Progress`]) and the job table
//! of the orchestrator's queue ([`watch`]), as indicatif bars on a terminal and structured
//! `tracing` events otherwise. Shared by `wavesplat compress`, `decompress`, `archive submit`,
//! `jobs` and the demo.

use anyhow::{bail, Result};
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use std::collections::{BTreeMap, HashSet};
use std::io::{IsTerminal, Write};
use std::time::Duration;
use wavesplat_orchestrator::client;
use wavesplat_orchestrator::convert::state_name;
use wavesplat_proto::pb;

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

pub fn job_name(j: &pb::Job) -> &str {
    j.spec.as_ref().map_or("", |s| s.name.as_str())
}

/// A job in one tab-separated line: id, state, name, attempts, progress, worker, error.
pub fn describe(j: &pb::Job) -> String {
    format!(
        "{}\t{}\t{}\tattempts={}/{}\tprogress={:.0}%\tworker={}\tbytes={}\terror={}",
        j.id,
        state_name(j.state),
        job_name(j),
        j.attempts,
        j.max_attempts,
        100.0 * j.progress,
        j.worker,
        j.output_bytes,
        j.error
    )
}

fn is_terminal(j: &pb::Job) -> bool {
    matches!(state_name(j.state), "done" | "failed" | "cancelled")
}

/// Polls the jobs (all, or `ids`) until every one is finished, then writes the outcome to `say`: indicatif bars on a terminal
/// (one per job and one overall), `tracing` events on state changes otherwise. Fails if any
/// job failed.
pub async fn watch(
    c: &mut client::Client,
    ids: Option<&HashSet<u64>>,
    say: &mut (dyn Write + Send),
) -> Result<()> {
    let tty = std::io::stderr().is_terminal();
    let multi = MultiProgress::new();
    let style = ProgressStyle::with_template("{prefix:>24} [{bar:30}] {pos:>3}% {msg}")
        .expect("valid template")
        .progress_chars("=> ");
    let overall = tty.then(|| {
        let b = multi.add(ProgressBar::new(0));
        b.set_style(
            ProgressStyle::with_template("{prefix:>24} [{bar:30}] {pos}/{len} {msg} {elapsed}")
                .expect("valid template")
                .progress_chars("=> "),
        );
        b.set_prefix("overall");
        b
    });
    let mut bars: BTreeMap<u64, ProgressBar> = BTreeMap::new();
    let mut last: BTreeMap<u64, String> = BTreeMap::new();
    loop {
        let jobs: Vec<pb::Job> = client::list(c)
            .await?
            .into_iter()
            .filter(|j| ids.is_none_or(|s| s.contains(&j.id)))
            .collect();
        let finished = jobs.iter().filter(|j| is_terminal(j)).count();
        let failed = jobs
            .iter()
            .filter(|j| state_name(j.state) == "failed")
            .count();
        for j in &jobs {
            let state = state_name(j.state);
            let msg = match state {
                "running" => format!("{} {} ({})", state, j.stage, j.worker),
                "failed" => format!("failed: {}", j.error),
                "queued" if !j.error.is_empty() => format!("queued (retry after: {})", j.error),
                s => s.to_string(),
            };
            if tty {
                let b = bars.entry(j.id).or_insert_with(|| {
                    let b = multi.add(ProgressBar::new(100));
                    b.set_style(style.clone());
                    b.set_prefix(job_name(j).to_string());
                    b
                });
                b.set_position((j.progress * 100.0).round() as u64);
                b.set_message(msg);
            } else if last.get(&j.id) != Some(&state.to_string()) {
                tracing::info!(job = j.id, name = job_name(j), state, error = %j.error, "job");
                last.insert(j.id, state.to_string());
            }
        }
        if let Some(o) = &overall {
            o.set_length(jobs.len() as u64);
            o.set_position(finished as u64);
            o.set_message(format!("finished, {failed} failed"));
        }
        if finished == jobs.len() {
            if let Some(o) = &overall {
                o.finish();
            }
            for b in bars.values() {
                b.finish();
            }
            let done = jobs
                .iter()
                .filter(|j| state_name(j.state) == "done")
                .count();
            writeln!(
                say,
                "{} jobs: {done} done, {failed} failed, {} cancelled",
                jobs.len(),
                jobs.len() - done - failed
            )?;
            for j in jobs.iter().filter(|j| state_name(j.state) == "failed") {
                writeln!(say, "failed: job {} {}: {}", j.id, job_name(j), j.error)?;
            }
            if failed > 0 {
                bail!("{failed} job(s) failed");
            }
            return Ok(());
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
}
