//! `store-compare`: which checkpoint is better, read from the store's catalog.
//!
//! This crate owns the paired comparison of two arms of a policy with its anytime-valid
//! intervals ([`Compare`], `compare.rs`), the scoreboard of success per checkpoint and run
//! ([`Scoreboards`], `scoreboard.rs`) and the policy aliases that move only when a comparison
//! holds ([`PolicyAliases`], `policy_aliases.rs`), each a trait implemented for `store::Store`
//! over the catalog face (`store::sql`).

mod compare;
mod policy_aliases;
mod scoreboard;

pub use compare::{
    ArmSpec, Compare, CompareRequest, Comparison, ComparisonSlice, EValues, PairTable, DEFAULT_PAIR_KEY,
};
pub use policy_aliases::{MoveAlias, PolicyAlias, PolicyAliasMove, PolicyAliases};
pub use scoreboard::{BaselineComparison, Scoreboard, ScoreboardRequest, ScoreboardRow, Scoreboards, NO_RUN};
