//! Verifier artifacts: immutable, content-addressed file sets (id = sha256 of their manifest)
//! with per-checkpoint aliases (`latest` is moved automatically on publish).

use bytes::Bytes;
use serde::{Deserialize, Serialize};
use std::future::Future;
use std::path::Path;
use store::sql::{forget_pending, now_rfc3339, refresh_review_scores_where, RowExt, Tx};
use store::{sha256_hex, EventKind, NewEvent, Store, StoreError, DEFAULT_REVIEW_ALIAS, DEFAULT_REVIEW_KIND};

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ArtifactFile {
    pub name: String,
    pub sha256: String,
    pub size_bytes: u64,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ArtifactRecord {
    pub id: String,
    pub policy: String,
    pub checkpoint: String,
    /// `classifier` or `q`
    pub kind: String,
    pub split_id: Option<String>,
    pub job_id: Option<String>,
    /// Object-store folder holding the files.
    pub prefix: String,
    pub files: Vec<ArtifactFile>,
    pub config: serde_json::Value,
    pub aliases: Vec<String>,
    pub created_at: String,
}

/// What to publish: a directory with `manifest.json`, `config.json` and the weights.
pub struct NewArtifact<'a> {
    pub dir: &'a Path,
    pub policy: &'a str,
    pub checkpoint: &'a str,
    pub kind: &'a str,
    pub split_id: Option<&'a str>,
    pub job_id: Option<&'a str>,
}

const ART_COLS: &str = "id, policy, checkpoint, kind, split_id, job_id, prefix, files, config, created_at";

fn read(dir: &Path, name: &str) -> Result<Vec<u8>, StoreError> {
    std::fs::read(dir.join(name))
        .map_err(|e| StoreError::invalid(format!("artifact {}: cannot read {name}: {e}", dir.display())))
}

/// Verifier artifacts on a [`Store`]: published file sets with per-checkpoint aliases.
pub trait Artifacts {
    /// Publishes an artifact directory: checks every file against its manifest, copies the files
    /// into object storage and records the artifact; moves the `latest` alias unless the artifact
    /// was trained off-policy (on other checkpoints' rollouts): a robot that asks for a
    /// checkpoint's `latest` verifier gets one trained on that checkpoint's own rollouts.
    fn publish_artifact(
        &self,
        new: NewArtifact<'_>,
    ) -> impl Future<Output = Result<ArtifactRecord, StoreError>> + Send;

    fn artifact(&self, id: &str) -> impl Future<Output = Result<ArtifactRecord, StoreError>> + Send;

    fn artifacts(
        &self,
        policy: Option<&str>,
        checkpoint: Option<&str>,
        kind: Option<&str>,
    ) -> impl Future<Output = Result<Vec<ArtifactRecord>, StoreError>> + Send;

    /// Points `alias` of the artifact's (policy, checkpoint, kind) at the artifact.
    fn set_alias(
        &self,
        alias: &str,
        artifact_id: &str,
    ) -> impl Future<Output = Result<ArtifactRecord, StoreError>> + Send;

    /// Resolves `policy/checkpoint/kind@alias` to an artifact.
    fn resolve_alias(
        &self,
        policy: &str,
        checkpoint: &str,
        kind: &str,
        alias: &str,
    ) -> impl Future<Output = Result<ArtifactRecord, StoreError>> + Send;

    /// Resolves an artifact reference: an id, or `policy/checkpoint/kind@alias`.
    fn resolve_artifact(
        &self,
        reference: &str,
    ) -> impl Future<Output = Result<ArtifactRecord, StoreError>> + Send;

    /// Copies an artifact's files into `dir` (checking their sha256).
    fn download_artifact(
        &self,
        id: &str,
        dir: &Path,
    ) -> impl Future<Output = Result<ArtifactRecord, StoreError>> + Send;
}

impl Artifacts for Store {
    async fn publish_artifact(&self, new: NewArtifact<'_>) -> Result<ArtifactRecord, StoreError> {
        if new.kind != "classifier" && new.kind != "q" {
            return Err(StoreError::invalid(format!("unknown verifier kind {:?}", new.kind)));
        }
        let manifest_bytes = read(new.dir, "manifest.json")?;
        let id = sha256_hex(&manifest_bytes)[..16].to_string();
        let manifest: serde_json::Value = serde_json::from_slice(&manifest_bytes)
            .map_err(|e| StoreError::invalid(format!("artifact manifest.json is not JSON: {e}")))?;
        let listed = manifest
            .get("files")
            .and_then(|f| f.as_object())
            .ok_or_else(|| StoreError::invalid("artifact manifest.json has no \"files\" object"))?;
        let prefix = format!("artifacts/{id}");
        let mut files = vec![ArtifactFile {
            name: "manifest.json".into(),
            sha256: sha256_hex(&manifest_bytes),
            size_bytes: manifest_bytes.len() as u64,
        }];
        let mut config = serde_json::Value::Null;
        let mut uploads = vec![("manifest.json".to_string(), manifest_bytes.clone())];
        for (name, sha) in listed {
            if name.contains('/') || name.contains("..") {
                return Err(StoreError::invalid(format!("artifact file name {name:?} is not a plain name")));
            }
            let data = read(new.dir, name)?;
            let actual = sha256_hex(&data);
            if Some(actual.as_str()) != sha.as_str() {
                return Err(StoreError::invalid(format!(
                    "artifact file {name}: sha256 {actual} does not match the manifest"
                )));
            }
            if name == "config.json" {
                config = serde_json::from_slice(&data)
                    .map_err(|e| StoreError::invalid(format!("artifact config.json is not JSON: {e}")))?;
            }
            files.push(ArtifactFile { name: name.clone(), sha256: actual, size_bytes: data.len() as u64 });
            uploads.push((name.clone(), data));
        }
        if config.is_null() {
            return Err(StoreError::invalid("artifact has no config.json in its manifest"));
        }
        let off_policy = match new.split_id {
            Some(s) => self.split(s).await?.mode == "off_policy",
            None => false,
        };
        // Pending until the artifact's row commits: gc keeps them (the store's gc.rs).
        let publisher = format!("publish-{}", uuid::Uuid::new_v4().simple());
        let objects =
            uploads.into_iter().map(|(name, data)| (format!("{prefix}/{name}"), Bytes::from(data))).collect();
        self.put_pending_content(&publisher, objects).await?;
        let now = now_rfc3339();
        let mut tx = self.catalog().begin_write().await?;
        let inserted = sqlx::query(&format!(
            "INSERT INTO artifacts ({ART_COLS}) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10) ON CONFLICT DO NOTHING"
        ))
        .bind(&id)
        .bind(new.policy)
        .bind(new.checkpoint)
        .bind(new.kind)
        .bind(new.split_id.map(String::from))
        .bind(new.job_id.map(String::from))
        .bind(&prefix)
        .bind(serde_json::to_string(&files)?)
        .bind(serde_json::to_string(&config)?)
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        let mut events = Vec::new();
        if inserted.rows_affected() == 1 {
            events.push(
                NewEvent::new(
                    EventKind::ArtifactPublished,
                    id.clone(),
                    serde_json::json!({
                        "kind": new.kind,
                        "split_id": new.split_id,
                        "job_id": new.job_id,
                        "off_policy": off_policy,
                    }),
                )
                .of(new.policy, Some(new.checkpoint)),
            );
        }
        if !off_policy {
            upsert_alias(&mut tx, new.policy, new.checkpoint, new.kind, "latest", &id, &now).await?;
            events.push(alias_moved(new.policy, new.checkpoint, new.kind, "latest", &id));
        }
        forget_pending(&mut tx, &publisher).await?;
        self.commit_with_events(tx, &events).await?;
        self.artifact(&id).await
    }

    async fn artifact(&self, id: &str) -> Result<ArtifactRecord, StoreError> {
        let row = sqlx::query(&format!("SELECT {ART_COLS} FROM artifacts WHERE id = $1"))
            .bind(id)
            .fetch_optional(&self.catalog().pool)
            .await?
            .ok_or_else(|| StoreError::not_found("artifact", id))?;
        let mut rec = artifact_from_row(&row)?;
        rec.aliases = aliases_of(self, id).await?;
        Ok(rec)
    }

    async fn artifacts(
        &self,
        policy: Option<&str>,
        checkpoint: Option<&str>,
        kind: Option<&str>,
    ) -> Result<Vec<ArtifactRecord>, StoreError> {
        let rows = sqlx::query(&format!(
            "SELECT {ART_COLS} FROM artifacts WHERE ($1 = '' OR policy = $1) AND ($2 = '' OR checkpoint = $2) \
             AND ($3 = '' OR kind = $3) ORDER BY created_at, id"
        ))
        .bind(policy.unwrap_or(""))
        .bind(checkpoint.unwrap_or(""))
        .bind(kind.unwrap_or(""))
        .fetch_all(&self.catalog().pool)
        .await?;
        let mut out = Vec::with_capacity(rows.len());
        for r in &rows {
            let mut rec = artifact_from_row(r)?;
            rec.aliases = aliases_of(self, &rec.id).await?;
            out.push(rec);
        }
        Ok(out)
    }

    async fn set_alias(&self, alias: &str, artifact_id: &str) -> Result<ArtifactRecord, StoreError> {
        store::model::check_name("alias", alias)?;
        if alias.contains('@') || alias.contains('/') {
            return Err(StoreError::invalid(format!("alias {alias:?} may not contain '@' or '/'")));
        }
        let a = self.artifact(artifact_id).await?;
        let mut tx = self.catalog().begin_write().await?;
        upsert_alias(&mut tx, &a.policy, &a.checkpoint, &a.kind, alias, &a.id, &now_rfc3339()).await?;
        let event = alias_moved(&a.policy, &a.checkpoint, &a.kind, alias, &a.id);
        self.commit_with_events(tx, &[event]).await?;
        self.artifact(artifact_id).await
    }

    async fn resolve_alias(
        &self,
        policy: &str,
        checkpoint: &str,
        kind: &str,
        alias: &str,
    ) -> Result<ArtifactRecord, StoreError> {
        let row = sqlx::query(
            "SELECT artifact_id FROM artifact_aliases WHERE policy = $1 AND checkpoint = $2 AND kind = $3 AND alias = $4",
        )
        .bind(policy)
        .bind(checkpoint)
        .bind(kind)
        .bind(alias)
        .fetch_optional(&self.catalog().pool)
        .await?
        .ok_or_else(|| StoreError::not_found("artifact alias", format!("{policy}/{checkpoint}/{kind}@{alias}")))?;
        self.artifact(&row.s("artifact_id")?).await
    }

    async fn resolve_artifact(&self, reference: &str) -> Result<ArtifactRecord, StoreError> {
        if let Some((path, alias)) = reference.rsplit_once('@') {
            let parts: Vec<&str> = path.rsplitn(3, '/').collect();
            if parts.len() != 3 {
                return Err(StoreError::invalid(format!(
                    "artifact reference {reference:?}: expected ID or POLICY/CHECKPOINT/KIND@ALIAS"
                )));
            }
            return self.resolve_alias(parts[2], parts[1], parts[0], alias).await;
        }
        self.artifact(reference).await
    }

    async fn download_artifact(&self, id: &str, dir: &Path) -> Result<ArtifactRecord, StoreError> {
        let a = self.artifact(id).await?;
        std::fs::create_dir_all(dir)
            .map_err(|e| StoreError::invalid(format!("cannot create {}: {e}", dir.display())))?;
        for f in &a.files {
            let data = self.get_object(&format!("{}/{}", a.prefix, f.name)).await?;
            if sha256_hex(&data) != f.sha256 {
                return Err(StoreError::Corrupt(format!("artifact {id} file {} fails its sha256", f.name)));
            }
            std::fs::write(dir.join(&f.name), &data)
                .map_err(|e| StoreError::invalid(format!("cannot write {}: {e}", dir.display())))?;
        }
        Ok(a)
    }
}

async fn aliases_of(store: &Store, id: &str) -> Result<Vec<String>, StoreError> {
    let rows = sqlx::query("SELECT alias FROM artifact_aliases WHERE artifact_id = $1 ORDER BY alias")
        .bind(id)
        .fetch_all(&store.catalog().pool)
        .await?;
    rows.iter().map(|r| r.s("alias")).collect()
}

async fn upsert_alias(
    tx: &mut Tx,
    policy: &str,
    checkpoint: &str,
    kind: &str,
    alias: &str,
    id: &str,
    now: &str,
) -> Result<(), StoreError> {
    sqlx::query(
        "INSERT INTO artifact_aliases (policy, checkpoint, kind, alias, artifact_id, updated_at) \
         VALUES ($1, $2, $3, $4, $5, $6) ON CONFLICT (policy, checkpoint, kind, alias) \
         DO UPDATE SET artifact_id = excluded.artifact_id, updated_at = excluded.updated_at",
    )
    .bind(policy)
    .bind(checkpoint)
    .bind(kind)
    .bind(alias)
    .bind(id)
    .bind(now)
    .execute(&mut **tx)
    .await?;
    // The checkpoint's review queue is scored by its `classifier@latest` (unless its policy has
    // a setting): its episodes' review scores follow the alias.
    if kind == DEFAULT_REVIEW_KIND && alias == DEFAULT_REVIEW_ALIAS {
        refresh_review_scores_where(tx, policy, Some(checkpoint)).await?;
    }
    Ok(())
}

fn artifact_from_row(r: &sqlx::any::AnyRow) -> Result<ArtifactRecord, StoreError> {
    Ok(ArtifactRecord {
        id: r.s("id")?,
        policy: r.s("policy")?,
        checkpoint: r.s("checkpoint")?,
        kind: r.s("kind")?,
        split_id: r.os("split_id")?,
        job_id: r.os("job_id")?,
        prefix: r.s("prefix")?,
        files: serde_json::from_str(&r.s("files")?)?,
        config: serde_json::from_str(&r.s("config")?)?,
        aliases: Vec::new(),
        created_at: r.s("created_at")?,
    })
}

/// The event of an artifact alias pointed at `artifact_id`.
fn alias_moved(policy: &str, checkpoint: &str, kind: &str, alias: &str, artifact_id: &str) -> NewEvent {
    NewEvent::new(
        EventKind::AliasMoved,
        alias,
        serde_json::json!({"target": "artifact", "kind": kind, "artifact_id": artifact_id}),
    )
    .of(policy, Some(checkpoint))
}
