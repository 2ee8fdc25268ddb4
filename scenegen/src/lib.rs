//! msth-scenegen: dynamic-scene datasets rendered from animated glTF 2.0 models.
//!
//! The pipeline, one module each:
//! 1. [`model`]: load `.gltf` / `.glb` (through the `gltf` crate) into a plain [`model::Model`],
//!    with [`accessor`] reading every buffer range with bounds checks;
//! 2. [`anim`]: sample the animation (STEP / LINEAR / CUBICSPLINE), evaluate the node
//!    hierarchy, skin vertices;
//! 3. [`scene`]: world-space triangles and materials ([`texture`] for image and procedural
//!    textures, [`stage`] for the set around the model), Lambert shading, supersampled
//!    rendering;
//! 4. [`raster`]: the triangle rasteriser (depth buffer, perspective-correct interpolation,
//!    top-left fill rule), a plain reference and the fast path;
//! 5. [`layout`]: the object (D-NeRF) and stage (DyNeRF) datasets and their writers, with
//!    [`dynerf`] for `poses_bounds.npy` and the ffmpeg videos.
//!
//! World frame: +Z up (the glTF +Y-up model is rotated on load, as Blender's importer does);
//! cameras follow `msth_core::Camera` (OpenGL axes, camera-to-world poses). Nothing here trains
//! or knows about the field; the datasets are read back by `msth_dataset`, which also writes them.

pub mod accessor;
pub mod anim;
pub mod dynerf;
pub mod error;
pub mod layout;
pub mod model;
pub mod raster;
pub mod scene;
pub mod stage;
pub mod texture;

pub use error::{Result, SceneGenError};
pub use layout::{generate, Layout, Summary, SynthSettings};
pub use model::{load, Model};
