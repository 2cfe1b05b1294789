//! The `/v1` handlers, one module per API resource, each with its own `router()`. Each handler
//! checks the caller's role, validates ids and calls the store: every rule (label revisions,
//! splits, leases, aliases) lives in the store, not here.

/// A route-level role check (runs after the token check, before the body is read).
macro_rules! need {
    ($role:expr) => {
        from_fn_with_state($role, crate::auth::require_role)
    };
}

mod admin;
mod artifacts;
mod automations;
mod catalog;
mod compare;
mod consensus;
mod episodes;
mod events;
mod exports;
mod frames;
mod infra;
mod jobs;
mod labels;
mod layers;
mod monitors;
mod review;
mod scoreboard;
mod splits;
mod webhooks;

pub use admin::*;
pub use artifacts::*;
pub use automations::*;
pub use catalog::*;
pub use compare::*;
pub use consensus::*;
pub use episodes::*;
pub use events::*;
pub use exports::*;
pub use frames::*;
pub use infra::*;
pub use jobs::*;
pub use labels::*;
pub use layers::*;
pub use monitors::*;
pub use review::*;
pub use scoreboard::*;
pub use splits::*;
pub use webhooks::*;

use crate::auth::Caller;
use crate::body_schemas::FileBytes;
use crate::error::{ApiError, ApiResult, Problem};
use crate::extract::{check_id, check_name, ApiJson, ApiPath, ApiQuery};
use crate::AppState;
use axum::body::Body;
use axum::extract::State;
use axum::handler::Handler;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::from_fn_with_state;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, put};
use axum::Router;
use axum::{Extension, Json};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::sync::atomic::Ordering;
use store::{EpisodeFilter, Label, LabelUpdate, Role};
use store_artifacts::{Artifacts, Monitors};
use store_labeling::{Consensus, ReviewQueue};
use utoipa::{IntoParams, ToSchema};

pub const ARROW_STREAM: &str = "application/vnd.apache.arrow.stream";

/// A label as the API spells it: exactly `success`, `failure` or `unknown` (the document's enum;
/// the CLI's shorthands such as `s` or `true` are not part of the HTTP contract).
fn parse_label(s: &str) -> ApiResult<Label> {
    match s {
        "success" | "failure" | "unknown" => s.parse::<Label>().map_err(ApiError::from),
        _ => Err(ApiError::bad_request(format!("unknown label {s:?}: expected success, failure or unknown"))),
    }
}

/// Every resource's routes (the token check is layered on by the caller).
pub(crate) fn authed_routes() -> Router<AppState> {
    Router::new()
        .merge(admin::router())
        .merge(artifacts::router())
        .merge(automations::router())
        .merge(exports::router())
        .merge(catalog::router())
        .merge(compare::router())
        .merge(consensus::router())
        .merge(episodes::router())
        .merge(events::router())
        .merge(frames::router())
        .merge(infra::router())
        .merge(jobs::router())
        .merge(labels::router())
        .merge(layers::router())
        .merge(monitors::router())
        .merge(review::router())
        .merge(scoreboard::router())
        .merge(splits::router())
        .merge(webhooks::router())
}

fn etag(revision: i64) -> HeaderValue {
    HeaderValue::from_str(&format!("\"{revision}\"")).expect("digits are a valid header")
}
