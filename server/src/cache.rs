//! The served files' bytes, held in memory while they stay the same on disk: [`FileCache`].
//!
//! Serving a file from disk costs a trip to tokio's blocking pool for every open, stat, seek and
//! 64 KiB read; under load those hops, not the bytes, were where the time went (a 1 MiB GET took
//! about 20 of them). A file read once is kept as one shared buffer ([`Bytes`]) and every later
//! response, whole or a range, is a slice of it written straight to the socket. An entry is used
//! only while the file on disk still has the same length, modification time, inode and device
//! (one `stat` per request, which the catalog's lookup does anyway), so a replaced or rewritten
//! file is read again and never served stale; a file that changes while it is being read is not
//! kept.
//!
//! Bounds: a budget of bytes in all (`msth serve --cache-mib`, default 256 MiB; 0 turns
//! the cache off), files larger than a quarter of it are always streamed from disk, and the
//! least recently used entries make room for new ones. So the memory the cache takes is at most
//! the budget, whatever the load.

use std::collections::HashMap;
use std::fs::Metadata;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::SystemTime;

use axum::body::Bytes;

/// What identifies one version of a file on disk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct FileId {
    len: u64,
    modified: SystemTime,
    ino: u64,
    dev: u64,
}

impl FileId {
    pub(crate) fn of(meta: &Metadata) -> FileId {
        #[cfg(unix)]
        let (ino, dev) = {
            use std::os::unix::fs::MetadataExt;
            (meta.ino(), meta.dev())
        };
        #[cfg(not(unix))]
        let (ino, dev) = (0, 0);
        FileId {
            len: meta.len(),
            modified: meta.modified().unwrap_or(SystemTime::UNIX_EPOCH),
            ino,
            dev,
        }
    }
}

struct Entry {
    id: FileId,
    bytes: Bytes,
    last_used: u64,
}

#[derive(Default)]
struct Inner {
    entries: HashMap<PathBuf, Entry>,
    used: u64,
    clock: u64,
}

/// Files' bytes by path, at most `budget` bytes in all.
pub(crate) struct FileCache {
    inner: Mutex<Inner>,
    budget: u64,
}

impl FileCache {
    pub(crate) fn new(budget: u64) -> FileCache {
        FileCache {
            inner: Mutex::new(Inner::default()),
            budget,
        }
    }

    /// Whether a file of `len` bytes is kept (larger ones are streamed from disk).
    pub(crate) fn admits(&self, len: u64) -> bool {
        len > 0 && len <= self.budget / 4
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The bytes of `path` if they were read from the version `id` describes.
    pub(crate) fn get(&self, path: &Path, id: FileId) -> Option<Bytes> {
        let mut inner = self.lock();
        inner.clock += 1;
        let clock = inner.clock;
        let e = inner.entries.get_mut(path)?;
        if e.id != id {
            return None;
        }
        e.last_used = clock;
        Some(e.bytes.clone())
    }

    /// Keeps `bytes`, read from the version `id` of `path`, evicting the least recently used
    /// entries to stay within the budget.
    pub(crate) fn insert(&self, path: &Path, id: FileId, bytes: Bytes) {
        let len = bytes.len() as u64;
        if !self.admits(len) {
            return;
        }
        let mut inner = self.lock();
        if let Some(old) = inner.entries.remove(path) {
            inner.used -= old.bytes.len() as u64;
        }
        while inner.used + len > self.budget {
            let Some(oldest) = inner
                .entries
                .iter()
                .min_by_key(|(_, e)| e.last_used)
                .map(|(p, _)| p.clone())
            else {
                break;
            };
            if let Some(e) = inner.entries.remove(&oldest) {
                inner.used -= e.bytes.len() as u64;
            }
        }
        inner.clock += 1;
        let last_used = inner.clock;
        inner.used += len;
        inner.entries.insert(
            path.to_path_buf(),
            Entry {
                id,
                bytes,
                last_used,
            },
        );
    }

    /// Bytes held now.
    #[cfg(test)]
    fn used(&self) -> u64 {
        self.lock().used
    }
}

/// Reads the whole file at `path` if it is still the version `id` before and after the read
/// (`None`: it changed, or cannot be read; the caller then streams it from disk).
pub(crate) fn read_version(path: &Path, id: FileId) -> Option<Bytes> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).ok()?;
    if FileId::of(&f.metadata().ok()?) != id {
        return None;
    }
    let mut buf = Vec::with_capacity(id.len as usize);
    (&mut f).take(id.len + 1).read_to_end(&mut buf).ok()?;
    let after = FileId::of(&f.metadata().ok()?);
    (after == id && buf.len() as u64 == id.len).then(|| Bytes::from(buf))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entries_follow_the_file_and_stay_within_the_budget() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b, c) = (
            dir.path().join("a.msth"),
            dir.path().join("b.msth"),
            dir.path().join("c.msth"),
        );
        std::fs::write(&a, [1u8; 100]).unwrap();
        std::fs::write(&b, [2u8; 100]).unwrap();
        std::fs::write(&c, [3u8; 100]).unwrap();
        let id = |p: &Path| FileId::of(&std::fs::metadata(p).unwrap());
        let cache = FileCache::new(400);
        assert!(cache.admits(100) && !cache.admits(101) && !cache.admits(0));
        for p in [&a, &b] {
            let bytes = read_version(p, id(p)).unwrap();
            cache.insert(p, id(p), bytes);
        }
        assert_eq!(cache.get(&a, id(&a)).unwrap()[0], 1);
        // b is now the least recently used: c takes more room than is left, b goes.
        cache.insert(&c, id(&c), Bytes::from(vec![3u8; 100]));
        cache.insert(&dir.path().join("d"), id(&c), Bytes::from(vec![4u8; 100]));
        cache.insert(&dir.path().join("e"), id(&c), Bytes::from(vec![5u8; 100]));
        assert!(cache.used() <= 400);
        assert!(cache.get(&b, id(&b)).is_none());
        // A rewritten file is another version: the entry no longer answers.
        std::fs::write(&a, [9u8; 50]).unwrap();
        assert!(cache.get(&a, id(&a)).is_none());
        // read_version refuses a version that is not the file's.
        let old = id(&c);
        std::fs::write(&c, [7u8; 10]).unwrap();
        assert!(read_version(&c, old).is_none());
    }
}
