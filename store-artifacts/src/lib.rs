//! `store-artifacts`: what training publishes, kept in the store's catalog and objects.
//!
//! This crate owns verifier artifacts (immutable, content-addressed file sets with
//! per-checkpoint aliases, `latest` moved on publish: [`Artifacts`], `artifacts.rs`) and failure
//! monitors (thresholds calibrated on an artifact's scores, with their own aliases:
//! [`Monitors`], `monitors.rs`), each a trait implemented for `store::Store` over the catalog
//! face (`store::sql`). An artifact's files go through the store's pending-object protocol
//! (`Store::put_pending_content`), so gc never deletes a file a publication is about to
//! reference; moving a checkpoint's `classifier@latest` re-derives its episodes' review scores
//! in the same transaction (`store::sql::refresh_review_scores_where`).

mod artifacts;
mod monitors;

pub use artifacts::{ArtifactFile, ArtifactRecord, Artifacts, NewArtifact};
pub use monitors::{MonitorEntry, Monitors, NewMonitor};
