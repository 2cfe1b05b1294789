//! Training jobs over the store: a split's episodes are read back from their pinned version,
//! turned into [`EpisodeSeries`]s, trained on, and published as an artifact with its lineage. The CLI
//! (`ufops train`), the API's workers and the demo all run training through this one function.

use crate::{
    build_samples, train_samples, write_artifact, EpisodeSeries, EpochReport, InputSpec, Kind, ObsKey,
    TrainConfig,
};
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use store_artifacts::Artifacts;

/// What a training job runs (stored as the job's spec).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainJobSpec {
    pub split_id: String,
    pub kind: Kind,
    /// The recipe (default: the paper's for this kind).
    #[serde(default)]
    pub config: Option<TrainConfig>,
    /// Observation keys, in order (default: every observation column of the episodes).
    #[serde(default)]
    pub obs_keys: Option<Vec<String>>,
    /// `T_o` (default 2).
    #[serde(default)]
    pub obs_history: Option<usize>,
    /// `H`: the policy's chunk length. Default: the length of the chunks the episodes store;
    /// required when they store none (an error names it).
    #[serde(default)]
    pub chunk_len: Option<usize>,
    /// Train only on steps `t` with `t % step_stride == 0`: the steps where a chunking policy
    /// re-planned, i.e. the (obs, chunk, t) the verifier is queried on (default 1: every step).
    #[serde(default)]
    pub step_stride: Option<usize>,
    /// Train an ensemble of this many members (overrides the recipe's `ensemble`; see
    /// `crate::ensemble`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ensemble: Option<usize>,
}

/// A split's episodes, ready for training.
pub struct SplitData {
    pub train: Vec<EpisodeSeries>,
    pub val: Vec<EpisodeSeries>,
    pub input: InputSpec,
    pub version: i64,
}

/// Notes the producer of each layer column among `keys` (field metadata of the joined read);
/// every episode of a training set must hold the same producer's features of a layer.
fn record_producers(
    id: &str,
    batch: &arrow::array::RecordBatch,
    keys: &[String],
    producers: &mut [Option<String>],
) -> Result<()> {
    let schema = batch.schema();
    for (k, slot) in keys.iter().zip(producers.iter_mut()) {
        let Ok(field) = schema.field_with_name(&format!("{}{k}", store::steps::OBS_PREFIX)) else { continue };
        let Some(p) = field.metadata().get(store::PRODUCER_META_KEY) else { continue };
        match slot {
            None => *slot = Some(p.clone()),
            Some(first) if first != p => bail!(
                "layer {k}: episode {id} holds features of producer {}, others of producer {}; \
                 compute the layer with one encoder for every episode of the split",
                verifier::short_hash(p),
                verifier::short_hash(first)
            ),
            _ => {}
        }
    }
    Ok(())
}

/// Reads a split's labeled episodes back from the store, at the split's pinned version; an
/// episode a human took over trains on its steps before the takeover (`policy_steps`).
pub async fn load_split(store: &store::Store, spec: &TrainJobSpec) -> Result<SplitData> {
    let split = store.split(&spec.split_id).await?;
    let members = store.split_episodes(&split.id).await?;
    // Only labeled episodes train; all of them are read in one pass grouped by steps file (each
    // row group once), then put back in the split's order so training stays deterministic.
    let labeled: Vec<(&store::SplitEpisode, bool)> =
        members.iter().filter_map(|m| m.label.as_bool().map(|s| (m, s))).collect();
    let ids: Vec<String> = labeled.iter().map(|(m, _)| m.episode_id.clone()).collect();
    let locations = store.locate_episodes(&ids, Some(split.version)).await?;
    let keys = observation_keys(store, spec, members.first(), split.version).await?;
    let layer_keys = match (&keys, locations.first()) {
        (Some(keys), Some(first)) => layer_keys(store, keys, &first.data_file).await?,
        _ => vec![],
    };
    let mut producers: Vec<Option<String>> = vec![None; keys.as_ref().map_or(0, |k| k.len())];
    let mut episodes: Vec<Option<EpisodeSeries>> = (0..labeled.len()).map(|_| None).collect();
    {
        let wanted = keys.clone().unwrap_or_default();
        let mut stream = if layer_keys.is_empty() {
            store.read_episodes(locations)
        } else {
            let at = store.locate_layers(&ids, &layer_keys, None).await?;
            store.read_episodes_with_layers(locations, layer_keys.clone(), at)
        };
        while let Some(item) = stream.next().await {
            let item = item?;
            let (m, success) = labeled[item.index];
            record_producers(&m.episode_id, &item.steps, &wanted, &mut producers)?;
            let mut ep = verifier::steps::episode_from_steps(&m.episode_id, success, &item.steps, &wanted)?;
            // After a human took over, the rollout is not the checkpoint's own behaviour.
            ep.policy_steps = store::steps::step_flags(&item.steps)?.first_intervention();
            episodes[item.index] = Some(ep);
        }
    }
    let mut train = Vec::new();
    let mut val = Vec::new();
    let mut dims: Vec<usize> = Vec::new();
    let mut chunk_len = None;
    let mut action_dim = 0;
    for ((m, _), ep) in labeled.iter().zip(episodes) {
        let ep = ep.with_context(|| format!("episode {} was not read", m.episode_id))?;
        if dims.is_empty() {
            dims = ep.obs.iter().map(|o| o.dim).collect();
            action_dim = ep.action_dim;
            chunk_len = ep.action_chunk.as_ref().map(|(h, _)| *h);
        }
        if m.part == "val" {
            val.push(ep)
        } else {
            train.push(ep)
        }
    }
    let keys = keys.unwrap_or_default();
    let chunk_len = resolve_chunk_len(chunk_len, spec.chunk_len, &split.id)?;
    if let Some(stride) = spec.step_stride.filter(|s| *s > 1 && *s != chunk_len) {
        tracing::warn!("step_stride {stride} differs from the chunk length {chunk_len}: a chunking policy re-plans every chunk");
    }
    if train.is_empty() {
        bail!("split {} has no labeled training episodes", split.id);
    }
    if keys.is_empty() {
        bail!("the episodes of split {} have no observation columns", split.id);
    }
    let input = InputSpec {
        obs_keys: keys
            .iter()
            .zip(&dims)
            .zip(producers)
            .map(|((k, d), producer)| ObsKey { key: k.clone(), dim: *d, producer })
            .collect(),
        obs_history: spec.obs_history.unwrap_or(2),
        chunk_len,
        action_dim,
        t_embed_dim: spec.config.as_ref().map(|c| c.architecture.t_embed_dim).unwrap_or(64),
        extra_inputs: vec![],
    };
    Ok(SplitData { train, val, input, version: split.version })
}

/// The observation keys to train on: the spec's, or else the observation columns of the split's
/// first episode (`None` for an empty split).
async fn observation_keys(
    store: &store::Store,
    spec: &TrainJobSpec,
    first: Option<&store::SplitEpisode>,
    version: i64,
) -> Result<Option<Vec<String>>> {
    Ok(match (&spec.obs_keys, first) {
        (Some(k), _) => Some(k.clone()),
        (None, Some(first)) => {
            let at = store.locate_episodes(std::slice::from_ref(&first.episode_id), Some(version)).await?;
            let schema = store.steps_schema(&at[0].data_file).await?;
            Some(store::steps::observation_keys(schema.as_ref()).into_iter().map(|(k, _)| k).collect())
        }
        (None, None) => None,
    })
}

/// Keys the steps files lack (judged by `data_file`, one of them) but a layer of the store
/// provides (an encoder's features): read joined, from the layer values current now (derived
/// data computed after the split was frozen counts; the producer recorded with the input spec
/// pins what they were).
async fn layer_keys(store: &store::Store, keys: &[String], data_file: &str) -> Result<Vec<String>> {
    let schema = store.steps_schema(data_file).await?;
    let names: std::collections::HashSet<String> =
        store.layers().await?.into_iter().map(|l| l.name).collect();
    Ok(keys
        .iter()
        .filter(|k| {
            schema.field_with_name(&format!("{}{k}", store::steps::OBS_PREFIX)).is_err() && names.contains(*k)
        })
        .cloned()
        .collect())
}

/// The verifier's chunk length: the one the episodes store (a different one given is refused:
/// its chunks would straddle the policy's own), else the one given.
fn resolve_chunk_len(stored: Option<usize>, given: Option<usize>, split_id: &str) -> Result<usize> {
    Ok(match (stored, given) {
        (Some(stored), Some(given)) if stored != given => bail!(
            "the episodes store action chunks of length {stored}: chunk_len {given} would build chunks that straddle \
             the policy's own; leave it out (it is inferred) or give {stored}"
        ),
        (Some(stored), _) => stored,
        (None, Some(given)) => given,
        // A guess here (the paper's 16) trained verifiers over chunks straddling the policy's own,
        // found only when scoring: the policy's chunk length is asked for instead.
        (None, None) => bail!(
            "the episodes of split {split_id} store no action chunks, so the verifier's chunk length is unknown: give \
             the policy's chunk length, the number of actions it executes per prediction (--chunk-len N, or \
             chunk_len in the recipe file; 1 for a policy that acts one step at a time)"
        ),
    })
}

/// Runs a training job end to end and publishes the artifact (which becomes `latest`).
pub async fn run_train_job(
    store: &store::Store,
    spec: &TrainJobSpec,
    job_id: Option<&str>,
    observer: Box<dyn FnMut(&EpochReport) + Send>,
    cancel: Option<Arc<AtomicBool>>,
) -> Result<store_artifacts::ArtifactRecord> {
    let split = store.split(&spec.split_id).await?;
    let data = load_split(store, spec).await?;
    // The paper's recipe for its input: the image column (features variant) when the
    // observation includes an encoder's features, else the low-dimensional one.
    let sees = !data.input.required_producers().is_empty();
    let variant = if sees { crate::Variant::Features } else { crate::Variant::Lowdim };
    let mut cfg = spec.config.clone().unwrap_or_else(|| TrainConfig::preset(spec.kind, variant));
    cfg.kind = spec.kind;
    if let Some(k) = spec.ensemble {
        cfg.ensemble = k;
    }
    cfg.validate()?;
    let lineage = serde_json::json!({
        "store_version": split.version,
        "label_snapshot_version": split.version,
        "split_id": split.id,
        "split_mode": split.mode,
        "source_checkpoints": split.source_checkpoints,
        "policy": split.policy,
        "checkpoint": split.checkpoint,
        "train_episodes": data.train.len(),
        "val_episodes": data.val.len(),
        "train_successes": data.train.iter().filter(|e| e.success).count(),
        "val_successes": data.val.iter().filter(|e| e.success).count(),
        "job_id": job_id,
        "step_stride": spec.step_stride.unwrap_or(1),
        "layers": data.input.required_producers().iter()
            .map(|(k, p)| serde_json::json!({"layer": k, "producer_hash": p}))
            .collect::<Vec<_>>(),
        "code_version": concat!("ufops-trainer ", env!("CARGO_PKG_VERSION")),
    });
    let dir = tempfile::tempdir().context("creating a temporary artifact directory")?;
    let out = dir.path().to_path_buf();
    let stride = spec.step_stride.unwrap_or(1).max(1) as u32;
    let trained = tokio::task::spawn_blocking(move || -> Result<()> {
        let mut observer = observer;
        let keep = |t: u32| t.is_multiple_of(stride);
        let tr = build_samples(&data.train, &data.input, cfg.gamma)
            .context("building train samples")?
            .filter_steps(keep);
        let va = build_samples(&data.val, &data.input, cfg.gamma)
            .context("building validation samples")?
            .filter_steps(keep);
        let t = train_samples(tr, va, &data.input, &cfg, &mut *observer, cancel.as_deref())?;
        write_artifact(&out, &t, lineage)?;
        Ok(())
    });
    trained.await.context("training thread panicked")??;
    let kind = match spec.kind {
        Kind::Classifier => "classifier",
        Kind::Q => "q",
    };
    let rec = store
        .publish_artifact(store_artifacts::NewArtifact {
            dir: dir.path(),
            policy: &split.policy,
            checkpoint: &split.checkpoint,
            kind,
            split_id: Some(&split.id),
            job_id,
        })
        .await?;
    Ok(rec)
}
