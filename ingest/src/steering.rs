//! Steering telemetry beside a source: a sidecar Parquet file of best-of-N records
//! (`verifier::steps::steering_sidecar_batch`: `episode_index`, `t`, `steering`), which the
//! ingest attaches to the source's episodes as their steps' steering column.
//!
//! The sidecar of `rollouts.hdf5` is `rollouts.hdf5.steering.parquet`, of a dataset folder its
//! `steering.parquet` (or any file `--steering-log` names). It is untrusted like the source: its
//! footer and page sizes are checked before anything is decoded, only its `episode_index` column
//! is read up front (an index of which rows belong to which episode), and each episode's rows
//! are read when that episode is ingested, so memory holds one episode's records. A record for a
//! step outside its episode, two records on one step, or a record for an episode the source does
//! not have fails the ingest with a message naming it, and the store stays as it was.

use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};

use arrow::array::{ArrayRef, AsArray};
use arrow::datatypes::Int64Type;
use parquet::arrow::arrow_reader::{ArrowReaderMetadata, ParquetRecordBatchReaderBuilder, RowSelection};
use parquet::arrow::ProjectionMask;

use crate::error::{IngestError, Result};

/// The sidecar `ufops ingest` picks up beside `source` when no `--steering-log` is given.
pub fn sidecar_for(source: &Path) -> PathBuf {
    if source.is_dir() {
        source.join("steering.parquet")
    } else {
        let mut s = source.as_os_str().to_owned();
        s.push(".steering.parquet");
        PathBuf::from(s)
    }
}

/// An open sidecar: which rows hold each episode's records, read an episode at a time.
pub struct SteeringSidecar {
    path: PathBuf,
    file: File,
    meta: ArrowReaderMetadata,
    /// Source episode index → its rows (ascending).
    rows: BTreeMap<u64, Vec<usize>>,
    records: usize,
}

impl SteeringSidecar {
    /// Opens and indexes the sidecar at `path`.
    pub fn open(path: &Path) -> Result<Self> {
        let file = File::open(path).map_err(|e| IngestError::io(path, e))?;
        let meta = crate::lerobot::columns::checked_metadata(path, &file)?;
        let bad = |m: String| IngestError::invalid(path, format!("steering sidecar: {m}"));
        let schema = meta.schema().clone();
        for (name, want) in [
            (verifier::steps::SIDECAR_EPISODE_COLUMN, arrow::datatypes::DataType::Int64),
            ("t", arrow::datatypes::DataType::Int32),
            (store::steps::STEERING_COLUMN, store::steps::steering_data_type()),
        ] {
            let f = schema.field_with_name(name).map_err(|_| bad(format!("no column {name:?}")))?;
            if f.data_type() != &want {
                return Err(bad(format!("column {name:?} is {}, expected {want}", f.data_type())));
            }
        }
        let idx = schema.index_of(verifier::steps::SIDECAR_EPISODE_COLUMN).map_err(|e| bad(e.to_string()))?;
        let mask = ProjectionMask::roots(meta.parquet_schema(), [idx]);
        // The parquet decoder can still panic on corrupt pages: `guarded` makes that an error.
        let (rows, records) = crate::lerobot::columns::guarded(path, || {
            let f = file.try_clone().map_err(|e| IngestError::io(path, e))?;
            let reader = ParquetRecordBatchReaderBuilder::new_with_metadata(f, meta.clone())
                .with_projection(mask)
                .build()
                .map_err(|e| bad(e.to_string()))?;
            let mut rows: BTreeMap<u64, Vec<usize>> = BTreeMap::new();
            let mut row = 0usize;
            for batch in reader {
                let batch = batch.map_err(|e| bad(e.to_string()))?;
                let col = batch.column(0).as_primitive::<Int64Type>();
                for i in 0..col.len() {
                    let e = u64::try_from(col.value(i))
                        .map_err(|_| bad(format!("row {row}: negative episode_index")))?;
                    rows.entry(e).or_default().push(row);
                    row += 1;
                }
            }
            Ok((rows, row))
        })?;
        Ok(SteeringSidecar { path: path.to_path_buf(), file, meta, rows, records })
    }

    /// Records in the file.
    pub fn records(&self) -> usize {
        self.records
    }

    /// The steering column of the source's episode `index` of `steps` steps (`None` when the
    /// sidecar has no record for it); the episode's records are consumed.
    pub fn take(&mut self, index: u64, steps: usize) -> Result<Option<ArrayRef>> {
        let Some(rows) = self.rows.remove(&index) else { return Ok(None) };
        let path = self.path.clone();
        let bad = |m: String| IngestError::invalid(&path, format!("steering sidecar, episode {index}: {m}"));
        // Consecutive rows become one selected range each.
        let mut ranges: Vec<std::ops::Range<usize>> = Vec::new();
        for &r in &rows {
            match ranges.last_mut() {
                Some(last) if last.end == r => last.end = r + 1,
                _ => ranges.push(r..r + 1),
            }
        }
        let selection = RowSelection::from_consecutive_ranges(ranges.into_iter(), self.records);
        let log = crate::lerobot::columns::guarded(&path, || {
            let f = self.file.try_clone().map_err(|e| IngestError::io(&path, e))?;
            let reader = ParquetRecordBatchReaderBuilder::new_with_metadata(f, self.meta.clone())
                .with_row_selection(selection)
                .build()
                .map_err(|e| bad(e.to_string()))?;
            let mut log = Vec::with_capacity(rows.len());
            for batch in reader {
                let batch = batch.map_err(|e| bad(e.to_string()))?;
                log.extend(verifier::steps::steering_log(&batch).map_err(|e| bad(e.to_string()))?);
            }
            Ok(log)
        })?;
        if log.len() != rows.len() {
            return Err(bad(format!(
                "{} records read for {} rows (a null steering row?)",
                log.len(),
                rows.len()
            )));
        }
        verifier::steps::steering_array(&log, steps).map(Some).map_err(|e| bad(e.to_string()))
    }

    /// Checks that every record found its episode.
    pub fn finish(self) -> Result<()> {
        match self.rows.keys().next() {
            None => Ok(()),
            Some(e) => Err(IngestError::invalid(
                &self.path,
                format!(
                    "steering sidecar: records for episode index {e} (and {} more episodes), which the source does not have",
                    self.rows.len() - 1
                ),
            )),
        }
    }
}
