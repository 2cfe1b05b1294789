//! The store's error type: every variant names the problem in words a user can act on.

use crate::Label;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{0}")]
    Invalid(String),
    #[error("{what} not found: {id}")]
    NotFound { what: &'static str, id: String },
    #[error("source already ingested: sha256 {sha256} is in version {version}")]
    AlreadyIngested { sha256: String, version: i64 },
    #[error(
        "label conflict on episode {episode_id}: expected revision {expected}, but it is at revision {revision} \
         ({label}, set by {actor} at {at})"
    )]
    LabelConflict {
        episode_id: String,
        expected: i64,
        revision: i64,
        label: Label,
        actor: String,
        at: String,
    },
    #[error("conflict: {0}")]
    Conflict(String),
    /// What was asked for existed but was deleted for good (events behind the feed's retention).
    #[error("gone: {0}")]
    Gone(String),
    #[error("catalog error: {0}")]
    Db(#[from] sqlx::Error),
    #[error("catalog migration failed: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error("object store error: {0}")]
    Object(#[from] object_store::Error),
    #[error("parquet error: {0}")]
    Parquet(#[from] parquet::errors::ParquetError),
    #[error("arrow error: {0}")]
    Arrow(#[from] arrow::error::ArrowError),
    #[error("corrupt store data: {0}")]
    Corrupt(String),
}

impl StoreError {
    pub fn invalid(msg: impl Into<String>) -> Self {
        StoreError::Invalid(msg.into())
    }
    pub fn not_found(what: &'static str, id: impl Into<String>) -> Self {
        StoreError::NotFound { what, id: id.into() }
    }
}

impl From<serde_json::Error> for StoreError {
    fn from(e: serde_json::Error) -> Self {
        StoreError::Corrupt(format!("bad JSON in catalog: {e}"))
    }
}
