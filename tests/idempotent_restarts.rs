//! Idempotency keys hold across crashes: 10,000 mutating requests (tokens and training jobs),
//! each sent one to three times with the same `Idempotency-Key` and retried on every failure,
//! while the `ufops serve` process is killed (SIGKILL, mid-request) and restarted at random
//! moments. Every request creates exactly one row (counted in the catalog afterwards), and every
//! answer a request got names the same row.

use crate::common;
use common::*;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};
use store_jobs::JobQueue;

/// A small seeded generator (splitmix64): the test needs no statistics, only variety.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// What the requests got back: per request, the ids of its 2xx answers, and how many said its
/// response was lost in a crash.
#[derive(Default)]
struct Outcomes {
    ids: Vec<Vec<String>>,
    lost: usize,
    retries: usize,
}

fn retried_requests_create_one_resource_each(t: Target, requests: usize) {
    t.ok(&["init"]);
    t.ok(&["dev", "synth", "--episodes", "12", "--steps", "10", "--seed", "5"]);
    let split = t.json(&["split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--json"]);
    let split_id = split["id"].as_str().unwrap().to_string();
    let auth = t.bearer("ops", "admin");
    let serve = || t.serve(&["--no-worker", "--idempotency-lease-secs", "1", "--rate-limit-per-token", "0"]);
    let server = Arc::new(Mutex::new(Some(serve())));
    let url = Arc::new(RwLock::new(server.lock().unwrap().as_ref().unwrap().url.clone()));
    let done = Arc::new(AtomicBool::new(false));
    let restarts = Arc::new(AtomicUsize::new(0));
    let t0 = Instant::now();
    std::thread::scope(|scope| {
        // The crashes: SIGKILL at a random moment, then a new process (on a new port).
        {
            let (server, url, done, restarts) = (server.clone(), url.clone(), done.clone(), restarts.clone());
            let serve = &serve;
            scope.spawn(move || {
                let mut rng = Rng(7);
                while !done.load(Ordering::Relaxed) {
                    std::thread::sleep(Duration::from_millis(300 + rng.below(1200)));
                    if done.load(Ordering::Relaxed) {
                        break;
                    }
                    drop(server.lock().unwrap().take()); // kills it (SIGKILL) and reaps it
                    let next = serve();
                    *url.write().unwrap() = next.url.clone();
                    *server.lock().unwrap() = Some(next);
                    restarts.fetch_add(1, Ordering::Relaxed);
                }
            });
        }
        const CLIENTS: usize = 16;
        let outcomes: Vec<Outcomes> = std::thread::scope(|clients| {
            let handles: Vec<_> = (0..CLIENTS)
                .map(|c| {
                    let (url, auth, split_id) = (url.clone(), auth.clone(), split_id.clone());
                    clients.spawn(move || {
                        let mut rng = Rng(1000 + c as u64);
                        let mut out = Outcomes::default();
                        for i in (c..requests).step_by(CLIENTS) {
                            let key = format!("req-{i}");
                            let (path, body) = if i % 2 == 0 {
                                ("/v1/tokens", serde_json::json!({"name": format!("idem-{i}"), "role": "viewer"}))
                            } else {
                                (
                                    "/v1/jobs",
                                    serde_json::json!({"split_id": split_id, "kind": "classifier", "chunk_len": 4,
                                        "config": {"request": i}}),
                                )
                            };
                            let mut ids = Vec::new();
                            // Sent once, twice or three times, each send retried until it is answered.
                            for _ in 0..1 + rng.below(3) {
                                loop {
                                    let base = url.read().unwrap().clone();
                                    let headers = [("Authorization", auth.as_str()), ("Idempotency-Key", key.as_str())];
                                    let r = http(&base, "POST", path, &headers, Some(&body));
                                    let problem = || -> String {
                                        serde_json::from_slice::<serde_json::Value>(&r.body)
                                            .ok()
                                            .and_then(|v| v["type"].as_str().map(str::to_string))
                                            .unwrap_or_default()
                                    };
                                    match r.status {
                                        201 => {
                                            let v = r.json();
                                            let id = if i % 2 == 0 { &v["record"]["id"] } else { &v["id"] };
                                            ids.push(id.as_str().unwrap().to_string());
                                            break;
                                        }
                                        409 if problem().ends_with("idempotent-response-lost") => {
                                            out.lost += 1;
                                            break;
                                        }
                                        // The server is gone (0), restarting, or still serving this key.
                                        0 | 409 | 503 => {
                                            out.retries += 1;
                                            std::thread::sleep(Duration::from_millis(20 + rng.below(80)));
                                        }
                                        s => panic!("request {i}: unexpected {s}: {}", String::from_utf8_lossy(&r.body)),
                                    }
                                }
                            }
                            out.ids.push(ids);
                        }
                        out
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        done.store(true, Ordering::Relaxed);
        let (mut lost, mut retries) = (0, 0);
        for (c, o) in outcomes.iter().enumerate() {
            lost += o.lost;
            retries += o.retries;
            for (k, ids) in o.ids.iter().enumerate() {
                let i = c + k * CLIENTS;
                assert!(ids.windows(2).all(|w| w[0] == w[1]), "request {i} got different answers: {ids:?}");
            }
        }
        eprintln!(
            "{requests} requests in {:.1} s: {} server kills, {retries} retried sends, {lost} answers lost in a crash",
            t0.elapsed().as_secs_f64(),
            restarts.load(Ordering::Relaxed),
        );
        assert!(restarts.load(Ordering::Relaxed) >= 3, "the server was hardly restarted");
    });
    drop(server.lock().unwrap().take());

    // Count rows: one token per even request, one job per odd one.
    let rt = tokio::runtime::Runtime::new().unwrap();
    let store = rt
        .block_on(store::Store::open(&store::StoreConfig {
            data_dir: t.data_dir.clone(),
            database_url: t.database_url.clone(),
            object_store_url: None,
        }))
        .unwrap();
    let mut per_request = vec![0usize; requests];
    for tok in rt.block_on(store.tokens()).unwrap() {
        if let Some(i) = tok.name.strip_prefix("idem-") {
            per_request[i.parse::<usize>().unwrap()] += 1;
        }
    }
    for job in rt.block_on(store.jobs(None)).unwrap() {
        if let Some(i) = job.spec["config"]["request"].as_u64() {
            per_request[i as usize] += 1;
        }
    }
    let wrong: Vec<(usize, usize)> =
        per_request.iter().copied().enumerate().filter(|(_, n)| *n != 1).collect();
    assert!(wrong.is_empty(), "requests that did not create exactly one row (request, rows): {wrong:?}");
}

#[test]
fn ten_thousand_retried_requests_through_crashes_sqlite() {
    let dir = tempfile::tempdir().unwrap();
    retried_requests_create_one_resource_each(Target::sqlite(dir.path()), 10_000);
}

#[test]
fn ten_thousand_retried_requests_through_crashes_postgres() {
    let dir = tempfile::tempdir().unwrap();
    let Some(t) = postgres_target(dir.path()) else { return };
    retried_requests_create_one_resource_each(t, 10_000);
}
