//! The render kernels' WGSL, in modules that name the modules they use on `// #import NAME`
//! lines; [`compose`] writes the modules reachable from some roots into one shader text, each
//! once, after its imports.

mod compose;

pub use compose::{compose, imports, order, ComposeError, IMPORT, MODULE};
