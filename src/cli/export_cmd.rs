//! `ufops export`: a version, split or filter of the store as a LeRobot v3.0 dataset or a
//! robomimic HDF5 file (the export crate), optionally curated by a verifier's episode scores; and
//! `ufops rank`: the selected episodes ordered by such a score (worst first), the list a team
//! reviews before deleting or relabeling demonstrations (Demo-SCORE-style curation).

use super::{print_json, EpisodeFilterArgs, StoreArgs};
use anyhow::{bail, Context, Result};
use std::io::IsTerminal;
use std::path::PathBuf;
use store_artifacts::Artifacts;

/// Which episodes `export` and `rank` take: the filters every episode-listing command shares,
/// a split, and the layers to carry.
#[derive(clap::Args, Debug)]
pub struct SelectionArgs {
    #[command(flatten)]
    pub filter: EpisodeFilterArgs,
    /// A split id: its episodes at its version (robomimic: mask/train and mask/valid).
    #[arg(long)]
    pub split: Option<String>,
    /// Layers to carry as observation columns (an encoder's features; see `ufops layers`):
    /// LeRobot `observation.<layer>`, robomimic `obs/<layer>`. Comma-separated.
    #[arg(long, value_delimiter = ',')]
    pub layers: Vec<String>,
}

impl SelectionArgs {
    fn selection(&self, score: Option<store::ScoreRange>) -> Result<store::Selection> {
        let f = &self.filter;
        Ok(store::Selection {
            version: f.version,
            split: self.split.clone(),
            policy: f.policy.clone(),
            checkpoint: f.checkpoint.clone(),
            task: f.task.clone(),
            label: f.label()?,
            tag: f.tag.clone(),
            score,
            layers: self.layers.clone(),
        })
    }
}

#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    /// The new dataset folder (lerobot, aloha) or .hdf5 file (robomimic); must not exist.
    pub out: PathBuf,
    /// lerobot (v3.0) | robomimic | aloha (one `episode_<i>.hdf5` per episode)
    #[arg(long)]
    pub format: String,
    #[command(flatten)]
    pub select: SelectionArgs,
    /// Keep only episodes this verifier artifact (id or POLICY/CHECKPOINT/KIND@ALIAS) scores in
    /// [--min-score, --max-score]; an episode's score is the mean of its steps' scores.
    #[arg(long)]
    pub score_artifact: Option<String>,
    #[arg(long, requires = "score_artifact")]
    pub min_score: Option<f64>,
    #[arg(long, requires = "score_artifact")]
    pub max_score: Option<f64>,
    #[arg(long)]
    pub json: bool,
}

/// A verifier artifact of the store with its id; it scores stored steps as
/// `verifier::StepScorer` (pass `&loaded.verifier`).
pub struct StoreVerifier {
    pub verifier: verifier::Verifier,
    /// The artifact's id (an alias resolved once, so everything names the same artifact).
    pub artifact: String,
}

impl StoreVerifier {
    /// Loads an artifact of the store (id or POLICY/CHECKPOINT/KIND@ALIAS).
    pub async fn load(store: &store::Store, reference: &str) -> Result<Self> {
        let rec = store.resolve_artifact(reference).await?;
        let tmp = tempfile::tempdir()?;
        store.download_artifact(&rec.id, tmp.path()).await?;
        let verifier = verifier::Verifier::load_dir(tmp.path())
            .with_context(|| format!("loading artifact {}", rec.id))?;
        Ok(StoreVerifier { verifier, artifact: rec.id })
    }
}

fn progress_bar(show: bool, len: usize, what: &str) -> Option<indicatif::ProgressBar> {
    (show && std::io::stderr().is_terminal()).then(|| {
        let b = indicatif::ProgressBar::new(len as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(&format!(
                "{{spinner}} [{{elapsed_precise}}] [{{bar:30}}] {{pos}}/{{len}} {what}"
            ))
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
        );
        b
    })
}

/// The progress callback the exports and the scoring of stored episodes take, moving `bar` (if any).
fn ticker(bar: &Option<indicatif::ProgressBar>) -> impl Fn(usize, usize) + Send + Sync + '_ {
    move |done, _total| {
        if let Some(b) = bar {
            b.set_position(done as u64);
        }
    }
}

pub async fn export(args: &StoreArgs, a: ExportArgs) -> Result<()> {
    let store = args.open().await?;
    let scorer = match &a.score_artifact {
        Some(r) => Some(StoreVerifier::load(&store, r).await?),
        None => None,
    };
    let range = scorer.as_ref().map(|s| store::ScoreRange {
        artifact: s.artifact.clone(),
        min: a.min_score,
        max: a.max_score,
    });
    let mut selected = store::select(&store, &a.select.selection(range)?).await?;
    if let Some(s) = &scorer {
        let bar = progress_bar(!a.json, selected.episodes.len(), "episodes scored");
        let tick = ticker(&bar);
        let r = verifier::stored::filter_by_score(&store, &mut selected, &s.verifier, Some(&tick)).await;
        if let Some(b) = &bar {
            b.finish_and_clear();
        }
        r?;
    }
    let bar = progress_bar(!a.json, selected.episodes.len(), "episodes");
    let tick = ticker(&bar);
    let progress: store::Progress<'_> = Some(&tick);
    let report = match a.format.as_str() {
        "lerobot" => ::export::lerobot::export(&store, &selected, &a.out, progress).await,
        "robomimic" => ::export::robomimic::export(&store, &selected, &a.out, progress).await,
        "aloha" => ::export::aloha::export(&store, &selected, &a.out, progress).await,
        other => bail!("--format {other:?}: expected lerobot, robomimic or aloha"),
    };
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    let report = report?;
    if a.json {
        let mut v = serde_json::to_value(&report)?;
        v["episodes_scored"] = serde_json::json!(selected.scored);
        return print_json(&v);
    }
    if let Some(n) = selected.scored {
        println!(
            "scored {n} episodes with {}: {} in range",
            scorer.as_ref().map(|s| s.artifact.as_str()).unwrap_or_default(),
            report.episodes
        );
    }
    println!(
        "exported {} episodes, {} frames of version {} as {} to {} ({:.1} MB) — labels: {} success, {} failure, {} unknown",
        report.episodes,
        report.frames,
        report.version,
        report.format,
        report.path.display(),
        report.bytes as f64 / 1e6,
        report.labels.success,
        report.labels.failure,
        report.labels.unknown
    );
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct RankArgs {
    /// The verifier artifact: id or POLICY/CHECKPOINT/KIND@ALIAS.
    #[arg(long)]
    pub artifact: String,
    #[command(flatten)]
    pub select: SelectionArgs,
    /// Print only the N lowest-scored episodes.
    #[arg(long)]
    pub worst: Option<usize>,
    #[arg(long)]
    pub json: bool,
}

/// `ufops rank`: every selected episode's score, lowest first (ties by id).
pub async fn rank(args: &StoreArgs, a: RankArgs) -> Result<()> {
    let store = args.open().await?;
    let v = StoreVerifier::load(&store, &a.artifact).await?;
    let selected = store::select(&store, &a.select.selection(None)?).await?;
    let bar = progress_bar(!a.json, selected.episodes.len(), "episodes scored");
    let tick = ticker(&bar);
    let scores = verifier::stored::score_episodes(&store, &selected.episodes, &v.verifier, Some(&tick)).await;
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    let scores = scores?;
    let mut rows: Vec<(&store::EpisodeRecord, f64)> =
        selected.episodes.iter().zip(scores).filter_map(|(e, s)| s.map(|s| (e, s))).collect();
    rows.sort_by(|a, b| a.1.total_cmp(&b.1).then_with(|| a.0.id.cmp(&b.0.id)));
    rows.truncate(a.worst.unwrap_or(usize::MAX));
    if a.json {
        let out: Vec<serde_json::Value> = rows
            .iter()
            .map(|(e, s)| {
                serde_json::json!({
                    "episode_id": e.id, "score": s, "label": e.label.as_str(), "policy": e.policy,
                    "checkpoint": e.checkpoint, "source_name": e.source_name, "source_index": e.source_index,
                })
            })
            .collect();
        return print_json(
            &serde_json::json!({ "artifact": v.artifact, "version": selected.version, "episodes": out }),
        );
    }
    println!("{:<40} {:>8}  {:<8} source", "episode", "score", "label");
    for (e, s) in rows {
        println!("{:<40} {:>8.4}  {:<8} {}#{}", e.id, s, e.label.as_str(), e.source_name, e.source_index);
    }
    Ok(())
}
