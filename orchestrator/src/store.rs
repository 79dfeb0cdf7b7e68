//! The sled store. Trees: `jobs` (id, big-endian → JSON [`Job`]) and `blobs` (SHA-256 → the
//! bytes of an uploaded source). The queue lives in memory ([`crate::queue::Queue`]) and every
//! change is written through and flushed before the request that caused it is answered, so an
//! acknowledged submission or outcome survives SIGKILL. Heartbeats are not flushed (a lease
//! gets fresh grace on restart instead).

use crate::error::OrchestratorError;
use crate::model::{Job, JobState, Source};
use std::path::Path;

/// Handle to the store; cheap to clone.
#[derive(Clone, Debug)]
pub struct Store {
    db: sled::Db,
    jobs: sled::Tree,
    blobs: sled::Tree,
}

impl Store {
    /// Opens (or creates) the store in `dir`.
    pub fn open(dir: impl AsRef<Path>) -> Result<Store, OrchestratorError> {
        let db = sled::open(dir)?;
        Ok(Store {
            jobs: db.open_tree("jobs")?,
            blobs: db.open_tree("blobs")?,
            db,
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

    /// Writes jobs (not yet flushed).
    pub fn put(&self, jobs: &[Job]) -> Result<(), OrchestratorError> {
        let mut batch = sled::Batch::default();
        for j in jobs {
            let v = serde_json::to_vec(j)
                .map_err(|e| OrchestratorError::Corrupt(format!("encoding job {}: {e}", j.id)))?;
            batch.insert(&j.id.to_be_bytes(), v);
        }
        self.jobs.apply_batch(batch)?;
        Ok(())
    }

    /// Makes everything written so far durable.
    pub async fn flush(&self) -> Result<(), OrchestratorError> {
        self.db.flush_async().await?;
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

    /// Drops the uploaded source of `job` unless another unfinished job still needs it.
    pub fn release_blob<'a>(
        &self,
        job: &Job,
        all: impl Iterator<Item = &'a Job>,
    ) -> Result<(), OrchestratorError> {
        if !matches!(job.spec.source, Source::Upload { .. }) {
            return Ok(());
        }
        let needed = all.filter(|j| j.id != job.id).any(|j| {
            j.spec.sha256 == job.spec.sha256
                && matches!(j.spec.source, Source::Upload { .. })
                && !matches!(j.state, JobState::Done { .. })
        });
        if !needed {
            self.blobs.remove(job.spec.sha256)?;
        }
        Ok(())
    }
}
