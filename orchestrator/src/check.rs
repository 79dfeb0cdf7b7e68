//! Confirming a worker's delivery with the cache before the job is marked done: the cache must
//! hold the job's name as the volume the worker reports, with the content (SHA-256) it reports.
//! A worker cannot then finish a job with a made-up volume id, or one it never stored.

use crate::error::OrchestratorError;
use crate::model::Delivery;
use wavesplat_client::{CacheClient, VolumeKey};
use wavesplat_net::ConnectOptions;

/// A connection to the cache deliveries are checked against.
#[derive(Debug, Clone)]
pub struct DeliveryCheck {
    cache: CacheClient,
}

impl DeliveryCheck {
    /// Checks against the cache at `url` (connected on first use; needs the `read` role).
    pub fn new(url: &str, options: &ConnectOptions) -> Result<DeliveryCheck, OrchestratorError> {
        let cache = CacheClient::connect_lazy(url, options)
            .map_err(|e| OrchestratorError::Connect(e.to_string()))?;
        Ok(DeliveryCheck { cache })
    }

    /// Whether the cache holds `name` as the delivered volume.
    pub async fn confirm(&self, name: &str, d: &Delivery) -> Result<(), OrchestratorError> {
        let mut cache = self.cache.clone();
        match cache.describe(&VolumeKey::Name(name.to_string())).await {
            Ok(v) if v.id == d.cache_volume_id && v.sha256 == d.sha256 => Ok(()),
            Ok(v) => Err(OrchestratorError::Unconfirmed(format!(
                "the cache holds {name:?} as volume {} with SHA-256 {}; the worker reported \
                 volume {} with {}",
                v.id, v.sha256, d.cache_volume_id, d.sha256
            ))),
            Err(e) if e.code() == Some(tonic::Code::NotFound) => Err(
                OrchestratorError::Unconfirmed(format!("the cache holds no volume named {name:?}")),
            ),
            Err(e) => Err(OrchestratorError::CacheUnavailable(e.to_string())),
        }
    }
}
