//! Async client helpers over the generated `OrchestratorClient`, used by the CLI, the worker
//! and the tests: connecting (TLS and the token through [`ConnectOptions`]), submitting,
//! listing.

use crate::convert;
use crate::error::ClientError;
use crate::model::JobSpec;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::Status;
use wavesplat_net::{ConnectOptions, Credentials};
use wavesplat_proto::pb;
use wavesplat_proto::pb::orchestrator_client::OrchestratorClient;

/// The generated client over a channel that adds the caller's token.
pub type Client = OrchestratorClient<InterceptedService<Channel, Credentials>>;

fn client(channel: Channel, options: &ConnectOptions) -> Client {
    OrchestratorClient::new(InterceptedService::new(
        channel,
        options.credentials.clone(),
    ))
    .max_decoding_message_size(64 << 20)
}

/// Connects to an orchestrator at `url` (`http://HOST:PORT`, `https://HOST:PORT` or
/// `HOST:PORT`) without a token.
pub async fn connect(url: &str) -> Result<Client, ClientError> {
    connect_with(url, &ConnectOptions::default()).await
}

/// Connects to an orchestrator at `url` with `options` (CA, token).
pub async fn connect_with(url: &str, options: &ConnectOptions) -> Result<Client, ClientError> {
    let (url, ep) = options
        .endpoint(url)
        .map_err(|e| ClientError::Connect(e.to_string()))?;
    let channel = ep.connect().await.map_err(|e| {
        ClientError::Connect(format!(
            "{url}: {}",
            wavesplat_net::tls::explain_connect_error(&url, &e)
        ))
    })?;
    Ok(client(channel, options))
}

/// A client that connects on first use and reconnects after failures.
pub fn connect_lazy(url: &str, options: &ConnectOptions) -> Result<Client, ClientError> {
    let (_, ep) = options
        .endpoint(url)
        .map_err(|e| ClientError::Connect(e.to_string()))?;
    Ok(client(ep.connect_lazy(), options))
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

/// Every job.
pub async fn list(client: &mut Client) -> Result<Vec<pb::Job>, Status> {
    Ok(client
        .list_jobs(pb::ListJobsRequest {})
        .await?
        .into_inner()
        .jobs)
}
