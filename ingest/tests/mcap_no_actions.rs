//! A ROS 2 recording in which some labeled episodes have no action messages: every labeled
//! episode is ingested (steps on the observation timeline, no action column), none is left out.
//!
//! The fixture `fixtures/mcap/ros2_no_actions_eval.mcap` is `ros2_jointstate_eval.mcap` with the
//! `/action` messages of episodes 1 and 3 removed, rewritten with the `mcap` crate by
//! [`drop_actions`] below (schemas, channels, the other messages and every Metadata record
//! copied as they are). `no_actions_fixture_is_reproducible` checks that the committed file is
//! exactly what it writes; `UFOPS_WRITE_FIXTURES=1` rewrites it.

use crate::common;

use std::collections::{BTreeMap, HashMap};

use common::fixtures;
use ingest::sink::CollectSink;
use ingest::{ingest, read_path, Format, IngestOptions, ReadOptions};
use store::{EpisodeFilter, Store, StoreConfig};

const FIXTURE: &str = "mcap/ros2_no_actions_eval.mcap";
/// Episodes whose `/action` messages are dropped.
const WITHOUT_ACTIONS: [i64; 2] = [1, 3];

/// Copies an MCAP file, leaving out the `/action` messages inside the given episodes (by the
/// `start_ns`/`end_ns` of their `episode` Metadata records).
fn drop_actions(src: &[u8], episodes: &[i64]) -> Vec<u8> {
    use mcap::records::Record;
    let records =
        || mcap::read::ChunkFlattener::new(src).expect("source is MCAP").map(|r| r.expect("readable record"));
    let mut spans = Vec::new();
    for r in records() {
        if let Record::Metadata(m) = r {
            if m.name == "episode" && episodes.contains(&m.metadata["index"].parse::<i64>().unwrap()) {
                spans.push((
                    m.metadata["start_ns"].parse::<u64>().unwrap(),
                    m.metadata["end_ns"].parse::<u64>().unwrap(),
                ));
            }
        }
    }
    assert_eq!(spans.len(), episodes.len(), "every episode has its Metadata record");
    let mut out = std::io::Cursor::new(Vec::new());
    let opts = mcap::WriteOptions::new()
        .profile("ros2")
        .library("ufops ingest/tests/mcap_no_actions.rs (mcap crate 0.26)")
        .compression(Some(mcap::Compression::Zstd))
        .chunk_size(Some(64 << 10));
    let mut w = opts.create(&mut out).unwrap();
    let mut schema_ids: HashMap<u16, u16> = HashMap::new();
    let mut channel_ids: HashMap<u16, (u16, String)> = HashMap::new();
    for r in records() {
        match r {
            Record::Schema { header, data } => {
                let id = w.add_schema(&header.name, &header.encoding, &data).unwrap();
                schema_ids.insert(header.id, id);
            }
            Record::Channel(c) => {
                let id = w
                    .add_channel(schema_ids[&c.schema_id], &c.topic, &c.message_encoding, &c.metadata)
                    .unwrap();
                channel_ids.insert(c.id, (id, c.topic.clone()));
            }
            Record::Message { header, data } => {
                let (id, topic) = &channel_ids[&header.channel_id];
                let t = header.log_time;
                if topic == "/action" && spans.iter().any(|&(s, e)| s <= t && t <= e) {
                    continue;
                }
                let h = mcap::records::MessageHeader { channel_id: *id, ..header };
                w.write_to_known_channel(&h, &data).unwrap();
            }
            Record::Metadata(m) => w.write_metadata(&m).unwrap(),
            _ => {}
        }
    }
    w.finish().unwrap();
    drop(w);
    out.into_inner()
}

#[test]
fn no_actions_fixture_is_reproducible() {
    let src = std::fs::read(fixtures().join("mcap/ros2_jointstate_eval.mcap")).unwrap();
    let made = drop_actions(&src, &WITHOUT_ACTIONS);
    let path = fixtures().join(FIXTURE);
    if std::env::var("UFOPS_WRITE_FIXTURES").is_ok_and(|v| v == "1") {
        std::fs::write(&path, &made).unwrap();
    }
    let committed = std::fs::read(&path).expect("fixture committed (UFOPS_WRITE_FIXTURES=1 writes it)");
    assert!(committed == made, "{} differs from what drop_actions writes", path.display());
}

/// All five labeled episodes come out, 1 and 3 without actions.
#[test]
fn labeled_episodes_without_actions_are_read() {
    let mut s = CollectSink::default();
    read_path(&fixtures().join(FIXTURE), Format::Auto, &ReadOptions::default(), &mut s).unwrap();
    let idx: Vec<i64> = s.episodes.iter().map(|e| e.metadata["index"].as_i64().unwrap()).collect();
    assert_eq!(idx, vec![0, 1, 2, 3, 4]);
    let full = {
        let mut f = CollectSink::default();
        read_path(
            &fixtures().join("mcap/ros2_jointstate_eval.mcap"),
            Format::Auto,
            &ReadOptions::default(),
            &mut f,
        )
        .unwrap();
        f
    };
    for (e, f) in s.episodes.iter().zip(&full.episodes) {
        let i = e.metadata["index"].as_i64().unwrap();
        assert_eq!(e.label, f.label, "episode {i}: the label of its Metadata record");
        let counts: BTreeMap<String, u64> =
            serde_json::from_value(e.metadata["message_counts"].clone()).unwrap();
        if WITHOUT_ACTIONS.contains(&i) {
            assert_eq!(e.action.dim, 0, "episode {i}");
            assert!(e.action.values.is_empty());
            assert!(!counts.contains_key("/action"));
            // One step per joint state message, observations as recorded.
            assert_eq!(e.len() as u64, counts["/joint_states"], "episode {i}");
            assert_eq!(e.observations.iter().find(|o| o.name == "joint_pos").unwrap().dim, 7);
            assert!(e.timestamps.windows(2).all(|w| w[0] < w[1]));
        } else {
            assert_eq!(e, f, "episode {i} is read as from the original file");
        }
    }
}

/// Into a store: every labeled episode, the ones without actions have no `action` column, and the
/// human report has no note about left-out episodes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn labeled_episodes_without_actions_are_ingested() {
    let tmp = tempfile::tempdir().unwrap();
    let store = Store::open(&StoreConfig::local(tmp.path())).await.unwrap();
    let opts =
        IngestOptions { policy: "toy-dp".into(), checkpoint: "step-80000".into(), ..Default::default() };
    let rep = ingest(&store, &fixtures().join(FIXTURE), &opts).await.unwrap();
    assert_eq!(rep.episodes, 5);
    assert_eq!((rep.labels.success, rep.labels.failure, rep.labels.unknown), (3, 2, 0));
    assert!(rep.notes.is_empty(), "{:?}", rep.notes);
    let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();
    assert_eq!(eps.len(), 5);
    for e in &eps {
        let steps = store.read_steps(&e.id, None).await.unwrap();
        let i = e.metadata["index"].as_i64().unwrap();
        assert_eq!(steps.column_by_name("action").is_none(), WITHOUT_ACTIONS.contains(&i), "episode {i}");
        assert_eq!(steps.num_rows() as i64, e.length);
    }
}
