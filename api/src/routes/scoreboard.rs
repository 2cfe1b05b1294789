//! Scoreboard: success per policy × checkpoint × task × run at a version with Wilson intervals,
//! each row against a baseline (Newcombe interval, rollouts to separate, unlabeled episodes that
//! could flip the answer), as JSON or CSV; and the evaluation runs themselves.

use super::*;
use store_compare::Scoreboards;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new().route("/v1/scoreboard", get(get_scoreboard)).route("/v1/runs", get(list_runs))
}

/// The scoreboard's formats.
#[derive(ToSchema)]
#[schema(rename_all = "lowercase")]
#[allow(dead_code)]
pub enum ScoreboardFormat {
    Json,
    Csv,
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ScoreboardQuery {
    /// The policy (required).
    policy: String,
    /// The version whose frozen labels count (default: the latest).
    version: Option<i64>,
    checkpoint: Option<String>,
    task: Option<String>,
    /// The baseline run's name (default `base`; `-` for episodes ingested without a run).
    baseline: Option<String>,
    /// The baseline's checkpoint (default: each row's own).
    baseline_checkpoint: Option<String>,
    /// `json` (default) or `csv`.
    #[param(value_type = Option<ScoreboardFormat>)]
    format: Option<String>,
}

/// The scoreboard of a policy, computed in SQL from a version's frozen labels.
#[utoipa::path(get, path = "/v1/scoreboard", tag = "scoreboard", params(ScoreboardQuery),
    responses((status = 200, description = "the scoreboard (JSON) or its rows as CSV",
               content((store_compare::Scoreboard = "application/json"), (String = "text/csv"))),
              (status = 404, description = "no such policy or version")))]
pub async fn get_scoreboard(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<ScoreboardQuery>,
) -> ApiResult<Response> {
    check_name("policy", &q.policy)?;
    for (what, v) in
        [("checkpoint", &q.checkpoint), ("task", &q.task), ("baseline_checkpoint", &q.baseline_checkpoint)]
    {
        if let Some(v) = v {
            check_name(what, v)?;
        }
    }
    if let Some(b) = &q.baseline {
        check_name("baseline", b)?;
    }
    let csv = match q.format.as_deref() {
        None | Some("json") => false,
        Some("csv") => true,
        Some(other) => return Err(ApiError::bad_request(format!("unknown format {other:?}: json or csv"))),
    };
    let req = store_compare::ScoreboardRequest {
        policy: q.policy,
        version: q.version,
        checkpoint: q.checkpoint,
        task: q.task,
        baseline: q.baseline,
        baseline_checkpoint: q.baseline_checkpoint,
    };
    let sb = s.store().scoreboard(&req).await?;
    if csv {
        let mut resp = Response::new(Body::from(sb.to_csv()));
        let h = resp.headers_mut();
        h.insert(header::CONTENT_TYPE, HeaderValue::from_static("text/csv; charset=utf-8"));
        let name = format!("attachment; filename=\"scoreboard-v{}.csv\"", sb.version);
        h.insert(
            header::CONTENT_DISPOSITION,
            HeaderValue::from_str(&name).map_err(|e| ApiError::internal(e.to_string()))?,
        );
        return Ok(resp);
    }
    Ok(Json(sb).into_response())
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct RunQuery {
    /// Only runs of this name.
    name: Option<String>,
}

/// The evaluation runs ingests have named.
#[utoipa::path(get, path = "/v1/runs", tag = "scoreboard", params(RunQuery),
    responses((status = 200, body = Vec<store::RunRecord>)))]
pub async fn list_runs(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<RunQuery>,
) -> ApiResult<Json<Vec<store::RunRecord>>> {
    if let Some(n) = &q.name {
        check_name("run", n)?;
    }
    Ok(Json(s.store().runs(q.name.as_deref()).await?))
}
