//! MCAP recordings, read linearly with the `mcap` crate's sans-io `LinearReader` (bounded memory:
//! only the decoded values of mapped topics inside not-yet-finished episodes are buffered).
//!
//! Message encodings: `cdr` with `ros2msg` schemas ([`crate::ros2msg`]), `protobuf` with
//! FileDescriptorSet schemas (prost-reflect), `json`. Episodes come from Metadata records named
//! `episode` (`start_ns`, `end_ns` inclusive, `success`, `policy`, `checkpoint`, ...) or from an
//! event topic (`/episode_event`: `{"event":"start","episode":i}` ... `{"event":"end","episode":i,
//! "success":bool}`); which topic/field becomes what is set by a [`Mapping`].

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::io::Read;
use std::path::Path;
use std::sync::Arc;

use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
use serde_json::{json, Map, Value};

use crate::dvalue::DValue;
use crate::error::{IngestError, Result};
use crate::mapping::Mapping;
use crate::model::{EpisodeInput, Label, VectorColumn};
use crate::options::ReadOptions;
use crate::ros2msg;
use crate::sink::{EpisodeSink, SourceMeta};

/// How long (in log time) after an episode's end we keep reading before we consider its messages
/// complete (tolerates slightly out-of-order chunks).
const GRACE_NS: u64 = 2_000_000_000;

/// Largest believable compression ratio / decompressed size of one chunk. A chunk is decompressed
/// whole, so its declared `uncompressed_size` is checked against both before anything is
/// allocated (writers cut chunks at a few MB: the mcap CLI and rosbag2 at 4 MiB, a chunk holding
/// one big message is that message's size).
pub const MAX_CHUNK_RATIO: u64 = 4096;
pub const MAX_CHUNK_BYTES: u64 = 256 << 20;

/// Largest message decoded on a mapped topic (actions, observations, rewards, episode events are
/// small vectors): decoding expands a message up to ~30 times (one `DValue` per list element),
/// so a huge one is refused instead.
pub const MAX_MAPPED_MESSAGE_BYTES: usize = 8 << 20;

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

enum End {
    Clean,
    Truncated(String),
}

/// Streams all records of an MCAP; `on` sees each record (chunks are decompressed).
fn stream_records(
    path: &Path,
    r: &mut dyn Read,
    size_hint: u64,
    on: &mut dyn FnMut(Record<'_>) -> Result<()>,
) -> Result<End> {
    let limit = (size_hint as usize).saturating_add(1024).max(1 << 16);
    // Chunks are emitted whole and unpacked here: the crate's in-place unpacking of
    // uncompressed chunks underflows on a record longer than its chunk (fuzzing found it).
    let opts = LinearReaderOptions::default().with_emit_chunks(true).with_record_length_limit(limit);
    let mut reader = LinearReader::new_with_options(opts);
    let mut total = 0u64;
    while let Some(ev) = reader.next_event() {
        match ev {
            Ok(LinearReadEvent::ReadRequest(need)) => {
                let buf = reader.insert(need.clamp(1, 8 << 20));
                let n = loop {
                    match r.read(buf) {
                        Ok(n) => break n,
                        Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                        Err(e) => return Err(IngestError::io(path, e)),
                    }
                };
                total += n as u64;
                reader.notify_read(n);
            }
            Ok(LinearReadEvent::Record { opcode, data }) => {
                let rec = mcap::parse_record(opcode, data).map_err(|e| {
                    IngestError::invalid(
                        path,
                        format!("corrupt MCAP record (opcode {opcode:#04x}) near byte {total}: {e}"),
                    )
                })?;
                match rec {
                    Record::Chunk { header, data } => unpack_chunk(path, total, header, &data, on)?,
                    rec => on(rec)?,
                }
            }
            Err(mcap::McapError::UnexpectedEof) => {
                return Ok(End::Truncated(format!("the file ends in the middle of a record after {total} bytes (no footer): the recording was cut off")));
            }
            Err(mcap::McapError::BadMagic) => {
                return Err(IngestError::invalid(path, "not an MCAP file (bad magic)"));
            }
            Err(e) => {
                return Err(IngestError::invalid(path, format!("corrupt MCAP data near byte {total}: {e}")))
            }
        }
    }
    Ok(End::Clean)
}

/// Yields the records inside a chunk, checking its CRC and lengths.
fn unpack_chunk(
    path: &Path,
    at: u64,
    header: mcap::records::ChunkHeader,
    data: &[u8],
    on: &mut dyn FnMut(Record<'_>) -> Result<()>,
) -> Result<()> {
    let bad = |m: String| IngestError::invalid(path, format!("corrupt MCAP chunk near byte {at}: {m}"));
    let owned;
    let data: &[u8] = if header.compression.is_empty() {
        data
    } else {
        // bound the claimed size by a generous compression ratio before allocating it
        let max =
            (data.len() as u64).saturating_mul(MAX_CHUNK_RATIO).saturating_add(1 << 16).min(MAX_CHUNK_BYTES);
        if header.uncompressed_size > max {
            return Err(bad(format!(
                "claims {} uncompressed bytes from {} compressed bytes (more than {max}: at most {MAX_CHUNK_RATIO}:1 and {MAX_CHUNK_BYTES} bytes): refused",
                header.uncompressed_size,
                data.len()
            )));
        }
        let want = header.uncompressed_size as usize;
        owned = match header.compression.as_str() {
            "zstd" => zstd::bulk::decompress(data, want).map_err(|e| bad(format!("zstd: {e}")))?,
            "lz4" => {
                use std::io::Read as _;
                let mut out = Vec::with_capacity(want);
                let dec = lz4::Decoder::new(data).map_err(|e| bad(format!("lz4: {e}")))?;
                dec.take(want as u64 + 1).read_to_end(&mut out).map_err(|e| bad(format!("lz4: {e}")))?;
                out
            }
            other => return Err(bad(format!("unsupported chunk compression {other:?}"))),
        };
        &owned
    };
    if header.uncompressed_size != data.len() as u64 {
        return Err(bad(format!(
            "uncompressed_size {} but {} bytes of records",
            header.uncompressed_size,
            data.len()
        )));
    }
    if header.uncompressed_crc != 0 {
        let c = crc32(data);
        if c != header.uncompressed_crc {
            return Err(bad(format!(
                "CRC mismatch (saved {:#010x}, computed {c:#010x})",
                header.uncompressed_crc
            )));
        }
    }
    let mut p = 0usize;
    while p < data.len() {
        if data.len() - p < 9 {
            return Err(bad("ends in the middle of a record header".into()));
        }
        let op = data[p];
        let len = u64::from_le_bytes(data[p + 1..p + 9].try_into().expect("8 bytes"));
        if len > (data.len() - p - 9) as u64 {
            return Err(bad(format!(
                "record of {len} bytes (opcode {op:#04x}) runs past the end of its chunk"
            )));
        }
        let body = &data[p + 9..p + 9 + len as usize];
        let rec = mcap::parse_record(op, body).map_err(|e| bad(format!("record (opcode {op:#04x}): {e}")))?;
        on(rec)?;
        p += 9 + len as usize;
    }
    Ok(())
}

fn crc32(data: &[u8]) -> u32 {
    // CRC-32 (IEEE), table-less bitwise is too slow for big chunks: use a small table.
    static TABLE: std::sync::OnceLock<[u32; 256]> = std::sync::OnceLock::new();
    let t = TABLE.get_or_init(|| {
        let mut t = [0u32; 256];
        for (i, e) in t.iter_mut().enumerate() {
            let mut c = i as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 { 0xedb8_8320 ^ (c >> 1) } else { c >> 1 };
            }
            *e = c;
        }
        t
    });
    let mut c = !0u32;
    for &b in data {
        c = t[((c ^ b as u32) & 0xff) as usize] ^ (c >> 8);
    }
    !c
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

/// Decodes messages of one channel.
pub enum Decoder {
    Cdr(Arc<ros2msg::Schema>),
    Proto(prost_reflect::MessageDescriptor),
    Json,
}

impl Decoder {
    pub fn new(message_encoding: &str, schema: Option<&SchemaRec>) -> std::result::Result<Decoder, String> {
        match message_encoding {
            "json" => Ok(Decoder::Json),
            "cdr" => {
                let s = schema.ok_or("cdr messages without a schema")?;
                match s.encoding.as_str() {
                    "ros2msg" => {
                        let text = std::str::from_utf8(&s.data).map_err(|_| "ros2msg schema is not UTF-8")?;
                        Ok(Decoder::Cdr(Arc::new(ros2msg::parse_schema(&s.name, text)?)))
                    }
                    other => {
                        Err(format!("cdr with schema encoding {other:?} is not supported (only ros2msg)"))
                    }
                }
            }
            "protobuf" => {
                let s = schema.ok_or("protobuf messages without a schema")?;
                let pool = prost_reflect::DescriptorPool::decode(s.data.as_slice())
                    .map_err(|e| format!("bad protobuf FileDescriptorSet for {}: {e}", s.name))?;
                let d = pool
                    .get_message_by_name(&s.name)
                    .ok_or_else(|| format!("protobuf schema has no message {}", s.name))?;
                Ok(Decoder::Proto(d))
            }
            other => Err(format!("message encoding {other:?} is not supported (cdr, protobuf, json)")),
        }
    }

    pub fn decode(&self, data: &[u8]) -> std::result::Result<DValue, String> {
        match self {
            Decoder::Json => {
                let v: Value = serde_json::from_slice(data).map_err(|e| format!("bad JSON message: {e}"))?;
                Ok(DValue::from_json(&v))
            }
            Decoder::Cdr(s) => ros2msg::decode_cdr(s, data),
            Decoder::Proto(d) => {
                let m = prost_reflect::DynamicMessage::decode(d.clone(), data)
                    .map_err(|e| format!("bad protobuf message: {e}"))?;
                Ok(proto_to_dvalue(&prost_reflect::Value::Message(m)))
            }
        }
    }
}

fn proto_to_dvalue(v: &prost_reflect::Value) -> DValue {
    use prost_reflect::Value as P;
    match v {
        P::Bool(b) => DValue::Bool(*b),
        P::I32(i) => DValue::Int(*i as i64),
        P::I64(i) => DValue::Int(*i),
        P::U32(u) => DValue::UInt(*u as u64),
        P::U64(u) => DValue::UInt(*u),
        P::F32(f) => DValue::Float(*f as f64),
        P::F64(f) => DValue::Float(*f),
        P::String(s) => DValue::Str(s.clone()),
        P::Bytes(b) => DValue::Bytes(b.to_vec()),
        P::EnumNumber(n) => DValue::Int(*n as i64),
        P::Message(m) => {
            use prost_reflect::ReflectMessage;
            let desc = m.descriptor();
            DValue::Msg(
                desc.fields().map(|f| (f.name().to_string(), proto_to_dvalue(&m.get_field(&f)))).collect(),
            )
        }
        P::List(l) => DValue::List(l.iter().map(proto_to_dvalue).collect()),
        P::Map(m) => DValue::Msg(m.iter().map(|(k, v)| (format!("{k:?}"), proto_to_dvalue(v))).collect()),
    }
}

pub struct SchemaRec {
    pub name: String,
    pub encoding: String,
    pub data: Vec<u8>,
}

/// What a decoded message contributes.
#[derive(Debug, Clone)]
enum Kind {
    Other,
    Action(Vec<f32>),
    Obs(usize, Vec<f32>),
    Reward(f32),
}

#[derive(Debug, Clone)]
struct Sample {
    t: u64,
    chan: u16,
    kind: Kind,
}

#[derive(Debug, Clone)]
struct PendingEp {
    index: Option<i64>,
    start: u64,
    end: u64,
    success: Option<bool>,
    meta: BTreeMap<String, String>,
    label_source: String,
}

struct Chan {
    topic: String,
    message_encoding: String,
    schema_id: u16,
    /// (roles) this channel feeds
    action: bool,
    obs: Vec<usize>,
    reward: bool,
    events: bool,
    decoder: Option<std::result::Result<Decoder, String>>,
}

struct Assembler<'a> {
    path: &'a Path,
    opts: &'a ReadOptions,
    mapping: Mapping,
    obs_keys: Vec<String>,
    schemas: HashMap<u16, SchemaRec>,
    chans: HashMap<u16, Chan>,
    buf: VecDeque<Sample>,
    pending: Vec<PendingEp>,
    open_events: HashMap<i64, (u64, BTreeMap<String, String>)>,
    max_t: u64,
    emitted: usize,
    emitted_indices: Vec<i64>,
    skipped_empty: Vec<i64>,
    next_index: i64,
    summary: McapSummary,
    source_sent: bool,
    other_metadata: Map<String, Value>,
    saw_episode_markers: bool,
    first_t: Option<u64>,
}

fn parse_u64(s: Option<&String>) -> Option<u64> {
    s.and_then(|v| v.trim().parse::<u64>().ok())
}

impl<'a> Assembler<'a> {
    fn new(path: &'a Path, opts: &'a ReadOptions) -> Self {
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

    fn err(&self, msg: impl Into<String>) -> IngestError {
        IngestError::invalid(self.path, msg)
    }

    fn send_source(&mut self, sink: &mut dyn EpisodeSink) -> Result<()> {
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

    fn on_record(&mut self, rec: Record<'_>, sink: &mut dyn EpisodeSink) -> Result<()> {
        match rec {
            Record::Header(h) => {
                self.summary.profile = h.profile;
                self.summary.library = h.library;
            }
            Record::Schema { header, data } => {
                self.summary.schemas += 1;
                self.schemas.insert(
                    header.id,
                    SchemaRec { name: header.name, encoding: header.encoding, data: data.into_owned() },
                );
            }
            Record::Channel(c) => {
                if self.chans.contains_key(&c.id) {
                    return Ok(());
                }
                self.summary.channels += 1;
                let obs = self
                    .mapping
                    .observations
                    .values()
                    .enumerate()
                    .filter(|(_, f)| f.topic == c.topic)
                    .map(|(i, _)| i)
                    .collect();
                let ch = Chan {
                    action: self.mapping.action.topic == c.topic,
                    reward: self.mapping.reward.as_ref().map(|r| r.topic == c.topic).unwrap_or(false),
                    events: self.mapping.episodes.topic == c.topic,
                    obs,
                    topic: c.topic,
                    message_encoding: c.message_encoding,
                    schema_id: c.schema_id,
                    decoder: None,
                };
                self.chans.insert(c.id, ch);
            }
            Record::Message { header, data } => {
                self.summary.message_count += 1;
                let t = header.log_time;
                self.first_t = Some(self.first_t.map_or(t, |x| x.min(t)));
                self.summary.first_log_time = self.first_t;
                self.summary.last_log_time = Some(self.summary.last_log_time.map_or(t, |x| x.max(t)));
                let topic = self
                    .chans
                    .get(&header.channel_id)
                    .map(|c| c.topic.clone())
                    .unwrap_or_else(|| format!("<channel {}>", header.channel_id));
                *self.summary.message_counts.entry(topic).or_default() += 1;
                self.on_message(header.channel_id, t, &data)?;
                if t > self.max_t {
                    self.max_t = t;
                    self.flush(sink, false)?;
                }
            }
            Record::Metadata(m) => {
                self.summary.metadata.push((m.name.clone(), m.metadata.clone()));
                if m.name == self.mapping.episodes.metadata {
                    let start = parse_u64(m.metadata.get("start_ns"));
                    let end = parse_u64(m.metadata.get("end_ns"));
                    let (Some(start), Some(end)) = (start, end) else {
                        return Err(self.err(format!(
                            "Metadata record {:?} without numeric start_ns/end_ns: {:?}",
                            m.name, m.metadata
                        )));
                    };
                    if end < start {
                        return Err(self.err(format!(
                            "Metadata record {:?} has end_ns {end} before start_ns {start}",
                            m.name
                        )));
                    }
                    let success = m.metadata.get("success").and_then(|s| DValue::Str(s.clone()).as_bool());
                    let index = m.metadata.get("index").and_then(|s| s.trim().parse::<i64>().ok());
                    self.saw_episode_markers = true;
                    let ls = format!("mcap:metadata:{}", m.name);
                    self.add_pending(PendingEp {
                        index,
                        start,
                        end,
                        success,
                        meta: m.metadata,
                        label_source: ls,
                    });
                    self.flush(sink, false)?;
                } else {
                    let v: Map<String, Value> =
                        m.metadata.iter().map(|(k, v)| (k.clone(), json!(v))).collect();
                    self.other_metadata.insert(m.name, Value::Object(v));
                }
            }
            Record::Attachment { .. } => self.summary.attachments += 1,
            Record::DataEnd(_) => self.summary.data_complete = true,
            _ => {}
        }
        Ok(())
    }

    fn add_pending(&mut self, p: PendingEp) {
        if self.pending.iter().any(|q| q.start == p.start && q.end == p.end) {
            return;
        }
        self.pending.push(p);
        self.pending.sort_by_key(|p| (p.end, p.start));
    }

    fn decoder(&mut self, chan: u16) -> Option<std::result::Result<&Decoder, String>> {
        let c = self.chans.get_mut(&chan)?;
        if c.decoder.is_none() {
            let s = if c.schema_id == 0 { None } else { self.schemas.get(&c.schema_id) };
            c.decoder = Some(Decoder::new(&c.message_encoding, s));
        }
        Some(c.decoder.as_ref().expect("set").as_ref().map_err(|e| e.clone()))
    }

    fn on_message(&mut self, chan: u16, t: u64, data: &[u8]) -> Result<()> {
        let Some(c) = self.chans.get(&chan) else {
            return Err(self.err(format!("message on channel {chan}, which no Channel record declared")));
        };
        let (is_action, obs, is_reward, is_events, topic) =
            (c.action, c.obs.clone(), c.reward, c.events, c.topic.clone());
        if !(is_action || is_reward || is_events || !obs.is_empty()) {
            self.buf.push_back(Sample { t, chan, kind: Kind::Other });
            return Ok(());
        }
        let path = self.path.to_path_buf();
        let dec = match self.decoder(chan) {
            Some(Ok(d)) => d,
            Some(Err(e)) => return Err(IngestError::invalid(&path, format!("topic {topic}: {e}"))),
            None => unreachable!("channel checked above"),
        };
        if data.len() > MAX_MAPPED_MESSAGE_BYTES {
            return Err(IngestError::invalid(
                &path,
                format!("topic {topic}, message at log time {t}: {} bytes, more than the {MAX_MAPPED_MESSAGE_BYTES} decoded on a mapped topic: refused", data.len()),
            ));
        }
        let v = dec.decode(data).map_err(|e| {
            IngestError::invalid(&path, format!("topic {topic}, message at log time {t}: {e}"))
        })?;
        let to_f32 = |x: Vec<f64>| x.into_iter().map(|v| v as f32).collect::<Vec<f32>>();
        let mut first = true;
        let mut push = |buf: &mut VecDeque<Sample>, kind: Kind| {
            // one entry per message for counting; further roles of the same message are tagged
            // with an impossible channel id so they are not counted twice
            buf.push_back(Sample { t, chan: if first { chan } else { u16::MAX }, kind });
            first = false;
        };
        if is_events {
            let ev = v.get_path("event").and_then(|x| x.as_str()).map(str::to_ascii_lowercase);
            let idx = v.get_path("episode").and_then(|x| x.as_f64()).map(|x| x as i64);
            match ev.as_deref() {
                Some("start") => {
                    let i = idx.unwrap_or(self.next_index);
                    let mut meta = BTreeMap::new();
                    if let DValue::Msg(fields) = &v {
                        for (k, x) in fields {
                            if k != "event" {
                                meta.insert(
                                    k.clone(),
                                    x.as_str().map(str::to_string).unwrap_or_else(|| x.to_json().to_string()),
                                );
                            }
                        }
                    }
                    self.open_events.insert(i, (t, meta));
                    self.saw_episode_markers = true;
                }
                Some("end") => {
                    let i = idx.unwrap_or(self.next_index);
                    let Some((start, mut meta)) = self.open_events.remove(&i) else {
                        return Err(IngestError::invalid(&path, format!("topic {topic}: end event for episode {i} at log time {t} without a start event")));
                    };
                    if let DValue::Msg(fields) = &v {
                        for (k, x) in fields {
                            if k != "event" {
                                meta.insert(
                                    k.clone(),
                                    x.as_str().map(str::to_string).unwrap_or_else(|| x.to_json().to_string()),
                                );
                            }
                        }
                    }
                    let success = v.get_path("success").and_then(|x| x.as_bool());
                    self.add_pending(PendingEp {
                        index: Some(i),
                        start,
                        end: t,
                        success,
                        meta,
                        label_source: format!("mcap:topic:{topic}"),
                    });
                }
                _ => {}
            }
        }
        if is_action {
            let vals = v.numbers_any(&self.mapping.action.field).ok_or_else(|| {
                IngestError::invalid(
                    &path,
                    format!(
                        "topic {topic}: no numeric field {:?} in the action message",
                        self.mapping.action.field
                    ),
                )
            })?;
            push(&mut self.buf, Kind::Action(to_f32(vals)));
        }
        for k in obs {
            let f = &self.mapping.observations[&self.obs_keys[k]];
            if let Some(vals) = v.numbers_any(&f.field) {
                if !vals.is_empty() {
                    push(&mut self.buf, Kind::Obs(k, to_f32(vals)));
                }
            }
        }
        if is_reward {
            let f = self.mapping.reward.as_ref().expect("reward mapped");
            if let Some(vals) = v.numbers_any(&f.field) {
                if let Some(r) = vals.first() {
                    push(&mut self.buf, Kind::Reward(*r as f32));
                }
            }
        }
        if first {
            self.buf.push_back(Sample { t, chan, kind: Kind::Other });
        }
        Ok(())
    }

    /// Emits the pending episodes whose messages are all in (or all, at the end of the file).
    fn flush(&mut self, sink: &mut dyn EpisodeSink, all: bool) -> Result<()> {
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

    fn build(
        &self,
        p: &PendingEp,
        index: i64,
        samples: &[&Sample],
        counts: BTreeMap<String, u64>,
    ) -> Result<Option<EpisodeInput>> {
        let nobs = self.obs_keys.len();
        struct Col {
            dim: Option<usize>,
            vals: Vec<f32>,
            missing: usize,
        }
        let mut cols: Vec<Col> = (0..nobs).map(|_| Col { dim: None, vals: Vec::new(), missing: 0 }).collect();
        let mut latest: Vec<Option<&Vec<f32>>> = vec![None; nobs];
        let mut latest_action: Option<&Vec<f32>> = None;
        let mut latest_reward = 0f32;
        let mut action = Col { dim: None, vals: Vec::new(), missing: 0 };
        let mut times: Vec<u64> = Vec::new();
        let mut reward = Vec::new();
        let topic_of = |k: usize| self.mapping.observations[&self.obs_keys[k]].topic.clone();

        let push_col = |c: &mut Col, v: Option<&Vec<f32>>, what: &str, t: u64| -> Result<()> {
            match v {
                None => c.missing += 1,
                Some(v) => {
                    match c.dim {
                        None => c.dim = Some(v.len()),
                        Some(d) if d != v.len() => {
                            return Err(self.err(format!(
                                "{what}: {} values at log time {t}, earlier messages had {d}",
                                v.len()
                            )));
                        }
                        _ => {}
                    }
                    c.vals.extend_from_slice(v);
                }
            }
            Ok(())
        };
        let mut step = |t: u64,
                        latest: &[Option<&Vec<f32>>],
                        act: Option<&Vec<f32>>,
                        r: f32,
                        cols: &mut Vec<Col>,
                        action: &mut Col|
         -> Result<()> {
            times.push(t);
            reward.push(r);
            push_col(action, act, &format!("action topic {}", self.mapping.action.topic), t)?;
            for (k, c) in cols.iter_mut().enumerate() {
                push_col(
                    c,
                    latest[k],
                    &format!("observation {} (topic {})", self.obs_keys[k], topic_of(k)),
                    t,
                )?;
            }
            Ok(())
        };
        let has_action = samples.iter().any(|s| matches!(s.kind, Kind::Action(_)));
        match self.mapping.rate_hz {
            None if has_action => {
                for s in samples {
                    match &s.kind {
                        Kind::Obs(k, v) => latest[*k] = Some(v),
                        Kind::Reward(r) => latest_reward = *r,
                        Kind::Action(v) => {
                            step(s.t, &latest, Some(v), latest_reward, &mut cols, &mut action)?
                        }
                        Kind::Other => {}
                    }
                }
            }
            None => {
                // No action messages: one step per observation time (all observations
                // published at that log time taken together), actions null.
                for (i, s) in samples.iter().enumerate() {
                    match &s.kind {
                        Kind::Obs(k, v) => latest[*k] = Some(v),
                        Kind::Reward(r) => latest_reward = *r,
                        _ => {}
                    }
                    let last_at_t = samples.get(i + 1).is_none_or(|n| n.t != s.t);
                    let obs_at_t = samples[..=i]
                        .iter()
                        .rev()
                        .take_while(|p| p.t == s.t)
                        .any(|p| matches!(p.kind, Kind::Obs(..)));
                    if last_at_t && obs_at_t {
                        step(s.t, &latest, None, latest_reward, &mut cols, &mut action)?;
                    }
                }
            }
            Some(rate) => {
                let dt = 1e9 / rate;
                let mut k = 0u64;
                let mut i = 0usize;
                loop {
                    let ts = p.start + (k as f64 * dt) as u64;
                    if ts > p.end || k > 10_000_000 {
                        break;
                    }
                    while i < samples.len() && samples[i].t <= ts {
                        match &samples[i].kind {
                            Kind::Obs(j, v) => latest[*j] = Some(v),
                            Kind::Reward(r) => latest_reward = *r,
                            Kind::Action(v) => latest_action = Some(v),
                            Kind::Other => {}
                        }
                        i += 1;
                    }
                    if latest_action.is_some() || action.dim.is_some() || i > 0 {
                        step(ts, &latest, latest_action, latest_reward, &mut cols, &mut action)?;
                    }
                    k += 1;
                }
            }
        }
        if times.is_empty() {
            return Ok(None);
        }
        let backfill = |c: Col| -> Option<(usize, Vec<f32>)> {
            let d = c.dim?;
            if c.missing == 0 {
                return Some((d, c.vals));
            }
            let first: Vec<f32> = c.vals[..d].to_vec();
            let mut v = Vec::with_capacity(c.vals.len() + c.missing * d);
            for _ in 0..c.missing {
                v.extend_from_slice(&first);
            }
            v.extend_from_slice(&c.vals);
            Some((d, v))
        };
        // No action in the whole episode: dimension 0, stored without an action column.
        let (adim, avals) = backfill(action).unwrap_or((0, Vec::new()));
        let mut observations = Vec::new();
        for (k, c) in cols.into_iter().enumerate() {
            if let Some((dim, values)) = backfill(c) {
                if dim > 0 {
                    observations.push(VectorColumn { name: self.obs_keys[k].clone(), dim, values });
                }
            }
        }
        let steps = times.len();
        let timestamps: Vec<f64> = times.iter().map(|t| t.saturating_sub(p.start) as f64 / 1e9).collect();
        let mut done = vec![false; steps];
        if let Some(d) = done.last_mut() {
            *d = true;
        }
        let name = format!("episode_{index}");
        let (label, label_source) = match self.opts.user_label(&name, index.max(0) as u32, &reward) {
            Some(l) => l,
            None => match p.success {
                Some(b) => (Label::from_bool(Some(b)), p.label_source.clone()),
                None => (Label::Unknown, String::new()),
            },
        };
        let mut md = Map::new();
        md.insert("index".into(), json!(index));
        md.insert("start_ns".into(), json!(p.start));
        md.insert("end_ns".into(), json!(p.end));
        md.insert("message_counts".into(), json!(counts));
        for (k, v) in &p.meta {
            if !matches!(k.as_str(), "index" | "start_ns" | "end_ns" | "episode") {
                md.insert(k.clone(), json!(v));
            }
        }
        let task = self.opts.task.clone().or_else(|| p.meta.get("task").cloned());
        Ok(Some(EpisodeInput {
            source_name: name,
            source_index: index.clamp(0, u32::MAX as i64) as u32,
            task,
            label,
            label_source,
            tags: Vec::new(),
            metadata: Value::Object(md),
            timestamps,
            observations,
            action: VectorColumn { name: "action".into(), dim: adim, values: avals },
            reward,
            done,
            action_chunk: None,
            images: Vec::new(),
            media: Vec::new(),
            flags: Default::default(),
        }))
    }
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
        Some(m) if !a.summary.data_complete => {
            // episodes complete: data continued past their end
            let max_t = a.max_t;
            let (complete, partial): (Vec<PendingEp>, Vec<PendingEp>) =
                a.pending.drain(..).partition(|p| max_t > p.end);
            for p in complete {
                a.emit(p, sink)?;
            }
            let mut lost: Vec<String> = partial
                .iter()
                .map(|p| format!("episode {}", p.index.map(|i| i.to_string()).unwrap_or_else(|| "?".into())))
                .collect();
            let mut opens: Vec<_> = a.open_events.keys().copied().collect();
            opens.sort();
            lost.extend(opens.iter().map(|i| format!("episode {i} (started, never ended)")));
            let last_end = a.summary.last_log_time.unwrap_or(0);
            let trailing = a.buf.iter().filter(|s| s.chan != u16::MAX).count();
            let complete_list = if a.emitted_indices.is_empty() {
                "none".to_string()
            } else {
                a.emitted_indices.iter().map(|i| i.to_string()).collect::<Vec<_>>().join(", ")
            };
            let what = format!(
                "truncated MCAP: {m}. Recovered {} messages (last log time {last_end}); complete episodes: {complete_list}; {} message(s) after the last complete episode belong to an episode that was cut off{}",
                a.summary.message_count,
                trailing,
                if lost.is_empty() { String::new() } else { format!(" ({})", lost.join(", ")) }
            );
            if !opts.recover {
                return Err(IngestError::Truncated {
                    path: path.to_path_buf(),
                    msg: format!(
                        "{what}. Run again with --recover to ingest the {} complete episode(s)",
                        a.emitted
                    ),
                    recoverable: a.emitted,
                });
            }
            report.incomplete = lost;
            a.summary.truncated = Some(what);
        }
        other => {
            if let Some(m) = other {
                // only the summary section was cut: all data is there
                a.summary.truncated = Some(format!("{m} (summary section only; all data records present)"));
            }
            // open event episodes at the end: close them at the last message
            if !a.open_events.is_empty() {
                let mut opens: Vec<_> = a.open_events.drain().collect();
                opens.sort_by_key(|(i, _)| *i);
                for (i, (start, meta)) in opens {
                    let end = a.summary.last_log_time.unwrap_or(start);
                    let ls = String::new();
                    a.add_pending(PendingEp {
                        index: Some(i),
                        start,
                        end,
                        success: None,
                        meta,
                        label_source: ls,
                    });
                }
            }
            if !a.saw_episode_markers && a.summary.message_count > 0 {
                // the whole recording is one episode
                let start = a.first_t.unwrap_or(0);
                let end = a.summary.last_log_time.unwrap_or(start);
                a.add_pending(PendingEp {
                    index: Some(0),
                    start,
                    end,
                    success: None,
                    meta: BTreeMap::new(),
                    label_source: String::new(),
                });
            }
            a.flush(sink, true)?;
        }
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
