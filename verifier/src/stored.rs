//! Scoring stored episodes (feature `steps`): every step of each episode of a selection, read
//! through the store's selection path (`store::for_each_episode_with_layers`) and scored with a
//! [`StepScorer`]; an episode's score ([`episode_score`]); and the score filter of a selection
//! ([`filter_by_score`]). Export curation, the review queue's score job, `ufops rank`, the failure
//! monitors and the replay of steering telemetry all score stored steps this way, and
//! [`StoredEpisodesError`] is the error of the crates that do nothing else (`monitor`, `replay`).

use store::{EpisodeRecord, Progress, Selected, Store, StoreError};

use crate::steps::StepScorer;
use crate::VerifierError;

/// Why work on stored episodes failed: reading them (the store), scoring them (the verifier), or
/// a request that cannot be met.
#[derive(Debug, thiserror::Error)]
pub enum StoredEpisodesError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Verifier(#[from] VerifierError),
    #[error("{0}")]
    Invalid(String),
}

impl StoredEpisodesError {
    pub fn invalid(msg: impl Into<String>) -> Self {
        StoredEpisodesError::Invalid(msg.into())
    }
}

/// An episode's score: the mean of its steps' scores, as Demo-SCORE aggregates a rollout
/// classifier over a demonstration. `None` for an episode without steps.
pub fn episode_score(step_scores: &[f32]) -> Option<f64> {
    (!step_scores.is_empty())
        .then(|| step_scores.iter().map(|&x| x as f64).sum::<f64>() / step_scores.len() as f64)
}

/// Scores every step of each episode (in order) with `scorer`, reading steps with bounded
/// memory (the layers it reads joined), and hands `f` the episode's index, record and step
/// scores (all finite).
pub async fn score_each_episode(
    store: &Store,
    episodes: &[EpisodeRecord],
    scorer: &dyn StepScorer,
    mut f: impl FnMut(usize, &EpisodeRecord, Vec<f32>) -> Result<(), StoredEpisodesError>,
) -> Result<(), StoredEpisodesError> {
    store::for_each_episode_with_layers(store, episodes, &scorer.layers(), None, |i, e, steps| {
        let s = scorer
            .score_steps(&steps)
            .map_err(|m| StoredEpisodesError::invalid(format!("scoring episode {}: {m}", e.id)))?;
        if s.iter().any(|x| !x.is_finite()) {
            return Err(StoredEpisodesError::invalid(format!(
                "scoring episode {}: the verifier returned a non-finite score",
                e.id
            )));
        }
        f(i, e, s)
    })
    .await
}

/// Scores each episode (in order) with `scorer`: its [`episode_score`].
pub async fn score_episodes(
    store: &Store,
    episodes: &[EpisodeRecord],
    scorer: &dyn StepScorer,
    progress: Progress<'_>,
) -> Result<Vec<Option<f64>>, StoredEpisodesError> {
    let mut scores = vec![None; episodes.len()];
    let total = episodes.len();
    score_each_episode(store, episodes, scorer, |i, _, s| {
        scores[i] = episode_score(&s);
        if let Some(p) = progress {
            p(i + 1, total);
        }
        Ok(())
    })
    .await?;
    Ok(scores)
}

/// Narrows a resolved selection to the episodes whose score lies in `sel.selection.score`
/// (a no-op without one) and records each kept episode's score.
pub async fn filter_by_score(
    store: &Store,
    sel: &mut Selected,
    scorer: &dyn StepScorer,
    progress: Progress<'_>,
) -> Result<(), StoredEpisodesError> {
    let Some(range) = sel.selection.score.clone() else { return Ok(()) };
    let scores = score_episodes(store, &sel.episodes, scorer, progress).await?;
    sel.scored = Some(sel.episodes.len());
    let mut kept = Vec::new();
    for (e, s) in std::mem::take(&mut sel.episodes).into_iter().zip(scores) {
        if let Some(s) = s.filter(|s| range.contains(*s)) {
            sel.scores.insert(e.id.clone(), s);
            kept.push(e);
        }
    }
    sel.episodes = kept;
    Ok(())
}
