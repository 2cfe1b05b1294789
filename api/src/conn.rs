//! Connections: the accept loop of `ufops serve`.
//!
//! Our own loop instead of `axum::serve`, because the server must bound what one client can hold:
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
//! Each request carries the client's address (`ConnectInfo<SocketAddr>`) for the per-address
//! limits of `auth.rs`: the peer's, or behind a trusted reverse proxy the one its
//! `X-Forwarded-For` names ([`client_addr`]).

use axum::extract::ConnectInfo;
use axum::Router;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::Duration;
use tower::ServiceExt;

/// What one connection may hold (see the module docs).
#[derive(Debug, Clone)]
pub(crate) struct ConnLimits {
    pub header_read_timeout: Duration,
    pub write_stall_timeout: Duration,
    pub max_connections: usize,
    pub trusted_proxies: Arc<[IpAddr]>,
}

/// The address the per-address limits count for a request from `peer`: the peer itself, or,
/// when the peer is a trusted proxy, the rightmost `X-Forwarded-For` entry that is not a
/// trusted proxy (entries left of it are the client's own claims, which anyone can forge). A
/// header that is missing or unreadable there leaves the proxy's address.
pub(crate) fn client_addr(
    peer: SocketAddr,
    headers: &axum::http::HeaderMap,
    trusted: &[IpAddr],
) -> SocketAddr {
    if !trusted.contains(&peer.ip()) {
        return peer;
    }
    let lines: Vec<&str> =
        headers.get_all("x-forwarded-for").iter().filter_map(|v| v.to_str().ok()).collect();
    for hop in lines.iter().rev().flat_map(|l| l.rsplit(',')).map(str::trim) {
        let ip = hop.parse::<IpAddr>().ok().or_else(|| hop.parse::<SocketAddr>().ok().map(|s| s.ip()));
        match ip {
            Some(ip) if trusted.contains(&ip) => continue,
            Some(ip) => return SocketAddr::new(ip, 0),
            None => return peer,
        }
    }
    peer
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
        let trusted = limits.trusted_proxies.clone();
        let service = hyper::service::service_fn(move |mut req: hyper::Request<hyper::body::Incoming>| {
            let client = client_addr(peer, req.headers(), &trusted);
            req.extensions_mut().insert(ConnectInfo(client));
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

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(lines: &[&str]) -> axum::http::HeaderMap {
        let mut h = axum::http::HeaderMap::new();
        for l in lines {
            h.append("x-forwarded-for", l.parse().unwrap());
        }
        h
    }

    #[test]
    fn only_a_trusted_proxy_names_the_client() {
        let proxy: SocketAddr = "10.0.0.1:5000".parse().unwrap();
        let trusted: Vec<IpAddr> = vec!["10.0.0.1".parse().unwrap(), "10.0.0.2".parse().unwrap()];
        let ip = |s: &str| -> IpAddr { s.parse().unwrap() };
        // Not trusted: the header is ignored.
        assert_eq!(client_addr(proxy, &headers(&["203.0.113.7"]), &[]), proxy);
        // Trusted: the rightmost entry that is not a proxy; forged entries to its left are ignored.
        assert_eq!(client_addr(proxy, &headers(&["1.2.3.4, 203.0.113.7"]), &trusted).ip(), ip("203.0.113.7"));
        assert_eq!(
            client_addr(proxy, &headers(&["1.2.3.4", "203.0.113.7, 10.0.0.2"]), &trusted).ip(),
            ip("203.0.113.7")
        );
        assert_eq!(client_addr(proxy, &headers(&["[2001:db8::1]:443"]), &trusted).ip(), ip("2001:db8::1"));
        // Missing, only proxies, or unreadable: the proxy's own address.
        assert_eq!(client_addr(proxy, &headers(&[]), &trusted), proxy);
        assert_eq!(client_addr(proxy, &headers(&["10.0.0.2"]), &trusted), proxy);
        assert_eq!(client_addr(proxy, &headers(&["1.2.3.4, not-an-address"]), &trusted), proxy);
    }
}
