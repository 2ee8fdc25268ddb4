//! The choice between the CPU renderer ([`crate::render::Renderer`]) and the GPU renderer
//! ([`crate::gpu::GpuRenderer`]), behind one [`FrameRenderer`].
//!
//! - [`BackendChoice::Auto`] (the default): the GPU when a hardware adapter exists (discrete,
//!   integrated or virtual GPU), else the CPU. Software adapters (Mesa's lavapipe, WARP) render
//!   on the CPU cores anyway and are slower than the CPU renderer, so the automatic choice skips
//!   them unless `MSTH_GPU_SOFTWARE=1`; when the GPU cannot render a model (limits), it falls
//!   back to the CPU and says why ([`FrameRenderer::note`]).
//! - [`BackendChoice::Cpu`] (`--cpu`): the CPU renderer.
//! - [`BackendChoice::Gpu`] (`--gpu`): any adapter, software ones included; an error when there
//!   is none or it cannot render the model.

use crate::gpu::{AdapterPolicy, GpuContext, GpuError, GpuRenderer};
use crate::render::{Frame, RenderSettings, Renderer};
use msth_core::config::ModelConfig;
use msth_core::Camera;

/// Which renderer to use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum BackendChoice {
    #[default]
    Auto,
    Cpu,
    Gpu,
}

/// A CPU or GPU renderer with the same interface.
pub enum FrameRenderer {
    Cpu(Box<Renderer>),
    Gpu(Box<GpuRenderer>),
}

/// Which backend a playback used, for reports.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct BackendInfo {
    /// `"cpu"` or `"gpu"`.
    pub kind: &'static str,
    /// The GPU adapter (name, API, device type), or the CPU threads.
    pub device: String,
    /// Why the automatic choice fell back to the CPU, when it did, or what the chosen backend
    /// does differently from the settings.
    pub note: Option<String>,
    /// GPU: whether the passes' MLPs were compiled for the model (and in how long) or stayed
    /// generic, and why (`GpuRenderer::mlp_status`, after the first frame).
    pub mlps: Option<String>,
    /// GPU: how the device holds the hash tables (`"f32"` or `"f16"`).
    pub tables: Option<&'static str>,
    /// GPU: the most table values held clamped at once during the playback (binary16 tables
    /// hold at most ±65504: `--gpu-tables f32` renders larger ones as they are).
    pub tables_clamped: usize,
}

impl FrameRenderer {
    /// A renderer of `cfg` on the backend `choice` selects.
    pub fn new(
        cfg: &ModelConfig,
        settings: RenderSettings,
        choice: BackendChoice,
    ) -> Result<(Self, BackendInfo), GpuError> {
        let cpu = |note: Option<String>| {
            (
                FrameRenderer::Cpu(Box::new(Renderer::new(cfg, settings))),
                BackendInfo {
                    kind: "cpu",
                    device: format!("{} threads", rayon::current_num_threads()),
                    note,
                    mlps: None,
                    tables: None,
                    tables_clamped: 0,
                },
            )
        };
        let gpu = |policy| -> Result<(Self, BackendInfo), GpuError> {
            let ctx =
                GpuContext::open_with_kernels(policy, settings.gpu_tables, settings.gpu_lanes)?;
            let device = ctx.adapter_name();
            let r = GpuRenderer::new(ctx, cfg, settings)?;
            // The GPU renderer has the CPU renderer's caches (sample-level reuse included).
            let note = None;
            Ok((
                FrameRenderer::Gpu(Box::new(r)),
                BackendInfo {
                    kind: "gpu",
                    device,
                    note,
                    mlps: None,
                    tables: Some(settings.gpu_tables.name()),
                    tables_clamped: 0,
                },
            ))
        };
        match choice {
            BackendChoice::Cpu => Ok(cpu(None)),
            BackendChoice::Gpu => gpu(AdapterPolicy::any()),
            BackendChoice::Auto => match gpu(AdapterPolicy::automatic()) {
                Ok(r) => Ok(r),
                Err(GpuError::NoAdapter(_)) => Ok(cpu(None)),
                Err(e) => Ok(cpu(Some(format!("GPU not used: {e}")))),
            },
        }
    }

    /// Renders one frame (see [`Renderer::render`]).
    pub fn render(
        &mut self,
        camera: &Camera,
        time: f32,
        params: &[f32],
    ) -> Result<Frame, GpuError> {
        self.render_probing(camera, time, params, &mut |_| None)
    }

    /// Renders one frame, the probes of the static test using `params_at` (see
    /// [`Renderer::render_probing`]), on either backend.
    pub fn render_probing(
        &mut self,
        camera: &Camera,
        time: f32,
        params: &[f32],
        params_at: &mut dyn FnMut(f32) -> Option<Vec<f32>>,
    ) -> Result<Frame, GpuError> {
        match self {
            FrameRenderer::Cpu(r) => Ok(r.render_probing(camera, time, params, params_at)),
            FrameRenderer::Gpu(r) => r.render_probing(camera, time, params, params_at),
        }
    }

    /// Promises that the parameters passed from now on hold the same values while `version`
    /// stays the same ([`GpuRenderer::set_params_version`]; the CPU renderer reads them anew
    /// each frame and needs no promise).
    pub fn set_params_version(&mut self, version: u64) {
        if let FrameRenderer::Gpu(r) = self {
            r.set_params_version(version);
        }
    }

    /// GPU: the most hash-table values held clamped at once
    /// ([`GpuRenderer::clamped_table_values`]); 0 on the CPU.
    pub fn clamped_table_values(&self) -> usize {
        match self {
            FrameRenderer::Cpu(_) => 0,
            FrameRenderer::Gpu(r) => r.clamped_table_values(),
        }
    }

    /// GPU: how the passes run the MLPs ([`GpuRenderer::mlp_status`]); `None` on the CPU.
    pub fn mlp_note(&self) -> Option<String> {
        match self {
            FrameRenderer::Cpu(_) => None,
            FrameRenderer::Gpu(r) => Some(r.mlp_status().to_string()),
        }
    }

    /// Fraction of the cached camera's pixels re-rendered each frame.
    pub fn dynamic_fraction(&self) -> Option<f32> {
        match self {
            FrameRenderer::Cpu(r) => r.dynamic_fraction(),
            FrameRenderer::Gpu(r) => r.dynamic_fraction(),
        }
    }

    /// Hands the file's occupancy grid to the renderer: both skip the main field's samples in
    /// empty cells (the GPU renderer in its per-sample passes).
    pub fn set_occupancy(
        &mut self,
        grid: Option<std::sync::Arc<msth_codec::OccupancyGrid>>,
    ) -> Result<(), GpuError> {
        match self {
            FrameRenderer::Cpu(r) => r.set_occupancy(grid),
            FrameRenderer::Gpu(r) => r.set_occupancy(grid)?,
        }
        Ok(())
    }

    /// Draws frames from `volume` from now on (`None`: from the exact field). The GPU uploads
    /// it; when it cannot (beyond its limits), frames stay exact and the error says why.
    pub fn set_volume(
        &mut self,
        volume: Option<crate::volume::BakedVolume>,
    ) -> Result<(), GpuError> {
        match self {
            FrameRenderer::Cpu(r) => {
                r.set_volume(volume);
                Ok(())
            }
            FrameRenderer::Gpu(r) => r.set_volume(volume),
        }
    }

    /// Bakes `plan` with `params` on the GPU and waits for it, where the GPU bakes
    /// ([`GpuRenderer::bake_on_device`]); `None` on the CPU and on software adapters (the bake
    /// thread, [`crate::volume::BakeJob`], bakes there).
    pub fn bake_on_device(
        &mut self,
        plan: std::sync::Arc<msth_core::volume::BakePlan>,
        params: &[f32],
    ) -> Option<Result<crate::volume::BakedVolume, msth_core::volume::BakeError>> {
        match self {
            FrameRenderer::Cpu(_) => None,
            FrameRenderer::Gpu(r) => r.bake_on_device(plan, params),
        }
    }

    /// Takes the volume frames are drawn from, if any, back from the renderer (it draws from
    /// the exact field from now on).
    pub fn take_volume(&mut self) -> Option<crate::volume::BakedVolume> {
        match self {
            FrameRenderer::Cpu(r) => r.take_volume(),
            FrameRenderer::Gpu(r) => r.take_volume(),
        }
    }

    /// Switches between the exact field and the volume ([`Renderer::set_exact`]).
    pub fn set_exact(&mut self, exact: bool) {
        match self {
            FrameRenderer::Cpu(r) => r.set_exact(exact),
            FrameRenderer::Gpu(r) => r.set_exact(exact),
        }
    }

    /// Whether the next frame comes from a volume ([`Renderer::uses_volume`]).
    pub fn uses_volume(&self) -> bool {
        match self {
            FrameRenderer::Cpu(r) => r.uses_volume(),
            FrameRenderer::Gpu(r) => r.uses_volume(),
        }
    }

    /// The most bytes the play-time volume may take by default on this backend: 512 MiB on the
    /// CPU ([`crate::volume::DEFAULT_CPU_BUDGET`]), a quarter of the GPU's buffer limit
    /// ([`GpuRenderer::volume_budget`]).
    pub fn volume_budget(&self) -> u64 {
        match self {
            FrameRenderer::Cpu(_) => crate::volume::DEFAULT_CPU_BUDGET,
            FrameRenderer::Gpu(r) => r.volume_budget(),
        }
    }

    /// Forgets the static cache.
    pub fn invalidate(&mut self) {
        match self {
            FrameRenderer::Cpu(r) => r.invalidate(),
            FrameRenderer::Gpu(r) => r.invalidate(),
        }
    }
}
