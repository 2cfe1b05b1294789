//! The async glue: one ingest = one store version, all or nothing.
//!
//! The format reader runs on a blocking thread and pushes into a bounded channel (at most
//! [`CHANNEL_DEPTH`] episodes and
//! [`MemoryBudget::in_flight_bytes`](crate::MemoryBudget::in_flight_bytes) in flight); the
//! source's sha256 is computed on a second blocking thread reading the file itself at the same
//! time. The store's `IngestWriter` encodes episodes as they come; until the hash (the episode
//! ids' prefix) is known it holds at most
//! [`MemoryBudget::unhashed_bytes`](crate::MemoryBudget::unhashed_bytes) of encoded steps, then
//! the reader waits for the hash. Memory is therefore bounded by an episode and the budgets,
//! never by the source. Any error aborts the writer, so the store stays exactly as it was.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};

use crate::error::{IngestError, Result};
use crate::model::{EpisodeInput, ExtraColumn, Label, MediaFile, SourceInput};
use crate::options::{Format, IngestOptions, ReadOptions};
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
        let extra_bytes: usize = extras.iter().map(|x| x.values.memory_size()).sum();
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
    // Streamed cameras count nothing: their frames are read as the writer pulls them.
    let images: usize = ep
        .images
        .iter()
        .filter_map(|im| im.frames.as_encoded())
        .flat_map(|f| f.iter().map(|f| f.len() + 24))
        .sum();
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

/// The threads an ingest runs beside the store's writer: the format reader (feeding the
/// channel) and the source's hash. Every way out of [`ingest`] ends them the same way
/// ([`Background::stop`]).
struct Background {
    feed: Feed,
    reader: tokio::task::JoinHandle<Result<crate::ReadOutcome>>,
    /// `None` once the hash is known (or after `stop`).
    hash: Option<tokio::task::JoinHandle<Result<(String, u64)>>>,
    /// Bytes hashed so far (the progress bar's position).
    hashed: Arc<AtomicU64>,
    /// `--images video`: the cameras' MP4s are written here on the reader's thread and copied
    /// into the store as the writer takes them; the folder lives until the ingest ends.
    _video_dir: Option<tempfile::TempDir>,
}

impl Background {
    /// Starts hashing `path` (sequentially, in 4 MB buffers, on its own thread) and reading it
    /// as `format` into a bounded channel, at most `in_flight_bytes` of episodes ahead.
    fn start(
        path: &Path,
        format: Format,
        read_opts: ReadOptions,
        opts: &IngestOptions,
    ) -> Result<Background> {
        let hashed = Arc::new(AtomicU64::new(0));
        let hash = {
            let p = path.to_path_buf();
            let h = hashed.clone();
            tokio::task::spawn_blocking(move || crate::hashing::hash_path_progress(&p, Some(&h)))
        };
        let (tx, rx) = mpsc::channel::<Msg>(CHANNEL_DEPTH);
        let budget_kib = (opts.memory.in_flight_bytes / 1024)
            .clamp(1, Semaphore::MAX_PERMITS.min(u32::MAX as usize)) as u32;
        let feed = Feed { rx, in_flight: Arc::new(Semaphore::new(budget_kib as usize)) };
        let video_dir = match opts.images {
            crate::model::ImageStorage::Video => {
                Some(tempfile::tempdir().map_err(|e| IngestError::io(Path::new("video temp dir"), e))?)
            }
            crate::model::ImageStorage::Png => None,
        };
        let mut sink = ChannelSink {
            tx,
            in_flight: feed.in_flight.clone(),
            budget_kib,
            runtime: tokio::runtime::Handle::current(),
        };
        let p = path.to_path_buf();
        let dir = video_dir.as_ref().map(|d| d.path().to_path_buf());
        let reader = tokio::task::spawn_blocking(move || match dir {
            Some(dir) => crate::read_path_report(
                &p,
                format,
                &read_opts,
                &mut crate::video::VideoSink::new(&mut sink, &dir),
            ),
            None => crate::read_path_report(&p, format, &read_opts, &mut sink),
        });
        Ok(Background { feed, reader, hash: Some(hash), hashed, _video_dir: video_dir })
    }

    /// Closes the channel (a reader waiting on it or on the budget stops), waits for both
    /// threads and returns the reader's result.
    async fn stop(mut self) -> Result<crate::ReadOutcome> {
        self.feed.close();
        if let Some(h) = self.hash.take() {
            let _ = h.await;
        }
        self.reader.await.map_err(join_err).and_then(|r| r)
    }
}

/// How feeding the writer ended.
enum Fed {
    Done,
    /// The source's hash names a version that already holds it.
    AlreadyIngested(i64),
}

/// Ingests `path` into `store` as one new version (or reports the version that already holds
/// the same content). On any error nothing is committed and the error names the file.
#[allow(
    clippy::too_many_lines,
    reason = "the ingest pipeline in its order: detect, hash, read, write, commit, report"
)]
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
    // Steering telemetry beside the source (`--steering-log`, else `<source>.steering.parquet`).
    let sidecar_path = match &opts.steering_log {
        Some(p) => Some(p.clone()),
        None => Some(crate::steering::sidecar_for(path)).filter(|p| p.is_file()),
    };
    let mut sidecar = sidecar_path.as_deref().map(crate::steering::SteeringSidecar::open).transpose()?;
    let mut bg = Background::start(path, format, read_opts, opts)?;
    let progress = Progress::new(opts.progress, total);

    // The first message is the source metadata (or the channel closes on a reader error).
    let meta = match bg.feed.rx.recv().await {
        Some(Msg::Source(m)) => m,
        Some(_) => {
            let _ = bg.stop().await;
            return Err(IngestError::Usage("internal error: reader sent data before the source".into()));
        }
        None => {
            return Err(match bg.stop().await {
                Err(e) => e,
                Ok(_) => IngestError::invalid(path, "the reader produced nothing"),
            })
        }
    };
    // Robomimic: the source's metadata says how many episodes to expect (progress without a
    // separate hashing pass to count bytes).
    let expected_episodes = meta.metadata.get("num_demos").and_then(|v| v.as_u64()).filter(|&n| n > 0);
    let mut report = IngestReport::empty(path, &meta.format, total);
    let source = SourceInput {
        path: path.display().to_string(),
        sha256: String::new(),
        format: meta.format,
        size_bytes: total,
        metadata: meta.metadata,
    };
    // The writer encodes episodes while the hash is still being computed; nothing is written to
    // object storage before the hash is known (and checked against the store).
    let mut writer = match begin_writer(store, source, opts) {
        Ok(w) => w,
        Err(e) => {
            let _ = bg.stop().await;
            progress.finish();
            return Err(store_err(path, e));
        }
    };

    let fed = {
        let mut feeding = Feeding {
            path,
            bg: &mut bg,
            writer: &mut writer,
            report: &mut report,
            progress: &progress,
            unhashed_bytes: opts.memory.unhashed_bytes,
            expected_episodes,
            total,
            sidecar: sidecar.as_mut(),
        };
        feeding.run().await
    };
    let read = bg.stop().await;
    let outcome = match (fed, read) {
        (Ok(Fed::AlreadyIngested(version)), _) => {
            progress.finish();
            let _ = writer.abort().await;
            return Ok(IngestReport {
                version,
                already_ingested: true,
                episodes: 0,
                steps: 0,
                labels: LabelTally::default(),
                media_files: 0,
                ..report
            });
        }
        (Err(e), _) | (Ok(Fed::Done), Err(e)) => {
            progress.finish();
            let _ = writer.abort().await;
            return Err(e);
        }
        (Ok(Fed::Done), Ok(outcome)) => outcome,
    };
    if let Some(sc) = sidecar {
        let records = sc.records();
        if let Err(e) = sc.finish() {
            progress.finish();
            let _ = writer.abort().await;
            return Err(e);
        }
        report
            .notes
            .push(format!("{records} steering records from {}", sidecar_path.unwrap_or_default().display()));
    }
    report.notes.extend(outcome.notes);
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
    report.version = info?.version;
    Ok(report)
}

/// Feeds the reader's episodes to the writer until the channel closes and the hash is known;
/// on any error the caller aborts the writer (nothing becomes visible).
struct Feeding<'a> {
    path: &'a Path,
    bg: &'a mut Background,
    writer: &'a mut store::IngestWriter,
    report: &'a mut IngestReport,
    progress: &'a Progress,
    /// Past this many encoded bytes held for want of the hash, stop taking episodes.
    unhashed_bytes: usize,
    expected_episodes: Option<u64>,
    total: u64,
    /// The source's steering telemetry, attached to its episodes as they come.
    sidecar: Option<&'a mut crate::steering::SteeringSidecar>,
}

enum Event {
    Hash(Result<(String, u64)>),
    Msg(Option<Msg>),
}

impl Feeding<'_> {
    async fn run(&mut self) -> Result<Fed> {
        let mut open = true;
        while open || self.bg.hash.is_some() {
            // Until the hash is known the writer holds what it encodes: past the budget, stop
            // taking episodes (the reader blocks on the channel) and wait for the hash.
            let take = open && (self.bg.hash.is_none() || self.writer.unhashed_bytes() < self.unhashed_bytes);
            let hashing = self.bg.hash.is_some();
            let ev = tokio::select! {
                biased;
                h = async { self.bg.hash.as_mut().expect("guarded").await }, if hashing => {
                    Event::Hash(h.map_err(join_err).and_then(|r| r))
                }
                m = self.bg.feed.rx.recv(), if take => Event::Msg(m),
            };
            match ev {
                Event::Hash(h) => {
                    self.bg.hash = None;
                    let (sha256, size) = h?;
                    if let Some(version) = self.source_hashed(sha256, size).await? {
                        return Ok(Fed::AlreadyIngested(version));
                    }
                }
                Event::Msg(None) => open = false,
                Event::Msg(Some(Msg::Source(_))) => {}
                Event::Msg(Some(Msg::Media(f))) => {
                    self.writer.add_media(&f).await.map_err(|e| store_err(self.path, e))?;
                    self.report.media_files += 1;
                }
                Event::Msg(Some(Msg::Episode(item, permit))) => {
                    let (ep, extras) = *item;
                    self.episode(ep, extras).await?;
                    // Encoded: its decoded columns are gone, so is its share of the budget.
                    drop(permit);
                }
            }
        }
        Ok(Fed::Done)
    }

    /// The source's hash: checks the store for it (`Some(version)` when a version already holds
    /// it); from now on files can be written.
    async fn source_hashed(&mut self, sha256: String, size: u64) -> Result<Option<i64>> {
        self.report.bytes = size;
        let set = self.writer.set_source_hash(&sha256, size).await;
        self.report.sha256 = sha256;
        match set {
            Ok(()) => Ok(None),
            Err(store::StoreError::AlreadyIngested { version, .. }) => Ok(Some(version)),
            Err(e) => Err(store_err(self.path, e)),
        }
    }

    async fn episode(&mut self, ep: EpisodeInput, extras: Vec<ExtraColumn>) -> Result<()> {
        let report = &mut *self.report;
        report.episodes += 1;
        report.steps += ep.len() as u64;
        match ep.label {
            Label::Success => report.labels.success += 1,
            Label::Failure => report.labels.failure += 1,
            Label::Unknown => report.labels.unknown += 1,
        }
        let steering = match self.sidecar.as_deref_mut() {
            Some(sc) => sc.take(u64::from(ep.source_index), ep.len())?,
            None => None,
        };
        self.writer.push_episode_steered(ep, extras, steering).await.map_err(|e| store_err(self.path, e))?;
        let pos = match self.expected_episodes {
            Some(n) if self.bg.hash.is_none() => self.total.saturating_mul(report.episodes as u64) / n,
            _ => self.bg.hashed.load(Ordering::Relaxed),
        };
        self.progress.update(pos, report.episodes, report.steps);
        Ok(())
    }
}

impl IngestReport {
    /// Nothing ingested yet from `path` (`total` bytes, read as `format`).
    fn empty(path: &Path, format: &str, total: u64) -> IngestReport {
        IngestReport {
            path: path.to_path_buf(),
            format: format.to_string(),
            sha256: String::new(),
            version: 0,
            already_ingested: false,
            episodes: 0,
            steps: 0,
            labels: LabelTally::default(),
            bytes: total,
            media_files: 0,
            notes: Vec::new(),
        }
    }
}

/// The store's writer for `source`, before its hash is known, with the ingest's budgets and run.
fn begin_writer(
    store: &store::Store,
    source: SourceInput,
    opts: &IngestOptions,
) -> std::result::Result<store::IngestWriter, store::StoreError> {
    let mut w = store
        .begin_ingest_unhashed(source, &opts.policy, &opts.checkpoint)?
        .with_max_file_bytes(opts.memory.file_bytes)
        .with_max_row_group_bytes(opts.memory.row_group_bytes);
    if let Some(run) = &opts.run {
        w.set_run(run.clone())?;
    }
    Ok(w)
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
