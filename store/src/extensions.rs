//! Per-store state of the upper crates: one value per type, made on first use, behind the
//! store handle (as `http::Extensions` holds a request's). A crate above the store keeps its
//! caches here instead of in a global, so two stores in one process never share them.

use std::any::{Any, TypeId};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

#[derive(Default)]
pub(crate) struct Extensions(Mutex<HashMap<TypeId, Arc<dyn Any + Send + Sync>>>);

impl Extensions {
    pub(crate) fn get_or_default<T: Default + Send + Sync + 'static>(&self) -> Arc<T> {
        let mut map = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let slot = map.entry(TypeId::of::<T>()).or_insert_with(|| Arc::new(T::default()));
        match Arc::clone(slot).downcast::<T>() {
            Ok(v) => v,
            // The map is keyed by the value's own type id: a value of another type is never there.
            Err(_) => unreachable!("extension slot of {} holds another type", std::any::type_name::<T>()),
        }
    }
}
