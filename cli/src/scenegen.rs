//! `msth synth --gltf`: datasets rendered from animated glTF models (msth-scenegen), with a
//! progress bar.

use std::time::Instant;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use msth_scenegen::{generate, load, Layout, SynthSettings};

use crate::SynthArgs;

pub fn synth_gltf(a: SynthArgs) -> Result<()> {
    let path = a.gltf.clone().expect("called with --gltf");
    let layout = match a.layout.as_str() {
        "object" => Layout::Object,
        "stage" => Layout::Stage,
        other => bail!("--layout `{other}`: expected `object` or `stage`"),
    };
    if a.static_scene {
        bail!("--static applies to the built-in scene only");
    }
    let mut s = SynthSettings::new(layout);
    if let Some(v) = a.width {
        s.width = v;
    }
    if let Some(v) = a.height {
        s.height = v;
    }
    if let Some(v) = a.frames {
        s.frames = v;
    }
    if let Some(v) = a.cameras {
        s.cameras = v;
    }
    if let Some(v) = a.supersample {
        s.supersample = v;
    }
    s.seed = a.seed;
    if a.no_video {
        s.ffmpeg = None;
    }
    s.validate()?;
    let model = load(&path)?;
    for note in &model.notes {
        eprintln!("note: {note}");
    }
    let pb = ProgressBar::new(s.total_images() as u64);
    pb.set_style(
        ProgressStyle::with_template("rendering {bar:30} {pos}/{len} images [{elapsed}<{eta}]")
            .expect("valid template"),
    );
    let t = Instant::now();
    let summary = generate(&model, &s, &a.out, &|| pb.inc(1))
        .with_context(|| format!("writing {}", a.out.display()))?;
    pb.finish_and_clear();
    if let Some(why) = &summary.videos_skipped {
        eprintln!("note: {why}");
    }
    println!(
        "wrote the {} layout of {} to {} ({} images of {}x{}, {} frames, {}x{} supersampling) in {:.1} s \
         (rendering {:.1} s, {:.1} images/s)",
        a.layout,
        path.display(),
        a.out.display(),
        summary.images,
        s.width,
        s.height,
        s.frames,
        s.supersample,
        s.supersample,
        t.elapsed().as_secs_f64(),
        summary.render_secs,
        summary.images as f64 / summary.render_secs.max(1e-9),
    );
    Ok(())
}
