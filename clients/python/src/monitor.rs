//! `ufops.Monitor`: a failure monitor bound to the verifier artifact it was calibrated for,
//! stepping the verifier core's running statistic (`verifier::monitor`, the code `ufops monitor
//! evaluate` and `steer::Monitor` run) on the score of each executed chunk.

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::arrays::{f32_array, values};
use crate::errors::from_verifier;
use crate::verifier::PyVerifier;
use verifier::monitor::{MonitorRecord, MonitorState, MonitorStep};

#[pyclass(module = "ufops._ufops", name = "Monitor")]
pub struct PyMonitor {
    verifier: Py<PyVerifier>,
    record: MonitorRecord,
    state: MonitorState,
}

fn step_tuple(s: MonitorStep) -> (f32, f64, bool, bool) {
    (s.score, s.statistic, s.alarm, s.first_alarm)
}

#[pymethods]
impl PyMonitor {
    /// Binds a monitor record (its JSON) to `verifier`; refuses a verifier other than the
    /// artifact the record was calibrated for.
    #[new]
    fn new(verifier: Py<PyVerifier>, record_json: &str) -> PyResult<Self> {
        let record = MonitorRecord::from_json(record_json.as_bytes()).map_err(from_verifier)?;
        record.check_artifact(verifier.get().v.id()).map_err(from_verifier)?;
        let state = record.state();
        Ok(PyMonitor { verifier, record, state })
    }

    /// Scores one chunk (`(act_dim,)` or `(chunk_len, action_dim)`) for one observation history
    /// (`(obs_dim,)`) at step `t` and steps the statistic: `(score, statistic, alarm, first_alarm)`.
    fn update(
        &mut self,
        py: Python<'_>,
        obs: &Bound<'_, PyAny>,
        act: &Bound<'_, PyAny>,
        t: u32,
    ) -> PyResult<(f32, f64, bool, bool)> {
        let v = &self.verifier.get().v;
        let (od, ad) = (v.obs_dim(), v.act_dim());
        let obs = f32_array(obs, "obs", || format!("({od},)"))?;
        let act = f32_array(act, "act", || format!("({ad},)"))?;
        let (o, a) = (values(&obs), values(&act));
        if o.len() != od || a.len() != ad {
            return Err(PyValueError::new_err(format!(
                "the monitor takes one observation history of {od} values and one chunk of {ad}; got {} and {}",
                o.len(),
                a.len()
            )));
        }
        let score = py.detach(|| v.score(&o, &[t], &a, 1)).map_err(from_verifier)?[0];
        Ok(step_tuple(self.state.update(score)))
    }

    /// Steps the statistic with a score already computed (best-of-N's score of the chosen chunk).
    fn update_score(&mut self, score: f32) -> (f32, f64, bool, bool) {
        step_tuple(self.state.update(score))
    }

    /// Starts a new episode.
    fn reset(&mut self) {
        self.state.reset();
    }

    #[getter]
    fn alarmed(&self) -> bool {
        self.state.alarmed()
    }

    #[getter]
    fn threshold(&self) -> f64 {
        self.record.threshold
    }

    #[getter]
    fn alpha(&self) -> f64 {
        self.record.alpha
    }

    #[getter]
    fn artifact_id(&self) -> &str {
        &self.record.artifact_id
    }

    fn record_json(&self) -> PyResult<String> {
        serde_json::to_string(&self.record).map_err(|e| PyValueError::new_err(e.to_string()))
    }
}
