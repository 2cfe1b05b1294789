//! Group commit of single-label PUTs, on both catalogs.
//!
//! A label write is a few microseconds of SQL wrapped in a transaction whose fixed costs
//! dominate: on SQLite its one writer (BEGIN IMMEDIATE, COMMIT, the hand-offs to sqlx's
//! connection thread), on Postgres the commit's WAL flush, during which the write holds the row
//! locks of the maintained counts every other write of that checkpoint needs. So concurrent
//! `PUT /v1/episodes/{id}/label` requests are queued to one writer
//! task, which takes everything waiting (up to [`MAX_BATCH`]) and commits it in ONE transaction
//! with [`store::Store::set_labels_each`]: each request keeps its own outcome — its If-Match check
//! against the revision at the moment its item runs, its 409 with the current label and who set
//! it, its audit event — and a conflict on one item does not roll back the others. A request is
//! answered only after its batch has committed, so an acknowledged write is durable and in the
//! audit log. If a batch fails as a whole (a catalog error: nothing was committed), its items are
//! retried one transaction each, so every request gets its own answer.
//!
//! The writer takes the API's SQLite write gate for each batch, so it queues behind bulk label
//! writes and snapshots instead of spinning in SQLite's busy handler. On Postgres (no gate) the
//! batch locks its episodes in id order, so batches of several servers cannot deadlock; one
//! transaction per PUT was measured slower there (api/README.md).

use crate::{AppState, Inner};
use std::sync::{Arc, OnceLock, Weak};
use store::{LabelChange, LabelUpdate, StoreError};
use tokio::sync::{mpsc, oneshot};

/// The most label writes committed in one transaction.
pub(crate) const MAX_BATCH: usize = 256;
/// Requests waiting for the writer beyond this wait in `send` (backpressure).
const QUEUE_DEPTH: usize = 4096;

type Reply = oneshot::Sender<Result<LabelChange, StoreError>>;

struct Pending {
    update: LabelUpdate,
    actor: String,
    reply: Reply,
}

/// The queue to the writer task; the task starts with the first write and ends when the server
/// state is dropped (the queue's sender goes with it).
#[derive(Default)]
pub(crate) struct LabelWriter {
    queue: OnceLock<mpsc::Sender<Pending>>,
}

/// Sets one label (source `human`) with the semantics of [`store::Store::set_label`], through
/// the group-commit writer.
pub(crate) async fn set_label(
    state: &AppState,
    update: LabelUpdate,
    actor: &str,
) -> Result<LabelChange, StoreError> {
    let queue = state.inner.label_writer.queue.get_or_init(|| {
        let (tx, rx) = mpsc::channel(QUEUE_DEPTH);
        tokio::spawn(run(Arc::downgrade(&state.inner), rx));
        tx
    });
    let (reply, answer) = oneshot::channel();
    let item = Pending { update, actor: actor.to_string(), reply };
    if let Err(mpsc::error::SendError(item)) = queue.send(item).await {
        // The writer is gone (the server is shutting down): write directly.
        let _gate = state.write_gate().await;
        return state.store().set_label(item.update, &item.actor, "human").await;
    }
    match answer.await {
        Ok(r) => r,
        // The writer dropped the request without answering: it stopped before running it.
        Err(_) => Err(StoreError::Conflict("the label writer stopped before this write; retry".into())),
    }
}

async fn run(state: Weak<Inner>, mut rx: mpsc::Receiver<Pending>) {
    let mut batch: Vec<Pending> = Vec::with_capacity(MAX_BATCH);
    while rx.recv_many(&mut batch, MAX_BATCH).await > 0 {
        let Some(inner) = state.upgrade() else { break };
        let state = AppState { inner };
        commit(&state, std::mem::take(&mut batch)).await;
    }
}

async fn commit(state: &AppState, batch: Vec<Pending>) {
    let items: Vec<(LabelUpdate, String)> =
        batch.iter().map(|p| (p.update.clone(), p.actor.clone())).collect();
    let result = {
        let _gate = state.write_gate().await;
        state.store().set_labels_each(items, "human").await
    };
    match result {
        Ok(outcomes) => {
            // One outcome per item, in order (a request left without one would get "retry").
            for (p, outcome) in batch.into_iter().zip(outcomes) {
                // A client that went away is not waiting for its answer; its write stands.
                let _ = p.reply.send(outcome);
            }
        }
        // Nothing was committed: give every request its own transaction and its own answer.
        Err(_) => {
            for p in batch {
                let outcome = {
                    let _gate = state.write_gate().await;
                    state.store().set_label(p.update, &p.actor, "human").await
                };
                let _ = p.reply.send(outcome);
            }
        }
    }
}
