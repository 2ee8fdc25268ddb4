//! Servers that misbehave: a loopback server with a mode for each fault (`support/fault_server.rs`:
//! an endless 200 body without `Content-Length`, a drip-fed body, a wrong `Content-Range` total, a
//! wrong range, a short body, a redirect loop, a file changed mid-stream, a stall; and two that
//! are no fault: correct ranges, and a server that ignores `Range`) against `msth play`, `msth
//! inspect --validate` (each as a child process, whose peak memory `wait4` reports) and the web
//! page (headless Chromium through `web/tests/faults.mjs`).
//!
//! Each must end as its mode says: playing (or valid) where the file's bytes are all there, else
//! an error naming what went wrong, before the deadlines set here (`--deadline 6 --stall-timeout
//! 2`; the page `?deadline=6&stall=2`) plus a margin, with a peak memory under 256 MiB. Time to
//! the error and peak memory are printed, one line per mode (`-- --nocapture` not needed: this
//! harness does not capture). Timing decides nothing here beyond "an error arrived": a hang
//! would be killed after [`HANG`] and fail.

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};
use std::time::Duration;

use msth_testkit::{Need, Tests};

#[path = "support/fault_server.rs"]
mod fault_server;
mod support;

use fault_server::{Fault, FaultServer};
use support::run_measured;

fn main() -> ExitCode {
    let browser = Need::new("browser", || browser_prerequisites().map(drop));
    Tests::new(file!())
        .test("play_ends_each_fault_in_time_and_memory", play_faults)
        .test("inspect_ends_each_fault_in_time_and_memory", inspect_faults)
        .needs(
            &[&browser],
            "the_page_ends_each_fault_in_time_and_memory",
            page_faults,
        )
        .run()
}

/// The deadlines given to every client here, seconds.
const DEADLINE: u64 = 6;
const STALL: u64 = 2;
/// A child still running after this is a hang (and fails the test).
const HANG: Duration = Duration::from_secs(90);
/// The peak memory every client must stay under.
const MAX_PEAK_MIB: f64 = 256.0;

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(path)
}

/// The served file: the codec fixture (136 KB, several chunks: the probe of 64 KiB holds its
/// prefix but not the whole file).
fn model() -> PathBuf {
    repo("tests/fixtures/v1.msth")
}

fn model_len() -> u64 {
    std::fs::metadata(model()).unwrap().len()
}

/// What a client must end with against `fault`: `None` plays (or validates), else an error
/// whose message contains each of the strings.
fn expected(fault: Fault) -> Option<Vec<String>> {
    let len = model_len();
    let v = |s: &[&str]| Some(s.iter().map(|s| s.to_string()).collect());
    match fault {
        Fault::Good | Fault::IgnoresRange | Fault::EndlessBody => None,
        Fault::DripFeed => v(&["deadline"]),
        Fault::WrongTotal => Some(vec![
            format!("the server says the file is {} bytes", len + 1000),
            format!("says {len}"),
        ]),
        Fault::WrongRange => v(&["got Content-Range"]),
        Fault::ShortBody => v(&["body ended after"]),
        Fault::RedirectLoop => v(&["redirect"]),
        Fault::ChangedMidStream => v(&["changed on the server"]),
        Fault::Stall => v(&["nothing received"]),
    }
}

/// One client against one mode, as printed and checked.
struct Outcome {
    fault: Fault,
    ok: bool,
    message: String,
    seconds: f64,
    peak_mib: f64,
}

fn check(client: &str, results: &[Outcome]) {
    println!("{client}: mode, result, time to the end, peak memory");
    let mut failures = Vec::new();
    for r in results {
        let last_line = r.message.lines().last().unwrap_or("").trim();
        println!(
            "  {:<19} {:<5} {:>6.2} s {:>7.1} MiB  {}",
            r.fault.name(),
            if r.ok { "ok" } else { "error" },
            r.seconds,
            r.peak_mib,
            last_line
        );
        match expected(r.fault) {
            None if !r.ok => failures.push(format!("{}: failed: {}", r.fault.name(), r.message)),
            Some(_) if r.ok => failures.push(format!("{}: no error", r.fault.name())),
            Some(words) => {
                for w in words {
                    if !r.message.contains(&w) {
                        failures.push(format!(
                            "{}: the message does not say `{w}`: {}",
                            r.fault.name(),
                            r.message
                        ));
                    }
                }
            }
            None => {}
        }
        if r.peak_mib >= MAX_PEAK_MIB {
            failures.push(format!(
                "{}: peak memory {:.1} MiB (at most {MAX_PEAK_MIB})",
                r.fault.name(),
                r.peak_mib
            ));
        }
    }
    assert!(failures.is_empty(), "{client}:\n{}", failures.join("\n"));
}

/// Runs `msth ARGS...` against every mode (one server each, in parallel pairs).
fn run_all(args: impl Fn(&str) -> Vec<String> + Sync) -> Vec<Outcome> {
    let run = |fault: Fault| {
        let server = FaultServer::start(&model(), "scene.msth", fault, None);
        let url = server.url("/models/scene.msth");
        let m = run_measured(
            Command::new(env!("CARGO_BIN_EXE_msth"))
                .args(args(&url))
                .env("RAYON_NUM_THREADS", "1"),
            HANG,
        );
        assert!(
            m.signal.is_none(),
            "{}: ended by signal {:?}\n{}",
            fault.name(),
            m.signal,
            m.stderr
        );
        Outcome {
            fault,
            ok: m.code == Some(0),
            message: m.stderr.trim().to_string(),
            seconds: m.seconds,
            peak_mib: m.peak_kib as f64 / 1024.0,
        }
    };
    // Two at a time: most modes wait on the network, not the CPU.
    let mut out = Vec::new();
    for pair in Fault::ALL.chunks(2) {
        let got: Vec<Outcome> = std::thread::scope(|s| {
            let handles: Vec<_> = pair.iter().map(|&f| s.spawn(move || run(f))).collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        out.extend(got);
    }
    out
}

fn network_flags() -> Vec<String> {
    [
        "--deadline".to_string(),
        DEADLINE.to_string(),
        "--stall-timeout".to_string(),
        STALL.to_string(),
    ]
    .to_vec()
}

fn play_faults() {
    let results = run_all(|url| {
        let mut a: Vec<String> = [
            "play", url, "--cpu", "--path", "0", "--size", "16x12", "--frames", "2", "--quiet",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        a.extend(network_flags());
        a
    });
    check("msth play", &results);
}

fn inspect_faults() {
    let results = run_all(|url| {
        let mut a: Vec<String> = ["inspect", url, "--validate"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        a.extend(network_flags());
        a
    });
    check("msth inspect --validate", &results);
}

fn find_chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("MSTH_CHROMIUM") {
        return Some(PathBuf::from(p)).filter(|p| p.is_file());
    }
    let fixed = Path::new("/usr/bin/chromium");
    if fixed.is_file() {
        return Some(fixed.to_path_buf());
    }
    std::env::split_paths(&std::env::var_os("PATH")?)
        .flat_map(|d| ["chromium", "chromium-browser"].map(|n| d.join(n)))
        .find(|p| p.is_file())
}

/// Chromium, `node` and the page's npm packages, or why not.
fn browser_prerequisites() -> Result<PathBuf, String> {
    let node = Command::new("node").arg("--version").output();
    if !node.map(|o| o.status.success()).unwrap_or(false) {
        return Err("`node` is not installed".into());
    }
    let chromium = find_chromium()
        .ok_or("Chromium is not installed (or MSTH_CHROMIUM names no file): install `chromium`")?;
    for dep in ["fzstd", "playwright-core"] {
        if !repo(&format!("web/node_modules/{dep}/package.json")).is_file() {
            return Err(format!(
                "web/node_modules/{dep} is missing (run `npm ci --prefix web`)"
            ));
        }
    }
    Ok(chromium)
}

fn page_faults() {
    let chromium = browser_prerequisites().unwrap();
    let servers: Vec<(Fault, FaultServer)> = Fault::ALL
        .iter()
        .map(|&f| {
            let s = FaultServer::start(&model(), "scene.msth", f, Some(repo("web")));
            (f, s)
        })
        .collect();
    let list: Vec<String> = servers
        .iter()
        .map(|(f, s)| {
            format!(
                "{}={}",
                f.name(),
                s.url(&format!(
                    "/?model=scene.msth&size=16x12&play=0&deadline={DEADLINE}&stall={STALL}"
                ))
            )
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("faults.json");
    let m = run_measured(
        Command::new("node")
            .current_dir(repo(""))
            .args(["web/tests/faults.mjs", "--out"])
            .arg(&out)
            .arg("--chromium")
            .arg(&chromium)
            .args(list),
        Duration::from_secs(600),
    );
    println!("{}{}", m.stdout, m.stderr);
    assert_eq!(
        m.code,
        Some(0),
        "web/tests/faults.mjs failed:\n{}",
        m.stderr
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&out).unwrap()).expect("faults.mjs writes JSON");
    let results: Vec<Outcome> = servers
        .iter()
        .map(|(f, _)| {
            let r = &json[f.name()];
            Outcome {
                fault: *f,
                ok: r["error"].is_null() && r["complete"].as_bool() == Some(true),
                message: r["error"]
                    .as_str()
                    .unwrap_or(if r["complete"].as_bool() == Some(true) {
                        "played"
                    } else {
                        "neither an error nor the whole file"
                    })
                    .to_string(),
                seconds: r["ms"].as_f64().unwrap_or(f64::NAN) / 1e3,
                peak_mib: r["peakMiB"].as_f64().unwrap_or(f64::INFINITY),
            }
        })
        .collect();
    check("the page (renderer process)", &results);
}
