//! What a verifier's held-out metrics say about steering with it: the action-sensitivity figure.
//!
//! A held-out AUROC over every (obs, chunk, t) sample is mostly earned by the observation: after a
//! missed grasp the outcome is visible whatever chunk comes next. Best-of-N and guidance only use
//! how the score ranks *chunks* at one observation. The trainer therefore trains an
//! observation-only twin on the same split and recipe (the action input held constant) and
//! records, next to the AUROC, how much the chunk adds: the twin's AUROC, the gain over it, and
//! the AUROC of the verifier's excess over the twin *within* strata of samples the twin scores
//! alike (the action AUROC). The record and its
//! flag live here so the trainer that writes it, the listings that show it and the robot-side
//! helpers that warn about it read one definition.

use serde::{Deserialize, Serialize};

/// Below this stratified action AUROC a verifier is flagged as unlikely to steer well: among
/// samples whose observation-predicted outcome is alike, the chunks it prefers are the ones that
/// failed more often (below chance). Chosen on the demo's verifiers, where action AUROCs of
/// 0.55-0.92 all steered best-of-N up by 21-28 pp and one of 0.25 steered it down by 30 pp
/// (README, "Which verifier will steer well"): a higher floor flagged verifiers that steered well.
pub const ACTION_AUC_FLOOR: f64 = 0.5;

/// Samples in a twin-score stratum whose positive share lies in this range are ones the
/// observation alone leaves open (the "unsure" samples).
pub const UNSURE_POSITIVE_SHARE: (f64, f64) = (0.2, 0.8);

/// The action-sensitivity figure of a verifier (`config.json`:
/// `metrics.final.action_sensitivity`), measured on its split's held-out samples.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ActionSensitivity {
    /// Held-out AUROC of the observation-only twin (same samples, recipe and seed; the action
    /// input held constant).
    pub obs_only_auc: Option<f64>,
    /// The full verifier's held-out AUROC minus the twin's.
    pub auc_gain: Option<f64>,
    /// The AUROC of the verifier's score in excess of the twin's (`full − twin`: at one
    /// observation the twin's score is the same for every candidate, so this excess is what a
    /// steering step ranks candidates by) within strata of held-out samples the twin scores alike
    /// (`strata` equal-count bins of the twin's score), pooled over strata weighted by their
    /// positive-negative pairs: how well the chunk ranks outcomes once the observation's risk is
    /// accounted for. 0.5: the chunk adds nothing a steering step could use.
    pub action_auc: Option<f64>,
    pub strata: usize,
    /// Share of held-out samples in strata the twin leaves open (positive share within
    /// [`UNSURE_POSITIVE_SHARE`]).
    pub unsure_fraction: f64,
    /// On those samples: the full verifier's AUROC and the twin's.
    pub unsure_auc: Option<f64>,
    pub unsure_obs_only_auc: Option<f64>,
    /// Steering with this verifier is unlikely to help (see [`ActionSensitivity::flag`]).
    pub flagged: bool,
    /// Why it is flagged, in words a user can act on.
    #[serde(default)]
    pub reason: Option<String>,
    /// Seconds the twin took to train.
    #[serde(default)]
    pub twin_seconds: f64,
}

impl ActionSensitivity {
    /// The flag rule: a stratified action AUROC below [`ACTION_AUC_FLOOR`], or none at all
    /// while both outcomes were held out (the twin's score separates every stratum: the
    /// observation alone decided every held-out sample, and nothing was left for the chunk). Sets
    /// `flagged` and `reason`; without both outcomes held out there is no verdict.
    pub fn flag(mut self) -> Self {
        self.flagged = match self.action_auc {
            Some(a) => a < ACTION_AUC_FLOOR,
            None => self.obs_only_auc.is_some(),
        };
        self.reason = self.flagged.then(|| match self.action_auc {
            None => format!(
                "the verifier's observation-only twin separates every stratum of held-out samples (AUROC {:.3}): \
                 the observation alone decided them, so nothing shows that the verifier ranks action chunks, and \
                 best-of-N or guidance with it may not help. Train on rollouts where the outcome is still open \
                 when the chunk is chosen, or evaluate a steered run before relying on it",
                self.obs_only_auc.unwrap_or(f64::NAN)
            ),
            Some(_) => format!(
                "the verifier ranks action chunks at {:.2} AUROC among held-out samples its observation-only \
                 twin scores alike (below chance, {ACTION_AUC_FLOOR}; overall AUROC gain over the twin {}): the \
                 chunks it prefers failed more often, and best-of-N or guidance with it may hurt. Check that it \
                 was trained on this checkpoint's own rollouts, train on more, or evaluate a steered run before \
                 relying on it",
                self.action_auc.unwrap_or(f64::NAN),
                self.auc_gain.map(|g| format!("{g:+.3}")).unwrap_or_else(|| "unknown".into()),
            ),
        });
        self
    }

    /// The figure recorded in an artifact's `config.json` metrics (`None` for artifacts trained
    /// without a twin, e.g. before it existed).
    pub fn from_metrics(metrics: &serde_json::Value) -> Option<Self> {
        serde_json::from_value(metrics.get("final")?.get("action_sensitivity")?.clone()).ok()
    }

    /// One line for listings: `action 0.71 (obs-only 0.90)`, with `FLAGGED` when flagged.
    pub fn summary(&self) -> String {
        let n = |x: Option<f64>| x.map(|v| format!("{v:.3}")).unwrap_or_else(|| "-".into());
        format!(
            "action auroc {} (obs-only twin {}, gain {}){}",
            n(self.action_auc),
            n(self.obs_only_auc),
            self.auc_gain.map(|g| format!("{g:+.3}")).unwrap_or_else(|| "-".into()),
            if self.flagged { "  FLAGGED: unlikely to steer well" } else { "" }
        )
    }
}

impl crate::Verifier {
    /// The artifact's action-sensitivity figure, when its trainer recorded one.
    pub fn action_sensitivity(&self) -> Option<ActionSensitivity> {
        ActionSensitivity::from_metrics(&self.config().metrics)
    }

    /// A warning for steering helpers to show once: set when the artifact is flagged as unlikely to
    /// steer well.
    pub fn steering_warning(&self) -> Option<String> {
        let s = self.action_sensitivity().filter(|s| s.flagged)?;
        Some(format!(
            "verifier {}: {}",
            self.id().unwrap_or("(no id)"),
            s.reason.unwrap_or_else(|| "flagged as unlikely to steer well".into())
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn figure(action_auc: Option<f64>) -> ActionSensitivity {
        ActionSensitivity {
            obs_only_auc: Some(0.9),
            auc_gain: Some(0.01),
            action_auc,
            strata: 10,
            unsure_fraction: 0.3,
            unsure_auc: None,
            unsure_obs_only_auc: None,
            flagged: false,
            reason: None,
            twin_seconds: 0.0,
        }
        .flag()
    }

    #[test]
    fn flags_below_the_floor_only() {
        assert!(figure(Some(0.45)).flagged);
        assert!(figure(Some(0.45)).reason.unwrap().contains("0.45 AUROC"));
        assert!(!figure(Some(0.55)).flagged, "above chance: the demo's verifiers at 0.55 steered well");
        assert!(!figure(Some(0.75)).flagged);
        assert!(figure(None).flagged, "the twin decided every stratum: nothing left for the chunk");
        assert!(figure(None).reason.unwrap().contains("separates every stratum"));
        let no_outcomes = ActionSensitivity { obs_only_auc: None, ..figure(None) }.flag();
        assert!(!no_outcomes.flagged, "without both outcomes held out there is no verdict");
    }

    #[test]
    fn reads_back_from_metrics() {
        let f = figure(Some(0.4));
        let m = serde_json::json!({ "final": { "action_sensitivity": f } });
        assert_eq!(ActionSensitivity::from_metrics(&m), Some(f));
        assert_eq!(ActionSensitivity::from_metrics(&serde_json::json!({ "final": {} })), None);
    }
}
