//! Artifacts: verifier artifacts, their files, aliases, and resolution of
//! `POLICY/CHECKPOINT/KIND@ALIAS` for the robot-side loader.

use super::*;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/artifacts", get(list_artifacts))
        .route("/v1/artifacts/{id}", get(get_artifact))
        .route("/v1/artifacts/{id}/files/{name}", get(artifact_file))
        .route("/v1/artifacts/{id}/aliases/{alias}", put(set_alias.layer(need!(Role::Trainer))))
        .route(
            "/v1/policies/{policy}/checkpoints/{checkpoint}/verifiers/{kind_at_alias}",
            get(resolve_verifier),
        )
        .route(
            "/v1/policies/{policy}/checkpoints/{checkpoint}/verifiers/{kind_at_alias}/files/{name}",
            get(resolve_verifier_file),
        )
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ArtifactQuery {
    policy: Option<String>,
    checkpoint: Option<String>,
    kind: Option<String>,
}

/// Artifacts, optionally filtered.
#[utoipa::path(get, path = "/v1/artifacts", tag = "artifacts", params(ArtifactQuery),
    responses((status = 200, body = Vec<store_artifacts::ArtifactRecord>)))]
pub async fn list_artifacts(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<ArtifactQuery>,
) -> ApiResult<Json<Vec<store_artifacts::ArtifactRecord>>> {
    Ok(Json(s.store().artifacts(q.policy.as_deref(), q.checkpoint.as_deref(), q.kind.as_deref()).await?))
}

/// An artifact by id.
#[utoipa::path(get, path = "/v1/artifacts/{id}", tag = "artifacts", params(("id" = String, Path)),
    responses((status = 200, body = store_artifacts::ArtifactRecord), (status = 404, description = "no such artifact")))]
pub async fn get_artifact(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<store_artifacts::ArtifactRecord>> {
    check_id("artifact id", &id)?;
    Ok(Json(s.store().artifact(&id).await?))
}

/// One file of an artifact, checked against its sha256 (sent as `X-Checksum-Sha256` and `ETag`).
#[utoipa::path(get, path = "/v1/artifacts/{id}/files/{name}", tag = "artifacts",
    params(("id" = String, Path), ("name" = String, Path)),
    responses((status = 200, description = "the file (`application/json` for a .json file)", headers(("X-Checksum-Sha256" = String)),
               content((Object = "application/json"), (FileBytes = "application/octet-stream"))),
              (status = 404, description = "no such artifact or file")))]
pub async fn artifact_file(
    State(s): State<AppState>,
    ApiPath((id, name)): ApiPath<(String, String)>,
) -> ApiResult<Response> {
    check_id("artifact id", &id)?;
    check_id("file name", &name)?;
    let a = s.store().artifact(&id).await?;
    send_artifact_file(&s, &a, &name).await
}

async fn send_artifact_file(
    s: &AppState,
    a: &store_artifacts::ArtifactRecord,
    name: &str,
) -> ApiResult<Response> {
    let f = a
        .files
        .iter()
        .find(|f| f.name == name)
        .ok_or_else(|| ApiError::not_found(format!("artifact {} has no file {name:?}", a.id)))?;
    let data = s.store().get_object(&format!("{}/{}", a.prefix, f.name)).await?;
    if store::sha256_hex(&data) != f.sha256 {
        return Err(ApiError::internal_public(format!(
            "artifact {} file {} fails its sha256 check",
            a.id, f.name
        )));
    }
    let ctype = if name.ends_with(".json") { "application/json" } else { "application/octet-stream" };
    let mut resp = Response::new(Body::from(data));
    let h = resp.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(ctype));
    h.insert(
        "x-checksum-sha256",
        HeaderValue::from_str(&f.sha256).map_err(|e| ApiError::internal(e.to_string()))?,
    );
    h.insert(
        header::ETAG,
        HeaderValue::from_str(&format!("\"{}\"", f.sha256)).map_err(|e| ApiError::internal(e.to_string()))?,
    );
    h.insert("x-artifact-id", HeaderValue::from_str(&a.id).map_err(|e| ApiError::internal(e.to_string()))?);
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("private, max-age=31536000, immutable"));
    Ok(resp)
}

fn split_kind_alias(s: &str) -> ApiResult<(&str, &str)> {
    let (kind, alias) =
        s.split_once('@').ok_or_else(|| ApiError::bad_request(format!("expected KIND@ALIAS, got {s:?}")))?;
    check_id("verifier kind", kind)?;
    check_id("alias", alias)?;
    Ok((kind, alias))
}

/// Resolves `policies/{p}/checkpoints/{c}/verifiers/{kind}@{alias}` to an artifact.
#[utoipa::path(get, path = "/v1/policies/{policy}/checkpoints/{checkpoint}/verifiers/{kind_at_alias}", tag = "artifacts",
    params(("policy" = String, Path), ("checkpoint" = String, Path),
           ("kind_at_alias" = String, Path, description = "KIND@ALIAS, e.g. classifier@latest")),
    responses((status = 200, body = store_artifacts::ArtifactRecord), (status = 404, description = "no artifact has that alias")))]
pub async fn resolve_verifier(
    State(s): State<AppState>,
    ApiPath((policy, checkpoint, ka)): ApiPath<(String, String, String)>,
) -> ApiResult<Json<store_artifacts::ArtifactRecord>> {
    check_name("policy", &policy)?;
    check_name("checkpoint", &checkpoint)?;
    let (kind, alias) = split_kind_alias(&ka)?;
    Ok(Json(s.store().resolve_alias(&policy, &checkpoint, kind, alias).await?))
}

/// Downloads a file of the artifact an alias points at.
#[utoipa::path(get, path = "/v1/policies/{policy}/checkpoints/{checkpoint}/verifiers/{kind_at_alias}/files/{name}",
    tag = "artifacts",
    params(("policy" = String, Path), ("checkpoint" = String, Path), ("kind_at_alias" = String, Path),
           ("name" = String, Path)),
    responses((status = 200, description = "the file (`application/json` for a .json file)",
               headers(("X-Checksum-Sha256" = String), ("X-Artifact-Id" = String)),
               content((Object = "application/json"), (FileBytes = "application/octet-stream"))),
              (status = 404, description = "no artifact has that alias, or it has no such file")))]
pub async fn resolve_verifier_file(
    State(s): State<AppState>,
    ApiPath((policy, checkpoint, ka, name)): ApiPath<(String, String, String, String)>,
) -> ApiResult<Response> {
    check_name("policy", &policy)?;
    check_name("checkpoint", &checkpoint)?;
    check_id("file name", &name)?;
    let (kind, alias) = split_kind_alias(&ka)?;
    let a = s.store().resolve_alias(&policy, &checkpoint, kind, alias).await?;
    send_artifact_file(&s, &a, &name).await
}

/// Points an alias of the artifact's (policy, checkpoint, kind) at it.
#[utoipa::path(put, path = "/v1/artifacts/{id}/aliases/{alias}", tag = "artifacts",
    params(("id" = String, Path), ("alias" = String, Path)),
    responses((status = 200, body = store_artifacts::ArtifactRecord), (status = 404, description = "no such artifact"),
              (status = 409, description = "the alias cannot be moved"), (status = 403, description = "the token's role is below trainer")))]
pub async fn set_alias(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath((id, alias)): ApiPath<(String, String)>,
) -> ApiResult<Json<store_artifacts::ArtifactRecord>> {
    caller.require(Role::Trainer)?;
    check_id("artifact id", &id)?;
    check_id("alias", &alias)?;
    Ok(Json(s.store().set_alias(&alias, &id).await?))
}
