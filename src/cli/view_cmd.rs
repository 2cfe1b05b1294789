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
    /// Observation dims drawn as the trajectory (e.g. pos, robot0_eef_pos, `state[0,1]`).
    #[arg(long, num_args = 1..)]
    pub position_keys: Vec<String>,
    /// Leave out the image-column cameras (by default every camera is logged: image columns as
    /// one EncodedImage per step, videos as frame references into the embedded mp4).
    #[arg(long)]
    pub no_images: bool,
    /// Keep every N-th frame of image-column cameras (1: every frame).
    #[arg(long, default_value_t = 1)]
    pub image_stride: usize,
    /// Leave out the video cameras (no mp4 embedded).
    #[arg(long)]
    pub no_videos: bool,
    /// Image cameras are logged by default now; kept so older command lines still run.
    #[arg(long, hide = true)]
    pub images: bool,
    #[arg(long)]
    pub out: PathBuf,
}

pub async fn view(args: &StoreArgs, a: ViewArgs) -> Result<()> {
    let store = args.open().await?;
    let mut opts = viewer::ViewOptions::new(&a.policy, &a.checkpoint);
    opts.split_id = a.split;
    opts.version = a.version;
    opts.max_episodes = a.episodes;
    opts.position_keys = a.position_keys;
    opts.no_images = a.no_images;
    opts.image_stride = a.image_stride;
    opts.no_videos = a.no_videos;
    let scorer = match &a.artifact {
        Some(r) => Some(super::export_cmd::StoreVerifier::load(&store, r).await?.verifier),
        None => None,
    };
    let report =
        viewer::write_recording(&store, &opts, scorer.as_ref().map(|v| v as &dyn viewer::StepScorer), &a.out)
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
    if !report.cameras.is_empty() {
        println!(
            "cameras {}: {} image frames, {} video frame references into {} videos",
            report.cameras.join(", "),
            report.images,
            report.video_frames,
            report.videos
        );
    }
    if report.steered_episodes > 0 {
        println!(
            "{} steered episodes: their best-of-N candidates' score spread and chosen score under episodes/…/steering",
            report.steered_episodes
        );
    }
    if let (Some(s), Some(f)) = (report.mean_score_success, report.mean_score_failure) {
        println!(
            "mean verifier score: successes {s:.3}, failures {f:.3}; largest gap at {:?}",
            report.max_separation
        );
    }
    Ok(())
}
