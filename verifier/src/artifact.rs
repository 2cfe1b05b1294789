//! Loading an artifact with every file checked against `manifest.json` (from a directory, from
//! bytes, or through any getter: the store, HTTP...), and building the files the trainer writes.

use std::path::Path;

use crate::error::{Result, VerifierError};
use crate::format::{ArtifactConfig, Manifest, CONFIG_FILE, MANIFEST_FILE, MODEL_FILE};
use crate::weights::Weights;
use crate::{artifact_id, Verifier};

/// A checked artifact: its configuration and weights, consistent with each other.
#[derive(Clone, Debug)]
pub struct Artifact {
    /// First 16 hex digits of sha256(manifest.json); `None` when built from unchecked bytes.
    pub id: Option<String>,
    pub config: ArtifactConfig,
    pub weights: Weights,
}

fn read(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| VerifierError::io(path, e))
}

impl Artifact {
    /// Load an artifact directory: `manifest.json` first, then every file it lists, each checked
    /// against its sha256 before it is parsed.
    pub fn load_dir(dir: impl AsRef<Path>) -> Result<Self> {
        let dir = dir.as_ref();
        let manifest = read(&dir.join(MANIFEST_FILE))?;
        Self::load_with(&manifest, |name| read(&dir.join(name)))
    }

    /// Load through `get` (file name → bytes): the manifest is parsed, every file it lists is
    /// fetched and checked against its sha256, then the configuration and weights are parsed
    /// and checked against each other. The id is derived from the manifest bytes.
    pub fn load_with(manifest: &[u8], mut get: impl FnMut(&str) -> Result<Vec<u8>>) -> Result<Self> {
        let m = Manifest::parse(manifest)?;
        let (mut config, mut model) = (None, None);
        for name in m.files.keys() {
            let bytes = get(name)?;
            m.check(name, &bytes)?;
            match name.as_str() {
                CONFIG_FILE => config = Some(bytes),
                MODEL_FILE => model = Some(bytes),
                _ => {}
            }
        }
        // Manifest::parse guarantees both are listed.
        let missing = |f: &str| VerifierError::Manifest(format!("files does not list {f}"));
        let config = config.ok_or_else(|| missing(CONFIG_FILE))?;
        let model = model.ok_or_else(|| missing(MODEL_FILE))?;
        let mut a = Self::from_checked_bytes(&config, &model)?;
        if a.config.schema_version != m.schema_version {
            return Err(VerifierError::Manifest(format!(
                "manifest.json has schema_version {}, config.json {}",
                m.schema_version, a.config.schema_version
            )));
        }
        a.id = Some(artifact_id(manifest));
        Ok(a)
    }

    /// Parse `config.json` and `model.safetensors` bytes the caller has already checked.
    pub fn from_checked_bytes(config_json: &[u8], safetensors: &[u8]) -> Result<Self> {
        let config = ArtifactConfig::from_json(config_json)?;
        let weights = Weights::from_safetensors(safetensors)?;
        weights.validate(&config)?;
        Ok(Artifact { id: None, config, weights })
    }

    /// The runnable verifier.
    pub fn verifier(&self) -> Result<Verifier> {
        let mut v = Verifier::new(self.config.clone(), &self.weights)?;
        v.set_id(self.id.clone());
        Ok(v)
    }
}

/// The three files of an artifact, as written: `config.json` and `manifest.json` pretty-printed
/// with a trailing newline, `model.safetensors` with no metadata. Identical weights and
/// configuration give identical bytes, hence the same id.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ArtifactFiles {
    pub id: String,
    pub manifest: Vec<u8>,
    pub config: Vec<u8>,
    pub model: Vec<u8>,
}

impl ArtifactFiles {
    /// Build the files of a configuration and its weights (both validated first).
    pub fn build(config: &ArtifactConfig, weights: &Weights) -> Result<Self> {
        config.validate()?;
        weights.validate(config)?;
        let model = weights.to_safetensors()?;
        let cfg = config.to_json()?;
        let manifest = Manifest::of(config.schema_version, &cfg, &model).to_json();
        Ok(ArtifactFiles { id: artifact_id(&manifest), manifest, config: cfg, model })
    }

    /// (file name, bytes), manifest first.
    pub fn files(&self) -> [(&'static str, &[u8]); 3] {
        [(MANIFEST_FILE, &self.manifest), (CONFIG_FILE, &self.config), (MODEL_FILE, &self.model)]
    }

    /// Write the files into `dir` (created if needed); the manifest last, so a directory with a
    /// manifest has all its files.
    pub fn write_dir(&self, dir: impl AsRef<Path>) -> Result<()> {
        let dir = dir.as_ref();
        std::fs::create_dir_all(dir).map_err(|e| VerifierError::io(dir, e))?;
        for (name, bytes) in self.files().iter().rev() {
            let p = dir.join(name);
            std::fs::write(&p, bytes).map_err(|e| VerifierError::io(&p, e))?;
        }
        Ok(())
    }
}
