//! Failing over between orchestrators: a channel over several orchestrator URLs
//! (`--orchestrator URL,URL`) that sends each request to the current one and moves on to the
//! next when a request fails at the transport (refused, reset, the host gone). Orchestrators
//! over one shared queue database are interchangeable, so the caller's own retry (a worker's
//! lease loop, heartbeats and outcome reports all retry) lands on a live one. Failures the
//! orchestrator answers itself (a gRPC status) do not move it: another would answer the same.
//!
//! Written here because tonic's balancing channel spreads load over endpoints instead of
//! keeping one and moving on failure, and keeps a dead endpoint in rotation until its
//! discovery stream says otherwise.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use tonic::body::Body;
use tonic::codegen::{BoxFuture, Context, Poll, Service};
use tonic::transport::Channel;

/// Channels to several orchestrators, one in use at a time.
#[derive(Clone, Debug)]
pub struct Failover {
    channels: Arc<[(String, Channel)]>,
    current: Arc<AtomicUsize>,
}

impl Failover {
    /// Over `channels` (URL, channel), starting at `first`.
    pub fn new(channels: Vec<(String, Channel)>, first: usize) -> Failover {
        let n = channels.len().max(1);
        Failover {
            channels: channels.into(),
            current: Arc::new(AtomicUsize::new(first % n)),
        }
    }
}

impl Service<http::Request<Body>> for Failover {
    type Response = http::Response<Body>;
    type Error = tonic::transport::Error;
    type Future = BoxFuture<Self::Response, Self::Error>;

    fn poll_ready(&mut self, _cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        // Readiness is awaited on the chosen channel in `call`.
        Poll::Ready(Ok(()))
    }

    fn call(&mut self, request: http::Request<Body>) -> Self::Future {
        let n = self.channels.len();
        let i = self.current.load(Ordering::Relaxed) % n;
        let (url, mut channel) = self.channels[i].clone();
        let current = self.current.clone();
        let channels = self.channels.clone();
        Box::pin(async move {
            let result = async {
                std::future::poll_fn(|cx| channel.poll_ready(cx)).await?;
                channel.call(request).await
            }
            .await;
            if let Err(e) = &result {
                if n > 1
                    && current
                        .compare_exchange(i, (i + 1) % n, Ordering::Relaxed, Ordering::Relaxed)
                        .is_ok()
                {
                    tracing::warn!(
                        from = %url,
                        to = %channels[(i + 1) % n].0,
                        error = %e,
                        "orchestrator unreachable; failing over"
                    );
                }
            }
            result
        })
    }
}
