//! The SQL catalog: one connection pool over SQLite or Postgres (sqlx's `Any` driver, so every
//! query is written once with `$n` placeholders), the embedded migrations, and write transactions.

use crate::StoreError;
use sqlx::any::{AnyPoolOptions, AnyRow};
use sqlx::migrate::{Migration, MigrationType, Migrator};
use sqlx::{Any, AnyPool, Transaction};
use std::borrow::Cow;
use std::time::Duration;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    Sqlite,
    Postgres,
}

pub type Tx = Transaction<'static, Any>;

pub struct Catalog {
    pub pool: AnyPool,
    pub backend: Backend,
    url_for_display: String,
}

/// The migrations, embedded so the binary needs no files at run time. Both histories carry the
/// same versions and names (a test checks it).
const SQLITE_MIGRATIONS: &[(i64, &str, &str)] = &[
    (1, "store", include_str!("../../migrations/sqlite/0001_store.sql")),
    (2, "splits_artifacts_jobs", include_str!("../../migrations/sqlite/0002_splits_artifacts_jobs.sql")),
    (3, "episode_row_ranges", include_str!("../../migrations/sqlite/0003_episode_row_ranges.sql")),
    (
        4,
        "catalog_indexes_and_counts",
        include_str!("../../migrations/sqlite/0004_catalog_indexes_and_counts.sql"),
    ),
    (5, "episode_media", include_str!("../../migrations/sqlite/0005_episode_media.sql")),
    (6, "runs", include_str!("../../migrations/sqlite/0006_runs.sql")),
    (7, "pending_objects", include_str!("../../migrations/sqlite/0007_pending_objects.sql")),
    (8, "review_scores", include_str!("../../migrations/sqlite/0008_review_scores.sql")),
    (9, "label_campaigns", include_str!("../../migrations/sqlite/0009_label_campaigns.sql")),
    (10, "layers", include_str!("../../migrations/sqlite/0010_layers.sql")),
    (11, "episode_takeovers", include_str!("../../migrations/sqlite/0011_episode_takeovers.sql")),
    (12, "policy_aliases", include_str!("../../migrations/sqlite/0012_policy_aliases.sql")),
    (13, "episode_tags", include_str!("../../migrations/sqlite/0013_episode_tags.sql")),
    (14, "review_score_index", include_str!("../../migrations/sqlite/0014_review_score_index.sql")),
    (15, "monitors", include_str!("../../migrations/sqlite/0015_monitors.sql")),
    (16, "events", include_str!("../../migrations/sqlite/0016_events.sql")),
    (17, "webhooks", include_str!("../../migrations/sqlite/0017_webhooks.sql")),
    (18, "automations", include_str!("../../migrations/sqlite/0018_automations.sql")),
    (19, "version_spans", include_str!("../../migrations/sqlite/0019_version_spans.sql")),
];
const POSTGRES_MIGRATIONS: &[(i64, &str, &str)] = &[
    (1, "store", include_str!("../../migrations/postgres/0001_store.sql")),
    (2, "splits_artifacts_jobs", include_str!("../../migrations/postgres/0002_splits_artifacts_jobs.sql")),
    (3, "episode_row_ranges", include_str!("../../migrations/postgres/0003_episode_row_ranges.sql")),
    (
        4,
        "catalog_indexes_and_counts",
        include_str!("../../migrations/postgres/0004_catalog_indexes_and_counts.sql"),
    ),
    (5, "episode_media", include_str!("../../migrations/postgres/0005_episode_media.sql")),
    (6, "runs", include_str!("../../migrations/postgres/0006_runs.sql")),
    (7, "pending_objects", include_str!("../../migrations/postgres/0007_pending_objects.sql")),
    (8, "review_scores", include_str!("../../migrations/postgres/0008_review_scores.sql")),
    (9, "label_campaigns", include_str!("../../migrations/postgres/0009_label_campaigns.sql")),
    (10, "layers", include_str!("../../migrations/postgres/0010_layers.sql")),
    (11, "episode_takeovers", include_str!("../../migrations/postgres/0011_episode_takeovers.sql")),
    (12, "policy_aliases", include_str!("../../migrations/postgres/0012_policy_aliases.sql")),
    (13, "episode_tags", include_str!("../../migrations/postgres/0013_episode_tags.sql")),
    (14, "review_score_index", include_str!("../../migrations/postgres/0014_review_score_index.sql")),
    (15, "monitors", include_str!("../../migrations/postgres/0015_monitors.sql")),
    (16, "events", include_str!("../../migrations/postgres/0016_events.sql")),
    (17, "webhooks", include_str!("../../migrations/postgres/0017_webhooks.sql")),
    (18, "automations", include_str!("../../migrations/postgres/0018_automations.sql")),
    (19, "version_spans", include_str!("../../migrations/postgres/0019_version_spans.sql")),
];

fn migrator(backend: Backend) -> Migrator {
    migrator_of(match backend {
        Backend::Sqlite => SQLITE_MIGRATIONS,
        Backend::Postgres => POSTGRES_MIGRATIONS,
    })
}

fn migrator_of(list: &[(i64, &'static str, &'static str)]) -> Migrator {
    let migrations: Vec<Migration> = list
        .iter()
        .map(|(v, name, sql)| {
            Migration::new(*v, Cow::Borrowed(*name), MigrationType::Simple, Cow::Borrowed(*sql), false)
        })
        .collect();
    Migrator { migrations: Cow::Owned(migrations), ignore_missing: false, locking: true, no_tx: false }
}

/// A migration's number and name.
pub type MigrationName = (i64, &'static str);

/// The names of the embedded migrations per backend (for the in-step check).
pub fn migration_names() -> (Vec<MigrationName>, Vec<MigrationName>) {
    (
        SQLITE_MIGRATIONS.iter().map(|(v, n, _)| (*v, *n)).collect(),
        POSTGRES_MIGRATIONS.iter().map(|(v, n, _)| (*v, *n)).collect(),
    )
}

impl Catalog {
    pub async fn connect(url: &str) -> Result<Catalog, StoreError> {
        sqlx::any::install_default_drivers();
        let (backend, url) = if url.starts_with("sqlite:") {
            let u = if url.contains('?') { url.to_string() } else { format!("{url}?mode=rwc") };
            (Backend::Sqlite, u)
        } else if url.starts_with("postgres:") || url.starts_with("postgresql:") {
            (Backend::Postgres, url.to_string())
        } else {
            return Err(StoreError::invalid(format!(
                "unsupported database URL {url:?}: use sqlite://PATH or postgres://USER@HOST/DB"
            )));
        };
        let mut opts = AnyPoolOptions::new().acquire_timeout(Duration::from_secs(30));
        opts = match backend {
            // One writer at a time anyway; WAL lets readers run beside it. synchronous = FULL
            // fsyncs the WAL at every commit, so an acknowledged write (a label) survives a power
            // cut, not only a crash of the process; the API's label writer groups commits to pay
            // for it once per batch.
            Backend::Sqlite => opts.max_connections(8).after_connect(|conn, _| {
                Box::pin(async move {
                    use sqlx::Executor;
                    conn.execute("PRAGMA journal_mode = WAL; PRAGMA synchronous = FULL; PRAGMA busy_timeout = 30000; PRAGMA foreign_keys = ON;").await?;
                    Ok(())
                })
            }),
            Backend::Postgres => opts.max_connections(16),
        };
        let pool = opts.connect(&url).await.map_err(|e| {
            StoreError::invalid(format!("cannot open catalog database {}: {e}", redact(&url)))
        })?;
        let catalog = Catalog { pool, backend, url_for_display: redact(&url) };
        catalog.migrate().await?;
        Ok(catalog)
    }

    async fn migrate(&self) -> Result<(), StoreError> {
        // Two processes opening a fresh SQLite file at once can race on the first migration; the
        // loser sees the tables already there and succeeds on a second look.
        let m = migrator(self.backend);
        let mut last = None;
        for attempt in 0..5 {
            match m.run(&self.pool).await {
                Ok(()) => return Ok(()),
                Err(e) => {
                    last = Some(e);
                    tokio::time::sleep(Duration::from_millis(50 * (attempt + 1))).await;
                }
            }
        }
        Err(last.expect("at least one attempt").into())
    }

    pub fn describe(&self) -> String {
        self.url_for_display.clone()
    }

    /// A transaction that creates a new version: it holds the store-wide version lock until it
    /// commits, so version numbers are dense and no concurrent write is lost.
    pub async fn begin_version_write(&self) -> Result<Tx, StoreError> {
        match self.backend {
            Backend::Sqlite => Ok(self.pool.begin_with("BEGIN IMMEDIATE").await?),
            Backend::Postgres => {
                let mut tx = self.pool.begin().await?;
                sqlx::query("SELECT version FROM store_head WHERE id = 1 FOR UPDATE")
                    .execute(&mut *tx)
                    .await?;
                Ok(tx)
            }
        }
    }

    /// A transaction for row-level writes (labels, jobs): SQLite takes its write lock up front
    /// (avoids upgrade deadlocks); Postgres relies on conditional updates.
    pub async fn begin_write(&self) -> Result<Tx, StoreError> {
        match self.backend {
            Backend::Sqlite => Ok(self.pool.begin_with("BEGIN IMMEDIATE").await?),
            Backend::Postgres => Ok(self.pool.begin().await?),
        }
    }
}

fn redact(url: &str) -> String {
    // postgres://user:secret@host → postgres://user:***@host
    if let Some(at) = url.find('@') {
        if let Some(scheme_end) = url.find("://") {
            let cred = &url[scheme_end + 3..at];
            if let Some(colon) = cred.find(':') {
                return format!("{}{}:***{}", &url[..scheme_end + 3], &cred[..colon], &url[at..]);
            }
        }
    }
    url.to_string()
}

/// Small helpers to read columns from `Any` rows with a useful error.
pub trait RowExt {
    fn s(&self, col: &str) -> Result<String, StoreError>;
    fn os(&self, col: &str) -> Result<Option<String>, StoreError>;
    fn i(&self, col: &str) -> Result<i64, StoreError>;
    fn oi(&self, col: &str) -> Result<Option<i64>, StoreError>;
    fn f(&self, col: &str) -> Result<f64, StoreError>;
}

impl RowExt for AnyRow {
    fn s(&self, col: &str) -> Result<String, StoreError> {
        use sqlx::Row;
        Ok(self.try_get::<String, _>(col)?)
    }
    fn os(&self, col: &str) -> Result<Option<String>, StoreError> {
        use sqlx::Row;
        Ok(self.try_get::<Option<String>, _>(col)?)
    }
    fn i(&self, col: &str) -> Result<i64, StoreError> {
        use sqlx::Row;
        Ok(self.try_get::<i64, _>(col)?)
    }
    fn oi(&self, col: &str) -> Result<Option<i64>, StoreError> {
        use sqlx::Row;
        Ok(self.try_get::<Option<i64>, _>(col)?)
    }
    fn f(&self, col: &str) -> Result<f64, StoreError> {
        use sqlx::Row;
        Ok(self.try_get::<f64, _>(col)?)
    }
}

/// A value bound into a dynamically built statement.
#[derive(Debug, Clone)]
pub enum Val {
    I(i64),
    S(String),
    OS(Option<String>),
    OI(Option<i64>),
    F(f64),
}

impl From<f64> for Val {
    fn from(v: f64) -> Self {
        Val::F(v)
    }
}

impl From<i64> for Val {
    fn from(v: i64) -> Self {
        Val::I(v)
    }
}
impl From<String> for Val {
    fn from(v: String) -> Self {
        Val::S(v)
    }
}
impl From<&str> for Val {
    fn from(v: &str) -> Self {
        Val::S(v.to_string())
    }
}
impl From<Option<String>> for Val {
    fn from(v: Option<String>) -> Self {
        Val::OS(v)
    }
}
impl From<Option<i64>> for Val {
    fn from(v: Option<i64>) -> Self {
        Val::OI(v)
    }
}

pub fn bind_val<'q>(
    q: sqlx::query::Query<'q, Any, sqlx::any::AnyArguments<'q>>,
    v: Val,
) -> sqlx::query::Query<'q, Any, sqlx::any::AnyArguments<'q>> {
    match v {
        Val::I(x) => q.bind(x),
        Val::S(x) => q.bind(x),
        Val::OS(x) => q.bind(x),
        Val::OI(x) => q.bind(x),
        Val::F(x) => q.bind(x),
    }
}

/// `$1, $2, …, $n`: the parameters of an `IN (…)` list of `n` values.
pub fn placeholders(n: usize) -> String {
    (1..=n).map(|i| format!("${i}")).collect::<Vec<_>>().join(", ")
}

/// Inserts many rows in batches of multi-row `INSERT`s (`suffix` may add `ON CONFLICT DO NOTHING`).
pub async fn insert_rows(
    tx: &mut Tx,
    table: &str,
    cols: &[&str],
    rows: Vec<Vec<Val>>,
    suffix: &str,
) -> Result<(), StoreError> {
    // Bound values per statement: SQLite allows 32,766, Postgres 65,535.
    let per_batch = (32_000 / cols.len().max(1)).max(1);
    // SQLite looks `$n` parameters up by name, a linear scan per parameter: quadratic in the
    // parameters of a statement (seconds for 1000 episodes). Anonymous `?` parameters are bound by
    // position.
    let positional = tx.backend_name().eq_ignore_ascii_case("sqlite");
    let mut rows = rows.into_iter().peekable();
    while rows.peek().is_some() {
        let batch: Vec<Vec<Val>> = rows.by_ref().take(per_batch).collect();
        let mut sql = format!("INSERT INTO {table} ({}) VALUES ", cols.join(", "));
        let mut n = 0;
        for (i, row) in batch.iter().enumerate() {
            debug_assert_eq!(row.len(), cols.len());
            if i > 0 {
                sql.push_str(", ");
            }
            sql.push('(');
            for j in 0..row.len() {
                if j > 0 {
                    sql.push_str(", ");
                }
                n += 1;
                if positional {
                    sql.push('?');
                } else {
                    sql.push_str(&format!("${n}"));
                }
            }
            sql.push(')');
        }
        sql.push(' ');
        sql.push_str(suffix);
        let mut q = sqlx::query(&sql);
        for row in batch {
            for v in row {
                q = bind_val(q, v);
            }
        }
        q.execute(&mut **tx).await?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use sqlx::Row;

    /// Every pooled SQLite connection syncs each commit to disk (synchronous = FULL, i.e. 2).
    #[tokio::test]
    async fn sqlite_commits_are_durable() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}/catalog.sqlite?mode=rwc", dir.path().display());
        let cat = Catalog::connect(&url).await.unwrap();
        for _ in 0..3 {
            let r = sqlx::query("PRAGMA synchronous").fetch_one(&cat.pool).await.unwrap();
            assert_eq!(r.try_get::<i64, _>(0).unwrap(), 2, "synchronous = FULL");
        }
    }

    /// A catalog written before migration 0003 (one row group per episode) gets exact row ranges.
    #[tokio::test]
    async fn migration_0003_backfills_row_ranges() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}/catalog.sqlite?mode=rwc", dir.path().display());
        sqlx::any::install_default_drivers();
        let pool = AnyPoolOptions::new().max_connections(1).connect(&url).await.unwrap();
        migrator_of(&SQLITE_MIGRATIONS[..2]).run(&pool).await.unwrap();
        // one connection: the episode row below stands alone, without its source and file rows
        sqlx::query("PRAGMA foreign_keys = OFF").execute(&pool).await.unwrap();
        sqlx::query(
            "INSERT INTO episodes (id, policy, checkpoint, task, source_sha256, source_name, source_index, length, \
             tags, metadata, data_file, row_group, version_added, label, label_source, label_revision, label_actor, \
             label_updated_at, created_at) VALUES ('e-00000', 'p', 'c', NULL, 'x', 'demo_0', 0, 7, '[]', '{}', \
             'steps/a.parquet', 3, 1, 'unknown', '', 1, 'ingest', 'now', 'now')",
        )
        .execute(&pool)
        .await
        .unwrap();
        pool.close().await;
        let cat = Catalog::connect(&url).await.unwrap();
        let r = sqlx::query("SELECT row_group, row_offset, row_count FROM episodes")
            .fetch_one(&cat.pool)
            .await
            .unwrap();
        assert_eq!(r.try_get::<i64, _>("row_group").unwrap(), 3);
        assert_eq!(r.try_get::<i64, _>("row_offset").unwrap(), 0);
        assert_eq!(r.try_get::<i64, _>("row_count").unwrap(), 7);
    }

    /// Migration 0004 fills the maintained counts from the rows already there: the visible
    /// episodes now (a removed one and a task-less one included), and each version's frozen labels.
    #[tokio::test]
    async fn migration_0004_backfills_counts() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}/catalog.sqlite?mode=rwc", dir.path().display());
        sqlx::any::install_default_drivers();
        let pool = AnyPoolOptions::new().max_connections(1).connect(&url).await.unwrap();
        migrator_of(&SQLITE_MIGRATIONS[..3]).run(&pool).await.unwrap();
        sqlx::query("PRAGMA foreign_keys = OFF").execute(&pool).await.unwrap();
        // (id, task, label now, removed in, label frozen in version 1)
        let rows = [
            ("e-1", Some("reach"), "success", None, "unknown"),
            ("e-2", Some("reach"), "unknown", None, "unknown"),
            ("e-3", None, "failure", None, "failure"),
            ("e-4", Some("reach"), "success", Some(2), "success"),
        ];
        for (id, task, label, removed, frozen) in rows {
            sqlx::query(
                "INSERT INTO episodes (id, policy, checkpoint, task, source_sha256, source_name, source_index, length, \
                 tags, metadata, data_file, row_group, row_offset, row_count, version_added, version_removed, label, \
                 label_source, label_revision, label_actor, label_updated_at, created_at) VALUES ($1, 'p', 'c', $2, 'x', \
                 'demo', 0, 1, '[]', '{}', 'steps/a.parquet', 0, 0, 1, 1, $3, $4, 'test', 1, 'ingest', 'now', 'now')",
            )
            .bind(id)
            .bind(task)
            .bind(removed)
            .bind(label)
            .execute(&pool)
            .await
            .unwrap();
            sqlx::query("INSERT INTO version_labels (version, episode_id, label, label_source, revision) VALUES (1, $1, $2, 'test', 1)")
                .bind(id)
                .bind(frozen)
                .execute(&pool)
                .await
                .unwrap();
        }
        pool.close().await;
        let cat = Catalog::connect(&url).await.unwrap();
        let read = |sql: &'static str| {
            let pool = cat.pool.clone();
            async move {
                let rows = sqlx::query(sql).fetch_all(&pool).await.unwrap();
                rows.iter()
                    .map(|r| {
                        (
                            r.try_get::<String, _>("task").unwrap(),
                            r.try_get::<String, _>("label").unwrap(),
                            r.try_get::<i64, _>("n").unwrap(),
                        )
                    })
                    .collect::<Vec<_>>()
            }
        };
        let now = read(
            "SELECT task, label, SUM(n) AS n FROM episode_counts GROUP BY task, label ORDER BY task, label",
        )
        .await;
        let s = |t: &str, l: &str, n: i64| (t.to_string(), l.to_string(), n);
        assert_eq!(now, [s("", "failure", 1), s("reach", "success", 1), s("reach", "unknown", 1)]);
        let v1 =
            read("SELECT task, label, n FROM version_counts WHERE version_from <= 1 AND (version_to IS NULL OR version_to > 1) ORDER BY task, label").await;
        assert_eq!(v1, [s("", "failure", 1), s("reach", "success", 1), s("reach", "unknown", 2)]);
    }

    /// Migration 0019 turns each version's copies into spans: one label span per revision, open
    /// at the head only while the episode is visible; the revision the head froze on the episode.
    #[tokio::test]
    async fn migration_0019_turns_copies_into_spans() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}/catalog.sqlite?mode=rwc", dir.path().display());
        sqlx::any::install_default_drivers();
        let pool = AnyPoolOptions::new().max_connections(1).connect(&url).await.unwrap();
        migrator_of(&SQLITE_MIGRATIONS[..18]).run(&pool).await.unwrap();
        sqlx::query("PRAGMA foreign_keys = OFF").execute(&pool).await.unwrap();
        // e-1 relabeled in version 3, e-2 removed in version 2, e-3 added in version 2.
        for (id, removed, rev) in [("e-1", None, 2), ("e-2", Some(2), 1), ("e-3", None, 1)] {
            sqlx::query(
                "INSERT INTO episodes (id, policy, checkpoint, task, source_sha256, source_name, source_index, length, \
                 tags, metadata, data_file, row_group, row_offset, row_count, version_added, version_removed, label, \
                 label_source, label_revision, label_actor, label_updated_at, created_at) VALUES ($1, 'p', 'c', NULL, 'x', \
                 'demo', 0, 1, '[]', '{}', 'steps/a.parquet', 0, 0, 1, 1, $2, 'failure', 'test', $3, 'ingest', 'now', 'now')",
            )
            .bind(id)
            .bind(removed)
            .bind(rev)
            .execute(&pool)
            .await
            .unwrap();
        }
        let frozen = [
            (1, "e-1", "success", 1),
            (2, "e-1", "success", 1),
            (3, "e-1", "failure", 2),
            (1, "e-2", "unknown", 1),
            (2, "e-3", "success", 1),
            (3, "e-3", "success", 1),
        ];
        for (v, id, label, rev) in frozen {
            sqlx::query("INSERT INTO version_labels (version, episode_id, label, label_source, revision) VALUES ($1, $2, $3, 'test', $4)")
                .bind(v)
                .bind(id)
                .bind(label)
                .bind(rev)
                .execute(&pool)
                .await
                .unwrap();
        }
        for (v, n) in [(1, 1), (2, 2), (3, 1)] {
            sqlx::query("INSERT INTO version_counts (version, policy, checkpoint, task, label, n) VALUES ($1, 'p', 'c', '', 'success', $2)")
                .bind(v)
                .bind(n)
                .execute(&pool)
                .await
                .unwrap();
        }
        sqlx::query("UPDATE store_head SET version = 3").execute(&pool).await.unwrap();
        pool.close().await;
        let cat = Catalog::connect(&url).await.unwrap();
        let rows = sqlx::query(
            "SELECT episode_id, version_from, version_to, revision FROM version_labels ORDER BY episode_id, version_from",
        )
        .fetch_all(&cat.pool)
        .await
        .unwrap();
        let spans: Vec<(String, i64, Option<i64>, i64)> = rows
            .iter()
            .map(|r| {
                (
                    r.try_get("episode_id").unwrap(),
                    r.try_get("version_from").unwrap(),
                    r.try_get("version_to").unwrap(),
                    r.try_get("revision").unwrap(),
                )
            })
            .collect();
        let e = |id: &str, from, to, rev| (id.to_string(), from, to, rev);
        assert_eq!(
            spans,
            [e("e-1", 1, Some(3), 1), e("e-1", 3, None, 2), e("e-2", 1, Some(2), 1), e("e-3", 2, None, 1)]
        );
        let rows = sqlx::query("SELECT id, label_frozen_revision FROM episodes ORDER BY id")
            .fetch_all(&cat.pool)
            .await
            .unwrap();
        let frozen: Vec<Option<i64>> =
            rows.iter().map(|r| r.try_get("label_frozen_revision").unwrap()).collect();
        assert_eq!(frozen, [Some(2), None, Some(1)]);
        let rows =
            sqlx::query("SELECT version_from, version_to, n FROM version_counts ORDER BY version_from")
                .fetch_all(&cat.pool)
                .await
                .unwrap();
        let counts: Vec<(i64, Option<i64>, i64)> = rows
            .iter()
            .map(|r| {
                (
                    r.try_get("version_from").unwrap(),
                    r.try_get("version_to").unwrap(),
                    r.try_get("n").unwrap(),
                )
            })
            .collect();
        assert_eq!(counts, [(1, Some(2), 1), (2, Some(3), 2), (3, None, 1)]);
    }

    /// Migration 0013 indexes the tags of the episodes already stored (each tag once per episode).
    #[tokio::test]
    async fn migration_0013_backfills_the_tag_index() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}/catalog.sqlite?mode=rwc", dir.path().display());
        sqlx::any::install_default_drivers();
        let pool = AnyPoolOptions::new().max_connections(1).connect(&url).await.unwrap();
        migrator_of(&SQLITE_MIGRATIONS[..12]).run(&pool).await.unwrap();
        sqlx::query("PRAGMA foreign_keys = OFF").execute(&pool).await.unwrap();
        for (id, tags) in [("e-1", r#"["a","b"]"#), ("e-2", "[]"), ("e-3", r#"["a","a","c d"]"#)] {
            sqlx::query(
                "INSERT INTO episodes (id, policy, checkpoint, task, source_sha256, source_name, source_index, length, \
                 tags, metadata, data_file, row_group, row_offset, row_count, version_added, label, label_source, \
                 label_revision, label_actor, label_updated_at, created_at) VALUES ($1, 'p', 'c', NULL, 'x', 'demo', \
                 0, 1, $2, '{}', 'steps/a.parquet', 0, 0, 1, 1, 'unknown', '', 1, 'ingest', 'now', 'now')",
            )
            .bind(id)
            .bind(tags)
            .execute(&pool)
            .await
            .unwrap();
        }
        pool.close().await;
        let cat = Catalog::connect(&url).await.unwrap();
        let rows = sqlx::query("SELECT tag, episode_id FROM episode_tags ORDER BY tag, episode_id")
            .fetch_all(&cat.pool)
            .await
            .unwrap();
        let got: Vec<(String, String)> =
            rows.iter().map(|r| (r.try_get("tag").unwrap(), r.try_get("episode_id").unwrap())).collect();
        let want = [("a", "e-1"), ("a", "e-3"), ("b", "e-1"), ("c d", "e-3")];
        assert_eq!(got, want.map(|(t, e)| (t.to_string(), e.to_string())));
    }
}
