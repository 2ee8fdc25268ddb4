//! Where a dataset's pixels live: in memory, or in a compact memory-mapped frame cache on disk.
//!
//! A frame cache is one file of 8-bit RGB frames of one size, back to back after a 4096-byte
//! header, so that a dataset larger than RAM is bounded by disk: the training ray sampler and
//! the evaluation read pixels straight from the mapping and the kernel pages them in and out.
//!
//! Header (little-endian): magic `MSTHFRC1`, `u32` version (1), `u32` width, `u32` height,
//! `u32` 0, `u64` frame count, `u64` source fingerprint, `u64` data offset (4096), `u32` CRC-32
//! of the preceding 52 bytes. The fingerprint covers the source files (paths, sizes, modification
//! times) and the loading options that change pixels (downscale, undistortion); a cache whose
//! header, fingerprint or length does not match is rebuilt. A cache is written to a temporary
//! file next to it and renamed into place when complete, so an interrupted build leaves nothing
//! that looks valid.

use std::fs::File;
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::{DatasetError, Pixels};

const MAGIC: &[u8; 8] = b"MSTHFRC1";
const VERSION: u32 = 1;
/// Size of the header; frames start here (page aligned).
pub const DATA_OFFSET: u64 = 4096;
const HEADER_USED: usize = 56;

/// A progress callback: `(done, total)` frames.
pub type ProgressFn = dyn Fn(u64, u64) + Send + Sync;

/// Where to keep a dataset's frames.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum FrameStorage {
    /// Every frame in memory (the default; fastest for small datasets).
    #[default]
    Memory,
    /// Always in the cache file at this path (created or rebuilt as needed).
    Disk(PathBuf),
    /// In memory when the frames take at most `memory_limit` bytes, else in the cache `file`.
    Auto { file: PathBuf, memory_limit: u64 },
}

impl FrameStorage {
    /// The cache file that frames of `bytes` bytes in total would go to, if any.
    pub fn cache_file(&self, bytes: u64) -> Option<&Path> {
        match self {
            FrameStorage::Memory => None,
            FrameStorage::Disk(p) => Some(p),
            FrameStorage::Auto { file, memory_limit } => (bytes > *memory_limit).then_some(file),
        }
    }
}

/// What a cache must hold to be valid for a dataset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CacheKey {
    pub width: u32,
    pub height: u32,
    pub count: u64,
    pub fingerprint: u64,
}

impl CacheKey {
    fn frame_bytes(&self) -> u64 {
        self.width as u64 * self.height as u64 * 3
    }

    fn header(&self) -> [u8; DATA_OFFSET as usize] {
        let mut h = [0u8; DATA_OFFSET as usize];
        h[0..8].copy_from_slice(MAGIC);
        h[8..12].copy_from_slice(&VERSION.to_le_bytes());
        h[12..16].copy_from_slice(&self.width.to_le_bytes());
        h[16..20].copy_from_slice(&self.height.to_le_bytes());
        h[24..32].copy_from_slice(&self.count.to_le_bytes());
        h[32..40].copy_from_slice(&self.fingerprint.to_le_bytes());
        h[40..48].copy_from_slice(&DATA_OFFSET.to_le_bytes());
        let crc = crc32fast::hash(&h[0..52]);
        h[52..56].copy_from_slice(&crc.to_le_bytes());
        h
    }
}

/// A 64-bit FNV-1a hash, built up from the parts that identify a dataset's pixels.
#[derive(Clone, Copy, Debug)]
pub struct Fingerprint(u64);

impl Default for Fingerprint {
    fn default() -> Self {
        Fingerprint(0xcbf2_9ce4_8422_2325)
    }
}

impl Fingerprint {
    /// Adds raw bytes (delimited, so that consecutive parts cannot run together).
    pub fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 ^= x as u64;
            self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
        }
        // A separator so that ("ab", "c") and ("a", "bc") differ.
        self.0 ^= 0xff;
        self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
    }

    /// Adds a string.
    pub fn str(&mut self, s: &str) {
        self.bytes(s.as_bytes());
    }

    /// A source file: its path, size and modification time (an error names the file).
    pub fn file(&mut self, path: &Path) -> Result<(), DatasetError> {
        let meta = std::fs::metadata(path).map_err(|source| DatasetError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        self.str(&path.to_string_lossy());
        self.bytes(&meta.len().to_le_bytes());
        let mtime = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        self.bytes(&mtime.to_le_bytes());
        Ok(())
    }

    /// The hash of everything added.
    pub fn finish(&self) -> u64 {
        self.0
    }
}

/// An open cache file: the file (for positional reads) and its read-only mapping.
#[derive(Debug)]
pub struct CacheFile {
    file: File,
    map: memmap2::Mmap,
}

impl CacheFile {
    /// The whole file, mapped.
    pub fn bytes(&self) -> &[u8] {
        &self.map
    }

    /// Reads `buf.len()` bytes at `offset` with a positional read (`pread`), without mapping
    /// them into the process: the pages stay in the kernel's page cache, which it can drop at
    /// will, so random access over a file larger than RAM does not grow the resident set.
    /// Falls back to the mapping where positional reads are unavailable or fail.
    pub fn read_at(&self, offset: usize, buf: &mut [u8]) {
        #[cfg(unix)]
        {
            use std::os::unix::fs::FileExt;
            if self.file.read_exact_at(buf, offset as u64).is_ok() {
                return;
            }
        }
        buf.copy_from_slice(&self.map[offset..offset + buf.len()]);
    }
}

/// Why [`FrameCache::open`] found no usable cache (the caller rebuilds it).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum StaleCache {
    #[error("no cache yet")]
    Absent,
    #[error("shorter than a header")]
    ShortHeader,
    #[error("header differs (other source files, sizes or options)")]
    HeaderDiffers,
    #[error("{len} bytes where {want} were expected")]
    Length { len: u64, want: u64 },
}

/// An open, validated frame cache.
#[derive(Clone, Debug)]
pub struct FrameCache {
    map: Arc<CacheFile>,
    key: CacheKey,
    path: PathBuf,
}

impl FrameCache {
    /// Opens `path` if it exists and matches `key`; `Ok(Err(reason))` when it is absent or stale,
    /// so that the caller rebuilds it; `Err` for I/O errors other than absence.
    pub fn open(
        path: &Path,
        key: &CacheKey,
    ) -> Result<Result<FrameCache, StaleCache>, DatasetError> {
        let io = |source| DatasetError::Io {
            path: path.to_path_buf(),
            source,
        };
        let mut file = match File::open(path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok(Err(StaleCache::Absent))
            }
            Err(e) => return Err(io(e)),
        };
        let mut head = [0u8; HEADER_USED];
        if file.read_exact(&mut head).is_err() {
            return Ok(Err(StaleCache::ShortHeader));
        }
        if head[..] != key.header()[..HEADER_USED] {
            return Ok(Err(StaleCache::HeaderDiffers));
        }
        let want = DATA_OFFSET + key.count * key.frame_bytes();
        let len = file.metadata().map_err(io)?.len();
        if len != want {
            return Ok(Err(StaleCache::Length { len, want }));
        }
        // SAFETY: the file is opened read-only and only ever replaced by rename, never modified
        // in place by msth; another process truncating it would be a user error we cannot
        // prevent (the usual caveat of memory-mapped files).
        let map = unsafe { memmap2::Mmap::map(&file) }.map_err(io)?;
        #[cfg(unix)]
        {
            // Whole-frame reads through the mapping are rare; no read-ahead around them.
            let _ = map.advise(memmap2::Advice::Random);
        }
        Ok(Ok(FrameCache {
            map: Arc::new(CacheFile { file, map }),
            key: *key,
            path: path.to_path_buf(),
        }))
    }

    /// Frame `i` as mapped pixels.
    pub fn frame(&self, i: usize) -> Pixels {
        let len = self.key.frame_bytes() as usize;
        Pixels::Mapped {
            file: self.map.clone(),
            offset: DATA_OFFSET as usize + i * len,
            len,
        }
    }

    /// The cache file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.key.count as usize
    }

    /// Whether it holds no frames.
    pub fn is_empty(&self) -> bool {
        self.key.count == 0
    }

    /// Size of the file in bytes.
    pub fn file_bytes(&self) -> u64 {
        self.map.map.len() as u64
    }
}

/// Receives a dataset's frames in order (each exactly `width * height * 3` bytes).
pub trait FrameSink {
    fn push(&mut self, rgb: &[u8]) -> Result<(), DatasetError>;
}

struct MemorySink<'a> {
    frames: Vec<Pixels>,
    key: CacheKey,
    progress: Option<&'a ProgressFn>,
}

impl FrameSink for MemorySink<'_> {
    fn push(&mut self, rgb: &[u8]) -> Result<(), DatasetError> {
        debug_assert_eq!(rgb.len() as u64, self.key.frame_bytes());
        self.frames.push(Pixels::Owned(rgb.to_vec()));
        if let Some(p) = self.progress {
            p(self.frames.len() as u64, self.key.count);
        }
        Ok(())
    }
}

struct FileSink<'a> {
    out: BufWriter<File>,
    tmp: &'a Path,
    key: CacheKey,
    written: u64,
    progress: Option<&'a ProgressFn>,
}

impl FrameSink for FileSink<'_> {
    fn push(&mut self, rgb: &[u8]) -> Result<(), DatasetError> {
        if rgb.len() as u64 != self.key.frame_bytes() || self.written >= self.key.count {
            return Err(DatasetError::Invalid {
                path: self.tmp.to_path_buf(),
                message: format!(
                    "internal: frame {} of {} bytes does not fit the cache ({} frames of {} bytes)",
                    self.written,
                    rgb.len(),
                    self.key.count,
                    self.key.frame_bytes()
                ),
            });
        }
        self.out.write_all(rgb).map_err(|source| DatasetError::Io {
            path: self.tmp.to_path_buf(),
            source,
        })?;
        self.written += 1;
        if let Some(p) = self.progress {
            p(self.written, self.key.count);
        }
        Ok(())
    }
}

/// Removes a temporary file unless disarmed.
struct TempGuard<'a>(&'a Path, bool);

impl Drop for TempGuard<'_> {
    fn drop(&mut self) {
        if !self.1 {
            let _ = std::fs::remove_file(self.0);
        }
    }
}

/// Where the frames of a dataset ended up.
#[derive(Clone, Debug)]
pub enum Stored {
    Memory(Vec<Pixels>),
    /// In a cache; `built` says whether it was (re)built now rather than reused.
    Cache {
        cache: FrameCache,
        built: bool,
    },
}

impl Stored {
    /// The frames, in the order they were produced.
    pub fn frames(self) -> Vec<Pixels> {
        match self {
            Stored::Memory(v) => v,
            Stored::Cache { cache, .. } => (0..cache.len()).map(|i| cache.frame(i)).collect(),
        }
    }
}

/// Stores `key.count` frames according to `storage`. `produce` is called to push every frame in
/// order into the sink, unless a valid cache already exists (then the sources are not read at
/// all). A new cache is written to a temporary file and renamed into place once complete.
pub fn store_frames(
    storage: &FrameStorage,
    key: CacheKey,
    progress: Option<&ProgressFn>,
    produce: &mut dyn FnMut(&mut dyn FrameSink) -> Result<(), DatasetError>,
) -> Result<Stored, DatasetError> {
    let total = key.count * key.frame_bytes();
    let Some(path) = storage.cache_file(total) else {
        let mut sink = MemorySink {
            frames: Vec::with_capacity(key.count.min(1 << 20) as usize),
            key,
            progress,
        };
        produce(&mut sink)?;
        check_count(&sink.frames.len(), key.count, Path::new("(memory)"))?;
        return Ok(Stored::Memory(sink.frames));
    };
    if let Ok(cache) = FrameCache::open(path, &key)? {
        return Ok(Stored::Cache {
            cache,
            built: false,
        });
    }
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| DatasetError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    let tmp = PathBuf::from(format!("{}.tmp-{}", path.display(), std::process::id()));
    let io = |source, p: &Path| DatasetError::Io {
        path: p.to_path_buf(),
        source,
    };
    let mut guard = TempGuard(&tmp, false);
    let file = File::create(&tmp).map_err(|e| io(e, &tmp))?;
    let mut out = BufWriter::with_capacity(1 << 22, file);
    out.write_all(&key.header()).map_err(|e| io(e, &tmp))?;
    let mut sink = FileSink {
        out,
        tmp: &tmp,
        key,
        written: 0,
        progress,
    };
    produce(&mut sink)?;
    check_count(&(sink.written as usize), key.count, path)?;
    let file = sink
        .out
        .into_inner()
        .map_err(|e| io(e.into_error(), &tmp))?;
    file.sync_all().map_err(|e| io(e, &tmp))?;
    drop(file);
    std::fs::rename(&tmp, path).map_err(|e| io(e, path))?;
    guard.1 = true;
    let cache = FrameCache::open(path, &key)?.map_err(|why| DatasetError::Invalid {
        path: path.to_path_buf(),
        message: format!("the cache just written does not validate: {why}"),
    })?;
    Ok(Stored::Cache { cache, built: true })
}

fn check_count(got: &usize, want: u64, path: &Path) -> Result<(), DatasetError> {
    if *got as u64 != want {
        return Err(DatasetError::Invalid {
            path: path.to_path_buf(),
            message: format!("internal: {got} frames were produced where {want} were announced"),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frames(n: usize, seed: u8) -> Vec<Vec<u8>> {
        (0..n)
            .map(|i| (0..4 * 3 * 3).map(|j| (i * 31 + j) as u8 ^ seed).collect())
            .collect()
    }

    fn key(count: u64, fingerprint: u64) -> CacheKey {
        CacheKey {
            width: 4,
            height: 3,
            count,
            fingerprint,
        }
    }

    fn store(
        storage: &FrameStorage,
        k: CacheKey,
        data: &[Vec<u8>],
        calls: &mut usize,
    ) -> Result<Stored, DatasetError> {
        store_frames(storage, k, None, &mut |sink| {
            *calls += 1;
            for f in data {
                sink.push(f)?;
            }
            Ok(())
        })
    }

    #[test]
    fn memory_and_disk_hold_the_same_frames_and_reuse_is_validated() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/d.frames");
        let data = frames(5, 0);
        let mut calls = 0;
        let mem = store(&FrameStorage::Memory, key(5, 1), &data, &mut calls).unwrap();
        assert!(matches!(mem, Stored::Memory(_)));
        let disk = store(
            &FrameStorage::Disk(path.clone()),
            key(5, 1),
            &data,
            &mut calls,
        )
        .unwrap();
        assert!(matches!(disk, Stored::Cache { built: true, .. }));
        assert_eq!(calls, 2);
        let (m, d) = (mem.frames(), disk.frames());
        assert!(d.iter().all(|p| p.is_mapped()));
        assert_eq!(m, d);
        for (f, p) in data.iter().zip(&d) {
            assert_eq!(&f[..], &p[..]);
        }
        assert_eq!(
            std::fs::metadata(&path).unwrap().len(),
            DATA_OFFSET + 5 * 36
        );
        // Reused without reading the sources.
        let again = store(
            &FrameStorage::Disk(path.clone()),
            key(5, 1),
            &data,
            &mut calls,
        )
        .unwrap();
        assert!(matches!(again, Stored::Cache { built: false, .. }));
        assert_eq!(calls, 2);
        // A different fingerprint or count rebuilds it.
        let other = frames(5, 7);
        let re = store(
            &FrameStorage::Disk(path.clone()),
            key(5, 2),
            &other,
            &mut calls,
        )
        .unwrap();
        assert!(matches!(re, Stored::Cache { built: true, .. }));
        assert_eq!(&re.frames()[3][..], &other[3][..]);
        let re = store(
            &FrameStorage::Disk(path.clone()),
            key(4, 2),
            &other[..4],
            &mut calls,
        );
        assert!(matches!(re.unwrap(), Stored::Cache { built: true, .. }));
        assert_eq!(calls, 4);
        // A truncated file is stale, not an error.
        let f = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
        f.set_len(DATA_OFFSET + 10).unwrap();
        let why = FrameCache::open(&path, &key(4, 2)).unwrap().unwrap_err();
        assert!(why.to_string().contains("bytes where"), "{why}");
        // Nothing but the cache is left in the folder.
        let names: Vec<_> = std::fs::read_dir(path.parent().unwrap())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, ["d.frames"]);
    }

    #[test]
    fn a_failed_build_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.frames");
        let data = frames(3, 0);
        let err = store_frames(
            &FrameStorage::Disk(path.clone()),
            key(3, 1),
            None,
            &mut |s| {
                s.push(&data[0])?;
                Err(DatasetError::Invalid {
                    path: "video.mp4".into(),
                    message: "broken".into(),
                })
            },
        )
        .unwrap_err();
        assert!(err.to_string().contains("broken"));
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        // Too few frames is caught too.
        let err = store(
            &FrameStorage::Disk(path.clone()),
            key(3, 1),
            &data[..2],
            &mut 0,
        );
        assert!(err.unwrap_err().to_string().contains("2 frames"));
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn auto_storage_switches_on_size() {
        let s = FrameStorage::Auto {
            file: "x.frames".into(),
            memory_limit: 100,
        };
        assert_eq!(s.cache_file(100), None);
        assert_eq!(s.cache_file(101), Some(Path::new("x.frames")));
    }

    #[test]
    fn mapped_pixels_copy_on_write() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.frames");
        let data = frames(2, 0);
        let s = store(&FrameStorage::Disk(path.clone()), key(2, 1), &data, &mut 0).unwrap();
        let mut p = s.frames().remove(1);
        // Positional reads and the mapping agree.
        for i in (0..36).step_by(3) {
            assert_eq!(p.rgb_at(i), [data[1][i], data[1][i + 1], data[1][i + 2]]);
        }
        assert_eq!(&p.loaded()[..], &data[1][..]);
        let img = crate::Image8 {
            width: 4,
            height: 3,
            data: p.clone(),
        };
        assert!(!img.loaded().data.is_mapped());
        assert_eq!(img.loaded().into_owned(), img);
        assert_eq!(img.get(1, 2)[0], data[1][(2 * 4 + 1) * 3] as f32 / 255.0);
        p[0] = p[0].wrapping_add(1);
        assert!(!p.is_mapped());
        let back = FrameCache::open(&path, &key(2, 1)).unwrap().unwrap();
        assert_eq!(&back.frame(1)[..], &data[1][..]);
    }
}
