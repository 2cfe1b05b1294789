//! uint8 HDF5 datasets read a window of rows at a time, never whole: checked windows, windowed
//! visits, and raw `(T, H, W, C)` cameras as PNG frame streams the store's writer pulls. ALOHA's
//! cameras (raw and JPEG) and robomimic's image observations (and their `next_obs`) share it, so
//! a camera's memory is a window whatever the episode's length.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use arrow::array::{ArrayRef, FixedSizeListArray, UInt8Array};
use arrow::buffer::NullBuffer;
use arrow::datatypes::{DataType, Field};
use hdf5_pure::Dataset;
use store::ExtraPages;

use crate::error::{IngestError, Result};
use crate::h5src::{h5err, Src};
use crate::model::{FrameStream, Frames, ImageColumn};

/// Decoded bytes read at once by [`read_rows_windowed`].
pub(crate) const WINDOW_BYTES: u64 = 32 << 20;

/// A raw camera is streamed to the store (PNG-encoded as the writer pulls it): this many raw
/// bytes (at most [`STREAM_WINDOW_FRAMES`] frames) are read and encoded at once, and at most
/// [`STREAM_AHEAD`] encoded frames wait ahead of the writer. With the writer's page of frames,
/// memory per camera is about 20 MB whatever the episode's length.
const STREAM_WINDOW_BYTES: u64 = 8 << 20;
const STREAM_WINDOW_FRAMES: u64 = 32;
const STREAM_AHEAD: usize = 16;

/// A raw camera: a stream of its frames, read a window at a time and PNG-encoded on a thread
/// of its own as the store's writer pulls them (never the whole camera in memory). A window that
/// reads short (frames the file declares but does not hold) fails the stream with a message
/// naming the dataset.
pub(crate) fn raw_camera(
    ds: &Dataset,
    src: &Src,
    what: &str,
    name: &str,
    shape: &[u64],
) -> Result<ImageColumn> {
    let (t, h, w, c) = (shape[0] as usize, shape[1] as usize, shape[2] as usize, shape[3] as usize);
    if !(1..=4).contains(&c) || h == 0 || w == 0 || h > 1 << 15 || w > 1 << 15 {
        return Err(IngestError::invalid(
            src,
            format!("{what}: unsupported image shape {shape:?} (expected T x H x W x C, C in 1..=4)"),
        ));
    }
    let frames = RawFrames {
        ds: ds.clone(),
        path: src.path.to_path_buf(),
        what: what.to_string(),
        rows: t as u64,
        next_row: 0,
        shape: [h, w, c],
        encoded: std::collections::VecDeque::new(),
    };
    let stream = FrameStream::new(name, t, "png", frames).prefetched(STREAM_AHEAD);
    Ok(ImageColumn { name: name.to_string(), shape: [h, w, c], frames: Frames::Stream(stream) })
}

/// The PNG frames of a raw camera, read [`STREAM_WINDOW_BYTES`] at a time.
struct RawFrames {
    ds: Dataset,
    path: PathBuf,
    what: String,
    rows: u64,
    next_row: u64,
    shape: [usize; 3],
    encoded: std::collections::VecDeque<Vec<u8>>,
}

/// Rows of `row_bytes` bytes read at once where a camera is streamed or compared (at most
/// [`STREAM_WINDOW_BYTES`] and [`STREAM_WINDOW_FRAMES`], at least one), `left` rows remaining.
pub(crate) fn stream_window_rows(row_bytes: u64, left: u64) -> u64 {
    (STREAM_WINDOW_BYTES / row_bytes.max(1)).clamp(1, STREAM_WINDOW_FRAMES).min(left)
}

impl RawFrames {
    fn read_window(&mut self) -> Result<()> {
        let [h, w, c] = self.shape;
        let row_bytes = (h * w * c) as u64;
        let n = stream_window_rows(row_bytes, self.rows - self.next_row);
        let src = Src::new(&self.path, 0);
        let bytes = read_window(&self.ds, &src, &self.what, self.next_row, n, row_bytes)?;
        let enc = crate::png::encode_png_frames(&bytes, n as usize, h, w, c)
            .map_err(|e| IngestError::invalid(&self.path, format!("{}: {e}", self.what)))?;
        self.encoded.extend(enc);
        self.next_row += n;
        Ok(())
    }
}

impl Iterator for RawFrames {
    type Item = store::FrameResult;
    fn next(&mut self) -> Option<store::FrameResult> {
        if self.encoded.is_empty() && self.next_row < self.rows {
            if let Err(e) = self.read_window() {
                self.next_row = self.rows;
                return Some(Err(store::StoreError::invalid(e.to_string())));
            }
        }
        self.encoded.pop_front().map(Ok)
    }
}

/// Rows `start..start + n` of `row_bytes` bytes each of a uint8 dataset, checked to be all there.
pub(crate) fn read_window(
    ds: &Dataset,
    src: &Src,
    what: &str,
    start: u64,
    n: u64,
    row_bytes: u64,
) -> Result<Vec<u8>> {
    let bytes = ds.read_u8_rows(start, n).map_err(h5err(src, format!("cannot read {what}")))?;
    if bytes.len() as u64 != n * row_bytes {
        return Err(IngestError::invalid(
            src,
            format!(
                "{what}: read {} bytes for frames {start}..{}, expected {}",
                bytes.len(),
                start + n,
                n * row_bytes
            ),
        ));
    }
    Ok(bytes)
}

/// Reads the `rows` rows of `row_bytes` bytes each of a uint8 dataset in windows of about
/// [`WINDOW_BYTES`], checking each window's length, and hands each window to `f` with its first
/// row and row count: memory is bounded by a window, not by the camera.
pub(crate) fn read_rows_windowed(
    ds: &Dataset,
    src: &Src,
    what: &str,
    rows: u64,
    row_bytes: u64,
    mut f: impl FnMut(u64, usize, &[u8]) -> Result<()>,
) -> Result<()> {
    let window = (WINDOW_BYTES / row_bytes.max(1)).max(1);
    let mut start = 0u64;
    while start < rows {
        let n = window.min(rows - start);
        let bytes = read_window(ds, src, what, start, n, row_bytes)?;
        f(start, n as usize, &bytes)?;
        start += n;
    }
    Ok(())
}

/// For each row `t` of `next` (`steps` rows of `row_bytes`), whether it differs from row `t + 1`
/// of `obs` (the last row always counts as differing): robomimic's `next_obs` against a shift
/// of `obs`. Both datasets are read a window at a time, never whole.
pub(crate) fn rows_differ_from_shift(
    next: (&Dataset, &str),
    obs: (&Dataset, &str),
    src: &Src,
    row_bytes: u64,
    steps: u64,
) -> Result<Vec<bool>> {
    let mut differ = Vec::with_capacity(steps as usize);
    let mut start = 0u64;
    while start < steps {
        let n = stream_window_rows(row_bytes, steps - start);
        let a = read_window(next.0, src, next.1, start, n, row_bytes)?;
        // obs rows start + 1 ..= start + n, the last of which is past the end on the last window.
        let m = n.min(steps - start - 1);
        let b = read_window(obs.0, src, obs.1, start + 1, m, row_bytes)?;
        let rb = row_bytes as usize;
        for k in 0..n as usize {
            differ.push(k >= m as usize || a[k * rb..(k + 1) * rb] != b[k * rb..(k + 1) * rb]);
        }
        start += n;
    }
    Ok(differ)
}

/// A `(T, ...)` uint8 dataset as an extra column of `FixedSizeList<UInt8>` (`dim` values a row,
/// rows where `valid` is false null) that the store's writer reads a page of rows at a time.
pub(crate) fn u8_rows_paged(ds: &Dataset, src: &Src, what: &str, dim: usize, valid: Vec<bool>) -> ExtraPages {
    let steps = valid.len();
    let item = Arc::new(Field::new("item", DataType::UInt8, false));
    let data_type = DataType::FixedSizeList(item.clone(), dim as i32);
    // What the whole column would occupy (values and validity bitmap): the writer cuts pages by it.
    let slice_bytes = steps * dim + steps.div_ceil(8);
    let (ds, path, what) = (Mutex::new(ds.clone()), src.path.to_path_buf(), what.to_string());
    ExtraPages::new(data_type, steps, slice_bytes, move |first, count| {
        let ds = ds.lock().map_err(|_| store::StoreError::invalid(format!("{what}: reader poisoned")))?;
        let src = Src::new(&path, 0);
        let v = read_window(&ds, &src, &what, first as u64, count as u64, dim as u64)
            .map_err(|e| store::StoreError::invalid(e.to_string()))?;
        let nulls = NullBuffer::from(&valid[first..first + count]);
        let child = Arc::new(UInt8Array::from(v));
        let a = FixedSizeListArray::try_new(item.clone(), dim as i32, child, Some(nulls))?;
        Ok(Arc::new(a) as ArrayRef)
    })
}
