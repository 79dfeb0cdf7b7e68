//! Resuming an interrupted bricked compression. A large volume takes hours in one process
//! (2048³ on two cores: most of an hour), and a kill, a reboot or a full disk near the end
//! should not cost the bricks already done. A [`Checkpoint`] is a directory that keeps, as
//! they are made, the plan's choices (a byte target's depth, compared on a sample of the
//! bricks), every brick's score summary (the first pass), the top coefficients that pass kept
//! where the bricks do not refine ([`crate::encode::KeptTop`], so that a run again codes the
//! bricks not yet coded without reading and transforming them again; within
//! [`TOP_DISK_SHARE`] of the free disk space) and every coded brick (the second,
//! keyed by the count it kept, so a byte target's trials are kept apart). A run of the
//! same compression finds them and does only what is missing; the result is the same file,
//! byte for byte, since each brick's pass depends only on the brick, the options and its count.
//!
//! Each entry is written to a temporary name and renamed, and carries a CRC-32 of its bytes,
//! so an entry cut off by a kill is never read: a damaged or unreadable one is done again. The
//! directory is tied to one compression by a key (the input's identity and the options, which
//! the caller builds): a checkpoint of another compression is emptied before it is used. The
//! caller also has a digest of every byte of the input taken in the background
//! ([`Checkpoint::record_content`]) and compares it with the input's when it runs again, since
//! a key cannot read a large input whole.
//! A checkpoint that cannot be written (a full disk, a name taken) is a warning, not an error:
//! the compression goes on without it ([`Checkpoint::keep_summary`]).

use crate::encode::{CompressOptions, KeptTop, ScoreSummary, TOP_DISK_SHARE};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};

/// The file naming the compression a checkpoint belongs to.
const KEY_FILE: &str = "key";
/// The entry of the plan's choices.
const PLAN_FILE: &str = "plan";
/// The entry naming the unfinished output file of the run that made the checkpoint.
const UNFINISHED_FILE: &str = "unfinished-output";
/// The entry of a digest of every byte of the input, taken by the run that made the
/// checkpoint ([`Checkpoint::record_content`]).
const CONTENT_FILE: &str = "content";

/// A digest of the input taken in the background: stopped and joined before the checkpoint
/// is removed, so that it never writes into a directory being removed.
#[derive(Debug)]
struct ContentTask {
    stop: std::sync::Arc<AtomicBool>,
    handle: std::thread::JoinHandle<()>,
}

/// A directory of the finished passes of one bricked compression.
#[derive(Debug)]
pub struct Checkpoint {
    dir: PathBuf,
    /// Set by the first entry that could not be written: no more are tried.
    unwritable: AtomicBool,
    /// The bytes kept tops may take here: [`TOP_DISK_SHARE`] of the free space when the
    /// first is kept (`None`: the space could not be read; no tops are kept).
    top_budget: std::sync::OnceLock<Option<u64>>,
    /// Bytes of the kept tops written so far.
    top_bytes: AtomicU64,
    /// Set by the first top that could not be written: no more are tried (the other
    /// entries still are).
    tops_given_up: AtomicBool,
    /// The digest of the input being taken, if any ([`Checkpoint::record_content`]).
    content_task: std::sync::Mutex<Option<ContentTask>>,
}

/// What a checkpoint held when it was opened.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Resumed {
    /// Whether it held the plan's choices.
    pub planned: bool,
    /// Bricks whose score summary it held.
    pub scored: usize,
    /// Bricks whose kept top it held.
    pub tops: usize,
    /// Coded bricks it held (over every count).
    pub coded: usize,
    /// Whether it held another compression's entries, which were removed.
    pub replaced: bool,
}

impl Checkpoint {
    /// Opens the checkpoint in `dir` (created when missing) for the compression `key` names.
    /// Entries of another key are removed first; an empty or new directory takes the key.
    pub fn open(dir: &Path, key: &str) -> std::io::Result<(Checkpoint, Resumed)> {
        std::fs::create_dir_all(dir)?;
        let cp = Checkpoint {
            dir: dir.to_path_buf(),
            unwritable: Default::default(),
            top_budget: Default::default(),
            top_bytes: Default::default(),
            tops_given_up: Default::default(),
            content_task: Default::default(),
        };
        let mut resumed = Resumed::default();
        let stored = std::fs::read(dir.join(KEY_FILE)).ok();
        if stored.as_deref() != Some(key.as_bytes()) {
            resumed.replaced = stored.is_some();
            for entry in std::fs::read_dir(dir)? {
                let path = entry?.path();
                if is_entry(&path) {
                    resumed.replaced = true;
                    std::fs::remove_file(&path)?;
                }
            }
            cp.write_atomic(KEY_FILE, key.as_bytes())?;
        }
        for entry in std::fs::read_dir(dir)? {
            let name = entry?.file_name();
            let name = name.to_string_lossy();
            if name == PLAN_FILE {
                resumed.planned = true;
            } else if name.starts_with("score-") && !name.ends_with(".tmp") {
                resumed.scored += 1;
            } else if name.starts_with("brick-") && !name.ends_with(".tmp") {
                resumed.coded += 1;
            } else if name.starts_with("top-") && !name.ends_with(".tmp") {
                resumed.tops += 1;
            }
        }
        Ok((cp, resumed))
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The plan's choices as the caller wrote them ([`Checkpoint::keep_plan`]), if kept and
    /// intact.
    pub fn plan(&self) -> Option<Vec<u8>> {
        self.read_checked(PLAN_FILE)
    }

    /// Keeps the plan's choices (the depth a byte target compared on a sample, the whole's
    /// offset or colour transform), so that a run again does not plan again; a checkpoint that
    /// cannot be written is given up as [`Checkpoint::keep_summary`] says.
    pub fn keep_plan(&self, bytes: &[u8]) {
        if !self.is_unwritable() {
            let kept = self.write_checked(PLAN_FILE, bytes);
            self.note(kept);
        }
    }

    /// The unfinished output file the run that made the checkpoint in `dir` was writing, as
    /// the caller recorded it ([`Checkpoint::keep_unfinished_output`]), read without opening
    /// the checkpoint (so before one is discarded). Kept whatever the key: the file of a run
    /// with other options is just as unfinished.
    pub fn unfinished_output_in(dir: &Path) -> Option<PathBuf> {
        let bytes = read_checked_at(&dir.join(UNFINISHED_FILE))?;
        Some(PathBuf::from(String::from_utf8(bytes).ok()?))
    }

    /// Records the unfinished output file this run writes (a temporary name renamed into place
    /// at the end), so that a run again can remove it if this one is killed before it can
    /// (SIGKILL is not caught).
    pub fn keep_unfinished_output(&self, path: &Path) {
        if let Some(name) = path.to_str() {
            if !self.is_unwritable() {
                let kept = self.write_checked(UNFINISHED_FILE, name.as_bytes());
                self.note(kept);
            }
        }
    }

    /// The digest of the input's bytes the run that made the checkpoint recorded
    /// ([`Checkpoint::record_content`]), if it finished and is intact.
    pub fn content(&self) -> Option<Vec<u8>> {
        self.read_checked(CONTENT_FILE)
    }

    /// Takes a digest of the input (`digest`, which reads all of it and gives up, returning
    /// `None`, once its flag is set) on a thread of its own while the compression runs, and
    /// keeps it: a run again compares it with the input's digest then
    /// ([`Checkpoint::content`]), so an input changed anywhere is not resumed from, whatever
    /// its length and modification time. A run killed before the digest is kept leaves a
    /// checkpoint that is not resumed from.
    pub fn record_content(
        &self,
        digest: impl FnOnce(&AtomicBool) -> Option<Vec<u8>> + Send + 'static,
    ) {
        let stop = std::sync::Arc::new(AtomicBool::new(false));
        let dir = self.dir.clone();
        let flag = stop.clone();
        let handle = std::thread::spawn(move || {
            if let Some(bytes) = digest(&flag) {
                if !flag.load(Relaxed) {
                    let crc = crc32fast::hash(&bytes).to_le_bytes();
                    if let Err(e) = write_atomic_at(&dir, CONTENT_FILE, &[&bytes, &crc]) {
                        tracing::debug!(error = %e, "keeping the input's digest in the checkpoint");
                    }
                }
            }
        });
        if let Ok(mut task) = self.content_task.lock() {
            *task = Some(ContentTask { stop, handle });
        }
    }

    /// Stops and joins the digest being taken, if any.
    fn stop_content_task(&self) {
        let task = self.content_task.lock().ok().and_then(|mut t| t.take());
        if let Some(task) = task {
            task.stop.store(true, Relaxed);
            let _ = task.handle.join();
        }
    }

    /// Brick `i`'s score summary, if kept and intact.
    pub fn summary(&self, i: usize) -> Option<ScoreSummary> {
        let bytes = self.read_checked(&format!("score-{i}"))?;
        ScoreSummary::from_bytes(&bytes).ok()
    }

    /// Keeps brick `i`'s score summary (`energies`: with its energies, which a Q_V target needs).
    pub fn save_summary(
        &self,
        i: usize,
        summary: &ScoreSummary,
        energies: bool,
    ) -> std::io::Result<()> {
        self.write_checked(&format!("score-{i}"), &summary.to_bytes(energies))
    }

    /// Brick `i` coded keeping `count` coefficients (`None`: all), if kept and intact: its
    /// file and the count its header says it kept.
    pub fn coded(&self, i: usize, count: Option<u64>) -> Option<(Vec<u8>, u64)> {
        let bytes = self.read_checked(&coded_name(i, count))?;
        let (header, _) = wavesplat_codec::format::read_header_section(&bytes).ok()?;
        Some((bytes, header.kept))
    }

    /// Keeps brick `i` coded keeping `count` coefficients.
    pub fn save_coded(&self, i: usize, count: Option<u64>, file: &[u8]) -> std::io::Result<()> {
        self.write_checked(&coded_name(i, count), file)
    }

    /// Brick `i`'s kept top, if kept, intact and valid for a brick of `dims` and `opts` (the
    /// options of the run, which the checkpoint's key ties to those it was scored with).
    pub fn top(&self, i: usize, dims: [usize; 3], opts: &CompressOptions) -> Option<KeptTop> {
        let bytes = self.read_checked(&format!("top-{i}"))?;
        match KeptTop::from_bytes(&bytes, dims, opts) {
            Ok(top) => Some(top),
            Err(e) => {
                tracing::warn!(brick = i, error = %e, "a kept top in the checkpoint is not used");
                None
            }
        }
    }

    /// Keeps brick `i`'s top while the tops take at most [`TOP_DISK_SHARE`] of the free
    /// space (as it was at the first): they are 8–9 bytes a coefficient, tens of times the
    /// output's size, and must not take the room the output and the coded bricks need. One
    /// that cannot be written stops the tops (a warning), not the other entries.
    pub fn keep_top(&self, i: usize, top: &KeptTop) {
        if self.is_unwritable() || self.tops_given_up.load(Relaxed) {
            return;
        }
        let budget = *self.top_budget.get_or_init(|| {
            fs2::available_space(&self.dir)
                .ok()
                .map(|free| (free as f64 * TOP_DISK_SHARE) as u64)
        });
        let size = top.written_size();
        let within = budget.is_some_and(|b| self.top_bytes.fetch_add(size, Relaxed) + size <= b);
        if !within {
            return;
        }
        let kept = top
            .to_bytes()
            .map_err(std::io::Error::other)
            .and_then(|bytes| self.write_checked(&format!("top-{i}"), &bytes));
        if let Err(e) = kept {
            let _ = std::fs::remove_file(self.dir.join(format!("top-{i}.tmp")));
            if !self.tops_given_up.swap(true, Relaxed) {
                tracing::warn!(
                    dir = %self.dir.display(),
                    error = %e,
                    "cannot keep the bricks' kept tops in the checkpoint: going on without them \
                     (a run again transforms the bricks not yet coded)"
                );
            }
        }
    }

    /// Keeps brick `i`'s score summary as [`Checkpoint::save_summary`] does; one that cannot
    /// be written is a warning (the first time) and the compression goes on without the
    /// checkpoint, which is a convenience, never a reason to fail.
    pub fn keep_summary(&self, i: usize, summary: &ScoreSummary, energies: bool) {
        if !self.is_unwritable() {
            let kept = self.save_summary(i, summary, energies);
            self.note(kept);
        }
    }

    /// Keeps brick `i` coded as [`Checkpoint::save_coded`] does, going on without the
    /// checkpoint where it cannot be written ([`Checkpoint::keep_summary`]).
    pub fn keep_coded(&self, i: usize, count: Option<u64>, file: &[u8]) {
        if !self.is_unwritable() {
            let kept = self.save_coded(i, count, file);
            self.note(kept);
        }
    }

    fn is_unwritable(&self) -> bool {
        self.unwritable.load(Relaxed)
    }

    /// Warns of the first entry that could not be written, and stops writing.
    fn note(&self, kept: std::io::Result<()>) {
        if let Err(e) = kept {
            if !self.unwritable.swap(true, Relaxed) {
                tracing::warn!(
                    dir = %self.dir.display(),
                    error = %e,
                    "cannot keep finished bricks in the checkpoint: going on without it (an \
                     interruption now loses what is not kept)"
                );
            }
        }
    }

    /// Removes the checkpoint (once the file it served is written).
    pub fn remove(self) -> std::io::Result<()> {
        self.stop_content_task();
        std::fs::remove_dir_all(&self.dir)
    }

    /// The bytes of entry `name` less its CRC-32 trailer, if present and the CRC matches.
    fn read_checked(&self, name: &str) -> Option<Vec<u8>> {
        read_checked_at(&self.dir.join(name))
    }

    /// Writes entry `name`: `bytes` and their CRC-32 (a kept top is hundreds of MB on a
    /// large volume: the two are written one after the other, not copied together).
    fn write_checked(&self, name: &str, bytes: &[u8]) -> std::io::Result<()> {
        let crc = crc32fast::hash(bytes).to_le_bytes();
        self.write_atomic_parts(name, &[bytes, &crc])
    }

    /// Writes `name` under a temporary name and renames it, so a kill leaves the old entry or
    /// none, never part of one.
    fn write_atomic(&self, name: &str, bytes: &[u8]) -> std::io::Result<()> {
        self.write_atomic_parts(name, &[bytes])
    }

    /// [`Checkpoint::write_atomic`] of `parts` one after the other.
    fn write_atomic_parts(&self, name: &str, parts: &[&[u8]]) -> std::io::Result<()> {
        write_atomic_at(&self.dir, name, parts)
    }
}

/// Writes `parts` to `name` in `dir` under a temporary name and renames it.
fn write_atomic_at(dir: &Path, name: &str, parts: &[&[u8]]) -> std::io::Result<()> {
    use std::io::Write;
    let tmp = dir.join(format!("{name}.tmp"));
    let mut file = std::fs::File::create(&tmp)?;
    for part in parts {
        file.write_all(part)?;
    }
    drop(file);
    std::fs::rename(&tmp, dir.join(name))
}

/// The bytes of the entry at `path` less its CRC-32 trailer, if present and the CRC matches.
fn read_checked_at(path: &Path) -> Option<Vec<u8>> {
    let mut bytes = std::fs::read(path).ok()?;
    let body = bytes.len().checked_sub(4)?;
    let stored = u32::from_le_bytes(bytes[body..].try_into().ok()?);
    bytes.truncate(body);
    (crc32fast::hash(&bytes) == stored).then_some(bytes)
}

/// Whether `path` is a checkpoint entry's file (a summary, a kept top or a coded brick, or one
/// being written): what a checkpoint of another key has removed, and nothing else of the
/// directory.
fn is_entry(path: &Path) -> bool {
    path.is_file()
        && path.file_name().and_then(|n| n.to_str()).is_some_and(|n| {
            n.starts_with("score-")
                || n.starts_with("brick-")
                || n.starts_with("top-")
                || n.starts_with(PLAN_FILE)
                || n.starts_with(CONTENT_FILE)
        })
}

/// The entry name of brick `i` coded keeping `count` coefficients.
fn coded_name(i: usize, count: Option<u64>) -> String {
    match count {
        Some(k) => format!("brick-{i}-{k}"),
        None => format!("brick-{i}-all"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encode::{score_summary, CompressOptions};
    use crate::phantom::Phantom;

    /// Entries read back as written; one cut short, with a byte changed, or left under its
    /// temporary name (a kill while writing) is not read, so its pass is done again.
    #[test]
    fn entries_read_back_and_damaged_ones_are_not_read() {
        let dir = tempfile::tempdir().unwrap();
        let (cp, resumed) = Checkpoint::open(dir.path(), "k").unwrap();
        assert_eq!(resumed, Resumed::default());
        let v = Phantom::Spheres.generate([16, 16, 16]);
        let opts = CompressOptions::default();
        let summary = score_summary(&v, &opts, &|_, _| {}).unwrap();
        cp.save_summary(3, &summary, false).unwrap();
        let file = crate::encode::compress(&v, &opts, &|_, _| {}).unwrap();
        cp.save_coded(3, Some(7), &file.bytes).unwrap();
        assert_eq!(
            cp.summary(3).unwrap().to_bytes(false),
            summary.to_bytes(false)
        );
        assert_eq!(
            cp.coded(3, Some(7)),
            Some((file.bytes.clone(), file.header.kept))
        );
        // Another count, another brick: not there.
        assert!(cp.coded(3, Some(8)).is_none() && cp.coded(3, None).is_none());
        assert!(cp.summary(2).is_none());
        let (_, resumed) = Checkpoint::open(dir.path(), "k").unwrap();
        assert_eq!((resumed.scored, resumed.coded), (1, 1));

        let path = dir.path().join("brick-3-7");
        let good = std::fs::read(&path).unwrap();
        std::fs::write(&path, &good[..good.len() - 1]).unwrap();
        assert!(cp.coded(3, Some(7)).is_none(), "cut short");
        let mut flipped = good.clone();
        flipped[good.len() / 2] ^= 0x10;
        std::fs::write(&path, &flipped).unwrap();
        assert!(cp.coded(3, Some(7)).is_none(), "a byte changed");
        std::fs::remove_file(&path).unwrap();
        std::fs::write(dir.path().join("brick-3-7.tmp"), &good).unwrap();
        assert!(cp.coded(3, Some(7)).is_none(), "never renamed");
        let (_, resumed) = Checkpoint::open(dir.path(), "k").unwrap();
        assert_eq!((resumed.scored, resumed.coded), (1, 0));
    }

    /// A kept top reads back as one that codes the same file; one cut short, changed, or
    /// read with other options is not used; a count of them is given on opening.
    #[test]
    fn a_kept_top_reads_back_and_a_damaged_one_is_not_used() {
        let dir = tempfile::tempdir().unwrap();
        let (cp, _) = Checkpoint::open(dir.path(), "k").unwrap();
        let v = Phantom::Spheres.generate([16, 16, 16]);
        // A brick's options under the fast effort: no refinement.
        let opts = CompressOptions {
            refine: None,
            ..crate::encode::Effort::Fast.options()
        };
        let (_, top) = crate::encode::score_keeping_top(&v, &opts, 300, &|_, _| {}).unwrap();
        let top = top.unwrap();
        cp.keep_top(2, &top);
        let back = cp.top(2, v.dims(), &opts).expect("kept and read back");
        assert_eq!(
            back.compress(200).unwrap().bytes,
            top.compress(200).unwrap().bytes
        );
        assert!(cp.top(1, v.dims(), &opts).is_none());
        assert!(cp.top(2, [16, 16, 15], &opts).is_none(), "another size");
        let other = CompressOptions {
            family: wavesplat_codec::family::Family::ALL
                .into_iter()
                .find(|f| *f != opts.family)
                .unwrap(),
            ..opts.clone()
        };
        assert!(cp.top(2, v.dims(), &other).is_none(), "other options");
        let (_, resumed) = Checkpoint::open(dir.path(), "k").unwrap();
        assert_eq!(resumed.tops, 1);
        let path = dir.path().join("top-2");
        let good = std::fs::read(&path).unwrap();
        let mut flipped = good.clone();
        flipped[good.len() / 2] ^= 0x10;
        std::fs::write(&path, &flipped).unwrap();
        assert!(cp.top(2, v.dims(), &opts).is_none(), "a byte changed");
        std::fs::write(&path, &good[..good.len() - 9]).unwrap();
        assert!(cp.top(2, v.dims(), &opts).is_none(), "cut short");
    }

    /// An entry that cannot be written (its name taken by a directory) leaves the checkpoint
    /// unwritten from then on, without an error; what was kept before still reads.
    #[test]
    fn an_unwritable_checkpoint_is_given_up_without_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let (cp, _) = Checkpoint::open(dir.path(), "k").unwrap();
        cp.keep_coded(0, None, b"first");
        std::fs::create_dir_all(dir.path().join("brick-1-all").join("taken")).unwrap();
        cp.keep_coded(1, None, b"second");
        assert!(cp.is_unwritable());
        cp.keep_coded(2, None, b"third");
        assert!(!dir.path().join("brick-2-all").exists());
        assert!(cp
            .read_checked("brick-0-all")
            .is_some_and(|b| b == b"first"));
    }

    /// Another key empties the checkpoint of its entries (and only of them); removing it
    /// removes the directory.
    #[test]
    fn another_key_empties_the_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let at = dir.path().join("out.wsp.checkpoint");
        let (cp, _) = Checkpoint::open(&at, "first").unwrap();
        cp.write_checked("score-0", b"anything").unwrap();
        cp.write_checked("top-0", b"anything").unwrap();
        std::fs::write(at.join("notes.txt"), b"mine").unwrap();
        let (cp, resumed) = Checkpoint::open(&at, "second").unwrap();
        assert!(resumed.replaced);
        assert_eq!((resumed.scored, resumed.tops, resumed.coded), (0, 0, 0));
        assert!(!at.join("score-0").exists() && at.join("notes.txt").exists());
        assert!(!at.join("top-0").exists());
        assert_eq!(std::fs::read(at.join(KEY_FILE)).unwrap(), b"second");
        cp.remove().unwrap();
        assert!(!at.exists());
    }
}
