//! Async client helpers over the generated `OrchestratorClient`, used by the CLI, the worker
//! and the tests: connecting (TLS and the token through [`ConnectOptions`]), submitting,
//! listing.

use crate::convert;
use crate::error::ClientError;
use crate::failover::Failover;
use crate::model::JobSpec;
use tonic::service::interceptor::InterceptedService;
use tonic::Status;
use wavesplat_net::{ConnectOptions, Credentials};
use wavesplat_proto::pb;
use wavesplat_proto::pb::orchestrator_client::OrchestratorClient;

/// The generated client over a channel (one orchestrator, or failing over between several)
/// that adds the caller's token.
pub type Client = OrchestratorClient<InterceptedService<Failover, Credentials>>;

fn client(channel: Failover, options: &ConnectOptions) -> Client {
    OrchestratorClient::new(InterceptedService::new(
        channel,
        options.credentials.clone(),
    ))
    .max_decoding_message_size(64 << 20)
}

/// The URLs of a comma-separated list (`URL` or `URL,URL,…`), each trimmed.
pub fn split_urls(urls: &str) -> Result<Vec<&str>, ClientError> {
    let list: Vec<&str> = urls.split(',').map(str::trim).collect();
    if list.iter().any(|u| u.is_empty()) {
        return Err(ClientError::Connect(format!(
            "orchestrator URL list {urls:?} has an empty entry"
        )));
    }
    Ok(list)
}

/// Connects to an orchestrator at `url` (`http://HOST:PORT`, `https://HOST:PORT` or
/// `HOST:PORT`; several separated by commas) without a token.
pub async fn connect(url: &str) -> Result<Client, ClientError> {
    connect_with(url, &ConnectOptions::default()).await
}

/// Connects to the first orchestrator of `urls` (comma-separated) that answers, with `options`
/// (CA, token); later requests fail over to the others ([`Failover`]). Fails, naming each
/// URL's reason, when none answers.
pub async fn connect_with(urls: &str, options: &ConnectOptions) -> Result<Client, ClientError> {
    let mut channels = Vec::new();
    let mut first = None;
    let mut reasons = Vec::new();
    for u in split_urls(urls)? {
        let (url, ep) = options
            .endpoint(u)
            .map_err(|e| ClientError::Connect(e.to_string()))?;
        let channel = if first.is_none() {
            match ep.connect().await {
                Ok(c) => {
                    first = Some(channels.len());
                    c
                }
                Err(e) => {
                    reasons.push(format!(
                        "{url}: {}",
                        wavesplat_net::tls::explain_connect_error(&url, &e)
                    ));
                    ep.connect_lazy()
                }
            }
        } else {
            ep.connect_lazy()
        };
        channels.push((url, channel));
    }
    let Some(first) = first else {
        return Err(ClientError::Connect(reasons.join("; ")));
    };
    Ok(client(Failover::new(channels, first), options))
}

/// A client over `urls` (comma-separated) that connects on first use, reconnects after
/// failures and fails over between the URLs.
pub fn connect_lazy(urls: &str, options: &ConnectOptions) -> Result<Client, ClientError> {
    let mut channels = Vec::new();
    for u in split_urls(urls)? {
        let (url, ep) = options
            .endpoint(u)
            .map_err(|e| ClientError::Connect(e.to_string()))?;
        channels.push((url, ep.connect_lazy()));
    }
    Ok(client(Failover::new(channels, 0), options))
}

/// Submits a job; `upload` carries the source's bytes when the spec says so.
pub async fn submit(
    client: &mut Client,
    spec: &JobSpec,
    upload: Option<&[u8]>,
) -> Result<pb::SubmitResponse, Status> {
    use pb::submit_request::Msg;
    let mut msgs = vec![pb::SubmitRequest {
        msg: Some(Msg::Spec(convert::spec_to_pb(spec))),
    }];
    if let Some(bytes) = upload {
        msgs.extend(bytes.chunks(crate::CHUNK_BYTES).map(|c| pb::SubmitRequest {
            msg: Some(Msg::Chunk(c.to_vec())),
        }));
    }
    Ok(client.submit(tokio_stream::iter(msgs)).await?.into_inner())
}

/// Every job, in id order (read page by page).
pub async fn list(client: &mut Client) -> Result<Vec<pb::Job>, Status> {
    let mut jobs: Vec<pb::Job> = Vec::new();
    loop {
        let after_id = jobs.last().map_or(0, |j| j.id);
        let page = client
            .list_jobs(pb::ListJobsRequest { after_id })
            .await?
            .into_inner();
        let more = page.more && !page.jobs.is_empty();
        jobs.extend(page.jobs);
        if !more {
            return Ok(jobs);
        }
    }
}
