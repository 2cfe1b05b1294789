//! Store subcommands: init, versions, episodes, label, history, snapshot, gc.

use super::{print_json, EpisodeFilterArgs, StoreArgs};
use anyhow::{Context, Result};
use store::{EpisodeFilter, Label, LabelUpdate};

pub async fn init(args: &StoreArgs) -> Result<()> {
    let store = args.open_or_create().await?;
    println!("store ready ({}), head version {}", store.describe(), store.head_version().await?);
    Ok(())
}

pub async fn versions(args: &StoreArgs, json: bool) -> Result<()> {
    let store = args.open().await?;
    let versions = store.versions().await?;
    if json {
        return print_json(&versions);
    }
    println!(
        "{:>7}  {:<15} {:>8} {:>6} {:>8}  {:<24} message",
        "version", "kind", "episodes", "added", "relabel", "created"
    );
    for v in versions {
        println!(
            "{:>7}  {:<15} {:>8} {:>6} {:>8}  {:<24} {}",
            v.version, v.kind, v.episode_count, v.episodes_added, v.labels_changed, v.created_at, v.message
        );
    }
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct EpisodesArgs {
    #[command(flatten)]
    pub filter: EpisodeFilterArgs,
    /// Only episodes whose id sorts after this one (the next page: pass the last id shown).
    #[arg(long)]
    pub after: Option<String>,
    /// At most this many episodes (a page, in id order).
    #[arg(long)]
    pub limit: Option<i64>,
    #[arg(long)]
    pub json: bool,
}

pub async fn episodes(args: &StoreArgs, a: EpisodesArgs) -> Result<()> {
    let store = args.open().await?;
    let label = a.filter.label()?;
    let f = a.filter;
    let filter = EpisodeFilter {
        version: f.version,
        policy: f.policy,
        checkpoint: f.checkpoint,
        task: f.task,
        label,
        tag: f.tag,
        after: a.after,
        limit: a.limit,
        ..Default::default()
    };
    let eps = store.episodes(&filter).await?;
    if a.json {
        return print_json(&eps);
    }
    println!(
        "{:<20} {:<28} {:>6}  {:<8} {:>3}  {:<24} task",
        "id", "policy/checkpoint", "steps", "label", "rev", "label source"
    );
    for e in &eps {
        println!(
            "{:<20} {:<28} {:>6}  {:<8} {:>3}  {:<24} {}",
            e.id,
            format!("{}/{}", e.policy, e.checkpoint),
            e.length,
            e.label.as_str(),
            e.label_revision,
            e.label_source,
            e.task.as_deref().unwrap_or("-")
        );
    }
    let s = eps.iter().filter(|e| e.label == Label::Success).count();
    let f = eps.iter().filter(|e| e.label == Label::Failure).count();
    println!("{} episodes: {s} success, {f} failure, {} unknown", eps.len(), eps.len() - s - f);
    if let (Some(n), Some(last)) = (a.limit, eps.last()) {
        if eps.len() as i64 == n {
            println!("next page: --after {}", last.id);
        }
    }
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct LabelArgs {
    pub episode: String,
    /// success | failure | unknown
    pub label: String,
    /// Refuse unless the episode's label is at this revision (optimistic concurrency).
    #[arg(long)]
    pub expect_revision: Option<i64>,
    #[arg(long)]
    pub note: Option<String>,
    #[arg(long, env = "USER", default_value = "cli")]
    pub actor: String,
    #[arg(long)]
    pub json: bool,
}

pub async fn label(args: &StoreArgs, a: LabelArgs) -> Result<()> {
    let store = args.open().await?;
    let label: Label = a.label.parse()?;
    let change = store
        .set_label(
            LabelUpdate {
                episode_id: a.episode.clone(),
                label,
                expect_revision: a.expect_revision,
                note: a.note,
            },
            &a.actor,
            "human",
        )
        .await?;
    if a.json {
        return print_json(&change);
    }
    println!(
        "{}: {} -> {} (revision {})",
        change.episode_id, change.old_label, change.label, change.revision
    );
    Ok(())
}

pub async fn history(args: &StoreArgs, episode: &str, json: bool) -> Result<()> {
    let store = args.open().await?;
    let events = store.label_history(episode).await?;
    if json {
        return print_json(&events);
    }
    for e in events {
        println!(
            "rev {:>3}  {:<24} {:<10} {:>8} -> {:<8} {:<24} {}",
            e.revision,
            e.created_at,
            e.actor,
            e.old_label.map(|l| l.as_str()).unwrap_or("-"),
            e.new_label.as_str(),
            e.source,
            e.note.unwrap_or_default()
        );
    }
    Ok(())
}

pub async fn snapshot(args: &StoreArgs, message: &str, actor: &str) -> Result<()> {
    let store = args.open().await?;
    let (c, created) =
        store.snapshot_labels_if_changed(actor, message).await.context("label snapshot failed")?;
    if created {
        println!("version {}: labels of {} episodes frozen", c.version, c.episodes);
    } else {
        println!("no label changed since version {}: no new version", c.version);
    }
    Ok(())
}

pub async fn gc(args: &StoreArgs, grace_seconds: u64, dry_run: bool, json: bool) -> Result<()> {
    let store = args.open().await?;
    let r = store.gc(grace_seconds, dry_run).await?;
    if json {
        return print_json(&r);
    }
    println!(
        "{} objects scanned, {} referenced, {} {}, {} unreferenced but younger than {grace_seconds}s kept, \
         {} kept for writers in flight",
        r.objects_scanned,
        r.referenced,
        r.deleted.len(),
        if dry_run { "would be deleted" } else { "deleted" },
        r.kept_recent,
        r.kept_pending
    );
    if !r.uploads_aborted.is_empty() || r.uploads_in_flight > 0 {
        println!(
            "{} incomplete multipart uploads {}, {} in flight left alone",
            r.uploads_aborted.len(),
            if dry_run { "would be aborted" } else { "aborted" },
            r.uploads_in_flight
        );
    }
    Ok(())
}
