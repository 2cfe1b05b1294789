//! Episode frames: one step of an episode's image camera (an `image.<camera>` column of its
//! steps, one PNG per step) as an image, read alone (the store fetches the one page holding it).
//! The labeling page loads them as the timeline moves; a version's frames never change, so they
//! are cached for good.

use super::*;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new().route("/v1/episodes/{id}/frames/{camera}/{t}", get(get_frame))
}

/// Frames are immutable (an episode's steps never change; a version only hides them), so a
/// browser keeps them (per user: they sit behind the token).
const FRAME_CACHE: &str = "private, max-age=31536000, immutable";

/// Step `t` of the episode's image camera `camera` (listed with `kind: image` in the episode's
/// `cameras`), as the image the store holds (`image/png`, or `image/jpeg` for a camera recorded
/// as JPEG). Only that frame is read. Answers carry a strong `ETag` and
/// `Cache-Control: private, max-age=31536000, immutable`; `If-None-Match` with it is a 304.
#[utoipa::path(get, path = "/v1/episodes/{id}/frames/{camera}/{t}", tag = "episodes",
    params(("id" = String, Path), ("camera" = String, Path, description = "an image camera of the episode"),
           ("t" = u64, Path, minimum = 0, description = "the step, from 0"), VersionQuery,
           ("If-None-Match" = Option<String>, Header, description = "the `ETag` of a frame already held")),
    responses(
        (status = 200, description = "the frame",
         content((FileBytes = "image/png"), (FileBytes = "image/jpeg")),
         headers(("ETag" = String, description = "names the frame"), ("Cache-Control" = String))),
        (status = 304, description = "the frame of `If-None-Match`, unchanged",
         headers(("ETag" = String), ("Cache-Control" = String))),
        (status = 404, description = "no such episode or version, the episode has no image camera `camera`, or no step `t`")))]
pub async fn get_frame(
    State(s): State<AppState>,
    ApiPath((id, camera, t)): ApiPath<(String, String, String)>,
    ApiQuery(q): ApiQuery<VersionQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    check_id("episode id", &id)?;
    check_id("camera", &camera)?;
    if t.is_empty() || !t.bytes().all(|b| b.is_ascii_digit()) {
        return Err(ApiError::bad_request(format!("step {t:?}: a step index from 0")));
    }
    // Past u64: past every episode's end, like any step it does not have.
    let t: u64 = t.parse().unwrap_or(u64::MAX);
    let at = s.store().locate_frame(&id, q.version, &camera, t).await?;
    let stem = at.data_file.trim_start_matches("steps/").trim_end_matches(".parquet");
    let etag = HeaderValue::from_str(&format!("\"{stem}.{}.{}.{camera}\"", at.row_group, at.row))
        .map_err(|e| ApiError::internal(e.to_string()))?;
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|x| etag == x.trim().trim_start_matches("W/") || x.trim() == "*"));
    let mut resp = if fresh {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        let png = s.store().read_frame_at(&at, &camera).await?;
        let ctype = if at.encoding == "jpeg" { "image/jpeg" } else { "image/png" };
        ([(header::CONTENT_TYPE, HeaderValue::from_static(ctype))], png).into_response()
    };
    let h = resp.headers_mut();
    h.insert(header::ETAG, etag);
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static(FRAME_CACHE));
    Ok(resp)
}
