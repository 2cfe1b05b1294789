//! `ufops.Verifier`: a loaded verifier artifact (every file checked against its sha256 by the
//! verifier core) scoring and differentiating batches of action chunks through the core's
//! forward pass, with the GIL released while it computes.

use std::time::Duration;

use numpy::{IxDyn, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::arrays::{f32_array, shape_str, steps, values};
use crate::errors::{from_steer, from_verifier};

/// A verifier (success classifier or time-to-success Q) loaded from an artifact.
///
/// Immutable and thread-safe: one instance serves any number of threads; `score` and `grad`
/// release the GIL while the verifier core computes.
#[pyclass(module = "ufops._ufops", name = "Verifier", frozen)]
pub struct PyVerifier {
    pub(crate) v: verifier::Verifier,
}

/// Two arrays of the same shape (`telemetry_grid`'s scored and raw chunks).
type ArrayPair<'py> = (Bound<'py, PyArrayDyn<f32>>, Bound<'py, PyArrayDyn<f32>>);

/// How the action argument is laid out: rows of `lead` chunks, each flat (`act_dim`) or `(H, A)`.
struct Chunks {
    lead: Vec<usize>,
}

/// The arguments of a scoring call, checked: `B` groups of `n` candidates, the output's shape.
struct ScoreArgs<'py> {
    obs: PyReadonlyArrayDyn<'py, f32>,
    act: PyReadonlyArrayDyn<'py, f32>,
    extras: Vec<PyReadonlyArrayDyn<'py, f32>>,
    t: Vec<u32>,
    n: usize,
    out_shape: Vec<usize>,
}

impl ScoreArgs<'_> {
    /// Runs `f` on the values (obs, extras, t, candidates, n) with the GIL released.
    fn detach<T: Send>(
        &self,
        py: Python<'_>,
        f: impl FnOnce(&[f32], &[&[f32]], &[u32], &[f32], usize) -> ::verifier::Result<T> + Send,
    ) -> PyResult<T> {
        let (o, a) = (values(&self.obs), values(&self.act));
        let ex: Vec<_> = self.extras.iter().map(values).collect();
        let (t, n) = (self.t.as_slice(), self.n);
        py.detach(|| {
            let ex: Vec<&[f32]> = ex.iter().map(|c| c.as_ref()).collect();
            f(&o, &ex, t, &a, n)
        })
        .map_err(from_verifier)
    }
}

impl PyVerifier {
    /// The accepted shapes of chunks with leading dims `lead` ("" or "N, " ...).
    fn chunk_shapes(&self, lead: &str) -> String {
        let l = &self.v.config().input.layout;
        let flat = if lead.is_empty() {
            format!("({},)", self.v.act_dim())
        } else {
            format!("({lead}{})", self.v.act_dim())
        };
        if l.chunk_len > 1 {
            format!("{flat} or ({lead}{}, {})", l.chunk_len, l.action_dim)
        } else {
            flat
        }
    }

    /// Splits the action array's shape into leading dims and the chunk (flat or `(H, A)`).
    fn chunks(&self, shape: &[usize]) -> Option<Chunks> {
        let l = &self.v.config().input.layout;
        let nd = shape.len();
        if nd >= 1 && shape[nd - 1] == self.v.act_dim() {
            return Some(Chunks { lead: shape[..nd - 1].to_vec() });
        }
        if nd >= 2 && shape[nd - 2] == l.chunk_len && shape[nd - 1] == l.action_dim {
            return Some(Chunks { lead: shape[..nd - 2].to_vec() });
        }
        None
    }

    /// The observation rows: `(obs_dim,)` → 1 row (unbatched), `(B, obs_dim)` → B rows.
    fn obs_rows(&self, obs: &PyReadonlyArrayDyn<'_, f32>) -> PyResult<Option<usize>> {
        let od = self.v.obs_dim();
        match obs.shape() {
            [d] if *d == od => Ok(None),
            [b, d] if *d == od => Ok(Some(*b)),
            s => Err(PyValueError::new_err(format!(
                "obs must have shape ({od},) or (B, {od}); got {}",
                shape_str(s)
            ))),
        }
    }

    /// Extra inputs (`architecture.extra_inputs`), each `(dim,)` or `(B, dim)` like `obs`.
    fn extras<'py>(
        &self,
        extras: Option<&Bound<'py, PyDict>>,
        batch: Option<usize>,
    ) -> PyResult<Vec<PyReadonlyArrayDyn<'py, f32>>> {
        if extras.is_none() && self.v.config().architecture.extra_inputs.is_empty() {
            return Ok(Vec::new());
        }
        let wanted = self.v.extra_inputs();
        let mut out = Vec::with_capacity(wanted.len());
        for (name, dim) in &wanted {
            let expected = match batch {
                None => format!("({dim},)"),
                Some(b) => format!("({b}, {dim})"),
            };
            let item = extras.map(|d| d.get_item(name)).transpose()?.flatten().ok_or_else(|| {
                PyValueError::new_err(format!("this verifier takes the extra input {name:?} of shape {expected}: pass extras={{{name:?}: array}}"))
            })?;
            let a = f32_array(&item, &format!("extras[{name:?}]"), || expected.clone())?;
            let ok = match batch {
                None => a.shape() == [*dim],
                Some(b) => a.shape() == [b, *dim],
            };
            if !ok {
                return Err(PyValueError::new_err(format!(
                    "extras[{name:?}] must have shape {expected}; got {}",
                    shape_str(a.shape())
                )));
            }
            out.push(a);
        }
        if let Some(d) = extras {
            for k in d.keys() {
                let k: String = k.extract()?;
                if !wanted.iter().any(|(n, _)| *n == k) {
                    return Err(PyValueError::new_err(format!("this verifier has no extra input {k:?}")));
                }
            }
        }
        Ok(out)
    }

    /// Checks a scoring call's arguments (see `score`).
    fn score_args<'py>(
        &self,
        obs: &Bound<'py, PyAny>,
        act: &Bound<'py, PyAny>,
        t: &Bound<'py, PyAny>,
        extras: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<ScoreArgs<'py>> {
        let od = self.v.obs_dim();
        let obs = f32_array(obs, "obs", || format!("({od},) or (B, {od})"))?;
        let batch = self.obs_rows(&obs)?;
        let expected = || match batch {
            None => format!("{} for obs of shape ({od},)", self.chunk_shapes("N, ")),
            Some(b) => format!(
                "{} or {} for obs of shape ({b}, {od})",
                self.chunk_shapes(&format!("{b}, N, ")),
                self.chunk_shapes(&format!("{b}, "))
            ),
        };
        let act = f32_array(act, "act", expected)?;
        let lead = self.chunks(act.shape()).map(|c| c.lead);
        // (groups, candidates per group, output shape)
        let (b, n, out_shape) = match (batch, lead.as_deref()) {
            (None, Some([n])) => (1, *n, vec![*n]),
            (Some(b), Some([b2, n])) if *b2 == b => (b, *n, vec![b, *n]),
            (Some(b), Some([b2])) if *b2 == b => (b, 1, vec![b]),
            _ => {
                return Err(PyValueError::new_err(format!(
                    "act must have shape {}; got {}",
                    expected(),
                    shape_str(act.shape())
                )));
            }
        };
        let t = steps(t, b)?;
        let extras = self.extras(extras, batch)?;
        Ok(ScoreArgs { obs, act, extras, t, n, out_shape })
    }
}

#[pymethods]
impl PyVerifier {
    /// Loads an artifact directory (`manifest.json`, `config.json`, `model.safetensors`), every
    /// file checked against the sha256 the manifest records.
    #[staticmethod]
    fn load(py: Python<'_>, path: std::path::PathBuf) -> PyResult<Self> {
        let v = py.detach(|| verifier::Verifier::load_dir(&path)).map_err(from_verifier)?;
        Ok(PyVerifier { v })
    }

    /// Fetches `reference` (`POLICY/CHECKPOINT/KIND@ALIAS` or an artifact id) from a
    /// `ufops serve` API with a bearer token (role viewer or above): the alias is resolved to an
    /// id once, the manifest must hash to that id and every file to the manifest's sha256.
    #[staticmethod]
    #[pyo3(signature = (url, reference, token, timeout=60.0))]
    fn from_server(py: Python<'_>, url: &str, reference: &str, token: &str, timeout: f64) -> PyResult<Self> {
        if !(timeout.is_finite() && timeout > 0.0) {
            return Err(PyValueError::new_err(format!(
                "timeout must be a positive number of seconds; got {timeout}"
            )));
        }
        let src = steer::http::ApiSource {
            timeout: Duration::from_secs_f64(timeout),
            ..steer::http::ApiSource::new(url, token)
        };
        let v = py.detach(|| steer::http::load_verifier(&src, reference)).map_err(from_steer)?;
        Ok(PyVerifier { v })
    }

    /// The artifact id (first 16 hex digits of sha256(manifest.json)).
    #[getter]
    fn id(&self) -> Option<&str> {
        self.v.id()
    }
    /// "classifier" (scores are probabilities of success) or "q" (time-to-success values).
    #[getter]
    fn kind(&self) -> &'static str {
        self.v.kind().as_str()
    }
    /// Length of one observation row: obs_history x the observation keys' widths.
    #[getter]
    fn obs_dim(&self) -> usize {
        self.v.obs_dim()
    }
    /// Length of one flattened action chunk: chunk_len x action_dim.
    #[getter]
    fn act_dim(&self) -> usize {
        self.v.act_dim()
    }
    #[getter]
    fn chunk_len(&self) -> usize {
        self.v.config().input.layout.chunk_len
    }
    #[getter]
    fn action_dim(&self) -> usize {
        self.v.config().input.layout.action_dim
    }
    /// True when chunks are in the policy's normalised sample space (guide x̂0 directly).
    #[getter]
    fn takes_policy_space(&self) -> bool {
        self.v.takes_policy_space()
    }
    /// The kernels in use ("avx2+fma" or "portable").
    /// Networks behind the scores: 1, or an ensemble's members.
    #[getter]
    fn members(&self) -> usize {
        self.v.members()
    }

    #[getter]
    fn backend(&self) -> &'static str {
        self.v.backend_name()
    }
    /// `(name, dim)` of each extra input, in order.
    #[getter]
    fn extra_inputs(&self) -> Vec<(String, usize)> {
        self.v.extra_inputs().into_iter().map(|(n, d)| (n.to_string(), d)).collect()
    }
    /// `{observation key: producer sha256}` of each key that is a store layer (an encoder's
    /// features): scoring needs features from exactly that producer.
    #[getter]
    fn required_producers(&self) -> std::collections::BTreeMap<String, String> {
        let l = &self.v.config().input.layout;
        l.required_producers().into_iter().map(|(k, p)| (k.to_string(), p.to_string())).collect()
    }
    /// Raises ValueError unless `provided` (`{observation key: producer sha256}`) names, for
    /// every layer key of this verifier, the producer it was trained on.
    fn check_producers(&self, provided: std::collections::BTreeMap<String, String>) -> PyResult<()> {
        let l = &self.v.config().input.layout;
        l.check_producers(provided.iter().map(|(k, p)| (k.as_str(), p.as_str()))).map_err(from_verifier)
    }
    /// Why steering with this verifier may not help, when its training flagged it (the
    /// action-sensitivity figure of `config.json`'s metrics); `None` otherwise.
    #[getter]
    fn steering_warning(&self) -> Option<String> {
        self.v.steering_warning()
    }
    /// `config.json` as a JSON string.
    fn config_json(&self) -> PyResult<String> {
        serde_json::to_string(self.v.config()).map_err(|e| PyValueError::new_err(e.to_string()))
    }

    fn __repr__(&self) -> String {
        format!(
            "Verifier(id={:?}, kind={:?}, obs_dim={}, act_dim={}, backend={:?})",
            self.v.id().unwrap_or("-"),
            self.v.kind().as_str(),
            self.v.obs_dim(),
            self.v.act_dim(),
            self.v.backend_name()
        )
    }

    /// The steering-telemetry grid of chunks given in the space the verifier takes (any shape
    /// ending in `act_dim`, or `(…, chunk_len, action_dim)`): their raw actions (the artifact's
    /// action normaliser undone) rounded to half floats, and those put back into the verifier's
    /// space. A recorded best-of-N scores and executes the second and stores the first, so a
    /// replay scores exactly what the robot did (`verifier::telemetry`). Returns `(scored, raw)`,
    /// both shaped like `act`.
    fn telemetry_grid<'py>(&self, py: Python<'py>, act: &Bound<'py, PyAny>) -> PyResult<ArrayPair<'py>> {
        let ad = self.v.act_dim();
        let act = f32_array(act, "act", || format!("(..., {ad}) chunks"))?;
        let shape = act.shape().to_vec();
        let mut raw = values(&act).into_owned();
        if ad == 0 || !raw.len().is_multiple_of(ad) {
            return Err(PyValueError::new_err(format!(
                "act of shape {} does not hold whole chunks of {ad} values",
                shape_str(&shape)
            )));
        }
        let cfg = self.v.config();
        let action_dim = cfg.input.layout.action_dim;
        cfg.input.action_space.input_to_raw(&mut raw, action_dim);
        ::verifier::telemetry::round_to_f16(&mut raw);
        let mut scored = raw.clone();
        cfg.input.action_space.raw_to_input(&mut scored, action_dim);
        let as_array = |v: Vec<f32>| -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
            numpy::PyArray1::from_vec(py, v).reshape(IxDyn(&shape))
        };
        Ok((as_array(scored)?, as_array(raw)?))
    }

    /// Scores of action chunks: `obs` `(obs_dim,)` with `act` `(N, act_dim)` → `(N,)`;
    /// `obs` `(B, obs_dim)` with `act` `(B, N, act_dim)` → `(B, N)` or `(B, act_dim)` → `(B,)`.
    /// A chunk may also be `(chunk_len, action_dim)`. `t` is the step (an int, or `(B,)` ints).
    #[allow(unsafe_code, reason = "filling the numpy array this call just created")]
    #[pyo3(signature = (obs, act, t, extras=None))]
    fn score<'py>(
        &self,
        py: Python<'py>,
        obs: &Bound<'py, PyAny>,
        act: &Bound<'py, PyAny>,
        t: &Bound<'py, PyAny>,
        extras: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let args = self.score_args(obs, act, t, extras)?;
        let out = PyArrayDyn::<f32>::zeros(py, IxDyn(&args.out_shape), false);
        // SAFETY: `out` was just created here and is not shared with anything yet.
        let out_slice = unsafe { out.as_slice_mut() }.map_err(|e| PyValueError::new_err(e.to_string()))?;
        args.detach(py, |o, ex, t, a, n| self.v.score_into(o, ex, t, a, n, out_slice))?;
        Ok(out)
    }

    /// Every member's scores, `(members, *score's shape)` (one network: `(1, …)`); `score` is their
    /// mean.
    #[allow(unsafe_code, reason = "filling the numpy array this call just created")]
    #[pyo3(signature = (obs, act, t, extras=None))]
    fn score_members<'py>(
        &self,
        py: Python<'py>,
        obs: &Bound<'py, PyAny>,
        act: &Bound<'py, PyAny>,
        t: &Bound<'py, PyAny>,
        extras: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let args = self.score_args(obs, act, t, extras)?;
        let shape: Vec<usize> =
            std::iter::once(self.v.members()).chain(args.out_shape.iter().copied()).collect();
        let out = PyArrayDyn::<f32>::zeros(py, IxDyn(&shape), false);
        // SAFETY: `out` was just created here and is not shared with anything yet.
        let out_slice = unsafe { out.as_slice_mut() }.map_err(|e| PyValueError::new_err(e.to_string()))?;
        args.detach(py, |o, ex, t, a, n| self.v.score_members_into(o, ex, t, a, n, out_slice))?;
        Ok(out)
    }

    /// Best-of-N's choice, the verifier core's rule (`verifier::Verifier::pick`): `obs`
    /// `(obs_dim,)` with `act` `(N, chunk)`, or `(B, obs_dim)` with `(B, N, chunk)`. Returns
    /// `(index, scores, spread, fell_back, agreement)`: per group the chosen index, whether an
    /// ensemble fell back to the first candidate and the share of members preferring the pick
    /// (lists of B), and every candidate's score and spread shaped like `score`'s result.
    #[pyo3(signature = (obs, act, t, extras=None))]
    #[allow(clippy::type_complexity)] // the five results of one pick
    fn pick<'py>(
        &self,
        py: Python<'py>,
        obs: &Bound<'py, PyAny>,
        act: &Bound<'py, PyAny>,
        t: &Bound<'py, PyAny>,
        extras: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<(Vec<usize>, Bound<'py, PyArrayDyn<f32>>, Bound<'py, PyArrayDyn<f32>>, Vec<bool>, Vec<f32>)>
    {
        let args = self.score_args(obs, act, t, extras)?;
        if args.out_shape.len() == 1 && args.t.len() > 1 {
            return Err(PyValueError::new_err(
                "pick needs groups of candidates: act (N, chunk) for obs (obs_dim,), or (B, N, chunk) for (B, obs_dim)",
            ));
        }
        let p = args.detach(py, |o, ex, t, a, n| self.v.pick(o, ex, t, a, n))?;
        let shaped = |v: Vec<f32>| numpy::PyArray1::from_vec(py, v).reshape(IxDyn(&args.out_shape));
        Ok((p.index, shaped(p.scores)?, shaped(p.spread)?, p.fell_back, p.agreement))
    }

    /// Guidance gradients w.r.t. the chunk as passed: d log C / d act (classifier) or d Q / d act.
    /// `obs` `(obs_dim,)` with `act` a chunk → the chunk's shape; `obs` `(B, obs_dim)` with `act`
    /// `(B, chunk)` → `(B, chunk)`; a chunk is `(act_dim,)` or `(chunk_len, action_dim)`.
    #[allow(unsafe_code, reason = "filling the numpy array this call just created")]
    #[pyo3(signature = (obs, act, t, extras=None))]
    fn grad<'py>(
        &self,
        py: Python<'py>,
        obs: &Bound<'py, PyAny>,
        act: &Bound<'py, PyAny>,
        t: &Bound<'py, PyAny>,
        extras: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let od = self.v.obs_dim();
        let obs = f32_array(obs, "obs", || format!("({od},) or (B, {od})"))?;
        let batch = self.obs_rows(&obs)?;
        let expected = || match batch {
            None => format!("{} for obs of shape ({od},)", self.chunk_shapes("")),
            Some(b) => format!("{} for obs of shape ({b}, {od})", self.chunk_shapes(&format!("{b}, "))),
        };
        let act = f32_array(act, "act", expected)?;
        let lead = self.chunks(act.shape()).map(|c| c.lead);
        let b = match (batch, lead.as_deref()) {
            (None, Some([])) => 1,
            (Some(b), Some([b2])) if *b2 == b => b,
            _ => {
                return Err(PyValueError::new_err(format!(
                    "act must have shape {}; got {}",
                    expected(),
                    shape_str(act.shape())
                )));
            }
        };
        let t = steps(t, b)?;
        let extras = self.extras(extras, batch)?;
        let out = PyArrayDyn::<f32>::zeros(py, IxDyn(act.shape()), false);
        // SAFETY: `out` was just created here and is not shared with anything yet.
        let out_slice = unsafe { out.as_slice_mut() }.map_err(|e| PyValueError::new_err(e.to_string()))?;
        let (o, a) = (values(&obs), values(&act));
        let ex: Vec<_> = extras.iter().map(values).collect();
        py.detach(|| {
            let ex: Vec<&[f32]> = ex.iter().map(|c| c.as_ref()).collect();
            self.v.grad_into(&o, &ex, &t, &a, out_slice)
        })
        .map_err(from_verifier)?;
        Ok(out)
    }
}
