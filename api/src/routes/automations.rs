//! Automations: rules declared per policy that queue jobs from the change feed (train a verifier
//! when a checkpoint has enough labels, score its review queue when one is published, snapshot a
//! run's scoreboard rows when its episodes are all labeled). Running them is `automations.rs` at
//! the crate root; what they decide is `store-feed`'s (`store-feed/src/automations.rs`).

use super::*;
use store_feed::Automations;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/automations", get(list_automations).post(create_automation.layer(need!(Role::Trainer))))
        .route(
            "/v1/automations/{id}",
            get(get_automation).delete(delete_automation.layer(need!(Role::Trainer))),
        )
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct AutomationCreate {
    policy: String,
    #[schema(value_type = store_feed::AutomationRule)]
    rule: String,
    /// The rule's parameters: `TrainOnLabels` (`min_labeled` is required), `ScoreOnPublish` or
    /// `ScoreboardOnRunLabeled`.
    #[serde(default)]
    #[schema(value_type = Object)]
    params: Value,
}

/// Declares an automation (trainer). It acts on the change feed from now on, queueing its jobs on
/// the job queue and recording each as an `automation.fired` event; see api/README.md.
#[utoipa::path(post, path = "/v1/automations", tag = "automations", request_body = AutomationCreate,
    responses((status = 201, body = store_feed::AutomationRecord),
              (status = 400, description = "an unknown rule or bad parameters", body = Problem, content_type = "application/problem+json"),
              (status = 403, description = "the token's role is below trainer")))]
pub async fn create_automation(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(b): ApiJson<AutomationCreate>,
) -> ApiResult<(StatusCode, Json<store_feed::AutomationRecord>)> {
    caller.require(Role::Trainer)?;
    check_name("policy", &b.policy)?;
    let rule: store_feed::AutomationRule = b.rule.parse()?;
    let a = s.store().create_automation(&b.policy, rule, &b.params, &caller.name).await?;
    Ok((StatusCode::CREATED, Json(a)))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct AutomationQuery {
    /// Only this policy's.
    policy: Option<String>,
}

/// Every automation, oldest first, with its cursor in the feed and how many jobs it queued.
#[utoipa::path(get, path = "/v1/automations", tag = "automations", params(AutomationQuery),
    responses((status = 200, body = Vec<store_feed::AutomationRecord>)))]
pub async fn list_automations(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<AutomationQuery>,
) -> ApiResult<Json<Vec<store_feed::AutomationRecord>>> {
    if let Some(p) = &q.policy {
        check_name("policy", p)?;
    }
    Ok(Json(s.store().automations(q.policy.as_deref()).await?))
}

/// One automation, with what it knows of each target it has seen (a checkpoint or a run: the
/// last change, what its verifier covers, its last job): why it fired, or did not.
#[utoipa::path(get, path = "/v1/automations/{id}", tag = "automations", params(("id" = String, Path,)),
    responses((status = 200, body = store_feed::AutomationRecord), (status = 404, description = "no such automation")))]
pub async fn get_automation(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<store_feed::AutomationRecord>> {
    check_id("automation id", &id)?;
    Ok(Json(s.store().automation(&id).await?))
}

/// Deletes an automation (trainer); the jobs it queued go on.
#[utoipa::path(delete, path = "/v1/automations/{id}", tag = "automations", params(("id" = String, Path,)),
    responses((status = 204, description = "deleted"), (status = 403, description = "the token's role is below trainer"),
              (status = 404, description = "no such automation")))]
pub async fn delete_automation(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<StatusCode> {
    caller.require(Role::Trainer)?;
    check_id("automation id", &id)?;
    s.store().delete_automation(&id, &caller.name).await?;
    Ok(StatusCode::NO_CONTENT)
}
