//! Helpers shared by the end-to-end tests in `tests/tests/`: where the shared datasets are and the
//! needs of the tests that use outside things (for `msth-testkit`'s harness, see
//! testkit/src/lib.rs), small built-in scenes, and running the `msth` command in-process.

use std::path::{Path, PathBuf};

use msth_core::config::Preset;
use msth_dataset::Dataset;
use msth_testkit::Need;
use msth_trainer::synth::{generate, SynthConfig};
use msth_trainer::train::TrainSettings;

/// `../shared/data/NAME` next to the repository (whether or not it exists: tests that read it
/// declare [`msth_testkit::Need::shared_data`]`(NAME)`).
pub fn shared_dataset(name: &str) -> PathBuf {
    msth_testkit::shared_data(name)
}

/// A GPU adapter of any kind (software ones included), as `msth play --gpu` takes it. "No
/// adapter" is a missing need (`MSTH_REQUIRE_GPU=1` makes it a failure); any other error opening
/// one panics, failing the test.
pub fn gpu_need() -> Need {
    use msth_player::gpu::{AdapterPolicy, GpuContext, GpuError};
    Need::new("gpu", || match GpuContext::open(AdapterPolicy::any()) {
        Ok(_) => Ok(()),
        Err(e @ GpuError::NoAdapter(_)) => Err(e.to_string()),
        Err(e) => panic!("{e}"),
    })
}

/// A small version of the built-in scene that trains in seconds.
pub fn tiny_scene() -> (SynthConfig, Dataset) {
    let cfg = SynthConfig {
        width: 48,
        height: 36,
        num_frames: 6,
        num_train_cams: 6,
        supersample: 2,
        ..SynthConfig::default()
    };
    let d = generate(&cfg);
    (cfg, d)
}

/// The fast preset cut down to a short run for tests: `iters` steps of 512 rays, proposal
/// annealing over the first quarter (rounded up), no intermediate checkpoints.
pub fn short_run(data: &Dataset, iters: usize) -> TrainSettings {
    let mut s = TrainSettings::for_preset(Preset::Fast, data);
    s.iters = iters;
    s.batch_rays = 512;
    s.anneal_steps = iters.div_ceil(4).max(1);
    s.checkpoint_every = 0;
    s
}

/// The settings of the codec fixture (`tests/fixtures/v1.*`): small tables, trained long enough
/// (200 steps of 1024 rays) for the moving objects to show up as dynamic pixels.
pub fn fixture_run(data: &Dataset) -> TrainSettings {
    let mut s = short_run(data, 200);
    for enc in [&mut s.model.field.encoding, &mut s.model.proposal.encoding] {
        enc.resize(6, 12, 96.0, 16);
    }
    s.model.proposal.encoding.grid3.log2_table_size = 10;
    s.model.proposal.encoding.grid4.log2_table_size = 10;
    s.batch_rays = 1024;
    s
}

/// Runs `msth ARGS...` in-process.
pub fn msth(args: &[&str]) -> anyhow_like::Result {
    let mut v = vec!["msth"];
    v.extend_from_slice(args);
    msth_cli::run(v).map_err(|e| format!("{e:#}"))
}

/// `msth train DATA --out OUT EXTRA...` in-process.
pub fn train_cmd(data: &Path, out: &Path, extra: &[&str]) -> anyhow_like::Result {
    msth_with(&["train", path_str(data), "--out", path_str(out)], extra)
}

/// `msth export CKPT -o OUT EXTRA...` in-process.
pub fn export_cmd(ckpt: &Path, out: &Path, extra: &[&str]) -> anyhow_like::Result {
    msth_with(&["export", path_str(ckpt), "-o", path_str(out)], extra)
}

/// `msth synth --out OUT EXTRA...` in-process.
pub fn synth_cmd(out: &Path, extra: &[&str]) -> anyhow_like::Result {
    msth_with(&["synth", "--out", path_str(out)], extra)
}

/// `msth render CKPT -o PNG EXTRA...` in-process.
pub fn render_cmd(ckpt: &Path, png: &Path, extra: &[&str]) -> anyhow_like::Result {
    msth_with(&["render", path_str(ckpt), "-o", path_str(png)], extra)
}

/// `msth play SRC --path 0 --out OUT --no-video --quiet EXTRA...` with a JSON report next to
/// `out` (`OUT.json`); returns the report. A failed command panics, naming `src`.
pub fn play_report(src: &str, out: &Path, extra: &[&str]) -> serde_json::Value {
    let report = out.with_extension("json");
    let head = ["play", src, "--path", "0", "--out", path_str(out)];
    let tail = ["--no-video", "--quiet", "--report", path_str(&report)];
    msth_with(&[&head[..], &tail[..]].concat(), extra)
        .unwrap_or_else(|e| panic!("msth play {src}: {e}"));
    read_json(&report)
}

/// A JSON file the commands wrote (a report, `metrics.json`), parsed.
pub fn read_json(path: &Path) -> serde_json::Value {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_slice(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// `msth HEAD... EXTRA...` in-process.
fn msth_with(head: &[&str], extra: &[&str]) -> anyhow_like::Result {
    msth(&[head, extra].concat())
}

/// A path as the `&str` argument of a command (test paths are UTF-8).
fn path_str(p: &Path) -> &str {
    p.to_str().expect("test paths are UTF-8")
}

pub mod anyhow_like {
    /// The error of a command as its displayed message.
    pub type Result = std::result::Result<(), String>;
}

/// An X server of our own (`Xvfb`) on a free display number, stopped on drop: what the window
/// tests (`tests/tests/view_window.rs`) draw on. Its software rendering needs no GPU; the window's
/// Vulkan driver is Mesa's lavapipe where there is no GPU.
pub struct Xvfb {
    child: std::process::Child,
    /// `:N`, the value of `DISPLAY` for it.
    pub display: String,
}

impl Xvfb {
    /// Starts `Xvfb :N -screen 0 WxHx24` on the first free `N` from 90 and waits (up to 10 s)
    /// for its socket. A number whose lock file names a process that is gone is free: a server
    /// killed without its clean-up (as [`Drop`] kills ours) leaves its lock file and socket
    /// behind, and 40 such runs would otherwise take every number.
    pub fn start(width: u32, height: u32) -> Result<Xvfb, String> {
        for n in 90..130 {
            let socket = PathBuf::from(format!("/tmp/.X11-unix/X{n}"));
            let lock = PathBuf::from(format!("/tmp/.X{n}-lock"));
            if lock.exists() {
                if !stale_x_lock(&lock) || std::fs::remove_file(&lock).is_err() {
                    continue;
                }
                let _ = std::fs::remove_file(&socket);
            }
            if socket.exists() {
                continue;
            }
            let display = format!(":{n}");
            let mut child = std::process::Command::new("Xvfb")
                .args([
                    display.as_str(),
                    "-screen",
                    "0",
                    &format!("{width}x{height}x24"),
                    "-nolisten",
                    "tcp",
                ])
                .stdin(std::process::Stdio::null())
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::null())
                .spawn()
                .map_err(|e| format!("`Xvfb` cannot run: {e}"))?;
            let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
            while std::time::Instant::now() < deadline {
                if let Ok(Some(status)) = child.try_wait() {
                    if lock.exists() {
                        break; // another server took the number meanwhile
                    }
                    return Err(format!("Xvfb {display} exited at once ({status})"));
                }
                if socket.exists() {
                    return Ok(Xvfb { child, display });
                }
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            let _ = child.kill();
            let _ = child.wait();
        }
        Err("no free X display number in :90..:130, or Xvfb never came up".into())
    }
}

/// Whether the X server lock file `lock` names a process that no longer runs (its PID, as
/// text). An unreadable lock is not stale: its number is left alone.
fn stale_x_lock(lock: &Path) -> bool {
    std::fs::read_to_string(lock)
        .ok()
        .and_then(|s| s.trim().parse::<u32>().ok())
        .is_some_and(|pid| !Path::new(&format!("/proc/{pid}")).exists())
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A display to open windows on: `Xvfb` starts (the `xvfb` package). "Cannot run it" is a missing
/// need (`MSTH_REQUIRE_DISPLAY=1` makes it a failure).
/// `node` with the page's npm packages (`npm ci --prefix web`): what the page's decoder needs to
/// run outside a browser (`web/tests/*.mjs`).
pub fn web_decoder_need() -> Need {
    Need::new("browser", || {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let node_ok = std::process::Command::new("node")
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success());
        if !node_ok {
            Err("`node` is not installed".into())
        } else if !root.join("web/node_modules/fzstd/package.json").is_file() {
            Err("web/node_modules/fzstd is missing (run `npm ci --prefix web`)".into())
        } else {
            Ok(())
        }
    })
}

pub fn display_need() -> Need {
    Need::new("display", || Xvfb::start(64, 64).map(|_| ()))
}

/// `tests/fixtures/v2.msth` with a mask that splits the scene, encoded again as the fixture was
/// (the file's bytes): the fixture's mask leaves every vertex to the 4D grid, so here the mask
/// holds the vertices with the highest index along the grid's first axis dynamic (a quarter of
/// them) and makes the others static, so that a play-time volume baked from it has both parts.
pub fn split_mask_fixture() -> Vec<u8> {
    use msth_codec::decode_all;
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/v2.msth");
    let d = decode_all(&std::fs::read(path).unwrap()).unwrap();
    let mut params = d.params.clone();
    let (grid, range) = d
        .layout
        .field
        .encoding
        .mask
        .clone()
        .expect("the fixture has a mask");
    for (i, m) in params[range].iter_mut().enumerate() {
        let first_axis = i % grid.res;
        *m = if 4 * first_axis >= 3 * grid.res {
            -20.0
        } else {
            20.0
        };
    }
    reencode(&d, &params, &d.cameras)
}

/// `d` encoded again with other parameters or cameras, under the export settings it was
/// written with.
pub fn reencode(
    d: &msth_codec::DecodedModel,
    params: &[f32],
    cameras: &[msth_core::Camera],
) -> Vec<u8> {
    let opts = msth_codec::EncodeOptions {
        quant: d.metadata.quant,
        chunk_frames: d.metadata.chunk_frames as usize,
        dynamic_threshold: d.metadata.dynamic_threshold,
        frame_rate: d.metadata.frame_rate,
        occupancy_resolution: d.occupancy.as_ref().map_or(64, |g| g.resolution),
        ..Default::default()
    };
    msth_codec::encode(&d.config, params, cameras, &opts)
        .unwrap()
        .0
}

#[cfg(test)]
mod x_lock_tests {
    use super::stale_x_lock;

    #[test]
    fn a_lock_of_a_process_that_is_gone_is_stale() {
        let dir = tempfile::tempdir().unwrap();
        let lock = dir.path().join(".X99-lock");
        std::fs::write(&lock, format!("{:>10}\n", std::process::id())).unwrap();
        assert!(!stale_x_lock(&lock), "this process runs");
        std::fs::write(&lock, "999999999\n").unwrap();
        assert!(stale_x_lock(&lock), "no such process");
        std::fs::write(&lock, "garbage").unwrap();
        assert!(!stale_x_lock(&lock), "unreadable: left alone");
        assert!(!stale_x_lock(&dir.path().join("missing")));
    }
}
