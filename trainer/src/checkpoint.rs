//! Checkpoint files (`model.ckpt`): the model configuration, training settings and metadata as
//! JSON, then the flat parameter buffer and optionally the Adam moments, with a CRC-32 at the end.
//!
//! Layout (little endian):
//! `b"MSTHCKPT"`, `version: u32 = 1`, `flags: u32` (bit 0: Adam state present, other bits 0),
//! `header_len: u64`, header JSON, `n: u64`, `params: [f32; n]`, if flag 0: `m: [f32; n]`,
//! `v: [f32; n]`, `adam_step: u64`; then `crc32: u32` of every preceding byte.
//! Files are written to a temporary sibling and renamed, so a crash never leaves half a file.

use std::io::Read;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use msth_core::config::{ModelConfig, ModelConfigError};
use msth_core::field::ModelLayout;
use msth_core::Camera;

use crate::adam::Adam;

const MAGIC: &[u8; 8] = b"MSTHCKPT";
const VERSION: u32 = 1;
const MAX_HEADER: u64 = 64 << 20;
const MAX_PARAMS: u64 = 1 << 31;

/// Everything in the JSON header.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CheckpointHeader {
    pub model: ModelConfig,
    /// The training settings used (free-form so that old files stay readable).
    pub train: serde_json::Value,
    pub step: u64,
    pub dataset: String,
    /// Cameras worth playing back from (the dataset's test and training poses, deduplicated).
    pub cameras: Vec<Camera>,
    /// How many of `cameras` (the first ones) are the poses of every training view; absent in
    /// checkpoints written before 2026-11-28 and where the 64 cameras could not hold every
    /// training pose.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub train_cameras: Option<usize>,
    pub train_seconds: f64,
}

impl CheckpointHeader {
    /// The poses of every training view, when the checkpoint lists them.
    pub fn training_cameras(&self) -> Option<&[Camera]> {
        self.train_cameras
            .map(|n| &self.cameras[..n.min(self.cameras.len())])
    }
}

impl CheckpointHeader {
    /// The world scale the model was trained at (`train.scene_scale`, 1 when absent): world
    /// lengths of the dataset are multiplied by it to match the model.
    pub fn scene_scale(&self) -> f32 {
        self.train
            .get("scene_scale")
            .and_then(|v| v.as_f64())
            .map(|v| v as f32)
            .filter(|v| v.is_finite() && *v > 0.0)
            .unwrap_or(1.0)
    }
}

#[derive(Clone, Debug)]
pub struct Checkpoint {
    pub header: CheckpointHeader,
    pub params: Vec<f32>,
    pub adam: Option<Adam>,
}

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: not an msth checkpoint ({reason})")]
    Format {
        path: PathBuf,
        reason: CheckpointFormatError,
    },
}

/// What is wrong with the bytes of a checkpoint (`model.ckpt`) or its mask-learning companion
/// (`model.aux`).
#[derive(Debug, thiserror::Error)]
pub enum CheckpointFormatError {
    #[error("file is {len} bytes, larger than any valid checkpoint")]
    TooLarge { len: u64 },
    #[error("bad magic number")]
    BadMagic,
    #[error("short file")]
    ShortFile,
    #[error("checksum mismatch (truncated or corrupted file)")]
    Checksum,
    #[error("unsupported version {version} (this build reads {VERSION})")]
    Version { version: u32 },
    #[error("truncated: wanted {wanted} bytes at offset {offset}")]
    Truncated { wanted: usize, offset: usize },
    #[error("size overflow")]
    SizeOverflow,
    #[error("reserved flag bits set: {flags:#x}")]
    ReservedFlags { flags: u32 },
    #[error("header length {len} exceeds {MAX_HEADER}")]
    HeaderTooLong { len: u64 },
    #[error("header JSON: {0}")]
    HeaderJson(serde_json::Error),
    #[error("model config: {0}")]
    Model(ModelConfigError),
    #[error("{stored} parameters stored but the configuration needs {expected}")]
    ParamCount { stored: u64, expected: u64 },
    #[error("{stored} parameters stored but the mask-learning settings need {expected}")]
    AuxParamCount { stored: u64, expected: usize },
    #[error("{bytes} unexpected trailing bytes")]
    Trailing { bytes: usize },
    #[error("it belongs to step {aux_step} but the checkpoint is at step {step}")]
    StepMismatch { aux_step: u64, step: usize },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CheckpointError + '_ {
    move |source| CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    }
}

impl Checkpoint {
    /// Serialises into bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let header = serde_json::to_vec(&self.header).expect("header serialises");
        let n = self.params.len();
        let mut b = Vec::with_capacity(32 + header.len() + n * 4 * 3);
        b.extend_from_slice(MAGIC);
        b.extend_from_slice(&VERSION.to_le_bytes());
        b.extend_from_slice(&(self.adam.is_some() as u32).to_le_bytes());
        b.extend_from_slice(&(header.len() as u64).to_le_bytes());
        b.extend_from_slice(&header);
        b.extend_from_slice(&(n as u64).to_le_bytes());
        let put = |b: &mut Vec<u8>, v: &[f32]| {
            for x in v {
                b.extend_from_slice(&x.to_le_bytes());
            }
        };
        put(&mut b, &self.params);
        if let Some(a) = &self.adam {
            put(&mut b, &a.m);
            put(&mut b, &a.v);
            b.extend_from_slice(&a.step.to_le_bytes());
        }
        let crc = crc32fast::hash(&b);
        b.extend_from_slice(&crc.to_le_bytes());
        b
    }

    /// Writes atomically (temporary file in the same folder, then rename).
    pub fn save(&self, path: &Path) -> Result<(), CheckpointError> {
        write_atomic(path, &self.to_bytes()).map_err(io(path))
    }

    pub fn load(path: &Path) -> Result<Self, CheckpointError> {
        let mut f = std::fs::File::open(path).map_err(io(path))?;
        let len = f.metadata().map_err(io(path))?.len();
        if len > MAX_HEADER + 3 * 4 * MAX_PARAMS + 64 {
            return Err(CheckpointError::Format {
                path: path.into(),
                reason: CheckpointFormatError::TooLarge { len },
            });
        }
        let mut bytes = Vec::with_capacity(len as usize);
        f.read_to_end(&mut bytes).map_err(io(path))?;
        Self::from_bytes(&bytes).map_err(|reason| CheckpointError::Format {
            path: path.into(),
            reason,
        })
    }

    pub fn from_bytes(b: &[u8]) -> Result<Self, CheckpointFormatError> {
        let mut r = Reader::framed(b, MAGIC, 28)?;
        let flags = r.u32()?;
        if flags & !1 != 0 {
            return Err(CheckpointFormatError::ReservedFlags { flags });
        }
        let hlen = r.u64()?;
        if hlen > MAX_HEADER {
            return Err(CheckpointFormatError::HeaderTooLong { len: hlen });
        }
        let header: CheckpointHeader = serde_json::from_slice(r.take(hlen as usize)?)
            .map_err(CheckpointFormatError::HeaderJson)?;
        header
            .model
            .validate()
            .map_err(CheckpointFormatError::Model)?;
        let n = r.u64()?;
        let expect = ModelLayout::new(&header.model).params.total as u64;
        if n != expect {
            return Err(CheckpointFormatError::ParamCount {
                stored: n,
                expected: expect,
            });
        }
        let params = r.f32s(n as usize)?;
        let adam = if flags & 1 == 1 {
            let m = r.f32s(n as usize)?;
            let v = r.f32s(n as usize)?;
            let step = r.u64()?;
            Some(Adam { m, v, step })
        } else {
            None
        };
        if r.pos != r.b.len() {
            return Err(CheckpointFormatError::Trailing {
                bytes: r.b.len() - r.pos,
            });
        }
        Ok(Checkpoint {
            header,
            params,
            adam,
        })
    }
}

const AUX_MAGIC: &[u8; 8] = b"MSTHAUX\0";

/// The training-only mask-learning state next to a checkpoint (`model.aux`): the auxiliary
/// parameters (uncertainty grid, MINE network) and their Adam moments. Layout (little endian):
/// `b"MSTHAUX\0"`, `version: u32 = 1`, `step: u64` (the checkpoint step it belongs to),
/// `n: u64`, `params`, `m`, `v: [f32; n]`, `adam_step: u64`, `crc32: u32` of every preceding byte.
#[derive(Clone, Debug, PartialEq)]
pub struct AuxCheckpoint {
    pub step: u64,
    pub params: Vec<f32>,
    pub adam: Adam,
}

impl AuxCheckpoint {
    pub fn to_bytes(&self) -> Vec<u8> {
        let n = self.params.len();
        let mut b = Vec::with_capacity(40 + n * 12);
        b.extend_from_slice(AUX_MAGIC);
        b.extend_from_slice(&VERSION.to_le_bytes());
        b.extend_from_slice(&self.step.to_le_bytes());
        b.extend_from_slice(&(n as u64).to_le_bytes());
        for v in [&self.params, &self.adam.m, &self.adam.v] {
            for x in v.iter() {
                b.extend_from_slice(&x.to_le_bytes());
            }
        }
        b.extend_from_slice(&self.adam.step.to_le_bytes());
        let crc = crc32fast::hash(&b);
        b.extend_from_slice(&crc.to_le_bytes());
        b
    }

    /// Parses a file that must hold `expect` parameters.
    pub fn from_bytes(b: &[u8], expect: usize) -> Result<Self, CheckpointFormatError> {
        let mut r = Reader::framed(b, AUX_MAGIC, 36)?;
        let step = r.u64()?;
        let n = r.u64()?;
        if n != expect as u64 {
            return Err(CheckpointFormatError::AuxParamCount {
                stored: n,
                expected: expect,
            });
        }
        let params = r.f32s(expect)?;
        let m = r.f32s(expect)?;
        let v = r.f32s(expect)?;
        let adam_step = r.u64()?;
        if r.pos != r.b.len() {
            return Err(CheckpointFormatError::Trailing {
                bytes: r.b.len() - r.pos,
            });
        }
        Ok(AuxCheckpoint {
            step,
            params,
            adam: Adam {
                m,
                v,
                step: adam_step,
            },
        })
    }

    /// Writes atomically.
    pub fn save(&self, path: &Path) -> Result<(), CheckpointError> {
        write_atomic(path, &self.to_bytes()).map_err(io(path))
    }

    pub fn load(path: &Path, expect: usize) -> Result<Self, CheckpointError> {
        let bytes = std::fs::read(path).map_err(io(path))?;
        Self::from_bytes(&bytes, expect).map_err(|reason| CheckpointError::Format {
            path: path.into(),
            reason,
        })
    }
}

struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    /// Checks a file's frame (`magic`, at least `min_len` bytes, CRC-32 of everything before the
    /// last 4 bytes, the format version) and returns a reader positioned after the version.
    fn framed(b: &'a [u8], magic: &[u8], min_len: usize) -> Result<Self, CheckpointFormatError> {
        if b.len() < min_len || &b[..8] != magic {
            return Err(CheckpointFormatError::BadMagic);
        }
        let (body, crc) = b.split_at(b.len() - 4);
        let crc = u32::from_le_bytes(
            crc.try_into()
                .map_err(|_| CheckpointFormatError::ShortFile)?,
        );
        if crc32fast::hash(body) != crc {
            return Err(CheckpointFormatError::Checksum);
        }
        let mut r = Reader { b: body, pos: 8 };
        let version = r.u32()?;
        if version != VERSION {
            return Err(CheckpointFormatError::Version { version });
        }
        Ok(r)
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], CheckpointFormatError> {
        if n > self.b.len() - self.pos {
            return Err(CheckpointFormatError::Truncated {
                wanted: n,
                offset: self.pos,
            });
        }
        let s = &self.b[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn u32(&mut self) -> Result<u32, CheckpointFormatError> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }
    fn u64(&mut self) -> Result<u64, CheckpointFormatError> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }
    fn f32s(&mut self, n: usize) -> Result<Vec<f32>, CheckpointFormatError> {
        let bytes = self.take(
            n.checked_mul(4)
                .ok_or(CheckpointFormatError::SizeOverflow)?,
        )?;
        Ok(bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
            .collect())
    }
}

/// Writes `bytes` to `path` through a temporary sibling and a rename (from the dataset crate's
/// [`msth_dataset::staging`], the one atomic writer).
pub use msth_dataset::staging::write_atomic;

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Checkpoint {
        let model = ModelConfig::fast_on_white(4);
        let layout = ModelLayout::new(&model);
        let params = layout.init_params(1);
        let n = params.len();
        Checkpoint {
            header: CheckpointHeader {
                model,
                train: serde_json::json!({"iters": 3}),
                step: 3,
                dataset: "t".into(),
                cameras: vec![],
                train_cameras: None,
                train_seconds: 1.5,
            },
            params,
            adam: Some(Adam::new(n)),
        }
    }

    #[test]
    fn round_trip_and_corruption() {
        let c = sample();
        let b = c.to_bytes();
        let d = Checkpoint::from_bytes(&b).unwrap();
        assert_eq!(d.params, c.params);
        assert_eq!(d.adam, c.adam);
        assert_eq!(d.header.step, 3);
        // Every truncation fails cleanly.
        for cut in [0, 5, 27, 100, b.len() / 2, b.len() - 1] {
            assert!(Checkpoint::from_bytes(&b[..cut]).is_err());
        }
        // A flipped byte is caught by the checksum.
        let mut e = b.clone();
        e[b.len() / 3] ^= 0x40;
        assert!(Checkpoint::from_bytes(&e)
            .unwrap_err()
            .to_string()
            .contains("checksum"));
    }

    #[test]
    fn aux_round_trip_and_corruption() {
        let a = AuxCheckpoint {
            step: 9,
            params: vec![1.0, -2.0, 3.5],
            adam: Adam {
                m: vec![0.1; 3],
                v: vec![0.2; 3],
                step: 9,
            },
        };
        let b = a.to_bytes();
        assert_eq!(AuxCheckpoint::from_bytes(&b, 3).unwrap(), a);
        assert!(AuxCheckpoint::from_bytes(&b, 4)
            .unwrap_err()
            .to_string()
            .contains("need 4"));
        for cut in [0, 7, 35, b.len() - 1] {
            assert!(AuxCheckpoint::from_bytes(&b[..cut], 3).is_err());
        }
        let mut e = b.clone();
        e[20] ^= 1;
        assert!(AuxCheckpoint::from_bytes(&e, 3)
            .unwrap_err()
            .to_string()
            .contains("checksum"));
    }

    #[test]
    fn save_is_atomic_and_loads() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("model.ckpt");
        sample().save(&p).unwrap();
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 1, "{names:?}");
        assert_eq!(Checkpoint::load(&p).unwrap().header.dataset, "t");
        let err = Checkpoint::load(&dir.path().join("missing.ckpt"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("missing.ckpt"));
    }
}
