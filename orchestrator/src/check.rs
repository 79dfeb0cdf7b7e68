//! Confirming a worker's delivery with the cache before the job is marked done: the cache must
//! hold the job's name as the volume the worker reports, with the content (SHA-256) it reports.
//! A worker cannot then finish a job with a made-up volume id, or one it never stored.

use crate::error::OrchestratorError;
use crate::model::Delivery;
use tokio::sync::OnceCell;
use wavesplat_client::{CacheClient, VolumeKey};
use wavesplat_net::ConnectOptions;

/// A connection to the cache deliveries are checked against. Made before any async runtime
/// exists (the server's arguments are read first): the URL, CA and token are checked at once,
/// the connection is opened on the first check, inside the server's runtime.
#[derive(Debug, Clone)]
pub struct DeliveryCheck {
    url: String,
    options: ConnectOptions,
    cache: std::sync::Arc<OnceCell<CacheClient>>,
}

impl DeliveryCheck {
    /// Checks against the cache at `url` (connected on first use; needs the `read` role).
    /// Fails at once on a malformed URL or an unreadable CA file.
    pub fn new(url: &str, options: &ConnectOptions) -> Result<DeliveryCheck, OrchestratorError> {
        options
            .endpoint(url)
            .map_err(|e| OrchestratorError::Connect(e.to_string()))?;
        Ok(DeliveryCheck {
            url: url.to_string(),
            options: options.clone(),
            cache: std::sync::Arc::new(OnceCell::new()),
        })
    }

    /// The cache URL deliveries are checked against.
    pub fn url(&self) -> &str {
        &self.url
    }

    async fn client(&self) -> Result<CacheClient, OrchestratorError> {
        let client = self
            .cache
            .get_or_try_init(|| async {
                CacheClient::connect_lazy(&self.url, &self.options)
                    .map_err(|e| OrchestratorError::Connect(e.to_string()))
            })
            .await?;
        Ok(client.clone())
    }

    /// Whether the cache holds `name` as the delivered volume.
    pub async fn confirm(&self, name: &str, d: &Delivery) -> Result<(), OrchestratorError> {
        let mut cache = self.client().await?;
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The server reads its arguments, and so makes its check, before its runtime starts.
    #[test]
    fn a_check_is_made_outside_any_async_runtime() {
        let check = DeliveryCheck::new("http://127.0.0.1:1", &ConnectOptions::default()).unwrap();
        assert_eq!(check.url(), "http://127.0.0.1:1");
        assert!(DeliveryCheck::new("ftp://x", &ConnectOptions::default()).is_err());
    }
}
