//! `msth view`'s render thread (viewer/src/worker.rs) driven without a window: the exact /
//! volume switch ([`RenderControls::volume`]) on the CPU renderer, with the fixture whose mask
//! splits the scene ([`msth_tests::split_mask_fixture`]). Turning the switch on starts a bake that
//! reports its progress while the thread goes on drawing; once it is done frames come from the
//! volume; off is the exact field again, and on again the volume without a second bake, also
//! after a renderer rebuilt for other samples per ray. A bake that cannot be planned is reported,
//! not a panic, and frames stay exact.
//!
//! Needs neither a display nor a GPU (the window's part of the switch is in view_window.rs).

use std::path::Path;
use std::sync::mpsc::{self, Receiver, Sender};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use msth_core::config::{PlaySamples, SampleLevel};
use msth_core::Camera;
use msth_player::policy::{Activity, Step};
use msth_player::volume::VolumeOptions;
use msth_player::{source, BackendChoice, Frame, HttpOptions, ModelStream};
use msth_viewer::worker::{self, Job, RenderControls, Reply, VolumeStatus, WorkerSetup};

/// What the thread said besides frames.
#[derive(Debug)]
enum Said {
    Renderer,
    Volume(VolumeStatus),
    Buffering,
}

struct Worker {
    jobs: Option<Sender<Job>>,
    replies: Receiver<Reply>,
    handle: Option<JoinHandle<()>>,
    camera: Camera,
    next: u64,
}

/// Longest wait for any reply: a hang guard, far above what anything here takes.
const HANG: Duration = Duration::from_secs(900);

impl Worker {
    fn start(file: &Path, volume: VolumeOptions) -> Worker {
        let src = source::open(file.to_str().unwrap(), &HttpOptions::default()).unwrap();
        let stream = Arc::new(ModelStream::open(src, &msth_codec::Limits::default()).unwrap());
        let meta = stream.index().metadata.clone();
        let setup = WorkerSetup {
            stream,
            base: worker::base_settings(meta.quant, None, true),
            backend: BackendChoice::Cpu,
            skip_empty: true,
            section_timeout: Duration::from_secs(60),
            limits: msth_codec::Limits::default(),
            volume,
        };
        let (job_tx, job_rx) = mpsc::channel();
        let (reply_tx, reply_rx) = mpsc::channel();
        let handle = std::thread::spawn(move || worker::run(setup, job_rx, reply_tx, || {}));
        Worker {
            jobs: Some(job_tx),
            replies: reply_rx,
            handle: Some(handle),
            camera: meta.cameras[0],
            next: 0,
        }
    }

    fn said(r: Reply) -> Result<Said, Box<Frame>> {
        match r {
            Reply::Renderer { .. } => Ok(Said::Renderer),
            Reply::Volume(s) => Ok(Said::Volume(s)),
            Reply::Buffering => Ok(Said::Buffering),
            Reply::Failed(e) => panic!("the render thread failed: {e}"),
            Reply::Frame { frame, .. } => Err(Box::new(frame)),
        }
    }

    fn recv(&self) -> Reply {
        self.replies
            .recv_timeout(HANG)
            .unwrap_or_else(|e| panic!("no reply from the render thread: {e}"))
    }

    /// Draws file camera 0 at `time` with `controls`; what the thread said on the way.
    fn frame(&mut self, controls: RenderControls, time: f32) -> (Frame, Vec<Said>) {
        let job = Job {
            id: self.next,
            camera: self.camera,
            full_camera: self.camera,
            time,
            controls,
            step: Step {
                divisor: 1,
                activity: Activity::Refining,
                incremental: true,
            },
            file_camera: Some(0),
        };
        self.next += 1;
        self.jobs.as_ref().unwrap().send(job).unwrap();
        let mut said = Vec::new();
        loop {
            match Self::said(self.recv()) {
                Ok(s) => said.push(s),
                Err(frame) => return (*frame, said),
            }
        }
    }

    /// Waits, sending nothing, until the bake has finished or failed (the thread looks at it
    /// while no job comes); every status said on the way, that one last.
    fn wait_bake(&mut self) -> Vec<VolumeStatus> {
        let mut seen = Vec::new();
        loop {
            match Self::said(self.recv()) {
                Ok(Said::Volume(s)) => {
                    let done = !matches!(s, VolumeStatus::Baking { .. });
                    seen.push(s);
                    if done {
                        return seen;
                    }
                }
                Ok(other) => panic!("unexpected while idle: {other:?}"),
                Err(_) => panic!("a frame while no job was sent"),
            }
        }
    }

    /// Closes the job channel (the window going away) and waits for the thread.
    fn close(mut self) {
        self.jobs = None;
        let h = self.handle.take().unwrap();
        assert!(h.join().is_ok(), "the render thread panicked");
    }
}

fn fixture_file(dir: &Path) -> std::path::PathBuf {
    let file = dir.join("split.msth");
    std::fs::write(&file, msth_tests::split_mask_fixture()).unwrap();
    file
}

fn controls(volume: bool) -> RenderControls {
    RenderControls {
        samples: PlaySamples::default(),
        volume,
    }
}

fn bakes(said: &[Said]) -> usize {
    said.iter()
        .filter(|s| matches!(s, Said::Volume(VolumeStatus::Baking { .. })))
        .count()
}

#[test]
fn the_volume_switch_bakes_in_the_background_and_switches_both_ways() {
    let dir = tempfile::tempdir().unwrap();
    let mut w = Worker::start(&fixture_file(dir.path()), VolumeOptions::default());
    let t = 0.37;

    let (exact, said) = w.frame(controls(false), t);
    assert!(
        !exact.stats.volume,
        "the switch starts off: the exact field"
    );
    assert!(
        said.iter().any(|s| matches!(s, Said::Renderer)),
        "a renderer is made: {said:?}"
    );
    assert_eq!(bakes(&said), 0, "nothing is baked while the switch is off");

    // On: the bake starts and the frame is drawn meanwhile (from the exact field unless the
    // bake happened to be done first).
    let (_, said) = w.frame(controls(true), t);
    assert!(bakes(&said) >= 1, "the bake started: {said:?}");
    let mut statuses: Vec<VolumeStatus> = said
        .into_iter()
        .filter_map(|s| match s {
            Said::Volume(v) => Some(v),
            _ => None,
        })
        .collect();
    if matches!(statuses.last(), Some(VolumeStatus::Baking { .. })) {
        statuses.extend(w.wait_bake());
    }
    let Some(VolumeStatus::Ready(info)) = statuses.pop() else {
        panic!("the bake did not finish: {statuses:?}");
    };
    let fractions: Vec<f64> = statuses
        .iter()
        .map(|s| match s {
            VolumeStatus::Baking { fraction } => *fraction,
            other => panic!("{other:?} before the end"),
        })
        .collect();
    println!(
        "volume {}^3, {} bricks ({} dynamic), {} bytes, baked in {:.2} s; progress said {:?}",
        info.resolution, info.bricks, info.dynamic_bricks, info.bytes, info.seconds, fractions
    );
    assert!(info.bricks > 0 && info.dynamic_bricks > 0 && info.bytes > 0);
    assert!(
        fractions.windows(2).all(|p| p[0] <= p[1])
            && fractions.iter().all(|f| (0.0..=1.0).contains(f)),
        "{fractions:?}"
    );

    // Baked: frames come from the volume, close to the exact field from the file's camera
    // (play_volume.rs measures 37 dB for this camera).
    let (vol, said) = w.frame(controls(true), t);
    assert!(vol.stats.volume, "the volume is ready: {said:?}");
    let p = vol.psnr_displayed(&exact);
    println!("volume frame against the exact frame: {p:.2} dB");
    assert!(p >= 30.0, "{p:.2} dB");

    // Off: the exact field at once, the same frame as before.
    let (back, said) = w.frame(controls(false), t);
    assert!(!back.stats.volume);
    assert_eq!(bakes(&said), 0);
    assert_eq!(back.to_rgb8(), exact.to_rgb8(), "the exact frame again");

    // On again: the volume kept, no second bake.
    let (again, said) = w.frame(controls(true), t);
    assert!(again.stats.volume && bakes(&said) == 0, "{said:?}");
    assert_eq!(again.to_rgb8(), vol.to_rgb8());

    // Other samples per ray rebuild the renderer; the volume goes with it (a dynamic time: its
    // slice is baked for the frame).
    let fast = RenderControls {
        samples: PlaySamples::Level(SampleLevel::ALL[1]),
        volume: true,
    };
    let (f, said) = w.frame(fast, 0.7);
    assert!(
        said.iter().any(|s| matches!(s, Said::Renderer)),
        "rebuilt: {said:?}"
    );
    assert!(f.stats.volume && bakes(&said) == 0, "{said:?}");
    let (e, _) = w.frame(
        RenderControls {
            volume: false,
            ..fast
        },
        0.7,
    );
    assert!(!e.stats.volume);
    w.close();
}

#[test]
fn a_volume_that_cannot_be_planned_leaves_exact_frames() {
    let dir = tempfile::tempdir().unwrap();
    let tiny = VolumeOptions {
        budget: Some(1),
        ..Default::default()
    };
    let mut w = Worker::start(&fixture_file(dir.path()), tiny);
    let failed = |said: &[Said]| {
        said.iter()
            .find_map(|s| match s {
                Said::Volume(VolumeStatus::Failed(e)) => Some(e.clone()),
                _ => None,
            })
            .unwrap_or_else(|| panic!("no failure said: {said:?}"))
    };
    let (f, said) = w.frame(controls(true), 0.5);
    let e = failed(&said);
    println!("{e}");
    assert!(e.contains("budget"), "{e}");
    assert!(!f.stats.volume);
    // Still on (a job sent before the window heard): the same answer, no new bake.
    let (f, said) = w.frame(controls(true), 0.5);
    assert!(!f.stats.volume && bakes(&said) == 0);
    assert_eq!(failed(&said), e);
    // Off, then on again: it tries again (and fails the same way).
    let (f, said) = w.frame(controls(false), 0.5);
    assert!(!f.stats.volume && said.is_empty(), "{said:?}");
    let (_, said) = w.frame(controls(true), 0.5);
    assert_eq!(failed(&said), e);
    w.close();
}

#[test]
fn closing_the_window_while_it_bakes_ends_the_thread() {
    let dir = tempfile::tempdir().unwrap();
    let mut w = Worker::start(&fixture_file(dir.path()), VolumeOptions::default());
    let (_, said) = w.frame(controls(true), 0.0);
    assert!(bakes(&said) >= 1, "{said:?}");
    w.close();
}
