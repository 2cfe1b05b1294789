//! The label load test (shared by `benches/label_load.rs` and a short test): N concurrent
//! labelers, each with its own token, update overlapping episodes over HTTP with If-Match; on a
//! 409 they take the current revision from the problem document and retry. Afterwards the audit
//! log is replayed and must reproduce every episode's final label and revision, and contain
//! exactly the writes the clients were told succeeded.

use super::{Db, TestServer};
use serde_json::{json, Value};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use store::{EpisodeFilter, Label, Role};

#[derive(Debug)]
pub struct LoadReport {
    pub db: Db,
    pub labelers: usize,
    pub episodes: usize,
    pub seconds: f64,
    pub writes: u64,
    pub conflicts: u64,
    pub errors: u64,
    pub p50_ms: f64,
    pub p99_ms: f64,
    pub max_ms: f64,
    pub events_replayed: usize,
    /// `label.set` events a follower of `GET /v1/events?wait=` received during and after the load.
    pub feed_events: usize,
}

impl LoadReport {
    pub fn writes_per_s(&self) -> f64 {
        self.writes as f64 / self.seconds
    }
    pub fn print(&self) {
        println!(
            "label load on {:?}: {} labelers x {} episodes for {:.1} s: {} writes ({:.0}/s), {} conflicts (409, retried), \
             {} errors; PUT latency p50 {:.2} ms, p99 {:.2} ms, max {:.1} ms; audit log replayed ({} events): no lost updates; \
             feed followed ({} label.set events): every acknowledged write once, in commit order",
            self.db, self.labelers, self.episodes, self.seconds, self.writes, self.writes_per_s(), self.conflicts,
            self.errors, self.p50_ms, self.p99_ms, self.max_ms, self.events_replayed, self.feed_events
        );
    }
}

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
}

/// Where the server under load runs.
pub enum ServerAt {
    /// In this process (the test): client and server share the runtime and the cores' scheduler.
    InProcess,
    /// In a child process started as `EXE --serve-child DATA_DIR [DATABASE_URL]` (the benchmark
    /// re-runs itself, see `benches/label_load.rs`), so client and server are measured apart.
    Child(std::path::PathBuf),
}

/// A server of the load test: in this process or a child (killed on drop).
struct LoadServer {
    base: String,
    store: store::Store,
    in_process: Option<TestServer>,
    child: Option<std::process::Child>,
    _dir: Option<tempfile::TempDir>,
}

impl LoadServer {
    async fn start(db: Db, at: &ServerAt) -> LoadServer {
        match at {
            ServerAt::InProcess => {
                let srv = TestServer::start(db, false).await;
                LoadServer {
                    base: srv.base.clone(),
                    store: srv.store.clone(),
                    in_process: Some(srv),
                    child: None,
                    _dir: None,
                }
            }
            ServerAt::Child(exe) => {
                use std::io::BufRead;
                let dir = tempfile::tempdir().unwrap();
                let url = match db {
                    Db::Sqlite => None,
                    Db::Postgres => {
                        Some(store::create_test_schema("load").await.expect("the Postgres server"))
                    }
                };
                let cfg = store::StoreConfig {
                    data_dir: dir.path().into(),
                    database_url: url.clone(),
                    object_store_url: None,
                };
                let store = store::Store::open(&cfg).await.unwrap();
                let mut cmd = std::process::Command::new(exe);
                cmd.arg("--serve-child").arg(dir.path());
                if let Some(u) = &url {
                    cmd.arg(u);
                }
                let mut child =
                    cmd.stdout(std::process::Stdio::piped()).spawn().expect("start the server process");
                let mut line = String::new();
                std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
                let base = line
                    .trim()
                    .strip_prefix("listening on ")
                    .unwrap_or_else(|| panic!("server said {line:?}"))
                    .to_string();
                LoadServer { base, store, in_process: None, child: Some(child), _dir: Some(dir) }
            }
        }
    }

    async fn stop(mut self) {
        if let Some(srv) = self.in_process.take() {
            srv.stop().await;
        }
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

pub async fn run_label_load(db: Db, labelers: usize, n_episodes: usize, duration: Duration) -> LoadReport {
    run_label_load_at(db, &ServerAt::InProcess, labelers, n_episodes, duration, true).await
}

pub async fn run_label_load_at(
    db: Db,
    at: &ServerAt,
    labelers: usize,
    n_episodes: usize,
    duration: Duration,
    follow_feed: bool,
) -> LoadReport {
    let srv = LoadServer::start(db, at).await;
    // Episodes: several ingests so the pool has enough of them.
    let mut ids = Vec::new();
    let mut k = 0;
    while ids.len() < n_episodes {
        let n = (n_episodes - ids.len()).min(200) as u32;
        ids.extend(super::ingest(&srv.store, &format!("load-{k}"), "c1", n).await);
        k += 1;
    }
    let ids = Arc::new(ids);
    let mut secrets = Vec::new();
    for i in 0..labelers {
        secrets.push(srv.store.create_token(&format!("labeler-{i:02}"), Role::Labeler).await.unwrap().0);
    }
    let http = reqwest::Client::builder().pool_max_idle_per_host(labelers * 2).build().unwrap();
    let base = srv.base.clone();
    // A follower of the change feed, long-polling the API while the labelers write, from the
    // feed's head before the first write (without `follow_feed`, it reads the feed at the end).
    let (feed_start, _) = srv.store.event_head().await.unwrap();
    let (feed_stop_tx, feed_stop) = tokio::sync::watch::channel(None::<i64>);
    let follower = {
        let (http, base) = (http.clone(), base.clone());
        let viewer = srv.store.create_token("feed-follower", Role::Viewer).await.unwrap().0;
        tokio::spawn(async move {
            let mut after = feed_start;
            let mut got: Vec<Value> = Vec::new();
            let mut feed_stop = feed_stop;
            if !follow_feed {
                let _ = feed_stop.wait_for(|h| h.is_some()).await;
            }
            loop {
                // Stop once the load is over and the follower reached the head it was told.
                if let Some(head) = *feed_stop.borrow() {
                    if after >= head {
                        return got;
                    }
                }
                let url = format!("{base}/v1/events?after={after}&kind=label.set&wait=2");
                let page: Value =
                    http.get(url).bearer_auth(&viewer).send().await.unwrap().json().await.unwrap();
                got.extend(page["events"].as_array().unwrap().iter().cloned());
                after = page["next"].as_i64().unwrap();
            }
        })
    };
    let deadline = Instant::now() + duration;
    let t0 = Instant::now();
    let mut tasks = Vec::new();
    for (i, secret) in secrets.into_iter().enumerate() {
        let http = http.clone();
        let base = base.clone();
        let ids = ids.clone();
        tasks.push(tokio::spawn(async move {
            let mut rng = Rng(0x9E3779B97F4A7C15 ^ (i as u64 + 1).wrapping_mul(0x2545F4914F6CDD1D));
            let mut known: HashMap<usize, i64> = HashMap::new();
            let mut lat = Vec::new();
            let mut acked: Vec<(String, i64, Label)> = Vec::new();
            let (mut conflicts, mut errors) = (0u64, 0u64);
            // A labeler picks an episode and a label, and keeps at it (re-reading the revision
            // from each 409) until its write lands.
            let mut pending: Option<(usize, Label)> = None;
            while Instant::now() < deadline {
                let (e, label) = match pending {
                    Some(p) => p,
                    None => (
                        (rng.next() % ids.len() as u64) as usize,
                        [Label::Success, Label::Failure, Label::Unknown][(rng.next() % 3) as usize],
                    ),
                };
                pending = Some((e, label));
                let id = &ids[e];
                let rev = match known.get(&e) {
                    Some(r) => *r,
                    None => {
                        let r =
                            http.get(format!("{base}/v1/episodes/{id}")).bearer_auth(&secret).send().await;
                        match r {
                            Ok(r) if r.status() == 200 => {
                                let v: Value = r.json().await.unwrap();
                                v["episode"]["label_revision"].as_i64().unwrap()
                            }
                            _ => {
                                errors += 1;
                                continue;
                            }
                        }
                    }
                };
                let t = Instant::now();
                let r = http
                    .put(format!("{base}/v1/episodes/{id}/label"))
                    .bearer_auth(&secret)
                    .header("If-Match", format!("\"{rev}\""))
                    .json(&json!({"label": label, "note": format!("labeler {i}")}))
                    .send()
                    .await;
                let status = r.as_ref().map(|r| r.status().as_u16()).unwrap_or(0);
                let body: Value = match r {
                    Ok(r) => r.json().await.unwrap_or(Value::Null),
                    Err(_) => Value::Null,
                };
                lat.push(t.elapsed().as_micros() as u32);
                match status {
                    200 => {
                        let new_rev = body["revision"].as_i64().unwrap();
                        known.insert(e, new_rev);
                        acked.push((id.clone(), new_rev, label));
                        pending = None;
                    }
                    409 => {
                        conflicts += 1;
                        match body["current_revision"].as_i64() {
                            Some(cur) => {
                                known.insert(e, cur);
                            }
                            None => {
                                known.remove(&e);
                            }
                        }
                    }
                    _ => {
                        errors += 1;
                        known.remove(&e);
                    }
                }
            }
            (lat, acked, conflicts, errors)
        }));
    }
    let mut lat = Vec::new();
    let mut acked = Vec::new();
    let (mut conflicts, mut errors) = (0, 0);
    for t in tasks {
        let (l, a, c, e) = t.await.unwrap();
        lat.extend(l);
        acked.extend(a);
        conflicts += c;
        errors += e;
    }
    let seconds = t0.elapsed().as_secs_f64();
    let (feed_head, _) = srv.store.event_head().await.unwrap();
    feed_stop_tx.send(Some(feed_head)).unwrap();
    let feed = follower.await.unwrap();
    lat.sort_unstable();
    let pct = |p: f64| {
        if lat.is_empty() {
            0.0
        } else {
            lat[((lat.len() as f64 * p) as usize).min(lat.len() - 1)] as f64 / 1000.0
        }
    };

    // Replay the audit log.
    let mut events = Vec::new();
    let mut after = 0;
    loop {
        let page = srv.store.label_events_since(after, 10_000).await.unwrap();
        if page.is_empty() {
            break;
        }
        after = page.last().unwrap().0;
        events.extend(page.into_iter().map(|(_, e)| e));
    }
    let mut replay: HashMap<String, (i64, Label)> = HashMap::new();
    for ev in &events {
        let entry = replay.get(&ev.episode_id).copied();
        match entry {
            None => assert_eq!(ev.revision, 1, "first event of {} is not revision 1", ev.episode_id),
            Some((rev, label)) => {
                assert_eq!(ev.revision, rev + 1, "revision gap on {}", ev.episode_id);
                assert_eq!(
                    ev.old_label,
                    Some(label),
                    "event {} of {} does not start from the previous label",
                    ev.revision,
                    ev.episode_id
                );
            }
        }
        replay.insert(ev.episode_id.clone(), (ev.revision, ev.new_label));
    }
    let eps = srv.store.episodes(&EpisodeFilter::default()).await.unwrap();
    assert_eq!(eps.len(), ids.len());
    for e in &eps {
        assert_eq!(
            replay.get(&e.id),
            Some(&(e.label_revision, e.label)),
            "replay of {} disagrees with the catalog",
            e.id
        );
    }
    let human: Vec<_> = events.iter().filter(|e| e.actor.starts_with("labeler-")).collect();
    assert_eq!(human.len(), acked.len(), "audit events by labelers != writes acknowledged to clients");
    let by_key: HashMap<(&str, i64), Label> =
        human.iter().map(|e| ((e.episode_id.as_str(), e.revision), e.new_label)).collect();
    for (id, rev, label) in &acked {
        assert_eq!(
            by_key.get(&(id.as_str(), *rev)),
            Some(label),
            "acknowledged write {id}@{rev} missing from the log"
        );
    }
    // The feed: dense sequence numbers, each acknowledged write exactly once, and per episode
    // the revisions in the order they committed.
    let mut last_rev: HashMap<String, i64> = HashMap::new();
    let mut in_feed: HashMap<(String, i64), Label> = HashMap::new();
    for (i, e) in feed.iter().enumerate() {
        if i > 0 {
            assert!(e["seq"].as_i64() > feed[i - 1]["seq"].as_i64(), "feed out of order at {e}");
        }
        let id = e["subject"].as_str().unwrap().to_string();
        let rev = e["data"]["revision"].as_i64().unwrap();
        if let Some(prev) = last_rev.insert(id.clone(), rev) {
            assert_eq!(rev, prev + 1, "feed skips or reorders revisions of {id}: {prev} then {rev}");
        }
        let label: Label = e["data"]["label"].as_str().unwrap().parse().unwrap();
        assert!(in_feed.insert((id, rev), label).is_none(), "an event twice in the feed: {e}");
    }
    assert_eq!(feed.len(), events.iter().filter(|e| e.actor.starts_with("labeler-")).count());
    for (id, rev, label) in &acked {
        assert_eq!(
            in_feed.get(&(id.clone(), *rev)),
            Some(label),
            "acknowledged write {id}@{rev} not in the feed"
        );
    }
    let report = LoadReport {
        db,
        labelers,
        episodes: ids.len(),
        seconds,
        writes: acked.len() as u64,
        conflicts,
        errors,
        p50_ms: pct(0.50),
        p99_ms: pct(0.99),
        max_ms: lat.last().map(|x| *x as f64 / 1000.0).unwrap_or(0.0),
        events_replayed: events.len(),
        feed_events: feed.len(),
    };
    srv.stop().await;
    report
}
