//! Message decoding: one [`Decoder`] per channel, from its message encoding and schema (`cdr`
//! with ros2msg, `protobuf` with a FileDescriptorSet, `json`), into [`DValue`]s.

use std::sync::Arc;

use serde_json::Value;

use crate::dvalue::DValue;
use crate::ros2msg;

/// Largest message decoded on a mapped topic (actions, observations, rewards, episode events are
/// small vectors): decoding expands a message up to ~30 times (one `DValue` per list element),
/// so a huge one is refused instead.
pub const MAX_MAPPED_MESSAGE_BYTES: usize = 8 << 20;

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
