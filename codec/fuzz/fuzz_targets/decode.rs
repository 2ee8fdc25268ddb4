//! Fuzzes the `.msth` decoder: whole-file decoding, streaming decoding of every prefix-complete
//! section, random access to sections from arbitrary byte ranges, and the parameters of every
//! prefix of a layered file's layers must never panic, hang or allocate beyond the (reduced)
//! limits.
#![no_main]

use libfuzzer_sys::fuzz_target;
use msth_codec::{decode_all_with_limits, Decoder, Limits};

fuzz_target!(|data: &[u8]| {
    let limits = Limits {
        max_params: 1 << 22,
        max_section_bytes: 64 << 20,
        ..Limits::default()
    };
    let _ = decode_all_with_limits(data, &limits);
    if let Ok(mut d) = Decoder::with_limits(data, &limits) {
        let _ = d.feed(data);
        // Random access: hand each section the bytes at its offset, whatever they are.
        for i in 0..d.index().sections.len().min(64) {
            let e = d.index().sections[i].clone();
            let start = (e.offset as usize).min(data.len());
            let end = (start as u64 + e.length).min(data.len() as u64) as usize;
            let _ = d.decode_section(i, &data[start..end]);
        }
        let _ = d.params_for_time(0.5);
        // Progressive layers (version 4): what a player holding some of them draws.
        let chunk = d.index().chunk_for_time(0.5);
        let _ = d.layers_ready(chunk);
        let mut out = Vec::new();
        for k in 0..=d.index().layer_count() {
            let _ = d.params_for_layers_into(0.5, k, &mut out);
        }
        let _ = d.index().sections_for(chunk, usize::MAX);
    }
});
