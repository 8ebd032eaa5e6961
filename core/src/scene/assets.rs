//! Files a load has parsed, kept for the loads after it. The frames of an animation share
//! their meshes, curve files and images: a worker rendering frame after frame, or a
//! submission checking every frame, reads and parses each such file once
//! ([`LoadLimits::assets`](super::LoadLimits)).
//!
//! A file is known by what it is on disk (device, inode, length and modification time), not by
//! its path: a worker lays each bundle out afresh as hard links to its cached files, so the same
//! file has a new path in every load. What a load keeps is the parsed file in the object's own
//! space (a scene transforms its copy); images are shared as they are. Entries no load used
//! since the one before the latest are dropped when the next load begins, so the cache holds
//! about one scene's files.

use std::any::Any;
use std::collections::HashMap;
use std::path::Path;
use std::sync::{Arc, Mutex};

/// Parsed files by identity; see the module's documentation.
#[derive(Default)]
pub struct AssetCache {
    inner: Mutex<Inner>,
}

#[derive(Default)]
struct Inner {
    entries: HashMap<Key, (Arc<dyn Any + Send + Sync>, u64)>,
    /// Loads begun so far.
    loads: u64,
    hits: u64,
    misses: u64,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq)]
struct Key {
    dev: u64,
    ino: u64,
    len: u64,
    modified: Option<std::time::SystemTime>,
    /// What was made of the file (the parser and its settings).
    what: String,
}

impl std::fmt::Debug for AssetCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (hits, misses) = self.counts();
        f.debug_struct("AssetCache").field("hits", &hits).field("misses", &misses).finish()
    }
}

impl AssetCache {
    pub fn new() -> AssetCache {
        AssetCache::default()
    }

    /// Marks the start of a load: what neither the last load nor this one uses goes.
    pub(crate) fn begin_load(&self) {
        let mut inner = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        inner.loads += 1;
        let keep_from = inner.loads - 1;
        inner.entries.retain(|_, (_, used)| *used >= keep_from);
    }

    /// Files found parsed already, and files parsed, so far.
    pub fn counts(&self) -> (u64, u64) {
        let inner = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        (inner.hits, inner.misses)
    }

    /// What `load` makes of the file at `path` (`what` names the parser and its settings),
    /// made once while the file is unchanged. A file whose identity cannot be read is loaded
    /// every time (its loader says why it cannot be read).
    pub(crate) fn get<T: Send + Sync + 'static, E>(
        &self,
        path: &Path,
        what: &str,
        load: impl FnOnce() -> Result<T, E>,
    ) -> Result<Arc<T>, E> {
        let Some(key) = identity(path, what) else { return load().map(Arc::new) };
        {
            let mut inner = self.inner.lock().unwrap_or_else(|e| e.into_inner());
            let now = inner.loads;
            let found = inner.entries.get_mut(&key).and_then(|(v, used)| {
                *used = now;
                v.clone().downcast::<T>().ok()
            });
            if let Some(v) = found {
                inner.hits += 1;
                return Ok(v);
            }
            inner.misses += 1;
        }
        // Parsed without the lock.
        let v = Arc::new(load()?);
        let mut inner = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        let now = inner.loads;
        inner.entries.insert(key, (v.clone(), now));
        Ok(v)
    }
}

#[cfg(unix)]
fn identity(path: &Path, what: &str) -> Option<Key> {
    use std::os::unix::fs::MetadataExt;
    let m = std::fs::metadata(path).ok()?;
    Some(Key {
        dev: m.dev(),
        ino: m.ino(),
        len: m.len(),
        modified: m.modified().ok(),
        what: what.to_string(),
    })
}

#[cfg(not(unix))]
fn identity(_: &Path, _: &str) -> Option<Key> {
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_is_parsed_once_while_unchanged_and_dropped_when_unused() {
        let dir = std::env::temp_dir().join(format!("furnace-assets-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (a, link) = (dir.join("a.txt"), dir.join("link.txt"));
        std::fs::write(&a, "one").unwrap();
        std::fs::remove_file(&link).ok();
        std::fs::hard_link(&a, &link).unwrap();
        let cache = AssetCache::new();
        let read = |p: &Path| cache.get(p, "text", || std::fs::read_to_string(p)).unwrap();
        cache.begin_load();
        assert_eq!(*read(&a), "one");
        // The same file through another path (a bundle laid out again) is the same entry.
        assert_eq!(*read(&link), "one");
        assert_eq!(cache.counts(), (1, 1));
        // Another parse of the same file is another entry.
        assert_eq!(cache.get(&a, "length", || Ok::<_, ()>(3usize)).unwrap(), Arc::new(3));
        assert_eq!(cache.counts(), (1, 2));
        // Changed (another length): parsed again.
        std::fs::write(&a, "two!").unwrap();
        assert_eq!(*read(&a), "two!");
        assert_eq!(cache.counts(), (1, 3));
        // Unused by two loads: gone.
        cache.begin_load();
        cache.begin_load();
        cache.begin_load();
        assert!(cache.inner.lock().unwrap().entries.is_empty());
        std::fs::remove_dir_all(&dir).ok();
    }
}
