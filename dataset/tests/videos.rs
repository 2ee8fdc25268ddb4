//! The DyNeRF loader on real videos: encoded with the real `ffmpeg`, decoded exactly (FFV1) and
//! through the frame cache, and broken, mismatched or missing videos named in the error.
//!
//! These tests need `ffmpeg` and `ffprobe` (`MSTH_FFMPEG`, `MSTH_FFPROBE`, else on `PATH`);
//! without them they are reported as ignored with the reason, unless `MSTH_REQUIRE_FFMPEG=1`
//! (then they fail). This binary runs on `msth-testkit`'s harness (`harness = false`): [`main`]
//! lists its tests. The synthetic rig and frames are those of the loader's unit tests.

use std::path::Path;

use glam::Vec3;
use msth_core::Camera;
use msth_dataset::cache::{FrameStorage, Stored};
use msth_dataset::dynerf::{load, load_with_rig, write_poses_bounds, DynerfOptions, Normalization};
use msth_dataset::video::{self, Tools, VideoInfo};
use msth_testkit::{Need, Tests};

fn main() -> std::process::ExitCode {
    let ffmpeg = Need::ffmpeg();
    Tests::new(file!())
        .needs(
            &[&ffmpeg],
            "videos_decode_exactly_and_go_through_the_cache",
            videos_decode_exactly_and_go_through_the_cache,
        )
        .needs(
            &[&ffmpeg],
            "broken_videos_are_named",
            broken_videos_are_named,
        )
        .run()
}

/// A forward-facing arc of `n` cameras looking at a point in front of them.
fn rig(n: usize, w: u32, h: u32) -> Vec<Camera> {
    let target = Vec3::new(0.0, 0.3, 0.9);
    (0..n)
        .map(|i| {
            let a = (i as f32 / (n - 1).max(1) as f32 - 0.5) * 1.2;
            let eye = target + Vec3::new(4.0 * a.sin(), -4.0 * a.cos(), 0.5 + 0.1 * i as f32);
            Camera::look_at(w, h, 0.9, eye, target, Vec3::Z)
        })
        .collect()
}

/// The RGB pixels of camera `c`, frame `j`.
fn frame(c: usize, j: usize, w: u32, h: u32) -> Vec<u8> {
    (0..(w * h) as usize * 3)
        .map(|k| ((c * 60 + j * 17 + (k / 3) * 5 + (k % 3) * 40) % 256) as u8)
        .collect()
}

fn write_npy(dir: &Path, cams: &[Camera]) {
    let rows: Vec<(Camera, f64, f64)> = cams.iter().map(|c| (*c, 2.0, 9.0)).collect();
    write_poses_bounds(&dir.join("poses_bounds.npy"), &rows).unwrap();
}

fn raw_opts() -> DynerfOptions {
    DynerfOptions {
        normalization: Normalization::None,
        ..Default::default()
    }
}

fn expect_err(dir: &Path, opts: &DynerfOptions, needles: &[&str]) {
    let e = load(dir, opts).unwrap_err().to_string();
    for n in needles {
        assert!(e.contains(n), "error `{e}` should mention `{n}`");
    }
}

fn videos_decode_exactly_and_go_through_the_cache() {
    let tools = Tools::default();
    let dir = tempfile::tempdir().unwrap();
    let (w, h, n) = (16u32, 12u32, 5usize);
    let cams = rig(3, w, h);
    for c in 0..3 {
        let frames: Vec<Vec<u8>> = (0..n).map(|j| frame(c, j, w, h)).collect();
        video::encode(
            &tools,
            &dir.path().join(format!("cam{c:02}.mkv")),
            w,
            h,
            &frames,
            0,
        )
        .unwrap();
    }
    write_npy(dir.path(), &cams);
    let mem = load(dir.path(), &raw_opts()).unwrap();
    assert_eq!((mem.train.len(), mem.test.len()), (2 * n, n));
    for v in mem.train.iter().chain(&mem.test) {
        let j = (v.time * (n - 1) as f32).round() as usize;
        assert_eq!(v.image.data, frame(v.camera_id.unwrap(), j, w, h));
        assert!(!v.image.data.is_mapped());
    }
    // Through a cache file: the same pixels, mapped; reused on the second load.
    let cache_dir = tempfile::tempdir().unwrap();
    let path = cache_dir.path().join("c.frames");
    let opts = DynerfOptions {
        storage: FrameStorage::Disk(path.clone()),
        ..raw_opts()
    };
    let (disk, _, stored) = load_with_rig(dir.path(), &opts).unwrap();
    assert!(matches!(stored, Stored::Cache { built: true, .. }));
    for (a, b) in mem
        .train
        .iter()
        .chain(&mem.test)
        .zip(disk.train.iter().chain(&disk.test))
    {
        assert!(b.image.data.is_mapped());
        assert_eq!(a.image, b.image);
        assert_eq!(a.time, b.time);
    }
    let (_, _, again) = load_with_rig(dir.path(), &opts).unwrap();
    assert!(matches!(again, Stored::Cache { built: false, .. }));
    // A changed source rebuilds it.
    let frames: Vec<Vec<u8>> = (0..n).map(|j| frame(2, j + 1, w, h)).collect();
    std::thread::sleep(std::time::Duration::from_millis(20));
    video::encode(&tools, &dir.path().join("cam02.mkv"), w, h, &frames, 0).unwrap();
    let (d3, _, re) = load_with_rig(dir.path(), &opts).unwrap();
    assert!(matches!(re, Stored::Cache { built: true, .. }));
    assert_eq!(d3.train[n].image.data, frame(2, 1, w, h));
    // H.264 (lossy) decodes close to the source.
    let frames: Vec<Vec<u8>> = (0..n).map(|j| frame(0, j, w, h)).collect();
    let mp4 = cache_dir.path().join("x.mp4");
    video::encode(&tools, &mp4, w, h, &frames, 12).unwrap();
    let info = video::probe(&tools, &mp4).unwrap();
    assert_eq!(
        info,
        VideoInfo {
            width: w,
            height: h,
            frames: n as u64
        }
    );
}

fn broken_videos_are_named() {
    let tools = Tools::default();
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (16u32, 12u32);
    let cams = rig(3, w, h);
    write_npy(dir.path(), &cams);
    for (c, n) in [(0, 4), (1, 4), (2, 3)] {
        let frames: Vec<Vec<u8>> = (0..n).map(|j| frame(c, j, w, h)).collect();
        video::encode(
            &tools,
            &dir.path().join(format!("cam{c:02}.mp4")),
            w,
            h,
            &frames,
            20,
        )
        .unwrap();
    }
    let o = raw_opts();
    // Mismatched frame counts.
    expect_err(dir.path(), &o, &["cam02.mp4", "3 frames", "cam00.mp4", "4"]);
    // A video that is not a video.
    std::fs::write(dir.path().join("cam02.mp4"), b"this is not a video at all").unwrap();
    expect_err(dir.path(), &o, &["cam02.mp4", "not a readable video"]);
    // A missing video.
    std::fs::remove_file(dir.path().join("cam02.mp4")).unwrap();
    expect_err(
        dir.path(),
        &o,
        &["3 rows", "2 camNN.mp4 videos", "cam00, cam01"],
    );
    // ffmpeg missing.
    let frames: Vec<Vec<u8>> = (0..4).map(|j| frame(2, j, w, h)).collect();
    video::encode(&tools, &dir.path().join("cam02.mp4"), w, h, &frames, 20).unwrap();
    assert!(load(dir.path(), &o).is_ok());
    let missing = DynerfOptions {
        tools: Tools {
            ffmpeg: "/nonexistent/ffmpeg".into(),
            ffprobe: "/nonexistent/ffprobe".into(),
        },
        ..raw_opts()
    };
    expect_err(
        dir.path(),
        &missing,
        &["cam00.mp4", "was not found", "install ffmpeg"],
    );
}
