//! Failure monitors: immutable records of a threshold calibrated on a verifier artifact's scores
//! (id = the first 16 hex digits of sha256 of the record's JSON), with what the calibration
//! measured on held-out episodes and per-checkpoint aliases (`latest` moves on every put). The
//! record's meaning is the verifier core's (`verifier::monitor`); the store keeps it as JSON and
//! checks only what it indexes.

use crate::Artifacts;
use serde::Serialize;
use std::future::Future;
use store::sql::{now_rfc3339, RowExt, Tx};
use store::{sha256_hex, EventKind, NewEvent, Store, StoreError};

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct MonitorEntry {
    pub id: String,
    pub policy: String,
    pub checkpoint: String,
    pub artifact_id: String,
    pub alpha: f64,
    pub threshold: f64,
    /// The monitor record (`verifier::monitor::MonitorRecord`).
    #[cfg_attr(feature = "openapi", schema(value_type = Object))]
    pub record: serde_json::Value,
    /// The calibration's measurement on held-out episodes (false-alarm rate, detection, lead time).
    #[cfg_attr(feature = "openapi", schema(value_type = Option<Object>))]
    pub evaluation: Option<serde_json::Value>,
    pub aliases: Vec<String>,
    pub created_by: String,
    pub created_at: String,
}

/// A monitor to record: the record's exact JSON bytes (its id is their hash) and what the store
/// indexes of it.
pub struct NewMonitor<'a> {
    pub record_json: &'a [u8],
    pub policy: &'a str,
    pub checkpoint: &'a str,
    pub artifact_id: &'a str,
    pub alpha: f64,
    pub threshold: f64,
    pub evaluation: Option<&'a serde_json::Value>,
    pub created_by: &'a str,
}

const MON_COLS: &str =
    "id, policy, checkpoint, artifact_id, alpha, threshold, record, evaluation, created_by, created_at";

/// Failure monitors on a [`Store`]: calibrated thresholds of an artifact, with per-checkpoint
/// aliases.
pub trait Monitors {
    /// Records a monitor (idempotent: the same record is the same monitor) and moves the
    /// checkpoint's `latest` monitor alias to it. The artifact must be in the store and belong to
    /// the same policy and checkpoint.
    fn put_monitor(
        &self,
        new: NewMonitor<'_>,
    ) -> impl Future<Output = Result<MonitorEntry, StoreError>> + Send;

    fn monitor(&self, id: &str) -> impl Future<Output = Result<MonitorEntry, StoreError>> + Send;

    /// Monitors, oldest first, narrowed by policy, checkpoint and artifact (empty = any).
    fn monitors(
        &self,
        policy: Option<&str>,
        checkpoint: Option<&str>,
        artifact_id: Option<&str>,
    ) -> impl Future<Output = Result<Vec<MonitorEntry>, StoreError>> + Send;

    /// The newest monitor calibrated for `artifact_id`, if any (what the scoreboard shows).
    fn latest_monitor(
        &self,
        artifact_id: &str,
    ) -> impl Future<Output = Result<Option<MonitorEntry>, StoreError>> + Send;

    /// Points `alias` of the monitor's (policy, checkpoint) at it.
    fn set_monitor_alias(
        &self,
        alias: &str,
        id: &str,
    ) -> impl Future<Output = Result<MonitorEntry, StoreError>> + Send;

    /// Resolves a monitor reference: an id, or `POLICY/CHECKPOINT@ALIAS`.
    fn resolve_monitor(
        &self,
        reference: &str,
    ) -> impl Future<Output = Result<MonitorEntry, StoreError>> + Send;
}

impl Monitors for Store {
    async fn put_monitor(&self, new: NewMonitor<'_>) -> Result<MonitorEntry, StoreError> {
        let record: serde_json::Value = serde_json::from_slice(new.record_json)
            .map_err(|e| StoreError::invalid(format!("monitor record is not JSON: {e}")))?;
        for (field, want) in
            [("artifact_id", new.artifact_id), ("policy", new.policy), ("checkpoint", new.checkpoint)]
        {
            if record.get(field).and_then(|v| v.as_str()) != Some(want) {
                return Err(StoreError::invalid(format!("monitor record's {field} is not {want:?}")));
            }
        }
        if !(new.alpha > 0.0 && new.alpha < 1.0 && new.threshold.is_finite()) {
            return Err(StoreError::invalid("monitor alpha must be in (0, 1) and its threshold finite"));
        }
        let artifact = self.artifact(new.artifact_id).await?;
        if artifact.policy != new.policy || artifact.checkpoint != new.checkpoint {
            return Err(StoreError::invalid(format!(
                "artifact {} belongs to {}/{}, not {}/{}",
                artifact.id, artifact.policy, artifact.checkpoint, new.policy, new.checkpoint
            )));
        }
        let id = sha256_hex(new.record_json)[..16].to_string();
        let now = now_rfc3339();
        let mut tx = self.catalog().begin_write().await?;
        let inserted = sqlx::query(&format!(
            "INSERT INTO monitors ({MON_COLS}) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10) ON CONFLICT DO NOTHING"
        ))
        .bind(&id)
        .bind(new.policy)
        .bind(new.checkpoint)
        .bind(new.artifact_id)
        .bind(new.alpha)
        .bind(new.threshold)
        .bind(String::from_utf8_lossy(new.record_json).into_owned())
        .bind(new.evaluation.map(|e| e.to_string()))
        .bind(new.created_by)
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        upsert_monitor_alias(&mut tx, new.policy, new.checkpoint, "latest", &id, &now).await?;
        let mut events = Vec::new();
        if inserted.rows_affected() == 1 {
            events.push(
                NewEvent::new(
                    EventKind::MonitorCreated,
                    id.clone(),
                    serde_json::json!({"artifact_id": new.artifact_id, "alpha": new.alpha, "threshold": new.threshold}),
                )
                .of(new.policy, Some(new.checkpoint)),
            );
        }
        events.push(monitor_alias_moved(new.policy, new.checkpoint, "latest", &id));
        self.commit_with_events(tx, &events).await?;
        self.monitor(&id).await
    }

    async fn monitor(&self, id: &str) -> Result<MonitorEntry, StoreError> {
        let row = sqlx::query(&format!("SELECT {MON_COLS} FROM monitors WHERE id = $1"))
            .bind(id)
            .fetch_optional(&self.catalog().pool)
            .await?
            .ok_or_else(|| StoreError::not_found("monitor", id))?;
        let mut m = monitor_from_row(&row)?;
        m.aliases = monitor_aliases_of(self, id).await?;
        Ok(m)
    }

    async fn monitors(
        &self,
        policy: Option<&str>,
        checkpoint: Option<&str>,
        artifact_id: Option<&str>,
    ) -> Result<Vec<MonitorEntry>, StoreError> {
        let rows = sqlx::query(&format!(
            "SELECT {MON_COLS} FROM monitors WHERE ($1 = '' OR policy = $1) AND ($2 = '' OR checkpoint = $2) \
             AND ($3 = '' OR artifact_id = $3) ORDER BY created_at, id"
        ))
        .bind(policy.unwrap_or(""))
        .bind(checkpoint.unwrap_or(""))
        .bind(artifact_id.unwrap_or(""))
        .fetch_all(&self.catalog().pool)
        .await?;
        let mut out = Vec::with_capacity(rows.len());
        for r in &rows {
            let mut m = monitor_from_row(r)?;
            m.aliases = monitor_aliases_of(self, &m.id).await?;
            out.push(m);
        }
        Ok(out)
    }

    async fn latest_monitor(&self, artifact_id: &str) -> Result<Option<MonitorEntry>, StoreError> {
        let row = sqlx::query(&format!(
            "SELECT {MON_COLS} FROM monitors WHERE artifact_id = $1 ORDER BY created_at DESC, id DESC LIMIT 1"
        ))
        .bind(artifact_id)
        .fetch_optional(&self.catalog().pool)
        .await?;
        let Some(row) = row else { return Ok(None) };
        let mut m = monitor_from_row(&row)?;
        m.aliases = monitor_aliases_of(self, &m.id).await?;
        Ok(Some(m))
    }

    async fn set_monitor_alias(&self, alias: &str, id: &str) -> Result<MonitorEntry, StoreError> {
        store::model::check_name("alias", alias)?;
        if alias.contains('@') || alias.contains('/') {
            return Err(StoreError::invalid(format!("alias {alias:?} may not contain '@' or '/'")));
        }
        let m = self.monitor(id).await?;
        let mut tx = self.catalog().begin_write().await?;
        upsert_monitor_alias(&mut tx, &m.policy, &m.checkpoint, alias, id, &now_rfc3339()).await?;
        let event = monitor_alias_moved(&m.policy, &m.checkpoint, alias, id);
        self.commit_with_events(tx, &[event]).await?;
        self.monitor(id).await
    }

    async fn resolve_monitor(&self, reference: &str) -> Result<MonitorEntry, StoreError> {
        let Some((path, alias)) = reference.rsplit_once('@') else { return self.monitor(reference).await };
        let Some((policy, checkpoint)) = path.rsplit_once('/') else {
            return Err(StoreError::invalid(format!(
                "monitor reference {reference:?}: expected ID or POLICY/CHECKPOINT@ALIAS"
            )));
        };
        let row = sqlx::query(
            "SELECT monitor_id FROM monitor_aliases WHERE policy = $1 AND checkpoint = $2 AND alias = $3",
        )
        .bind(policy)
        .bind(checkpoint)
        .bind(alias)
        .fetch_optional(&self.catalog().pool)
        .await?
        .ok_or_else(|| StoreError::not_found("monitor alias", reference))?;
        self.monitor(&row.s("monitor_id")?).await
    }
}

async fn monitor_aliases_of(store: &Store, id: &str) -> Result<Vec<String>, StoreError> {
    let rows = sqlx::query("SELECT alias FROM monitor_aliases WHERE monitor_id = $1 ORDER BY alias")
        .bind(id)
        .fetch_all(&store.catalog().pool)
        .await?;
    rows.iter().map(|r| r.s("alias")).collect()
}

async fn upsert_monitor_alias(
    tx: &mut Tx,
    policy: &str,
    checkpoint: &str,
    alias: &str,
    id: &str,
    now: &str,
) -> Result<(), StoreError> {
    sqlx::query(
        "INSERT INTO monitor_aliases (policy, checkpoint, alias, monitor_id, updated_at) VALUES ($1, $2, $3, $4, $5) \
         ON CONFLICT (policy, checkpoint, alias) DO UPDATE SET monitor_id = excluded.monitor_id, \
         updated_at = excluded.updated_at",
    )
    .bind(policy)
    .bind(checkpoint)
    .bind(alias)
    .bind(id)
    .bind(now)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

fn monitor_from_row(r: &sqlx::any::AnyRow) -> Result<MonitorEntry, StoreError> {
    Ok(MonitorEntry {
        id: r.s("id")?,
        policy: r.s("policy")?,
        checkpoint: r.s("checkpoint")?,
        artifact_id: r.s("artifact_id")?,
        alpha: r.f("alpha")?,
        threshold: r.f("threshold")?,
        record: serde_json::from_str(&r.s("record")?)?,
        evaluation: r.os("evaluation")?.map(|e| serde_json::from_str(&e)).transpose()?,
        aliases: Vec::new(),
        created_by: r.s("created_by")?,
        created_at: r.s("created_at")?,
    })
}

/// The event of a monitor alias pointed at `monitor_id`.
fn monitor_alias_moved(policy: &str, checkpoint: &str, alias: &str, monitor_id: &str) -> NewEvent {
    NewEvent::new(
        EventKind::AliasMoved,
        alias,
        serde_json::json!({"target": "monitor", "monitor_id": monitor_id}),
    )
    .of(policy, Some(checkpoint))
}
