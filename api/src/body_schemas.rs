//! Schema markers for raw bodies: the OpenAPI document's binary types, named by the routes that
//! send or take bytes (`openapi.rs` only adds `UploadBytes`'s `minLength`). Kept apart from
//! `openapi.rs` so that the routes, which the document lists, do not import the document.

use utoipa::ToSchema;

/// A file's bytes (downloads and uploads).
#[derive(ToSchema)]
#[schema(value_type = String, format = Binary)]
#[allow(dead_code)]
pub(crate) struct FileBytes(Vec<u8>);

/// An uploaded file's bytes: at least one (the modifier sets `minLength`, which utoipa's
/// attribute cannot on a `value_type`).
#[derive(ToSchema)]
#[schema(value_type = String, format = Binary)]
#[allow(dead_code)]
pub(crate) struct UploadBytes(Vec<u8>);
