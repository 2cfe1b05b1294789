//! The anytime-valid comparison and the evidence-gated policy alias, on both catalogs: the store's
//! comparison equals `evalstats` run by hand on the version's episodes (paired by key, and in
//! arrival order), tasks are tested at α/K, progress scores are compared when asked, a protected
//! alias refuses a move without a decided "not worse" and accepts one with it, and the stored
//! evidence, recomputed at its version, gives the same comparison.

use evalstats::{compare_pairs, Pair, SequentialConfig};
use store::*;
use store_compare::*;

use evalstats::splitmix::SplitMix64 as Rng;

/// A run's rollouts: per initial condition i (`pair_key` "ic{i}"), a difficulty u_i shared by
/// every run, and success when u_i + noise < rate (so runs correlate through u_i). Episode i of
/// task `push` when i % 3 == 0, else `reach`; a `progress` score in the metadata.
fn outcomes(seed: u64, rate: f64, n: u32) -> Vec<(Label, f64)> {
    let mut shared = Rng(1);
    let mut own = Rng(seed);
    (0..n)
        .map(|_| {
            let u = shared.next_f64();
            let x = 0.7 * u + 0.3 * own.next_f64();
            let ok = x < rate;
            (
                if ok { Label::Success } else { Label::Failure },
                if ok { 1.0 } else { (1.0 - x).clamp(0.0, 0.9) },
            )
        })
        .collect()
}

async fn ingest(store: &Store, run: &str, outcomes: &[(Label, f64)], keys: bool) -> i64 {
    let src = SourceInput {
        path: format!("/tmp/{run}"),
        sha256: sha256_hex(run.as_bytes()),
        format: "test".into(),
        size_bytes: 1,
        metadata: serde_json::json!({}),
    };
    let mut w = store.begin_ingest(src, "pol", "c1").await.unwrap();
    w.set_run(RunInput::new(run, Steering::Base)).unwrap();
    for (i, &(label, progress)) in outcomes.iter().enumerate() {
        let task = if i % 3 == 0 { "push" } else { "reach" };
        let mut e = test_support::two_step_episode(i as u32, Some(task), label);
        e.metadata = if keys {
            serde_json::json!({ "pair_key": format!("ic{i}"), "progress": progress })
        } else {
            serde_json::json!({ "progress": progress })
        };
        w.add_episode(e).await.unwrap();
    }
    w.commit("compare test").await.unwrap().version
}

fn arm(s: &str) -> ArmSpec {
    s.parse().unwrap()
}

/// The same comparison by hand: pairs from the outcomes (episode i of A with episode i of B, the
/// shared key), a task's pairs, evalstats.
fn by_hand(
    a: &[(Label, f64)],
    b: &[(Label, f64)],
    task: Option<usize>,
    alpha: f64,
    progress: bool,
) -> evalstats::SequentialResult {
    let y = |o: &(Label, f64)| {
        if progress {
            o.1
        } else if o.0 == Label::Success {
            1.0
        } else {
            0.0
        }
    };
    let pairs: Vec<Pair> = a
        .iter()
        .zip(b)
        .enumerate()
        .filter(|(i, _)| task.is_none_or(|t| (i % 3 == 0) == (t == 0)))
        .map(|(_, (x, z))| Pair { a: y(x), b: y(z) })
        .collect();
    compare_pairs(&pairs, SequentialConfig { alpha, ..Default::default() })
}

fn same(slice: &ComparisonSlice, r: &evalstats::SequentialResult) {
    assert_eq!(slice.decision, r.decision.as_str(), "{slice:?}");
    assert_eq!(slice.decided_at_pairs, r.decided_at);
    assert_eq!(slice.pairs, r.pairs);
    assert_eq!(slice.confidence_sequence, r.confidence_sequence);
    assert_eq!(slice.more_pairs, r.more_pairs);
}

async fn compare_and_gate(store: Store) {
    let base = outcomes(2, 0.5, 240);
    let good = outcomes(3, 0.8, 240);
    let bad = outcomes(4, 0.25, 240);
    let few = outcomes(5, 0.55, 12);
    ingest(&store, "base", &base, true).await;
    ingest(&store, "good", &good, true).await;
    ingest(&store, "bad", &bad, true).await;
    let v_few = ingest(&store, "few", &few, true).await;

    // Paired by key, per task at α/2 and pooled at α, equal to evalstats by hand.
    let c = store.compare(&CompareRequest::new("pol", arm("c1/base"), arm("c1/good"))).await.unwrap();
    assert_eq!((c.version, c.pairing.as_str(), c.outcome.as_str()), (v_few, "key:pair_key", "success label"));
    same(&c.pooled, &by_hand(&base, &good, None, 0.05, false));
    assert_eq!(c.tasks.iter().map(|t| t.task.clone().unwrap()).collect::<Vec<_>>(), ["push", "reach"]);
    same(&c.tasks[0], &by_hand(&base, &good, Some(0), 0.025, false));
    same(&c.tasks[1], &by_hand(&base, &good, Some(1), 0.025, false));
    assert_eq!((c.pooled.decision.as_str(), c.gate.as_str(), c.exit_code), ("better", "not_worse", 0));
    let t = c.pooled.pair_table.as_ref().unwrap();
    assert_eq!(t.both + t.only_a + t.only_b + t.neither, 240);
    assert!(c.pooled.decided_at_pairs.unwrap() < 240);
    let w = store.compare(&CompareRequest::new("pol", arm("c1/base"), arm("c1/bad"))).await.unwrap();
    assert_eq!((w.pooled.decision.as_str(), w.exit_code), ("worse", 1));
    // Unpaired (arrival order) pairs the same episodes here (keys follow the order), so the
    // answer is the same; progress scores are another outcome.
    let u = store
        .compare(&CompareRequest {
            pair_key: Some(String::new()),
            ..CompareRequest::new("pol", arm("c1/base"), arm("c1/good"))
        })
        .await
        .unwrap();
    assert_eq!(u.pairing, "arrival order");
    assert_eq!(u.pooled, c.pooled);
    let p = store
        .compare(&CompareRequest {
            progress: Some("progress".into()),
            ..CompareRequest::new("pol", arm("c1/base"), arm("c1/good"))
        })
        .await
        .unwrap();
    assert_eq!(p.outcome, "progress:progress");
    assert!(p.pooled.pair_table.is_none());
    same(&p.pooled, &by_hand(&base, &good, None, 0.05, true));
    // A margin: with δ = 0.5 the good run is "better" and the bad one is not worse by more than δ.
    let m = store
        .compare(&CompareRequest { margin: 0.5, ..CompareRequest::new("pol", arm("c1/base"), arm("c1/bad")) })
        .await
        .unwrap();
    assert_ne!(m.pooled.decision, "worse", "{:?}", m.pooled);

    // Bad requests are named and change nothing.
    for (req, want) in [
        (CompareRequest::new("pol", arm("c1/base"), arm("c1/base")), "both"),
        (
            CompareRequest { alpha: 1.5, ..CompareRequest::new("pol", arm("c1/base"), arm("c1/good")) },
            "alpha",
        ),
        (CompareRequest::new("pol", arm("c1/base"), arm("c1/nope")), "c1/nope"),
        (
            CompareRequest {
                version: Some(99),
                ..CompareRequest::new("pol", arm("c1/base"), arm("c1/good"))
            },
            "99",
        ),
    ] {
        let e = store.compare(&req).await.unwrap_err();
        assert!(e.to_string().contains(want), "{e}");
    }

    // The gated alias: a first move needs no evidence; protected, it refuses a worse target and
    // an undecided one, and accepts a better one with its evidence.
    let a = store
        .move_policy_alias(&MoveAlias {
            protect: Some(true),
            ..MoveAlias::new("pol", "prod", arm("c1/base"), "alice")
        })
        .await
        .unwrap();
    assert_eq!((a.target.as_str(), a.protected, a.evidence.is_none()), ("c1/base", true, true));
    for to in ["c1/bad", "c1/few"] {
        let e = store.move_policy_alias(&MoveAlias::new("pol", "prod", arm(to), "bob")).await.unwrap_err();
        assert!(matches!(e, StoreError::Conflict(_)), "{e}");
        assert!(e.to_string().contains(if to == "c1/bad" { "worse" } else { "undecided" }), "{e}");
        assert_eq!(store.policy_alias("pol", "prod").await.unwrap(), a, "a refused move changes nothing");
    }
    let e = store.move_policy_alias(&MoveAlias::new("pol", "prod", arm("c1/typo"), "bob")).await.unwrap_err();
    assert!(matches!(e, StoreError::NotFound { .. }), "{e}");
    let e = store
        .move_policy_alias(&MoveAlias {
            protect: Some(false),
            ..MoveAlias::new("pol", "prod", arm("c1/good"), "bob")
        })
        .await
        .unwrap_err();
    assert!(e.to_string().contains("protected"), "{e}");
    let moved =
        store.move_policy_alias(&MoveAlias::new("pol", "prod", arm("c1/good"), "carol")).await.unwrap();
    assert_eq!((moved.target.as_str(), moved.protected, moved.actor.as_str()), ("c1/good", true, "carol"));
    let ev = moved.evidence.clone().unwrap();
    assert_eq!(
        (ev.a.to_string(), ev.b.to_string(), ev.gate.as_str()),
        ("c1/base".into(), "c1/good".into(), "not_worse")
    );
    // The evidence reproduces: the same comparison at its version, after more data arrived.
    ingest(&store, "later", &outcomes(6, 0.5, 30), true).await;
    let again = store
        .compare(&CompareRequest {
            version: Some(ev.version),
            alpha: ev.alpha,
            margin: ev.margin,
            plan_effect: ev.plan_effect,
            ..CompareRequest::new("pol", ev.a.clone(), ev.b.clone())
        })
        .await
        .unwrap();
    // Equal to the last bits JSON keeps (serde_json's float parsing may differ in the last bit).
    close(&serde_json::to_value(&again).unwrap(), &serde_json::to_value(&ev).unwrap(), "evidence");
    let history = store.policy_alias_history("pol", "prod").await.unwrap();
    assert_eq!(history.len(), 2);
    assert_eq!(
        (history[0].from_target.as_deref(), history[1].from_target.as_deref()),
        (None, Some("c1/base"))
    );
    assert_eq!(history[1].evidence.as_ref(), Some(&ev));
    assert_eq!(store.policy_aliases("pol").await.unwrap(), vec![moved]);
}

/// JSON values equal, numbers within a relative 1e-12.
fn close(a: &serde_json::Value, b: &serde_json::Value, at: &str) {
    use serde_json::Value::*;
    match (a, b) {
        (Number(x), Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!((x - y).abs() <= 1e-12 * x.abs().max(y.abs()).max(1.0), "{at}: {x} vs {y}");
        }
        (Array(x), Array(y)) => {
            assert_eq!(x.len(), y.len(), "{at}");
            for (i, (x, y)) in x.iter().zip(y).enumerate() {
                close(x, y, &format!("{at}[{i}]"));
            }
        }
        (Object(x), Object(y)) => {
            assert_eq!(x.keys().collect::<Vec<_>>(), y.keys().collect::<Vec<_>>(), "{at}");
            for (k, v) in x {
                close(v, &y[k], &format!("{at}.{k}"));
            }
        }
        _ => assert_eq!(a, b, "{at}"),
    }
}

#[tokio::test]
async fn sqlite_compare_and_gate() {
    let dir = tempfile::tempdir().unwrap();
    compare_and_gate(test_support::open_test_store(Backend::Sqlite, dir.path(), "compare").await).await;
}

#[tokio::test]
async fn postgres_compare_and_gate() {
    if !test_support::require_postgres() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    compare_and_gate(test_support::open_test_store(Backend::Postgres, dir.path(), "compare").await).await;
}
