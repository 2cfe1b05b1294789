//! The integration tests of this crate, one binary: each file of `tests/` is a module here.
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

mod campaign_cache;
mod review_index;
