//! Runs and the scoreboard on both catalogs: ingests name their runs, the scoreboard's rows at a
//! version equal a count of that version's episodes done here by hand with `evalstats` (and its
//! frozen counts a `GROUP BY` over the version's labels), a later
//! label change shows only at the version that froze it, steered episodes stay out of splits, and
//! a run naming a missing artifact leaves the store unchanged.

use std::collections::BTreeMap;
use store::*;
use store_compare::*;

/// Ingests `n` episodes of `pol/ckpt` as `run`; episode i's label is `labels[i % len]`.
async fn ingest(
    store: &Store,
    tag: &str,
    ckpt: &str,
    run: Option<RunInput>,
    n: u32,
    labels: &[Label],
) -> Result<i64, StoreError> {
    let src = SourceInput {
        path: format!("/tmp/{tag}"),
        sha256: sha256_hex(tag.as_bytes()),
        format: "test".into(),
        size_bytes: 1,
        metadata: serde_json::json!({}),
    };
    let mut w = store.begin_ingest(src, "pol", ckpt).await?;
    if let Some(r) = run {
        w.set_run(r)?;
    }
    for i in 0..n {
        let task = if i % 7 == 0 { Some("push") } else { Some("reach") };
        w.add_episode(test_support::two_step_episode(i, task, labels[i as usize % labels.len()])).await?;
    }
    Ok(w.commit("scoreboard test").await?.version)
}

/// The scoreboard's rows against a count of the version's episodes made here.
async fn check_against_episodes(store: &Store, version: i64) {
    let sb = store
        .scoreboard(&ScoreboardRequest { policy: "pol".into(), version: Some(version), ..Default::default() })
        .await
        .unwrap();
    assert_eq!(sb.version, version);
    // The counts frozen with the version equal a GROUP BY over its labels.
    let req = ScoreboardRequest { policy: "pol".into(), ..Default::default() };
    assert_eq!(
        store.scoreboard_counts(&req, version).await.unwrap(),
        store.recount_scoreboard(&req, version).await.unwrap()
    );
    let eps = store
        .episodes(&EpisodeFilter { version: Some(version), policy: Some("pol".into()), ..Default::default() })
        .await
        .unwrap();
    let runs: BTreeMap<String, RunRecord> =
        store.runs(None).await.unwrap().into_iter().map(|r| (r.id.clone(), r)).collect();
    let mut want: BTreeMap<(String, Option<String>, String), [u64; 3]> = BTreeMap::new();
    for e in &eps {
        let name = e.run_id.as_ref().map_or("-".to_string(), |id| runs[id].name.clone());
        let c = want.entry((e.checkpoint.clone(), e.task.clone(), name)).or_default();
        c[match e.label {
            Label::Success => 0,
            Label::Failure => 1,
            Label::Unknown => 2,
        }] += 1;
    }
    assert_eq!(sb.rows.len(), want.len(), "{:#?}", sb.rows);
    for r in &sb.rows {
        let [s, f, u] = want[&(r.checkpoint.clone(), r.task.clone(), r.run_name.clone())];
        assert_eq!((r.successes, r.failures, r.unlabeled, r.episodes), (s, f, u, s + f + u), "{r:?}");
        assert_eq!(r.wilson_95, evalstats::wilson(s, s + f));
        assert_eq!(r.is_baseline, r.run_name == "base");
        match &r.baseline {
            None => assert!(
                r.is_baseline || !want.contains_key(&(r.checkpoint.clone(), r.task.clone(), "base".into()))
            ),
            Some(b) => {
                let [bs, bf, bu] = want[&(r.checkpoint.clone(), r.task.clone(), "base".to_string())];
                assert_eq!(b.run_name, "base");
                assert_eq!(b.newcombe_95, evalstats::newcombe_diff(s, s + f, bs, bs + bf));
                assert_eq!(b.separates, evalstats::separates(b.newcombe_95));
                assert_eq!(b.diff, s as f64 / (s + f) as f64 - bs as f64 / (bs + bf) as f64);
                let row = evalstats::Arm { successes: s, failures: f, unlabeled: u };
                let base = evalstats::Arm { successes: bs, failures: bf, unlabeled: bu };
                assert_eq!(b.unlabeled_to_flip, evalstats::unlabeled_to_flip(&row, &base));
            }
        }
    }
    // CSV: a header and one line per row.
    assert_eq!(sb.to_csv().lines().count(), sb.rows.len() + 1);
}

async fn runs_and_scoreboard(store: Store) {
    use Label::*;
    let base = RunInput::new("base", Steering::Base);
    let mut bon = RunInput::new("c-bon10", Steering::Bon { n: 10 });
    bon.tags = vec!["on-policy".into()];
    ingest(&store, "base", "c1", Some(base.clone()), 60, &[Success, Failure, Failure, Unknown])
        .await
        .unwrap();
    ingest(&store, "bon", "c1", Some(bon.clone()), 60, &[Success, Success, Success, Failure, Unknown])
        .await
        .unwrap();
    ingest(
        &store,
        "cg",
        "c1",
        Some(RunInput::new("c-cg3", Steering::Cg { lambda: 3.0 })),
        40,
        &[Success, Failure],
    )
    .await
    .unwrap();
    // Another checkpoint with its own base run, and episodes ingested without a run.
    ingest(&store, "c2-base", "c2", Some(base.clone()), 30, &[Failure, Success, Failure]).await.unwrap();
    let v = ingest(&store, "plain", "c2", None, 20, &[Success]).await.unwrap();
    // The same run again: its row is reused.
    ingest(&store, "bon-more", "c1", Some(bon.clone()), 10, &[Success]).await.unwrap();
    assert_eq!(store.runs(Some("c-bon10")).await.unwrap().len(), 1);
    let head = store.head_version().await.unwrap();
    check_against_episodes(&store, v).await;
    check_against_episodes(&store, head).await;

    // The bon row of c1/reach at head, by hand.
    let sb =
        store.scoreboard(&ScoreboardRequest { policy: "pol".into(), ..Default::default() }).await.unwrap();
    let row = sb
        .rows
        .iter()
        .find(|r| r.checkpoint == "c1" && r.task.as_deref() == Some("reach") && r.run_name == "c-bon10")
        .unwrap();
    let run = row.run.as_ref().unwrap();
    assert_eq!((run.steering, run.tags.clone()), (Steering::Bon { n: 10 }, vec!["on-policy".to_string()]));
    assert!(row.baseline.as_ref().unwrap().separates, "{row:?}");
    assert!(row.baseline.as_ref().unwrap().rollouts_to_separate.unwrap() <= 60);

    // A label change shows at the version that freezes it, not before.
    let ep = store
        .episodes(&EpisodeFilter {
            checkpoint: Some("c1".into()),
            task: Some("reach".into()),
            label: Some(Unknown),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_iter()
        .find(|e| e.run_id.as_deref() == Some(base.id().as_str()))
        .unwrap();
    store
        .set_label(
            LabelUpdate { episode_id: ep.id.clone(), label: Success, expect_revision: None, note: None },
            "t",
            "human",
        )
        .await
        .unwrap();
    let snap = store.snapshot_labels("t", "after a label").await.unwrap().version;
    let at = |v: i64| {
        let store = store.clone();
        async move {
            let sb = store
                .scoreboard(&ScoreboardRequest {
                    policy: "pol".into(),
                    version: Some(v),
                    ..Default::default()
                })
                .await
                .unwrap();
            let r = sb
                .rows
                .into_iter()
                .find(|r| r.checkpoint == "c1" && r.task.as_deref() == Some("reach") && r.run_name == "base")
                .unwrap();
            (r.successes, r.unlabeled)
        }
    };
    let (s0, u0) = at(head).await;
    assert_eq!(at(snap).await, (s0 + 1, u0 - 1));
    check_against_episodes(&store, snap).await;

    // Another baseline: every c2 row against c1's c-bon10 run.
    let sb = store
        .scoreboard(&ScoreboardRequest {
            policy: "pol".into(),
            baseline: Some("c-bon10".into()),
            baseline_checkpoint: Some("c1".into()),
            ..Default::default()
        })
        .await
        .unwrap();
    let c2 = sb
        .rows
        .iter()
        .find(|r| r.checkpoint == "c2" && r.task.as_deref() == Some("reach") && r.run_name == "-")
        .unwrap();
    assert_eq!(c2.baseline.as_ref().unwrap().checkpoint, "c1");
    assert_eq!(c2.baseline.as_ref().unwrap().run_name, "c-bon10");
    // The same, asking for c2 only: its rows, the baseline's rows, the same comparisons.
    let only = store
        .scoreboard(&ScoreboardRequest {
            policy: "pol".into(),
            checkpoint: Some("c2".into()),
            baseline: Some("c-bon10".into()),
            baseline_checkpoint: Some("c1".into()),
            ..Default::default()
        })
        .await
        .unwrap();
    let want: Vec<&ScoreboardRow> =
        sb.rows.iter().filter(|r| r.checkpoint == "c2" || r.is_baseline).collect();
    assert_eq!(only.rows.iter().collect::<Vec<_>>(), want);

    // Steered episodes stay out of splits: c1's split holds its base run's labeled episodes only.
    let split = store
        .create_split(&SplitRequest {
            policy: "pol".into(),
            checkpoint: "c1".into(),
            version: None,
            off_policy_from: vec![],
            val_fraction: 0.2,
            seed: 1,
            actor: "t".into(),
            max_episodes: None,
        })
        .await
        .unwrap();
    let labeled_base = store
        .episodes(&EpisodeFilter { checkpoint: Some("c1".into()), ..Default::default() })
        .await
        .unwrap()
        .into_iter()
        .filter(|e| e.run_id.as_deref() == Some(base.id().as_str()) && e.label != Unknown)
        .count() as i64;
    assert_eq!(split.train_episodes + split.val_episodes, labeled_base);

    // Hostile input: a run naming a missing artifact, an unknown policy, a missing version.
    let before = store.head_version().await.unwrap();
    let mut bad = RunInput::new("c-bon30", Steering::Bon { n: 30 });
    bad.artifact_id = Some("art-does-not-exist".into());
    let e = ingest(&store, "bad", "c1", Some(bad), 5, &[Success]).await.unwrap_err();
    assert!(e.to_string().contains("art-does-not-exist"), "{e}");
    assert_eq!(store.head_version().await.unwrap(), before);
    assert!(store.runs(Some("c-bon30")).await.unwrap().is_empty());
    let empty =
        store.scoreboard(&ScoreboardRequest { policy: "nobody".into(), ..Default::default() }).await.unwrap();
    assert!(empty.rows.is_empty());
    let e = store
        .scoreboard(&ScoreboardRequest { policy: "pol".into(), version: Some(999), ..Default::default() })
        .await
        .unwrap_err();
    assert!(e.to_string().contains("999"), "{e}");
}

#[tokio::test]
async fn sqlite_runs_and_scoreboard() {
    let dir = tempfile::tempdir().unwrap();
    runs_and_scoreboard(test_support::open_test_store(Backend::Sqlite, dir.path(), "scoreboard").await).await;
}

#[tokio::test]
async fn postgres_runs_and_scoreboard() {
    if !test_support::require_postgres() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    runs_and_scoreboard(test_support::open_test_store(Backend::Postgres, dir.path(), "scoreboard").await)
        .await;
}

/// Checkpoints and runs sort by their numbers' values, the baseline first in each checkpoint.
#[tokio::test]
async fn rows_sort_naturally() {
    let dir = tempfile::tempdir().unwrap();
    let store = test_support::open_test_store(Backend::Sqlite, dir.path(), "scoreboard").await;
    for ckpt in ["e1000", "e600"] {
        for (k, run) in ["bon16", "bon4", "base", "bon8"].into_iter().enumerate() {
            let steering = if run == "base" { Steering::Base } else { Steering::Bon { n: 4 } };
            let tag = format!("{ckpt}-{run}");
            ingest(&store, &tag, ckpt, Some(RunInput::new(run, steering)), 1 + k as u32, &[Label::Success])
                .await
                .unwrap();
        }
    }
    let req = ScoreboardRequest { policy: "pol".into(), task: Some("push".into()), ..Default::default() };
    let rows: Vec<(String, String)> =
        store.scoreboard(&req).await.unwrap().rows.into_iter().map(|r| (r.checkpoint, r.run_name)).collect();
    let want: Vec<(String, String)> = ["e600", "e1000"]
        .into_iter()
        .flat_map(|c| ["base", "bon4", "bon8", "bon16"].map(|r| (c.to_string(), r.to_string())))
        .collect();
    assert_eq!(rows, want);
}
