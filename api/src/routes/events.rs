//! The change feed: every catalog change as an event, replayable from any sequence number, with
//! long polling (`wait`) so a follower learns of a change as it commits.

use super::*;
use std::time::Duration;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new().route("/v1/events", get(list_events))
}

/// The longest a request may wait for an event.
pub const MAX_EVENT_WAIT_SECONDS: u64 = 60;
/// How often a waiting request looks at the catalog for other servers' commits (this server's
/// own wake it at once).
const POLL: Duration = Duration::from_millis(500);

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct EventsQuery {
    /// Events with a sequence number above this one (default 0: from the start of what is kept).
    #[param(minimum = 0)]
    after: Option<i64>,
    /// At most this many (default and maximum 1000).
    #[param(minimum = 1, maximum = 1000)]
    limit: Option<i64>,
    /// Only these kinds, comma-separated (e.g. `label.set,job.changed`).
    kind: Option<String>,
    /// Only events of this policy.
    policy: Option<String>,
    /// When nothing is there yet, wait up to this many seconds for an event (long polling; at most 60).
    #[param(minimum = 0, maximum = 60)]
    wait: Option<u64>,
}

/// Events after `after`, oldest first, and the sequence number to continue from (`next`). With
/// `wait`, an empty answer comes only after that long without a matching event. 410 when
/// retention deleted events after `after` (re-read the current state, then follow from the
/// `next` the problem names).
#[utoipa::path(get, path = "/v1/events", tag = "events", params(EventsQuery),
    responses((status = 200, body = store::EventPage),
              (status = 410, description = "events after `after` were deleted by retention")))]
pub async fn list_events(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<EventsQuery>,
) -> ApiResult<Json<store::EventPage>> {
    let after = q.after.unwrap_or(0);
    if after < 0 {
        return Err(ApiError::bad_request("after must be 0 or more"));
    }
    let limit = q.limit.unwrap_or(store::MAX_EVENT_PAGE);
    if !(1..=store::MAX_EVENT_PAGE).contains(&limit) {
        return Err(ApiError::bad_request(format!("limit must be 1 to {}", store::MAX_EVENT_PAGE)));
    }
    let wait = q.wait.unwrap_or(0);
    if wait > MAX_EVENT_WAIT_SECONDS {
        return Err(ApiError::bad_request(format!("wait must be 0 to {MAX_EVENT_WAIT_SECONDS} seconds")));
    }
    let mut filter = store::EventFilter::default();
    if let Some(kinds) = &q.kind {
        for k in kinds.split(',').filter(|k| !k.is_empty()) {
            filter.kinds.push(k.parse()?);
        }
    }
    if let Some(p) = &q.policy {
        check_name("policy", p)?;
        filter.policy = Some(p.clone());
    }
    let page = s.store().wait_for_events(after, limit, &filter, Duration::from_secs(wait), POLL).await?;
    Ok(Json(page))
}
