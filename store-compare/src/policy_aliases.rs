//! A policy's aliases (`prod`, `canary`): names for one of its checkpoints or one steered run of it,
//! which deployment scripts resolve. A protected alias is evidence-gated: it moves to a new target
//! only when [`crate::Compare::compare`] of the new target (B) against the current one (A) at the head
//! version has decided "not worse" on every task and pooled; the comparison is stored with the
//! move (in the alias and in the append-only `policy_alias_moves`), so anyone can recompute it at
//! the same version and get the same decision.

use crate::compare::{ArmSpec, Compare, CompareRequest, Comparison};
use serde::{Deserialize, Serialize};
use std::future::Future;
use store::sql::now_rfc3339;
use store::sql::RowExt;
use store::{Store, StoreError};

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PolicyAlias {
    pub policy: String,
    pub alias: String,
    /// `CHECKPOINT` or `CHECKPOINT/RUN`.
    pub target: String,
    pub protected: bool,
    /// The comparison that allowed the last move (none for a first or unprotected move).
    #[cfg_attr(feature = "openapi", schema(value_type = Option<Object>))]
    pub evidence: Option<Comparison>,
    pub actor: String,
    pub updated_at: String,
}

/// One move in an alias's history.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PolicyAliasMove {
    pub id: i64,
    pub from_target: Option<String>,
    pub to_target: String,
    #[cfg_attr(feature = "openapi", schema(value_type = Option<Object>))]
    pub evidence: Option<Comparison>,
    pub actor: String,
    pub created_at: String,
}

/// A request to point an alias at a target.
#[derive(Debug, Clone)]
pub struct MoveAlias {
    pub policy: String,
    pub alias: String,
    pub to: ArmSpec,
    /// Protect the alias from now on (`Some(false)` lifts protection — only allowed when it is not
    /// protected yet; `None` keeps it as it is).
    pub protect: Option<bool>,
    /// How to compare (policy, arms and version are filled in by the move).
    pub alpha: f64,
    pub margin: f64,
    pub plan_effect: Option<f64>,
    pub pair_key: Option<String>,
    pub progress: Option<String>,
    pub actor: String,
}

impl MoveAlias {
    pub fn new(policy: &str, alias: &str, to: ArmSpec, actor: &str) -> Self {
        MoveAlias {
            policy: policy.into(),
            alias: alias.into(),
            to,
            protect: None,
            alpha: 0.05,
            margin: 0.0,
            plan_effect: None,
            pair_key: None,
            progress: None,
            actor: actor.into(),
        }
    }
}

fn alias_from_row(r: &sqlx::any::AnyRow) -> Result<PolicyAlias, StoreError> {
    Ok(PolicyAlias {
        policy: r.s("policy")?,
        alias: r.s("alias")?,
        target: r.s("target")?,
        protected: r.i("protected")? != 0,
        evidence: r.os("evidence")?.map(|e| serde_json::from_str(&e)).transpose()?,
        actor: r.s("actor")?,
        updated_at: r.s("updated_at")?,
    })
}

const ALIAS_COLS: &str = "policy, alias, target, protected, evidence, actor, updated_at";

/// Policy aliases (`prod`, `candidate`) on a [`Store`]: moved only when the comparison that
/// the move names holds, with their history.
pub trait PolicyAliases {
    /// A policy's aliases, by name.
    fn policy_aliases(
        &self,
        policy: &str,
    ) -> impl Future<Output = Result<Vec<PolicyAlias>, StoreError>> + Send;

    fn policy_alias(
        &self,
        policy: &str,
        alias: &str,
    ) -> impl Future<Output = Result<PolicyAlias, StoreError>> + Send;

    /// An alias's moves, oldest first.
    fn policy_alias_history(
        &self,
        policy: &str,
        alias: &str,
    ) -> impl Future<Output = Result<Vec<PolicyAliasMove>, StoreError>> + Send;

    /// Points an alias at `req.to`. A protected alias that points elsewhere moves only when the
    /// comparison of the new target against the current one decides "not worse" on every task
    /// (else [`StoreError::Conflict`] naming the decision, and nothing changes).
    fn move_policy_alias(
        &self,
        req: &MoveAlias,
    ) -> impl Future<Output = Result<PolicyAlias, StoreError>> + Send;
}

impl PolicyAliases for Store {
    async fn policy_aliases(&self, policy: &str) -> Result<Vec<PolicyAlias>, StoreError> {
        let rows =
            sqlx::query(&format!("SELECT {ALIAS_COLS} FROM policy_aliases WHERE policy = $1 ORDER BY alias"))
                .bind(policy)
                .fetch_all(&self.catalog().pool)
                .await?;
        rows.iter().map(alias_from_row).collect()
    }

    async fn policy_alias(&self, policy: &str, alias: &str) -> Result<PolicyAlias, StoreError> {
        let row =
            sqlx::query(&format!("SELECT {ALIAS_COLS} FROM policy_aliases WHERE policy = $1 AND alias = $2"))
                .bind(policy)
                .bind(alias)
                .fetch_optional(&self.catalog().pool)
                .await?
                .ok_or_else(|| StoreError::not_found("policy alias", format!("{policy}@{alias}")))?;
        alias_from_row(&row)
    }

    async fn policy_alias_history(
        &self,
        policy: &str,
        alias: &str,
    ) -> Result<Vec<PolicyAliasMove>, StoreError> {
        let rows = sqlx::query(
            "SELECT id, from_target, to_target, evidence, actor, created_at FROM policy_alias_moves \
             WHERE policy = $1 AND alias = $2 ORDER BY id",
        )
        .bind(policy)
        .bind(alias)
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(PolicyAliasMove {
                    id: r.i("id")?,
                    from_target: r.os("from_target")?,
                    to_target: r.s("to_target")?,
                    evidence: r.os("evidence")?.map(|e| serde_json::from_str(&e)).transpose()?,
                    actor: r.s("actor")?,
                    created_at: r.s("created_at")?,
                })
            })
            .collect()
    }

    #[allow(
        clippy::too_many_lines,
        reason = "the alias move's checks and its comparison, in the transaction that moves it"
    )]
    async fn move_policy_alias(&self, req: &MoveAlias) -> Result<PolicyAlias, StoreError> {
        store::model::check_name("policy", &req.policy)?;
        store::model::check_name("alias", &req.alias)?;
        if req.alias.contains('/') || req.alias.contains('@') {
            return Err(StoreError::invalid(format!("alias {:?} may not contain '@' or '/'", req.alias)));
        }
        let current = match self.policy_alias(&req.policy, &req.alias).await {
            Ok(a) => Some(a),
            Err(StoreError::NotFound { .. }) => None,
            Err(e) => return Err(e),
        };
        let target = req.to.to_string();
        let protected_now = current.as_ref().is_some_and(|c| c.protected);
        if protected_now && req.protect == Some(false) {
            return Err(StoreError::invalid(format!(
                "alias {}@{} is protected; protection cannot be lifted",
                req.policy, req.alias
            )));
        }
        // The target must hold episodes of the policy (a typo must not become an alias).
        if !arm_exists(self, &req.policy, &req.to).await? {
            return Err(StoreError::not_found("episodes of arm", format!("{}/{}", req.policy, target)));
        }
        let evidence = match &current {
            Some(c) if c.protected && c.target != target => {
                let compare = CompareRequest {
                    alpha: req.alpha,
                    margin: req.margin,
                    plan_effect: req.plan_effect,
                    pair_key: req.pair_key.clone(),
                    progress: req.progress.clone(),
                    ..CompareRequest::new(&req.policy, c.target.parse()?, req.to.clone())
                };
                let cmp = self.compare(&compare).await?;
                if cmp.exit_code != 0 {
                    return Err(StoreError::Conflict(format!(
                        "alias {}@{} is protected: {} against {} is {} at version {} (pooled: {} after {} pairs, \
                         confidence sequence [{:+.3}, {:+.3}]); it moves only on a decided \"not worse\" on every task",
                        req.policy,
                        req.alias,
                        target,
                        c.target,
                        cmp.gate,
                        cmp.version,
                        cmp.pooled.decision,
                        cmp.pooled.pairs,
                        cmp.pooled.confidence_sequence.0,
                        cmp.pooled.confidence_sequence.1,
                    )));
                }
                Some(cmp)
            }
            _ => None,
        };
        let protected = req.protect.unwrap_or(protected_now);
        let evidence_json = evidence.as_ref().map(serde_json::to_string).transpose()?;
        let now = now_rfc3339();
        let mut tx = self.catalog().begin_write().await?;
        // Moved under our feet since we compared: refuse rather than overwrite (the caller retries).
        let row = sqlx::query("SELECT target FROM policy_aliases WHERE policy = $1 AND alias = $2")
            .bind(&req.policy)
            .bind(&req.alias)
            .fetch_optional(&mut *tx)
            .await?;
        let now_target = row.map(|r| r.s("target")).transpose()?;
        if now_target != current.as_ref().map(|c| c.target.clone()) {
            return Err(StoreError::Conflict(format!(
                "alias {}@{} moved while it was being compared; try again",
                req.policy, req.alias
            )));
        }
        sqlx::query(
            "INSERT INTO policy_aliases (policy, alias, target, protected, evidence, actor, updated_at) \
             VALUES ($1, $2, $3, $4, $5, $6, $7) ON CONFLICT (policy, alias) DO UPDATE SET \
             target = excluded.target, protected = excluded.protected, evidence = excluded.evidence, \
             actor = excluded.actor, updated_at = excluded.updated_at",
        )
        .bind(&req.policy)
        .bind(&req.alias)
        .bind(&target)
        .bind(i64::from(protected))
        .bind(evidence_json.clone())
        .bind(&req.actor)
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        sqlx::query(
            "INSERT INTO policy_alias_moves (policy, alias, from_target, to_target, evidence, actor, created_at) \
             VALUES ($1, $2, $3, $4, $5, $6, $7)",
        )
        .bind(&req.policy)
        .bind(&req.alias)
        .bind(current.as_ref().map(|c| c.target.clone()))
        .bind(&target)
        .bind(evidence_json)
        .bind(&req.actor)
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        let event = store::NewEvent::new(
            store::EventKind::AliasMoved,
            req.alias.clone(),
            serde_json::json!({
                "target": "policy",
                "to": target,
                "from": current.map(|c| c.target),
                "protected": protected,
                "gated": evidence.is_some(),
                "actor": req.actor,
            }),
        )
        .of(&req.policy, None);
        self.commit_with_events(tx, &[event]).await?;
        self.policy_alias(&req.policy, &req.alias).await
    }
}

/// Whether the policy has an episode in this arm (any version).
async fn arm_exists(store: &Store, policy: &str, arm: &ArmSpec) -> Result<bool, StoreError> {
    let row = match arm.run.as_deref() {
        Some(crate::NO_RUN) => sqlx::query(
            "SELECT 1 AS one FROM episodes WHERE policy = $1 AND checkpoint = $2 AND run_id IS NULL LIMIT 1",
        )
        .bind(policy)
        .bind(&arm.checkpoint)
        .fetch_optional(&store.catalog().pool)
        .await?,
        Some(run) => {
            sqlx::query(
                "SELECT 1 AS one FROM episodes e JOIN runs r ON r.id = e.run_id \
             WHERE e.policy = $1 AND e.checkpoint = $2 AND r.name = $3 LIMIT 1",
            )
            .bind(policy)
            .bind(&arm.checkpoint)
            .bind(run)
            .fetch_optional(&store.catalog().pool)
            .await?
        }
        None => {
            sqlx::query("SELECT 1 AS one FROM episodes WHERE policy = $1 AND checkpoint = $2 LIMIT 1")
                .bind(policy)
                .bind(&arm.checkpoint)
                .fetch_optional(&store.catalog().pool)
                .await?
        }
    };
    Ok(row.is_some())
}
