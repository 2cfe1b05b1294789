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

/// Declaring an automation: a policy, a rule, and the rule's parameters.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AutomationCreate {
    policy: String,
    rule: String,
    #[serde(default)]
    params: Value,
}

/// The document states the body per rule, one `oneOf` branch each, so that `params` has the
/// rule's own schema (`TrainOnLabels` requires `min_labeled`; the other rules' parameters are
/// optional, `null` being none): the store checks them by the rule (`store_feed::check_params`),
/// and a derived schema could only call them an object. `openapi.rs` adds the policy's pattern.
impl utoipa::PartialSchema for AutomationCreate {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        let branch = |rule: store_feed::AutomationRule, params: &str, required: bool| {
            let params = serde_json::json!({"$ref": format!("#/components/schemas/{params}")});
            let (params, required) = if required {
                (params, serde_json::json!(["policy", "rule", "params"]))
            } else {
                (
                    serde_json::json!({"oneOf": [params, {"type": "null"}]}),
                    serde_json::json!(["policy", "rule"]),
                )
            };
            serde_json::json!({
                "type": "object",
                "required": required,
                "properties": {
                    "policy": {"type": "string"},
                    "rule": {"type": "string", "enum": [rule.as_str()]},
                    "params": params,
                },
                "additionalProperties": false,
            })
        };
        let schema = serde_json::json!({
            "description": "Declaring an automation: a policy, a rule, and the rule's parameters (`params`).",
            "oneOf": [
                branch(store_feed::AutomationRule::TrainOnLabels, "TrainOnLabels", true),
                branch(store_feed::AutomationRule::ScoreOnPublish, "ScoreOnPublish", false),
                branch(store_feed::AutomationRule::ScoreboardOnRunLabeled, "ScoreboardOnRunLabeled", false),
            ],
        });
        serde_json::from_value(schema).expect("the AutomationCreate schema is an OpenAPI schema")
    }
}

impl utoipa::ToSchema for AutomationCreate {}

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
