//! Writing without half-written results. A file goes to a temporary sibling that is synced and
//! renamed over the target ([`write_atomic`], [`write_atomic_with`]); a folder is built as a
//! hidden sibling staging folder and renamed onto the target at the end ([`StagingDir`]). On
//! failure the temporary file or folder is removed and the target is left as it was.

use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// Writes `bytes` to `path` through a temporary sibling and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomic_with(path, &mut |w| w.write_all(bytes))
}

/// Writes what `write` produces to `path` atomically: into a temporary file in the same folder
/// (`.NAME.tmp-PID-N`, unique per process and call), synced, then renamed over `path`, and the
/// folder synced so that the rename itself survives a power cut. A process killed at any moment
/// leaves either the old file or the new one at `path` (and perhaps the temporary file); a write
/// that fails (a full disk) removes the temporary file and leaves `path` as it was.
pub fn write_atomic_with(
    path: &Path,
    write: &mut dyn FnMut(&mut dyn Write) -> io::Result<()>,
) -> io::Result<()> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let file_name = path.file_name().ok_or_else(|| {
        io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("{}: not a file path", path.display()),
        )
    })?;
    let tmp = path.with_file_name(format!(
        ".{}.tmp-{}-{}",
        file_name.to_string_lossy(),
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let result = (|| {
        let mut writer = BufWriter::new(std::fs::File::create(&tmp)?);
        write(&mut writer)?;
        let file = writer.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)?;
        // The rename is durable once the folder is (best effort: not every platform opens
        // folders as files).
        let dir = path.parent().filter(|p| !p.as_os_str().is_empty());
        if let Ok(d) = std::fs::File::open(dir.unwrap_or(Path::new("."))) {
            let _ = d.sync_all();
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Why a staging folder could not be made or committed. Callers word the first two in their own
/// terms (a dataset writer, a generator's settings).
#[derive(Debug, thiserror::Error)]
pub enum StagingError {
    /// The target exists and is not an empty folder.
    #[error("{0}: exists and is not an empty folder")]
    NotEmpty(PathBuf),
    /// The target has no file name (`/`, `..`).
    #[error("{0}: not a folder name")]
    NotAFolderName(PathBuf),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
}

/// A folder built next to its target `out` (`.NAME.staging-PID-NANOS`), renamed onto `out` by
/// [`StagingDir::commit`] and removed with its contents when dropped uncommitted. `out` must not
/// exist or be an empty folder.
pub struct StagingDir {
    dir: PathBuf,
    out: PathBuf,
    done: bool,
}

impl StagingDir {
    /// Checks `out` and creates the staging folder (and `out`'s parent folders).
    pub fn new(out: &Path) -> Result<StagingDir, StagingError> {
        if out.exists() {
            let empty = std::fs::read_dir(out)
                .map(|mut e| e.next().is_none())
                .unwrap_or(false);
            if !empty {
                return Err(StagingError::NotEmpty(out.to_path_buf()));
            }
        }
        let name = out
            .file_name()
            .ok_or_else(|| StagingError::NotAFolderName(out.to_path_buf()))?
            .to_string_lossy()
            .into_owned();
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos())
            .unwrap_or(0);
        let dir = out.with_file_name(format!(".{name}.staging-{}-{nanos}", std::process::id()));
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| StagingError::Io { path, source }
        };
        if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(io(parent))?;
        }
        std::fs::create_dir(&dir).map_err(io(&dir))?;
        Ok(StagingDir {
            dir,
            out: out.to_path_buf(),
            done: false,
        })
    }

    /// The staging folder to write into.
    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// Renames the staging folder onto the target (replacing an empty folder there).
    pub fn commit(mut self) -> Result<(), StagingError> {
        let io = |source| StagingError::Io {
            path: self.out.clone(),
            source,
        };
        if self.out.exists() {
            std::fs::remove_dir(&self.out).map_err(io)?;
        }
        std::fs::rename(&self.dir, &self.out).map_err(io)?;
        self.done = true;
        Ok(())
    }
}

impl Drop for StagingDir {
    fn drop(&mut self) {
        if !self.done {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_staging_folder_is_renamed_on_commit_and_removed_on_drop() {
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("a/b");
        let s = StagingDir::new(&out).unwrap();
        std::fs::write(s.path().join("x"), b"1").unwrap();
        drop(s);
        assert!(!out.exists());
        assert_eq!(std::fs::read_dir(root.path().join("a")).unwrap().count(), 0);
        let s = StagingDir::new(&out).unwrap();
        std::fs::write(s.path().join("x"), b"2").unwrap();
        s.commit().unwrap();
        assert_eq!(std::fs::read(out.join("x")).unwrap(), b"2");
        assert!(matches!(
            StagingDir::new(&out),
            Err(StagingError::NotEmpty(_))
        ));
        assert_eq!(std::fs::read_dir(root.path().join("a")).unwrap().count(), 1);
    }

    #[test]
    fn write_atomic_replaces_and_leaves_no_temporary_file() {
        let root = tempfile::tempdir().unwrap();
        let p = root.path().join("f.bin");
        write_atomic(&p, b"one").unwrap();
        write_atomic(&p, b"two").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        let failed = write_atomic_with(&p, &mut |_| Err(io::Error::other("no")));
        assert!(failed.is_err());
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        assert_eq!(std::fs::read_dir(root.path()).unwrap().count(), 1);
    }
}
