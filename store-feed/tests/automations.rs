//! What an automation decides, on both catalogs, with the jobs it queues run by hand: nothing below
//! the threshold (or with one class only), one `train` job when it is reached, none more while
//! that one is queued, another after a failure only for a label newer than its firing; a server
//! whose copy of the automation is stale, or that lost its lease, writes nothing (so an event
//! never fires twice); and a run's `scoreboard` job only once all its episodes are labeled.

use store::*;
use store_feed::*;
use store_jobs::*;

/// Ingests `n` unlabeled episodes of `pol/ckpt` (optionally as `run`); returns their ids.
async fn ingest(store: &Store, tag: &str, ckpt: &str, run: Option<RunInput>, n: u32) -> Vec<String> {
    let mut w = store.begin_ingest(test_support::source(tag), "pol", ckpt).await.unwrap();
    if let Some(r) = run {
        w.set_run(r).unwrap();
    }
    for i in 0..n {
        w.add_episode(test_support::two_step_episode(i, Some("reach"), Label::Unknown)).await.unwrap();
    }
    w.commit("automation test").await.unwrap();
    let f = EpisodeFilter { policy: Some("pol".into()), checkpoint: Some(ckpt.into()), ..Default::default() };
    let mut ids: Vec<String> = store.episodes(&f).await.unwrap().into_iter().map(|e| e.id).collect();
    ids.sort();
    ids
}

async fn label(store: &Store, id: &str, l: Label) {
    let update = LabelUpdate { episode_id: id.into(), label: l, expect_revision: None, note: None };
    store.set_label(update, "labeler", "human").await.unwrap();
}

/// What a server's loop does once: claims every automation due and advances each until the feed
/// has nothing more for it. Returns how many jobs were queued.
async fn step(store: &Store, owner: &str) -> i64 {
    let before: i64 = store.automations(None).await.unwrap().iter().map(|a| a.fired).sum();
    for mut a in store.claim_automations(owner, 60_000).await.unwrap() {
        while let Some(c) = store.advance_automation(&a, owner).await.unwrap() {
            if c == a.cursor_seq {
                break;
            }
            a.cursor_seq = c;
        }
        store.release_automation(&a.id, owner).await.unwrap();
    }
    store.automations(None).await.unwrap().iter().map(|a| a.fired).sum::<i64>() - before
}

async fn fired_jobs(store: &Store) -> Vec<JobRecord> {
    let mut jobs: Vec<JobRecord> = store
        .jobs(None)
        .await
        .unwrap()
        .into_iter()
        .filter(|j| j.created_by.starts_with("automation:"))
        .collect();
    jobs.sort_by(|a, b| a.created_at.cmp(&b.created_at).then(a.id.cmp(&b.id)));
    jobs
}

async fn fail_job(store: &Store, id: &str) {
    let j = store.claim_job("worker", 60_000).await.unwrap().expect("a queued job");
    assert_eq!(j.id, id);
    assert!(store.finish_job(id, "worker", j.attempts, Err("no good".into())).await.unwrap());
}

async fn decides(db: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let store = test_support::open_test_store(db, dir.path(), "automations").await;
    let ids = ingest(&store, "c1-rollouts", "c1", None, 8).await;
    for bad in [
        serde_json::json!({}),
        serde_json::json!({"min_labeled": 1}),
        serde_json::json!({"min_labeled": 4, "kind": "ranker"}),
        serde_json::json!({"min_labeled": 4, "val_fraction": 1.5}),
        serde_json::json!({"min_labeled": 4, "surprise": true}),
    ] {
        let e = store.create_automation("pol", AutomationRule::TrainOnLabels, &bad, "t").await.unwrap_err();
        assert!(matches!(e, StoreError::Invalid(_)), "{bad}: {e}");
    }
    let a = store
        .create_automation(
            "pol",
            AutomationRule::TrainOnLabels,
            &serde_json::json!({"min_labeled": 4, "chunk_len": 1}),
            "t",
        )
        .await
        .unwrap();
    assert_eq!(a.params["val_fraction"], 0.2, "defaults filled in: {}", a.params);
    // Declared on unlabeled episodes, then four labels of one class: nothing.
    assert_eq!(step(&store, "s1").await, 0);
    for id in &ids[..4] {
        label(&store, id, Label::Success).await;
    }
    assert_eq!(step(&store, "s1").await, 0, "one class only");
    // The threshold with both classes: one train job, its firing an event before the job's.
    label(&store, &ids[4], Label::Failure).await;
    assert_eq!(step(&store, "s1").await, 1);
    let jobs = fired_jobs(&store).await;
    assert_eq!(jobs.len(), 1);
    assert_eq!(jobs[0].kind, JobKind::Train);
    assert_eq!(jobs[0].spec["checkpoint"], "c1");
    assert_eq!(jobs[0].spec["freeze"]["val_fraction"], 0.2);
    assert_eq!(jobs[0].spec["chunk_len"], 1);
    let feed = store.events_after(0, 1000, &EventFilter::default()).await.unwrap().events;
    let fired = feed.iter().position(|e| e.kind == EventKind::AutomationFired).unwrap();
    assert_eq!(feed[fired].data["job_id"], jobs[0].id.as_str());
    assert_eq!(feed[fired + 1].kind, EventKind::JobChanged);
    assert_eq!(feed[fired + 1].subject, jobs[0].id);
    // It says why: the checkpoint's last change, and the job it queued for it.
    let seen = store.automation(&a.id).await.unwrap().targets;
    assert_eq!(seen.len(), 1, "{seen:?}");
    assert_eq!((seen[0].target.as_str(), seen[0].job_id.as_deref()), ("c1", Some(jobs[0].id.as_str())));
    assert!(
        seen[0].changed_seq > seen[0].covered_seq && seen[0].fired_seq >= seen[0].changed_seq,
        "{seen:?}"
    );
    // A label while it is queued: no second job.
    label(&store, &ids[5], Label::Failure).await;
    assert_eq!(step(&store, "s1").await, 0, "one job per checkpoint at a time");
    // It fails: the label that came after its firing fires the next one...
    fail_job(&store, &jobs[0].id).await;
    assert_eq!(step(&store, "s1").await, 1);
    let jobs = fired_jobs(&store).await;
    // ...and when that one fails too, nothing fires again until a newer label.
    fail_job(&store, &jobs[1].id).await;
    assert_eq!(step(&store, "s1").await, 0, "no retry loop on a failing recipe");
    label(&store, &ids[6], Label::Success).await;

    // A server whose copy of the automation is stale, or which does not hold its lease, writes
    // nothing: the label above fires exactly once.
    let held = store.claim_automations("s2", 60_000).await.unwrap();
    assert_eq!(held.len(), 1);
    assert!(store.claim_automations("s3", 60_000).await.unwrap().is_empty(), "leased to s2");
    assert_eq!(store.advance_automation(&held[0], "s3").await.unwrap(), None, "s3 holds no lease");
    let mut stale = held[0].clone();
    stale.cursor_seq -= 1;
    assert_eq!(store.advance_automation(&stale, "s2").await.unwrap(), None, "a stale cursor");
    assert_eq!(fired_jobs(&store).await.len(), 2);
    assert!(store.advance_automation(&held[0], "s2").await.unwrap().is_some());
    assert_eq!(store.advance_automation(&held[0], "s2").await.unwrap(), None, "the same page again");
    store.release_automation(&held[0].id, "s2").await.unwrap();
    assert_eq!(fired_jobs(&store).await.len(), 3);
    assert_eq!(step(&store, "s1").await, 0);

    store.cancel_job(&fired_jobs(&store).await[2].id).await.unwrap();
    store.delete_automation(&a.id, "t").await.unwrap();
    assert!(store.automations(None).await.unwrap().is_empty());

    // A run's scoreboard: fired once its last episode is labeled, and the job freezes a version
    // whose rows for the run say what was labeled.
    let run_ids =
        ingest(&store, "c2-steered", "c2", Some(RunInput::new("bon-4", Steering::Bon { n: 4 })), 3).await;
    let r = store
        .create_automation("pol", AutomationRule::ScoreboardOnRunLabeled, &serde_json::json!({}), "t")
        .await
        .unwrap();
    label(&store, &run_ids[0], Label::Success).await;
    label(&store, &run_ids[1], Label::Failure).await;
    assert_eq!(step(&store, "s1").await, 0, "one episode still unlabeled");
    label(&store, &run_ids[2], Label::Success).await;
    assert_eq!(step(&store, "s1").await, 1);
    let job = fired_jobs(&store).await.into_iter().find(|j| j.kind == JobKind::Scoreboard).unwrap();
    let out = store.run_scoreboard_job(&job.spec).await.unwrap();
    let rows = out["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 1, "{out}");
    assert_eq!((rows[0]["successes"].as_u64(), rows[0]["failures"].as_u64()), (Some(2), Some(1)), "{out}");
    assert_eq!(out["version"].as_i64().unwrap(), store.head_version().await.unwrap());
    // Relabeling while it is queued waits for it; after it, the change fires once more.
    label(&store, &run_ids[2], Label::Failure).await;
    assert_eq!(step(&store, "s1").await, 0, "its job is still queued");
    let j = store.claim_job("worker", 60_000).await.unwrap().unwrap();
    let j = if j.id == job.id { j } else { panic!("unexpected job {j:?}") };
    assert!(store.finish_job(&j.id, "worker", j.attempts, Ok(out)).await.unwrap());
    assert_eq!(step(&store, "s1").await, 1);

    // Retention deleted events it had not read: it goes on from the oldest left, no error loop.
    label(&store, &run_ids[0], Label::Failure).await;
    tokio::time::sleep(std::time::Duration::from_millis(5)).await;
    assert!(store.prune_events(std::time::Duration::ZERO).await.unwrap() > 0);
    let (head, pruned_through) = store.event_head().await.unwrap();
    assert!(store.automation(&r.id).await.unwrap().cursor_seq < pruned_through);
    assert_eq!(step(&store, "s1").await, 0);
    assert_eq!(store.automation(&r.id).await.unwrap().cursor_seq, pruned_through.max(head));
    store.delete_automation(&r.id, "t").await.unwrap();
}

#[tokio::test]
async fn automations_decide_on_sqlite() {
    decides(Backend::Sqlite).await;
}

#[tokio::test]
async fn automations_decide_on_postgres() {
    if !test_support::require_postgres() {
        return;
    }
    decides(Backend::Postgres).await;
}
