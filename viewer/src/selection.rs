//! Which episodes a recording shows: those of a policy checkpoint or of a split, at a store
//! version, and under a limit alternately from successes, failures and unknowns.

use crate::{ViewError, ViewOptions};
use std::collections::{BTreeMap, HashSet};
use store::{EpisodeFilter, EpisodeRecord, Label, Store};

/// Selects the episodes of the view, in recording order.
pub(crate) async fn select_episodes(
    store: &Store,
    opts: &ViewOptions,
) -> Result<Vec<EpisodeRecord>, ViewError> {
    let eps = listed_episodes(store, opts).await?;
    Ok(match opts.max_episodes {
        Some(max) => alternate_labels(eps, max),
        None => eps,
    })
}

/// Every episode of the split, or of the policy checkpoint, at the version asked for.
async fn listed_episodes(store: &Store, opts: &ViewOptions) -> Result<Vec<EpisodeRecord>, ViewError> {
    Ok(match &opts.split_id {
        Some(split_id) => {
            let split = store.split(split_id).await?;
            let version = opts.version.unwrap_or(split.version);
            let ids: HashSet<String> =
                store.split_episodes(split_id).await?.into_iter().map(|e| e.episode_id).collect();
            let all = store.episodes(&EpisodeFilter { version: Some(version), ..Default::default() }).await?;
            all.into_iter().filter(|e| ids.contains(&e.id)).collect::<Vec<_>>()
        }
        None => {
            if opts.policy.is_empty() || opts.checkpoint.is_empty() {
                return Err(ViewError::Invalid("a policy and a checkpoint (or a split) are required".into()));
            }
            let f = EpisodeFilter {
                version: opts.version,
                policy: Some(opts.policy.clone()),
                checkpoint: Some(opts.checkpoint.clone()),
                ..Default::default()
            };
            store.episodes(&f).await?
        }
    })
}

/// At most `max` of `eps`, sorted by id, taken in turn from successes, failures and unknowns.
fn alternate_labels(eps: Vec<EpisodeRecord>, max: usize) -> Vec<EpisodeRecord> {
    // Round-robin over labels so a limit keeps successes and failures side by side.
    let mut by_label: BTreeMap<u8, std::collections::VecDeque<EpisodeRecord>> = BTreeMap::new();
    for e in eps {
        let k = match e.label {
            Label::Success => 0,
            Label::Failure => 1,
            Label::Unknown => 2,
        };
        by_label.entry(k).or_default().push_back(e);
    }
    let mut out = Vec::new();
    while out.len() < max && by_label.values().any(|q| !q.is_empty()) {
        for q in by_label.values_mut() {
            if out.len() < max {
                if let Some(e) = q.pop_front() {
                    out.push(e);
                }
            }
        }
    }
    out.sort_by(|a, b| a.id.cmp(&b.id));
    out
}
