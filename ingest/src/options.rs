//! Options of one ingest run (what `ufops ingest` passes in) and success-label sources.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use crate::error::{IngestError, Result};
use crate::model::Label;

/// Which reader to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Format {
    /// Decide from the path: a folder with `meta/info.json` is LeRobot, a file starting with the
    /// HDF5 signature is robomimic (ALOHA when it has `/observations/qpos` and `/action` and no
    /// `/data`; a folder of `episode_<i>.hdf5` too), one starting with the MCAP magic is MCAP.
    #[default]
    Auto,
    Robomimic,
    /// ALOHA / ACT: one HDF5 file per episode (a folder of `episode_<i>.hdf5`, or one of them).
    Aloha,
    Lerobot,
    /// What `lerobot-eval` writes: a folder with `eval_info.json` and `videos/`.
    LerobotEval,
    Mcap,
}

impl Format {
    pub fn as_str(self) -> &'static str {
        match self {
            Format::Auto => "auto",
            Format::Robomimic => "robomimic",
            Format::Aloha => "aloha",
            Format::Lerobot => "lerobot",
            Format::LerobotEval => "lerobot-eval",
            Format::Mcap => "mcap",
        }
    }
}

impl std::str::FromStr for Format {
    type Err = IngestError;
    fn from_str(s: &str) -> Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "auto" => Ok(Format::Auto),
            "robomimic" | "hdf5" | "h5" => Ok(Format::Robomimic),
            "aloha" | "act" => Ok(Format::Aloha),
            "lerobot" => Ok(Format::Lerobot),
            "lerobot-eval" | "lerobot_eval" => Ok(Format::LerobotEval),
            "mcap" => Ok(Format::Mcap),
            other => Err(IngestError::Usage(format!(
                "unknown format {other:?}: expected auto, robomimic, aloha, lerobot, lerobot-eval or mcap"
            ))),
        }
    }
}

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Everything `ufops ingest` needs besides the path and the store.
#[derive(Debug, Clone, Default)]
pub struct IngestOptions {
    /// `--policy NAME`
    pub policy: String,
    /// `--checkpoint ID`
    pub checkpoint: String,
    /// `--task T`: the task of every episode (overrides what the source says).
    pub task: Option<String>,
    /// `--format`
    pub format: Format,
    /// `--success-file FILE`: JSON `{"demo_0": true, ...}` or CSV `demo_0,true` lines.
    pub success_file: Option<PathBuf>,
    /// `--success-from rewards [--reward-threshold X]`: success iff the last reward >= X
    /// (X defaults to 1.0). `None` = not asked.
    pub success_from_rewards: Option<f64>,
    /// `--mapping FILE.toml` (MCAP topic/field mapping).
    pub mapping: Option<PathBuf>,
    /// `--recover`: ingest what is complete in a truncated recording instead of refusing it.
    pub recover: bool,
    /// Show a progress bar (only honoured when stderr is a terminal).
    pub progress: bool,
    /// How much memory the ingest may hold (the defaults suit any source size).
    pub memory: MemoryBudget,
    /// `--run NAME --steering SPEC …`: the evaluation run every episode belongs to.
    pub run: Option<store::RunInput>,
    /// `--images png|video`: image cameras as one PNG per step (lossless, the default) or as
    /// one H.264 MP4 per episode and camera (lossy; see [`crate::video`]).
    pub images: crate::model::ImageStorage,
    /// `--intervention-key NAME`: the source's per-step human-takeover flag (a LeRobot feature,
    /// a robomimic demo's or an ALOHA file's dataset) when it is not named `intervention`.
    pub intervention_key: Option<String>,
    /// `--start-seed S`: the seed of a lerobot-eval output's first episode (lerobot-eval's
    /// `--seed`; episode i of a task ran with S + i), which lerobot >= 0.4 does not record.
    pub start_seed: Option<i64>,
    /// `--steering-log FILE`: the source's steering telemetry (a sidecar of best-of-N records,
    /// [`crate::steering`]); by default `<source>.steering.parquet` (a folder's
    /// `steering.parquet`) when it exists.
    pub steering_log: Option<std::path::PathBuf>,
}

/// What one ingest may hold in memory, whatever the source's size: readers decode one episode
/// at a time, and these bound the buffers between the reader and the object store. With the
/// defaults a multi-GB source is ingested in a few hundred MB; tests shrink them to check that
/// memory does not grow with the source.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MemoryBudget {
    /// Decoded episodes on their way from the reader to the writer (one always passes, however
    /// large: an episode is the unit of work).
    pub in_flight_bytes: usize,
    /// Encoded steps the writer may hold while the source's sha256 (the episode ids' prefix) is
    /// still being computed; past it the reader waits for the hash.
    pub unhashed_bytes: usize,
    /// Encoded bytes of the row group being filled (the store's default row group size).
    pub row_group_bytes: usize,
    /// Bytes of the steps file being filled before it is uploaded and the next one begins.
    pub file_bytes: usize,
}

impl Default for MemoryBudget {
    fn default() -> Self {
        MemoryBudget {
            in_flight_bytes: 64 << 20,
            unhashed_bytes: 96 << 20,
            row_group_bytes: store::steps::ROW_GROUP_MAX_BYTES,
            file_bytes: store::MAX_STEPS_FILE_BYTES,
        }
    }
}

/// Success labels given by the user in a side file.
#[derive(Debug, Clone, PartialEq)]
pub struct SuccessFile {
    /// `success-file:<file name>`
    pub label_source: String,
    pub labels: HashMap<String, bool>,
}

impl SuccessFile {
    pub fn load(path: &Path) -> Result<SuccessFile> {
        let text = std::fs::read_to_string(path).map_err(|e| IngestError::io(path, e))?;
        let labels = parse_success_text(&text).map_err(|m| IngestError::invalid(path, m))?;
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        Ok(SuccessFile { label_source: format!("success-file:{name}"), labels })
    }

    /// The label of an episode; accepts `demo_3`, `3` or `episode_3` style keys.
    pub fn get(&self, name: &str, index: u32) -> Option<bool> {
        if let Some(b) = self.labels.get(name) {
            return Some(*b);
        }
        let idx = index.to_string();
        if let Some(b) = self.labels.get(&idx) {
            return Some(*b);
        }
        let digits: String = name.chars().rev().take_while(|c| c.is_ascii_digit()).collect();
        if !digits.is_empty() {
            let n: String = digits.chars().rev().collect();
            let n = n.trim_start_matches('0');
            let n = if n.is_empty() { "0" } else { n };
            return self.labels.get(n).copied();
        }
        None
    }
}

fn parse_bool(v: &str) -> Option<bool> {
    match v.trim().trim_matches('"').to_ascii_lowercase().as_str() {
        "true" | "1" | "yes" | "y" | "success" | "s" | "t" => Some(true),
        "false" | "0" | "no" | "n" | "failure" | "fail" | "f" => Some(false),
        _ => None,
    }
}

/// JSON object `{name: bool|0/1|"success"}` or CSV lines `name,bool` (a header line is skipped).
pub fn parse_success_text(text: &str) -> std::result::Result<HashMap<String, bool>, String> {
    let trimmed = text.trim_start();
    let mut out = HashMap::new();
    if trimmed.starts_with('{') {
        let v: serde_json::Value = serde_json::from_str(text).map_err(|e| format!("not valid JSON: {e}"))?;
        let obj = v.as_object().ok_or("expected a JSON object {\"demo_0\": true, ...}")?;
        for (k, v) in obj {
            let b = match v {
                serde_json::Value::Bool(b) => *b,
                serde_json::Value::Number(n) => n.as_f64().map(|x| x != 0.0).unwrap_or(false),
                serde_json::Value::String(s) => {
                    parse_bool(s).ok_or_else(|| format!("value of {k:?} is not a boolean: {s:?}"))?
                }
                other => return Err(format!("value of {k:?} is not a boolean: {other}")),
            };
            out.insert(k.clone(), b);
        }
    } else {
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let mut parts = line.splitn(2, [',', ';', '\t']);
            let name = parts.next().unwrap_or("").trim().trim_matches('"');
            let val = parts
                .next()
                .ok_or_else(|| format!("line {}: expected `name,true|false`, got {line:?}", i + 1))?;
            match parse_bool(val) {
                Some(b) => {
                    out.insert(name.to_string(), b);
                }
                None if i == 0 => continue, // header
                None => {
                    return Err(format!("line {}: {val:?} is not true/false", i + 1));
                }
            }
        }
    }
    if out.is_empty() {
        return Err("no labels found (expected JSON {\"demo_0\": true} or CSV demo_0,true)".into());
    }
    Ok(out)
}

/// How a reader labels episodes, resolved from [`IngestOptions`].
#[derive(Debug, Clone, Default)]
pub struct ReadOptions {
    pub task: Option<String>,
    pub success_file: Option<SuccessFile>,
    pub success_from_rewards: Option<f64>,
    pub mapping: Option<crate::mapping::Mapping>,
    pub recover: bool,
    pub policy: String,
    pub checkpoint: String,
    /// The per-step takeover flag's name in the source (see [`IngestOptions::intervention_key`]).
    pub intervention_key: Option<String>,
    /// lerobot-eval's `--seed` (see [`IngestOptions::start_seed`]).
    pub start_seed: Option<i64>,
}

/// The name of a per-step human-takeover flag readers look for when `--intervention-key` names
/// none: LeRobot's DAgger recordings' feature, and what ufops' exports write.
pub const DEFAULT_INTERVENTION_KEY: &str = "intervention";

impl ReadOptions {
    /// The takeover flag's name in the source, and whether the user named it (then a source
    /// without it is refused rather than read without flags).
    pub fn intervention_key(&self) -> (&str, bool) {
        match &self.intervention_key {
            Some(k) => (k.as_str(), true),
            None => (DEFAULT_INTERVENTION_KEY, false),
        }
    }

    pub fn from_ingest(opts: &IngestOptions) -> Result<ReadOptions> {
        let success_file = opts.success_file.as_deref().map(SuccessFile::load).transpose()?;
        let mapping = opts.mapping.as_deref().map(crate::mapping::Mapping::load).transpose()?;
        Ok(ReadOptions {
            task: opts.task.clone(),
            success_file,
            success_from_rewards: opts.success_from_rewards,
            mapping,
            recover: opts.recover,
            policy: opts.policy.clone(),
            checkpoint: opts.checkpoint.clone(),
            intervention_key: opts.intervention_key.clone(),
            start_seed: opts.start_seed,
        })
    }

    /// A label from the user's side file or the rewards rule, if either was asked for.
    /// Returns `None` when neither applies (the reader then uses its own source or unknown).
    pub fn user_label(&self, name: &str, index: u32, rewards: &[f32]) -> Option<(Label, String)> {
        if let Some(sf) = &self.success_file {
            return Some(match sf.get(name, index) {
                Some(b) => (Label::from_bool(Some(b)), sf.label_source.clone()),
                None => (Label::Unknown, String::new()),
            });
        }
        if let Some(th) = self.success_from_rewards {
            let last = rewards.last().copied();
            let ok = last.map(|r| (r as f64) >= th).unwrap_or(false);
            return Some((Label::from_bool(Some(ok)), format!("rewards>={}", fmt_num(th))));
        }
        None
    }
}

pub(crate) fn fmt_num(x: f64) -> String {
    if x.fract() == 0.0 && x.abs() < 1e15 {
        format!("{}", x as i64)
    } else {
        format!("{x}")
    }
}
