//! `store-feed`: what the store's change feed drives.
//!
//! The feed itself (events appended in the transaction of every catalog change, read in order)
//! is the store's. This crate owns what subscribes to it: webhook subscriptions, their delivery
//! claims, attempts and dead letters ([`Webhooks`], `webhooks.rs`), and automations, rules that
//! queue jobs from it ([`Automations`], `automations.rs`: train on new labels, score on publish,
//! a run's scoreboard once it is labeled). Both are traits implemented for `store::Store`.

mod automations;
mod webhooks;

pub use automations::{
    check_params, AutomationRecord, AutomationRule, AutomationTarget, Automations, ScoreOnPublish,
    ScoreboardOnRunLabeled, TrainOnLabels,
};
pub use webhooks::{delivery_id, DeadLetter, HeldWebhook, WebhookRecord, Webhooks, MAX_WEBHOOK_ATTEMPTS};
