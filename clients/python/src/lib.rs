//! `ufops-py`: the native module `ufops._ufops` of the Python package `ufops` (clients/python).
//!
//! It owns the bindings only: the verifier core (`verifier`: checked loading, forward pass and
//! gradient) and steer's HTTP loader as `ufops.Verifier`, the failure monitor as `ufops.Monitor`, the store's read path as
//! `ufops.Store`, the steering-telemetry sidecar writer, and the exception hierarchy. Nothing numeric is re-implemented here or in the
//! Python layer (python/ufops), which adds types, docstrings and the PyTorch helpers.

mod arrays;
mod errors;
mod monitor;
mod store;
mod verifier;

use pyo3::prelude::*;

/// Writes an artifact with random weights (`verifier::testutil`) of the given dimensions
/// ("square": the paper's Square task; "nav", "nav_features": the 2-D task) into `dir` and
/// returns its id; `metrics_json` becomes its `config.json` metrics (e.g. a flagged
/// action-sensitivity figure); `members` > 1 writes an ensemble of that many random networks.
/// For the tests and the benchmark (feature `testing`): it is not a trained verifier.
#[cfg(feature = "testing")]
#[pyfunction]
#[pyo3(signature = (dir, dims, seed, metrics_json=None, members=1))]
fn write_random_artifact(
    py: Python<'_>,
    dir: std::path::PathBuf,
    dims: &str,
    seed: u64,
    metrics_json: Option<&str>,
    members: usize,
) -> PyResult<String> {
    use ::verifier::testutil::RandomSpec;
    use pyo3::exceptions::PyValueError;
    let spec = match dims {
        "square" => RandomSpec::square(),
        "nav" => RandomSpec::nav(),
        "nav_features" => RandomSpec::nav_features(),
        other => {
            return Err(PyValueError::new_err(format!("unknown dims {other:?}: square, nav or nav_features")))
        }
    };
    let metrics = metrics_json
        .map(serde_json::from_str::<serde_json::Value>)
        .transpose()
        .map_err(|e| PyValueError::new_err(format!("metrics_json: {e}")))?;
    py.detach(|| {
        let (mut config, weights) =
            if members > 1 { spec.build_ensemble(seed, members) } else { spec.build(seed) };
        if let Some(m) = metrics {
            config.metrics = m;
        }
        let files = ::verifier::ArtifactFiles::build(&config, &weights)?;
        files.write_dir(&dir)?;
        Ok(files.id)
    })
    .map_err(errors::from_verifier)
}

/// One best-of-N step as the Python layer hands it over: `(episode_index, t, artifact_id,
/// candidates (raw, N * act_dim), scores (N), chosen, latency_us)`.
type SteeringRecord = (u64, u32, String, Vec<f32>, Vec<f32>, u32, u32);

/// Writes a steering sidecar (`verifier::steps::steering_sidecar_batch`: what `ufops ingest`
/// attaches to the episodes of the source it lies beside) at `path`, through a temporary file
/// renamed into place; returns the number of records.
#[pyfunction]
fn write_steering_log(
    py: Python<'_>,
    path: std::path::PathBuf,
    records: Vec<SteeringRecord>,
) -> PyResult<usize> {
    use pyo3::exceptions::{PyOSError, PyValueError};
    let n = records.len();
    py.detach(|| -> PyResult<()> {
        let records: Vec<(u64, ::verifier::SteeringStep)> = records
            .into_iter()
            .map(|(e, t, artifact_id, candidates, scores, chosen, latency_us)| {
                (e, ::verifier::SteeringStep { t, artifact_id, candidates, scores, chosen, latency_us })
            })
            .collect();
        let batch = ::verifier::steps::steering_sidecar_batch(&records).map_err(errors::from_verifier)?;
        let io = |e: std::io::Error| PyOSError::new_err(format!("{}: {e}", path.display()));
        let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(std::path::Path::new("."));
        let tmp = tempfile::NamedTempFile::new_in(dir).map_err(io)?;
        let props = parquet::file::properties::WriterProperties::builder()
            .set_compression(parquet::basic::Compression::ZSTD(Default::default()))
            .build();
        let mut w = parquet::arrow::ArrowWriter::try_new(tmp.as_file(), batch.schema(), Some(props))
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        w.write(&batch).map_err(|e| PyValueError::new_err(e.to_string()))?;
        w.close().map_err(|e| PyValueError::new_err(e.to_string()))?;
        tmp.as_file().sync_all().map_err(io)?;
        tmp.persist(&path).map_err(|e| io(e.error))?;
        Ok(())
    })?;
    Ok(n)
}

#[pymodule]
fn _ufops(m: &Bound<'_, PyModule>) -> PyResult<()> {
    errors::register(m)?;
    m.add_class::<verifier::PyVerifier>()?;
    m.add_class::<monitor::PyMonitor>()?;
    m.add_class::<store::PyStore>()?;
    m.add_function(wrap_pyfunction!(store::episodes_ipc_from_json, m)?)?;
    m.add_function(wrap_pyfunction!(write_steering_log, m)?)?;
    #[cfg(feature = "testing")]
    m.add_function(wrap_pyfunction!(write_random_artifact, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
