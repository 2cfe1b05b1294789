//! Ingest writes: data files first under unique names (put-if-absent), then one catalog
//! transaction that makes the new version visible (`versioning/version.rs`). A crash before the commit
//! leaves only unreferenced objects, which `gc` removes.
//!
//! Past 700 lines with its unit tests (about 100 of them).

use crate::catalog::{insert_rows, RowExt, Val};
use crate::model::{check_name, check_ref_name};
use crate::objects::Staging;
use crate::steps::{self, StepsFileWriter};
use crate::versioning::counts::CountDeltas;
use crate::versioning::version::{finish_version, next_version, VersionHead};
use crate::{now_rfc3339, EpisodeInput, ExtraColumn, Label, MediaFile, SourceInput, Store, StoreError};
use std::collections::{HashMap, HashSet};

/// Roll over to a new data file past this many encoded bytes (bounds one object's size).
pub const MAX_STEPS_FILE_BYTES: usize = 64 << 20;

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, serde::Serialize)]
pub struct CommitInfo {
    pub version: i64,
    pub episodes: usize,
}

/// An ingested source (catalog `sources`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct SourceRecord {
    pub sha256: String,
    pub path: String,
    pub format: String,
    pub size_bytes: i64,
    pub metadata: serde_json::Value,
    /// The version its ingest created.
    pub version: i64,
}

struct PendingEpisode {
    source_name: String,
    source_index: u32,
    task: Option<String>,
    length: i64,
    tags: String,
    metadata: String,
    data_file: String,
    range: steps::RowRange,
    label: Label,
    label_source: String,
    /// `(key, video object, first and last frame time)` of each camera (catalog `episode_media`).
    media: Vec<(String, String, f64, f64)>,
    /// The episode's first step a human controlled and how many it controlled (catalog
    /// `first_intervention`, `intervention_steps`; see [`crate::StepFlags`]).
    first_intervention: Option<i64>,
    intervention_steps: Option<i64>,
}

struct WrittenFile {
    path: String,
    size: i64,
    rows: i64,
}

/// An ingest in progress; nothing is visible until [`IngestWriter::commit`].
pub struct IngestWriter {
    store: Store,
    source: SourceInput,
    policy: String,
    checkpoint: String,
    /// `<source sha256[:12]>`, the episode id prefix, once the source's hash is known.
    id_prefix: Option<String>,
    /// The steps file being filled: its object path, its writer, and where it is staged.
    current: Option<(String, StepsFileWriter, Staging)>,
    /// Files complete but for their episode ids (the schema changed before the hash was known).
    parked: Vec<(String, StepsFileWriter, Staging)>,
    files: Vec<WrittenFile>,
    episodes: Vec<PendingEpisode>,
    indexes: HashSet<u32>,
    media: HashMap<String, (String, String, i64)>,
    /// sha256 → object path of the media added so far (what step rows reference).
    media_paths: HashMap<String, String>,
    max_file_bytes: usize,
    max_row_group_bytes: usize,
    /// Names this writer's `pending_objects` records (gc keeps those objects until the commit).
    writer_id: String,
    /// Renews those records every third of the lease while this writer lives (gc.rs).
    lease_renewal: Option<tokio::task::JoinHandle<()>>,
    /// The evaluation run every episode of this ingest belongs to (catalog `runs`).
    run: Option<crate::RunInput>,
}

impl Drop for IngestWriter {
    fn drop(&mut self) {
        if let Some(h) = self.lease_renewal.take() {
            h.abort();
        }
    }
}

fn check_sha256(sha256: &str) -> Result<(), StoreError> {
    if sha256.len() != 64 || !sha256.chars().all(|c| c.is_ascii_hexdigit()) {
        return Err(StoreError::invalid(format!("source sha256 {sha256:?} is not 64 hex digits")));
    }
    Ok(())
}

impl Store {
    /// Starts an ingest of one source (its sha256 known) into a new version.
    pub async fn begin_ingest(
        &self,
        source: SourceInput,
        policy: &str,
        checkpoint: &str,
    ) -> Result<IngestWriter, StoreError> {
        check_sha256(&source.sha256)?;
        if let Some(version) = self.source_version(&source.sha256).await? {
            return Err(StoreError::AlreadyIngested { sha256: source.sha256, version });
        }
        let sha256 = source.sha256.clone();
        let mut w = self.begin_ingest_unhashed(source, policy, checkpoint)?;
        w.id_prefix = Some(sha256[..12].to_string());
        w.source.sha256 = sha256;
        Ok(w)
    }

    /// Starts an ingest whose source hash is still being computed (`source.sha256` is ignored):
    /// episodes are encoded meanwhile with [`IngestWriter::push_episode`], and
    /// [`IngestWriter::set_source_hash`] must be called before the commit. Nothing is written to
    /// object storage before the hash is known, so a source that is already in the store costs
    /// no writes.
    pub fn begin_ingest_unhashed(
        &self,
        mut source: SourceInput,
        policy: &str,
        checkpoint: &str,
    ) -> Result<IngestWriter, StoreError> {
        check_ref_name("policy", policy)?;
        check_ref_name("checkpoint", checkpoint)?;
        source.sha256.clear();
        Ok(IngestWriter {
            store: self.clone(),
            source,
            policy: policy.to_string(),
            checkpoint: checkpoint.to_string(),
            id_prefix: None,
            current: None,
            parked: Vec::new(),
            files: Vec::new(),
            episodes: Vec::new(),
            indexes: HashSet::new(),
            media: HashMap::new(),
            media_paths: HashMap::new(),
            max_file_bytes: MAX_STEPS_FILE_BYTES,
            max_row_group_bytes: steps::ROW_GROUP_MAX_BYTES,
            writer_id: format!("ingest-{}", uuid::Uuid::new_v4().simple()),
            lease_renewal: None,
            run: None,
        })
    }

    /// A source's record: what was ingested, its format and format-specific metadata.
    pub async fn source(&self, sha256: &str) -> Result<SourceRecord, StoreError> {
        let r = sqlx::query(
            "SELECT sha256, path, format, size_bytes, metadata, version FROM sources WHERE sha256 = $1",
        )
        .bind(sha256)
        .fetch_optional(&self.catalog().pool)
        .await?
        .ok_or_else(|| StoreError::not_found("source", sha256))?;
        let metadata = serde_json::from_str(&r.s("metadata")?)
            .map_err(|e| StoreError::Corrupt(format!("source {sha256}: metadata is not JSON: {e}")))?;
        Ok(SourceRecord {
            sha256: r.s("sha256")?,
            path: r.s("path")?,
            format: r.s("format")?,
            size_bytes: r.i("size_bytes")?,
            metadata,
            version: r.i("version")?,
        })
    }

    /// The version that holds a source with this sha256, if any.
    pub async fn source_version(&self, sha256: &str) -> Result<Option<i64>, StoreError> {
        let row = sqlx::query("SELECT version FROM sources WHERE sha256 = $1")
            .bind(sha256)
            .fetch_optional(&self.catalog().pool)
            .await?;
        row.map(|r| r.i("version")).transpose()
    }
}

impl IngestWriter {
    /// Rolls over to a new data file past this many encoded bytes (default 64 MB).
    pub fn with_max_file_bytes(mut self, bytes: usize) -> Self {
        self.max_file_bytes = bytes.max(1);
        self
    }

    /// Closes row groups past this many encoded bytes (default
    /// [`steps::ROW_GROUP_MAX_BYTES`]). With [`Self::with_max_file_bytes`] it bounds what the
    /// writer holds in memory once the source's hash is known: one open row group and the
    /// file being filled.
    pub fn with_max_row_group_bytes(mut self, bytes: usize) -> Self {
        self.max_row_group_bytes = bytes.max(1);
        self
    }

    /// Encoded steps held in memory because the source's sha256 (the episode ids' prefix) is not
    /// known yet; 0 once it is. A caller bounds its memory by waiting for the hash past a budget.
    pub fn unhashed_bytes(&self) -> usize {
        if self.id_prefix.is_some() {
            return 0;
        }
        self.parked.iter().chain(self.current.as_ref()).map(|(_, w, _)| w.bytes_written()).sum()
    }

    /// Supplies the source's sha256 and size (see [`Store::begin_ingest_unhashed`]). Fails with
    /// [`StoreError::AlreadyIngested`] when a version already holds this content; the writer
    /// should then be dropped (nothing was written).
    pub async fn set_source_hash(&mut self, sha256: &str, size_bytes: u64) -> Result<(), StoreError> {
        check_sha256(sha256)?;
        if !self.source.sha256.is_empty() && self.source.sha256 != sha256 {
            return Err(StoreError::invalid("the source's sha256 was already set to another value"));
        }
        if let Some(version) = self.store.source_version(sha256).await? {
            return Err(StoreError::AlreadyIngested { sha256: sha256.to_string(), version });
        }
        self.source.sha256 = sha256.to_string();
        self.source.size_bytes = size_bytes;
        let prefix = sha256[..12].to_string();
        self.id_prefix = Some(prefix.clone());
        for (path, mut w, mut staged) in std::mem::take(&mut self.parked) {
            self.stage(&path, &mut w, &mut staged)?;
            w.set_id_prefix(&prefix)?;
            self.put_file(path, w, staged).await?;
        }
        if let Some((path, mut w, mut staged)) = self.current.take() {
            self.stage(&path, &mut w, &mut staged)?;
            self.current = Some((path, w, staged));
        }
        if let Some((_, w, _)) = self.current.as_mut() {
            w.set_id_prefix(&prefix)?;
            if w.bytes_written() > self.max_file_bytes {
                self.finish_file().await?;
            }
        }
        Ok(())
    }

    /// Copies a media file into object storage under its sha256 (stored once), streaming it:
    /// memory stays bounded by a few upload parts whatever the file's size.
    pub async fn add_media(&mut self, file: &MediaFile) -> Result<(), StoreError> {
        if self.media.contains_key(&file.sha256) {
            return Ok(());
        }
        let ext = file
            .local_path
            .extension()
            .and_then(|e| e.to_str())
            .filter(|e| e.chars().all(|c| c.is_ascii_alphanumeric()))
            .unwrap_or("bin");
        let path = format!("media/{}.{ext}", file.sha256);
        // Before the existence check inside: an object re-used from an earlier failed ingest must
        // not be collected between that check and our commit (gc.rs).
        self.protect(&path).await?;
        self.store.objects().put_file_content_addressed(&path, &file.local_path, &file.sha256).await?;
        self.media_paths.insert(file.sha256.clone(), path.clone());
        self.media.insert(file.sha256.clone(), (path, file.content_type.clone(), file.size_bytes as i64));
        Ok(())
    }

    /// Marks every episode of this ingest as produced by `run` (checked now; its artifact, if any,
    /// must exist when the ingest commits).
    pub fn set_run(&mut self, run: crate::RunInput) -> Result<(), StoreError> {
        run.validate()?;
        self.run = Some(run);
        Ok(())
    }

    /// Appends one episode and returns its id (the source's sha256 must be known: see
    /// [`Self::push_episode`] otherwise).
    pub async fn add_episode(&mut self, ep: EpisodeInput) -> Result<String, StoreError> {
        let Some(prefix) = self.id_prefix.clone() else {
            return Err(StoreError::invalid(
                "episode ids are not known before the source's sha256: use push_episode",
            ));
        };
        let index = ep.source_index;
        self.push_episode(ep).await?;
        Ok(steps::episode_id(&prefix, index))
    }

    /// [`Self::add_episode`] with the episode's steering telemetry ([`Self::push_episode_steered`]).
    pub async fn add_episode_steered(
        &mut self,
        ep: EpisodeInput,
        steering: arrow::array::ArrayRef,
    ) -> Result<String, StoreError> {
        let Some(prefix) = self.id_prefix.clone() else {
            return Err(StoreError::invalid(
                "episode ids are not known before the source's sha256: use push_episode_steered",
            ));
        };
        let index = ep.source_index;
        self.push_episode_steered(ep, Vec::new(), Some(steering)).await?;
        Ok(steps::episode_id(&prefix, index))
    }

    /// Appends one episode to the current Parquet file (episodes share row groups).
    pub async fn push_episode(&mut self, ep: EpisodeInput) -> Result<(), StoreError> {
        self.push_episode_with_extras(ep, Vec::new()).await
    }

    /// [`Self::push_episode`] with per-step arrays of the source beyond the step model, stored as
    /// `extra.<name>` columns (store/README.md, "Steps schema").
    pub async fn push_episode_with_extras(
        &mut self,
        ep: EpisodeInput,
        extras: Vec<ExtraColumn>,
    ) -> Result<(), StoreError> {
        self.push_episode_steered(ep, extras, None).await
    }

    /// [`Self::push_episode_with_extras`] with the episode's steering telemetry, stored as the
    /// [`steps::STEERING_COLUMN`] (one row per step, of [`steps::steering_data_type`]; built by
    /// `verifier::steps::steering_array`).
    pub async fn push_episode_steered(
        &mut self,
        ep: EpisodeInput,
        extras: Vec<ExtraColumn>,
        steering: Option<arrow::array::ArrayRef>,
    ) -> Result<(), StoreError> {
        steps::validate_with_extras(&ep, &extras, steering.as_ref())?;
        if let Some(t) = &ep.task {
            check_name("task", t)?;
        }
        if !self.indexes.insert(ep.source_index) {
            return Err(StoreError::invalid(format!(
                "episode index {} ({:?}) appears twice in the source",
                ep.source_index, ep.source_name
            )));
        }
        let schema = steps::schema_with_extras(&ep, &extras, steering.is_some());
        if self.current.as_ref().is_some_and(|(_, w, _)| w.schema != schema) {
            self.finish_file().await?;
        }
        if self.current.is_none() {
            let path = format!("steps/{}.parquet", uuid::Uuid::new_v4());
            // Staged in the store only once the hash is known: nothing is written there before.
            let staged = match &self.id_prefix {
                Some(_) => self.store.objects().local_staging_file(&path)?,
                None => None,
            };
            let (w, staged) = match staged {
                Some((file, staged)) => (StepsFileWriter::in_file(schema, file)?, staged),
                None => (StepsFileWriter::new(schema)?, Staging::temporary()),
            };
            let mut w = w.with_max_row_group_bytes(self.max_row_group_bytes);
            if let Some(p) = &self.id_prefix {
                w = w.with_id_prefix(p);
            }
            self.current = Some((path, w, staged));
        }
        let pending = PendingEpisode {
            source_name: ep.source_name.clone(),
            source_index: ep.source_index,
            task: ep.task.clone(),
            length: ep.len() as i64,
            tags: serde_json::to_string(&ep.tags)?,
            metadata: serde_json::to_string(&ep.metadata)?,
            data_file: String::new(),
            range: steps::RowRange { row_group: 0, offset: 0, count: 0 },
            label: ep.label,
            label_source: ep.label_source.clone(),
            media: ep
                .media
                .iter()
                .filter_map(|m| {
                    let path = self.media_paths.get(&m.sha256)?;
                    let first = m.timestamps.first().copied().unwrap_or(0.0);
                    let last = m.timestamps.last().copied().unwrap_or(first);
                    Some((m.name.clone(), path.clone(), first, last))
                })
                .collect(),
            first_intervention: ep.flags.first_intervention().map(|t| t as i64),
            intervention_steps: ep.flags.intervention_steps().map(|n| n as i64),
        };
        let index = ep.source_index;
        let cols = steps::episode_columns_with_extras(
            ep,
            extras,
            steering,
            &self.policy,
            &self.checkpoint,
            &self.media_paths,
        )?;
        let (path, w, _) = self.current.as_mut().expect("writer just created");
        let range = w.write_episode(index, cols)?;
        self.episodes.push(PendingEpisode { data_file: path.clone(), range, ..pending });
        if w.bytes_written() > self.max_file_bytes && self.id_prefix.is_some() {
            self.finish_file().await?;
        }
        Ok(())
    }

    async fn finish_file(&mut self) -> Result<(), StoreError> {
        if let Some((path, w, staged)) = self.current.take() {
            if self.id_prefix.is_some() {
                self.put_file(path, w, staged).await?;
            } else {
                self.parked.push((path, w, staged));
            }
        }
        Ok(())
    }

    /// Moves a file started before the hash was known (in a temporary file) to a staging file
    /// in a local store, so that storing it is a rename rather than a copy.
    fn stage(&self, path: &str, w: &mut StepsFileWriter, staged: &mut Staging) -> Result<(), StoreError> {
        if let Some((file, s)) = self.store.objects().local_staging_file(path)? {
            if w.move_to(file)? {
                *staged = s;
            }
        }
        Ok(())
    }

    async fn put_file(
        &mut self,
        path: String,
        w: StepsFileWriter,
        staged: Staging,
    ) -> Result<(), StoreError> {
        let rows = w.rows as i64;
        let (file, size) = w.finish()?;
        self.protect(&path).await?;
        self.store.objects().put_new_staged(&path, staged, file, size).await?;
        self.files.push(WrittenFile { path, size: size as i64, rows });
        Ok(())
    }

    /// Records `path` as this writer's pending object (before it is uploaded or re-used), and
    /// starts renewing this writer's lease on the first one.
    async fn protect(&mut self, path: &str) -> Result<(), StoreError> {
        self.store.register_pending(&self.writer_id, path).await?;
        if self.lease_renewal.is_none() {
            let (store, id) = (self.store.clone(), self.writer_id.clone());
            let every =
                std::time::Duration::from_millis((crate::objects::writer_lease_ms() / 3).max(50) as u64);
            self.lease_renewal = Some(tokio::spawn(async move {
                loop {
                    tokio::time::sleep(every).await;
                    if let Err(e) = store.renew_pending(&id).await {
                        tracing::warn!("cannot renew the lease of writer {id} on its uploads: {e}");
                    }
                }
            }));
        }
        Ok(())
    }

    /// Gives up: nothing becomes visible (written files are left for `gc`, no longer protected).
    pub async fn abort(self) -> Result<(), StoreError> {
        self.store.clear_pending(&self.writer_id).await
    }

    /// Makes everything added so far visible as one new version.
    #[allow(
        clippy::too_many_lines,
        reason = "the commit protocol reads top to bottom: checks, rows, counts, the version"
    )]
    pub async fn commit(mut self, message: &str) -> Result<CommitInfo, StoreError> {
        if self.episodes.is_empty() {
            return Err(StoreError::invalid(format!(
                "source {} holds no episodes: nothing to ingest",
                self.source.path
            )));
        }
        let Some(prefix) = self.id_prefix.clone() else {
            return Err(StoreError::invalid("commit before the source's sha256 was set"));
        };
        self.finish_file().await?;
        let store = self.store.clone();
        let mut tx = store.catalog().begin_version_write().await?;
        if let Some(r) = sqlx::query("SELECT version FROM sources WHERE sha256 = $1")
            .bind(&self.source.sha256)
            .fetch_optional(&mut *tx)
            .await?
        {
            return Err(StoreError::AlreadyIngested {
                sha256: self.source.sha256.clone(),
                version: r.i("version")?,
            });
        }
        let version = next_version(&mut tx).await?;
        let now = now_rfc3339();
        // Referenced from this commit on: no longer pending.
        sqlx::query("DELETE FROM pending_objects WHERE writer = $1")
            .bind(&self.writer_id)
            .execute(&mut *tx)
            .await?;
        // The policy and its checkpoint, if they are new.
        sqlx::query("INSERT INTO policies (name, created_at) VALUES ($1, $2) ON CONFLICT DO NOTHING")
            .bind(&self.policy)
            .bind(&now)
            .execute(&mut *tx)
            .await?;
        sqlx::query(
            "INSERT INTO checkpoints (policy, name, created_at) VALUES ($1, $2, $3) ON CONFLICT DO NOTHING",
        )
        .bind(&self.policy)
        .bind(&self.checkpoint)
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        let run_id = match &self.run {
            Some(run) => Some(crate::runs::ensure_run(&mut tx, run, &now).await?),
            None => None,
        };
        let tasks: HashSet<&String> = self.episodes.iter().filter_map(|e| e.task.as_ref()).collect();
        insert_rows(
            &mut tx,
            "tasks",
            &["name", "created_at"],
            tasks.into_iter().map(|t| vec![t.as_str().into(), now.as_str().into()]).collect(),
            "ON CONFLICT DO NOTHING",
        )
        .await?;
        sqlx::query(
            "INSERT INTO sources (sha256, path, format, size_bytes, metadata, version, created_at) \
             VALUES ($1, $2, $3, $4, $5, $6, $7)",
        )
        .bind(&self.source.sha256)
        .bind(&self.source.path)
        .bind(&self.source.format)
        .bind(self.source.size_bytes as i64)
        .bind(serde_json::to_string(&self.source.metadata)?)
        .bind(version)
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        let ids: Vec<String> =
            self.episodes.iter().map(|e| steps::episode_id(&prefix, e.source_index)).collect();
        let [files, media] = self.file_rows(version);
        let [episodes, tags] = self.episode_rows(version, &ids, run_id.clone(), &now)?;
        let [media_refs, label_events] = self.media_ref_and_label_event_rows(&ids, &now);
        // Parents before the rows that reference them.
        for t in [files, media, episodes, tags, media_refs, label_events] {
            insert_rows(&mut tx, t.table, t.cols, t.rows, t.suffix).await?;
        }
        let n = self.episodes.len();
        let mut counts = CountDeltas::default();
        for e in &self.episodes {
            counts.add(&self.policy, &self.checkpoint, e.task.as_deref(), e.label, 1);
        }
        let head = VersionHead {
            version,
            kind: "ingest",
            message: message.to_string(),
            actor: "ingest".into(),
            source_sha256: Some(self.source.sha256.clone()),
            episodes_added: n as i64,
            episodes_removed: 0,
            events: vec![crate::events::NewEvent::new(
                crate::events::EventKind::IngestCommitted,
                self.source.sha256.clone(),
                serde_json::json!({
                    "version": version,
                    "episodes": n,
                    "format": self.source.format,
                    "path": self.source.path,
                    "run_id": run_id,
                }),
            )
            .of(&self.policy, Some(&self.checkpoint))],
        };
        finish_version(&store, tx, head, counts, None).await?;
        Ok(CommitInfo { version, episodes: n })
    }

    /// The commit's data files (steps files and media objects). (`&mut self`, as every method
    /// here: a steps file's column writers are not `Sync`, so the writer is only ever borrowed
    /// uniquely across an await.)
    /// The rows of the version's steps files and of the media objects they first reference.
    fn file_rows(&self, version: i64) -> [TableRows; 2] {
        [
            TableRows {
                table: "data_files",
                cols: &["path", "kind", "size_bytes", "num_rows", "version_added", "media_indexed"],
                rows: self
                    .files
                    .iter()
                    .map(|f| {
                        vec![
                            f.path.as_str().into(),
                            "steps".into(),
                            f.size.into(),
                            f.rows.into(),
                            version.into(),
                            1i64.into(),
                        ]
                    })
                    .collect(),
                suffix: "",
            },
            TableRows {
                table: "media_objects",
                cols: &["sha256", "path", "content_type", "size_bytes", "version_added"],
                rows: self
                    .media
                    .iter()
                    .map(|(sha, (p, ct, sz))| {
                        vec![
                            sha.as_str().into(),
                            p.as_str().into(),
                            ct.as_str().into(),
                            (*sz).into(),
                            version.into(),
                        ]
                    })
                    .collect(),
                suffix: "ON CONFLICT DO NOTHING",
            },
        ]
    }

    /// The commit's episodes (ids `ids`, in order).
    /// The rows of the version's episodes and of their tags.
    fn episode_rows(
        &self,
        version: i64,
        ids: &[String],
        run_id: Option<String>,
        now: &str,
    ) -> Result<[TableRows; 2], StoreError> {
        let ep_rows: Vec<Vec<Val>> = self
            .episodes
            .iter()
            .zip(ids)
            .map(|(e, id)| {
                vec![
                    id.as_str().into(),
                    self.policy.as_str().into(),
                    self.checkpoint.as_str().into(),
                    e.task.clone().into(),
                    self.source.sha256.as_str().into(),
                    e.source_name.as_str().into(),
                    (e.source_index as i64).into(),
                    e.length.into(),
                    e.tags.as_str().into(),
                    e.metadata.as_str().into(),
                    e.data_file.as_str().into(),
                    (e.range.row_group as i64).into(),
                    (e.range.offset as i64).into(),
                    (e.range.count as i64).into(),
                    version.into(),
                    e.label.as_str().into(),
                    e.label_source.as_str().into(),
                    1i64.into(),
                    "ingest".into(),
                    now.into(),
                    now.into(),
                    run_id.clone().into(),
                    e.first_intervention.into(),
                    e.intervention_steps.into(),
                ]
            })
            .collect();
        let episodes = TableRows {
            table: "episodes",
            cols: &[
                "id",
                "policy",
                "checkpoint",
                "task",
                "source_sha256",
                "source_name",
                "source_index",
                "length",
                "tags",
                "metadata",
                "data_file",
                "row_group",
                "row_offset",
                "row_count",
                "version_added",
                "label",
                "label_source",
                "label_revision",
                "label_actor",
                "label_updated_at",
                "created_at",
                "run_id",
                "first_intervention",
                "intervention_steps",
            ],
            rows: ep_rows,
            suffix: "",
        };
        // The tag index (`tag=` filters).
        let mut tag_rows: Vec<Vec<Val>> = Vec::new();
        for (e, id) in self.episodes.iter().zip(ids) {
            let tags: std::collections::BTreeSet<String> = serde_json::from_str(&e.tags)?;
            tag_rows.extend(tags.into_iter().map(|t| vec![t.into(), id.as_str().into()]));
        }
        let tags =
            TableRows { table: "episode_tags", cols: &["tag", "episode_id"], rows: tag_rows, suffix: "" };
        Ok([episodes, tags])
    }

    /// The episodes' (ids `ids`, in order) media references and their first label events.
    /// The rows of the episodes' media references and of their first label events.
    fn media_ref_and_label_event_rows(&self, ids: &[String], now: &str) -> [TableRows; 2] {
        let media_rows: Vec<Vec<Val>> = self
            .episodes
            .iter()
            .zip(ids)
            .flat_map(|(e, id)| {
                e.media.iter().map(move |(key, path, first, last)| {
                    vec![
                        id.as_str().into(),
                        key.as_str().into(),
                        path.as_str().into(),
                        (*first).into(),
                        (*last).into(),
                    ]
                })
            })
            .collect();
        let media_refs = TableRows {
            table: "episode_media",
            cols: &["episode_id", "media_key", "path", "start_seconds", "end_seconds"],
            rows: media_rows,
            suffix: "",
        };
        let ev_rows: Vec<Vec<Val>> = self
            .episodes
            .iter()
            .zip(ids)
            .map(|(e, id)| {
                vec![
                    id.as_str().into(),
                    1i64.into(),
                    Val::OS(None),
                    e.label.as_str().into(),
                    e.label_source.as_str().into(),
                    "ingest".into(),
                    Val::OS(None),
                    now.into(),
                ]
            })
            .collect();
        let label_events = TableRows {
            table: "label_events",
            cols: &[
                "episode_id",
                "revision",
                "old_label",
                "new_label",
                "source",
                "actor",
                "note",
                "created_at",
            ],
            rows: ev_rows,
            suffix: "",
        };
        [media_refs, label_events]
    }
}

/// One table's rows of a version, inserted with [`insert_rows`] (`suffix`: its conflict clause).
struct TableRows {
    table: &'static str,
    cols: &'static [&'static str],
    rows: Vec<Vec<Val>>,
    suffix: &'static str,
}

#[cfg(test)]
mod tests {
    use crate::*;
    use arrow::array::{Array, Int32Array, StringArray};

    fn episode(i: u32, steps: usize, obs_dim: usize) -> EpisodeInput {
        let label = if i.is_multiple_of(2) { Label::Success } else { Label::Failure };
        EpisodeInput {
            tags: vec![],
            metadata: serde_json::json!({}),
            timestamps: (0..steps).map(|t| t as f64).collect(),
            observations: vec![VectorColumn {
                name: "pos".into(),
                dim: obs_dim,
                values: (0..steps * obs_dim).map(|k| k as f32 + i as f32 * 1000.0).collect(),
            }],
            action: VectorColumn { name: "action".into(), dim: 2, values: vec![i as f32; steps * 2] },
            ..crate::test_support::episode(i, steps, label)
        }
    }

    fn source(tag: &str) -> SourceInput {
        SourceInput {
            path: tag.into(),
            sha256: String::new(),
            format: "test".into(),
            size_bytes: 1,
            metadata: serde_json::json!({}),
        }
    }

    fn source_hashed(tag: &str) -> SourceInput {
        SourceInput { sha256: sha256_hex(tag.as_bytes()), ..source(tag) }
    }

    fn steps_files(dir: &std::path::Path) -> usize {
        std::fs::read_dir(dir.join("objects/steps")).map(|d| d.count()).unwrap_or(0)
    }

    async fn check_episode(store: &Store, id: &str, i: u32, steps: usize, obs_dim: usize) {
        let b = store.read_steps(id, None).await.unwrap();
        assert_eq!(b.num_rows(), steps, "{id}");
        let ids = b.column_by_name("episode_id").unwrap().as_any().downcast_ref::<StringArray>().unwrap();
        assert!((0..ids.len()).all(|k| ids.value(k) == id), "{id}");
        let t = b.column_by_name("t").unwrap().as_any().downcast_ref::<Int32Array>().unwrap();
        assert_eq!(t.values().to_vec(), (0..steps as i32).collect::<Vec<_>>());
        let (dim, pos) = crate::steps::vector_column(&b, "obs.pos").unwrap();
        assert_eq!(dim, obs_dim);
        assert_eq!(pos, (0..steps * obs_dim).map(|k| k as f32 + i as f32 * 1000.0).collect::<Vec<_>>());
    }

    /// Episodes share row groups, files roll over and the schema changes while the hash is not
    /// known yet: nothing is written before `set_source_hash`, and every episode reads back.
    #[tokio::test]
    async fn unhashed_ingest_shares_row_groups_and_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let mut w = store.begin_ingest_unhashed(source("a"), "pol", "c1").unwrap().with_max_file_bytes(4000);
        let shape = |i: u32| (3 + (i as usize * 7) % 40, if i < 30 { 2 } else { 3 });
        for i in 0..60 {
            let (steps, dim) = shape(i);
            w.push_episode(episode(i, steps, dim)).await.unwrap();
        }
        assert!(w.add_episode(episode(99, 3, 2)).await.is_err(), "ids are not known yet");
        assert_eq!(steps_files(dir.path()), 0, "nothing written before the hash is known");
        let sha = sha256_hex(b"a");
        w.set_source_hash(&sha, 123).await.unwrap();
        assert!(steps_files(dir.path()) > 1, "files finished once the hash is known");
        w.push_episode(episode(60, 5, 3)).await.unwrap();
        let info = w.commit("t").await.unwrap();
        assert_eq!(info.episodes, 61);
        let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();
        assert_eq!(eps.len(), 61);
        let shared = eps.iter().filter(|e| e.row_offset > 0).count();
        assert!(shared > 10, "episodes share row groups ({shared} not first in theirs)");
        for e in &eps {
            let i = e.source_index as u32;
            assert_eq!(e.id, format!("{}-{i:05}", &sha[..12]));
            assert_eq!(e.row_count, e.length);
            let (steps, dim) = if i == 60 { (5, 3) } else { shape(i) };
            check_episode(&store, &e.id, i, steps, dim).await;
        }
        let src = store.source_version(&sha).await.unwrap();
        assert_eq!(src, Some(info.version));
    }

    /// Steps files are built in staging files of the local store and linked into place: nothing
    /// is staged before the hash is known, none is left after a commit or once a writer is
    /// dropped, and the stored files read back.
    #[tokio::test]
    async fn steps_files_are_staged_in_the_store_and_none_is_left() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let staged = || store.objects().local_staging_files().len();
        let mut w = store.begin_ingest_unhashed(source("s"), "pol", "c1").unwrap().with_max_file_bytes(2000);
        for i in 0..3 {
            w.push_episode(episode(i, 10, 2)).await.unwrap();
        }
        assert_eq!(staged(), 0, "nothing staged before the hash is known");
        let sha = sha256_hex(b"s");
        w.set_source_hash(&sha, 1).await.unwrap();
        for i in 3..40 {
            w.push_episode(episode(i, 10 + i as usize, 2)).await.unwrap();
        }
        assert_eq!(staged(), 1, "the open file is staged in the store");
        w.commit("t").await.unwrap();
        assert_eq!(staged(), 0);
        assert!(steps_files(dir.path()) > 2);
        for e in store.episodes(&EpisodeFilter::default()).await.unwrap() {
            let (i, n) = (e.source_index as u32, e.length as usize);
            check_episode(&store, &e.id, i, n, 2).await;
        }
        let files = steps_files(dir.path());
        let mut w = store.begin_ingest(source_hashed("t"), "pol", "c1").await.unwrap();
        w.push_episode(episode(0, 4, 2)).await.unwrap();
        assert_eq!(staged(), 1);
        drop(w);
        assert_eq!(staged(), 0, "a dropped writer leaves no staging file");
        assert_eq!(steps_files(dir.path()), files);
    }

    /// The same content again: refused as soon as the hash is set, and nothing is written.
    #[tokio::test]
    async fn same_hash_is_refused_before_anything_is_written() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let sha = sha256_hex(b"b");
        let mut w = store.begin_ingest_unhashed(source("b"), "pol", "c1").unwrap();
        w.push_episode(episode(0, 4, 2)).await.unwrap();
        w.set_source_hash(&sha, 1).await.unwrap();
        let v = w.commit("t").await.unwrap().version;
        let before = steps_files(dir.path());
        let mut w =
            store.begin_ingest_unhashed(source("b again"), "pol", "c1").unwrap().with_max_file_bytes(1);
        for i in 0..5 {
            w.push_episode(episode(i, 4, 2)).await.unwrap();
        }
        match w.set_source_hash(&sha, 1).await {
            Err(StoreError::AlreadyIngested { version, .. }) => assert_eq!(version, v),
            other => panic!("expected AlreadyIngested, got {:?}", other.err()),
        }
        assert_eq!(steps_files(dir.path()), before);
        assert_eq!(store.head_version().await.unwrap(), v);
    }
}
