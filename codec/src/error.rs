//! The codec's errors, grouped by who is at fault: the caller's input to the encoder
//! ([`EncodeError`]), or the bytes given to the decoder ([`DecodeError`]: malformed, over a limit,
//! unsupported, incomplete, or inconsistent with the model configuration).

/// Why a model could not be encoded (the caller's data or options are at fault).
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    #[error("invalid model configuration: {0}")]
    InvalidConfig(String),
    #[error("{got} parameters given but the configuration needs {expected}")]
    ParamCount { got: usize, expected: usize },
    #[error("parameter slice `{slice}` holds a non-finite value at index {index}")]
    NonFinite { slice: String, index: usize },
    #[error("invalid option: {0}")]
    InvalidOption(String),
    #[error("camera {index}: {message}")]
    InvalidCamera { index: usize, message: String },
    #[error("zstd compression failed: {0}")]
    Compress(#[source] std::io::Error),
}

/// Why bytes could not be decoded. Every variant is a clean failure: the decoder never panics,
/// hangs or allocates more than its [`crate::Limits`] allow on hostile input.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    /// More bytes are needed (streaming: fetch at least `needed` bytes from the start of the file,
    /// or the named section's byte range).
    #[error("truncated: {what} needs {needed} bytes, {have} available")]
    Truncated {
        what: String,
        needed: u64,
        have: u64,
    },
    /// The bytes are not a well-formed `.msth` file.
    #[error("malformed {what}: {message}")]
    Malformed { what: String, message: String },
    /// A checksum does not match (corruption in storage or transfer).
    #[error("checksum mismatch in {what}: stored {stored:#010x}, computed {computed:#010x}")]
    Checksum {
        what: String,
        stored: u32,
        computed: u32,
    },
    /// A size or count exceeds the decoder's limits (checked before allocating).
    #[error("limit exceeded in {what}: {value} > {limit}")]
    Limit {
        what: String,
        value: u64,
        limit: u64,
    },
    /// A well-formed file this decoder does not support (newer version, unknown encoding).
    #[error("unsupported {what}: {message}")]
    Unsupported { what: String, message: String },
    /// The metadata's model configuration is invalid or disagrees with the stored data.
    #[error("model: {0}")]
    Model(String),
    /// zstd rejected a section's payload.
    #[error("zstd in {what}: {message}")]
    Zstd { what: String, message: String },
}

impl DecodeError {
    pub(crate) fn malformed(what: impl Into<String>, message: impl Into<String>) -> Self {
        DecodeError::Malformed {
            what: what.into(),
            message: message.into(),
        }
    }

    pub(crate) fn limit(what: impl Into<String>, value: u64, limit: u64) -> Self {
        DecodeError::Limit {
            what: what.into(),
            value,
            limit,
        }
    }

    /// `true` when the error only means "not enough bytes yet" (streaming clients wait for more).
    pub fn is_truncated(&self) -> bool {
        matches!(self, DecodeError::Truncated { .. })
    }
}

/// Checksums are verified except in fuzzing builds (`cargo fuzz` sets `cfg(fuzzing)`), so that
/// the fuzzer reaches the parsers behind them instead of stopping at every CRC.
#[allow(unexpected_cfgs)]
pub(crate) const VERIFY_CHECKSUMS: bool = !cfg!(fuzzing);
