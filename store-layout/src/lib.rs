//! `store-layout`: the rollout data model and the Parquet layout of episode steps, below the
//! catalog.
//!
//! This crate owns what an episode IS (`model.rs`: labels, vector, image and extra columns, step
//! flags, frame streams, the name rule), how its steps are laid out in Parquet (`steps.rs`: the
//! schema, the writer that builds steps files, the labels files; `spill.rs`: image pages spilled
//! to temporary files), how a stored camera video decodes (`video.rs`: the H.264 MP4 that ingest
//! encodes, read a frame at a time) and the store's one error type (`error.rs`). It knows no
//! catalog and no object store: `store` records where the files it writes live, and re-exports
//! all of this as `store::model`, `store::steps`, `store::video` and `store::StoreError`.

mod error;
pub mod model;
mod spill;
pub mod steps;
pub mod video;

pub use error::StoreError;
pub use model::*;
