//! Monitors: failure alarms calibrated on a verifier artifact's scores (`ufops monitor
//! calibrate`), with their held-out evaluation, and resolution of a checkpoint's monitor alias
//! for the robot (the record is what `steer::Monitor` and `ufops.Monitor` load).

use super::*;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/monitors", get(list_monitors))
        .route("/v1/monitors/{id}", get(get_monitor))
        .route("/v1/policies/{policy}/checkpoints/{checkpoint}/monitors/{alias}", get(resolve_monitor))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct MonitorQuery {
    policy: Option<String>,
    checkpoint: Option<String>,
    /// The verifier artifact the monitors threshold.
    artifact: Option<String>,
}

/// Monitors, oldest first, optionally filtered.
#[utoipa::path(get, path = "/v1/monitors", tag = "monitors", params(MonitorQuery),
    responses((status = 200, body = Vec<store_artifacts::MonitorEntry>)))]
pub async fn list_monitors(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<MonitorQuery>,
) -> ApiResult<Json<Vec<store_artifacts::MonitorEntry>>> {
    Ok(Json(s.store().monitors(q.policy.as_deref(), q.checkpoint.as_deref(), q.artifact.as_deref()).await?))
}

/// A monitor by id.
#[utoipa::path(get, path = "/v1/monitors/{id}", tag = "monitors", params(("id" = String, Path)),
    responses((status = 200, body = store_artifacts::MonitorEntry), (status = 404, description = "no such monitor")))]
pub async fn get_monitor(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<store_artifacts::MonitorEntry>> {
    check_id("monitor id", &id)?;
    Ok(Json(s.store().monitor(&id).await?))
}

/// The monitor an alias of a checkpoint points at (`latest`: the last calibrated).
#[utoipa::path(get, path = "/v1/policies/{policy}/checkpoints/{checkpoint}/monitors/{alias}", tag = "monitors",
    params(("policy" = String, Path), ("checkpoint" = String, Path), ("alias" = String, Path)),
    responses((status = 200, body = store_artifacts::MonitorEntry), (status = 404, description = "no monitor has that alias")))]
pub async fn resolve_monitor(
    State(s): State<AppState>,
    ApiPath((policy, checkpoint, alias)): ApiPath<(String, String, String)>,
) -> ApiResult<Json<store_artifacts::MonitorEntry>> {
    check_name("policy", &policy)?;
    check_name("checkpoint", &checkpoint)?;
    check_id("alias", &alias)?;
    Ok(Json(s.store().resolve_monitor(&format!("{policy}/{checkpoint}@{alias}")).await?))
}
