//! A byte-budgeted cache of values loaded from immutable objects (an entry never goes stale):
//! the least recently used are dropped first past the budget, and concurrent readers of one key
//! share one load. The steps files' footers (`read::MetaCache`) and the decoded pages of image
//! columns (`frames::PageCache`) are two of them.

use std::collections::HashMap;
use std::hash::Hash;
use std::sync::{Arc, Mutex};

use tokio::sync::OnceCell;

pub(crate) struct ByteLru<K, V> {
    state: Mutex<State<K, V>>,
    budget: usize,
}

struct State<K, V> {
    entries: HashMap<K, Entry<V>>,
    tick: u64,
    bytes: usize,
}

struct Entry<V> {
    cell: Arc<OnceCell<V>>,
    last_used: u64,
    /// 0 until [`ByteLru::loaded`] records the loaded value's size.
    size: usize,
}

impl<K: Eq + Hash + Clone, V> ByteLru<K, V> {
    pub(crate) fn new(budget: usize) -> Self {
        ByteLru { state: Mutex::new(State { entries: HashMap::new(), tick: 0, bytes: 0 }), budget }
    }

    /// The cell of `key` (created empty when absent), marked as used now: fill it with
    /// `get_or_try_init`, then call [`Self::loaded`] if this caller did the load.
    pub(crate) fn cell(&self, key: &K) -> Arc<OnceCell<V>> {
        let mut st = self.state.lock().unwrap_or_else(|p| p.into_inner());
        st.tick += 1;
        let tick = st.tick;
        let e = st.entries.entry(key.clone()).or_insert_with(|| Entry {
            cell: Arc::new(OnceCell::new()),
            last_used: tick,
            size: 0,
        });
        e.last_used = tick;
        e.cell.clone()
    }

    /// Records the size of a freshly loaded value and evicts the least recently used others
    /// until the cache is within its budget.
    pub(crate) fn loaded(&self, key: &K, size: usize) {
        let mut st = self.state.lock().unwrap_or_else(|p| p.into_inner());
        match st.entries.get_mut(key) {
            Some(e) if e.size == 0 => e.size = size,
            _ => return,
        }
        st.bytes += size;
        while st.bytes > self.budget && st.entries.len() > 1 {
            let Some(victim) = st
                .entries
                .iter()
                .filter(|(k, e)| *k != key && e.size > 0)
                .min_by_key(|(_, e)| e.last_used)
                .map(|(k, _)| k.clone())
            else {
                break;
            };
            if let Some(e) = st.entries.remove(&victim) {
                st.bytes -= e.size;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::ByteLru;

    #[test]
    fn evicts_the_least_recently_used_past_the_budget() {
        let lru: ByteLru<u32, u32> = ByteLru::new(10);
        for k in 0..3 {
            lru.cell(&k).set(k).unwrap();
            lru.loaded(&k, 4);
        }
        // 12 bytes > 10: key 0, the least recently used, went when key 2 came.
        assert!(lru.cell(&0).get().is_none());
        assert_eq!((lru.cell(&1).get(), lru.cell(&2).get()), (Some(&1), Some(&2)));
        // Using 1 makes 2 the oldest: a new key evicts 2.
        lru.cell(&1);
        lru.cell(&3).set(3).unwrap();
        lru.loaded(&3, 4);
        assert!(lru.cell(&2).get().is_none());
        assert_eq!(lru.cell(&1).get(), Some(&1));
    }
}
