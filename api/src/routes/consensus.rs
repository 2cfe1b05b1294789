//! Several labelers: campaign settings, failure-cause taxonomies, votes, the
//! adjudication queue and agreement. The rules (when votes agree, what a dispute is) live in
//! the store (`store::consensus`); these handlers check roles and hide votes from blind labelers.

use super::*;
use store_labeling::{Agreement, Campaign, Dispute, EpisodeVotes, NewVote, Span, VerdictData, VoteOutcome};

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/campaigns/{policy}", get(get_campaign).put(put_campaign.layer(need!(Role::Admin))))
        .route(
            "/v1/tasks/{task}/failure-causes",
            get(get_failure_causes).put(put_failure_causes.layer(need!(Role::Admin))),
        )
        .route("/v1/episodes/{id}/votes", get(get_votes).post(post_vote.layer(need!(Role::Labeler))))
        .route("/v1/episodes/{id}/adjudication", post(adjudicate.layer(need!(Role::Admin))))
        .route("/v1/adjudication", get(adjudication_queue.layer(need!(Role::Admin))))
        .route("/v1/agreement", get(get_agreement))
}

/// A policy's labeling campaign: how many labelers must agree, and blind mode.
#[utoipa::path(get, path = "/v1/campaigns/{policy}", tag = "labels", params(("policy" = String, Path)),
    responses((status = 200, description = "the settings (defaults: 1 labeler, not blind)", body = Campaign),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 401, body = Problem, content_type = "application/problem+json")))]
pub async fn get_campaign(
    State(s): State<AppState>,
    ApiPath(policy): ApiPath<String>,
) -> ApiResult<Json<Campaign>> {
    check_name("policy", &policy)?;
    Ok(Json(s.store().campaign(&policy).await?))
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CampaignRequest {
    /// Independent verdicts an episode needs (1-10; 1 = one verdict sets the label).
    #[schema(minimum = 1, maximum = 10)]
    labels_needed: i64,
    /// Labelers do not see the others' verdicts until they have given theirs.
    #[serde(default)]
    blind: bool,
}

/// Sets a policy's campaign (admin).
#[utoipa::path(put, path = "/v1/campaigns/{policy}", tag = "labels", params(("policy" = String, Path)),
    request_body = CampaignRequest,
    responses((status = 200, description = "the settings", body = Campaign),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 403, body = Problem, content_type = "application/problem+json")))]
pub async fn put_campaign(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(policy): ApiPath<String>,
    ApiJson(b): ApiJson<CampaignRequest>,
) -> ApiResult<Json<Campaign>> {
    check_name("policy", &policy)?;
    let _gate = s.write_gate().await;
    Ok(Json(s.store().set_campaign(&policy, b.labels_needed, b.blind, &caller.name).await?))
}

#[derive(Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FailureCauses {
    /// In number-key order: the first is key 1 (at most 9; a cause listed twice counts once).
    #[schema(max_items = 9)]
    causes: Vec<String>,
}

/// A task's failure causes (`*`: the taxonomy of tasks without their own).
#[utoipa::path(get, path = "/v1/tasks/{task}/failure-causes", tag = "labels", params(("task" = String, Path)),
    responses((status = 200, description = "the causes, empty when none are set", body = FailureCauses),
              (status = 400, body = Problem, content_type = "application/problem+json")))]
pub async fn get_failure_causes(
    State(s): State<AppState>,
    ApiPath(task): ApiPath<String>,
) -> ApiResult<Json<FailureCauses>> {
    check_name("task", &task)?;
    Ok(Json(FailureCauses { causes: s.store().failure_causes(&task).await? }))
}

/// Sets a task's failure causes (admin).
#[utoipa::path(put, path = "/v1/tasks/{task}/failure-causes", tag = "labels", params(("task" = String, Path)),
    request_body = FailureCauses,
    responses((status = 200, description = "the causes", body = FailureCauses),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 403, body = Problem, content_type = "application/problem+json")))]
pub async fn put_failure_causes(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(task): ApiPath<String>,
    ApiJson(b): ApiJson<FailureCauses>,
) -> ApiResult<Json<FailureCauses>> {
    check_name("task", &task)?;
    let _gate = s.write_gate().await;
    if b.causes.len() > 9 {
        return Err(ApiError::bad_request("at most 9 failure causes (one number key each)"));
    }
    // A cause listed twice is the same key: keep its first place.
    let mut seen = std::collections::HashSet::new();
    let causes: Vec<String> = b.causes.into_iter().filter(|c| seen.insert(c.clone())).collect();
    Ok(Json(FailureCauses { causes: s.store().set_failure_causes(&task, &causes, &caller.name).await? }))
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct VoteRequest {
    /// `success`, `failure` or `unknown`.
    #[schema(value_type = store::Label)]
    label: String,
    /// One of the task's failure causes (failure verdicts only).
    failure_cause: Option<String>,
    /// Stretches of the episode the verdict points at, in steps.
    #[serde(default)]
    spans: Vec<Span>,
    note: Option<String>,
    /// With one labeler per episode the vote is a label write: 409 unless the episode is at this revision.
    expect_revision: Option<i64>,
}

/// Records the caller's verdict on an episode. Its label moves when enough labelers agree
/// (one, by default); a disagreement goes to the adjudication queue.
#[utoipa::path(post, path = "/v1/episodes/{id}/votes", tag = "labels", params(("id" = String, Path)),
    request_body = VoteRequest,
    responses((status = 200, description = "the episode's state after the vote", body = VoteOutcome),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 403, body = Problem, content_type = "application/problem+json"),
              (status = 404, body = Problem, content_type = "application/problem+json"),
              (status = 409, body = Problem, content_type = "application/problem+json")))]
pub async fn post_vote(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
    ApiJson(b): ApiJson<VoteRequest>,
) -> ApiResult<Json<VoteOutcome>> {
    check_id("episode id", &id)?;
    let vote = NewVote {
        episode_id: id,
        label: parse_label(&b.label)?,
        data: VerdictData {
            failure_cause: cause_of(&b.label, b.failure_cause),
            spans: b.spans.into_iter().map(Span::ordered).collect(),
        },
        note: b.note,
        expect_revision: b.expect_revision,
    };
    let out = {
        let _gate = s.write_gate().await;
        s.store().cast_vote(vote, &caller.name).await
    };
    match out {
        Ok(o) => {
            if o.change.is_some() {
                s.inner.metrics.label_writes.fetch_add(1, Ordering::Relaxed);
            }
            Ok(Json(o))
        }
        Err(e) => {
            if matches!(e, store::StoreError::LabelConflict { .. } | store::StoreError::Conflict(_)) {
                s.inner.metrics.label_conflicts.fetch_add(1, Ordering::Relaxed);
            }
            Err(e.into())
        }
    }
}

/// 409 when a labeler tries to set the label of an episode whose campaign takes votes.
pub(crate) fn votes_required(id: &str) -> ApiError {
    ApiError::new(
        StatusCode::CONFLICT,
        "votes-required",
        format!("episode {id} is in a campaign where several labelers vote: POST /v1/episodes/{id}/votes (admins may still set labels)"),
    )
}

/// An episode's votes (each labeler's latest) and its state. In a blind campaign a labeler who
/// has not voted on it sees only how many have (`hidden`); admins see every vote.
#[utoipa::path(get, path = "/v1/episodes/{id}/votes", tag = "labels", params(("id" = String, Path)),
    responses((status = 200, description = "the votes", body = EpisodeVotes),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 404, body = Problem, content_type = "application/problem+json")))]
pub async fn get_votes(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<EpisodeVotes>> {
    check_id("episode id", &id)?;
    let mut v = s.store().episode_votes(&id).await?;
    if caller.role < Role::Admin {
        v.hide_others(&caller.name);
    }
    Ok(Json(v))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct AdjudicationQuery {
    /// Only this policy's disputes.
    policy: Option<String>,
    /// At most this many (default 100, at most 1000).
    #[param(minimum = 1, maximum = 1000)]
    limit: Option<usize>,
}

/// Disputed episodes: enough labelers voted and they disagree (admin).
#[utoipa::path(get, path = "/v1/adjudication", tag = "labels", params(AdjudicationQuery),
    responses((status = 200, description = "the disputes, by episode id", body = Vec<Dispute>),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 403, body = Problem, content_type = "application/problem+json")))]
pub async fn adjudication_queue(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<AdjudicationQuery>,
) -> ApiResult<Json<Vec<Dispute>>> {
    if let Some(p) = &q.policy {
        check_name("policy", p)?;
    }
    let limit = q.limit.unwrap_or(100);
    if !(1..=1000).contains(&limit) {
        return Err(ApiError::bad_request("limit must be 1 to 1000"));
    }
    Ok(Json(s.store().adjudication_queue(q.policy.as_deref(), limit).await?))
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct AdjudicationRequest {
    /// The settled verdict: `success`, `failure` or `unknown`.
    #[schema(value_type = store::Label)]
    label: String,
    failure_cause: Option<String>,
    #[serde(default)]
    spans: Vec<Span>,
    note: Option<String>,
}

/// Settles an episode: its label becomes the given verdict (source `adjudication`) (admin).
#[utoipa::path(post, path = "/v1/episodes/{id}/adjudication", tag = "labels", params(("id" = String, Path)),
    request_body = AdjudicationRequest,
    responses((status = 200, description = "the label change", body = store::LabelChange),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 403, body = Problem, content_type = "application/problem+json"),
              (status = 404, body = Problem, content_type = "application/problem+json"),
              (status = 409, description = "a span past the episode's end, or a cause not in the task's taxonomy", body = Problem, content_type = "application/problem+json")))]
pub async fn adjudicate(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
    ApiJson(b): ApiJson<AdjudicationRequest>,
) -> ApiResult<Json<store::LabelChange>> {
    check_id("episode id", &id)?;
    let label = parse_label(&b.label)?;
    let data = VerdictData {
        failure_cause: cause_of(&b.label, b.failure_cause),
        spans: b.spans.into_iter().map(Span::ordered).collect(),
    };
    let change = {
        let _gate = s.write_gate().await;
        s.store().adjudicate(&id, label, data, b.note, &caller.name).await
    };
    Ok(Json(s.count_label_result(change)?))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct AgreementQuery {
    /// The campaign's policy (required).
    policy: String,
}

/// Agreement in a campaign: per-labeler vote counts, pairwise Cohen's κ and Krippendorff's α
/// (nominal), from each labeler's latest vote per episode.
#[utoipa::path(get, path = "/v1/agreement", tag = "labels", params(AgreementQuery),
    responses((status = 200, description = "the agreement", body = Agreement),
              (status = 400, body = Problem, content_type = "application/problem+json")))]
pub async fn get_agreement(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<AgreementQuery>,
) -> ApiResult<Json<Agreement>> {
    check_name("policy", &q.policy)?;
    Ok(Json(s.store().agreement(&q.policy).await?))
}

/// A failure cause goes with a failure verdict only: on another verdict it is ignored (the page
/// may keep a cause selected while the labeler changes their mind).
fn cause_of(label: &str, cause: Option<String>) -> Option<String> {
    cause.filter(|_| label == "failure")
}
