//! Two real `ufops worker` processes on one Postgres catalog with 10 queued training jobs (real
//! `train` jobs on a tiny split, run by the binary's job runner): every job succeeds exactly once,
//! and a worker killed with SIGKILL while it holds a running job gets that job retried by the
//! other worker — only after the dead worker's lease ran out. Everything is checked from the
//! catalog (jobs: state, attempts, worker, lease; artifacts: one per job, naming it) and from the
//! workers' own `job started` / `job finished` log lines.

use crate::common;
use common::*;
use serde_json::json;
use std::collections::HashMap;
use std::path::Path;
use std::process::{Child, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use store::{Store, StoreConfig};
use store_artifacts::Artifacts;
use store_jobs::{JobQueue, JobRecord, JobState};

const JOBS: usize = 10;
const LEASE_MS: i64 = 3000;
/// Epochs per training job: enough that a job runs for a few seconds (so there is time to kill
/// a worker in the middle of one), few enough that the test stays well under a minute.
const EPOCHS: u64 = 150;

fn now_ms() -> i64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_millis() as i64).unwrap_or(0)
}

/// A worker process, killed and reaped when dropped (a failing assertion leaves no process behind).
struct Worker(Child);

impl std::ops::Deref for Worker {
    type Target = Child;
    fn deref(&self) -> &Child {
        &self.0
    }
}

impl std::ops::DerefMut for Worker {
    fn deref_mut(&mut self) -> &mut Child {
        &mut self.0
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn spawn_worker(target: &Target, id: &str, log: &Path) -> Worker {
    let file = std::fs::File::create(log).unwrap();
    let child = target
        .command()
        .args(["worker", "--id", id, "--lease-ms", &LEASE_MS.to_string()])
        .env("UFOPS_LOG", "warn,api=info")
        .env("NO_COLOR", "1")
        .stdout(Stdio::null())
        .stderr(file)
        .spawn()
        .expect("start ufops worker");
    Worker(child)
}

/// `(event, job id, attempt)` of each `job started` / `job finished` line of a worker's log.
fn job_log(log: &Path) -> Vec<(String, String, Option<i64>)> {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let mut out = Vec::new();
    for line in text.lines() {
        let event = if line.contains("job started") {
            "started"
        } else if line.contains("job finished") {
            "finished"
        } else {
            continue;
        };
        let field = |name: &str| {
            line.split_whitespace()
                .find_map(|w| w.strip_prefix(name))
                .map(|v| v.trim_matches('"').to_string())
        };
        if let Some(job) = field("job=") {
            out.push((event.to_string(), job, field("attempt=").and_then(|a| a.parse().ok())));
        }
    }
    out
}

fn counts(log: &[(String, String, Option<i64>)], event: &str) -> HashMap<String, usize> {
    let mut m = HashMap::new();
    for (e, job, _) in log {
        if e == event {
            *m.entry(job.clone()).or_insert(0) += 1;
        }
    }
    m
}

fn epoch_of(job: &JobRecord) -> Option<u64> {
    job.progress.get("epoch").and_then(|e| e.as_u64())
}

#[test]
fn two_worker_processes_on_postgres_run_each_job_once_and_retry_a_killed_workers_job() {
    let dir = tempfile::tempdir().unwrap();
    let Some(target) = postgres_target(&dir.path().join("data")) else { return };
    target.ok(&["init"]);
    target.ok(&[
        "dev",
        "synth",
        "--seed",
        "7",
        "--episodes",
        "24",
        "--steps",
        "60",
        "--policy",
        "pol",
        "--checkpoint",
        "c1",
    ]);
    let split = target.json(&[
        "split",
        "create",
        "--policy",
        "pol",
        "--checkpoint",
        "c1",
        "--val-fraction",
        "0.25",
        "--json",
    ]);
    let split_id = split["id"].as_str().expect("split id").to_string();

    let rt = tokio::runtime::Runtime::new().unwrap();
    let store: Store = rt
        .block_on(Store::open(&StoreConfig {
            data_dir: target.data_dir.clone(),
            database_url: target.database_url.clone(),
            object_store_url: None,
        }))
        .unwrap();
    // Queue the jobs exactly as `POST /v1/jobs` does (a distinct seed each: distinct artifacts).
    let mut job_ids = Vec::new();
    for i in 0..JOBS {
        let spec = json!({
            "split_id": split_id, "kind": "classifier", "policy": "pol", "checkpoint": "c1", "chunk_len": 16,
            "config": {"epochs": EPOCHS, "batch_size": 64, "seed": i},
        });
        job_ids.push(rt.block_on(store.create_job(store_jobs::JobKind::Train, &spec, "test")).unwrap().id);
        std::thread::sleep(Duration::from_millis(3)); // distinct created_at: claims follow queue order
    }

    let (log_a, log_b) = (dir.path().join("worker-a.log"), dir.path().join("worker-b.log"));
    let mut a = spawn_worker(&target, "worker-a", &log_a);
    let mut b = spawn_worker(&target, "worker-b", &log_b);
    let jobs = |state: Option<JobState>| rt.block_on(store.jobs(state)).unwrap();

    // SIGKILL worker A while it holds a running job that is still early in its epochs, once it
    // has finished a job of its own (so both processes demonstrably ran jobs side by side).
    let t0 = Instant::now();
    let mut seen_running: HashMap<String, Instant> = HashMap::new();
    let (killed, lease_of_killed) = loop {
        let all = jobs(None);
        let a_done = all
            .iter()
            .filter(|j| j.state == JobState::Succeeded && j.worker.as_deref() == Some("worker-a"))
            .count();
        let held =
            all.iter().find(|j| j.state == JobState::Running && j.worker.as_deref() == Some("worker-a"));
        if let (Some(j), true) = (held, a_done >= 1) {
            let since = *seen_running.entry(j.id.clone()).or_insert_with(Instant::now);
            let early = epoch_of(j).is_none_or(|e| e < EPOCHS / 2);
            if since.elapsed() > Duration::from_millis(300) && early {
                a.kill().unwrap(); // SIGKILL: no cleanup, no more heartbeats
                a.wait().unwrap();
                // The job as the dead worker left it: still running, leased to A.
                let j = rt.block_on(store.job(&j.id)).unwrap();
                assert_eq!((j.state, j.worker.as_deref()), (JobState::Running, Some("worker-a")), "{j:?}");
                break (j.id.clone(), j.lease_until_ms.expect("a running job has a lease"));
            }
        }
        if t0.elapsed() > Duration::from_secs(180) {
            let _ = (a.kill(), b.kill());
            panic!("worker A never held a second running job early enough to be killed: {all:?}");
        }
        std::thread::sleep(Duration::from_millis(25));
    };

    // Wait for every job to finish; note when worker B is first seen holding the killed job.
    let t0 = Instant::now();
    let mut retried_at_ms: Option<i64> = None;
    loop {
        let all = jobs(None);
        if let Some(j) = all.iter().find(|j| j.id == killed) {
            if retried_at_ms.is_none() && j.worker.as_deref() == Some("worker-b") {
                retried_at_ms = Some(now_ms());
            }
        }
        if all.iter().all(|j| matches!(j.state, JobState::Succeeded | JobState::Failed | JobState::Cancelled))
        {
            break;
        }
        if t0.elapsed() > Duration::from_secs(300) {
            let _ = b.kill();
            panic!(
                "jobs did not finish: {:?}",
                all.iter().map(|j| (&j.id, j.state, &j.worker)).collect::<Vec<_>>()
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    b.kill().unwrap();
    b.wait().unwrap();

    // The catalog: every job succeeded; the killed one on its second attempt, by worker B, after
    // A's lease had expired; every other job on its first attempt.
    let all = jobs(None);
    assert_eq!(all.len(), JOBS);
    for j in &all {
        assert_eq!(j.state, JobState::Succeeded, "job {} did not succeed: {:?}", j.id, j.error);
        if j.id == killed {
            assert_eq!(j.attempts, 2, "the killed job ran again: {j:?}");
            assert_eq!(j.worker.as_deref(), Some("worker-b"), "{j:?}");
        } else {
            assert_eq!(j.attempts, 1, "job {} was claimed {} times", j.id, j.attempts);
        }
    }
    let retried_at_ms = retried_at_ms.expect("worker B was seen holding the killed job");
    assert!(
        retried_at_ms >= lease_of_killed,
        "worker B held the job at {retried_at_ms} ms, before A's lease ran out at {lease_of_killed} ms"
    );

    // One artifact per job, published by that job, and the job's result names it.
    let artifacts = rt.block_on(store.artifacts(Some("pol"), Some("c1"), None)).unwrap();
    assert_eq!(
        artifacts.len(),
        JOBS,
        "{:?}",
        artifacts.iter().map(|a| (&a.id, &a.job_id)).collect::<Vec<_>>()
    );
    let mut by_job: HashMap<&str, Vec<&str>> = HashMap::new();
    for art in &artifacts {
        by_job
            .entry(art.job_id.as_deref().expect("a job's artifact names its job"))
            .or_default()
            .push(&art.id);
    }
    for j in &all {
        let published = by_job.get(j.id.as_str()).cloned().unwrap_or_default();
        assert_eq!(published.len(), 1, "job {} published {} artifacts", j.id, published.len());
        let result = j.result.as_ref().expect("a succeeded job has a result");
        assert_eq!(result["artifact_id"].as_str(), Some(published[0]), "job {}: {result}", j.id);
    }

    // The workers' own logs: each job started once (the killed one twice: A, then B on attempt
    // 2) and finished exactly once; A never finished the job it was killed in.
    let (la, lb) = (job_log(&log_a), job_log(&log_b));
    let (started_a, started_b) = (counts(&la, "started"), counts(&lb, "started"));
    let (finished_a, finished_b) = (counts(&la, "finished"), counts(&lb, "finished"));
    for id in &job_ids {
        let s = (started_a.get(id).copied().unwrap_or(0), started_b.get(id).copied().unwrap_or(0));
        let f = (finished_a.get(id).copied().unwrap_or(0), finished_b.get(id).copied().unwrap_or(0));
        if id == &killed {
            assert_eq!((s, f), ((1, 1), (0, 1)), "killed job {id}: started (A, B) {s:?}, finished {f:?}");
            assert!(lb.iter().any(|(e, j, att)| e == "started" && j == id && *att == Some(2)), "{lb:?}");
        } else {
            assert_eq!(s.0 + s.1, 1, "job {id} started {s:?} times by (A, B)");
            assert_eq!(f, s, "job {id}: finished {f:?} != started {s:?}");
        }
    }
    let finished_by_a = all.iter().filter(|j| j.worker.as_deref() == Some("worker-a")).count();
    assert!(finished_by_a >= 1, "worker A finished no job before it was killed");
    assert_eq!(finished_by_a, finished_a.len(), "jobs the catalog credits to A != jobs A logged as finished");
    assert!(started_b.len() >= 2, "worker B ran only {} jobs", started_b.len());
    eprintln!(
        "killed worker A in job {killed}; A started {} jobs, B {}; B took the job over {} ms after A's lease ended",
        started_a.len(),
        started_b.len(),
        retried_at_ms - lease_of_killed
    );
}
