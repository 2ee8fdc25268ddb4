//! winit's event loop: the application handler, and the redraw pass that runs the viewer once
//! per frame (replies, the clock, the script, the controls, the next job, the paint).

use std::num::NonZeroU32;
use std::time::Instant;

use winit::application::ApplicationHandler;
use winit::event::{StartCause, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::window::WindowId;

use super::gfx::Gfx;
use super::input::FLY_KEYS;
use super::ui::UiAction;
use super::{App, Wake};
use crate::ViewError;

/// winit's event loop; on X11 it may run on any thread (the tests run it off the main thread).
pub(super) fn build_event_loop() -> Result<EventLoop<Wake>, ViewError> {
    let mut builder = EventLoop::<Wake>::with_user_event();
    #[cfg(all(
        unix,
        not(any(target_os = "macos", target_os = "ios", target_os = "android"))
    ))]
    {
        use winit::platform::x11::EventLoopBuilderExtX11;
        builder.with_any_thread(true);
    }
    // A missing display is reported by some winit versions with a panic rather than an error.
    let built = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| builder.build()));
    match built {
        Ok(Ok(l)) => Ok(l),
        Ok(Err(e)) => Err(ViewError::NoDisplay(e.to_string())),
        Err(_) => Err(ViewError::NoDisplay(
            "the window system could not be reached (is DISPLAY set?)".into(),
        )),
    }
}

impl ApplicationHandler<Wake> for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.gfx.is_some() {
            return;
        }
        if let Err(e) = self.open(event_loop) {
            self.fail(event_loop, e);
            return;
        }
        if let Some(g) = &self.gfx {
            g.window.request_redraw();
        }
    }

    fn new_events(&mut self, _: &ActiveEventLoop, cause: StartCause) {
        if let (StartCause::ResumeTimeReached { .. }, Some(g)) = (cause, &self.gfx) {
            g.window.request_redraw();
        }
    }

    fn user_event(&mut self, _: &ActiveEventLoop, _: Wake) {
        if let Some(g) = &self.gfx {
            g.window.request_redraw();
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        let Some(mut gfx) = self.gfx.take() else {
            return;
        };
        let response = gfx.egui.on_window_event(&gfx.window, &event);
        match &event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => {
                if let (Some(w), Some(h)) =
                    (NonZeroU32::new(size.width), NonZeroU32::new(size.height))
                {
                    gfx.painter.on_window_resized(egui::ViewportId::ROOT, w, h);
                }
                gfx.window.request_redraw();
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.redraw(&mut gfx) {
                    self.gfx = Some(gfx);
                    self.fail(event_loop, e);
                    return;
                }
                if self.quit {
                    event_loop.exit();
                }
            }
            _ => {}
        }
        if response.repaint {
            gfx.window.request_redraw();
        }
        self.gfx = Some(gfx);
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        let now = self.now();
        match (self.wake_at, &self.gfx) {
            (Some(t), Some(g)) if t <= now => {
                g.window.request_redraw();
                event_loop.set_control_flow(ControlFlow::Wait);
            }
            (Some(t), Some(_)) => match std::time::Duration::try_from_secs_f64(t) {
                Ok(d) => event_loop.set_control_flow(ControlFlow::WaitUntil(self.start + d)),
                Err(_) => event_loop.set_control_flow(ControlFlow::Wait),
            },
            _ => event_loop.set_control_flow(ControlFlow::Wait),
        }
    }
}

impl App {
    /// One pass: replies, the clock, the script, the controls, the next job, the paint.
    fn redraw(&mut self, gfx: &mut Gfx) -> Result<(), ViewError> {
        let now = self.now();
        let dt = (now - self.last_tick).clamp(0.0, 0.25);
        self.last_tick = now;
        self.take_replies(gfx, now)?;
        self.finish_bench(now, 0.0);
        if self.bench.is_none() {
            let ready = self.stream.ready_for(self.timeline.t);
            self.timeline.advance(dt, ready);
        }
        self.run_script(now)?;
        let before = self.view.camera();
        let mut raw = gfx.egui.take_egui_input(&gfx.window);
        raw.events.append(&mut self.events);
        let ctx = gfx.egui.egui_ctx().clone();
        let picture = gfx.picture.as_ref().map(|p| (p.nearest, p.linear, p.size));
        let adapter = gfx.adapter.clone();
        let mut actions = Vec::new();
        let mut output = ctx.run_ui(raw, |ui| {
            self.ui(ui, now, dt, picture, &adapter, &mut actions);
        });
        if self.view.camera() != before {
            self.policy.input(now);
        }
        for a in actions {
            match a {
                UiAction::Shot => self.request_shot(),
                UiAction::Record => self.toggle_recording(now)?,
                UiAction::Quit => self.quit = true,
            }
        }
        self.record_tick(now);
        gfx.egui
            .handle_platform_output(&gfx.window, std::mem::take(&mut output.platform_output));
        self.pixels_per_point = output.pixels_per_point;
        self.submit(now);
        // Paint.
        let paint_start = Instant::now();
        let primitives =
            ctx.tessellate(std::mem::take(&mut output.shapes), output.pixels_per_point);
        let captures: Vec<egui::ScreenshotCallback> =
            self.pending_capture.take().into_iter().collect();
        let capture = !captures.is_empty();
        gfx.painter.paint_and_update_textures(
            egui::ViewportId::ROOT,
            output.pixels_per_point,
            [0.1, 0.1, 0.1, 1.0],
            &primitives,
            &mut output.textures_delta,
            captures,
            &gfx.window,
        );
        if capture {
            if let Some(rs) = gfx.painter.render_state() {
                let _ = rs.device.poll(wgpu::PollType::wait_indefinitely());
            }
        }
        let paint_seconds = paint_start.elapsed().as_secs_f64();
        self.save_shot(gfx)?;
        self.finish_bench(self.now(), paint_seconds);
        // When to come back: egui's wish, the script, playback, refinement, held keys.
        let repaint = output
            .viewport_output
            .get(&egui::ViewportId::ROOT)
            .map(|v| v.repaint_delay.as_secs_f64())
            .unwrap_or(f64::INFINITY);
        let mut wake = now + repaint;
        let soon = now + 1.0 / 60.0;
        let keys_held = ctx.input(|i| FLY_KEYS.iter().any(|(k, _)| i.key_down(*k)));
        if self.script.is_some() || keys_held || self.shot.is_some() {
            wake = wake.min(soon);
        }
        if self.in_flight.is_none() && (self.timeline.playing || self.bench.is_some()) {
            wake = wake.min(if self.buffering { now + 0.05 } else { now });
        }
        if self.policy.moving(now) || self.policy.wants_refine(now + 1.0, false) {
            wake = wake.min(now + msth_player::policy::STILL / 4.0);
        }
        if let Some(r) = &self.recording {
            wake = wake.min(r.next_tick);
        }
        // egui's "no repaint needed" is a delay of years.
        self.wake_at = (wake < now + 3600.0).then_some(wake);
        Ok(())
    }
}
