//! `store-jobs`: the job queue on the store's catalog.
//!
//! This crate owns jobs (training, ingest, export, scoring, scoreboard) as catalog rows that
//! workers claim with a lease: queued → running → succeeded | failed | cancelled, fenced by
//! attempt so no job runs twice at once ([`JobQueue`], implemented for `store::Store`). It keeps
//! its rows through the store's catalog face (`store::sql`); what a job does is its runner's
//! (trainer, export, api's worker).

mod jobs;

pub use jobs::{insert_job, JobKind, JobQueue, JobRecord, JobState};
