//! The job worker loop shared by `ufops serve` (in-process) and `ufops worker`: claim a job
//! (the store's claim/lease rules guarantee no job runs twice at once), run it with a heartbeat
//! that extends the lease and records progress, stop it when the lease is lost or a cancel is
//! requested, and record the outcome. A job whose worker died is claimed again after its lease
//! expires (up to the store's `max_attempts`).

use futures::future::BoxFuture;
use futures::FutureExt;
use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use store::Store;
use store_jobs::{JobQueue, JobRecord};

/// A worker's name, unique across machines and restarts: `ROLE-HOST-PID-RANDOM`. The process id
/// alone is not (every container's main process is PID 1, so all workers were `worker-1`), and
/// the job lease and its fencing are only as good as the names.
pub fn worker_identity(role: &str) -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| {
            h.trim()
                .chars()
                .filter(|c| c.is_ascii_alphanumeric() || *c == '-' || *c == '.')
                .collect::<String>()
        })
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "host".into());
    let random = &uuid::Uuid::new_v4().simple().to_string()[..8];
    format!("{role}-{host}-{}-{random}", std::process::id())
}

/// Does the work of a job. The binary implements training (trainer crate) and ingest (ingest
/// crate); tests implement fakes. Long, blocking work should poll [`JobContext::is_cancelled`].
pub trait JobRunner: Send + Sync + 'static {
    /// Runs `job` to completion: `Ok(result)` is stored as the job's result, `Err(message)` fails it.
    fn run<'a>(
        &'a self,
        store: &'a Store,
        job: &'a JobRecord,
        ctx: JobContext,
    ) -> BoxFuture<'a, Result<serde_json::Value, String>>;
}

/// What a running job sees: progress reporting (sent with the next heartbeat) and cancellation.
#[derive(Clone)]
pub struct JobContext {
    progress: Arc<Mutex<serde_json::Value>>,
    cancelled: Arc<AtomicBool>,
    notify: Arc<tokio::sync::Notify>,
    pub worker_id: String,
}

impl JobContext {
    fn new(worker_id: &str, progress: serde_json::Value) -> Self {
        JobContext {
            progress: Arc::new(Mutex::new(progress)),
            cancelled: Arc::new(AtomicBool::new(false)),
            notify: Arc::new(tokio::sync::Notify::new()),
            worker_id: worker_id.to_string(),
        }
    }

    /// Records the job's progress (e.g. `{"epoch": 3, "train_loss": 0.41, "val_loss": 0.44}`);
    /// it reaches the catalog with the next heartbeat.
    pub fn progress(&self, value: serde_json::Value) {
        *self.progress.lock().expect("progress lock") = value;
    }

    /// True once the job was cancelled or this worker lost its lease: stop as soon as possible.
    pub fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::SeqCst)
    }

    /// Resolves when the job is cancelled (or the lease lost).
    pub async fn cancelled(&self) {
        loop {
            let n = self.notify.notified();
            if self.is_cancelled() {
                return;
            }
            n.await;
        }
    }

    fn cancel(&self) {
        self.cancelled.store(true, Ordering::SeqCst);
        self.notify.notify_waiters();
    }

    fn current_progress(&self) -> serde_json::Value {
        self.progress.lock().expect("progress lock").clone()
    }
}

/// Tunables of [`run_worker_with`].
#[derive(Debug, Clone)]
pub struct WorkerOptions {
    pub worker_id: String,
    /// How long a claim lasts without a heartbeat; heartbeats come every `lease_ms / 3`.
    pub lease_ms: i64,
    /// How long to wait before looking for work again when the queue is empty.
    pub poll_interval: Duration,
    /// After a cancel, how long the runner gets to return by itself before it is dropped.
    pub cancel_grace: Duration,
}

impl WorkerOptions {
    pub fn new(worker_id: impl Into<String>, lease_ms: i64) -> Self {
        WorkerOptions {
            worker_id: worker_id.into(),
            lease_ms: lease_ms.max(30),
            poll_interval: Duration::from_millis(250),
            cancel_grace: Duration::from_secs(5),
        }
    }
}

/// The worker loop: runs jobs until `stop` resolves (a job in progress is interrupted and
/// released: queued again for another worker, or cancelled if a cancel was pending).
pub async fn run_worker(
    store: Store,
    runner: Arc<dyn JobRunner>,
    worker_id: impl Into<String>,
    lease_ms: i64,
    stop: impl Future<Output = ()> + Send,
) {
    run_worker_with(store, runner, WorkerOptions::new(worker_id, lease_ms), stop).await
}

/// [`run_worker`] with all options.
pub async fn run_worker_with(
    store: Store,
    runner: Arc<dyn JobRunner>,
    opts: WorkerOptions,
    stop: impl Future<Output = ()> + Send,
) {
    // The job being run, to give back when the worker is stopped in the middle of it.
    let current: Mutex<Option<(String, i64)>> = Mutex::new(None);
    let work = async {
        let mut backoff = opts.poll_interval;
        loop {
            match store.claim_job(&opts.worker_id, opts.lease_ms).await {
                Ok(Some(job)) => {
                    backoff = opts.poll_interval;
                    *current.lock().expect("current job") = Some((job.id.clone(), job.attempts));
                    run_one(&store, runner.as_ref(), &opts, job).await;
                    *current.lock().expect("current job") = None;
                }
                Ok(None) => tokio::time::sleep(opts.poll_interval).await,
                Err(e) => {
                    tracing::warn!(worker = %opts.worker_id, "cannot claim a job: {e}");
                    tokio::time::sleep(backoff).await;
                    backoff = (backoff * 2).min(Duration::from_secs(10));
                }
            }
        }
    };
    tokio::select! {
        _ = stop => {}
        _ = work => {}
    }
    // Stopped mid-job (SIGTERM, Ctrl-C): the runner was dropped with `work`. Give the job back
    // at once (queued again, this attempt not counted; cancelled if a cancel was pending) rather
    // than leaving it to look running until its lease runs out.
    let held = current.lock().expect("current job").take();
    if let Some((id, attempt)) = held {
        match store.release_job(&id, &opts.worker_id, attempt).await {
            Ok(true) => tracing::info!(worker = %opts.worker_id, job = %id, "job released at shutdown"),
            Ok(false) => {}
            Err(e) => {
                tracing::warn!(worker = %opts.worker_id, job = %id, "cannot release the job (its lease will expire): {e}")
            }
        }
    }
}

/// Runs one claimed job: the runner's future and the heartbeat run in this task (aborting the
/// task stops both, and the lease then expires).
pub(crate) async fn run_one(store: &Store, runner: &dyn JobRunner, opts: &WorkerOptions, job: JobRecord) {
    tracing::info!(worker = %opts.worker_id, job = %job.id, kind = %job.kind, attempt = job.attempts, "job started");
    let ctx = JobContext::new(&opts.worker_id, job.progress.clone());
    // Dropped with this future (the worker stopped mid-job): cancel the runner, so work it moved
    // to other threads (training runs in `spawn_blocking`) stops too and the process can exit.
    struct CancelOnDrop(JobContext);
    impl Drop for CancelOnDrop {
        fn drop(&mut self) {
            self.0.cancel();
        }
    }
    let _cancel_on_drop = CancelOnDrop(ctx.clone());
    let beat_every = Duration::from_millis((opts.lease_ms / 3).max(10) as u64);
    let heartbeat = {
        let ctx = ctx.clone();
        let job_id: &str = &job.id;
        let attempt = job.attempts;
        async move {
            let mut last_ok = Instant::now();
            loop {
                tokio::time::sleep(beat_every).await;
                match store
                    .heartbeat_job(job_id, &opts.worker_id, attempt, opts.lease_ms, &ctx.current_progress())
                    .await
                {
                    Ok(true) => last_ok = Instant::now(),
                    Ok(false) => {
                        // Either a cancel was requested (the job is still ours) or another
                        // worker holds it now (we must stop at once).
                        let ours = match store.job(job_id).await {
                            Ok(j) => {
                                j.worker.as_deref() == Some(opts.worker_id.as_str())
                                    && j.attempts == attempt
                                    && j.state == store_jobs::JobState::Running
                            }
                            Err(_) => false,
                        };
                        return if ours {
                            Stop::Cancelled
                        } else {
                            Stop::LeaseLost("the lease was lost to another worker")
                        };
                    }
                    Err(e) => {
                        tracing::warn!(job = %job_id, "heartbeat failed: {e}");
                        // Stop before the lease can run out under us: another worker may take it.
                        if last_ok.elapsed() + beat_every >= Duration::from_millis(opts.lease_ms as u64) {
                            return Stop::LeaseLost("heartbeats failed for the whole lease");
                        }
                    }
                }
            }
        }
    };
    let run = runner.run(store, &job, ctx.clone()).fuse();
    let heartbeat = heartbeat.fuse();
    futures::pin_mut!(run, heartbeat);
    let outcome = futures::select! {
        r = run => r,
        stop = heartbeat => {
            ctx.cancel();
            match stop {
                Stop::LeaseLost(why) => Err(format!("stopped: {why}")),
                Stop::Cancelled => {
                    // Let the runner wind down by itself briefly (it may be writing files).
                    let grace = tokio::time::sleep(opts.cancel_grace).fuse();
                    futures::pin_mut!(grace);
                    futures::select! {
                        r = run => r,
                        _ = grace => Err("cancelled".to_string()),
                    }
                }
            }
        }
    };
    let ok = outcome.is_ok();
    match store.finish_job(&job.id, &opts.worker_id, job.attempts, outcome).await {
        Ok(true) => {
            tracing::info!(worker = %opts.worker_id, job = %job.id, ok, "job finished");
            if job.kind == store_jobs::JobKind::Ingest {
                crate::upload::remove_upload(&job.spec).await; // finished: nobody will ingest it again
            }
        }
        Ok(false) => {
            tracing::warn!(worker = %opts.worker_id, job = %job.id, "job no longer ours; outcome dropped")
        }
        Err(e) => tracing::error!(worker = %opts.worker_id, job = %job.id, "cannot record the outcome: {e}"),
    }
}

enum Stop {
    Cancelled,
    LeaseLost(&'static str),
}

#[cfg(test)]
mod tests {
    #[test]
    fn worker_identities_are_unique_and_say_where_they_run() {
        let (a, b) = (super::worker_identity("worker"), super::worker_identity("worker"));
        assert_ne!(a, b, "two workers of one process (or two PID-1 containers) get different names");
        assert!(a.starts_with("worker-") && a.contains(&format!("-{}-", std::process::id())), "{a}");
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
        assert!(a.contains(host.trim()), "{a} names the host {host}");
    }
}
