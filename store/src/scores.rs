//! Stored verifier scores of episodes (one row per artifact and episode: the mean step score
//! and the per-step series, written by the `score` job) and the episode's `review_score`, its
//! score by the artifact that scores its policy's review queue, kept in step with every write
//! that changes which artifact that is. The queue itself is `store-labeling`'s.

use crate::catalog::{insert_rows, Tx, Val};
use crate::{now_rfc3339, Store, StoreError};
use serde::Serialize;

/// The artifact kind and alias that score a checkpoint's episodes when its policy names none.
pub const DEFAULT_REVIEW_KIND: &str = "classifier";
pub const DEFAULT_REVIEW_ALIAS: &str = "latest";

/// An episode's stored verifier scores by one artifact: one per step, and their mean.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema), schema(as = EpisodeScores))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct EpisodeScore {
    pub episode_id: String,
    pub artifact_id: String,
    /// The mean of `step_scores` (what orders the queue).
    pub score: f64,
    /// One score per step, in step order (a classifier's success probability).
    pub step_scores: Vec<f32>,
    /// The score job that stored them.
    pub job_id: Option<String>,
    pub created_at: String,
}

/// Sets `episodes.review_score` to the episode's stored score by its review artifact (the
/// policy's setting, else its checkpoint's `classifier@latest`), NULL without one, for the rows
/// a condition appended to this statement picks. Every write that can change that score runs it
/// in its own transaction: scores stored, the policy's setting, the `latest` classifier alias
/// moving (a new episode has no stored score: its id is new). The same rule as
/// the review queue's joins and migration 0014's backfill.
pub(crate) const REFRESH_REVIEW_SCORE: &str = "UPDATE episodes SET review_score = (\
     SELECT s.score FROM episode_scores s WHERE s.episode_id = episodes.id AND s.artifact_id = COALESCE(\
     (SELECT ra.artifact_id FROM review_artifacts ra WHERE ra.policy = episodes.policy), \
     (SELECT aa.artifact_id FROM artifact_aliases aa WHERE aa.policy = episodes.policy \
     AND aa.checkpoint = episodes.checkpoint AND aa.kind = 'classifier' AND aa.alias = 'latest'))) WHERE ";

/// [`REFRESH_REVIEW_SCORE`] for the episodes `ids` (in statements of at most 500 ids).
pub(crate) async fn refresh_review_scores_of(tx: &mut Tx, ids: &[String]) -> Result<(), StoreError> {
    for chunk in ids.chunks(500) {
        let sql = format!("{REFRESH_REVIEW_SCORE}id IN ({})", crate::catalog::placeholders(chunk.len()));
        let mut q = sqlx::query(&sql);
        for id in chunk {
            q = q.bind(id);
        }
        q.execute(&mut **tx).await?;
    }
    Ok(())
}

/// Sets the `review_score` of a policy's episodes, or one checkpoint's, to their stored score by
/// their review artifact (the policy's setting, else the checkpoint's `classifier@latest`), NULL
/// without one: run by every write that moves that artifact, in its own transaction.
pub async fn refresh_review_scores_where(
    tx: &mut Tx,
    policy: &str,
    checkpoint: Option<&str>,
) -> Result<(), StoreError> {
    let sql = match checkpoint {
        Some(_) => format!("{REFRESH_REVIEW_SCORE}policy = $1 AND checkpoint = $2"),
        None => format!("{REFRESH_REVIEW_SCORE}policy = $1"),
    };
    sqlx::query(&sql).bind(policy).bind(checkpoint).execute(&mut **tx).await?;
    Ok(())
}

impl Store {
    /// Stores episode scores of `artifact_id` (replacing earlier ones): `(episode, mean step
    /// score, per-step scores)`.
    pub async fn put_episode_scores(
        &self,
        artifact_id: &str,
        job_id: Option<&str>,
        rows: Vec<(String, f64, Vec<f32>)>,
    ) -> Result<(), StoreError> {
        if rows.is_empty() {
            return Ok(());
        }
        let now = now_rfc3339();
        let mut vals = Vec::with_capacity(rows.len());
        let ids: Vec<String> = rows.iter().map(|(e, _, _)| e.clone()).collect();
        for (episode, score, steps) in rows {
            if !score.is_finite() || steps.iter().any(|x| !x.is_finite()) {
                return Err(StoreError::invalid(format!("episode {episode}: a score is not finite")));
            }
            vals.push(vec![
                Val::S(artifact_id.into()),
                Val::S(episode),
                Val::F(score),
                Val::S(serde_json::to_string(&steps)?),
                Val::OS(job_id.map(String::from)),
                Val::S(now.clone()),
            ]);
        }
        let mut tx = self.catalog().begin_write().await?;
        insert_rows(
            &mut tx,
            "episode_scores",
            &["artifact_id", "episode_id", "score", "step_scores", "job_id", "created_at"],
            vals,
            "ON CONFLICT (artifact_id, episode_id) DO UPDATE SET score = excluded.score, \
             step_scores = excluded.step_scores, job_id = excluded.job_id, created_at = excluded.created_at",
        )
        .await?;
        refresh_review_scores_of(&mut tx, &ids).await?;
        let event = crate::events::NewEvent::new(
            crate::events::EventKind::ReviewScored,
            artifact_id,
            serde_json::json!({"episodes": ids.len(), "job_id": job_id}),
        );
        self.commit_with_events(tx, &[event]).await?;
        Ok(())
    }
}
