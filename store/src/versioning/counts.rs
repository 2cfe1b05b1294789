//! Episode counts per label state for the labeling page's progress bar, at any catalog size.
//!
//! Counting rows at read time is O(episodes) (about 200 ms on SQLite and 300 ms on Postgres at a
//! million, store/README.md), so the counts are maintained instead: `episode_counts` holds one
//! row per (policy, checkpoint, task, label, shard) of the visible episodes, and every write that
//! changes a label or visibility (label writes, ingests, deletions) adds its deltas in its own
//! transaction, just before it commits. A read sums a few rows. Each version also freezes its
//! counts (`version_counts`): spans of versions per group, moved on by the groups it changes
//! (`version.rs`).

use crate::catalog::{bind_val, RowExt, Tx, Val};
use crate::spans::covers;
use crate::{Backend, Label, Store, StoreError};
use serde::Serialize;
use std::collections::BTreeMap;

/// Episodes per label state, and their total.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq, Eq)]
pub struct LabelCounts {
    pub total: i64,
    pub success: i64,
    pub failure: i64,
    pub unknown: i64,
}

impl LabelCounts {
    fn add(&mut self, label: Label, n: i64) {
        match label {
            Label::Success => self.success += n,
            Label::Failure => self.failure += n,
            Label::Unknown => self.unknown += n,
        }
        self.total += n;
    }
}

/// Which episodes to count: now (`version: None`, the latest labels) or as frozen in a version.
#[derive(Debug, Clone, Default)]
pub struct CountFilter {
    pub version: Option<i64>,
    pub policy: Option<String>,
    pub checkpoint: Option<String>,
    pub task: Option<String>,
}

/// Counter rows per key on Postgres: a transaction adds its deltas to one shard picked at random,
/// so concurrent label writers of one checkpoint seldom wait on each other's row locks. SQLite has
/// one writer at a time, so one row per key is enough there.
const POSTGRES_SHARDS: u64 = 16;

/// `task` as stored in the count tables: '' for none (task names are never empty).
fn task_key(task: Option<&str>) -> String {
    task.unwrap_or("").to_string()
}

/// Count changes gathered by one write transaction, applied once, last, by [`CountDeltas::apply`].
#[derive(Debug, Default)]
pub(crate) struct CountDeltas {
    by_key: BTreeMap<(String, String, String, &'static str), i64>,
}

impl CountDeltas {
    pub(crate) fn add(&mut self, policy: &str, checkpoint: &str, task: Option<&str>, label: Label, n: i64) {
        *self
            .by_key
            .entry((policy.to_string(), checkpoint.to_string(), task_key(task), label.as_str()))
            .or_default() += n;
    }

    /// One episode moved from `old` to `new`.
    pub(crate) fn relabel(
        &mut self,
        policy: &str,
        checkpoint: &str,
        task: Option<&str>,
        old: Label,
        new: Label,
    ) {
        if old != new {
            self.add(policy, checkpoint, task, old, -1);
            self.add(policy, checkpoint, task, new, 1);
        }
    }

    /// Adds the deltas to `episode_counts` in one statement. Rows are written in key order, so two
    /// transactions lock counter rows in the same order and never deadlock on them; call it last
    /// before the commit, since on Postgres the rows stay locked until then.
    pub(crate) async fn apply(self, tx: &mut Tx, backend: Backend) -> Result<(), StoreError> {
        let rows: Vec<_> = self.by_key.into_iter().filter(|(_, n)| *n != 0).collect();
        if rows.is_empty() {
            return Ok(());
        }
        let shard = match backend {
            Backend::Sqlite => 0,
            Backend::Postgres => (uuid::Uuid::new_v4().as_u128() as u64 % POSTGRES_SHARDS) as i64,
        };
        // A few keys per transaction: far below the bound-parameter limits.
        let mut sql =
            String::from("INSERT INTO episode_counts (policy, checkpoint, task, label, shard, n) VALUES ");
        let mut args: Vec<Val> = Vec::with_capacity(rows.len() * 6);
        for (i, ((policy, checkpoint, task, label), n)) in rows.into_iter().enumerate() {
            if i > 0 {
                sql.push_str(", ");
            }
            let b = args.len();
            sql.push_str(&format!(
                "(${}, ${}, ${}, ${}, ${}, ${})",
                b + 1,
                b + 2,
                b + 3,
                b + 4,
                b + 5,
                b + 6
            ));
            args.extend([
                Val::S(policy),
                Val::S(checkpoint),
                Val::S(task),
                Val::S(label.into()),
                Val::I(shard),
                Val::I(n),
            ]);
        }
        sql.push_str(
            " ON CONFLICT (policy, checkpoint, task, label, shard) DO UPDATE SET n = episode_counts.n + excluded.n",
        );
        let mut q = sqlx::query(&sql);
        for a in args {
            q = bind_val(q, a);
        }
        q.execute(&mut **tx).await?;
        Ok(())
    }
}

/// `WHERE` terms for the filter's policy/checkpoint/task on columns prefixed by `p`.
fn filter_terms(f: &CountFilter, p: &str, args: &mut Vec<Val>, conds: &mut Vec<String>) {
    for (col, v) in [("policy", &f.policy), ("checkpoint", &f.checkpoint), ("task", &f.task)] {
        if let Some(v) = v {
            args.push(Val::S(v.clone()));
            conds.push(format!("{p}{col} = ${}", args.len()));
        }
    }
}

async fn counts_query(store: &Store, sql: &str, args: Vec<Val>) -> Result<LabelCounts, StoreError> {
    let mut q = sqlx::query(sql);
    for a in args {
        q = bind_val(q, a);
    }
    let mut out = LabelCounts::default();
    for r in q.fetch_all(&store.catalog().pool).await? {
        out.add(r.s("label")?.parse()?, r.i("n")?);
    }
    Ok(out)
}

impl Store {
    /// Episodes per label state, now or as frozen in a version: a sum over the maintained count
    /// rows, a few dozen rows whatever the catalog's size.
    pub async fn episode_counts(&self, f: &CountFilter) -> Result<LabelCounts, StoreError> {
        let mut args = Vec::new();
        let mut conds = Vec::new();
        let table = match f.version {
            None => "episode_counts",
            Some(v) => {
                self.version(v).await?;
                args.push(Val::I(v));
                conds.push(covers("", "$1"));
                "version_counts"
            }
        };
        filter_terms(f, "", &mut args, &mut conds);
        let wh = if conds.is_empty() { String::new() } else { format!(" WHERE {}", conds.join(" AND ")) };
        // SUM of BIGINT is NUMERIC on Postgres: cast back.
        let sql = format!("SELECT label, CAST(SUM(n) AS BIGINT) AS n FROM {table}{wh} GROUP BY label");
        counts_query(self, &sql, args).await
    }

    /// The same counts computed from the episode rows: O(episodes). The reference the maintained
    /// counts are checked against (tests, `catalog_scale` bench).
    pub async fn recount_episodes(&self, f: &CountFilter) -> Result<LabelCounts, StoreError> {
        let mut args = Vec::new();
        let mut conds = Vec::new();
        let sql_head = match f.version {
            None => {
                conds.push("e.version_removed IS NULL".to_string());
                "SELECT e.label AS label, COUNT(*) AS n FROM episodes e"
            }
            Some(v) => {
                self.version(v).await?;
                args.push(Val::I(v));
                conds.push(covers("l", "$1"));
                "SELECT l.label AS label, COUNT(*) AS n FROM version_labels l JOIN episodes e ON e.id = l.episode_id"
            }
        };
        filter_terms(f, "e.", &mut args, &mut conds);
        let group = if f.version.is_some() { "l.label" } else { "e.label" };
        let sql = format!("{sql_head} WHERE {} GROUP BY {group}", conds.join(" AND "));
        counts_query(self, &sql, args).await
    }

    /// Recomputes the maintained counts from the episode rows (after rows were loaded with plain
    /// SQL, say). Concurrent label writes stay correct: on Postgres the table lock makes a writer
    /// that has already added its deltas finish first (the recount then sees its label), and one
    /// that has not yet wait until the recount committed (its deltas then apply on top of it).
    pub async fn rebuild_episode_counts(&self) -> Result<(), StoreError> {
        let mut tx = self.catalog().begin_version_write().await?;
        if self.backend() == Backend::Postgres {
            sqlx::query("LOCK TABLE episode_counts IN EXCLUSIVE MODE").execute(&mut *tx).await?;
        }
        sqlx::query("DELETE FROM episode_counts").execute(&mut *tx).await?;
        sqlx::query(
            "INSERT INTO episode_counts (policy, checkpoint, task, label, shard, n) \
             SELECT policy, checkpoint, COALESCE(task, ''), label, 0, COUNT(*) FROM episodes \
             WHERE version_removed IS NULL GROUP BY policy, checkpoint, COALESCE(task, ''), label",
        )
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }
}
