//! `ufops review score` and `ufops review queue` on the Lift rollouts with a trained classifier:
//! the stored scores are `ufops rank`'s, the uncertain-first queue pages without repeats or gaps
//! in |score − 0.5| order, and a policy without a verifier fails with a message naming the fix;
//! `ufops review campaign` and `agreement` read and set what the labeling page's votes use.

use crate::common;
use common::*;

/// Every page of `ufops review queue --json` with `args`: (episode id, score) in queue order.
fn queue(t: &Target, args: &[&str], limit: usize) -> Vec<(String, Option<f64>)> {
    let mut out = Vec::new();
    let mut after: Option<String> = None;
    loop {
        let limit = limit.to_string();
        let mut a = vec!["review", "queue", "--policy", "bc", "--limit", &limit, "--json"];
        a.extend_from_slice(args);
        if let Some(c) = &after {
            a.extend(["--after", c.as_str()]);
        }
        let page = t.json(&a);
        for e in page["entries"].as_array().unwrap() {
            out.push((e["episode"]["id"].as_str().unwrap().to_string(), e["score"].as_f64()));
        }
        match page["next_cursor"].as_str() {
            Some(c) => after = Some(c.to_string()),
            None => return out,
        }
    }
}

#[test]
fn review_queue_from_the_cli() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    let (artifact, n) = lift_with_classifier(&t);

    // No artifact given and no setting for the policy: the error says what to give.
    let out = t.run(&["review", "score", "--policy", "bc"]);
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("--artifact"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = t.run(&["review", "queue", "--order", "random"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("random"));

    let unscored = queue(&t, &[], 100);
    assert_eq!(unscored.len(), n);
    assert!(unscored.iter().all(|(_, s)| s.is_none()), "{unscored:?}");

    // With --checkpoint, its classifier@latest scores the policy's queue.
    let r = t.json(&["review", "score", "--policy", "bc", "--checkpoint", "e600", "--json"]);
    assert_eq!(r["episodes_scored"].as_u64().unwrap() as usize, n, "{r}");
    let want = rank_scores(&t, artifact);
    let q = queue(&t, &["--order", "uncertain"], 5);
    assert_eq!(q.len(), n, "pages neither repeat nor skip: {q:?}");
    assert_eq!(q.iter().map(|e| &e.0).collect::<std::collections::HashSet<_>>().len(), n);
    let dist: Vec<f64> = q
        .iter()
        .map(|(id, s)| {
            let s = s.expect("scored");
            assert!((s - want[id]).abs() < 1e-5, "{id}: stored {s}, rank {}", want[id]);
            (s - 0.5).abs()
        })
        .collect();
    assert!(dist.windows(2).all(|w| w[0] <= w[1]), "{q:?}");
    assert!(dist.last().unwrap() - dist[0] > 0.05, "the trained classifier's scores differ: {q:?}");

    // The table: a header, one line per episode and the next page's cursor.
    let table = t.ok(&["review", "queue", "--policy", "bc", "--limit", "3"]);
    assert_eq!(table.lines().count(), 5, "{table}");
    assert!(table.lines().nth(1).unwrap().starts_with(&q[0].0), "{table}");
    assert!(table.contains("next page: --after"), "{table}");

    // The campaign: one verdict by default; two, blind, once set.
    assert_eq!(t.json(&["review", "campaign", "--policy", "bc", "--json"])["labels_needed"], 1);
    t.ok(&["review", "campaign", "--policy", "bc", "--labels-needed", "2", "--blind", "true"]);
    let c = t.json(&["review", "campaign", "--policy", "bc", "--json"]);
    assert_eq!((&c["labels_needed"], &c["blind"]), (&serde_json::json!(2), &serde_json::json!(true)), "{c}");
    let none = t.ok(&["review", "agreement", "--policy", "bc"]);
    assert!(none.contains("0 episodes voted") && none.contains("alpha -"), "{none}");

    // Two labelers vote over HTTP: they agree on one episode and not on the other.
    let mut auth = Vec::new();
    for name in ["alice", "bob"] {
        auth.push(t.bearer(name, "labeler"));
    }
    let server = t.serve(&["--no-worker"]);
    for (who, votes) in [(0, ["success", "success"]), (1, ["success", "failure"])] {
        for (ep, label) in [&q[0].0, &q[1].0].into_iter().zip(votes) {
            let r = http(
                &server.url,
                "POST",
                &format!("/v1/episodes/{ep}/votes"),
                &[("Authorization", &auth[who])],
                Some(&serde_json::json!({"label": label})),
            );
            assert!(r.status < 300, "{}", String::from_utf8_lossy(&r.body));
        }
    }
    let a = t.json(&["review", "agreement", "--policy", "bc", "--json"]);
    assert_eq!(
        (a["episodes_voted"].as_u64(), a["agreed"].as_u64(), a["disputed"].as_u64()),
        (Some(2), Some(1), Some(1)),
        "{a}"
    );
    let pair = &a["pairs"][0];
    assert_eq!((pair["episodes"].as_u64(), pair["observed"].as_f64()), (Some(2), Some(0.5)), "{a}");
    let text = t.ok(&["review", "agreement", "--policy", "bc"]);
    assert!(text.contains("alice / bob: 2 common episodes, observed 0.500"), "{text}");
}
