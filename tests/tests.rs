//! The integration tests of this crate, one binary: each file of `tests/` is a module here
//! (one link of the whole dependency tree instead of one per file). A file that installs a
//! global allocator to measure memory stays a binary of its own (see Cargo.toml).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

mod automations;
mod cli_pipes;
mod common;
mod compare_cli;
mod concurrent_writers;
mod crash_safety;
mod demo_quick;
mod export_api;
mod export_cli;
mod graceful_shutdown;
mod hostile_corpus;
mod idempotent_restarts;
mod ingest_runs;
mod lerobot_eval_cli;
mod openapi_contract;
mod pyarrow_interop;
mod review_cli;
mod review_queue;
mod s3_store;
mod snapshot_stalled_store;
mod soak;
mod steer_http;
mod steering_telemetry;
mod takeovers;
mod upload_cleanup;
mod verifier_parity;
mod web_labeling;
mod webhook_receiver;
mod worker_processes;
