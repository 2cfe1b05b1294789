//! Layers: derived per-step data (a camera policy's encoder features) attached to stored
//! episodes. Listing, which episodes hold one (to resume a computation), an episode's layers,
//! and writing one group of episodes' values as an Arrow IPC stream (store/README.md, "Layers").

use super::*;
use axum::body::Bytes;
use axum::extract::DefaultBodyLimit;

/// The largest layer upload: one group of episodes' values (a client sends a computation in
/// groups, each a version).
pub const MAX_LAYER_UPLOAD_BYTES: usize = 256 << 20;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/layers", get(list_layers))
        .route(
            "/v1/layers/{name}",
            post(write_layer.layer(need!(Role::Trainer)))
                .layer(DefaultBodyLimit::max(MAX_LAYER_UPLOAD_BYTES)),
        )
        .route("/v1/layers/{name}/episodes", get(layer_episodes))
        .route("/v1/episodes/{id}/layers", get(episode_layers))
}

/// Every (layer, producer) pair, with the episodes holding it now.
#[utoipa::path(get, path = "/v1/layers", tag = "layers", responses((status = 200, body = Vec<store::LayerRecord>)))]
pub async fn list_layers(State(s): State<AppState>) -> ApiResult<Json<Vec<store::LayerRecord>>> {
    Ok(Json(s.store().layers().await?))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ProducerQuery {
    /// The producer's sha256 (`producer_hash` of `GET /v1/layers`).
    #[param(pattern = r"^[0-9a-f]{64}$")]
    producer_hash: String,
}

/// The episodes that hold layer `name` from a producer now (ids, in id order): what a resumed
/// computation skips.
#[utoipa::path(get, path = "/v1/layers/{name}/episodes", tag = "layers",
    params(("name" = String, Path, pattern = r"^[A-Za-z0-9._-]{1,120}$"), ProducerQuery),
    responses((status = 200, body = Vec<String>), (status = 400, description = "a bad layer name or producer hash")))]
pub async fn layer_episodes(
    State(s): State<AppState>,
    ApiPath(name): ApiPath<String>,
    ApiQuery(q): ApiQuery<ProducerQuery>,
) -> ApiResult<Json<Vec<String>>> {
    store::check_layer_name(&name)?;
    if q.producer_hash.len() != 64
        || !q.producer_hash.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
    {
        return Err(ApiError::bad_request("producer_hash: 64 lower-case hex digits"));
    }
    Ok(Json(s.store().layer_episodes(&name, &q.producer_hash).await?))
}

/// The layers an episode holds, now or as of a version.
#[utoipa::path(get, path = "/v1/episodes/{id}/layers", tag = "layers",
    params(("id" = String, Path), VersionQuery),
    responses((status = 200, body = Vec<store::EpisodeLayer>), (status = 404, description = "no such version")))]
pub async fn episode_layers(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(q): ApiQuery<VersionQuery>,
) -> ApiResult<Json<Vec<store::EpisodeLayer>>> {
    check_id("episode id", &id)?;
    if let Some(v) = q.version {
        s.store().version(v).await?;
    }
    Ok(Json(s.store().episode_layers(&id, q.version).await?))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct LayerWriteQuery {
    /// The producer, a JSON object with at least one member (encoder, the policy checkpoint whose
    /// encoder it is, the weights' content hash, ...): e.g.
    /// `{"encoder":"dp-resnet18","policy":"p","checkpoint":"c","content_hash":"…"}`.
    // The document states it as a JSON parameter (`openapi.rs`), which the derive cannot.
    producer: String,
}

/// Writes one group of episodes' values of layer `name` as a new version. The body is an Arrow
/// IPC stream with columns `episode_id` (utf8, large utf8 or utf8 view) and `value`
/// (fixed_size_list<float32>[dim]), one row per stored step of each episode, the episode's rows
/// together and in step order. Episodes holding the layer from this producer already are
/// skipped: 201 with the new version, or 200 with none when every episode was skipped.
#[utoipa::path(post, path = "/v1/layers/{name}", tag = "layers",
    params(("name" = String, Path, pattern = r"^[A-Za-z0-9._-]{1,120}$"), LayerWriteQuery),
    request_body(content = crate::body_schemas::UploadBytes, content_type = "application/octet-stream", description = "the values, an Arrow IPC stream (any content type is read as one)"),
    responses((status = 201, body = store::LayerWrite), (status = 200, body = store::LayerWrite, description = "nothing to write"),
              (status = 400, description = "a bad stream, producer or values"),
              (status = 403, description = "the token's role is below trainer"),
              (status = 404, description = "no such episode"),
              (status = 413, description = "larger than 256 MiB: send fewer episodes per request")))]
pub async fn write_layer(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(name): ApiPath<String>,
    ApiQuery(q): ApiQuery<LayerWriteQuery>,
    body: Bytes,
) -> ApiResult<Response> {
    caller.require(Role::Trainer)?;
    store::check_layer_name(&name)?;
    let producer: Value = serde_json::from_str(&q.producer)
        .map_err(|e| ApiError::bad_request(format!("producer is not JSON: {e}")))?;
    store::producer_hash(&producer)?;
    // Decoding untrusted IPC on a blocking thread: a reader bug is a 400, never a dead server.
    let decoded = tokio::task::spawn_blocking(move || decode_layer_stream(&body)).await;
    let values = match decoded {
        Ok(r) => r?,
        Err(_) => return Err(ApiError::bad_request("the Arrow IPC stream could not be decoded")),
    };
    let done = {
        let _gate = s.write_gate().await;
        s.store().write_layer(&name, &producer, values, &caller.name).await?
    };
    let status = if done.version.is_some() { StatusCode::CREATED } else { StatusCode::OK };
    Ok((status, Json(done)).into_response())
}

/// The ids of a string column of any Arrow string type.
fn string_values(col: &dyn arrow::array::Array) -> Option<Vec<&str>> {
    use arrow::array::{LargeStringArray, StringArray, StringViewArray};
    if col.null_count() > 0 {
        return None;
    }
    let any = col.as_any();
    if let Some(a) = any.downcast_ref::<StringArray>() {
        return Some(a.iter().map(|v| v.unwrap_or("")).collect());
    }
    if let Some(a) = any.downcast_ref::<LargeStringArray>() {
        return Some(a.iter().map(|v| v.unwrap_or("")).collect());
    }
    any.downcast_ref::<StringViewArray>().map(|a| a.iter().map(|v| v.unwrap_or("")).collect())
}

/// The per-episode values of an upload (see [`write_layer`]).
fn decode_layer_stream(body: &[u8]) -> ApiResult<Vec<store::LayerValues>> {
    use arrow::array::{Array, FixedSizeListArray, Float32Array};
    let bad = |m: String| ApiError::bad_request(m);
    let reader = arrow::ipc::reader::StreamReader::try_new(std::io::Cursor::new(body), None)
        .map_err(|e| bad(format!("not an Arrow IPC stream: {e}")))?;
    let mut out: Vec<store::LayerValues> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for batch in reader {
        let batch = batch.map_err(|e| bad(format!("reading the Arrow IPC stream: {e}")))?;
        let ids = batch
            .column_by_name("episode_id")
            .and_then(|c| string_values(c.as_ref()))
            .ok_or_else(|| bad("the stream needs a string column episode_id without nulls".into()))?;
        let values = batch
            .column_by_name("value")
            .and_then(|c| c.as_any().downcast_ref::<FixedSizeListArray>())
            .ok_or_else(|| bad("the stream needs a fixed_size_list<float32> column value".into()))?;
        if values.null_count() > 0 {
            return Err(bad("value may not be null".into()));
        }
        let dim = values.value_length() as usize;
        let floats = values
            .values()
            .as_any()
            .downcast_ref::<Float32Array>()
            .ok_or_else(|| bad("value must hold float32".into()))?;
        if floats.null_count() > 0 || values.len() != ids.len() {
            return Err(bad("value has nulls or another length than episode_id".into()));
        }
        for (row, id) in ids.iter().enumerate() {
            let start = values.value_offset(row) as usize;
            let v = floats
                .values()
                .get(start..start + dim)
                .ok_or_else(|| bad(format!("row {row}: value is shorter than its dim {dim}")))?;
            match out.last_mut() {
                Some(last) if last.episode_id == *id => last.values.extend_from_slice(v),
                _ => {
                    if !seen.insert(id.to_string()) {
                        return Err(bad(format!("episode {id}: its rows are not together")));
                    }
                    out.push(store::LayerValues { episode_id: id.to_string(), dim, values: v.to_vec() });
                }
            }
        }
    }
    if out.is_empty() {
        return Err(bad("the stream holds no rows".into()));
    }
    Ok(out)
}
