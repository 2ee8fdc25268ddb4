//! `msth-trainer`: everything that turns a dataset into a trained MSTH model.
//!
//! - [`dataset`]: dataset types and loaders (one module per format), with validation;
//! - [`synth`]: the built-in procedural dynamic scene with analytic ground truth;
//! - [`metrics`], [`imageio`]: PSNR / SSIM / D-SSIM, PNG output and comparison pictures;
//! - [`autosize`]: sizing the model from the data (scene, frame count, motion);
//! - [`ray_sampling`]: uniform, dynamics-aware (paper §3.4) and static/dynamic batch samplers;
//! - [`adam`], [`train`], [`checkpoint`], [`eval`]: the optimiser, the loop, the checkpoint file
//!   and held-out evaluation;
//! - [`import`]: `msth import`, videos to a dataset with COLMAP's camera poses;
//! - [`unreached`]: hash-table values no training ray reached (dropped on export).

pub mod adam;
pub mod autosize;
pub mod checkpoint;
pub mod dataset;
pub mod eval;
pub mod imageio;
pub mod import;
pub mod metrics;
pub mod ray_sampling;
pub mod synth;
pub mod train;
pub mod unreached;
