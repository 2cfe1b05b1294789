//! Two workers on one Postgres schema with 10 queued jobs: each job runs exactly once and never
//! twice at the same time; a worker killed mid-job (its task aborted: no more heartbeats) gets
//! its job retried by the other after the lease expires. Also: cancel and progress reporting.

use crate::common;
use store_jobs::{JobQueue, JobState};

use common::{Db, TestRunner};
use serde_json::json;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

const LEASE_MS: i64 = 500;

fn opts(id: &str) -> api::WorkerOptions {
    let mut o = api::WorkerOptions::new(id, LEASE_MS);
    o.poll_interval = Duration::from_millis(20);
    o
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn two_workers_on_postgres_run_each_job_once_and_retry_a_killed_workers_job() {
    if !store::test_support::require_postgres() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let store = common::open_store(Db::Postgres, dir.path()).await;
    let runner = TestRunner::new(100);
    let mut job_ids = Vec::new();
    for i in 0..10 {
        job_ids
            .push(store.create_job(store_jobs::JobKind::Score, &json!({"i": i}), "test").await.unwrap().id);
        // distinct created_at so the claim order is the creation order
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    // A second store handle = a second process's connection pool on the same schema.
    let url_store_b = store.clone();
    let wa = tokio::spawn(api::run_worker_with(
        store.clone(),
        runner.clone(),
        opts("worker-a"),
        std::future::pending(),
    ));
    let wb = tokio::spawn(api::run_worker_with(
        url_store_b,
        runner.clone(),
        opts("worker-b"),
        std::future::pending(),
    ));

    // Kill worker A in the middle of its third job.
    let t0 = Instant::now();
    let killed_job = loop {
        let started_by_a: Vec<_> =
            runner.runs.lock().unwrap().iter().filter(|r| r.worker == "worker-a").cloned().collect();
        if started_by_a.len() >= 3
            && started_by_a[2].end.is_none()
            && started_by_a[2].start.elapsed() > Duration::from_millis(30)
        {
            wa.abort();
            break started_by_a[2].job_id.clone();
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "worker A never reached its third job");
        tokio::time::sleep(Duration::from_millis(5)).await;
    };
    let killed_at = Instant::now();
    let _ = wa.await;

    // Wait until every job is done.
    let t0 = Instant::now();
    loop {
        let jobs = store.jobs(None).await.unwrap();
        if jobs.iter().all(|j| j.state == JobState::Succeeded) {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "jobs stuck: {:?}",
            jobs.iter().map(|j| (&j.id, j.state)).collect::<Vec<_>>()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    wb.abort();
    let _ = wb.await;

    let runs = runner.runs.lock().unwrap().clone();
    let mut by_job: HashMap<&str, Vec<&common::Run>> = HashMap::new();
    for r in &runs {
        by_job.entry(r.job_id.as_str()).or_default().push(r);
    }
    for id in &job_ids {
        let rs = &by_job[id.as_str()];
        let completed: Vec<_> = rs.iter().filter(|r| r.end.is_some()).collect();
        assert_eq!(completed.len(), 1, "job {id} completed {} times", completed.len());
        let job = store.job(id).await.unwrap();
        if id == &killed_job {
            assert_eq!(rs.len(), 2, "the killed job ran again");
            assert_eq!((rs[0].worker.as_str(), rs[1].worker.as_str()), ("worker-a", "worker-b"));
            assert!(rs[0].end.is_none());
            // Not twice at once: B started only after A was killed and its lease had run out.
            assert!(rs[1].start >= killed_at, "the retry started before the kill");
            assert_eq!(job.attempts, 2);
            assert_eq!(job.worker.as_deref(), Some("worker-b"));
        } else {
            assert_eq!(rs.len(), 1, "job {id} ran {} times", rs.len());
            assert_eq!(job.attempts, 1);
        }
    }
    let a_runs = runs.iter().filter(|r| r.worker == "worker-a").count();
    assert_eq!(a_runs, 3, "worker A stopped after the kill");
    assert!(runs.iter().filter(|r| r.worker == "worker-b").count() >= 7);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_stops_a_running_job_and_progress_is_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let store = common::open_store(Db::Sqlite, dir.path()).await;
    let runner = TestRunner::new(3_000);
    let job = store.create_job(store_jobs::JobKind::Score, &json!({}), "test").await.unwrap();
    let mut o = api::WorkerOptions::new("w", 300);
    o.poll_interval = Duration::from_millis(20);
    let w = tokio::spawn(api::run_worker_with(
        store.clone(),
        runner.clone() as Arc<dyn api::JobRunner>,
        o,
        std::future::pending(),
    ));
    // Progress arrives with the heartbeats.
    let t0 = Instant::now();
    loop {
        let j = store.job(&job.id).await.unwrap();
        if j.progress.get("epoch").is_some() {
            assert_eq!(j.state, JobState::Running);
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(5), "no progress recorded: {j:?}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    store.cancel_job(&job.id).await.unwrap();
    let t0 = Instant::now();
    loop {
        let j = store.job(&job.id).await.unwrap();
        if j.state == JobState::Cancelled {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(3), "not cancelled: {j:?}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(runner.runs.lock().unwrap()[0].end.is_none(), "the runner stopped early");
    w.abort();
}
