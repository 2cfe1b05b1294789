//! Logging the selected episodes into the recording stream: each episode's trajectory, action,
//! state, reward, verifier score and cameras as columns on the `step` / `time` timelines, then the
//! summary and the blueprint. The trajectories, cameras and summary have their own submodules.

mod cameras;
mod summary;
mod trajectory;

use crate::blueprint::{blueprint, EpisodeEntities};
use crate::selection::select_episodes;
use crate::{rr, StepScorer, ViewError, ViewOptions, ViewReport, MAX_STATE_DIMS};
use arrow::array::{Array, Float64Array, Int32Array, RecordBatch};
use re_sdk::blueprint::BlueprintActivation;
use re_sdk::log::TimeColumn;
use re_sdk::RecordingStream;
use re_sdk_types::archetypes::{Scalars, SeriesLines};
use re_sdk_types::components::Color;
use std::collections::{BTreeSet, HashMap, HashSet};
use store::{EpisodeRecord, Label, Store, StoreError};
use summary::ScoreAcc;

const GREEN: Color = Color(re_sdk_types::datatypes::Rgba32::from_rgb(40, 180, 70));
const RED: Color = Color(re_sdk_types::datatypes::Rgba32::from_rgb(220, 50, 47));
const GREY: Color = Color(re_sdk_types::datatypes::Rgba32::from_rgb(150, 150, 150));
const BLUE: Color = Color(re_sdk_types::datatypes::Rgba32::from_rgb(60, 110, 220));

fn label_color(l: Label) -> Color {
    match l {
        Label::Success => GREEN,
        Label::Failure => RED,
        Label::Unknown => GREY,
    }
}

/// The episode path `episodes/L/ID` (the id is one path part, escaped if needed).
pub fn episode_path(label: Label, id: &str) -> String {
    let part = re_sdk::EntityPathPart::from(id);
    format!("episodes/{}/{}", label.as_str(), part.escaped_string())
}

fn indexes(t: &[i64], ts: &[f64]) -> [TimeColumn; 2] {
    [
        TimeColumn::new_sequence("step", t.iter().copied()),
        TimeColumn::new_duration_secs("time", ts.iter().copied()),
    ]
}

fn f64_col<'a>(batch: &'a RecordBatch, name: &str) -> Result<&'a Float64Array, ViewError> {
    batch
        .column_by_name(name)
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| ViewError::Invalid(format!("steps have no float64 column {name:?}")))
}

/// The stream plus the entity paths written so far.
struct Out<'a> {
    rec: &'a RecordingStream,
    entities: HashSet<String>,
    /// Video object (store key) → its AssetVideo entity: each video is embedded once, however
    /// many episodes share it (LeRobot v3.0 keeps a camera's episodes in one mp4).
    videos: HashMap<String, String>,
}

/// One episode's step indexes: `t` and its `timestamp` (seconds since the episode start).
#[derive(Clone, Copy)]
struct StepIndex<'a> {
    t: &'a [i64],
    ts: &'a [f64],
}

impl StepIndex<'_> {
    /// The `step` and `time` columns of the rows `rows`.
    fn of(&self, rows: impl Iterator<Item = usize> + Clone) -> [TimeColumn; 2] {
        indexes(
            &rows.clone().map(|i| self.t[i]).collect::<Vec<_>>(),
            &rows.map(|i| self.ts[i]).collect::<Vec<_>>(),
        )
    }
}

impl Out<'_> {
    fn send(
        &mut self,
        path: String,
        idx: &[TimeColumn],
        cols: Vec<re_sdk::SerializedComponentColumn>,
    ) -> Result<(), ViewError> {
        self.rec.send_columns(path.as_str(), idx.iter().cloned(), cols).map_err(rr)?;
        self.entities.insert(path);
        Ok(())
    }

    /// A scalar series entity of `dim` series (named `names`), `values` row-major over the steps.
    fn series(
        &mut self,
        idx: &[TimeColumn],
        color: Color,
        path: String,
        names: Vec<String>,
        dim: usize,
        values: Vec<f32>,
    ) -> Result<(), ViewError> {
        self.rec
            .log_static(path.as_str(), &SeriesLines::new().with_colors(vec![color; dim]).with_names(names))
            .map_err(rr)?;
        let n = values.len() / dim.max(1);
        let values: Vec<f64> = values.into_iter().map(f64::from).collect();
        let cols = Scalars::new(values).columns(std::iter::repeat_n(dim, n)).map_err(rr)?.collect();
        self.send(path, idx, cols)
    }
}

/// One episode's (non-empty) steps as they are logged: where, in which colour, on which indexes.
struct EpisodeSteps<'e> {
    ep: &'e EpisodeRecord,
    batch: &'e RecordBatch,
    /// Rows (steps) of `batch`, at least one.
    n: usize,
    label: Label,
    color: Color,
    /// The episode's entity path, `episodes/L/ID`.
    base: String,
    t: Vec<i64>,
    ts: Vec<f64>,
    /// The `step` and `time` columns of every row.
    idx: [TimeColumn; 2],
    /// The observation keys and their dims.
    obs: Vec<(String, usize)>,
}

impl<'e> EpisodeSteps<'e> {
    fn new(ep: &'e EpisodeRecord, batch: &'e RecordBatch) -> Result<Self, ViewError> {
        let n = batch.num_rows();
        let label = ep.label;
        let t: Vec<i64> =
            match batch.column_by_name("t").and_then(|c| c.as_any().downcast_ref::<Int32Array>()) {
                Some(a) => a.values().iter().map(|&v| v as i64).collect(),
                None => (0..n as i64).collect(),
            };
        let ts: Vec<f64> = f64_col(batch, "timestamp")?.values().to_vec();
        let idx = indexes(&t, &ts);
        let obs = store::steps::observation_keys(batch.schema().as_ref());
        let (color, base) = (label_color(label), episode_path(label, &ep.id));
        Ok(EpisodeSteps { ep, batch, n, label, color, base, t, ts, idx, obs })
    }

    fn at(&self) -> StepIndex<'_> {
        StepIndex { t: &self.t, ts: &self.ts }
    }
}

/// Everything a recording accumulates while its episodes are logged.
struct Recorder<'a> {
    out: Out<'a>,
    opts: &'a ViewOptions,
    scorer: Option<&'a dyn StepScorer>,
    report: ViewReport,
    /// What each episode logged, for the blueprint.
    logged: Vec<EpisodeEntities>,
    /// Per-step verifier scores by label, for the summary.
    acc: HashMap<Label, ScoreAcc>,
    lengths: HashMap<Label, Vec<usize>>,
    /// 2 or 3: the trajectories' dims, set by the first episode with a position.
    pos_dims: Option<usize>,
    cameras_seen: BTreeSet<String>,
}

/// Logs everything; shared by the file and the in-memory writers.
pub(crate) async fn record(
    rec: &RecordingStream,
    store: &Store,
    opts: &ViewOptions,
    scorer: Option<&dyn StepScorer>,
) -> Result<ViewReport, ViewError> {
    let episodes = select_episodes(store, opts).await?;
    let mut r = Recorder::new(rec, opts, scorer);
    r.log_episodes(store, &episodes).await?;
    r.check_positions_found()?;
    if scorer.is_some() {
        r.log_score_summary()?;
    }
    r.log_summary_info()?;
    r.send_blueprint()?;
    Ok(r.into_report())
}

impl<'a> Recorder<'a> {
    fn new(rec: &'a RecordingStream, opts: &'a ViewOptions, scorer: Option<&'a dyn StepScorer>) -> Self {
        Recorder {
            out: Out { rec, entities: HashSet::new(), videos: HashMap::new() },
            opts,
            scorer,
            report: ViewReport { scored: scorer.is_some(), ..Default::default() },
            logged: Vec::new(),
            acc: HashMap::new(),
            lengths: HashMap::new(),
            pos_dims: None,
            cameras_seen: BTreeSet::new(),
        }
    }

    /// Reads and logs every episode of `episodes`.
    ///
    /// The episodes' steps are read in one pass grouped by steps file (each row group once) and
    /// logged as they arrive, one episode (its frames included) in memory at a time; the
    /// blueprint orders them back by the listing.
    async fn log_episodes(&mut self, store: &Store, episodes: &[EpisodeRecord]) -> Result<(), ViewError> {
        let locations =
            episodes.iter().map(store::EpisodeLocation::try_from).collect::<Result<Vec<_>, StoreError>>()?;
        let mut steps = store.read_episodes(locations);
        let mut seen = vec![false; episodes.len()];
        while let Some(item) = steps.next().await {
            let item = item.map_err(StoreError::from)?;
            let i = item.index;
            let (Some(ep), batch) = (episodes.get(i), item.steps) else {
                return Err(StoreError::Corrupt(format!(
                    "the read returned episode #{i} of {}",
                    episodes.len()
                ))
                .into());
            };
            seen[i] = true;
            if batch.num_rows() == 0 {
                continue;
            }
            self.log_episode(store, i, &EpisodeSteps::new(ep, &batch)?).await?;
        }
        if let Some(i) = seen.iter().position(|s| !s) {
            return Err(StoreError::Corrupt(format!("episode {} was not read", episodes[i].id)).into());
        }
        self.logged.sort_by_key(|e| e.index);
        self.report.cameras = std::mem::take(&mut self.cameras_seen).into_iter().collect();
        Ok(())
    }

    /// One episode: its trajectory, scalar series, score and cameras. `index`: its place in the
    /// listing.
    async fn log_episode(
        &mut self,
        store: &Store,
        index: usize,
        e: &EpisodeSteps<'_>,
    ) -> Result<(), ViewError> {
        self.count_episode(e.label, e.n);
        self.log_trajectory(e)?;
        self.log_series(e)?;
        let has_score = self.log_score(e)?;
        let has_steering = self.log_steering(e)?;
        let cameras = self.log_cameras(store, e).await?;
        tracing::debug!(episode = %e.ep.id, steps = e.n, label = %e.label, "recorded episode");
        self.logged.push(EpisodeEntities {
            index,
            base: e.base.clone(),
            label: e.label,
            has_score,
            has_steering,
            cameras,
        });
        Ok(())
    }

    fn count_episode(&mut self, label: Label, n: usize) {
        let report = &mut self.report;
        report.episodes += 1;
        report.steps += n;
        match label {
            Label::Success => report.success += 1,
            Label::Failure => report.failure += 1,
            Label::Unknown => report.unknown += 1,
        }
        self.lengths.entry(label).or_default().push(n);
    }

    /// Action and state dims (and the reward) as scalar series, coloured by label.
    fn log_series(&mut self, e: &EpisodeSteps<'_>) -> Result<(), ViewError> {
        let (batch, base, color, idx) = (e.batch, &e.base, e.color, &e.idx);
        if let Ok((dim, values)) = store::steps::vector_column(batch, "action") {
            let names = (0..dim).map(|i| format!("action[{i}]")).collect();
            self.out.series(idx, color, format!("{base}/action"), names, dim, values)?;
        }
        for (key, dim) in &e.obs {
            if *dim > MAX_STATE_DIMS {
                continue;
            }
            let (dim, values) =
                store::steps::vector_column(batch, &format!("{}{key}", store::steps::OBS_PREFIX))?;
            let names = (0..dim).map(|i| format!("{key}[{i}]")).collect();
            let part = re_sdk::EntityPathPart::from(key.as_str()).escaped_string();
            self.out.series(idx, color, format!("{base}/state/{part}"), names, dim, values)?;
        }
        if let Some(r) = batch
            .column_by_name("reward")
            .and_then(|c| c.as_any().downcast_ref::<arrow::array::Float32Array>())
        {
            let vals: Vec<f32> =
                (0..e.n).map(|i| if r.is_valid(i) { r.value(i) } else { f32::NAN }).collect();
            self.out.series(idx, color, format!("{base}/reward"), vec!["reward".into()], 1, vals)?;
        }
        Ok(())
    }

    /// The verifier's score along the episode (with a scorer); true if logged.
    fn log_score(&mut self, e: &EpisodeSteps<'_>) -> Result<bool, ViewError> {
        let Some(sc) = self.scorer else { return Ok(false) };
        let (ep, n) = (e.ep, e.n);
        let scores = sc
            .score_steps(e.batch)
            .map_err(|err| ViewError::Scorer { episode: ep.id.clone(), message: err.to_string() })?;
        if scores.len() != n {
            return Err(ViewError::Scorer {
                episode: ep.id.clone(),
                message: format!("{} scores for {n} steps", scores.len()),
            });
        }
        self.acc.entry(e.label).or_default().add(&scores);
        self.out.series(&e.idx, e.color, format!("{}/score", e.base), vec!["score".into()], 1, scores)?;
        Ok(true)
    }

    /// A steered episode's best-of-N steps (its steering column): at each, the lowest, median
    /// and highest candidate score and the chosen one's (NaN, so no line, on the other steps);
    /// true if the episode has any.
    fn log_steering(&mut self, e: &EpisodeSteps<'_>) -> Result<bool, ViewError> {
        let log = verifier::steps::steering_log(e.batch)
            .map_err(|err| ViewError::Invalid(format!("episode {}: {err}", e.ep.id)))?;
        if log.is_empty() {
            return Ok(false);
        }
        let mut values = vec![f32::NAN; e.n * 4];
        for s in &log {
            let Some(row) = values.get_mut(s.t as usize * 4..s.t as usize * 4 + 4) else { continue };
            let mut sorted = s.scores.clone();
            sorted.sort_by(f32::total_cmp);
            row.copy_from_slice(&[
                sorted[0],
                sorted[sorted.len() / 2],
                sorted[sorted.len() - 1],
                s.scores[s.chosen as usize],
            ]);
        }
        let names = ["lowest", "median", "highest", "chosen"].map(String::from).to_vec();
        self.out.series(&e.idx, e.color, format!("{}/steering", e.base), names, 4, values)?;
        self.report.steered_episodes += 1;
        Ok(true)
    }

    /// Position keys asked for that no episode has are an error, not an empty recording.
    fn check_positions_found(&self) -> Result<(), ViewError> {
        let (opts, report) = (self.opts, &self.report);
        if !opts.position_keys.is_empty() && report.episodes > 0 && report.without_position == report.episodes
        {
            return Err(ViewError::Invalid(format!(
                "no episode has the position keys {:?} among its observation keys",
                opts.position_keys
            )));
        }
        Ok(())
    }

    fn send_blueprint(&self) -> Result<(), ViewError> {
        let bp = blueprint(&self.logged, self.pos_dims, self.scorer.is_some());
        bp.send(self.out.rec, BlueprintActivation { make_active: true, make_default: true }).map_err(rr)
    }

    /// The report, with the entity paths that have data (sorted).
    fn into_report(self) -> ViewReport {
        let mut report = self.report;
        let mut ents: Vec<String> = self.out.entities.into_iter().collect();
        ents.sort();
        report.entities = ents;
        report
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn episode_paths_escape_ids() {
        assert_eq!(episode_path(Label::Success, "abc123-4"), "episodes/success/abc123-4");
        assert!(!episode_path(Label::Failure, "a/b").ends_with("a/b"));
    }
}
