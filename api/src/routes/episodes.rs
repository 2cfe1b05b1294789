//! Episodes: listing with filters and cursor pagination, counts per label state, one episode
//! with its label history, its step table (JSON or Arrow IPC) and its media (range requests).

use super::*;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/episodes", get(list_episodes))
        .route("/v1/episodes/counts", get(episode_counts))
        .route("/v1/episodes/{id}", get(get_episode))
        .route("/v1/episodes/{id}/steps", get(get_steps))
        .route("/v1/episodes/{id}/media/{key}", get(get_media))
}

#[derive(Deserialize, IntoParams, Default)]
#[into_params(parameter_in = Query)]
pub struct EpisodeQuery {
    pub(crate) policy: Option<String>,
    pub(crate) checkpoint: Option<String>,
    pub(crate) task: Option<String>,
    #[param(value_type = Option<store::Label>)]
    pub(crate) label: Option<String>,
    pub(crate) label_source: Option<String>,
    pub(crate) tag: Option<String>,
    /// Read the store as of this version (labels frozen in it); default: now.
    pub(crate) version: Option<i64>,
    /// Cursor: the `next_cursor` of the previous page.
    /// Any printable text works as a position in id order; a review order's cursors are its own.
    #[param(pattern = r"^[^\x00-\x1f\x7f-\x9f]{1,400}$")]
    pub(crate) after: Option<String>,
    /// Page size, 1-1000 (default 100).
    #[param(minimum = 1, maximum = 1000)]
    pub(crate) limit: Option<i64>,
    /// Sort order; only `id` (ascending, the cursor order) is supported.
    #[param(value_type = Option<EpisodeSort>)]
    pub(crate) sort: Option<String>,
    /// Review queue order: `id` (default), `uncertain` (verifier score nearest 0.5 first),
    /// `disagreement` (score furthest from the current label first) or `source` (by label
    /// source). Orders other than `id` use the stored scores of each policy's review artifact
    /// (`/v1/review/artifacts/{policy}`), list the episodes of `version` (default: now) with its
    /// labels, put episodes without a score last, and page with their own cursors
    /// (`next_cursor`); text that is not one of the order's cursors lies past its end.
    #[param(value_type = Option<EpisodeOrder>)]
    pub(crate) order: Option<String>,
}

impl EpisodeQuery {
    /// The page size: 1-1000, default 100.
    pub(crate) fn page_limit(&self) -> ApiResult<i64> {
        let limit = self.limit.unwrap_or(100);
        if !(1..=1000).contains(&limit) {
            return Err(ApiError::bad_request(format!("limit {limit} must be in 1..=1000")));
        }
        Ok(limit)
    }

    /// The query's filters (policy, checkpoint, task, label, label source, tag), without the
    /// version, cursor or page size.
    pub(crate) fn filters(&self) -> ApiResult<EpisodeFilter> {
        Ok(EpisodeFilter {
            policy: self.policy.clone(),
            checkpoint: self.checkpoint.clone(),
            task: self.task.clone(),
            label: self.label.as_deref().map(parse_label).transpose()?,
            label_source: self.label_source.clone(),
            tag: self.tag.clone(),
            ..Default::default()
        })
    }
}

/// The sort orders of `GET /v1/episodes` (the doc's enum; the handler matches the same words).
#[derive(ToSchema)]
#[schema(rename_all = "lowercase")]
#[allow(dead_code)]
pub enum EpisodeSort {
    Id,
}

/// The review orders of `GET /v1/episodes` (the doc's enum; `store_labeling::ReviewOrder` parses them).
#[derive(ToSchema)]
#[schema(rename_all = "lowercase")]
#[allow(dead_code)]
pub enum EpisodeOrder {
    Id,
    Uncertain,
    Disagreement,
    Source,
}

#[derive(Serialize, ToSchema)]
pub struct EpisodePage {
    pub(crate) episodes: Vec<store::EpisodeRecord>,
    /// Pass as `after` for the next page; absent on the last page.
    pub(crate) next_cursor: Option<String>,
    /// With a review `order`: each listed episode's stored score, in the same order as `episodes`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(crate) review: Option<Vec<super::review::ReviewScoreRef>>,
}

/// Lists episodes with filters, in id order, a page at a time: pass the page's `next_cursor` as
/// `after` for the next one. Pages are keyset pages, so they stay fast at any depth and, while
/// labels change, never repeat an episode nor skip one that still matches the filters.
#[utoipa::path(get, path = "/v1/episodes", tag = "episodes", params(EpisodeQuery),
    responses((status = 200, body = EpisodePage)))]
pub async fn list_episodes(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<EpisodeQuery>,
) -> ApiResult<Json<EpisodePage>> {
    if let Some(order) = q.order.clone().filter(|o| o != "id") {
        return super::review::list_review_queue(&s, &order, q).await.map(Json);
    }
    match q.sort.as_deref() {
        None | Some("id") => {}
        Some(other) => {
            return Err(ApiError::bad_request(format!(
                "unsupported sort {other:?}: only \"id\" (the cursor order)"
            )))
        }
    }
    let limit = q.page_limit()?;
    if let Some(a) = &q.after {
        // A keyset bound, compared with ids: any printable text is a position.
        if a.is_empty() || a.chars().count() > 400 || a.chars().any(char::is_control) {
            return Err(ApiError::bad_request("cursor: 1-400 printable characters"));
        }
    }
    let filter =
        EpisodeFilter { version: q.version, after: q.after.clone(), limit: Some(limit + 1), ..q.filters()? };
    let mut episodes = s.store().episodes(&filter).await?;
    let next_cursor = if episodes.len() as i64 > limit {
        episodes.truncate(limit as usize);
        episodes.last().map(|e| e.id.clone())
    } else {
        None
    };
    Ok(Json(EpisodePage { episodes, next_cursor, review: None }))
}

#[derive(Deserialize, IntoParams, Default)]
#[into_params(parameter_in = Query)]
pub struct CountsQuery {
    policy: Option<String>,
    checkpoint: Option<String>,
    task: Option<String>,
    /// Count the labels frozen in this version; default: now.
    version: Option<i64>,
}

/// Episodes per label state and their total.
#[derive(Serialize, ToSchema)]
pub struct EpisodeCounts {
    total: i64,
    success: i64,
    failure: i64,
    unknown: i64,
}

/// Counts the episodes matching `policy`, `checkpoint` and `task` per label state (the labeling
/// page's progress bar). The counts are maintained with every label write and version, so this
/// reads a few rows whatever the catalog's size.
#[utoipa::path(get, path = "/v1/episodes/counts", tag = "episodes", params(CountsQuery),
    responses((status = 200, body = EpisodeCounts), (status = 404, description = "no such version")))]
pub async fn episode_counts(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<CountsQuery>,
) -> ApiResult<Json<EpisodeCounts>> {
    let filter =
        store::CountFilter { version: q.version, policy: q.policy, checkpoint: q.checkpoint, task: q.task };
    let c = s.store().episode_counts(&filter).await?;
    Ok(Json(EpisodeCounts { total: c.total, success: c.success, failure: c.failure, unknown: c.unknown }))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct VersionQuery {
    /// As of this version; default: now.
    pub(crate) version: Option<i64>,
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct StepsQuery {
    /// As of this version; default: now.
    pub(crate) version: Option<i64>,
    /// Layers to join as `obs.<layer>` columns (comma-separated layer names, see `GET /v1/layers`).
    #[param(pattern = r"^[A-Za-z0-9._-]{1,120}(,[A-Za-z0-9._-]{1,120}){0,15}$")]
    pub(crate) layers: Option<String>,
}

/// An episode, its label history (oldest first) and its cameras.
#[derive(Serialize, ToSchema)]
pub struct EpisodeDetail {
    episode: store::EpisodeRecord,
    history: Vec<store::LabelEvent>,
    /// Every camera of the episode, in column order: videos (`kind: video`, served by
    /// `/v1/episodes/{id}/media/{name}`) and image columns (`kind: image`, one frame per step
    /// from `/v1/episodes/{id}/frames/{name}/{t}`).
    cameras: Vec<store::Camera>,
}

/// An episode's step table as columns.
#[derive(Serialize, ToSchema)]
pub struct StepColumns {
    episode_id: String,
    num_rows: usize,
    /// `{column name: [value per row]}`; vector columns hold arrays.
    #[schema(value_type = Object)]
    columns: serde_json::Map<String, Value>,
    /// Binary columns left out (read them as Arrow IPC).
    omitted: Vec<String>,
}

/// An episode: metadata, current label (its revision is also the `ETag`), label history and
/// cameras (videos and image columns, from its steps file's footer).
#[utoipa::path(get, path = "/v1/episodes/{id}", tag = "episodes",
    params(("id" = String, Path), VersionQuery),
    responses((status = 200, body = EpisodeDetail, headers(("ETag" = String, description = "the label revision"))),
              (status = 404, description = "no such episode or version")))]
pub async fn get_episode(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(q): ApiQuery<VersionQuery>,
) -> ApiResult<Response> {
    check_id("episode id", &id)?;
    let ep = s.store().episode(&id, q.version).await?;
    let history = s.store().label_history(&id).await?;
    let cameras = match s.store().steps_schema(&ep.data_file).await {
        Ok(schema) => store::cameras_of(&schema),
        Err(e) => {
            // The label and history stay readable; the steps route reports the file's fault.
            tracing::warn!(episode = %id, error = %e, "cannot read the steps file's schema: no cameras listed");
            Vec::new()
        }
    };
    let rev = ep.label_revision;
    let mut resp = Json(EpisodeDetail { episode: ep, history, cameras }).into_response();
    resp.headers_mut().insert(header::ETAG, etag(rev));
    Ok(resp)
}

/// The step table: JSON (columnar) or, with `Accept: application/vnd.apache.arrow.stream`, Arrow IPC.
#[utoipa::path(get, path = "/v1/episodes/{id}/steps", tag = "episodes",
    params(("id" = String, Path), StepsQuery),
    responses(
        (status = 200, description = "columnar JSON, or with `Accept: application/vnd.apache.arrow.stream` an Arrow IPC stream",
         content((StepColumns = "application/json"), (FileBytes = "application/vnd.apache.arrow.stream"))),
        (status = 400, description = "a bad layer name"),
        (status = 404, description = "no such episode or version, or the episode lacks a layer asked for")))]
pub async fn get_steps(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(q): ApiQuery<StepsQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    check_id("episode id", &id)?;
    let layers: Vec<String> = match q.layers.as_deref() {
        None => vec![],
        Some(list) => list.split(',').map(str::to_string).collect(),
    };
    if layers.len() > 16 {
        return Err(ApiError::bad_request("at most 16 layers at once"));
    }
    for l in &layers {
        store::check_layer_name(l)?;
    }
    let batch = if layers.is_empty() {
        s.store().read_steps(&id, q.version).await?
    } else {
        s.store().read_steps_with_layers(&id, q.version, &layers).await?
    };
    let wants_arrow = headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|a| a.split(',').any(|p| p.trim().starts_with(ARROW_STREAM)));
    if wants_arrow {
        let mut buf = Vec::new();
        {
            let mut w = arrow::ipc::writer::StreamWriter::try_new(&mut buf, &batch.schema())
                .map_err(|e| ApiError::internal(e.to_string()))?;
            w.write(&batch).map_err(|e| ApiError::internal(e.to_string()))?;
            w.finish().map_err(|e| ApiError::internal(e.to_string()))?;
        }
        return Ok(([(header::CONTENT_TYPE, ARROW_STREAM)], buf).into_response());
    }
    let (columns, omitted) = crate::steps_json::columns(&batch);
    Ok(Json(StepColumns { episode_id: id, num_rows: batch.num_rows(), columns, omitted }).into_response())
}

/// The episode's video `key` (a `media.<key>.path` column of its steps, found in the catalog), with
/// HTTP range requests: a range is fetched from the object store as asked, nothing more.
#[utoipa::path(get, path = "/v1/episodes/{id}/media/{key}", tag = "episodes",
    params(("id" = String, Path), ("key" = String, Path), ("Range" = Option<String>, Header)),
    responses((status = 200, description = "the whole file", content_type = "*/*", body = FileBytes),
              (status = 206, description = "a byte range", content_type = "*/*", body = FileBytes),
              (status = 416, description = "the range is outside the file"), (status = 404, description = "no such episode or media key")))]
pub async fn get_media(
    State(s): State<AppState>,
    ApiPath((id, key)): ApiPath<(String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    check_id("episode id", &id)?;
    check_id("media key", &key)?;
    // The catalog says where the video is (and its size): no steps file, no HEAD request.
    let m = s.store().episode_media(&id, &key).await?;
    crate::media::serve_object(s.store(), &m.path, m.size_bytes, headers.get(header::RANGE)).await
}
