//! `store-labeling`: the labelers' protocol, kept in the store's catalog.
//!
//! This crate owns several labelers per episode (campaign settings, failure-cause taxonomies,
//! votes, their consensus and its adjudication, agreement between labelers: [`Consensus`],
//! `consensus.rs`) and the review queue (the artifact that scores each policy's queue and the
//! queue in the order a labeler asks for: [`ReviewQueue`], `review.rs`), each a trait
//! implemented for `store::Store` over the catalog face (`store::sql`). A verdict becomes a
//! label through the store's one label write (`store::sql::write_label`); the scores the queue
//! is ordered by are the store's (`Store::put_episode_scores`).

mod consensus;
mod review;

pub use consensus::{
    Agreement, Campaign, Consensus, ConsensusState, Dispute, EpisodeVotes, LabelerCounts, NewVote,
    PairAgreement, Span, VerdictData, Vote, VoteOutcome, CAMPAIGN_CACHE_TTL, MAX_FAILURE_CAUSES,
    MAX_LABELS_NEEDED, MAX_SPANS,
};
pub use review::{ReviewArtifact, ReviewEntry, ReviewOrder, ReviewQueue};
