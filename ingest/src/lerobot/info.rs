//! `meta/info.json`: the dataset's layout (version, fps, features, path templates), parsed and
//! checked, and the size-capped read of the metadata files.

use std::path::Path;

use serde_json::Value;

use crate::error::{IngestError, Result};

#[derive(Debug, Clone, PartialEq)]
pub struct Feature {
    pub key: String,
    pub dtype: String,
    pub shape: Vec<usize>,
    pub names: Value,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Info {
    pub codebase_version: String,
    pub fps: f64,
    pub robot_type: Option<String>,
    pub features: Vec<Feature>,
    pub total_episodes: Option<u64>,
    pub chunks_size: u64,
    pub data_path: String,
    pub video_path: Option<String>,
    pub raw: Value,
}

impl Info {
    pub fn is_v3(&self) -> bool {
        self.codebase_version.starts_with("v3")
    }
    pub(super) fn feature(&self, key: &str) -> Option<&Feature> {
        self.features.iter().find(|f| f.key == key)
    }
    pub(super) fn video_keys(&self) -> Vec<&Feature> {
        self.features.iter().filter(|f| f.dtype == "video").collect()
    }
}

/// The keys of info.json's `features` object in the order the file lists them (empty when the
/// file does not parse; [`parse_info`] reports that).
fn feature_order(bytes: &[u8]) -> Vec<String> {
    struct Keys(Vec<String>);
    impl<'de> serde::Deserialize<'de> for Keys {
        fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
            struct Visit;
            impl<'de> serde::de::Visitor<'de> for Visit {
                type Value = Keys;
                fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                    f.write_str("a JSON object")
                }
                fn visit_map<A: serde::de::MapAccess<'de>>(
                    self,
                    mut map: A,
                ) -> std::result::Result<Keys, A::Error> {
                    let mut keys = Vec::new();
                    while let Some((k, _)) = map.next_entry::<String, serde::de::IgnoredAny>()? {
                        keys.push(k);
                    }
                    Ok(Keys(keys))
                }
            }
            d.deserialize_map(Visit)
        }
    }
    #[derive(serde::Deserialize)]
    struct Info {
        features: Keys,
    }
    serde_json::from_slice::<Info>(bytes).map(|i| i.features.0).unwrap_or_default()
}

/// Parses `meta/info.json`.
pub fn parse_info(path: &Path, bytes: &[u8]) -> Result<Info> {
    let raw: Value = serde_json::from_slice(bytes)
        .map_err(|e| IngestError::invalid(path, format!("not valid JSON: {e}")))?;
    let obj = raw.as_object().ok_or_else(|| IngestError::invalid(path, "expected a JSON object"))?;
    let codebase_version = obj
        .get("codebase_version")
        .and_then(|v| v.as_str())
        .ok_or_else(|| IngestError::invalid(path, "no `codebase_version`"))?
        .to_string();
    if !(codebase_version.starts_with("v2") || codebase_version.starts_with("v3")) {
        return Err(IngestError::invalid(
            path,
            format!("codebase_version {codebase_version:?} is not supported (expected v2.1 or v3.0)"),
        ));
    }
    let fps = obj
        .get("fps")
        .and_then(|v| v.as_f64())
        .filter(|f| f.is_finite() && *f > 0.0)
        .ok_or_else(|| IngestError::invalid(path, "no positive `fps`"))?;
    let feats = obj
        .get("features")
        .and_then(|v| v.as_object())
        .ok_or_else(|| IngestError::invalid(path, "no `features` object"))?;
    let mut features = Vec::new();
    for (key, f) in feats {
        let dtype = f
            .get("dtype")
            .and_then(|v| v.as_str())
            .ok_or_else(|| IngestError::invalid(path, format!("feature {key:?} has no dtype")))?
            .to_string();
        let shape = match f.get("shape") {
            Some(Value::Array(a)) => a
                .iter()
                .map(|d| d.as_u64().map(|x| x as usize))
                .collect::<Option<Vec<_>>>()
                .ok_or_else(|| IngestError::invalid(path, format!("feature {key:?} has a bad shape")))?,
            _ => vec![1],
        };
        features.push(Feature {
            key: key.clone(),
            dtype,
            shape,
            names: f.get("names").cloned().unwrap_or(Value::Null),
        });
    }
    // serde_json's map sorts keys; the file's order is the dataset's own (state before
    // environment state, say), which the store keeps and default verifier inputs follow.
    let order = feature_order(bytes);
    features.sort_by_key(|f| order.iter().position(|k| *k == f.key).unwrap_or(usize::MAX));
    let v3 = codebase_version.starts_with("v3");
    let data_path = obj.get("data_path").and_then(|v| v.as_str()).map(str::to_string).unwrap_or_else(|| {
        if v3 {
            "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet".into()
        } else {
            "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet".into()
        }
    });
    Ok(Info {
        codebase_version,
        fps,
        robot_type: obj.get("robot_type").and_then(|v| v.as_str()).map(str::to_string),
        features,
        total_episodes: obj.get("total_episodes").and_then(|v| v.as_u64()),
        chunks_size: obj.get("chunks_size").and_then(|v| v.as_u64()).filter(|&c| c > 0).unwrap_or(1000),
        data_path,
        video_path: obj.get("video_path").and_then(|v| v.as_str()).map(str::to_string),
        raw,
    })
}

/// Widest zero padding a template may ask for (a u64 has 20 digits): `{episode_index:0999999999d}`
/// would otherwise allocate a GB-long path.
const MAX_TEMPLATE_WIDTH: usize = 32;

/// Fills a LeRobot path template such as `data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet`.
/// The result is untrusted: callers confine it to the dataset with [`crate::confine::Root::file`].
pub fn fill_template(t: &str, vars: &[(&str, &str, u64)]) -> std::result::Result<String, String> {
    let mut out = String::new();
    let mut rest = t;
    while let Some(i) = rest.find('{') {
        out.push_str(&rest[..i]);
        let Some(j) = rest[i..].find('}') else {
            out.push_str(&rest[i..]);
            return Ok(out);
        };
        let inner = &rest[i + 1..i + j];
        let (name, fmt) = inner.split_once(':').unwrap_or((inner, ""));
        let mut done = false;
        for (n, s, v) in vars {
            if *n == name {
                if !s.is_empty() {
                    out.push_str(s);
                } else {
                    let width: usize = fmt.trim_start_matches('0').trim_end_matches('d').parse().unwrap_or(0);
                    if width > MAX_TEMPLATE_WIDTH {
                        return Err(format!(
                            "{{{inner}}} asks for a width of {width} digits (at most {MAX_TEMPLATE_WIDTH})"
                        ));
                    }
                    out.push_str(&format!("{:0width$}", v, width = width));
                }
                done = true;
            }
        }
        if !done {
            out.push_str(&rest[i..=i + j]);
        }
        rest = &rest[i + j + 1..];
    }
    out.push_str(rest);
    Ok(out)
}

/// Largest metadata files read whole (`meta/info.json`, `meta/*.jsonl`): far above real ones
/// (a v2.1 `episodes.jsonl` of 100,000 episodes is ~20 MB), so that a huge one is refused instead
/// of being loaded.
pub(super) const MAX_INFO_BYTES: u64 = 16 << 20;
pub(super) const MAX_JSONL_BYTES: u64 = 512 << 20;

/// A metadata file read whole, refused when larger than `max` bytes.
pub(crate) fn read_bounded(path: &Path, max: u64) -> Result<Vec<u8>> {
    use std::io::Read;
    let f = std::fs::File::open(path).map_err(|e| IngestError::io(path, e))?;
    let len = f.metadata().map_err(|e| IngestError::io(path, e))?.len();
    if len > max {
        return Err(IngestError::invalid(
            path,
            format!("metadata file of {len} bytes (at most {max} are read): refused"),
        ));
    }
    let mut out = Vec::with_capacity(len as usize);
    f.take(max + 1).read_to_end(&mut out).map_err(|e| IngestError::io(path, e))?;
    if out.len() as u64 > max {
        return Err(IngestError::invalid(
            path,
            format!("metadata file grew past {max} bytes while read: refused"),
        ));
    }
    Ok(out)
}
