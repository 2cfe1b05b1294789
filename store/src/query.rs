//! Reads: versions, episodes (now or at any past version) and version diffs (steps: read.rs).

use crate::catalog::{bind_val, RowExt, Val};
use crate::spans::covers;
use crate::{Backend, Label, Store, StoreError};
use serde::{Deserialize, Serialize};

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct VersionInfo {
    pub version: i64,
    pub kind: String,
    pub message: String,
    pub actor: String,
    pub created_at: String,
    /// This version's labels file: the rows it changed (`labels_kind` "delta") or all of them
    /// ("full"). [`Store::labels_files`] lists the files that make up its labels.
    pub labels_path: String,
    pub labels_kind: String,
    /// A full labels file of this version written after it committed, if one was.
    pub labels_checkpoint: Option<String>,
    pub source_sha256: Option<String>,
    pub episodes_added: i64,
    pub episodes_removed: i64,
    pub labels_changed: i64,
    pub episode_count: i64,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
// Deserialize: clients turn the API's JSON records back into this one type (episodes_batch).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct EpisodeRecord {
    pub id: String,
    pub policy: String,
    pub checkpoint: String,
    pub task: Option<String>,
    pub source_sha256: String,
    pub source_name: String,
    pub source_index: i64,
    pub length: i64,
    pub tags: Vec<String>,
    pub metadata: serde_json::Value,
    pub data_file: String,
    pub row_group: i64,
    /// The episode's first row inside `row_group`, and its number of rows.
    pub row_offset: i64,
    pub row_count: i64,
    pub version_added: i64,
    pub label: Label,
    pub label_source: String,
    pub label_revision: i64,
    pub label_actor: String,
    pub label_updated_at: String,
    pub created_at: String,
    /// The evaluation run that produced it (`Store::run`), if its ingest named one.
    pub run_id: Option<String>,
    /// The first step a human took over (the steps' `intervention` flag); null when the source
    /// records no takeovers or none happened. The steps before it are the policy's own.
    #[serde(default)]
    pub first_intervention: Option<i64>,
    /// How many steps a human controlled; null when the source records no takeovers.
    #[serde(default)]
    pub intervention_steps: Option<i64>,
}

/// Filters for listing episodes; `version: None` means the current state (latest labels).
#[derive(Debug, Clone, Default)]
pub struct EpisodeFilter {
    pub version: Option<i64>,
    pub id: Option<String>,
    pub policy: Option<String>,
    pub checkpoint: Option<String>,
    pub task: Option<String>,
    pub label: Option<Label>,
    pub label_source: Option<String>,
    pub tag: Option<String>,
    /// Only episodes of these evaluation runs (`episodes.run_id`); empty: any.
    pub run_ids: Vec<String>,
    /// Only episodes whose id sorts after this one (cursor pagination).
    pub after: Option<String>,
    pub limit: Option<i64>,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct VersionDiff {
    pub from: i64,
    pub to: i64,
    pub episodes_added: Vec<String>,
    pub episodes_removed: Vec<String>,
    /// `(episode, label in from, label in to)`
    pub labels_changed: Vec<(String, Label, Label)>,
}

const VERSION_COLS: &str = "version, kind, message, actor, created_at, labels_path, labels_kind, \
    labels_checkpoint, source_sha256, episodes_added, episodes_removed, labels_changed, episode_count";

fn version_from_row(r: &sqlx::any::AnyRow) -> Result<VersionInfo, StoreError> {
    Ok(VersionInfo {
        version: r.i("version")?,
        kind: r.s("kind")?,
        message: r.s("message")?,
        actor: r.s("actor")?,
        created_at: r.s("created_at")?,
        labels_path: r.s("labels_path")?,
        labels_kind: r.s("labels_kind")?,
        labels_checkpoint: r.os("labels_checkpoint")?,
        source_sha256: r.os("source_sha256")?,
        episodes_added: r.i("episodes_added")?,
        episodes_removed: r.i("episodes_removed")?,
        labels_changed: r.i("labels_changed")?,
        episode_count: r.i("episode_count")?,
    })
}

/// The episode columns every episode listing selects (`e`: the episodes table); the label
/// columns and the FROM clause follow.
pub const EPISODE_SELECT: &str =
    "SELECT e.id, e.policy, e.checkpoint, e.task, e.source_sha256, e.source_name, e.source_index, \
     e.length, e.tags, e.metadata, e.data_file, e.row_group, COALESCE(e.row_offset, 0) AS row_offset, \
     COALESCE(e.row_count, e.length) AS row_count, e.version_added, e.created_at, e.run_id, \
     e.first_intervention, e.intervention_steps, ";

/// Binds `v` as the next parameter of a statement being built; its placeholder (`$n`).
pub fn push_arg(args: &mut Vec<Val>, v: Val) -> String {
    args.push(v);
    format!("${}", args.len())
}

/// The filter's conditions on the label columns of table alias `lab` (label, then source).
pub fn label_conds(filter: &EpisodeFilter, lab: &str, args: &mut Vec<Val>) -> Vec<String> {
    let mut conds = Vec::new();
    if let Some(l) = filter.label {
        conds.push(format!("{lab}.label = {}", push_arg(args, Val::S(l.as_str().into()))));
    }
    if let Some(s) = &filter.label_source {
        conds.push(format!("{lab}.label_source = {}", push_arg(args, Val::S(s.clone()))));
    }
    conds
}

/// The filter's conditions on the episode's own columns (`e`): id, policy, checkpoint, task, tag.
pub fn episode_conds(filter: &EpisodeFilter, args: &mut Vec<Val>) -> Result<Vec<String>, StoreError> {
    let mut conds = Vec::new();
    if let Some(id) = &filter.id {
        conds.push(format!("e.id = {}", push_arg(args, Val::S(id.clone()))));
    }
    if let Some(p) = &filter.policy {
        conds.push(format!("e.policy = {}", push_arg(args, Val::S(p.clone()))));
    }
    if let Some(c) = &filter.checkpoint {
        conds.push(format!("e.checkpoint = {}", push_arg(args, Val::S(c.clone()))));
    }
    if let Some(t) = &filter.task {
        conds.push(format!("e.task = {}", push_arg(args, Val::S(t.clone()))));
    }
    if let Some(t) = &filter.tag {
        conds.push(format!(
            "e.id IN (SELECT episode_id FROM episode_tags WHERE tag = {})",
            push_arg(args, Val::S(t.clone()))
        ));
    }
    if !filter.run_ids.is_empty() {
        let ids: Vec<String> = filter.run_ids.iter().map(|r| push_arg(args, Val::S(r.clone()))).collect();
        conds.push(format!("e.run_id IN ({})", ids.join(", ")));
    }
    Ok(conds)
}

/// Where [`Store::episodes`] reads the labels from, and how it orders and bounds a page there.
struct LabelSource {
    /// The label columns and the FROM clause (a LATERAL subquery is left open for its label
    /// conditions).
    from: String,
    /// A condition on the source itself (episodes now, or the version's labels).
    cond: Option<String>,
    /// The column that orders the page, and the columns the cursor bounds.
    order_col: &'static str,
    cursor_cols: &'static [&'static str],
    /// The alias of the table the label conditions name.
    label_alias: &'static str,
    /// Whether `from` ends in an open LATERAL subquery.
    lateral: bool,
}

impl Store {
    /// The latest committed version (0 for an empty store).
    pub async fn head_version(&self) -> Result<i64, StoreError> {
        let r = sqlx::query("SELECT version FROM store_head WHERE id = 1")
            .fetch_one(&self.catalog().pool)
            .await?;
        r.i("version")
    }

    pub async fn versions(&self) -> Result<Vec<VersionInfo>, StoreError> {
        let rows = sqlx::query(&format!("SELECT {VERSION_COLS} FROM versions ORDER BY version"))
            .fetch_all(&self.catalog().pool)
            .await?;
        rows.iter().map(version_from_row).collect()
    }

    pub async fn version(&self, version: i64) -> Result<VersionInfo, StoreError> {
        let row = sqlx::query(&format!("SELECT {VERSION_COLS} FROM versions WHERE version = $1"))
            .bind(version)
            .fetch_optional(&self.catalog().pool)
            .await?
            .ok_or_else(|| StoreError::not_found("version", version.to_string()))?;
        version_from_row(&row)
    }

    /// Lists episodes, now (`filter.version = None`) or as they were in a past version, in id
    /// order; `after` + `limit` page through them by keyset (store/README.md, "Catalog indexes and
    /// counts", has the query plans behind each shape).
    pub async fn episodes(&self, filter: &EpisodeFilter) -> Result<Vec<EpisodeRecord>, StoreError> {
        let (sql, args) = self.episodes_sql(filter).await?;
        let mut q = sqlx::query(&sql);
        for a in args {
            q = bind_val(q, a);
        }
        let rows = q.fetch_all(&self.catalog().pool).await?;
        rows.iter().map(episode_from_row).collect()
    }

    /// The statement [`Self::episodes`] runs for `filter`, and the values it binds.
    async fn episodes_sql(&self, filter: &EpisodeFilter) -> Result<(String, Vec<Val>), StoreError> {
        let mut args: Vec<Val> = Vec::new();
        let source = self.label_source(filter, &mut args).await?;
        let mut sql = format!("{EPISODE_SELECT}{}", source.from);
        let mut conds: Vec<String> = source.cond.into_iter().collect();
        // Label conditions go on the label source's table (inside its LATERAL subquery, if any).
        let mut on_labels = label_conds(filter, source.label_alias, &mut args);
        if source.lateral {
            for c in on_labels.drain(..) {
                sql.push_str(" AND ");
                sql.push_str(&c);
            }
            sql.push_str(" OFFSET 0) l");
        }
        conds.append(&mut on_labels);
        conds.extend(episode_conds(filter, &mut args)?);
        if let Some(a) = &filter.after {
            let p = push_arg(&mut args, Val::S(a.clone()));
            conds.extend(source.cursor_cols.iter().map(|c| format!("{c} > {p}")));
        }
        if !conds.is_empty() {
            sql.push_str(" WHERE ");
            sql.push_str(&conds.join(" AND "));
        }
        sql.push_str(&format!(" ORDER BY {}", source.order_col));
        if let Some(n) = filter.limit {
            sql.push_str(&format!(" LIMIT {}", push_arg(&mut args, Val::I(n.max(0)))));
        }
        Ok((sql, args))
    }

    /// Where [`Self::episodes`] takes the labels from: the episodes' current columns, or the
    /// frozen labels of `filter.version` (which must exist; its number is bound into `args`).
    async fn label_source(
        &self,
        filter: &EpisodeFilter,
        args: &mut Vec<Val>,
    ) -> Result<LabelSource, StoreError> {
        let filters_episode_columns = filter.id.is_some()
            || filter.policy.is_some()
            || filter.checkpoint.is_some()
            || !filter.run_ids.is_empty()
            || filter.task.is_some()
            || filter.tag.is_some();
        Ok(match filter.version {
            None => LabelSource {
                from: String::from(
                    "e.label AS label, e.label_source AS label_source, e.label_revision AS label_revision, \
                     e.label_actor AS label_actor, e.label_updated_at AS label_updated_at FROM episodes e",
                ),
                cond: Some("e.version_removed IS NULL".into()),
                order_col: "e.id",
                cursor_cols: &["e.id"],
                label_alias: "e",
                lateral: false,
            },
            // Filters on the episode's own columns: walk their index in id order and look each
            // episode's frozen label up. Postgres would rather merge-join the whole version's
            // labels (hundreds of ms at a million); a LATERAL subquery behind `OFFSET 0` keeps
            // it to lookups.
            Some(v) if filters_episode_columns => {
                self.version(v).await?;
                let p = push_arg(args, Val::I(v));
                match self.backend() {
                    Backend::Sqlite => LabelSource {
                        from: format!(
                            "l.label AS label, l.label_source AS label_source, l.revision AS label_revision, \
                             ev.actor AS label_actor, ev.created_at AS label_updated_at FROM episodes e \
                             JOIN version_labels l ON l.episode_id = e.id AND {} \
                             JOIN label_events ev ON ev.episode_id = e.id AND ev.revision = l.revision",
                            covers("l", &p)
                        ),
                        cond: None,
                        order_col: "e.id",
                        cursor_cols: &["e.id"],
                        label_alias: "l",
                        lateral: false,
                    },
                    Backend::Postgres => LabelSource {
                        from: format!(
                            "l.label AS label, l.label_source AS label_source, l.revision AS label_revision, \
                             l.actor AS label_actor, l.created_at AS label_updated_at FROM episodes e \
                             CROSS JOIN LATERAL (SELECT v.label, v.label_source, v.revision, ev.actor, ev.created_at \
                             FROM version_labels v JOIN label_events ev ON ev.episode_id = v.episode_id \
                             AND ev.revision = v.revision WHERE v.episode_id = e.id AND {}",
                            covers("v", &p)
                        ),
                        cond: None,
                        order_col: "e.id",
                        cursor_cols: &["e.id"],
                        label_alias: "v",
                        lateral: true,
                    },
                }
            }
            // Otherwise walk the version's labels in episode order (`version_labels`' key). The
            // cursor bounds every joined side: Postgres does not carry an inequality across a
            // join, and its merge joins would start from the first episode. On Postgres the
            // label's event is a LATERAL lookup instead: joined, its cursor bound counted a
            // third time in the row estimate, which fell under the page's LIMIT past the middle
            // of the ids, and the planner hash-joined the rest of the version and sorted it
            // (0.2-0.4 s a page at a million episodes, against 5 ms).
            Some(v) => {
                self.version(v).await?;
                let p = push_arg(args, Val::I(v));
                let (event, cursor_cols): (&str, &'static [&'static str]) = match self.backend() {
                    Backend::Sqlite => (
                        "JOIN label_events ev ON ev.episode_id = l.episode_id AND ev.revision = l.revision",
                        &["l.episode_id", "e.id", "ev.episode_id"],
                    ),
                    Backend::Postgres => (
                        "CROSS JOIN LATERAL (SELECT x.actor, x.created_at FROM label_events x \
                         WHERE x.episode_id = l.episode_id AND x.revision = l.revision OFFSET 0) ev",
                        &["l.episode_id", "e.id"],
                    ),
                };
                LabelSource {
                    from: format!(
                        "l.label AS label, l.label_source AS label_source, l.revision AS label_revision, \
                         ev.actor AS label_actor, ev.created_at AS label_updated_at FROM version_labels l \
                         JOIN episodes e ON e.id = l.episode_id {event}"
                    ),
                    cond: Some(covers("l", &p)),
                    order_col: "l.episode_id",
                    cursor_cols,
                    label_alias: "l",
                    lateral: false,
                }
            }
        })
    }

    /// One episode, now or at a past version.
    pub async fn episode(&self, id: &str, version: Option<i64>) -> Result<EpisodeRecord, StoreError> {
        let filter = EpisodeFilter { version, id: Some(id.to_string()), ..Default::default() };
        self.episodes(&filter).await?.pop().ok_or_else(|| StoreError::not_found("episode", id))
    }

    pub async fn policies(&self) -> Result<Vec<String>, StoreError> {
        let rows =
            sqlx::query("SELECT name FROM policies ORDER BY name").fetch_all(&self.catalog().pool).await?;
        rows.iter().map(|r| r.s("name")).collect()
    }

    /// `(policy, checkpoint)` pairs.
    pub async fn checkpoints(&self, policy: Option<&str>) -> Result<Vec<(String, String)>, StoreError> {
        let rows = sqlx::query(
            "SELECT policy, name FROM checkpoints WHERE ($1 = '' OR policy = $1) ORDER BY policy, name",
        )
        .bind(policy.unwrap_or(""))
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter().map(|r| Ok((r.s("policy")?, r.s("name")?))).collect()
    }

    pub async fn tasks(&self) -> Result<Vec<String>, StoreError> {
        let rows =
            sqlx::query("SELECT name FROM tasks ORDER BY name").fetch_all(&self.catalog().pool).await?;
        rows.iter().map(|r| r.s("name")).collect()
    }

    /// Episodes added/removed and labels changed between two versions.
    pub async fn diff(&self, from: i64, to: i64) -> Result<VersionDiff, StoreError> {
        let a = self.episodes(&EpisodeFilter { version: Some(from), ..Default::default() }).await?;
        let b = self.episodes(&EpisodeFilter { version: Some(to), ..Default::default() }).await?;
        let am: std::collections::HashMap<&str, Label> = a.iter().map(|e| (e.id.as_str(), e.label)).collect();
        let bm: std::collections::HashMap<&str, Label> = b.iter().map(|e| (e.id.as_str(), e.label)).collect();
        let mut d = VersionDiff {
            from,
            to,
            episodes_added: vec![],
            episodes_removed: vec![],
            labels_changed: vec![],
        };
        for e in &b {
            match am.get(e.id.as_str()) {
                None => d.episodes_added.push(e.id.clone()),
                Some(old) if *old != e.label => d.labels_changed.push((e.id.clone(), *old, e.label)),
                _ => {}
            }
        }
        d.episodes_removed =
            a.iter().filter(|e| !bm.contains_key(e.id.as_str())).map(|e| e.id.clone()).collect();
        Ok(d)
    }
}

pub fn episode_from_row(r: &sqlx::any::AnyRow) -> Result<EpisodeRecord, StoreError> {
    Ok(EpisodeRecord {
        id: r.s("id")?,
        policy: r.s("policy")?,
        checkpoint: r.s("checkpoint")?,
        task: r.os("task")?,
        source_sha256: r.s("source_sha256")?,
        source_name: r.s("source_name")?,
        source_index: r.i("source_index")?,
        length: r.i("length")?,
        tags: serde_json::from_str(&r.s("tags")?)?,
        metadata: serde_json::from_str(&r.s("metadata")?)?,
        data_file: r.s("data_file")?,
        row_group: r.i("row_group")?,
        row_offset: r.i("row_offset")?,
        row_count: r.i("row_count")?,
        version_added: r.i("version_added")?,
        label: r.s("label")?.parse()?,
        label_source: r.s("label_source")?,
        label_revision: r.i("label_revision")?,
        label_actor: r.s("label_actor")?,
        label_updated_at: r.s("label_updated_at")?,
        created_at: r.s("created_at")?,
        run_id: r.os("run_id")?,
        first_intervention: r.oi("first_intervention")?,
        intervention_steps: r.oi("intervention_steps")?,
    })
}
