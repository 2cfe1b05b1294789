//! The review queue: each policy's episodes in the order that matters to a labeler, by the
//! scores stored for them (`store`'s `scores.rs`: the `score` job writes them, each episode's
//! `review_score` follows the artifact that scores its policy's queue), and that artifact's
//! setting per policy.

use serde::Serialize;
use std::future::Future;
use store::sql::{
    bind_val, covers, episode_conds, episode_from_row, label_conds, now_rfc3339, push_arg,
    refresh_review_scores_where, RowExt, Val, EPISODE_SELECT,
};
use store::{
    EpisodeFilter, EpisodeRecord, EpisodeScore, Store, StoreError, DEFAULT_REVIEW_ALIAS, DEFAULT_REVIEW_KIND,
};
use store_artifacts::Artifacts;

/// How the review queue is ordered. Every order ends with the episode id (a total order, so
/// keyset pages neither repeat nor skip), and episodes without a stored score come last.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReviewOrder {
    /// Score nearest 0.5 first (|score − 0.5| ascending): where the verifier is least sure.
    Uncertain,
    /// The verifier's score furthest from the current label first (|score − y|, y = 1 for
    /// success, 0 for failure, descending); unlabeled episodes after the labeled ones.
    Disagreement,
    /// By the label's source (e.g. `key`, `sim`, `import`), then id.
    Source,
}

impl std::str::FromStr for ReviewOrder {
    type Err = StoreError;
    fn from_str(s: &str) -> Result<Self, StoreError> {
        match s {
            "uncertain" => Ok(ReviewOrder::Uncertain),
            "disagreement" => Ok(ReviewOrder::Disagreement),
            "source" => Ok(ReviewOrder::Source),
            other => Err(StoreError::invalid(format!(
                "unknown order {other:?}: uncertain, disagreement, source or id"
            ))),
        }
    }
}

impl ReviewOrder {
    /// The SQL sort key (lower first) over the label columns of table alias `lab`. Numeric keys
    /// stay below 8 for scored episodes; 8 marks a scored but unlabeled episode (disagreement)
    /// and 9 an unscored one.
    ///
    /// Over the current labels (`lab` = `e`) these are, to the character, the expressions of
    /// migration 0014's indexes, which is what lets a policy's page walk them.
    fn key_sql(self, lab: &str) -> String {
        match self {
            ReviewOrder::Uncertain => "COALESCE(ABS(e.review_score - 0.5), 9.0)".into(),
            ReviewOrder::Disagreement => format!(
                "CASE WHEN e.review_score IS NULL THEN 9.0 WHEN {lab}.label = 'success' THEN e.review_score - 1.0 \
                 WHEN {lab}.label = 'failure' THEN 0.0 - e.review_score ELSE 8.0 END"
            ),
            ReviewOrder::Source => format!("{lab}.label_source"),
        }
    }

    fn numeric(self) -> bool {
        self != ReviewOrder::Source
    }
}

/// One episode of the review queue with the stored score that placed it.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ReviewEntry {
    pub episode: EpisodeRecord,
    /// The artifact scoring this episode's policy (override or its checkpoint's default alias).
    pub artifact_id: Option<String>,
    /// The episode's stored mean step score by that artifact; `None` until a score job ran.
    pub score: Option<f64>,
    /// The position of this entry in the order: pass the last one as the next page's cursor.
    pub cursor: String,
}

/// The artifact a policy's queue is scored with, when set explicitly.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ReviewArtifact {
    pub policy: String,
    pub artifact_id: String,
    pub updated_by: String,
    pub updated_at: String,
}

/// The artifact each episode row `e` is scored by: its policy's override, else its checkpoint's
/// default alias (its score by it is `e.review_score`, kept by the store's `scores.rs`).
const REVIEW_JOINS: &str = "LEFT JOIN review_artifacts ra ON ra.policy = e.policy \
     LEFT JOIN artifact_aliases aa ON aa.policy = e.policy AND aa.checkpoint = e.checkpoint \
     AND aa.kind = 'classifier' AND aa.alias = 'latest'";

/// The review queue on a [`Store`]: the artifact that scores each policy's queue, the
/// episodes' stored scores by it and the queue in the order a labeler asks for.
pub trait ReviewQueue {
    /// The artifact that scores `policy`'s queue when set explicitly.
    fn review_artifact(
        &self,
        policy: &str,
    ) -> impl Future<Output = Result<Option<ReviewArtifact>, StoreError>> + Send;

    /// Scores `policy`'s queue with `reference` (an artifact id or `P/C/KIND@ALIAS`, resolved
    /// now so the setting names one artifact).
    fn set_review_artifact(
        &self,
        policy: &str,
        reference: &str,
        actor: &str,
    ) -> impl Future<Output = Result<ReviewArtifact, StoreError>> + Send;

    /// Back to the default (each checkpoint's `classifier@latest`); false when none was set.
    fn clear_review_artifact(&self, policy: &str) -> impl Future<Output = Result<bool, StoreError>> + Send;

    /// The artifact that scores a checkpoint's episodes in the review queue, if any.
    fn review_artifact_for(
        &self,
        policy: &str,
        checkpoint: &str,
    ) -> impl Future<Output = Result<Option<String>, StoreError>> + Send;

    /// The artifact a score job for `policy` (one `checkpoint`'s episodes, or all) uses:
    /// `reference` (an id or `P/C/KIND@ALIAS`) resolved when given, else the checkpoint's review
    /// artifact, else the policy's setting; `None` when there is none. The API's
    /// `POST /v1/review/score` and `ufops review score` choose it alike.
    fn artifact_to_score(
        &self,
        policy: &str,
        checkpoint: Option<&str>,
        reference: Option<&str>,
    ) -> impl Future<Output = Result<Option<String>, StoreError>> + Send;

    /// An episode's stored score by `artifact_id` (default: the artifact of its review queue).
    fn episode_score(
        &self,
        episode_id: &str,
        artifact_id: Option<&str>,
    ) -> impl Future<Output = Result<EpisodeScore, StoreError>> + Send;

    /// The episodes matching `filter` (its `id` and `after` must be unset), now or as a past
    /// `version` froze them (its episodes and labels), in review `order` by the current scores, a
    /// keyset page after `cursor` (an entry's `cursor`). Any text is a position: one that is not
    /// a position of this order lies past its end (an empty page). A policy's `uncertain` and
    /// `disagreement` pages of the current labels walk an index on the order's key (migration
    /// 0014: a page costs its rows, plus those the other filters skip); without a policy, at a
    /// past version or in `source` order, a page sorts the filtered episodes.
    fn review_queue(
        &self,
        filter: &EpisodeFilter,
        order: ReviewOrder,
        cursor: Option<&str>,
        limit: i64,
    ) -> impl Future<Output = Result<Vec<ReviewEntry>, StoreError>> + Send;
}

impl ReviewQueue for Store {
    async fn review_artifact(&self, policy: &str) -> Result<Option<ReviewArtifact>, StoreError> {
        let row = sqlx::query(
            "SELECT policy, artifact_id, updated_by, updated_at FROM review_artifacts WHERE policy = $1",
        )
        .bind(policy)
        .fetch_optional(&self.catalog().pool)
        .await?;
        row.map(|r| {
            Ok(ReviewArtifact {
                policy: r.s("policy")?,
                artifact_id: r.s("artifact_id")?,
                updated_by: r.s("updated_by")?,
                updated_at: r.s("updated_at")?,
            })
        })
        .transpose()
    }

    async fn set_review_artifact(
        &self,
        policy: &str,
        reference: &str,
        actor: &str,
    ) -> Result<ReviewArtifact, StoreError> {
        let a = self.resolve_artifact(reference).await?;
        let now = now_rfc3339();
        let mut tx = self.catalog().begin_write().await?;
        sqlx::query(
            "INSERT INTO review_artifacts (policy, artifact_id, updated_by, updated_at) VALUES ($1, $2, $3, $4) \
             ON CONFLICT (policy) DO UPDATE SET artifact_id = excluded.artifact_id, updated_by = excluded.updated_by, \
             updated_at = excluded.updated_at",
        )
        .bind(policy)
        .bind(&a.id)
        .bind(actor)
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        refresh_review_scores_where(&mut tx, policy, None).await?;
        tx.commit().await?;
        Ok(ReviewArtifact {
            policy: policy.into(),
            artifact_id: a.id,
            updated_by: actor.into(),
            updated_at: now,
        })
    }

    async fn clear_review_artifact(&self, policy: &str) -> Result<bool, StoreError> {
        let mut tx = self.catalog().begin_write().await?;
        let r = sqlx::query("DELETE FROM review_artifacts WHERE policy = $1")
            .bind(policy)
            .execute(&mut *tx)
            .await?;
        if r.rows_affected() > 0 {
            refresh_review_scores_where(&mut tx, policy, None).await?;
        }
        tx.commit().await?;
        Ok(r.rows_affected() > 0)
    }

    async fn review_artifact_for(
        &self,
        policy: &str,
        checkpoint: &str,
    ) -> Result<Option<String>, StoreError> {
        if let Some(a) = self.review_artifact(policy).await? {
            return Ok(Some(a.artifact_id));
        }
        match self.resolve_alias(policy, checkpoint, DEFAULT_REVIEW_KIND, DEFAULT_REVIEW_ALIAS).await {
            Ok(a) => Ok(Some(a.id)),
            Err(StoreError::NotFound { .. }) => Ok(None),
            Err(e) => Err(e),
        }
    }

    async fn artifact_to_score(
        &self,
        policy: &str,
        checkpoint: Option<&str>,
        reference: Option<&str>,
    ) -> Result<Option<String>, StoreError> {
        match (reference, checkpoint) {
            (Some(r), _) => Ok(Some(self.resolve_artifact(r).await?.id)),
            (None, Some(c)) => self.review_artifact_for(policy, c).await,
            (None, None) => Ok(self.review_artifact(policy).await?.map(|a| a.artifact_id)),
        }
    }

    async fn episode_score(
        &self,
        episode_id: &str,
        artifact_id: Option<&str>,
    ) -> Result<EpisodeScore, StoreError> {
        let artifact = match artifact_id {
            Some(a) => a.to_string(),
            None => {
                let e = self.episode(episode_id, None).await?;
                self.review_artifact_for(&e.policy, &e.checkpoint).await?.ok_or_else(|| {
                    StoreError::not_found(
                        "review artifact",
                        format!(
                            "{}/{}/{DEFAULT_REVIEW_KIND}@{DEFAULT_REVIEW_ALIAS} (or a policy setting)",
                            e.policy, e.checkpoint
                        ),
                    )
                })?
            }
        };
        let row = sqlx::query(
            "SELECT episode_id, artifact_id, score, step_scores, job_id, created_at FROM episode_scores \
             WHERE artifact_id = $1 AND episode_id = $2",
        )
        .bind(&artifact)
        .bind(episode_id)
        .fetch_optional(&self.catalog().pool)
        .await?
        .ok_or_else(|| StoreError::not_found("episode score", format!("{episode_id} by {artifact}")))?;
        Ok(EpisodeScore {
            episode_id: row.s("episode_id")?,
            artifact_id: row.s("artifact_id")?,
            score: row.f("score")?,
            step_scores: serde_json::from_str(&row.s("step_scores")?)?,
            job_id: row.os("job_id")?,
            created_at: row.s("created_at")?,
        })
    }

    async fn review_queue(
        &self,
        filter: &EpisodeFilter,
        order: ReviewOrder,
        cursor: Option<&str>,
        limit: i64,
    ) -> Result<Vec<ReviewEntry>, StoreError> {
        if filter.id.is_some() || filter.after.is_some() {
            return Err(StoreError::invalid(
                "a review order pages with its own cursor (no id or after filter)",
            ));
        }
        let Some((sql, args)) = review_queue_sql(self, filter, order, cursor, limit).await? else {
            return Ok(Vec::new());
        };
        let mut q = sqlx::query(&sql);
        for a in args {
            q = bind_val(q, a);
        }
        let rows = q.fetch_all(&self.catalog().pool).await?;
        rows.iter().map(|r| review_entry_from_row(r, order)).collect()
    }
}

/// The statement [`ReviewQueue::review_queue`] runs and the values it binds; none when `cursor` is
/// not a position of `order` (the page past its end is empty).
async fn review_queue_sql(
    store: &Store,
    filter: &EpisodeFilter,
    order: ReviewOrder,
    cursor: Option<&str>,
    limit: i64,
) -> Result<Option<(String, Vec<Val>)>, StoreError> {
    let mut args: Vec<Val> = Vec::new();
    let (lab, labels_from) = review_labels_from(store, filter.version, &mut args).await?;
    let key = order.key_sql(lab);
    let mut sql = format!(
        "{EPISODE_SELECT}e.review_score AS review_score, COALESCE(ra.artifact_id, aa.artifact_id) AS review_artifact, {}",
        labels_from.replace("{key}", &format!("{key} AS review_key"))
    );
    let mut conds = label_conds(filter, lab, &mut args);
    conds.extend(episode_conds(filter, &mut args)?);
    if let Some(c) = cursor {
        let Some(after) = cursor_cond(order, &key, c, &mut args) else { return Ok(None) };
        conds.push(after);
    }
    for c in conds {
        sql.push_str(" AND ");
        sql.push_str(&c);
    }
    sql.push_str(&format!(" ORDER BY review_key, e.id LIMIT {}", push_arg(&mut args, Val::I(limit.max(0)))));
    Ok(Some((sql, args)))
}

/// The alias of the table holding the label columns, and the queue's label columns, `{key}`
/// placeholder and FROM clause up to an open WHERE: the episodes now, or as `version` froze
/// them (which must exist; its number is bound into `args`).
async fn review_labels_from(
    store: &Store,
    version: Option<i64>,
    args: &mut Vec<Val>,
) -> Result<(&'static str, String), StoreError> {
    Ok(match version {
        None => (
            "e",
            format!(
                "e.label AS label, e.label_source AS label_source, e.label_revision AS label_revision, \
                 e.label_actor AS label_actor, e.label_updated_at AS label_updated_at, {{key}} \
                 FROM episodes e {REVIEW_JOINS} WHERE e.version_removed IS NULL"
            ),
        ),
        Some(v) => {
            store.version(v).await?;
            let p = push_arg(args, Val::I(v));
            (
                "l",
                format!(
                    "l.label AS label, l.label_source AS label_source, l.revision AS label_revision, \
                     ev.actor AS label_actor, ev.created_at AS label_updated_at, {{key}} FROM episodes e \
                     JOIN version_labels l ON l.episode_id = e.id AND {} \
                     JOIN label_events ev ON ev.episode_id = e.id AND ev.revision = l.revision \
                     {REVIEW_JOINS} WHERE 1 = 1",
                    covers("l", &p)
                ),
            )
        }
    })
}

/// The keyset condition for the page after `cursor` (`key|episode id`) in `order`, whose sort
/// key is the SQL `key`; none when its key is not a number a numeric order can hold.
fn cursor_cond(order: ReviewOrder, key: &str, cursor: &str, args: &mut Vec<Val>) -> Option<String> {
    let (k, id) = cursor.rsplit_once('|').unwrap_or((cursor, ""));
    let kv = if order.numeric() {
        match k.parse::<f64>() {
            Ok(x) if x.is_finite() => Val::F(x),
            _ => return None,
        }
    } else {
        Val::S(k.to_string())
    };
    // A row value: both catalogs walk an index on (…, key, id) from it.
    let (pk, pid) = (push_arg(args, kv), push_arg(args, Val::S(id.into())));
    Some(format!("({key}, e.id) > ({pk}, {pid})"))
}

/// One queue entry from a row of [`ReviewQueue::review_queue`]'s statement.
fn review_entry_from_row(r: &sqlx::any::AnyRow, order: ReviewOrder) -> Result<ReviewEntry, StoreError> {
    use sqlx::Row;
    let episode = episode_from_row(r)?;
    let key = if order.numeric() { r.f("review_key")?.to_string() } else { r.s("review_key")? };
    Ok(ReviewEntry {
        cursor: format!("{key}|{}", episode.id),
        artifact_id: r.os("review_artifact")?,
        score: r.try_get::<Option<f64>, _>("review_score")?,
        episode,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use store::StoreConfig;

    /// A policy's page of either order, first or after a cursor, walks the order's index of
    /// migration 0014: SQLite's plan names it and sorts nothing.
    #[tokio::test]
    async fn a_policys_page_walks_its_orders_index() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let filter = EpisodeFilter { policy: Some("p".into()), ..Default::default() };
        for (order, index) in [
            (ReviewOrder::Uncertain, "episodes_review_uncertain"),
            (ReviewOrder::Disagreement, "episodes_review_disagreement"),
        ] {
            for cursor in [None, Some("0.25|e-1")] {
                let (sql, args) =
                    review_queue_sql(&store, &filter, order, cursor, 50).await.unwrap().unwrap();
                let explain = format!("EXPLAIN QUERY PLAN {sql}");
                let mut q = sqlx::query(&explain);
                for a in args {
                    q = bind_val(q, a);
                }
                let plan: Vec<String> = q
                    .fetch_all(&store.catalog().pool)
                    .await
                    .unwrap()
                    .iter()
                    .map(|r| r.s("detail").unwrap())
                    .collect();
                assert!(plan.iter().any(|d| d.contains(index)), "{order:?} {cursor:?}: {plan:?}");
                assert!(!plan.iter().any(|d| d.contains("TEMP B-TREE")), "{order:?} {cursor:?}: {plan:?}");
            }
        }
    }
}
