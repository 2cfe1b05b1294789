//! [`Verifier`]: an artifact loaded from a directory or from bytes, dispatching to the fast path
//! when the configuration allows it and to the candle reference otherwise.
use crate::config::{Kind, VerifierConfig};
use crate::error::{Result, SteerError};
use crate::fast::FastLowdim;
use crate::reference::CandleVerifier;
use crate::weights::Weights;
use crate::Scorer;
use sha2::{Digest, Sha256};
use std::path::Path;

enum Backend {
    Fast(FastLowdim),
    Reference(CandleVerifier),
}

/// A loaded verifier (success classifier or time-to-success Q).
pub struct Verifier {
    config: VerifierConfig,
    backend: Backend,
    id: Option<String>,
}

/// The parsed `manifest.json`.
#[derive(Debug, Clone, serde::Deserialize)]
pub struct Manifest {
    pub schema_version: u64,
    pub files: std::collections::BTreeMap<String, String>,
}

impl Manifest {
    pub fn parse(bytes: &[u8]) -> Result<Self> {
        let raw: serde_json::Value =
            serde_json::from_slice(bytes).map_err(|e| SteerError::Manifest(format!("not valid JSON: {e}")))?;
        match raw.get("schema_version").and_then(|v| v.as_u64()) {
            Some(1) => {}
            Some(v) => return Err(SteerError::UnknownSchema(v)),
            None => return Err(SteerError::Manifest("missing or non-integer schema_version".into())),
        }
        let m: Manifest = serde_json::from_value(raw).map_err(|e| SteerError::Manifest(e.to_string()))?;
        for f in ["config.json", "model.safetensors"] {
            if !m.files.contains_key(f) {
                return Err(SteerError::Manifest(format!("files does not list {f}")));
            }
        }
        Ok(m)
    }

    /// Check `bytes` against the manifest's sha256 for `file`.
    pub fn check(&self, file: &str, bytes: &[u8]) -> Result<()> {
        let expected = self
            .files
            .get(file)
            .ok_or_else(|| SteerError::Manifest(format!("files does not list {file}")))?;
        let actual = sha256_hex(bytes);
        if !actual.eq_ignore_ascii_case(expected.trim()) {
            return Err(SteerError::HashMismatch { file: file.into(), expected: expected.clone(), actual });
        }
        Ok(())
    }
}

pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// Artifact id: first 16 hex digits of sha256(manifest.json bytes).
pub fn artifact_id(manifest_bytes: &[u8]) -> String {
    sha256_hex(manifest_bytes)[..16].to_string()
}

fn read(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| SteerError::Io { path: path.display().to_string(), source: e })
}

impl Verifier {
    /// Load an artifact directory: `manifest.json` is read first, every file it lists is checked
    /// against its sha256 before use, then `config.json` and `model.safetensors` are parsed.
    pub fn load_dir(dir: impl AsRef<Path>) -> Result<Self> {
        let dir = dir.as_ref();
        let mbytes = read(&dir.join("manifest.json"))?;
        let (cfg, st) = Self::checked_files(&mbytes, |name| {
            if name.contains('/') || name.contains('\\') || name.contains("..") {
                return Err(SteerError::Manifest(format!("file name {name:?} is not a plain name")));
            }
            read(&dir.join(name))
        })?;
        let mut v = Self::from_bytes(&cfg, &st)?;
        v.id = Some(artifact_id(&mbytes));
        Ok(v)
    }

    /// Verify a manifest and fetch its files through `get` (a directory, the store, HTTP...):
    /// returns the checked (config.json, model.safetensors) bytes.
    pub fn checked_files(
        manifest: &[u8],
        mut get: impl FnMut(&str) -> Result<Vec<u8>>,
    ) -> Result<(Vec<u8>, Vec<u8>)> {
        let m = Manifest::parse(manifest)?;
        let mut cfg = None;
        let mut st = None;
        for name in m.files.keys() {
            let bytes = get(name)?;
            m.check(name, &bytes)?;
            match name.as_str() {
                "config.json" => cfg = Some(bytes),
                "model.safetensors" => st = Some(bytes),
                _ => {}
            }
        }
        Ok((cfg.unwrap(), st.unwrap()))
    }

    /// Build from already-verified bytes (the caller is responsible for the manifest check).
    /// Picks the fast path when the configuration supports it.
    pub fn from_bytes(config_json: &[u8], safetensors: &[u8]) -> Result<Self> {
        let config = VerifierConfig::from_json(config_json)?;
        let weights = Weights::from_safetensors(safetensors)?;
        Self::from_parts(config, &weights)
    }

    pub fn from_parts(config: VerifierConfig, weights: &Weights) -> Result<Self> {
        config.validate()?;
        weights.validate(&config)?;
        let backend = if FastLowdim::supports(&config) {
            Backend::Fast(FastLowdim::new(&config, weights)?)
        } else {
            Backend::Reference(CandleVerifier::new(&config, weights)?)
        };
        Ok(Verifier { config, backend, id: None })
    }

    /// Same, always using the candle reference back-end.
    pub fn from_parts_reference(config: VerifierConfig, weights: &Weights) -> Result<Self> {
        let backend = Backend::Reference(CandleVerifier::new(&config, weights)?);
        Ok(Verifier { config, backend, id: None })
    }

    pub fn config(&self) -> &VerifierConfig {
        &self.config
    }
    pub fn kind(&self) -> Kind {
        self.config.kind()
    }
    #[cfg_attr(not(feature = "http"), allow(dead_code))]
    pub(crate) fn set_id(&mut self, id: String) {
        self.id = Some(id);
    }

    /// The artifact id (when loaded through a manifest).
    pub fn id(&self) -> Option<&str> {
        self.id.as_deref()
    }
    /// "fast-avx2", "fast-portable" or "candle".
    pub fn backend_name(&self) -> &'static str {
        match &self.backend {
            Backend::Fast(f) if f.uses_simd() => "fast-avx2",
            Backend::Fast(_) => "fast-portable",
            Backend::Reference(_) => "candle",
        }
    }
    pub fn is_fast(&self) -> bool {
        matches!(self.backend, Backend::Fast(_))
    }

    /// Scoring with extra inputs (`extras[i]` is `B * dim_i`, in `extra_inputs` order).
    pub fn score_batch_ext(&self, obs: &[f32], extras: &[&[f32]], t: &[u32], cands: &[f32], n: usize) -> Result<Vec<f32>> {
        match &self.backend {
            Backend::Reference(r) => r.score_batch_ext(obs, extras, t, cands, n),
            Backend::Fast(f) if extras.is_empty() => f.score_batch(obs, t, cands, n),
            Backend::Fast(_) => Err(SteerError::Input("this verifier takes no extra inputs".into())),
        }
    }
    /// Gradients with extra inputs.
    pub fn grad_batch_ext(&self, obs: &[f32], extras: &[&[f32]], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>> {
        match &self.backend {
            Backend::Reference(r) => r.grad_batch_ext(obs, extras, t, chunks),
            Backend::Fast(f) if extras.is_empty() => f.grad_batch(obs, t, chunks),
            Backend::Fast(_) => Err(SteerError::Input("this verifier takes no extra inputs".into())),
        }
    }
}

impl Scorer for Verifier {
    fn obs_dim(&self) -> usize {
        self.config.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.config.act_dim()
    }
    fn score_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Vec<f32>> {
        match &self.backend {
            Backend::Fast(f) => f.score_batch(obs, t, candidates, n),
            Backend::Reference(r) => r.score_batch(obs, t, candidates, n),
        }
    }
    fn grad_batch(&self, obs: &[f32], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>> {
        match &self.backend {
            Backend::Fast(f) => f.grad_batch(obs, t, chunks),
            Backend::Reference(r) => r.grad_batch(obs, t, chunks),
        }
    }
}
