//! Connections: the accept loop of `ufops serve`.
//!
//! Our own loop instead of `axum::serve`, because the server must bound what one client can hold
//! (issue 15, "request and body timeouts"):
//! - a request's headers must arrive within `header_read_timeout`, counted from when the
//!   connection waits for them: a slowloris client trickling headers is cut off, and an idle
//!   keep-alive connection is closed after the same time;
//! - a response the client stops reading fails after `write_stall_timeout` without progress
//!   (a write-side timeout on the socket: hyper stops polling the body while the socket is full,
//!   so a body-level timeout would never fire);
//! - at most `max_connections` are open at once; further clients wait in the kernel's backlog
//!   instead of exhausting file descriptors.
//!
//! Request bodies get an idle timeout in the router (`RequestBodyTimeoutLayer`, see `lib.rs`).
//! Each request carries the peer's address (`ConnectInfo<SocketAddr>`) for the per-address
//! limits of `auth.rs`.

use axum::extract::ConnectInfo;
use axum::Router;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;
use tower::ServiceExt;

/// What one connection may hold (see the module docs).
#[derive(Debug, Clone, Copy)]
pub(crate) struct ConnLimits {
    pub header_read_timeout: Duration,
    pub write_stall_timeout: Duration,
    pub max_connections: usize,
}

/// Accepts connections until `shutdown` resolves, then stops accepting and waits until every
/// open connection has finished its request in flight (the caller bounds that wait).
pub(crate) async fn serve_connections(
    listener: tokio::net::TcpListener,
    app: Router,
    limits: ConnLimits,
    shutdown: impl Future<Output = ()> + Send + 'static,
) {
    let permits = Arc::new(tokio::sync::Semaphore::new(limits.max_connections.max(1)));
    let graceful = GracefulShutdown::new();
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(TokioTimer::new()).header_read_timeout(limits.header_read_timeout);
    tokio::pin!(shutdown);
    loop {
        let permit = tokio::select! {
            p = permits.clone().acquire_owned() => p.expect("the connection semaphore is never closed"),
            _ = &mut shutdown => break,
        };
        let (tcp, peer) = tokio::select! {
            r = listener.accept() => match r {
                Ok(c) => c,
                Err(e) => {
                    // Out of descriptors, or a connection reset before we took it: keep serving
                    // the connections we have, try again shortly.
                    tracing::warn!("cannot accept a connection: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
            _ = &mut shutdown => break,
        };
        let _ = tcp.set_nodelay(true);
        let mut io = tokio_io_timeout::TimeoutStream::new(tcp);
        io.set_write_timeout(Some(limits.write_stall_timeout));
        let io = TokioIo::new(Box::pin(io));
        let app = app.clone();
        let service = hyper::service::service_fn(move |mut req: hyper::Request<hyper::body::Incoming>| {
            req.extensions_mut().insert(ConnectInfo(peer));
            app.clone().oneshot(req)
        });
        let conn = graceful.watch(http.serve_connection(io, service));
        tokio::spawn(async move {
            let _permit = permit;
            if let Err(e) = conn.await {
                tracing::debug!("connection from {peer} ended: {e}");
            }
        });
    }
    drop(listener);
    graceful.shutdown().await;
}
