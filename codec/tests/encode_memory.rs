//! Encoder memory at 10,000 frames (issue #8, part 2, found by the stability suite): the encoder
//! used to keep every chunk's list of reached 4D rows at once, `chunks x rows x 4` bytes (1.1 GB
//! for the fast preset at 10,000 frames). It now keeps one count and one owner per row.
//!
//! A counting global allocator measures the peak heap during `encode`; this file holds a single
//! test so that no other test allocates concurrently.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use msth_codec::{decode_all, encode, EncodeOptions, QuantMode};
use msth_core::config::{BlendMode, ModelConfig};
use msth_core::field::ModelLayout;

struct Counting;

static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator unchanged; only counts bytes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract for `alloc` is passed through.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = CURRENT.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: the caller's contract for `dealloc` is passed through.
        unsafe { System.dealloc(ptr, layout) };
        CURRENT.fetch_sub(layout.size(), Ordering::Relaxed);
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

#[test]
fn encoding_10000_frames_keeps_memory_per_row_not_per_chunk_and_row() {
    let frames = 10_000;
    let mut c = ModelConfig::fast_on_white(frames);
    for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
        enc.blend = BlendMode::Mt;
        enc.resize(4, 12, 64.0, 16);
    }
    c.resize_mlps(8, 4);
    let layout = ModelLayout::new(&c);
    let mut p = layout.init_params(1);
    // Half the mask dynamic: every chunk reaches most of the 4D table.
    let (g, r) = layout.field.encoding.mask.as_ref().unwrap();
    let res = g.res;
    for (i, v) in p[r.clone()].iter_mut().enumerate() {
        *v = if i % res < res / 2 { -5.0 } else { 5.0 };
    }
    let (h4, _) = layout.field.encoding.h4.as_ref().unwrap();
    let h4_rows: usize = h4.levels.iter().map(|l| l.rows).sum();
    let opts = EncodeOptions {
        quant: QuantMode::Q8,
        chunk_frames: 10,
        ..Default::default()
    };
    let param_bytes = 4 * p.len();
    let base = CURRENT.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let (bytes, report) = encode(&c, &p, &[], &opts).unwrap();
    let peak = PEAK.load(Ordering::Relaxed) - base;
    let reached: u64 = report.chunks.iter().map(|c| c.reached_values).sum();
    println!(
        "{} chunks, {} 4D rows, {reached} reached values in all, params {param_bytes} B, \
         file {} B, peak heap during encode {peak} B",
        report.chunks.len(),
        h4_rows,
        bytes.len()
    );
    assert_eq!(report.chunks.len(), 1000);
    // The per-chunk lists would need reached / features x 4 bytes at once.
    let per_chunk_lists = reached as usize / h4.features * 4;
    assert!(per_chunk_lists > 8 * param_bytes, "test too small to tell");
    // The occupancy grid costs the same at any number of frames: a byte per vertex while it is
    // computed, and its bits (twice, for the dilation).
    let r = opts.occupancy_resolution as usize;
    let occupancy = (r + 1).pow(3) + 2 * r.pow(3) / 8;
    assert!(
        peak < 4 * param_bytes + 2 * bytes.len() + occupancy + (1 << 20),
        "peak {peak} B for {param_bytes} B of parameters and a {r}^3 occupancy grid \
         (per-chunk lists: {per_chunk_lists} B)"
    );
    let d = decode_all(&bytes).unwrap();
    assert!(d.params_for_time(1.0).iter().all(|v| v.is_finite()));
}
