//! The OpenAPI 3.1 document, generated from the handlers' annotations.

use crate::error::Problem;
use crate::routes;
use crate::upload;
use axum::Json;
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi};

#[derive(OpenApi)]
#[openapi(
    info(title = "ufops API", description = "Rollouts, labels, splits, training jobs and verifier artifacts. \
        Every endpoint except /healthz needs `Authorization: Bearer <token>`; roles viewer < labeler < trainer < admin \
        gate writes. Errors are application/problem+json."),
    paths(
        routes::healthz, routes::metrics, serve_openapi,
        routes::list_policies, routes::list_checkpoints, routes::list_tasks,
        routes::list_versions, routes::get_version, routes::diff_versions,
        routes::list_episodes, routes::episode_counts, routes::get_episode, routes::get_steps, routes::get_media,
        routes::put_label, routes::bulk_labels, routes::create_snapshot,
        routes::create_split, routes::list_splits, routes::get_split,
        routes::create_job, routes::list_jobs, routes::get_job, routes::cancel_job,
        routes::list_artifacts, routes::get_artifact, routes::artifact_file, routes::set_alias,
        routes::resolve_verifier, routes::resolve_verifier_file,
        routes::create_export, routes::list_exports, routes::get_export, routes::export_file, routes::delete_export,
        routes::get_scoreboard, routes::list_runs,
        routes::get_episode_scores, routes::get_review_artifact, routes::put_review_artifact,
        routes::delete_review_artifact, routes::create_score_job,
        upload::ingest, routes::gc, routes::create_token, routes::list_tokens, routes::revoke_token,
    ),
    components(schemas(Problem)),
    modifiers(&Bearer),
    security(("bearer" = [])),
)]
struct ApiDoc;

struct Bearer;

impl Modify for Bearer {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
        );
    }
}

/// The OpenAPI document of this API.
pub fn openapi() -> utoipa::openapi::OpenApi {
    ApiDoc::openapi()
}

/// This document.
#[utoipa::path(get, path = "/openapi.json", tag = "infra",
    responses((status = 200, description = "the OpenAPI document", body = Object), (status = 401, body = Problem)))]
pub(crate) async fn serve_openapi() -> Json<utoipa::openapi::OpenApi> {
    Json(openapi())
}
