//! The MCAP mapping file (TOML): which topic/field becomes which observation key and the action,
//! how steps are formed, and where episodes come from. See the crate README for the format.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Deserialize;

use crate::error::{IngestError, Result};

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldRef {
    pub topic: String,
    /// Dotted field path; lists map over their elements (`joints.position`); `a|b` tries `a`
    /// then `b`. Empty = the whole message's numbers.
    #[serde(default)]
    pub field: String,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EpisodeSource {
    /// Name of the MCAP Metadata records that delimit episodes (`start_ns`, `end_ns`, `success`, ...).
    #[serde(default = "default_meta_name")]
    pub metadata: String,
    /// Topic whose messages carry `{"event": "start"|"end", "episode": i, "success": bool}`.
    #[serde(default = "default_event_topic")]
    pub topic: String,
}

fn default_meta_name() -> String {
    "episode".into()
}
fn default_event_topic() -> String {
    "/episode_event".into()
}

impl Default for EpisodeSource {
    fn default() -> Self {
        EpisodeSource { metadata: default_meta_name(), topic: default_event_topic() }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mapping {
    /// Steps at a fixed rate (Hz) instead of one step per action message.
    #[serde(default)]
    pub rate_hz: Option<f64>,
    pub action: FieldRef,
    #[serde(default)]
    pub observations: BTreeMap<String, FieldRef>,
    #[serde(default)]
    pub reward: Option<FieldRef>,
    #[serde(default)]
    pub episodes: EpisodeSource,
}

impl Default for Mapping {
    /// `/action` `data` → action; `/joint_states` `position` → `joint_pos`, `velocity` →
    /// `joint_vel` (also for `foxglove.JointStates`: `joints.position`); one step per action
    /// message; episodes from Metadata `episode` or the `/episode_event` topic.
    fn default() -> Self {
        let mut observations = BTreeMap::new();
        observations.insert(
            "joint_pos".to_string(),
            FieldRef { topic: "/joint_states".into(), field: "position|joints.position".into() },
        );
        observations.insert(
            "joint_vel".to_string(),
            FieldRef { topic: "/joint_states".into(), field: "velocity|joints.velocity".into() },
        );
        Mapping {
            rate_hz: None,
            action: FieldRef { topic: "/action".into(), field: "data|position|values".into() },
            observations,
            reward: None,
            episodes: EpisodeSource::default(),
        }
    }
}

impl Mapping {
    pub fn load(path: &Path) -> Result<Mapping> {
        let text = std::fs::read_to_string(path).map_err(|e| IngestError::io(path, e))?;
        Mapping::parse(&text).map_err(|m| IngestError::invalid(path, m))
    }

    pub fn parse(text: &str) -> std::result::Result<Mapping, String> {
        let m: Mapping = toml::from_str(text).map_err(|e| format!("not a valid mapping file: {e}"))?;
        if let Some(r) = m.rate_hz {
            if !(r.is_finite() && r > 0.0) {
                return Err(format!("rate_hz must be a positive number, got {r}"));
            }
        }
        if m.action.topic.is_empty() {
            return Err("action.topic is empty".into());
        }
        Ok(m)
    }

    /// Topics whose messages must be decoded.
    pub fn decoded_topics(&self) -> Vec<&str> {
        let mut t: Vec<&str> = vec![self.action.topic.as_str(), self.episodes.topic.as_str()];
        t.extend(self.observations.values().map(|f| f.topic.as_str()));
        if let Some(r) = &self.reward {
            t.push(r.topic.as_str());
        }
        t.sort();
        t.dedup();
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_example() {
        let m = Mapping::parse(
            r#"
rate_hz = 10
action = { topic = "/cmd", field = "data" }
[observations]
joint_pos = { topic = "/joint_states", field = "position" }
[episodes]
metadata = "episode"
"#,
        )
        .unwrap();
        assert_eq!(m.rate_hz, Some(10.0));
        assert_eq!(m.action.topic, "/cmd");
        assert_eq!(m.episodes.topic, "/episode_event");
        assert!(Mapping::parse("action = 3").is_err());
    }
}
