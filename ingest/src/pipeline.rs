//! The async glue: one ingest = one store version, all or nothing.
//!
//! The format reader runs on a blocking thread and pushes into a bounded channel (at most
//! [`CHANNEL_DEPTH`] episodes and [`MemoryBudget::in_flight_bytes`] in flight); the source's
//! sha256 is computed on a second blocking thread reading the file itself at the same time. The
//! store's `IngestWriter` encodes episodes as they come; until the hash (the episode ids' prefix)
//! is known it holds at most [`MemoryBudget::unhashed_bytes`] of encoded steps, then the reader
//! waits for the hash. Memory is therefore bounded by an episode and the budgets, never by the
//! source. Any error aborts the writer, so the store stays exactly as it was.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use arrow::array::Array as _;
use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};

use crate::error::{IngestError, Result};
use crate::model::{EpisodeInput, ExtraColumn, Label, MediaFile, SourceInput};
use crate::options::{Format, IngestOptions, MemoryBudget, ReadOptions};
use crate::sink::{EpisodeSink, SourceMeta};

/// Episodes (or media files) buffered between the reader thread and the store writer.
pub const CHANNEL_DEPTH: usize = 4;

/// How many of one ingest's episodes got each label (the catalog's running counts per version
/// are `store::LabelCounts`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct LabelTally {
    pub success: usize,
    pub failure: usize,
    pub unknown: usize,
}

/// What one `ufops ingest` did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct IngestReport {
    pub path: PathBuf,
    pub format: String,
    pub sha256: String,
    /// The new version, or the version that already holds this source (`already_ingested`).
    pub version: i64,
    /// True when the same content was ingested before: nothing was written.
    pub already_ingested: bool,
    pub episodes: usize,
    pub steps: u64,
    pub labels: LabelTally,
    /// Size of the source (file, or all files of the folder).
    pub bytes: u64,
    pub media_files: usize,
    /// Things worth telling the user (e.g. episodes left out by `--recover`).
    pub notes: Vec<String>,
}

impl std::fmt::Display for IngestReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.already_ingested {
            return write!(
                f,
                "{} (sha256 {}) is already in the store: version {} holds it; nothing to do",
                self.path.display(),
                &self.sha256[..12.min(self.sha256.len())],
                self.version
            );
        }
        write!(
            f,
            "ingested {} ({}, {:.1} MB) as version {}: {} episodes, {} steps, labels: {} success / {} failure / {} unknown",
            self.path.display(),
            self.format,
            self.bytes as f64 / 1e6,
            self.version,
            self.episodes,
            self.steps,
            self.labels.success,
            self.labels.failure,
            self.labels.unknown
        )?;
        if self.media_files > 0 {
            write!(f, ", {} media files", self.media_files)?;
        }
        for n in &self.notes {
            write!(f, "\nwarning: {n}")?;
        }
        Ok(())
    }
}

enum Msg {
    Source(SourceMeta),
    Media(MediaFile),
    /// An episode and its share of the in-flight budget, returned once it is encoded.
    Episode(Box<(EpisodeInput, Vec<ExtraColumn>)>, OwnedSemaphorePermit),
}

/// The reader's end: a bounded channel plus a byte budget, a semaphore of KiB permits (an
/// episode larger than the whole budget takes all of it, so it passes alone).
struct ChannelSink {
    tx: mpsc::Sender<Msg>,
    in_flight: Arc<Semaphore>,
    budget_kib: u32,
    runtime: tokio::runtime::Handle,
}

impl ChannelSink {
    fn send(&self, m: Msg) -> Result<()> {
        self.tx.blocking_send(m).map_err(|_| IngestError::Cancelled)
    }
}

impl EpisodeSink for ChannelSink {
    fn source(&mut self, meta: SourceMeta) -> Result<()> {
        self.send(Msg::Source(meta))
    }
    fn media(&mut self, file: MediaFile) -> Result<()> {
        self.send(Msg::Media(file))
    }
    fn episode_with_extras(&mut self, episode: EpisodeInput, extras: Vec<ExtraColumn>) -> Result<()> {
        let extra_bytes: usize = extras.iter().map(|x| x.values.get_array_memory_size()).sum();
        let kib = ((approx_bytes(&episode) + extra_bytes) / 1024 + 1).min(self.budget_kib as usize) as u32;
        // Blocks this (blocking-pool) thread until enough earlier episodes were encoded; fails
        // once the writer's side gave up (the semaphore is closed).
        let permit = self
            .runtime
            .block_on(self.in_flight.clone().acquire_many_owned(kib))
            .map_err(|_| IngestError::Cancelled)?;
        self.send(Msg::Episode(Box::new((episode, extras)), permit))
    }
}

/// Heap bytes of an episode's step data (what the in-flight budget counts).
fn approx_bytes(ep: &EpisodeInput) -> usize {
    let floats = ep.observations.iter().map(|o| o.values.len()).sum::<usize>()
        + ep.action.values.len()
        + ep.reward.len()
        + ep.action_chunk.as_ref().map_or(0, |c| c.values.len());
    let images: usize = ep.images.iter().flat_map(|im| im.png_frames.iter().map(|f| f.len() + 24)).sum();
    let media: usize = ep.media.iter().map(|m| m.timestamps.len() * 8).sum();
    floats * 4 + ep.timestamps.len() * 8 + ep.done.len() + images + media
}

/// The writer's side of the channel: closing it makes a reader waiting on the channel or on the
/// budget stop with [`IngestError::Cancelled`].
struct Feed {
    rx: mpsc::Receiver<Msg>,
    in_flight: Arc<Semaphore>,
}

impl Feed {
    fn close(&mut self) {
        self.rx.close();
        self.in_flight.close();
    }
}

fn join_err(e: tokio::task::JoinError) -> IngestError {
    if e.is_panic() {
        IngestError::Usage(format!("internal error: a reader thread panicked: {e}"))
    } else {
        IngestError::Cancelled
    }
}

struct Progress {
    bar: Option<indicatif::ProgressBar>,
}

impl Progress {
    fn new(enabled: bool, total: u64) -> Self {
        if !enabled || !std::io::stderr().is_terminal() {
            return Progress { bar: None };
        }
        let bar = indicatif::ProgressBar::new(total.max(1));
        let style = indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] [{bar:30}] {bytes}/{total_bytes} ({bytes_per_sec}) {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> ");
        bar.set_style(style);
        bar.set_draw_target(indicatif::ProgressDrawTarget::stderr());
        Progress { bar: Some(bar) }
    }
    fn update(&self, bytes: u64, episodes: usize, steps: u64) {
        if let Some(b) = &self.bar {
            b.set_position(bytes);
            b.set_message(format!("{episodes} episodes, {steps} steps"));
        }
    }
    fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}

fn store_err(path: &Path, e: store::StoreError) -> IngestError {
    IngestError::Store(format!("{}: {e}", path.display()))
}

/// Ingests `path` into `store` as one new version (or reports the version that already holds
/// the same content). On any error nothing is committed and the error names the file.
pub async fn ingest(store: &store::Store, path: &Path, opts: &IngestOptions) -> Result<IngestReport> {
    if opts.policy.trim().is_empty() || opts.checkpoint.trim().is_empty() {
        return Err(IngestError::Usage("--policy and --checkpoint are required".into()));
    }
    let read_opts = ReadOptions::from_ingest(opts)?;
    let format = match opts.format {
        Format::Auto => crate::detect(path)?,
        f => f,
    };
    let total = source_size(path)?;

    // Hash the source on its own thread, reading the file itself (sequentially, in 4 MB
    // buffers), while the reader decodes it.
    let hashed = Arc::new(AtomicU64::new(0));
    let hash_task = {
        let p = path.to_path_buf();
        let h = hashed.clone();
        Some(tokio::task::spawn_blocking(move || crate::hashing::hash_path_progress(&p, Some(&h))))
    };

    let MemoryBudget { in_flight_bytes, unhashed_bytes, row_group_bytes, file_bytes } = opts.memory;
    let (tx, rx) = mpsc::channel::<Msg>(CHANNEL_DEPTH);
    let budget_kib = (in_flight_bytes / 1024).clamp(1, Semaphore::MAX_PERMITS.min(u32::MAX as usize)) as u32;
    let mut feed = Feed { rx, in_flight: Arc::new(Semaphore::new(budget_kib as usize)) };
    let reader = {
        let p = path.to_path_buf();
        let mut sink = ChannelSink {
            tx,
            in_flight: feed.in_flight.clone(),
            budget_kib,
            runtime: tokio::runtime::Handle::current(),
        };
        tokio::task::spawn_blocking(move || crate::read_path_report(&p, format, &read_opts, &mut sink))
    };

    let progress = Progress::new(opts.progress, total);

    // The first message is the source metadata (or the channel closes on a reader error).
    let first = feed.rx.recv().await;
    let meta = match first {
        Some(Msg::Source(m)) => m,
        Some(_) => {
            feed.close();
            let _ = reader.await;
            return Err(IngestError::Usage("internal error: reader sent data before the source".into()));
        }
        None => {
            let r = reader.await.map_err(join_err)?;
            if let Some(h) = hash_task {
                let _ = h.await;
            }
            return Err(match r {
                Err(e) => e,
                Ok(_) => IngestError::invalid(path, "the reader produced nothing"),
            });
        }
    };
    let meta_episodes = meta.metadata.get("num_demos").and_then(|v| v.as_u64());
    let source = SourceInput {
        path: path.display().to_string(),
        sha256: String::new(),
        format: meta.format.clone(),
        size_bytes: total,
        metadata: meta.metadata,
    };
    let mut report = IngestReport {
        path: path.to_path_buf(),
        format: meta.format,
        sha256: String::new(),
        version: 0,
        already_ingested: false,
        episodes: 0,
        steps: 0,
        labels: LabelTally::default(),
        bytes: total,
        media_files: 0,
        notes: Vec::new(),
    };
    // The writer encodes episodes while the hash is still being computed; nothing is written to
    // object storage before the hash is known (and checked against the store).
    let writer = store
        .begin_ingest_unhashed(source, &opts.policy, &opts.checkpoint)
        .map(|w| w.with_max_file_bytes(file_bytes).with_max_row_group_bytes(row_group_bytes))
        .and_then(|mut w| {
            if let Some(run) = &opts.run {
                w.set_run(run.clone())?;
            }
            Ok(w)
        });
    let mut writer = match writer {
        Ok(w) => w,
        Err(e) => {
            feed.close();
            let _ = reader.await;
            if let Some(h) = hash_task {
                let _ = h.await;
            }
            progress.finish();
            return Err(store_err(path, e));
        }
    };

    enum Fed {
        Done,
        AlreadyIngested(i64),
    }
    enum Event {
        Hash(Result<(String, u64)>),
        Msg(Option<Msg>),
    }
    let mut hash_task = hash_task;
    // Robomimic: the source's metadata says how many episodes to expect (progress without a
    // separate hashing pass to count bytes).
    let expected_episodes = meta_episodes.filter(|&n| n > 0);
    // Feed the writer; on any error abort (nothing becomes visible).
    let fed: Result<Fed> = async {
        let mut open = true;
        while open || hash_task.is_some() {
            // Until the hash is known the writer holds what it encodes: past the budget, stop
            // taking episodes (the reader blocks on the channel) and wait for the hash.
            let take = open && (hash_task.is_none() || writer.unhashed_bytes() < unhashed_bytes);
            let ev = tokio::select! {
                biased;
                h = async { hash_task.as_mut().expect("guarded").await }, if hash_task.is_some() => {
                    Event::Hash(h.map_err(join_err).and_then(|r| r))
                }
                m = feed.rx.recv(), if take => Event::Msg(m),
            };
            let (sha256, size) = match ev {
                Event::Hash(h) => {
                    hash_task = None;
                    h?
                }
                Event::Msg(None) => {
                    open = false;
                    continue;
                }
                Event::Msg(Some(Msg::Source(_))) => continue,
                Event::Msg(Some(Msg::Media(f))) => {
                    writer.add_media(&f).await.map_err(|e| store_err(path, e))?;
                    report.media_files += 1;
                    continue;
                }
                Event::Msg(Some(Msg::Episode(item, permit))) => {
                    let (ep, extras) = *item;
                    report.episodes += 1;
                    report.steps += ep.len() as u64;
                    match ep.label {
                        Label::Success => report.labels.success += 1,
                        Label::Failure => report.labels.failure += 1,
                        Label::Unknown => report.labels.unknown += 1,
                    }
                    writer.push_episode_with_extras(ep, extras).await.map_err(|e| store_err(path, e))?;
                    // Encoded: its decoded columns are gone, so is its share of the budget.
                    drop(permit);
                    let pos = match expected_episodes {
                        Some(n) if hash_task.is_none() => total.saturating_mul(report.episodes as u64) / n,
                        _ => hashed.load(Ordering::Relaxed),
                    };
                    progress.update(pos, report.episodes, report.steps);
                    continue;
                }
            };
            // The source's hash: check the store for it; from now on files can be written.
            report.sha256 = sha256.clone();
            report.bytes = size;
            match writer.set_source_hash(&sha256, size).await {
                Ok(()) => {}
                Err(store::StoreError::AlreadyIngested { version, .. }) => {
                    return Ok(Fed::AlreadyIngested(version))
                }
                Err(e) => return Err(store_err(path, e)),
            }
        }
        Ok(Fed::Done)
    }
    .await;
    feed.close();
    if let Some(h) = hash_task.take() {
        let _ = h.await;
    }
    let read_result = reader.await.map_err(join_err);
    if let Ok(Fed::AlreadyIngested(version)) = fed {
        progress.finish();
        let _ = writer.abort().await;
        report.version = version;
        report.already_ingested = true;
        report.episodes = 0;
        report.steps = 0;
        report.labels = LabelTally::default();
        report.media_files = 0;
        return Ok(report);
    }
    let outcome = match (fed, read_result) {
        (Err(e), _) => Err(e),
        (Ok(_), Err(e)) => Err(e),
        (Ok(_), Ok(Err(e))) => Err(e),
        (Ok(_), Ok(Ok(out))) => Ok(out),
    };
    let outcome = match outcome {
        Ok(o) => o,
        Err(e) => {
            progress.finish();
            let _ = writer.abort().await;
            return Err(e);
        }
    };
    report.notes = outcome.notes;
    let msg = format!(
        "ingest {} {} ({} episodes, policy {}, checkpoint {})",
        report.format,
        path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
        report.episodes,
        opts.policy,
        opts.checkpoint
    );
    let info = writer.commit(&msg).await.map_err(|e| store_err(path, e));
    progress.finish();
    let info = info?;
    report.version = info.version;
    Ok(report)
}

fn source_size(path: &Path) -> Result<u64> {
    let md = std::fs::metadata(path).map_err(|e| IngestError::io(path, e))?;
    if md.is_dir() {
        Ok(crate::hashing::list_files(path)?
            .iter()
            .map(|(_, p)| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0))
            .sum())
    } else {
        Ok(md.len())
    }
}
