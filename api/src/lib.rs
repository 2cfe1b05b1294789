//! The ufops HTTP API (`ufops serve`) and the job worker loop (`ufops worker`).
//!
//! This crate owns the HTTP surface only: routing, authentication (bearer tokens verified by the
//! store) and role checks, request validation and size limits, problem+json errors, the OpenAPI
//! document (generated from the handlers with utoipa), Prometheus metrics, media range requests,
//! streamed uploads, `Idempotency-Key` replay (`idempotency.rs`), webhook delivery from the
//! change feed (`webhooks.rs`), the automations (`automations.rs`), the loop both run in
//! (`feed_consumers.rs`), and the worker loop that claims jobs and runs them through a
//! [`JobRunner`]. Every rule about data (label revisions, versions, splits, leases, aliases) lives in the
//! `store` crate, which the CLI uses too; the real job runner (training, ingest) is the binary's.

mod auth;
mod automations;
mod body_schemas;
mod conn;
mod error;
mod extract;
mod feed_consumers;
mod idempotency;
mod label_writer;
mod media;
mod metrics;
mod openapi;
mod routes;
mod session;
mod session_routes;
mod steps_json;
mod upload;
mod webhooks;
mod worker;

pub use auth::Caller;
pub use error::{ApiError, Problem};
pub use media::parse_range;
pub use openapi::{openapi, openapi_json};
pub use upload::{sanitize_filename, sweep as sweep_uploads};
pub use webhooks::{signature as webhook_signature, DELIVERY_TIMEOUT};
pub use worker::{run_worker, run_worker_with, worker_identity, JobContext, JobRunner, WorkerOptions};

use axum::extract::DefaultBodyLimit;
use axum::handler::Handler;
use axum::middleware::from_fn_with_state;
use axum::routing::{get, post};
use axum::Router;
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use store::{Backend, Role, Store};

/// How `ufops serve` runs.
#[derive(Debug, Clone)]
pub struct ServeConfig {
    /// Default `127.0.0.1:8080`; binding elsewhere is explicit.
    pub addr: SocketAddr,
    /// Largest JSON request body (default 1 MiB).
    pub body_limit_bytes: usize,
    /// Largest upload to `POST /v1/ingest` (default 50 GiB); uploads are streamed to disk.
    pub upload_limit_bytes: u64,
    /// Where uploads land (one fresh folder per upload); default `<data_dir>/uploads`.
    pub upload_dir: PathBuf,
    /// Run a job worker inside the server (default true).
    pub run_worker_in_process: bool,
    /// The in-process worker's id (default `serve-<pid>`).
    pub worker_id: String,
    /// The lease of the in-process worker's jobs (default 30 s; heartbeats every third of it).
    pub worker_lease_ms: i64,
    /// How long a verified token is trusted without asking the catalog again (default 5 s):
    /// a revoked token stops working within this time (at once on this server).
    pub token_cache_ttl: Duration,
    /// After the shutdown signal, how long requests in flight get to finish before the server
    /// closes anyway (default 10 s; a slow download must not hold a restart forever).
    pub shutdown_deadline: Duration,
    /// The origin browsers reach this server at when it runs behind a TLS proxy
    /// (`https://label.example.com`, see [`public_origin`]): the CSRF origin check compares with
    /// it, and https makes the session cookie `Secure`. None: the request's `Host`.
    pub public_url: Option<String>,
    /// Requests one token may have in flight at once (default 64); more get 429. A stalled or
    /// greedy client cannot take every connection the server has.
    pub max_in_flight_per_token: usize,
    /// Catalog lookups of tokens not in the cache at once (default 16); more get 429, so a flood
    /// of made-up tokens cannot keep the catalog busy.
    pub max_token_checks_in_flight: usize,
    /// Requests per second one token may make on average (default 1000, bursts of twice that);
    /// more get 429. 0: no limit.
    pub rate_limit_per_token: u32,
    /// Checks of tokens the server has not seen valid, per second per peer address (default 100,
    /// bursts of 1000); more get 429 before the catalog is asked. Bounds token guessing and a
    /// flood of made-up tokens; tokens seen valid recently are re-checked without this limit.
    pub unverified_checks_per_peer: u32,
    /// A request's headers must arrive within this time, counted from when the connection waits
    /// for them (default 30 s); idle keep-alive connections are closed after the same time.
    pub header_read_timeout: Duration,
    /// A request body that sends nothing for this long fails (default 30 s).
    pub body_idle_timeout: Duration,
    /// A response the client does not read for this long fails (default 60 s).
    pub write_stall_timeout: Duration,
    /// Open connections at once (default 4096); more wait in the kernel's backlog.
    pub max_connections: usize,
    /// Reverse proxies whose `X-Forwarded-For` is believed (default none): a request from one
    /// counts against the per-address limits of the client the header names (see `conn.rs`).
    pub trusted_proxies: Vec<std::net::IpAddr>,
    /// How long a request's `Idempotency-Key` and its response are kept (default 24 h).
    pub idempotency_ttl: Duration,
    /// The lease of a request being served under an idempotency key (default 30 s, renewed
    /// every third of it): after the server dies, a retry waits this long at most.
    pub idempotency_lease: Duration,
    /// Events of the change feed older than this are deleted (default 30 days; None: kept).
    pub event_retention: Option<Duration>,
    /// Deliver webhooks from this server (default true).
    pub deliver_webhooks: bool,
    /// The first retry of a failed webhook delivery waits this long, each next one twice as
    /// long (default 1 s; at most an hour).
    pub webhook_backoff: Duration,
    /// How often the delivery loop looks for due subscriptions besides waking on this server's
    /// commits (default 1 s): other servers' events and retries due.
    pub webhook_poll: Duration,
    /// Run the automations from this server (default true; `ufops serve --no-automations`).
    pub run_automations: bool,
}

/// `scheme://host[:port]` of a public URL (a trailing `/` allowed; no path, query or user info).
pub fn public_origin(url: &str) -> Result<String, String> {
    let u = url.trim().trim_end_matches('/');
    let (scheme, rest) =
        u.split_once("://").ok_or_else(|| format!("public URL {url:?}: expected https://HOST[:PORT]"))?;
    let scheme = scheme.to_ascii_lowercase();
    if scheme != "https" && scheme != "http" {
        return Err(format!("public URL {url:?}: the scheme must be https (or http)"));
    }
    let ok = !rest.is_empty()
        && rest.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | ':' | '[' | ']'));
    if !ok {
        return Err(format!("public URL {url:?}: expected https://HOST[:PORT], without a path"));
    }
    Ok(format!("{scheme}://{}", rest.to_ascii_lowercase()))
}

impl ServeConfig {
    /// Defaults, with uploads under `<data_dir>/uploads`.
    pub fn new(data_dir: &std::path::Path) -> Self {
        ServeConfig {
            addr: SocketAddr::from(([127, 0, 0, 1], 8080)),
            body_limit_bytes: 1 << 20,
            upload_limit_bytes: 50 << 30,
            upload_dir: data_dir.join("uploads"),
            run_worker_in_process: true,
            worker_id: worker::worker_identity("serve"),
            worker_lease_ms: 30_000,
            token_cache_ttl: Duration::from_secs(5),
            shutdown_deadline: Duration::from_secs(10),
            public_url: None,
            max_in_flight_per_token: 64,
            max_token_checks_in_flight: 16,
            rate_limit_per_token: 1000,
            unverified_checks_per_peer: 100,
            header_read_timeout: Duration::from_secs(30),
            body_idle_timeout: Duration::from_secs(30),
            write_stall_timeout: Duration::from_secs(60),
            max_connections: 4096,
            trusted_proxies: Vec::new(),
            idempotency_ttl: Duration::from_secs(24 * 3600),
            idempotency_lease: Duration::from_secs(30),
            event_retention: Some(Duration::from_secs(30 * 24 * 3600)),
            deliver_webhooks: true,
            webhook_backoff: Duration::from_secs(1),
            webhook_poll: Duration::from_secs(1),
            run_automations: true,
        }
    }
}

/// Shared state of the handlers; cheap to clone.
#[derive(Clone)]
pub struct AppState {
    pub(crate) inner: Arc<Inner>,
}

pub(crate) struct Inner {
    pub store: Store,
    pub cfg: ServeConfig,
    pub metrics: metrics::Metrics,
    pub tokens: auth::TokenCache,
    /// Signed-in sessions of the labeling page (`session.rs`).
    pub sessions: session::Sessions,
    /// SQLite has one writer: queueing label writes here, instead of letting pool connections
    /// spin on the database lock (SQLite's busy handler sleeps in steps of up to 100 ms),
    /// keeps write latency flat under contention. `None` on Postgres (row-level locking).
    pub write_gate: Option<tokio::sync::Mutex<()>>,
    /// Group commit of label PUTs on SQLite (`label_writer.rs`).
    pub label_writer: label_writer::LabelWriter,
    /// `cfg.public_url` reduced to its origin.
    pub public_origin: Option<String>,
    /// Per token id: permits for its requests in flight (`cfg.max_in_flight_per_token`).
    pub in_flight: std::sync::Mutex<std::collections::HashMap<String, Arc<tokio::sync::Semaphore>>>,
    /// Permits for catalog lookups of uncached tokens (`cfg.max_token_checks_in_flight`).
    pub token_checks: tokio::sync::Semaphore,
    /// Per token id: `cfg.rate_limit_per_token` (None when 0).
    pub token_rate: Option<auth::KeyedLimiter<String>>,
    /// Per peer address: `cfg.unverified_checks_per_peer` (None when 0).
    pub unverified_checks: Option<auth::KeyedLimiter<std::net::IpAddr>>,
}

impl AppState {
    pub fn new(store: Store, cfg: ServeConfig) -> Self {
        let write_gate = (store.backend() == Backend::Sqlite).then(|| tokio::sync::Mutex::new(()));
        let tokens = auth::TokenCache::new(cfg.token_cache_ttl);
        // `serve` checked the URL already; an invalid one here (embedding) is treated as absent.
        let public_origin = cfg.public_url.as_deref().and_then(|u| public_origin(u).ok());
        let token_checks = tokio::sync::Semaphore::new(cfg.max_token_checks_in_flight.max(1));
        let token_rate = auth::keyed_limiter(cfg.rate_limit_per_token, 2);
        let unverified_checks = auth::keyed_limiter(cfg.unverified_checks_per_peer, 10);
        AppState {
            inner: Arc::new(Inner {
                store,
                cfg,
                metrics: Default::default(),
                tokens,
                sessions: Default::default(),
                write_gate,
                label_writer: Default::default(),
                public_origin,
                in_flight: Default::default(),
                token_checks,
                token_rate,
                unverified_checks,
            }),
        }
    }
    pub fn store(&self) -> &Store {
        &self.inner.store
    }
    /// The public origin (`--public-url`), if the server runs behind a proxy.
    pub(crate) fn public_origin(&self) -> Option<&str> {
        self.inner.public_origin.as_deref()
    }
    /// Session cookies are `Secure` when browsers reach us over https.
    pub(crate) fn secure_cookies(&self) -> bool {
        self.public_origin().is_some_and(|o| o.starts_with("https://"))
    }
    pub(crate) async fn write_gate(&self) -> Option<tokio::sync::MutexGuard<'_, ()>> {
        match &self.inner.write_gate {
            Some(m) => Some(m.lock().await),
            None => None,
        }
    }
}

/// The whole HTTP surface: `/healthz` (open), and behind a bearer token `/metrics`,
/// `/openapi.json` and `/v1/...` (one router per resource, `routes/`); the labeling page (`/`,
/// `/ui/...`, open static assets from the `web` crate) and its sign-in `/ui/session` (cookie
/// sessions, `session.rs`).
pub fn router(state: AppState) -> Router {
    use routes as r;
    let body_limit = state.inner.cfg.body_limit_bytes;
    let body_idle = state.inner.cfg.body_idle_timeout;
    let authed = r::authed_routes()
        .route("/openapi.json", get(openapi::serve_openapi))
        .route(
            "/v1/ingest",
            post(upload::ingest.layer(from_fn_with_state(Role::Admin, auth::require_role)))
                .layer(DefaultBodyLimit::disable()),
        )
        .route_layer(from_fn_with_state(state.clone(), idempotency::guard))
        .route_layer(from_fn_with_state(state.clone(), auth::require_token));
    Router::new()
        .route("/healthz", get(r::healthz))
        .merge(authed)
        .merge(session_routes::routes(state.clone()))
        .merge(web::router::<AppState>())
        .fallback(r::not_found)
        .layer(DefaultBodyLimit::max(body_limit))
        .layer(tower_http::timeout::RequestBodyTimeoutLayer::new(body_idle))
        .layer(from_fn_with_state(state.clone(), metrics::track))
        .with_state(state)
}

/// A server running in the background (for tests and embedding): its bound address and a way
/// to stop it.
pub struct RunningServer {
    pub addr: SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<anyhow::Result<()>>,
}

impl RunningServer {
    /// Stops accepting, finishes requests in flight, stops the in-process worker.
    pub async fn shutdown(mut self) -> anyhow::Result<()> {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        self.task.await?
    }
}

/// Binds `cfg.addr` (port 0 picks a free one) and serves in a background task.
pub async fn spawn(
    store: Store,
    cfg: ServeConfig,
    runner: Arc<dyn JobRunner>,
) -> anyhow::Result<RunningServer> {
    let listener = tokio::net::TcpListener::bind(cfg.addr)
        .await
        .map_err(|e| anyhow::anyhow!("cannot listen on {}: {e}", cfg.addr))?;
    let addr = listener.local_addr()?;
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let task = tokio::spawn(serve_on(listener, store, cfg, runner, async move {
        let _ = rx.await;
    }));
    Ok(RunningServer { addr, stop: Some(tx), task })
}

/// `ufops serve`: binds `cfg.addr`, prints `listening on http://ADDR`, serves until `shutdown`
/// resolves (then finishes requests in flight and stops the in-process worker).
pub async fn serve(
    store: Store,
    cfg: ServeConfig,
    runner: Arc<dyn JobRunner>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    if let Some(u) = &cfg.public_url {
        public_origin(u).map_err(|e| anyhow::anyhow!(e))?;
    }
    let listener = tokio::net::TcpListener::bind(cfg.addr)
        .await
        .map_err(|e| anyhow::anyhow!("cannot listen on {}: {e}", cfg.addr))?;
    println!("listening on http://{}", listener.local_addr()?);
    serve_on(listener, store, cfg, runner, shutdown).await
}

/// Serves on an already bound listener.
pub async fn serve_on(
    listener: tokio::net::TcpListener,
    store: Store,
    cfg: ServeConfig,
    runner: Arc<dyn JobRunner>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(&cfg.upload_dir)
        .map_err(|e| anyhow::anyhow!("cannot create the upload dir {}: {e}", cfg.upload_dir.display()))?;
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    // Uploads nobody will ingest (their job ended, or none was queued): at start, then hourly.
    let sweeper = {
        let (store, dir) = (store.clone(), cfg.upload_dir.clone());
        tokio::spawn(async move {
            loop {
                match upload::sweep(&store, &dir, Duration::from_secs(3600)).await {
                    Ok(0) => {}
                    Ok(n) => tracing::info!("deleted {n} stale uploads"),
                    Err(e) => tracing::warn!("cannot sweep the uploads: {e}"),
                }
                tokio::time::sleep(Duration::from_secs(3600)).await;
            }
        })
    };
    // Feed retention and expired idempotency keys: at start, then hourly.
    let pruner = {
        let (store, retention) = (store.clone(), cfg.event_retention);
        tokio::spawn(async move {
            loop {
                if let Some(r) = retention {
                    match store.prune_events(r).await {
                        Ok(0) => {}
                        Ok(n) => tracing::info!("deleted {n} events past the feed's retention"),
                        Err(e) => tracing::warn!("cannot prune the change feed: {e}"),
                    }
                }
                if let Err(e) = store.prune_idempotency_keys().await {
                    tracing::warn!("cannot prune idempotency keys: {e}");
                }
                tokio::time::sleep(Duration::from_secs(3600)).await;
            }
        })
    };
    let stop_tx = Arc::new(stop_tx);
    let stop_tx2 = stop_tx.clone();
    let worker = cfg.run_worker_in_process.then(|| {
        let mut rx = stop_rx.clone();
        tokio::spawn(run_worker(
            store.clone(),
            runner,
            cfg.worker_id.clone(),
            cfg.worker_lease_ms,
            async move {
                let _ = rx.wait_for(|s| *s).await;
            },
        ))
    });
    let deliveries = cfg.deliver_webhooks.then(|| {
        let consumers = webhooks::Deliveries::new(format!("{}-webhooks", cfg.worker_id), cfg.webhook_backoff);
        tokio::spawn(feed_consumers::run(store.clone(), cfg.webhook_poll, stop_rx.clone(), consumers))
    });
    let automations = cfg.run_automations.then(|| {
        let consumers = automations::Automations { owner: format!("{}-automations", cfg.worker_id) };
        tokio::spawn(feed_consumers::run(store.clone(), cfg.webhook_poll, stop_rx.clone(), consumers))
    });
    let deadline = cfg.shutdown_deadline;
    let limits = conn::ConnLimits {
        header_read_timeout: cfg.header_read_timeout,
        write_stall_timeout: cfg.write_stall_timeout,
        max_connections: cfg.max_connections,
        trusted_proxies: cfg.trusted_proxies.clone().into(),
    };
    let app = router(AppState::new(store, cfg));
    let server = conn::serve_connections(listener, app, limits, async move {
        shutdown.await;
        let _ = stop_tx2.send(true);
    });
    let mut stopping = stop_rx.clone();
    tokio::select! {
        _ = server => {}
        _ = async move {
            let _ = stopping.wait_for(|s| *s).await;
            tokio::time::sleep(deadline).await;
        } => {
            tracing::warn!("requests still in flight {deadline:?} after the shutdown signal: closing them");
        }
    };
    let _ = stop_tx.send(true);
    sweeper.abort();
    pruner.abort();
    if let Some(w) = worker {
        let _ = w.await;
    }
    if let Some(d) = deliveries {
        let _ = d.await;
    }
    if let Some(a) = automations {
        let _ = a.await;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::public_origin;

    #[test]
    fn public_urls_reduce_to_an_origin() {
        assert_eq!(public_origin("https://Label.Example.com/").unwrap(), "https://label.example.com");
        assert_eq!(public_origin("http://10.0.0.5:8443").unwrap(), "http://10.0.0.5:8443");
        for bad in
            ["label.example.com", "ftp://x", "https://x/ui", "https://user@x", "https://", "https://x?a=1"]
        {
            assert!(public_origin(bad).is_err(), "{bad}");
        }
    }
}
