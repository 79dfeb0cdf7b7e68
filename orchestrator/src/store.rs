//! The sled store. Trees: `jobs` (id, big-endian → JSON [`Job`]), `blobs` (SHA-256 → the
//! bytes of an uploaded source) and `results` (a bricked job's id and its part's id, both
//! big-endian → the part's result). The queue lives in memory ([`crate::queue::Queue`]) and every
//! change is written through and flushed before the request that caused it is answered, so an
//! acknowledged submission or outcome survives SIGKILL. Heartbeats are not flushed (a lease
//! gets fresh grace on restart instead).

use crate::error::OrchestratorError;
use crate::model::{Job, JobState, Source};
use std::collections::HashSet;
use std::path::Path;

/// Handle to the store; cheap to clone.
#[derive(Clone, Debug)]
pub struct Store {
    db: sled::Db,
    jobs: sled::Tree,
    blobs: sled::Tree,
    results: sled::Tree,
    /// One flush at a time (see [`Store::flush`]).
    flushing: std::sync::Arc<tokio::sync::Mutex<()>>,
}

impl Store {
    /// Opens (or creates) the store in `dir`.
    pub fn open(dir: impl AsRef<Path>) -> Result<Store, OrchestratorError> {
        let db = sled::open(dir)?;
        Ok(Store {
            jobs: db.open_tree("jobs")?,
            blobs: db.open_tree("blobs")?,
            results: db.open_tree("results")?,
            db,
            flushing: Default::default(),
        })
    }

    /// Every stored job, by id.
    pub fn load(&self) -> Result<Vec<Job>, OrchestratorError> {
        self.jobs
            .iter()
            .map(|kv| {
                let (k, v) = kv?;
                serde_json::from_slice(&v).map_err(|e| {
                    OrchestratorError::Corrupt(format!("job record {:?}: {e}", k.as_ref()))
                })
            })
            .collect()
    }

    /// Writes jobs (not yet flushed), one insert each: every record stands alone, and a
    /// `sled::Batch` would take sled's exclusive lock, which deadlocks against a flush in
    /// progress (the flush waits on the log flusher, which waits behind the batch's lock).
    pub fn put(&self, jobs: &[Job]) -> Result<(), OrchestratorError> {
        for j in jobs {
            let v = serde_json::to_vec(j)
                .map_err(|e| OrchestratorError::Corrupt(format!("encoding job {}: {e}", j.id)))?;
            self.jobs.insert(j.id.to_be_bytes(), v)?;
        }
        Ok(())
    }

    /// Makes everything written so far durable. Flushes run one at a time, each a blocking
    /// `flush` off the async threads: sled 0.34's `flush_async` deadlocks when called
    /// concurrently with itself and with writes (spacejam/sled#1308; `bench queue` with eight
    /// workers hung within seconds), and the release that fixes it never shipped. A caller
    /// that waited for another's flush flushes again, which costs little when nothing is new.
    pub async fn flush(&self) -> Result<(), OrchestratorError> {
        let _one = self.flushing.lock().await;
        let db = self.db.clone();
        tokio::task::spawn_blocking(move || db.flush())
            .await
            .map_err(|e| OrchestratorError::Corrupt(format!("flushing the store failed: {e}")))??;
        Ok(())
    }

    /// Stores an uploaded source under its hash.
    pub fn put_blob(&self, sha: &[u8; 32], bytes: &[u8]) -> Result<(), OrchestratorError> {
        self.blobs.insert(sha, bytes)?;
        Ok(())
    }

    /// An uploaded source.
    pub fn blob(&self, sha: &[u8; 32]) -> Result<Option<sled::IVec>, OrchestratorError> {
        Ok(self.blobs.get(sha)?)
    }

    /// Stores the result of part `id` of the bricked job `parent` (not yet flushed).
    pub fn put_result(&self, parent: u64, id: u64, bytes: &[u8]) -> Result<(), OrchestratorError> {
        self.results.insert(result_key(parent, id), bytes)?;
        Ok(())
    }

    /// The result of part `id` of `parent`.
    pub fn result(&self, parent: u64, id: u64) -> Result<Option<sled::IVec>, OrchestratorError> {
        Ok(self.results.get(result_key(parent, id))?)
    }

    /// Of the parts `ids` of `parent`, those whose results are stored (by key alone: a poll
    /// asks this of a parent's done parts, whose results may be large).
    pub fn result_ids_among(
        &self,
        parent: u64,
        ids: impl IntoIterator<Item = u64>,
    ) -> Result<HashSet<u64>, OrchestratorError> {
        let mut stored = HashSet::new();
        for id in ids {
            if self.results.contains_key(result_key(parent, id))? {
                stored.insert(id);
            }
        }
        Ok(stored)
    }

    /// Drops every result of `parent`'s parts; returns how many.
    pub fn drop_results(&self, parent: u64) -> Result<usize, OrchestratorError> {
        let keys: Vec<sled::IVec> = self
            .results
            .scan_prefix(parent.to_be_bytes())
            .keys()
            .collect::<Result<_, _>>()?;
        for k in &keys {
            self.results.remove(k)?;
        }
        Ok(keys.len())
    }

    /// Drops the uploaded source of `job` unless another unfinished job still needs it.
    pub fn release_blob<'a>(
        &self,
        job: &Job,
        all: impl Iterator<Item = &'a Job>,
    ) -> Result<(), OrchestratorError> {
        if !matches!(job.spec.source, Source::Upload { .. }) {
            return Ok(());
        }
        self.drop_blob_unless_needed(&job.spec.sha256, all.filter(|j| j.id != job.id))
    }

    /// Removes the uploaded source `sha256` unless one of `jobs` still needs it (an upload
    /// job of that source not yet done).
    pub fn drop_blob_unless_needed<'a>(
        &self,
        sha256: &[u8; 32],
        mut jobs: impl Iterator<Item = &'a Job>,
    ) -> Result<(), OrchestratorError> {
        let needed = jobs.any(|j| {
            j.spec.sha256 == *sha256
                && matches!(j.spec.source, Source::Upload { .. })
                && !matches!(j.state, JobState::Done { .. })
        });
        if !needed {
            self.blobs.remove(sha256)?;
        }
        Ok(())
    }
}

fn result_key(parent: u64, id: u64) -> [u8; 16] {
    let mut k = [0u8; 16];
    k[..8].copy_from_slice(&parent.to_be_bytes());
    k[8..].copy_from_slice(&id.to_be_bytes());
    k
}
