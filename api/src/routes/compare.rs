//! Comparison: the anytime-valid comparison of two arms of a policy's evaluation (per task and
//! pooled, with the gate's answer), and the policy aliases it guards (`prod` moves only on a
//! decided "not worse", the comparison kept as the move's evidence).

use super::*;
use store_compare::{Compare, PolicyAliases};

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/compare", get(get_compare))
        .route("/v1/policies/{policy}/aliases", get(list_policy_aliases))
        .route("/v1/policies/{policy}/aliases/{alias}", put(move_policy_alias.layer(need!(Role::Trainer))))
        .route("/v1/policies/{policy}/aliases/{alias}/history", get(policy_alias_history))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct CompareQuery {
    /// The policy (required).
    policy: String,
    /// The baseline arm: `CHECKPOINT` or `CHECKPOINT/RUN` (`-` for episodes without a run).
    a: String,
    /// The candidate arm: another arm than `a` (the same arm twice is a 400, a rule between two
    /// parameters that OpenAPI cannot state otherwise).
    b: String,
    /// The version whose labels count (default: the latest).
    version: Option<i64>,
    /// Only this task.
    task: Option<String>,
    /// The probability of ever making a false claim (default 0.05).
    #[param(exclusive_minimum = 0.0, exclusive_maximum = 1.0)]
    alpha: Option<f64>,
    /// δ in rate units (default 0): "worse" is worse by more than δ; δ > 0 allows "no practical
    /// difference" and "not worse".
    #[param(minimum = 0.0, exclusive_maximum = 1.0)]
    margin: Option<f64>,
    /// The difference the evaluation is planned to detect (bets sized for it).
    #[param(exclusive_minimum = 0.0, maximum = 1.0)]
    plan_effect: Option<f64>,
    /// The episode metadata field that pairs rollouts (default `pair_key`; empty: arrival order).
    pair_key: Option<String>,
    /// A metadata field with a progress score in [0, 1] to compare instead of labels.
    progress: Option<String>,
}

fn arm(what: &str, s: &str) -> ApiResult<store_compare::ArmSpec> {
    let spec: store_compare::ArmSpec =
        s.parse().map_err(|e: store::StoreError| ApiError::bad_request(format!("{what}: {e}")))?;
    check_name(what, &spec.checkpoint)?;
    Ok(spec)
}

/// Is B better than A yet? Decisions hold at every sample size however often anyone looks.
#[utoipa::path(get, path = "/v1/compare", tag = "scoreboard", params(CompareQuery),
    responses((status = 200, body = store_compare::Comparison),
              (status = 400, description = "a bad arm, alpha, margin or plan, or arm B is arm A"),
              (status = 404, description = "no such policy or version, or an arm without episodes")))]
pub async fn get_compare(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<CompareQuery>,
) -> ApiResult<Json<store_compare::Comparison>> {
    check_name("policy", &q.policy)?;
    if let Some(t) = &q.task {
        check_name("task", t)?;
    }
    let req = store_compare::CompareRequest {
        version: q.version,
        task: q.task,
        alpha: q.alpha.unwrap_or(0.05),
        margin: q.margin.unwrap_or(0.0),
        plan_effect: q.plan_effect,
        pair_key: q.pair_key,
        progress: q.progress,
        ..store_compare::CompareRequest::new(&q.policy, arm("a", &q.a)?, arm("b", &q.b)?)
    };
    Ok(Json(s.store().compare(&req).await?))
}

/// A policy's aliases with the evidence of their last move.
#[utoipa::path(get, path = "/v1/policies/{policy}/aliases", tag = "scoreboard",
    params(("policy" = String, Path)),
    responses((status = 200, body = Vec<store_compare::PolicyAlias>)))]
pub async fn list_policy_aliases(
    State(s): State<AppState>,
    ApiPath(policy): ApiPath<String>,
) -> ApiResult<Json<Vec<store_compare::PolicyAlias>>> {
    check_name("policy", &policy)?;
    Ok(Json(s.store().policy_aliases(&policy).await?))
}

/// Moving a policy alias.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PolicyAliasMoveBody {
    /// The new target: `CHECKPOINT` or `CHECKPOINT/RUN`.
    to: String,
    /// Protect the alias from now on (it then moves only on a decided comparison).
    #[serde(default)]
    protect: bool,
    alpha: Option<f64>,
    margin: Option<f64>,
    plan_effect: Option<f64>,
    pair_key: Option<String>,
    progress: Option<String>,
}

/// Points a policy alias at a checkpoint or run. A protected alias moves only when the
/// comparison of the new target against the current one has decided "not worse" on every task
/// (409 with the decision otherwise); the comparison is stored with the move.
#[utoipa::path(put, path = "/v1/policies/{policy}/aliases/{alias}", tag = "scoreboard",
    params(("policy" = String, Path), ("alias" = String, Path)),
    request_body = PolicyAliasMoveBody,
    responses((status = 200, body = store_compare::PolicyAlias),
              (status = 400, description = "a bad target or comparison setting"),
              (status = 404, description = "the target has no episodes"),
              (status = 409, description = "the alias is protected and the comparison has not decided \"not worse\""),
              (status = 403, description = "the token's role is below trainer")))]
pub async fn move_policy_alias(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath((policy, alias)): ApiPath<(String, String)>,
    ApiJson(b): ApiJson<PolicyAliasMoveBody>,
) -> ApiResult<Json<store_compare::PolicyAlias>> {
    caller.require(Role::Trainer)?;
    check_name("policy", &policy)?;
    check_id("alias", &alias)?;
    let mv = store_compare::MoveAlias {
        protect: b.protect.then_some(true),
        alpha: b.alpha.unwrap_or(0.05),
        margin: b.margin.unwrap_or(0.0),
        plan_effect: b.plan_effect,
        pair_key: b.pair_key,
        progress: b.progress,
        ..store_compare::MoveAlias::new(&policy, &alias, arm("to", &b.to)?, &caller.name)
    };
    Ok(Json(s.store().move_policy_alias(&mv).await?))
}

/// An alias's moves, oldest first, each with its evidence.
#[utoipa::path(get, path = "/v1/policies/{policy}/aliases/{alias}/history", tag = "scoreboard",
    params(("policy" = String, Path), ("alias" = String, Path)),
    responses((status = 200, body = Vec<store_compare::PolicyAliasMove>)))]
pub async fn policy_alias_history(
    State(s): State<AppState>,
    ApiPath((policy, alias)): ApiPath<(String, String)>,
) -> ApiResult<Json<Vec<store_compare::PolicyAliasMove>>> {
    check_name("policy", &policy)?;
    check_id("alias", &alias)?;
    Ok(Json(s.store().policy_alias_history(&policy, &alias).await?))
}
