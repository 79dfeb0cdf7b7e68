//! What an interrupted command leaves behind: the unfinished output files it is writing
//! ([`super::write_output`]'s temporary files beside the output), removed when the process is
//! stopped by Ctrl-C (SIGINT) or SIGTERM, and what it keeps on purpose ([`Kept`]: a bricked
//! compression's checkpoint), said. Without this, a stopped compression of a large
//! volume would leave a file about the output's size in the output's directory, under a
//! hidden name nobody removes. The handler is a thread waiting on tokio's signal streams
//! (tokio is already the binary's runtime; the signal crates would add a second way to the
//! same thing); it is installed on the first unfinished file and, once installed, stops the
//! process with status 130 on either signal (what the default action's shell status says).

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

/// The unfinished files of this process.
static UNFINISHED: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());
/// What an interrupt leaves on purpose, said when it comes ([`Kept`]).
static KEPT: Mutex<Vec<String>> = Mutex::new(Vec::new());
/// Whether the handler is installed (set once, by the first [`Unfinished::register`]).
static HANDLER: OnceLock<bool> = OnceLock::new();

/// An unfinished file, removed if the process is interrupted while this lives.
pub struct Unfinished {
    path: PathBuf,
}

impl Unfinished {
    /// Installs the handler (once per process) and puts `path` on the list of files to remove,
    /// then runs `create` (which makes the file): registered first, so that no signal can come
    /// between the file and its registration. A failed `create` takes the name off again. The
    /// caller keeps a [`Unfinished::guard`] of the created file. Without a handler (it could
    /// not be installed), the file would be left as before.
    pub fn register<T>(
        path: &Path,
        create: impl FnOnce() -> std::io::Result<T>,
    ) -> std::io::Result<T> {
        HANDLER.get_or_init(install);
        lock().push(path.to_path_buf());
        let made = create();
        if made.is_err() {
            forget(path);
        }
        made
    }

    /// The guard of a registered file: it comes off the list when this is dropped (the file
    /// renamed into place, or removed).
    pub fn guard(path: &Path) -> Unfinished {
        Unfinished {
            path: path.to_path_buf(),
        }
    }
}

impl Drop for Unfinished {
    fn drop(&mut self) {
        forget(&self.path);
    }
}

/// What an interrupted command leaves on purpose (a checkpoint to resume from): its line is
/// said after the unfinished files are removed, while this lives.
pub struct Kept {
    line: String,
}

impl Kept {
    /// Says `line` if the process is interrupted while the returned guard lives (installing
    /// the handler, as [`Unfinished::register`] does).
    pub fn note(line: String) -> Kept {
        HANDLER.get_or_init(install);
        KEPT.lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(line.clone());
        Kept { line }
    }
}

impl Drop for Kept {
    fn drop(&mut self) {
        let mut kept = KEPT.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(i) = kept.iter().position(|l| *l == self.line) {
            kept.remove(i);
        }
    }
}

/// The unfinished files of this process now, oldest first.
pub fn unfinished() -> Vec<PathBuf> {
    lock().clone()
}

fn forget(path: &Path) {
    lock().retain(|p| p != path);
}

fn lock() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    UNFINISHED.lock().unwrap_or_else(|p| p.into_inner())
}

/// Starts the thread that waits for SIGINT or SIGTERM; returns once the signals are routed to
/// it (false if they could not be).
#[cfg(unix)]
fn install() -> bool {
    use tokio::signal::unix::{signal, SignalKind};
    let (tx, rx) = std::sync::mpsc::channel();
    let spawned = std::thread::Builder::new()
        .name("interrupt".into())
        .spawn(move || {
            let Ok(rt) = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
            else {
                let _ = tx.send(false);
                return;
            };
            let streams = {
                let _entered = rt.enter();
                signal(SignalKind::interrupt())
                    .and_then(|i| Ok((i, signal(SignalKind::terminate())?)))
            };
            let Ok((mut interrupt, mut terminate)) = streams else {
                let _ = tx.send(false);
                return;
            };
            let _ = tx.send(true);
            rt.block_on(async {
                tokio::select! {
                    _ = interrupt.recv() => {}
                    _ = terminate.recv() => {}
                }
            });
            for p in lock().drain(..) {
                if std::fs::remove_file(&p).is_ok() {
                    eprintln!("interrupted: removed the unfinished {}", p.display());
                }
            }
            for line in KEPT.lock().unwrap_or_else(|p| p.into_inner()).drain(..) {
                eprintln!("interrupted: {line}");
            }
            std::process::exit(130);
        });
    spawned.is_ok() && rx.recv().unwrap_or(false)
}

#[cfg(not(unix))]
fn install() -> bool {
    false
}
