//! What long commands show while they work: a spinner per task ([`Progress`]) and the job table
//! of the orchestrator's queue ([`watch`]), as indicatif bars on a terminal and structured
//! `tracing` events otherwise (or, for the demo's long stages, plain lines on stderr with a
//! reminder every [`HEARTBEAT`], so that a log filter cannot make it silent). Shared by
//! `wavesplat compress`, `decompress`, `archive submit`, `jobs` and the demo.

use anyhow::{bail, Result};
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use std::collections::{BTreeMap, HashSet};
use std::io::{IsTerminal, Write};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use wavesplat_orchestrator_client as client;
use wavesplat_orchestrator_client::convert::state_name;
use wavesplat_proto::pb;

/// A progress reporter for one long task.
pub struct Progress {
    bar: Option<ProgressBar>,
    task: &'static str,
    lines: Option<Lines>,
}

/// Plain progress lines on stderr (no terminal): the stage as it changes, and every
/// [`HEARTBEAT`] without a change a line saying the stage is still under way, from a thread of
/// its own so that a long stage (a walk, a reference image) is not silent.
struct Lines {
    state: Arc<(Mutex<LineState>, Condvar)>,
    ticker: Option<std::thread::JoinHandle<()>>,
}

struct LineState {
    stage: String,
    since: Instant,
    last_line: Instant,
    done: bool,
}

/// How long a stage runs before a plain-line [`Progress`] says it is still under way.
pub const HEARTBEAT: Duration = Duration::from_secs(10);

/// The line a plain-line [`Progress`] writes for `stage` of `task`, `running` into it.
pub fn progress_line(task: &str, stage: &str, running: Option<Duration>) -> String {
    match running {
        None => format!("{task}: {stage}"),
        Some(d) => format!("{task}: {stage} (still running, {:.0} s)", d.as_secs_f64()),
    }
}

impl Progress {
    /// Starts reporting `task`: a spinner on a terminal, `tracing` events otherwise.
    pub fn new(task: &'static str) -> Progress {
        Progress {
            bar: Progress::spinner(task),
            task,
            lines: None,
        }
    }

    /// Starts reporting `task`: a spinner on a terminal, otherwise plain lines on stderr
    /// whatever the log level — each stage, and a reminder every [`HEARTBEAT`] while one
    /// lasts. For commands whose stages take tens of seconds (the demo).
    pub fn with_lines(task: &'static str) -> Progress {
        let bar = Progress::spinner(task);
        let lines = bar.is_none().then(|| {
            let now = Instant::now();
            let state = Arc::new((
                Mutex::new(LineState {
                    stage: String::new(),
                    since: now,
                    last_line: now,
                    done: false,
                }),
                Condvar::new(),
            ));
            let shared = Arc::clone(&state);
            let ticker = std::thread::Builder::new()
                .name("progress".into())
                .spawn(move || {
                    let (lock, wake) = &*shared;
                    let mut s = lock.lock().unwrap_or_else(|e| e.into_inner());
                    while !s.done {
                        let due = s.last_line + HEARTBEAT;
                        let now = Instant::now();
                        if now >= due {
                            if !s.stage.is_empty() {
                                eprintln!("{}", progress_line(task, &s.stage, Some(now - s.since)));
                            }
                            s.last_line = now;
                            continue;
                        }
                        s = wake
                            .wait_timeout(s, due - now)
                            .unwrap_or_else(|e| e.into_inner())
                            .0;
                    }
                })
                .ok();
            Lines { state, ticker }
        });
        Progress { bar, task, lines }
    }

    fn spinner(task: &'static str) -> Option<ProgressBar> {
        std::io::stderr().is_terminal().then(|| {
            let b = ProgressBar::new_spinner();
            b.set_style(
                ProgressStyle::with_template("{spinner} {elapsed:>4} {prefix}: {msg}")
                    .expect("valid template"),
            );
            b.set_prefix(task);
            b.enable_steady_tick(std::time::Duration::from_millis(120));
            b
        })
    }

    /// Reports a new stage.
    pub fn stage(&self, msg: &str) {
        match (&self.bar, &self.lines) {
            (Some(b), _) => b.set_message(msg.to_string()),
            (None, Some(l)) => {
                let (lock, _) = &*l.state;
                let mut s = lock.lock().unwrap_or_else(|e| e.into_inner());
                let now = Instant::now();
                s.stage = msg.to_string();
                s.since = now;
                s.last_line = now;
                eprintln!("{}", progress_line(self.task, msg, None));
            }
            (None, None) => tracing::info!(task = self.task, stage = msg, "progress"),
        }
    }

    /// Ends the report.
    pub fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
        if let Some(l) = &self.lines {
            let (lock, wake) = &*l.state;
            lock.lock().unwrap_or_else(|e| e.into_inner()).done = true;
            wake.notify_all();
        }
    }
}

impl Drop for Progress {
    /// Stops the plain lines' reminders (a spinner is left as indicatif leaves it).
    fn drop(&mut self) {
        if let Some(l) = self.lines.as_mut() {
            let (lock, wake) = &*l.state;
            lock.lock().unwrap_or_else(|e| e.into_inner()).done = true;
            wake.notify_all();
            if let Some(t) = l.ticker.take() {
                let _ = t.join();
            }
        }
    }
}

pub fn job_name(j: &pb::Job) -> &str {
    j.spec.as_ref().map_or("", |s| s.name.as_str())
}

/// The part a job is of a bricked job ("part of 7: brick 3/8 coding"), if it is one.
pub fn part_label(j: &pb::Job) -> Option<String> {
    let p = j.spec.as_ref()?.part.clone()?;
    match client::convert::part_from_pb(p) {
        Ok(p) => Some(format!("part of {}: {}", p.parent, p.label())),
        Err(_) => Some("part of a bricked job (unreadable)".into()),
    }
}

/// A job in one tab-separated line: id, state, name (and which part of a bricked job it is),
/// attempts, progress, worker, error.
pub fn describe(j: &pb::Job) -> String {
    let name = match part_label(j) {
        Some(p) => format!("{} ({p})", job_name(j)),
        None => job_name(j).to_string(),
    };
    format!(
        "{}\t{}\t{}\tattempts={}/{}\tprogress={:.0}%\tworker={}\tbytes={}\terror={}",
        j.id,
        state_name(j.state),
        name,
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
/// job failed. The parts of a bricked job are not shown: the job's own line says how many of
/// its bricks are done.
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
            .filter(|j| ids.is_none_or(|s| s.contains(&j.id)) && part_label(j).is_none())
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn progress_lines_name_the_task_the_stage_and_how_long_it_runs() {
        assert_eq!(
            progress_line("demo", "browsing rgb-head (multiview), walk 5 of 6", None),
            "demo: browsing rgb-head (multiview), walk 5 of 6"
        );
        assert_eq!(
            progress_line("demo", "scoring", Some(Duration::from_millis(20_400))),
            "demo: scoring (still running, 20 s)"
        );
    }
}
