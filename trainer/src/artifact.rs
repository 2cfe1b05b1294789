//! Verifier artifacts (see ARTIFACT.md): the trainer writes them, and scores rows with them,
//! through the `verifier` core — its format types, its file writer and its forward pass — so
//! `ufops score`, the viewer and the robot run one implementation.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::{ensure, Context, Result};
use rand::SeedableRng;
use serde::{Deserialize, Serialize};

use crate::model::{CandleModel, Kind, ModelSpec, ParamSet};
use crate::train::Trained;

pub use verifier::{
    artifact_id, sha256_hex, ActionSpace, ArtifactConfig, ArtifactFiles, EnsembleSpec, InputConfig, Manifest,
    Verifier, Weights, CONFIG_FILE, ENSEMBLE_SCHEMA_VERSION, MANIFEST_FILE, MODEL_FILE, SCHEMA_VERSION,
};

/// What [`write_artifact`] wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct ArtifactInfo {
    /// First 16 hex digits of sha256(manifest.json).
    pub id: String,
    pub dir: PathBuf,
    pub manifest: Manifest,
}

/// The model spec an artifact's configuration describes.
pub fn model_spec(cfg: &ArtifactConfig) -> ModelSpec {
    ModelSpec {
        kind: cfg.kind,
        arch: cfg.architecture.clone(),
        obs_dim: cfg.input.obs_dim,
        act_dim: cfg.input.act_dim,
    }
}

/// Build `config.json` for a trained model.
pub fn artifact_config(t: &Trained, lineage: serde_json::Value) -> Result<ArtifactConfig> {
    let mut layout = t.input.clone();
    layout.t_embed_dim = t.spec.arch.t_embed_dim;
    let ensemble = (!t.members.is_empty()).then(|| EnsembleSpec::new(t.members.len()));
    let mut metrics = serde_json::json!({
        "final": t.metrics,
        "history": t.history,
    });
    if let Some(e) = &t.ensemble {
        metrics["ensemble"] = serde_json::to_value(e)?;
    }
    Ok(ArtifactConfig {
        schema_version: if ensemble.is_some() { ENSEMBLE_SCHEMA_VERSION } else { SCHEMA_VERSION },
        kind: t.spec.kind,
        architecture: t.spec.arch.clone(),
        input: InputConfig {
            obs_dim: layout.obs_dim(),
            act_dim: layout.act_dim(),
            layout,
            obs_mean: t.norm.obs_mean.clone(),
            obs_std: t.norm.obs_std.clone(),
            act_mean: t.norm.act_mean.clone(),
            act_std: t.norm.act_std.clone(),
            action_space: t.action_space.clone(),
        },
        gamma: (t.spec.kind == Kind::Q).then_some(t.config.gamma),
        hyperparameters: serde_json::to_value(&t.config)?,
        metrics,
        lineage,
        ensemble,
    })
}

/// The weights of a trained model: one network's, or every member's under its prefix.
pub fn trained_weights(t: &Trained) -> Result<Weights> {
    if t.members.is_empty() {
        return t.params.to_weights();
    }
    let mut w = Weights::default();
    for (k, p) in t.members.iter().enumerate() {
        t.spec.check_params(p)?;
        let prefix = verifier::member_prefix(k);
        for ((n, s), v) in p.names.iter().zip(&p.shapes).zip(&p.values) {
            w.insert(&format!("{prefix}{n}"), s.clone(), v.clone())?;
        }
    }
    Ok(w)
}

/// The core's verifier of a trained model (no artifact written; no id).
pub fn verifier_of(t: &Trained) -> Result<Verifier> {
    let cfg = artifact_config(t, serde_json::Value::Null)?;
    Ok(Verifier::new(cfg, &trained_weights(t)?)?)
}

/// Write the artifact files of `trained` into `dir` (created if needed). `lineage` is stored
/// as-is (store version, label snapshot, split id, episode counts, code version...).
pub fn write_artifact(dir: &Path, trained: &Trained, lineage: serde_json::Value) -> Result<ArtifactInfo> {
    let cfg = artifact_config(trained, lineage)?;
    if trained.members.is_empty() {
        return write_parts(dir, &cfg, &trained.params);
    }
    let files = ArtifactFiles::build(&cfg, &trained_weights(trained)?)?;
    files.write_dir(dir).with_context(|| format!("writing the artifact into {}", dir.display()))?;
    let manifest = Manifest::parse(&files.manifest)?;
    Ok(ArtifactInfo { id: files.id, dir: dir.to_path_buf(), manifest })
}

/// Write an artifact from its parts (through the core's writer).
pub fn write_parts(dir: &Path, cfg: &ArtifactConfig, params: &ParamSet) -> Result<ArtifactInfo> {
    model_spec(cfg).check_params(params)?;
    let files = ArtifactFiles::build(cfg, &params.to_weights()?)?;
    files.write_dir(dir).with_context(|| format!("writing the artifact into {}", dir.display()))?;
    let manifest = Manifest::parse(&files.manifest)?;
    Ok(ArtifactInfo { id: files.id, dir: dir.to_path_buf(), manifest })
}

/// A loaded, checked artifact: its configuration, parameters (an ensemble's member 0) and the
/// core's verifier (every member).
pub struct TrainedArtifact {
    pub id: String,
    pub dir: PathBuf,
    pub config: ArtifactConfig,
    pub spec: ModelSpec,
    pub params: ParamSet,
    pub verifier: Verifier,
}

/// Load an artifact directory through the core (every sha256 checked, schema, variant,
/// tensors).
pub fn load_artifact(dir: &Path) -> Result<TrainedArtifact> {
    let a = verifier::Artifact::load_dir(dir)?;
    let spec = model_spec(&a.config);
    let params = if a.config.ensemble.is_some() {
        let prefix = verifier::member_prefix(0);
        let mut first = Weights::default();
        for (name, t) in a.weights.iter() {
            if let Some(rest) = name.strip_prefix(&prefix) {
                first.insert(rest, t.shape.clone(), t.data.clone())?;
            }
        }
        ParamSet::from_weights(&spec, &first)?
    } else {
        ParamSet::from_weights(&spec, &a.weights)?
    };
    let verifier = a.verifier()?;
    Ok(TrainedArtifact {
        id: a.id.context("an artifact loaded from a directory has an id")?,
        dir: dir.to_path_buf(),
        config: a.config,
        spec,
        params,
        verifier,
    })
}

impl TrainedArtifact {
    /// Scores: classifier `sigmoid(logit)`, Q the value.
    pub fn score(&self, rows: &[ScoreRow]) -> Result<Vec<f32>> {
        score_rows(&self.verifier, rows)
    }

    /// The candle graph of these weights (spectral norm already folded in), for comparisons
    /// with the core's forward pass and gradient.
    pub fn candle_model(&self) -> Result<CandleModel> {
        let mut spec = self.spec.clone();
        spec.arch.spectral_norm = false; // weights are stored already divided by sigma
        CandleModel::new(&spec, &self.params, &mut rand_chacha::ChaCha8Rng::seed_from_u64(0))
    }

    /// Scores and guidance gradients of rows from the candle training graph and its autograd:
    /// an implementation independent of the core's, to check it against.
    pub fn candle_scores_and_grads(&self, rows: &[ScoreRow]) -> Result<(Vec<f32>, Vec<Vec<f32>>)> {
        use candle_core::{Tensor, Var};
        let model = self.candle_model()?;
        let (mut obs, extras, t, act) = batch(&self.verifier, rows)?;
        let i = &self.config.input;
        let (n, ad, td) = (rows.len(), i.act_dim, self.config.architecture.t_embed_dim);
        for row in obs.chunks_exact_mut(i.obs_dim) {
            for ((v, m), s) in row.iter_mut().zip(&i.obs_mean).zip(&i.obs_std) {
                *v = (*v - m) / s;
            }
        }
        let dev = model.device().clone();
        let chunk = Var::from_tensor(&Tensor::from_slice(&act, (n, ad), &dev)?)?;
        let mean = Tensor::from_slice(&i.act_mean, ad, &dev)?;
        let std = Tensor::from_slice(&i.act_std, ad, &dev)?;
        let mut temb = vec![0f32; n * td];
        for (r, &tt) in t.iter().enumerate() {
            verifier::time_embedding_into(tt as f64, &mut temb[r * td..(r + 1) * td]);
        }
        let bt = crate::model::BatchTensors {
            obs: Tensor::from_slice(&obs, (n, i.obs_dim), &dev)?,
            act: chunk.as_tensor().broadcast_sub(&mean)?.broadcast_div(&std)?,
            temb: Tensor::from_vec(temb, (n, td), &dev)?,
            extras: extras
                .iter()
                .zip(self.verifier.extra_inputs())
                .map(|(x, (_, d))| Tensor::from_slice(x, (n, d), &dev))
                .collect::<candle_core::Result<_>>()?,
        };
        let (y, _) = model.forward(&bt, &Default::default())?;
        let objective = match self.config.kind {
            // log sigmoid(y) = -relu(-y) - log(1 + exp(-|y|))
            Kind::Classifier => {
                (y.neg()?.relu()?.neg()? - y.abs()?.neg()?.exp()?.affine(1.0, 1.0)?.log()?)?
            }
            Kind::Q => y.clone(),
        };
        let grads = objective.sum_all()?.backward()?;
        let g = grads.get(chunk.as_tensor()).context("no gradient for the action chunk")?;
        let g: Vec<f32> = g.flatten_all()?.to_vec1()?;
        let y: Vec<f32> = y.to_vec1()?;
        let scores = match self.config.kind {
            Kind::Classifier => y.into_iter().map(verifier::sigmoid).collect(),
            Kind::Q => y,
        };
        Ok((scores, g.chunks(ad.max(1)).map(<[f32]>::to_vec).collect()))
    }
}

/// One row to score: the verifier's inputs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScoreRow {
    /// `obs_dim` floats: the `T_o` most recent observations, oldest first (raw: the artifact
    /// standardises them).
    pub obs: Vec<f32>,
    /// `act_dim` floats: the action chunk, row-major `H x A`, in the space the artifact takes
    /// (`input.action_space`: the policy's normalised space, or raw for older artifacts).
    pub action: Vec<f32>,
    /// Episode step (a whole number >= 0).
    pub t: f64,
    /// Extra inputs by name (only for artifacts with extra inputs).
    #[serde(default, skip_serializing_if = "HashMap::is_empty")]
    pub extras: HashMap<String, Vec<f32>>,
}

#[derive(Deserialize)]
struct ScoreInput {
    rows: Vec<ScoreRow>,
}

/// Parse `{"rows": [{"obs": [..], "action": [..], "t": 3}]}`.
pub fn parse_rows(input_json: &str) -> Result<Vec<ScoreRow>> {
    Ok(serde_json::from_str::<ScoreInput>(input_json).context("parsing score input JSON")?.rows)
}

/// Rows as the core's batch: obs, extras (in the verifier's order), t, chunks.
type Batch = (Vec<f32>, Vec<Vec<f32>>, Vec<u32>, Vec<f32>);

fn batch(v: &Verifier, rows: &[ScoreRow]) -> Result<Batch> {
    let (od, ad) = (v.obs_dim(), v.act_dim());
    let names = v.extra_inputs();
    let mut obs = Vec::with_capacity(rows.len() * od);
    let mut act = Vec::with_capacity(rows.len() * ad);
    let mut t = Vec::with_capacity(rows.len());
    let mut extras: Vec<Vec<f32>> = vec![Vec::new(); names.len()];
    for (k, r) in rows.iter().enumerate() {
        ensure!(r.obs.len() == od, "row {k}: obs has {} values, expected {od}", r.obs.len());
        ensure!(r.action.len() == ad, "row {k}: action has {} values, expected {ad}", r.action.len());
        ensure!(
            r.t >= 0.0 && r.t.fract() == 0.0 && r.t <= u32::MAX as f64,
            "row {k}: t = {} is not an episode step (a whole number >= 0)",
            r.t
        );
        obs.extend_from_slice(&r.obs);
        act.extend_from_slice(&r.action);
        t.push(r.t as u32);
        for ((name, dim), dst) in names.iter().zip(extras.iter_mut()) {
            let x = r.extras.get(*name).with_context(|| format!("row {k}: missing extra input {name}"))?;
            ensure!(x.len() == *dim, "row {k}: extra input {name} has {} values, expected {dim}", x.len());
            dst.extend_from_slice(x);
        }
    }
    Ok((obs, extras, t, act))
}

/// Scores of rows under a verifier (the core's forward pass).
pub fn score_rows(v: &Verifier, rows: &[ScoreRow]) -> Result<Vec<f32>> {
    let (obs, extras, t, act) = batch(v, rows)?;
    let ex: Vec<&[f32]> = extras.iter().map(|e| e.as_slice()).collect();
    Ok(v.score_ext(&obs, &ex, &t, &act, 1)?)
}

/// The members' spread of each row's score (0 for one network).
pub fn spread_rows(v: &Verifier, rows: &[ScoreRow]) -> Result<Vec<f32>> {
    let (obs, extras, t, act) = batch(v, rows)?;
    let ex: Vec<&[f32]> = extras.iter().map(|e| e.as_slice()).collect();
    let (mut mean, mut spread) = (vec![0f32; rows.len()], vec![0f32; rows.len()]);
    v.score_spread_into(&obs, &ex, &t, &act, 1, &mut mean, &mut spread)?;
    Ok(spread)
}

/// Guidance gradients of rows (d log C / d action for the classifier, d Q / d action), one
/// `act_dim` vector per row.
pub fn grad_rows(v: &Verifier, rows: &[ScoreRow]) -> Result<Vec<Vec<f32>>> {
    let (obs, extras, t, act) = batch(v, rows)?;
    let ex: Vec<&[f32]> = extras.iter().map(|e| e.as_slice()).collect();
    let g = v.grad_ext(&obs, &ex, &t, &act)?;
    Ok(g.chunks(v.act_dim().max(1)).map(<[f32]>::to_vec).collect())
}

/// Scores of raw rows under an artifact.
pub fn score(artifact: &TrainedArtifact, rows: &[ScoreRow]) -> Result<Vec<f32>> {
    artifact.score(rows)
}

/// Load the artifact in `artifact_dir` and score `{"rows":[{"obs":[..], "action":[..], "t":3}]}`.
pub fn score_json(artifact_dir: &Path, input_json: &str) -> Result<Vec<f32>> {
    let v = Verifier::load_dir(artifact_dir)?;
    score_rows(&v, &parse_rows(input_json)?)
}
