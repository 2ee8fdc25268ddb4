//! The one error type of this crate, grouped by who is at fault: the input file
//! ([`SceneGenError::Format`], [`SceneGenError::Invalid`], [`SceneGenError::Unsupported`]),
//! the caller's settings ([`SceneGenError::Settings`]), or the machine (I/O, ffmpeg).

use std::path::PathBuf;

use msth_dataset::DatasetError;

/// Everything that can go wrong while loading a model or writing a dataset. Every variant that
/// concerns a file names it.
#[derive(Debug, thiserror::Error)]
pub enum SceneGenError {
    /// Reading or writing a file failed (the I/O error is part of the message, not a
    /// separate source, so that it is printed once).
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    /// The bytes are not a glTF / GLB document (syntax, truncated, failed validation).
    #[error("{path}: not a valid glTF file: {message}")]
    Format { path: PathBuf, message: String },
    /// A well-formed document whose content is wrong (accessor out of range, bad keyframes...).
    #[error("{path}: {what}: {message}")]
    Invalid {
        path: PathBuf,
        what: String,
        message: String,
    },
    /// Valid glTF that uses something this generator does not implement.
    #[error("{path}: {what}: not supported: {message}")]
    Unsupported {
        path: PathBuf,
        what: String,
        message: String,
    },
    /// Settings that cannot produce a dataset (zero sizes, too many pixels...).
    #[error("invalid settings: {0}")]
    Settings(String),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("ffmpeg failed on {path}: {message}")]
    Ffmpeg { path: PathBuf, message: String },
}

impl SceneGenError {
    pub(crate) fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> SceneGenError {
        let path = path.into();
        move |error| SceneGenError::Io { path, error }
    }
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, SceneGenError>;
