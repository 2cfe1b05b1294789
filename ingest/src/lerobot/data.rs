//! The data Parquet files: which columns become what ([`Plan`]), and the rows streamed batch by
//! batch into one buffer per episode ([`EpBuf`]). Image columns are checked there but only each
//! episode's first frame is kept: the frames are read again, by one reader per column and file,
//! as the store's writer pulls them (an episode's frames never sit in memory together).

use std::path::Path;

use arrow::array::RecordBatch;
use arrow::datatypes::DataType;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::file::reader::ChunkReader;

use super::columns::{
    bools, checked_metadata, col, episode_frames, flatten_single, floats64, guarded, image_bytes, ints,
    list_f32, opt_bools, png_column, png_shape, PngColumn,
};
use super::info::Info;
use super::VALIDITY_KEY;
use crate::error::{IngestError, Result};
use crate::model::FrameStream;
use crate::options::ReadOptions;

/// Which data columns become what.
pub(super) struct Plan {
    pub(super) observations: Vec<(String, String)>, // (parquet column, store name)
    pub(super) images: Vec<(String, String)>,
    pub(super) has_reward: bool,
    pub(super) has_done: bool,
    pub(super) has_success: bool,
    /// The per-frame takeover flag's column, when the dataset has one.
    pub(super) intervention: Option<String>,
    pub(super) has_validity: bool,
}

pub(super) fn plan(info: &Info, opts: &ReadOptions) -> Result<Plan> {
    let (key, named) = opts.intervention_key();
    let intervention = match info.feature(key) {
        Some(_) => Some(key.to_string()),
        None if named => {
            return Err(IngestError::Usage(format!(
                "--intervention-key {key:?}: the dataset has no such feature (its features: {})",
                info.features.iter().map(|f| f.key.as_str()).collect::<Vec<_>>().join(", ")
            )))
        }
        None => None,
    };
    let mut observations = Vec::new();
    let mut images = Vec::new();
    for f in &info.features {
        let short = f.key.strip_prefix("observation.").unwrap_or(&f.key).to_string();
        match f.dtype.as_str() {
            "video" => {}
            "image" => images.push((f.key.clone(), short)),
            "string" | "str" => {}
            _ if intervention.as_deref() == Some(f.key.as_str()) => {}
            _ if f.key.starts_with("observation.") => observations.push((f.key.clone(), short)),
            _ => {}
        }
    }
    Ok(Plan {
        observations,
        images,
        has_reward: info.feature("next.reward").is_some(),
        has_done: info.feature("next.done").is_some(),
        has_success: info.feature("next.success").is_some(),
        intervention,
        has_validity: info.feature(VALIDITY_KEY).is_some(),
    })
}

/// Accumulates the rows of one episode.
#[derive(Default)]
pub(super) struct EpBuf {
    pub(super) episode_index: u64,
    /// The episode's first row in its data file.
    pub(super) first_row: usize,
    pub(super) rows: usize,
    pub(super) timestamps: Vec<f64>,
    pub(super) frame_index: Vec<i64>,
    pub(super) global_index: Vec<i64>,
    pub(super) task_index: Vec<i64>,
    pub(super) obs: Vec<(usize, Vec<f32>)>,
    pub(super) action: (usize, Vec<f32>),
    pub(super) reward: Vec<f32>,
    pub(super) done: Vec<bool>,
    /// `next.success` per row; null rows (an unlabeled episode in a ufops export) are `None`.
    pub(super) success: Vec<Option<bool>>,
    /// Each image column's first frame.
    first_frames: Vec<Vec<u8>>,
    /// Each image column's frames (with the first frame's shape, `None` when it is not a PNG),
    /// filled in when the episode's rows end.
    pub(super) images: Vec<(Option<[usize; 3]>, FrameStream)>,
    pub(super) intervention: Vec<bool>,
    /// GR00T validity per row: a bool, or a task index (resolved when the episode ends).
    pub(super) validity: Vec<Validity>,
}

/// One row's `annotation.human.validity`.
#[derive(Clone, Copy)]
pub(super) enum Validity {
    Flag(bool),
    TaskIndex(i64),
}

/// Streams one data file's batches into per-episode buffers, calling `emit` when an episode's
/// rows end (rows of an episode are contiguous).
struct DataReader<'a> {
    plan: &'a Plan,
    cur: Option<EpBuf>,
    /// The file row of the next batch's first row.
    row: usize,
    /// Each image column of the file, read a second time for the frame streams.
    columns: Vec<std::sync::Arc<std::sync::Mutex<PngColumn>>>,
}

impl DataReader<'_> {
    /// Ends the current episode: its image columns become streams over its rows, then `emit`.
    fn close(&mut self, emit: &mut dyn FnMut(EpBuf) -> Result<()>) -> Result<()> {
        let Some(mut b) = self.cur.take() else { return Ok(()) };
        for (((_, short), column), first) in self.plan.images.iter().zip(&self.columns).zip(&b.first_frames) {
            let shape = png_shape(first);
            b.images.push((shape, episode_frames(column, short, b.first_row, b.rows)));
        }
        emit(b)
    }

    fn push_batch(
        &mut self,
        path: &Path,
        b: &RecordBatch,
        emit: &mut dyn FnMut(EpBuf) -> Result<()>,
    ) -> Result<()> {
        let n = b.num_rows();
        if n == 0 {
            return Ok(());
        }
        let BatchColumns {
            ep,
            ts,
            fi,
            gi,
            ti,
            alens,
            avals,
            obs,
            reward,
            done,
            success,
            imgs,
            intervention,
            validity,
        } = self.columns(path, b)?;
        let aoff = offsets(&alens);
        let ooffs: Vec<Vec<usize>> = obs.iter().map(|(l, _)| offsets(l)).collect();
        for r in 0..n {
            let e = u64::try_from(ep[r])
                .map_err(|_| IngestError::invalid(path, format!("negative episode_index {}", ep[r])))?;
            if self.cur.as_ref().map(|c| c.episode_index) != Some(e) {
                self.close(emit)?;
                let mut nb = EpBuf { episode_index: e, first_row: self.row + r, ..Default::default() };
                nb.obs = vec![(0, Vec::new()); obs.len()];
                nb.first_frames = imgs.iter().map(|im| im[r].clone()).collect();
                nb.action.0 = alens[r];
                for (k, (l, _)) in obs.iter().enumerate() {
                    nb.obs[k].0 = l[r];
                }
                self.cur = Some(nb);
            }
            let cur = self.cur.as_mut().expect("set above");
            cur.rows += 1;
            cur.timestamps.push(ts[r]);
            if let Some(fi) = &fi {
                cur.frame_index.push(fi[r]);
            }
            if let Some(gi) = &gi {
                cur.global_index.push(gi[r]);
            }
            if let Some(ti) = &ti {
                cur.task_index.push(ti[r]);
            }
            if alens[r] != cur.action.0 {
                return Err(IngestError::invalid(
                    path,
                    format!("episode {e}: action length changes from {} to {}", cur.action.0, alens[r]),
                ));
            }
            cur.action.1.extend_from_slice(&avals[aoff[r]..aoff[r + 1]]);
            for (k, (lens, vals)) in obs.iter().enumerate() {
                if lens[r] != cur.obs[k].0 {
                    return Err(IngestError::invalid(
                        path,
                        format!(
                            "episode {e}: {} length changes from {} to {}",
                            self.plan.observations[k].0, cur.obs[k].0, lens[r]
                        ),
                    ));
                }
                cur.obs[k].1.extend_from_slice(&vals[ooffs[k][r]..ooffs[k][r + 1]]);
            }
            if let Some((_, v)) = &reward {
                cur.reward.push(v[r]);
            }
            if let Some(d) = &done {
                cur.done.push(d[r]);
            }
            if let Some(s) = &success {
                cur.success.push(s[r]);
            }
            if let Some(i) = &intervention {
                cur.intervention.push(i[r]);
            }
            if let Some(v) = &validity {
                cur.validity.push(v[r]);
            }
        }
        self.row += n;
        Ok(())
    }

    /// Decodes the columns the plan reads from one (non-empty) batch.
    fn columns(&self, path: &Path, b: &RecordBatch) -> Result<BatchColumns> {
        let need = |name: &str| {
            col(b, name).ok_or_else(|| IngestError::invalid(path, format!("no `{name}` column")))
        };
        let ep = ints(path, need("episode_index")?, "episode_index")?;
        let ts = floats64(path, &flatten_single(path, need("timestamp")?, "timestamp")?, "timestamp")?;
        let fi = col(b, "frame_index")
            .map(|c| flatten_single(path, c, "frame_index").and_then(|c| ints(path, &c, "frame_index")))
            .transpose()?;
        let gi = col(b, "index")
            .map(|c| flatten_single(path, c, "index").and_then(|c| ints(path, &c, "index")))
            .transpose()?;
        let ti = col(b, "task_index")
            .map(|c| flatten_single(path, c, "task_index").and_then(|c| ints(path, &c, "task_index")))
            .transpose()?;
        let (alens, avals) = list_f32(path, need("action")?, "action")?;
        let mut obs = Vec::new();
        for (c, _) in &self.plan.observations {
            obs.push(list_f32(path, need(c)?, c)?);
        }
        let reward = if self.plan.has_reward {
            Some(list_f32(path, need("next.reward")?, "next.reward")?)
        } else {
            None
        };
        let done =
            if self.plan.has_done { Some(bools(path, need("next.done")?, "next.done")?) } else { None };
        let success = if self.plan.has_success {
            Some(opt_bools(path, need("next.success")?, "next.success")?)
        } else {
            None
        };
        let mut imgs = Vec::new();
        for (c, _) in &self.plan.images {
            imgs.push(image_bytes(path, need(c)?, c)?);
        }
        let intervention = match &self.plan.intervention {
            Some(c) => Some(bools(path, need(c)?, c)?),
            None => None,
        };
        let validity = if self.plan.has_validity {
            let c = flatten_single(path, need(VALIDITY_KEY)?, VALIDITY_KEY)?;
            Some(match c.data_type() {
                DataType::Boolean => bools(path, &c, VALIDITY_KEY)?.into_iter().map(Validity::Flag).collect(),
                _ => ints(path, &c, VALIDITY_KEY)?.into_iter().map(Validity::TaskIndex).collect::<Vec<_>>(),
            })
        } else {
            None
        };
        if let Some(r) = &reward {
            if r.0.iter().any(|&l| l != 1) {
                return Err(IngestError::invalid(path, "column next.reward: expected one value per row"));
            }
        }
        Ok(BatchColumns {
            ep,
            ts,
            fi,
            gi,
            ti,
            alens,
            avals,
            obs,
            reward,
            done,
            success,
            imgs,
            intervention,
            validity,
        })
    }
}

// offsets into flat arrays
fn offsets(lens: &[usize]) -> Vec<usize> {
    let mut o = Vec::with_capacity(lens.len() + 1);
    let mut s = 0;
    o.push(0);
    for l in lens {
        s += l;
        o.push(s);
    }
    o
}

/// One batch's columns as [`DataReader::columns`] decodes them (numeric lists as per-row
/// lengths and flat values); each is named as in `push_batch`, which reads them row by row.
struct BatchColumns {
    ep: Vec<i64>,
    ts: Vec<f64>,
    fi: Option<Vec<i64>>,
    gi: Option<Vec<i64>>,
    ti: Option<Vec<i64>>,
    alens: Vec<usize>,
    avals: Vec<f32>,
    obs: Vec<(Vec<usize>, Vec<f32>)>,
    reward: Option<(Vec<usize>, Vec<f32>)>,
    done: Option<Vec<bool>>,
    success: Option<Vec<Option<bool>>>,
    /// Each image column's PNG bytes per row (checked; only an episode's first is kept).
    imgs: Vec<Vec<Vec<u8>>>,
    intervention: Option<Vec<bool>>,
    validity: Option<Vec<Validity>>,
}

/// Streams the data file `path` (`open` opens it: once for the rows, once more per image
/// column for the frame streams) into episodes.
pub(super) fn stream_data<R: ChunkReader + 'static>(
    path: &Path,
    open: &dyn Fn() -> Result<R>,
    plan: &Plan,
    emit: &mut dyn FnMut(EpBuf) -> Result<()>,
) -> Result<()> {
    let meta = checked_metadata(path, &open()?)?;
    // Rows are decoded a batch at a time, page by page from the file (the sync reader reads
    // pages, not whole row groups); PNG image columns make a row KBs, so their batches are small.
    let batch_rows = if plan.images.is_empty() { 4096 } else { 64 };
    let mut reader = guarded(path, || {
        ParquetRecordBatchReaderBuilder::new_with_metadata(open()?, meta.clone())
            .with_batch_size(batch_rows)
            .build()
            .map_err(|e| IngestError::invalid(path, format!("not a readable Parquet file: {e}")))
    })?;
    let mut columns = Vec::with_capacity(plan.images.len());
    for (c, _) in &plan.images {
        if meta.schema().index_of(c).is_ok() {
            columns.push(png_column(path, open()?, &meta, c)?);
        }
    }
    let mut dr = DataReader { plan, cur: None, row: 0, columns };
    while let Some(b) = guarded(path, || Ok(reader.next()))? {
        let b = b.map_err(|e| IngestError::invalid(path, format!("corrupt Parquet data: {e}")))?;
        dr.push_batch(path, &b, emit)?;
    }
    dr.close(emit)
}
