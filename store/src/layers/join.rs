//! Reading episodes with their layers joined to the steps as `obs.<layer>` columns.

use super::{LAYER_META_KEY, PRODUCER_META_KEY};
use crate::read::{EpisodeLocation, EpisodeSteps, StepsReadError, StepsStream};
use crate::steps::OBS_PREFIX;
use crate::{Store, StoreError};
use arrow::array::{Array, ArrayRef, Int32Array, RecordBatch};
use arrow::datatypes::{Field, Schema};
use std::collections::HashMap;
use std::sync::Arc;
use tokio::sync::mpsc;

/// Rows of layer values held at once by a joined read (the layer side of one group of episodes).
const JOIN_GROUP_ROWS: usize = 1 << 15;

impl Store {
    /// The steps of one episode with the layers joined (as `obs.<layer>` columns).
    pub async fn read_steps_with_layers(
        &self,
        id: &str,
        version: Option<i64>,
        layers: &[String],
    ) -> Result<RecordBatch, StoreError> {
        let ids = [id.to_string()];
        let loc = self.locate_episodes(&ids, version).await?;
        let layer_locs = self.locate_layers(&ids, layers, version).await?;
        let mut stream = self.read_episodes_with_layers(loc, layers.to_vec(), layer_locs);
        match stream.next().await {
            Some(Ok(ep)) => Ok(ep.steps),
            Some(Err(e)) => Err(e.error),
            None => Err(StoreError::Corrupt(format!("episode {id}: the read returned nothing"))),
        }
    }

    /// [`Store::read_episodes`] with layers joined: each episode's steps gain one column
    /// `obs.<layer>` per layer (field metadata [`LAYER_META_KEY`], [`PRODUCER_META_KEY`] and
    /// `ufops.observation_key`), checked step by step (`t`) against the steps. `layer_locations`
    /// come from [`Store::locate_layers`] for the same episodes. Episodes are read in groups of
    /// about `JOIN_GROUP_ROWS` rows: a group's layer values first (each layer file's pages
    /// once), then its steps, joined as they arrive; memory is one group's layer values plus
    /// the steps reads in flight.
    pub fn read_episodes_with_layers(
        &self,
        locations: Vec<EpisodeLocation>,
        layers: Vec<String>,
        layer_locations: Vec<Vec<(EpisodeLocation, String)>>,
    ) -> StepsStream {
        let (tx, rx) = mpsc::channel(16);
        let store = self.clone();
        let task = tokio::spawn(async move {
            // Groups in the steps' file order, so each group's reads stay sequential.
            let mut order: Vec<usize> = (0..locations.len()).collect();
            order.sort_by(|&a, &b| {
                let (x, y) = (&locations[a], &locations[b]);
                (&x.data_file, x.row_group, x.row_offset).cmp(&(&y.data_file, y.row_group, y.row_offset))
            });
            let mut start = 0;
            while start < order.len() {
                let mut end = start;
                let mut rows = 0;
                while end < order.len()
                    && (end == start || rows + locations[order[end]].row_count <= JOIN_GROUP_ROWS)
                {
                    rows += locations[order[end]].row_count;
                    end += 1;
                }
                let group = &order[start..end];
                start = end;
                if !join_group(&store, &locations, &layers, &layer_locations, group, &tx).await {
                    return;
                }
            }
        });
        StepsStream::from_parts(rx, task)
    }
}

/// Reads one group's layer values, then its steps, and sends each episode joined. False when
/// the receiver is gone.
async fn join_group(
    store: &Store,
    locations: &[EpisodeLocation],
    layers: &[String],
    layer_locations: &[Vec<(EpisodeLocation, String)>],
    group: &[usize],
    tx: &mpsc::Sender<Result<EpisodeSteps, StepsReadError>>,
) -> bool {
    // values[layer][position in group] = the value column and its producer.
    type Column = Option<(ArrayRef, Arc<Int32Array>)>;
    let mut values: Vec<Vec<Column>> = vec![vec![None; group.len()]; layers.len()];
    let mut failed: HashMap<usize, StepsReadError> = HashMap::new();
    for (li, locs) in layer_locations.iter().enumerate() {
        let wanted: Vec<EpisodeLocation> = group.iter().map(|&i| locs[i].0.clone()).collect();
        let mut stream = store.read_episodes(wanted);
        while let Some(item) = stream.next().await {
            match item {
                Ok(ep) => {
                    let cols = (ep.steps.column_by_name("value").cloned(), ep.steps.column_by_name("t"));
                    match cols {
                        (Some(v), Some(t)) => match t.as_any().downcast_ref::<Int32Array>() {
                            Some(t) => values[li][ep.index] = Some((v, Arc::new(t.clone()))),
                            None => {
                                let err = StoreError::Corrupt(format!(
                                    "layer {}: column t is not int32",
                                    layers[li]
                                ));
                                failed.insert(
                                    group[ep.index],
                                    read_error(vec![group[ep.index]], &locs[group[ep.index]].0, err),
                                );
                            }
                        },
                        _ => {
                            let err = StoreError::Corrupt(format!(
                                "layer {}: file lacks its value or t column",
                                layers[li]
                            ));
                            failed.insert(
                                group[ep.index],
                                read_error(vec![group[ep.index]], &locs[group[ep.index]].0, err),
                            );
                        }
                    }
                }
                Err(e) => {
                    for k in &e.indexes {
                        let i = group[*k];
                        failed.insert(
                            i,
                            StepsReadError {
                                indexes: vec![i],
                                file: e.file.clone(),
                                error: StoreError::Corrupt(e.error.to_string()),
                            },
                        );
                    }
                }
            }
        }
    }
    let wanted: Vec<EpisodeLocation> = group.iter().map(|&i| locations[i].clone()).collect();
    let mut stream = store.read_episodes(wanted);
    while let Some(item) = stream.next().await {
        let out = match item {
            Err(e) => Err(StepsReadError {
                indexes: e.indexes.iter().map(|k| group[*k]).collect(),
                file: e.file,
                error: e.error,
            }),
            Ok(ep) => {
                let i = group[ep.index];
                match failed.remove(&i) {
                    Some(err) => Err(err),
                    None => join_episode(&ep.steps, layers, layer_locations, &values, ep.index, i)
                        .map(|steps| EpisodeSteps { index: i, steps })
                        .map_err(|error| read_error(vec![i], &locations[i], error)),
                }
            }
        };
        if tx.send(out).await.is_err() {
            return false;
        }
    }
    true
}

fn read_error(indexes: Vec<usize>, loc: &EpisodeLocation, error: StoreError) -> StepsReadError {
    StepsReadError { indexes, file: loc.data_file.clone(), error }
}

#[allow(clippy::type_complexity)]
fn join_episode(
    steps: &RecordBatch,
    layers: &[String],
    layer_locations: &[Vec<(EpisodeLocation, String)>],
    values: &[Vec<Option<(ArrayRef, Arc<Int32Array>)>>],
    pos: usize,
    index: usize,
) -> Result<RecordBatch, StoreError> {
    let steps_t = steps
        .column_by_name("t")
        .and_then(|c| c.as_any().downcast_ref::<Int32Array>())
        .ok_or_else(|| StoreError::Corrupt("steps lack their t column".into()))?;
    let mut fields: Vec<Arc<Field>> = steps.schema().fields().iter().cloned().collect();
    let mut columns: Vec<ArrayRef> = steps.columns().to_vec();
    for (li, name) in layers.iter().enumerate() {
        let (loc, producer) = &layer_locations[li][index];
        let Some((value, t)) = &values[li][pos] else {
            return Err(StoreError::Corrupt(format!(
                "episode {}: layer {name} was not read",
                loc.episode_id
            )));
        };
        if t.values() != steps_t.values() {
            return Err(StoreError::Corrupt(format!(
                "episode {}: layer {name} has {} rows whose steps differ from the episode's {}",
                loc.episode_id,
                t.len(),
                steps_t.len()
            )));
        }
        let column = format!("{OBS_PREFIX}{name}");
        if fields.iter().any(|f| f.name() == &column) {
            return Err(StoreError::invalid(format!(
                "layer {name} shadows the observation key {name:?} of episode {}",
                loc.episode_id
            )));
        }
        let meta = HashMap::from([
            ("ufops.observation_key".to_string(), name.clone()),
            (LAYER_META_KEY.to_string(), name.clone()),
            (PRODUCER_META_KEY.to_string(), producer.clone()),
        ]);
        fields.push(Arc::new(Field::new(column, value.data_type().clone(), false).with_metadata(meta)));
        columns.push(value.clone());
    }
    let schema = Arc::new(Schema::new_with_metadata(fields, steps.schema().metadata().clone()));
    Ok(RecordBatch::try_new(schema, columns)?)
}
