//! `model.safetensors`: F32 tensors by name, parsed, checked against the tensor list of a
//! configuration ([`crate::Architecture::tensors`]) and written back.

use std::collections::BTreeMap;

use crate::error::{Result, VerifierError};
use crate::format::ArtifactConfig;

/// One F32 tensor, row-major, PyTorch layout (`Linear.weight` is `[out, in]`).
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// Named tensors (sorted by name, so writing is deterministic).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Weights {
    tensors: BTreeMap<String, Tensor>,
}

impl Weights {
    /// Parse safetensors bytes: every tensor F32 little-endian with finite values.
    pub fn from_safetensors(bytes: &[u8]) -> Result<Self> {
        let st = safetensors::SafeTensors::deserialize(bytes)
            .map_err(|e| VerifierError::Safetensors(e.to_string()))?;
        let mut tensors = BTreeMap::new();
        for (name, view) in st.iter() {
            if view.dtype() != safetensors::Dtype::F32 {
                return Err(VerifierError::TensorDtype {
                    name: name.into(),
                    dtype: format!("{:?}", view.dtype()),
                });
            }
            let raw = view.data();
            let n = view.shape().iter().try_fold(1usize, |a, &d| a.checked_mul(d));
            if n.and_then(|n| n.checked_mul(4)) != Some(raw.len()) {
                return Err(VerifierError::Safetensors(format!(
                    "tensor {name:?}: data length does not match its shape"
                )));
            }
            let data: Vec<f32> =
                raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            if data.iter().any(|x| !x.is_finite()) {
                return Err(VerifierError::Safetensors(format!(
                    "tensor {name:?} contains non-finite values"
                )));
            }
            tensors.insert(name.to_string(), Tensor { shape: view.shape().to_vec(), data });
        }
        Ok(Weights { tensors })
    }

    /// Serialize (no `__metadata__`); identical weights give identical bytes.
    pub fn to_safetensors(&self) -> Result<Vec<u8>> {
        let bytes: Vec<(&String, &Tensor, Vec<u8>)> = self
            .tensors
            .iter()
            .map(|(n, t)| (n, t, t.data.iter().flat_map(|x| x.to_le_bytes()).collect()))
            .collect();
        let views = bytes
            .iter()
            .map(|(n, t, b)| {
                safetensors::tensor::TensorView::new(safetensors::Dtype::F32, t.shape.clone(), b)
                    .map(|v| (n.as_str(), v))
                    .map_err(|e| VerifierError::Safetensors(format!("tensor {n:?}: {e}")))
            })
            .collect::<Result<Vec<_>>>()?;
        safetensors::tensor::serialize(views, None).map_err(|e| VerifierError::Safetensors(e.to_string()))
    }

    /// Add or replace a tensor; its data length must match its shape.
    pub fn insert(&mut self, name: &str, shape: Vec<usize>, data: Vec<f32>) -> Result<()> {
        if shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)) != Some(data.len()) {
            return Err(VerifierError::TensorShape {
                name: name.into(),
                expected: shape,
                actual: vec![data.len()],
            });
        }
        self.tensors.insert(name.to_string(), Tensor { shape, data });
        Ok(())
    }

    pub fn remove(&mut self, name: &str) -> Option<Tensor> {
        self.tensors.remove(name)
    }

    pub fn get(&self, name: &str) -> Option<&Tensor> {
        self.tensors.get(name)
    }

    pub fn len(&self) -> usize {
        self.tensors.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tensors.is_empty()
    }

    pub fn iter(&self) -> impl Iterator<Item = (&str, &Tensor)> {
        self.tensors.iter().map(|(n, t)| (n.as_str(), t))
    }

    /// The tensor `name`, which must exist with exactly `shape`.
    pub fn tensor(&self, name: &str, shape: &[usize]) -> Result<&Tensor> {
        let t = self.tensors.get(name).ok_or_else(|| VerifierError::MissingTensor { name: name.into() })?;
        if t.shape != shape {
            return Err(VerifierError::TensorShape {
                name: name.into(),
                expected: shape.to_vec(),
                actual: t.shape.clone(),
            });
        }
        Ok(t)
    }

    /// Exactly the tensors `cfg` needs, each with its shape (a tensor the architecture does not
    /// use means the file belongs to another architecture).
    pub fn validate(&self, cfg: &ArtifactConfig) -> Result<()> {
        let want = cfg.tensors();
        for t in &want {
            self.tensor(&t.name, &t.shape)?;
        }
        if self.tensors.len() != want.len() {
            let known: std::collections::BTreeSet<&str> = want.iter().map(|t| t.name.as_str()).collect();
            if let Some(extra) = self.tensors.keys().find(|n| !known.contains(n.as_str())) {
                return Err(VerifierError::UnexpectedTensor { name: extra.clone() });
            }
        }
        Ok(())
    }
}
