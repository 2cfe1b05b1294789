//! Prometheus text metrics, hand-rolled: request counts by route and status, request latency
//! sums, label writes, and (read at scrape time) jobs by state and the object store's reads.

use crate::AppState;
use axum::extract::{MatchedPath, Request, State};
use axum::http::Method;
use axum::middleware::Next;
use axum::response::Response;
use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// A request class: (method, route, status); the metrics keep (count, total seconds) per class.
type RequestKey = (String, String, u16);

#[derive(Default)]
pub(crate) struct Metrics {
    requests: Mutex<BTreeMap<RequestKey, (u64, f64)>>,
    pub label_writes: AtomicU64,
    pub label_conflicts: AtomicU64,
    pub uploads_bytes: AtomicU64,
}

impl Metrics {
    pub fn render(&self, jobs: &BTreeMap<String, u64>, objects: store::FetchCounts) -> String {
        let mut out = String::new();
        out.push_str("# HELP ufops_object_store_requests_total Read requests made to the object store.\n");
        out.push_str("# TYPE ufops_object_store_requests_total counter\n");
        let _ = writeln!(out, "ufops_object_store_requests_total{{method=\"GET\"}} {}", objects.get_requests);
        let _ =
            writeln!(out, "ufops_object_store_requests_total{{method=\"HEAD\"}} {}", objects.head_requests);
        out.push_str("# HELP ufops_object_store_fetched_bytes_total Bytes returned by object store reads.\n");
        out.push_str("# TYPE ufops_object_store_fetched_bytes_total counter\n");
        let _ = writeln!(out, "ufops_object_store_fetched_bytes_total {}", objects.bytes_fetched);
        out.push_str("# HELP ufops_http_requests_total HTTP requests by method, route and status.\n");
        out.push_str("# TYPE ufops_http_requests_total counter\n");
        let reqs = self.requests.lock().expect("metrics lock").clone();
        for ((m, r, s), (n, _)) in &reqs {
            let _ =
                writeln!(out, "ufops_http_requests_total{{method=\"{m}\",route=\"{r}\",status=\"{s}\"}} {n}");
        }
        out.push_str("# HELP ufops_http_request_seconds_sum Total time spent serving requests.\n");
        out.push_str("# TYPE ufops_http_request_seconds_sum counter\n");
        for ((m, r, s), (_, t)) in &reqs {
            let _ = writeln!(
                out,
                "ufops_http_request_seconds_sum{{method=\"{m}\",route=\"{r}\",status=\"{s}\"}} {t:.6}"
            );
        }
        out.push_str("# HELP ufops_label_writes_total Label changes committed through the API.\n");
        out.push_str("# TYPE ufops_label_writes_total counter\n");
        let _ = writeln!(out, "ufops_label_writes_total {}", self.label_writes.load(Ordering::Relaxed));
        out.push_str("# HELP ufops_label_conflicts_total Label writes refused for a stale revision.\n");
        out.push_str("# TYPE ufops_label_conflicts_total counter\n");
        let _ = writeln!(out, "ufops_label_conflicts_total {}", self.label_conflicts.load(Ordering::Relaxed));
        out.push_str("# HELP ufops_upload_bytes_total Bytes received by the ingest upload endpoint.\n");
        out.push_str("# TYPE ufops_upload_bytes_total counter\n");
        let _ = writeln!(out, "ufops_upload_bytes_total {}", self.uploads_bytes.load(Ordering::Relaxed));
        out.push_str("# HELP ufops_jobs Jobs in the catalog by state.\n");
        out.push_str("# TYPE ufops_jobs gauge\n");
        for (state, n) in jobs {
            let _ = writeln!(out, "ufops_jobs{{state=\"{state}\"}} {n}");
        }
        out
    }
}

/// Middleware counting every request by its route template (never the raw path) and method.
pub(crate) async fn track(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|m| m.as_str().to_string())
        .unwrap_or_else(|| "unmatched".to_string());
    // A fixed set of label values: a client inventing methods (or paths, see above) must not
    // grow the metrics without bound.
    let method = match *req.method() {
        Method::GET => "GET",
        Method::HEAD => "HEAD",
        Method::POST => "POST",
        Method::PUT => "PUT",
        Method::DELETE => "DELETE",
        Method::PATCH => "PATCH",
        Method::OPTIONS => "OPTIONS",
        _ => "other",
    }
    .to_string();
    let t0 = Instant::now();
    let resp = next.run(req).await;
    let dt = t0.elapsed().as_secs_f64();
    let key = (method, route, resp.status().as_u16());
    let mut m = state.inner.metrics.requests.lock().expect("metrics lock");
    let e = m.entry(key).or_insert((0, 0.0));
    e.0 += 1;
    e.1 += dt;
    resp
}
