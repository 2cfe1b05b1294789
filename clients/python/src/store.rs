//! `ufops.Store`: the store's read path (catalog queries and the Parquet steps reader) for a
//! local data directory or Postgres + S3, read-only. Episodes (of `store::episodes_schema`) and
//! steps cross into Python as Arrow IPC streams (polars and pyarrow read them without a second
//! Arrow binding in this crate), other records as JSON; the Python class `ufops.Store` composes
//! this one. One Tokio runtime, made on first use, runs the store's async reads.

use std::path::PathBuf;
use std::sync::OnceLock;

use arrow::ipc::writer::StreamWriter;
use numpy::{PyArray1, PyArray2, PyArrayMethods};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyBytes;

use crate::errors::{from_store, from_verifier, NotFoundError};
use crate::verifier::PyVerifier;
use store_artifacts::{Artifacts, Monitors};

/// A stored episode's verifier inputs: `(obs (T, obs_dim), t (T,), act (T, act_dim))`.
type StepInputs<'py> = (Bound<'py, PyArray2<f32>>, Bound<'py, PyArray1<u32>>, Bound<'py, PyArray2<f32>>);

/// Episode records as one Arrow IPC stream (the store's one definition of their columns).
fn episodes_stream(records: &[store::EpisodeRecord]) -> PyResult<Vec<u8>> {
    let batch = store::episodes_batch(records).map_err(from_store)?;
    let ipc_err = |e: arrow::error::ArrowError| PyRuntimeError::new_err(format!("writing Arrow IPC: {e}"));
    let mut w = StreamWriter::try_new(Vec::new(), &batch.schema()).map_err(ipc_err)?;
    w.write(&batch).map_err(ipc_err)?;
    w.into_inner().map_err(ipc_err)
}

/// Episode records as the API returns them (a JSON list) → one Arrow IPC stream of the same
/// columns as `Store.episodes_ipc`, so both reach Python through one schema.
#[pyfunction]
pub(crate) fn episodes_ipc_from_json<'py>(
    py: Python<'py>,
    records_json: &str,
) -> PyResult<Bound<'py, PyBytes>> {
    let records: Vec<store::EpisodeRecord> = serde_json::from_str(records_json)
        .map_err(|e| PyValueError::new_err(format!("episode records: {e}")))?;
    let stream = py.detach(|| episodes_stream(&records))?;
    Ok(PyBytes::new(py, &stream))
}

fn runtime() -> PyResult<&'static tokio::runtime::Runtime> {
    static RT: OnceLock<tokio::runtime::Runtime> = OnceLock::new();
    if let Some(rt) = RT.get() {
        return Ok(rt);
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("ufops-store")
        .enable_all()
        .build()
        .map_err(|e| PyRuntimeError::new_err(format!("cannot start the store's runtime: {e}")))?;
    Ok(RT.get_or_init(|| rt))
}

fn json<T: serde::Serialize>(v: &T) -> PyResult<String> {
    serde_json::to_string(v).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// A ufops store opened read-only.
#[pyclass(module = "ufops._ufops", name = "Store", frozen)]
pub struct PyStore {
    store: store::Store,
    describe: String,
}

impl PyStore {
    /// The steps of episodes `ids` (in that order) with `layers` joined, as of `version`: one
    /// batch per episode (`None` where the read returned nothing).
    fn read_steps(
        &self,
        ids: &[String],
        version: Option<i64>,
        layers: Vec<String>,
    ) -> PyResult<Vec<Option<arrow::array::RecordBatch>>> {
        runtime()?
            .block_on(async {
                let locations = self.store.locate_episodes(ids, version).await?;
                let mut batches = vec![None; locations.len()];
                let mut stream = if layers.is_empty() {
                    self.store.read_episodes(locations)
                } else {
                    let at = self.store.locate_layers(ids, &layers, version).await?;
                    self.store.read_episodes_with_layers(locations, layers, at)
                };
                while let Some(item) = stream.next().await {
                    let ep = item?;
                    batches[ep.index] = Some(ep.steps);
                }
                Ok::<_, store::StoreError>(batches)
            })
            .map_err(from_store)
    }
}

#[pymethods]
impl PyStore {
    /// Opens the store in `data_dir` (its SQLite catalog and local objects), or the catalog at
    /// `database_url` (`postgres://…`, `sqlite://…`) with the objects at `object_store`
    /// (a path or `s3://bucket/prefix`). Nothing is created: a missing store is NotFoundError.
    #[new]
    #[pyo3(signature = (data_dir=None, *, database_url=None, object_store=None))]
    fn new(
        py: Python<'_>,
        data_dir: Option<PathBuf>,
        database_url: Option<String>,
        object_store: Option<String>,
    ) -> PyResult<Self> {
        if data_dir.is_none() && database_url.is_none() {
            return Err(PyValueError::new_err("pass a data directory or database_url"));
        }
        let data_dir = data_dir.unwrap_or_else(|| PathBuf::from("."));
        if database_url.is_none() && !data_dir.join("catalog.sqlite").is_file() {
            return Err(NotFoundError::new_err(format!(
                "no ufops store in {} (no catalog.sqlite): create one with `ufops init`",
                data_dir.display()
            )));
        }
        let config = store::StoreConfig { data_dir, database_url, object_store_url: object_store };
        let rt = runtime()?;
        let store = py.detach(|| rt.block_on(store::Store::open(&config))).map_err(from_store)?;
        let describe = store.describe();
        Ok(PyStore { store, describe })
    }

    fn __repr__(&self) -> String {
        format!("Store({})", self.describe)
    }

    /// The latest committed version.
    fn head_version(&self, py: Python<'_>) -> PyResult<i64> {
        py.detach(|| runtime()?.block_on(self.store.head_version()).map_err(from_store))
    }

    /// The versions as a JSON list (see `ufops versions --json`).
    fn versions_json(&self, py: Python<'_>) -> PyResult<String> {
        let v = py.detach(|| runtime()?.block_on(self.store.versions()).map_err(from_store))?;
        json(&v)
    }

    /// Episodes as one Arrow IPC stream of [`store::episodes_schema`] (the records `ufops episodes
    /// --json` prints), now or at `version`.
    #[pyo3(signature = (version=None, policy=None, checkpoint=None, task=None, label=None, tag=None, after=None, limit=None))]
    #[allow(clippy::too_many_arguments)]
    fn episodes_ipc<'py>(
        &self,
        py: Python<'py>,
        version: Option<i64>,
        policy: Option<String>,
        checkpoint: Option<String>,
        task: Option<String>,
        label: Option<String>,
        tag: Option<String>,
        after: Option<String>,
        limit: Option<i64>,
    ) -> PyResult<Bound<'py, PyBytes>> {
        let label = label.as_deref().map(str::parse::<store::Label>).transpose().map_err(from_store)?;
        let filter = store::EpisodeFilter {
            version,
            policy,
            checkpoint,
            task,
            label,
            tag,
            after,
            limit,
            ..Default::default()
        };
        let stream = py.detach(|| {
            let eps = runtime()?.block_on(self.store.episodes(&filter)).map_err(from_store)?;
            episodes_stream(&eps)
        })?;
        Ok(PyBytes::new(py, &stream))
    }

    /// The steps of the episodes `ids` (in that order) as Arrow IPC streams: one stream per run
    /// of episodes sharing a schema (usually one in all).
    /// `layers` joins those layers' values as `obs.<layer>` columns.
    #[pyo3(signature = (ids, version=None, layers=None))]
    fn steps_ipc<'py>(
        &self,
        py: Python<'py>,
        ids: Vec<String>,
        version: Option<i64>,
        layers: Option<Vec<String>>,
    ) -> PyResult<Vec<Bound<'py, PyBytes>>> {
        let streams = py.detach(|| -> PyResult<Vec<Vec<u8>>> {
            let batches = self.read_steps(&ids, version, layers.unwrap_or_default())?;
            let ipc_err =
                |e: arrow::error::ArrowError| PyRuntimeError::new_err(format!("writing Arrow IPC: {e}"));
            let mut streams = Vec::new();
            let mut writer: Option<(StreamWriter<Vec<u8>>, arrow::datatypes::SchemaRef)> = None;
            for (id, b) in ids.iter().zip(batches) {
                let b = b.ok_or_else(|| {
                    NotFoundError::new_err(format!("episode {id}: the read returned nothing"))
                })?;
                if writer.as_ref().is_some_and(|(_, s)| *s != b.schema()) {
                    streams.push(writer.take().expect("checked").0.into_inner().map_err(ipc_err)?);
                }
                if writer.is_none() {
                    writer =
                        Some((StreamWriter::try_new(Vec::new(), &b.schema()).map_err(ipc_err)?, b.schema()));
                }
                writer.as_mut().expect("set above").0.write(&b).map_err(ipc_err)?;
            }
            if let Some((w, _)) = writer {
                streams.push(w.into_inner().map_err(ipc_err)?);
            }
            Ok(streams)
        })?;
        Ok(streams.iter().map(|s| PyBytes::new(py, s)).collect())
    }

    /// The layers (name, producer, dim, episodes holding it now) as a JSON list.
    fn layers_json(&self, py: Python<'_>) -> PyResult<String> {
        let v = py.detach(|| runtime()?.block_on(self.store.layers()).map_err(from_store))?;
        json(&v)
    }

    /// The layers an episode holds, now or at `version`, as a JSON list.
    #[pyo3(signature = (episode_id, version=None))]
    fn episode_layers_json(
        &self,
        py: Python<'_>,
        episode_id: &str,
        version: Option<i64>,
    ) -> PyResult<String> {
        let v = py.detach(|| {
            runtime()?.block_on(self.store.episode_layers(episode_id, version)).map_err(from_store)
        })?;
        json(&v)
    }

    /// The episodes (ids) that hold layer `name` from the producer `producer_hash` now.
    fn layer_episodes(&self, py: Python<'_>, name: &str, producer_hash: &str) -> PyResult<Vec<String>> {
        py.detach(|| runtime()?.block_on(self.store.layer_episodes(name, producer_hash)).map_err(from_store))
    }

    /// The sha256 of a producer (a JSON object) as the store computes it.
    #[staticmethod]
    fn producer_hash(producer_json: &str) -> PyResult<String> {
        let p: serde_json::Value = serde_json::from_str(producer_json)
            .map_err(|e| PyValueError::new_err(format!("producer: {e}")))?;
        store::producer_hash(&p).map_err(from_store)
    }

    /// Writes one group of episodes' values of layer `name` (one float32 array of shape
    /// `(steps, dim)` per episode id) as a new version; episodes holding it from this producer
    /// already are skipped. Returns what was done as JSON (`version` null when nothing was).
    #[pyo3(signature = (name, producer_json, episode_ids, values, actor="python"))]
    fn write_layer_arrays(
        &self,
        py: Python<'_>,
        name: &str,
        producer_json: &str,
        episode_ids: Vec<String>,
        values: Vec<numpy::PyReadonlyArray2<'_, f32>>,
        actor: &str,
    ) -> PyResult<String> {
        use numpy::PyUntypedArrayMethods;
        if episode_ids.len() != values.len() {
            return Err(PyValueError::new_err(format!(
                "{} episode ids but {} value arrays",
                episode_ids.len(),
                values.len()
            )));
        }
        let producer: serde_json::Value = serde_json::from_str(producer_json)
            .map_err(|e| PyValueError::new_err(format!("producer: {e}")))?;
        let mut eps = Vec::with_capacity(values.len());
        for (id, a) in episode_ids.into_iter().zip(&values) {
            let dim = a.shape()[1];
            let flat: Vec<f32> = match a.as_slice() {
                Ok(s) => s.to_vec(),
                Err(_) => a.as_array().iter().copied().collect(),
            };
            eps.push(store::LayerValues { episode_id: id, dim, values: flat });
        }
        let done = py.detach(|| {
            runtime()?.block_on(self.store.write_layer(name, &producer, eps, actor)).map_err(from_store)
        })?;
        json(&done)
    }

    /// The size of a store object (a video the steps name in `media.<camera>.path`).
    fn object_size(&self, py: Python<'_>, path: &str) -> PyResult<u64> {
        py.detach(|| runtime()?.block_on(self.store.object_size(path)).map_err(from_store))
    }

    /// Bytes `start..end` of a store object (one ranged read; on S3 a ranged GET).
    fn read_object_range<'py>(
        &self,
        py: Python<'py>,
        path: &str,
        start: u64,
        end: u64,
    ) -> PyResult<Bound<'py, PyBytes>> {
        if end < start || end - start > (256 << 20) {
            return Err(PyValueError::new_err(format!(
                "range {start}..{end}: at most 256 MiB, end >= start"
            )));
        }
        let b = py.detach(|| {
            runtime()?.block_on(self.store.get_object_range(path, start..end)).map_err(from_store)
        })?;
        Ok(PyBytes::new(py, &b))
    }

    /// The splits as a JSON list of records.
    fn splits_json(&self, py: Python<'_>) -> PyResult<String> {
        let v = py.detach(|| runtime()?.block_on(self.store.splits()).map_err(from_store))?;
        json(&v)
    }

    /// A split's members (episode, part, label) as a JSON list.
    fn split_episodes_json(&self, py: Python<'_>, split_id: &str) -> PyResult<String> {
        let v = py.detach(|| runtime()?.block_on(self.store.split_episodes(split_id)).map_err(from_store))?;
        json(&v)
    }

    /// The artifacts as a JSON list of records (with their aliases).
    #[pyo3(signature = (policy=None, checkpoint=None, kind=None))]
    fn artifacts_json(
        &self,
        py: Python<'_>,
        policy: Option<&str>,
        checkpoint: Option<&str>,
        kind: Option<&str>,
    ) -> PyResult<String> {
        let v = py.detach(|| {
            runtime()?.block_on(self.store.artifacts(policy, checkpoint, kind)).map_err(from_store)
        })?;
        json(&v)
    }

    /// The monitor `reference` (an id or `POLICY/CHECKPOINT@ALIAS`) as JSON: its record, the
    /// evaluation its calibration measured, its aliases.
    fn monitor_json(&self, py: Python<'_>, reference: &str) -> PyResult<String> {
        let m =
            py.detach(|| runtime()?.block_on(self.store.resolve_monitor(reference)).map_err(from_store))?;
        json(&m)
    }

    /// The monitors as a JSON list (narrowed by policy, checkpoint and artifact).
    #[pyo3(signature = (policy=None, checkpoint=None, artifact=None))]
    fn monitors_json(
        &self,
        py: Python<'_>,
        policy: Option<&str>,
        checkpoint: Option<&str>,
        artifact: Option<&str>,
    ) -> PyResult<String> {
        let v = py.detach(|| {
            runtime()?.block_on(self.store.monitors(policy, checkpoint, artifact)).map_err(from_store)
        })?;
        json(&v)
    }

    /// The verifier inputs of every step of a stored episode, built by the verifier core exactly
    /// as training and `ufops monitor evaluate` build them: `(obs (T, obs_dim), t (T,), act
    /// (T, act_dim))`, with the layers the verifier reads joined.
    #[pyo3(signature = (episode_id, verifier, version=None))]
    fn step_inputs<'py>(
        &self,
        py: Python<'py>,
        episode_id: String,
        verifier: &PyVerifier,
        version: Option<i64>,
    ) -> PyResult<StepInputs<'py>> {
        let v = &verifier.v;
        let samples = py.detach(|| -> PyResult<verifier::Samples> {
            let layers: Vec<String> =
                v.config().input.layout.required_producers().iter().map(|(k, _)| k.to_string()).collect();
            let batch = self.read_steps(std::slice::from_ref(&episode_id), version, layers)?.pop().flatten();
            let batch = batch.ok_or_else(|| {
                NotFoundError::new_err(format!("episode {episode_id}: the read returned nothing"))
            })?;
            verifier::steps::step_inputs(v.config(), &batch).map_err(from_verifier)
        })?;
        let rows = samples.t.len();
        let shaped = |data: Vec<f32>, width: usize| -> PyResult<Bound<'py, PyArray2<f32>>> {
            PyArray1::from_vec(py, data)
                .reshape([rows, width])
                .map_err(|e| PyValueError::new_err(e.to_string()))
        };
        Ok((
            shaped(samples.obs, v.obs_dim())?,
            PyArray1::from_vec(py, samples.t),
            shaped(samples.act, v.act_dim())?,
        ))
    }

    /// Loads the verifier `reference` (an artifact id or `POLICY/CHECKPOINT/KIND@ALIAS`) from
    /// the store, every file checked against the manifest by the verifier core.
    pub(crate) fn verifier(&self, py: Python<'_>, reference: &str) -> PyResult<PyVerifier> {
        py.detach(|| {
            let rt = runtime()?;
            let rec = rt.block_on(self.store.resolve_artifact(reference)).map_err(from_store)?;
            let get = |name: &str| -> Result<Vec<u8>, verifier::VerifierError> {
                rt.block_on(self.store.get_object(&format!("{}/{name}", rec.prefix)))
                    .map(|b| b.to_vec())
                    .map_err(|e| verifier::VerifierError::Fetch { file: name.into(), message: e.to_string() })
            };
            let manifest = get(verifier::MANIFEST_FILE).map_err(from_verifier)?;
            let v = verifier::Verifier::load_with(&manifest, get).map_err(from_verifier)?;
            if v.id() != Some(rec.id.as_str()) {
                return Err(crate::errors::IntegrityError::new_err(format!(
                    "artifact {}: its manifest.json hashes to {}",
                    rec.id,
                    v.id().unwrap_or("-")
                )));
            }
            Ok(PyVerifier { v })
        })
    }
}
