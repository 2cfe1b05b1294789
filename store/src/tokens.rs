//! API tokens: shown once at creation, stored as sha256 hashes, each with one role.

use crate::catalog::RowExt;
use crate::{now_rfc3339, Store, StoreError};
use serde::{Deserialize, Serialize};

/// Roles, each including the rights of the ones before it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    Viewer,
    Labeler,
    Trainer,
    Admin,
}

impl Role {
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Viewer => "viewer",
            Role::Labeler => "labeler",
            Role::Trainer => "trainer",
            Role::Admin => "admin",
        }
    }
}

impl std::str::FromStr for Role {
    type Err = StoreError;
    fn from_str(s: &str) -> Result<Self, StoreError> {
        match s {
            "viewer" => Ok(Role::Viewer),
            "labeler" => Ok(Role::Labeler),
            "trainer" => Ok(Role::Trainer),
            "admin" => Ok(Role::Admin),
            _ => Err(StoreError::invalid(format!("unknown role {s:?}: viewer, labeler, trainer or admin"))),
        }
    }
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize)]
pub struct TokenRecord {
    pub id: String,
    pub name: String,
    pub role: Role,
    pub created_at: String,
    pub revoked_at: Option<String>,
}

fn from_row(r: &sqlx::any::AnyRow) -> Result<TokenRecord, StoreError> {
    Ok(TokenRecord {
        id: r.s("id")?,
        name: r.s("name")?,
        role: r.s("role")?.parse()?,
        created_at: r.s("created_at")?,
        revoked_at: r.os("revoked_at")?,
    })
}

impl Store {
    /// Creates a token; returns the secret (shown once) and its record.
    pub async fn create_token(&self, name: &str, role: Role) -> Result<(String, TokenRecord), StoreError> {
        crate::model::check_name("token", name)?;
        let secret = format!("ufops_{}{}", uuid::Uuid::new_v4().simple(), uuid::Uuid::new_v4().simple());
        let id = format!("tok_{}", &uuid::Uuid::new_v4().simple().to_string()[..12]);
        let now = now_rfc3339();
        let mut tx = self.catalog().begin_write().await?;
        sqlx::query(
            "INSERT INTO tokens (id, name, role, token_hash, created_at) VALUES ($1, $2, $3, $4, $5)",
        )
        .bind(&id)
        .bind(name)
        .bind(role.as_str())
        .bind(crate::sha256_hex(secret.as_bytes()))
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        let event = token_changed(&id, "created", name, role);
        self.commit_with_events(tx, &[event]).await?;
        Ok((secret, TokenRecord { id, name: name.into(), role, created_at: now, revoked_at: None }))
    }

    /// The live token with this secret, if any.
    pub async fn verify_token(&self, secret: &str) -> Result<Option<TokenRecord>, StoreError> {
        let row = sqlx::query(
            "SELECT id, name, role, created_at, revoked_at FROM tokens WHERE token_hash = $1 AND revoked_at IS NULL",
        )
        .bind(crate::sha256_hex(secret.as_bytes()))
        .fetch_optional(&self.catalog().pool)
        .await?;
        row.as_ref().map(from_row).transpose()
    }

    pub async fn tokens(&self) -> Result<Vec<TokenRecord>, StoreError> {
        let rows =
            sqlx::query("SELECT id, name, role, created_at, revoked_at FROM tokens ORDER BY created_at")
                .fetch_all(&self.catalog().pool)
                .await?;
        rows.iter().map(from_row).collect()
    }

    pub async fn revoke_token(&self, id: &str) -> Result<(), StoreError> {
        let mut tx = self.catalog().begin_write().await?;
        let row = sqlx::query(
            "UPDATE tokens SET revoked_at = $1 WHERE id = $2 AND revoked_at IS NULL RETURNING name, role",
        )
        .bind(now_rfc3339())
        .bind(id)
        .fetch_optional(&mut *tx)
        .await?;
        let Some(row) = row else {
            return Err(StoreError::not_found("token", id));
        };
        let event = token_changed(id, "revoked", &row.s("name")?, row.s("role")?.parse()?);
        self.commit_with_events(tx, &[event]).await
    }
}

fn token_changed(id: &str, change: &str, name: &str, role: Role) -> crate::events::NewEvent {
    crate::events::NewEvent::new(
        crate::events::EventKind::TokenChanged,
        id,
        serde_json::json!({"change": change, "name": name, "role": role.as_str()}),
    )
}
