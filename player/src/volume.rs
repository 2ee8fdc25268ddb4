//! The play-time volume on the CPU: baked over the rendering threads with progress, its time
//! slices baked when frames need them, and rays rendered through it ([`msth_core::volume`] holds
//! the layout, the bake and the march).

use std::sync::Arc;

use msth_codec::OccupancyGrid;
use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_core::pipeline::TimedRay;
use msth_core::volume::bake::{
    bake_slice_with, bake_with, cell_bits, eval_vertices, fill_borders, plan_with, BrickSet,
    PlanOptions, DEFAULT_MIN_CELL_ALPHA, DEFAULT_MIN_PROPOSAL_ALPHA,
};
use msth_core::volume::{
    BakeError, BakePlan, BakeProgress, BakeScratch, ColourMode, MarchOutput, MarchSettings,
    MarchWorkspace, Occupancy, OutsideViews, Value, Volume,
};
use msth_core::Camera;
use msth_gpu::{GpuContext, GpuScene};
use rayon::prelude::*;

pub use msth_core::volume::DEFAULT_CPU_BUDGET;

/// How a volume is baked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VolumeOptions {
    /// The most memory the volume may take, bytes (`None`: the renderer's default,
    /// [`crate::FrameRenderer::volume_budget`]; [`DEFAULT_CPU_BUDGET`] where no renderer says).
    pub budget: Option<u64>,
    /// Cells per side at most (`None`: the model's finest grid resolution).
    pub max_resolution: Option<u32>,
    /// A cell that cannot reach this opacity counts as empty.
    pub min_cell_alpha: f32,
    /// A cell where the proposal network's density cannot reach this opacity counts as empty.
    pub min_proposal_alpha: f32,
    /// What the vertices hold: a colour (the players' mode) or features (measurements).
    pub colour: ColourMode,
    /// What becomes of the occupied bricks none of the file's cameras looks into
    /// ([`PlanOptions::outside`]).
    pub outside: OutsideViews,
}

impl Default for VolumeOptions {
    fn default() -> Self {
        VolumeOptions {
            budget: None,
            max_resolution: None,
            min_cell_alpha: DEFAULT_MIN_CELL_ALPHA,
            min_proposal_alpha: DEFAULT_MIN_PROPOSAL_ALPHA,
            colour: ColourMode::default(),
            outside: OutsideViews::Auto,
        }
    }
}

/// The occupancy grid as the bake reads it.
pub fn occupancy_view(grid: &OccupancyGrid) -> Occupancy<'_> {
    Occupancy {
        resolution: grid.resolution,
        words: &grid.words,
        density_threshold: grid.density_threshold,
    }
}

/// Plans a bake of `cfg` under `options` with the file's occupancy grid and cameras (the baked
/// colours face them); `params` holds at least the static part (the mask sorts the bricks).
pub fn plan_bake(
    cfg: &ModelConfig,
    params: &[f32],
    occupancy: Option<&OccupancyGrid>,
    cameras: &[Camera],
    options: &VolumeOptions,
) -> Result<BakePlan, BakeError> {
    let layout = ModelLayout::new(cfg);
    plan_with(
        cfg,
        &layout,
        params,
        occupancy.map(occupancy_view),
        &PlanOptions {
            budget: options.budget.unwrap_or(DEFAULT_CPU_BUDGET),
            max_resolution: options.max_resolution,
            min_cell_alpha: options.min_cell_alpha,
            min_proposal_alpha: options.min_proposal_alpha,
            colour: options.colour,
            eyes: cameras.iter().map(|c| c.center()).collect(),
            views: cameras.to_vec(),
            outside: options.outside,
        },
    )
}

/// Bricks per work item of the parallel bake (progress moves by this much).
const BAKE_BATCH: usize = 16;

/// Bakes `set` over the rayon pool: values and cell bits of every brick, and the field
/// evaluations made.
fn bake_set(
    plan: &BakePlan,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    set: &BrickSet<'_>,
    progress: &BakeProgress,
) -> Result<(Vec<Value>, Vec<u32>, usize), BakeError> {
    let g = plan.geometry;
    let (fw, sv) = (g.flag_words(), g.vertices_per_brick() * plan.channels);
    let n = set.bricks.len();
    let mut values = vec![Value::ZERO; n * sv];
    let mut occupied = vec![0u32; n * fw];
    let evaluated: Result<Vec<usize>, BakeError> = values
        .par_chunks_mut(BAKE_BATCH * sv)
        .enumerate()
        .map_init(BakeScratch::default, |scratch, (c, chunk)| {
            eval_vertices(
                plan,
                cfg,
                layout,
                params,
                set,
                c * BAKE_BATCH,
                chunk,
                scratch,
                progress,
            )
        })
        .collect();
    let evaluated = evaluated?.iter().sum();
    fill_borders(plan, set, &mut values);
    cell_bits_par(plan, layout, params, set, &values, &mut occupied);
    Ok((values, occupied, evaluated))
}

/// The cell bits of every brick of `set` from its values, over the rayon pool (phase 3 of the
/// bake, [`cell_bits`]).
fn cell_bits_par(
    plan: &BakePlan,
    layout: &ModelLayout,
    params: &[f32],
    set: &BrickSet<'_>,
    values: &[Value],
    occupied: &mut [u32],
) {
    let g = plan.geometry;
    let (fw, sv) = (g.flag_words(), g.vertices_per_brick() * plan.channels);
    occupied
        .par_chunks_mut(BAKE_BATCH * fw)
        .zip(values.par_chunks(BAKE_BATCH * sv))
        .enumerate()
        .for_each(|(c, (occ, vals))| {
            cell_bits(plan, layout, params, set, c * BAKE_BATCH, vals, occ)
        });
}

/// [`bake_set`] with the vertices evaluated on the GPU (`scene` holds `params`): every vertex of
/// every brick (a brick's border vertices are evaluated by each brick that has them, which
/// costs the device little and spares the border copies), the colours baked for the plan's
/// reference directions; the cell bits on the host. Baked colours only.
pub fn bake_set_on_device(
    ctx: &GpuContext,
    scene: &GpuScene,
    plan: &BakePlan,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    set: &BrickSet<'_>,
) -> Result<(Vec<Value>, Vec<u32>, usize), BakeError> {
    if plan.colour != ColourMode::Baked || plan.channels != 4 {
        return Err(BakeError::Device(
            "the device bakes colours only (--colour baked)".into(),
        ));
    }
    let g = plan.geometry;
    let (b, n_side) = (g.brick, g.bricks_per_side());
    let v1 = b + 1;
    let nv = g.vertices_per_brick();
    let res = g.resolution as f32;
    let time = msth_core::pipeline::sample_time(set.time);
    let kind = if set.dynamic { 2.0 } else { 3.0 };
    let mut points = Vec::with_capacity(set.bricks.len() * nv * 8);
    for &brick in set.bricks {
        let o = [
            (brick % n_side) * b,
            (brick / n_side % n_side) * b,
            (brick / (n_side * n_side)) * b,
        ];
        for z in 0..v1 {
            for y in 0..v1 {
                for x in 0..v1 {
                    let u = glam::Vec3::new(
                        (o[0] + x) as f32 / res,
                        (o[1] + y) as f32 / res,
                        (o[2] + z) as f32 / res,
                    );
                    let d =
                        msth_core::volume::reference_direction(&plan.eyes, cfg.bounds.from_unit(u));
                    points.extend_from_slice(&[u.x, u.y, u.z, time, d.x, d.y, d.z, kind]);
                }
            }
        }
    }
    let out = msth_gpu::volume::eval_points(ctx, scene, &points)
        .map_err(|e| BakeError::Device(e.to_string()))?;
    let mut values = vec![Value::ZERO; out.len() * 4];
    for (j, (v, dst)) in out.iter().zip(values.chunks_exact_mut(4)).enumerate() {
        if v.iter().any(|x| !x.is_finite()) {
            let p = &points[j * 8..j * 8 + 3];
            return Err(BakeError::NotFinite([p[0], p[1], p[2]]));
        }
        for (d, x) in dst.iter_mut().zip([v[3], v[0], v[1], v[2]]) {
            *d = Value::from_f32(x);
        }
    }
    let mut occupied = vec![0u32; set.bricks.len() * g.flag_words()];
    cell_bits_par(plan, layout, params, set, &values, &mut occupied);
    Ok((values, occupied, out.len()))
}

/// Bakes `plan`'s static bricks over the rayon pool; `progress` counts bricks and can stop it.
/// The dynamic bricks' slices are baked when frames need them ([`bake_slice`]).
pub fn bake(
    plan: &BakePlan,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    progress: &BakeProgress,
) -> Result<Volume, BakeError> {
    bake_with(plan, &mut |set| {
        bake_set(plan, cfg, layout, params, set, progress)
    })
}

/// Bakes time slice `k` of `vol` over the rayon pool with `params` (the flat buffer at the
/// slice's time); returns the field evaluations made.
pub fn bake_slice(
    vol: &mut Volume,
    plan: &BakePlan,
    k: usize,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
) -> Result<usize, BakeError> {
    bake_slice_with(vol, plan, k, &mut |set| {
        bake_set(plan, cfg, layout, params, set, &BakeProgress::default())
    })
}

/// Rays per work item of the parallel march.
const MARCH_CHUNK: usize = 64;

/// Renders `rays` through `vol` in parallel, in order.
pub fn render_rays(
    vol: &Volume,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    settings: &MarchSettings,
) -> MarchOutput {
    let parts: Vec<MarchOutput> = rays
        .par_chunks(MARCH_CHUNK)
        .map_init(MarchWorkspace::default, |ws, chunk| {
            let mut out = MarchOutput::default();
            msth_core::volume::march::march_chunk(
                vol, cfg, layout, params, chunk, settings, ws, &mut out,
            );
            out
        })
        .collect();
    let mut out = MarchOutput::default();
    for p in &parts {
        out.append(p);
    }
    out
}

/// A baked volume with the plan that made it (its slices are baked from the plan).
#[derive(Clone, Debug)]
pub struct BakedVolume {
    pub volume: Volume,
    pub plan: Arc<BakePlan>,
}

/// One time slice baked into a volume: `(volume, plan, slice, flat buffer at its time)`.
pub type SliceBaker<'a> =
    dyn FnMut(&mut Volume, &BakePlan, usize, &[f32]) -> Result<usize, BakeError> + 'a;

impl BakedVolume {
    /// Bakes the time slices a frame at `time` needs that the volume does not hold, each through
    /// `bake` with the flat buffer at its own time (`params_at`, else `params`); stops at the
    /// first error (the renderers then draw dynamic bricks from the exact field).
    pub fn bake_missing_slices(
        &mut self,
        time: f32,
        params: &[f32],
        params_at: &mut dyn FnMut(f32) -> Option<Vec<f32>>,
        bake: &mut SliceBaker<'_>,
    ) -> Result<(), BakeError> {
        let plan = self.plan.clone();
        for k in self.volume.dynamic.missing_for(time) {
            let owned = params_at(plan.slice_times[k]);
            bake(
                &mut self.volume,
                &plan,
                k,
                owned.as_deref().unwrap_or(params),
            )?;
        }
        Ok(())
    }
}

/// A bake on its own thread: the renderer draws exact frames until [`BakeJob::poll`] hands over
/// the volume.
pub struct BakeJob {
    pub plan: Arc<BakePlan>,
    pub progress: Arc<BakeProgress>,
    handle: Option<std::thread::JoinHandle<Result<Volume, BakeError>>>,
    spawn_error: Option<String>,
}

impl BakeJob {
    /// Starts baking `plan`'s static bricks with a copy of `params`.
    pub fn start(plan: impl Into<Arc<BakePlan>>, cfg: &ModelConfig, params: Vec<f32>) -> BakeJob {
        let plan = plan.into();
        let progress = Arc::new(BakeProgress::default());
        let (p, pr, cfg) = (plan.clone(), progress.clone(), cfg.clone());
        let spawned = std::thread::Builder::new()
            .name("msth-bake".into())
            .spawn(move || {
                let layout = ModelLayout::new(&cfg);
                bake(&p, &cfg, &layout, &params, &pr)
            });
        let (handle, spawn_error) = match spawned {
            Ok(h) => (Some(h), None),
            Err(e) => (None, Some(e.to_string())),
        };
        BakeJob {
            plan,
            progress,
            handle,
            spawn_error,
        }
    }

    /// Static bricks baked, as a fraction.
    pub fn fraction(&self) -> f64 {
        self.progress.done() as f64 / self.plan.static_bricks.len().max(1) as f64
    }

    /// The volume once the bake has finished (`None` while it runs).
    pub fn poll(&mut self) -> Option<Result<BakedVolume, String>> {
        if self.handle.as_ref().is_some_and(|h| !h.is_finished()) {
            return None;
        }
        self.finish()
    }

    /// Waits for the bake.
    pub fn wait(&mut self) -> Option<Result<BakedVolume, String>> {
        self.finish()
    }

    fn finish(&mut self) -> Option<Result<BakedVolume, String>> {
        if let Some(e) = self.spawn_error.take() {
            return Some(Err(format!("cannot start the bake's thread: {e}")));
        }
        let h = self.handle.take()?;
        Some(match h.join() {
            Ok(Ok(volume)) => Ok(BakedVolume {
                volume,
                plan: self.plan.clone(),
            }),
            Ok(Err(e)) => Err(e.to_string()),
            Err(_) => Err("the bake's thread panicked".to_string()),
        })
    }
}

impl Drop for BakeJob {
    fn drop(&mut self) {
        self.progress.cancel();
    }
}
