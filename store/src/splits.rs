//! Splits: a frozen train/val division, by episode with a seeded hash, of the labeled episodes
//! of one checkpoint (on-policy) or of other checkpoints (off-policy), pinned to a version.
//!
//! An episode a human took over (its `intervention` steps) is the checkpoint's own behaviour only
//! up to the takeover: the trainer builds samples from the steps before its first takeover, and
//! a split reports per checkpoint how many steps that keeps ([`SplitCheckpointSteps`]).

use crate::catalog::{insert_rows, RowExt, Val};
use crate::{now_rfc3339, EpisodeFilter, EpisodeRecord, Label, Store, StoreError};
use serde::Serialize;

#[derive(Debug, Clone)]
pub struct SplitRequest {
    pub policy: String,
    pub checkpoint: String,
    /// Pin to this version; `None`: the head, after freezing any unsnapshotted label changes.
    pub version: Option<i64>,
    /// Off-policy: take the episodes of these `(policy, checkpoint)`s instead.
    pub off_policy_from: Vec<(String, String)>,
    pub val_fraction: f64,
    pub seed: u64,
    pub actor: String,
    /// Keep at most this many labeled episodes, a seeded sample (nested: with the same seed, the
    /// sample of 100 is inside the sample of 250), e.g. for a verifier's learning curve.
    pub max_episodes: Option<u64>,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct SplitRecord {
    pub id: String,
    pub policy: String,
    pub checkpoint: String,
    /// `on_policy` or `off_policy`
    pub mode: String,
    /// `[policy, checkpoint]` pairs.
    #[cfg_attr(feature = "openapi", schema(value_type = Vec<Vec<String>>))]
    pub source_checkpoints: Vec<(String, String)>,
    pub version: i64,
    pub val_fraction: f64,
    pub seed: i64,
    pub train_episodes: i64,
    pub val_episodes: i64,
    pub created_by: String,
    pub created_at: String,
    /// Per source checkpoint, the share of its episodes' steps that are the policy's own (before
    /// a human took over): what training uses.
    pub checkpoint_steps: Vec<SplitCheckpointSteps>,
}

/// The steps one checkpoint contributes to a split.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct SplitCheckpointSteps {
    pub policy: String,
    pub checkpoint: String,
    pub episodes: i64,
    /// Episodes in which a human took over.
    pub episodes_taken_over: i64,
    /// Steps of its episodes.
    pub steps: i64,
    /// Steps before each episode's first takeover (all of an episode without one): the steps
    /// the trainer builds samples from.
    pub on_policy_steps: i64,
    /// `on_policy_steps / steps`.
    pub on_policy_fraction: f64,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct SplitEpisode {
    pub episode_id: String,
    /// `train` or `val`
    pub part: String,
    pub label: Label,
}

/// Deterministic position of an episode in [0, 1) for a seed.
fn split_key(seed: u64, episode_id: &str) -> f64 {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    h.update(seed.to_le_bytes());
    h.update(episode_id.as_bytes());
    let d = h.finalize();
    let x = u64::from_le_bytes(d[..8].try_into().expect("8 bytes"));
    (x >> 11) as f64 / (1u64 << 53) as f64
}

const SPLIT_COLS: &str = "id, policy, checkpoint, mode, source_checkpoints, version, val_fraction, seed, \
    train_episodes, val_episodes, created_by, created_at";

fn split_from_row(r: &sqlx::any::AnyRow) -> Result<SplitRecord, StoreError> {
    Ok(SplitRecord {
        id: r.s("id")?,
        policy: r.s("policy")?,
        checkpoint: r.s("checkpoint")?,
        mode: r.s("mode")?,
        source_checkpoints: serde_json::from_str(&r.s("source_checkpoints")?)?,
        version: r.i("version")?,
        val_fraction: r.f("val_fraction")?,
        seed: r.i("seed")?,
        train_episodes: r.i("train_episodes")?,
        val_episodes: r.i("val_episodes")?,
        created_by: r.s("created_by")?,
        created_at: r.s("created_at")?,
        checkpoint_steps: Vec::new(),
    })
}

/// The largest validation fraction of a split.
pub const MAX_VAL_FRACTION: f64 = 0.99;

/// The mode of a split and its source checkpoints: the requested one (on-policy), or the
/// `off_policy_from` list.
fn split_sources(req: &SplitRequest) -> (&'static str, Vec<(String, String)>) {
    if req.off_policy_from.is_empty() {
        ("on_policy", vec![(req.policy.clone(), req.checkpoint.clone())])
    } else {
        ("off_policy", req.off_policy_from.clone())
    }
}

/// Keeps a seeded sample of at most `cap` members (nested across caps for one seed).
fn sample_members(members: &mut Vec<EpisodeRecord>, cap: u64, seed: u64) -> Result<(), StoreError> {
    if cap == 0 {
        return Err(StoreError::invalid("max episodes must be at least 1"));
    }
    // A key independent of the train/val key, so the sample keeps the val fraction.
    let sample_seed = seed ^ 0x9e37_79b9_7f4a_7c15;
    members.sort_by(|a, b| split_key(sample_seed, &a.id).total_cmp(&split_key(sample_seed, &b.id)));
    members.truncate(usize::try_from(cap).unwrap_or(usize::MAX));
    Ok(())
}

/// Each member's part (`val` below the val fraction on the seeded key, else `train`), in
/// episode id order.
fn assign_parts(members: &[EpisodeRecord], seed: u64, val_fraction: f64) -> Vec<SplitEpisode> {
    let mut parts: Vec<SplitEpisode> = members
        .iter()
        .map(|e| SplitEpisode {
            episode_id: e.id.clone(),
            part: if split_key(seed, &e.id) < val_fraction { "val" } else { "train" }.into(),
            label: e.label,
        })
        .collect();
    parts.sort_by(|a, b| a.episode_id.cmp(&b.episode_id));
    parts
}

impl Store {
    pub async fn create_split(&self, req: &SplitRequest) -> Result<SplitRecord, StoreError> {
        // At most 0.99: a closed range a JSON client states exactly (near 1 nothing would train).
        if !(0.0..=MAX_VAL_FRACTION).contains(&req.val_fraction) {
            return Err(StoreError::invalid(format!(
                "val fraction {} must be in [0, {MAX_VAL_FRACTION}]",
                req.val_fraction
            )));
        }
        let version = self.split_version(req).await?;
        let (mode, sources) = split_sources(req);
        let mut members = self.split_members(&sources, version).await?;
        if let Some(cap) = req.max_episodes {
            sample_members(&mut members, cap, req.seed)?;
        }
        if members.is_empty() {
            // The store's state (nothing labeled yet), not the request, is what is missing: 409.
            return Err(StoreError::Conflict(format!(
                "no labeled episodes of {} in version {version}",
                sources.iter().map(|(p, c)| format!("{p}/{c}")).collect::<Vec<_>>().join(", ")
            )));
        }
        let parts = assign_parts(&members, req.seed, req.val_fraction);
        let n_val = parts.iter().filter(|p| p.part == "val").count() as i64;
        let rec = SplitRecord {
            id: format!("split-{}", &uuid::Uuid::new_v4().simple().to_string()[..12]),
            policy: req.policy.clone(),
            checkpoint: req.checkpoint.clone(),
            mode: mode.into(),
            source_checkpoints: sources,
            version,
            val_fraction: req.val_fraction,
            seed: req.seed as i64,
            train_episodes: parts.len() as i64 - n_val,
            val_episodes: n_val,
            created_by: req.actor.clone(),
            created_at: now_rfc3339(),
            checkpoint_steps: Vec::new(),
        };
        self.insert_split(&rec, &parts).await?;
        let checkpoint_steps = self.split_checkpoint_steps(&rec.id).await?;
        Ok(SplitRecord { checkpoint_steps, ..rec })
    }

    /// The version a split pins: the requested one (which must exist), else the head after
    /// freezing any unsnapshotted label changes; never version 0 (the empty store).
    async fn split_version(&self, req: &SplitRequest) -> Result<i64, StoreError> {
        let version = match req.version {
            Some(v) => {
                self.version(v).await?;
                v
            }
            None => {
                if self.labels_changed_since_head().await? {
                    self.snapshot_labels(&req.actor, "label snapshot for a split").await?.version
                } else {
                    self.head_version().await?
                }
            }
        };
        if version == 0 {
            // Version 0 is the empty store before its first write: nothing to split yet.
            return Err(StoreError::Conflict(format!(
                "the store is empty (no version yet), so {}/{} has no episodes to split: ingest its rollouts first \
                 (`ufops ingest PATH --policy {} --checkpoint {}`)",
                req.policy, req.checkpoint, req.policy, req.checkpoint
            )));
        }
        Ok(version)
    }

    /// The labeled episodes of `sources` in `version` that their policy ran on its own (no
    /// steered run's).
    async fn split_members(
        &self,
        sources: &[(String, String)],
        version: i64,
    ) -> Result<Vec<EpisodeRecord>, StoreError> {
        // Only what the checkpoint's policy did on its own: episodes of steered runs (best-of-N,
        // guidance) are evaluations of the policy plus a verifier, not its on-policy rollouts.
        let steered: std::collections::HashSet<String> =
            sqlx::query("SELECT id FROM runs WHERE steering <> 'base'")
                .fetch_all(&self.catalog().pool)
                .await?
                .iter()
                .map(|r| r.s("id"))
                .collect::<Result<_, _>>()?;
        let mut members = Vec::new();
        for (p, c) in sources {
            let eps = self
                .episodes(&EpisodeFilter {
                    version: Some(version),
                    policy: Some(p.clone()),
                    checkpoint: Some(c.clone()),
                    ..Default::default()
                })
                .await?;
            members.extend(eps.into_iter().filter(|e| {
                e.label != Label::Unknown && !e.run_id.as_ref().is_some_and(|r| steered.contains(r))
            }));
        }
        Ok(members)
    }

    /// Writes a split's row and its episodes' parts in one transaction.
    async fn insert_split(&self, rec: &SplitRecord, parts: &[SplitEpisode]) -> Result<(), StoreError> {
        let mut tx = self.catalog().begin_write().await?;
        sqlx::query(&format!(
            "INSERT INTO splits ({SPLIT_COLS}) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12)"
        ))
        .bind(&rec.id)
        .bind(&rec.policy)
        .bind(&rec.checkpoint)
        .bind(&rec.mode)
        .bind(serde_json::to_string(&rec.source_checkpoints)?)
        .bind(rec.version)
        .bind(rec.val_fraction)
        .bind(rec.seed)
        .bind(rec.train_episodes)
        .bind(rec.val_episodes)
        .bind(&rec.created_by)
        .bind(&rec.created_at)
        .execute(&mut *tx)
        .await?;
        insert_rows(
            &mut tx,
            "split_episodes",
            &["split_id", "episode_id", "part", "label"],
            parts
                .iter()
                .map(|p| {
                    vec![
                        Val::S(rec.id.clone()),
                        p.episode_id.as_str().into(),
                        p.part.as_str().into(),
                        p.label.as_str().into(),
                    ]
                })
                .collect(),
            "",
        )
        .await?;
        let event = crate::events::NewEvent::new(
            crate::events::EventKind::SplitFrozen,
            rec.id.clone(),
            serde_json::json!({
                "version": rec.version,
                "mode": rec.mode,
                "source_checkpoints": rec.source_checkpoints,
                "train_episodes": rec.train_episodes,
                "val_episodes": rec.val_episodes,
                "actor": rec.created_by,
            }),
        )
        .of(&rec.policy, Some(&rec.checkpoint));
        self.commit_with_events(tx, &[event]).await?;
        Ok(())
    }

    pub async fn split(&self, id: &str) -> Result<SplitRecord, StoreError> {
        let row = sqlx::query(&format!("SELECT {SPLIT_COLS} FROM splits WHERE id = $1"))
            .bind(id)
            .fetch_optional(&self.catalog().pool)
            .await?
            .ok_or_else(|| StoreError::not_found("split", id))?;
        let rec = split_from_row(&row)?;
        let checkpoint_steps = self.split_checkpoint_steps(id).await?;
        Ok(SplitRecord { checkpoint_steps, ..rec })
    }

    pub async fn splits(&self) -> Result<Vec<SplitRecord>, StoreError> {
        let rows = sqlx::query(&format!("SELECT {SPLIT_COLS} FROM splits ORDER BY created_at"))
            .fetch_all(&self.catalog().pool)
            .await?;
        let mut out = Vec::with_capacity(rows.len());
        for r in &rows {
            let rec = split_from_row(r)?;
            let checkpoint_steps = self.split_checkpoint_steps(&rec.id).await?;
            out.push(SplitRecord { checkpoint_steps, ..rec });
        }
        Ok(out)
    }

    /// Per checkpoint of a split's episodes: its steps and those before a human took over
    /// (computed from the episodes' catalog rows, which never change once written).
    async fn split_checkpoint_steps(&self, id: &str) -> Result<Vec<SplitCheckpointSteps>, StoreError> {
        // CAST: Postgres sums BIGINT into NUMERIC.
        let rows = sqlx::query(
            "SELECT e.policy, e.checkpoint, COUNT(*) AS episodes, \
             CAST(SUM(CASE WHEN e.first_intervention IS NULL THEN 0 ELSE 1 END) AS BIGINT) AS taken_over, \
             CAST(SUM(e.length) AS BIGINT) AS steps, \
             CAST(SUM(COALESCE(e.first_intervention, e.length)) AS BIGINT) AS on_policy_steps \
             FROM split_episodes s JOIN episodes e ON e.id = s.episode_id WHERE s.split_id = $1 \
             GROUP BY e.policy, e.checkpoint ORDER BY e.policy, e.checkpoint",
        )
        .bind(id)
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter()
            .map(|r| {
                let (steps, on_policy_steps) = (r.i("steps")?, r.i("on_policy_steps")?);
                Ok(SplitCheckpointSteps {
                    policy: r.s("policy")?,
                    checkpoint: r.s("checkpoint")?,
                    episodes: r.i("episodes")?,
                    episodes_taken_over: r.i("taken_over")?,
                    steps,
                    on_policy_steps,
                    on_policy_fraction: if steps > 0 { on_policy_steps as f64 / steps as f64 } else { 1.0 },
                })
            })
            .collect()
    }

    pub async fn split_episodes(&self, id: &str) -> Result<Vec<SplitEpisode>, StoreError> {
        self.split(id).await?;
        let rows = sqlx::query(
            "SELECT episode_id, part, label FROM split_episodes WHERE split_id = $1 ORDER BY episode_id",
        )
        .bind(id)
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(SplitEpisode {
                    episode_id: r.s("episode_id")?,
                    part: r.s("part")?,
                    label: r.s("label")?.parse()?,
                })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn split_key_is_uniform_and_seeded() {
        let xs: Vec<f64> = (0..10_000).map(|i| super::split_key(7, &format!("ep-{i}"))).collect();
        let below = xs.iter().filter(|x| **x < 0.2).count();
        assert!((1800..2200).contains(&below), "{below}");
        assert_ne!(super::split_key(7, "a"), super::split_key(8, "a"));
        assert_eq!(super::split_key(7, "a"), super::split_key(7, "a"));
    }
}
