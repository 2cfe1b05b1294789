//! A bounded soak of `ufops serve` (loopback, 30 s by default; `UFOPS_SOAK_SECONDS` for longer):
//! labelers writing with If-Match, readers listing episodes and reading steps and video ranges,
//! and a hostile client flooding bad tokens, oversized and malformed bodies and invented methods,
//! all at once. Valid requests never get a 5xx, hostile ones get their 4xx, the server's RSS is
//! stable (the last third's peak within 1.5x + 32 MB of the first third's), and nothing is lost:
//! the audit log replays to every episode's final label and holds every acknowledged write.

use crate::common;
use common::*;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

fn rss_kb(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0)
}

#[test]
fn serve_survives_a_mixed_and_hostile_load() {
    let seconds: u64 = std::env::var("UFOPS_SOAK_SECONDS").ok().and_then(|v| v.parse().ok()).unwrap_or(30);
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    let f = fixtures();
    t.ok(&[
        "ingest",
        f.join("lerobot/v30_eval_video").to_str().unwrap(),
        "--policy",
        "arm",
        "--checkpoint",
        "c1",
    ]);
    t.ok(&[
        "ingest",
        f.join("robomimic/lift_rollouts_lowdim.hdf5").to_str().unwrap(),
        "--policy",
        "bc",
        "--checkpoint",
        "e600",
    ]);
    let episodes: Vec<(String, bool)> = t
        .json(&["episodes", "--json"])
        .as_array()
        .unwrap()
        .iter()
        .map(|e| (e["id"].as_str().unwrap().to_string(), e["policy"] == "arm"))
        .collect();
    let labelers: Vec<String> = (0..4).map(|i| t.bearer(&format!("labeler-{i}"), "labeler")).collect();
    let viewer = t.bearer("reader", "viewer");
    let mut server = t.serve(&["--no-worker"]);
    let url = server.url.clone();
    let pid = server.child_mut().id();

    let stop = Arc::new(AtomicBool::new(false));
    let failures: Arc<Mutex<Vec<String>>> = Arc::default();
    let acked: Arc<Mutex<Vec<(String, i64, String)>>> = Arc::default();
    let counts: Arc<Mutex<HashMap<&'static str, u64>>> = Arc::default();
    let mut threads = Vec::new();
    for (i, auth) in labelers.into_iter().enumerate() {
        let (url, eps, stop, failures, acked, counts) =
            (url.clone(), episodes.clone(), stop.clone(), failures.clone(), acked.clone(), counts.clone());
        threads.push(std::thread::spawn(move || {
            let mut k = i * 7;
            while !stop.load(Ordering::Relaxed) {
                k = (k * 31 + 17) % eps.len();
                let id = &eps[k].0;
                let label = ["success", "failure", "unknown"][k % 3];
                let r = http(&url, "GET", &format!("/v1/episodes/{id}"), &[("Authorization", &auth)], None);
                if r.status != 200 {
                    failures.lock().unwrap().push(format!("GET episode: {}", r.status));
                    continue;
                }
                let rev = r.json()["episode"]["label_revision"].as_i64().unwrap();
                let r = http(
                    &url,
                    "PUT",
                    &format!("/v1/episodes/{id}/label"),
                    &[("Authorization", &auth), ("If-Match", &format!("\"{rev}\""))],
                    Some(&serde_json::json!({"label": label})),
                );
                match r.status {
                    200 => acked.lock().unwrap().push((
                        id.clone(),
                        r.json()["revision"].as_i64().unwrap(),
                        label.to_string(),
                    )),
                    409 => {}
                    s => failures
                        .lock()
                        .unwrap()
                        .push(format!("PUT label: {s} {}", String::from_utf8_lossy(&r.body))),
                }
                *counts.lock().unwrap().entry("label writes").or_default() += 1;
            }
        }));
    }
    for _ in 0..2 {
        let (url, eps, stop, failures, counts, auth) =
            (url.clone(), episodes.clone(), stop.clone(), failures.clone(), counts.clone(), viewer.clone());
        threads.push(std::thread::spawn(move || {
            let mut k = 3;
            while !stop.load(Ordering::Relaxed) {
                k = (k * 17 + 5) % eps.len();
                let (id, video) = &eps[k];
                let mut reqs = vec![
                    ("/v1/episodes?limit=50".to_string(), vec![200]),
                    (format!("/v1/episodes/{id}/steps"), vec![200]),
                ];
                if *video {
                    reqs.push((format!("/v1/episodes/{id}/media/images.front"), vec![206]));
                }
                for (path, ok) in reqs {
                    let r =
                        http(&url, "GET", &path, &[("Authorization", &auth), ("Range", "bytes=0-999")], None);
                    if !ok.contains(&r.status) {
                        failures.lock().unwrap().push(format!("GET {path}: {}", r.status));
                    }
                    *counts.lock().unwrap().entry("reads").or_default() += 1;
                }
            }
        }));
    }
    {
        let (url, stop, failures, counts, id) =
            (url.clone(), stop.clone(), failures.clone(), counts.clone(), episodes[0].0.clone());
        threads.push(std::thread::spawn(move || {
            let big = serde_json::json!({"updates": [], "pad": "x".repeat(2 << 20)});
            let mut n = 0u64;
            while !stop.load(Ordering::Relaxed) {
                n += 1;
                let bad = format!("Bearer ufops_{n:032x}");
                let cases: Vec<(HttpResponse, &[u16])> = vec![
                    (http(&url, "GET", "/v1/episodes", &[("Authorization", &bad)], None), &[401, 429]),
                    (http(&url, "GET", "/v1/episodes", &[], None), &[401]),
                    // refused before the body is read: 401/413, or the connection closed under the sender;
                    // 429 once this address has made too many checks of unknown tokens
                    (
                        http(&url, "POST", "/v1/labels/bulk", &[("Authorization", &bad)], Some(&big)),
                        &[0, 401, 413, 429],
                    ),
                    (
                        http_bytes(
                            &url,
                            "PUT",
                            &format!("/v1/episodes/{id}/label"),
                            &[("Authorization", &bad)],
                            b"{not json",
                            Some("application/json"),
                        ),
                        &[401, 400, 422, 429],
                    ),
                    (
                        http(
                            &url,
                            &format!("BREW{}", n % 50),
                            "/v1/episodes",
                            &[("Authorization", &bad)],
                            None,
                        ),
                        &[400, 401, 404, 405, 429],
                    ),
                    (
                        http(
                            &url,
                            "GET",
                            "/v1/episodes/..%2F..%2Fetc%2Fpasswd",
                            &[("Authorization", &bad)],
                            None,
                        ),
                        &[400, 401, 404, 429],
                    ),
                ];
                for (r, ok) in cases {
                    if !ok.contains(&r.status) {
                        failures.lock().unwrap().push(format!(
                            "hostile request answered {}: {}",
                            r.status,
                            String::from_utf8_lossy(&r.body)
                        ));
                    }
                    *counts.lock().unwrap().entry("hostile").or_default() += 1;
                }
            }
        }));
    }
    // RSS of the server, sampled through the run.
    let t0 = Instant::now();
    let mut samples: Vec<(f64, u64)> = Vec::new();
    while t0.elapsed() < Duration::from_secs(seconds) {
        std::thread::sleep(Duration::from_millis(250));
        samples.push((t0.elapsed().as_secs_f64(), rss_kb(pid)));
    }
    stop.store(true, Ordering::Relaxed);
    for th in threads {
        th.join().unwrap();
    }
    let third = seconds as f64 / 3.0;
    let peak = |from: f64, to: f64| {
        samples.iter().filter(|(t, _)| *t >= from && *t < to).map(|(_, r)| *r).max().unwrap_or(0)
    };
    let (first, last) = (peak(0.0, third), peak(2.0 * third, f64::MAX));
    let counts = counts.lock().unwrap().clone();
    eprintln!(
        "soak {seconds} s: {counts:?}; server RSS peak first third {} MB, last third {} MB",
        first / 1024,
        last / 1024
    );
    let failures = failures.lock().unwrap();
    assert!(
        failures.is_empty(),
        "{} unexpected answers, e.g. {:?}",
        failures.len(),
        &failures[..failures.len().min(5)]
    );
    assert!(counts["label writes"] > 50 && counts["reads"] > 50 && counts["hostile"] > 50, "{counts:?}");
    assert!(
        last <= first * 3 / 2 + 32 * 1024,
        "server RSS grew: {} MB in the first third, {} MB in the last",
        first / 1024,
        last / 1024
    );
    drop(server);

    // Nothing lost: the audit log replays to every episode's label and holds every acked write.
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let store = store::Store::open(&store::StoreConfig::local(dir.path())).await.unwrap();
        let mut last_rev: HashMap<String, (i64, store::Label)> = HashMap::new();
        let mut by_key: HashMap<(String, i64), store::Label> = HashMap::new();
        let mut after = 0;
        loop {
            let page = store.label_events_since(after, 10_000).await.unwrap();
            let Some((id, _)) = page.last() else { break };
            after = *id;
            for (_, ev) in page {
                if let Some((rev, label)) = last_rev.get(&ev.episode_id) {
                    assert_eq!((ev.revision, ev.old_label), (rev + 1, Some(*label)), "{}", ev.episode_id);
                }
                last_rev.insert(ev.episode_id.clone(), (ev.revision, ev.new_label));
                by_key.insert((ev.episode_id, ev.revision), ev.new_label);
            }
        }
        for e in store.episodes(&store::EpisodeFilter::default()).await.unwrap() {
            assert_eq!(last_rev.get(&e.id), Some(&(e.label_revision, e.label)), "{}", e.id);
        }
        for (id, rev, label) in acked.lock().unwrap().iter() {
            assert_eq!(
                by_key.get(&(id.clone(), *rev)).map(|l| l.as_str()),
                Some(label.as_str()),
                "acked write {id}@{rev} not in the log"
            );
        }
    });
}
