//! Layers: derived per-step data attached to stored episodes without rewriting their steps files
//! (store/README.md, "Layers"). A layer is a named per-step float32 vector — typically the
//! frozen embedding of a policy's own vision encoder for each step's camera frame — made by a
//! *producer* (a JSON object naming the encoder, the policy checkpoint whose encoder it is and
//! the weights' content hash) and identified by the sha256 of its canonical JSON.
//!
//! Writing a layer is a new version: the values go to their own Parquet file (one page per
//! episode, as the steps files), the catalog records where each episode's rows are
//! (`episode_layers`), and the read path joins them to the steps as `obs.<layer name>` columns.
//! An episode that already holds the layer from the same producer is skipped, so a computation
//! that commits in groups resumes where it stopped and a re-run writes nothing.

use crate::catalog::{insert_rows, RowExt, Tx, Val};
use crate::model::check_name;
use crate::read::{visible, EpisodeLocation, EpisodeSteps, StepsReadError, StepsStream};
use crate::steps::{OBS_PREFIX, PAGE_MAX_BYTES, ROW_GROUP_MAX_BYTES};
use crate::version::{finish_version, next_version, VersionHead};
use crate::{Store, StoreError};
use arrow::array::{Array, ArrayRef, FixedSizeListArray, Float32Array, Int32Array, RecordBatch, StringArray};
use arrow::datatypes::{DataType, Field, Schema};
use bytes::Bytes;
use parquet::arrow::ArrowWriter;
use serde::Serialize;
use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use tokio::sync::mpsc;

/// The widest layer accepted (values per step).
pub const MAX_LAYER_DIM: usize = 1 << 16;
/// Field metadata of a joined layer column: its layer name and its producer's hash.
pub const LAYER_META_KEY: &str = "ufops.layer";
pub const PRODUCER_META_KEY: &str = "ufops.layer_producer";
/// Rows of layer values held at once by a joined read (the layer side of one group of episodes).
const JOIN_GROUP_ROWS: usize = 1 << 15;
/// Catalog look-ups per statement.
const IDS_PER_QUERY: usize = 400;

/// One layer as the catalog lists it: a (name, producer) pair.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct LayerRecord {
    pub name: String,
    pub producer_hash: String,
    /// The producer as written (a JSON object).
    #[cfg_attr(feature = "openapi", schema(value_type = Object))]
    pub producer: serde_json::Value,
    pub dim: i64,
    /// Episodes whose current value of this layer comes from this producer.
    pub episodes: i64,
    /// The version that first wrote it.
    pub version: i64,
}

/// One episode's values of a layer, as given to [`Store::write_layer`]: `values` is
/// `steps * dim`, row-major, one row per step of the episode (t = 0, 1, …).
#[derive(Debug, Clone)]
pub struct LayerValues {
    pub episode_id: String,
    pub dim: usize,
    pub values: Vec<f32>,
}

/// What [`Store::write_layer`] did.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct LayerWrite {
    /// The new version, or none when every episode already held the layer from this producer.
    pub version: Option<i64>,
    pub producer_hash: String,
    pub episodes_written: usize,
    pub episodes_skipped: usize,
}

/// A layer an episode holds (see [`Store::episode_layers`]).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct EpisodeLayer {
    pub layer: String,
    pub producer_hash: String,
    pub dim: i64,
    pub version_added: i64,
}

/// The sha256 of a producer's canonical JSON (object keys sorted at every level, no spaces):
/// equal producers hash equally however their keys were ordered.
pub fn producer_hash(producer: &serde_json::Value) -> Result<String, StoreError> {
    if !producer.is_object() || producer.as_object().is_some_and(|o| o.is_empty()) {
        return Err(StoreError::invalid(
            "a layer's producer must be a non-empty JSON object (e.g. {\"encoder\": …, \"policy\": …, \"checkpoint\": …, \"content_hash\": …})",
        ));
    }
    let mut out = String::new();
    canonical(producer, &mut out);
    Ok(crate::sha256_hex(out.as_bytes()))
}

fn canonical(v: &serde_json::Value, out: &mut String) {
    match v {
        serde_json::Value::Object(m) => {
            let mut keys: Vec<&String> = m.keys().collect();
            keys.sort();
            out.push('{');
            for (i, k) in keys.into_iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                out.push_str(&serde_json::Value::String(k.clone()).to_string());
                out.push(':');
                canonical(&m[k], out);
            }
            out.push('}');
        }
        serde_json::Value::Array(a) => {
            out.push('[');
            for (i, x) in a.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                canonical(x, out);
            }
            out.push(']');
        }
        other => out.push_str(&other.to_string()),
    }
}

/// A layer name: a store name that is also usable as an observation key (no `/`, no spaces).
pub fn check_layer_name(name: &str) -> Result<(), StoreError> {
    check_name("layer", name)?;
    if name.len() > 120 || !name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-')) {
        return Err(StoreError::invalid(format!(
            "invalid layer name {name:?}: up to 120 ASCII letters, digits, '.', '_' or '-' (e.g. features.dp-resnet18)"
        )));
    }
    Ok(())
}

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
        let skipped = episodes.len() - todo.len();
        if todo.is_empty() {
            return Ok(LayerWrite {
                version: None,
                producer_hash: hash,
                episodes_written: 0,
                episodes_skipped: skipped,
            });
        }
        let version = self.store_layer(name, producer, &hash, dim, &todo, actor).await?;
        Ok(LayerWrite {
            version: Some(version),
            producer_hash: hash,
            episodes_written: todo.len(),
            episodes_skipped: skipped,
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
    /// commit) and commits them as a new version: the version.
    async fn store_layer(
        &self,
        name: &str,
        producer: &serde_json::Value,
        hash: &str,
        dim: usize,
        todo: &[&LayerValues],
        actor: &str,
    ) -> Result<i64, StoreError> {
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
        if committed.is_err() {
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
    ) -> Result<i64, StoreError> {
        let mut tx = self.db().begin_version_write().await?;
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
        };
        finish_version(self, tx, head, Default::default(), None).await
    }

    async fn layer_dim(&self, name: &str, hash: &str) -> Result<Option<i64>, StoreError> {
        let r = sqlx::query("SELECT dim FROM layers WHERE name = $1 AND producer_hash = $2")
            .bind(name)
            .bind(hash)
            .fetch_optional(&self.db().pool)
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
            for r in q.fetch_all(&self.db().pool).await? {
                out.insert(r.s("episode_id")?);
            }
        }
        Ok(out)
    }

    /// The episodes (ids, in id order) that hold layer `name` from `producer_hash` now: what a
    /// resumed computation skips.
    pub async fn layer_episodes(&self, name: &str, producer_hash: &str) -> Result<Vec<String>, StoreError> {
        let rows = sqlx::query(
            "SELECT episode_id FROM episode_layers WHERE layer = $1 AND producer_hash = $2 \
             AND version_removed IS NULL ORDER BY episode_id",
        )
        .bind(name)
        .bind(producer_hash)
        .fetch_all(&self.db().pool)
        .await?;
        rows.iter().map(|r| r.s("episode_id")).collect()
    }

    /// Every (layer, producer) the store holds, with how many episodes hold it now.
    pub async fn layers(&self) -> Result<Vec<LayerRecord>, StoreError> {
        let rows = sqlx::query(
            "SELECT l.name, l.producer_hash, l.producer, l.dim, l.version_added, \
             (SELECT COUNT(*) FROM episode_layers e WHERE e.layer = l.name AND e.producer_hash = l.producer_hash \
              AND e.version_removed IS NULL) AS episodes \
             FROM layers l ORDER BY l.name, l.version_added",
        )
        .fetch_all(&self.db().pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(LayerRecord {
                    name: r.s("name")?,
                    producer_hash: r.s("producer_hash")?,
                    producer: serde_json::from_str(&r.s("producer")?)?,
                    dim: r.i("dim")?,
                    episodes: r.i("episodes")?,
                    version: r.i("version_added")?,
                })
            })
            .collect()
    }

    /// The layers an episode holds, now or as of `version`.
    pub async fn episode_layers(
        &self,
        episode_id: &str,
        version: Option<i64>,
    ) -> Result<Vec<EpisodeLayer>, StoreError> {
        let rows = sqlx::query(
            "SELECT e.layer, e.producer_hash, e.version_added, e.version_removed, l.dim FROM episode_layers e \
             JOIN layers l ON l.name = e.layer AND l.producer_hash = e.producer_hash \
             WHERE e.episode_id = $1 ORDER BY e.layer",
        )
        .bind(episode_id)
        .fetch_all(&self.db().pool)
        .await?;
        let mut out = Vec::new();
        for r in rows {
            if visible(r.i("version_added")?, r.oi("version_removed")?, version) {
                out.push(EpisodeLayer {
                    layer: r.s("layer")?,
                    producer_hash: r.s("producer_hash")?,
                    dim: r.i("dim")?,
                    version_added: r.i("version_added")?,
                });
            }
        }
        Ok(out)
    }

    /// Where each episode's values of each layer are (now, or as of `version`): one list per
    /// layer, in the order of `ids`, with the producer of each. An episode without the layer is
    /// [`StoreError::NotFound`] naming both.
    pub async fn locate_layers(
        &self,
        ids: &[String],
        layers: &[String],
        version: Option<i64>,
    ) -> Result<Vec<Vec<(EpisodeLocation, String)>>, StoreError> {
        let mut out = Vec::with_capacity(layers.len());
        for name in layers {
            check_layer_name(name)?;
            let mut found: HashMap<String, (EpisodeLocation, String)> = HashMap::with_capacity(ids.len());
            for chunk in ids.chunks(IDS_PER_QUERY) {
                let marks: Vec<String> = (2..chunk.len() + 2).map(|i| format!("${i}")).collect();
                let sql = format!(
                    "SELECT episode_id, producer_hash, data_file, row_group, row_offset, row_count, version_added, \
                     version_removed FROM episode_layers WHERE layer = $1 AND episode_id IN ({})",
                    marks.join(", ")
                );
                let mut q = sqlx::query(&sql).bind(name.as_str());
                for id in chunk {
                    q = q.bind(id.as_str());
                }
                for r in q.fetch_all(&self.db().pool).await? {
                    if visible(r.i("version_added")?, r.oi("version_removed")?, version) {
                        let (id, loc) = EpisodeLocation::from_row(&r, "episode_id")?;
                        found.insert(id, (loc, r.s("producer_hash")?));
                    }
                }
            }
            let per_id = ids
                .iter()
                .map(|id| {
                    found.remove(id).ok_or_else(|| {
                        let at = version.map_or_else(|| "now".to_string(), |v| format!("in version {v}"));
                        StoreError::not_found(
                            "layer",
                            format!("{name} of episode {id} {at} (see `ufops layers`)"),
                        )
                    })
                })
                .collect::<Result<Vec<_>, _>>()?;
            out.push(per_id);
        }
        Ok(out)
    }

    /// The steps of one episode with the layers joined (as `obs.<layer>` columns).
    pub async fn read_steps_with_layers(
        &self,
        id: &str,
        version: Option<i64>,
        layers: &[String],
    ) -> Result<RecordBatch, StoreError> {
        let ids = [id.to_string()];
        let loc = self.locate_episodes(&ids, version).await?;
        let layer_locs = self.locate_layers(&ids, layers, version).await?;
        let mut stream = self.read_episodes_with_layers(loc, layers.to_vec(), layer_locs);
        match stream.next().await {
            Some(Ok(ep)) => Ok(ep.steps),
            Some(Err(e)) => Err(e.error),
            None => Err(StoreError::Corrupt(format!("episode {id}: the read returned nothing"))),
        }
    }

    /// [`Store::read_episodes`] with layers joined: each episode's steps gain one column
    /// `obs.<layer>` per layer (field metadata [`LAYER_META_KEY`], [`PRODUCER_META_KEY`] and
    /// `ufops.observation_key`), checked step by step (`t`) against the steps. `layer_locations`
    /// come from [`Store::locate_layers`] for the same episodes. Episodes are read in groups of
    /// about `JOIN_GROUP_ROWS` rows: a group's layer values first (each layer file's pages
    /// once), then its steps, joined as they arrive; memory is one group's layer values plus
    /// the steps reads in flight.
    pub fn read_episodes_with_layers(
        &self,
        locations: Vec<EpisodeLocation>,
        layers: Vec<String>,
        layer_locations: Vec<Vec<(EpisodeLocation, String)>>,
    ) -> StepsStream {
        let (tx, rx) = mpsc::channel(16);
        let store = self.clone();
        let task = tokio::spawn(async move {
            // Groups in the steps' file order, so each group's reads stay sequential.
            let mut order: Vec<usize> = (0..locations.len()).collect();
            order.sort_by(|&a, &b| {
                let (x, y) = (&locations[a], &locations[b]);
                (&x.data_file, x.row_group, x.row_offset).cmp(&(&y.data_file, y.row_group, y.row_offset))
            });
            let mut start = 0;
            while start < order.len() {
                let mut end = start;
                let mut rows = 0;
                while end < order.len()
                    && (end == start || rows + locations[order[end]].row_count <= JOIN_GROUP_ROWS)
                {
                    rows += locations[order[end]].row_count;
                    end += 1;
                }
                let group = &order[start..end];
                start = end;
                if !join_group(&store, &locations, &layers, &layer_locations, group, &tx).await {
                    return;
                }
            }
        });
        StepsStream::from_parts(rx, task)
    }
}

/// Reads one group's layer values, then its steps, and sends each episode joined. False when
/// the receiver is gone.
async fn join_group(
    store: &Store,
    locations: &[EpisodeLocation],
    layers: &[String],
    layer_locations: &[Vec<(EpisodeLocation, String)>],
    group: &[usize],
    tx: &mpsc::Sender<Result<EpisodeSteps, StepsReadError>>,
) -> bool {
    // values[layer][position in group] = the value column and its producer.
    type Column = Option<(ArrayRef, Arc<Int32Array>)>;
    let mut values: Vec<Vec<Column>> = vec![vec![None; group.len()]; layers.len()];
    let mut failed: HashMap<usize, StepsReadError> = HashMap::new();
    for (li, locs) in layer_locations.iter().enumerate() {
        let wanted: Vec<EpisodeLocation> = group.iter().map(|&i| locs[i].0.clone()).collect();
        let mut stream = store.read_episodes(wanted);
        while let Some(item) = stream.next().await {
            match item {
                Ok(ep) => {
                    let cols = (ep.steps.column_by_name("value").cloned(), ep.steps.column_by_name("t"));
                    match cols {
                        (Some(v), Some(t)) => match t.as_any().downcast_ref::<Int32Array>() {
                            Some(t) => values[li][ep.index] = Some((v, Arc::new(t.clone()))),
                            None => {
                                let err = StoreError::Corrupt(format!(
                                    "layer {}: column t is not int32",
                                    layers[li]
                                ));
                                failed.insert(
                                    group[ep.index],
                                    read_error(vec![group[ep.index]], &locs[group[ep.index]].0, err),
                                );
                            }
                        },
                        _ => {
                            let err = StoreError::Corrupt(format!(
                                "layer {}: file lacks its value or t column",
                                layers[li]
                            ));
                            failed.insert(
                                group[ep.index],
                                read_error(vec![group[ep.index]], &locs[group[ep.index]].0, err),
                            );
                        }
                    }
                }
                Err(e) => {
                    for k in &e.indexes {
                        let i = group[*k];
                        failed.insert(
                            i,
                            StepsReadError {
                                indexes: vec![i],
                                file: e.file.clone(),
                                error: StoreError::Corrupt(e.error.to_string()),
                            },
                        );
                    }
                }
            }
        }
    }
    let wanted: Vec<EpisodeLocation> = group.iter().map(|&i| locations[i].clone()).collect();
    let mut stream = store.read_episodes(wanted);
    while let Some(item) = stream.next().await {
        let out = match item {
            Err(e) => Err(StepsReadError {
                indexes: e.indexes.iter().map(|k| group[*k]).collect(),
                file: e.file,
                error: e.error,
            }),
            Ok(ep) => {
                let i = group[ep.index];
                match failed.remove(&i) {
                    Some(err) => Err(err),
                    None => join_episode(&ep.steps, layers, layer_locations, &values, ep.index, i)
                        .map(|steps| EpisodeSteps { index: i, steps })
                        .map_err(|error| read_error(vec![i], &locations[i], error)),
                }
            }
        };
        if tx.send(out).await.is_err() {
            return false;
        }
    }
    true
}

fn read_error(indexes: Vec<usize>, loc: &EpisodeLocation, error: StoreError) -> StepsReadError {
    StepsReadError { indexes, file: loc.data_file.clone(), error }
}

#[allow(clippy::type_complexity)]
fn join_episode(
    steps: &RecordBatch,
    layers: &[String],
    layer_locations: &[Vec<(EpisodeLocation, String)>],
    values: &[Vec<Option<(ArrayRef, Arc<Int32Array>)>>],
    pos: usize,
    index: usize,
) -> Result<RecordBatch, StoreError> {
    let steps_t = steps
        .column_by_name("t")
        .and_then(|c| c.as_any().downcast_ref::<Int32Array>())
        .ok_or_else(|| StoreError::Corrupt("steps lack their t column".into()))?;
    let mut fields: Vec<Arc<Field>> = steps.schema().fields().iter().cloned().collect();
    let mut columns: Vec<ArrayRef> = steps.columns().to_vec();
    for (li, name) in layers.iter().enumerate() {
        let (loc, producer) = &layer_locations[li][index];
        let Some((value, t)) = &values[li][pos] else {
            return Err(StoreError::Corrupt(format!(
                "episode {}: layer {name} was not read",
                loc.episode_id
            )));
        };
        if t.values() != steps_t.values() {
            return Err(StoreError::Corrupt(format!(
                "episode {}: layer {name} has {} rows whose steps differ from the episode's {}",
                loc.episode_id,
                t.len(),
                steps_t.len()
            )));
        }
        let column = format!("{OBS_PREFIX}{name}");
        if fields.iter().any(|f| f.name() == &column) {
            return Err(StoreError::invalid(format!(
                "layer {name} shadows the observation key {name:?} of episode {}",
                loc.episode_id
            )));
        }
        let meta = HashMap::from([
            ("ufops.observation_key".to_string(), name.clone()),
            (LAYER_META_KEY.to_string(), name.clone()),
            (PRODUCER_META_KEY.to_string(), producer.clone()),
        ]);
        fields.push(Arc::new(Field::new(column, value.data_type().clone(), false).with_metadata(meta)));
        columns.push(value.clone());
    }
    let schema = Arc::new(Schema::new_with_metadata(fields, steps.schema().metadata().clone()));
    Ok(RecordBatch::try_new(schema, columns)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn producer_hash_ignores_key_order_and_needs_an_object() {
        let a = serde_json::json!({"encoder": "cnn", "policy": "p", "nested": {"b": 1, "a": [1, 2]}});
        let b: serde_json::Value =
            serde_json::from_str(r#"{"nested": {"a": [1, 2], "b": 1}, "policy": "p", "encoder": "cnn"}"#)
                .unwrap();
        assert_eq!(producer_hash(&a).unwrap(), producer_hash(&b).unwrap());
        let c = serde_json::json!({"encoder": "cnn2", "policy": "p", "nested": {"b": 1, "a": [1, 2]}});
        assert_ne!(producer_hash(&a).unwrap(), producer_hash(&c).unwrap());
        assert!(producer_hash(&serde_json::json!("cnn")).is_err());
        assert!(producer_hash(&serde_json::json!({})).is_err());
    }

    #[test]
    fn layer_names_are_observation_keys() {
        assert!(check_layer_name("features.dp-resnet18").is_ok());
        for bad in ["", "a b", "../x", "x/y", "é"] {
            assert!(check_layer_name(bad).is_err(), "{bad:?}");
        }
    }
}
