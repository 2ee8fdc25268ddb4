//! Prints how decided a checkpoint's mask is: the fractions of mask vertices with
//! `m = sigmoid(logit)` below 0.1 (dynamic) and above 0.9 (static), and the mean `m`.
//!
//! Usage: `cargo run --release -p msth-trainer --example mask_fractions -- CHECKPOINT...`

use std::path::Path;

use msth_core::field::ModelLayout;
use msth_trainer::checkpoint::Checkpoint;

fn main() {
    let paths: Vec<String> = std::env::args().skip(1).collect();
    if paths.is_empty() {
        eprintln!("usage: mask_fractions CHECKPOINT...");
        std::process::exit(2);
    }
    let mut failed = false;
    for p in &paths {
        match Checkpoint::load(Path::new(p)) {
            Ok(c) => {
                let layout = ModelLayout::new(&c.header.model);
                match layout.field.encoding.mask_fractions(&c.params, 0.1, 0.9) {
                    Some((lo, hi)) => {
                        let (_, r) = layout.field.encoding.mask.as_ref().expect("has a mask");
                        let vals = &c.params[r.clone()];
                        let mean = vals
                            .iter()
                            .map(|&v| msth_core::activation::sigmoid(v) as f64)
                            .sum::<f64>()
                            / vals.len().max(1) as f64;
                        println!(
                            "{p}: step {}, mask vertices m < 0.1: {:.2}%, m > 0.9: {:.2}%, mean m {mean:.4}",
                            c.header.step,
                            100.0 * lo,
                            100.0 * hi
                        )
                    }
                    None => println!("{p}: the model has no mask"),
                }
            }
            Err(e) => {
                eprintln!("{e}");
                failed = true;
            }
        }
    }
    if failed {
        std::process::exit(1);
    }
}
