//! The Parquet files (opened only after their footer and pages are checked, decoder panics
//! turned into errors) and their Arrow columns read as plain vectors (image columns as PNG bytes).

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use arrow::array::{Array, ArrayRef, AsArray, RecordBatch};
use arrow::datatypes::{DataType, Float32Type, Float64Type, Int64Type};
use parquet::arrow::arrow_reader::{
    ArrowReaderMetadata, ArrowReaderOptions, ParquetRecordBatchReader, ParquetRecordBatchReaderBuilder,
};
use parquet::arrow::ProjectionMask;
use parquet::file::reader::ChunkReader;

use crate::error::{IngestError, Result};
use crate::model::{FrameResult, FrameStream};

pub(super) fn open_parquet(path: &Path) -> Result<Vec<RecordBatch>> {
    let f = std::fs::File::open(path).map_err(|e| IngestError::io(path, e))?;
    parquet_batches(path, f)
}

/// Opens a Parquet reader after checking what the parquet crate asserts on (it panics on
/// negative column offsets/sizes in corrupt footers).
pub(super) fn checked_builder<R: ChunkReader + 'static>(
    path: &Path,
    r: R,
) -> Result<ParquetRecordBatchReaderBuilder<R>> {
    let meta = checked_metadata(path, &r)?;
    Ok(ParquetRecordBatchReaderBuilder::new_with_metadata(r, meta))
}

/// The reader metadata of a Parquet file, checked as [`checked_builder`] checks it (once per
/// file: the readers of its image columns reuse it).
pub(crate) fn checked_metadata<R: ChunkReader + 'static>(path: &Path, r: &R) -> Result<ArrowReaderMetadata> {
    guarded(path, || checked_metadata_inner(path, r))
}

/// The parquet crate still panics on some corrupt pages (e.g. "Decoder for dict should have been
/// set", apache/arrow-rs#9434-style index errors): such a panic becomes an error naming the file.
pub(crate) fn guarded<T>(path: &Path, f: impl FnOnce() -> Result<T>) -> Result<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => Err(IngestError::invalid(
            path,
            format!(
                "corrupt Parquet data: the parquet decoder failed ({})",
                crate::panic_message(p.as_ref())
            ),
        )),
    }
}

fn checked_metadata_inner<R: ChunkReader + 'static>(path: &Path, r: &R) -> Result<ArrowReaderMetadata> {
    let bad = |e: String| IngestError::invalid(path, format!("not a readable Parquet file: {e}"));
    // The parquet crate trusts the element counts in the footer when it allocates: check them first.
    crate::pqfooter::check(r).map_err(bad)?;
    let meta = parquet::file::metadata::ParquetMetaDataReader::new()
        .parse_and_finish(r)
        .map_err(|e| bad(e.to_string()))?;
    // ... and the page sizes the page headers declare (the decompression buffers' sizes); this
    // also checks that every column chunk lies inside the file.
    crate::pqfooter::check_pages(r, &meta)
        .map_err(|e| IngestError::invalid(path, format!("corrupt Parquet data: {e}")))?;
    // The embedded Arrow schema (IPC flatbuffer in the footer) is skipped: the schema derived from
    // the Parquet types is enough here, and arrow-ipc panics on some corrupt ones (fuzzing).
    let opts = ArrowReaderOptions::new().with_skip_arrow_metadata(true);
    ArrowReaderMetadata::try_new(std::sync::Arc::new(meta), opts).map_err(|e| bad(e.to_string()))
}

/// All record batches of a (small) Parquet file.
fn parquet_batches<R: ChunkReader + 'static>(path: &Path, r: R) -> Result<Vec<RecordBatch>> {
    let reader = checked_builder(path, r)?
        .build()
        .map_err(|e| IngestError::invalid(path, format!("not a readable Parquet file: {e}")))?;
    let mut reader = reader;
    let mut out = Vec::new();
    while let Some(b) = guarded(path, || Ok(reader.next()))? {
        out.push(b.map_err(|e| IngestError::invalid(path, format!("corrupt Parquet data: {e}")))?);
    }
    Ok(out)
}

pub(super) fn col<'a>(b: &'a RecordBatch, name: &str) -> Option<&'a ArrayRef> {
    b.schema().index_of(name).ok().map(|i| b.column(i))
}

/// Values of an integer-like column as i64 (nulls → error).
pub(super) fn ints(path: &Path, a: &ArrayRef, what: &str) -> Result<Vec<i64>> {
    let c = arrow::compute::cast(a, &DataType::Int64)
        .map_err(|e| IngestError::invalid(path, format!("column {what}: {e}")))?;
    let c = c.as_primitive::<Int64Type>();
    if c.null_count() > 0 {
        return Err(IngestError::invalid(path, format!("column {what} has null values")));
    }
    Ok(c.values().to_vec())
}

pub(super) fn floats64(path: &Path, a: &ArrayRef, what: &str) -> Result<Vec<f64>> {
    let c = arrow::compute::cast(a, &DataType::Float64)
        .map_err(|e| IngestError::invalid(path, format!("column {what}: {e}")))?;
    let c = c.as_primitive::<Float64Type>();
    if c.null_count() > 0 {
        return Err(IngestError::invalid(path, format!("column {what} has null values")));
    }
    Ok(c.values().to_vec())
}

/// A boolean column keeping its nulls.
pub(super) fn opt_bools(path: &Path, a: &ArrayRef, what: &str) -> Result<Vec<Option<bool>>> {
    let a = flatten_single(path, a, what)?;
    let c = arrow::compute::cast(&a, &DataType::Boolean)
        .map_err(|e| IngestError::invalid(path, format!("column {what}: {e}")))?;
    Ok(c.as_boolean().iter().collect())
}

pub(super) fn bools(path: &Path, a: &ArrayRef, what: &str) -> Result<Vec<bool>> {
    let a = flatten_single(path, a, what)?;
    let c = arrow::compute::cast(&a, &DataType::Boolean)
        .map_err(|e| IngestError::invalid(path, format!("column {what}: {e}")))?;
    let c = c.as_boolean();
    Ok((0..c.len()).map(|i| c.is_valid(i) && c.value(i)).collect())
}

/// A column that may be a scalar or a one-element list: returns the scalar values.
pub(super) fn flatten_single(path: &Path, a: &ArrayRef, what: &str) -> Result<ArrayRef> {
    match a.data_type() {
        DataType::FixedSizeList(_, 1) => Ok(a.as_fixed_size_list().values().clone()),
        DataType::List(_) | DataType::LargeList(_) | DataType::FixedSizeList(_, _) => {
            let (dim, vals) = list_f32(path, a, what)?;
            if dim.iter().any(|&d| d != 1) {
                return Err(IngestError::invalid(path, format!("column {what}: expected one value per row")));
            }
            Ok(std::sync::Arc::new(arrow::array::Float32Array::from(vals)))
        }
        _ => Ok(a.clone()),
    }
}

/// A numeric list (fixed or variable) or scalar column as (per-row lengths, flat f32 values).
pub(super) fn list_f32(path: &Path, a: &ArrayRef, what: &str) -> Result<(Vec<usize>, Vec<f32>)> {
    let bad = |e: String| IngestError::invalid(path, format!("column {what}: {e}"));
    let to_f32 = |v: &ArrayRef| -> Result<Vec<f32>> {
        let c = arrow::compute::cast(v, &DataType::Float32).map_err(|e| bad(e.to_string()))?;
        Ok(c.as_primitive::<Float32Type>().values().to_vec())
    };
    if a.null_count() > 0 {
        return Err(bad("has null rows".into()));
    }
    match a.data_type() {
        DataType::FixedSizeList(_, n) => {
            let l = a.as_fixed_size_list();
            let n = *n as usize;
            let start = l.offset() * n;
            let vals = l.values().slice(start, l.len() * n);
            Ok((vec![n; l.len()], to_f32(&vals)?))
        }
        DataType::List(_) => {
            let l = a.as_list::<i32>();
            let offs = l.value_offsets();
            let (s, e) = (offs[0] as usize, offs[offs.len() - 1] as usize);
            let lens = offs.windows(2).map(|w| (w[1] - w[0]) as usize).collect();
            Ok((lens, to_f32(&l.values().slice(s, e - s))?))
        }
        DataType::LargeList(_) => {
            let l = a.as_list::<i64>();
            let offs = l.value_offsets();
            let (s, e) = (offs[0] as usize, offs[offs.len() - 1] as usize);
            let lens = offs.windows(2).map(|w| (w[1] - w[0]) as usize).collect();
            Ok((lens, to_f32(&l.values().slice(s, e - s))?))
        }
        _ => {
            let v = to_f32(a)?;
            Ok((vec![1; v.len()], v))
        }
    }
}

pub(super) fn strings(a: &ArrayRef) -> Option<Vec<String>> {
    let c = arrow::compute::cast(a, &DataType::Utf8).ok()?;
    let c = c.as_string::<i32>();
    Some((0..c.len()).map(|i| if c.is_valid(i) { c.value(i).to_string() } else { String::new() }).collect())
}

pub(super) fn list_strings(a: &ArrayRef) -> Option<Vec<Vec<String>>> {
    match a.data_type() {
        DataType::List(_) => {
            let l = a.as_list::<i32>();
            Some((0..l.len()).map(|i| strings(&l.value(i)).unwrap_or_default()).collect())
        }
        DataType::LargeList(_) => {
            let l = a.as_list::<i64>();
            Some((0..l.len()).map(|i| strings(&l.value(i)).unwrap_or_default()).collect())
        }
        _ => strings(a).map(|v| v.into_iter().map(|s| vec![s]).collect()),
    }
}

/// PNG bytes per row from an `image` column (`struct<bytes: binary, path: string>` or binary).
pub(super) fn image_bytes(path: &Path, a: &ArrayRef, what: &str) -> Result<Vec<Vec<u8>>> {
    let bin: ArrayRef = match a.data_type() {
        DataType::Struct(_) => {
            let s = a.as_struct();
            s.column_by_name("bytes").cloned().ok_or_else(|| {
                IngestError::invalid(path, format!("image column {what} has no `bytes` field"))
            })?
        }
        _ => a.clone(),
    };
    let bin = arrow::compute::cast(&bin, &DataType::LargeBinary)
        .map_err(|e| IngestError::invalid(path, format!("image column {what}: {e}")))?;
    let bin = bin.as_binary::<i64>();
    let mut out = Vec::with_capacity(bin.len());
    for i in 0..bin.len() {
        if !bin.is_valid(i) {
            return Err(IngestError::invalid(path, format!("image column {what}: row {i} has no image bytes (images stored only by path are not supported)")));
        }
        let v = bin.value(i);
        if !v.starts_with(b"\x89PNG\r\n\x1a\n") {
            return Err(IngestError::invalid(
                path,
                format!("image column {what}: row {i} is not a PNG image"),
            ));
        }
        out.push(v.to_vec());
    }
    Ok(out)
}

/// (height, width, channels) from a PNG's IHDR.
pub(super) fn png_shape(png: &[u8]) -> Option<[usize; 3]> {
    if png.len() < 33 || &png[12..16] != b"IHDR" {
        return None;
    }
    let w = u32::from_be_bytes(png[16..20].try_into().ok()?) as usize;
    let h = u32::from_be_bytes(png[20..24].try_into().ok()?) as usize;
    let c = match png[25] {
        0 => 1,
        2 => 3,
        3 => 3,
        4 => 2,
        6 => 4,
        _ => return None,
    };
    Some([h, w, c])
}

/// Rows of an image column read at once when it is streamed (PNG frames are KBs to MBs each).
const IMAGE_BATCH_ROWS: usize = 64;

/// How many PNG frames a streamed image column reads ahead of the store's writer.
const IMAGE_AHEAD: usize = 16;

/// The image column `column` of a data file, read front to back [`IMAGE_BATCH_ROWS`] at a time
/// (no row selection: the parquet crate then fetches the whole column chunk at once), shared by
/// the frame streams of the file's episodes ([`episode_frames`]), which the store's writer pulls
/// in episode order.
pub(super) fn png_column<R: ChunkReader + 'static>(
    path: &Path,
    r: R,
    meta: &ArrowReaderMetadata,
    column: &str,
) -> Result<Arc<Mutex<PngColumn>>> {
    let root = meta
        .schema()
        .index_of(column)
        .map_err(|_| IngestError::invalid(path, format!("no `{column}` column")))?;
    let reader = guarded(path, || {
        ParquetRecordBatchReaderBuilder::new_with_metadata(r, meta.clone())
            .with_projection(ProjectionMask::roots(meta.parquet_schema(), [root]))
            .with_batch_size(IMAGE_BATCH_ROWS)
            .build()
            .map_err(|e| IngestError::invalid(path, format!("not a readable Parquet file: {e}")))
    })?;
    let rows =
        PngRows { path: path.to_path_buf(), what: column.to_string(), reader, pending: VecDeque::new() };
    Ok(Arc::new(Mutex::new(PngColumn { rows, next_row: 0 })))
}

/// An image column read front to back, and the file row its next frame is.
pub(super) struct PngColumn {
    rows: PngRows,
    next_row: usize,
}

/// The frames of rows `first..first + rows` of a shared image column (camera `name`), pulled
/// from it as the store's writer asks. Rows before `first` (an episode whose frames nobody
/// pulled) are skipped; rows already taken are an error.
pub(super) fn episode_frames(
    column: &Arc<Mutex<PngColumn>>,
    name: &str,
    first: usize,
    rows: usize,
) -> FrameStream {
    let column = column.clone();
    let mut next = first;
    let frames = std::iter::from_fn(move || {
        if next == first + rows {
            return None;
        }
        let mut c = match column.lock() {
            Ok(c) => c,
            Err(_) => return Some(Err(store::StoreError::invalid("image column reader poisoned"))),
        };
        loop {
            if c.next_row > next {
                let what = c.rows.what.clone();
                return Some(Err(store::StoreError::invalid(format!(
                    "image column {what}: row {next} was read before its episode asked for it"
                ))));
            }
            let f = c.rows.next()?;
            c.next_row += 1;
            // A row skipped over that cannot be read fails this episode's frames too.
            if c.next_row > next || f.is_err() {
                next += 1;
                return Some(f);
            }
        }
    });
    FrameStream::new(name, rows, "png", frames).prefetched(IMAGE_AHEAD)
}

/// An image column's PNG frames, a record batch at a time.
struct PngRows {
    path: PathBuf,
    what: String,
    reader: ParquetRecordBatchReader,
    pending: VecDeque<Vec<u8>>,
}

impl PngRows {
    /// Reads batches until a frame is pending or the rows end.
    fn fill(&mut self) -> Result<()> {
        let path = self.path.as_path();
        while self.pending.is_empty() {
            let Some(b) = guarded(path, || Ok(self.reader.next()))? else { return Ok(()) };
            let b = b.map_err(|e| IngestError::invalid(path, format!("corrupt Parquet data: {e}")))?;
            self.pending.extend(image_bytes(path, b.column(0), &self.what)?);
        }
        Ok(())
    }
}

impl Iterator for PngRows {
    type Item = FrameResult;
    fn next(&mut self) -> Option<FrameResult> {
        if let Err(e) = self.fill() {
            self.pending.clear();
            // Nothing after an error: FrameStream stops at the first one.
            return Some(Err(store::StoreError::invalid(e.to_string())));
        }
        self.pending.pop_front().map(Ok)
    }
}
