//! What `lerobot-eval` writes, into the store and compared: two checkpoints evaluated with the
//! same `--seed` (`fixtures/lerobot_eval/`, written by lerobot's own `lerobot-eval`, 0.4.4 and
//! 0.3.3) are ingested with `ufops ingest` and `ufops compare` pairs their episodes by seed — the
//! default `pair_key` and `--pair-key seed` alike — giving the paired table the expected file
//! computes from the two `eval_info.json` files. Without `--start-seed` (lerobot 0.4 records no
//! seeds) the ingest warns and the comparison pairs in arrival order.

use crate::common;
use common::*;

use serde_json::Value;

fn expected(rel: &str) -> Value {
    serde_json::from_slice(&std::fs::read(fixtures().join(rel)).unwrap()).unwrap()
}

/// `ufops ingest` of `layout`'s two runs as checkpoints `ckpt-a` and `ckpt-b` of `policy`
/// (run `eval`); returns each ingest's stderr.
fn ingest_runs(t: &Target, layout: &str, policy: &str, extra: &[&str]) -> Vec<String> {
    ["ckpt-a", "ckpt-b"]
        .iter()
        .map(|ckpt| {
            let path = fixtures().join(format!("lerobot_eval/{layout}/{ckpt}"));
            let mut args = vec!["ingest", path.to_str().unwrap(), "--policy", policy, "--checkpoint", ckpt];
            args.extend_from_slice(&["--run", "eval"]);
            args.extend_from_slice(extra);
            let out = t.run(&args);
            let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
            assert!(out.status.success(), "ufops {args:?}: {stderr}");
            let stdout = String::from_utf8_lossy(&out.stdout);
            assert!(stdout.contains("8 episodes") && stdout.contains("(lerobot-eval,"), "{stdout}");
            stderr
        })
        .collect()
}

/// `ufops compare` of the policy's two checkpoints, as JSON, with its exit status.
fn compare(t: &Target, policy: &str, extra: &[&str]) -> (Option<i32>, Value) {
    let mut args = vec!["compare", "--policy", policy, "--a", "ckpt-a/eval", "--b", "ckpt-b/eval"];
    args.extend_from_slice(&["--format", "json"]);
    args.extend_from_slice(extra);
    let out = t.run(&args);
    let c = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stderr)));
    (out.status.code(), c)
}

/// The pooled slice against the expected file's pairs and paired table.
fn check_paired(c: &Value, exp: &Value) {
    let p = &c["pooled"];
    assert_eq!(p["pairs"], exp["pairs"], "{c}");
    assert_eq!((&p["unpaired_a"], &p["unpaired_b"]), (&Value::from(0), &Value::from(0)), "{c}");
    assert_eq!(p["pair_table"], exp["pair_table"], "{c}");
    let runs = &exp["runs"];
    let pairs = exp["pairs"].as_f64().unwrap();
    let rate = |r: &str| runs[r]["n_success"].as_f64().unwrap() / pairs;
    assert!((p["rate_a"].as_f64().unwrap() - rate("ckpt-a")).abs() < 1e-12, "{c}");
    assert!((p["rate_b"].as_f64().unwrap() - rate("ckpt-b")).abs() < 1e-12, "{c}");
    // Eight pairs decide nothing: undecided, with the pairs still needed.
    assert_eq!(p["decision"], "undecided", "{c}");
}

#[test]
fn two_lerobot_eval_runs_pair_by_seed() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());

    // lerobot 0.4: the seed comes from --start-seed; the pair key names the task and the seed.
    let warnings = ingest_runs(&t, "v04", "pusht-dp", &["--start-seed", "1000"]);
    assert!(warnings.iter().all(|w| !w.contains("warning")), "{warnings:?}");
    let exp = expected("lerobot_eval/v04.expected.json");
    let (code, c) = compare(&t, "pusht-dp", &[]);
    assert_eq!(code, Some(2));
    assert_eq!(c["pairing"], "key:pair_key");
    check_paired(&c, &exp);
    assert_eq!(exp["pair_table"]["only_a"], 1, "the fixture's checkpoints disagree both ways");
    assert_eq!(exp["pair_table"]["only_b"], 1);
    let (_, by_seed) = compare(&t, "pusht-dp", &["--pair-key", "seed"]);
    assert_eq!(by_seed["pairing"], "key:seed");
    check_paired(&by_seed, &exp);
    // The episodes carry their seed and key.
    let eps = t.json(&["episodes", "--policy", "pusht-dp", "--checkpoint", "ckpt-b", "--json"]);
    let eps = eps.as_array().unwrap();
    assert_eq!(eps.len(), 8);
    let e7 = eps.iter().find(|e| e["source_name"] == "episode_7").expect("episode 7");
    assert_eq!(e7["metadata"]["pair_key"], "pusht_0/seed:1007");
    assert_eq!(e7["metadata"]["outcome_only"], true);

    // lerobot 0.3: the seeds are in the file.
    ingest_runs(&t, "v03", "pusht-dp-03", &[]);
    let exp = expected("lerobot_eval/v03.expected.json");
    let (code, c) = compare(&t, "pusht-dp-03", &[]);
    assert_eq!(code, Some(2));
    assert_eq!(c["pairing"], "key:pair_key");
    check_paired(&c, &exp);

    // lerobot 0.4 without --start-seed: a warning, no keys, arrival order (episode i with i). A
    // store holds a source once (by its hash), so this is another store.
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    let warnings = ingest_runs(&t, "v04", "pusht-dp-unseeded", &[]);
    for w in &warnings {
        assert!(
            w.contains("warning:") && w.contains("does not record seeds") && w.contains("--start-seed"),
            "{w}"
        );
    }
    let (_, c) = compare(&t, "pusht-dp-unseeded", &[]);
    assert_eq!(c["pairing"], "arrival order");
    check_paired(&c, &expected("lerobot_eval/v04.expected.json"));
}
