//! The verifier-ordered review queue through `ufops serve` and its worker:
//! a classifier trained on real Lift rollouts scores the episodes in a `score` job, and
//! `GET /v1/episodes?order=uncertain` lists them nearest 0.5 first, a keyset page at a time;
//! the per-step series is served for the timeline; hostile queries are 4xx.

use crate::common;
use common::*;
use std::time::{Duration, Instant};

fn wait_job(url: &str, auth: &str, id: &str) -> serde_json::Value {
    let t0 = Instant::now();
    loop {
        let r = http(url, "GET", &format!("/v1/jobs/{id}"), &[("Authorization", auth)], None);
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let v = r.json();
        match v["state"].as_str().unwrap() {
            "succeeded" => return v,
            "failed" | "cancelled" => panic!("job {id} did not succeed: {v}"),
            _ => {}
        }
        assert!(t0.elapsed() < Duration::from_secs(180), "job {id} still not done: {v}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Every page of `GET /v1/episodes?order=…&limit=…`: (episode id, label, score) in queue order.
fn queue(url: &str, auth: &str, order: &str, limit: usize) -> Vec<(String, String, Option<f64>)> {
    queue_with(url, auth, &format!("order={order}&limit={limit}"))
}

/// [`queue`] with any query (`order=…&limit=…&version=…`).
fn queue_with(url: &str, auth: &str, query: &str) -> Vec<(String, String, Option<f64>)> {
    let mut out = Vec::new();
    let mut after: Option<String> = None;
    loop {
        let mut path = format!("/v1/episodes?policy=bc&{query}");
        if let Some(a) = &after {
            path.push_str(&format!("&after={}", urlencode(a)));
        }
        let r = http(url, "GET", &path, &[("Authorization", auth)], None);
        assert_eq!(r.status, 200, "{path}: {}", String::from_utf8_lossy(&r.body));
        let v = r.json();
        let eps = v["episodes"].as_array().unwrap();
        let review = v["review"].as_array().unwrap();
        assert_eq!(eps.len(), review.len(), "{v}");
        for (e, s) in eps.iter().zip(review) {
            assert_eq!(e["id"], s["episode_id"]);
            out.push((
                e["id"].as_str().unwrap().to_string(),
                e["label"].as_str().unwrap().to_string(),
                s["score"].as_f64(),
            ));
        }
        match v["next_cursor"].as_str() {
            Some(c) => after = Some(c.to_string()),
            None => return out,
        }
    }
}

fn urlencode(s: &str) -> String {
    s.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || b"-_.~".contains(&b) {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}

#[test]
fn uncertain_first_on_sqlite() {
    let dir = tempfile::tempdir().unwrap();
    uncertain_first_orders_by_stored_scores(&Target::sqlite(dir.path()));
}

/// The order's SQL (float keys, keyset bounds, the artifact joins) on the other catalog backend.
#[test]
fn uncertain_first_on_postgres() {
    let dir = tempfile::tempdir().unwrap();
    let Some(t) = postgres_target(dir.path()) else { return };
    uncertain_first_orders_by_stored_scores(&t);
}

fn uncertain_first_orders_by_stored_scores(t: &Target) {
    t.ok(&["init"]);
    let (artifact, n) = lift_with_classifier(t);
    let trainer = t.bearer("curator", "trainer");
    let viewer = t.bearer("labeler", "viewer");
    let server = t.serve(&[]);
    let url = server.url.as_str();

    // Before any score job: every episode listed, all unscored, in id order (the tie-break).
    let before = queue(url, &viewer, "uncertain", 5);
    assert_eq!(before.len(), n);
    assert!(before.iter().all(|(_, _, s)| s.is_none()), "{before:?}");
    assert!(before.windows(2).all(|w| w[0].0 < w[1].0));
    let r = http(
        url,
        "GET",
        &format!("/v1/episodes/{}/scores", before[0].0),
        &[("Authorization", &viewer)],
        None,
    );
    assert_eq!(r.status, 404, "not scored yet");

    // Refused: viewers cannot queue work; unknown orders, bad page sizes.
    let body = serde_json::json!({"policy": "bc", "checkpoint": "e600"});
    assert_eq!(http(url, "POST", "/v1/review/score", &[("Authorization", &viewer)], Some(&body)).status, 403);
    for (path, status) in [("/v1/episodes?order=random", 400), ("/v1/episodes?order=uncertain&limit=0", 400)]
    {
        let r = http(url, "GET", path, &[("Authorization", &viewer)], None);
        assert_eq!(r.status, status, "{path}: {}", String::from_utf8_lossy(&r.body));
        assert_eq!(r.header("content-type"), Some("application/problem+json"), "{path}");
    }
    let r = http(
        url,
        "POST",
        "/v1/review/score",
        &[("Authorization", &trainer)],
        Some(&serde_json::json!({"policy": "bc"})),
    );
    assert_eq!(r.status, 409, "no artifact, no checkpoint, no setting: the policy's state");

    // The score job with the default artifact (bc/e600's classifier@latest).
    let r = http(url, "POST", "/v1/review/score", &[("Authorization", &trainer)], Some(&body));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let job = r.json();
    assert_eq!(job["kind"], "score");
    let done = wait_job(url, &viewer, job["id"].as_str().unwrap());
    assert_eq!(done["result"]["episodes_scored"].as_u64().unwrap() as usize, n, "{done}");

    // The stored scores are `ufops rank`'s (one scoring definition).
    let want = rank_scores(t, artifact);
    let q = queue(url, &viewer, "uncertain", 5);
    assert_eq!(q.len(), n, "pages neither repeat nor skip");
    let ids: std::collections::HashSet<&str> = q.iter().map(|e| e.0.as_str()).collect();
    assert_eq!(ids.len(), n);
    for (id, _, s) in &q {
        let s = s.expect("scored");
        assert!((s - want[id]).abs() < 1e-5, "{id}: stored {s}, rank {}", want[id]);
    }
    // Uncertain first: |score − 0.5| never decreases along the queue, and the first is the closest.
    let dist: Vec<f64> = q.iter().map(|(_, _, s)| (s.unwrap() - 0.5).abs()).collect();
    assert!(dist.windows(2).all(|w| w[0] <= w[1]), "{q:?}");
    let closest = want.values().map(|s| (s - 0.5).abs()).fold(f64::INFINITY, f64::min);
    assert_eq!(dist[0], closest);
    let spread = dist.last().unwrap() - dist[0];
    assert!(spread > 0.05, "the trained classifier's scores differ: {q:?}");
    eprintln!(
        "uncertain-first queue: {:?}",
        q.iter().map(|(id, l, s)| format!("{id} {l} {:.3}", s.unwrap())).collect::<Vec<_>>()
    );

    // Disagreement first: |score − label| never increases.
    let d = queue(url, &viewer, "disagreement", 4);
    assert_eq!(d.len(), n);
    let gap: Vec<f64> = d
        .iter()
        .map(|(_, l, s)| match l.as_str() {
            "success" => 1.0 - s.unwrap(),
            "failure" => s.unwrap(),
            other => panic!("lift episodes are labeled, not {other}"),
        })
        .collect();
    assert!(gap.windows(2).all(|w| w[0] >= w[1]), "{d:?}");
    assert_eq!(queue(url, &viewer, "source", 3).len(), n);
    // At a past version: its episodes with the labels it froze (here the head, the same as now),
    // and the version must exist.
    let head = http(url, "GET", "/v1/versions", &[("Authorization", &viewer)], None).json();
    let head = head.as_array().unwrap().last().unwrap()["version"].as_i64().unwrap();
    assert_eq!(queue_with(url, &viewer, &format!("order=disagreement&limit=7&version={head}")), d);
    let r = http(
        url,
        "GET",
        &format!("/v1/episodes?order=uncertain&version={}", head + 1),
        &[("Authorization", &viewer)],
        None,
    );
    assert_eq!(r.status, 404);
    // Text that is not one of the order's cursors lies past its end: an empty last page.
    for after in ["nonsense", "NaN%7Cx", "inf%7Cx"] {
        let r = http(
            url,
            "GET",
            &format!("/v1/episodes?order=uncertain&after={after}"),
            &[("Authorization", &viewer)],
            None,
        );
        assert_eq!(r.status, 200, "{after}");
        assert_eq!(
            (r.json()["episodes"].as_array().unwrap().len(), &r.json()["next_cursor"]),
            (0, &serde_json::Value::Null),
            "{after}"
        );
    }

    // The per-step series, one per step, whose mean is the queue's score.
    let (id, _, s) = &q[0];
    let r = http(url, "GET", &format!("/v1/episodes/{id}/scores"), &[("Authorization", &viewer)], None);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let v = r.json();
    let steps: Vec<f64> = v["step_scores"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
    let ep = http(url, "GET", &format!("/v1/episodes/{id}"), &[("Authorization", &viewer)], None).json();
    assert_eq!(steps.len() as u64, ep["episode"]["length"].as_u64().unwrap());
    let mean = steps.iter().sum::<f64>() / steps.len() as f64;
    assert!((mean - s.unwrap()).abs() < 1e-5, "{mean} vs {s:?}");
    assert!(steps.iter().all(|x| (0.0..=1.0).contains(x)));

    // The per-policy setting: an unknown artifact is 404; setting the same one keeps the order.
    let put = |a: &str| {
        http(
            url,
            "PUT",
            "/v1/review/artifacts/bc",
            &[("Authorization", &trainer)],
            Some(&serde_json::json!({"artifact": a})),
        )
    };
    assert_eq!(put("bc/e600/classifier@nope").status, 404);
    let r = put(artifact);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["artifact_id"], v["artifact_id"]);
    let g = http(url, "GET", "/v1/review/artifacts/bc", &[("Authorization", &viewer)], None).json();
    assert_eq!(g["source"], "setting");
    assert_eq!(queue(url, &viewer, "uncertain", 100), q);
    let r = http(url, "DELETE", "/v1/review/artifacts/bc", &[("Authorization", &trainer)], None);
    assert_eq!(r.status, 204);
    let r = http(url, "DELETE", "/v1/review/artifacts/bc", &[("Authorization", &trainer)], None);
    assert_eq!(r.status, 404);
}
