//! The integration tests of this crate, one binary: each file of `tests/` is a module here
//! (one link of the whole dependency tree instead of one per file). A file that installs a
//! global allocator to measure memory stays a binary of its own (see Cargo.toml).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

mod catalog_lists;
mod gc_in_flight;
mod split_sample;
mod store;
mod version_history;
