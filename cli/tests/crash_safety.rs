//! Training and export lose nothing when the process dies or the disk fills, with the `msth`
//! binary as a child process:
//!
//! - SIGKILL at random moments of a small run ([`KILLS`] times, a checkpoint every step, so that
//!   many kills land inside a checkpoint write): after each, `model.ckpt` loads (or was never
//!   written yet) and its step never goes back; the run resumed to the end equals, bit for bit
//!   (parameters and Adam state), the same run never interrupted. The random delays come from a
//!   seed printed at the start (`MSTH_CRASH_SEED` repeats a run).
//! - Ctrl-C (SIGINT): the run stops after its step, writes a checkpoint, says how to resume, and
//!   the resumed run again equals the uninterrupted one.
//! - A full disk, as a file size limit (`ulimit -f`, RLIMIT_FSIZE, in the child; runs anywhere):
//!   a checkpoint that cannot be written and an export that cannot be written end in an error
//!   that says the previous file is unchanged, and it is (byte for byte), with no temporary file
//!   left behind.
//! - The same on a real full file system, a small tmpfs (needs root: the need `tmpfs`, reported
//!   as ignored without it).

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use msth_testkit::{Need, Tests};
use msth_trainer::checkpoint::Checkpoint;

mod support;

use support::{run_measured, KillOnDrop};

fn main() -> ExitCode {
    let tmpfs = Need::new("tmpfs", probe_tmpfs);
    Tests::new(file!())
        .test(
            "sigkill_at_random_points_leaves_a_loadable_checkpoint_and_resume_is_exact",
            sigkill_at_random_points,
        )
        .test(
            "ctrl_c_writes_a_last_checkpoint_and_says_how_to_resume",
            ctrl_c_checkpoints_and_says_how_to_resume,
        )
        .test(
            "a_file_size_limit_during_checkpoint_and_export_keeps_the_previous_files",
            file_size_limit_keeps_previous_files,
        )
        .needs(
            &[&tmpfs],
            "a_full_tmpfs_during_checkpoint_and_export_keeps_the_previous_files",
            full_tmpfs_keeps_previous_files,
        )
        .run()
}

/// SIGKILLs of the random-kill test.
const KILLS: usize = 20;
/// Steps of the runs the kill and Ctrl-C tests compare.
const ITERS: usize = 60;
/// A child still running after this is a hang.
const HANG: Duration = Duration::from_secs(300);

fn msth() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_msth"));
    // The same worker count in every run: the gradient sums are then identical.
    c.env("RAYON_NUM_THREADS", "2");
    c
}

/// A small dataset of the built-in scene, written once per test binary.
fn dataset() -> &'static Path {
    static DATA: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &DATA
        .get_or_init(|| {
            let dir = tempfile::tempdir().unwrap();
            let data = dir.path().join("data");
            let m = run_measured(
                msth().args(["synth", "--out"]).arg(&data).args([
                    "--width",
                    "32",
                    "--height",
                    "24",
                    "--frames",
                    "4",
                    "--cameras",
                    "4",
                ]),
                HANG,
            );
            assert_eq!(m.code, Some(0), "msth synth: {}", m.stderr);
            (dir, data)
        })
        .1
}

/// `msth train DATA --out OUT` with a small model, `iters` steps, a checkpoint every `every`.
fn train_args(out: &Path, iters: usize, every: usize, resume: bool) -> Vec<String> {
    let mut a: Vec<String> = vec![
        "train".into(),
        dataset().to_str().unwrap().into(),
        "--out".into(),
        out.to_str().unwrap().into(),
    ];
    for s in [
        "--preset",
        "fast",
        "--no-autosize",
        "--no-eval",
        "--device",
        "cpu",
        "--seed",
        "3",
        "--batch-rays",
        "256",
        "--set",
        "model.field.encoding.grid3.log2_table_size=12",
        "--set",
        "model.field.encoding.grid4.log2_table_size=12",
        "--set",
        "model.proposal.encoding.grid3.log2_table_size=10",
        "--set",
        "model.proposal.encoding.grid4.log2_table_size=10",
    ] {
        a.push(s.into());
    }
    a.extend([
        "--iters".into(),
        iters.to_string(),
        "--checkpoint-every".into(),
        every.to_string(),
    ]);
    if resume {
        a.push("--resume".into());
    }
    a
}

/// Runs `msth ARGS` to its end; panics unless it succeeds.
fn run_ok(args: &[String]) {
    let m = run_measured(msth().args(args), HANG);
    assert_eq!(m.code, Some(0), "msth {}: {}", args.join(" "), m.stderr);
}

/// The uninterrupted run of [`ITERS`] steps, once per binary: its checkpoint's bytes.
fn reference() -> &'static Checkpoint {
    static REF: OnceLock<(tempfile::TempDir, Checkpoint)> = OnceLock::new();
    &REF.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("run");
        let t = Instant::now();
        run_ok(&train_args(&out, ITERS, 1, false));
        println!(
            "uninterrupted run: {ITERS} steps in {:.1} s, checkpoint {} bytes",
            t.elapsed().as_secs_f64(),
            std::fs::metadata(out.join("model.ckpt")).unwrap().len()
        );
        let c = Checkpoint::load(&out.join("model.ckpt")).unwrap();
        assert_eq!(c.header.step as usize, ITERS);
        (dir, c)
    })
    .1
}

/// Panics unless `c` holds exactly the state of the uninterrupted run.
fn assert_same_as_reference(c: &Checkpoint, what: &str) {
    let r = reference();
    assert_eq!(c.header.step, r.header.step, "{what}: step");
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>();
    assert!(
        bits(&c.params) == bits(&r.params),
        "{what}: the parameters differ from the uninterrupted run's"
    );
    let (a, b) = (c.adam.as_ref().unwrap(), r.adam.as_ref().unwrap());
    assert!(
        a.step == b.step && bits(&a.m) == bits(&b.m) && bits(&a.v) == bits(&b.v),
        "{what}: the Adam state differs from the uninterrupted run's"
    );
}

/// Temporary files a write left in `dir` (`.NAME.tmp-...`).
fn temporaries(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .map(|d| {
            d.flatten()
                .map(|e| e.file_name().to_string_lossy().to_string())
                .filter(|n| n.starts_with('.') && n.contains(".tmp-"))
                .collect()
        })
        .unwrap_or_default()
}

/// xorshift64*: the kill delays, repeatable from the printed seed.
struct Rng(u64);

impl Rng {
    fn next_f64(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn sigkill_at_random_points() {
    reference();
    let seed = std::env::var("MSTH_CRASH_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_nanos() as u64
                | 1
        });
    println!("kill delays from MSTH_CRASH_SEED={seed}");
    let mut rng = Rng(seed);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let ckpt = out.join("model.ckpt");
    let mut last_step = 0u64;
    let (mut during_write, mut before_first) = (0, 0);
    for k in 0..KILLS {
        let resume = ckpt.exists();
        let mut child = KillOnDrop(
            msth()
                .args(train_args(&out, ITERS, 1, resume))
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .unwrap(),
        );
        let delay = Duration::from_secs_f64(0.05 + 1.5 * rng.next_f64());
        std::thread::sleep(delay);
        let finished = child.0.try_wait().unwrap().is_some();
        child.0.kill().unwrap_or(()); // SIGKILL
        child.0.wait().unwrap();
        drop(child);
        if !temporaries(&out).is_empty() {
            during_write += 1;
        }
        if !ckpt.exists() {
            before_first += 1;
            println!("kill {k}: after {delay:.2?}, before the first checkpoint");
            continue;
        }
        let c = Checkpoint::load(&ckpt).unwrap_or_else(|e| {
            panic!("kill {k} after {delay:.2?}: the checkpoint does not load: {e}")
        });
        assert!(
            c.header.step >= last_step,
            "kill {k}: the checkpoint went back from step {last_step} to {}",
            c.header.step
        );
        last_step = c.header.step;
        println!(
            "kill {k}: after {delay:.2?}{}, checkpoint at step {}, loads",
            if finished { " (the run had ended)" } else { "" },
            c.header.step
        );
    }
    println!(
        "{KILLS} kills: {during_write} left a temporary file (killed while writing a checkpoint), \
         {before_first} came before the first checkpoint; the last checkpoint was at step {last_step}"
    );
    // Resume to the end: the same state as the run never interrupted.
    run_ok(&train_args(&out, ITERS, 1, ckpt.exists()));
    assert!(
        temporaries(&out).is_empty(),
        "temporary files left: {:?}",
        temporaries(&out)
    );
    assert_same_as_reference(&Checkpoint::load(&ckpt).unwrap(), "resumed after the kills");
}

fn ctrl_c_checkpoints_and_says_how_to_resume() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let ckpt = out.join("model.ckpt");
    // A checkpoint only at the end, unless interrupted: the one found is Ctrl-C's.
    let args = train_args(&out, ITERS, 0, false);
    let child = msth()
        .args(&args)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id() as libc::pid_t;
    let mut child = KillOnDrop(child);
    let stderr = child.0.stderr.take().unwrap();
    let (started_tx, started) = std::sync::mpsc::channel();
    let err = std::thread::spawn(move || {
        use std::io::BufRead;
        let mut s = String::new();
        for line in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            if line.starts_with("step ") {
                let _ = started_tx.send(());
            }
            s.push_str(&line);
            s.push('\n');
        }
        s
    });
    // Interrupt once the run has begun its steps (a progress line every 5% of them).
    started
        .recv_timeout(HANG)
        .expect("the run printed no progress line");
    // SAFETY: `pid` is our running child.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGINT) }, 0);
    let status = child.0.wait().unwrap();
    let text = err.join().unwrap();
    println!("{text}");
    let c = Checkpoint::load(&ckpt).expect("Ctrl-C wrote a checkpoint");
    let step = c.header.step as usize;
    if step < ITERS {
        assert!(!status.success(), "an interrupted run exits with an error");
        for words in [
            format!("interrupted at step {step} of {ITERS}"),
            "--resume".to_string(),
            ckpt.display().to_string(),
        ] {
            assert!(
                text.contains(&words),
                "the message does not say `{words}`:\n{text}"
            );
        }
    } else {
        println!("(the run ended before the signal: nothing to interrupt)");
    }
    let mut resumed = args.clone();
    resumed.push("--resume".into());
    run_ok(&resumed);
    assert_same_as_reference(&Checkpoint::load(&ckpt).unwrap(), "resumed after Ctrl-C");
}

/// `msth ARGS` with writes limited to `limit_bytes` per file (RLIMIT_FSIZE; SIGXFSZ ignored, so
/// a write past it fails with EFBIG instead of killing the process).
fn limited(args: &[String], limit_bytes: u64) -> support::Measured {
    let mut c = Command::new("sh");
    c.env("RAYON_NUM_THREADS", "2")
        .arg("-c")
        .arg(format!(
            "trap '' XFSZ; ulimit -f {} && exec \"$0\" \"$@\"",
            limit_bytes.div_ceil(512)
        ))
        .arg(env!("CARGO_BIN_EXE_msth"))
        .args(args);
    run_measured(&mut c, HANG)
}

fn file_size_limit_keeps_previous_files() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let ckpt = out.join("model.ckpt");
    run_ok(&train_args(&out, 4, 2, false));
    let before = std::fs::read(&ckpt).unwrap();
    // Resumed with a checkpoint every 2 steps, but files may not grow past half a checkpoint.
    let m = limited(&train_args(&out, 8, 2, true), before.len() as u64 / 2);
    println!("checkpoint past the size limit: {}", m.stderr.trim());
    assert_ne!(m.code, Some(0), "the checkpoint write cannot succeed");
    for words in [
        "writing the checkpoint of step 6 failed",
        "File too large",
        "(step 4) is unchanged",
    ] {
        assert!(
            m.stderr.contains(words),
            "the message does not say `{words}`: {}",
            m.stderr
        );
    }
    assert!(
        std::fs::read(&ckpt).unwrap() == before,
        "the previous checkpoint changed"
    );
    assert_eq!(Checkpoint::load(&ckpt).unwrap().header.step, 4);
    assert!(temporaries(&out).is_empty(), "{:?}", temporaries(&out));

    // Export: a first file, then a larger one (lossless) that cannot be written.
    let msth_file = dir.path().join("scene.msth");
    let export = |quant: &str| -> Vec<String> {
        [
            "export",
            ckpt.to_str().unwrap(),
            "-o",
            msth_file.to_str().unwrap(),
            "--quant",
            quant,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    run_ok(&export("q5"));
    let first = std::fs::read(&msth_file).unwrap();
    let m = limited(&export("f32"), first.len() as u64 / 2);
    println!("export past the size limit: {}", m.stderr.trim());
    assert_ne!(m.code, Some(0));
    for words in [
        "failed (the file there before is unchanged)",
        "File too large",
    ] {
        assert!(
            m.stderr.contains(words),
            "the message does not say `{words}`: {}",
            m.stderr
        );
    }
    assert!(
        std::fs::read(&msth_file).unwrap() == first,
        "the previous export changed"
    );
    assert!(
        temporaries(dir.path()).is_empty(),
        "{:?}",
        temporaries(dir.path())
    );
}

/// Whether a tmpfs can be mounted here (root with CAP_SYS_ADMIN).
fn probe_tmpfs() -> Result<(), String> {
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let m = Tmpfs::mount(dir.path(), 1 << 20)?;
    drop(m);
    Ok(())
}

/// A tmpfs mounted at a folder, unmounted when dropped.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(at: &Path, bytes: u64) -> Result<Tmpfs, String> {
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={bytes}"), "tmpfs"])
            .arg(at)
            .output()
            .map_err(|e| format!("cannot run `mount`: {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "mounting a tmpfs needs root with CAP_SYS_ADMIN: {}",
                String::from_utf8_lossy(&out.stderr).trim()
            ));
        }
        Ok(Tmpfs(at.to_path_buf()))
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

/// Fills the file system of `dir` with a file of zeros until it is full.
fn fill(dir: &Path) {
    use std::io::Write;
    let mut f = std::fs::File::create(dir.join("filler")).unwrap();
    let block = vec![0u8; 4096];
    while f.write_all(&block).is_ok() {}
    let _ = f.sync_all();
}

fn full_tmpfs_keeps_previous_files() {
    let dir = tempfile::tempdir().unwrap();
    // The size of this run's checkpoint, from a run on the ordinary disk.
    let probe = dir.path().join("probe");
    run_ok(&train_args(&probe, 2, 2, false));
    let ckpt_len = std::fs::metadata(probe.join("model.ckpt")).unwrap().len();
    // Room for one checkpoint and a half: the second cannot be written beside the first.
    let mnt = dir.path().join("mnt");
    std::fs::create_dir(&mnt).unwrap();
    let _tmpfs = Tmpfs::mount(&mnt, ckpt_len * 3 / 2).unwrap();
    let out = mnt.join("run");
    let ckpt = out.join("model.ckpt");
    let m = run_measured(msth().args(train_args(&out, 6, 2, false)), HANG);
    println!("checkpoint on a full tmpfs: {}", m.stderr.trim());
    assert_ne!(m.code, Some(0));
    for words in [
        "writing the checkpoint of step 4 failed",
        "No space left on device",
        "(step 2) is unchanged",
    ] {
        assert!(
            m.stderr.contains(words),
            "the message does not say `{words}`: {}",
            m.stderr
        );
    }
    assert_eq!(Checkpoint::load(&ckpt).unwrap().header.step, 2);
    assert!(temporaries(&out).is_empty(), "{:?}", temporaries(&out));

    // Export onto the full file system: a first file fits, then the disk is filled.
    let msth_file = out.join("scene.msth");
    let export = |quant: &str| -> Vec<String> {
        [
            "export",
            ckpt.to_str().unwrap(),
            "-o",
            msth_file.to_str().unwrap(),
            "--quant",
            quant,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    run_ok(&export("q4"));
    let first = std::fs::read(&msth_file).unwrap();
    fill(&out);
    let m = run_measured(msth().args(export("q5")), HANG);
    println!("export on a full tmpfs: {}", m.stderr.trim());
    assert_ne!(m.code, Some(0));
    for words in [
        "failed (the file there before is unchanged)",
        "No space left on device",
    ] {
        assert!(
            m.stderr.contains(words),
            "the message does not say `{words}`: {}",
            m.stderr
        );
    }
    assert!(
        std::fs::read(&msth_file).unwrap() == first,
        "the previous export changed"
    );
    assert!(temporaries(&out).is_empty(), "{:?}", temporaries(&out));
}
