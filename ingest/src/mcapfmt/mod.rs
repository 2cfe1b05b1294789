//! MCAP recordings, read linearly with the `mcap` crate's sans-io `LinearReader` (bounded memory:
//! only the decoded values of mapped topics inside not-yet-finished episodes are buffered).
//!
//! Message encodings: `cdr` with `ros2msg` schemas ([`crate::ros2msg`]), `protobuf` with
//! FileDescriptorSet schemas (prost-reflect), `json`. Episodes come from Metadata records named
//! `episode` (`start_ns`, `end_ns` inclusive, `success`, `policy`, `checkpoint`, ...) or from an
//! event topic (`/episode_event`: `{"event":"start","episode":i}` ... `{"event":"end","episode":i,
//! "success":bool}`); which topic/field becomes what is set by a [`Mapping`].
//!
//! [`Mapping`]: crate::mapping::Mapping

mod assembler;
mod decode;
mod messages;
mod records;
mod steps;

use std::collections::{BTreeMap, HashMap};
use std::io::Read;
use std::path::Path;

use mcap::records::Record;

use crate::error::{IngestError, Result};
use crate::options::ReadOptions;
use crate::sink::EpisodeSink;
use assembler::Assembler;
pub use decode::{Decoder, SchemaRec, MAX_MAPPED_MESSAGE_BYTES};
use records::{stream_records, End};
pub use records::{MAX_CHUNK_BYTES, MAX_CHUNK_RATIO};

/// What a linear read of an MCAP file saw.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct McapSummary {
    pub profile: String,
    pub library: String,
    pub message_count: u64,
    pub message_counts: BTreeMap<String, u64>,
    pub schemas: usize,
    pub channels: usize,
    pub attachments: usize,
    pub metadata: Vec<(String, BTreeMap<String, String>)>,
    pub first_log_time: Option<u64>,
    pub last_log_time: Option<u64>,
    /// Set when the file ended in the middle of a record or without its footer.
    pub truncated: Option<String>,
    /// True when the data section ended cleanly (DataEnd seen) even if the summary was cut.
    pub data_complete: bool,
}

/// Reads the whole file and counts what it holds (no decoding).
pub fn scan(path: &Path, r: &mut dyn Read, size_hint: u64) -> Result<McapSummary> {
    let mut s = McapSummary::default();
    let mut topics: HashMap<u16, String> = HashMap::new();
    let mut saw_footer = false;
    let end = stream_records(path, r, size_hint, &mut |rec| {
        match rec {
            Record::Header(h) => {
                s.profile = h.profile;
                s.library = h.library;
            }
            Record::Schema { .. } => s.schemas += 1,
            Record::Channel(c) if !topics.contains_key(&c.id) => {
                topics.insert(c.id, c.topic);
                s.channels += 1;
            }
            Record::Message { header, .. } => {
                s.message_count += 1;
                let t = topics
                    .get(&header.channel_id)
                    .cloned()
                    .unwrap_or_else(|| format!("<channel {}>", header.channel_id));
                *s.message_counts.entry(t).or_default() += 1;
                s.first_log_time = Some(s.first_log_time.map_or(header.log_time, |x| x.min(header.log_time)));
                s.last_log_time = Some(s.last_log_time.map_or(header.log_time, |x| x.max(header.log_time)));
            }
            Record::Attachment { .. } => s.attachments += 1,
            Record::Metadata(m) => s.metadata.push((m.name, m.metadata)),
            Record::DataEnd(_) => s.data_complete = true,
            Record::Footer(_) => saw_footer = true,
            _ => {}
        }
        Ok(())
    })?;
    if let End::Truncated(m) = end {
        s.truncated = Some(m);
    } else if !saw_footer {
        s.truncated = Some("no footer".into());
    }
    Ok(s)
}

/// What [`read`] did, for reports and tests.
#[derive(Debug, Clone, Default)]
pub struct McapReadReport {
    pub summary: McapSummary,
    pub episodes: Vec<i64>,
    pub skipped_empty: Vec<i64>,
    /// Episodes whose messages were cut off (only with `--recover`).
    pub incomplete: Vec<String>,
}

/// Reads an MCAP file from disk.
pub fn read_file(path: &Path, opts: &ReadOptions, sink: &mut dyn EpisodeSink) -> Result<McapReadReport> {
    let f = std::fs::File::open(path).map_err(|e| IngestError::io(path, e))?;
    let size = f.metadata().map_err(|e| IngestError::io(path, e))?.len();
    let mut r = std::io::BufReader::with_capacity(1 << 20, f);
    read(path, &mut r, size, opts, sink)
}

/// Reads an MCAP stream and emits its episodes.
pub fn read(
    path: &Path,
    r: &mut dyn Read,
    size_hint: u64,
    opts: &ReadOptions,
    sink: &mut dyn EpisodeSink,
) -> Result<McapReadReport> {
    // A takeover flag would be a topic's field, which the mapping file does not name yet: refuse
    // rather than ingest without the flags asked for.
    if let Some(k) = &opts.intervention_key {
        return Err(IngestError::Usage(format!(
            "--intervention-key {k:?}: MCAP recordings do not support a takeover flag yet (LeRobot, robomimic and ALOHA sources do)"
        )));
    }
    let mut a = Assembler::new(path, opts);
    let mut saw_footer = false;
    let end = stream_records(path, r, size_hint, &mut |rec| {
        if matches!(rec, Record::Footer(_)) {
            saw_footer = true;
        }
        a.on_record(rec, sink)
    })?;
    let mut report = McapReadReport::default();
    let truncated = match end {
        End::Truncated(m) => Some(m),
        End::Clean if !saw_footer => Some("no footer".to_string()),
        End::Clean => None,
    };
    match truncated {
        Some(m) if !a.summary.data_complete => report.incomplete = a.end_cut_off(m, sink)?,
        other => a.end_complete(other, sink)?,
    }
    a.send_source(sink)?;
    report.episodes = a.emitted_indices.clone();
    report.skipped_empty = a.skipped_empty.clone();
    report.summary = a.summary.clone();
    if a.emitted == 0 {
        let topics: Vec<String> =
            a.summary.message_counts.iter().map(|(t, n)| format!("{t} ({n})")).collect();
        return Err(IngestError::invalid(
            path,
            format!(
                "no episodes with steps: the action topic {} has no messages inside an episode (topics: {}). Give a --mapping file",
                a.mapping.action.topic,
                if topics.is_empty() { "none".into() } else { topics.join(", ") }
            ),
        ));
    }
    Ok(report)
}
