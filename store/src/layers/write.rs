//! Writing a layer: its values encoded in one Parquet file, then the version that records
//! where each episode's rows are.

use super::{check_layer_name, producer_hash, LayerValues, LayerWrite, IDS_PER_QUERY, MAX_LAYER_DIM};
use crate::catalog::{insert_rows, RowExt, Tx, Val};
use crate::steps::{OBS_PREFIX, PAGE_MAX_BYTES, ROW_GROUP_MAX_BYTES};
use crate::versioning::version::{finish_version, next_version, VersionHead};
use crate::{Store, StoreError};
use arrow::array::{ArrayRef, FixedSizeListArray, Float32Array, Int32Array, RecordBatch, StringArray};
use arrow::datatypes::{DataType, Field, Schema};
use bytes::Bytes;
use parquet::arrow::ArrowWriter;
use std::collections::HashSet;
use std::sync::Arc;

fn layer_schema(dim: usize) -> Arc<Schema> {
    let item = Arc::new(Field::new("item", DataType::Float32, false));
    Arc::new(Schema::new(vec![
        Field::new("episode_id", DataType::Utf8, false),
        Field::new("t", DataType::Int32, false),
        Field::new("value", DataType::FixedSizeList(item, dim as i32), false),
    ]))
}

/// Where each episode's rows landed in a layer file.
struct LayerFile {
    bytes: Vec<u8>,
    rows: usize,
    ranges: Vec<(usize, usize, usize)>,
}

/// Writes the episodes' values into one Parquet file with the steps files' properties: one
/// page per episode and column (or per [`PAGE_MAX_BYTES`] of it), row groups cut between
/// episodes, the offset index written, so one episode's read fetches only its own pages.
fn encode_layer_file(eps: &[&LayerValues], dim: usize) -> Result<LayerFile, StoreError> {
    let schema = layer_schema(dim);
    let parquet = parquet::arrow::ArrowSchemaConverter::new().convert(&schema)?;
    let props = crate::steps::steps_writer_properties(&parquet);
    let mut w = ArrowWriter::try_new(Vec::with_capacity(1 << 20), schema.clone(), Some(props))?;
    let rows_per_page = (PAGE_MAX_BYTES / (dim * 4)).max(1);
    let (mut row_group, mut offset, mut rows) = (0usize, 0usize, 0usize);
    let mut ranges = Vec::with_capacity(eps.len());
    for ep in eps {
        let n = ep.values.len() / dim;
        ranges.push((row_group, offset, n));
        let mut start = 0;
        while start < n {
            let len = rows_per_page.min(n - start);
            let ids: ArrayRef = Arc::new(StringArray::from(vec![ep.episode_id.as_str(); len]));
            let t: ArrayRef = Arc::new(Int32Array::from_iter_values((start..start + len).map(|t| t as i32)));
            let values = Float32Array::from(ep.values[start * dim..(start + len) * dim].to_vec());
            let item = Arc::new(Field::new("item", DataType::Float32, false));
            let value: ArrayRef =
                Arc::new(FixedSizeListArray::try_new(item, dim as i32, Arc::new(values), None)?);
            w.write(&RecordBatch::try_new(schema.clone(), vec![ids, t, value])?)?;
            start += len;
        }
        offset += n;
        rows += n;
        if w.in_progress_size() >= ROW_GROUP_MAX_BYTES || offset >= crate::steps::ROW_GROUP_MAX_ROWS {
            w.flush()?;
            row_group += 1;
            offset = 0;
        }
    }
    let bytes = w.into_inner()?;
    Ok(LayerFile { bytes, rows, ranges })
}

/// The dim the episodes' values share, checked: in `1..=MAX_LAYER_DIM`, whole rows of finite
/// values, each episode given once.
fn check_layer_values(name: &str, episodes: &[LayerValues]) -> Result<usize, StoreError> {
    let Some(dim) = episodes.first().map(|e| e.dim) else {
        return Err(StoreError::invalid(format!("layer {name}: no episodes given")));
    };
    if dim == 0 || dim > MAX_LAYER_DIM {
        return Err(StoreError::invalid(format!("layer {name}: dim {dim} is not in 1..={MAX_LAYER_DIM}")));
    }
    let mut seen = HashSet::new();
    for e in episodes {
        if e.dim != dim {
            return Err(StoreError::invalid(format!(
                "layer {name}: episode {} has dim {}, the others {dim}",
                e.episode_id, e.dim
            )));
        }
        if e.values.len() % dim != 0 {
            return Err(StoreError::invalid(format!(
                "layer {name}: episode {} has {} values, not a multiple of dim {dim}",
                e.episode_id,
                e.values.len()
            )));
        }
        if let Some(k) = e.values.iter().position(|v| !v.is_finite()) {
            return Err(StoreError::invalid(format!(
                "layer {name}: episode {} has a non-finite value at step {}",
                e.episode_id,
                k / dim
            )));
        }
        if !seen.insert(e.episode_id.as_str()) {
            return Err(StoreError::invalid(format!("layer {name}: episode {} given twice", e.episode_id)));
        }
    }
    Ok(dim)
}

/// Inside a layer's commit: checks that no episode of `todo` was removed meanwhile, and ends
/// the values of layer `name` they held so far at `version`.
async fn end_current_layer_values(
    tx: &mut Tx,
    name: &str,
    todo: &[&LayerValues],
    version: i64,
) -> Result<(), StoreError> {
    // Episodes removed meanwhile cannot take the layer.
    for chunk in todo.chunks(IDS_PER_QUERY) {
        let marks: Vec<String> = (1..=chunk.len()).map(|i| format!("${i}")).collect();
        let sql = format!(
            "SELECT COUNT(*) AS n FROM episodes WHERE version_removed IS NULL AND id IN ({})",
            marks.join(", ")
        );
        let mut q = sqlx::query(&sql);
        for e in chunk {
            q = q.bind(e.episode_id.as_str());
        }
        if q.fetch_one(&mut **tx).await?.i("n")? != chunk.len() as i64 {
            return Err(StoreError::Conflict(format!(
                "layer {name}: an episode was removed while its values were written; retry"
            )));
        }
        // The values they held so far (another producer's, or a concurrent writer's) end here.
        let sql = format!(
            "UPDATE episode_layers SET version_removed = ${} WHERE layer = ${} AND version_removed IS NULL AND episode_id IN ({})",
            chunk.len() + 1,
            chunk.len() + 2,
            marks.join(", ")
        );
        let mut q = sqlx::query(&sql);
        for e in chunk {
            q = q.bind(e.episode_id.as_str());
        }
        q.bind(version).bind(name).execute(&mut **tx).await?;
    }
    Ok(())
}

/// Inside a layer's commit: one `episode_layers` row per episode of `todo`, where its rows are
/// in the layer file (`ranges`: row group, offset, count).
async fn insert_episode_layers(
    tx: &mut Tx,
    name: &str,
    hash: &str,
    path: &str,
    version: i64,
    todo: &[&LayerValues],
    ranges: &[(usize, usize, usize)],
) -> Result<(), StoreError> {
    let rows: Vec<Vec<Val>> = todo
        .iter()
        .zip(ranges)
        .map(|(e, (rg, off, n))| {
            vec![
                name.into(),
                e.episode_id.as_str().into(),
                hash.into(),
                path.into(),
                (*rg as i64).into(),
                (*off as i64).into(),
                (*n as i64).into(),
                version.into(),
            ]
        })
        .collect();
    insert_rows(
        tx,
        "episode_layers",
        &[
            "layer",
            "episode_id",
            "producer_hash",
            "data_file",
            "row_group",
            "row_offset",
            "row_count",
            "version_added",
        ],
        rows,
        "",
    )
    .await
}

impl Store {
    /// Writes one group of episodes' values of layer `name` from `producer` as a new version.
    /// Every episode must be visible now and get one row per stored step; an episode that
    /// already holds this layer from this producer is skipped (no version when all are). A
    /// layer name may not shadow an observation key the episode's steps already have.
    ///
    /// Which episodes hold the layer already is decided again inside the version's transaction
    /// (under the version write lock), so two writers of one producer at once — two runs of a
    /// computation, on any number of servers — write each episode once: the later commit skips
    /// what the earlier one wrote.
    pub async fn write_layer(
        &self,
        name: &str,
        producer: &serde_json::Value,
        episodes: Vec<LayerValues>,
        actor: &str,
    ) -> Result<LayerWrite, StoreError> {
        check_layer_name(name)?;
        let hash = producer_hash(producer)?;
        let dim = check_layer_values(name, &episodes)?;
        let todo = self.layer_episodes_to_write(name, &hash, dim, &episodes).await?;
        let written = if todo.is_empty() {
            None
        } else {
            self.store_layer(name, producer, &hash, dim, &todo, actor).await?
        };
        let (version, episodes_written) = written.map_or((None, 0), |(v, n)| (Some(v), n));
        Ok(LayerWrite {
            version,
            producer_hash: hash,
            episodes_written,
            episodes_skipped: episodes.len() - episodes_written,
        })
    }

    /// The episodes that do not hold layer `name` from producer `hash` yet, each checked against
    /// its stored steps: a layer already written with another dim, a row count other than the
    /// episode's steps, or a name its steps have as an observation key is an error.
    async fn layer_episodes_to_write<'a>(
        &self,
        name: &str,
        hash: &str,
        dim: usize,
        episodes: &'a [LayerValues],
    ) -> Result<Vec<&'a LayerValues>, StoreError> {
        if let Some(existing) = self.layer_dim(name, hash).await? {
            if existing != dim as i64 {
                return Err(StoreError::invalid(format!(
                    "layer {name} from producer {}: dim {dim}, but it was written with dim {existing}",
                    &hash[..12]
                )));
            }
        }
        // Where the episodes are (visible now) and what they hold already.
        let ids: Vec<String> = episodes.iter().map(|e| e.episode_id.clone()).collect();
        let locations = self.locate_episodes(&ids, None).await?;
        let done = self.episodes_with_layer(name, hash, &ids).await?;
        let mut files_checked = HashSet::new();
        let mut todo: Vec<&LayerValues> = Vec::new();
        for (e, loc) in episodes.iter().zip(&locations) {
            if done.contains(&e.episode_id) {
                continue;
            }
            let rows = e.values.len() / dim;
            if rows != loc.row_count {
                return Err(StoreError::invalid(format!(
                    "layer {name}: episode {} has {} steps, {rows} rows of values were given",
                    e.episode_id, loc.row_count
                )));
            }
            if files_checked.insert(loc.data_file.clone()) {
                let schema = self.steps_schema(&loc.data_file).await?;
                if schema.field_with_name(&format!("{OBS_PREFIX}{name}")).is_ok() {
                    return Err(StoreError::invalid(format!(
                        "layer {name}: episode {} already has an observation key {name:?}; name the layer otherwise",
                        e.episode_id
                    )));
                }
            }
            todo.push(e);
        }
        Ok(todo)
    }

    /// Puts the episodes' values in a new layer file (protected from gc as pending until the
    /// commit) and commits them as a new version: the version and the episodes it wrote, or
    /// none when another writer committed all of them meanwhile (the file is then left to gc).
    async fn store_layer(
        &self,
        name: &str,
        producer: &serde_json::Value,
        hash: &str,
        dim: usize,
        todo: &[&LayerValues],
        actor: &str,
    ) -> Result<Option<(i64, usize)>, StoreError> {
        let file = encode_layer_file(todo, dim)?;
        let path = format!("layers/{}.parquet", uuid::Uuid::new_v4());
        let writer = format!("layer-{}", uuid::Uuid::new_v4().simple());
        self.register_pending(&writer, &path).await?;
        let size = file.bytes.len() as i64;
        let put = self.objects().put_new(&path, Bytes::from(file.bytes)).await;
        if let Err(e) = put {
            self.clear_pending(&writer).await.ok();
            return Err(e.into());
        }
        let committed = self
            .commit_layer(
                name,
                producer,
                hash,
                dim,
                todo,
                &file.ranges,
                &path,
                size,
                file.rows,
                &writer,
                actor,
            )
            .await;
        if !matches!(committed, Ok(Some(_))) {
            // The file is left for gc (no longer protected).
            self.clear_pending(&writer).await.ok();
        }
        committed
    }

    #[allow(clippy::too_many_arguments)]
    async fn commit_layer(
        &self,
        name: &str,
        producer: &serde_json::Value,
        hash: &str,
        dim: usize,
        todo: &[&LayerValues],
        ranges: &[(usize, usize, usize)],
        path: &str,
        size: i64,
        rows: usize,
        writer: &str,
        actor: &str,
    ) -> Result<Option<(i64, usize)>, StoreError> {
        let mut tx = self.catalog().begin_version_write().await?;
        // Under the version write lock: a concurrent writer of this producer may have committed
        // some of these episodes since they were checked; they are not written again.
        let ids: Vec<String> = todo.iter().map(|e| e.episode_id.clone()).collect();
        let held = episodes_with_layer_in(&mut tx, name, hash, &ids).await?;
        let (todo, ranges): (Vec<&LayerValues>, Vec<(usize, usize, usize)>) = todo
            .iter()
            .zip(ranges)
            .filter(|(e, _)| !held.contains(&e.episode_id))
            .map(|(e, r)| (*e, *r))
            .unzip();
        if todo.is_empty() {
            return Ok(None); // the transaction rolls back
        }
        let (todo, ranges) = (todo.as_slice(), ranges.as_slice());
        let version = next_version(&mut tx).await?;
        let now = crate::now_rfc3339();
        sqlx::query("DELETE FROM pending_objects WHERE writer = $1").bind(writer).execute(&mut *tx).await?;
        end_current_layer_values(&mut tx, name, todo, version).await?;
        sqlx::query(
            "INSERT INTO data_files (path, kind, size_bytes, num_rows, version_added, media_indexed) \
             VALUES ($1, 'layer', $2, $3, $4, 1)",
        )
        .bind(path)
        .bind(size)
        .bind(rows as i64)
        .bind(version)
        .execute(&mut *tx)
        .await?;
        sqlx::query(
            "INSERT INTO layers (name, producer_hash, producer, dim, version_added, created_at) \
             VALUES ($1, $2, $3, $4, $5, $6) ON CONFLICT DO NOTHING",
        )
        .bind(name)
        .bind(hash)
        .bind(serde_json::to_string(producer)?)
        .bind(dim as i64)
        .bind(version)
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        insert_episode_layers(&mut tx, name, hash, path, version, todo, ranges).await?;
        let head = VersionHead {
            version,
            kind: "layer",
            message: format!("layer {name} from producer {} on {} episode(s)", &hash[..12], todo.len()),
            actor: actor.to_string(),
            source_sha256: None,
            episodes_added: 0,
            episodes_removed: 0,
            events: Vec::new(),
        };
        let version = finish_version(self, tx, head, Default::default(), None).await?;
        Ok(Some((version, todo.len())))
    }

    async fn layer_dim(&self, name: &str, hash: &str) -> Result<Option<i64>, StoreError> {
        let r = sqlx::query("SELECT dim FROM layers WHERE name = $1 AND producer_hash = $2")
            .bind(name)
            .bind(hash)
            .fetch_optional(&self.catalog().pool)
            .await?;
        r.map(|r| r.i("dim")).transpose()
    }

    /// Which of `ids` hold layer `name` from `producer_hash` now.
    async fn episodes_with_layer(
        &self,
        name: &str,
        producer_hash: &str,
        ids: &[String],
    ) -> Result<HashSet<String>, StoreError> {
        let mut conn = self.catalog().pool.acquire().await?;
        episodes_with_layer_in(&mut conn, name, producer_hash, ids).await
    }
}

/// Which of `ids` hold layer `name` from `producer_hash` now, read on `conn` (a transaction's,
/// to decide under its locks).
async fn episodes_with_layer_in(
    conn: &mut sqlx::AnyConnection,
    name: &str,
    producer_hash: &str,
    ids: &[String],
) -> Result<HashSet<String>, StoreError> {
    let mut out = HashSet::new();
    for chunk in ids.chunks(IDS_PER_QUERY) {
        let marks: Vec<String> = (3..chunk.len() + 3).map(|i| format!("${i}")).collect();
        let sql = format!(
            "SELECT episode_id FROM episode_layers WHERE layer = $1 AND producer_hash = $2 \
             AND version_removed IS NULL AND episode_id IN ({})",
            marks.join(", ")
        );
        let mut q = sqlx::query(&sql).bind(name).bind(producer_hash);
        for id in chunk {
            q = q.bind(id.as_str());
        }
        for r in q.fetch_all(&mut *conn).await? {
            out.insert(r.s("episode_id")?);
        }
    }
    Ok(out)
}
