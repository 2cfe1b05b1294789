//! The episode and task metadata: v2.1 `meta/episodes.jsonl` / `meta/tasks.jsonl`, v3.0
//! `meta/episodes/chunk-*/file-*.parquet` / `meta/tasks.parquet`.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use arrow::array::RecordBatch;
use arrow::datatypes::DataType;
use serde_json::Value;

use super::columns::{col, floats64, ints, list_strings, open_parquet, strings};
use super::info::{read_bounded, Info, MAX_JSONL_BYTES};
use crate::error::{IngestError, Result};

#[derive(Debug, Clone, Default)]
pub(super) struct VideoRef {
    pub(super) chunk_index: u64,
    pub(super) file_index: u64,
    pub(super) from_timestamp: f64,
}

#[derive(Debug, Clone, Default)]
pub(super) struct EpisodeMeta {
    pub(super) episode_index: u64,
    pub(super) tasks: Vec<String>,
    pub(super) length: Option<u64>,
    pub(super) data_chunk: u64,
    pub(super) data_file: u64,
    pub(super) from_index: Option<u64>,
    pub(super) to_index: Option<u64>,
    pub(super) videos: BTreeMap<String, VideoRef>,
}

fn read_jsonl(path: &Path) -> Result<Vec<Value>> {
    let text = String::from_utf8(read_bounded(path, MAX_JSONL_BYTES)?)
        .map_err(|e| IngestError::invalid(path, format!("not UTF-8 text: {e}")))?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        out.push(
            serde_json::from_str(line)
                .map_err(|e| IngestError::invalid(path, format!("line {}: not valid JSON: {e}", i + 1)))?,
        );
    }
    Ok(out)
}

pub(super) fn load_tasks(confine: &crate::confine::Root, info: &Info) -> Result<HashMap<i64, String>> {
    let root = confine.dir();
    let mut tasks = HashMap::new();
    if info.is_v3() {
        let p = root.join("meta/tasks.parquet");
        if !p.exists() {
            return Ok(tasks);
        }
        confine.check_inside(&p, "meta/tasks.parquet")?;
        for b in open_parquet(&p)? {
            let idx =
                col(&b, "task_index").ok_or_else(|| IngestError::invalid(&p, "no task_index column"))?;
            let idx = ints(&p, idx, "task_index")?;
            let names = ["task", "__index_level_0__"]
                .iter()
                .find_map(|n| col(&b, n).and_then(strings))
                .or_else(|| {
                    b.columns()
                        .iter()
                        .find(|c| matches!(c.data_type(), DataType::Utf8 | DataType::LargeUtf8))
                        .and_then(strings)
                })
                .ok_or_else(|| IngestError::invalid(&p, "no task text column"))?;
            for (i, t) in idx.into_iter().zip(names) {
                tasks.insert(i, t);
            }
        }
    } else {
        let p = root.join("meta/tasks.jsonl");
        if !p.exists() {
            return Ok(tasks);
        }
        confine.check_inside(&p, "meta/tasks.jsonl")?;
        for v in read_jsonl(&p)? {
            if let (Some(i), Some(t)) =
                (v.get("task_index").and_then(|x| x.as_i64()), v.get("task").and_then(|x| x.as_str()))
            {
                tasks.insert(i, t.to_string());
            }
        }
    }
    Ok(tasks)
}

pub(super) fn load_episodes(confine: &crate::confine::Root, info: &Info) -> Result<Vec<EpisodeMeta>> {
    let root = confine.dir();
    let mut eps = if info.is_v3() { episodes_v3(confine, info)? } else { episodes_v2(confine, info)? };
    eps.sort_by_key(|e| e.episode_index);
    for w in eps.windows(2) {
        if w[0].episode_index == w[1].episode_index {
            return Err(IngestError::invalid(
                root,
                format!("episode {} is listed twice in the episode metadata", w[0].episode_index),
            ));
        }
    }
    if eps.is_empty() {
        return Err(IngestError::invalid(root, "the dataset lists no episodes"));
    }
    Ok(eps)
}

/// v3.0: the rows of `meta/episodes/chunk-*/file-*.parquet`, file by file.
fn episodes_v3(confine: &crate::confine::Root, info: &Info) -> Result<Vec<EpisodeMeta>> {
    let root = confine.dir();
    let dir = root.join("meta/episodes");
    confine.check_inside(&dir, "meta/episodes")?;
    let mut files: Vec<PathBuf> = crate::hashing::list_files(&dir)
        .map_err(|e| match e {
            IngestError::Io { .. } => IngestError::invalid(
                &dir,
                "missing: a v3.0 dataset needs meta/episodes/chunk-*/file-*.parquet",
            ),
            refused => refused,
        })?
        .into_iter()
        .filter(|(r, _)| r.ends_with(".parquet"))
        .map(|(_, p)| p)
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(IngestError::invalid(&dir, "no episode Parquet files"));
    }
    let video_keys: Vec<String> = info.video_keys().iter().map(|f| f.key.clone()).collect();
    let mut eps = Vec::new();
    for p in files {
        for b in open_parquet(&p)? {
            episode_rows(&p, &b, &video_keys, &mut eps)?;
        }
    }
    Ok(eps)
}

/// One record batch of a v3.0 episodes file (`p`), one [`EpisodeMeta`] per row.
fn episode_rows(p: &Path, b: &RecordBatch, video_keys: &[String], eps: &mut Vec<EpisodeMeta>) -> Result<()> {
    let n = b.num_rows();
    let need = |name: &str| -> Result<Vec<i64>> {
        let c = col(b, name).ok_or_else(|| IngestError::invalid(p, format!("no {name} column")))?;
        ints(p, c, name)
    };
    let idx = need("episode_index")?;
    let opt_ints =
        |name: &str| -> Result<Option<Vec<i64>>> { col(b, name).map(|c| ints(p, c, name)).transpose() };
    let length = opt_ints("length")?;
    let dchunk = opt_ints("data/chunk_index")?;
    let dfile = opt_ints("data/file_index")?;
    let from = opt_ints("dataset_from_index")?;
    let to = opt_ints("dataset_to_index")?;
    let tasks = col(b, "tasks").and_then(list_strings);
    type VideoCols = (String, Vec<i64>, Vec<i64>, Vec<f64>);
    let mut vids: Vec<VideoCols> = Vec::new();
    for k in video_keys {
        let c = opt_ints(&format!("videos/{k}/chunk_index"))?;
        let f = opt_ints(&format!("videos/{k}/file_index"))?;
        let t = col(b, &format!("videos/{k}/from_timestamp"))
            .map(|c| floats64(p, c, "from_timestamp"))
            .transpose()?;
        match (c, f, t) {
            (Some(c), Some(f), Some(t)) => vids.push((k.clone(), c, f, t)),
            _ => {
                return Err(IngestError::invalid(
                    p,
                    format!(
                    "no videos/{k}/{{chunk_index,file_index,from_timestamp}} columns for video feature {k}"
                ),
                ))
            }
        }
    }
    for r in 0..n {
        let nonneg = |v: i64, what: &str| -> Result<u64> {
            u64::try_from(v).map_err(|_| IngestError::invalid(p, format!("negative {what} {v}")))
        };
        let mut videos = BTreeMap::new();
        for (k, c, f, t) in &vids {
            videos.insert(
                k.clone(),
                VideoRef {
                    chunk_index: nonneg(c[r], "chunk_index")?,
                    file_index: nonneg(f[r], "file_index")?,
                    from_timestamp: t[r],
                },
            );
        }
        eps.push(EpisodeMeta {
            episode_index: nonneg(idx[r], "episode_index")?,
            tasks: tasks.as_ref().map(|t| t[r].clone()).unwrap_or_default(),
            length: length.as_ref().map(|l| nonneg(l[r], "length")).transpose()?,
            data_chunk: dchunk.as_ref().map(|l| nonneg(l[r], "data/chunk_index")).transpose()?.unwrap_or(0),
            data_file: dfile.as_ref().map(|l| nonneg(l[r], "data/file_index")).transpose()?.unwrap_or(0),
            from_index: from.as_ref().map(|l| nonneg(l[r], "dataset_from_index")).transpose()?,
            to_index: to.as_ref().map(|l| nonneg(l[r], "dataset_to_index")).transpose()?,
            videos,
        });
    }
    Ok(())
}

/// v2.1: the lines of `meta/episodes.jsonl`.
fn episodes_v2(confine: &crate::confine::Root, info: &Info) -> Result<Vec<EpisodeMeta>> {
    let root = confine.dir();
    let mut eps = Vec::new();
    let p = root.join("meta/episodes.jsonl");
    if !p.exists() {
        return Err(IngestError::invalid(&p, "missing: a v2.1 dataset needs meta/episodes.jsonl"));
    }
    confine.check_inside(&p, "meta/episodes.jsonl")?;
    for v in read_jsonl(&p)? {
        let idx = v
            .get("episode_index")
            .and_then(|x| x.as_u64())
            .ok_or_else(|| IngestError::invalid(&p, format!("entry without episode_index: {v}")))?;
        let tasks = v
            .get("tasks")
            .and_then(|t| t.as_array())
            .map(|a| a.iter().filter_map(|x| x.as_str().map(str::to_string)).collect())
            .unwrap_or_default();
        eps.push(EpisodeMeta {
            episode_index: idx,
            tasks,
            length: v.get("length").and_then(|x| x.as_u64()),
            data_chunk: idx / info.chunks_size,
            ..Default::default()
        });
    }
    Ok(eps)
}
