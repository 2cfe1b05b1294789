//! The failure monitor's contract, once: the monitor record (what a calibration produced and
//! the store keeps), the running statistic over a verifier's per-step scores, the alarm rule,
//! and the split-conformal threshold. The offline evaluation (`monitor` crate), the robot
//! (`steer::Monitor`) and the Python package all step the same [`MonitorState`], so they raise
//! the same alarm at the same step.
//!
//! The rule. At step `t` the verifier scores the executed chunk: `s_t` (a classifier's success
//! probability, or a Q value). The risk is `r_t = 1 − s_t`, smoothed by an exponential moving
//! average `m_t = β·m_{t−1} + (1 − β)·r_t` (`m_0 = r_0`). The alarm fires at the first step with
//! `m_t > τ`. Calibration takes each calibration success's peak `max_t m_t` and sets `τ` to the
//! `⌈(n + 1)(1 − α)⌉`-th smallest of the n peaks (split conformal prediction). A fresh successful
//! episode, exchangeable with the calibration episodes, then has peak `> τ` — the alarm fires —
//! with probability at most α (and at least α − 1/(n + 1) when peaks have no ties).

use serde::{Deserialize, Serialize};

use crate::{Result, VerifierError};

/// The record's schema version.
pub const MONITOR_SCHEMA_VERSION: u32 = 1;
/// The calibration method the record names.
pub const SPLIT_CONFORMAL_PEAK: &str = "split_conformal_peak";

/// The running statistic the alarm thresholds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Statistic {
    /// Exponential moving average of the risk `1 − score` with weight `smoothing` (β, in [0, 1))
    /// on the past; β = 0 is the raw per-step risk.
    RiskEma { smoothing: f64 },
}

impl Statistic {
    pub fn check(&self) -> Result<()> {
        match *self {
            Statistic::RiskEma { smoothing } if (0.0..1.0).contains(&smoothing) => Ok(()),
            Statistic::RiskEma { smoothing } => {
                Err(VerifierError::Input(format!("monitor smoothing must be in [0, 1), got {smoothing}")))
            }
        }
    }
}

/// A calibrated monitor: immutable; the store names it by the sha256 of its JSON.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MonitorRecord {
    pub schema_version: u32,
    /// The verifier artifact whose scores it thresholds; it refuses any other.
    pub artifact_id: String,
    pub policy: String,
    pub checkpoint: String,
    /// [`SPLIT_CONFORMAL_PEAK`].
    pub method: String,
    pub statistic: Statistic,
    /// The false-alarm rate on successful episodes it guarantees (at most).
    pub alpha: f64,
    /// τ: the alarm fires when the statistic exceeds it.
    pub threshold: f64,
    /// The store version whose labels the calibration read.
    pub version: i64,
    /// The seed that drew the calibration episodes from the pool.
    pub seed: u64,
    /// The successful episodes the threshold was calibrated on, by id.
    pub calibration_episodes: Vec<String>,
}

impl MonitorRecord {
    /// Parses and checks a record (schema, method, statistic, α, a finite threshold).
    pub fn from_json(bytes: &[u8]) -> Result<Self> {
        let r: MonitorRecord = serde_json::from_slice(bytes)
            .map_err(|e| VerifierError::Input(format!("monitor record is invalid: {e}")))?;
        r.check()?;
        Ok(r)
    }

    pub fn check(&self) -> Result<()> {
        if self.schema_version != MONITOR_SCHEMA_VERSION {
            return Err(VerifierError::Input(format!(
                "monitor record schema_version {} (this client knows {MONITOR_SCHEMA_VERSION})",
                self.schema_version
            )));
        }
        if self.method != SPLIT_CONFORMAL_PEAK {
            return Err(VerifierError::Input(format!("unknown monitor method {:?}", self.method)));
        }
        self.statistic.check()?;
        if !(self.alpha > 0.0 && self.alpha < 1.0) {
            return Err(VerifierError::Input(format!("monitor alpha must be in (0, 1), got {}", self.alpha)));
        }
        if !self.threshold.is_finite() {
            return Err(VerifierError::Input("monitor threshold is not finite".into()));
        }
        Ok(())
    }

    /// Refuses a verifier the monitor was not calibrated for: its scores would be thresholded
    /// against another model's scale, and the false-alarm guarantee would be void.
    pub fn check_artifact(&self, artifact_id: Option<&str>) -> Result<()> {
        match artifact_id {
            Some(id) if id == self.artifact_id => Ok(()),
            Some(id) => Err(VerifierError::Input(format!(
                "monitor was calibrated for verifier artifact {} and cannot run on artifact {id}: calibrate one \
                 for it (`ufops monitor calibrate --artifact {id}`)",
                self.artifact_id
            ))),
            None => Err(VerifierError::Input(format!(
                "monitor was calibrated for verifier artifact {}, and this verifier has no artifact id to check it \
                 against (load it from its artifact directory, the store or the API)",
                self.artifact_id
            ))),
        }
    }

    pub fn state(&self) -> MonitorState {
        MonitorState::new(self.statistic, self.threshold)
    }
}

/// What one step of the monitor reports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MonitorStep {
    /// The verifier's score of this step.
    pub score: f32,
    /// The running statistic after this step.
    pub statistic: f64,
    /// The statistic exceeds the threshold at this step.
    pub alarm: bool,
    /// This is the episode's first alarm.
    pub first_alarm: bool,
}

/// The monitor's state over one episode; [`MonitorState::reset`] between episodes.
#[derive(Debug, Clone)]
pub struct MonitorState {
    statistic: Statistic,
    threshold: f64,
    current: Option<f64>,
    alarmed: bool,
}

impl MonitorState {
    pub fn new(statistic: Statistic, threshold: f64) -> Self {
        MonitorState { statistic, threshold, current: None, alarmed: false }
    }

    pub fn reset(&mut self) {
        self.current = None;
        self.alarmed = false;
    }

    /// The statistic after a step scored `score`.
    #[inline]
    pub fn update(&mut self, score: f32) -> MonitorStep {
        let risk = 1.0 - score as f64;
        let m = match (self.statistic, self.current) {
            (_, None) => risk,
            (Statistic::RiskEma { smoothing }, Some(prev)) => smoothing * prev + (1.0 - smoothing) * risk,
        };
        self.current = Some(m);
        let alarm = m > self.threshold;
        let first_alarm = alarm && !self.alarmed;
        self.alarmed |= alarm;
        MonitorStep { score, statistic: m, alarm, first_alarm }
    }

    /// Whether the alarm has fired in this episode.
    pub fn alarmed(&self) -> bool {
        self.alarmed
    }
}

/// An episode's peak statistic (its conformity score): `max_t m_t`; −∞ for no steps.
pub fn peak(statistic: Statistic, scores: &[f32]) -> f64 {
    let mut s = MonitorState::new(statistic, f64::INFINITY);
    scores.iter().map(|&x| s.update(x).statistic).fold(f64::NEG_INFINITY, f64::max)
}

/// The first step at which the alarm fires on an episode's scores, if any.
pub fn first_alarm(statistic: Statistic, threshold: f64, scores: &[f32]) -> Option<usize> {
    let mut s = MonitorState::new(statistic, threshold);
    scores.iter().position(|&x| s.update(x).alarm)
}

/// The fewest calibration episodes for which a finite threshold exists at `alpha`:
/// `⌈(n + 1)(1 − α)⌉ ≤ n` ⇔ `n ≥ (1 − α)/α`.
pub fn min_calibration_episodes(alpha: f64) -> usize {
    ((1.0 - alpha) / alpha - 1e-9).ceil().max(1.0) as usize
}

/// The split-conformal threshold: the `⌈(n + 1)(1 − α)⌉`-th smallest of the calibration peaks.
pub fn conformal_threshold(peaks: &[f64], alpha: f64) -> Result<f64> {
    if !(alpha > 0.0 && alpha < 1.0) {
        return Err(VerifierError::Input(format!("alpha must be in (0, 1), got {alpha}")));
    }
    let mut p: Vec<f64> = peaks.iter().copied().filter(|x| x.is_finite()).collect();
    let n = p.len();
    let k = ((n as f64 + 1.0) * (1.0 - alpha) - 1e-9).ceil() as usize;
    if n == 0 || k > n {
        return Err(VerifierError::Input(format!(
            "calibrating at alpha = {alpha} needs at least {} successful episodes with steps, got {n}",
            min_calibration_episodes(alpha)
        )));
    }
    p.sort_by(f64::total_cmp);
    Ok(p[k.max(1) - 1])
}

#[cfg(test)]
mod tests {
    use super::*;

    const EMA: Statistic = Statistic::RiskEma { smoothing: 0.7 };

    #[test]
    fn threshold_is_the_conformal_order_statistic() {
        let peaks: Vec<f64> = (1..=19).map(|i| i as f64).collect();
        // n = 19, α = 0.1: ⌈20 · 0.9⌉ = 18th smallest.
        assert_eq!(conformal_threshold(&peaks, 0.1).unwrap(), 18.0);
        assert_eq!(min_calibration_episodes(0.1), 9);
        assert!(conformal_threshold(&peaks[..8], 0.1).is_err());
        assert_eq!(conformal_threshold(&peaks[..9], 0.1).unwrap(), 9.0);
    }

    #[test]
    fn ema_and_alarm_follow_the_rule() {
        let mut s = MonitorState::new(EMA, 0.5);
        let a = s.update(0.9); // risk 0.1
        assert!((a.statistic - 0.1).abs() < 1e-6 && !a.alarm);
        let b = s.update(0.0); // 0.7·0.1 + 0.3·1
        assert!((b.statistic - 0.37).abs() < 1e-6 && !b.alarm);
        let c = s.update(0.0); // 0.7·0.37 + 0.3
        assert!(c.alarm && c.first_alarm);
        assert!(!s.update(0.0).first_alarm);
        s.reset();
        assert!(!s.alarmed());
        assert_eq!(first_alarm(EMA, 0.5, &[0.9, 0.0, 0.0, 0.0]), Some(2));
        assert!((peak(EMA, &[0.9, 0.0, 0.0]) - c.statistic).abs() < 1e-12);
    }

    #[test]
    fn a_record_refuses_another_artifact() {
        let r = MonitorRecord {
            schema_version: 1,
            artifact_id: "aaaa".into(),
            policy: "p".into(),
            checkpoint: "c".into(),
            method: SPLIT_CONFORMAL_PEAK.into(),
            statistic: EMA,
            alpha: 0.1,
            threshold: 0.4,
            version: 1,
            seed: 0,
            calibration_episodes: vec![],
        };
        assert!(r.check_artifact(Some("aaaa")).is_ok());
        let e = r.check_artifact(Some("bbbb")).unwrap_err().to_string();
        assert!(e.contains("calibrated for verifier artifact aaaa") && e.contains("bbbb"), "{e}");
        assert!(r.check_artifact(None).is_err());
        let bytes = serde_json::to_vec(&r).unwrap();
        assert_eq!(MonitorRecord::from_json(&bytes).unwrap(), r);
        let bad = String::from_utf8(bytes).unwrap().replace("0.1", "1.5");
        assert!(MonitorRecord::from_json(bad.as_bytes()).is_err());
    }
}
