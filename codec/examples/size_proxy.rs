//! A file of a trained model's configuration whose hash tables hold random values of a trained
//! table's spread: it compresses as a converged model of that size does, where a model trained
//! briefly (most fine-level rows still near their initial values) compresses far better. For
//! measuring transfers (`msth bench stream`) at a configuration there is no time to train to
//! convergence; what it draws is meaningless.
//!
//! `cargo run --release -p msth-codec --example size_proxy -- IN.msth OUT.msth [LAYERS] [QUANT]`
//! keeps IN's configuration, MLPs, masks, cameras and chunking; each hashed level of the field's
//! and the proposal's tables gets values drawn from N(0, s), `s` the spread of IN's densely
//! indexed levels (its trained coarse levels); writes LAYERS progressive layers (default 4) in
//! mode QUANT (default q5).

use msth_codec::{decode_all, encode, EncodeOptions, QuantMode};
use msth_core::rng::Rng;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, output, rest @ ..] = args.as_slice() else {
        return Err("usage: size_proxy IN.msth OUT.msth [LAYERS] [QUANT]".into());
    };
    let layers: usize = rest.first().map_or(Ok(4), |s| s.parse())?;
    let quant: QuantMode = rest.get(1).map_or(Ok(QuantMode::Q5), |s| s.parse())?;
    let d = decode_all(&std::fs::read(input)?)?;
    let mut params = d.params.clone();
    let encodings = [&d.layout.field.encoding, &d.layout.proposal.field.encoding];
    // The spread of the densely indexed (trained, coarse) levels.
    let (mut sum, mut sq, mut n) = (0.0f64, 0.0f64, 0usize);
    for e in encodings {
        for (g, r) in [&e.h3, &e.h4].into_iter().flatten() {
            for level in g.levels.iter().filter(|l| l.dense) {
                let s = r.start + level.offset;
                for &v in &params[s..s + level.rows * g.features] {
                    sum += v as f64;
                    sq += (v as f64) * (v as f64);
                    n += 1;
                }
            }
        }
    }
    let mean = sum / n.max(1) as f64;
    let spread = (sq / n.max(1) as f64 - mean * mean).max(0.0).sqrt() as f32;
    let mut rng = Rng::new(7);
    let mut filled = 0usize;
    for e in encodings {
        for (g, r) in [&e.h3, &e.h4].into_iter().flatten() {
            for level in g.levels.iter().filter(|l| !l.dense) {
                let s = r.start + level.offset;
                for v in &mut params[s..s + level.rows * g.features] {
                    // A sum of 4 uniforms: near-Gaussian, spread `spread`.
                    let u: f32 = (0..4).map(|_| rng.range_f32(-1.0, 1.0)).sum();
                    *v = u * spread * (3.0f32 / 4.0).sqrt();
                    filled += 1;
                }
            }
        }
    }
    let opts = EncodeOptions {
        quant,
        chunk_frames: d.metadata.chunk_frames as usize,
        dynamic_threshold: d.metadata.dynamic_threshold,
        frame_rate: d.metadata.frame_rate,
        layers,
        ..Default::default()
    };
    let (bytes, report) = encode(&d.config, &params, &d.cameras, &opts)?;
    std::fs::write(output, &bytes)?;
    println!(
        "{output}: {} bytes ({layers} layers, {quant}); {filled} hashed values drawn with spread {spread:.4}; first frame with layer 0: {} bytes",
        bytes.len(),
        report.first_frame_bytes(1)
    );
    Ok(())
}
