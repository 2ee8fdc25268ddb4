//! Streaming a `.msth` file: the prefix first, then the static sections, then dynamic chunks in
//! playback order from the playhead, on a background thread.
//!
//! [`ModelStream::open`] reads and checks the prefix (header, metadata, index) synchronously, so a
//! bad URL or a corrupt file fails right away. A fetch thread then asks [`crate::abr`] what to
//! read next, from what is decoded, the playhead, the playback speed and the throughput it
//! measures:
//! 1. the sections every frame needs (MLPs, proposal, static tables, shared 4D rows; of a
//!    layered file, layer 0 of them) in one Range request when they are contiguous, as they are
//!    in files the encoder writes;
//! 2. the chunk the playhead wants ([`ModelStream::seek`] or a blocking
//!    [`ModelStream::params_for_time`] moves it), then the following chunks in playback order,
//!    wrapping around; of a layered file, layer 0 of the coming chunks first, then as many finer
//!    layers as the link carries before each chunk plays ([`ModelStream::set_speed`] says how
//!    fast playback runs), until the whole file is in.
//!
//! A source that must be read forward ([`ByteSource::sequential`]: a server that ignores Range
//! requests) is read in file order instead, one section at a time, whatever the playhead. Once
//! the index is parsed, the source is told the length the header declares
//! ([`ByteSource::limit_to`]), so nothing past it is ever read, and a server that declared another
//! length fails here.
//!
//! Sections are decoded on the fetch thread as they arrive; a fetch or decode error stops the
//! thread and is returned by every later call, and waiting calls give up after their timeout.

use std::ops::Range;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use msth_codec::format::{FileIndex, FIXED_HEADER};
use msth_codec::{Decoder, Limits};

use crate::abr::{Playback, RateMeter};
use crate::source::{ByteSource, SourceError, TransferStats};

/// Errors of streaming playback.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    #[error(transparent)]
    Source(#[from] SourceError),
    #[error("{name}: {error}")]
    Decode {
        name: String,
        error: msth_codec::DecodeError,
    },
    #[error("{name}: {what} did not arrive within {:.0} s{}", waited.as_secs_f64(), activity.as_ref().map_or(String::new(), |a| format!(" ({a})")))]
    Timeout {
        name: String,
        what: String,
        waited: Duration,
        /// The request in progress when the wait ended ([`ByteSource::activity`]).
        activity: Option<String>,
    },
    /// An earlier failure of the fetch thread, repeated for every later call.
    #[error("{0}")]
    Failed(String),
}

/// How far the download has got.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StreamProgress {
    /// Bytes of the file decoded so far (prefix included).
    pub bytes_ready: u64,
    pub file_len: u64,
    pub sections_ready: usize,
    pub sections: usize,
    pub transfer: TransferStats,
}

struct State {
    decoder: Decoder,
    /// The chunk the playhead needs (fetched first), if any.
    want: Option<usize>,
    /// The playhead and the playback speed the layer policy plans with.
    playback: Playback,
    /// Throughput of the requests so far.
    meter: RateMeter,
    error: Option<String>,
    bytes_ready: u64,
    stop: bool,
}

struct Shared {
    state: Mutex<State>,
    changed: Condvar,
    source: Box<dyn ByteSource>,
    name: String,
    index: FileIndex,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// A `.msth` file being streamed; cheap to query from the render loop.
pub struct ModelStream {
    shared: Arc<Shared>,
}

impl ModelStream {
    /// Reads and checks the prefix from `source`, then starts fetching the rest.
    pub fn open(source: Box<dyn ByteSource>, limits: &Limits) -> Result<Self, StreamError> {
        let name = source.name().to_string();
        let decode_err = |error| StreamError::Decode {
            name: name.clone(),
            error,
        };
        let len = source.len();
        let first = source.read_range(0..(FIXED_HEADER as u64).min(len))?;
        let prefix_len = FileIndex::prefix_len(&first, limits).map_err(decode_err)?;
        if prefix_len > len {
            return Err(decode_err(msth_codec::DecodeError::Truncated {
                what: "header and index".into(),
                needed: prefix_len,
                have: len,
            }));
        }
        let began = Instant::now();
        let prefix = source.read_range(0..prefix_len)?;
        let mut meter = RateMeter::default();
        meter.add(prefix_len, began.elapsed().as_secs_f64());
        let decoder = Decoder::with_limits(&prefix, limits).map_err(decode_err)?;
        let index = decoder.index().clone();
        if index.file_len() > len {
            return Err(decode_err(msth_codec::DecodeError::Truncated {
                what: "file (the index points past its end)".into(),
                needed: index.file_len(),
                have: len,
            }));
        }
        source.limit_to(index.file_len())?;
        let shared = Arc::new(Shared {
            state: Mutex::new(State {
                decoder,
                want: None,
                playback: Playback {
                    time: 0.0,
                    seconds_per_unit: 0.0,
                },
                meter,
                error: None,
                bytes_ready: prefix_len,
                stop: false,
            }),
            changed: Condvar::new(),
            source,
            name,
            index,
        });
        let worker = Arc::clone(&shared);
        std::thread::Builder::new()
            .name("msth-fetch".into())
            .spawn(move || fetch_loop(&worker))
            .map_err(|e| StreamError::Failed(format!("cannot start the fetch thread: {e}")))?;
        Ok(ModelStream { shared })
    }

    /// The file's prefix: metadata (model, cameras, chunks) and section index.
    pub fn index(&self) -> &FileIndex {
        &self.shared.index
    }

    /// Moves the playhead: the chunk for normalised time `t` is fetched next.
    pub fn seek(&self, t: f32) {
        let want = self.index().chunk_for_time(t);
        let mut st = self.shared.lock();
        st.playback.time = t;
        if st.want != want {
            st.want = want;
            self.shared.changed.notify_all();
        }
    }

    /// How fast playback runs: wall-clock seconds per unit of normalised time (the clip's
    /// length), 0 when paused. The layer policy plans each chunk's layers against it; by default
    /// (0) it fetches every layer of the chunk on screen first.
    pub fn set_speed(&self, seconds_per_unit: f64) {
        let mut st = self.shared.lock();
        let s = if seconds_per_unit.is_finite() {
            seconds_per_unit.max(0.0)
        } else {
            0.0
        };
        if st.playback.seconds_per_unit != s {
            st.playback.seconds_per_unit = s;
            self.shared.changed.notify_all();
        }
    }

    /// The progressive layers a frame at time `t` is drawn with now (0: not ready; 1 for a file
    /// without layers once ready).
    pub fn layers_for(&self, t: f32) -> usize {
        let st = self.shared.lock();
        st.decoder.layers_ready(self.index().chunk_for_time(t))
    }

    /// The throughput measured over the last requests, bytes per second.
    pub fn rate(&self) -> Option<f64> {
        self.shared.lock().meter.rate()
    }

    /// Waits until the static sections are decoded (the first frame needs nothing else when the
    /// file has no dynamic chunks).
    pub fn wait_static(&self, timeout: Duration) -> Result<(), StreamError> {
        self.wait("the static sections", timeout, |st| {
            st.decoder.static_ready()
        })
        .map(|_| ())
    }

    /// Writes the parameters for time `t` into `out`, waiting up to `timeout` for the sections
    /// they need, every progressive layer of them (what `msth play` renders: the same frames
    /// however fast the link); moves the playhead to `t`. Returns the chunk used (`None`: a
    /// static file).
    pub fn params_for_time(
        &self,
        t: f32,
        out: &mut Vec<f32>,
        timeout: Duration,
    ) -> Result<Option<usize>, StreamError> {
        self.seek(t);
        self.params_at(t, out, timeout)
    }

    /// [`ModelStream::params_for_time`] without moving the playhead: waits for the sections as
    /// the fetch thread brings them in playback order (the incremental renderer's probes at other
    /// times use it, so that they do not disturb the order frames are fetched in).
    pub fn params_at(
        &self,
        t: f32,
        out: &mut Vec<f32>,
        timeout: Duration,
    ) -> Result<Option<usize>, StreamError> {
        let chunk = self.index().chunk_for_time(t);
        let what = waiting_for(chunk, t);
        let layers = self.index().layer_count();
        let st = self.wait(&what, timeout, |st| {
            st.decoder.layers_ready(chunk) == layers
        })?;
        st.decoder
            .params_for_time_into(t, out)
            .map_err(|error| StreamError::Decode {
                name: self.shared.name.clone(),
                error,
            })?;
        Ok(chunk)
    }

    /// Writes the parameters for time `t` into `out` as soon as the chunk's layer 0 is in (a
    /// progressive player: it draws at once and again as finer layers arrive); moves the
    /// playhead to `t`. Returns the chunk and the layers used.
    pub fn params_progressive(
        &self,
        t: f32,
        out: &mut Vec<f32>,
        timeout: Duration,
    ) -> Result<(Option<usize>, usize), StreamError> {
        self.seek(t);
        let chunk = self.index().chunk_for_time(t);
        let what = waiting_for(chunk, t);
        let st = self.wait(&what, timeout, |st| st.decoder.layers_ready(chunk) > 0)?;
        st.decoder
            .params_for_time_into(t, out)
            .map_err(|error| StreamError::Decode {
                name: self.shared.name.clone(),
                error,
            })?;
        Ok((chunk, st.decoder.layers_ready(chunk)))
    }

    /// The file's occupancy grid once its section is decoded (`None` before, and for a
    /// version-1 file, which has none).
    pub fn occupancy(&self) -> Option<Arc<msth_codec::OccupancyGrid>> {
        let st = self.shared.lock();
        st.decoder.occupancy().cloned().map(Arc::new)
    }

    /// Whether the chunk for time `t` (and the static part) is already decoded, every layer.
    pub fn ready_for(&self, t: f32) -> bool {
        let st = self.shared.lock();
        st.decoder.layers_ready(self.index().chunk_for_time(t)) == self.index().layer_count()
    }

    /// Waits until every section is decoded.
    pub fn wait_all(&self, timeout: Duration) -> Result<(), StreamError> {
        let n = self.index().sections.len();
        self.wait("the whole file", timeout, |st| {
            (0..n).all(|i| st.decoder.is_decoded(i))
        })
        .map(|_| ())
    }

    pub fn progress(&self) -> StreamProgress {
        let st = self.shared.lock();
        let sections = self.index().sections.len();
        StreamProgress {
            bytes_ready: st.bytes_ready,
            file_len: self.index().file_len(),
            sections_ready: (0..sections).filter(|&i| st.decoder.is_decoded(i)).count(),
            sections,
            transfer: self.shared.source.stats(),
        }
    }

    fn wait(
        &self,
        what: &str,
        timeout: Duration,
        ready: impl Fn(&State) -> bool,
    ) -> Result<MutexGuard<'_, State>, StreamError> {
        let deadline = Instant::now() + timeout;
        let mut st = self.shared.lock();
        loop {
            if ready(&st) {
                return Ok(st);
            }
            if let Some(e) = &st.error {
                return Err(StreamError::Failed(e.clone()));
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(StreamError::Timeout {
                    name: self.shared.name.clone(),
                    what: what.to_string(),
                    waited: timeout,
                    activity: self.shared.source.activity(),
                });
            }
            st = self
                .shared
                .changed
                .wait_timeout(st, deadline - now)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }
}

/// What a wait for time `t` (in `chunk`) waits for, as timeouts name it.
fn waiting_for(chunk: Option<usize>, t: f32) -> String {
    match chunk {
        Some(c) => format!("dynamic chunk {c} (time {t})"),
        None => "the static sections".into(),
    }
}

impl Drop for ModelStream {
    fn drop(&mut self) {
        // The fetch thread notices after its current request (bounded by the source's timeouts).
        self.shared.lock().stop = true;
        self.shared.changed.notify_all();
    }
}

/// What the fetch thread reads next: index positions of contiguous sections.
fn next_request(st: &State, index: &FileIndex, sequential: bool) -> Option<Range<usize>> {
    if sequential {
        // File order, one section at a time: the stream never goes back.
        return (0..index.sections.len())
            .filter(|&i| !st.decoder.is_decoded(i))
            .min_by_key(|&i| index.sections[i].offset)
            .map(|i| i..i + 1);
    }
    let decoded: Vec<bool> = (0..index.sections.len())
        .map(|i| st.decoder.is_decoded(i))
        .collect();
    crate::abr::next_request(index, &decoded, Some(st.playback), st.meter.rate())
}

fn fetch_loop(shared: &Shared) {
    loop {
        let index = &shared.index;
        let request = {
            let mut st = shared.lock();
            loop {
                if st.stop {
                    return;
                }
                if let Some(r) = next_request(&st, index, shared.source.sequential()) {
                    break r;
                }
                if (0..index.sections.len()).all(|i| st.decoder.is_decoded(i)) {
                    return;
                }
                // The policy holds back until the playhead or the speed moves.
                st = shared
                    .changed
                    .wait_timeout(st, Duration::from_millis(200))
                    .unwrap_or_else(|p| p.into_inner())
                    .0;
            }
        };
        let entries = &index.sections[request.clone()];
        let start = entries[0].offset;
        let end = entries
            .iter()
            .map(|e| e.offset + e.length)
            .max()
            .unwrap_or(start);
        let began = Instant::now();
        let result = shared.source.read_range(start..end);
        let took = began.elapsed().as_secs_f64();
        let mut st = shared.lock();
        match result {
            Ok(bytes) => {
                st.meter.add(end - start, took);
                for (i, e) in request.clone().zip(entries) {
                    let lo = (e.offset - start) as usize;
                    let stored = &bytes[lo..lo + e.length as usize];
                    if let Err(err) = st.decoder.decode_section(i, stored) {
                        st.error = Some(format!("{}: {err}", shared.name));
                        shared.changed.notify_all();
                        return;
                    }
                    st.bytes_ready += e.length;
                }
            }
            Err(err) => {
                st.error = Some(err.to_string());
                shared.changed.notify_all();
                return;
            }
        }
        shared.changed.notify_all();
    }
}
