//! `msth-core`: the field math of MSTH (Masked Space-Time Hash encoding, NeurIPS 2023) shared by
//! the trainer and the player. No files, no network, no GPU.
//!
//! What lives here:
//! - [`camera`]: pinhole cameras and rays (conventions stated there and in the README);
//! - [`scene`]: scene box / contraction into the unit cube;
//! - [`grid`]: multi-resolution hash grids over 3D and 4D (per-axis resolutions), dense mask grid;
//! - [`mlp`], [`sh`], [`activation`]: decoders;
//! - [`render`], [`sampling`], [`losses`]: volume rendering, proposal resampling, losses;
//! - [`params`]: the flat parameter buffer with named slices;
//! - [`config`], [`field`], [`pipeline`]: the model, its forward and backward passes.
//!
//! Every kernel has a plain per-point reference (`reference` functions) next to the batched fast
//! path; tests check the two agree and check every backward pass against finite differences.

pub mod activation;
pub mod camera;
pub mod config;
pub mod field;
pub mod grid;
pub mod layers;
pub mod losses;
pub mod mlp;
pub mod params;
pub mod pipeline;
pub mod render;
pub mod rng;
pub mod sampling;
pub mod scene;
pub mod sh;
#[cfg(test)]
mod test_support;
pub mod uncertainty;
pub mod volume;

pub use camera::{Camera, Ray};
pub use scene::SceneBounds;
