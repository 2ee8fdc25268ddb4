//! COLMAP's binary sparse model (`cameras.bin`, `images.bin`, `points3D.bin`, as `colmap
//! mapper` writes it), read into the same [`Model`] as the text reader.
//!
//! Layout (little-endian; every file opens with a `u64` entry count):
//! ```text
//! cameras.bin   per camera: u32 id, i32 model id, u64 width, u64 height, f64 params[n(model)]
//! images.bin    per image: u32 id, f64 qw qx qy qz, f64 tx ty tz, u32 camera id,
//!               name (bytes up to a NUL), u64 count, count x (f64 x, f64 y, u64 point id;
//!               u64::MAX = no 3D point)
//! points3D.bin  per point: u64 id, f64 x y z, u8 r g b, f64 error,
//!               u64 track length, length x (u32 image id, u32 point2D index)
//! ```
//! Every count is checked against the bytes left before anything is allocated for it (an entry
//! takes at least a known number of bytes), so a corrupt or truncated file gives a
//! [`BinaryModelError`] naming the byte offset, never a panic or a huge allocation.

use std::path::Path;

use glam::DVec3;

use super::{
    bad, camera_entry, pose_entry, CameraModel, ColmapImage, ColmapPoint, Model, ModelEntryError,
    MAX_ENTRIES,
};
use crate::DatasetError;

/// What is wrong with a binary model file (the file is named by
/// [`DatasetError::ColmapBinary`]).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum BinaryModelError {
    #[error("truncated: {what} at byte {offset} needs {needed} bytes, {left} left")]
    Truncated {
        what: &'static str,
        offset: usize,
        needed: usize,
        left: usize,
    },
    #[error("at byte {offset}: {count} {what} cannot fit in the {left} bytes left ({min_bytes} bytes each at least)")]
    CountTooLarge {
        what: &'static str,
        offset: usize,
        count: u64,
        left: usize,
        min_bytes: usize,
    },
    #[error("at byte {offset}: camera model id {id} is not supported (0-4: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV); import with --camera-model opencv")]
    UnknownModel { offset: usize, id: i32 },
    #[error("{left} bytes after the last entry")]
    TrailingBytes { left: usize },
}

impl CameraModel {
    /// COLMAP's numeric model id (`cameras.bin`).
    pub fn id(self) -> i32 {
        match self {
            CameraModel::SimplePinhole => 0,
            CameraModel::Pinhole => 1,
            CameraModel::SimpleRadial => 2,
            CameraModel::Radial => 3,
            CameraModel::Opencv => 4,
        }
    }

    fn from_id(id: i32) -> Option<CameraModel> {
        [
            CameraModel::SimplePinhole,
            CameraModel::Pinhole,
            CameraModel::SimpleRadial,
            CameraModel::Radial,
            CameraModel::Opencv,
        ]
        .into_iter()
        .find(|m| m.id() == id)
    }
}

/// Smallest entry sizes in bytes (a camera with the fewest parameters, an image with a
/// one-byte name and no observations, a point with an empty track).
const CAMERA_MIN_BYTES: usize = 4 + 4 + 8 + 8 + 3 * 8;
const IMAGE_MIN_BYTES: usize = 4 + 7 * 8 + 4 + 1 + 8;
const OBSERVATION_BYTES: usize = 8 + 8 + 8;
const POINT_MIN_BYTES: usize = 8 + 3 * 8 + 3 + 8 + 8;
const TRACK_ELEMENT_BYTES: usize = 4 + 4;

/// A cursor over a file's bytes.
struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn left(&self) -> usize {
        self.bytes.len() - self.at
    }

    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], BinaryModelError> {
        if n > self.left() {
            return Err(BinaryModelError::Truncated {
                what,
                offset: self.at,
                needed: n,
                left: self.left(),
            });
        }
        let s = &self.bytes[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], BinaryModelError> {
        let mut a = [0; N];
        a.copy_from_slice(self.take(N, what)?);
        Ok(a)
    }

    fn u32(&mut self, what: &'static str) -> Result<u32, BinaryModelError> {
        self.array(what).map(u32::from_le_bytes)
    }

    fn i32(&mut self, what: &'static str) -> Result<i32, BinaryModelError> {
        self.array(what).map(i32::from_le_bytes)
    }

    fn u64(&mut self, what: &'static str) -> Result<u64, BinaryModelError> {
        self.array(what).map(u64::from_le_bytes)
    }

    fn f64(&mut self, what: &'static str) -> Result<f64, BinaryModelError> {
        self.array(what).map(f64::from_le_bytes)
    }

    fn f64s<const N: usize>(&mut self, what: &'static str) -> Result<[f64; N], BinaryModelError> {
        let mut a = [0.0; N];
        for v in &mut a {
            *v = self.f64(what)?;
        }
        Ok(a)
    }

    /// A `u64` count of entries of at least `min_bytes` each, checked against the bytes left.
    fn count(&mut self, what: &'static str, min_bytes: usize) -> Result<usize, BinaryModelError> {
        let offset = self.at;
        let count = self.u64(what)?;
        let fits = usize::try_from(count)
            .ok()
            .filter(|&c| c <= MAX_ENTRIES)
            .filter(|&c| c.checked_mul(min_bytes).is_some_and(|b| b <= self.left()));
        fits.ok_or(BinaryModelError::CountTooLarge {
            what,
            offset,
            count,
            left: self.left(),
            min_bytes,
        })
    }

    /// Bytes up to a NUL (consumed), as UTF-8 (lossy).
    fn name(&mut self) -> Result<String, BinaryModelError> {
        let rest = &self.bytes[self.at..];
        let Some(end) = rest.iter().position(|&b| b == 0) else {
            return Err(BinaryModelError::Truncated {
                what: "image name (no terminating NUL)",
                offset: self.at,
                needed: rest.len() + 1,
                left: rest.len(),
            });
        };
        let name = String::from_utf8_lossy(&rest[..end]).into_owned();
        self.at += end + 1;
        Ok(name)
    }

    fn end(&self) -> Result<(), BinaryModelError> {
        match self.left() {
            0 => Ok(()),
            left => Err(BinaryModelError::TrailingBytes { left }),
        }
    }
}

/// Reads `cameras.bin`, `images.bin` and `points3D.bin` from `dir`; images in id order.
pub fn read_binary_model(dir: &Path) -> Result<Model, DatasetError> {
    let mut model = Model::default();
    read_file(&dir.join("cameras.bin"), &mut model, cameras)?;
    read_file(&dir.join("images.bin"), &mut model, images)?;
    read_file(&dir.join("points3D.bin"), &mut model, points)?;
    Ok(model)
}

/// An entry that parsed but does not make sense, and where it starts.
struct Semantic {
    offset: usize,
    error: ModelEntryError,
}

enum FileError {
    Binary(BinaryModelError),
    Semantic(Semantic),
}

impl From<BinaryModelError> for FileError {
    fn from(e: BinaryModelError) -> Self {
        FileError::Binary(e)
    }
}

fn semantic(offset: usize) -> impl FnOnce(ModelEntryError) -> FileError {
    move |error| FileError::Semantic(Semantic { offset, error })
}

fn read_file(
    path: &Path,
    model: &mut Model,
    parse: fn(&mut Reader, &mut Model) -> Result<(), FileError>,
) -> Result<(), DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut r = Reader {
        bytes: &bytes,
        at: 0,
    };
    parse(&mut r, model)
        .and_then(|()| r.end().map_err(FileError::Binary))
        .map_err(|e| match e {
            FileError::Binary(source) => DatasetError::ColmapBinary {
                path: path.to_path_buf(),
                source,
            },
            FileError::Semantic(s) => bad(path, format!("at byte {}: {}", s.offset, s.error)),
        })
}

fn cameras(r: &mut Reader, model: &mut Model) -> Result<(), FileError> {
    for _ in 0..r.count("cameras", CAMERA_MIN_BYTES)? {
        let offset = r.at;
        let id = r.u32("camera id")?;
        let model_offset = r.at;
        let model_id = r.i32("camera model id")?;
        let kind = CameraModel::from_id(model_id).ok_or(BinaryModelError::UnknownModel {
            offset: model_offset,
            id: model_id,
        })?;
        let width = r.u64("width")?;
        let height = r.u64("height")?;
        let params = (0..kind.num_params())
            .map(|_| r.f64("camera parameters"))
            .collect::<Result<Vec<_>, _>>()?;
        camera_entry(kind, width, height, params)
            .and_then(|camera| model.add_camera(id, camera))
            .map_err(semantic(offset))?;
    }
    Ok(())
}

fn images(r: &mut Reader, model: &mut Model) -> Result<(), FileError> {
    for _ in 0..r.count("images", IMAGE_MIN_BYTES)? {
        let offset = r.at;
        let image_id = r.u32("image id")?;
        let qvec = r.f64s::<4>("quaternion")?;
        let tvec = r.f64s::<3>("translation")?;
        let camera_id = r.u32("camera id")?;
        let name = r.name()?;
        pose_entry(&qvec, &tvec).map_err(semantic(offset))?;
        let n = r.count("observations", OBSERVATION_BYTES)?;
        let mut observed = Vec::with_capacity(n);
        for _ in 0..n {
            r.take(16, "observation x y")?;
            let id = r.u64("observation point id")?;
            observed.push((id != u64::MAX).then_some(id));
        }
        let image = ColmapImage {
            image_id,
            qvec,
            tvec,
            camera_id,
            name,
            point_ids: Vec::new(),
        };
        model
            .add_image(image, observed.into_iter())
            .map_err(semantic(offset))?;
    }
    model.sort_images().map_err(semantic(r.at))
}

fn points(r: &mut Reader, model: &mut Model) -> Result<(), FileError> {
    for _ in 0..r.count("points", POINT_MIN_BYTES)? {
        let offset = r.at;
        let id = r.u64("point id")?;
        let [x, y, z] = r.f64s::<3>("point position")?;
        r.take(3, "point colour")?;
        let error_px = r.f64("point error")?;
        let track_len = r.count("track elements", TRACK_ELEMENT_BYTES)?;
        r.take(track_len * TRACK_ELEMENT_BYTES, "track")?;
        let point = ColmapPoint {
            position: DVec3::new(x, y, z),
            error_px,
            track_len,
        };
        model.add_point(id, point).map_err(semantic(offset))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Little-endian byte strings for hand-made files.
    #[derive(Default)]
    struct Bytes(Vec<u8>);

    impl Bytes {
        fn u32(mut self, v: u32) -> Self {
            self.0.extend(v.to_le_bytes());
            self
        }
        fn i32(mut self, v: i32) -> Self {
            self.0.extend(v.to_le_bytes());
            self
        }
        fn u64(mut self, v: u64) -> Self {
            self.0.extend(v.to_le_bytes());
            self
        }
        fn f64s(mut self, v: &[f64]) -> Self {
            for x in v {
                self.0.extend(x.to_le_bytes());
            }
            self
        }
        fn raw(mut self, v: &[u8]) -> Self {
            self.0.extend(v);
            self
        }
    }

    /// Two cameras, two images (image 1 observes point 7 twice and no point once), two points:
    /// the binary twin of the text reader's test model, with the images in the other order.
    fn files() -> [Vec<u8>; 3] {
        let cameras = Bytes::default()
            .u64(2)
            .u32(1)
            .i32(4)
            .u64(200)
            .u64(150)
            .f64s(&[180.0, 170.0, 100.0, 75.0, -0.1, 0.02, 0.001, -0.002])
            .u32(2)
            .i32(2)
            .u64(64)
            .u64(48)
            .f64s(&[50.0, 32.0, 24.0, 0.05]);
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let images = Bytes::default()
            .u64(2)
            .u32(2)
            .f64s(&[h, 0.0, h, 0.0, 0.0, 0.0, 2.0])
            .u32(2)
            .raw(b"cam01/t0000.png\0")
            .u64(0)
            .u32(1)
            .f64s(&[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
            .u32(1)
            .raw(b"cam00/t0000.png\0")
            .u64(3)
            .f64s(&[10.0, 20.0])
            .u64(7)
            .f64s(&[30.0, 40.0])
            .u64(u64::MAX)
            .f64s(&[50.0, 60.0])
            .u64(7);
        let points = Bytes::default()
            .u64(2)
            .u64(7)
            .f64s(&[0.0, 0.0, 2.0])
            .raw(&[255, 0, 0])
            .f64s(&[0.5])
            .u64(2)
            .u32(1)
            .u32(0)
            .u32(1)
            .u32(2)
            .u64(30)
            .f64s(&[1.0, 1.0, 3.0])
            .raw(&[0, 255, 0])
            .f64s(&[0.25])
            .u64(1)
            .u32(1)
            .u32(1);
        [cameras.0, images.0, points.0]
    }

    const NAMES: [&str; 3] = ["cameras.bin", "images.bin", "points3D.bin"];

    fn write(dir: &Path, files: &[Vec<u8>; 3]) {
        for (name, bytes) in NAMES.iter().zip(files) {
            std::fs::write(dir.join(name), bytes).unwrap();
        }
    }

    #[test]
    fn reads_a_hand_made_binary_model() {
        use crate::colmap::tests::{write_model, CAMERAS, IMAGES, POINTS};
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), &files());
        let m = read_binary_model(dir.path()).unwrap();
        let text = tempfile::tempdir().unwrap();
        write_model(text.path(), CAMERAS, IMAGES, POINTS);
        assert_eq!(m, crate::colmap::read_text_model(text.path()).unwrap());
        // Id order, whatever the file order.
        let ids: Vec<u32> = m.images.iter().map(|i| i.image_id).collect();
        assert_eq!(ids, [1, 2]);
        assert_eq!(m.images[0].point_ids, [7]);
        assert_eq!(m.cameras[&2].model, CameraModel::SimpleRadial);
        // `read_model` picks the binary model when there is one.
        assert_eq!(crate::colmap::read_model(dir.path()).unwrap(), m);
    }

    fn error_of(files: &[Vec<u8>; 3]) -> DatasetError {
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), files);
        read_binary_model(dir.path()).unwrap_err()
    }

    #[test]
    fn every_truncation_is_a_typed_error() {
        let good = files();
        for (f, name) in NAMES.iter().enumerate() {
            for len in 0..good[f].len() {
                let mut cut = good.clone();
                cut[f].truncate(len);
                match error_of(&cut) {
                    DatasetError::ColmapBinary { path, source } => {
                        assert!(path.ends_with(name), "{path:?}");
                        assert!(
                            matches!(
                                source,
                                BinaryModelError::Truncated { .. }
                                    | BinaryModelError::CountTooLarge { .. }
                            ),
                            "{name} cut at {len}: {source}"
                        );
                    }
                    e => panic!("{name} cut at {len}: {e}"),
                }
            }
        }
    }

    #[test]
    fn corrupt_files_are_named_without_allocating() {
        let good = files();
        let with = |f: usize, at: usize, bytes: &[u8]| {
            let mut c = good.clone();
            c[f][at..at + bytes.len()].copy_from_slice(bytes);
            c
        };
        // A count far beyond the file: refused before allocating.
        let e = error_of(&with(2, 0, &u64::MAX.to_le_bytes()));
        assert!(
            matches!(
                &e,
                DatasetError::ColmapBinary {
                    source: BinaryModelError::CountTooLarge {
                        count: u64::MAX,
                        ..
                    },
                    ..
                }
            ),
            "{e}"
        );
        // An observation count of 2^40 in the second image.
        // (the count, the first image: 88 bytes, the second's id, pose, camera and name).
        let obs_at = 8 + 88 + 4 + 7 * 8 + 4 + 16;
        let e = error_of(&with(1, obs_at, &(1u64 << 40).to_le_bytes()));
        assert!(e.to_string().contains("observations cannot fit"), "{e}");
        // A track length of 2^61 (the byte count would overflow).
        let track_at = 8 + 8 + 24 + 3 + 8;
        let e = error_of(&with(2, track_at, &(1u64 << 61).to_le_bytes()));
        assert!(e.to_string().contains("track elements cannot fit"), "{e}");
        // A model COLMAP has but msth does not read (5 = OPENCV_FISHEYE).
        let e = error_of(&with(0, 12, &5i32.to_le_bytes())).to_string();
        assert!(
            e.contains("camera model id 5") && e.contains("byte 12"),
            "{e}"
        );
        // A zero focal length, a NaN translation, a quaternion that is not a rotation.
        let e = error_of(&with(0, 32, &0f64.to_le_bytes())).to_string();
        assert!(e.contains("non-positive focal length"), "{e}");
        let e = error_of(&with(1, 12 + 6 * 8, &f64::NAN.to_le_bytes())).to_string();
        assert!(e.contains("not finite"), "{e}");
        let e = error_of(&with(1, 12, &9f64.to_le_bytes())).to_string();
        assert!(e.contains("not a rotation"), "{e}");
        // An image of an unknown camera, a point given twice, bytes after the end.
        let e = error_of(&with(1, 12 + 7 * 8, &5u32.to_le_bytes())).to_string();
        assert!(e.contains("camera 5 is not"), "{e}");
        let second_point = 8 + POINT_MIN_BYTES + 2 * TRACK_ELEMENT_BYTES;
        let e = error_of(&with(2, second_point, &7u64.to_le_bytes())).to_string();
        assert!(e.contains("point 7 appears twice"), "{e}");
        let mut long = good.clone();
        long[0].push(0);
        let e = error_of(&long).to_string();
        assert!(
            e.contains("cameras.bin") && e.contains("1 bytes after"),
            "{e}"
        );
        // A name without its NUL at the end of the file.
        let mut c = good.clone();
        c[1] = Bytes::default()
            .u64(1)
            .u32(1)
            .f64s(&[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
            .u32(1)
            .raw(b"a name that never ends and pads the entry out")
            .0;
        let e = error_of(&c).to_string();
        assert!(e.contains("no terminating NUL"), "{e}");
    }
}
