//! Which `.msth` files are served, and the only way a URL name becomes a path: [`Catalog`].
//!
//! A name is served only if it matches `[A-Za-z0-9._-]+\.msth`, does not start with `.`, and
//! (folder mode) canonicalises to a regular file whose parent is the canonical served folder, so
//! `..`, separators, absolute paths and symlinks that leave the folder never resolve. The folder
//! is read again on every request: files added or removed while serving are seen at once.

use std::fs;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use crate::ServeError;

/// What is served: a folder of `.msth` files, or one file under its own name.
#[derive(Debug, Clone)]
pub struct Catalog {
    root: Root,
}

#[derive(Debug, Clone)]
enum Root {
    /// Canonical folder.
    Dir(PathBuf),
    /// One file: the name it is served under, and its canonical path.
    File { name: String, path: PathBuf },
}

/// One served model, as the listing shows it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelEntry {
    pub name: String,
    pub path: PathBuf,
    pub bytes: u64,
    pub modified: SystemTime,
}

/// `[A-Za-z0-9._-]+\.msth`, not starting with `.`.
pub fn is_servable_name(name: &str) -> bool {
    name.len() > ".msth".len()
        && name.len() <= 255
        && name.ends_with(".msth")
        && !name.starts_with('.')
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

impl Catalog {
    /// A catalog for `path`: a folder (served: its `.msth` files) or one `.msth` file.
    pub fn open(path: &Path) -> Result<Self, ServeError> {
        let canonical = fs::canonicalize(path).map_err(|source| ServeError::Path {
            path: path.to_path_buf(),
            source,
        })?;
        let meta = fs::metadata(&canonical).map_err(|source| ServeError::Path {
            path: path.to_path_buf(),
            source,
        })?;
        if meta.is_dir() {
            return Ok(Self {
                root: Root::Dir(canonical),
            });
        }
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .filter(|n| is_servable_name(n) && meta.is_file())
            .ok_or_else(|| ServeError::NotServable {
                path: path.to_path_buf(),
            })?;
        Ok(Self {
            root: Root::File {
                name: name.to_string(),
                path: canonical,
            },
        })
    }

    /// The served models, sorted by name.
    pub fn list(&self) -> Result<Vec<ModelEntry>, ServeError> {
        match &self.root {
            Root::File { name, .. } => Ok(self.lookup(name).into_iter().collect()),
            Root::Dir(dir) => {
                let read = fs::read_dir(dir).map_err(|source| ServeError::Path {
                    path: dir.clone(),
                    source,
                })?;
                let mut out: Vec<ModelEntry> = read
                    .filter_map(Result::ok)
                    .filter_map(|e| e.file_name().to_str().and_then(|n| self.lookup(n)))
                    .collect();
                out.sort_by(|a, b| a.name.cmp(&b.name));
                Ok(out)
            }
        }
    }

    /// The model served under `name`, if any (see the module header for the rules).
    pub fn lookup(&self, name: &str) -> Option<ModelEntry> {
        self.lookup_with_meta(name).map(|(e, _)| e)
    }

    /// [`Catalog::lookup`] and the file's metadata.
    pub(crate) fn lookup_with_meta(&self, name: &str) -> Option<(ModelEntry, fs::Metadata)> {
        if !is_servable_name(name) {
            return None;
        }
        let (path, meta) = match &self.root {
            Root::File { name: own, path } => {
                let path = (own == name).then(|| path.clone())?;
                let meta = fs::metadata(&path).ok()?;
                (path, meta)
            }
            Root::Dir(dir) => {
                // The folder is canonical and the name one plain component, so a regular file
                // there is its own canonical path: one `lstat` answers. Only a symlink needs
                // resolving (every request: its target may change), and must stay inside.
                let joined = dir.join(name);
                let own = fs::symlink_metadata(&joined).ok()?;
                if own.file_type().is_symlink() {
                    let canonical = fs::canonicalize(&joined).ok()?;
                    if canonical.parent() != Some(dir.as_path()) {
                        return None;
                    }
                    let meta = fs::metadata(&canonical).ok()?;
                    (canonical, meta)
                } else {
                    (joined, own)
                }
            }
        };
        let meta = Some(meta).filter(fs::Metadata::is_file)?;
        let entry = ModelEntry {
            name: name.to_string(),
            path,
            bytes: meta.len(),
            modified: meta.modified().unwrap_or(SystemTime::UNIX_EPOCH),
        };
        Some((entry, meta))
    }

    /// The folder or file served, for messages.
    pub fn describe(&self) -> &Path {
        match &self.root {
            Root::Dir(dir) => dir,
            Root::File { path, .. } => path,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names() {
        assert!(is_servable_name("scene.msth"));
        assert!(is_servable_name("a-b_c.1.msth"));
        for bad in [
            ".msth",
            ".hidden.msth",
            "../x.msth",
            "a/b.msth",
            "a\\b.msth",
            "x.msth.txt",
            "x y.msth",
            "/etc/x.msth",
            "%2e%2e.msth",
            "",
        ] {
            assert!(!is_servable_name(bad), "{bad}");
        }
    }

    #[test]
    fn folder_lookup_refuses_escapes() {
        let root = tempfile::tempdir().unwrap();
        let served = root.path().join("served");
        fs::create_dir(&served).unwrap();
        fs::write(served.join("a.msth"), b"abc").unwrap();
        fs::write(served.join("notes.txt"), b"x").unwrap();
        fs::create_dir(served.join("dir.msth")).unwrap();
        fs::write(root.path().join("outside.msth"), b"secret").unwrap();
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink(root.path().join("outside.msth"), served.join("out.msth"))
                .unwrap();
            std::os::unix::fs::symlink(served.join("a.msth"), served.join("alias.msth")).unwrap();
        }
        let cat = Catalog::open(&served).unwrap();
        let names: Vec<String> = cat.list().unwrap().into_iter().map(|e| e.name).collect();
        #[cfg(unix)]
        assert_eq!(names, ["a.msth", "alias.msth"]);
        assert_eq!(cat.lookup("a.msth").map(|e| e.bytes), Some(3));
        assert!(cat.lookup("out.msth").is_none());
        assert!(cat.lookup("../outside.msth").is_none());
        assert!(cat.lookup("dir.msth").is_none());
        assert!(cat.lookup("notes.txt").is_none());
    }

    #[test]
    fn single_file() {
        let root = tempfile::tempdir().unwrap();
        let file = root.path().join("one.msth");
        fs::write(&file, b"12345").unwrap();
        fs::write(root.path().join("two.msth"), b"x").unwrap();
        let cat = Catalog::open(&file).unwrap();
        assert_eq!(cat.list().unwrap().len(), 1);
        assert!(cat.lookup("two.msth").is_none());
        assert!(matches!(
            Catalog::open(&root.path().join("missing.msth")),
            Err(ServeError::Path { .. })
        ));
        fs::write(root.path().join("bad name.msth"), b"x").unwrap();
        assert!(matches!(
            Catalog::open(&root.path().join("bad name.msth")),
            Err(ServeError::NotServable { .. })
        ));
    }
}
