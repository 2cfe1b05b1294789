//! Verifier artifacts (see ARTIFACT.md): `model.safetensors` + `config.json` + `manifest.json`
//! in a directory, content-addressed by the sha256 of `manifest.json`. Writing, verified loading,
//! and the reference scorer (`ufops score`).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use candle_core::{Device, Tensor};
use rand::SeedableRng;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::data::{time_embedding_into, ExtraInputSpec, InputSpec, Normalization, ObsKey};
use crate::loss::sigmoid;
use crate::model::{
    params_from_tensors, params_to_tensors, Architecture, CandleModel, Kind, ModelSpec, ParamSet,
    Variant,
};
use crate::train::Trained;

pub const SCHEMA_VERSION: u32 = 1;
pub const CONFIG_FILE: &str = "config.json";
pub const MODEL_FILE: &str = "model.safetensors";
pub const MANIFEST_FILE: &str = "manifest.json";

/// `config.json`'s `input` object.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InputConfig {
    pub obs_keys: Vec<ObsKey>,
    pub obs_history: usize,
    pub chunk_len: usize,
    pub action_dim: usize,
    pub obs_dim: usize,
    pub act_dim: usize,
    /// Same as `architecture.t_embed_dim` (repeated for convenience).
    pub t_embed_dim: usize,
    /// Extra inputs (extension): where each comes from; the model side is in `architecture`.
    #[serde(default)]
    pub extra_inputs: Vec<ExtraInputSpec>,
    pub obs_mean: Vec<f32>,
    pub obs_std: Vec<f32>,
    pub act_mean: Vec<f32>,
    pub act_std: Vec<f32>,
}

/// `config.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ArtifactConfig {
    pub schema_version: u32,
    pub kind: Kind,
    pub architecture: Architecture,
    pub input: InputConfig,
    /// Q only (null for the classifier).
    pub gamma: Option<f64>,
    pub hyperparameters: serde_json::Value,
    pub metrics: serde_json::Value,
    pub lineage: serde_json::Value,
}

impl ArtifactConfig {
    pub fn model_spec(&self) -> ModelSpec {
        ModelSpec {
            kind: self.kind,
            arch: self.architecture.clone(),
            obs_dim: self.input.obs_dim,
            act_dim: self.input.act_dim,
        }
    }
    pub fn input_spec(&self) -> InputSpec {
        InputSpec {
            obs_keys: self.input.obs_keys.clone(),
            obs_history: self.input.obs_history,
            chunk_len: self.input.chunk_len,
            action_dim: self.input.action_dim,
            t_embed_dim: self.input.t_embed_dim,
            extra_inputs: self.input.extra_inputs.clone(),
        }
    }
    pub fn normalization(&self) -> Normalization {
        Normalization {
            obs_mean: self.input.obs_mean.clone(),
            obs_std: self.input.obs_std.clone(),
            act_mean: self.input.act_mean.clone(),
            act_std: self.input.act_std.clone(),
        }
    }
}

/// `manifest.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub schema_version: u32,
    pub files: BTreeMap<String, String>,
}

/// What [`write_artifact`] wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct ArtifactInfo {
    /// First 16 hex digits of sha256(manifest.json).
    pub id: String,
    pub dir: PathBuf,
    pub manifest: Manifest,
}

pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// The artifact id of manifest bytes.
pub fn artifact_id(manifest_bytes: &[u8]) -> String {
    sha256_hex(manifest_bytes)[..16].to_string()
}

/// Build `config.json` for a trained model.
pub fn artifact_config(t: &Trained, lineage: serde_json::Value) -> Result<ArtifactConfig> {
    let i = &t.input;
    Ok(ArtifactConfig {
        schema_version: SCHEMA_VERSION,
        kind: t.spec.kind,
        architecture: t.spec.arch.clone(),
        input: InputConfig {
            obs_keys: i.obs_keys.clone(),
            obs_history: i.obs_history,
            chunk_len: i.chunk_len,
            action_dim: i.action_dim,
            obs_dim: i.obs_dim(),
            act_dim: i.act_dim(),
            t_embed_dim: i.t_embed_dim,
            extra_inputs: i.extra_inputs.clone(),
            obs_mean: t.norm.obs_mean.clone(),
            obs_std: t.norm.obs_std.clone(),
            act_mean: t.norm.act_mean.clone(),
            act_std: t.norm.act_std.clone(),
        },
        gamma: (t.spec.kind == Kind::Q).then_some(t.config.gamma),
        hyperparameters: serde_json::to_value(&t.config)?,
        metrics: serde_json::json!({
            "final": t.metrics,
            "history": t.history,
        }),
        lineage,
    })
}

/// Write the artifact files of `trained` into `dir` (created if needed). `lineage` is stored
/// as-is (store version, label snapshot, split id, episode counts, code version...).
pub fn write_artifact(dir: &Path, trained: &Trained, lineage: serde_json::Value) -> Result<ArtifactInfo> {
    let cfg = artifact_config(trained, lineage)?;
    write_parts(dir, &cfg, &trained.params)
}

/// Write an artifact from its parts.
pub fn write_parts(dir: &Path, cfg: &ArtifactConfig, params: &ParamSet) -> Result<ArtifactInfo> {
    cfg.model_spec().check_params(params)?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let model_path = dir.join(MODEL_FILE);
    candle_core::safetensors::save(&params_to_tensors(params)?, &model_path)?;
    let model_bytes = std::fs::read(&model_path)?;
    let mut config_bytes = serde_json::to_vec_pretty(cfg)?;
    config_bytes.push(b'\n');
    std::fs::write(dir.join(CONFIG_FILE), &config_bytes)?;
    let manifest = Manifest {
        schema_version: SCHEMA_VERSION,
        files: BTreeMap::from([
            (CONFIG_FILE.to_string(), sha256_hex(&config_bytes)),
            (MODEL_FILE.to_string(), sha256_hex(&model_bytes)),
        ]),
    };
    let mut manifest_bytes = serde_json::to_vec_pretty(&manifest)?;
    manifest_bytes.push(b'\n');
    std::fs::write(dir.join(MANIFEST_FILE), &manifest_bytes)?;
    Ok(ArtifactInfo { id: artifact_id(&manifest_bytes), dir: dir.to_path_buf(), manifest })
}

/// A loaded, verified artifact with its reference (candle) model.
pub struct Artifact {
    pub id: String,
    pub dir: PathBuf,
    pub config: ArtifactConfig,
    pub spec: ModelSpec,
    pub params: ParamSet,
    pub model: CandleModel,
}

/// Load an artifact directory: check the manifest's sha256s, the schema version and variant,
/// and rebuild the candle model. Spectral norm is already folded into the stored weights, so
/// the model is rebuilt without it.
pub fn load_artifact(dir: &Path) -> Result<Artifact> {
    let manifest_bytes = std::fs::read(dir.join(MANIFEST_FILE))
        .with_context(|| format!("reading {}", dir.join(MANIFEST_FILE).display()))?;
    let manifest: Manifest = serde_json::from_slice(&manifest_bytes).context("parsing manifest.json")?;
    ensure!(manifest.schema_version == SCHEMA_VERSION, "unknown schema_version {}", manifest.schema_version);
    for f in [CONFIG_FILE, MODEL_FILE] {
        let want = manifest.files.get(f).with_context(|| format!("manifest lists no {f}"))?;
        let bytes = std::fs::read(dir.join(f)).with_context(|| format!("reading {f}"))?;
        let got = sha256_hex(&bytes);
        ensure!(&got == want, "sha256 mismatch for {f}: manifest {want}, file {got}");
    }
    let raw: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join(CONFIG_FILE))?)?;
    match raw.get("schema_version").and_then(|v| v.as_u64()) {
        Some(v) if v == SCHEMA_VERSION as u64 => {}
        other => bail!("unknown config schema_version {other:?}"),
    }
    match raw.pointer("/architecture/variant").and_then(|v| v.as_str()) {
        Some("lowdim") | Some("features") => {}
        other => bail!("unknown architecture variant {other:?}"),
    }
    let config: ArtifactConfig = serde_json::from_value(raw).context("parsing config.json")?;
    let spec = config.model_spec();
    let tensors = candle_core::safetensors::load(dir.join(MODEL_FILE), &Device::Cpu)?;
    let params = params_from_tensors(&spec, &tensors)?;
    let mut model_spec = spec.clone();
    model_spec.arch.spectral_norm = false; // weights are stored already divided by sigma
    let model = CandleModel::new(&model_spec, &params, &mut rand_chacha::ChaCha8Rng::seed_from_u64(0))?;
    Ok(Artifact { id: artifact_id(&manifest_bytes), dir: dir.to_path_buf(), config, spec, params, model })
}

/// One row to score (raw, un-normalised values).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScoreRow {
    /// `obs_dim` floats: the `T_o` most recent observations, oldest first.
    pub obs: Vec<f32>,
    /// `act_dim` floats: the action chunk, row-major `H x A`.
    pub action: Vec<f32>,
    /// Episode step.
    pub t: f64,
    /// Extra inputs by name (only for artifacts with extra inputs).
    #[serde(default, skip_serializing_if = "HashMap::is_empty")]
    pub extras: HashMap<String, Vec<f32>>,
}

#[derive(Deserialize)]
struct ScoreInput {
    rows: Vec<ScoreRow>,
}

impl Artifact {
    /// Head outputs (logit or value) for raw rows.
    pub fn head_outputs(&self, rows: &[ScoreRow]) -> Result<Vec<f32>> {
        if rows.is_empty() {
            return Ok(vec![]);
        }
        let i = &self.config.input;
        let a = &self.config.architecture;
        let n = rows.len();
        let mut obs = Vec::with_capacity(n * i.obs_dim);
        let mut act = Vec::with_capacity(n * i.act_dim);
        let mut temb = vec![0f32; n * a.t_embed_dim];
        let mut extras: Vec<Vec<f32>> = vec![Vec::new(); a.extra_inputs.len()];
        for (k, r) in rows.iter().enumerate() {
            ensure!(r.obs.len() == i.obs_dim, "row {k}: obs has {} values, expected {}", r.obs.len(), i.obs_dim);
            ensure!(r.action.len() == i.act_dim, "row {k}: action has {} values, expected {}", r.action.len(), i.act_dim);
            obs.extend_from_slice(&r.obs);
            act.extend_from_slice(&r.action);
            time_embedding_into(r.t, &mut temb[k * a.t_embed_dim..(k + 1) * a.t_embed_dim]);
            for (e, dst) in a.extra_inputs.iter().zip(extras.iter_mut()) {
                let v = r.extras.get(&e.name).with_context(|| format!("row {k}: missing extra input {}", e.name))?;
                ensure!(v.len() == e.dim, "row {k}: extra {} has wrong length", e.name);
                dst.extend_from_slice(v);
            }
        }
        self.config.normalization().apply(&mut obs, &mut act);
        let ex: Vec<&[f32]> = extras.iter().map(|v| v.as_slice()).collect();
        let bt = self.model.batch_tensors(n, &obs, &act, &temb, &ex)?;
        let (y, _) = self.model.forward(&bt, &Default::default())?;
        Ok(y.to_vec1::<f32>()?)
    }

    /// Scores: classifier `sigmoid(logit)`, Q the value.
    pub fn score(&self, rows: &[ScoreRow]) -> Result<Vec<f32>> {
        let y = self.head_outputs(rows)?;
        Ok(match self.spec.kind {
            Kind::Classifier => y.into_iter().map(sigmoid).collect(),
            Kind::Q => y,
        })
    }

    pub fn variant(&self) -> Variant {
        self.spec.arch.variant
    }
}

/// Scores of raw rows under an artifact (the reference `ufops score` prints).
pub fn score(artifact: &Artifact, rows: &[ScoreRow]) -> Result<Vec<f32>> {
    artifact.score(rows)
}

/// Load the artifact in `artifact_dir` and score `{"rows":[{"obs":[..], "action":[..], "t":3}]}`.
pub fn score_json(artifact_dir: &Path, input_json: &str) -> Result<Vec<f32>> {
    let a = load_artifact(artifact_dir)?;
    let inp: ScoreInput = serde_json::from_str(input_json).context("parsing score input JSON")?;
    a.score(&inp.rows)
}

/// Unused-import guard for Tensor in docs.
#[allow(dead_code)]
fn _tensor_type(_: &Tensor) {}
