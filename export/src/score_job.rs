//! The `score` job: scores a policy's (or one checkpoint's) current
//! episodes with one verifier artifact and stores each episode's mean step score and per-step
//! series in the catalog (`Store::put_episode_scores`), so the labeling queue is ordered and the
//! timeline plotted from stored scores, never by a forward pass per page view. The scoring is
//! the verifier core's [`score_each_episode`], the one used by `ufops export --score-artifact`
//! and `ufops rank`.

use crate::{ExportError, Result};
use serde::{Deserialize, Serialize};
use store::{EpisodeFilter, Store};
use verifier::stored::{episode_score, score_each_episode};
use verifier::StepScorer;

/// The job's spec as the API queues it (the artifact already resolved to an id).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScoreJobSpec {
    pub artifact_id: String,
    pub policy: String,
    /// Only this checkpoint's episodes; default: all of the policy's.
    #[serde(default)]
    pub checkpoint: Option<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ScoreJobResult {
    pub artifact_id: String,
    pub episodes_scored: usize,
}

/// Episodes scored and stored per catalog write (and per progress report / cancel check).
const CHUNK: usize = 64;

/// Runs a score job: `progress` gets `{"scored": n, "total": m}`; `cancelled` is polled between
/// chunks (what was stored stays: each row is a complete score).
pub async fn run_score_job(
    store: &Store,
    job_id: Option<&str>,
    spec: &ScoreJobSpec,
    scorer: &dyn StepScorer,
    progress: &(dyn Fn(serde_json::Value) + Send + Sync),
    cancelled: &(dyn Fn() -> bool + Send + Sync),
) -> Result<ScoreJobResult> {
    let filter = EpisodeFilter {
        policy: Some(spec.policy.clone()),
        checkpoint: spec.checkpoint.clone(),
        ..Default::default()
    };
    let episodes = store.episodes(&filter).await?;
    let total = episodes.len();
    progress(serde_json::json!({"scored": 0, "total": total}));
    let mut done = 0;
    for chunk in episodes.chunks(CHUNK) {
        if cancelled() {
            return Err(ExportError::invalid("cancelled"));
        }
        let mut rows = Vec::with_capacity(chunk.len());
        score_each_episode(store, chunk, scorer, |_, e, steps| {
            if let Some(mean) = episode_score(&steps) {
                rows.push((e.id.clone(), mean, steps));
            }
            Ok(())
        })
        .await?;
        done += rows.len();
        store.put_episode_scores(&spec.artifact_id, job_id, rows).await?;
        progress(serde_json::json!({"scored": done, "total": total}));
    }
    Ok(ScoreJobResult { artifact_id: spec.artifact_id.clone(), episodes_scored: done })
}
