//! Async client helpers over the generated `OrchestratorClient`, used by the CLI and the tests.

use crate::convert;
use crate::model::JobSpec;
use tonic::transport::Channel;
use tonic::Status;
use wavesplat_proto::pb;
use wavesplat_proto::pb::orchestrator_client::OrchestratorClient;

/// Connects to an orchestrator at `url` (`http://HOST:PORT` or `HOST:PORT`).
pub async fn connect(url: &str) -> Result<OrchestratorClient<Channel>, tonic::transport::Error> {
    let u = if url.contains("://") {
        url.to_string()
    } else {
        format!("http://{url}")
    };
    Ok(OrchestratorClient::connect(u)
        .await?
        .max_decoding_message_size(64 << 20))
}

/// Submits a job; `upload` carries the source's bytes when the spec says so.
pub async fn submit(
    client: &mut OrchestratorClient<Channel>,
    spec: &JobSpec,
    upload: Option<&[u8]>,
) -> Result<pb::SubmitResponse, Status> {
    use pb::submit_request::Msg;
    let mut msgs = vec![pb::SubmitRequest {
        msg: Some(Msg::Spec(convert::spec_to_pb(spec))),
    }];
    if let Some(bytes) = upload {
        msgs.extend(
            bytes
                .chunks(crate::service::CHUNK_BYTES)
                .map(|c| pb::SubmitRequest {
                    msg: Some(Msg::Chunk(c.to_vec())),
                }),
        );
    }
    Ok(client.submit(tokio_stream::iter(msgs)).await?.into_inner())
}

/// Every job.
pub async fn list(client: &mut OrchestratorClient<Channel>) -> Result<Vec<pb::Job>, Status> {
    Ok(client
        .list_jobs(pb::ListJobsRequest {})
        .await?
        .into_inner()
        .jobs)
}
