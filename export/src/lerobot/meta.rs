//! `meta/`: `info.json` (features, fps, paths, provenance), `stats.json`, `tasks.parquet` and
//! `episodes/chunk-000/file-000.parquet` (one [`EpisodeRow`] per episode, as the data
//! [`Writer`] recorded it).

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::path::Path;
use std::sync::Arc;

use arrow::array::{
    ArrayRef, Float64Array, Int64Array, ListBuilder, RecordBatch, StringArray, StringBuilder,
};
use arrow::datatypes::{DataType, Field, Schema};
use parquet::arrow::ArrowWriter;
use serde_json::{json, Map, Value};
use store::steps::INTERVENTION_COLUMN;

use super::data::{data_props, EpisodeRow, Writer};
use super::{
    feature_key, source_feature, CHUNKS_SIZE, CODEBASE_VERSION, DATA_FILE_BYTES, DATA_PATH, VALIDITY_KEY,
    VIDEO_PATH,
};
use crate::{ExportError, Result, Selected};

/// Writes `meta/` under `root` once every episode's data is written: tasks, episodes, stats and
/// `info.json` (whose features take names and video shapes from the sources' metadata).
pub(super) fn write_meta(
    root: &Path,
    w: &Writer,
    sources: &[Value],
    robot_type: Option<String>,
    sel: &Selected,
) -> Result<()> {
    let meta = root.join("meta");
    write_parquet(&meta.join("tasks.parquet"), &tasks_batch(w.tasks)?)?;
    write_parquet(
        &meta.join("episodes/chunk-000/file-000.parquet"),
        &episodes_batch(&w.episodes, &w.layout.videos)?,
    )?;
    let mut stats = Map::new();
    for (k, s) in &w.stats {
        stats.insert(k.clone(), s.json());
    }
    write_json(&meta.join("stats.json"), &Value::Object(stats))?;

    let features = features_json(w, sources)?;
    let n = w.episodes.len();
    let info = json!({
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": n,
        "total_frames": w.frames,
        "total_tasks": w.tasks.len(),
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILE_BYTES >> 20,
        "video_files_size_in_mb": 200,
        "fps": w.fps,
        "splits": {"train": format!("0:{n}")},
        "data_path": DATA_PATH,
        "video_path": if w.layout.videos.is_empty() { Value::Null } else { json!(VIDEO_PATH) },
        "features": features,
        "ufops": sel.provenance("lerobot"),
    });
    write_json(&meta.join("info.json"), &info)
}

/// `info.json`'s features: dtype, shape and names of every data column (vector names from a
/// LeRobot source of the same shape; videos as their source describes them).
fn features_json(w: &Writer, sources: &[Value]) -> Result<Map<String, Value>> {
    let mut features = Map::new();
    let vector = |key: &str, dim: usize| -> Value {
        let names = source_feature(sources, key)
            .filter(|f| f.get("shape") == Some(&json!([dim])))
            .and_then(|f| f.get("names").cloned())
            .unwrap_or(Value::Null);
        json!({"dtype": "float32", "shape": [dim], "names": names})
    };
    for (k, d) in &w.layout.obs {
        features.insert(feature_key(k), vector(&feature_key(k), *d));
    }
    features.insert("action".into(), vector("action", w.layout.action));
    for (k, shape) in &w.layout.images {
        features.insert(
            feature_key(k),
            json!({"dtype": "image", "shape": shape, "names": ["height", "width", "channel"]}),
        );
    }
    for k in &w.layout.videos {
        let fk = feature_key(k);
        let f = source_feature(sources, &fk).filter(|f| f.get("dtype") == Some(&json!("video")));
        let f = f.ok_or_else(|| {
            ExportError::invalid(format!(
                "video {fk}: its source does not say the video's shape (not a LeRobot source)"
            ))
        })?;
        features.insert(fk, f);
    }
    features.insert("next.reward".into(), json!({"dtype": "float32", "shape": [1], "names": null}));
    features.insert("next.done".into(), json!({"dtype": "bool", "shape": [1], "names": null}));
    if w.labeled {
        features.insert("next.success".into(), json!({"dtype": "bool", "shape": [1], "names": null}));
    }
    if w.layout.intervention {
        features.insert(INTERVENTION_COLUMN.into(), json!({"dtype": "bool", "shape": [1], "names": null}));
    }
    if w.layout.validity {
        let dtype = if w.validity_tasks.is_some() { "int64" } else { "bool" };
        features.insert(VALIDITY_KEY.into(), json!({"dtype": dtype, "shape": [1], "names": null}));
    }
    features.insert("timestamp".into(), json!({"dtype": "float32", "shape": [1], "names": null}));
    for k in ["frame_index", "episode_index", "index", "task_index"] {
        features.insert(k.into(), json!({"dtype": "int64", "shape": [1], "names": null}));
    }
    Ok(features)
}

fn write_parquet(path: &Path, batch: &RecordBatch) -> Result<()> {
    std::fs::create_dir_all(path.parent().expect("has a parent")).map_err(|e| ExportError::io(path, e))?;
    let f = File::create(path).map_err(|e| ExportError::io(path, e))?;
    let mut w = ArrowWriter::try_new(f, batch.schema(), Some(data_props()))
        .map_err(|e| ExportError::write(path, e))?;
    w.write(batch).map_err(|e| ExportError::write(path, e))?;
    w.close().map_err(|e| ExportError::write(path, e))?;
    Ok(())
}

fn write_json(path: &Path, v: &Value) -> Result<()> {
    let text = serde_json::to_string_pretty(v).map_err(|e| ExportError::write(path, e))?;
    std::fs::write(path, text).map_err(|e| ExportError::io(path, e))
}

/// `meta/tasks.parquet`: `task_index`, `task`, with the pandas index metadata lerobot reads the
/// task text by (`pd.read_parquet(...)` gives a frame indexed by task).
fn tasks_batch(tasks: &BTreeMap<String, i64>) -> Result<RecordBatch> {
    let mut by_index: Vec<(&i64, &String)> = tasks.iter().map(|(t, i)| (i, t)).collect();
    by_index.sort();
    let pandas = json!({
        "index_columns": ["task"],
        "column_indexes": [{"name": null, "field_name": null, "pandas_type": "unicode", "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": null},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": null}
        ],
        "attributes": {}, "creator": {"library": "ufops", "version": env!("CARGO_PKG_VERSION")}, "pandas_version": "2.3.3"
    });
    let schema = Schema::new(vec![
        Field::new("task_index", DataType::Int64, false),
        Field::new("task", DataType::Utf8, false),
    ])
    .with_metadata(HashMap::from([("pandas".to_string(), pandas.to_string())]));
    RecordBatch::try_new(
        Arc::new(schema),
        vec![
            Arc::new(Int64Array::from_iter_values(by_index.iter().map(|(i, _)| **i))),
            Arc::new(StringArray::from_iter_values(by_index.iter().map(|(_, t)| t.as_str()))),
        ],
    )
    .map_err(|e| ExportError::invalid(e.to_string()))
}

fn episodes_batch(rows: &[EpisodeRow], video_keys: &[String]) -> Result<RecordBatch> {
    let mut fields = vec![
        Field::new("episode_index", DataType::Int64, false),
        Field::new("tasks", DataType::List(Arc::new(Field::new("item", DataType::Utf8, true))), false),
        Field::new("length", DataType::Int64, false),
        Field::new("data/chunk_index", DataType::Int64, false),
        Field::new("data/file_index", DataType::Int64, false),
        Field::new("dataset_from_index", DataType::Int64, false),
        Field::new("dataset_to_index", DataType::Int64, false),
    ];
    let ints = |f: &dyn Fn(&EpisodeRow) -> i64| -> ArrayRef {
        Arc::new(Int64Array::from_iter_values(rows.iter().map(f)))
    };
    let mut tasks = ListBuilder::new(StringBuilder::new());
    for r in rows {
        tasks.values().append_value(&r.task);
        tasks.append(true);
    }
    let mut cols: Vec<ArrayRef> = vec![
        ints(&|r| r.index),
        Arc::new(tasks.finish()),
        ints(&|r| r.length),
        ints(&|r| (r.data_file / CHUNKS_SIZE) as i64),
        ints(&|r| (r.data_file % CHUNKS_SIZE) as i64),
        ints(&|r| r.from),
        ints(&|r| r.from + r.length),
    ];
    for (v, k) in video_keys.iter().enumerate() {
        let fk = feature_key(k);
        fields.push(Field::new(format!("videos/{fk}/chunk_index"), DataType::Int64, false));
        fields.push(Field::new(format!("videos/{fk}/file_index"), DataType::Int64, false));
        fields.push(Field::new(format!("videos/{fk}/from_timestamp"), DataType::Float64, false));
        fields.push(Field::new(format!("videos/{fk}/to_timestamp"), DataType::Float64, false));
        cols.push(ints(&|r| (r.videos[v].0 / CHUNKS_SIZE) as i64));
        cols.push(ints(&|r| (r.videos[v].0 % CHUNKS_SIZE) as i64));
        cols.push(Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.videos[v].1))));
        cols.push(Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.videos[v].2))));
    }
    fields.push(Field::new("meta/episodes/chunk_index", DataType::Int64, false));
    fields.push(Field::new("meta/episodes/file_index", DataType::Int64, false));
    cols.push(ints(&|_| 0));
    cols.push(ints(&|_| 0));
    fields.push(Field::new("ufops/episode_id", DataType::Utf8, false));
    fields.push(Field::new("ufops/label", DataType::Utf8, false));
    fields.push(Field::new("ufops/source_name", DataType::Utf8, false));
    fields.push(Field::new("ufops/split_part", DataType::Utf8, true));
    cols.push(Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.id.as_str()))));
    cols.push(Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.label.as_str()))));
    cols.push(Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.source_name.as_str()))));
    cols.push(Arc::new(StringArray::from_iter(rows.iter().map(|r| r.part.as_deref()))));
    if rows.iter().any(|r| r.score.is_some()) {
        fields.push(Field::new("ufops/verifier_score", DataType::Float64, true));
        cols.push(Arc::new(Float64Array::from_iter(rows.iter().map(|r| r.score))));
    }
    if rows.iter().any(|r| r.failure_cause.is_some() || r.spans.is_some()) {
        fields.push(Field::new("ufops/failure_cause", DataType::Utf8, true));
        fields.push(Field::new("ufops/label_spans", DataType::Utf8, true));
        cols.push(Arc::new(StringArray::from_iter(rows.iter().map(|r| r.failure_cause.as_deref()))));
        cols.push(Arc::new(StringArray::from_iter(rows.iter().map(|r| r.spans.as_deref()))));
    }
    RecordBatch::try_new(Arc::new(Schema::new(fields)), cols).map_err(|e| ExportError::invalid(e.to_string()))
}
