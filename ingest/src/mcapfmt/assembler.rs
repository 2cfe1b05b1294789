//! The episode assembler's state (channels, buffered samples, pending and open episodes), and
//! the episodes' lifecycle: emitted once their messages are in, and closed at the end of the file.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::Path;

use serde_json::{json, Map, Value};

use super::decode::{Decoder, SchemaRec};
use super::McapSummary;
use crate::error::{IngestError, Result};
use crate::mapping::Mapping;
use crate::options::ReadOptions;
use crate::sink::{EpisodeSink, SourceMeta};

/// How long (in log time) after an episode's end we keep reading before we consider its messages
/// complete (tolerates slightly out-of-order chunks).
const GRACE_NS: u64 = 2_000_000_000;

/// What a decoded message contributes.
#[derive(Debug, Clone)]
pub(super) enum Kind {
    Other,
    Action(Vec<f32>),
    Obs(usize, Vec<f32>),
    Reward(f32),
}

#[derive(Debug, Clone)]
pub(super) struct Sample {
    pub(super) t: u64,
    pub(super) chan: u16,
    pub(super) kind: Kind,
}

#[derive(Debug, Clone)]
pub(super) struct PendingEp {
    pub(super) index: Option<i64>,
    pub(super) start: u64,
    pub(super) end: u64,
    pub(super) success: Option<bool>,
    pub(super) meta: BTreeMap<String, String>,
    pub(super) label_source: String,
}

pub(super) struct Chan {
    pub(super) topic: String,
    pub(super) message_encoding: String,
    pub(super) schema_id: u16,
    /// (roles) this channel feeds
    pub(super) action: bool,
    pub(super) obs: Vec<usize>,
    pub(super) reward: bool,
    pub(super) events: bool,
    pub(super) decoder: Option<std::result::Result<Decoder, String>>,
}

pub(super) struct Assembler<'a> {
    pub(super) path: &'a Path,
    pub(super) opts: &'a ReadOptions,
    pub(super) mapping: Mapping,
    pub(super) obs_keys: Vec<String>,
    pub(super) schemas: HashMap<u16, SchemaRec>,
    pub(super) chans: HashMap<u16, Chan>,
    pub(super) buf: VecDeque<Sample>,
    pub(super) pending: Vec<PendingEp>,
    pub(super) open_events: HashMap<i64, (u64, BTreeMap<String, String>)>,
    pub(super) max_t: u64,
    pub(super) emitted: usize,
    pub(super) emitted_indices: Vec<i64>,
    pub(super) skipped_empty: Vec<i64>,
    pub(super) next_index: i64,
    pub(super) summary: McapSummary,
    pub(super) source_sent: bool,
    pub(super) other_metadata: Map<String, Value>,
    pub(super) saw_episode_markers: bool,
    pub(super) first_t: Option<u64>,
}

impl<'a> Assembler<'a> {
    pub(super) fn new(path: &'a Path, opts: &'a ReadOptions) -> Self {
        let mapping = opts.mapping.clone().unwrap_or_default();
        let obs_keys = mapping.observations.keys().cloned().collect();
        Assembler {
            path,
            opts,
            mapping,
            obs_keys,
            schemas: HashMap::new(),
            chans: HashMap::new(),
            buf: VecDeque::new(),
            pending: Vec::new(),
            open_events: HashMap::new(),
            max_t: 0,
            emitted: 0,
            emitted_indices: Vec::new(),
            skipped_empty: Vec::new(),
            next_index: 0,
            summary: McapSummary::default(),
            source_sent: false,
            other_metadata: Map::new(),
            saw_episode_markers: false,
            first_t: None,
        }
    }

    pub(super) fn err(&self, msg: impl Into<String>) -> IngestError {
        IngestError::invalid(self.path, msg)
    }

    pub(super) fn send_source(&mut self, sink: &mut dyn EpisodeSink) -> Result<()> {
        if self.source_sent {
            return Ok(());
        }
        self.source_sent = true;
        let mut topics = Map::new();
        let mut ids: Vec<_> = self.chans.keys().copied().collect();
        ids.sort();
        for id in ids {
            let c = &self.chans[&id];
            let s = self.schemas.get(&c.schema_id);
            topics.insert(
                c.topic.clone(),
                json!({"message_encoding": c.message_encoding, "schema": s.map(|s| s.name.clone()), "schema_encoding": s.map(|s| s.encoding.clone())}),
            );
        }
        let obs: Map<String, Value> = self
            .mapping
            .observations
            .iter()
            .map(|(k, f)| (k.clone(), json!({"topic": f.topic, "field": f.field})))
            .collect();
        let meta = json!({
            "profile": self.summary.profile,
            "library": self.summary.library,
            "topics": topics,
            "metadata": self.other_metadata,
            "mapping": {
                "action": {"topic": self.mapping.action.topic, "field": self.mapping.action.field},
                "observations": obs,
                "rate_hz": self.mapping.rate_hz,
                "episodes": {"metadata": self.mapping.episodes.metadata, "topic": self.mapping.episodes.topic},
            },
        });
        sink.source(SourceMeta { format: "mcap".into(), metadata: meta })
    }

    pub(super) fn add_pending(&mut self, p: PendingEp) {
        if self.pending.iter().any(|q| q.start == p.start && q.end == p.end) {
            return;
        }
        self.pending.push(p);
        self.pending.sort_by_key(|p| (p.end, p.start));
    }

    /// Emits the pending episodes whose messages are all in (or all, at the end of the file).
    pub(super) fn flush(&mut self, sink: &mut dyn EpisodeSink, all: bool) -> Result<()> {
        while let Some(p) = self.pending.first() {
            let ready = all || self.max_t > p.end.saturating_add(GRACE_NS);
            if !ready {
                break;
            }
            let p = self.pending.remove(0);
            self.emit(p, sink)?;
        }
        if self.pending.is_empty() && self.open_events.is_empty() && self.saw_episode_markers {
            // nothing can refer to samples that are older than what was emitted and no episode is open
        }
        Ok(())
    }

    fn emit(&mut self, p: PendingEp, sink: &mut dyn EpisodeSink) -> Result<()> {
        let index = p.index.unwrap_or(self.next_index);
        self.next_index = self.next_index.max(index.saturating_add(1));
        let mut samples: Vec<&Sample> = self.buf.iter().filter(|s| s.t >= p.start && s.t <= p.end).collect();
        samples.sort_by_key(|s| s.t);
        let mut counts: BTreeMap<String, u64> = BTreeMap::new();
        for s in &samples {
            if let Some(c) = self.chans.get(&s.chan) {
                *counts.entry(c.topic.clone()).or_default() += 1;
            }
        }
        let ep = self.build(&p, index, &samples, counts)?;
        // drop what no later episode can use
        let end = p.end;
        let min_start =
            self.pending.iter().map(|q| q.start).chain(self.open_events.values().map(|v| v.0)).min();
        self.buf.retain(|s| s.t > end || min_start.map(|m| s.t >= m).unwrap_or(false));
        match ep {
            Some(ep) => {
                self.send_source(sink)?;
                self.emitted += 1;
                self.emitted_indices.push(index);
                sink.episode(ep)?;
            }
            None => self.skipped_empty.push(index),
        }
        Ok(())
    }

    /// The data section was cut off (`m` says where): emits the episodes whose data continued
    /// past their end, then refuses the file unless `--recover`; returns the episodes lost.
    pub(super) fn end_cut_off(&mut self, m: String, sink: &mut dyn EpisodeSink) -> Result<Vec<String>> {
        // episodes complete: data continued past their end
        let max_t = self.max_t;
        let (complete, partial): (Vec<PendingEp>, Vec<PendingEp>) =
            self.pending.drain(..).partition(|p| max_t > p.end);
        for p in complete {
            self.emit(p, sink)?;
        }
        let mut lost: Vec<String> = partial
            .iter()
            .map(|p| format!("episode {}", p.index.map(|i| i.to_string()).unwrap_or_else(|| "?".into())))
            .collect();
        let mut opens: Vec<_> = self.open_events.keys().copied().collect();
        opens.sort();
        lost.extend(opens.iter().map(|i| format!("episode {i} (started, never ended)")));
        let last_end = self.summary.last_log_time.unwrap_or(0);
        let trailing = self.buf.iter().filter(|s| s.chan != u16::MAX).count();
        let complete_list = if self.emitted_indices.is_empty() {
            "none".to_string()
        } else {
            self.emitted_indices.iter().map(|i| i.to_string()).collect::<Vec<_>>().join(", ")
        };
        let what = format!(
            "truncated MCAP: {m}. Recovered {} messages (last log time {last_end}); complete episodes: {complete_list}; {} message(s) after the last complete episode belong to an episode that was cut off{}",
            self.summary.message_count,
            trailing,
            if lost.is_empty() { String::new() } else { format!(" ({})", lost.join(", ")) }
        );
        if !self.opts.recover {
            return Err(IngestError::Truncated {
                path: self.path.to_path_buf(),
                msg: format!(
                    "{what}. Run again with --recover to ingest the {} complete episode(s)",
                    self.emitted
                ),
                recoverable: self.emitted,
            });
        }
        self.summary.truncated = Some(what);
        Ok(lost)
    }

    /// All data records are in (`cut` says how the summary section was cut, if it was): closes
    /// the episodes still open at the last message, makes the whole recording one episode when
    /// nothing marks episodes, and emits every pending episode.
    pub(super) fn end_complete(&mut self, cut: Option<String>, sink: &mut dyn EpisodeSink) -> Result<()> {
        if let Some(m) = cut {
            // only the summary section was cut: all data is there
            self.summary.truncated = Some(format!("{m} (summary section only; all data records present)"));
        }
        // open event episodes at the end: close them at the last message
        if !self.open_events.is_empty() {
            let mut opens: Vec<_> = self.open_events.drain().collect();
            opens.sort_by_key(|(i, _)| *i);
            for (i, (start, meta)) in opens {
                let end = self.summary.last_log_time.unwrap_or(start);
                let ls = String::new();
                self.add_pending(PendingEp {
                    index: Some(i),
                    start,
                    end,
                    success: None,
                    meta,
                    label_source: ls,
                });
            }
        }
        if !self.saw_episode_markers && self.summary.message_count > 0 {
            // the whole recording is one episode
            let start = self.first_t.unwrap_or(0);
            let end = self.summary.last_log_time.unwrap_or(start);
            self.add_pending(PendingEp {
                index: Some(0),
                start,
                end,
                success: None,
                meta: BTreeMap::new(),
                label_source: String::new(),
            });
        }
        self.flush(sink, true)?;
        Ok(())
    }
}
