//! The window's drawing: the window and its egui-wgpu painter, the adapter they use, and the
//! picture's texture that frames are uploaded to.

use std::sync::Arc;

use msth_player::Frame;
use winit::event_loop::ActiveEventLoop;
use winit::window::Window;

use super::App;
use crate::ViewError;

/// The window and what draws into it.
pub(super) struct Gfx {
    pub(super) window: Arc<Window>,
    pub(super) painter: egui_wgpu::winit::Painter,
    pub(super) egui: egui_winit::State,
    pub(super) picture: Option<Picture>,
    pub(super) adapter: String,
}

/// The picture's texture, shown through two egui ids: nearest (a full-size frame at an integer
/// zoom: each rendered pixel a block of window pixels) and linear (reduced frames, scaled).
pub(super) struct Picture {
    pub(super) texture: wgpu::Texture,
    pub(super) size: (u32, u32),
    pub(super) nearest: egui::TextureId,
    pub(super) linear: egui::TextureId,
}

impl App {
    /// Opens the window, its painter and the render thread.
    pub(super) fn open(&mut self, event_loop: &ActiveEventLoop) -> Result<(), ViewError> {
        let t = self.view.rig().template;
        let (w, h) = self.opts.window_size.unwrap_or_else(|| {
            // The picture at most about 640x480 at a whole zoom: the window is painted once per
            // frame, and on a software adapter its size is what that costs.
            let zoom = (640 / t.width.max(1)).min(480 / t.height.max(1)).max(1);
            (t.width * zoom + 300, t.height * zoom + 90)
        });
        let attrs = Window::default_attributes()
            .with_title(format!("msth view: {}", self.name))
            .with_inner_size(winit::dpi::LogicalSize::new(w, h));
        let window = Arc::new(
            event_loop
                .create_window(attrs)
                .map_err(|e| ViewError::NoDisplay(e.to_string()))?,
        );
        let ctx = egui::Context::default();
        let config = egui_wgpu::WgpuConfiguration {
            wgpu_setup: egui_wgpu::WgpuSetup::CreateNew(egui_wgpu::WgpuSetupCreateNew {
                native_adapter_selector: Some(Arc::new(pick_window_adapter)),
                ..egui_wgpu::WgpuSetupCreateNew::without_display_handle()
            }),
            // Frames come when the renderer has them: presenting should not wait for a vblank.
            surface: egui_wgpu::SurfaceConfig {
                present_mode: wgpu::PresentMode::AutoNoVsync,
                desired_maximum_frame_latency: Some(1),
            },
            ..egui_wgpu::WgpuConfiguration::default()
        };
        let options = egui_wgpu::RendererOptions {
            dithering: false,
            ..egui_wgpu::RendererOptions::default()
        };
        let mut painter = pollster::block_on(egui_wgpu::winit::Painter::new(
            ctx.clone(),
            config,
            false,
            options,
        ));
        pollster::block_on(painter.set_window(egui::ViewportId::ROOT, Some(window.clone())))
            .map_err(|e| ViewError::NoPresenter(e.to_string()))?;
        let rs = painter
            .render_state()
            .ok_or_else(|| ViewError::NoPresenter("no device".into()))?;
        let info = rs.adapter.get_info();
        let adapter = format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type);
        self.report.window_adapter = adapter.clone();
        let egui = egui_winit::State::new(
            ctx,
            egui::ViewportId::ROOT,
            window.as_ref(),
            Some(window.scale_factor() as f32),
            None,
            painter.max_texture_side(),
        );
        self.gfx = Some(Gfx {
            window,
            painter,
            egui,
            picture: None,
            adapter,
        });
        self.start_worker()
    }
}

/// The adapter the window is drawn with: a hardware one that can draw into the window, else a
/// software one (Mesa's lavapipe draws a window without a GPU).
fn pick_window_adapter(
    adapters: &[wgpu::Adapter],
    surface: Option<&wgpu::Surface<'_>>,
) -> Result<wgpu::Adapter, String> {
    let rank = |t: wgpu::DeviceType| match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    };
    let usable: Vec<&wgpu::Adapter> = adapters
        .iter()
        .filter(|a| surface.is_none_or(|s| a.is_surface_supported(s)))
        .collect();
    usable
        .into_iter()
        .min_by_key(|a| rank(a.get_info().device_type))
        .cloned()
        .ok_or_else(|| {
            if adapters.is_empty() {
                "no Vulkan, Metal or DX12 adapter at all".to_string()
            } else {
                format!(
                    "none of the adapters can draw into the window: {}",
                    adapters
                        .iter()
                        .map(|a| a.get_info().name)
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            }
        })
}

/// Uploads `frame` to the picture's texture (made anew when the size changes).
pub(super) fn upload(gfx: &mut Gfx, frame: &Frame) {
    let Some(rs) = gfx.painter.render_state() else {
        return;
    };
    let size = (frame.width, frame.height);
    if gfx.picture.as_ref().is_none_or(|p| p.size != size) {
        let texture = rs.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("msth view picture"),
            size: wgpu::Extent3d {
                width: size.0,
                height: size.1,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8Unorm,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let mut renderer = rs.renderer.write();
        let sampler = |filter| wgpu::SamplerDescriptor {
            label: Some("msth view picture"),
            mag_filter: filter,
            min_filter: filter,
            ..Default::default()
        };
        let (nearest, linear) = match gfx.picture.take() {
            Some(p) => {
                renderer.update_egui_texture_from_wgpu_texture_with_sampler_options(
                    &rs.device,
                    &view,
                    sampler(wgpu::FilterMode::Nearest),
                    p.nearest,
                );
                renderer.update_egui_texture_from_wgpu_texture_with_sampler_options(
                    &rs.device,
                    &view,
                    sampler(wgpu::FilterMode::Linear),
                    p.linear,
                );
                (p.nearest, p.linear)
            }
            None => (
                renderer.register_native_texture_with_sampler_options(
                    &rs.device,
                    &view,
                    sampler(wgpu::FilterMode::Nearest),
                ),
                renderer.register_native_texture_with_sampler_options(
                    &rs.device,
                    &view,
                    sampler(wgpu::FilterMode::Linear),
                ),
            ),
        };
        gfx.picture = Some(Picture {
            texture,
            size,
            nearest,
            linear,
        });
    }
    let Some(p) = &gfx.picture else {
        return;
    };
    let rgb = frame.to_rgb8();
    let mut rgba = Vec::with_capacity(rgb.len() / 3 * 4);
    for c in rgb.chunks_exact(3) {
        rgba.extend_from_slice(&[c[0], c[1], c[2], 255]);
    }
    rs.queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture: &p.texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        &rgba,
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(4 * size.0),
            rows_per_image: Some(size.1),
        },
        wgpu::Extent3d {
            width: size.0,
            height: size.1,
            depth_or_array_layers: 1,
        },
    );
}
