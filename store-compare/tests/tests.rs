//! The integration tests of this crate, one binary: each file of `tests/` is a module here.

mod compare;
mod scoreboard;
