//! Jobs (training, ingest, export, scoring) as catalog rows that workers claim with a lease: queued → running →
//! succeeded | failed | cancelled. A job whose worker stops heartbeating is claimed again (up to
//! `max_attempts`); no job runs twice at once. Postgres claims with `FOR UPDATE SKIP LOCKED`.

use serde::Serialize;
use std::future::Future;
use store::sql::RowExt;
use store::sql::{now_ms, now_rfc3339};
use store::Backend;
use store::{EventKind, NewEvent};
use store::{Store, StoreError};

/// What a job does; its spec's type follows from it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum JobKind {
    /// Train a verifier on a split (`trainer::TrainJobSpec`).
    Train,
    /// Ingest an uploaded source file.
    Ingest,
    /// Write an export of a selection of episodes.
    Export,
    /// Score episodes with a verifier for the review queue.
    Score,
    /// Freeze the labels into a version and compute a run's scoreboard rows
    /// (`store_feed::Automations::run_scoreboard_job`; queued by an automation).
    Scoreboard,
}

impl JobKind {
    pub fn as_str(self) -> &'static str {
        match self {
            JobKind::Train => "train",
            JobKind::Ingest => "ingest",
            JobKind::Export => "export",
            JobKind::Score => "score",
            JobKind::Scoreboard => "scoreboard",
        }
    }

    fn parse(s: &str) -> Result<Self, StoreError> {
        Ok(match s {
            "train" => JobKind::Train,
            "ingest" => JobKind::Ingest,
            "export" => JobKind::Export,
            "score" => JobKind::Score,
            "scoreboard" => JobKind::Scoreboard,
            _ => return Err(StoreError::Corrupt(format!("unknown job kind {s:?}"))),
        })
    }
}

impl std::fmt::Display for JobKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }
    fn parse(s: &str) -> Result<Self, StoreError> {
        Ok(match s {
            "queued" => JobState::Queued,
            "running" => JobState::Running,
            "succeeded" => JobState::Succeeded,
            "failed" => JobState::Failed,
            "cancelled" => JobState::Cancelled,
            _ => return Err(StoreError::Corrupt(format!("unknown job state {s:?}"))),
        })
    }
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize)]
pub struct JobRecord {
    pub id: String,
    pub kind: JobKind,
    pub state: JobState,
    pub spec: serde_json::Value,
    pub progress: serde_json::Value,
    pub result: Option<serde_json::Value>,
    pub error: Option<String>,
    pub attempts: i64,
    pub max_attempts: i64,
    pub worker: Option<String>,
    pub lease_until_ms: Option<i64>,
    pub cancel_requested: bool,
    pub created_by: String,
    pub created_at: String,
    pub updated_at: String,
}

/// Cancels running jobs whose cancel was requested (callers add the lease condition on `$2`).
const CANCEL_ORPHANS: &str = "UPDATE jobs SET state = 'cancelled', \
    error = COALESCE(error, 'cancelled; its worker stopped before it could finish'), lease_until_ms = NULL, \
    updated_at = $1 WHERE state = 'running' AND cancel_requested = 1";

const JOB_COLS: &str = "id, kind, state, spec, progress, result, error, attempts, max_attempts, worker, \
    lease_until_ms, cancel_requested, created_by, created_at, updated_at";

fn job_from_row(r: &sqlx::any::AnyRow) -> Result<JobRecord, StoreError> {
    Ok(JobRecord {
        id: r.s("id")?,
        kind: JobKind::parse(&r.s("kind")?)?,
        state: JobState::parse(&r.s("state")?)?,
        spec: serde_json::from_str(&r.s("spec")?)?,
        progress: serde_json::from_str(&r.s("progress")?)?,
        result: r.os("result")?.map(|s| serde_json::from_str(&s)).transpose()?,
        error: r.os("error")?,
        attempts: r.i("attempts")?,
        max_attempts: r.i("max_attempts")?,
        worker: r.os("worker")?,
        lease_until_ms: r.oi("lease_until_ms")?,
        cancel_requested: r.i("cancel_requested")? != 0,
        created_by: r.s("created_by")?,
        created_at: r.s("created_at")?,
        updated_at: r.s("updated_at")?,
    })
}

/// The feed's events of jobs whose rows a statement returned: `job.changed`, and
/// `export.finished` for an export that succeeded.
fn job_events(rows: &[sqlx::any::AnyRow]) -> Result<Vec<NewEvent>, StoreError> {
    let mut out = Vec::with_capacity(rows.len());
    for r in rows {
        let job = job_from_row(r)?;
        let text = |k: &str| job.spec.get(k).and_then(|v| v.as_str()).map(str::to_string);
        let (policy, checkpoint) = (text("policy"), text("checkpoint"));
        let scope = |e: NewEvent| match &policy {
            Some(p) => e.of(p, checkpoint.as_deref()),
            None => e,
        };
        out.push(scope(NewEvent::new(
            EventKind::JobChanged,
            job.id.clone(),
            serde_json::json!({
                "kind": job.kind,
                "state": job.state,
                "attempts": job.attempts,
                "worker": job.worker,
                "error": job.error,
                "result": job.result,
                "created_by": job.created_by,
            }),
        )));
        if job.kind == JobKind::Export && job.state == JobState::Succeeded {
            out.push(scope(NewEvent::new(
                EventKind::ExportFinished,
                job.id.clone(),
                serde_json::json!({"result": job.result, "files_prefix": format!("{}/{}/", store::EXPORTS_PREFIX, job.id)}),
            )));
        }
    }
    Ok(out)
}

/// Queues a job inside `tx`: its id and the events the transaction must append.
pub async fn insert_job(
    tx: &mut store::sql::Tx,
    kind: JobKind,
    spec: &serde_json::Value,
    actor: &str,
) -> Result<(String, Vec<NewEvent>), StoreError> {
    let id = format!("job-{}", &uuid::Uuid::new_v4().simple().to_string()[..12]);
    let now = now_rfc3339();
    let row = sqlx::query(&format!(
        "INSERT INTO jobs ({JOB_COLS}) VALUES ($1, $2, 'queued', $3, '{{}}', NULL, NULL, 0, 3, NULL, NULL, 0, $4, $5, $5) \
         RETURNING {JOB_COLS}"
    ))
    .bind(&id)
    .bind(kind.as_str())
    .bind(serde_json::to_string(spec)?)
    .bind(actor)
    .bind(&now)
    .fetch_one(&mut **tx)
    .await?;
    let events = job_events(&[row])?;
    Ok((id, events))
}

/// The job queue's operations on a [`Store`]: queue, claim with a lease, heartbeat, finish,
/// release and cancel. Every change commits with its `job.changed` event.
pub trait JobQueue {
    fn create_job(
        &self,
        kind: JobKind,
        spec: &serde_json::Value,
        actor: &str,
    ) -> impl Future<Output = Result<JobRecord, StoreError>> + Send;

    fn job(&self, id: &str) -> impl Future<Output = Result<JobRecord, StoreError>> + Send;

    fn jobs(
        &self,
        state: Option<JobState>,
    ) -> impl Future<Output = Result<Vec<JobRecord>, StoreError>> + Send;

    /// Claims the oldest runnable job (queued, or running with an expired lease) for `worker`.
    fn claim_job(
        &self,
        worker: &str,
        lease_ms: i64,
    ) -> impl Future<Output = Result<Option<JobRecord>, StoreError>> + Send;

    /// Extends the lease and records progress. Returns `false` when the worker no longer owns
    /// the job (lease lost, or a later attempt holds it) or a cancel was requested: the worker
    /// must stop. `attempt` is the claim's `attempts`: it fences a stale runner of the same
    /// worker that re-claimed the job after its own lease expired.
    fn heartbeat_job(
        &self,
        id: &str,
        worker: &str,
        attempt: i64,
        lease_ms: i64,
        progress: &serde_json::Value,
    ) -> impl Future<Output = Result<bool, StoreError>> + Send;

    /// Ends a job the worker owns (this `attempt` of it): succeeded with a result, or
    /// failed/cancelled with an error. Returns `false` when the job is no longer this attempt's.
    fn finish_job(
        &self,
        id: &str,
        worker: &str,
        attempt: i64,
        outcome: Result<serde_json::Value, String>,
    ) -> impl Future<Output = Result<bool, StoreError>> + Send;

    /// Gives back a job this attempt holds, when its worker stops before finishing it: queued
    /// again without counting the attempt (a graceful restart is not a failure), or cancelled
    /// if a cancel was requested. Returns `false` when the job was no longer this attempt's.
    fn release_job(
        &self,
        id: &str,
        worker: &str,
        attempt: i64,
    ) -> impl Future<Output = Result<bool, StoreError>> + Send;

    /// Requests cancellation: a queued job is cancelled at once, a running one at its next heartbeat.
    fn cancel_job(&self, id: &str) -> impl Future<Output = Result<JobRecord, StoreError>> + Send;
}

impl JobQueue for Store {
    async fn create_job(
        &self,
        kind: JobKind,
        spec: &serde_json::Value,
        actor: &str,
    ) -> Result<JobRecord, StoreError> {
        let mut tx = self.catalog().begin_write().await?;
        let (id, events) = insert_job(&mut tx, kind, spec, actor).await?;
        self.commit_with_events(tx, &events).await?;
        self.job(&id).await
    }

    async fn job(&self, id: &str) -> Result<JobRecord, StoreError> {
        let row = sqlx::query(&format!("SELECT {JOB_COLS} FROM jobs WHERE id = $1"))
            .bind(id)
            .fetch_optional(&self.catalog().pool)
            .await?
            .ok_or_else(|| StoreError::not_found("job", id))?;
        job_from_row(&row)
    }

    async fn jobs(&self, state: Option<JobState>) -> Result<Vec<JobRecord>, StoreError> {
        let rows = sqlx::query(&format!(
            "SELECT {JOB_COLS} FROM jobs WHERE ($1 = '' OR state = $1) ORDER BY created_at, id"
        ))
        .bind(state.map(|s| s.as_str()).unwrap_or(""))
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter().map(job_from_row).collect()
    }

    async fn claim_job(&self, worker: &str, lease_ms: i64) -> Result<Option<JobRecord>, StoreError> {
        let now = now_ms();
        let mut tx = self.catalog().begin_write().await?;
        // A cancelled job whose worker died (lease expired) is cancelled now, not left running.
        let mut ended =
            sqlx::query(&format!("{CANCEL_ORPHANS} AND lease_until_ms < $2 RETURNING {JOB_COLS}"))
                .bind(now_rfc3339())
                .bind(now)
                .fetch_all(&mut *tx)
                .await?;
        // Jobs whose lease ran out too often are failed for good.
        ended.extend(
            sqlx::query(&format!(
                "UPDATE jobs SET state = 'failed', error = 'worker lost too many times (lease expired)', updated_at = $1 \
                 WHERE state = 'running' AND lease_until_ms < $2 AND attempts >= max_attempts RETURNING {JOB_COLS}"
            ))
            .bind(now_rfc3339())
            .bind(now)
            .fetch_all(&mut *tx)
            .await?,
        );
        let mut events = job_events(&ended)?;
        let lock = if self.backend() == Backend::Postgres { " FOR UPDATE SKIP LOCKED" } else { "" };
        let row = sqlx::query(&format!(
            "SELECT id FROM jobs WHERE (state = 'queued' OR (state = 'running' AND lease_until_ms < $1)) \
             AND cancel_requested = 0 ORDER BY created_at, id LIMIT 1{lock}"
        ))
        .bind(now)
        .fetch_optional(&mut *tx)
        .await?;
        let Some(row) = row else {
            self.commit_with_events(tx, &events).await?;
            return Ok(None);
        };
        let id = row.s("id")?;
        let claimed = sqlx::query(&format!(
            "UPDATE jobs SET state = 'running', worker = $1, lease_until_ms = $2, attempts = attempts + 1, \
             updated_at = $3 WHERE id = $4 RETURNING {JOB_COLS}"
        ))
        .bind(worker)
        .bind(now + lease_ms)
        .bind(now_rfc3339())
        .bind(&id)
        .fetch_one(&mut *tx)
        .await?;
        events.extend(job_events(&[claimed])?);
        self.commit_with_events(tx, &events).await?;
        Ok(Some(self.job(&id).await?))
    }

    async fn heartbeat_job(
        &self,
        id: &str,
        worker: &str,
        attempt: i64,
        lease_ms: i64,
        progress: &serde_json::Value,
    ) -> Result<bool, StoreError> {
        let r = sqlx::query(
            "UPDATE jobs SET lease_until_ms = $1, progress = $2, updated_at = $3 \
             WHERE id = $4 AND worker = $5 AND attempts = $6 AND state = 'running' AND cancel_requested = 0",
        )
        .bind(now_ms() + lease_ms)
        .bind(serde_json::to_string(progress)?)
        .bind(now_rfc3339())
        .bind(id)
        .bind(worker)
        .bind(attempt)
        .execute(&self.catalog().pool)
        .await?;
        Ok(r.rows_affected() == 1)
    }

    async fn finish_job(
        &self,
        id: &str,
        worker: &str,
        attempt: i64,
        outcome: Result<serde_json::Value, String>,
    ) -> Result<bool, StoreError> {
        let (state, result, error) = match outcome {
            Ok(v) => ("succeeded", Some(serde_json::to_string(&v)?), None),
            Err(e) => ("failed", None, Some(e)),
        };
        let mut tx = self.catalog().begin_write().await?;
        let rows = sqlx::query(&format!(
            "UPDATE jobs SET state = CASE WHEN cancel_requested = 1 AND CAST($1 AS TEXT) = 'failed' THEN 'cancelled' ELSE CAST($1 AS TEXT) END, \
             result = $2, error = $3, lease_until_ms = NULL, updated_at = $4 \
             WHERE id = $5 AND worker = $6 AND attempts = $7 AND state = 'running' RETURNING {JOB_COLS}"
        ))
        .bind(state)
        .bind(result)
        .bind(error)
        .bind(now_rfc3339())
        .bind(id)
        .bind(worker)
        .bind(attempt)
        .fetch_all(&mut *tx)
        .await?;
        let events = job_events(&rows)?;
        self.commit_with_events(tx, &events).await?;
        Ok(rows.len() == 1)
    }

    async fn release_job(&self, id: &str, worker: &str, attempt: i64) -> Result<bool, StoreError> {
        let mut tx = self.catalog().begin_write().await?;
        let rows = sqlx::query(&format!(
            "UPDATE jobs SET state = CASE WHEN cancel_requested = 1 THEN 'cancelled' ELSE 'queued' END, \
             attempts = CASE WHEN cancel_requested = 1 THEN attempts ELSE attempts - 1 END, \
             worker = NULL, lease_until_ms = NULL, updated_at = $1 \
             WHERE id = $2 AND worker = $3 AND attempts = $4 AND state = 'running' RETURNING {JOB_COLS}"
        ))
        .bind(now_rfc3339())
        .bind(id)
        .bind(worker)
        .bind(attempt)
        .fetch_all(&mut *tx)
        .await?;
        let events = job_events(&rows)?;
        self.commit_with_events(tx, &events).await?;
        Ok(rows.len() == 1)
    }

    async fn cancel_job(&self, id: &str) -> Result<JobRecord, StoreError> {
        let now = now_rfc3339();
        let mut tx = self.catalog().begin_write().await?;
        let mut rows = sqlx::query(&format!(
            "UPDATE jobs SET state = 'cancelled', cancel_requested = 1, updated_at = $1 WHERE id = $2 AND state = 'queued' \
             RETURNING {JOB_COLS}"
        ))
        .bind(&now)
        .bind(id)
        .fetch_all(&mut *tx)
        .await?;
        sqlx::query(
            "UPDATE jobs SET cancel_requested = 1, updated_at = $1 WHERE id = $2 AND state = 'running'",
        )
        .bind(&now)
        .bind(id)
        .execute(&mut *tx)
        .await?;
        // Its worker already gone (lease expired): nobody will see the request, so finish it here.
        rows.extend(
            sqlx::query(&format!(
                "{CANCEL_ORPHANS} AND lease_until_ms < $2 AND id = $3 RETURNING {JOB_COLS}"
            ))
            .bind(&now)
            .bind(now_ms())
            .bind(id)
            .fetch_all(&mut *tx)
            .await?,
        );
        let events = job_events(&rows)?;
        self.commit_with_events(tx, &events).await?;
        self.job(id).await
    }
}
