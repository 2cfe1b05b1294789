//! The change feed and idempotency keys over real HTTP, on SQLite and Postgres: every catalog
//! change of the loop (ingest, label, vote, snapshot, split, job states, publish, alias, export,
//! token) appears once, numbered in commit order; a long poll wakes on a commit; retention
//! answers 410 behind it. A retried request with an `Idempotency-Key` gets the first response
//! and does its work once; another body under the key is a 422; a key being served is a 409;
//! a request whose change committed before its server died is not done again.

use crate::common;
use store_feed::Webhooks;

use common::{Db, TestServer};
use futures::FutureExt;
use reqwest::Method;
use serde_json::{json, Value};
use std::time::{Duration, Instant};

async fn events(srv: &TestServer, query: &str) -> Value {
    srv.get_json(&format!("/v1/events?{query}"), "viewer").await
}

fn kinds(page: &Value) -> Vec<String> {
    page["events"].as_array().unwrap().iter().map(|e| e["kind"].as_str().unwrap().to_string()).collect()
}

async fn feed_follows_the_loop(db: Db) {
    let srv = TestServer::start(db, true).await;
    let start = events(&srv, "after=0").await;
    // The tokens the server was started with.
    assert_eq!(kinds(&start), vec!["token.changed"; 4], "{start}");
    let mut after = start["next"].as_i64().unwrap();

    let ids = common::ingest(&srv.store, "feed", "c1", 6).await;
    // Label over HTTP.
    let r = srv
        .req(Method::PUT, &format!("/v1/episodes/{}/label", ids[0]), "labeler")
        .header("If-Match", "\"1\"")
        .json(&json!({"label": "failure"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
    let r = srv
        .req(Method::POST, "/v1/label-snapshots", "labeler")
        .json(&json!({"message": "m"}))
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "{}", r.text().await.unwrap());
    let r = srv
        .req(Method::POST, "/v1/splits", "trainer")
        .json(&json!({"policy": "pol", "checkpoint": "c1", "val_fraction": 0.34}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let split: Value = r.json().await.unwrap();
    let r = srv
        .req(Method::POST, "/v1/jobs", "trainer")
        .json(&json!({"split_id": split["id"], "kind": "classifier", "chunk_len": 4}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let job: Value = r.json().await.unwrap();
    let done = srv.wait_job(job["id"].as_str().unwrap()).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    let artifact = done["result"]["artifact_id"].as_str().unwrap().to_string();
    let r = srv
        .req(Method::PUT, &format!("/v1/artifacts/{artifact}/aliases/prod"), "trainer")
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "{}", r.text().await.unwrap());

    let page = events(&srv, &format!("after={after}")).await;
    let got = kinds(&page);
    let expected = [
        "version.created",
        "ingest.committed",
        "label.set",
        "version.created",
        "split.frozen",
        "job.changed",
        "job.changed",
        "artifact.published",
        "alias.moved",
        "job.changed",
        "alias.moved",
    ];
    assert_eq!(got, expected, "{page:#}");
    let evs = page["events"].as_array().unwrap();
    // Numbered densely in commit order.
    for (i, e) in evs.iter().enumerate() {
        assert_eq!(e["seq"].as_i64().unwrap(), after + 1 + i as i64, "{e}");
    }
    assert_eq!(evs[1]["data"]["episodes"], 6);
    assert_eq!(evs[2]["subject"], ids[0].as_str());
    assert_eq!(evs[2]["data"]["revision"], 2);
    assert_eq!(evs[2]["data"]["label"], "failure");
    assert_eq!(evs[2]["data"]["actor"], "labeler-user");
    assert_eq!(evs[2]["checkpoint"], "c1");
    assert_eq!(evs[4]["subject"], split["id"]);
    let states: Vec<&str> = [5, 6, 9].iter().map(|&i| evs[i]["data"]["state"].as_str().unwrap()).collect();
    assert_eq!(states, ["queued", "running", "succeeded"]);
    assert_eq!(evs[7]["subject"], artifact.as_str());
    assert_eq!((evs[8]["subject"].as_str(), evs[10]["subject"].as_str()), (Some("latest"), Some("prod")));
    assert_eq!(page["next"], evs.last().unwrap()["seq"]);
    after = page["next"].as_i64().unwrap();

    // Filters: by kind and policy; a page of one continues where it stopped.
    let only = events(&srv, "after=0&kind=label.set,split.frozen&policy=pol").await;
    assert_eq!(kinds(&only), ["label.set", "split.frozen"]);
    let one = events(&srv, "after=0&kind=job.changed&limit=1").await;
    let two = events(&srv, &format!("after={}&kind=job.changed&limit=1", one["next"])).await;
    assert_eq!(two["events"][0]["data"]["state"], "running");
    for bad in ["after=-1", "limit=0", "kind=label.sets", "wait=61"] {
        let r = srv.req(Method::GET, &format!("/v1/events?{bad}"), "viewer").send().await.unwrap();
        assert_eq!(r.status(), 400, "{bad}");
    }

    // A long poll returns as soon as a change commits, with that change.
    let poll = {
        let (http, url, token) = (
            srv.http.clone(),
            srv.url(&format!("/v1/events?after={after}&wait=20")),
            srv.tokens["viewer"].clone(),
        );
        tokio::spawn(async move {
            let t0 = Instant::now();
            let page: Value = http.get(url).bearer_auth(token).send().await.unwrap().json().await.unwrap();
            (page, t0.elapsed())
        })
    };
    tokio::time::sleep(Duration::from_millis(300)).await;
    let r = srv
        .req(Method::POST, "/v1/exports", "trainer")
        .json(&json!({"format": "lerobot", "policy": "pol"}))
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "{}", r.text().await.unwrap());
    let export: Value = r.json().await.unwrap();
    let (page, waited) = poll.await.unwrap();
    assert_eq!(page["events"][0]["kind"], "job.changed", "{page}");
    assert_eq!(page["events"][0]["subject"], export["id"]);
    assert!(waited < Duration::from_secs(20), "the poll ran out instead of waking: {waited:?}");
    srv.wait_job(export["id"].as_str().unwrap()).await;
    let tail = events(&srv, &format!("after={after}&kind=export.finished")).await;
    assert_eq!(tail["events"][0]["subject"], export["id"], "{tail}");

    // Retention: deleted events are a 410, not a silent gap; after them the feed goes on.
    let (head, _) = srv.store.event_head().await.unwrap();
    assert_eq!(srv.store.prune_events(Duration::ZERO).await.unwrap() as i64, head);
    let r = srv.req(Method::GET, "/v1/events?after=3", "viewer").send().await.unwrap();
    assert_eq!(r.status(), 410);
    let rest = events(&srv, &format!("after={head}")).await;
    assert!(rest["events"].as_array().unwrap().is_empty());
    assert_eq!(rest["next"], head);
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn feed_follows_the_loop_sqlite() {
    feed_follows_the_loop(Db::Sqlite).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn feed_follows_the_loop_postgres() {
    if !store::test_support::require_postgres() {
        return;
    }
    feed_follows_the_loop(Db::Postgres).await;
}

async fn idempotency_keys(db: Db) {
    let srv = TestServer::start_with(db, false, |c| c.idempotency_lease = Duration::from_millis(600)).await;
    let post = |key: &str, name: &str| {
        srv.req(Method::POST, "/v1/tokens", "admin")
            .header("Idempotency-Key", key)
            .json(&json!({"name": name, "role": "viewer"}))
    };
    let count = |name: &'static str| {
        let store = srv.store.clone();
        async move { store.tokens().await.unwrap().iter().filter(|t| t.name == name).count() }
    };
    // The first answer, replayed: the same token (and secret), created once.
    let first = post("k-1", "robot-a").send().await.unwrap();
    assert_eq!(first.status(), 201);
    assert_eq!(first.headers()["idempotent-replayed"], "false");
    let first: Value = first.json().await.unwrap();
    let again = post("k-1", "robot-a").send().await.unwrap();
    assert_eq!(again.status(), 201);
    assert_eq!(again.headers()["idempotent-replayed"], "true");
    assert_eq!(again.headers()["content-type"], "application/json");
    assert_eq!(again.json::<Value>().await.unwrap(), first);
    assert_eq!(count("robot-a").await, 1);
    // Another body under the key: 422, nothing created.
    let r = post("k-1", "robot-b").send().await.unwrap();
    assert_eq!(r.status(), 422);
    let p: Value = r.json().await.unwrap();
    assert_eq!(p["type"], "urn:ufops:problem:idempotency-key-reused");
    assert_eq!(count("robot-b").await, 0);
    // Keys are per token: the trainer's "k-1" is its own.
    let r = srv
        .req(Method::POST, "/v1/label-snapshots", "trainer")
        .header("Idempotency-Key", "k-1")
        .json(&json!({"message": "m"}))
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "{}", r.status());
    // Without a key, a repeat is a second request.
    for _ in 0..2 {
        let r = srv
            .req(Method::POST, "/v1/tokens", "admin")
            .json(&json!({"name": "robot-c", "role": "viewer"}))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 201);
    }
    assert_eq!(count("robot-c").await, 2);
    // Malformed keys.
    let r = post("", "robot-d").send().await.unwrap();
    assert_eq!(r.status(), 400);
    let r = post(&"k".repeat(256), "robot-d").send().await.unwrap();
    assert_eq!(r.status(), 400);

    // A label PUT: the replay carries the first answer's ETag (a plain retry would be a 409).
    let ids = common::ingest(&srv.store, "idem", "c1", 2).await;
    let put = || {
        srv.req(Method::PUT, &format!("/v1/episodes/{}/label", ids[0]), "labeler")
            .header("If-Match", "\"1\"")
            .header("Idempotency-Key", "label-1")
            .json(&json!({"label": "failure"}))
    };
    let a = put().send().await.unwrap();
    let b = put().send().await.unwrap();
    assert_eq!((a.status(), b.status()), (reqwest::StatusCode::OK, reqwest::StatusCode::OK));
    assert_eq!(a.headers()["etag"], b.headers()["etag"]);
    assert_eq!(srv.store.label_history(&ids[0]).await.unwrap().len(), 2);

    // A key being served elsewhere: 409 with Retry-After (claimed here as a live server would).
    let admin = srv.store.verify_token(&srv.tokens["admin"]).await.unwrap().unwrap();
    let body = serde_json::to_vec(&json!({"name": "robot-e", "role": "viewer"})).unwrap();
    // The same request as `ask` below describes, sent over HTTP under `key`.
    let raw_post = |key: &'static str| {
        srv.req(Method::POST, "/v1/tokens", "admin")
            .header("Idempotency-Key", key)
            .header("Content-Type", "application/json")
            .body(body.clone())
            .send()
            .map(|r| r.unwrap())
    };
    let ask = store::IdempotentRequest {
        principal: &admin.id,
        key: "k-2",
        method: "POST",
        path: "/v1/tokens",
        fingerprint: &store::sha256_hex(&body),
    };
    assert_eq!(srv.store.claim_idempotent(&ask, 60_000, 3_600_000).await.unwrap(), store::Claim::Run);
    let r = raw_post("k-2").await;
    assert_eq!(r.status(), 409);
    assert!(r.headers().contains_key("retry-after"));

    // Its server died after the change committed (the key marked in the change's transaction)
    // and before the response was stored: a retry is told so and nothing is done again.
    let ask = store::IdempotentRequest { key: "k-3", ..ask };
    assert_eq!(srv.store.claim_idempotent(&ask, 300, 3_600_000).await.unwrap(), store::Claim::Run);
    let ctx = store::RequestContext { idempotency: Some((admin.id.clone(), "k-3".into())) };
    store::with_request(ctx, srv.store.create_token("robot-e", store::Role::Viewer)).await.unwrap();
    tokio::time::sleep(Duration::from_millis(400)).await;
    let r = raw_post("k-3").await;
    assert_eq!(r.status(), 409);
    let p: Value = r.json().await.unwrap();
    assert_eq!(p["type"], "urn:ufops:problem:idempotent-response-lost", "{p}");
    assert_eq!(count("robot-e").await, 1);
    // One that died before its change committed is run by the retry, once.
    let ask = store::IdempotentRequest { key: "k-4", ..ask };
    assert_eq!(srv.store.claim_idempotent(&ask, 300, 3_600_000).await.unwrap(), store::Claim::Run);
    tokio::time::sleep(Duration::from_millis(400)).await;
    let r = raw_post("k-4").await;
    assert_eq!(r.status(), 201);
    assert_eq!(count("robot-e").await, 2);
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idempotency_keys_sqlite() {
    idempotency_keys(Db::Sqlite).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idempotency_keys_postgres() {
    if !store::test_support::require_postgres() {
        return;
    }
    idempotency_keys(Db::Postgres).await;
}

/// A webhook receiver: checks each delivery's signature, answers 500 to the very first one, and
/// records the others (delivery id, event).
#[derive(Clone, Default)]
struct Receiver {
    secret: std::sync::Arc<std::sync::Mutex<String>>,
    attempts: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    bad_signatures: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    accepted: std::sync::Arc<std::sync::Mutex<Vec<(String, Value)>>>,
}

async fn receive(
    axum::extract::State(r): axum::extract::State<Receiver>,
    headers: axum::http::HeaderMap,
    body: axum::body::Bytes,
) -> axum::http::StatusCode {
    use std::sync::atomic::Ordering;
    let n = r.attempts.fetch_add(1, Ordering::SeqCst);
    let sig = headers["ufops-signature"].to_str().unwrap();
    let t: i64 = sig.strip_prefix("t=").unwrap().split(',').next().unwrap().parse().unwrap();
    let secret = r.secret.lock().unwrap().clone();
    if api::webhook_signature(&secret, t, &body) != sig || (chrono_now() - t).abs() > 300 {
        r.bad_signatures.fetch_add(1, Ordering::SeqCst);
        return axum::http::StatusCode::UNAUTHORIZED;
    }
    if n == 0 {
        return axum::http::StatusCode::INTERNAL_SERVER_ERROR; // the forced failure
    }
    let event: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(headers["ufops-event"], event["kind"].as_str().unwrap());
    r.accepted.lock().unwrap().push((headers["ufops-delivery"].to_str().unwrap().to_string(), event));
    axum::http::StatusCode::NO_CONTENT
}

fn chrono_now() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs() as i64
}

/// Starts the server of `srv` again (no worker, `tune`d) on the same store.
async fn restart(srv: &mut TestServer, tune: impl FnOnce(&mut api::ServeConfig)) {
    let mut cfg = api::ServeConfig::new(srv.dir.path());
    cfg.addr = "127.0.0.1:0".parse().unwrap();
    cfg.run_worker_in_process = false;
    tune(&mut cfg);
    let restarted = api::spawn(srv.store.clone(), cfg, srv.runner.clone()).await.unwrap();
    srv.base = format!("http://{}", restarted.addr);
    srv.server = Some(restarted);
}

/// What `receiver` accepted once it holds `n` deliveries (and nothing more came for a moment);
/// fails after 30 s with the subscription's state.
async fn delivered(receiver: &Receiver, n: usize, srv: &TestServer, hook: &str) -> Vec<(String, Value)> {
    let t0 = Instant::now();
    while receiver.accepted.lock().unwrap().len() < n {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "deliveries stalled: {:?}",
            srv.store.webhook(hook).await
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    tokio::time::sleep(Duration::from_millis(300)).await; // nothing more arrives
    receiver.accepted.lock().unwrap().clone()
}

async fn webhooks_deliver_each_event_once(db: Db) {
    let tune = |c: &mut api::ServeConfig| {
        c.webhook_backoff = Duration::from_millis(50);
        c.webhook_poll = Duration::from_millis(100);
    };
    let mut srv = TestServer::start_with(db, false, tune).await;
    let receiver = Receiver::default();
    let app = axum::Router::new()
        .route("/hook", axum::routing::post(receive))
        .route("/down", axum::routing::post(|| async { axum::http::StatusCode::SERVICE_UNAVAILABLE }))
        .with_state(receiver.clone());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let hook_url = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });

    let kinds = json!(["label.set", "version.created", "split.frozen"]);
    let r = srv
        .req(Method::POST, "/v1/webhooks", "admin")
        .json(&json!({"url": format!("{hook_url}/hook"), "kinds": kinds}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let created: Value = r.json().await.unwrap();
    *receiver.secret.lock().unwrap() = created["secret"].as_str().unwrap().to_string();
    let hook = created["webhook"]["id"].as_str().unwrap().to_string();
    let r = srv
        .req(Method::POST, "/v1/webhooks", "admin")
        .json(&json!({"url": format!("{hook_url}/down"), "kinds": ["split.frozen"], "max_attempts": 2}))
        .send()
        .await
        .unwrap();
    let down: Value = r.json().await.unwrap();
    let down = down["webhook"]["id"].as_str().unwrap().to_string();
    let r = srv
        .req(Method::POST, "/v1/webhooks", "trainer")
        .json(&json!({"url": "http://x/"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 403);
    let from = srv.store.webhook(&hook).await.unwrap().cursor_seq;

    // Changes over HTTP: labels, a snapshot, a split.
    let ids = common::ingest(&srv.store, "hook", "c1", 4).await;
    for id in &ids[..3] {
        let r = srv
            .req(Method::PUT, &format!("/v1/episodes/{id}/label"), "labeler")
            .header("If-Match", "\"1\"")
            .json(&json!({"label": "unknown"}))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
    }
    srv.req(Method::POST, "/v1/label-snapshots", "labeler").json(&json!({})).send().await.unwrap();
    let r = srv
        .req(Method::POST, "/v1/splits", "trainer")
        .json(&json!({"policy": "pol", "checkpoint": "c1"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());

    // The server stops; changes go on in the store meanwhile; a new server delivers them.
    srv.server.take().unwrap().shutdown().await.unwrap();
    srv.store
        .set_label(
            store::LabelUpdate {
                episode_id: ids[3].clone(),
                label: store::Label::Unknown,
                expect_revision: None,
                note: None,
            },
            "offline",
            "human",
        )
        .await
        .unwrap();
    restart(&mut srv, tune).await;

    // What the receiver must get: every matching event after the subscription began.
    let filter = store::EventFilter {
        kinds: vec![
            store::EventKind::LabelSet,
            store::EventKind::VersionCreated,
            store::EventKind::SplitFrozen,
        ],
        policy: None,
    };
    let expected: Vec<i64> =
        srv.store.events_after(from, 1000, &filter).await.unwrap().events.iter().map(|e| e.seq).collect();
    assert_eq!(expected.len(), 1 + 3 + 1 + 1 + 1, "ingest, 3 labels, snapshot, split, offline label");
    let accepted = delivered(&receiver, expected.len(), &srv, &hook).await;
    let seqs: Vec<i64> = accepted.iter().map(|(_, e)| e["seq"].as_i64().unwrap()).collect();
    assert_eq!(seqs, expected, "each event once, in feed order");
    for (delivery, e) in &accepted {
        assert_eq!(delivery, &store_feed::delivery_id(&hook, e["seq"].as_i64().unwrap()));
    }
    use std::sync::atomic::Ordering;
    assert_eq!(receiver.attempts.load(Ordering::SeqCst), expected.len() + 1, "the 500 was retried once");
    assert_eq!(receiver.bad_signatures.load(Ordering::SeqCst), 0);
    let state = srv.get_json(&format!("/v1/webhooks/{hook}"), "admin").await;
    assert_eq!(state["delivered"], expected.len());
    assert_eq!(state["cursor_seq"], *expected.last().unwrap());

    // A receiver that is down: the event goes to the dead letters after 2 attempts.
    let t0 = Instant::now();
    let letters = loop {
        let l = srv.get_json(&format!("/v1/webhooks/{down}/dead-letters"), "admin").await;
        if !l.as_array().unwrap().is_empty() {
            break l;
        }
        assert!(t0.elapsed() < Duration::from_secs(30), "no dead letter");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(letters[0]["attempts"], 2);
    assert_eq!(
        letters[0]["delivery_id"],
        store_feed::delivery_id(&down, letters[0]["seq"].as_i64().unwrap())
    );
    assert!(letters[0]["last_error"].as_str().unwrap().contains("503"), "{letters}");
    let r = srv.req(Method::DELETE, &format!("/v1/webhooks/{down}"), "admin").send().await.unwrap();
    assert_eq!(r.status(), 204);
    assert_eq!(srv.get_json("/v1/webhooks", "admin").await.as_array().unwrap().len(), 1);
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn webhooks_deliver_each_event_once_sqlite() {
    webhooks_deliver_each_event_once(Db::Sqlite).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn webhooks_deliver_each_event_once_postgres() {
    if !store::test_support::require_postgres() {
        return;
    }
    webhooks_deliver_each_event_once(Db::Postgres).await;
}

/// A subscription whose undelivered events retention deleted (its receiver was away longer than
/// the retention) goes on from the oldest event left, instead of failing on every try.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn webhooks_go_on_past_retention() {
    let tune = |c: &mut api::ServeConfig| {
        c.webhook_backoff = Duration::from_millis(50);
        c.webhook_poll = Duration::from_millis(100);
    };
    let mut srv = TestServer::start_with(Db::Sqlite, false, tune).await;
    let receiver = Receiver::default();
    let app = axum::Router::new().route("/hook", axum::routing::post(receive)).with_state(receiver.clone());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let hook_url = format!("http://{}/hook", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    let r = srv
        .req(Method::POST, "/v1/webhooks", "admin")
        .json(&json!({"url": hook_url, "kinds": ["label.set"]}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let created: Value = r.json().await.unwrap();
    *receiver.secret.lock().unwrap() = created["secret"].as_str().unwrap().to_string();
    let hook = created["webhook"]["id"].as_str().unwrap().to_string();

    // No server while a label is set and retention deletes its event; then another label.
    srv.server.take().unwrap().shutdown().await.unwrap();
    let ids = common::ingest(&srv.store, "gone", "c1", 2).await;
    let label = |id: &str| store::LabelUpdate {
        episode_id: id.to_string(),
        label: store::Label::Failure,
        expect_revision: None,
        note: None,
    };
    srv.store.set_label(label(&ids[0]), "offline", "human").await.unwrap();
    tokio::time::sleep(Duration::from_millis(5)).await;
    assert!(srv.store.prune_events(Duration::ZERO).await.unwrap() > 0);
    srv.store.set_label(label(&ids[1]), "offline", "human").await.unwrap();
    restart(&mut srv, tune).await;

    let accepted = delivered(&receiver, 1, &srv, &hook).await;
    let subjects: Vec<&str> = accepted.iter().map(|(_, e)| e["subject"].as_str().unwrap()).collect();
    assert_eq!(subjects, [ids[1].as_str()], "the deleted event is gone; the next one delivered once");
}
