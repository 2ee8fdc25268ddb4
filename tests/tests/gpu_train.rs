//! Training on the GPU (`msth train --device gpu`, here through `msth_trainer::train` with
//! `TrainSettings::device`) against training on the CPU, on the built-in scene:
//! - the same seed gives the same steps: every step's loss terms within 1e-3 relative of the
//!   CPU's (of 1e-4 for terms below it) (the device draws the same samples from the same random numbers; what differs is
//!   rounding, `gpu/tests/step.rs`);
//! - checkpoints are the same format whichever device wrote them: a run started on the GPU
//!   resumes on the CPU and the other way round, continuing the same schedule (step count,
//!   Adam state), and both end where the all-CPU run ends (loss terms within 1e-3 relative at the last step;
//!   measured on lavapipe: 1.3e-5).
//!
//! Without an adapter the tests are reported as ignored (with the reason), unless
//! `MSTH_REQUIRE_GPU=1` (then they fail): this binary runs on `msth-testkit`'s harness.

use std::path::Path;

use msth_dataset::Dataset;
use msth_testkit::Tests;
use msth_tests::{gpu_need, short_run, tiny_scene};
use msth_trainer::checkpoint::Checkpoint;
use msth_trainer::device::TrainDevice;
use msth_trainer::train::{train, LossTerms, TrainSettings};

fn main() -> std::process::ExitCode {
    let gpu = gpu_need();
    Tests::new(file!())
        .needs(
            &[&gpu],
            "gpu_steps_equal_cpu_steps",
            gpu_steps_equal_cpu_steps,
        )
        .needs(
            &[&gpu],
            "runs_resume_across_devices",
            runs_resume_across_devices,
        )
        .needs(
            &[&gpu],
            "what_the_gpu_step_lacks_is_a_clear_error",
            what_the_gpu_step_lacks_is_a_clear_error,
        )
        .run()
}

fn settings(data: &Dataset, iters: usize) -> TrainSettings {
    let mut s = short_run(data, 8);
    s.iters = iters;
    s.batch_rays = 256;
    s
}

/// Trains `settings` on `device` in `dir` (resuming its checkpoint when `resume`), stopping
/// after `stop` steps when given (checkpointed, as Ctrl-C does); returns each step's loss terms.
fn run(
    data: &Dataset,
    mut s: TrainSettings,
    device: TrainDevice,
    dir: &Path,
    (resume, stop): (bool, Option<usize>),
) -> Vec<LossTerms> {
    s.device = device;
    let ckpt = resume.then(|| Checkpoint::load(&dir.join("model.ckpt")).unwrap());
    let mut terms = Vec::new();
    let (trainer, _) = train(data, s, dir, ckpt, &mut |p| {
        terms.push(p.terms);
        stop.is_none_or(|n| terms.len() < n)
    })
    .unwrap_or_else(|e| panic!("{device}: {e}"));
    assert_eq!(trainer.on_gpu(), device == TrainDevice::Gpu);
    terms
}

fn close(a: &LossTerms, b: &LossTerms, rel: f32, what: &str) {
    for (name, x, y) in [
        ("rgb", a.rgb, b.rgb),
        ("interlevel", a.interlevel, b.interlevel),
        ("distortion", a.distortion, b.distortion),
        ("mask", a.mask, b.mask),
    ] {
        assert!(
            (x - y).abs() <= rel * y.abs().max(1e-4),
            "{what}: {name} {x} against the CPU's {y}"
        );
    }
}

fn gpu_steps_equal_cpu_steps() {
    let (_, data) = tiny_scene();
    let dir = tempfile::tempdir().unwrap();
    // With the stages' weight decay of the hash tables, which both Adams apply.
    let mut s = settings(&data, 4);
    s.grid_decay = 0.3;
    let cpu = run(
        &data,
        s.clone(),
        TrainDevice::Cpu,
        &dir.path().join("cpu"),
        (false, None),
    );
    let gpu = run(
        &data,
        s,
        TrainDevice::Gpu,
        &dir.path().join("gpu"),
        (false, None),
    );
    assert_eq!(cpu.len(), 4);
    assert_eq!(gpu.len(), 4);
    for (i, (g, c)) in gpu.iter().zip(&cpu).enumerate() {
        println!("step {i}: gpu {g:?}\n        cpu {c:?}");
        close(g, c, 1e-3, &format!("step {i}"));
    }
}

fn runs_resume_across_devices() {
    let (_, data) = tiny_scene();
    let dir = tempfile::tempdir().unwrap();
    let cpu = run(
        &data,
        settings(&data, 8),
        TrainDevice::Cpu,
        &dir.path().join("cpu"),
        (false, None),
    );
    for (first, then) in [
        (TrainDevice::Gpu, TrainDevice::Cpu),
        (TrainDevice::Cpu, TrainDevice::Gpu),
    ] {
        let d = dir.path().join(format!("{first}-{then}"));
        run(&data, settings(&data, 8), first, &d, (false, Some(4)));
        let c = Checkpoint::load(&d.join("model.ckpt")).unwrap();
        assert_eq!(c.header.step, 4, "{first} wrote step {}", c.header.step);
        let adam = c.adam.as_ref().expect("Adam's state in the checkpoint");
        assert_eq!(adam.step, 4);
        assert!(
            adam.v.iter().any(|&v| v > 0.0),
            "{first}: Adam's moments are empty"
        );
        let rest = run(&data, settings(&data, 8), then, &d, (true, None));
        assert_eq!(rest.len(), 4, "{first} then {then}: steps after resuming");
        let last = rest.last().unwrap();
        println!(
            "{first} then {then}: last step {last:?}, all-CPU {:?}",
            cpu[7]
        );
        close(last, &cpu[7], 1e-3, &format!("{first} then {then}, step 8"));
        assert_eq!(
            Checkpoint::load(&d.join("model.ckpt")).unwrap().header.step,
            8
        );
    }
}

/// Uncertainty-guided mask learning is not on the GPU step: `--device gpu` says so and names
/// the way out, and `--device auto` trains on the CPU instead, saying why.
fn what_the_gpu_step_lacks_is_a_clear_error() {
    let (_, data) = tiny_scene();
    let dir = tempfile::tempdir().unwrap();
    let mut s = settings(&data, 1);
    s.mask_learning.uncertainty = true;
    s.device = TrainDevice::Gpu;
    let e = train(&data, s.clone(), dir.path(), None, &mut |_| true)
        .err()
        .expect("uncertainty on the GPU");
    let msg = e.to_string();
    assert!(
        msg.contains("not on the GPU step") && msg.contains("--device cpu"),
        "{msg}"
    );
    // `auto` takes hardware adapters only: with the software one of CI it is the CPU anyway;
    // where it finds a GPU, the note says why it stays on the CPU.
    s.device = TrainDevice::Auto;
    let mut notes = Vec::new();
    let (trainer, _) = train(&data, s, dir.path(), None, &mut |p| {
        notes.extend(p.notes.iter().cloned());
        true
    })
    .unwrap();
    assert!(!trainer.on_gpu());
    assert!(
        notes.iter().any(|n| n.contains("device: the CPU")),
        "{notes:?}"
    );
}
