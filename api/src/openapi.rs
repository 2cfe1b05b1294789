//! The OpenAPI 3.1 document, generated from the handlers' annotations and the Rust types they
//! return (store records derive their schemas with the store's `openapi` feature), so it cannot
//! drift from the code. [`Contract`] adds what every route shares: the errors of the token, role,
//! size and rate layers and of the extractors, all as `application/problem+json`, and the
//! patterns of ids and names the handlers check. `ufops openapi --write api/openapi.json`
//! regenerates the committed copy (tests/openapi_contract.rs fails when it is stale).

use crate::error::Problem;
use crate::routes;
use crate::upload;
use axum::Json;
use utoipa::openapi::path::{Operation, ParameterBuilder, ParameterIn};
use utoipa::openapi::schema::{ObjectBuilder, Schema, Type};
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::openapi::Required;
use utoipa::openapi::{ContentBuilder, Ref, RefOr, ResponseBuilder};
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
        routes::list_events,
        routes::list_episodes, routes::episode_counts, routes::get_episode, routes::get_steps, routes::get_media,
        routes::get_frame,
        routes::put_label, routes::bulk_labels, routes::create_snapshot,
        routes::get_campaign, routes::put_campaign, routes::get_failure_causes, routes::put_failure_causes,
        routes::post_vote, routes::get_votes, routes::adjudication_queue, routes::adjudicate, routes::get_agreement,
        routes::list_layers, routes::layer_episodes, routes::episode_layers, routes::write_layer,
        routes::create_split, routes::list_splits, routes::get_split,
        routes::create_job, routes::list_jobs, routes::get_job, routes::cancel_job,
        routes::list_artifacts, routes::get_artifact, routes::artifact_file, routes::set_alias,
        routes::resolve_verifier, routes::resolve_verifier_file,
        routes::list_monitors, routes::get_monitor, routes::resolve_monitor,
        routes::create_export, routes::list_exports, routes::get_export, routes::export_file, routes::delete_export,
        routes::get_scoreboard, routes::list_runs,
        routes::get_compare, routes::list_policy_aliases, routes::move_policy_alias, routes::policy_alias_history,
        routes::get_episode_scores, routes::get_review_artifact, routes::put_review_artifact,
        routes::delete_review_artifact, routes::create_score_job,
        upload::ingest, routes::gc, routes::create_token, routes::list_tokens, routes::revoke_token,
        routes::create_webhook, routes::list_webhooks, routes::get_webhook, routes::delete_webhook,
        routes::list_dead_letters,
        routes::create_automation, routes::list_automations, routes::get_automation, routes::delete_automation,
    ),
    components(schemas(
        Problem, routes::EpisodeSort, routes::EpisodeOrder, routes::ScoreboardFormat, store_feed::TrainOnLabels,
        store_feed::ScoreOnPublish, store_feed::ScoreboardOnRunLabeled
    )),
    modifiers(&Bearer, &Contract),
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

/// An id a handler checks with `extract::check_id`.
pub const ID_PATTERN: &str = r"^[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}$";
/// A policy or checkpoint name in a URL (`extract::check_name`): printable, no '/', no
/// whitespace at either end.
pub const NAME_PATTERN: &str =
    r"^[^/\s\x00-\x1f\x7f-\x9f]([^/\x00-\x1f\x7f-\x9f]{0,198}[^/\s\x00-\x1f\x7f-\x9f])?$";

/// An arm of a comparison: `CHECKPOINT` or `CHECKPOINT/RUN` (a checkpoint name, then a run name).
pub const ARM_PATTERN: &str = concat!(
    r"^[^/\s\x00-\x1f\x7f-\x9f]([^/\x00-\x1f\x7f-\x9f]{0,198}[^/\s\x00-\x1f\x7f-\x9f])?",
    r"(/[^\s\x00-\x1f\x7f-\x9f]([^\x00-\x1f\x7f-\x9f]{0,198}[^\s\x00-\x1f\x7f-\x9f])?)?$"
);

/// A token or run name (`store::model::check_name`): printable, no whitespace at either end.
pub const TOKEN_NAME_PATTERN: &str =
    r"^[^\s\x00-\x1f\x7f-\x9f]([^\x00-\x1f\x7f-\x9f]{0,198}[^\s\x00-\x1f\x7f-\x9f])?$";
/// An artifact reference a handler resolves: an artifact id, or `POLICY/CHECKPOINT/KIND@ALIAS`.
pub const ARTIFACT_REF_PATTERN: &str = concat!(
    r"^(?:[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}|",
    r"[^/\s\x00-\x1f\x7f-\x9f](?:[^/\x00-\x1f\x7f-\x9f]{0,198}[^/\s\x00-\x1f\x7f-\x9f])?/",
    r"[^/\s\x00-\x1f\x7f-\x9f](?:[^/\x00-\x1f\x7f-\x9f]{0,198}[^/\s\x00-\x1f\x7f-\x9f])?/",
    r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}@[A-Za-z0-9_-][A-Za-z0-9._-]{0,127})$"
);
/// An ingest's run tags (`run_tags`): comma-separated run names (`store::model::check_name`,
/// no ','), at most 64; empty items are ignored.
pub const RUN_TAGS_PATTERN: &str = concat!(
    r"^,*(?:[^,\s\x00-\x1f\x7f-\x9f](?:[^,\x00-\x1f\x7f-\x9f]{0,198}[^,\s\x00-\x1f\x7f-\x9f])?",
    r"(?:,+[^,\s\x00-\x1f\x7f-\x9f](?:[^,\x00-\x1f\x7f-\x9f]{0,198}[^,\s\x00-\x1f\x7f-\x9f])?){0,63})?,*$"
);
/// A run's steering (`store::Steering`'s text form): `base`, `bon:N`, `cg:LAMBDA`, `flow:LAMBDA`.
pub const STEERING_PATTERN: &str = r"^(base|bon:[1-9][0-9]{0,8}|(cg|flow):[0-9]{1,6}(\.[0-9]{1,6})?)$";
/// `If-Match` of a label write: a label revision, quoted or not, weak or not.
pub const IF_MATCH_PATTERN: &str = r#"^(W/)?("[0-9]{1,18}"|[0-9]{1,18})$"#;

/// An `Idempotency-Key`: 1 to 255 visible ASCII characters.
pub const IDEMPOTENCY_KEY_PATTERN: &str = r"^[!-~]{1,255}$";

/// A webhook's URL (`store_feed::Webhooks::create_webhook`).
pub const WEBHOOK_URL_PATTERN: &str = r"^[hH][tT][tT][pP][sS]?://[^\s]{1,1990}$";

/// `kind` of `GET /v1/events`: event kinds separated by commas.
fn event_kinds_pattern() -> String {
    let one =
        store::EventKind::ALL.iter().map(|k| k.as_str().replace('.', r"\.")).collect::<Vec<_>>().join("|");
    format!("^(({one})(,({one}))*)?$")
}

/// Query parameters the handlers check as names (`extract::check_name`) or ids, per path.
const CHECKED_QUERY: &[(&str, &str, &str)] = &[
    ("/v1/scoreboard", "policy", NAME_PATTERN),
    ("/v1/scoreboard", "checkpoint", NAME_PATTERN),
    ("/v1/scoreboard", "task", NAME_PATTERN),
    ("/v1/scoreboard", "baseline", NAME_PATTERN),
    ("/v1/scoreboard", "baseline_checkpoint", NAME_PATTERN),
    ("/v1/runs", "name", NAME_PATTERN),
    ("/v1/compare", "policy", NAME_PATTERN),
    ("/v1/compare", "task", NAME_PATTERN),
    ("/v1/compare", "a", ARM_PATTERN),
    ("/v1/compare", "b", ARM_PATTERN),
    ("/v1/ingest", "policy", NAME_PATTERN),
    ("/v1/ingest", "checkpoint", NAME_PATTERN),
    ("/v1/ingest", "format", ID_PATTERN),
    ("/v1/ingest", "run", TOKEN_NAME_PATTERN),
    ("/v1/ingest", "run_artifact", TOKEN_NAME_PATTERN),
    ("/v1/ingest", "steering", STEERING_PATTERN),
    ("/v1/ingest", "run_tags", RUN_TAGS_PATTERN),
    ("/v1/adjudication", "policy", NAME_PATTERN),
    ("/v1/agreement", "policy", NAME_PATTERN),
    ("/v1/episodes/{id}/scores", "artifact", ID_PATTERN),
    ("/v1/review/artifacts/{policy}", "checkpoint", NAME_PATTERN),
    ("/v1/events", "policy", NAME_PATTERN),
    ("/v1/automations", "policy", NAME_PATTERN),
];

/// Request-body fields the handlers check, per component schema.
const CHECKED_FIELDS: &[(&str, &str, &str)] = &[
    ("SplitCreate", "policy", NAME_PATTERN),
    ("SplitCreate", "checkpoint", NAME_PATTERN),
    ("ExportCreate", "policy", NAME_PATTERN),
    ("ExportCreate", "checkpoint", NAME_PATTERN),
    ("ExportCreate", "task", NAME_PATTERN),
    ("ExportCreate", "tag", NAME_PATTERN),
    ("ExportCreate", "split", ID_PATTERN),
    ("ExportScore", "artifact", ARTIFACT_REF_PATTERN),
    ("JobCreate", "split_id", ID_PATTERN),
    ("BulkLabelItem", "episode_id", ID_PATTERN),
    ("TokenCreate", "name", TOKEN_NAME_PATTERN),
    ("ScoreJobCreate", "policy", NAME_PATTERN),
    ("ScoreJobCreate", "checkpoint", NAME_PATTERN),
    ("ScoreJobCreate", "artifact", ARTIFACT_REF_PATTERN),
    ("ReviewArtifactUpdate", "artifact", ARTIFACT_REF_PATTERN),
    ("PolicyAliasMoveBody", "to", ARM_PATTERN),
    ("WebhookCreate", "url", WEBHOOK_URL_PATTERN),
    ("WebhookCreate", "policy", NAME_PATTERN),
    ("AutomationCreate", "policy", NAME_PATTERN),
    // An automation's parameters, which the store checks (`store_feed::check_params`) as names.
    ("TrainOnLabels", "checkpoint", TOKEN_NAME_PATTERN),
    ("ScoreOnPublish", "checkpoint", TOKEN_NAME_PATTERN),
    ("ScoreboardOnRunLabeled", "run", TOKEN_NAME_PATTERN),
    ("ScoreboardOnRunLabeled", "baseline", TOKEN_NAME_PATTERN),
    // Array fields: the pattern goes on their items.
    ("FailureCauses", "causes", TOKEN_NAME_PATTERN),
];

/// Bounds of request-body numbers the store checks, per component schema: `(schema, field,
/// minimum, maximum)` (`store_feed::check_params` for an automation's `TrainOnLabels`).
const CHECKED_BOUNDS: &[(&str, &str, Option<f64>, Option<f64>)] = &[
    ("TrainOnLabels", "val_fraction", Some(0.0), Some(0.99)),
    ("TrainOnLabels", "obs_history", Some(1.0), None),
    ("TrainOnLabels", "chunk_len", Some(1.0), None),
    ("TrainOnLabels", "step_stride", Some(1.0), None),
];

/// A number of the document: an integer when it is one.
fn number(x: f64) -> utoipa::Number {
    if x.fract() == 0.0 {
        utoipa::Number::Int(x as isize)
    } else {
        utoipa::Number::Float(x)
    }
}

/// The object schemas of a component: itself, or each inline branch of a `oneOf`.
fn objects_mut(schema: &mut RefOr<Schema>) -> Vec<&mut utoipa::openapi::schema::Object> {
    match schema {
        RefOr::T(Schema::Object(o)) => vec![o],
        RefOr::T(Schema::OneOf(one)) => one
            .items
            .iter_mut()
            .filter_map(|item| match item {
                RefOr::T(Schema::Object(o)) => Some(o),
                _ => None,
            })
            .collect(),
        _ => vec![],
    }
}

/// Sets `pattern` on a string schema, on the string branch of a nullable one, or on the items
/// of an array of strings.
fn set_pattern(schema: &mut RefOr<Schema>, pattern: &str) {
    match schema {
        RefOr::T(Schema::Object(o)) => o.pattern = Some(pattern.to_string()),
        RefOr::T(Schema::Array(a)) => {
            if let utoipa::openapi::schema::ArrayItems::RefOrSchema(items) = &mut a.items {
                set_pattern(items, pattern);
            }
        }
        RefOr::T(Schema::OneOf(one)) => {
            for item in one.items.iter_mut() {
                if let RefOr::T(Schema::Object(o)) = item {
                    if o.schema_type != utoipa::openapi::schema::SchemaType::Type(Type::Null) {
                        o.pattern = Some(pattern.to_string());
                    }
                }
            }
        }
        _ => {}
    }
}

/// The shared part of the contract, added to every operation.
struct Contract;

fn problem(description: &str) -> RefOr<utoipa::openapi::Response> {
    RefOr::T(
        ResponseBuilder::new()
            .description(description)
            .content(
                "application/problem+json",
                ContentBuilder::new().schema(Some(Ref::from_schema_name("Problem"))).build(),
            )
            .build(),
    )
}

fn string_schema(pattern: &str) -> RefOr<Schema> {
    RefOr::T(Schema::Object(ObjectBuilder::new().schema_type(Type::String).pattern(Some(pattern)).build()))
}

impl Contract {
    #[allow(
        clippy::too_many_lines,
        reason = "one pass that writes every rule of an operation into the document"
    )]
    fn operation(op: &mut Operation, path: &str, public: bool, mutating: bool) {
        let params = op.parameters.get_or_insert_with(Vec::new);
        if mutating && !public {
            params.push(
                ParameterBuilder::new()
                    .name("Idempotency-Key")
                    .parameter_in(ParameterIn::Header)
                    .required(Required::False)
                    .description(Some(
                        "Makes a retry safe: a request sent again with the same key (per token) gets the first \
                         response (with `Idempotent-Replayed: true`) and does its work once. Kept 24 h. The same \
                         key with another method, path or body is a 422; while the first is still being served, \
                         a 409 with Retry-After.",
                    ))
                    .schema(Some(string_schema(IDEMPOTENCY_KEY_PATTERN)))
                    .build(),
            );
        }
        for p in params.iter_mut() {
            if p.parameter_in == ParameterIn::Query {
                if let Some((_, _, pattern)) =
                    CHECKED_QUERY.iter().find(|(at, name, _)| *at == path && *name == p.name)
                {
                    if let Some(s) = p.schema.as_mut() {
                        set_pattern(s, pattern);
                    }
                }
            }
            if p.parameter_in == ParameterIn::Query && path == "/v1/events" && p.name == "kind" {
                if let Some(s) = p.schema.as_mut() {
                    set_pattern(s, &event_kinds_pattern());
                }
            }
            if p.parameter_in == ParameterIn::Query && path == "/v1/layers/{name}" && p.name == "producer" {
                // A JSON object in the query, with at least one member (`store::producer_hash`):
                // a parameter with `content`, which utoipa's `Parameter` lacks; its extensions are
                // serialized inline, so `content` goes there and `schema` goes away.
                p.schema = None;
                let content = serde_json::json!({
                    "application/json": {"schema": {"type": "object", "minProperties": 1}}
                });
                p.extensions.get_or_insert_with(Default::default).insert("content".into(), content);
            }
            if p.parameter_in == ParameterIn::Header && p.name == "If-Match" {
                p.schema = Some(string_schema(IF_MATCH_PATTERN));
            }
        }
        let mut has_path = false;
        // A version that does not exist is a 404, like a path id.
        let names_version = params.iter().any(|p| p.name == "version");
        for p in params.iter_mut() {
            if p.parameter_in == ParameterIn::Path {
                has_path = true;
                let pattern = match p.name.as_str() {
                    "policy" | "checkpoint" => Some(NAME_PATTERN.to_string()),
                    "task" => Some(TOKEN_NAME_PATTERN.to_string()),
                    "kind_at_alias" => Some(format!(
                        "{}@{}",
                        ID_PATTERN.trim_end_matches('$'),
                        ID_PATTERN.trim_start_matches('^')
                    )),
                    "id" | "key" | "alias" | "name" | "camera" => Some(ID_PATTERN.to_string()),
                    _ => None,
                };
                if let Some(pattern) = pattern {
                    p.schema = Some(string_schema(&pattern));
                }
            }
        }
        let has_body = op.request_body.is_some();
        let responses = &mut op.responses.responses;
        // A status the route declares already keeps its description; the idempotency layer's
        // answers (`also`) come on top of what the route answers with the same status (a 422 for
        // a body of the wrong shape, a 409 of the store's state), so those declare both reasons.
        let mut declare =
            |status: &str, description: &str, also: bool| match responses.entry(status.to_string()) {
                std::collections::btree_map::Entry::Vacant(e) => {
                    e.insert(problem(description));
                }
                std::collections::btree_map::Entry::Occupied(mut e) => {
                    if let (true, RefOr::T(r)) = (also, e.get_mut()) {
                        if r.description.is_empty() {
                            r.description = description.to_string();
                        } else if !r.description.contains(description) {
                            r.description = format!("{}; or {description}", r.description);
                        }
                    }
                }
            };
        if !params_empty(&op.parameters) || has_body {
            declare("400", "a parameter or the body is invalid", false);
        }
        if has_path || names_version {
            declare("404", "not found", false);
        }
        if has_body {
            declare("413", "the body is larger than the server's limit", false);
            declare("415", "the body is not of the documented content type", false);
            declare("422", "the body does not have the documented shape", false);
        }
        if mutating && !public {
            declare(
                "409",
                "a request with this Idempotency-Key is still being served (`idempotency-key-in-use`, see \
                 Retry-After), or was done but its server stopped before answering (`idempotent-response-lost`, \
                 naming the change's event)",
                true,
            );
            declare(
                "422",
                "the Idempotency-Key was used for another request (`idempotency-key-reused`: another method, \
                 path or body)",
                true,
            );
        }
        if !public {
            declare("401", "no valid bearer token", false);
            declare(
                "429",
                "too many requests in flight for this token, or token checks; see Retry-After",
                false,
            );
            declare("503", "the catalog is busy; retry", false);
        }
        declare(
            "500",
            "a server-side failure (the problem names an incident id the server's log explains)",
            false,
        );
        // Every error is a problem document, whatever the annotation said.
        for (status, r) in responses.iter_mut() {
            if status.starts_with('4') || status.starts_with('5') {
                let description = match r {
                    RefOr::T(r) => r.description.clone(),
                    RefOr::Ref(_) => String::new(),
                };
                *r = problem(&description);
            }
        }
    }
}

fn params_empty(p: &Option<Vec<utoipa::openapi::path::Parameter>>) -> bool {
    p.as_ref().is_none_or(|v| v.is_empty())
}

impl Modify for Contract {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        for (path, item) in openapi.paths.paths.iter_mut() {
            let public = path == "/healthz";
            if let Some(op) = item.get.as_mut() {
                Contract::operation(op, path, public, false);
            }
            for op in [&mut item.put, &mut item.post, &mut item.delete, &mut item.patch].into_iter().flatten()
            {
                Contract::operation(op, path, public, true);
            }
        }
        if let Some(components) = openapi.components.as_mut() {
            if let Some(RefOr::T(Schema::Object(o))) = components.schemas.get_mut("UploadBytes") {
                o.min_length = Some(1);
            }
            for (schema, field, pattern) in CHECKED_FIELDS {
                for o in components.schemas.get_mut(*schema).map(objects_mut).unwrap_or_default() {
                    if let Some(prop) = o.properties.get_mut(*field) {
                        set_pattern(prop, pattern);
                    }
                }
            }
            for (schema, field, min, max) in CHECKED_BOUNDS {
                for o in components.schemas.get_mut(*schema).map(objects_mut).unwrap_or_default() {
                    if let Some(RefOr::T(Schema::Object(prop))) = o.properties.get_mut(*field) {
                        prop.minimum = min.map(number).or(prop.minimum.take());
                        prop.maximum = max.map(number).or(prop.maximum.take());
                    }
                }
            }
            // An automation's verifier kind is a training job's (`store_feed::check_params`).
            if let Some(RefOr::T(Schema::Object(o))) = components.schemas.get_mut("TrainOnLabels") {
                if let Some(kind) = o.properties.get_mut("kind") {
                    let description = match kind {
                        RefOr::T(Schema::Object(k)) => k.description.take(),
                        _ => None,
                    };
                    let mut r = Ref::from_schema_name("VerifierKind");
                    r.description = description.unwrap_or_default();
                    *kind = RefOr::Ref(r);
                }
            }
        }
    }
}

/// The OpenAPI document of this API.
pub fn openapi() -> utoipa::openapi::OpenApi {
    ApiDoc::openapi()
}

/// The document as `ufops openapi` prints it and `api/openapi.json` holds it.
pub fn openapi_json() -> String {
    let mut s = serde_json::to_string_pretty(&openapi()).expect("the document serializes");
    s.push('\n');
    s
}

/// This document.
#[utoipa::path(get, path = "/openapi.json", tag = "infra",
    responses((status = 200, description = "the OpenAPI document", body = Object)))]
pub(crate) async fn serve_openapi() -> Json<utoipa::openapi::OpenApi> {
    Json(openapi())
}
