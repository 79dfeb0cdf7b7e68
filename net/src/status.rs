//! Client faults get client statuses. tonic answers a request it cannot decode with `INTERNAL`
//! and one over the message-size limit with `OUT_OF_RANGE`; both are the caller's fault, so the
//! services answer `INVALID_ARGUMENT` and `RESOURCE_EXHAUSTED` instead. Unary requests are
//! decoded before a handler runs: [`ClientFaultLayer`] rewrites those answers on their way out.
//! Streaming requests are decoded as the handler reads them: [`client_fault`] maps the error
//! where it is read.

use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use tonic::{Code, Status};

const DECODE_ERROR: &str = "failed to decode";
const TOO_LARGE: &str = "message length too large";

/// The status a client should see for an error reading its request.
pub fn client_fault(s: Status) -> Status {
    match remap(s.code(), s.message()) {
        Some(code) => Status::new(code, s.message().to_string()),
        None => s,
    }
}

fn remap(code: Code, message: &str) -> Option<Code> {
    match code {
        Code::Internal if message.contains(DECODE_ERROR) => Some(Code::InvalidArgument),
        Code::OutOfRange if message.contains(TOO_LARGE) => Some(Code::ResourceExhausted),
        _ => None,
    }
}

/// Rewrites the status of trailers-only responses (errors before a handler ran) with
/// [`client_fault`]'s rules. Add it to a server with `Server::builder().layer(..)`.
#[derive(Debug, Clone, Copy, Default)]
pub struct ClientFaultLayer;

impl<S> tower::Layer<S> for ClientFaultLayer {
    type Service = ClientFault<S>;
    fn layer(&self, inner: S) -> ClientFault<S> {
        ClientFault(inner)
    }
}

/// The service [`ClientFaultLayer`] makes.
#[derive(Debug, Clone)]
pub struct ClientFault<S>(S);

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

impl<S, B, R> tower::Service<http::Request<B>> for ClientFault<S>
where
    S: tower::Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
{
    type Response = http::Response<R>;
    type Error = S::Error;
    type Future = BoxFuture<Result<http::Response<R>, S::Error>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.0.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<B>) -> Self::Future {
        let fut = self.0.call(req);
        Box::pin(async move {
            let mut response = fut.await?;
            rewrite(response.headers_mut());
            Ok(response)
        })
    }
}

fn rewrite(headers: &mut http::HeaderMap) {
    if headers.get("grpc-status").is_none() {
        return;
    }
    let Some(status) = Status::from_header_map(headers) else {
        return;
    };
    if let Some(new) = remap(status.code(), status.message()) {
        headers.insert("grpc-status", http::HeaderValue::from(new as i32));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decode_and_size_errors_become_client_statuses_and_others_stay() {
        let s = client_fault(Status::internal("failed to decode Protobuf message: x"));
        assert_eq!(s.code(), Code::InvalidArgument);
        let s = client_fault(Status::out_of_range(
            "Error, decoded message length too large: found 9 bytes, the limit is: 1 bytes",
        ));
        assert_eq!(s.code(), Code::ResourceExhausted);
        assert_eq!(
            client_fault(Status::internal("disk")).code(),
            Code::Internal
        );
        assert_eq!(
            client_fault(Status::out_of_range("x")).code(),
            Code::OutOfRange
        );
        let mut h = http::HeaderMap::new();
        h.insert("grpc-status", http::HeaderValue::from(13));
        h.insert(
            "grpc-message",
            http::HeaderValue::from_static("failed%20to%20decode%20Protobuf%20message"),
        );
        rewrite(&mut h);
        assert_eq!(h.get("grpc-status").unwrap(), "3");
    }
}
