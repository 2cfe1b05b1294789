//! `ufops view`: a rerun recording of a checkpoint's episodes, scored by a verifier if given.

use super::StoreArgs;
use anyhow::Result;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct ViewArgs {
    #[arg(long)]
    pub policy: String,
    #[arg(long)]
    pub checkpoint: String,
    #[arg(long)]
    pub split: Option<String>,
    #[arg(long)]
    pub version: Option<i64>,
    /// Score every step with this verifier (id or POLICY/CHECKPOINT/KIND@ALIAS).
    #[arg(long)]
    pub artifact: Option<String>,
    /// At most this many episodes (successes and failures alternately).
    #[arg(long)]
    pub episodes: Option<usize>,
    /// Observation dims drawn as the trajectory (e.g. pos, robot0_eef_pos, state[0,1]).
    #[arg(long, num_args = 1..)]
    pub position_keys: Vec<String>,
    /// Log stored image frames.
    #[arg(long)]
    pub images: bool,
    #[arg(long)]
    pub out: PathBuf,
}

/// Scores episodes with a trainer artifact (the reference forward pass).
pub struct ArtifactScorer(pub trainer::Artifact);

impl viewer::EpisodeScorer for ArtifactScorer {
    fn score_episode(&self, batch: &arrow::array::RecordBatch) -> Result<Vec<f32>, String> {
        trainer::score_steps(&self.0, batch).map_err(|e| format!("{e:#}"))
    }
}

/// Loads an artifact from the store into a temporary directory (sha256-checked).
pub async fn load_artifact(store: &store::Store, reference: &str) -> Result<(trainer::Artifact, tempfile::TempDir)> {
    let rec = store.resolve_artifact(reference).await?;
    let dir = tempfile::tempdir()?;
    store.download_artifact(&rec.id, dir.path()).await?;
    Ok((trainer::load_artifact(dir.path())?, dir))
}

pub async fn view(args: &StoreArgs, a: ViewArgs) -> Result<()> {
    let store = args.open().await?;
    let mut opts = viewer::ViewOptions::new(&a.policy, &a.checkpoint);
    opts.split_id = a.split;
    opts.version = a.version;
    opts.max_episodes = a.episodes;
    opts.position_keys = a.position_keys;
    opts.images = a.images;
    let scorer = match &a.artifact {
        Some(r) => Some(load_artifact(&store, r).await?),
        None => None,
    };
    let scorer = scorer.map(|(art, dir)| (ArtifactScorer(art), dir));
    let report = viewer::write_recording(
        &store,
        &opts,
        scorer.as_ref().map(|(s, _)| s as &dyn viewer::EpisodeScorer),
        &a.out,
    )
    .await?;
    println!(
        "{}: {} episodes ({} success, {} failure, {} unknown), {} steps",
        a.out.display(),
        report.episodes,
        report.success,
        report.failure,
        report.unknown,
        report.steps
    );
    if let (Some(s), Some(f)) = (report.mean_score_success, report.mean_score_failure) {
        println!("mean verifier score: successes {s:.3}, failures {f:.3}; largest gap at {:?}", report.max_separation);
    }
    Ok(())
}
