//! What a streaming player fetches next, and how many progressive layers (format.md §6.6) each
//! time chunk gets: the adaptive-bitrate policy of `msth play` and the page (`web/js/abr.js`
//! implements the same function; `tests/tests/web_layers.rs` checks that both choose the same
//! requests on the same simulated link).
//!
//! The policy is a pure function of the file's index, what is decoded, the playhead, the
//! playback speed and the measured throughput ([`next_request`]); it keeps no state, so it
//! follows the link as the measurement moves.
//!
//! 1. The sections every frame needs (layer 0 of the static part), in one request when they are
//!    contiguous.
//! 2. Layer 0 of every chunk needed within [`BASE_AHEAD`] seconds of playback.
//! 3. Then the chunks in playback order from the playhead, wrapping around. Chunk `j` of that
//!    order is needed in `T_j` seconds of playback (the chunk under the playhead: now, and its
//!    finer layers are worth fetching while it still plays). Walking the order with the bytes
//!    `P` the chunks before it still need, chunk `j` gets the most layers `k` whose missing
//!    sections (the chunk's, and the static and shared sections of those layers that no earlier
//!    chunk counted) fit `P + bytes <= SAFETY x rate x T_j`, and always its layer 0: quality
//!    drops before playback stalls. The first missing section of a chosen layer is fetched.
//!    A finer layer is taken only if every later chunk's layer 0 still fits before it is needed.
//! 4. A paused player (no playback speed) or an unmeasured link asks for every layer of the
//!    chunk under the playhead first, then the rest in order.
//! 5. Once the plan holds what it wants, the rest (finer layers of chunks that play again in a
//!    looping clip), coarse layers first, unless a request could delay a missing layer 0.
//!
//! A file of one layer comes down as before: the static sections, then the chunks in playback
//! order.

use std::collections::HashSet;
use std::ops::Range;

use msth_codec::format::FileIndex;
use msth_codec::SectionKind;

/// The share of the measured throughput the policy plans with.
pub const SAFETY: f64 = 0.8;
/// Seconds of playback whose chunks' layer 0 is fetched before any finer layer: a link that
/// falls while a large finer section is on its way still finds the coming chunks there.
pub const BASE_AHEAD: f64 = 10.0;
/// Largest gap between two sections fetched in one request (the format pads to 8 bytes).
pub const MAX_GAP: u64 = 4096;

/// The playback clock the policy plans against.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Playback {
    /// The normalised time on screen.
    pub time: f32,
    /// Wall-clock seconds per unit of normalised time (the clip's length): 0 when paused.
    pub seconds_per_unit: f64,
}

/// Chunks in playback order from the one covering `time`, wrapping around, with the seconds of
/// playback until each is needed (0 for the one on screen; `None` when paused).
fn chunk_order(index: &FileIndex, playback: Option<Playback>) -> Vec<(usize, Option<f64>)> {
    let spans = &index.metadata.chunks;
    let n = spans.len();
    let time = playback.map_or(0.0, |p| p.time);
    let first = index.chunk_for_time(time).unwrap_or(0);
    (0..n)
        .map(|j| {
            let c = (first + j) % n;
            let wait = playback.filter(|p| p.seconds_per_unit > 0.0).map(|p| {
                if j == 0 {
                    // Upgrades of the chunk on screen help while it plays.
                    (spans[c].t_end - time).max(0.0) as f64 * p.seconds_per_unit
                } else {
                    let ahead = spans[c].t_start - time;
                    let ahead = if ahead < 0.0 { ahead + 1.0 } else { ahead };
                    ahead as f64 * p.seconds_per_unit
                }
            });
            (c, wait)
        })
        .collect()
}

/// The index positions chunk `c` needs for layer `l`: the chunk's section and, for `l > 0`,
/// the proposal, static and shared sections of that layer.
fn layer_sections(index: &FileIndex, c: usize, l: usize) -> Vec<usize> {
    let mut out = Vec::with_capacity(4);
    if l > 0 {
        out.extend(index.position(SectionKind::Proposal, 0, l));
        out.extend(index.position(SectionKind::Static, 0, l));
        out.extend(index.position(SectionKind::Shared, 0, l));
    }
    out.extend(index.position(SectionKind::Dynamic, c, l));
    out
}

/// The layers each chunk gets, in playback order from the playhead: `(chunk, layers)`, by the
/// rule of the module's point 3. `rate` in bytes per second (`None`: not measured yet). A finer
/// layer of chunk `j` is taken only if every later chunk's layer 0 still fits before that chunk
/// is needed: enhancements never push a base layer late.
pub fn plan_layers(
    index: &FileIndex,
    decoded: &[bool],
    playback: Option<Playback>,
    rate: Option<f64>,
) -> Vec<(usize, usize)> {
    let layers = index.layer_count();
    let missing = |i: &usize| !decoded.get(*i).copied().unwrap_or(false);
    let order = chunk_order(index, playback);
    let n = order.len();
    let budget: Vec<f64> = order
        .iter()
        .map(|&(_, wait)| match (wait, rate) {
            (Some(w), Some(r)) => SAFETY * r * w,
            // Paused, or no measurement yet: every layer.
            _ => f64::INFINITY,
        })
        .collect();
    let base: Vec<f64> = order
        .iter()
        .map(|&(c, _)| {
            layer_sections(index, c, 0)
                .iter()
                .filter(|i| missing(i))
                .map(|&i| index.sections[i].length as f64)
                .sum()
        })
        .collect();
    // slack[j]: the most bytes chunks 0..=j may take so that every later chunk's layer 0 still
    // arrives before it is needed.
    let mut slack = vec![f64::INFINITY; n];
    for j in (0..n.saturating_sub(1)).rev() {
        slack[j] = budget[j + 1].min(slack[j + 1]) - base[j + 1];
    }
    let mut counted: HashSet<usize> = HashSet::new();
    let mut pending = 0.0f64;
    order
        .iter()
        .enumerate()
        .map(|(j, &(c, _))| {
            let mut chosen = 0;
            for l in 0..layers {
                let new: Vec<usize> = layer_sections(index, c, l)
                    .into_iter()
                    .filter(|i| missing(i) && !counted.contains(i))
                    .collect();
                let bytes: f64 = new.iter().map(|&i| index.sections[i].length as f64).sum();
                let total = pending + bytes;
                if l > 0 && (total > budget[j] || total > slack[j]) {
                    break;
                }
                pending = total;
                counted.extend(new);
                chosen = l + 1;
            }
            (c, chosen)
        })
        .collect()
}

/// The next request: index positions of contiguous sections to fetch, or `None` when the plan
/// holds everything it wants (which, for a file of one layer, is the whole file).
pub fn next_request(
    index: &FileIndex,
    decoded: &[bool],
    playback: Option<Playback>,
    rate: Option<f64>,
) -> Option<Range<usize>> {
    let missing = |i: usize| !decoded.get(i).copied().unwrap_or(false);
    let statics: Vec<usize> = (0..index.before_first_frame())
        .filter(|&i| missing(i))
        .collect();
    if let (Some(&first), Some(&last)) = (statics.first(), statics.last()) {
        // One request for all of them when only padding lies between them, as in files the
        // encoder writes.
        let contiguous = statics.len() == last - first + 1
            && (first..last).all(|i| {
                let (a, b) = (&index.sections[i], &index.sections[i + 1]);
                b.offset >= a.offset + a.length && b.offset - (a.offset + a.length) <= MAX_GAP
            });
        return Some(if contiguous {
            first..last + 1
        } else {
            first..first + 1
        });
    }
    if index.metadata.chunks.is_empty() {
        // A file without chunks: its further proposal and static layers, coarse first.
        return (1..index.layer_count())
            .flat_map(|l| {
                [SectionKind::Proposal, SectionKind::Static]
                    .into_iter()
                    .filter_map(move |k| index.position(k, 0, l))
            })
            .find(|&i| missing(i))
            .map(|i| i..i + 1);
    }
    // Layer 0 of the chunks needed within BASE_AHEAD seconds (the one on screen when paused).
    for (c, wait) in chunk_order(index, playback) {
        if wait.is_none_or(|w| w <= BASE_AHEAD) {
            if let Some(i) = index
                .position(SectionKind::Dynamic, c, 0)
                .filter(|&i| missing(i))
            {
                return Some(i..i + 1);
            }
        }
        if wait.is_none() {
            break;
        }
    }
    let order = chunk_order(index, playback);
    for (c, k) in plan_layers(index, decoded, playback, rate) {
        for l in 0..k {
            if let Some(i) = layer_sections(index, c, l)
                .into_iter()
                .find(|&i| missing(i))
            {
                return Some(i..i + 1);
            }
        }
    }
    // The plan holds what it wants: spare time goes to what is left, finer layers of chunks
    // that play again (a looping clip) coarse first, as long as a request cannot delay a layer 0
    // past its chunk's time.
    let first_missing_base = order.iter().find(|&&(c, _)| {
        index
            .position(SectionKind::Dynamic, c, 0)
            .is_some_and(missing)
    });
    for l in 0..index.layer_count() {
        for &(c, _) in &order {
            for i in layer_sections(index, c, l) {
                if !missing(i) {
                    continue;
                }
                let fits = match (first_missing_base, rate) {
                    (None, _) => true,
                    (Some(&(_, Some(wait))), Some(r)) => {
                        index.sections[i].length as f64 <= SAFETY * r * wait
                    }
                    // Paused, or no measurement: the plan already asked for everything.
                    _ => true,
                };
                return fits.then_some(i..i + 1);
            }
        }
    }
    None
}

/// Throughput measured over the last requests: total bytes over total seconds of the most recent
/// requests that together took at least [`RateMeter::WINDOW`] seconds (all of them before).
#[derive(Clone, Debug, Default)]
pub struct RateMeter {
    samples: std::collections::VecDeque<(u64, f64)>,
}

impl RateMeter {
    /// Seconds of transfers the estimate spans.
    pub const WINDOW: f64 = 1.0;

    /// Records a request of `bytes` that took `seconds`.
    pub fn add(&mut self, bytes: u64, seconds: f64) {
        if !(seconds.is_finite() && seconds >= 0.0) {
            return;
        }
        self.samples.push_front((bytes, seconds.max(1e-6)));
        let mut total = 0.0;
        let mut keep = 0;
        for (_, s) in &self.samples {
            keep += 1;
            total += s;
            if total >= Self::WINDOW {
                break;
            }
        }
        self.samples.truncate(keep);
    }

    /// Bytes per second (`None` before the first request).
    pub fn rate(&self) -> Option<f64> {
        if self.samples.is_empty() {
            return None;
        }
        let (b, s) = self
            .samples
            .iter()
            .fold((0u64, 0.0), |(b, s), &(bb, ss)| (b + bb, s + ss));
        Some(b as f64 / s)
    }
}

/// One step of a [`simulate`]d session.
#[derive(Clone, Debug, PartialEq)]
pub struct SimEvent {
    /// Wall-clock seconds since the session started.
    pub at: f64,
    /// The request's index positions.
    pub sections: Range<usize>,
    pub bytes: u64,
    /// The measured rate it was chosen with (bytes/s).
    pub rate: Option<f64>,
}

/// A frame of a [`simulate`]d session.
#[derive(Clone, Debug, PartialEq)]
pub struct SimFrame {
    /// Wall-clock seconds when it was shown.
    pub at: f64,
    pub time: f32,
    /// Layers it was drawn with.
    pub layers: usize,
}

/// What a [`simulate`]d session did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SimTrace {
    pub requests: Vec<SimEvent>,
    pub frames: Vec<SimFrame>,
    /// Seconds from the start to the first frame.
    pub first_frame: f64,
    /// Each stall: when it began and how long it lasted (seconds).
    pub stalls: Vec<(f64, f64)>,
}

/// A player on a simulated link: requests take `latency + bytes / rate(t)` seconds with the rate
/// `rate_at(t)` (bytes/s at wall-clock time `t`, integrated over the transfer), one request at a
/// time; playback starts at the first frame and shows `frames` frames at `fps`, looping over the
/// model's frames, waiting (a stall) when a frame's chunk has no layer yet. The prefix (`index.header.header_size` bytes) is one
/// request before the others. Deterministic: the page's simulator (`web/js/abr.js`) gives the
/// same trace for the same file and link.
pub fn simulate(
    index: &FileIndex,
    rate_at: &dyn Fn(f64) -> f64,
    latency: f64,
    frames: usize,
    fps: f64,
) -> SimTrace {
    let mut trace = SimTrace::default();
    let n = index.sections.len();
    let mut decoded = vec![false; n];
    let mut meter = RateMeter::default();
    // Transfers `bytes` from `start`: returns the end time.
    let transfer = |start: f64, bytes: u64| -> f64 {
        let mut t = start + latency;
        let mut left = bytes as f64;
        // 10 ms steps of the schedule.
        while left > 0.0 {
            let r = rate_at(t).max(1.0);
            let step = 0.01;
            if left <= r * step {
                t += left / r;
                left = 0.0;
            } else {
                left -= r * step;
                t += step;
            }
        }
        t
    };
    let mut now = transfer(0.0, index.header.header_size as u64);
    meter.add(index.header.header_size as u64, now);
    let clip = index.metadata.model.num_frames.max(1);
    let seconds_per_unit = clip as f64 / fps.max(1e-3);
    let frame_time = |f: usize| msth_codec::encode::frame_time(f % clip, clip);
    // Playback: the next frame to show and when it is due (from the first frame on).
    let mut next_frame = 0usize;
    let mut due: Option<f64> = None;
    let mut stalled_since: Option<f64> = None;
    let ready = |decoded: &[bool], t: f32| -> usize {
        if !(0..index.before_first_frame()).all(|i| decoded[i]) {
            return 0;
        }
        let chunk = index.chunk_for_time(t);
        (0..index.layer_count())
            .take_while(|&l| match chunk {
                Some(c) => layer_sections(index, c, l).iter().all(|&i| decoded[i]),
                None => [SectionKind::Proposal, SectionKind::Static]
                    .into_iter()
                    .filter_map(|k| index.position(k, 0, l))
                    .all(|i| decoded[i]),
            })
            .count()
    };
    // Shows the frames due up to `until` (or the next one, when playback has not started) while
    // the decoded sections stay as they are; a frame without its chunk starts a stall.
    let show = |decoded: &[bool],
                until: f64,
                next_frame: &mut usize,
                due: &mut Option<f64>,
                stalled_since: &mut Option<f64>,
                trace: &mut SimTrace| {
        while *next_frame < frames {
            let at = match (*due, *stalled_since) {
                (_, Some(_)) => until,
                (Some(d), None) => d,
                (None, None) => until,
            };
            if at > until {
                return;
            }
            let t = frame_time(*next_frame);
            let layers = ready(decoded, t);
            if layers == 0 {
                if due.is_some() && stalled_since.is_none() {
                    *stalled_since = Some(at);
                }
                return;
            }
            if let Some(s) = stalled_since.take() {
                trace.stalls.push((s, at - s));
            }
            if trace.frames.is_empty() {
                trace.first_frame = at;
            }
            trace.frames.push(SimFrame {
                at,
                time: t,
                layers,
            });
            *next_frame += 1;
            *due = Some(at + 1.0 / fps);
        }
    };
    let mut guard = 0;
    while next_frame < frames && guard < 1_000_000 {
        guard += 1;
        show(
            &decoded,
            now,
            &mut next_frame,
            &mut due,
            &mut stalled_since,
            &mut trace,
        );
        if next_frame >= frames {
            break;
        }
        let playback = Playback {
            time: frame_time(next_frame),
            seconds_per_unit,
        };
        match next_request(index, &decoded, Some(playback), meter.rate()) {
            Some(r) => {
                let bytes: u64 = r.clone().map(|i| index.sections[i].length).sum();
                let end = transfer(now, bytes);
                trace.requests.push(SimEvent {
                    at: now,
                    sections: r.clone(),
                    bytes,
                    rate: meter.rate(),
                });
                // Frames due during the transfer, from what was there before it.
                if due.is_some() {
                    show(
                        &decoded,
                        end,
                        &mut next_frame,
                        &mut due,
                        &mut stalled_since,
                        &mut trace,
                    );
                }
                meter.add(bytes, end - now);
                for i in r {
                    decoded[i] = true;
                }
                now = end;
            }
            None => {
                // Everything wanted is in: on to the next frame.
                now = due.map_or(now, |d| d.max(now));
            }
        }
    }
    trace
}

#[cfg(test)]
mod tests {
    use super::*;
    use msth_codec::{encode, EncodeOptions, QuantMode};
    use msth_core::config::{BlendMode, ModelConfig};
    use msth_core::field::ModelLayout;

    /// A small model of 12 frames with a dynamic region, in `layers` layers and 4 chunks.
    fn file(layers: usize) -> Vec<u8> {
        let mut c = ModelConfig::fast_on_white(12);
        c.field.encoding.blend = BlendMode::Mst;
        c.field.encoding.resize(4, 12, 48.0, 8);
        c.proposal.encoding.blend = BlendMode::Mst;
        c.proposal.encoding.resize(2, 8, 16.0, 4);
        c.resize_mlps(8, 8);
        let layout = ModelLayout::new(&c);
        let mut p = layout.init_params(5);
        if let Some((g, r)) = &layout.field.encoding.mask {
            let res = g.res;
            for (i, v) in p[r.clone()].iter_mut().enumerate() {
                let (x, y, z) = (i % res, (i / res) % res, i / (res * res));
                *v = if [x, y, z].iter().all(|&a| (2..=5).contains(&a)) {
                    -3.0
                } else {
                    3.0
                };
            }
        }
        let opts = EncodeOptions {
            quant: QuantMode::Q8,
            chunk_frames: 3,
            layers,
            occupancy_resolution: 16,
            ..Default::default()
        };
        encode(&c, &p, &[], &opts).unwrap().0
    }

    fn index(bytes: &[u8]) -> FileIndex {
        FileIndex::parse(bytes, &msth_codec::Limits::default()).unwrap()
    }

    /// Every request of a session on a still playhead, as `next_request` gives them.
    fn requests(ix: &FileIndex, playback: Option<Playback>, rate: Option<f64>) -> Vec<usize> {
        let mut decoded = vec![false; ix.sections.len()];
        let mut out = Vec::new();
        while let Some(r) = next_request(ix, &decoded, playback, rate) {
            for i in r {
                assert!(!decoded[i], "section {i} asked for twice");
                decoded[i] = true;
                out.push(i);
            }
        }
        out
    }

    #[test]
    fn a_file_of_one_layer_streams_in_playback_order() {
        let ix = index(&file(1));
        assert_eq!(ix.metadata.chunks.len(), 4);
        let paused = Playback {
            time: 0.5,
            seconds_per_unit: 0.0,
        };
        // Statics (MLP, proposal, static, occupancy, shared) in one request, then the chunks
        // from the one on screen (chunk 1 covers t = 0.5 of 4 chunks of 3 frames), wrapping.
        let mut decoded = vec![false; ix.sections.len()];
        assert_eq!(next_request(&ix, &decoded, Some(paused), None), Some(0..5));
        decoded[..5].fill(true);
        let first = ix.first_chunk();
        let c = ix.chunk_for_time(0.5).unwrap();
        assert_eq!(
            next_request(&ix, &decoded, Some(paused), None),
            Some(first + c..first + c + 1)
        );
        let all = requests(&ix, Some(paused), None);
        let chunks: Vec<usize> = all[5..].iter().map(|i| i - first).collect();
        assert_eq!(chunks, (0..4).map(|k| (c + k) % 4).collect::<Vec<_>>());
        assert_eq!(all.len(), ix.sections.len());
    }

    #[test]
    fn a_paused_player_takes_every_layer_of_the_chunk_on_screen_first() {
        let ix = index(&file(3));
        let paused = Playback {
            time: 0.5,
            seconds_per_unit: 0.0,
        };
        let c = ix.chunk_for_time(0.5).unwrap();
        let all = requests(&ix, Some(paused), Some(1e3));
        assert_eq!(all.len(), ix.sections.len());
        let pos = |kind, chunk, layer| ix.position(kind, chunk, layer).unwrap();
        let expect = [
            pos(SectionKind::Dynamic, c, 0),
            pos(SectionKind::Proposal, 0, 1),
            pos(SectionKind::Static, 0, 1),
            pos(SectionKind::Shared, 0, 1),
            pos(SectionKind::Dynamic, c, 1),
            pos(SectionKind::Proposal, 0, 2),
            pos(SectionKind::Static, 0, 2),
            pos(SectionKind::Shared, 0, 2),
            pos(SectionKind::Dynamic, c, 2),
        ];
        assert_eq!(&all[5..14], &expect);
    }

    #[test]
    fn a_playing_player_fetches_the_coming_base_layers_before_finer_ones() {
        let ix = index(&file(3));
        let playing = Playback {
            time: 0.0,
            seconds_per_unit: 0.4,
        };
        let all = requests(&ix, Some(playing), Some(1e9));
        let bases: Vec<usize> = (0..4)
            .map(|c| ix.position(SectionKind::Dynamic, c, 0).unwrap())
            .collect();
        assert_eq!(&all[5..9], &bases[..]);
        // A fast link then takes every layer; a slow one only what fits before each chunk.
        assert_eq!(all.len(), ix.sections.len());
        let slow = plan_layers(
            &ix,
            &vec![false; ix.sections.len()],
            Some(playing),
            Some(10.0),
        );
        assert!(slow.iter().all(|&(_, k)| k == 1), "{slow:?}");
        let fast = plan_layers(
            &ix,
            &vec![false; ix.sections.len()],
            Some(playing),
            Some(1e9),
        );
        assert!(fast.iter().all(|&(_, k)| k == 3), "{fast:?}");
    }

    /// On a simulated link the first frame comes with layer 0 alone, playback never stalls once
    /// started, and frames gain layers as the finer sections arrive; a link that falls keeps
    /// fewer layers, and every frame still has at least one.
    #[test]
    fn simulated_sessions_draw_early_and_refine() {
        let bytes = file(3);
        let ix = index(&bytes);
        let total = ix.file_len() as f64;
        // The whole file in about 4 s: the first frame well before.
        let steady = simulate(&ix, &|_| total / 4.0, 0.01, 120, 30.0);
        assert_eq!(steady.frames.len(), 120);
        let base_bytes: u64 = ix.header.header_size as u64
            + ix.sections_for(Some(0), 1)
                .iter()
                .map(|&i| ix.sections[i].length)
                .sum::<u64>();
        assert!(
            steady.first_frame < 4.0 * base_bytes as f64 / total + 0.2,
            "{}",
            steady.first_frame
        );
        assert_eq!(steady.frames[0].layers, 1);
        assert_eq!(steady.frames.last().unwrap().layers, 3);
        assert!(steady.stalls.is_empty(), "{:?}", steady.stalls);
        // Same link, falling to a tenth after 1 s.
        let fall = simulate(
            &ix,
            &|t| if t < 1.0 { total / 4.0 } else { total / 40.0 },
            0.01,
            120,
            30.0,
        );
        assert!(fall.frames.iter().all(|f| f.layers >= 1));
        let full_at = |tr: &SimTrace| {
            tr.frames
                .iter()
                .find(|f| f.layers == 3)
                .map_or(f64::INFINITY, |f| f.at)
        };
        assert!(full_at(&fall) > full_at(&steady));
        // Deterministic.
        assert_eq!(
            fall,
            simulate(
                &ix,
                &|t| if t < 1.0 { total / 4.0 } else { total / 40.0 },
                0.01,
                120,
                30.0
            )
        );
    }

    #[test]
    fn the_rate_meter_spans_the_last_second_of_transfers() {
        let mut m = RateMeter::default();
        assert_eq!(m.rate(), None);
        m.add(1000, 0.5);
        assert_eq!(m.rate(), Some(2000.0));
        m.add(100, 0.5);
        assert_eq!(m.rate(), Some(1100.0));
        // A new second of transfers pushes the old ones out.
        m.add(300, 1.0);
        assert_eq!(m.rate(), Some(300.0));
        m.add(10, f64::NAN);
        assert_eq!(m.rate(), Some(300.0));
    }
}
