//! `eval_info.json` in the two layouts `lerobot-eval` has written, read into one [`Evaluation`].
//!
//! * lerobot ≥ 0.4 (`lerobot/scripts/lerobot_eval.py`, `eval_policy_all`): `per_task` — one entry
//!   per `(task_group, task_id)` with `metrics.{sum_rewards, max_rewards, successes, video_paths}`
//!   (one value per episode, videos for the first rendered episodes) — plus `per_group` and
//!   `overall` aggregates. No seeds: episode i of every task ran with `--seed` + i.
//! * lerobot ≤ 0.3 (`lerobot/scripts/eval.py`, `eval_policy`): `per_episode` —
//!   `{episode_ix, sum_reward, max_reward, success, seed}` — plus `aggregated` and a top-level
//!   `video_paths`.
//!
//! Python's `json.dump` writes `NaN` and `Infinity` for such floats (an aggregate over no
//! episodes); they read as null. The file is read whole, at most [`MAX_EVAL_INFO_BYTES`], into
//! compact types (a flag, two floats and a seed per episode), never into a tree of values.

use std::collections::{BTreeMap, HashSet};
use std::path::Path;

use serde::de::{self, Deserializer, IgnoredAny, Visitor};
use serde::Deserialize;
use serde_json::{json, Map, Value};

use crate::error::{IngestError, Result};

/// The largest `eval_info.json` read (a real one is ~200 bytes per episode: 80,000 episodes).
pub(super) const MAX_EVAL_INFO_BYTES: u64 = 16 << 20;

/// Which `lerobot-eval` wrote the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Layout {
    /// lerobot ≥ 0.4: `per_task`, no seeds.
    PerTask,
    /// lerobot ≤ 0.3: `per_episode`, with seeds.
    PerEpisode,
}

impl Layout {
    pub(super) fn as_str(self) -> &'static str {
        match self {
            Layout::PerTask => "per_task (lerobot >= 0.4)",
            Layout::PerEpisode => "per_episode (lerobot <= 0.3)",
        }
    }
}

/// One task's episodes in their order (the 0.3 layout has one task without a name).
#[derive(Debug, Clone)]
pub(super) struct Task {
    pub(super) group: Option<String>,
    pub(super) id: Option<Value>,
    pub(super) episodes: Vec<Episode>,
    /// The video paths as the file lists them (the first rendered episodes', in order).
    pub(super) videos: Vec<String>,
}

impl Task {
    /// `<task_group>_<task_id>`: the name lerobot-eval gives the task's video folder.
    pub(super) fn name(&self) -> Option<String> {
        let group = self.group.as_ref()?;
        Some(match &self.id {
            Some(Value::String(s)) => format!("{group}_{s}"),
            Some(v) => format!("{group}_{v}"),
            None => group.clone(),
        })
    }
}

#[derive(Debug, Clone, PartialEq)]
pub(super) struct Episode {
    pub(super) success: Option<bool>,
    pub(super) sum_reward: Option<f64>,
    pub(super) max_reward: Option<f64>,
    /// The seed the file records (0.3 layout only).
    pub(super) seed: Option<i64>,
}

#[derive(Debug, Clone)]
pub(super) struct Evaluation {
    pub(super) layout: Layout,
    pub(super) tasks: Vec<Task>,
    /// The file's aggregates (`overall` and `per_group`, or `aggregated`), without video lists.
    pub(super) aggregates: Map<String, Value>,
}

/// `success`: a JSON bool (or 0/1, as numpy may leave it); null when it is null.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Flag(Option<bool>);

impl<'de> Deserialize<'de> for Flag {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Flag, D::Error> {
        struct V;
        impl Visitor<'_> for V {
            type Value = Flag;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a success flag (true/false, 1/0 or null)")
            }
            fn visit_bool<E: de::Error>(self, b: bool) -> std::result::Result<Flag, E> {
                Ok(Flag(Some(b)))
            }
            fn visit_u64<E: de::Error>(self, n: u64) -> std::result::Result<Flag, E> {
                match n {
                    0 | 1 => Ok(Flag(Some(n == 1))),
                    _ => Err(E::custom(format!("a success flag of {n} (expected true/false or 1/0)"))),
                }
            }
            fn visit_i64<E: de::Error>(self, n: i64) -> std::result::Result<Flag, E> {
                self.visit_u64(u64::try_from(n).map_err(|_| E::custom(format!("a success flag of {n}")))?)
            }
            fn visit_f64<E: de::Error>(self, x: f64) -> std::result::Result<Flag, E> {
                match x {
                    0.0 => Ok(Flag(Some(false))),
                    1.0 => Ok(Flag(Some(true))),
                    _ => Err(E::custom(format!("a success flag of {x} (expected true/false or 1/0)"))),
                }
            }
            fn visit_unit<E: de::Error>(self) -> std::result::Result<Flag, E> {
                Ok(Flag(None))
            }
        }
        d.deserialize_any(V)
    }
}

/// An aggregate block: its numbers kept, its video list (a copy of the tasks') skipped.
#[derive(Debug, Deserialize)]
#[serde(transparent)]
struct Aggregate {
    fields: BTreeMap<String, Scalar>,
}

/// A scalar of an aggregate; lists and objects are skipped.
#[derive(Debug)]
struct Scalar(Option<Value>);

impl<'de> Deserialize<'de> for Scalar {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Scalar, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Scalar;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a value")
            }
            fn visit_bool<E: de::Error>(self, b: bool) -> std::result::Result<Scalar, E> {
                Ok(Scalar(Some(json!(b))))
            }
            fn visit_u64<E: de::Error>(self, n: u64) -> std::result::Result<Scalar, E> {
                Ok(Scalar(Some(json!(n))))
            }
            fn visit_i64<E: de::Error>(self, n: i64) -> std::result::Result<Scalar, E> {
                Ok(Scalar(Some(json!(n))))
            }
            fn visit_f64<E: de::Error>(self, x: f64) -> std::result::Result<Scalar, E> {
                Ok(Scalar(Some(json!(x))))
            }
            fn visit_str<E: de::Error>(self, s: &str) -> std::result::Result<Scalar, E> {
                Ok(Scalar(Some(json!(s.chars().take(200).collect::<String>()))))
            }
            fn visit_unit<E: de::Error>(self) -> std::result::Result<Scalar, E> {
                Ok(Scalar(Some(Value::Null)))
            }
            fn visit_seq<A: de::SeqAccess<'de>>(self, mut a: A) -> std::result::Result<Scalar, A::Error> {
                while a.next_element::<IgnoredAny>()?.is_some() {}
                Ok(Scalar(None))
            }
            fn visit_map<A: de::MapAccess<'de>>(self, mut a: A) -> std::result::Result<Scalar, A::Error> {
                while a.next_entry::<IgnoredAny, IgnoredAny>()?.is_some() {}
                Ok(Scalar(None))
            }
        }
        d.deserialize_any(V)
    }
}

impl Aggregate {
    fn into_value(self) -> Value {
        Value::Object(self.fields.into_iter().filter_map(|(k, v)| v.0.map(|v| (k, v))).collect())
    }
}

#[derive(Debug, Deserialize)]
struct RawMetrics {
    #[serde(default)]
    sum_rewards: Vec<Option<f64>>,
    #[serde(default)]
    max_rewards: Vec<Option<f64>>,
    successes: Vec<Flag>,
    #[serde(default)]
    video_paths: Vec<String>,
}

#[derive(Debug, Deserialize)]
struct RawTask {
    task_group: Value,
    task_id: Value,
    metrics: RawMetrics,
}

#[derive(Debug, Deserialize)]
struct RawEpisode {
    episode_ix: Option<u64>,
    sum_reward: Option<f64>,
    max_reward: Option<f64>,
    success: Flag,
    seed: Option<i64>,
}

#[derive(Debug, Deserialize)]
struct Raw {
    per_task: Option<Vec<RawTask>>,
    per_group: Option<BTreeMap<String, Aggregate>>,
    overall: Option<Aggregate>,
    per_episode: Option<Vec<RawEpisode>>,
    aggregated: Option<Aggregate>,
    video_paths: Option<Vec<String>>,
}

/// What Python's `json.dump` writes for floats JSON has no words for.
const PYTHON_FLOATS: [&[u8]; 3] = [b"-Infinity", b"Infinity", b"NaN"];

/// Python's `NaN`, `Infinity` and `-Infinity` (outside strings) as `null`, so that a strict JSON
/// parser reads what `json.dump` wrote.
pub(super) fn python_floats_to_null(bytes: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(bytes.len());
    let (mut i, mut in_str, mut escaped) = (0, false, false);
    while i < bytes.len() {
        let b = bytes[i];
        if in_str {
            out.push(b);
            match (escaped, b) {
                (true, _) => escaped = false,
                (false, b'\\') => escaped = true,
                (false, b'"') => in_str = false,
                _ => {}
            }
            i += 1;
            continue;
        }
        let rest = &bytes[i..];
        if let Some(n) = PYTHON_FLOATS.iter().find(|t| rest.starts_with(t)).map(|t| t.len()) {
            out.extend_from_slice(b"null");
            i += n;
            continue;
        }
        in_str = b == b'"';
        out.push(b);
        i += 1;
    }
    out
}

fn task_group(v: Value) -> Option<String> {
    match v {
        Value::String(s) => Some(s),
        Value::Number(n) => Some(n.to_string()),
        _ => None,
    }
}

/// Parses `eval_info.json` (`path`, for errors) in either layout and checks that its lists agree.
pub(super) fn parse(path: &Path, bytes: &[u8]) -> Result<Evaluation> {
    let bytes = python_floats_to_null(bytes);
    let raw: Raw = serde_json::from_slice(&bytes)
        .map_err(|e| IngestError::invalid(path, format!("not a lerobot-eval eval_info.json: {e}")))?;
    let mut aggregates = Map::new();
    let (layout, tasks) = match (raw.per_task, raw.per_episode) {
        (Some(_), Some(_)) => {
            return Err(IngestError::invalid(
                path,
                "holds both `per_task` (lerobot >= 0.4) and `per_episode` (lerobot <= 0.3): not one lerobot-eval's output",
            ))
        }
        (None, None) => {
            return Err(IngestError::invalid(
                path,
                "not a lerobot-eval eval_info.json: it has neither `per_task` (lerobot >= 0.4) nor `per_episode` (lerobot <= 0.3)",
            ))
        }
        (Some(per_task), None) => {
            if let Some(o) = raw.overall {
                aggregates.insert("overall".into(), o.into_value());
            }
            if let Some(g) = raw.per_group {
                let g = g.into_iter().map(|(k, v)| (k, v.into_value())).collect();
                aggregates.insert("per_group".into(), Value::Object(g));
            }
            (Layout::PerTask, per_task_tasks(path, per_task)?)
        }
        (None, Some(per_episode)) => {
            if let Some(a) = raw.aggregated {
                aggregates.insert("aggregated".into(), a.into_value());
            }
            let episodes = per_episode
                .into_iter()
                .enumerate()
                .map(|(i, e)| match e.episode_ix {
                    Some(ix) if ix != i as u64 => Err(IngestError::invalid(
                        path,
                        format!("per_episode[{i}] has episode_ix {ix}: lerobot-eval numbers its episodes 0, 1, 2, …"),
                    )),
                    _ => Ok(Episode {
                        success: e.success.0,
                        sum_reward: e.sum_reward,
                        max_reward: e.max_reward,
                        seed: e.seed,
                    }),
                })
                .collect::<Result<Vec<_>>>()?;
            let videos = raw.video_paths.unwrap_or_default();
            (Layout::PerEpisode, vec![Task { group: None, id: None, episodes, videos }])
        }
    };
    if tasks.iter().all(|t| t.episodes.is_empty()) {
        return Err(IngestError::invalid(path, "lists no episodes"));
    }
    Ok(Evaluation { layout, tasks, aggregates })
}

fn per_task_tasks(path: &Path, per_task: Vec<RawTask>) -> Result<Vec<Task>> {
    let mut seen = HashSet::new();
    let mut tasks = Vec::with_capacity(per_task.len());
    for (k, t) in per_task.into_iter().enumerate() {
        let group = task_group(t.task_group)
            .ok_or_else(|| IngestError::invalid(path, format!("per_task[{k}] has no task_group (a name)")))?;
        let id = match t.task_id {
            Value::Number(n) if n.is_i64() || n.is_u64() => Value::Number(n),
            Value::String(s) => Value::String(s),
            other => {
                return Err(IngestError::invalid(
                    path,
                    format!("per_task[{k}] has task_id {other}: an integer (or a name) was expected"),
                ))
            }
        };
        let task = Task { group: Some(group), id: Some(id), episodes: Vec::new(), videos: Vec::new() };
        let name = task.name().unwrap_or_default();
        if !seen.insert(name.clone()) {
            return Err(IngestError::invalid(path, format!("task {name} appears twice in per_task")));
        }
        let m = t.metrics;
        let n = m.successes.len();
        for (what, len) in [("sum_rewards", m.sum_rewards.len()), ("max_rewards", m.max_rewards.len())] {
            if len != n {
                return Err(IngestError::invalid(
                    path,
                    format!("task {name}: {n} successes but {len} {what} (one per episode)"),
                ));
            }
        }
        let episodes = (0..n)
            .map(|i| Episode {
                success: m.successes[i].0,
                sum_reward: m.sum_rewards[i],
                max_reward: m.max_rewards[i],
                seed: None,
            })
            .collect();
        tasks.push(Task { episodes, videos: m.video_paths, ..task });
    }
    Ok(tasks)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn python_non_finite_floats_read_as_null_outside_strings() {
        let s = br#"{"a": NaN, "b": [Infinity, -Infinity, 1.5], "c": "NaN \" Infinity"}"#;
        let v: Value = serde_json::from_slice(&python_floats_to_null(s)).unwrap();
        assert_eq!(v, json!({"a": null, "b": [null, null, 1.5], "c": "NaN \" Infinity"}));
    }

    #[test]
    fn both_layouts_and_their_checks() {
        let p = Path::new("eval_info.json");
        let v04 = br#"{"per_task": [{"task_group": "libero_10", "task_id": 3, "metrics": {
            "sum_rewards": [1.0, 0.0], "max_rewards": [1.0, NaN], "successes": [true, false],
            "video_paths": ["out/videos/libero_10_3/eval_episode_0.mp4"]}}],
            "per_group": {"libero_10": {"pc_success": 50.0, "video_paths": ["x"]}},
            "overall": {"pc_success": 50.0, "n_episodes": 2, "video_paths": ["x"]}}"#;
        let e = parse(p, v04).unwrap();
        assert_eq!(e.layout, Layout::PerTask);
        assert_eq!(e.tasks[0].name().as_deref(), Some("libero_10_3"));
        assert_eq!(e.tasks[0].episodes[1].max_reward, None);
        assert_eq!(e.tasks[0].episodes[0].success, Some(true));
        assert_eq!(e.aggregates["overall"], json!({"pc_success": 50.0, "n_episodes": 2}));
        assert_eq!(e.aggregates["per_group"], json!({"libero_10": {"pc_success": 50.0}}));

        let v03 = br#"{"per_episode": [{"episode_ix": 0, "sum_reward": 0.0, "max_reward": 0.0,
            "success": false, "seed": 7}], "aggregated": {"pc_success": 0.0}, "video_paths": []}"#;
        let e = parse(p, v03).unwrap();
        assert_eq!((e.layout, e.tasks.len(), e.tasks[0].name()), (Layout::PerEpisode, 1, None));
        assert_eq!(e.tasks[0].episodes[0].seed, Some(7));

        let short = br#"{"per_task": [{"task_group": "g", "task_id": 0, "metrics": {
            "sum_rewards": [1.0], "max_rewards": [1.0, 0.0], "successes": [true, false]}}]}"#;
        let err = parse(p, short).unwrap_err().to_string();
        assert!(err.contains("2 successes but 1 sum_rewards"), "{err}");
        let twice = br#"{"per_task": [
            {"task_group": "g", "task_id": 0, "metrics": {"successes": []}},
            {"task_group": "g", "task_id": 0, "metrics": {"successes": []}}]}"#;
        assert!(parse(p, twice).unwrap_err().to_string().contains("task g_0 appears twice"));
        let err = parse(p, br#"{"per_episode": [{"episode_ix": 3, "success": 2}]}"#).unwrap_err().to_string();
        assert!(err.contains("success flag of 2"), "{err}");
        let err = parse(p, br#"{"overall": {}}"#).unwrap_err().to_string();
        assert!(err.contains("neither `per_task`"), "{err}");
    }
}
