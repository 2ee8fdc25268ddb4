//! The test harness of the test binaries whose tests need something from outside the process: a
//! GPU adapter, Chromium and the web player's npm packages, `node`, `ffmpeg`, `colmap`, `curl`, a font,
//! the shared datasets in `../shared/data`. When such a need is missing, the tests that have it
//! are reported by cargo as **ignored, with the reason** on their result line, and counted in the
//! binary's `test result: N passed; M failed; K ignored` line (which `.ci/run` and
//! `tools/test.sh` sum into `tests: N passed, N failed, N skipped`). They never count as passed.
//!
//! # Why a custom harness
//!
//! Rust's built-in test harness decides "ignored" at compile time (`#[ignore]`) only: a test
//! that finds no GPU at run time can pass or fail, not skip. A `build.rs` probe feeding
//! `#[cfg_attr(.., ignore)]` goes stale (the probe ran when the binary was built, not where it
//! runs, and cargo does not rebuild when a driver is installed). So these binaries use
//! [`libtest_mimic`] (`harness = false`), which prints the same result lines and summary line
//! as the built-in harness, understands the same arguments (filters, `--ignored`,
//! `--include-ignored`, `--list`, `--test-threads`, `--exact`), catches panics as failures, and
//! lets a test end as "ignored" at run time with a reason. Needs are probed when a test that
//! has them runs (once per binary), not when the binary is built.
//!
//! # Making a skip a failure
//!
//! `MSTH_REQUIRE_<KIND>=1` (the kind upper-cased: `MSTH_REQUIRE_GPU`, `MSTH_REQUIRE_BROWSER`,
//! `MSTH_REQUIRE_NODE`, `MSTH_REQUIRE_FFMPEG`, `MSTH_REQUIRE_COLMAP`, `MSTH_REQUIRE_CURL`,
//! `MSTH_REQUIRE_FONT`, `MSTH_REQUIRE_DATA`) turns a missing need of that kind into a failure, and
//! `MSTH_REQUIRE_ALL=1` does it for every kind (except those set to `0`). `tools/test.sh` (and
//! so CI) sets `MSTH_REQUIRE_ALL=1` after installing everything.
//!
//! # Use in a new test binary
//!
//! In the crate's `Cargo.toml` (with `msth-testkit` as a dev-dependency):
//!
//! ```toml
//! [[test]]
//! name = "videos"
//! harness = false
//! ```
//!
//! and in `tests/videos.rs`, a `main` that lists every test of the file (`#[test]` functions
//! are not compiled in a `harness = false` binary; [`Tests::new`] adds a failing test when the
//! file still has one):
//!
//! ```no_run
//! use msth_testkit::{Need, Skip, Tests};
//!
//! fn decodes_a_video() { /* asserts; panics fail the test */ }
//! fn parses_flags() {}
//! fn only_on_lavapipe() -> Result<(), Skip> {
//!     // A test may also decide at run time that it does not apply here.
//!     Err(Skip::new("the adapter is not lavapipe"))
//! }
//!
//! fn main() -> std::process::ExitCode {
//!     let ffmpeg = Need::ffmpeg();
//!     let gpu = Need::new("gpu", || Err("no adapter".into()));
//!     Tests::new(file!())
//!         .test("parses_flags", parses_flags)
//!         .needs(&[&ffmpeg], "decodes_a_video", decodes_a_video)
//!         .needs(&[&gpu], "only_on_lavapipe", only_on_lavapipe)
//!         .run()
//! }
//! ```
//!
//! Unlike the built-in harness, this one does not capture what tests print (it shows up as the
//! tests run); failures show their panic message as usual.

pub mod curl;

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::sync::{Arc, OnceLock};

use libtest_mimic::{Arguments, Completion, Failed, Trial};

/// Something a test needs from outside the process, probed once per test binary when the first
/// test that needs it runs. Cheap to clone (the probe's result is shared).
#[derive(Clone)]
pub struct Need(Arc<NeedInner>);

type Probe = Box<dyn Fn() -> Result<(), String> + Send + Sync>;

struct NeedInner {
    kind: String,
    probe: Probe,
    found: OnceLock<Result<(), String>>,
}

impl Need {
    /// A need of `kind` (lower case, one word: it names the variable `MSTH_REQUIRE_<KIND>`).
    /// `probe` returns `Err(why)` when the need is missing; a panic in it fails the test (use
    /// that for errors that are not "missing", e.g. a GPU that exists but fails to start).
    pub fn new(kind: &str, probe: impl Fn() -> Result<(), String> + Send + Sync + 'static) -> Need {
        Need(Arc::new(NeedInner {
            kind: kind.to_string(),
            probe: Box::new(probe),
            found: OnceLock::new(),
        }))
    }

    /// A program that must run: `program args...` exits with status 0. The program is the value
    /// of the environment variable `program_var` when that is given and set (e.g. `MSTH_FFMPEG`).
    pub fn program(kind: &str, program_var: Option<&str>, program: &str, args: &[&str]) -> Need {
        let (var, default) = (program_var.map(str::to_string), program.to_string());
        let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
        Need::new(kind, move || {
            let program = var
                .as_ref()
                .and_then(std::env::var_os)
                .map(PathBuf::from)
                .unwrap_or_else(|| PathBuf::from(&default));
            runs(&program, &args)
        })
    }

    /// `ffmpeg` and `ffprobe` (`MSTH_FFMPEG`, `MSTH_FFPROBE`, else on `PATH`), as the DyNeRF
    /// loader and `msth synth` run them.
    pub fn ffmpeg() -> Need {
        let ffmpeg = Need::program("ffmpeg", Some("MSTH_FFMPEG"), "ffmpeg", &["-version"]);
        let ffprobe = Need::program("ffmpeg", Some("MSTH_FFPROBE"), "ffprobe", &["-version"]);
        Need::new("ffmpeg", move || {
            ffmpeg.check()?;
            ffprobe.check()
        })
    }

    /// `colmap` (`MSTH_COLMAP`, else on `PATH`).
    pub fn colmap() -> Need {
        Need::program("colmap", Some("MSTH_COLMAP"), "colmap", &["help"])
    }

    /// `../shared/data/REL` beside the repository (a folder or a file), see [`shared_data`].
    pub fn shared_data(rel: &str) -> Need {
        let path = shared_data(rel);
        Need::new("data", move || {
            if path.exists() {
                Ok(())
            } else {
                Err(format!("{} is not present", path.display()))
            }
        })
    }

    /// The kind, as given to [`Need::new`].
    pub fn kind(&self) -> &str {
        &self.0.kind
    }

    /// `MSTH_REQUIRE_<KIND>`.
    pub fn require_var(&self) -> String {
        format!("MSTH_REQUIRE_{}", self.0.kind.to_uppercase())
    }

    /// Whether a missing need fails: `MSTH_REQUIRE_<KIND>=1`, or `MSTH_REQUIRE_ALL=1` unless
    /// `MSTH_REQUIRE_<KIND>=0`.
    pub fn required(&self) -> bool {
        let var = |k: &str| std::env::var(k).ok();
        match var(&self.require_var()).as_deref() {
            Some("1") => true,
            Some("0") => false,
            _ => var("MSTH_REQUIRE_ALL").as_deref() == Some("1"),
        }
    }

    /// `Ok` when present, else why not (probed on the first call only).
    pub fn check(&self) -> Result<(), String> {
        self.0.found.get_or_init(|| (self.0.probe)()).clone()
    }
}

/// Runs `program args...` with no output; `Ok` when it exits with status 0.
fn runs(program: &Path, args: &[String]) -> Result<(), String> {
    let cmd = || format!("`{} {}`", program.display(), args.join(" "));
    match Command::new(program)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
    {
        Ok(s) if s.success() => Ok(()),
        Ok(s) => Err(format!("{} exited with {s}", cmd())),
        Err(e) => Err(format!("{} cannot run: {e}", cmd())),
    }
}

/// The files of `dir` (not its subfolders) whose extension is `ext` (`"msth"`, `"png"`), sorted
/// by path. A folder that cannot be read panics, failing the test.
pub fn files_with_extension(dir: &Path, ext: &str) -> Vec<PathBuf> {
    let entries =
        std::fs::read_dir(dir).unwrap_or_else(|e| panic!("reading {}: {e}", dir.display()));
    let mut files: Vec<PathBuf> = entries
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file() && p.extension().is_some_and(|x| x == ext))
        .collect();
    files.sort();
    files
}

/// `../shared/data/REL` beside the repository root (the shared datasets of CI and development
/// machines); the path whether or not it exists.
pub fn shared_data(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(rel)
}

/// A test that decided at run time that it does not apply here (reported as ignored, with the
/// reason; not subject to `MSTH_REQUIRE_*`).
#[derive(Debug)]
pub struct Skip(String);

impl Skip {
    pub fn new(reason: impl Into<String>) -> Skip {
        Skip(reason.into())
    }
}

/// What a test function returns: `()` (it ran; a panic fails it) or `Result<(), Skip>`.
pub trait TestOutcome {
    fn completion(self) -> Completion;
}

impl TestOutcome for () {
    fn completion(self) -> Completion {
        Completion::Completed
    }
}

impl TestOutcome for Result<(), Skip> {
    fn completion(self) -> Completion {
        match self {
            Ok(()) => Completion::Completed,
            Err(Skip(why)) => Completion::ignored_with(why),
        }
    }
}

/// Runs `f` when every one of `needs` is present; else ignores it with the reason, or fails
/// when that need is required.
fn run_with_needs<R: TestOutcome>(
    needs: &[Need],
    f: impl FnOnce() -> R,
) -> Result<Completion, Failed> {
    for need in needs {
        if let Err(why) = need.check() {
            return if need.required() {
                Err(Failed::from(format!(
                    "no {}: {why} (required by {}=1 or MSTH_REQUIRE_ALL=1)",
                    need.kind(),
                    need.require_var()
                )))
            } else {
                Ok(Completion::ignored_with(format!(
                    "no {}: {why}; {}=1 makes this a failure",
                    need.kind(),
                    need.require_var()
                )))
            };
        }
    }
    Ok(f().completion())
}

/// The list of a binary's tests; [`Tests::run`] runs them as cargo's harness would.
pub struct Tests {
    trials: Vec<Trial>,
}

impl Tests {
    /// The tests of the file `source` (pass `file!()`). A `#[test]` attribute left in that file
    /// adds a failing test, `unlisted_test_functions`: in a `harness = false` binary such a
    /// function would silently not run (e.g. one added on a branch that did not know).
    pub fn new(source: &str) -> Tests {
        // `file!()` is relative to the workspace root, the folder above this crate.
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("..")
            .join(source);
        let text = std::fs::read_to_string(&path).unwrap_or_default();
        let stray = text
            .lines()
            .enumerate()
            .filter(|(_, l)| l.trim_start().starts_with("#[test]"))
            .map(|(i, _)| format!("{}:{}", source, i + 1))
            .collect::<Vec<_>>();
        let mut t = Tests { trials: Vec::new() };
        if !stray.is_empty() {
            t.trials
                .push(Trial::test("unlisted_test_functions", move || {
                    Err(format!(
                    "#[test] functions do not run in this harness = false binary; list them in \
                     its main() instead: {}",
                    stray.join(", ")
                )
                    .into())
                }));
        }
        t
    }

    /// A test that always runs.
    pub fn test<R: TestOutcome>(self, name: &str, f: impl FnOnce() -> R + Send + 'static) -> Tests {
        self.needs(&[], name, f)
    }

    /// A test that runs when every one of `needs` is present. Otherwise it is ignored with the
    /// reason, or fails when that need is required (`MSTH_REQUIRE_*`).
    pub fn needs<R: TestOutcome>(
        mut self,
        needs: &[&Need],
        name: &str,
        f: impl FnOnce() -> R + Send + 'static,
    ) -> Tests {
        let needs: Vec<Need> = needs.iter().map(|&n| n.clone()).collect();
        self.trials.push(Trial::ignorable_test(name, move || {
            run_with_needs(&needs, f)
        }));
        self
    }

    /// A test that runs only when asked (`--ignored`, `--include-ignored`), like `#[ignore]`:
    /// measurements and other slow, informational runs.
    pub fn on_request<R: TestOutcome>(
        mut self,
        needs: &[&Need],
        name: &str,
        f: impl FnOnce() -> R + Send + 'static,
    ) -> Tests {
        self = self.needs(needs, name, f);
        let t = self.trials.pop().expect("just added");
        self.trials.push(t.with_ignored_flag(true));
        self
    }

    /// Runs the tests selected by the command line and prints cargo's result lines and summary.
    /// Returns the exit code (rather than exiting) so that what the tests' closures own (shared
    /// fixtures, temporary folders) is dropped first.
    pub fn run(self) -> ExitCode {
        libtest_mimic::run(&Arguments::from_args(), self.trials).exit_code()
    }
}

/// The settings of the property tests (`core/tests/stability.rs`, `codec/tests/stability.rs`):
/// `cases` cases from a fixed seed, so that a run is repeatable (`PROPTEST_CASES` and
/// `PROPTEST_RNG_SEED=n` explore more); a failure prints its minimal input and is kept as a named
/// test, not as a regression file. Behind the `proptest` feature.
#[cfg(feature = "proptest")]
pub fn proptest_config(cases: u32) -> proptest::test_runner::Config {
    let mut c = proptest::test_runner::Config {
        failure_persistence: None,
        ..proptest::test_runner::Config::default()
    };
    if std::env::var_os("PROPTEST_CASES").is_none() {
        c.cases = cases;
    }
    if std::env::var_os("PROPTEST_RNG_SEED").is_none() {
        c.rng_seed = proptest::test_runner::RngSeed::Fixed(0x5747_2026);
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    /// "ran", "ignored: REASON" or "failed: MESSAGE".
    fn outcome(needs: &[&Need], f: impl FnOnce() -> Result<(), Skip>) -> String {
        let needs: Vec<Need> = needs.iter().map(|&n| n.clone()).collect();
        match run_with_needs(&needs, f) {
            Ok(Completion::Completed) => "ran".into(),
            Ok(Completion::Ignored { reason }) => format!("ignored: {}", reason.unwrap()),
            Err(e) => format!("failed: {}", e.message().unwrap()),
        }
    }

    fn set(var: &str, value: &str) {
        // Each test uses its own kinds, so no two tests touch the same variable.
        std::env::set_var(var, value);
    }

    #[test]
    fn a_missing_need_is_ignored_or_with_its_variable_a_failure() {
        let missing = Need::new("testkitmissing", || Err("not here".into()));
        let present = Need::new("testkitpresent", || Ok(()));
        assert_eq!(outcome(&[], || Ok(())), "ran");
        assert_eq!(outcome(&[&present], || Ok(())), "ran");
        assert_eq!(
            outcome(&[], || Err(Skip::new("not lavapipe"))),
            "ignored: not lavapipe"
        );
        set("MSTH_REQUIRE_TESTKITMISSING", "0");
        assert_eq!(
            outcome(&[&present, &missing], || panic!("must not run")),
            "ignored: no testkitmissing: not here; MSTH_REQUIRE_TESTKITMISSING=1 makes this a failure"
        );
        set("MSTH_REQUIRE_TESTKITMISSING", "1");
        assert_eq!(
            outcome(&[&present, &missing], || panic!("must not run")),
            "failed: no testkitmissing: not here (required by MSTH_REQUIRE_TESTKITMISSING=1 or MSTH_REQUIRE_ALL=1)"
        );
    }

    #[test]
    fn require_all_is_overridden_per_kind() {
        let n = Need::new("testkitall", || Ok(()));
        set("MSTH_REQUIRE_TESTKITALL", "0");
        assert!(!n.required());
        set("MSTH_REQUIRE_TESTKITALL", "1");
        assert!(n.required());
    }

    #[test]
    fn the_probe_runs_once() {
        let count = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let c = Arc::clone(&count);
        let n = Need::new("testkitonce", move || {
            c.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            Err("absent".into())
        });
        for _ in 0..3 {
            assert_eq!(n.clone().check(), Err("absent".to_string()));
        }
        assert_eq!(count.load(std::sync::atomic::Ordering::SeqCst), 1);
    }

    #[test]
    fn programs_that_do_not_run_are_missing() {
        let n = Need::program("testkitprog", None, "/nonexistent/program", &["-version"]);
        let why = n.check().unwrap_err();
        assert!(why.contains("/nonexistent/program"), "{why}");
        assert!(Need::shared_data("no/such/file").check().is_err());
    }

    #[cfg(feature = "proptest")]
    #[test]
    fn proptest_config_is_seeded_and_keeps_no_files() {
        let c = proptest_config(17);
        assert!(c.failure_persistence.is_none());
        if std::env::var_os("PROPTEST_CASES").is_none() {
            assert_eq!(c.cases, 17);
        }
        if std::env::var_os("PROPTEST_RNG_SEED").is_none() {
            let fixed = proptest::test_runner::RngSeed::Fixed(0x5747_2026);
            assert_eq!(c.rng_seed, fixed);
        }
    }

    #[test]
    fn files_with_extension_lists_matching_files_sorted() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["b.msth", "a.msth", "c.png", "d.msth.tmp", "noext"] {
            std::fs::write(dir.path().join(name), b"x").unwrap();
        }
        std::fs::create_dir(dir.path().join("sub.msth")).unwrap();
        let names: Vec<String> = files_with_extension(dir.path(), "msth")
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["a.msth", "b.msth"]);
        assert_eq!(files_with_extension(dir.path(), "png").len(), 1);
    }

    #[test]
    fn a_test_attribute_left_in_the_file_is_a_failing_test() {
        let path = std::env::temp_dir().join(format!("testkit-{}.rs", std::process::id()));
        std::fs::write(&path, "fn main() {}\n\n#[test]\nfn forgotten() {}\n").unwrap();
        let t = Tests::new(path.to_str().unwrap()).test("listed", || ());
        std::fs::remove_file(&path).unwrap();
        let names: Vec<&str> = t.trials.iter().map(|t| t.name()).collect();
        assert_eq!(names, ["unlisted_test_functions", "listed"]);
        // A file without one adds nothing.
        assert!(Tests::new("testkit/Cargo.toml").trials.is_empty());
    }
}
