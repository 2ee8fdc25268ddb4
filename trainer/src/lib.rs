//! `msth-trainer`: everything that turns a dataset into a trained MSTH model.
//!
//! - [`synth`]: the built-in procedural dynamic scene with analytic ground truth;
//! - [`metrics`]: PSNR / SSIM / D-SSIM (PNG output and pictures: `msth_dataset::imageio`);
//! - [`autosize`]: sizing the model from the data (scene, frame count, motion);
//! - [`ray_sampling`]: uniform, dynamics-aware (paper §3.4) and static/dynamic batch samplers;
//! - [`adam`], [`train`], [`checkpoint`], [`eval`]: the optimiser, the loop, the checkpoint file
//!   and held-out evaluation;
//! - [`device`]: where the steps run (`--device auto|cpu|gpu`; the GPU step is `msth-gpu`'s);
//! - [`import`]: `msth import`, videos to a dataset with COLMAP's camera poses;
//! - [`unreached`]: hash-table values no training ray reached (dropped on export).

pub mod adam;
pub mod autosize;
pub mod checkpoint;
pub mod device;
pub mod eval;
pub mod import;
pub mod metrics;
pub mod ray_sampling;
pub mod synth;
pub mod train;
pub mod unreached;
