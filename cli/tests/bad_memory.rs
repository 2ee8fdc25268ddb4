//! Hostile files under a memory cap: every file of the bad corpus (`tests/bad/`) and the hostile
//! sizes of issue #22 (a 100000 x 100000 camera, 4096 + 4096 samples per ray, a huge `--size`)
//! are played by the CPU player in a child process whose address space is capped
//! (`ulimit -v`, i.e. RLIMIT_AS). Each must end in an error exit with a message, never a signal
//! (an allocation the cap refuses aborts the process: SIGABRT). A valid file, and one whose
//! sampler sits at the decoder's limits, must play under the same cap, so the cap is not simply
//! too small for anything to run.
//!
//! The child is the `msth` binary itself, started through `sh -c 'ulimit -v ...; exec msth ...'`.

use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Address-space cap of the child, KiB: 1.5 GiB, enough for the test binary, two rendering
/// threads and their allocator arenas, far below what the hostile sizes would take.
const CAP_KIB: u64 = 1536 << 10;

fn bad_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/bad")
}

/// How a capped child ended (the fields are shown through `Debug` when a test fails).
#[derive(Debug)]
#[allow(dead_code)]
enum End {
    Ok,
    Error(String),
    Signal(i32, String),
    Other(i32, String),
}

/// Runs `msth ARGS` in a child under [`CAP_KIB`].
fn capped(args: &[&str]) -> End {
    let out = Command::new("sh")
        .arg("-c")
        .arg(format!("ulimit -v {CAP_KIB} && exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_msth"))
        .args(args)
        // Few allocator arenas: each reserves address space that the cap counts.
        .env("MALLOC_ARENA_MAX", "2")
        .env("RAYON_NUM_THREADS", "2")
        .output()
        .expect("sh starts");
    let text = String::from_utf8_lossy(&out.stderr).to_string();
    let status = out.status;
    if let Some(sig) = status.signal() {
        End::Signal(sig, text)
    } else {
        match status.code() {
            Some(0) => End::Ok,
            Some(1) if text.contains("error: ") => End::Error(text),
            Some(c) => End::Other(c, text),
            None => End::Other(-1, text),
        }
    }
}

fn play_args<'a>(file: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut a = vec![
        "play",
        file,
        "--cpu",
        "--frames",
        "2",
        "--no-video",
        "--quiet",
    ];
    a.extend_from_slice(extra);
    a
}

/// A view of the scene that needs no camera in the file, at a small size.
const VIEW: [&str; 4] = ["--path", "view:30,25,4", "--size", "32x24"];

fn expect_error(what: &str, end: End) -> String {
    match end {
        End::Error(text) => {
            let line = text
                .lines()
                .find(|l| l.starts_with("error: "))
                .unwrap_or_default()
                .to_string();
            println!("{what}: {line}");
            line
        }
        other => panic!("{what}: expected an error exit, got {other:?}"),
    }
}

#[test]
fn hostile_files_end_in_errors_under_a_memory_cap() {
    let files = msth_testkit::files_with_extension(&bad_dir(), "msth");
    assert!(files.len() >= 40, "only {} files in tests/bad", files.len());
    for p in &files {
        let f = p.to_str().unwrap();
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        // Trailing bytes and padding between sections lie outside everything a streaming
        // player reads (format.md §1.1, §4): it may play these, but must not crash.
        if name == "26_trailing_bytes.msth" || name == "32_nonzero_padding.msth" {
            match capped(&play_args(f, &VIEW)) {
                End::Ok | End::Error(_) => continue,
                other => panic!("{name}: {other:?}"),
            }
        }
        expect_error(&name, capped(&play_args(f, &VIEW)));
        // The file's own cameras and sizes, as `msth play FILE` uses them.
        if name.contains("camera") {
            expect_error(&format!("{name} (own camera)"), capped(&play_args(f, &[])));
        }
    }
}

/// A tiny valid file, trained for no step: the generator's model with `sampler` samples per ray
/// and one camera of 32 x 24 pixels.
fn valid_file(dir: &Path, proposal_samples: usize, samples: usize) -> PathBuf {
    use msth_core::config::{BlendMode, ModelConfig};
    let mut c = ModelConfig::fast_on_white(4);
    for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
        enc.blend = BlendMode::Mt;
        enc.resize(2, 8, 16.0, 4);
    }
    c.sampler.set_samples(proposal_samples, samples);
    let layout = msth_core::field::ModelLayout::new(&c);
    let p = layout.init_params(1);
    let cam = msth_core::Camera::look_at(
        32,
        24,
        0.8,
        glam::Vec3::new(0.0, -4.0, 1.0),
        glam::Vec3::ZERO,
        glam::Vec3::Z,
    );
    let opts = msth_codec::EncodeOptions {
        chunk_frames: 2,
        ..Default::default()
    };
    let (bytes, _) = msth_codec::encode(&c, &p, &[cam], &opts).unwrap();
    let path = dir.join(format!("valid_{proposal_samples}_{samples}.msth"));
    std::fs::write(&path, bytes).unwrap();
    path
}

#[test]
fn valid_files_play_under_the_same_cap_and_huge_sizes_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    // The paper's sampler, then the decoder's largest (1024 + 512): both render.
    for (np, nf) in [(128, 48), (1024, 512)] {
        let f = valid_file(dir.path(), np, nf);
        match capped(&play_args(f.to_str().unwrap(), &[])) {
            End::Ok => {}
            other => panic!("{np} + {nf} samples: expected to play, got {other:?}"),
        }
    }
    let f = valid_file(dir.path(), 128, 48);
    let f = f.to_str().unwrap();
    // A huge --size is refused with the limit, not attempted.
    let line = expect_error(
        "--size 100000x100000",
        capped(&play_args(f, &["--size", "100000x100000"])),
    );
    assert!(line.contains("--size") && line.contains("16384"), "{line}");
    let line = expect_error(
        "--size 16384x16384",
        capped(&play_args(f, &["--size", "16384x16384"])),
    );
    assert!(line.contains("16777216"), "{line}");
    // Samples per ray beyond what a file may hold are refused with the bound, not attempted;
    // a spec that is none of the forms names them.
    let line = expect_error(
        "--samples 100000,8",
        capped(&play_args(f, &["--samples", "100000,8"])),
    );
    assert!(
        line.contains("--samples 100000,8") && line.contains("1..=1024"),
        "{line}"
    );
    let line = expect_error(
        "--samples half",
        capped(&play_args(f, &["--samples", "half"])),
    );
    assert!(line.contains("full, fast, faster or P,M"), "{line}");
    // Fewer samples than the file's play.
    match capped(&play_args(f, &["--samples", "faster"])) {
        End::Ok => {}
        other => panic!("--samples faster: expected to play, got {other:?}"),
    }
}
