//! Layers: derived per-step data attached to stored episodes without rewriting their steps files
//! (store/README.md, "Layers"). A layer is a named per-step float32 vector — typically the
//! frozen embedding of a policy's own vision encoder for each step's camera frame — made by a
//! *producer* (a JSON object naming the encoder, the policy checkpoint whose encoder it is and
//! the weights' content hash) and identified by the sha256 of its canonical JSON.
//!
//! Writing a layer is a new version: the values go to their own Parquet file (one page per
//! episode, as the steps files), the catalog records where each episode's rows are
//! (`episode_layers`), and the read path joins them to the steps as `obs.<layer name>` columns.
//! An episode that already holds the layer from the same producer is skipped, so a computation
//! that commits in groups resumes where it stopped and a re-run writes nothing.
//!
//! `write` holds the write path (encoding a layer file, the version's catalog rows), `join` the
//! read path that joins layers to the steps; this file the types and the catalog's listings.

mod join;
mod write;

use crate::catalog::RowExt;
use crate::model::check_name;
use crate::read::{visible, EpisodeLocation};
use crate::{Store, StoreError};
use serde::Serialize;
use std::collections::HashMap;

/// The widest layer accepted (values per step).
pub const MAX_LAYER_DIM: usize = 1 << 16;
/// Field metadata of a joined layer column: its layer name and its producer's hash.
pub const LAYER_META_KEY: &str = "ufops.layer";
pub const PRODUCER_META_KEY: &str = "ufops.layer_producer";
/// Catalog look-ups per statement.
const IDS_PER_QUERY: usize = 400;

/// One layer as the catalog lists it: a (name, producer) pair.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct LayerRecord {
    pub name: String,
    pub producer_hash: String,
    /// The producer as written (a JSON object).
    #[cfg_attr(feature = "openapi", schema(value_type = Object))]
    pub producer: serde_json::Value,
    pub dim: i64,
    /// Episodes whose current value of this layer comes from this producer.
    pub episodes: i64,
    /// The version that first wrote it.
    pub version: i64,
}

/// One episode's values of a layer, as given to [`Store::write_layer`]: `values` is
/// `steps * dim`, row-major, one row per step of the episode (t = 0, 1, …).
#[derive(Debug, Clone)]
pub struct LayerValues {
    pub episode_id: String,
    pub dim: usize,
    pub values: Vec<f32>,
}

/// What [`Store::write_layer`] did.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct LayerWrite {
    /// The new version, or none when every episode already held the layer from this producer.
    pub version: Option<i64>,
    pub producer_hash: String,
    pub episodes_written: usize,
    pub episodes_skipped: usize,
}

/// A layer an episode holds (see [`Store::episode_layers`]).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct EpisodeLayer {
    pub layer: String,
    pub producer_hash: String,
    pub dim: i64,
    pub version_added: i64,
}

/// The sha256 of a producer's canonical JSON (object keys sorted at every level, no spaces):
/// equal producers hash equally however their keys were ordered.
pub fn producer_hash(producer: &serde_json::Value) -> Result<String, StoreError> {
    if !producer.is_object() || producer.as_object().is_some_and(|o| o.is_empty()) {
        return Err(StoreError::invalid(
            "a layer's producer must be a non-empty JSON object (e.g. {\"encoder\": …, \"policy\": …, \"checkpoint\": …, \"content_hash\": …})",
        ));
    }
    let mut out = String::new();
    canonical(producer, &mut out);
    Ok(crate::sha256_hex(out.as_bytes()))
}

fn canonical(v: &serde_json::Value, out: &mut String) {
    match v {
        serde_json::Value::Object(m) => {
            let mut keys: Vec<&String> = m.keys().collect();
            keys.sort();
            out.push('{');
            for (i, k) in keys.into_iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                out.push_str(&serde_json::Value::String(k.clone()).to_string());
                out.push(':');
                canonical(&m[k], out);
            }
            out.push('}');
        }
        serde_json::Value::Array(a) => {
            out.push('[');
            for (i, x) in a.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                canonical(x, out);
            }
            out.push(']');
        }
        other => out.push_str(&other.to_string()),
    }
}

/// A layer name: a store name that is also usable as an observation key (no `/`, no spaces).
pub fn check_layer_name(name: &str) -> Result<(), StoreError> {
    check_name("layer", name)?;
    if name.len() > 120 || !name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-')) {
        return Err(StoreError::invalid(format!(
            "invalid layer name {name:?}: up to 120 ASCII letters, digits, '.', '_' or '-' (e.g. features.dp-resnet18)"
        )));
    }
    Ok(())
}

impl Store {
    /// The episodes (ids, in id order) that hold layer `name` from `producer_hash` now: what a
    /// resumed computation skips.
    pub async fn layer_episodes(&self, name: &str, producer_hash: &str) -> Result<Vec<String>, StoreError> {
        let rows = sqlx::query(
            "SELECT episode_id FROM episode_layers WHERE layer = $1 AND producer_hash = $2 \
             AND version_removed IS NULL ORDER BY episode_id",
        )
        .bind(name)
        .bind(producer_hash)
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter().map(|r| r.s("episode_id")).collect()
    }

    /// Every (layer, producer) the store holds, with how many episodes hold it now.
    pub async fn layers(&self) -> Result<Vec<LayerRecord>, StoreError> {
        let rows = sqlx::query(
            "SELECT l.name, l.producer_hash, l.producer, l.dim, l.version_added, \
             (SELECT COUNT(*) FROM episode_layers e WHERE e.layer = l.name AND e.producer_hash = l.producer_hash \
              AND e.version_removed IS NULL) AS episodes \
             FROM layers l ORDER BY l.name, l.version_added",
        )
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(LayerRecord {
                    name: r.s("name")?,
                    producer_hash: r.s("producer_hash")?,
                    producer: serde_json::from_str(&r.s("producer")?)?,
                    dim: r.i("dim")?,
                    episodes: r.i("episodes")?,
                    version: r.i("version_added")?,
                })
            })
            .collect()
    }

    /// The layers an episode holds, now or as of `version`.
    pub async fn episode_layers(
        &self,
        episode_id: &str,
        version: Option<i64>,
    ) -> Result<Vec<EpisodeLayer>, StoreError> {
        let rows = sqlx::query(
            "SELECT e.layer, e.producer_hash, e.version_added, e.version_removed, l.dim FROM episode_layers e \
             JOIN layers l ON l.name = e.layer AND l.producer_hash = e.producer_hash \
             WHERE e.episode_id = $1 ORDER BY e.layer",
        )
        .bind(episode_id)
        .fetch_all(&self.catalog().pool)
        .await?;
        let mut out = Vec::new();
        for r in rows {
            if visible(r.i("version_added")?, r.oi("version_removed")?, version) {
                out.push(EpisodeLayer {
                    layer: r.s("layer")?,
                    producer_hash: r.s("producer_hash")?,
                    dim: r.i("dim")?,
                    version_added: r.i("version_added")?,
                });
            }
        }
        Ok(out)
    }

    /// Where each episode's values of each layer are (now, or as of `version`): one list per
    /// layer, in the order of `ids`, with the producer of each. An episode without the layer is
    /// [`StoreError::NotFound`] naming both.
    pub async fn locate_layers(
        &self,
        ids: &[String],
        layers: &[String],
        version: Option<i64>,
    ) -> Result<Vec<Vec<(EpisodeLocation, String)>>, StoreError> {
        let mut out = Vec::with_capacity(layers.len());
        for name in layers {
            check_layer_name(name)?;
            let mut found: HashMap<String, (EpisodeLocation, String)> = HashMap::with_capacity(ids.len());
            for chunk in ids.chunks(IDS_PER_QUERY) {
                let marks: Vec<String> = (2..chunk.len() + 2).map(|i| format!("${i}")).collect();
                let sql = format!(
                    "SELECT episode_id, producer_hash, data_file, row_group, row_offset, row_count, version_added, \
                     version_removed FROM episode_layers WHERE layer = $1 AND episode_id IN ({})",
                    marks.join(", ")
                );
                let mut q = sqlx::query(&sql).bind(name.as_str());
                for id in chunk {
                    q = q.bind(id.as_str());
                }
                for r in q.fetch_all(&self.catalog().pool).await? {
                    if visible(r.i("version_added")?, r.oi("version_removed")?, version) {
                        let (id, loc) = EpisodeLocation::from_row(&r, "episode_id")?;
                        found.insert(id, (loc, r.s("producer_hash")?));
                    }
                }
            }
            let per_id = ids
                .iter()
                .map(|id| {
                    found.remove(id).ok_or_else(|| {
                        let at = version.map_or_else(|| "now".to_string(), |v| format!("in version {v}"));
                        StoreError::not_found(
                            "layer",
                            format!("{name} of episode {id} {at} (see `ufops layers`)"),
                        )
                    })
                })
                .collect::<Result<Vec<_>, _>>()?;
            out.push(per_id);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn producer_hash_ignores_key_order_and_needs_an_object() {
        let a = serde_json::json!({"encoder": "cnn", "policy": "p", "nested": {"b": 1, "a": [1, 2]}});
        let b: serde_json::Value =
            serde_json::from_str(r#"{"nested": {"a": [1, 2], "b": 1}, "policy": "p", "encoder": "cnn"}"#)
                .unwrap();
        assert_eq!(producer_hash(&a).unwrap(), producer_hash(&b).unwrap());
        let c = serde_json::json!({"encoder": "cnn2", "policy": "p", "nested": {"b": 1, "a": [1, 2]}});
        assert_ne!(producer_hash(&a).unwrap(), producer_hash(&c).unwrap());
        assert!(producer_hash(&serde_json::json!("cnn")).is_err());
        assert!(producer_hash(&serde_json::json!({})).is_err());
    }

    #[test]
    fn layer_names_are_observation_keys() {
        assert!(check_layer_name("features.dp-resnet18").is_ok());
        for bad in ["", "a b", "../x", "x/y", "é"] {
            assert!(check_layer_name(bad).is_err(), "{bad:?}");
        }
    }
}
