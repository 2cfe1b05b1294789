//! Verifier inputs from stored steps (feature `steps`): a steps batch as the store reads it
//! (`obs.<key>`, `action`, `action_chunk` columns, layers joined as `obs.<layer>` with their
//! producer in the field metadata) → [`EpisodeSeries`] → the samples of [`build_samples`], and
//! [`StepScorer`], the one way anything (export curation, the review queue's score job, the
//! viewer, `ufops rank`) scores a stored episode's steps; and the encoding of steering telemetry
//! in the store's steering column ([`steering_array`](crate::steps::steering_array),
//! [`steering_log`](crate::steps::steering_log)).

use std::sync::Arc;

use arrow::array::{
    Array, ArrayRef, AsArray, Float16Array, Float32Array, Int32Array, Int64Array, ListArray, RecordBatch,
    StringArray, StructArray, UInt32Array,
};
use arrow::buffer::{NullBuffer, OffsetBuffer};
use arrow::datatypes::{DataType, Field, Float16Type, Float32Type, Int32Type, Schema, UInt32Type};

use crate::samples::{build_samples, EpisodeSeries, ObsSeries, Samples};
use crate::telemetry::SteeringStep;
use crate::{ArtifactConfig, Result, Verifier, VerifierError};

fn input_err(e: impl std::fmt::Display) -> VerifierError {
    VerifierError::Input(e.to_string())
}

/// The episode `id` of a steps batch, its observation series in the order of `keys`.
pub fn episode_from_steps(
    id: &str,
    success: bool,
    batch: &RecordBatch,
    keys: &[String],
) -> Result<EpisodeSeries> {
    let mut obs = Vec::with_capacity(keys.len());
    for k in keys {
        let (dim, values) = store::steps::vector_column(batch, &format!("{}{k}", store::steps::OBS_PREFIX))
            .map_err(|e| input_err(format!("episode {id}: {e}")))?;
        obs.push(ObsSeries { key: k.clone(), dim, values });
    }
    let (action_dim, actions) = store::steps::vector_column(batch, "action").map_err(input_err)?;
    let action_chunk = match batch.schema().field_with_name("action_chunk") {
        Ok(_) => {
            let (hd, values) = store::steps::vector_column(batch, "action_chunk").map_err(input_err)?;
            if action_dim == 0 || hd % action_dim != 0 {
                return Err(input_err(format!(
                    "episode {id}: action_chunk width {hd} is not a multiple of the action dim {action_dim}"
                )));
            }
            Some((hd / action_dim, values))
        }
        Err(_) => None,
    };
    Ok(EpisodeSeries {
        id: id.to_string(),
        success,
        obs,
        actions,
        action_dim,
        action_chunk,
        policy_steps: None,
    })
}

/// The verifier inputs of every step of a stored episode, built exactly as for training
/// (observation history; stored chunk, else the next H actions; step index) with the raw chunks
/// put into the space the artifact takes (`input.action_space`).
pub fn step_inputs(cfg: &ArtifactConfig, batch: &RecordBatch) -> Result<Samples> {
    let input = &cfg.input.layout;
    if !cfg.architecture.extra_inputs.is_empty() {
        return Err(input_err("building stored steps for a verifier with extra inputs is not supported"));
    }
    let keys: Vec<String> = input.obs_keys.iter().map(|k| k.key.clone()).collect();
    // Layer keys: the batch must hold them (a read joined with the layers) from the producer
    // the verifier was trained on.
    let schema = batch.schema();
    let mut provided = Vec::new();
    for (key, want) in input.required_producers() {
        let field = schema.field_with_name(&format!("{}{key}", store::steps::OBS_PREFIX)).map_err(|_| {
            input_err(format!(
                "this verifier reads layer {key} (features of producer {}): read the steps with that layer",
                crate::short_hash(want)
            ))
        })?;
        provided.push((key, field.metadata().get(store::PRODUCER_META_KEY).cloned().unwrap_or_default()));
    }
    input.check_producers(provided.iter().map(|(k, p)| (*k, p.as_str())))?;
    let mut ep = episode_from_steps("scored", false, batch, &keys)?;
    if ep.action_chunk.as_ref().is_some_and(|(h, _)| *h != input.chunk_len) {
        ep.action_chunk = None;
    }
    let mut s = build_samples(std::slice::from_ref(&ep), input, cfg.gamma.unwrap_or(0.99))?;
    cfg.input.action_space.raw_to_input(&mut s.act, input.action_dim);
    Ok(s)
}

/// Scores every step of a stored episode. [`Verifier`] implements it on [`step_inputs`]; tests
/// may bring their own.
pub trait StepScorer: Send + Sync {
    /// One score per row of `steps` (a steps batch as the store reads it).
    fn score_steps(&self, steps: &RecordBatch) -> Result<Vec<f32>>;
    /// The layers the scorer reads (observation keys that are layers): a caller joins them to
    /// the steps it passes.
    fn layers(&self) -> Vec<String> {
        Vec::new()
    }
}

impl StepScorer for Verifier {
    fn score_steps(&self, steps: &RecordBatch) -> Result<Vec<f32>> {
        let s = step_inputs(self.config(), steps)?;
        self.score(&s.obs, &s.t, &s.act, 1)
    }
    fn layers(&self) -> Vec<String> {
        self.config().input.layout.required_producers().iter().map(|(k, _)| k.to_string()).collect()
    }
}

/// The steering column of an episode of `rows` steps ([`store::steps::STEERING_COLUMN`]): each
/// record on the row of its step `t`, null elsewhere. Refuses an inconsistent record, a step
/// outside the episode and two records on one step.
pub fn steering_array(log: &[SteeringStep], rows: usize) -> Result<ArrayRef> {
    let mut at: Vec<Option<&SteeringStep>> = vec![None; rows];
    for s in log {
        s.check().map_err(input_err)?;
        let slot = at.get_mut(s.t as usize).ok_or_else(|| {
            input_err(format!("steering step at t={} is outside the episode's {rows} steps", s.t))
        })?;
        if slot.replace(s).is_some() {
            return Err(input_err(format!("two steering steps at t={}", s.t)));
        }
    }
    steering_struct(&at)
}

/// The `episode_index` column of a steering sidecar ([`steering_sidecar_batch`]).
pub const SIDECAR_EPISODE_COLUMN: &str = "episode_index";

/// A steering sidecar's rows: one per best-of-N step, `episode_index` (int64: the source's
/// episode index, as the store's `source_index`), `t` (int32) and the record as the store's
/// steering struct (never null). A file of these beside a source is what `ufops ingest` picks
/// up; [`steering_log`] reads a batch of it back.
pub fn steering_sidecar_batch(records: &[(u64, SteeringStep)]) -> Result<RecordBatch> {
    for (_, s) in records {
        s.check().map_err(input_err)?;
    }
    let episode = Int64Array::from_iter_values(records.iter().map(|(e, _)| *e as i64));
    let t = Int32Array::from_iter_values(records.iter().map(|(_, s)| s.t as i32));
    let slots: Vec<Option<&SteeringStep>> = records.iter().map(|(_, s)| Some(s)).collect();
    let st = steering_struct(&slots)?;
    let schema = Schema::new(vec![
        Field::new(SIDECAR_EPISODE_COLUMN, DataType::Int64, false),
        Field::new("t", DataType::Int32, false),
        Field::new(store::steps::STEERING_COLUMN, st.data_type().clone(), false),
    ]);
    RecordBatch::try_new(Arc::new(schema), vec![Arc::new(episode) as ArrayRef, Arc::new(t), st])
        .map_err(input_err)
}

/// The steering struct of `slots` (null where `None`).
fn steering_struct(slots: &[Option<&SteeringStep>]) -> Result<ArrayRef> {
    let (mut score_off, mut cand_off) = (vec![0i32], vec![0i32]);
    let (mut scores, mut cands) = (Vec::new(), Vec::new());
    let (mut ids, mut chosen, mut latency, mut valid) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for s in slots {
        valid.push(s.is_some());
        if let Some(s) = s {
            scores.extend_from_slice(&s.scores);
            cands.extend(s.candidates.iter().map(|&v| half::f16::from_f32(v)));
        }
        let offset =
            |n: usize| i32::try_from(n).map_err(|_| input_err("steering log too large for one column"));
        score_off.push(offset(scores.len())?);
        cand_off.push(offset(cands.len())?);
        ids.push(s.map_or("", |s| s.artifact_id.as_str()));
        chosen.push(s.map_or(0, |s| s.chosen));
        latency.push(s.map_or(0, |s| s.latency_us));
    }
    let DataType::Struct(fields) = store::steps::steering_data_type() else {
        unreachable!("the steering column is a struct")
    };
    let list_field = |i: usize| match fields[i].data_type() {
        DataType::List(f) => f.clone(),
        _ => unreachable!("scores and candidates are lists"),
    };
    let columns: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from(ids)),
        Arc::new(UInt32Array::from(chosen)),
        Arc::new(UInt32Array::from(latency)),
        Arc::new(
            ListArray::try_new(
                list_field(3),
                OffsetBuffer::new(score_off.into()),
                Arc::new(Float32Array::from(scores)),
                None,
            )
            .map_err(input_err)?,
        ),
        Arc::new(
            ListArray::try_new(
                list_field(4),
                OffsetBuffer::new(cand_off.into()),
                Arc::new(Float16Array::from(cands)),
                None,
            )
            .map_err(input_err)?,
        ),
    ];
    let nulls = valid.iter().any(|v| !v).then(|| NullBuffer::from(valid));
    Ok(Arc::new(StructArray::try_new(fields, columns, nulls).map_err(input_err)?))
}

/// The steering log of a steps batch (one episode's steps as the store reads them): a record per
/// non-null row of its [`store::steps::STEERING_COLUMN`], in step order; empty without the column.
/// Every record is checked ([`SteeringStep::check`]).
pub fn steering_log(batch: &RecordBatch) -> Result<Vec<SteeringStep>> {
    let Some(col) = batch.column_by_name(store::steps::STEERING_COLUMN) else { return Ok(Vec::new()) };
    if col.data_type() != &store::steps::steering_data_type() {
        return Err(input_err(format!(
            "the steering column is {}, not the steering record",
            col.data_type()
        )));
    }
    let st = col.as_struct();
    let t = batch
        .column_by_name("t")
        .and_then(|c| c.as_primitive_opt::<Int32Type>())
        .ok_or_else(|| input_err("steps have no int32 column t"))?;
    let ids = st.column(0).as_string::<i32>();
    let chosen = st.column(1).as_primitive::<UInt32Type>();
    let latency = st.column(2).as_primitive::<UInt32Type>();
    let scores = st.column(3).as_list::<i32>();
    let cands = st.column(4).as_list::<i32>();
    let mut log = Vec::new();
    for row in (0..st.len()).filter(|&r| st.is_valid(r)) {
        let s = SteeringStep {
            t: u32::try_from(t.value(row))
                .map_err(|_| input_err(format!("negative step {}", t.value(row))))?,
            artifact_id: ids.value(row).to_string(),
            candidates: cands
                .value(row)
                .as_primitive::<Float16Type>()
                .values()
                .iter()
                .map(|v| v.to_f32())
                .collect(),
            scores: scores.value(row).as_primitive::<Float32Type>().values().to_vec(),
            chosen: chosen.value(row),
            latency_us: latency.value(row),
        };
        s.check().map_err(input_err)?;
        log.push(s);
    }
    Ok(log)
}
