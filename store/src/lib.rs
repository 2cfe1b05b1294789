//! The ufops store: the single source of truth for rollouts, labels, splits and artifacts.
//!
//! It owns the catalog (SQL via sqlx: SQLite by default, Postgres for scale-out), the object
//! storage (a local directory or S3 via `object_store`) and where the Parquet steps files live
//! (their layout and the data model are `store-layout`'s, re-exported here). Every write creates
//! an immutable, numbered version; data files are written first under unique names and become
//! visible only when the version's catalog row commits in one transaction. Every catalog change
//! also records its events in the change feed, in the same transaction (`events.rs`), which
//! idempotency keys (`idempotency.rs`) build on.
//!
//! Above it, on its catalog face ([`sql`]), stand the crates that keep rows of their own: the
//! job queue (`store-jobs`), what the feed drives (`store-feed`: webhooks, automations), the
//! comparison of checkpoints (`store-compare`: compare, scoreboard, policy aliases), what
//! training publishes (`store-artifacts`: verifier artifacts and failure monitors with their
//! aliases) and the labelers' protocol (`store-labeling`: votes and consensus, the review queue).

mod catalog;
mod episodes_arrow;
mod events;
mod exports;
mod extensions;
mod frames;
mod gc;
mod idempotency;
mod ingest_writer;
mod labels;
mod layers;
mod lru;
mod media;
mod objects;
mod query;
mod read;
mod runs;
mod scores;
mod selection;
mod spans;
mod splits;
/// Test support for every crate's tests (feature `testing`, enabled by the dev-dependencies).
#[cfg(any(test, feature = "testing"))]
pub mod test_support;
mod tokens;
mod versioning;

pub use catalog::{migration_names, Backend};
pub use episodes_arrow::{episodes_batch, episodes_schema};
pub use events::{
    with_request, Event, EventFilter, EventKind, EventPage, NewEvent, RequestContext, MAX_EVENT_PAGE,
};
pub use exports::{check_export_path, ExportFile, EXPORTS_PREFIX};
pub use frames::{cameras_of, Camera, CameraKind, FrameLocation};
pub use gc::{GcReport, MAX_GRACE_SECONDS};
pub use idempotency::{Claim, IdempotentRequest, StoredResponse, MAX_IDEMPOTENCY_KEY_LEN};
pub use ingest_writer::{CommitInfo, IngestWriter, SourceRecord, MAX_STEPS_FILE_BYTES};
pub use labels::{LabelChange, LabelEvent, LabelUpdate, PreparedLabelSnapshot};
pub use layers::{
    check_layer_name, producer_hash, EpisodeLayer, LayerRecord, LayerValues, LayerWrite, LAYER_META_KEY,
    MAX_LAYER_DIM, PRODUCER_META_KEY,
};
pub use media::EpisodeMedia;
pub use model::*;
pub use objects::FetchCounts;
pub use query::{EpisodeFilter, EpisodeRecord, VersionDiff, VersionInfo};
pub use read::{EpisodeLocation, EpisodeSteps, StepsReadError, StepsStream};
pub use runs::{RunInput, RunRecord, Steering};
pub use scores::{EpisodeScore, DEFAULT_REVIEW_ALIAS, DEFAULT_REVIEW_KIND};
pub use selection::{
    for_each_episode, for_each_episode_with_layers, select, EpisodeReader, Progress, ScoreRange, Selected,
    Selection,
};
pub use splits::{SplitCheckpointSteps, SplitEpisode, SplitRecord, SplitRequest, MAX_VAL_FRACTION};
/// The data model, the steps layout and the stored video's decoding live below the catalog,
/// in `store-layout`.
pub use store_layout::{model, steps, video, StoreError};
pub use tokens::{Role, TokenRecord};
pub use versioning::{CountFilter, LabelCounts};

use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Where the store lives. Defaults: SQLite file and object directory inside `data_dir`.
#[derive(Debug, Clone)]
pub struct StoreConfig {
    pub data_dir: PathBuf,
    /// `sqlite://…` or `postgres://…`; default `sqlite://<data_dir>/catalog.sqlite`.
    pub database_url: Option<String>,
    /// A local path, `file:///…` or `s3://bucket/prefix`; default `<data_dir>/objects`.
    pub object_store_url: Option<String>,
}

impl StoreConfig {
    pub fn local(data_dir: impl Into<PathBuf>) -> Self {
        StoreConfig { data_dir: data_dir.into(), database_url: None, object_store_url: None }
    }
}

/// A handle on an opened store; cheap to clone.
#[derive(Clone)]
pub struct Store {
    inner: Arc<Inner>,
}

struct Inner {
    db: catalog::Catalog,
    objects: objects::Objects,
    data_dir: PathBuf,
    /// Steps files' footers and offset indexes, fetched once per file.
    meta_cache: read::MetaCache,
    /// Decoded pages of image columns (frames served one at a time).
    frame_pages: frames::PageCache,
    /// State kept per store by the upper crates ([`Store::extension`]).
    extensions: extensions::Extensions,
    /// The newest event sequence number this handle committed (`events.rs`).
    feed: tokio::sync::watch::Sender<i64>,
}

impl Store {
    /// Opens (creating if needed) the store and applies pending migrations.
    pub async fn open(config: &StoreConfig) -> Result<Store, StoreError> {
        let url = match &config.database_url {
            Some(u) => u.clone(),
            None => {
                std::fs::create_dir_all(&config.data_dir).map_err(|e| {
                    StoreError::invalid(format!("cannot create data dir {}: {e}", config.data_dir.display()))
                })?;
                format!("sqlite://{}/catalog.sqlite", config.data_dir.display())
            }
        };
        let db = catalog::Catalog::connect(&url).await?;
        let objects = objects::Objects::open(config)?;
        let meta_cache = read::MetaCache::new(read::METADATA_CACHE_BYTES);
        let frame_pages = frames::PageCache::new(frames::PAGE_CACHE_BYTES);
        Ok(Store {
            inner: Arc::new(Inner {
                db,
                objects,
                data_dir: config.data_dir.clone(),
                meta_cache,
                frame_pages,
                extensions: Default::default(),
                feed: tokio::sync::watch::Sender::new(0),
            }),
        })
    }

    pub fn backend(&self) -> Backend {
        self.inner.db.backend
    }

    pub fn data_dir(&self) -> &Path {
        &self.inner.data_dir
    }

    /// A short description of where the catalog and objects live.
    pub fn describe(&self) -> String {
        format!("catalog: {}, objects: {}", self.inner.db.describe(), self.inner.objects.describe())
    }

    /// Reads a whole object (a data file, a media file, an artifact file) by its store path.
    pub async fn get_object(&self, path: &str) -> Result<bytes::Bytes, StoreError> {
        self.inner.objects.get(path).await
    }

    /// Reads a byte range of an object (for HTTP range requests on media).
    pub async fn get_object_range(
        &self,
        path: &str,
        range: std::ops::Range<u64>,
    ) -> Result<bytes::Bytes, StoreError> {
        self.inner.objects.get_range(path, range).await
    }

    /// Read requests made to the object store and bytes fetched since the store was opened.
    pub fn fetch_counts(&self) -> FetchCounts {
        self.inner.objects.fetch_counts()
    }

    /// Size in bytes of an object.
    pub async fn object_size(&self, path: &str) -> Result<u64, StoreError> {
        self.inner.objects.size(path).await
    }

    /// The catalog itself: this crate's rooms and the store's upper crates ([`sql`]) keep their
    /// rows through it.
    pub fn catalog(&self) -> &sql::Catalog {
        &self.inner.db
    }
    /// This store handle's one value of type `T` (made with `T::default()` on first use): state
    /// an upper crate keeps per store, such as a cache of catalog reads, shared by the handle's
    /// clones and by nothing else.
    pub fn extension<T: Default + Send + Sync + 'static>(&self) -> Arc<T> {
        self.inner.extensions.get_or_default()
    }
    pub(crate) fn objects(&self) -> &objects::Objects {
        &self.inner.objects
    }
}

/// The catalog face that the store's upper crates (`store-jobs`, `store-feed`, `store-compare`,
/// `store-artifacts`, `store-labeling`) keep their rows with: the connection pool and its write transactions, the
/// dialect helpers, the episode filter's SQL, the label write inside a transaction,
/// the change feed's commit ([`Store::commit_with_events`]) and the version spans. The tables
/// are all the catalog's (one migration sequence, `migrations/`); applications use `Store`'s
/// methods and those crates' traits instead.
pub mod sql {
    pub use crate::catalog::{bind_val, insert_rows, placeholders, Catalog, RowExt, Tx, Val};
    pub use crate::gc::forget_pending;
    pub use crate::labels::write_label;
    pub use crate::query::{episode_conds, episode_from_row, label_conds, push_arg, EPISODE_SELECT};
    pub use crate::runs::run_from_row;
    pub use crate::scores::refresh_review_scores_where;
    pub use crate::spans::covers;
    pub use crate::{now_ms, now_rfc3339};
}

/// Now, as the catalog writes its timestamps (RFC 3339, UTC, milliseconds).
pub fn now_rfc3339() -> String {
    chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Millis, true)
}

/// Now, in Unix milliseconds (leases and deadlines).
pub fn now_ms() -> i64 {
    chrono::Utc::now().timestamp_millis()
}

/// Lower-case hex sha256 of a byte slice.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    hex::encode(sha2::Sha256::digest(bytes))
}

/// Test support: the Postgres server the tests use (`UFOPS_TEST_POSTGRES`, default the local
/// `test` database with trust auth, as on our machines).
#[cfg(any(test, feature = "testing"))]
pub fn test_postgres_base() -> String {
    std::env::var("UFOPS_TEST_POSTGRES").unwrap_or_else(|_| "postgres://postgres@127.0.0.1:5432/test".into())
}

/// Test support: creates a fresh schema on the test Postgres server and returns a database URL
/// whose connections use it, so tests never see each other's rows.
#[cfg(any(test, feature = "testing"))]
pub async fn create_test_schema(prefix: &str) -> Result<String, StoreError> {
    use sqlx::{Connection, Executor};
    sqlx::any::install_default_drivers();
    let base = test_postgres_base();
    let schema = format!("{prefix}_{}", &uuid::Uuid::new_v4().simple().to_string()[..10]);
    let mut conn = sqlx::AnyConnection::connect(&base).await.map_err(|e| {
        StoreError::invalid(format!(
            "cannot reach the test Postgres at {base}: {e} (start it, or set UFOPS_TEST_POSTGRES)"
        ))
    })?;
    conn.execute(format!("CREATE SCHEMA {schema}").as_str()).await?;
    let sep = if base.contains('?') { '&' } else { '?' };
    Ok(format!("{base}{sep}options[search_path]={schema}"))
}
