// passes: the per-sample passes' entry points (`pass_*`): the CPU renderer's rendering (msth-core
// `pipeline::render_chunk`), split into dispatches over compacted work lists, so that no
// invocation loops over a whole ray's field evaluations. One frame (or one batch of rays of it)
// is, in order:
//
//   pass_setup      one per pixel of the batch: ray limits; a ray that misses the scene under a
//                   constant background writes the background, the others are appended to the
//                   ray list (`ctrl[0]`);
//   pass_args       one invocation: indirect dispatch sizes from the counters (bound with the
//                   `args` buffer in the `work` slot);
//   pass_proposal   one per (ray, proposal sample): the proposal field's density;
//   pass_resample   one per ray: proposal weights and the inverse CDF, `S + 1` edges (short
//                   loops over the ray's histogram, no field evaluation);
//   pass_density    one per (ray, main sample): encoding, mask blend, density MLP; sigma and the
//                   geometry features;
//
// With the file's occupancy grid, `pass_live_proposal` and `pass_live_samples` first list the
// samples in occupied cells, split by the mask: those it leaves a 4D lookup go to
// `pass_proposal` and `pass_density`, those whose 4D lookup it skips to `pass_proposal3` and
// `pass_density3`, compiled without the 4D lookup (a static sample then costs its 3D lookup,
// wherever it falls among its neighbours);
//   pass_visible    one per ray: which samples light still reaches: those get a colour and are
//                   appended to the colour list (`ctrl[1]`);
//   pass_args       again (the colour list's size);
//   pass_color      one per listed sample: SH of the ray direction + colour MLP;
//   pass_composite  one per ray: volume compositing and the background into `frame`.
//
// Incremental playback with sample-level reuse (msth-player's `samples.rs`) runs the same passes
// on a persistent cache: `pass_wmax` (the per-bin maximum of the proposal weights over several
// times), `pass_resample` from that histogram, `pass_build` (static samples evaluated once,
// dynamic ones listed in `ctrl[2]`), then per frame `pass_dynamic` (the dynamic samples' density
// at the frame's time), `pass_visible`, `pass_color` and `pass_composite`.

// #import passes_rays
// #import passes_shade
// #import passes_cache
