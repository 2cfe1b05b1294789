//! Reading episode steps back, fetching only the bytes the episodes need (store/README.md, "Read
//! path"). The catalog says where each episode is (`data_file`, `row_group`, `row_offset`,
//! `row_count`); a steps file's footer and offset index are fetched once and cached; then only the
//! pages of the wanted rows are fetched (byte ranges, coalesced) and decoded with parquet's push
//! decoder, which leaves the I/O to us: fetches run on the async runtime, decoding on blocking
//! threads, several row-group jobs at once.
//!
//! [`Store::read_steps`] reads one episode; [`Store::read_episodes`] streams many (a split, a
//! version) grouped by file, reading each needed row group once, with memory bounded by the jobs
//! in flight (a few row-group slices of at most [`JOB_BYTES`] compressed) and what the caller
//! keeps.
//!
//! Past 700 lines with its unit tests (about 230 of them); the read path itself is one piece.

use crate::catalog::RowExt;
use crate::{EpisodeRecord, Store, StoreError};
use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use futures::StreamExt;
use parquet::arrow::arrow_reader::{
    ArrowReaderMetadata, ArrowReaderOptions, RowSelection, RowSelectionPolicy, RowSelector,
};
use parquet::arrow::push_decoder::ParquetPushDecoderBuilder;
use parquet::arrow::ProjectionMask;
use parquet::file::metadata::{PageIndexPolicy, ParquetMetaDataPushDecoder};
use parquet::DecodeResult;
use std::collections::HashMap;
use std::ops::Range;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use tokio::sync::mpsc;

/// Bytes fetched with a file's first request: its footer and, usually, nothing more is needed
/// before the offset index (one more request).
const FOOTER_PREFETCH: u64 = 64 << 10;
/// A row group is read in slices of about this many compressed bytes (whole episodes): they
/// decode in parallel and bound the memory of a job.
pub const JOB_BYTES: u64 = 16 << 20;
/// Decoded batches hold about this many bytes (at most 8,192 rows).
const BATCH_BYTES: u64 = 8 << 20;
const BATCH_MAX_ROWS: usize = 8192;
/// Footers kept in memory, all files together (the offset index of a 64 MB steps file of
/// ~300-step episodes is ~0.5 MB).
pub(crate) const METADATA_CACHE_BYTES: usize = 64 << 20;
/// Catalog look-ups per statement.
const IDS_PER_QUERY: usize = 500;

/// Where an episode's steps are: `row_count` rows from `row_offset` of row group `row_group`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EpisodeLocation {
    pub episode_id: String,
    pub data_file: String,
    pub row_group: usize,
    pub row_offset: usize,
    pub row_count: usize,
}

impl EpisodeLocation {
    pub(crate) fn try_from_parts(
        id: &str,
        file: String,
        rg: i64,
        offset: i64,
        count: i64,
    ) -> Result<Self, StoreError> {
        if rg < 0 || offset < 0 || count < 0 {
            return Err(StoreError::Corrupt(format!(
                "episode {id} points at row group {rg}, rows {offset}+{count}"
            )));
        }
        Ok(EpisodeLocation {
            episode_id: id.to_string(),
            data_file: file,
            row_group: rg as usize,
            row_offset: offset as usize,
            row_count: count as usize,
        })
    }
}

impl EpisodeLocation {
    /// The id (column `id_column`) and location of a catalog row holding `data_file`,
    /// `row_group`, `row_offset` and `row_count` (an episode, or its values of a layer).
    pub(crate) fn from_row(r: &sqlx::any::AnyRow, id_column: &str) -> Result<(String, Self), StoreError> {
        let id = r.s(id_column)?;
        let loc = EpisodeLocation::try_from_parts(
            &id,
            r.s("data_file")?,
            r.i("row_group")?,
            r.i("row_offset")?,
            r.i("row_count")?,
        )?;
        Ok((id, loc))
    }
}

/// Whether a catalog row added in version `added` (and removed in `removed`, if ever) is visible
/// now (`version` None) or in `version`: the one rule for episodes and their layers.
pub(crate) fn visible(added: i64, removed: Option<i64>, version: Option<i64>) -> bool {
    match version {
        None => removed.is_none(),
        Some(v) => added <= v && removed.is_none_or(|x| x > v),
    }
}

impl TryFrom<&EpisodeRecord> for EpisodeLocation {
    type Error = StoreError;
    fn try_from(e: &EpisodeRecord) -> Result<Self, StoreError> {
        EpisodeLocation::try_from_parts(&e.id, e.data_file.clone(), e.row_group, e.row_offset, e.row_count)
    }
}

/// One episode's steps, `index` being its position in the locations given to
/// [`Store::read_episodes`].
#[derive(Debug)]
pub struct EpisodeSteps {
    pub index: usize,
    pub steps: RecordBatch,
}

/// Some episodes could not be read (one job: a slice of one row group, or one whole file when
/// its footer is unreadable).
#[derive(Debug, thiserror::Error)]
#[error("reading {} episode(s) from {file}: {error}", indexes.len())]
pub struct StepsReadError {
    /// Positions, in the given locations, of the episodes not read.
    pub indexes: Vec<usize>,
    pub file: String,
    #[source]
    pub error: StoreError,
}

impl From<StepsReadError> for StoreError {
    fn from(e: StepsReadError) -> StoreError {
        e.error
    }
}

/// The steps of many episodes, in file order (see [`Store::read_episodes`]). Dropping it stops
/// the reads.
pub struct StepsStream {
    rx: mpsc::Receiver<Result<EpisodeSteps, StepsReadError>>,
    task: tokio::task::JoinHandle<()>,
}

impl StepsStream {
    pub(crate) fn from_parts(
        rx: mpsc::Receiver<Result<EpisodeSteps, StepsReadError>>,
        task: tokio::task::JoinHandle<()>,
    ) -> Self {
        StepsStream { rx, task }
    }

    /// The next episode read (or failure); `None` once every job is done.
    pub async fn next(&mut self) -> Option<Result<EpisodeSteps, StepsReadError>> {
        self.rx.recv().await
    }
}

impl futures::Stream for StepsStream {
    type Item = Result<EpisodeSteps, StepsReadError>;
    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        self.rx.poll_recv(cx)
    }
}

impl Drop for StepsStream {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// A steps file's footer (with its offset index) and size, and the bytes of its first request
/// (the file's tail: all of a small file), which serve the data ranges they hold.
#[derive(Clone)]
pub(crate) struct FileMeta {
    pub meta: ArrowReaderMetadata,
    pub size: u64,
    tail: bytes::Bytes,
}

impl FileMeta {
    fn tail_start(&self) -> u64 {
        self.size - self.tail.len() as u64
    }

    /// The ranges' bytes: from the tail when it holds them, else fetched (coalesced).
    pub(crate) async fn fetch(
        &self,
        store: &Store,
        path: &str,
        ranges: &[Range<u64>],
    ) -> Result<Vec<bytes::Bytes>, StoreError> {
        check_ranges(path, ranges, self.size)?;
        let start = self.tail_start();
        let missing: Vec<Range<u64>> = ranges.iter().filter(|r| r.start < start).cloned().collect();
        let mut fetched = store.objects().get_ranges(path, &missing).await?.into_iter();
        ranges
            .iter()
            .map(|r| match r.start >= start {
                true => Ok(self.tail.slice((r.start - start) as usize..(r.end - start) as usize)),
                false => fetched
                    .next()
                    .ok_or_else(|| StoreError::Corrupt(format!("{path}: a range was not fetched"))),
            })
            .collect()
    }
}

/// Footers by object path (objects are immutable, so a path's footer never changes), within
/// [`METADATA_CACHE_BYTES`].
pub(crate) type MetaCache = crate::lru::ByteLru<String, FileMeta>;

impl Store {
    /// The step table of an episode (one record batch), now or as of `version`.
    pub async fn read_steps(&self, id: &str, version: Option<i64>) -> Result<RecordBatch, StoreError> {
        let loc = self.locate_episodes(&[id.to_string()], version).await?;
        let mut stream = self.read_episodes(loc);
        match stream.next().await {
            Some(Ok(ep)) => Ok(ep.steps),
            Some(Err(e)) => Err(e.error),
            None => Err(StoreError::Corrupt(format!("episode {id}: the read returned nothing"))),
        }
    }

    /// Where the episodes' steps are, in the order of `ids`; an episode that is not visible (now,
    /// or in `version`) is [`StoreError::NotFound`].
    pub async fn locate_episodes(
        &self,
        ids: &[String],
        version: Option<i64>,
    ) -> Result<Vec<EpisodeLocation>, StoreError> {
        if let Some(v) = version {
            self.version(v).await?;
        }
        let mut found: HashMap<String, EpisodeLocation> = HashMap::with_capacity(ids.len());
        for chunk in ids.chunks(IDS_PER_QUERY) {
            let sql = format!(
                "SELECT id, data_file, row_group, COALESCE(row_offset, 0) AS row_offset, \
                 COALESCE(row_count, length) AS row_count, version_added, version_removed \
                 FROM episodes WHERE id IN ({})",
                crate::catalog::placeholders(chunk.len())
            );
            let mut q = sqlx::query(&sql);
            for id in chunk {
                q = q.bind(id.as_str());
            }
            for r in q.fetch_all(&self.catalog().pool).await? {
                if visible(r.i("version_added")?, r.oi("version_removed")?, version) {
                    let (id, loc) = EpisodeLocation::from_row(&r, "id")?;
                    found.insert(id, loc);
                }
            }
        }
        ids.iter()
            .map(|id| found.get(id).cloned().ok_or_else(|| StoreError::not_found("episode", id.as_str())))
            .collect()
    }

    /// The Arrow schema of a steps file (from its cached footer).
    pub async fn steps_schema(&self, data_file: &str) -> Result<SchemaRef, StoreError> {
        Ok(self.file_meta(data_file).await?.meta.schema().clone())
    }

    /// Streams the steps of many episodes: grouped by file and row group, each needed row group
    /// read once (its wanted pages, in coalesced ranges), slices of row groups decoded in
    /// parallel. Items come in file order, not in the order of `locations` (`index` says which
    /// episode each is); a failed read yields a [`StepsReadError`] naming its episodes and the
    /// stream goes on with the others. Must be called inside a Tokio runtime.
    pub fn read_episodes(&self, locations: Vec<EpisodeLocation>) -> StepsStream {
        self.read_episodes_projected(locations, None)
    }

    /// [`Self::read_episodes`], reading only the columns whose names `columns` accepts.
    pub(crate) fn read_episodes_projected(
        &self,
        locations: Vec<EpisodeLocation>,
        columns: Option<fn(&str) -> bool>,
    ) -> StepsStream {
        // Enough jobs in flight to keep every core decoding while the next slices are fetched.
        let parallel = std::thread::available_parallelism().map_or(2, |n| n.get()).clamp(2, 16) + 1;
        let (tx, rx) = mpsc::channel(64);
        let store = self.clone();
        let task = tokio::spawn(async move {
            let files = group_by_file(locations);
            let store2 = store.clone();
            let jobs = futures::stream::iter(files)
                .map(move |(file, eps)| {
                    let store = store2.clone();
                    async move {
                        match store.file_meta(&file).await {
                            Ok(fm) => plan_jobs(&fm, &file, eps, columns),
                            Err(error) => {
                                let indexes = eps.iter().map(|(i, _)| *i).collect();
                                vec![Err(StepsReadError { indexes, file, error })]
                            }
                        }
                    }
                })
                .buffered(parallel)
                .flat_map(futures::stream::iter);
            jobs.for_each_concurrent(parallel, |job| {
                let store = store.clone();
                let tx = tx.clone();
                async move {
                    match job {
                        Ok(job) => run_job(&store, job, &tx).await,
                        Err(e) => {
                            let _ = tx.send(Err(e)).await;
                        }
                    }
                }
            })
            .await;
        });
        StepsStream { rx, task }
    }

    /// A steps file's footer and offset index, from the cache or fetched (a suffix request,
    /// then the offset index if the suffix did not hold it).
    pub(crate) async fn file_meta(&self, path: &str) -> Result<FileMeta, StoreError> {
        let cache = &self.inner.meta_cache;
        let key = path.to_string();
        let cell = cache.cell(&key);
        let mut fresh = false;
        let fm = cell
            .get_or_try_init(|| async {
                fresh = true;
                load_meta(self, path).await
            })
            .await?
            .clone();
        if fresh {
            cache.loaded(&key, fm.meta.metadata().memory_size() + fm.tail.len());
        }
        Ok(fm)
    }
}

async fn load_meta(store: &Store, path: &str) -> Result<FileMeta, StoreError> {
    let objects = store.objects();
    let (range, tail, size) = objects.get_suffix(path, FOOTER_PREFETCH).await?;
    // Check the footer's own length before the decoder trusts it.
    let corrupt = |why: String| StoreError::Corrupt(format!("steps file {path}: {why}"));
    if size < 12 || tail.len() < 8 || &tail[tail.len() - 4..] != b"PAR1" {
        return Err(corrupt(format!("not a Parquet file ({size} bytes)")));
    }
    let n = tail.len();
    let footer_len = u32::from_le_bytes([tail[n - 8], tail[n - 7], tail[n - 6], tail[n - 5]]) as u64;
    if footer_len + 12 > size {
        return Err(corrupt(format!("footer of {footer_len} bytes in a file of {size}")));
    }
    let mut dec = ParquetMetaDataPushDecoder::try_new(size)?
        .with_offset_index_policy(PageIndexPolicy::Optional)
        .with_column_index_policy(PageIndexPolicy::Skip);
    dec.push_range(range, tail.clone())?;
    let meta = loop {
        match dec.try_decode()? {
            DecodeResult::NeedsData(ranges) => {
                check_ranges(path, &ranges, size)?;
                let data = objects.get_ranges(path, &ranges).await?;
                dec.push_ranges(ranges, data)?;
            }
            DecodeResult::Data(m) => break m,
            DecodeResult::Finished => return Err(corrupt("footer decoder finished without metadata".into())),
        }
    };
    let meta = ArrowReaderMetadata::try_new(Arc::new(meta), ArrowReaderOptions::new())?;
    Ok(FileMeta { meta, size, tail })
}

fn check_ranges(path: &str, ranges: &[Range<u64>], size: u64) -> Result<(), StoreError> {
    match ranges.iter().find(|r| r.start > r.end || r.end > size) {
        Some(r) => Err(StoreError::Corrupt(format!(
            "steps file {path}: its metadata points at bytes {r:?} of a {size}-byte file"
        ))),
        None => Ok(()),
    }
}

/// The episodes of each file, files in order of first appearance: `(index, location)`.
fn group_by_file(locations: Vec<EpisodeLocation>) -> Vec<(String, Vec<(usize, EpisodeLocation)>)> {
    let mut order: HashMap<String, usize> = HashMap::new();
    let mut files: Vec<(String, Vec<(usize, EpisodeLocation)>)> = Vec::new();
    for (i, loc) in locations.into_iter().enumerate() {
        let k = *order.entry(loc.data_file.clone()).or_insert_with(|| {
            files.push((loc.data_file.clone(), Vec::new()));
            files.len() - 1
        });
        files[k].1.push((i, loc));
    }
    files
}

/// A slice of one row group: episodes in row order, none overlapping.
struct Job {
    file: String,
    fm: FileMeta,
    row_group: usize,
    /// `(index, row_offset, row_count)`
    episodes: Vec<(usize, usize, usize)>,
    batch_rows: usize,
    projection: Option<ProjectionMask>,
}

/// Splits one file's episodes into jobs: by row group, in row order, about [`JOB_BYTES`] of
/// compressed data each. An episode outside its row group fails alone.
fn plan_jobs(
    fm: &FileMeta,
    file: &str,
    mut eps: Vec<(usize, EpisodeLocation)>,
    columns: Option<fn(&str) -> bool>,
) -> Vec<Result<Job, StepsReadError>> {
    let md = fm.meta.metadata();
    let projection = columns.map(|accept| {
        let roots =
            fm.meta.schema().fields().iter().enumerate().filter(|(_, f)| accept(f.name())).map(|(i, _)| i);
        ProjectionMask::roots(fm.meta.parquet_schema(), roots.collect::<Vec<_>>())
    });
    eps.sort_by_key(|(_, l)| (l.row_group, l.row_offset));
    let mut out: Vec<Result<Job, StepsReadError>> = Vec::new();
    let mut current: Option<(Job, u64, usize)> = None; // (job, its bytes, end row)
    for (index, loc) in eps {
        let fail = |why: String| StepsReadError {
            indexes: vec![index],
            file: file.to_string(),
            error: StoreError::Corrupt(format!("episode {}: {why}", loc.episode_id)),
        };
        if loc.row_group >= md.num_row_groups() {
            out.push(Err(fail(format!(
                "points at row group {} of a file with {}",
                loc.row_group,
                md.num_row_groups()
            ))));
            continue;
        }
        let rg = md.row_group(loc.row_group);
        let rg_rows = rg.num_rows().max(0) as usize;
        if loc.row_count == 0 || loc.row_offset.checked_add(loc.row_count).is_none_or(|end| end > rg_rows) {
            out.push(Err(fail(format!(
                "points at rows {}+{} of a row group with {rg_rows}",
                loc.row_offset, loc.row_count
            ))));
            continue;
        }
        let per_row = (rg.compressed_size().max(0) as u64 / rg_rows.max(1) as u64).max(1);
        let raw_per_row = (rg.total_byte_size().max(0) as u64 / rg_rows.max(1) as u64).max(1);
        let bytes = per_row.saturating_mul(loc.row_count as u64);
        let fits = current.as_ref().is_some_and(|(job, job_bytes, end)| {
            job.row_group == loc.row_group && loc.row_offset >= *end && job_bytes + bytes <= JOB_BYTES
        });
        if !fits {
            if let Some((job, _, _)) = current.take() {
                out.push(Ok(job));
            }
            let batch_rows = ((BATCH_BYTES / raw_per_row) as usize).clamp(1, BATCH_MAX_ROWS);
            let job = Job {
                file: file.to_string(),
                fm: fm.clone(),
                row_group: loc.row_group,
                episodes: Vec::new(),
                batch_rows,
                projection: projection.clone(),
            };
            current = Some((job, 0, 0));
        }
        let (job, job_bytes, end) = current.as_mut().expect("a job is open");
        job.episodes.push((index, loc.row_offset, loc.row_count));
        *job_bytes += bytes;
        *end = loc.row_offset + loc.row_count;
    }
    if let Some((job, _, _)) = current {
        out.push(Ok(job));
    }
    out
}

/// Fetches a job's pages and decodes them on a blocking thread, sending each episode as soon as
/// its rows are complete.
async fn run_job(store: &Store, job: Job, tx: &mpsc::Sender<Result<EpisodeSteps, StepsReadError>>) {
    let mut sent = 0usize;
    let result = fetch_and_decode(store, &job, tx, &mut sent).await;
    if let Err(error) = result {
        let indexes: Vec<usize> = job.episodes[sent.min(job.episodes.len())..].iter().map(|e| e.0).collect();
        if !indexes.is_empty() {
            let _ = tx.send(Err(StepsReadError { indexes, file: job.file.clone(), error })).await;
        }
    }
}

async fn fetch_and_decode(
    store: &Store,
    job: &Job,
    tx: &mpsc::Sender<Result<EpisodeSteps, StepsReadError>>,
    sent: &mut usize,
) -> Result<(), StoreError> {
    let md = job.fm.meta.metadata();
    let rg_rows = md.row_group(job.row_group).num_rows().max(0) as usize;
    let mut selectors = Vec::with_capacity(job.episodes.len() * 2 + 1);
    let mut at = 0;
    for &(_, offset, count) in &job.episodes {
        if offset > at {
            selectors.push(RowSelector::skip(offset - at));
        }
        selectors.push(RowSelector::select(count));
        at = offset + count;
    }
    if at < rg_rows {
        selectors.push(RowSelector::skip(rg_rows - at));
    }
    let mut builder = ParquetPushDecoderBuilder::new_with_metadata(job.fm.meta.clone())
        .with_row_groups(vec![job.row_group])
        .with_row_selection(RowSelection::from(selectors))
        .with_row_selection_policy(RowSelectionPolicy::Selectors)
        .with_batch_size(job.batch_rows);
    if let Some(p) = &job.projection {
        builder = builder.with_projection(p.clone());
    }
    let mut decoder = builder.build()?;
    loop {
        match decoder.try_next_reader()? {
            DecodeResult::NeedsData(ranges) => {
                let data = job.fm.fetch(store, &job.file, &ranges).await?;
                decoder.push_ranges(ranges, data)?;
            }
            DecodeResult::Data(reader) => {
                let episodes = job.episodes[*sent..].to_vec();
                let tx = tx.clone();
                let (n, result) = tokio::task::spawn_blocking(move || carve(reader, &episodes, &tx))
                    .await
                    .map_err(|e| StoreError::Corrupt(format!("decoding thread failed: {e}")))?;
                *sent += n;
                result?;
            }
            DecodeResult::Finished => break,
        }
    }
    if *sent != job.episodes.len() {
        return Err(StoreError::Corrupt(format!(
            "row group {} of {} ended before its episodes did",
            job.row_group, job.file
        )));
    }
    Ok(())
}

/// Cuts the decoded rows into episodes (in row order) and sends them; returns how many were sent.
fn carve(
    reader: impl Iterator<Item = Result<RecordBatch, arrow::error::ArrowError>>,
    episodes: &[(usize, usize, usize)],
    tx: &mpsc::Sender<Result<EpisodeSteps, StepsReadError>>,
) -> (usize, Result<(), StoreError>) {
    let mut sent = 0;
    let mut pieces: Vec<RecordBatch> = Vec::new();
    let mut have = 0;
    for batch in reader {
        let batch = match batch {
            Ok(b) => b,
            Err(e) => return (sent, Err(e.into())),
        };
        let mut at = 0;
        while at < batch.num_rows() {
            let Some(&(index, _, count)) = episodes.get(sent) else {
                return (
                    sent,
                    Err(StoreError::Corrupt("the decoder returned more rows than selected".into())),
                );
            };
            let take = (count - have).min(batch.num_rows() - at);
            pieces.push(batch.slice(at, take));
            at += take;
            have += take;
            if have == count {
                let steps = if pieces.len() == 1 {
                    pieces.pop().expect("one piece")
                } else {
                    match arrow::compute::concat_batches(&batch.schema(), &pieces) {
                        Ok(b) => b,
                        Err(e) => return (sent, Err(e.into())),
                    }
                };
                pieces.clear();
                have = 0;
                if tx.blocking_send(Ok(EpisodeSteps { index, steps })).is_err() {
                    // The reader went away: nothing left to do.
                    return (episodes.len(), Ok(()));
                }
                sent += 1;
            }
        }
    }
    (sent, Ok(()))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::*;
    use arrow::array::{Array, Int32Array, StringArray};

    pub(crate) fn episode(i: u32, steps: usize) -> EpisodeInput {
        let label = if i.is_multiple_of(3) { Label::Failure } else { Label::Success };
        EpisodeInput {
            tags: vec![],
            metadata: serde_json::json!({}),
            timestamps: (0..steps).map(|t| t as f64 * 0.05).collect(),
            observations: vec![
                VectorColumn {
                    name: "pos".into(),
                    dim: 3,
                    values: (0..steps * 3).map(|k| (k as f32 * 0.37 + i as f32).sin()).collect(),
                },
                VectorColumn {
                    name: "grip".into(),
                    dim: 1,
                    values: (0..steps).map(|k| k as f32 + i as f32 * 1000.0).collect(),
                },
            ],
            action: VectorColumn {
                name: "action".into(),
                dim: 2,
                values: (0..steps * 2).map(|k| (k as f32).cos()).collect(),
            },
            ..crate::test_support::episode(i, steps, label)
        }
    }

    fn steps_of(i: u32) -> usize {
        20 + (i as usize * 37) % 90
    }

    async fn ingest(store: &Store, tag: &str, n: u32, max_file_bytes: usize) -> Vec<EpisodeRecord> {
        let src = SourceInput {
            path: tag.into(),
            sha256: sha256_hex(tag.as_bytes()),
            format: "test".into(),
            size_bytes: 1,
            metadata: serde_json::json!({}),
        };
        let mut w = store.begin_ingest(src, "pol", tag).await.unwrap().with_max_file_bytes(max_file_bytes);
        for i in 0..n {
            w.add_episode(episode(i, steps_of(i))).await.unwrap();
        }
        w.commit("t").await.unwrap();
        let f = EpisodeFilter { checkpoint: Some(tag.into()), ..Default::default() };
        store.episodes(&f).await.unwrap()
    }

    fn check(batch: &RecordBatch, e: &EpisodeRecord) {
        let i = e.source_index as u32;
        assert_eq!(batch.num_rows(), steps_of(i), "{}", e.id);
        let ids = batch.column_by_name("episode_id").unwrap().as_any().downcast_ref::<StringArray>().unwrap();
        assert!((0..ids.len()).all(|k| ids.value(k) == e.id), "{}", e.id);
        let t = batch.column_by_name("t").unwrap().as_any().downcast_ref::<Int32Array>().unwrap();
        assert_eq!(t.values().to_vec(), (0..steps_of(i) as i32).collect::<Vec<_>>());
        let (_, grip) = steps::vector_column(batch, "obs.grip").unwrap();
        assert_eq!(grip, episode(i, steps_of(i)).observations[1].values);
    }

    fn file_sizes(dir: &std::path::Path) -> u64 {
        std::fs::read_dir(dir.join("objects/steps"))
            .unwrap()
            .map(|e| e.unwrap().metadata().unwrap().len())
            .sum()
    }

    /// Each episode is its own pages: one page per episode per column in every row group.
    #[tokio::test]
    async fn pages_are_cut_between_episodes() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let eps = ingest(&store, "a", 40, 64 << 20).await;
        let fm = store.file_meta(&eps[0].data_file).await.unwrap();
        let md = fm.meta.metadata();
        assert_eq!(md.num_row_groups(), 1);
        let index = md.offset_index().expect("offset index is written");
        for (c, col) in index[0].iter().enumerate() {
            let firsts: Vec<i64> = col.page_locations().iter().map(|p| p.first_row_index).collect();
            let mut want: Vec<i64> = eps.iter().map(|e| e.row_offset).collect();
            want.sort();
            assert_eq!(firsts, want, "column {c}");
        }
    }

    /// One episode's read fetches the footer once, then about its own bytes.
    #[tokio::test]
    async fn one_episode_reads_its_own_bytes() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let eps = ingest(&store, "a", 2000, 64 << 20).await;
        let total = file_sizes(dir.path());
        let before = store.fetch_counts();
        check(&store.read_steps(&eps[7].id, None).await.unwrap(), &eps[7]);
        let first = store.fetch_counts().since(before);
        let before = store.fetch_counts();
        check(&store.read_steps(&eps[1500].id, None).await.unwrap(), &eps[1500]);
        let second = store.fetch_counts().since(before);
        // The footer is cached: the second read fetches its own pages and the dictionaries only
        // (an average episode is 1/2000 of the file).
        assert!(second.bytes_fetched < first.bytes_fetched, "{first:?} {second:?}");
        assert!(second.bytes_fetched < 5 * total / 2000, "{second:?} of a {total}-byte file");
        assert_eq!(second.head_requests, 0);
    }

    /// Many episodes over several files and row groups: every one comes back once, correct, and
    /// the whole store is fetched about once.
    #[tokio::test]
    async fn many_episodes_read_each_file_once() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let eps = ingest(&store, "a", 1000, 300_000).await;
        let files: std::collections::HashSet<&str> = eps.iter().map(|e| e.data_file.as_str()).collect();
        assert!(files.len() > 3, "{} files", files.len());
        // Shuffled: the reader groups them by file itself.
        let mut order: Vec<usize> = (0..eps.len()).collect();
        order.sort_by_key(|&k| (k * 7919) % eps.len());
        let ids: Vec<String> = order.iter().map(|&k| eps[k].id.clone()).collect();
        let before = store.fetch_counts();
        let locs = store.locate_episodes(&ids, None).await.unwrap();
        let mut seen = vec![false; ids.len()];
        let mut stream = store.read_episodes(locs);
        while let Some(item) = stream.next().await {
            let item = item.unwrap();
            assert!(!std::mem::replace(&mut seen[item.index], true), "episode {} twice", item.index);
            check(&item.steps, &eps[order[item.index]]);
        }
        assert!(seen.iter().all(|s| *s));
        let got = store.fetch_counts().since(before);
        let total = file_sizes(dir.path());
        assert!(got.bytes_fetched <= total + total / 5, "fetched {got:?} of {total} bytes");
        assert!(got.bytes_fetched >= total * 9 / 10, "fetched {got:?} of {total} bytes");
    }

    /// Version visibility: a removed episode reads in the versions that hold it only.
    #[tokio::test]
    async fn visibility_follows_versions() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let eps = ingest(&store, "a", 5, 64 << 20).await;
        store.delete_episodes(&[eps[2].id.clone()], "t", "bad").await.unwrap();
        assert!(matches!(store.read_steps(&eps[2].id, None).await, Err(StoreError::NotFound { .. })));
        check(&store.read_steps(&eps[2].id, Some(1)).await.unwrap(), &eps[2]);
        assert!(matches!(store.read_steps(&eps[2].id, Some(9)).await, Err(StoreError::NotFound { .. })));
        let ids = vec![eps[1].id.clone(), eps[2].id.clone()];
        assert!(matches!(store.locate_episodes(&ids, None).await, Err(StoreError::NotFound { .. })));
        assert_eq!(store.locate_episodes(&ids, Some(1)).await.unwrap().len(), 2);
    }

    fn loc(id: &str, file: &str, rg: usize, offset: usize, count: usize) -> EpisodeLocation {
        EpisodeLocation {
            episode_id: id.into(),
            data_file: file.into(),
            row_group: rg,
            row_offset: offset,
            row_count: count,
        }
    }

    async fn collect(
        store: &Store,
        locs: Vec<EpisodeLocation>,
    ) -> (Vec<Option<RecordBatch>>, Vec<StepsReadError>) {
        let mut ok = vec![None; locs.len()];
        let mut errs = Vec::new();
        let mut s = store.read_episodes(locs);
        while let Some(item) = s.next().await {
            match item {
                Ok(e) => ok[e.index] = Some(e.steps),
                Err(e) => errs.push(e),
            }
        }
        (ok, errs)
    }

    /// Files of older stores (one page per 20,000 rows, episodes across page boundaries, no
    /// page alignment) read exactly their rows; bad locations and bad files fail alone, naming
    /// their episodes, without a panic.
    #[tokio::test]
    async fn older_layouts_and_bad_locations() {
        use arrow::array::ArrayRef;
        use parquet::arrow::ArrowWriter;
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let a: ArrayRef = Arc::new(Int32Array::from_iter_values(0..50_000));
        let batch = RecordBatch::try_from_iter([("t", a)]).unwrap();
        let mut w = ArrowWriter::try_new(Vec::new(), batch.schema(), None).unwrap();
        w.write(&batch.slice(0, 30_000)).unwrap();
        w.flush().unwrap();
        w.write(&batch.slice(30_000, 20_000)).unwrap();
        let data = bytes::Bytes::from(w.into_inner().unwrap());
        store.objects().put_new("steps/old.parquet", data).await.unwrap();
        store
            .objects()
            .put_new("steps/junk.parquet", bytes::Bytes::from_static(b"not parquet at all, PAR1"))
            .await
            .unwrap();
        let locs = vec![
            loc("a", "steps/old.parquet", 0, 19_990, 20),
            loc("b", "steps/old.parquet", 1, 0, 20_000),
            loc("c", "steps/old.parquet", 0, 0, 1),
            loc("d", "steps/old.parquet", 1, 19_999, 2),
            loc("e", "steps/old.parquet", 2, 0, 1),
            loc("f", "steps/missing.parquet", 0, 0, 1),
            loc("g", "steps/junk.parquet", 0, 0, 1),
            loc("h", "steps/old.parquet", 0, 29_999, 1),
        ];
        let (ok, errs) = collect(&store, locs).await;
        let ints = |b: &Option<RecordBatch>| {
            b.as_ref().unwrap().column(0).as_any().downcast_ref::<Int32Array>().unwrap().values().to_vec()
        };
        assert_eq!(ints(&ok[0]), (19_990..20_010).collect::<Vec<_>>());
        assert_eq!(ints(&ok[1]), (30_000..50_000).collect::<Vec<_>>());
        assert_eq!(ints(&ok[2]), vec![0]);
        assert_eq!(ints(&ok[7]), vec![29_999]);
        let mut failed: Vec<usize> = errs.iter().flat_map(|e| e.indexes.clone()).collect();
        failed.sort();
        assert_eq!(failed, vec![3, 4, 5, 6]);
        for e in &errs {
            match e.indexes[0] {
                5 => assert!(matches!(e.error, StoreError::NotFound { .. }), "{e}"),
                _ => assert!(matches!(e.error, StoreError::Corrupt(_)), "{e}"),
            }
        }
    }
}
