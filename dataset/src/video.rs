//! The one wrapper of the `ffmpeg` / `ffprobe` programs (no linked codec libraries): video
//! decoding for the DyNeRF reader, and encoding for fixtures, generated datasets and the
//! player's MP4s.
//!
//! [`probe`] reads a video's size and frame count with `ffprobe`; [`decode`] streams its frames
//! as 8-bit RGB from `ffmpeg -f rawvideo -pix_fmt rgb24` one frame at a time, so memory stays at
//! one frame whatever the length. Missing programs, files that are not videos, and videos whose
//! decoded frames disagree with the probe are reported naming the file. [`encode`] writes raw
//! frames to a video; [`encode_png_sequence`] turns numbered PNGs into an H.264 MP4; [`runs`]
//! says whether a program starts.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use crate::DatasetError;

/// Largest accepted frame side.
const MAX_SIDE: u32 = 1 << 15;
/// Largest accepted frame count per video.
const MAX_FRAMES: u64 = 1 << 20;

/// The programs to run: `ffmpeg` and `ffprobe` from `PATH`, or the paths in the environment
/// variables `MSTH_FFMPEG` / `MSTH_FFPROBE`.
#[derive(Clone, Debug, PartialEq)]
pub struct Tools {
    pub ffmpeg: PathBuf,
    pub ffprobe: PathBuf,
}

impl Default for Tools {
    fn default() -> Self {
        let var = |k: &str, d: &str| {
            std::env::var_os(k)
                .map(PathBuf::from)
                .unwrap_or_else(|| PathBuf::from(d))
        };
        Tools {
            ffmpeg: var("MSTH_FFMPEG", "ffmpeg"),
            ffprobe: var("MSTH_FFPROBE", "ffprobe"),
        }
    }
}

impl Tools {
    /// Whether both programs can be started.
    pub fn available(&self) -> bool {
        runs(&self.ffmpeg) && runs(&self.ffprobe)
    }
}

/// Whether `program -version` starts and succeeds.
pub fn runs(program: &Path) -> bool {
    Command::new(program)
        .arg("-version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// Why [`encode_png_sequence`] made no video.
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    /// The program was not found.
    #[error("`{}` is not installed", program.display())]
    NotInstalled { program: PathBuf },
    /// The program could not be started for another reason.
    #[error("cannot run `{}`: {source}", program.display())]
    Spawn {
        program: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// It ran and failed: its exit status and the last lines of what it printed.
    #[error("{status} ({stderr_tail})")]
    Failed {
        status: std::process::ExitStatus,
        stderr_tail: String,
    },
}

/// Encodes the numbered PNGs of `pattern` (an ffmpeg pattern such as `dir/%04d.png`) into
/// `output`: H.264 (libx264), yuv420p, quality `crf`, `fps` frames per second, odd sizes padded
/// by one pixel (yuv420p needs even ones), index at the front (`+faststart`).
pub fn encode_png_sequence(
    ffmpeg: &Path,
    pattern: &Path,
    fps: f32,
    crf: u32,
    output: &Path,
) -> Result<(), EncodeError> {
    let result = Command::new(ffmpeg)
        .args(["-nostdin", "-hide_banner", "-loglevel", "error", "-y"])
        .arg("-framerate")
        .arg(format!("{fps}"))
        .arg("-i")
        .arg(pattern)
        .args(["-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf"])
        .arg(crf.to_string())
        .args([
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-movflags",
            "+faststart",
        ])
        .arg(output)
        .stdin(Stdio::null())
        .output()
        .map_err(|source| match source.kind() {
            std::io::ErrorKind::NotFound => EncodeError::NotInstalled {
                program: ffmpeg.to_path_buf(),
            },
            _ => EncodeError::Spawn {
                program: ffmpeg.to_path_buf(),
                source,
            },
        })?;
    if !result.status.success() {
        let err = String::from_utf8_lossy(&result.stderr);
        let tail: String = err.lines().rev().take(5).collect::<Vec<_>>().join(" | ");
        return Err(EncodeError::Failed {
            status: result.status,
            stderr_tail: tail,
        });
    }
    Ok(())
}

/// Size and length of a video's first video stream.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct VideoInfo {
    pub width: u32,
    pub height: u32,
    pub frames: u64,
}

fn bad(path: &Path, message: impl Into<String>) -> DatasetError {
    DatasetError::Invalid {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

fn spawn_error(tool: &Path, video: &Path, e: std::io::Error) -> DatasetError {
    if e.kind() == std::io::ErrorKind::NotFound {
        bad(
            video,
            format!(
                "cannot decode the video: `{}` was not found (install ffmpeg, e.g. `apt-get install ffmpeg`, or set MSTH_FFMPEG / MSTH_FFPROBE)",
                tool.display()
            ),
        )
    } else {
        bad(video, format!("cannot run `{}`: {e}", tool.display()))
    }
}

/// The last non-empty line of a tool's error output.
fn last_line(stderr: &[u8]) -> String {
    String::from_utf8_lossy(stderr)
        .lines()
        .map(str::trim)
        .rfind(|l| !l.is_empty())
        .unwrap_or("(no message)")
        .chars()
        .take(300)
        .collect()
}

/// Reads the size and the frame count (packets of the first video stream) of `path`.
pub fn probe(tools: &Tools, path: &Path) -> Result<VideoInfo, DatasetError> {
    if !path.is_file() {
        return Err(DatasetError::Io {
            path: path.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such video file"),
        });
    }
    let out = Command::new(&tools.ffprobe)
        .args([
            "-v",
            "error",
            "-select_streams",
            "v:0",
            "-count_packets",
            "-show_entries",
            "stream=width,height,nb_read_packets",
            "-of",
            "json",
        ])
        .arg(path)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| spawn_error(&tools.ffprobe, path, e))?;
    if !out.status.success() {
        return Err(bad(
            path,
            format!("not a readable video (ffprobe: {})", last_line(&out.stderr)),
        ));
    }
    let v: serde_json::Value = serde_json::from_slice(&out.stdout)
        .map_err(|e| bad(path, format!("unexpected ffprobe output: {e}")))?;
    let Some(s) = v["streams"].as_array().and_then(|a| a.first()) else {
        return Err(bad(path, "not a video: it has no video stream"));
    };
    let num = |k: &str| -> Option<u64> {
        match &s[k] {
            serde_json::Value::Number(n) => n.as_u64(),
            serde_json::Value::String(t) => t.parse().ok(),
            _ => None,
        }
    };
    let (Some(w), Some(h)) = (num("width"), num("height")) else {
        return Err(bad(path, "not a video: its stream has no picture size"));
    };
    if w == 0 || h == 0 || w > MAX_SIDE as u64 || h > MAX_SIDE as u64 {
        return Err(bad(path, format!("unsupported frame size {w}x{h}")));
    }
    let frames = num("nb_read_packets").unwrap_or(0);
    if frames == 0 || frames > MAX_FRAMES {
        return Err(bad(
            path,
            format!("not a usable video: {frames} frames (expected 1..={MAX_FRAMES})"),
        ));
    }
    Ok(VideoInfo {
        width: w as u32,
        height: h as u32,
        frames,
    })
}

/// Receives decoded frames: `(index, rgb)`.
pub type FrameFn<'a> = dyn FnMut(usize, &[u8]) -> Result<(), DatasetError> + 'a;

/// Decodes every frame of `path` (which [`probe`] described as `info`) as 8-bit RGB, row 0 at
/// the top, calling `each(index, rgb)` in order. Fails when the video yields a different number
/// of frames than `info.frames`.
pub fn decode(
    tools: &Tools,
    path: &Path,
    info: &VideoInfo,
    each: &mut FrameFn<'_>,
) -> Result<(), DatasetError> {
    let mut child = Command::new(&tools.ffmpeg)
        .args(["-v", "error", "-nostdin", "-i"])
        .arg(path)
        .args([
            "-map",
            "0:v:0",
            "-vsync",
            "passthrough",
            "-f",
            "rawvideo",
            "-pix_fmt",
            "rgb24",
            "-",
        ])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| spawn_error(&tools.ffmpeg, path, e))?;
    // Drain stderr on a thread so that a chatty ffmpeg cannot block on a full pipe.
    let mut stderr = child.stderr.take();
    let err_thread = std::thread::spawn(move || {
        let mut buf = Vec::new();
        if let Some(s) = stderr.as_mut() {
            let _ = s.read_to_end(&mut buf);
        }
        buf
    });
    let frame_bytes = info.width as usize * info.height as usize * 3;
    let mut buf = vec![0u8; frame_bytes];
    let mut stdout = child.stdout.take();
    let mut index = 0u64;
    let mut result = Ok(());
    if let Some(out) = stdout.as_mut() {
        loop {
            match read_full(out, &mut buf) {
                Ok(0) => break,
                Ok(n) if n < frame_bytes => {
                    result = Err(bad(
                        path,
                        format!("the decoder stopped in the middle of frame {index} ({n} of {frame_bytes} bytes)"),
                    ));
                    break;
                }
                Ok(_) => {}
                Err(e) => {
                    result = Err(DatasetError::Io {
                        path: path.to_path_buf(),
                        source: e,
                    });
                    break;
                }
            }
            if index >= info.frames {
                result = Err(bad(
                    path,
                    format!(
                        "decodes to more frames than the {} it declares",
                        info.frames
                    ),
                ));
                break;
            }
            if let Err(e) = each(index as usize, &buf) {
                result = Err(e);
                break;
            }
            index += 1;
        }
    }
    drop(stdout);
    if result.is_err() {
        let _ = child.kill();
    }
    let status = child
        .wait()
        .map_err(|e| spawn_error(&tools.ffmpeg, path, e))?;
    let stderr = err_thread.join().unwrap_or_default();
    result?;
    if !status.success() {
        return Err(bad(
            path,
            format!("cannot decode the video (ffmpeg: {})", last_line(&stderr)),
        ));
    }
    if index != info.frames {
        return Err(bad(
            path,
            format!(
                "decodes to {index} frames but declares {} (a damaged video?)",
                info.frames
            ),
        ));
    }
    Ok(())
}

/// Reads until `buf` is full or the stream ends; returns the bytes read.
fn read_full(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

/// Encodes 8-bit RGB frames into a video with `ffmpeg` (lossless FFV1 for `.mkv`, H.264
/// yuv420p CRF `crf` otherwise). For tests and tools that make fixtures.
pub fn encode(
    tools: &Tools,
    path: &Path,
    width: u32,
    height: u32,
    frames: &[Vec<u8>],
    crf: u32,
) -> Result<(), DatasetError> {
    use std::io::Write;
    let lossless = path.extension().is_some_and(|e| e == "mkv");
    let mut cmd = Command::new(&tools.ffmpeg);
    cmd.args([
        "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s",
    ])
    .arg(format!("{width}x{height}"))
    .args(["-r", "30", "-i", "-"]);
    if lossless {
        cmd.args(["-c:v", "ffv1"]);
    } else {
        cmd.args(["-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf"])
            .arg(crf.to_string());
    }
    let mut child = cmd
        .arg(path)
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| spawn_error(&tools.ffmpeg, path, e))?;
    if let Some(mut stdin) = child.stdin.take() {
        for f in frames {
            stdin.write_all(f).map_err(|source| DatasetError::Io {
                path: path.to_path_buf(),
                source,
            })?;
        }
    }
    let out = child
        .wait_with_output()
        .map_err(|e| spawn_error(&tools.ffmpeg, path, e))?;
    if !out.status.success() {
        return Err(bad(
            path,
            format!("ffmpeg could not encode: {}", last_line(&out.stderr)),
        ));
    }
    Ok(())
}
