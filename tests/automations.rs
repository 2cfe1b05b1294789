//! The flywheel turns by itself, through `ufops serve` and its worker on
//! SQLite and Postgres: episodes are labeled over HTTP one at a time; below the threshold nothing
//! is queued; the label that reaches it makes the `train_on_labels` automation freeze a split and
//! train, the published verifier makes `score_on_publish` score the review queue, and a steered
//! run whose episodes are all labeled makes `scoreboard_on_run_labeled` snapshot and compute its
//! scoreboard row — with no further command. The feed shows every step in order, and a webhook
//! receiver that answers 500 to its first delivery gets each event exactly once by delivery id.

use crate::common;
use common::*;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Read, Write};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// A webhook receiver on a free port: answers 500 to the first delivery it gets and 200 to every
/// other; records `(delivery id, status it answered)` of each.
struct Receiver {
    url: String,
    got: Arc<Mutex<Vec<(String, u16)>>>,
}

fn receiver() -> Receiver {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}/hook", listener.local_addr().unwrap());
    let got = Arc::new(Mutex::new(Vec::new()));
    let log = got.clone();
    std::thread::spawn(move || {
        for conn in listener.incoming() {
            let Ok(mut conn) = conn else { continue };
            let mut reader = BufReader::new(conn.try_clone().unwrap());
            let (mut delivery, mut length) = (String::new(), 0usize);
            loop {
                let mut line = String::new();
                if reader.read_line(&mut line).unwrap_or(0) == 0 || line == "\r\n" {
                    break;
                }
                let lower = line.to_ascii_lowercase();
                if let Some(v) = lower.strip_prefix("ufops-delivery:") {
                    delivery = v.trim().to_string();
                }
                if let Some(v) = lower.strip_prefix("content-length:") {
                    length = v.trim().parse().unwrap_or(0);
                }
            }
            let mut body = vec![0; length];
            let _ = reader.read_exact(&mut body);
            let mut log = log.lock().unwrap();
            let status = if log.is_empty() { 500 } else { 200 };
            log.push((delivery, status));
            drop(log);
            let reason = if status == 200 { "OK" } else { "Internal Server Error" };
            let _ =
                write!(conn, "HTTP/1.1 {status} {reason}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n");
        }
    });
    Receiver { url, got }
}

fn events(url: &str, auth: &str) -> Vec<serde_json::Value> {
    let mut out = Vec::new();
    let mut after = 0;
    loop {
        let r = http(
            url,
            "GET",
            &format!("/v1/events?after={after}&limit=1000"),
            &[("Authorization", auth)],
            None,
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let page = r.json();
        let evs = page["events"].as_array().unwrap().clone();
        after = page["next"].as_i64().unwrap();
        if evs.is_empty() {
            return out;
        }
        out.extend(evs);
    }
}

fn jobs(url: &str, auth: &str) -> Vec<serde_json::Value> {
    let r = http(url, "GET", "/v1/jobs", &[("Authorization", auth)], None);
    assert_eq!(r.status, 200);
    r.json().as_array().unwrap().clone()
}

/// Waits until `done` holds of the feed (every event so far), or fails with the feed's kinds.
fn wait_feed(
    url: &str,
    auth: &str,
    what: &str,
    done: impl Fn(&[serde_json::Value]) -> bool,
) -> Vec<serde_json::Value> {
    let t0 = Instant::now();
    loop {
        let evs = events(url, auth);
        if done(&evs) {
            return evs;
        }
        if let Some(e) = evs.iter().find(|e| e["kind"] == "job.changed" && e["data"]["state"] == "failed") {
            panic!("a job failed while waiting for {what}: {e}");
        }
        assert!(
            t0.elapsed() < Duration::from_secs(240),
            "still waiting for {what}; the feed: {:?}",
            evs.iter().map(|e| format!("{} {} {}", e["seq"], e["kind"], e["subject"])).collect::<Vec<_>>()
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Labels `id` over HTTP with the revision it has now.
fn label(url: &str, auth: &str, id: &str, success: bool) {
    let r = http(url, "GET", &format!("/v1/episodes/{id}"), &[("Authorization", auth)], None);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let rev = r.json()["episode"]["label_revision"].as_i64().expect("label_revision");
    let body = serde_json::json!({"label": if success { "success" } else { "failure" }});
    let r = http(
        url,
        "PUT",
        &format!("/v1/episodes/{id}/label"),
        &[("Authorization", auth), ("If-Match", &rev.to_string())],
        Some(&body),
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
}

/// The episodes of `policy` and their true labels from a fixture's success file, in a fixed order.
fn episodes_with_truth(t: &Target, policy: &str, fixture: &str) -> Vec<(String, bool)> {
    let truth: BTreeMap<String, bool> = serde_json::from_str(
        &std::fs::read_to_string(fixtures().join("robomimic").join(format!("{fixture}.success.json")))
            .unwrap(),
    )
    .unwrap();
    let eps = t.json(&["episodes", "--policy", policy, "--json"]);
    let mut out: Vec<(String, bool)> = eps
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            assert_eq!(e["label"], "unknown", "ingested without labels: {e}");
            let name = e["source_name"].as_str().unwrap();
            (e["id"].as_str().unwrap().to_string(), truth[name])
        })
        .collect();
    out.sort();
    out
}

fn position(evs: &[serde_json::Value], what: &str, pred: impl Fn(&serde_json::Value) -> bool) -> usize {
    evs.iter().position(pred).unwrap_or_else(|| panic!("no {what} in the feed"))
}

#[test]
fn automations_turn_the_loop_on_sqlite() {
    let dir = tempfile::tempdir().unwrap();
    labels_train_publish_and_score_by_themselves(&Target::sqlite(dir.path()));
}

#[test]
fn automations_turn_the_loop_on_postgres() {
    let dir = tempfile::tempdir().unwrap();
    let Some(t) = postgres_target(dir.path()) else { return };
    labels_train_publish_and_score_by_themselves(&t);
}

fn labels_train_publish_and_score_by_themselves(t: &Target) {
    t.ok(&["init"]);
    let f = fixtures().join("robomimic");
    let lowdim = f.join("lift_rollouts_lowdim.hdf5");
    let image = f.join("lift_rollouts_image.hdf5");
    // Rollouts of checkpoint e600 (the base run), and a steered run of policy `lift`: all unlabeled.
    t.ok(&["ingest", lowdim.to_str().unwrap(), "--policy", "bc", "--checkpoint", "e600", "--run", "base"]);
    t.ok(&[
        "ingest",
        image.to_str().unwrap(),
        "--policy",
        "lift",
        "--checkpoint",
        "c1",
        "--steering",
        "bon:4",
    ]);
    let bc = episodes_with_truth(t, "bc", "lift_rollouts_lowdim");
    let steered = episodes_with_truth(t, "lift", "lift_rollouts_image");
    let admin = t.bearer("ops", "admin");
    let trainer = t.bearer("curator", "trainer");
    let labeler = t.bearer("labeler", "labeler");
    let server = t.serve(&[]);
    let url = server.url.as_str();

    let hook = receiver();
    let body = serde_json::json!({"url": hook.url});
    let r = http(url, "POST", "/v1/webhooks", &[("Authorization", &admin)], Some(&body));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let webhook = r.json()["webhook"]["id"].as_str().unwrap().to_string();

    // Refused: a labeler cannot declare automations; bad rules and parameters are 400s.
    let train_rule = serde_json::json!({"policy": "bc", "rule": "train_on_labels", "params": {
        "checkpoint": "e600", "min_labeled": 8, "chunk_len": 16, "config": {"epochs": 20, "batch_size": 256}}});
    let r = http(url, "POST", "/v1/automations", &[("Authorization", &labeler)], Some(&train_rule));
    assert_eq!(r.status, 403);
    for bad in [
        serde_json::json!({"policy": "bc", "rule": "train_when_ready", "params": {}}),
        serde_json::json!({"policy": "bc", "rule": "train_on_labels", "params": {}}),
        serde_json::json!({"policy": "bc", "rule": "train_on_labels", "params": {"min_labeled": 1}}),
        serde_json::json!({"policy": "bc", "rule": "score_on_publish", "params": {"min_labeled": 8}}),
    ] {
        let r = http(url, "POST", "/v1/automations", &[("Authorization", &trainer)], Some(&bad));
        assert_eq!(r.status, 400, "{bad}: {}", String::from_utf8_lossy(&r.body));
    }
    let mut ids = Vec::new();
    for rule in [
        train_rule,
        serde_json::json!({"policy": "bc", "rule": "score_on_publish"}),
        serde_json::json!({"policy": "lift", "rule": "scoreboard_on_run_labeled", "params": {"baseline": "base"}}),
    ] {
        let r = http(url, "POST", "/v1/automations", &[("Authorization", &trainer)], Some(&rule));
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        ids.push(r.json()["id"].as_str().unwrap().to_string());
    }
    let r = http(url, "GET", "/v1/automations?policy=bc", &[("Authorization", &labeler)], None);
    assert_eq!(r.status, 200);
    assert_eq!(r.json().as_array().unwrap().len(), 2, "{}", r.json());

    // Below the threshold (both labels among the first seven): nothing is queued.
    let mut order: Vec<&(String, bool)> = bc.iter().filter(|(_, s)| *s).take(4).collect();
    order.extend(bc.iter().filter(|(_, s)| !*s).take(4));
    assert_eq!(order.len(), 8);
    for (id, success) in &order[..7] {
        label(url, &labeler, id, *success);
    }
    // The automation has read past every one of those labels, and queued nothing.
    let t0 = Instant::now();
    loop {
        let head = events(url, &admin).last().unwrap()["seq"].as_i64().unwrap();
        let a = http(url, "GET", &format!("/v1/automations/{}", ids[0]), &[("Authorization", &admin)], None)
            .json();
        if a["cursor_seq"].as_i64().unwrap() >= head {
            assert_eq!(a["fired"], 0, "{a}");
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(30), "the automation never caught up: {a}");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(jobs(url, &admin).is_empty(), "{:?}", jobs(url, &admin));

    // The eighth label: train, publish, score, with no command.
    let (last_id, last_success) = order[7];
    label(url, &labeler, last_id, *last_success);
    let evs = wait_feed(url, &admin, "the review queue scored by the new verifier", |evs| {
        evs.iter().any(|e| {
            e["kind"] == "job.changed" && e["data"]["kind"] == "score" && e["data"]["state"] == "succeeded"
        })
    });
    let seq = |i: usize| evs[i]["seq"].as_i64().unwrap();
    let eighth = position(&evs, "the eighth label", |e| e["kind"] == "label.set" && e["subject"] == *last_id);
    let fired_train = position(&evs, "the train firing", |e| {
        e["kind"] == "automation.fired" && e["data"]["job_kind"] == "train"
    });
    let train_job = evs[fired_train]["data"]["job_id"].as_str().unwrap().to_string();
    let job_state = |job: &str, state: &str| {
        let (job, state) = (job.to_string(), state.to_string());
        move |e: &serde_json::Value| {
            e["kind"] == "job.changed" && e["subject"] == job && e["data"]["state"] == state
        }
    };
    let queued = position(&evs, "the train job queued", job_state(&train_job, "queued"));
    let running = position(&evs, "the train job running", job_state(&train_job, "running"));
    let frozen =
        position(&evs, "the split frozen", |e| e["kind"] == "split.frozen" && e["checkpoint"] == "e600");
    let published = position(&evs, "the verifier published", |e| e["kind"] == "artifact.published");
    let trained = position(&evs, "the train job succeeded", job_state(&train_job, "succeeded"));
    let artifact = evs[published]["subject"].as_str().unwrap().to_string();
    assert_eq!(evs[published]["data"]["job_id"], train_job.as_str());
    let fired_score = position(&evs, "the score firing", |e| {
        e["kind"] == "automation.fired" && e["data"]["job_kind"] == "score"
    });
    let score_job = evs[fired_score]["data"]["job_id"].as_str().unwrap().to_string();
    let scored = position(&evs, "the queue scored", |e| {
        e["kind"] == "review.scored" && e["subject"] == artifact.as_str()
    });
    let score_done = position(&evs, "the score job succeeded", job_state(&score_job, "succeeded"));
    let steps =
        [eighth, fired_train, queued, running, frozen, published, trained, fired_score, scored, score_done];
    assert!(
        steps.windows(2).all(|w| seq(w[0]) < seq(w[1])),
        "out of order: {:?}",
        steps
            .iter()
            .map(|&i| format!("{} {} {}", evs[i]["seq"], evs[i]["kind"], evs[i]["subject"]))
            .collect::<Vec<_>>()
    );
    // The split holds the eight labels, frozen after the last of them.
    assert_eq!(
        evs[frozen]["data"]["train_episodes"].as_i64().unwrap()
            + evs[frozen]["data"]["val_episodes"].as_i64().unwrap(),
        8,
        "{}",
        evs[frozen]
    );
    // The queue is ordered by the new verifier's scores: every bc episode scored.
    let r = http(
        url,
        "GET",
        "/v1/episodes?policy=bc&order=uncertain&limit=100",
        &[("Authorization", &labeler)],
        None,
    );
    assert_eq!(r.status, 200);
    let page = r.json();
    let review = page["review"].as_array().unwrap();
    assert_eq!(review.len(), 12);
    assert!(review.iter().all(|s| s["artifact_id"] == artifact.as_str() && s["score"].is_number()), "{page}");
    // One job each: nothing fired twice.
    let all = jobs(url, &admin);
    let kinds: Vec<&str> = all.iter().map(|j| j["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds.iter().filter(|k| **k == "train").count(), 1, "{kinds:?}");
    assert_eq!(kinds.iter().filter(|k| **k == "score").count(), 1, "{kinds:?}");
    assert!(all.iter().all(|j| j["created_by"].as_str().unwrap().starts_with("automation:")), "{all:?}");
    // The automation says why it fired: its verifier now covers the checkpoint's labels.
    let a =
        http(url, "GET", &format!("/v1/automations/{}", ids[0]), &[("Authorization", &labeler)], None).json();
    assert_eq!(a["fired"], 1, "{a}");
    let target = &a["targets"][0];
    assert_eq!(
        (target["target"].as_str(), target["job_id"].as_str()),
        (Some("e600"), Some(train_job.as_str())),
        "{a}"
    );
    assert_eq!(target["covered_seq"].as_i64(), Some(seq(frozen)), "covered up to its split's freeze: {a}");
    assert!(target["changed_seq"].as_i64().unwrap() <= seq(frozen), "{a}");

    // The steered run: its scoreboard row once its last episode is labeled, not before.
    for (i, (id, success)) in steered.iter().enumerate() {
        if i + 1 == steered.len() {
            assert!(
                !events(url, &admin)
                    .iter()
                    .any(|e| e["kind"] == "automation.fired" && e["subject"] == ids[2].as_str()),
                "fired before the run was all labeled"
            );
        }
        label(url, &labeler, id, *success);
    }
    let evs = wait_feed(url, &admin, "the run's scoreboard row", |evs| {
        evs.iter().any(|e| {
            e["kind"] == "job.changed"
                && e["data"]["kind"] == "scoreboard"
                && e["data"]["state"] == "succeeded"
        })
    });
    let done = evs
        .iter()
        .find(|e| {
            e["kind"] == "job.changed"
                && e["data"]["kind"] == "scoreboard"
                && e["data"]["state"] == "succeeded"
        })
        .unwrap();
    let result = &done["data"]["result"];
    let rows = result["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 1, "{result}");
    let successes = steered.iter().filter(|(_, s)| *s).count() as u64;
    assert_eq!(rows[0]["run_name"], "bon:4", "{result}");
    assert_eq!(rows[0]["successes"].as_u64().unwrap(), successes, "{result}");
    assert_eq!(rows[0]["failures"].as_u64().unwrap(), steered.len() as u64 - successes, "{result}");
    assert_eq!(rows[0]["unlabeled"], 0);
    // Its version froze the run's labels: the scoreboard at it says the same.
    let version = result["version"].as_i64().unwrap();
    assert!(evs
        .iter()
        .any(|e| e["kind"] == "version.created" && e["subject"] == version.to_string().as_str()));
    let r = http(
        url,
        "GET",
        &format!("/v1/scoreboard?policy=lift&version={version}"),
        &[("Authorization", &labeler)],
        None,
    );
    assert_eq!(r.status, 200);
    let board = r.json();
    let row = board["rows"].as_array().unwrap().iter().find(|r| r["run_name"] == "bon:4").unwrap().clone();
    assert_eq!(row["successes"], rows[0]["successes"]);

    // The receiver got every event of the feed, each accepted exactly once by delivery id, the
    // one it refused included (retried after the back-off).
    let head = evs.last().unwrap()["seq"].as_i64().unwrap();
    let t0 = Instant::now();
    loop {
        let w =
            http(url, "GET", &format!("/v1/webhooks/{webhook}"), &[("Authorization", &admin)], None).json();
        if w["cursor_seq"].as_i64().unwrap() >= head {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "deliveries behind: {w}");
        std::thread::sleep(Duration::from_millis(100));
    }
    let got = hook.got.lock().unwrap().clone();
    assert_eq!(got[0].1, 500, "the first delivery is refused");
    let mut accepted: BTreeMap<String, usize> = BTreeMap::new();
    for (id, status) in &got {
        if *status == 200 {
            *accepted.entry(id.clone()).or_default() += 1;
        }
    }
    assert!(accepted.contains_key(&got[0].0), "the refused delivery was retried and accepted");
    let created = position(&evs, "the webhook's first event", |e| e["kind"] == "automation.created");
    let expected: Vec<String> = evs[created..]
        .iter()
        .filter(|e| e["seq"].as_i64().unwrap() <= head)
        .map(|e| store_feed::delivery_id(&webhook, e["seq"].as_i64().unwrap()))
        .collect();
    for id in &expected {
        assert_eq!(accepted.get(id), Some(&1), "delivery {id}: {:?}", accepted.get(id));
    }
    assert!(accepted.values().all(|n| *n == 1), "a delivery accepted twice: {accepted:?}");
}

/// `ufops automation add|list|rm` on the store: bad rules and parameters fail with a message and
/// leave nothing behind; declared ones are listed and audited in the feed.
#[test]
fn automation_cli_declares_lists_and_deletes() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    for (args, says) in [
        (vec!["--rule", "train_when_ready"], "unknown automation rule"),
        (vec!["--rule", "train_on_labels", "--params", "{\"min_labeled\": 1}"], "min_labeled"),
        (vec!["--rule", "train_on_labels", "--params", "not json"], "--params is not JSON"),
        (vec!["--rule", "score_on_publish", "--params", "{\"min_labeled\": 8}"], "unknown field"),
    ] {
        let mut a = vec!["automation", "add", "--policy", "bc"];
        a.extend(args.iter().copied());
        let out = t.run(&a);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(says), "{args:?}: {err}");
    }
    assert_eq!(t.json(&["automation", "list", "--json"]), serde_json::json!([]));
    let a = t.json(&[
        "automation",
        "add",
        "--policy",
        "bc",
        "--rule",
        "train_on_labels",
        "--params",
        r#"{"min_labeled": 50, "chunk_len": 16}"#,
        "--json",
    ]);
    assert_eq!(a["params"]["min_labeled"], 50);
    assert_eq!(a["params"]["kind"], "classifier", "defaults filled in: {a}");
    let id = a["id"].as_str().unwrap();
    let listed = t.json(&["automation", "list", "--policy", "bc", "--json"]);
    assert_eq!(listed.as_array().unwrap().len(), 1);
    assert_eq!(listed[0]["id"], id);
    assert!(t.ok(&["automation", "rm", id]).contains("deleted"));
    assert!(!t.run(&["automation", "rm", id]).status.success(), "already gone");
    let feed = t.ok(&["events", "--kind", "automation.created,automation.deleted", "--json"]);
    let kinds: Vec<String> = feed
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["kind"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(kinds, ["automation.created", "automation.deleted"], "{feed}");
}
