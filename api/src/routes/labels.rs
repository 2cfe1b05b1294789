//! Labels: one write with If-Match (group-committed on SQLite), bulk writes, label snapshots.

use super::*;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/episodes/{id}/label", put(put_label.layer(need!(Role::Labeler))))
        .route("/v1/labels/bulk", post(bulk_labels.layer(need!(Role::Labeler))))
        .route("/v1/label-snapshots", post(create_snapshot.layer(need!(Role::Labeler))))
}

#[derive(Deserialize, ToSchema)]
pub struct LabelRequest {
    #[schema(value_type = store::Label)]
    label: String,
    note: Option<String>,
}

fn if_match(headers: &HeaderMap) -> ApiResult<i64> {
    let v = headers.get(header::IF_MATCH).ok_or_else(|| {
        ApiError::new(
            StatusCode::PRECONDITION_REQUIRED,
            "if-match-required",
            "PUT a label with If-Match: <label revision> (the ETag of GET /v1/episodes/{id})",
        )
    })?;
    // `W/"7"`, `"7"` or `7` (the document's pattern, crate::openapi::IF_MATCH_PATTERN).
    let raw = v.to_str().unwrap_or("").trim();
    let s = raw.strip_prefix("W/").unwrap_or(raw);
    let s = s.strip_prefix('"').and_then(|x| x.strip_suffix('"')).unwrap_or(s);
    let digits = (1..=18).contains(&s.len()) && s.bytes().all(|b| b.is_ascii_digit());
    digits.then(|| s.parse::<i64>().ok()).flatten().ok_or_else(|| {
        ApiError::bad_request(format!("If-Match {raw:?} is not a label revision (an integer)"))
    })
}

/// Sets an episode's label; `If-Match: <revision>` is required, a stale revision gets 409 with
/// the current label, its revision and who set it when.
#[utoipa::path(put, path = "/v1/episodes/{id}/label", tag = "labels",
    params(("id" = String, Path), ("If-Match" = String, Header, description = "the label revision you read (an integer, quoted or not)")),
    request_body = LabelRequest,
    responses((status = 200, body = store::LabelChange, headers(("ETag" = String, description = "the new label revision"))),
              (status = 404, description = "no such episode"),
              (status = 409, description = "a stale revision: the problem names the current label, its revision, who set it and when"),
              (status = 428, description = "no If-Match header"), (status = 403, description = "the token's role is below labeler")))]
pub async fn put_label(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
    ApiJson(body): ApiJson<LabelRequest>,
) -> ApiResult<Response> {
    caller.require(Role::Labeler)?;
    check_id("episode id", &id)?;
    let expect = if_match(&headers)?;
    // One small read per PUT: in a campaign where several labelers vote, a labeler's PUT would
    // bypass the votes (admins may still overrule).
    if caller.role < Role::Admin && s.store().votes_required(&id).await? {
        return Err(super::consensus::votes_required(&id));
    }
    let update = LabelUpdate {
        episode_id: id,
        label: parse_label(&body.label)?,
        expect_revision: Some(expect),
        note: body.note,
    };
    // Group-committed with concurrent PUTs (one transaction per batch, one outcome each).
    let change = crate::label_writer::set_label(&s, update, &caller.name).await;
    let change = s.count_label_result(change)?;
    let rev = change.revision;
    let mut resp = Json(change).into_response();
    resp.headers_mut().insert(header::ETAG, etag(rev));
    Ok(resp)
}

#[derive(Deserialize, ToSchema)]
pub struct BulkLabelItem {
    episode_id: String,
    #[schema(value_type = store::Label)]
    label: String,
    /// Fail the whole request unless the episode is at this revision.
    expect_revision: Option<i64>,
    note: Option<String>,
}

#[derive(Deserialize, ToSchema)]
pub struct BulkLabelRequest {
    updates: Vec<BulkLabelItem>,
}

/// Labels many episodes in one transaction: all succeed or none does.
#[utoipa::path(post, path = "/v1/labels/bulk", tag = "labels", request_body = BulkLabelRequest,
    responses((status = 200, body = Vec<store::LabelChange>), (status = 409, description = "a stale expected revision"),
              (status = 404, description = "no such episode"), (status = 403, description = "the token's role is below labeler")))]
pub async fn bulk_labels(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(body): ApiJson<BulkLabelRequest>,
) -> ApiResult<Json<Vec<store::LabelChange>>> {
    caller.require(Role::Labeler)?;
    if body.updates.len() > 10_000 {
        return Err(ApiError::bad_request("at most 10000 updates per request"));
    }
    let mut updates = Vec::with_capacity(body.updates.len());
    let check_votes = caller.role < Role::Admin && s.store().any_multi_labeler_campaign().await?;
    for u in body.updates {
        check_id("episode id", &u.episode_id)?;
        if check_votes && s.store().votes_required(&u.episode_id).await? {
            return Err(super::consensus::votes_required(&u.episode_id));
        }
        updates.push(LabelUpdate {
            episode_id: u.episode_id,
            label: parse_label(&u.label)?,
            expect_revision: u.expect_revision,
            note: u.note,
        });
    }
    let changes = {
        let _gate = s.write_gate().await;
        s.store().set_labels(updates, &caller.name, "human").await
    };
    let changes = s.count_labels_result(changes)?;
    Ok(Json(changes))
}

#[derive(Deserialize, ToSchema, Default)]
pub struct SnapshotRequest {
    message: Option<String>,
}

/// Freezes the current labels into a new version.
#[utoipa::path(post, path = "/v1/label-snapshots", tag = "labels", request_body = SnapshotRequest,
    responses((status = 201, description = "a new version", body = store::CommitInfo),
              (status = 200, description = "no label changed since the head version: the head", body = store::CommitInfo),
              (status = 403, description = "the token's role is below labeler")))]
pub async fn create_snapshot(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(body): ApiJson<SnapshotRequest>,
) -> ApiResult<(StatusCode, Json<store::CommitInfo>)> {
    caller.require(Role::Labeler)?;
    let msg = body.message.unwrap_or_else(|| "label snapshot".into());
    if msg.len() > 4000 {
        return Err(ApiError::bad_request("message is longer than 4000 bytes"));
    }
    // The labels file is uploaded before the write gate and the version lock are taken: label
    // writes go on meanwhile, however slow the object store.
    let (info, created) = match s.store().prepare_label_snapshot().await? {
        None => (s.store().head_commit().await?, false),
        Some(prepared) => {
            let _gate = s.write_gate().await;
            (s.store().commit_label_snapshot(prepared, &caller.name, &msg).await?, true)
        }
    };
    // Nothing changed since the head froze the labels: the head is the snapshot (200, no new version).
    Ok((if created { StatusCode::CREATED } else { StatusCode::OK }, Json(info)))
}

impl AppState {
    pub(super) fn count_label_result(
        &self,
        r: Result<store::LabelChange, store::StoreError>,
    ) -> ApiResult<store::LabelChange> {
        self.count_labels_result(r.map(|c| vec![c])).map(|mut v| v.remove(0))
    }
    fn count_labels_result(
        &self,
        r: Result<Vec<store::LabelChange>, store::StoreError>,
    ) -> ApiResult<Vec<store::LabelChange>> {
        let m = &self.inner.metrics;
        match r {
            Ok(v) => {
                m.label_writes.fetch_add(v.len() as u64, Ordering::Relaxed);
                Ok(v)
            }
            Err(e) => {
                if matches!(e, store::StoreError::LabelConflict { .. } | store::StoreError::Conflict(_)) {
                    m.label_conflicts.fetch_add(1, Ordering::Relaxed);
                }
                Err(e.into())
            }
        }
    }
}
