//! The records as they stream in: schemas and channels (each channel's roles in the mapping and
//! its decoder), mapped messages decoded into samples, and the episode markers (Metadata
//! records, event topic).

use std::collections::{BTreeMap, VecDeque};

use mcap::records::{Metadata, Record};
use serde_json::{json, Map, Value};

use super::assembler::{Assembler, Chan, Kind, PendingEp, Sample};
use super::decode::{Decoder, SchemaRec, MAX_MAPPED_MESSAGE_BYTES};
use crate::dvalue::DValue;
use crate::error::{IngestError, Result};
use crate::sink::EpisodeSink;

fn parse_u64(s: Option<&String>) -> Option<u64> {
    s.and_then(|v| v.trim().parse::<u64>().ok())
}

impl Assembler<'_> {
    pub(super) fn on_record(&mut self, rec: Record<'_>, sink: &mut dyn EpisodeSink) -> Result<()> {
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
            Record::Metadata(m) => self.on_metadata(m, sink)?,
            Record::Attachment { .. } => self.summary.attachments += 1,
            Record::DataEnd(_) => self.summary.data_complete = true,
            _ => {}
        }
        Ok(())
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
            self.on_event(&v, t, &topic)?;
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

    /// A Metadata record: the episode markers (`start_ns`, `end_ns`, `success`, ...) when it is
    /// named as the mapping says, else kept in the source's metadata.
    fn on_metadata(&mut self, m: Metadata, sink: &mut dyn EpisodeSink) -> Result<()> {
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
                return Err(self
                    .err(format!("Metadata record {:?} has end_ns {end} before start_ns {start}", m.name)));
            }
            let success = m.metadata.get("success").and_then(|s| DValue::Str(s.clone()).as_bool());
            let index = m.metadata.get("index").and_then(|s| s.trim().parse::<i64>().ok());
            self.saw_episode_markers = true;
            let ls = format!("mcap:metadata:{}", m.name);
            self.add_pending(PendingEp { index, start, end, success, meta: m.metadata, label_source: ls });
            self.flush(sink, false)?;
        } else {
            let v: Map<String, Value> = m.metadata.iter().map(|(k, v)| (k.clone(), json!(v))).collect();
            self.other_metadata.insert(m.name, Value::Object(v));
        }
        Ok(())
    }

    /// A message on the episode event topic (decoded as `v`, at log time `t`): `start` opens an
    /// episode, `end` closes it (pending until its messages are in).
    fn on_event(&mut self, v: &DValue, t: u64, topic: &str) -> Result<()> {
        let ev = v.get_path("event").and_then(|x| x.as_str()).map(str::to_ascii_lowercase);
        let idx = v.get_path("episode").and_then(|x| x.as_f64()).map(|x| x as i64);
        match ev.as_deref() {
            Some("start") => {
                let i = idx.unwrap_or(self.next_index);
                let mut meta = BTreeMap::new();
                event_fields(v, &mut meta);
                self.open_events.insert(i, (t, meta));
                self.saw_episode_markers = true;
            }
            Some("end") => {
                let i = idx.unwrap_or(self.next_index);
                let Some((start, mut meta)) = self.open_events.remove(&i) else {
                    return Err(IngestError::invalid(
                        self.path,
                        format!(
                            "topic {topic}: end event for episode {i} at log time {t} without a start event"
                        ),
                    ));
                };
                event_fields(v, &mut meta);
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
        Ok(())
    }
}

/// An episode event's fields other than `event` into `meta`, as text (a field that is not text as
/// its JSON).
fn event_fields(v: &DValue, meta: &mut BTreeMap<String, String>) {
    if let DValue::Msg(fields) = v {
        for (k, x) in fields.iter().filter(|(k, _)| k != "event") {
            meta.insert(k.clone(), x.as_str().map(str::to_string).unwrap_or_else(|| x.to_json().to_string()));
        }
    }
}
