//! Label writes ask whether an episode's campaign needs several labelers; the answer comes from
//! a cache of the multi-labeler policies: this process's own campaign changes are seen at once,
//! another process's (a second server on the same catalog) within `CAMPAIGN_CACHE_TTL`.

use store::test_support::{source, two_step_episode};
use store::{Label, Store, StoreConfig};
use store_labeling::{Consensus, CAMPAIGN_CACHE_TTL};

#[tokio::test]
async fn campaign_changes_reach_label_writes_at_once_here_and_within_the_ttl_elsewhere() {
    let dir = tempfile::tempdir().unwrap();
    let here = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
    let mut w = here.begin_ingest(source("a"), "pol", "c1").await.unwrap();
    w.add_episode(two_step_episode(0, Some("t"), Label::Unknown)).await.unwrap();
    w.commit("one episode").await.unwrap();
    let id = here.episodes(&Default::default()).await.unwrap()[0].id.clone();
    let elsewhere = Store::open(&StoreConfig::local(dir.path())).await.unwrap();

    assert!(!here.votes_required(&id).await.unwrap());
    assert!(!elsewhere.votes_required(&id).await.unwrap()); // cached: no multi-labeler policy
    here.set_campaign("pol", 2, true, "admin").await.unwrap();
    assert!(here.votes_required(&id).await.unwrap(), "this process's change is seen at once");
    assert!(here.any_multi_labeler_campaign().await.unwrap());
    std::thread::sleep(CAMPAIGN_CACHE_TTL + std::time::Duration::from_millis(100));
    assert!(elsewhere.votes_required(&id).await.unwrap(), "another process's, within the TTL");

    elsewhere.set_campaign("pol", 1, false, "admin").await.unwrap();
    assert!(!elsewhere.votes_required(&id).await.unwrap());
    std::thread::sleep(CAMPAIGN_CACHE_TTL + std::time::Duration::from_millis(100));
    assert!(!here.votes_required(&id).await.unwrap());
    assert!(!here.any_multi_labeler_campaign().await.unwrap());
}
