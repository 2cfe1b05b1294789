//! The failure alarm on the robot: a [`Monitor`] scores each executed chunk with the verifier it
//! was calibrated for and steps the monitor's running statistic ([`verifier::monitor`]: the same
//! code `ufops monitor evaluate` runs offline, so both raise the alarm at the same step).

use verifier::monitor::{MonitorRecord, MonitorState, MonitorStep};

use crate::{Result, Scorer, SteerError, Verifier};

/// A calibrated failure monitor bound to its verifier.
pub struct Monitor<S: Scorer> {
    scorer: S,
    record: MonitorRecord,
    state: MonitorState,
}

impl<'a> Monitor<&'a Verifier> {
    /// Binds `record` to `verifier`; refuses a verifier other than the artifact it was
    /// calibrated for.
    pub fn for_verifier(verifier: &'a Verifier, record: MonitorRecord) -> Result<Self> {
        Monitor::new(verifier, verifier.id(), record)
    }
}

impl<S: Scorer> Monitor<S> {
    /// Binds `record` to a scorer whose artifact id is `artifact_id`; refuses any id but the
    /// record's, and a record that fails its checks.
    pub fn new(scorer: S, artifact_id: Option<&str>, record: MonitorRecord) -> Result<Self> {
        record.check()?;
        record.check_artifact(artifact_id)?;
        let state = record.state();
        Ok(Monitor { scorer, record, state })
    }

    /// Scores the chunk about to run (or just run) at step `t` of the episode and steps the
    /// statistic: `alarm` is true while it exceeds the threshold, `first_alarm` once.
    pub fn update(&mut self, obs_history: &[f32], chunk: &[f32], t: u32) -> Result<MonitorStep> {
        let ad = self.scorer.act_dim();
        if chunk.len() != ad {
            return Err(SteerError::Input(format!(
                "the monitor takes one chunk of {ad} values (chunk_len x action_dim), got {}",
                chunk.len()
            )));
        }
        let score = self.scorer.score(obs_history, chunk, t)?[0];
        Ok(self.state.update(score))
    }

    /// Steps the statistic with a score the caller already has (best-of-N scored the chosen
    /// chunk): no second forward pass.
    pub fn update_score(&mut self, score: f32) -> MonitorStep {
        self.state.update(score)
    }

    /// Starts a new episode.
    pub fn reset(&mut self) {
        self.state.reset();
    }

    pub fn alarmed(&self) -> bool {
        self.state.alarmed()
    }

    pub fn record(&self) -> &MonitorRecord {
        &self.record
    }
}
